// Host tests of the IOD service (thesis §7.2.1): the conversions, the device
// database, open-time checks, port reservation, and the SIO driver over a
// pseudo-terminal pair and the MEM driver. The PIO and CAN drivers run against
// gpio-sim and vcan in the PREEMPT_RT guest (test_iod_guest.cpp); here only
// their "kernel interface missing" errors are checked.
#include "chimera/iod.hpp"
#include "chimera/ipc/segment.hpp"
#include "as_user.hpp"

#include <gtest/gtest.h>

#include <fcntl.h>
#include <sys/stat.h>
#include <poll.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>
#include <thread>

namespace iod = chimera::iod;

namespace {

std::string what_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const iod::Error& e) {
        return e.what();
    }
    return "(no error)";
}

// --- conversions (§7.2.1) ---------------------------------------------------
TEST(IodConvert, ExpandPadsWithZerosByDefault) {
    EXPECT_EQ(iod::convert_in(0xABC, 12, 16, 0), 0x0ABCu);
    EXPECT_EQ(iod::convert_in(0x800, 12, 32, 0), 0x800u);
    EXPECT_EQ(iod::convert_in(0x1, 1, 8, 0), 0x01u);
}

TEST(IodConvert, SignedExpandPadsWithTheSignBit) {
    EXPECT_EQ(iod::convert_in(0x800, 12, 16, iod::SIGNED), 0xF800u);
    EXPECT_EQ(iod::convert_in(0x800, 12, 32, iod::SIGNED), 0xFFFFF800u);
    EXPECT_EQ(iod::convert_in(0x7FF, 12, 16, iod::SIGNED), 0x07FFu);
    EXPECT_EQ(iod::convert_in(0x1, 1, 8, iod::SIGNED), 0xFFu);
    EXPECT_EQ(static_cast<std::int16_t>(iod::convert_in(0xFFE, 12, 16, iod::SIGNED)), -2);
}

TEST(IodConvert, ReduceTruncatesMsbByDefaultAndLsbOnRequest) {
    EXPECT_EQ(iod::convert_in(0xABC, 12, 8, 0), 0xBCu);
    EXPECT_EQ(iod::convert_in(0xABC, 12, 8, iod::TRUNC_LSB), 0xABu);  // bits 4..11
    EXPECT_EQ(iod::convert_in(0xABC, 12, 8, iod::SIGNED), 0xBCu);     // no effect when reducing
    EXPECT_EQ(iod::convert_in(0x12345678, 32, 16, iod::TRUNC_LSB), 0x1234u);
}

TEST(IodConvert, RawBitsAboveThePortAreIgnored) {
    EXPECT_EQ(iod::convert_in(0xFABC, 12, 16, 0), 0x0ABCu);
}

TEST(IodConvert, OutIsTheInverseOfIn) {
    EXPECT_EQ(iod::convert_out(0xBC, 8, 12, 0), 0x0BCu);
    EXPECT_EQ(iod::convert_out(0xFE, 8, 12, iod::SIGNED), 0xFFEu);
    EXPECT_EQ(iod::convert_out(0xAB, 8, 12, iod::TRUNC_LSB), 0xAB0u);
    EXPECT_EQ(iod::convert_out(0xFABC, 16, 12, 0), 0xABCu);
    EXPECT_EQ(iod::convert_out(0xABCD, 16, 12, iod::TRUNC_LSB), 0xABCu);
    for (std::uint32_t v = 0; v < 0x1000; v += 7) {
        EXPECT_EQ(iod::convert_out(iod::convert_in(v, 12, 16, iod::SIGNED), 16, 12, iod::SIGNED), v);
        EXPECT_EQ(iod::convert_out(iod::convert_in(v, 12, 32, 0), 32, 12, 0), v);
    }
}

// --- the device database ----------------------------------------------------
constexpr const char* kDb = R"(# test database
DEFINE DIO_LINES 8
DEVICE dio0 PIO gpio
  PATH chimera-no-such-chip
  LINES DIO_LINES
  WIDTH 4
