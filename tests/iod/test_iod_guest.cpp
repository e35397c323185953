// IOD drivers against the real kernel interfaces, inside the PREEMPT_RT guest
// (tests/rtguest): PIO on gpio-sim through libgpiod, RCB on vcan through
// SocketCAN. guest-init.sh creates the gpio-sim chip (bank0: 8 lines, bank1:
// 4 lines) and vcan0 and names them in the environment. Outside the guest the
// tests skip; inside it a missing interface is a failure.
#include "guest_env.hpp"
#include "chimera/iod.hpp"

#include <gtest/gtest.h>

#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <string>
#include <thread>

namespace iod = chimera::iod;

namespace {

using chimera::test::env;

std::string what_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const iod::Error& e) {
        return e.what();
    }
    return "(no error)";
}

#define REQUIRE_ENV(var) CHIMERA_REQUIRE_GUEST_ENV(var)

// --- PIO on gpio-sim --------------------------------------------------------
class PioGuest : public ::testing::Test {
protected:
    void SetUp() override {
        REQUIRE_ENV("CHIMERA_GPIOSIM_CHIP0");
        REQUIRE_ENV("CHIMERA_GPIOSIM_CHIP1");
        REQUIRE_ENV("CHIMERA_GPIOSIM_DEV");
        chip0_ = env("CHIMERA_GPIOSIM_CHIP0");
        chip1_ = env("CHIMERA_GPIOSIM_CHIP1");
        sysfs_ = "/sys/devices/platform/" + env("CHIMERA_GPIOSIM_DEV");
        db_ = iod::Database::from_string(
            "DEVICE dio PIO gpio\nPATH " + chip0_ + "\nLINES 8\nWIDTH 4\nEND\n"
            "DEVICE bits PIO gpio\nPATH " + chip1_ + "\nLINES 4\nEND\n"
            "DEVICE din PIO gpio\nPATH " + chip1_ + "\nLINES 4\nDIRECTION IN\nEND\nEOF\n",
            "guest.iod");
        for (int i = 0; i < 8; ++i) pull(chip0_, i, false);
        for (int i = 0; i < 4; ++i) pull(chip1_, i, false);
    }
    // Drives a simulated input line (gpio-sim's pull attribute).
    void pull(const std::string& chip, int line, bool up) { chimera::test::gpiosim_pull(sysfs_ + "/" + chip, line, up); }
    // What an output line drives, as gpio-sim sees it.
    int value(const std::string& chip, int line) { return chimera::test::gpiosim_value(sysfs_ + "/" + chip, line); }
    std::string chip0_, chip1_, sysfs_;
    iod::Database db_ = iod::Database::from_string("EOF\n", "empty");
};

TEST_F(PioGuest, ReadsPortsOfAdjacentLinesWithConversions) {
    auto in = iod::open(db_, "dio", 0, 0, iod::READ | iod::BYTE);
    EXPECT_EQ(in->status(iod::Status::PORTNUM), 2);
    EXPECT_EQ(in->status(iod::Status::PORTSIZE, 0L), 4);
    pull(chip0_, 1, true);
    pull(chip0_, 3, true);  // port 0 = 0b1010
    std::uint8_t v = 0;
    EXPECT_GE(in->read(&v, 1), 0);
    EXPECT_EQ(v, 0x0A);
    ASSERT_EQ(in->control(iod::Control::SET_FLAGS, iod::READ | iod::BYTE | iod::SIGNED), 0);
    EXPECT_GE(in->read(&v, 1), 0);
    EXPECT_EQ(v, 0xFA) << "a 4-bit port with its top bit set, sign-extended";
    ASSERT_EQ(in->control(iod::Control::SET_FLAGS, iod::READ | iod::WORD), 0);
    std::uint16_t w = 0;
    EXPECT_GE(in->read(&w, 1), 0);
    EXPECT_EQ(w, 0x000A);
}

