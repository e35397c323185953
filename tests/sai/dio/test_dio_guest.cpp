// The digital in/out SAI modules (modules/dio, thesis §7.3) in a real
// subsystem inside the PREEMPT_RT guest (tests/rtguest), on gpio-sim lines:
// SVAR values follow the simulated pulls (din, periodic and synchronous);
// gpio-sim sees what dout writes; dout shows SAFE from init, on off, on kill
// (before the lines are released), on a bad command and, with ILLEGAL safe,
// while the configuration is illegal; ports already open are refused at spawn
// with the other task running on; the cycles allocate nothing.
//
// guest-init.sh makes one gpio-sim chip with two banks (bank0: 8 lines,
// bank1: 4) and names them in CHIMERA_GPIOSIM_*. Outside the guest the tests
// skip. The modules are linked into this program (the guest has no module
// folders); the runtime finds them in the program. No timing is asserted (a
// TCG guest is slow and irregular): every "eventually" waits up to 10 s.
#include "guest_env.hpp"
#include "alloc_counter.hpp"
#include <chimera/iod.hpp>
#include <chimera/ipc/segment.hpp>
#include <chimera/module.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include <gtest/gtest.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <mutex>
#include <new>
#include <string>
#include <thread>
#include <vector>

namespace fs = std::filesystem;
namespace iod = chimera::iod;
using namespace std::chrono_literals;
using chimera::State;
using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;

// --- pinprobe: a test module ----------------------------------------------------------
// Placed before a dout in a combined task, its kill() runs after the dout's
// off() and before the dout's kill() releases the lines, and records what
// gpio-sim shows on LOCAL LINES of the bank at LOCAL SYSFS then. Its set() of
// ILLEGAL 1/0 raises/lowers the illegal-configuration flag (§3.10) as a task
// that halts on an error or a reconfiguration would.
namespace {
std::mutex g_probe_mu;
std::vector<int> g_probe_seen;

using chimera::test::gpiosim_value;

constexpr chimera::LocalKey kPinProbeLocalKeys[] = {
    {"ILLEGAL", chimera::LocalType::integer, 0, 1, true, "1 sets the illegal-configuration flag", "0"},
    {"SYSFS", chimera::LocalType::word, 0, 0, false, "gpio-sim bank folder read at kill()", ""},
    {"LINES", chimera::LocalType::numbers, 0, 63, false, "lines of that bank read at kill()", ""},
};

class PinProbe : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kPinProbeLocalKeys; }

    chimera::Result kill(chimera::Task& t) override {
        if (!t.local().has("LINES")) return chimera::Result::OK;  // a probe for set() only
        std::vector<int> seen;
        const std::string dir = t.local().text("SYSFS").value_or("");
        for (double line : t.local().numbers("LINES")) seen.push_back(gpiosim_value(dir, static_cast<int>(line)));
        std::lock_guard<std::mutex> lock(g_probe_mu);
        g_probe_seen = seen;
        return chimera::Result::OK;
    }
    chimera::Result set(chimera::Task& t) override {
        if (t.arg().substr(0, 8) == "ILLEGAL ") t.set_illegal_configuration(t.arg().substr(8) == "1");
        return chimera::Result::OK;
    }
};
}  // namespace

CHIMERA_MODULE(pinprobe, PinProbe)

namespace {

using chimera::test::env;

std::string what_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const std::exception& e) {
        return e.what();
    }
    return "(no error)";
}

