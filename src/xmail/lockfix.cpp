// xmLockFix (thesis §5.3.2): test-and-set among the RTPUs, the host side's
// own lock among hosts, then Peterson's algorithm between the two winners.
#include <time.h>

#include "chimera/ipc/clock.hpp"
#include "chimera/xmail.hpp"

namespace chimera::xm {
namespace {

// The thesis's delay(0.0001) between polls, after a short spin.
void pause_a_little(std::uint32_t& spins) noexcept {
    if (++spins < 64) {
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#endif
        return;
    }
    timespec ts{0, 50'000};
    nanosleep(&ts, nullptr);
}

}  // namespace

bool LockFix::lock(Who who, std::int64_t timeout_ns) noexcept {
    const std::int64_t deadline = timeout_ns < 0 ? -1 : ipc::now_ns() + timeout_ns;
    auto expired = [&] { return deadline >= 0 && ipc::now_ns() >= deadline; };
    std::atomic<std::uint32_t>& first = who == rtpu ? rtpumutex : hostmutex;
    std::uint32_t spins = 0;
    // Step 1: one contender per side. (A host without TAS would use its own
    // single-processor lock here; on Linux every side has an atomic exchange.)
    while (first.exchange(1, std::memory_order_seq_cst) != 0) {
        if (expired()) return false;
        pause_a_little(spins);
    }
    // Step 2: Peterson between the RTPU winner and the host winner.
    const std::uint32_t other = 1u - who;
    flag[who].store(1, std::memory_order_seq_cst);
    turn.store(other, std::memory_order_seq_cst);
    while (flag[other].load(std::memory_order_seq_cst) != 0 &&
           turn.load(std::memory_order_seq_cst) == other) {
        if (expired()) {
            flag[who].store(0, std::memory_order_seq_cst);
            first.store(0, std::memory_order_seq_cst);
            return false;
        }
        pause_a_little(spins);
    }
    return true;
}

void LockFix::unlock(Who who) noexcept {
    flag[who].store(0, std::memory_order_seq_cst);
    (who == rtpu ? rtpumutex : hostmutex).store(0, std::memory_order_seq_cst);
}

}  // namespace chimera::xm
