// output_file.hpp — where a module that writes a file may write it (issue #29.4).
// A subsystem often runs as root; a file it writes in a shared folder (/tmp)
// can be a symlink a local user planted there. So a relative name lands in the
// subsystem's own output folder, an absolute one only in a folder no one else
// can write to, and the file is opened relative to the folder's descriptor
// without following a symlink.
#pragma once

#include <fcntl.h>
#include <pwd.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>

namespace chimera::output {

/// The folder a subsystem's output files go to: $CHIMERA_OUTPUT_DIR when set
/// (the operator's choice, taken as is), else $XDG_STATE_HOME/chimera/SUBSYSTEM,
/// else $HOME/.local/state/chimera/SUBSYSTEM (XDG Base Directory spec; HOME
/// from the password database when unset, e.g. root's /root).
inline std::string output_dir(const std::string& subsystem) {
    if (const char* d = std::getenv("CHIMERA_OUTPUT_DIR"); d && *d) return d;
    if (subsystem.empty() || subsystem.find('/') != std::string::npos || subsystem == "..")
        throw std::runtime_error("subsystem name '" + subsystem + "' cannot name an output folder");
    std::string state;
    if (const char* x = std::getenv("XDG_STATE_HOME"); x && x[0] == '/') {  // the spec ignores a relative one
        state = x;
    } else {
        const char* home = std::getenv("HOME");
        if (!home || !*home) {
            const passwd* pw = ::getpwuid(::geteuid());
            home = pw ? pw->pw_dir : nullptr;
        }
        if (!home || !*home) throw std::runtime_error("no HOME for an output folder: set CHIMERA_OUTPUT_DIR");
        state = std::string(home) + "/.local/state";
    }
    return state + "/chimera/" + subsystem;
}

/// mkdir -p with mode 0700 for what is created (existing folders are left as they are).
inline void make_dirs(const std::string& dir) {
    for (std::size_t at = 1; at <= dir.size(); ++at) {
        if (at != dir.size() && dir[at] != '/') continue;
        const std::string part = dir.substr(0, at);
        if (::mkdir(part.c_str(), 0700) != 0 && errno != EEXIST)
            throw std::runtime_error("cannot create output folder " + part + ": " + std::strerror(errno));
    }
}

inline std::string octal_mode(mode_t m) {
    char text[8];
    std::snprintf(text, sizeof text, "%04o", static_cast<unsigned>(m & 07777));
    return text;
}

inline std::string user_name(uid_t uid) {
    const passwd* pw = ::getpwuid(uid);
    return pw ? std::string(pw->pw_name) + " (uid " + std::to_string(uid) + ")" : "uid " + std::to_string(uid);
}

/// Opens `dir` (not through a symlink) and checks no one but this user (or
/// root, when `root_may_own`) could have put anything in it. Returns the
/// folder's descriptor; throws naming the folder, its owner and mode.
inline int open_trusted_dir(const std::string& dir, bool root_may_own) {
    const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_NOFOLLOW | O_CLOEXEC);
    if (fd < 0) {
        const int e = errno;
        struct stat st{};
        if (::lstat(dir.c_str(), &st) == 0 && S_ISLNK(st.st_mode))
            throw std::runtime_error("output folder " + dir + " is a symlink: not followed; give a real folder");
        throw std::runtime_error("cannot open output folder " + dir + ": " + std::strerror(e));
    }
    struct stat st{};
    ::fstat(fd, &st);
    const bool owner_ok = st.st_uid == ::geteuid() || (root_may_own && st.st_uid == 0);
    if (!owner_ok || (st.st_mode & (S_IWGRP | S_IWOTH)) != 0) {
        ::close(fd);
        throw std::runtime_error("output folder " + dir + " is owned by " + user_name(st.st_uid) + " with mode " +
                                 octal_mode(st.st_mode) + ": files are written only in a folder of " +
                                 user_name(::geteuid()) + " that no one else may write to (chown it, chmod go-w it, "
                                 "or set CHIMERA_OUTPUT_DIR to such a folder)");
    }
    return fd;
}

/// The folder (open, trusted) and file name a FILE value names. A name without
/// a folder goes to output_dir(subsystem), created 0700 when missing; an
/// absolute path's folder must be this user's or root's and writable by no
/// one else (so /tmp is refused).
struct Target {
    int dir_fd = -1;
    std::string dir, name;
};

inline Target resolve(const std::string& file, const std::string& subsystem) {
    Target t;
    const auto slash = file.rfind('/');
    if (file.empty() || file.back() == '/' || file == "." || file == "..")
        throw std::runtime_error("not a file name");
    if (slash == std::string::npos) {
        t.dir = output_dir(subsystem);
        make_dirs(t.dir);
        t.name = file;
        t.dir_fd = open_trusted_dir(t.dir, false);
    } else if (file[0] == '/') {
        t.dir = slash == 0 ? "/" : file.substr(0, slash);
        t.name = file.substr(slash + 1);
        t.dir_fd = open_trusted_dir(t.dir, true);
    } else {
        throw std::runtime_error("a relative path: give a file name (written in the output folder) or an absolute path");
    }
    return t;
}

/// Creates or truncates t.name in its folder, 0600, never through a symlink
/// (O_NOFOLLOW: a planted one fails with ELOOP). Returns the descriptor or -1 (errno set).
inline int open_for_writing(const Target& t) {
    const int fd = ::openat(t.dir_fd, t.name.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_NOFOLLOW | O_CLOEXEC, 0600);
    if (fd >= 0) ::fchmod(fd, 0600);  // an existing file keeps its mode otherwise
    return fd;
}

}  // namespace chimera::output
