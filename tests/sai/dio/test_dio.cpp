// Host tests of the digital in/out SAI modules (modules/dio, thesis §7.3).
// This machine has no gpiochip, so what runs here is everything up to the
// hardware: the value mapping, the LOCAL configuration checked against the
// device database, and the din/dout shared objects spawned in a real
// subsystem (loaded from the module path like a user's), whose init must
// refuse every bad configuration with a message naming the .rmod and leave
// the task NOT-CREATED with its ports free. The shipped .rmod files must pass
// every check but the missing chip. Every database here names chips that do
// not exist, so the tests never touch the lines of a machine that has some.
// The lines themselves are tested in the PREEMPT_RT guest (test_dio_guest.cpp).
#include "dio/digital.hpp"

#include <chimera/sbs.hpp>
#include <chimera/sbs_files.hpp>

#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <regex>
#include <sstream>
#include <string>

namespace fs = std::filesystem;
namespace dio = chimera::dio;
namespace svar = chimera::svar;
using chimera::TaskType;
using chimera::sbs::Subsystem;

namespace {

std::string what_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const std::exception& e) {
        return e.what();
    }
    return "(no error)";
}

bool has(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

// --- value mapping ---------------------------------------------------------------

TEST(DioMapping, ExactBitsIsTheWidestPortATypeHoldsExactly) {
    EXPECT_EQ(dio::exact_bits(svar::Type::byte_), 8);
    EXPECT_EQ(dio::exact_bits(svar::Type::word), 16);
    EXPECT_EQ(dio::exact_bits(svar::Type::unsigned_), 32);
    EXPECT_EQ(dio::exact_bits(svar::Type::short_), 15) << "the sign bit holds no port bit";
    EXPECT_EQ(dio::exact_bits(svar::Type::int_), 31);
    EXPECT_EQ(dio::exact_bits(svar::Type::float_), 24) << "2^24 + 1 is not a float";
    EXPECT_EQ(dio::exact_bits(svar::Type::double_), 32);
    EXPECT_EQ(dio::exact_bits(svar::Type::char_), 0) << "characters, not numbers";
    EXPECT_EQ(dio::exact_bits(svar::Type::struct_), 0);
    // The claim behind the float entry.
    EXPECT_EQ(static_cast<std::uint32_t>(static_cast<float>((1u << 24) - 1)), (1u << 24) - 1);
    EXPECT_NE(static_cast<std::uint32_t>(static_cast<float>((1u << 24) + 1)), (1u << 24) + 1);
}

// Every type carries every value of the widest port it accepts, both ways.
TEST(DioMapping, StoreThenLoadRoundTripsTheWidestPortOfEveryType) {
    for (svar::Type type : {svar::Type::byte_, svar::Type::word, svar::Type::unsigned_, svar::Type::short_,
                            svar::Type::int_, svar::Type::float_, svar::Type::double_}) {
        const int bits = dio::exact_bits(type);
        const std::uint32_t max = bits >= 32 ? 0xFFFFFFFFu : (1u << bits) - 1u;
        alignas(8) unsigned char buf[3 * 8] = {};
        const std::uint32_t values[3] = {0, 1, max};
        for (std::size_t k = 0; k < 3; ++k) dio::store(type, buf, k, values[k]);
        for (std::size_t k = 0; k < 3; ++k) {
            std::uint32_t back = 12345;
            ASSERT_TRUE(dio::load(type, buf, k, max, back)) << svar::type_name(type) << " element " << k;
            EXPECT_EQ(back, values[k]) << svar::type_name(type);
        }
    }
    // Each element lands in its own slot of the variable's element size.
    alignas(8) std::uint16_t words[3] = {};
    dio::store(svar::Type::word, words, 1, 0xBEEF);
    EXPECT_EQ(words[0], 0);
    EXPECT_EQ(words[1], 0xBEEF);
    EXPECT_EQ(words[2], 0);
}

TEST(DioMapping, LoadRefusesCommandsThatAreNoPortValue) {
    std::uint32_t v = 77;
    const double doubles[] = {-1.0, 0.5, 2.0, std::nan(""), std::numeric_limits<double>::infinity(), -0.25};
    for (std::size_t k = 0; k < std::size(doubles); ++k)
        EXPECT_FALSE(dio::load(svar::Type::double_, doubles, k, 1, v)) << doubles[k] << " on a 1-bit port";
    const float floats[] = {1.5f, 256.0f};
    EXPECT_FALSE(dio::load(svar::Type::float_, floats, 0, 255, v));
    EXPECT_FALSE(dio::load(svar::Type::float_, floats, 1, 255, v));
    const std::int32_t ints[] = {-1, 16};
    EXPECT_FALSE(dio::load(svar::Type::int_, ints, 0, 15, v)) << "negative";
    EXPECT_FALSE(dio::load(svar::Type::int_, ints, 1, 15, v)) << "wider than the 4-bit port";
    const std::int16_t shorts[] = {-32768};
    EXPECT_FALSE(dio::load(svar::Type::short_, shorts, 0, 0x7FFF, v));
    const std::uint8_t bytes[] = {2};
    EXPECT_FALSE(dio::load(svar::Type::byte_, bytes, 0, 1, v)) << "2 is not a level";
    const char chars[] = {1};
    EXPECT_FALSE(dio::load(svar::Type::char_, chars, 0, 1, v));
    EXPECT_EQ(v, 77u) << "a refused command leaves the value alone";
    // The boundaries are values.
    const double edges[] = {0.0, 255.0, -0.0};
    EXPECT_TRUE(dio::load(svar::Type::double_, edges, 0, 255, v));
    EXPECT_TRUE(dio::load(svar::Type::double_, edges, 1, 255, v));
    EXPECT_EQ(v, 255u);
    EXPECT_TRUE(dio::load(svar::Type::double_, edges, 2, 255, v));
    EXPECT_EQ(v, 0u);
}

// --- files -----------------------------------------------------------------------

// The database of these tests: chips that do not exist.
constexpr const char* kDatabase = R"(# dio host tests
DEVICE dio0 PIO gpio
  PATH  chimera-no-such-chip
  LINES 8
END
DEVICE din0 PIO gpio
  PATH      chimera-no-such-chip
  LINES     4
  DIRECTION IN
END
DEVICE dout0 PIO gpio
  PATH      chimera-no-such-chip
  LINES     4
  DIRECTION OUT
END
DEVICE wide PIO gpio
  PATH  chimera-no-such-chip
  LINES 24
  WIDTH 12
END
DEVICE can0 RCB socketcan
  PATH  chimnocan0
  FRAME 0x181 IN 2 8
END
EOF
)";