END
DEVICE din PIO gpio
  PATH chimera-no-such-chip
  LINES 2
  DIRECTION IN
END
DEVICE arm RCB socketcan
  PATH chimnocan0
  FRAME 0x181 IN 4 16
  FRAME 0x201 OUT 2 32
  FRAME 0x182 IN 1 12
END
DEVICE tty SIO termios
  PATH /dev/null
  BAUD 19200
  PARITY EVEN
END
EOF
)";

TEST(IodDatabase, ParsesDevicesAndPorts) {
    auto db = iod::Database::from_string(kDb, "lab.iod");
    ASSERT_EQ(db.devices().size(), 4u);
    const iod::DeviceSpec* dio = db.find("dio0");
    ASSERT_NE(dio, nullptr);
    EXPECT_EQ(dio->device_class, iod::DeviceClass::PIO);
    EXPECT_EQ(dio->lines, 8);
    EXPECT_EQ(dio->port_count(), 2);
    EXPECT_EQ(dio->port_bits(1), 4);
    EXPECT_EQ(dio->directions, iod::RW);
    EXPECT_EQ(db.find("din")->directions, iod::READ);
    const iod::DeviceSpec* arm = db.find("arm");
    ASSERT_EQ(arm->frames.size(), 3u);
    EXPECT_EQ(arm->port_count(), 7);
    EXPECT_EQ(arm->frames[1].can_id, 0x201u);
    EXPECT_EQ(arm->frames[1].first_port, 4);
    EXPECT_EQ(arm->frames[2].first_port, 6);
    EXPECT_EQ(arm->port_bits(3), 16);
    EXPECT_EQ(arm->port_bits(5), 32);
    EXPECT_EQ(arm->port_bits(6), 12);
    EXPECT_EQ(arm->port_bits(7), -1);
    EXPECT_EQ(db.find("tty")->sio.baud_rx, 19200);
    EXPECT_EQ(db.find("tty")->sio.parity, iod::SIO_EVEN);
    EXPECT_EQ(db.find("nothing"), nullptr);
}

TEST(IodDatabase, ErrorsNameFileAndLine) {
    auto err = [](const std::string& text) {
        return what_of([&] { iod::Database::from_string(text, "bad.iod"); });
    };
    EXPECT_EQ(err("DEVICE x ADX gpio\nEND\nEOF\n"),
              "bad.iod:1: unknown device class ADX (SIO, PIO, ADC, DAC, RCB, SBS, MEM)");
    EXPECT_EQ(err("DEVICE x PIO termios\nEND\nEOF\n"),
              "bad.iod:1: device x: class PIO uses driver gpio, found termios");
    EXPECT_EQ(err("DEVICE x PIO gpio\nPATH c\nEOF\n"), "bad.iod:3: device x: missing END");
    EXPECT_EQ(err("DEVICE x PIO gpio\nPATH c\nEND\nEOF\n"), "bad.iod:1: device x: LINES missing");
    EXPECT_EQ(err("DEVICE x PIO gpio\nPATH c\nLINES 6\nWIDTH 4\nEND\nEOF\n"),
              "bad.iod:1: device x: LINES 6 is not a multiple of WIDTH 4");
    EXPECT_EQ(err("DEVICE x RCB socketcan\nPATH c\nFRAME 0x10 IN 3 32\nEND\nEOF\n"),
              "bad.iod:3: FRAME 0x10: 3 ports of 32 bits do not fit in 8 bytes");
    EXPECT_EQ(err("DEVICE x SIO termios\nPATH c\nLINES 4\nEND\nEOF\n"),
              "bad.iod:3: LINES is not a keyword of class SIO devices");
    EXPECT_EQ(err("DEVICE x MEM shm\nPATH m\nSIZE 8\nEND\nDEVICE x MEM shm\nPATH m\nSIZE 8\nEND\nEOF\n"),
              "bad.iod:5: device x is defined twice (first at line 1)");
    const std::string truncated = err("DEVICE x MEM shm\nPATH m\nSIZE 8\nEND\n");
    EXPECT_EQ(truncated.rfind("bad.iod:", 0), 0u) << truncated;
}

