// The classic three-thread priority inversion (tests/support/priority_inversion.hpp)
// with PiMutex, and with std::mutex as the control that inverts.
#include "chimera/ipc/pi_mutex.hpp"
#include "priority_inversion.hpp"

#include <gtest/gtest.h>

#include <mutex>
#include <vector>

using namespace chimera::test::inversion;

TEST(PiMutex, BoostsTheHolderPastAMediumHog) {
    chimera::ipc::PiMutex lock;
    const std::vector<int> ev = three_threads(lock);
    if (ev.empty()) GTEST_SKIP() << "SCHED_FIFO is not allowed here";
    // L (boosted to H's priority) released, H took the lock, and only then
    // did M run, finding H done: M never kept L from the CPU.
    EXPECT_EQ(ev, (std::vector<int>{l_released, h_acquired, m_saw_h_done}));
}

// The control: the same scene with a plain mutex inverts — M runs until its
// bound, only then does L release and H get the lock. This is what the test
// above would see if PiMutex lost its protocol.
TEST(PiMutex, APlainMutexInvertsInTheSameScene) {
    std::mutex lock;
    const std::vector<int> ev = three_threads(lock);
    if (ev.empty()) GTEST_SKIP() << "SCHED_FIFO is not allowed here";
    EXPECT_EQ(ev, (std::vector<int>{m_gave_up, l_released, h_acquired}));
}