class DioFiles : public ::testing::Test {
protected:
    void SetUp() override {
        static std::atomic<int> counter{0};
        name_ = "diot" + std::to_string(::getpid()) + "x" + std::to_string(counter++);
        dir_ = fs::temp_directory_path() / name_;
        fs::create_directories(dir_ / "locks");
        // Port reservations of these tests stay among themselves.
        ::setenv("CHIMERA_IOD_LOCKDIR", (dir_ / "locks").c_str(), 1);
        write("lab.iod", kDatabase);
    }
    void TearDown() override {
        sbs_.reset();
        fs::remove_all(dir_);
    }
    void write(const std::string& file, const std::string& text) { std::ofstream(dir_ / file) << text; }

    // A din or dout .rmod; `ports` is the port lines (SVARALIAS, INVAR,
    // OUTVAR), `local` the LOCAL section.
    std::string rmod(const std::string& name, const std::string& module, const std::string& ports,
                     const std::string& local, const std::string& type = "periodic") {
        write(name + ".rmod", "MODULE " + module + "\nDESC test " + name + "\n" + ports + "TASKTYPE " + type + "\n" +
                                  (type == "periodic" || type == "synchronous" ? "FREQ 100\n" : "") + "LOCAL\n" +
                                  local + "EOF\n");
        return (dir_ / (name + ".rmod")).string();
    }
    std::string din(const std::string& name, const std::string& local, const std::string& type = "periodic",
                    const std::string& ports = "SVARALIAS DIN=DI\nOUTVAR DIN\n") {
        return rmod(name, "din", ports, local, type);
    }
    std::string dout(const std::string& name, const std::string& local, const std::string& type = "periodic",
                     const std::string& ports = "SVARALIAS DOUT=DO\nINVAR DOUT\n") {
        return rmod(name, "dout", ports, local, type);
    }
    dio::Config config(const std::string& path, dio::Direction dir) {
        const chimera::RmodFile r = chimera::read_rmod(path);
        return dio::read_config(r, dir, r.type);
    }
    std::string config_error(const std::string& path, dio::Direction dir) {
        return what_of([&] { config(path, dir); });
    }

