// Squatted names (issue #29.5, docs/permissions.md): any local user may make
// /dev/shm/chimera.X.svar first, with a chimera header naming a live pid. A
// segment is believed only when its owner stands behind its header: group and
// others may not write to it, and its creator is a process of its owner.
// root removes a squatted one; another user is told whose it is and what to do.
#include <gtest/gtest.h>

#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <string>

#include "as_user.hpp"
#include "chimera/ipc/segment.hpp"
#include "sanitizer.hpp"
#include "test_util.hpp"

using namespace chimera::ipc;
using chimera::ipc::test::fork_child;
using chimera::ipc::test::kKind;
using chimera::ipc::test::make;
using chimera::ipc::test::shared_anon;
using chimera::ipc::test::unique_name;
using chimera::ipc::test::wait_child;

namespace {

// What a forked child saw, for the parent to compare.
struct Message {
    char text[512];
};

// In a forked child become nobody: a published segment NAME whose header
// names pid 1 (root's init) as its creator, left behind as a squatter would.
int squat_as_nobody(const std::string& name) {
    if (!chimera::test::become_nobody({})) return 10;
    Segment fake = make(name, 1, 0600);
    fake.header().creator_pid = 1;
    _exit(0);  // no destructor: the file stays, published
}

}  // namespace

TEST(Squat, ASegmentOfThisUsersOwnIsBelieved) {
    const std::string name = unique_name("own");
    Segment own = make(name);
    EXPECT_EQ(squatted(name), "");
    EXPECT_EQ(squatted(unique_name("none")), "");
    own.detach_destroy_if_last();
}

TEST(Squat, AFileOthersMayWriteIsSquattedAndItsOwnerMayReplaceIt) {
    const std::string name = unique_name("open");
    {
        Segment open = make(name, 1, 0600);
        ASSERT_EQ(::chmod(("/dev/shm" + name).c_str(), 0666), 0);  // as a planted file may be
        open.detach();
    }
    EXPECT_EQ(squatted(name), "squatted: group or others may write to it");
    make_way(name, squatted(name));  // this user's own file: removed
    EXPECT_FALSE(Segment::exists(name));
}

// The squat: nobody's file, its header naming root's pid 1 as a live
// creator. Root's check tells it from a running subsystem and removes it.
TEST(Squat, NobodysFakeNamingPid1IsSquattedAndRootRemovesIt) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("fake");
    ASSERT_EQ(wait_child(fork_child([&] { return squat_as_nobody(name); })), 0);
    ASSERT_TRUE(Segment::exists(name));
    EXPECT_FALSE(Segment::is_stale(name));  // what made `sbs` say "already running": pid 1 lives
    EXPECT_EQ(squatted(name), "squatted: its header names as its creator pid 1, a process of root, not of its owner");
    make_way(name, squatted(name));
    EXPECT_FALSE(Segment::exists(name));
}

// Another user may not remove root's file: the error names the owner and the remedy.
TEST(Squat, AUserWhoMayNotRemoveItIsToldWhoseItIsAndWhatToDo) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("roots");
    Segment roots = make(name, 1, 0600);
    ASSERT_EQ(::chmod(("/dev/shm" + name).c_str(), 0666), 0);
    auto* message = shared_anon<Message>();
    const pid_t child = fork_child([&] {
        if (!chimera::test::become_nobody({})) return 10;
        try {
            make_way(name, squatted(name));
            return 3;
        } catch (const SegmentError& e) {
            std::snprintf(message->text, sizeof message->text, "%s", e.what());
            return e.error_number() == EPERM ? 0 : 4;
        }
    });
    EXPECT_EQ(wait_child(child), 0);
    EXPECT_EQ(std::string(message->text),
              "segment " + name + ": squatted: group or others may write to it: it is root's (uid 0, mode 0666), and "
              "only root may remove it (sudo rm /dev/shm" + name + "), then start again");
    EXPECT_TRUE(Segment::exists(name));
    roots.detach_destroy_if_last();
}