TEST_F(PioGuest, WritesPortsToOutputLines) {
    auto out = iod::open(db_, "dio", 1, 1, iod::WRITE | iod::BYTE);
    std::uint8_t v = 0x5;  // lines 4..7 = 1,0,1,0
    EXPECT_EQ(out->write(&v, 1), 1);
    EXPECT_EQ(value(chip0_, 4), 1);
    EXPECT_EQ(value(chip0_, 5), 0);
    EXPECT_EQ(value(chip0_, 6), 1);
    EXPECT_EQ(value(chip0_, 7), 0);
    ASSERT_EQ(out->control(iod::Control::SET_FLAGS, iod::WRITE | iod::BYTE | iod::TRUNC_LSB), 0);
    v = 0x30;  // with TRUNC_LSB the byte's high nibble goes to the 4-bit port
    EXPECT_EQ(out->write(&v, 1), 1);
    EXPECT_EQ(value(chip0_, 4), 1);
    EXPECT_EQ(value(chip0_, 5), 1);
    EXPECT_EQ(value(chip0_, 6), 0);
    EXPECT_EQ(value(chip0_, 7), 0);
    std::uint8_t r;
    EXPECT_EQ(out->read(&r, 1), -EBADF);
}

TEST_F(PioGuest, WaitFlagsWaitForEdges) {
    auto in = iod::open(db_, "bits", 0, 1, iod::READ | iod::BYTE | iod::WAITNOALL);
    std::uint8_t v[2] = {9, 9};
    EXPECT_EQ(in->read(v, 2), 0) << "no edge yet";
    pull(chip1_, 0, true);
    usleep(20000);
    EXPECT_EQ(in->read(v, 2), 0) << "WAITNOALL: one port of two changed is nothing";
    EXPECT_EQ(v[0], 9) << "nothing returned";
    pull(chip1_, 1, true);
    usleep(20000);
    EXPECT_EQ(in->read(v, 2), 2);
    EXPECT_EQ(v[0], 1);
    EXPECT_EQ(v[1], 1);

    ASSERT_EQ(in->control(iod::Control::SET_FLAGS, iod::READ | iod::BYTE | iod::WAITNONE), 0);
    EXPECT_EQ(in->read(v, 2), 0) << "levels, nothing new";
    EXPECT_EQ(v[0], 1);

    ASSERT_EQ(in->control(iod::Control::SET_FLAGS, iod::READ | iod::BYTE | iod::WAITONE), 0);
    std::thread t([&] {
        usleep(50000);
        pull(chip1_, 1, false);
    });
    EXPECT_EQ(in->read(v, 2), 1) << "WAITONE returns at the first edge";
    t.join();
    EXPECT_EQ(v[1], 0);

    ASSERT_EQ(in->control(iod::Control::SET_FLAGS, iod::READ | iod::BYTE | iod::WAITALL), 0);
    std::thread t2([&] {
        usleep(30000);
        pull(chip1_, 0, false);
        usleep(30000);
        pull(chip1_, 1, true);
    });
    EXPECT_EQ(in->read(v, 2), 2) << "WAITALL waits for an edge on every port";
    t2.join();
    EXPECT_EQ(v[0], 0);
    EXPECT_EQ(v[1], 1);
    EXPECT_GE(in->status(iod::Status::PIO_EVENTS), 5);
}

TEST_F(PioGuest, OutputsComeUpAtTheirInitialValues) {
    // Watch the lines from the moment they are requested: gpio-sim shows a
    // released line at its pull, so pull them all up first and check that
    // a port asked to start at 0b0110 does not show the pull or 0.
    for (int i = 0; i < 8; ++i) pull(chip0_, i, true);
    const std::uint8_t initial[2] = {0x6, 0x9};
    auto out = iod::open(db_, "dio", 0, 1, iod::WRITE | iod::BYTE, initial);
    const int expect[8] = {0, 1, 1, 0, 1, 0, 0, 1};
    for (int i = 0; i < 8; ++i) EXPECT_EQ(value(chip0_, i), expect[i]) << "line " << i;
    // Without initial values the lines come up at 0.
    out.reset();
    auto zeros = iod::open(db_, "dio", 0, 1, iod::WRITE | iod::BYTE);
    for (int i = 0; i < 8; ++i) EXPECT_EQ(value(chip0_, i), 0) << "line " << i;
}