    std::string name_;
    fs::path dir_;
    std::unique_ptr<Subsystem> sbs_;
};

const std::string kDin = "DATABASE lab.iod\nDEVICE dio0\nPORTS 0 7\n";
const std::string kDout = "DATABASE lab.iod\nDEVICE dio0\nPORTS 4 7\nSAFE 0\n";

// --- configuration -----------------------------------------------------------------

TEST_F(DioFiles, ConfigReadsTheLocalSection) {
    const dio::Config c = config(din("in", kDin + "INVERT 0 1 0 0x1 0 0 0 1\n"), dio::Direction::in);
    EXPECT_EQ(c.database, (dir_ / "lab.iod").string()) << "relative to the .rmod's folder";
    EXPECT_EQ(c.device.name, "dio0");
    EXPECT_EQ(c.first_port, 0);
    EXPECT_EQ(c.last_port, 7);
    EXPECT_EQ(c.nports(), 8);
    EXPECT_EQ(c.invert, (std::vector<std::uint32_t>{0, 1, 0, 1, 0, 0, 0, 1}));
    EXPECT_EQ(c.port_mask(), 1u);
    EXPECT_TRUE(c.safe.empty()) << "din has no SAFE";

    const dio::Config o = config(dout("out", "DATABASE " + (dir_ / "lab.iod").string() +
                                                 "\nDEVICE wide\nPORTS 1\nSAFE 0xabc\nINVERT 0x800\nILLEGAL safe\n"),
                                 dio::Direction::out);
    EXPECT_EQ(o.first_port, 1) << "one number: a single port";
    EXPECT_EQ(o.last_port, 1);
    EXPECT_EQ(o.safe, (std::vector<std::uint32_t>{0xABC}));
    EXPECT_EQ(o.invert, (std::vector<std::uint32_t>{0x800}));
    EXPECT_EQ(o.port_mask(), 0xFFFu);
    EXPECT_TRUE(o.safe_when_illegal);

    const dio::Config one = config(dout("all", kDout), dio::Direction::out);
    EXPECT_EQ(one.safe, (std::vector<std::uint32_t>{0, 0, 0, 0})) << "one value for every port";
    EXPECT_EQ(one.invert, (std::vector<std::uint32_t>{0, 0, 0, 0})) << "INVERT defaults to none";
    EXPECT_FALSE(one.safe_when_illegal) << "ILLEGAL defaults to hold";

    const dio::Config sync = config(din("sync", kDin + "SYNC_TIMEOUT 0.005\n", "synchronous"), dio::Direction::in);
    EXPECT_EQ(sync.sync_timeout_us, 5000);
    EXPECT_EQ(config(din("sync2", kDin, "synchronous"), dio::Direction::in).sync_timeout_us, 20000);
}

TEST_F(DioFiles, ConfigErrorsNameTheRmodLineAndKey) {
    const std::string p = din("typo", kDin + "INVRET 1\n");
    EXPECT_EQ(config_error(p, dio::Direction::in),
              p + ":11: LOCAL INVRET: not a key of din (DATABASE, DEVICE, PORTS, INVERT, SYNC_TIMEOUT)");
    const std::string q = dout("typo2", kDout + "SYNC_TIMEOUT 0.01\n");
    EXPECT_EQ(config_error(q, dio::Direction::out),
              q + ":12: LOCAL SYNC_TIMEOUT: not a key of dout (DATABASE, DEVICE, PORTS, INVERT, SAFE, ILLEGAL)");

    const std::string nodb = din("nodb", "DEVICE dio0\nPORTS 0\n");
    EXPECT_EQ(config_error(nodb, dio::Direction::in), nodb + ": LOCAL DATABASE is missing (the device database file)");
    const std::string nodev = din("nodev", "DATABASE lab.iod\nPORTS 0\n");
    EXPECT_EQ(config_error(nodev, dio::Direction::in),
              nodev + ": LOCAL DEVICE is missing (the device's name in the database)");
    const std::string noports = din("noports", "DATABASE lab.iod\nDEVICE dio0\n");
    EXPECT_EQ(config_error(noports, dio::Direction::in),
              noports + ": LOCAL PORTS is missing (the first and last port: PORTS first [last])");
    const std::string nosafe = dout("nosafe", "DATABASE lab.iod\nDEVICE dio0\nPORTS 0\n");
    EXPECT_EQ(config_error(nosafe, dio::Direction::out),
              nosafe + ": LOCAL SAFE is missing (the value of each port from init, after off and kill, and on an error)");
}

