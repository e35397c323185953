// Squatted names (issue #29.5, docs/permissions.md): any local user may make
// /dev/shm/chimera.X.svar first, with a chimera header naming a live pid. A
// segment is believed only when its owner stands behind its header: group and
// others may not write to it, and its creator is a process of its owner.
// root removes a squatted one; another user is told whose it is and what to do.
#include <gtest/gtest.h>

#include <fcntl.h>
#include <pwd.h>
#include <sys/mman.h>
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
using chimera::ipc::test::unique_name;
using chimera::ipc::test::wait_child;

namespace {

// In a forked child become nobody: a published segment NAME whose header
// names pid 1 (root's init) as its creator, left behind as a squatter would.
int squat_as_nobody(const std::string& name) {
    if (!chimera::test::become_nobody({})) return 10;
    Segment fake = make(name, 1, 0600);
    fake.header().creator_pid = 1;
    _exit(0);  // no destructor: the file stays, published
}

// In a forked child become nobody and leave a published segment NAME behind:
// its header names the child itself, dead once it is reaped.
int squat_as_nobody_and_die(const std::string& name) {
    if (!chimera::test::become_nobody({})) return 10;
    Segment fake = make(name, 1, 0600);
    _exit(0);
}

// "nobody's (uid 65534, mode 0600)", as make_way() names nobody's file.
std::string nobodys(const char* mode) {
    const passwd* pw = getpwnam("nobody");
    return std::string("nobody's (uid ") + std::to_string(pw ? pw->pw_uid : 0) + ", mode " + mode + ")";
}

// Root's line on stderr for a file of nobody's removed to make way.
std::string removal(const std::string& name, const char* mode, const std::string& why) {
    return "chimera: segment " + name + ", " + nobodys(mode) + ": " + why + ": removed, to be created anew\n";
}

std::string dead_creator(pid_t pid) {
    return "squatted: it is another user's, and the creator its header names, pid " + std::to_string(pid) +
           ", is not running";
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
    EXPECT_EQ(chimera::test::eperm_refusal_as_nobody<SegmentError>([&] { make_way(name, squatted(name)); }),
              "segment " + name + ": squatted: group or others may write to it: it is root's (uid 0, mode 0666), and "
              "only root may remove it (sudo rm /dev/shm" + name + "), then start again");
    EXPECT_TRUE(Segment::exists(name));
    roots.detach_destroy_if_last();
}

// The same squat with a dead creator (issue #29.5, every name): is_stale()
// alone would not tell it from a crash leftover of root's, and create() met
// "already exists". Root's create removes it, says whose it was, and makes its own.
TEST(Squat, RootsCreateReplacesNobodysFakeNamingADeadCreator) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("deadfake");
    const pid_t squatter = fork_child([&] { return squat_as_nobody_and_die(name); });
    ASSERT_EQ(wait_child(squatter), 0);
    EXPECT_EQ(squatted(name), dead_creator(squatter));
    testing::internal::CaptureStderr();
    Segment mine = make(name, 7, 0600);
    EXPECT_EQ(testing::internal::GetCapturedStderr(), removal(name, "0600", dead_creator(squatter)));
    struct stat st {};
    ASSERT_EQ(::stat(("/dev/shm" + name).c_str(), &st), 0);
    EXPECT_EQ(st.st_uid, ::geteuid());
    Segment other = Segment::attach(name, kKind);  // root's own now: believed
    EXPECT_EQ(other.at_bytes<chimera::ipc::test::Body>(0)->value, 7u);
    other.detach();
    mine.detach_destroy_if_last();
}