TEST(IodDatabase, LoadsFromFile) {
    const std::string path = ::testing::TempDir() + "iod_test.iod";
    std::ofstream(path) << kDb;
    EXPECT_EQ(iod::Database::load(path).devices().size(), 4u);
    EXPECT_NE(what_of([] { iod::Database::load("/nonexistent/x.iod"); }).find("/nonexistent/x.iod"),
              std::string::npos);
}

// --- open-time checks -------------------------------------------------------
class IodOpen : public ::testing::Test {
protected:
    void SetUp() override {
        lockdir_ = ::testing::TempDir() + "iodlocks." + std::to_string(getpid());
        ::mkdir(lockdir_.c_str(), 0700);
        setenv("CHIMERA_IOD_LOCKDIR", lockdir_.c_str(), 1);
    }
    void TearDown() override {
        std::error_code ec;
        std::filesystem::remove_all(lockdir_, ec);
    }
    std::string lockdir_;
    iod::Database db_ = iod::Database::from_string(kDb, "lab.iod");
};

TEST_F(IodOpen, UnknownDeviceAndBadRange) {
    EXPECT_EQ(what_of([&] { iod::open(db_, "dio9", 0, 0, iod::READ); }),
              "iod: no device named dio9 in the device database");
    EXPECT_EQ(what_of([&] { iod::open(db_, "dio0", 1, 2, iod::READ); }),
              "device dio0 (lab.iod:3): port range 1..2 outside 0..1");
    EXPECT_EQ(what_of([&] { iod::open(db_, "dio0", 1, 0, iod::READ); }),
              "device dio0 (lab.iod:3): port range 1..0 outside 0..1");
}

TEST_F(IodOpen, DirectionErrorsAreCaughtAtOpen) {
    EXPECT_EQ(what_of([&] { iod::open(db_, "din", 0, 1, iod::WRITE); }),
              "device din (lab.iod:8): opened WRITE but its DIRECTION is IN");
    EXPECT_NE(what_of([&] { iod::open(db_, "dio0", 0, 1, iod::RW); }).find("READ or WRITE, not RW"),
              std::string::npos);
    EXPECT_EQ(what_of([&] { iod::open(db_, "arm", 0, 4, iod::READ); }),
              "device arm (lab.iod:13): opened READ but frame 0x201 (ports 4..5) is OUT");
    EXPECT_EQ(what_of([&] { iod::open(db_, "arm", 6, 6, iod::WRITE); }),
              "device arm (lab.iod:13): opened WRITE but frame 0x182 (ports 6..6) is IN");
}

TEST_F(IodOpen, FlagCombinationsAreCheckedAtOpen) {
    EXPECT_EQ(what_of([&] { iod::open(db_, "arm", 0, 3, iod::READ | iod::WAITALL | iod::WAITONE); }),
              "device arm (lab.iod:13): more than one WAIT flag");
    EXPECT_EQ(what_of([&] { iod::open(db_, "arm", 0, 3, iod::READ | iod::BYTE | iod::LONG); }),
              "device arm (lab.iod:13): more than one of BYTE, WORD, LONG");
    EXPECT_EQ(what_of([&] { iod::open(db_, "tty", 0, 0, iod::READ | iod::WORD); }),
              "device tty (lab.iod:19): a serial line transfers bytes: BYTE elements only");
    EXPECT_EQ(what_of([&] { iod::open(db_, "tty", 0, 0, iod::READ | iod::SIGNED); }),
              "device tty (lab.iod:19): SIGNED and TRUNC_LSB do not apply to a byte stream");
}