TEST_F(DioFiles, ConfigErrorsOfTheDatabaseAndDevice) {
    const std::string gone = din("gone", "DATABASE nowhere.iod\nDEVICE dio0\nPORTS 0\n");
    const std::string e1 = config_error(gone, dio::Direction::in);
    EXPECT_TRUE(has(e1, gone + ":8: LOCAL DATABASE: ")) << e1;
    EXPECT_TRUE(has(e1, (dir_ / "nowhere.iod").string())) << e1;
    EXPECT_TRUE(has(e1, "cannot open")) << e1;

    write("bad.iod", "DEVICE x PIO gpio\nPATH c\nLINES 2\nWIDHT 1\nEND\nEOF\n");
    const std::string bad = din("bad", "DATABASE bad.iod\nDEVICE x\nPORTS 0\n");
    EXPECT_EQ(config_error(bad, dio::Direction::in),
              bad + ":8: LOCAL DATABASE: " + (dir_ / "bad.iod").string() + ":4: unknown keyword WIDHT in device x");

    const std::string unknown = din("unknown", "DATABASE lab.iod\nDEVICE dio9\nPORTS 0\n");
    EXPECT_EQ(config_error(unknown, dio::Direction::in),
              unknown + ":9: LOCAL DEVICE: no device dio9 in " + (dir_ / "lab.iod").string() +
                  " (it has dio0, din0, dout0, wide, can0)");
    const std::string can = din("can", "DATABASE lab.iod\nDEVICE can0\nPORTS 0\n");
    EXPECT_EQ(config_error(can, dio::Direction::in),
              can + ":9: LOCAL DEVICE: device can0 (" + (dir_ / "lab.iod").string() +
                  ":21) is class RCB: din and dout use PIO (GPIO) devices");
    const std::string into = dout("into", "DATABASE lab.iod\nDEVICE din0\nPORTS 0\nSAFE 0\n");
    EXPECT_TRUE(has(config_error(into, dio::Direction::out),
                    into + ":9: LOCAL DEVICE: device din0 (" + (dir_ / "lab.iod").string() +
                        ":6) has DIRECTION IN: dout drives outputs"));
    const std::string from = din("from", "DATABASE lab.iod\nDEVICE dout0\nPORTS 0\n");
    EXPECT_TRUE(has(config_error(from, dio::Direction::in), "has DIRECTION OUT: din reads inputs"));
}

TEST_F(DioFiles, ConfigErrorsOfPortsAndPerPortValues) {
    const std::string lab = (dir_ / "lab.iod").string();
    const std::string far = din("far", "DATABASE lab.iod\nDEVICE dio0\nPORTS 4 8\n");
    EXPECT_EQ(config_error(far, dio::Direction::in),
              far + ":10: LOCAL PORTS: 4..8 is not a range of the ports 0..7 of device dio0 (" + lab + ":2)");
    const std::string back = din("back", "DATABASE lab.iod\nDEVICE dio0\nPORTS 5 4\n");
    EXPECT_TRUE(has(config_error(back, dio::Direction::in), "5..4 is not a range"));
    const std::string word = din("word", "DATABASE lab.iod\nDEVICE dio0\nPORTS all\n");
    EXPECT_EQ(config_error(word, dio::Direction::in), word + ":10: LOCAL PORTS: expected a port number, found 'all'");
    const std::string three = din("three", "DATABASE lab.iod\nDEVICE dio0\nPORTS 0 1 2\n");
    EXPECT_EQ(config_error(three, dio::Direction::in), three + ":10: LOCAL PORTS: expected first [last], found 3 values");

    const std::string count = din("count", kDin + "INVERT 1 0 1\n");
    EXPECT_EQ(config_error(count, dio::Direction::in),
              count + ":11: LOCAL INVERT: has 3 values, expected 1 (for every port) or 8 (one per port of PORTS 0..7)");
    const std::string wide = din("widebit", kDin + "INVERT 2\n");
    EXPECT_EQ(config_error(wide, dio::Direction::in),
              wide + ":11: LOCAL INVERT: 2 does not fit the 1-bit ports of device dio0 (" + lab + ":2) (0..0x1)");
    const std::string neg = dout("neg", "DATABASE lab.iod\nDEVICE wide\nPORTS 0 1\nSAFE -1\n");
    EXPECT_EQ(config_error(neg, dio::Direction::out),
              neg + ":11: LOCAL SAFE: -1 does not fit the 12-bit ports of device wide (" + lab + ":16) (0..0xfff)");
    const std::string real = dout("real", kDout + "INVERT 0.5\n");
    EXPECT_EQ(config_error(real, dio::Direction::out),
              real + ":12: LOCAL INVERT: expected an integer (decimal or 0x hex), found '0.5'");
    const std::string maybe = dout("maybe", kDout + "ILLEGAL maybe\n");
    EXPECT_EQ(config_error(maybe, dio::Direction::out), maybe + ":12: LOCAL ILLEGAL: expected hold or safe, found 'maybe'");
}

