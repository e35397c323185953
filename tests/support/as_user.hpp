// Runs test code as another, unprivileged user (issue 16.7: who may watch).
// Only root can switch; the tests that need it skip otherwise.
#pragma once

#include <grp.h>
#include <pwd.h>
#include <sys/types.h>
#include <unistd.h>

#include <string>
#include <vector>

namespace chimera::test {

/// True when this process may switch users (the permission tests need it).
inline bool can_switch_user() { return geteuid() == 0 && getpwnam("nobody") != nullptr; }

/// The gid of `group`, or -1.
inline gid_t gid_of(const std::string& group) {
    const struct group* g = getgrnam(group.c_str());
    return g ? g->gr_gid : static_cast<gid_t>(-1);
}

/// In a forked child: becomes `nobody` with exactly the supplementary groups
/// `groups` (its primary group stays nobody's own). False when it could not.
inline bool become_nobody(const std::vector<gid_t>& groups) {
    const passwd* pw = getpwnam("nobody");
    if (!pw) return false;
    return setgroups(groups.size(), groups.data()) == 0 && setresgid(pw->pw_gid, pw->pw_gid, pw->pw_gid) == 0 &&
           setresuid(pw->pw_uid, pw->pw_uid, pw->pw_uid) == 0 && geteuid() == pw->pw_uid;
}

}  // namespace chimera::test