// A user attaching first (a reader before its writer) must not map the fake:
// root removes it and gets "does not exist", as before its creator made it.
TEST(Squat, RootsAttachRemovesNobodysFakeInsteadOfMappingIt) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("deadattach");
    const pid_t squatter = fork_child([&] { return squat_as_nobody_and_die(name); });
    ASSERT_EQ(wait_child(squatter), 0);
    testing::internal::CaptureStderr();
    try {
        Segment::attach(name, kKind);
        ADD_FAILURE() << "attached to nobody's fake";
    } catch (const SegmentError& e) {
        EXPECT_EQ(std::string(e.what()), "segment " + name + ": does not exist");
        EXPECT_EQ(e.error_number(), ENOENT);
    }
    EXPECT_EQ(testing::internal::GetCapturedStderr(), removal(name, "0600", dead_creator(squatter)));
    EXPECT_FALSE(Segment::exists(name));
}

// A non-root runner cannot read another user's 0600 file, so cannot tell a
// fake from a live segment, and may not remove it: told whose it is and what to do.
TEST(Squat, ANonRootCreateMeetingAnotherUsersFileIsToldWhoseItIs) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("rootsfake");
    ASSERT_EQ(wait_child(fork_child([&] {
                  Segment fake = make(name, 1, 0600);
                  _exit(0);  // no destructor: root's file stays, its creator dead
                  return 0;
              })),
              0);
    EXPECT_EQ(chimera::test::eperm_refusal_as_nobody<SegmentError>([&] { make(name); }),
              "segment " + name + ": taken by another user's file, which this user may not read: it is root's (uid 0, "
              "mode 0600), and only root may remove it (sudo rm /dev/shm" + name + "), then start again");
    EXPECT_TRUE(Segment::exists(name));
    Segment::unlink(name);
}

// A symbolic link nobody plants under a segment name, pointing at root's
// segment: neither root's attach nor its create follows it; the link goes,
// the segment it points at stays untouched.
TEST(Squat, APlantedSymlinkIsNeverFollowed) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string target = unique_name("linktarget"), link = unique_name("link");
    Segment roots = make(target, 5, 0600);
    const auto plant = [&] {
        return wait_child(fork_child([&] {
            if (!chimera::test::become_nobody({})) return 10;
            return ::symlink(("/dev/shm" + target).c_str(), ("/dev/shm" + link).c_str()) == 0 ? 0 : 11;
        }));
    };
    const std::string why = "squatted: a symbolic link, not a segment";
    ASSERT_EQ(plant(), 0);
    EXPECT_EQ(squatted(link), why);
    testing::internal::CaptureStderr();
    EXPECT_THROW(Segment::attach(link, kKind), SegmentError);
    EXPECT_EQ(testing::internal::GetCapturedStderr(), removal(link, "0777", why));
    struct stat st {};
    EXPECT_NE(::lstat(("/dev/shm" + link).c_str(), &st), 0);

    ASSERT_EQ(plant(), 0);
    testing::internal::CaptureStderr();
    Segment mine = make(link, 9, 0600);
    EXPECT_EQ(testing::internal::GetCapturedStderr(), removal(link, "0777", why));
    ASSERT_EQ(::lstat(("/dev/shm" + link).c_str(), &st), 0);
    EXPECT_TRUE(S_ISREG(st.st_mode));
    EXPECT_EQ(roots.at_bytes<chimera::ipc::test::Body>(0)->value, 5u);  // the target kept its body
    mine.detach_destroy_if_last();
    roots.detach_destroy_if_last();
}