TEST_F(DioFiles, ConfigErrorsOfTheTaskType) {
    const std::string periodic = din("periodic", kDin + "SYNC_TIMEOUT 0.01\n");
    EXPECT_EQ(config_error(periodic, dio::Direction::in),
              periodic + ":11: LOCAL SYNC_TIMEOUT: applies to synchronous tasks only (this one is periodic)");
    const std::string slow = din("slow", kDin + "SYNC_TIMEOUT 2\n", "synchronous");
    EXPECT_EQ(config_error(slow, dio::Direction::in), slow + ":11: LOCAL SYNC_TIMEOUT: expected seconds in (0, 1], found '2'");
    const std::string zero = din("zero", kDin + "SYNC_TIMEOUT 0\n", "synchronous");
    EXPECT_TRUE(has(config_error(zero, dio::Direction::in), "expected seconds in (0, 1], found '0'"));
    // A synchronous dout would spin: sync() has nothing to wait for.
    const std::string sync = dout("sync", kDout, "synchronous");
    EXPECT_EQ(config_error(sync, dio::Direction::out),
              sync + ": TASKTYPE synchronous: dout has no event to wait for; make it periodic (or sporadic, to "
                     "write on each event)");
    EXPECT_NO_THROW(config(dout("sporadic", kDout, "sporadic"), dio::Direction::out));
}

TEST_F(DioFiles, UpdateConfigChangesOnlyWhatMayChangeWithThePortsOpen) {
    chimera::RmodFile r = chimera::read_rmod(dout("upd", kDout + "INVERT 0 0 1 1\n"));
    dio::Config c = dio::read_config(r, dio::Direction::out, r.type);
    // sbsSet updates the LOCAL entry (line 0), then set() asks for the change.
    r.local.set("SAFE", {"1", "0", "1", "0"});
    dio::update_config(c, r, dio::Direction::out, r.type, "SAFE");
    EXPECT_EQ(c.safe, (std::vector<std::uint32_t>{1, 0, 1, 0}));
    EXPECT_EQ(c.invert, (std::vector<std::uint32_t>{0, 0, 1, 1}));

    const dio::Config before = c;
    r.local.set("PORTS", {"0", "3"});
    EXPECT_EQ(what_of([&] { dio::update_config(c, r, dio::Direction::out, r.type, "PORTS"); }),
              r.path + ": LOCAL PORTS cannot change while the ports are open: kill the task and spawn it again");
    r.local.set("INVERT", {"3"});
    EXPECT_EQ(what_of([&] { dio::update_config(c, r, dio::Direction::out, r.type, "INVERT"); }),
              r.path + ": LOCAL INVERT (as set): 3 does not fit the 1-bit ports of device dio0 (" +
                  (dir_ / "lab.iod").string() + ":2) (0..0x1)");
    EXPECT_EQ(c.invert, before.invert) << "a refused value changes nothing";
    EXPECT_EQ(c.safe, before.safe);
    EXPECT_EQ(c.first_port, 4);
    EXPECT_EQ(what_of([&] { dio::update_config(c, r, dio::Direction::out, r.type, "GAIN"); }),
              r.path + ": LOCAL GAIN is not a key of dout (DATABASE, DEVICE, PORTS, INVERT, SAFE, ILLEGAL)");
}

