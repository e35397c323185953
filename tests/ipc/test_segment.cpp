#include <gtest/gtest.h>

#include <cstring>
#include <vector>
#include <sched.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>

#include "chimera/ipc/segment.hpp"
#include "sanitizer.hpp"
#include "test_util.hpp"

using namespace chimera::ipc;
using chimera::ipc::test::fork_child;
using chimera::ipc::test::unique_name;
using chimera::ipc::test::wait_child;
using chimera::ipc::test::shared_anon;
using chimera::ipc::test::wait_for;
using chimera::ipc::test::Body;
using chimera::ipc::test::kKind;
using chimera::ipc::test::make;

namespace {

template <typename F>
std::string error_of(F&& f) {
    try {
        f();
    } catch (const SegmentError& e) {
        return e.what();
    }
    return "";
}

}  // namespace

TEST(IpcSegment, NameIsChimeraSubsystemObject) {
    EXPECT_EQ(segment_name("arm", "svar"), "/chimera.arm.svar");
    EXPECT_NE(error_of([] { segment_name("", "svar"); }), "");
    EXPECT_NE(error_of([] { segment_name("a/b", "svar"); }), "");
    EXPECT_NE(error_of([] { segment_name("a", std::string(300, 'x')); }), "");
}

TEST(IpcSegment, CreatePublishAttachSeesBodyAndHeader) {
    const std::string name = unique_name("seg1");
    Segment a = make(name, 1234);
    EXPECT_TRUE(a.creator());
    EXPECT_EQ(a.header().magic, kSegmentMagic);
    EXPECT_EQ(a.header().byte_order, kByteOrderCode);
    EXPECT_EQ(a.header().creator_pid, getpid());
    EXPECT_EQ(a.header().total_size, sizeof(Body));
    Segment b = Segment::attach(name, kKind);
    EXPECT_FALSE(b.creator());
    EXPECT_NE(a.base(), b.base());  // two mappings, one memory
    EXPECT_EQ(b.at_bytes<Body>(0)->value, 1234u);
    b.at_bytes<Body>(0)->value = 7;
    EXPECT_EQ(a.at_bytes<Body>(0)->value, 7u);
    EXPECT_EQ(a.users(), 2u);
    b.detach();
    EXPECT_EQ(a.users(), 1u);
    EXPECT_TRUE(a.detach_destroy_if_last());
    EXPECT_FALSE(Segment::exists(name));
}

TEST(IpcSegment, CreateRefusesAnExistingName) {
    const std::string name = unique_name("seg2");
    Segment a = make(name);
    EXPECT_EQ(error_of([&] { Segment::create(name, 128, kKind); }),
              "segment " + name + ": already exists");
    a.detach_destroy_if_last();
}

TEST(IpcSegment, AttachToMissingSegmentNamesIt) {
    const std::string name = unique_name("missing");
    EXPECT_EQ(error_of([&] { Segment::attach(name, kKind); }),
              "segment " + name + ": does not exist");
}

TEST(IpcSegment, LayoutVersionMismatchIsAClearError) {
    const std::string name = unique_name("ver");
    Segment a = make(name);
    a.header().layout_version = 3;
    EXPECT_EQ(error_of([&] { Segment::attach(name, kKind); }),
              "segment " + name + ": layout version 3, this library expects 2");
    EXPECT_EQ(a.users(), 1u);  // a refused attach leaves no count behind
    a.detach_destroy_if_last();
}

TEST(IpcSegment, MagicTypeAndByteOrderMismatchesAreClearErrors) {
    const std::string name = unique_name("magic");
    Segment a = make(name);
    a.header().object_type = static_cast<std::uint32_t>(ObjectType::tbuf);
    EXPECT_EQ(error_of([&] { Segment::attach(name, kKind); }),
              "segment " + name + ": holds a tbuf, expected a test");
    a.header().object_type = static_cast<std::uint32_t>(ObjectType::test);
    a.header().byte_order = __builtin_bswap32(kByteOrderCode);
    EXPECT_NE(error_of([&] { Segment::attach(name, kKind); }).find("other byte order"),
              std::string::npos);
    a.header().byte_order = kByteOrderCode;
    a.header().magic = 0xdeadbeef;
    EXPECT_NE(error_of([&] { Segment::attach(name, kKind); }).find("not a chimera segment"),
              std::string::npos);
    a.header().magic = kSegmentMagic;
    EXPECT_NO_THROW(Segment::attach(name, kKind));
    a.detach_destroy_if_last();
}

TEST(IpcSegment, UnpublishedCreationIsUnlinkedWhenAbandoned) {
    const std::string name = unique_name("abandon");
    {
        Segment s = Segment::create(name, 256, kKind);
        EXPECT_TRUE(Segment::exists(name));
        // attach refuses a segment still being built
        AttachOptions quick;
        quick.ready_timeout_ns = 5'000'000;
        EXPECT_NE(error_of([&] { Segment::attach(name, kKind, quick); }).find("still being built"),
                  std::string::npos);
    }  // e.g. an exception during set-up
    EXPECT_FALSE(Segment::exists(name));
}