TEST_F(IodOpen, InitialValuesOnlyForPioOutputs) {
    const std::uint8_t initial[2] = {1, 1};
    EXPECT_EQ(what_of([&] { iod::open(db_, "din", 0, 1, iod::READ | iod::BYTE, initial); }),
              "device din (lab.iod:8): initial values are for PIO devices opened WRITE only");
    EXPECT_EQ(what_of([&] { iod::open(db_, "arm", 4, 5, iod::WRITE | iod::BYTE, initial); }),
              "device arm (lab.iod:13): initial values are for PIO devices opened WRITE only");
    // A PIO output gets as far as the chip (absent here): the values were accepted.
    EXPECT_NE(what_of([&] { iod::open(db_, "dio0", 0, 1, iod::WRITE | iod::BYTE, initial); })
                  .find("no gpiochip chimera-no-such-chip"),
              std::string::npos);
}

TEST_F(IodOpen, MissingKernelInterfacesSaySo) {
    const std::string pio = what_of([&] { iod::open(db_, "dio0", 0, 0, iod::READ); });
    EXPECT_NE(pio.find("no gpiochip chimera-no-such-chip"), std::string::npos) << pio;
    // Without AF_CAN (this host) the socket fails; with it, the interface is missing.
    const std::string can = what_of([&] { iod::open(db_, "arm", 0, 3, iod::READ); });
    EXPECT_TRUE(can.find("no AF_CAN support in this kernel") != std::string::npos ||
                can.find("no CAN interface named chimnocan0") != std::string::npos)
        << can;
    const std::string sio = what_of([&] { iod::open(db_, "tty", 0, 0, iod::READ); });
    EXPECT_EQ(sio, "device tty (lab.iod:19): /dev/null is not a terminal (termios)");
}

// --- SIO over a pseudo-terminal pair ----------------------------------------
class IodSio : public IodOpen {
protected:
    void SetUp() override {
        IodOpen::SetUp();
        master_ = posix_openpt(O_RDWR | O_NOCTTY);
        ASSERT_GE(master_, 0);
        ASSERT_EQ(grantpt(master_), 0);
        ASSERT_EQ(unlockpt(master_), 0);
        const std::string slave = ptsname(master_);
        sdb_ = iod::Database::from_string(
            "DEVICE ser SIO termios\nPATH " + slave + "\nBAUD 115200\nBITS 8\nEND\nEOF\n", "sio.iod");
    }
    void TearDown() override { ::close(master_); }
    // Writes on the master side and waits until the slave has `pending` bytes
    // to read (the line discipline forwards asynchronously).
    void put(const std::string& s, long pending) {
        ASSERT_EQ(::write(master_, s.data(), s.size()), static_cast<ssize_t>(s.size()));
        for (int i = 0; i < 2000 && dev_->status(iod::Status::SIO_NREAD) < pending; ++i) usleep(1000);
        ASSERT_EQ(dev_->status(iod::Status::SIO_NREAD), pending);
    }
    std::string get(std::size_t n) {
        std::string s(n, '\0');
        std::size_t got = 0;
        while (got < n) {
            pollfd p{master_, POLLIN, 0};
            if (::poll(&p, 1, 2000) <= 0) break;
            const ssize_t r = ::read(master_, s.data() + got, n - got);
            if (r <= 0) break;
            got += static_cast<std::size_t>(r);
        }
        s.resize(got);
        return s;
    }
    int master_ = -1;
    iod::Database sdb_ = iod::Database::from_string("EOF\n", "empty");
    std::unique_ptr<iod::Device> dev_;
};