// --- the modules in a subsystem -------------------------------------------------------

// Variables of every kind the port checks look at.
constexpr const char* kSvar =
    "NAME DI\nTYPE byte\nDESC 8 inputs\nUNITS none\nNELEM 8\n"
    "NAME DI4\nTYPE byte\nDESC 4 inputs\nUNITS none\nNELEM 4\n"
    "NAME DC\nTYPE char\nDESC text\nUNITS none\nNELEM 8\n"
    "NAME DE\nTYPE unsigned\nDESC edges\nUNITS none\nNELEM 8\n"
    "NAME DEB\nTYPE byte\nDESC edges, wrong type\nUNITS none\nNELEM 8\n"
    "NAME DW\nTYPE word\nDESC 2 wide inputs\nUNITS none\nNELEM 2\n"
    "NAME DS\nTYPE short\nDESC 2 wide values\nUNITS none\nNELEM 2\n"
    "NAME DO\nTYPE double\nDESC 4 outputs\nUNITS none\nNELEM 4\n"
    "EOF\n";

class DioSpawn : public DioFiles {
protected:
    Subsystem& init() {
        write("t.svar", kSvar);
        write("t.sbs", "SUBSYSTEM " + name_ + "\nSVARFILE t.svar\nRTPU cpu0\nERRPRINT none\nBACKEND other\nEOF\n");
        sbs_ = Subsystem::init((dir_ / "t.sbs").string());
        return *sbs_;
    }
    // Spawns and expects it to fail (in init, or before: the LOCAL keys are
    // checked against the declarations first): the message, with the task
    // checked to be NOT-CREATED and gone from the status.
    std::string spawn_error(const std::string& path, const char* stage = "init failed") {
        const std::string msg = what_of([&] { sbs_->spawn(path); });
        EXPECT_TRUE(has(msg, stage)) << msg;
        const std::string stem = fs::path(path).stem().string();
        if (auto id = sbs_->find(stem)) {
            EXPECT_EQ(sbs_->status(*id).state, chimera::State::NOT_CREATED) << msg;
        }
        EXPECT_TRUE(sbs_->status_all().empty()) << msg;
        return msg;
    }
};

TEST_F(DioSpawn, WrongValuePortIsRefusedAtInit) {
    init();
    const std::string ch = din("ch", kDin, "periodic", "SVARALIAS DIN=DC\nOUTVAR DIN\n");
    EXPECT_TRUE(has(spawn_error(ch), ch + ": port DIN (SVAR DC) is char, which does not hold port values as numbers; "
                                          "use byte, word, unsigned, short, int, float or double"));
    const std::string few = din("few", kDin, "periodic", "SVARALIAS DIN=DI4\nOUTVAR DIN\n");
    EXPECT_TRUE(has(spawn_error(few), few + ": port DIN (SVAR DI4) has 4 elements, but PORTS 0..7 opens 8: one "
                                            "element per port"));
    const std::string narrow = din("narrow", "DATABASE lab.iod\nDEVICE wide\nPORTS 0 1\n", "periodic",
                                   "SVARALIAS DIN=DI\nOUTVAR DIN\n");
    EXPECT_TRUE(has(spawn_error(narrow), narrow + ": port DIN (SVAR DI) is byte, which holds values of up to 8 bits "
                                                  "exactly: too narrow for the 12-bit ports of device wide (" +
                                                  (dir_ / "lab.iod").string() +
                                                  ":16); use word, short, unsigned, int, float, double"));
    const std::string unlisted = din("unlisted", kDin, "periodic", "SVARALIAS Z=DI\nOUTVAR Z\n");
    EXPECT_TRUE(has(spawn_error(unlisted),
                    unlisted + ": DIN must be listed as OUTVAR (SVARALIAS DIN=NAME puts it on the variable NAME)"));
    const std::string asin = dout("asin", kDout, "periodic", "SVARALIAS DOUT=DO\nOUTVAR DOUT\n");
    EXPECT_TRUE(has(spawn_error(asin), asin + ": DOUT must be listed as INVAR"));
    const std::string edges = din("edges", kDin, "periodic", "SVARALIAS DIN=DI\nSVARALIAS EDGES=DEB\nOUTVAR DIN EDGES\n");
    EXPECT_TRUE(has(spawn_error(edges), edges + ": port EDGES (SVAR DEB) is byte: edge counts are unsigned"));
    const std::string fewdo = dout("fewdo", "DATABASE lab.iod\nDEVICE dio0\nPORTS 0 7\nSAFE 0\n");
    EXPECT_TRUE(has(spawn_error(fewdo), fewdo + ": port DOUT (SVAR DO) has 4 elements, but PORTS 0..7 opens 8"));
}