TEST(IpcSegment, LastUserAcrossProcessesDestroys) {
    CHIMERA_NOT_UNDER_TSAN("a forked user");
    const std::string name = unique_name("last");
    Segment a = make(name, 5);
    const pid_t child = fork_child([&] {
        Segment b = Segment::attach(name, kKind);
        if (b.at_bytes<Body>(0)->value != 5) return 2;
        b.at_bytes<Body>(0)->value = 6;
        // not the last user: the parent still holds it
        return b.detach_destroy_if_last() ? 3 : 0;
    });
    ASSERT_EQ(wait_child(child), 0);
    EXPECT_TRUE(Segment::exists(name));
    EXPECT_EQ(a.at_bytes<Body>(0)->value, 6u);
    EXPECT_EQ(a.users(), 1u);
    EXPECT_TRUE(a.detach_destroy_if_last());
    EXPECT_FALSE(Segment::exists(name));
}

TEST(IpcSegment, DetachKeepsTheNameForLaterUsers) {
    const std::string name = unique_name("keep");
    make(name, 9).detach();
    Segment b = Segment::attach(name, kKind);
    EXPECT_EQ(b.at_bytes<Body>(0)->value, 9u);
    EXPECT_TRUE(b.detach_destroy_if_last());
}

TEST(IpcSegment, OffsetsResolveInEveryMapping) {
    const std::string name = unique_name("off");
    Segment a = Segment::create(name, 4096, kKind);
    Offset<std::uint32_t> off{256};
    *a.at(off) = 77;
    a.publish();
    Segment b = Segment::attach(name, kKind);
    EXPECT_EQ(*b.at(off), 77u);
    EXPECT_EQ(align_up(65, 64), 128u);
    b.detach();
    a.detach_destroy_if_last();
}

// Users killed with SIGKILL while attached are counted out at once (the
// kernel drops their locks), so the last live user frees the segment: the
// attach counter of the header used to keep every killed user counted.
TEST(IpcSegment, KilledUsersAreCountedOutAndTheLastLiveUserFrees) {
    CHIMERA_NOT_UNDER_TSAN("forked users killed");
    const std::string name = unique_name("killed");
    Segment a = make(name, 1);
    auto* attached = shared_anon<std::atomic<int>>();
    std::vector<pid_t> kids;
    for (int k = 0; k < 3; ++k) {
        kids.push_back(fork_child([&] {
            Segment b = Segment::attach(name, kKind);
            attached->fetch_add(1);
            for (;;) pause();  // killed while attached: never detaches
            return 0;
        }));
    }
    ASSERT_TRUE(wait_for([&] { return attached->load() == 3; }));
    EXPECT_EQ(a.users(), 4u);
    for (pid_t k : kids) {
        kill(k, SIGKILL);
        EXPECT_EQ(wait_child(k), 128 + SIGKILL);
    }
    EXPECT_EQ(a.users(), 1u);
    EXPECT_FALSE(Segment::in_use(name) && a.users() != 1u);
    EXPECT_TRUE(a.detach_destroy_if_last());
    EXPECT_FALSE(Segment::exists(name));
}

// The same when the killed process is still a zombie (not reaped): its
// descriptors are closed when it dies, not when its parent waits for it.
TEST(IpcSegment, AKilledUnreapedUserIsCountedOut) {
    CHIMERA_NOT_UNDER_TSAN("a forked user killed");
    const std::string name = unique_name("zombie");
    Segment a = make(name, 1);
    auto* attached = shared_anon<std::atomic<int>>();
    const pid_t kid = fork_child([&] {
        Segment b = Segment::attach(name, kKind);
        attached->store(1);
        for (;;) pause();
        return 0;
    });
    ASSERT_TRUE(wait_for([&] { return attached->load() == 1; }));
    kill(kid, SIGKILL);
    siginfo_t info{};
    ASSERT_EQ(waitid(P_PID, static_cast<id_t>(kid), &info, WEXITED | WNOWAIT), 0);  // a zombie
    EXPECT_TRUE(a.detach_destroy_if_last());
    EXPECT_FALSE(Segment::exists(name));
    wait_child(kid);
}

// A process that shares another's memory (clone with CLONE_VM) and holds
// nothing else: it closes every descriptor it got, stores its pid in `arg`
// and waits to be killed. Only system calls: it runs on a stack of its own in
// its creator's memory.
static int share_memory_only(void* arg) {
    syscall(SYS_close_range, 0u, ~0u, 0u);
    static_cast<std::atomic<int>*>(arg)->store(static_cast<int>(syscall(SYS_getpid)));
    for (;;) syscall(SYS_pause);
}