TEST_F(IodSio, ReadWaitFlags) {
    dev_ = iod::open(sdb_, "ser", 0, 0, iod::RW | iod::WAITNONE);
    char buf[16] = {};
    EXPECT_EQ(dev_->read(buf, 4), 0) << "WAITNONE, nothing there";
    put("ab", 2);
    EXPECT_EQ(dev_->read(buf, 4), 2);
    EXPECT_EQ(std::string(buf, 2), "ab");

    ASSERT_EQ(dev_->control(iod::Control::SET_FLAGS, iod::RW | iod::WAITNOALL), 0);
    put("cde", 3);
    EXPECT_EQ(dev_->read(buf, 4), 0) << "WAITNOALL: 3 of 4 bytes is nothing";
    put("f", 4);
    EXPECT_EQ(dev_->read(buf, 4), 4);
    EXPECT_EQ(std::string(buf, 4), "cdef");

    ASSERT_EQ(dev_->control(iod::Control::SET_FLAGS, iod::RW | iod::WAITALL), 0);
    std::thread writer([&] {
        usleep(20000);
        EXPECT_EQ(::write(master_, "12", 2), 2);
        usleep(20000);
        EXPECT_EQ(::write(master_, "345", 3), 3);
    });
    EXPECT_EQ(dev_->read(buf, 5), 5) << "WAITALL blocks for every byte";
    writer.join();
    EXPECT_EQ(std::string(buf, 5), "12345");

    ASSERT_EQ(dev_->control(iod::Control::SET_FLAGS, iod::RW | iod::WAITONE), 0);
    std::thread writer2([&] {
        usleep(20000);
        EXPECT_EQ(::write(master_, "x", 1), 1);
    });
    EXPECT_EQ(dev_->read(buf, 8), 1) << "WAITONE blocks for the first byte only";
    writer2.join();
    EXPECT_EQ(buf[0], 'x');
}

TEST_F(IodSio, WaitTimeoutBoundsABlockingReadAndLeavesTheBytesPending) {
    dev_ = iod::open(sdb_, "ser", 0, 0, iod::RW | iod::WAITALL);
    EXPECT_EQ(dev_->control(iod::Control::WAIT_TIMEOUT, -2), -EINVAL);
    ASSERT_EQ(dev_->control(iod::Control::WAIT_TIMEOUT, 30000), 0);
    char buf[8] = {};
    put("ab", 2);
    const auto t0 = std::chrono::steady_clock::now();
    EXPECT_EQ(dev_->read(buf, 4), 0) << "2 of 4 bytes when the time runs out: nothing";
    EXPECT_GE(std::chrono::steady_clock::now() - t0, std::chrono::milliseconds(30));
    EXPECT_EQ(dev_->status(iod::Status::SIO_NREAD), 2) << "and nothing was taken";
    put("cd", 4);
    EXPECT_EQ(dev_->read(buf, 4), 4);
    EXPECT_EQ(std::string(buf, 4), "abcd");
    // WAITONE: the first byte within the bound is enough.
    ASSERT_EQ(dev_->control(iod::Control::SET_FLAGS, iod::RW | iod::WAITONE), 0);
    EXPECT_EQ(dev_->read(buf, 4), 0);
    std::thread writer([&] {
        usleep(5000);
        EXPECT_EQ(::write(master_, "z", 1), 1);
    });
    ASSERT_EQ(dev_->control(iod::Control::WAIT_TIMEOUT, 2000000), 0);
    EXPECT_EQ(dev_->read(buf, 4), 1);
    writer.join();
    EXPECT_EQ(buf[0], 'z');
}

TEST_F(IodSio, WriteReachesThePeer) {
    dev_ = iod::open(sdb_, "ser", 0, 0, iod::WRITE);
    EXPECT_EQ(dev_->write("hello", 5), 5);
    EXPECT_EQ(get(5), "hello");
    char c;
    EXPECT_EQ(dev_->read(&c, 1), -EBADF) << "opened WRITE only";
}