TEST_F(DioSpawn, ConfigErrorsReachTheMasterWithTheRmod) {
    init();
    const std::string typo = dout("typo", kDout + "SAVE 1\n");
    EXPECT_TRUE(has(spawn_error(typo, "spawn: "), typo + ":12: LOCAL SAVE: not a key of dout (DATABASE, DEVICE, PORTS, "
                                                       "INVERT, SAFE, ILLEGAL)"))
        << "a misspelt key is not ignored";
}

// With the configuration right, init gets as far as the chip; nothing is left
// behind: the ports it had reserved are free for the next try.
TEST_F(DioSpawn, AbsentChipIsNamedAndThePortsAreFreedAgain) {
    init();
    const std::string in = din("in", kDin, "periodic", "SVARALIAS DIN=DI\nSVARALIAS EDGES=DE\nOUTVAR DIN EDGES\n");
    for (int attempt = 0; attempt < 2; ++attempt) {
        const std::string msg = spawn_error(in);
        EXPECT_TRUE(has(msg, in + ": device dio0 (" + (dir_ / "lab.iod").string() + ":2): no gpiochip chimera-no-such-chip"))
            << "attempt " << attempt << ": " << msg;
        EXPECT_FALSE(has(msg, "already open")) << msg;
    }
    const std::string out = dout("out", kDout);
    EXPECT_TRUE(has(spawn_error(out), out + ": device dio0 (" + (dir_ / "lab.iod").string() + ":2): no gpiochip"));
    const std::string w = din("w", "DATABASE lab.iod\nDEVICE wide\nPORTS 0 1\n", "synchronous",
                              "SVARALIAS DIN=DS\nOUTVAR DIN\n");
    EXPECT_TRUE(has(spawn_error(w), "no gpiochip chimera-no-such-chip")) << "12-bit ports in shorts";
}

// The .rmod files, database and .svar that ship in modules/dio agree with each
// other and with the modules: spawned as they are (only the chips renamed to
// ones that do not exist), each fails at the chip and nowhere before it.
TEST_F(DioSpawn, ShippedRmodsPassEveryCheckButTheChip) {
    const char* root = std::getenv("CHIMERA_SOURCE_ROOT");
    ASSERT_NE(root, nullptr) << "meson sets CHIMERA_SOURCE_ROOT";
    const fs::path shipped = fs::path(root) / "modules" / "dio";
    std::ifstream db_in(shipped / "lab.iod");
    ASSERT_TRUE(db_in.good());
    std::stringstream db;
    db << db_in.rdbuf();
    const std::string renamed =
        std::regex_replace(db.str(), std::regex(R"((\n\s*PATH\s+)(\S+))"), "$1chimera-absent-$2");
    ASSERT_NE(renamed, db.str());
    write("lab.iod", renamed);
    fs::copy_file(shipped / "dio.svar", dir_ / "t.svar", fs::copy_options::overwrite_existing);
    write("t.sbs", "SUBSYSTEM " + name_ + "\nSVARFILE t.svar\nRTPU cpu0\nERRPRINT none\nBACKEND other\nEOF\n");
    sbs_ = Subsystem::init((dir_ / "t.sbs").string());
    int checked = 0;
    for (const auto& entry : fs::directory_iterator(shipped)) {
        if (entry.path().extension() != ".rmod") continue;
        const fs::path copy = dir_ / entry.path().filename();
        fs::copy_file(entry.path(), copy, fs::copy_options::overwrite_existing);
        const std::string msg = spawn_error(copy.string());
        EXPECT_TRUE(has(msg, copy.string() + ": device ") && has(msg, "no gpiochip chimera-absent-gpiochip"))
            << entry.path().filename() << ": " << msg;
        ++checked;
    }
    EXPECT_GE(checked, 3) << "din8, dout8, limits";
}

}  // namespace
