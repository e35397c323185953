// Watchers and the watch group (issue 16.7, docs/permissions.md): a segment
// created with group bits belongs to the watch group with exactly that mode;
// a watcher maps it read-only, is not a user, never blocks the destroy, and
// cannot write; another user gets "permission denied" and what to do.
#include <gtest/gtest.h>

#include <fcntl.h>
#include <signal.h>
#include <unistd.h>
#include <sys/stat.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "as_user.hpp"
#include "chimera/ipc/segment.hpp"
#include "sanitizer.hpp"
#include "test_util.hpp"

using namespace chimera::ipc;
using chimera::ipc::test::fork_child;
using chimera::ipc::test::shared_anon;
using chimera::ipc::test::unique_name;
using chimera::ipc::test::wait_child;
using chimera::ipc::test::wait_for;
using chimera::ipc::test::Body;
using chimera::ipc::test::kKind;
using chimera::ipc::test::make;

namespace {

struct stat stat_of(const std::string& name) {
    struct stat st {};
    ::stat(("/dev/shm" + name).c_str(), &st);
    return st;
}

// The watch group for these tests: `users` (Debian's gid 100), so no group
// has to be made on the machine. Restores CHIMERA_GROUP afterwards.
class WatchGroup : public ::testing::Test {
protected:
    void SetUp() override {
        if (const char* old = std::getenv("CHIMERA_GROUP")) saved_ = old, had_ = true;
        ::setenv("CHIMERA_GROUP", "users", 1);
    }
    void TearDown() override {
        if (had_) ::setenv("CHIMERA_GROUP", saved_.c_str(), 1);
        else ::unsetenv("CHIMERA_GROUP");
    }
    std::string saved_;
    bool had_ = false;
};

}  // namespace

TEST_F(WatchGroup, GroupBitsGiveTheSegmentToTheWatchGroupWhateverTheUmask) {
    if (chimera::test::gid_of("users") == static_cast<gid_t>(-1)) GTEST_SKIP() << "no group 'users'";
    const mode_t old_umask = ::umask(077);  // would make shm_open's 0640 a 0600
    const std::string shared = unique_name("grp"), own = unique_name("own");
    Segment a = make(shared, 42, 0640);
    Segment b = make(own, 42, 0600);
    ::umask(old_umask);
    EXPECT_EQ(stat_of(shared).st_mode & 07777, 0640u);
    EXPECT_EQ(stat_of(shared).st_gid, chimera::test::gid_of("users"));
    EXPECT_EQ(stat_of(own).st_mode & 07777, 0600u);
    EXPECT_EQ(stat_of(own).st_gid, getegid());  // owner-only segments are not handed to the group
    a.detach_destroy_if_last();
    b.detach_destroy_if_last();
}

TEST_F(WatchGroup, WithoutTheGroupASegmentIsOwnerOnlyAndThatIsSaidOnce) {
    ::setenv("CHIMERA_GROUP", "chimera-no-such-group", 1);
    const std::string n1 = unique_name("nogrp1"), n2 = unique_name("nogrp2");
    ::testing::internal::CaptureStderr();
    Segment a = make(n1, 42, 0640);
    Segment b = make(n2, 42, 0640);
    const std::string said = ::testing::internal::GetCapturedStderr();
    EXPECT_EQ(stat_of(n1).st_mode & 07777, 0600u);
    EXPECT_EQ(stat_of(n2).st_mode & 07777, 0600u);
    const std::string expected = "chimera: group chimera-no-such-group does not exist (groupadd --system "
                                 "chimera-no-such-group): shared segments are owner-only (0600) from " + n1 +
                                 " on, so only their owner and root can watch them (docs/permissions.md)\n";
    // Once per process: an earlier creation in this run may have said it already.
    EXPECT_TRUE(said == expected || said.empty()) << said;
    a.detach_destroy_if_last();
    b.detach_destroy_if_last();
}