TEST_F(IodSio, SioGetSetRoundTrip) {
    dev_ = iod::open(sdb_, "ser", 0, 0, iod::RW);
    iod::SioParam p;
    ASSERT_EQ(dev_->status(iod::Status::SIO_GET, &p), 0);
    EXPECT_EQ(p.baud_rx, 115200);
    EXPECT_EQ(p.baud_tx, 115200);
    EXPECT_EQ(p.bits, 8);
    EXPECT_EQ(p.stop, 1);
    EXPECT_EQ(p.parity, iod::SIO_NONE);

    iod::SioParam split{19200, 9600, 8, 1, iod::SIO_NONE};
    EXPECT_EQ(dev_->status(iod::Status::SIO_SET, &split), -EINVAL) << "split rates are refused";
    iod::SioParam q{19200, 19200, 7, 2, iod::SIO_ODD};
    ASSERT_EQ(dev_->status(iod::Status::SIO_SET, &q), 0);
    iod::SioParam r;
    ASSERT_EQ(dev_->status(iod::Status::SIO_GET, &r), 0);
    EXPECT_EQ(r.baud_rx, 19200);
    EXPECT_EQ(r.baud_tx, 19200);
    EXPECT_EQ(r.stop, 2);
    // A pseudo-terminal forces CS8 and no parity (Linux pty_set_termios):
    // SIO_GET reports the line as the kernel holds it, not what was asked.
    EXPECT_EQ(r.bits, 8);
    EXPECT_EQ(r.parity, iod::SIO_NONE);

    iod::SioParam bad{12345, 12345, 8, 1, iod::SIO_NONE};
    EXPECT_EQ(dev_->status(iod::Status::SIO_SET, &bad), -EINVAL);
    bad = {9600, 9600, 9, 1, iod::SIO_NONE};
    EXPECT_EQ(dev_->status(iod::Status::SIO_SET, &bad), -EINVAL);
    EXPECT_EQ(dev_->status(iod::Status::PORTNUM), 1);
    EXPECT_EQ(dev_->status(iod::Status::PORTSIZE, 0L), 8);
    EXPECT_EQ(dev_->status(iod::Status::CAN_ERRORS), -ENOTSUP);
}

TEST_F(IodSio, DefaultWaitForStreamsIsWaitOne) {
    dev_ = iod::open(sdb_, "ser", 0, 0, iod::READ);
    EXPECT_EQ(dev_->flags() & iod::kWaitMask, iod::WAITONE);
    EXPECT_EQ(dev_->flags() & iod::kSizeMask, iod::BYTE);
}

// --- MEM ---------------------------------------------------------------------
class IodMem : public IodOpen {
protected:
    void SetUp() override {
        IodOpen::SetUp();
        seg_ = "/chimera.iodtest." + std::to_string(getpid());
        mdb_ = iod::Database::from_string("DEVICE board MEM shm\nPATH " + seg_ +
                                              "\nSIZE 64\nEND\nDEVICE view MEM shm\nPATH " + seg_ +
                                              "\nSIZE 64\nEND\nEOF\n",
                                          "mem.iod");
    }
    std::string seg_;
    iod::Database mdb_ = iod::Database::from_string("EOF\n", "empty");
};

TEST_F(IodMem, TwoDevicesShareTheBlock) {
    {
        auto a = iod::open(mdb_, "board", 0, 0, iod::WRITE);
        auto b = iod::open(mdb_, "view", 0, 0, iod::READ);
        EXPECT_TRUE(chimera::ipc::Segment::exists(seg_));
        EXPECT_EQ(a->status(iod::Status::MEM_SIZE), 64);
        ASSERT_EQ(a->control(iod::Control::MEM_SEEK, 10), 0);
        EXPECT_EQ(a->write("chimera", 7), 7);
        char buf[8] = {};
        ASSERT_EQ(b->control(iod::Control::MEM_SEEK, 10), 0);
        EXPECT_EQ(b->read(buf, 7), 7);
        EXPECT_EQ(std::string(buf, 7), "chimera");
        EXPECT_EQ(static_cast<char*>(b->mmap())[12], 'i');
        static_cast<char*>(a->mmap())[0] = 'Z';
        ASSERT_EQ(b->control(iod::Control::MEM_SEEK, 0), 0);
        EXPECT_EQ(b->read(buf, 1), 1);
        EXPECT_EQ(buf[0], 'Z');
        EXPECT_EQ(b->write("x", 1), -EBADF);
        EXPECT_EQ(a->control(iod::Control::MEM_SEEK, 65), -EINVAL);
        ASSERT_EQ(b->control(iod::Control::MEM_SEEK, 60), 0);
        EXPECT_EQ(b->read(buf, 8), 4) << "clipped at the end of the block";
        ASSERT_EQ(b->control(iod::Control::SET_FLAGS, iod::READ | iod::WAITNOALL), 0);
        EXPECT_EQ(b->read(buf, 8), 0) << "WAITNOALL: all or nothing";
        EXPECT_EQ(b->control(iod::Control::SET_FLAGS, iod::RW), -EINVAL) << "direction is fixed";
        EXPECT_EQ(b->control(iod::Control::WAIT_TIMEOUT, 1000), -ENOTSUP) << "PIO only";
        EXPECT_EQ(b->status(iod::Status::PIO_PORT_EVENTS, 0L), -ENOTSUP) << "PIO only";
    }
    EXPECT_FALSE(chimera::ipc::Segment::exists(seg_)) << "the last instance removes the block";
}

