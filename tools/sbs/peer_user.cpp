#include "peer_user.hpp"

#include <pwd.h>
#include <unistd.h>

namespace chimera::cli {

std::string user_name(uid_t uid) {
    const passwd* pw = ::getpwuid(uid);
    return pw ? pw->pw_name : "uid " + std::to_string(uid);
}

bool trusted_user(uid_t uid) noexcept { return uid == 0 || uid == ::geteuid(); }

bool peer_credentials(int fd, ucred& cred) noexcept {
    socklen_t len = sizeof cred;
    return ::getsockopt(fd, SOL_SOCKET, SO_PEERCRED, &cred, &len) == 0 && len == sizeof cred;
}

// The text is python/chimera/_master.py's too (_untrusted_master): keep them alike.
std::string untrusted_master(int fd, const std::string& path) {
    ucred cred{};
    if (!peer_credentials(fd, cred)) return "socket " + path + ": its peer's user cannot be told: not trusted";
    if (trusted_user(cred.uid)) return "";
    return "socket " + path + " is served by " + user_name(cred.uid) + "'s (uid " + std::to_string(cred.uid) +
           ") process, pid " + std::to_string(cred.pid) +
           ", not by this user's or root's: not trusted; stop that process or remove the socket (sudo rm " + path +
           "), then start the master again";
}

}  // namespace chimera::cli
