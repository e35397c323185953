// Runs test code as another, unprivileged user (issue 16.7: who may watch).
// Only root can switch; the tests that need it skip otherwise.
#pragma once

#include "process.hpp"

#include <grp.h>
#include <pwd.h>
#include <sys/types.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
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

/// Runs `attempt` as nobody in a forked child, where it must throw `Error`
/// whose error_number() is EPERM (another user's name it may not take):
/// that error's message. Anything else comes back as a text that says so,
/// which no expected message equals.
template <typename Error, typename F>
std::string eperm_refusal_as_nobody(F&& attempt) {
    struct Message {
        char text[512];
    };
    auto* message = shared_anon<Message>();
    const int rc = wait_child(fork_child([&] {
        if (!become_nobody({})) return 10;
        try {
            attempt();
            return 3;
        } catch (const Error& e) {
            std::snprintf(message->text, sizeof message->text, "%s", e.what());
            return e.error_number() == EPERM ? 0 : 4;
        }
    }));
    std::string text = message->text;
    if (rc != 0)
        text = "the child as nobody ended " + std::to_string(rc) +
               " (10: could not switch, 3: not refused, 4: another errno): " + text;
    munmap(message, sizeof *message);
    return text;
}

}  // namespace chimera::test