TEST_F(PioGuest, EdgesAreCountedPerPort) {
    auto in = iod::open(db_, "bits", 1, 3, iod::READ | iod::BYTE);
    std::uint8_t v[3];
    // One pull at a time: gpio-sim's interrupts of one line coalesce when
    // two changes come before the first is delivered.
    pull(chip1_, 1, true);
    usleep(20000);
    pull(chip1_, 1, false);
    usleep(20000);
    pull(chip1_, 3, true);
    usleep(20000);
    EXPECT_EQ(in->read(v, 3), 2) << "ports 1 and 3 changed";
    EXPECT_EQ(in->status(iod::Status::PIO_PORT_EVENTS, 1L), 2);
    EXPECT_EQ(in->status(iod::Status::PIO_PORT_EVENTS, 2L), 0);
    EXPECT_EQ(in->status(iod::Status::PIO_PORT_EVENTS, 3L), 1);
    EXPECT_EQ(in->status(iod::Status::PIO_EVENTS), 3);
    EXPECT_EQ(in->status(iod::Status::PIO_PORT_EVENTS, 0L), -EINVAL) << "not a port of this instance";
    EXPECT_EQ(in->status(iod::Status::PIO_PORT_EVENTS, 4L), -EINVAL);
}

TEST_F(PioGuest, WaitTimeoutBoundsABlockingRead) {
    auto in = iod::open(db_, "bits", 0, 1, iod::READ | iod::BYTE | iod::WAITONE);
    ASSERT_EQ(in->control(iod::Control::WAIT_TIMEOUT, 50000), 0);
    std::uint8_t v[2] = {9, 9};
    EXPECT_EQ(in->read(v, 2), 0) << "no edge within 50 ms";
    EXPECT_EQ(v[0], 9) << "buffer untouched on a timeout";
    pull(chip1_, 1, true);
    usleep(20000);
    EXPECT_EQ(in->read(v, 2), 1) << "an edge that came in is returned";
    EXPECT_EQ(v[1], 1);

    ASSERT_EQ(in->control(iod::Control::SET_FLAGS, iod::READ | iod::BYTE | iod::WAITALL), 0);
    pull(chip1_, 0, true);
    usleep(20000);
    std::uint8_t w[2] = {9, 9};
    EXPECT_EQ(in->read(w, 2), 0) << "WAITALL: port 1 has no new edge";
    EXPECT_EQ(w[0], 9);
    pull(chip1_, 1, false);
    usleep(20000);
    EXPECT_EQ(in->read(w, 2), 2) << "port 0's edge stayed pending through the timeout";
    EXPECT_EQ(w[0], 1);
    EXPECT_EQ(w[1], 0);

    EXPECT_EQ(in->control(iod::Control::WAIT_TIMEOUT, -2), -EINVAL);
    ASSERT_EQ(in->control(iod::Control::WAIT_TIMEOUT, -1), 0);
    std::thread t([&] {
        usleep(100000);
        pull(chip1_, 0, false);
        usleep(20000);
        pull(chip1_, 1, true);
    });
    EXPECT_EQ(in->read(w, 2), 2) << "-1: waits for as long as it takes";
    t.join();
}

TEST_F(PioGuest, OpenedPortsAreRefusedToOtherInstances) {
    auto a = iod::open(db_, "bits", 0, 1, iod::READ);
    EXPECT_NE(what_of([&] { iod::open(db_, "bits", 1, 2, iod::READ); }).find("already open"),
              std::string::npos);
    EXPECT_NO_THROW(iod::open(db_, "bits", 2, 3, iod::WRITE)) << "other ports of the same device";
    // The same lines under another database name: the kernel refuses them.
    const std::string busy = what_of([&] { iod::open(db_, "din", 0, 0, iod::READ); });
    EXPECT_NE(busy.find("cannot request lines"), std::string::npos) << busy;
}

TEST_F(PioGuest, DirectionAndRangeErrorsAtOpen) {
    EXPECT_EQ(what_of([&] { iod::open(db_, "din", 0, 0, iod::WRITE); }),
              "device din (guest.iod:10): opened WRITE but its DIRECTION is IN");
    const std::string far = what_of([&] {
        auto d = iod::Database::from_string("DEVICE big PIO gpio\nPATH " + chip1_ +
                                                "\nLINES 16\nEND\nEOF\n", "big.iod");
        iod::open(d, "big", 0, 15, iod::READ);
    });
    EXPECT_NE(far.find("do not exist on " + chip1_), std::string::npos) << far;
}