TEST_F(IodMem, DoubleOpenIsRefusedUntilClosed) {
    auto a = iod::open(mdb_, "board", 0, 0, iod::RW);
    EXPECT_EQ(what_of([&] { iod::open(mdb_, "board", 0, 0, iod::READ); }),
              "device board (mem.iod:1): ports 0..0 (or some of them) are already open in another "
              "instance");
    a.reset();
    EXPECT_NO_THROW(iod::open(mdb_, "board", 0, 0, iod::READ));
}

// Issue #29.5: a lock file another user made in the (shared) lock folder
// could be held by them for ever; root replaces it, and no open follows a
// symlink planted there.
TEST_F(IodMem, ALockFileAnotherUserMadeIsReplacedByRoot) {
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    ASSERT_EQ(::chmod(lockdir_.c_str(), 01777), 0) << "a shared folder, as /dev/shm is";
    const std::string lock = lockdir_ + "/chimera.iod.board.lock";
    const pid_t child = fork();
    if (child == 0) {
        if (!chimera::test::become_nobody({})) _exit(10);
        const int fd = ::open(lock.c_str(), O_RDWR | O_CREAT | O_EXCL, 0666);
        _exit(fd >= 0 && ::fchmod(fd, 0666) == 0 ? 0 : 11);
    }
    int status = 0;
    ASSERT_EQ(waitpid(child, &status, 0), child);
    ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << "nobody could not plant " << lock;
    auto a = iod::open(mdb_, "board", 0, 0, iod::RW);
    struct stat st {};
    ASSERT_EQ(::stat(lock.c_str(), &st), 0);
    EXPECT_EQ(st.st_uid, 0u) << "the squatter's file was replaced";
    EXPECT_EQ(st.st_mode & 0777, 0600u);
}

TEST_F(IodMem, ALockFileIsNeverOpenedThroughASymlink) {
    const std::string lock = lockdir_ + "/chimera.iod.board.lock";
    const std::string target = lockdir_ + "/target";
    std::ofstream(target) << "kept";
    ASSERT_EQ(::symlink(target.c_str(), lock.c_str()), 0);
    const std::string what = what_of([&] { iod::open(mdb_, "board", 0, 0, iod::RW); });
    EXPECT_EQ(what, "device board (mem.iod:1): cannot open lock file " + lock + ": Too many levels of symbolic links");
    std::ifstream in(target);
    std::string kept;
    in >> kept;
    EXPECT_EQ(kept, "kept");
}

TEST_F(IodMem, DoubleOpenIsRefusedAcrossProcesses) {
    auto a = iod::open(mdb_, "board", 0, 0, iod::RW);
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
        // Exit status 3: refused as expected; 0: the open wrongly succeeded.
        try {
            iod::open(mdb_, "board", 0, 0, iod::READ);
        } catch (const iod::Error& e) {
            _exit(std::string(e.what()).find("already open") != std::string::npos ? 3 : 4);
        }
        _exit(0);
    }
    int st = 0;
    ASSERT_EQ(waitpid(child, &st, 0), child);
    ASSERT_TRUE(WIFEXITED(st));
    EXPECT_EQ(WEXITSTATUS(st), 3);
}

}  // namespace