// A user whose memory outlives it is counted out when it dies, not when its
// memory goes. Here another process shares that memory for as long as the
// test likes; a reader of its /proc/PID/stat (ps, top) shares it for the
// read. The user lock used to sit on the open file description its mapping
// holds, so such a dead user counted on (the TBUF kill loop saw it) and a last
// user detaching meanwhile left the segment behind.
TEST(IpcSegment, AKilledUserIsCountedOutThoughItsMemoryLivesOn) {
    CHIMERA_NOT_UNDER_TSAN("a forked user killed");
    const std::string name = unique_name("memory");
    Segment a = make(name, 1);
    ASSERT_EQ(prctl(PR_SET_CHILD_SUBREAPER, 1), 0);  // the sharer comes back to us to be reaped
    auto* sharer = shared_anon<std::atomic<int>>();
    const pid_t kid = fork_child([&] {
        Segment b = Segment::attach(name, kKind);
        static char stack[64 * 1024];
        if (clone(share_memory_only, stack + sizeof stack, CLONE_VM | SIGCHLD, sharer) < 0) return 1;
        for (;;) pause();  // killed while attached
        return 0;
    });
    const bool sharing = wait_for([&] { return sharer->load() > 0; });
    EXPECT_TRUE(sharing) << "the process sharing the user's memory did not start";
    if (sharing) {
        EXPECT_EQ(a.users(), 2u);
    }
    kill(kid, SIGKILL);
    EXPECT_EQ(wait_child(kid), 128 + SIGKILL);
    EXPECT_EQ(a.users(), 1u);
    EXPECT_TRUE(a.detach_destroy_if_last());
    EXPECT_FALSE(Segment::exists(name));
    if (sharing) {
        kill(sharer->load(), SIGKILL);
        waitpid(sharer->load(), nullptr, 0);
    }
    prctl(PR_SET_CHILD_SUBREAPER, 0);
}

// A user that is not the creator frees it when the creator was killed.
TEST(IpcSegment, TheLastLiveUserFreesWhenTheCreatorWasKilled) {
    CHIMERA_NOT_UNDER_TSAN("a forked creator killed");
    const std::string name = unique_name("orphan");
    auto* made = shared_anon<std::atomic<int>>();
    const pid_t creator = fork_child([&] {
        Segment s = make(name, 3);
        made->store(1);
        for (;;) pause();
        return 0;
    });
    ASSERT_TRUE(wait_for([&] { return made->load() == 1; }));
    Segment b = Segment::attach(name, kKind);
    EXPECT_TRUE(Segment::in_use(name));
    kill(creator, SIGKILL);
    wait_child(creator);
    EXPECT_EQ(b.users(), 1u);
    EXPECT_TRUE(b.detach_destroy_if_last());
    EXPECT_FALSE(Segment::exists(name));
    EXPECT_FALSE(Segment::in_use(name));
}

// A handle a child inherits through fork() is its parent's mapping: the
// child's destructor neither frees the segment nor drops the parent's count.
TEST(IpcSegment, AHandleCopiedByForkNeitherCountsNorFrees) {
    CHIMERA_NOT_UNDER_TSAN("a forked copy of the handle");
    const std::string name = unique_name("forked");
    Segment a = make(name, 4);
    const pid_t kid = fork_child([&] { return a.detach_destroy_if_last() ? 1 : 0; });
    EXPECT_EQ(wait_child(kid), 0);
    EXPECT_TRUE(Segment::exists(name));
    EXPECT_EQ(a.users(), 1u);
    EXPECT_TRUE(a.detach_destroy_if_last());
}

// Nor does a child that keeps the inherited mapping after its parent
// detached keep the parent counted: the parent's locks are not on the
// description that mapping holds, so the next user is the last and frees.
TEST(IpcSegment, AChildKeepingAnInheritedMappingDoesNotKeepItsParentCounted) {
    CHIMERA_NOT_UNDER_TSAN("a forked copy of the mapping");
    const std::string name = unique_name("inherited");
    Segment a = make(name, 5);
    auto* forked = shared_anon<std::atomic<int>>();
    const pid_t kid = fork_child([&] {
        forked->store(1);  // past fork()'s handlers, which close the inherited descriptors
        for (;;) pause();  // the inherited mapping stays until killed
        return 0;
    });
    ASSERT_TRUE(wait_for([&] { return forked->load() == 1; }));
    a.detach();
    Segment b = Segment::attach(name, kKind);
    EXPECT_EQ(b.users(), 1u);
    EXPECT_TRUE(b.detach_destroy_if_last());
    EXPECT_FALSE(Segment::exists(name));
    kill(kid, SIGKILL);
    wait_child(kid);
}

// An attach racing with the last user's destroy either fails cleanly or
// keeps the segment as a new user: never a mapping of a removed name that
// counts as alive, never a leak.
TEST(IpcSegment, AttachRacingWithTheLastDetachNeverLeaks) {
    CHIMERA_NOT_UNDER_TSAN("forked attachers");
    for (int round = 0; round < 50; ++round) {
        const std::string name = unique_name("race" + std::to_string(round));
        Segment a = make(name, 5);
        auto* go = shared_anon<std::atomic<int>>();
        const pid_t kid = fork_child([&] {
            while (go->load() == 0) {
            }
            try {
                Segment b = Segment::attach(name, kKind);
                b.detach_destroy_if_last();
            } catch (const SegmentError&) {
            }
            return 0;
        });
        go->store(1);
        a.detach_destroy_if_last();
        EXPECT_EQ(wait_child(kid), 0);
        EXPECT_FALSE(Segment::exists(name)) << "round " << round;
        munmap(go, sizeof *go);
    }
}