TEST(IpcWatch, AWatcherIsNoUserAndNeverBlocksTheDestroy) {
    CHIMERA_NOT_UNDER_TSAN("a forked watcher");
    const std::string name = unique_name("watched");
    Segment owner = make(name, 7, 0600);
    auto* state = shared_anon<std::atomic<int>>();  // 1: watching, 2: owner destroyed
    const pid_t watcher = fork_child([&] {
        Segment w = Segment::watch(name, kKind);
        if (!w.read_only() || w.at_bytes<Body>(0)->value != 7) return 2;
        state->store(1);
        while (state->load() != 2) usleep(1000);
        // Destroyed under us: the mapping still reads, and says so.
        if (w.at_bytes<Body>(0)->value != 8) return 3;
        if (w.header().state.load() != static_cast<std::uint32_t>(SegmentState::destroyed)) return 4;
        return w.detach_destroy_if_last() ? 5 : 0;  // a watcher never destroys
    });
    ASSERT_TRUE(wait_for([&] { return state->load() == 1; }));
    EXPECT_FALSE(owner.read_only());
    EXPECT_EQ(owner.users(), 1u);  // the watcher is not counted
    EXPECT_EQ(owner.header().attaches.load(), 0u);
    owner.at_bytes<Body>(0)->value = 8;
    EXPECT_TRUE(owner.detach_destroy_if_last());  // not delayed by the watcher
    EXPECT_FALSE(Segment::exists(name));
    state->store(2);
    EXPECT_EQ(wait_child(watcher), 0);
}

TEST(IpcWatch, AWatcherCannotWrite) {
    const std::string name = unique_name("ro");
    Segment owner = make(name, 1, 0600);
    {
        Segment w = Segment::watch(name, kKind);
        // The kernel writing into the mapping (read(2) from /dev/zero) is
        // refused with EFAULT: PROT_READ. A store would be a SIGSEGV, which
        // AddressSanitizer turns into a report and exit status 1.
        const int zero = ::open("/dev/zero", O_RDONLY | O_CLOEXEC);
        ASSERT_GE(zero, 0);
        errno = 0;
        EXPECT_EQ(::read(zero, w.at_bytes<Body>(0), sizeof(Body)), -1);
        EXPECT_EQ(errno, EFAULT);
        ::close(zero);
    }
    EXPECT_EQ(owner.at_bytes<Body>(0)->value, 1u);
    owner.detach_destroy_if_last();
}

// As another user: a member of the watch group watches, cannot attach to
// write; a non-member is told "permission denied" and what to do.
TEST_F(WatchGroup, AMemberWatchesANonMemberIsToldWhatToDo) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const gid_t users = chimera::test::gid_of("users");
    if (users == static_cast<gid_t>(-1)) GTEST_SKIP() << "no group 'users'";
    const std::string name = unique_name("perm");
    Segment owner = make(name, 11, 0640);
    const std::string path = "/dev/shm" + name;
    struct Message {
        char text[512];
    };
    auto* message = shared_anon<Message>();  // the child's what(), for the parent to compare
    auto keep = [&](const SegmentError& e) { std::snprintf(message->text, sizeof message->text, "%s", e.what()); };

    const pid_t member = fork_child([&] {
        if (!chimera::test::become_nobody({users})) return 10;
        Segment w = Segment::watch(name, kKind);
        if (w.at_bytes<Body>(0)->value != 11) return 2;
        try {
            Segment::attach(name, kKind);
            return 3;
        } catch (const SegmentError& e) {
            keep(e);
            return e.error_number() == EACCES ? 0 : 4;
        }
    });
    EXPECT_EQ(wait_child(member), 0);
    EXPECT_EQ(std::string(message->text), "segment " + name + ": permission denied: " + path +
                                         " is root's (group users, mode 0640): only root may change it: run as "
                                         "root (sudo); members of group users may only watch it");
    EXPECT_EQ(owner.users(), 1u);

    const pid_t stranger = fork_child([&] {
        if (!chimera::test::become_nobody({})) return 10;
        try {
            Segment::watch(name, kKind);
            return 3;
        } catch (const SegmentError& e) {
            keep(e);
            return e.error_number() == EACCES ? 0 : 4;
        }
    });
    EXPECT_EQ(wait_child(stranger), 0);
    EXPECT_EQ(std::string(message->text), "segment " + name + ": permission denied: " + path +
                                         " is root's (group users, mode 0640): add yourself to group users "
                                         "(usermod -aG users nobody), then log in again");
    owner.detach_destroy_if_last();
}