bool has(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

template <typename P>
bool eventually(P pred, std::chrono::milliseconds t = 10000ms) {
    const auto end = std::chrono::steady_clock::now() + t;
    while (std::chrono::steady_clock::now() < end) {
        if (pred()) return true;
        std::this_thread::sleep_for(5ms);
    }
    return pred();
}

#define REQUIRE_ENV(var) CHIMERA_REQUIRE_GUEST_ENV(var)

constexpr const char* kSvar =
    "NAME DI\nTYPE byte\nDESC inputs\nUNITS none\nNELEM 4\n"
    "NAME DI_EDGES\nTYPE unsigned\nDESC edges per input\nUNITS none\nNELEM 4\n"
    "NAME DI2\nTYPE byte\nDESC inputs of a second din\nUNITS none\nNELEM 4\n"
    "NAME DO\nTYPE byte\nDESC outputs\nUNITS none\nNELEM 4\n"
    "NAME DOD\nTYPE double\nDESC outputs as numbers\nUNITS none\nNELEM 4\n"
    "NAME DOA\nTYPE byte\nDESC outputs, ILLEGAL safe\nUNITS none\nNELEM 2\n"
    "NAME DOB\nTYPE byte\nDESC outputs, ILLEGAL hold\nUNITS none\nNELEM 2\n"
    "NAME DW\nTYPE word\nDESC 2-bit inputs\nUNITS none\nNELEM 2\n"
    "EOF\n";

class DioGuest : public ::testing::Test {
protected:
    void SetUp() override {
        REQUIRE_ENV("CHIMERA_GPIOSIM_CHIP0");
        REQUIRE_ENV("CHIMERA_GPIOSIM_CHIP1");
        REQUIRE_ENV("CHIMERA_GPIOSIM_DEV");
        chip0_ = env("CHIMERA_GPIOSIM_CHIP0");
        chip1_ = env("CHIMERA_GPIOSIM_CHIP1");
        sysfs_ = "/sys/devices/platform/" + env("CHIMERA_GPIOSIM_DEV");
        for (int i = 0; i < 8; ++i) pull(chip0_, i, false);
        for (int i = 0; i < 4; ++i) pull(chip1_, i, false);

        static std::atomic<int> counter{0};
        name_ = "diog" + std::to_string(::getpid()) + "x" + std::to_string(counter++);
        dir_ = fs::temp_directory_path() / name_;
        fs::create_directories(dir_ / "locks");
        ::setenv("CHIMERA_IOD_LOCKDIR", (dir_ / "locks").c_str(), 1);
        // sim: bank0's 8 lines, one port each (inputs and outputs);
        // pairs: bank1's 4 lines as two 2-bit input ports.
        write("sim.iod", "DEVICE sim PIO gpio\nPATH " + chip0_ + "\nLINES 8\nEND\n"
                         "DEVICE pairs PIO gpio\nPATH " + chip1_ + "\nLINES 4\nWIDTH 2\nDIRECTION IN\nEND\nEOF\n");
        db_ = iod::Database::load((dir_ / "sim.iod").string());
        write("t.svar", kSvar);
        write("t.sbs", "SUBSYSTEM " + name_ + "\nSVARFILE t.svar\nRTPU cpu0\nERRPRINT errors\nEOF\n");
        sbs_ = Subsystem::init((dir_ / "t.sbs").string());
        global_ = std::make_unique<chimera::svar::Table>(
            chimera::svar::Table::attach(chimera::ipc::segment_name(name_, "svar")));
    }
    void TearDown() override {
        chimera::test::alloc_count_stop();
        global_.reset();
        if (sbs_) sbs_->finish();
        sbs_.reset();
        std::error_code ec;
        fs::remove_all(dir_, ec);
    }

    void write(const std::string& file, const std::string& text) { std::ofstream(dir_ / file) << text; }
    std::string rmod(const std::string& name, const std::string& module, const std::string& ports,
                     const std::string& local, const std::string& type = "periodic") {
        write(name + ".rmod", "MODULE " + module + "\nDESC guest " + name + "\n" + ports + "TASKTYPE " + type + "\n" +
                                  (type == "periodic" || type == "synchronous" ? "FREQ 50\n" : "") + "LOCAL\n" +
                                  local + "EOF\n");
        return (dir_ / (name + ".rmod")).string();
    }

    // gpio-sim: drive a simulated input; what an output line shows.
    void pull(const std::string& chip, int line, bool up) { chimera::test::gpiosim_pull(sysfs_ + "/" + chip, line, up); }
    std::vector<int> lines(int first, int last) {
        std::vector<int> v;
        for (int i = first; i <= last; ++i) v.push_back(gpiosim_value(sysfs_ + "/" + chip0_, i));
        return v;
    }

    template <typename T>
    std::vector<T> get(const std::string& var) {
        const std::size_t ix = global_->index_of(var);
        std::vector<T> v(global_->var(ix).nelem());
        EXPECT_EQ(global_->read(ix, v.data()), chimera::svar::Status::ok);
        return v;
    }
    template <typename T>
    void put(const std::string& var, std::vector<T> v) {
        const std::size_t ix = global_->index_of(var);
        EXPECT_EQ(v.size(), global_->var(ix).nelem());
        EXPECT_EQ(global_->write(ix, v.data()), chimera::svar::Status::ok);
    }
    State state(TaskId id) { return sbs_->status(id).state; }
    std::uint64_t cycles(TaskId id) { return sbs_->status(id).cycles; }
    // Waits for `n` more cycles of the task (each one a full in-vars, cycle, out-vars).
    void more_cycles(TaskId id, std::uint64_t n) {
        const std::uint64_t from = cycles(id);
        ASSERT_TRUE(eventually([&] { return cycles(id) >= from + n; })) << "the task stopped cycling";
    }

    std::string chip0_, chip1_, sysfs_, name_;
    fs::path dir_;
    iod::Database db_;
    std::unique_ptr<Subsystem> sbs_;
    std::unique_ptr<chimera::svar::Table> global_;
};

std::string din_local(const std::string& device, const std::string& ports, const std::string& more = "") {
    return "DATABASE sim.iod\nDEVICE " + device + "\nPORTS " + ports + "\n" + more;
}

using Bytes = std::vector<std::uint8_t>;
using Levels = std::vector<int>;

TEST_F(DioGuest, InputsFollowThePullsFromOnWithInversionAndEdgeCounts) {
    pull(chip0_, 0, true);  // before on: in DI from on, but not an edge counted by EDGES
    const TaskId in = sbs_->spawn(rmod("din4", "din", "SVARALIAS DIN=DI\nSVARALIAS EDGES=DI_EDGES\nOUTVAR DIN EDGES\n",
                                       din_local("sim", "0 3", "INVERT 0 0 0 1\n")));
    sbs_->control(in, Control::on);
    EXPECT_EQ(get<std::uint8_t>("DI"), (Bytes{1, 0, 0, 1})) << "read by on(), before any cycle; port 3 active-low";
    EXPECT_EQ(get<std::uint32_t>("DI_EDGES"), (std::vector<std::uint32_t>{0, 0, 0, 0}));

    pull(chip0_, 1, true);
    EXPECT_TRUE(eventually([&] { return get<std::uint8_t>("DI") == Bytes{1, 1, 0, 1}; }));
    pull(chip0_, 3, true);
    EXPECT_TRUE(eventually([&] { return get<std::uint8_t>("DI") == Bytes{1, 1, 0, 0}; })) << "active-low: high is 0";
    pull(chip0_, 1, false);
    EXPECT_TRUE(eventually([&] { return get<std::uint8_t>("DI") == Bytes{1, 0, 0, 0}; }));
    EXPECT_TRUE(eventually([&] { return get<std::uint32_t>("DI_EDGES") == std::vector<std::uint32_t>{0, 2, 0, 1}; }))
        << "edges since on, per port";

    sbs_->control(in, Control::kill);
    EXPECT_NO_THROW(iod::open(db_, "sim", 0, 3, iod::READ)) << "kill frees the ports";
}

TEST_F(DioGuest, OutputsFollowTheSvarAndShowSafeWheneverTheTaskIsNotCycling) {
    // SAFE 1 0 0 1 with ports 2 and 3 active-low: the lines show 1 0 1 0. The
    // pulls are set to the opposite so that a released line (gpio-sim shows
    // its pull) cannot pass for SAFE.
    const Levels safe{1, 0, 1, 0};
    for (int i = 0; i < 4; ++i) pull(chip0_, 4 + i, safe[static_cast<std::size_t>(i)] == 0);
    put<std::uint8_t>("DO", {1, 1, 0, 0});
    const TaskId out = sbs_->spawn(rmod("dout4", "dout", "SVARALIAS DOUT=DO\nINVAR DOUT\n",
                                        din_local("sim", "4 7", "SAFE 1 0 0 1\nINVERT 0 0 1 1\n")));
    EXPECT_EQ(lines(4, 7), safe) << "requested at SAFE by init";

    sbs_->control(out, Control::on);
    EXPECT_TRUE(eventually([&] { return lines(4, 7) == Levels{1, 1, 1, 1}; })) << "DO 1 1 0 0, ports 2 3 inverted";
    put<std::uint8_t>("DO", {0, 0, 1, 1});
    EXPECT_TRUE(eventually([&] { return lines(4, 7) == Levels{0, 0, 0, 0}; }));

    sbs_->control(out, Control::off);
    EXPECT_EQ(lines(4, 7), safe) << "SAFE as soon as off is done";
    sbs_->control(out, Control::on);
    EXPECT_TRUE(eventually([&] { return lines(4, 7) == Levels{0, 0, 0, 0}; })) << "the commands again";
    sbs_->control(out, Control::off);
    EXPECT_EQ(lines(4, 7), safe);

    // A new SAFE set while not cycling shows at once; PORTS cannot change.
    sbs_->set(out, "SAFE", "1 1 1 1");
    EXPECT_EQ(lines(4, 7), (Levels{1, 1, 0, 0}));
    const std::string ports = what_of([&] { sbs_->set(out, "PORTS", "0 3"); });
    EXPECT_TRUE(has(ports, "LOCAL PORTS of module dout is read only at spawn")) << ports;
    EXPECT_EQ(lines(4, 7), (Levels{1, 1, 0, 0}));

    sbs_->control(out, Control::kill);
    EXPECT_NO_THROW(iod::open(db_, "sim", 4, 7, iod::WRITE)) << "kill frees the ports";
}

TEST_F(DioGuest, KillDrivesSafeBeforeTheLinesAreReleased) {
    // gpio-sim shows a released line at its pull, so SAFE at kill can only be
    // seen before the release: by pinprobe, killed just before the dout.
    const Levels safe{0, 1, 1, 0};
    for (int i = 0; i < 4; ++i) pull(chip0_, 4 + i, safe[static_cast<std::size_t>(i)] == 0);
    put<std::uint8_t>("DO", {1, 0, 0, 1});
    const std::string probe = rmod("probe", "pinprobe", "", "SYSFS " + sysfs_ + "/" + chip0_ + "\nLINES 4 5 6 7\n");
    const std::string dout = rmod("dout4", "dout", "SVARALIAS DOUT=DO\nINVAR DOUT\n", din_local("sim", "4 7", "SAFE 0 1 1 0\n"));
    const TaskId both = sbs_->spawn_combined({probe, dout});
    sbs_->control(both, Control::on);
    ASSERT_TRUE(eventually([&] { return lines(4, 7) == Levels{1, 0, 0, 1}; }));

    sbs_->control(both, Control::kill);  // from ON: off, then kill, each object in order
    {
        std::lock_guard<std::mutex> lock(g_probe_mu);
        EXPECT_EQ(g_probe_seen, safe) << "what the lines showed when the dout was killed";
    }
    EXPECT_EQ(lines(4, 7), (Levels{1, 0, 0, 1})) << "released: gpio-sim shows the pulls";
}

TEST_F(DioGuest, BadCommandDrivesSafeAndHaltsNamingThePortAndValue) {
    put<double>("DOD", {1, 1, 1, 1});
    const TaskId out = sbs_->spawn(rmod("doutd", "dout", "SVARALIAS DOUT=DOD\nINVAR DOUT\n", din_local("sim", "4 7", "SAFE 0\n")));
    sbs_->control(out, Control::on);
    ASSERT_TRUE(eventually([&] { return lines(4, 7) == Levels{1, 1, 1, 1}; }));

    put<double>("DOD", {1, 1, 0.5, 1});
    ASSERT_TRUE(eventually([&] { return state(out) == State::ERROR; }));
    EXPECT_EQ(lines(4, 7), (Levels{0, 0, 0, 0})) << "every port SAFE, not only the bad one";
    const std::string error = sbs_->status(out).error;
    EXPECT_EQ(error, "DOUT[2] is 0.5, not a value of the 1-bit port 6 (0..1): all ports driven SAFE");
    put<double>("DOD", {1, 0, 1, 0});
    std::this_thread::sleep_for(200ms);
    EXPECT_EQ(lines(4, 7), (Levels{0, 0, 0, 0})) << "in ERROR nothing is written";

    sbs_->control(out, Control::clear);
    EXPECT_EQ(state(out), State::OFF);
    sbs_->control(out, Control::on);
    EXPECT_TRUE(eventually([&] { return lines(4, 7) == Levels{1, 0, 1, 0}; }));
}

TEST_F(DioGuest, IllegalSafeDropsToSafeWhileTheConfigurationIsIllegalAndHoldDoesNot) {
    put<std::uint8_t>("DOA", {1, 1});
    put<std::uint8_t>("DOB", {1, 1});
    const TaskId a = sbs_->spawn(rmod("douta", "dout", "SVARALIAS DOUT=DOA\nINVAR DOUT\n",
                                      din_local("sim", "4 5", "SAFE 0\nILLEGAL safe\n")));
    const TaskId b = sbs_->spawn(rmod("doutb", "dout", "SVARALIAS DOUT=DOB\nINVAR DOUT\n",
                                      din_local("sim", "6 7", "SAFE 0\nILLEGAL hold\n")));
    const TaskId probe = sbs_->spawn(rmod("probe", "pinprobe", "", "", "sporadic"));
    sbs_->control(a, Control::on);
    sbs_->control(b, Control::on);
    ASSERT_TRUE(eventually([&] { return lines(4, 7) == Levels{1, 1, 1, 1}; }));

    sbs_->set(probe, "ILLEGAL", "1");
    ASSERT_TRUE(sbs_->illegal_configuration());
    EXPECT_TRUE(eventually([&] { return lines(4, 5) == Levels{0, 0}; })) << "ILLEGAL safe";
    more_cycles(b, 3);
    EXPECT_EQ(lines(6, 7), (Levels{1, 1})) << "ILLEGAL hold keeps the commands";

    sbs_->set(probe, "ILLEGAL", "0");
    EXPECT_TRUE(eventually([&] { return lines(4, 5) == Levels{1, 1}; })) << "legal again: the commands";
}

TEST_F(DioGuest, PortsAlreadyOpenAreRefusedAndTheFirstTaskRunsOn) {
    const TaskId first = sbs_->spawn(rmod("first", "din", "SVARALIAS DIN=DI\nOUTVAR DIN\n", din_local("sim", "0 3")));
    sbs_->control(first, Control::on);

    const std::string second = rmod("second", "din", "SVARALIAS DIN=DI2\nOUTVAR DIN\n", din_local("sim", "2 5"));
    const std::string e1 = what_of([&] { sbs_->spawn(second); });
    EXPECT_TRUE(has(e1, second + ": device sim (")) << e1;
    EXPECT_TRUE(has(e1, "ports 2..5 (or some of them) are already open in another instance")) << e1;
    const std::string third = rmod("third", "dout", "SVARALIAS DOUT=DO\nINVAR DOUT\n", din_local("sim", "3 6", "SAFE 0\n"));
    const std::string e2 = what_of([&] { sbs_->spawn(third); });
    EXPECT_TRUE(has(e2, third + ": device sim (") && has(e2, "already open")) << e2;
    for (const char* refused : {"second", "third"})
        if (auto id = sbs_->find(refused)) {
            EXPECT_EQ(state(*id), State::NOT_CREATED) << refused;
        }

    EXPECT_EQ(state(first), State::ON);
    pull(chip0_, 2, true);
    EXPECT_TRUE(eventually([&] { return get<std::uint8_t>("DI") == Bytes{0, 0, 1, 0}; })) << "the first din runs on";

    sbs_->control(first, Control::kill);
    const TaskId again = sbs_->spawn(second);
    EXPECT_EQ(state(again), State::OFF) << "free once the first is killed";
}

TEST_F(DioGuest, SynchronousDinCyclesOnEdgesOnlyAndStillAnswersCommands) {
    const TaskId in = sbs_->spawn(rmod("sync", "din", "SVARALIAS DIN=DW\nOUTVAR DIN\n",
                                       din_local("pairs", "0 1", "SYNC_TIMEOUT 0.01\n"), "synchronous"));
    sbs_->control(in, Control::on);
    EXPECT_EQ(get<std::uint16_t>("DW"), (std::vector<std::uint16_t>{0, 0}));
    const std::uint64_t quiet = cycles(in);
    std::this_thread::sleep_for(300ms);
    EXPECT_EQ(cycles(in), quiet) << "no edge, no cycle";

    pull(chip1_, 0, true);
    EXPECT_TRUE(eventually([&] { return get<std::uint16_t>("DW") == std::vector<std::uint16_t>{1, 0}; }));
    pull(chip1_, 1, true);
    EXPECT_TRUE(eventually([&] { return get<std::uint16_t>("DW") == std::vector<std::uint16_t>{3, 0}; }));
    pull(chip1_, 3, true);
    EXPECT_TRUE(eventually([&] { return get<std::uint16_t>("DW") == std::vector<std::uint16_t>{3, 2}; }))
        << "2-bit ports: line 3 is bit 1 of port 1";
    EXPECT_GE(cycles(in), quiet + 3);

    // With the lines quiet, sync() is blocked on them: off and on still get in.
    sbs_->control(in, Control::off);
    EXPECT_EQ(state(in), State::OFF);
    sbs_->control(in, Control::on);
    pull(chip1_, 0, false);
    EXPECT_TRUE(eventually([&] { return get<std::uint16_t>("DW") == std::vector<std::uint16_t>{2, 2}; }));
    sbs_->control(in, Control::kill);
    EXPECT_NO_THROW(iod::open(db_, "pairs", 0, 1, iod::READ));
}

// No heap allocation in the cycle (docs/architecture.md §8): operator new calls
// made by each task's own thread over a run of cycles, with inputs changing.
TEST_F(DioGuest, CyclesDoNotAllocate) {
    const TaskId in = sbs_->spawn(rmod("din4", "din", "SVARALIAS DIN=DI\nSVARALIAS EDGES=DI_EDGES\nOUTVAR DIN EDGES\n",
                                       din_local("sim", "0 3", "INVERT 1\n")));
    const TaskId out = sbs_->spawn(rmod("dout4", "dout", "SVARALIAS DOUT=DOD\nINVAR DOUT\n",
                                        din_local("sim", "4 7", "SAFE 0\nILLEGAL safe\n")));
    const TaskId sync = sbs_->spawn(rmod("sync", "din", "SVARALIAS DIN=DW\nOUTVAR DIN\n", din_local("pairs", "0 1"),
                                         "synchronous"));
    for (TaskId id : {in, out, sync}) sbs_->control(id, Control::on);
    more_cycles(in, 3);
    more_cycles(out, 3);

    auto count_on = [&](TaskId id, const std::function<void()>& during) -> long {
        chimera::test::alloc_count_start(chimera::test::AllocScope::thread, sbs_->status(id).tid);
        during();
        return chimera::test::alloc_count_stop();
    };
    EXPECT_EQ(count_on(in, [&] {
                  for (int i = 0; i < 10; ++i) {
                      pull(chip0_, i % 4, i % 2 == 0);
                      more_cycles(in, 2);
                  }
              }),
              0)
        << "din";
    EXPECT_EQ(count_on(out, [&] {
                  for (int i = 0; i < 10; ++i) {
                      put<double>("DOD", {double(i % 2), 1, 0, double(i % 2)});
                      more_cycles(out, 2);
                  }
              }),
              0)
        << "dout";
    EXPECT_EQ(count_on(sync, [&] {
                  for (int i = 0; i < 6; ++i) {
                      const std::uint64_t before = cycles(sync);
                      pull(chip1_, i % 4, i < 4);
                      ASSERT_TRUE(eventually([&] { return cycles(sync) > before; }));
                  }
              }),
              0)
        << "synchronous din (sync and cycle)";
}

}  // namespace