// A watcher (chimtop, status and table watchers) must not show a squatter's
// data as the subsystem's, and is not the runner: it refuses, names the
// owner and the remedy, and removes nothing. A genuine segment still watches.
TEST(Squat, RootsWatchRefusesNobodysFakeAndLeavesIt) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("watchfake");
    ASSERT_EQ(wait_child(fork_child([&] { return squat_as_nobody(name); })), 0);
    try {
        Segment::watch(name, kKind);
        ADD_FAILURE() << "watched nobody's fake";
    } catch (const SegmentError& e) {
        EXPECT_EQ(std::string(e.what()),
                  "segment " + name + ": squatted: its header names as its creator pid 1, a process of root, not of "
                  "its owner: it is " + nobodys("0600") + ", and only nobody or root may remove it (sudo rm /dev/shm" +
                  name + "), then start again");
        EXPECT_EQ(e.error_number(), EPERM);
    }
    EXPECT_TRUE(Segment::exists(name));  // a watcher removes nothing
    Segment::unlink(name);

    const std::string genuine = unique_name("watchown");
    Segment own = make(genuine, 3, 0600);
    Segment watcher = Segment::watch(genuine, kKind);
    EXPECT_EQ(watcher.at_bytes<chimera::ipc::test::Body>(0)->value, 3u);
    watcher.detach();
    own.detach_destroy_if_last();
}

// A symbolic link planted under a name: a watcher neither follows nor removes it.
TEST(Squat, RootsWatchRefusesAPlantedSymlinkAndLeavesIt) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string target = unique_name("watchlinktarget"), link = unique_name("watchlink");
    Segment roots = make(target, 5, 0600);
    ASSERT_EQ(wait_child(fork_child([&] {
                  if (!chimera::test::become_nobody({})) return 10;
                  return ::symlink(("/dev/shm" + target).c_str(), ("/dev/shm" + link).c_str()) == 0 ? 0 : 11;
              })),
              0);
    try {
        Segment::watch(link, kKind);
        ADD_FAILURE() << "watched through nobody's link";
    } catch (const SegmentError& e) {
        EXPECT_EQ(std::string(e.what()), "segment " + link + ": squatted: a symbolic link, not a segment: it is " +
                                             nobodys("0777") + ", and only nobody or root may remove it (sudo rm "
                                             "/dev/shm" + link + "), then start again");
        EXPECT_EQ(e.error_number(), EPERM);
    }
    struct stat st {};
    EXPECT_EQ(::lstat(("/dev/shm" + link).c_str(), &st), 0);
    ::unlink(("/dev/shm" + link).c_str());
    roots.detach_destroy_if_last();
}

namespace {

// In a forked child become nobody and leave a file NAME without a chimera
// header, as a segment being made has for a few system calls.
int headerless_as_nobody(const std::string& name) {
    if (!chimera::test::become_nobody({})) return 10;
    const int fd = ::shm_open(name.c_str(), O_RDWR | O_CREAT | O_EXCL, 0600);
    return fd >= 0 && ::ftruncate(fd, 4096) == 0 ? 0 : 11;
}

}  // namespace

// Another user's file without a header counts as squatted only once it has
// had none for 10 s (ctime): judged at an exact `now`, no sleeping.
TEST(Squat, AnotherUsersHeaderlessFileIsSquattedFrom10SecondsOn) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("headerless");
    ASSERT_EQ(wait_child(fork_child([&] { return headerless_as_nobody(name); })), 0);
    struct stat st {};
    ASSERT_EQ(::stat(("/dev/shm" + name).c_str(), &st), 0);
    EXPECT_EQ(squatted(name, st.st_ctime + 9), "");  // may be one being made
    EXPECT_EQ(squatted(name, st.st_ctime + 10), "squatted: it is another user's, and holds no chimera header");
    EXPECT_EQ(squatted(name), "");  // just made: by the clock, young
    Segment::unlink(name);
}

// This user's own file without a header is never squatted, however old.
TEST(Squat, ThisUsersHeaderlessFileIsNeverSquatted) {
    const std::string name = unique_name("ownheaderless");
    const int fd = ::shm_open(name.c_str(), O_RDWR | O_CREAT | O_EXCL, 0600);
    ASSERT_GE(fd, 0);
    ::close(fd);
    struct stat st {};
    ASSERT_EQ(::stat(("/dev/shm" + name).c_str(), &st), 0);
    EXPECT_EQ(squatted(name, st.st_ctime + 3600), "");
    Segment::unlink(name);
}