// --- RCB on vcan ------------------------------------------------------------
class CanGuest : public ::testing::Test {
protected:
    void SetUp() override {
        REQUIRE_ENV("CHIMERA_VCAN");
        ifname_ = env("CHIMERA_VCAN");
        db_ = iod::Database::from_string("DEVICE arm RCB socketcan\nPATH " + ifname_ +
                                             "\n"
                                             "FRAME 0x181 IN 4 16\n"
                                             "FRAME 0x201 OUT 2 32\n"
                                             "FRAME 0x182 IN 1 12\n"
                                             "END\nEOF\n",
                                         "can.iod");
        peer_ = socket(PF_CAN, SOCK_RAW, CAN_RAW);
        ASSERT_GE(peer_, 0) << std::strerror(errno);
        sockaddr_can a{};
        a.can_family = AF_CAN;
        a.can_ifindex = static_cast<int>(if_nametoindex(ifname_.c_str()));
        ASSERT_EQ(bind(peer_, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
    }
    void TearDown() override {
        if (peer_ >= 0) close(peer_);
    }
    void send(std::uint32_t id, std::initializer_list<std::uint8_t> data) {
        can_frame f{};
        f.can_id = id;
        f.can_dlc = static_cast<std::uint8_t>(data.size());
        std::copy(data.begin(), data.end(), f.data);
        ASSERT_EQ(write(peer_, &f, sizeof f), static_cast<ssize_t>(sizeof f));
    }
    bool receive(can_frame& f) {
        pollfd p{peer_, POLLIN, 0};
        if (poll(&p, 1, 2000) != 1) return false;
        return read(peer_, &f, sizeof f) == static_cast<ssize_t>(sizeof f);
    }
    std::string ifname_;
    int peer_ = -1;
    iod::Database db_ = iod::Database::from_string("EOF\n", "empty");
};

TEST_F(CanGuest, FramesMapToPortsWithSignedConversion) {
    auto in = iod::open(db_, "arm", 0, 3, iod::READ | iod::WORD | iod::SIGNED | iod::WAITALL);
    send(0x181, {0x01, 0x00, 0xFE, 0xFF, 0x2C, 0x01, 0x00, 0x80});
    std::int16_t v[4] = {};
    EXPECT_EQ(in->read(v, 4), 4);
    EXPECT_EQ(v[0], 1);
    EXPECT_EQ(v[1], -2);
    EXPECT_EQ(v[2], 300);
    EXPECT_EQ(v[3], -32768);
    EXPECT_GT(in->status(iod::Status::CAN_TIMESTAMP, 2L), 0) << "kernel receive time stamp";
    EXPECT_EQ(in->status(iod::Status::CAN_RX_FRAMES), 1);
    EXPECT_EQ(in->status(iod::Status::PORTSIZE, 6L), 12);
    EXPECT_EQ(in->status(iod::Status::PORTNUM), 7);
}

TEST_F(CanGuest, FilterPassesOnlyItsFrames) {
    auto in = iod::open(db_, "arm", 0, 3, iod::READ | iod::WORD | iod::WAITNONE);
    send(0x182, {0x11, 0x02});
    send(0x999, {1});
    send(0x201, {1, 2, 3, 4, 5, 6, 7, 8});
    usleep(20000);
    std::uint16_t v[4] = {};
    EXPECT_EQ(in->read(v, 4), 0);
    EXPECT_EQ(in->status(iod::Status::CAN_RX_FRAMES), 0);
    send(0x181, {0x34, 0x12});
    usleep(20000);
    EXPECT_EQ(in->read(v, 4), 4);
    EXPECT_EQ(v[0], 0x1234);
    EXPECT_EQ(v[1], 0) << "beyond the frame's DLC";
}

TEST_F(CanGuest, WaitNoAllAndTruncLsb) {
    auto in = iod::open(db_, "arm", 0, 6, iod::RW | iod::BYTE | iod::TRUNC_LSB | iod::WAITNOALL);
    std::uint8_t v[7] = {};
    send(0x181, {0, 0x12, 0, 0x34, 0, 0x56, 0, 0x78});
    usleep(20000);
    EXPECT_EQ(in->read(v, 7), 0) << "frame 0x182 is still missing";
    send(0x182, {0xBC, 0x0A});  // 12-bit port = 0xABC
    usleep(20000);
    EXPECT_EQ(in->read(v, 7), 5) << "4 ports of 0x181 and 1 of 0x182";
    EXPECT_EQ(v[0], 0x12);
    EXPECT_EQ(v[3], 0x78);
    EXPECT_EQ(v[6], 0xAB) << "bits 4..11 of the 12-bit port";
}

TEST_F(CanGuest, WaitOneBlocksUntilAFrame) {
    auto in = iod::open(db_, "arm", 0, 3, iod::READ | iod::WORD | iod::WAITONE);
    std::thread t([&] {
        usleep(50000);
        send(0x181, {7, 0});
    });
    std::uint16_t v[4] = {};
    EXPECT_EQ(in->read(v, 4), 4);
    t.join();
    EXPECT_EQ(v[0], 7);
}

TEST_F(CanGuest, WaitTimeoutBoundsABlockingReadAndKeepsWhatArrived) {
    // Both input frames (ports 0..3 and 6; the output frame between them is
    // skipped by reads of a read-write instance).
    auto in = iod::open(db_, "arm", 0, 6, iod::RW | iod::WORD | iod::WAITALL);
    EXPECT_EQ(in->control(iod::Control::WAIT_TIMEOUT, -2), -EINVAL);
    ASSERT_EQ(in->control(iod::Control::WAIT_TIMEOUT, 30000), 0);
    std::uint16_t v[7] = {};
    send(0x181, {9, 0});  // one of the two frames WAITALL waits for
    const auto t0 = std::chrono::steady_clock::now();
    EXPECT_EQ(in->read(v, 7), 0) << "a frame missing when the time runs out: nothing";
    EXPECT_GE(std::chrono::steady_clock::now() - t0, std::chrono::milliseconds(30));
    EXPECT_EQ(v[0], 0) << "the buffer is untouched";
    send(0x182, {3, 0});
    EXPECT_EQ(in->read(v, 7), 5) << "the first frame stayed fresh: 4 + 1 ports";
    EXPECT_EQ(v[0], 9);
    EXPECT_EQ(v[6], 3);
}

TEST_F(CanGuest, WritePacksPortsIntoTheFrame) {
    auto out = iod::open(db_, "arm", 4, 5, iod::WRITE | iod::LONG);
    const std::uint32_t v[2] = {0x11223344u, 0xAABBCCDDu};
    EXPECT_EQ(out->write(v, 2), 2);
    can_frame f{};
    ASSERT_TRUE(receive(f));
    EXPECT_EQ(f.can_id, 0x201u);
    EXPECT_EQ(f.can_dlc, 8);
    const std::uint8_t expect[8] = {0x44, 0x33, 0x22, 0x11, 0xDD, 0xCC, 0xBB, 0xAA};
    EXPECT_EQ(std::memcmp(f.data, expect, 8), 0);
}

TEST_F(CanGuest, PartialFrameKeepsTheOtherPorts) {
    auto lo = iod::open(db_, "arm", 4, 4, iod::WRITE | iod::LONG);
    const std::uint32_t a = 5;
    EXPECT_EQ(lo->write(&a, 1), 1);
    can_frame f{};
    ASSERT_TRUE(receive(f));
    EXPECT_EQ(f.can_dlc, 8) << "the whole frame is sent";
    EXPECT_EQ(f.data[0], 5);
    EXPECT_EQ(f.data[4], 0);
}

TEST_F(CanGuest, ErrorFramesAreCountedAndReported) {
    auto in = iod::open(db_, "arm", 0, 3, iod::READ | iod::WAITNONE);
    send(CAN_ERR_FLAG | CAN_ERR_BUSOFF, {0, 0, 0, 0, 0, 0, 0, 0});
    usleep(20000);
    std::uint32_t v[4];
    EXPECT_EQ(in->read(v, 4), 0);
    EXPECT_EQ(in->status(iod::Status::CAN_ERRORS), 1);
    EXPECT_EQ(in->status(iod::Status::CAN_LAST_ERROR), static_cast<long>(CAN_ERR_BUSOFF));
}

TEST_F(CanGuest, DoubleOpenAndDirectionRefused) {
    auto a = iod::open(db_, "arm", 0, 3, iod::READ);
    EXPECT_NE(what_of([&] { iod::open(db_, "arm", 3, 3, iod::READ); }).find("already open"),
              std::string::npos);
    EXPECT_NO_THROW(iod::open(db_, "arm", 6, 6, iod::READ));
    EXPECT_EQ(what_of([&] { iod::open(db_, "arm", 4, 5, iod::READ); }),
              "device arm (can.iod:1): opened READ but frame 0x201 (ports 4..5) is OUT");
    auto nodev = iod::Database::from_string(
        "DEVICE x RCB socketcan\nPATH nocan7\nFRAME 1 IN 1 8\nEND\nEOF\n", "x.iod");
    EXPECT_EQ(what_of([&] { iod::open(nodev, "x", 0, 0, iod::READ); }),
              "device x (x.iod:1): no CAN interface named nocan7");
}

}  // namespace
