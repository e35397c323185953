// xmLockFix (§5.3.2): an exhaustive model of the algorithm under sequential
// consistency, with the thesis's own variant and two broken ones that the
// checker must catch; then a stress test on the real implementation.
#include <gtest/gtest.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdint>
#include <deque>
#include <string>
#include <thread>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "chimera/xmail.hpp"
#include "sanitizer.hpp"

namespace {

enum class Variant { fixed, thesis_unlock, no_peterson, wrong_turn };

// Processes 0,1 are RTPUs (TAS on rtpumutex); 2,3 are hosts (hostmutex).
constexpr int kProcs = 4, kRounds = 2;
struct State {
    std::array<std::uint8_t, kProcs> pc{}, rounds{};
    std::uint8_t m[2]{}, flag[2]{}, turn = 0;
    std::uint64_t key() const {
        std::uint64_t k = 0;
        for (int i = 0; i < kProcs; ++i) k = k * 8 + pc[i], k = k * 4 + rounds[i];
        return ((k * 2 + m[0]) * 2 + m[1]) * 4 + flag[0] * 2 + flag[1] + (std::uint64_t{turn} << 60);
    }
};

// One atomic step of process p; false when it cannot move (finished).
bool step(State& s, int p, Variant v) {
    const int side = p < 2 ? 0 : 1, other = 1 - side;
    switch (s.pc[p]) {
        case 0:  // step 1: TAS (RTPU) / byte-set (host, among hosts)
            if (s.rounds[p] == kRounds) return false;
            if (s.m[side] == 0) { s.m[side] = 1; s.pc[p] = v == Variant::no_peterson ? 4 : 1; }
            return true;
        case 1: s.flag[side] = 1; s.pc[p] = 2; return true;
        case 2: s.turn = static_cast<std::uint8_t>(v == Variant::wrong_turn ? side : other); s.pc[p] = 3; return true;
        case 3:
            if (!(s.flag[other] && s.turn == other)) s.pc[p] = 4;
            return true;
        case 4: s.pc[p] = 5; return true;  // leave the critical section
        case 5:
            if (v == Variant::fixed || v == Variant::wrong_turn) s.flag[side] = 0;
            s.pc[p] = 6;
            return true;
        case 6: s.m[side] = 0; s.pc[p] = 0; ++s.rounds[p]; return true;
    }
    return false;
}

struct Result {
    bool mutual_exclusion = true;
    bool always_can_finish = true;
    std::size_t states = 0;
};

Result explore(Variant v) {
    std::unordered_map<std::uint64_t, State> seen;
    std::unordered_map<std::uint64_t, std::vector<std::uint64_t>> preds;
    std::deque<State> todo;
    State init;
    seen.emplace(init.key(), init);
    todo.push_back(init);
    Result r;
    std::vector<std::uint64_t> finals;  // all done (turn may differ)
    while (!todo.empty()) {
        State s = todo.front();
        todo.pop_front();
        int in_cs = 0;
        for (int p = 0; p < kProcs; ++p) in_cs += s.pc[p] == 4;
        if (in_cs > 1) r.mutual_exclusion = false;
        bool done = true;
        for (int p = 0; p < kProcs; ++p) done = done && s.rounds[p] == kRounds;
        if (done) finals.push_back(s.key());
        for (int p = 0; p < kProcs; ++p) {
            State n = s;
            if (!step(n, p, v)) continue;
            preds[n.key()].push_back(s.key());
            if (seen.emplace(n.key(), n).second) todo.push_back(n);
        }
    }
    r.states = seen.size();
    // Every reachable state must still be able to reach the end (no hang).
    std::unordered_set<std::uint64_t> can_finish;
    {
        std::deque<std::uint64_t> back(finals.begin(), finals.end());
        can_finish.insert(finals.begin(), finals.end());
        while (!back.empty()) {
            const std::uint64_t k = back.front();
            back.pop_front();
            for (std::uint64_t p : preds[k])
                if (can_finish.insert(p).second) back.push_back(p);
        }
    }
    r.always_can_finish = can_finish.size() == seen.size();
    return r;
}

}  // namespace

TEST(LockFixModel, FixedAlgorithmIsMutuallyExclusiveAndNeverHangs) {
    const Result r = explore(Variant::fixed);
    EXPECT_GT(r.states, 1000u);
    EXPECT_TRUE(r.mutual_exclusion);
    EXPECT_TRUE(r.always_can_finish);
}

TEST(LockFixModel, ThesisListingUnlockCanHangTheHost) {
    // xmUnlockFix as printed releases only the first-step lock, leaving flag set.
    const Result r = explore(Variant::thesis_unlock);
    EXPECT_TRUE(r.mutual_exclusion);
    EXPECT_FALSE(r.always_can_finish);
}

TEST(LockFixModel, BrokenVariantsAreCaught) {
    EXPECT_FALSE(explore(Variant::no_peterson).mutual_exclusion);
    EXPECT_FALSE(explore(Variant::wrong_turn).mutual_exclusion);
}

TEST(LockFix, StressAcrossProcessesAndThreads) {
    CHIMERA_NOT_UNDER_TSAN("forked lockers");
    struct Shared {
        chimera::xm::LockFix lock;
        long counter;
        int inside;
        int violations;
    };
    auto* sh = static_cast<Shared*>(mmap(nullptr, sizeof(Shared), PROT_READ | PROT_WRITE,
                                         MAP_SHARED | MAP_ANONYMOUS, -1, 0));
    ASSERT_NE(sh, MAP_FAILED);
    new (&sh->lock) chimera::xm::LockFix{};
    constexpr int kIters = 20000;
    auto work = [sh](chimera::xm::LockFix::Who who) {
        for (int i = 0; i < kIters; ++i) {
            if (!sh->lock.lock(who, 5'000'000'000)) { sh->violations += 1000; return; }
            if (++sh->inside != 1) ++sh->violations;
            const long c = sh->counter;
            sh->counter = c + 1;
            --sh->inside;
            sh->lock.unlock(who);
        }
    };
    std::vector<pid_t> kids;
    for (int k = 0; k < 2; ++k) {
        const pid_t pid = fork();
        if (pid == 0) {
            // Each process: one RTPU-side and one host-side contender.
            std::thread a(work, chimera::xm::LockFix::rtpu), b(work, chimera::xm::LockFix::host);
            a.join();
            b.join();
            _exit(0);
        }
        kids.push_back(pid);
    }
    for (pid_t pid : kids) waitpid(pid, nullptr, 0);
    EXPECT_EQ(sh->violations, 0);
    EXPECT_EQ(sh->counter, 4L * kIters);
    // Timeout: held by the RTPU side, the host gives up and holds nothing.
    ASSERT_TRUE(sh->lock.lock(chimera::xm::LockFix::rtpu));
    EXPECT_FALSE(sh->lock.lock(chimera::xm::LockFix::host, 10'000'000));
    EXPECT_EQ(sh->lock.hostmutex.load(), 0u);
    EXPECT_EQ(sh->lock.flag[1].load(), 0u);
    sh->lock.unlock(chimera::xm::LockFix::rtpu);
    EXPECT_TRUE(sh->lock.lock(chimera::xm::LockFix::host, 10'000'000));
    munmap(sh, sizeof(Shared));
}
