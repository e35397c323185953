// The canrobot SAI module against the simulated drives of `candrive`, over a
// real SocketCAN bus (vcan0), inside the PREEMPT_RT guest (tests/rtguest): the
// PID subsystem of Figure 3.7 holds the PUMA's position with its robot
// interface on the bus, exactly as with the in-process simulation (transparent
// simulation, §7.3); a drive or a master that dies, a second master, a bus with
// no drive on it are each handled as the module's header promises. Outside the
// guest only the host test runs: without AF_CAN, init fails with a clear error.
// No timing is asserted (TCG emulation); bounds are on behaviour.
#include "guest_env.hpp"
#include "fig3_7.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include "canrobot/cia402.hpp"

#include <gtest/gtest.h>

#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <map>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

namespace {

using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;
using namespace chimera::canrobot::cia402;
using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

constexpr std::size_t kDof = 6;

using chimera::test::env;

bool kernel_has_af_can() {
    const int fd = ::socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (fd < 0) return false;
    ::close(fd);
    return true;
}

#define REQUIRE_VCAN() CHIMERA_REQUIRE_GUEST_ENV("CHIMERA_VCAN")

std::string read_file(const std::string& path) {
    std::ifstream f(path);
    std::stringstream s;
    s << f.rdbuf();
    return s.str();
}

// A copy of a shipped .rmod with lines replaced by key (header or LOCAL), or
// LOCAL keys added before EOF.
std::string rmod_variant(const std::string& source, const std::string& name,
                         const std::map<std::string, std::string>& keys) {
    std::istringstream in(read_file(source));
    std::string out, line;
    std::map<std::string, std::string> pending = keys;
    while (std::getline(in, line)) {
        std::istringstream words(line);
        std::string key;
        words >> key;
        if (key == "EOF") {
            for (const auto& [k, v] : pending) out += k + " " + v + "\n";
            pending.clear();
        } else if (auto it = pending.find(key); it != pending.end()) {
            line = key + " " + it->second;
            pending.erase(it);
        }
        out += line + "\n";
    }
    const std::string path = "/tmp/" + name + ".rmod";
    std::ofstream(path) << out;
    return path;
}

// TCG emulates the guest's CPUs 10-50 times slower than the host runs: the
// robot interfaces and the controller run at 200 Hz instead of 500, and the
// failure detectors get slack for a process that may not run for tens of
// milliseconds. Both ends read the same file.
constexpr const char* kGuestFreq = "200";
std::string guest_puma_can(const std::string& name, std::map<std::string, std::string> more = {}) {
    more.emplace("FREQ", kGuestFreq);
    more.emplace("DRIVE_STEP", "0.0005");
    more.emplace("INTERFACE", env("CHIMERA_VCAN"));
    more.emplace("FEEDBACK_MISSES", "100");
    more.emplace("HEARTBEAT_TIMEOUT", "2.0");
    more.emplace("ENABLE_TIMEOUT", "5.0");
    more.emplace("DRIVE_RPDO_TIMEOUT", "0.5");
    return rmod_variant(fig3_7::rmod("puma_can"), name, more);
}
// A trajectory generator that holds the start configuration.
std::string hold_trajectory() {
    std::ostringstream s;
    s << "MODULE trajgen\nDESC hold\nSVARALIAS Z=Q_REF\nSVARALIAS Z^=Q^_REF\nSVARALIAS Z^^=Q^^_REF\n"
         "INCONST NDOF\nOUTVAR Z Z^ Z^^\nTASKTYPE periodic\nFREQ 100\nLOCAL\nPROFILE quintic\nCYCLIC no\n"
         "START current\nPOINT1 1.0 0.0 0.785398 3.141593 0.0 0.785398 0.0\nEOF\n";
    std::ofstream("/tmp/jhold.rmod") << s.str();
    return "/tmp/jhold.rmod";
}

// Every frame on the bus, for what the test cannot see through the SVARs.
class Sniffer {
public:
    explicit Sniffer(const std::string& interface) {
        fd_ = ::socket(PF_CAN, SOCK_RAW | SOCK_NONBLOCK, CAN_RAW);
        sockaddr_can addr{};
        addr.can_family = AF_CAN;
        addr.can_ifindex = static_cast<int>(if_nametoindex(interface.c_str()));
        if (fd_ < 0 || ::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0)
            throw std::runtime_error("sniffer on " + interface + ": " + std::strerror(errno));
        // Room for seconds of traffic between drains (root may exceed rmem_max).
        const int bytes = 16 << 20;
        ::setsockopt(fd_, SOL_SOCKET, SO_RCVBUFFORCE, &bytes, sizeof bytes);
    }
    ~Sniffer() { ::close(fd_); }
    void drain() {
        can_frame f;
        while (::recv(fd_, &f, sizeof f, MSG_DONTWAIT) == static_cast<ssize_t>(sizeof f)) {
            last_[f.can_id] = f;
            ++count_[f.can_id];
            if (record_) record_->push_back(f);
        }
    }
    // Every frame drained from now on is appended to `to` (nullptr: stop).
    void record(std::vector<can_frame>* to) {
        drain();
        record_ = to;
    }
    // Waits until `pred` holds for the frames seen (false after `timeout`).
    bool wait_for(const std::function<bool()>& pred, std::chrono::milliseconds timeout) {
        const auto end = Clock::now() + timeout;
        for (;;) {
            drain();
            if (pred()) return true;
            if (Clock::now() > end) return false;
            pollfd p{fd_, POLLIN, 0};
            ::poll(&p, 1, 10);
        }
    }
    void forget() {
        drain();
        last_.clear();
        count_.clear();
    }
    bool seen(std::uint32_t id) const { return count_.count(id) > 0; }
    std::uint64_t count(std::uint32_t id) const {
        auto it = count_.find(id);
        return it == count_.end() ? 0 : it->second;
    }
    const can_frame& last(std::uint32_t id) const { return last_.at(id); }
    std::uint16_t u16(std::uint32_t id, int at) const {
        const can_frame& f = last(id);
        return static_cast<std::uint16_t>(f.data[at] | (f.data[at + 1] << 8));
    }

private:
    int fd_ = -1;
    std::map<std::uint32_t, can_frame> last_;
    std::map<std::uint32_t, std::uint64_t> count_;
    std::vector<can_frame>* record_ = nullptr;
};

// What the bus carried per node, for a failure message: did the drives stop
// sending, or did the master stop reading?
std::string bus_summary(const Sniffer& bus) {
    std::ostringstream s;
    s << "frames seen on the bus by a sniffer, per node (heartbeat/TPDO1/TPDO2/RPDO1):";
    for (int n = 1; n <= 6; ++n)
        s << " " << n << ":" << bus.count(cob_id(kHeartbeat, n)) << "/" << bus.count(cob_id(kTpdo1, n)) << "/"
          << bus.count(cob_id(kTpdo2, n)) << "/" << bus.count(cob_id(kRpdo1, n));
    return s.str();
}

// The simulated drives, as their own process.
class DriveProcess {
public:
    DriveProcess(const std::string& rmod, Sniffer& bus) {
        bus.forget();
        pid_ = ::fork();
        if (pid_ == 0) {
            // Above the subsystem's tasks (the dispatcher's SCHED_FIFO 80 and
            // below): the drives stand for hardware of their own, which the
            // controller's threads never hold up. Best effort, they went
            // unscheduled for half a second in the TCG guest (issue #36).
            ::execl(CANDRIVE_PATH, CANDRIVE_PATH, "--rmod", rmod.c_str(), "--quiet", "--priority", "85",
                    static_cast<char*>(nullptr));
            std::_Exit(127);
        }
        // Ready when every drive has announced itself (boot-up).
        ready_ = bus.wait_for([&] {
            for (int n = 1; n <= 6; ++n)
                if (!bus.seen(cob_id(kHeartbeat, n))) return false;
            return true;
        }, 20s);
    }
    ~DriveProcess() { stop(SIGTERM); }
    bool ready() const { return ready_; }
    // The exit status (signal number + 128 when killed).
    int stop(int signal) {
        if (pid_ <= 0) return status_;
        ::kill(pid_, signal);
        int st = 0;
        ::waitpid(pid_, &st, 0);
        pid_ = -1;
        status_ = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
        return status_;
    }

private:
    pid_t pid_ = -1;
    bool ready_ = false;
    int status_ = -1;
};

std::string unique_name(const char* what) { return std::string("can_") + what + std::to_string(::getpid()); }

// The subsystem of Figure 3.7 with `robot_rmod` as its robot interface, a
// trajectory generator holding the start configuration and the PID
// controller; the largest |Q_REF - Q_MEZ| over `seconds` after `settle`.
struct HoldResult {
    double max_error = -1;
    std::vector<double> window_errors;  // max error of each half second, for the log
    std::uint64_t robot_cycles = 0;
    chimera::State robot_state = chimera::State::NOT_CREATED;
    std::string robot_error;
    std::uint64_t misses = 0;  // deadline misses of all tasks during the hold
    std::uint64_t samples = 0, refused_reads = 0;  // the test's reads of Q_REF, Q_MEZ, and those the lock refused

    // No runaway after the settling time, and settled in the last half second.
    // The bounds are loose: TCG runs the tasks late and irregularly, more so
    // with the host loaded (the in-process robot's forward dynamics is the
    // heaviest task: 0.0205 rad at 1-1.5 s in a loaded run, 0.0002 at the end).
    bool holds() const { return max_error >= 0 && max_error < 0.05 && !window_errors.empty() && window_errors.back() < 0.005; }
};

class Fig37Run {
public:
    Fig37Run(const std::string& robot_rmod, const char* name, bool with_pid = true)
        : sbs_(Subsystem::init(fig3_7::load_sbs(nullptr, unique_name(name)))) {
        fig3_7::add_module_dirs(*sbs_);
        robot_ = sbs_->spawn(robot_rmod, "robot");
        traj_ = sbs_->spawn(hold_trajectory(), "ctrl");
        if (with_pid) pid_ = sbs_->spawn(rmod_variant(fig3_7::rmod("jpid"), "jpid_guest", {{"FREQ", kGuestFreq}}), "ctrl");
    }
    Subsystem& sbs() { return *sbs_; }
    TaskId robot() const { return robot_; }
    TaskId traj() const { return traj_; }
    TaskId pid() const { return pid_; }

    void on() {
        std::vector<chimera::sbs::ReconfigItem> items{{robot_, Control::on}, {traj_, Control::on}};
        if (pid_) items.push_back({pid_, Control::on});
        const auto r = sbs_->reconfig(items);
        ASSERT_TRUE(r.ok) << r.message;
    }

    HoldResult hold(double settle, double seconds, const std::function<void()>& meanwhile = {}) {
        HoldResult res;
        auto table = chimera::svar::Table::attach(chimera::ipc::segment_name(sbs_->name(), "svar"));
        chimera::svar::LocalTable local(table, std::vector<std::string>{"Q_REF", "Q_MEZ"});
        const auto set = local.make_set({"Q_REF", "Q_MEZ"});
        const double* q_ref = local.translate<double>("Q_REF");
        const double* q_mez = local.translate<double>("Q_MEZ");
        const auto misses = [&] {
            std::uint64_t n = 0;
            for (const auto& st : sbs_->status_all()) n += st.misses;
            return n;
        };
        const std::uint64_t misses_before = misses();
        const auto t0 = Clock::now();
        res.max_error = 0;
        for (double t = 0; t < settle + seconds;
             t = std::chrono::duration<double>(Clock::now() - t0).count()) {
            if (meanwhile) meanwhile();
            std::this_thread::sleep_for(5ms);
            // The test reads as an observer, at no real-time priority: in a TCG
            // guest on a loaded host a task preempted inside its copy can hold
            // the table past the observer's lock timeout (seen in a run beside
            // another whole suite). Such a sample is not taken, and counted.
            ++res.samples;
            if (!chimera::svar::transferred(local.copy_from_global(set))) {
                ++res.refused_reads;
                continue;
            }
            double e = 0;
            for (std::size_t j = 0; j < kDof; ++j) e = std::max(e, std::fabs(q_ref[j] - q_mez[j]));
            const auto w = static_cast<std::size_t>(t / 0.5);
            if (res.window_errors.size() <= w) res.window_errors.resize(w + 1, 0.0);
            res.window_errors[w] = std::max(res.window_errors[w], e);
            if (t >= settle) res.max_error = std::max(res.max_error, e);
        }
        for (const auto& st : sbs_->status_all())
            std::printf("  %-16s cycles %6llu misses %5llu refF %6.1f mezF %6.1f maxC %.6f\n", st.rmod.c_str(),
                        static_cast<unsigned long long>(st.cycles), static_cast<unsigned long long>(st.misses),
                        st.ref_freq, st.mez_freq, st.max_cycle_time);
        std::printf("  error per 0.5 s:");
        for (double e : res.window_errors) std::printf(" %.4f", e);
        std::printf("\n  samples %llu, refused by the table lock %llu\n", static_cast<unsigned long long>(res.samples),
                    static_cast<unsigned long long>(res.refused_reads));
        // A hold judged from fewer than half its samples is not measured.
        EXPECT_LE(2 * res.refused_reads, res.samples) << "the table lock refused most of the test's reads";
        res.misses = misses() - misses_before;
        const auto st = sbs_->status(robot_);
        res.robot_cycles = st.cycles;
        res.robot_state = st.state;
        res.robot_error = st.error;
        return res;
    }

private:
    std::unique_ptr<Subsystem> sbs_;
    TaskId robot_, traj_, pid_;
};

// A hold whose tasks missed deadlines and which then failed is measured once
// more, in the same running subsystem: a stall of the guest (the host is
// shared: one CI run had 32 misses and 0.30 rad) lets the simulated arm fall
// under gravity while nothing runs, as a real arm would. A hold that fails
// without a miss, or fails twice, is the controller's failure.
HoldResult hold_measured_again_if_disturbed(Fig37Run& run, const char* how, const std::function<void()>& meanwhile) {
    HoldResult h = run.hold(1.0, 3.0, meanwhile);
    if (h.holds() || h.misses == 0) return h;
    std::printf("hold %s: %llu deadline misses, error %.4f rad: measured again\n", how,
                static_cast<unsigned long long>(h.misses), h.max_error);
    return run.hold(1.0, 3.0, meanwhile);
}

// --- on the host -----------------------------------------------------------------

TEST(CanRobotHost, WithoutAfCanInitFailsNamingTheRmodAndTheReason) {
    if (kernel_has_af_can()) GTEST_SKIP() << "this kernel has AF_CAN (the guest tests cover the module)";
    auto sbs = Subsystem::init(fig3_7::load_sbs(nullptr, unique_name("host")));
    fig3_7::add_module_dirs(*sbs);
    try {
        sbs->spawn(fig3_7::rmod("puma_can"), "robot");
        FAIL() << "spawned without a CAN bus";
    } catch (const chimera::sbs::Error& e) {
        const std::string m = e.what();
        EXPECT_NE(m.find("puma_can"), std::string::npos) << m;
        EXPECT_NE(m.find("no AF_CAN support"), std::string::npos) << m;
    }
    EXPECT_TRUE(sbs->status_all().empty());  // nothing half-built
}

// --- in the guest ------------------------------------------------------------------

TEST(CanRobotGuest, ThePidSubsystemHoldsPositionOverCanAsInSimulation) {
    REQUIRE_VCAN();
    const std::string ifc = env("CHIMERA_VCAN");
    Sniffer bus(ifc);
    const std::string rmod = guest_puma_can("puma_can_hold");
    DriveProcess drives(rmod, bus);
    ASSERT_TRUE(drives.ready()) << "candrive did not announce its drives";

    HoldResult over_can, in_process;
    {
        Fig37Run run(rmod, "hold");
        run.on();
        // The drives are enabled (holding in CSP while the reconfiguration
        // runs, then in cyclic synchronous torque mode).
        ASSERT_TRUE(bus.wait_for([&] {
            for (int n = 1; n <= 6; ++n)
                if (!bus.seen(cob_id(kTpdo1, n)) ||
                    decode_statusword(bus.u16(cob_id(kTpdo1, n), 0)) != DriveState::operation_enabled)
                    return false;
            return true;
        }, 5s));
        over_can = hold_measured_again_if_disturbed(run, "over CAN", [&] { bus.drain(); });
        for (int n = 1; n <= 6; ++n)
            EXPECT_EQ(static_cast<std::int16_t>(bus.u16(cob_id(kTpdo1, n), 2)), kModeCst) << "node " << n;
        EXPECT_EQ(over_can.robot_state, chimera::State::ON) << over_can.robot_error << "\n" << bus_summary(bus);
        EXPECT_GT(over_can.robot_cycles, 50u);
        EXPECT_GT(bus.count(kSync), 50u);
        EXPECT_GT(bus.count(cob_id(kTpdo2, 6)), 50u);

        // A second master for the same bus is refused, naming what is taken.
        try {
            run.sbs().spawn(rmod, "robot");
            ADD_FAILURE() << "a second canrobot task on " << ifc << " was spawned";
        } catch (const chimera::sbs::Error& e) {
            EXPECT_NE(std::string(e.what()).find("already open"), std::string::npos) << e.what();
        }
        EXPECT_EQ(run.sbs().status(run.robot()).state, chimera::State::ON);

        // off: the drives are switched off (ready to switch on: brakes)...
        bus.forget();
        const auto r = run.sbs().reconfig({{run.pid(), Control::off}, {run.robot(), Control::off}});
        ASSERT_TRUE(r.ok) << r.message;
        EXPECT_TRUE(bus.wait_for([&] {
            for (int n = 1; n <= 6; ++n)
                if (!bus.seen(cob_id(kTpdo1, n)) ||
                    decode_statusword(bus.u16(cob_id(kTpdo1, n), 0)) != DriveState::ready_to_switch_on)
                    return false;
            return true;
        }, 3s)) << "every drive reports 'ready to switch on' after off";
        // ...and kill returns them to pre-operational.
        bus.forget();
        run.sbs().control(run.robot(), Control::kill);
        EXPECT_TRUE(bus.wait_for([&] {
            for (int n = 1; n <= 6; ++n)
                if (!bus.seen(cob_id(kHeartbeat, n)) ||
                    bus.last(cob_id(kHeartbeat, n)).data[0] != static_cast<std::uint8_t>(NmtState::preoperational))
                    return false;
            return true;
        }, 3s)) << "every drive's heartbeat says pre-operational after kill";
    }
    {
        Fig37Run run(rmod_variant(fig3_7::rmod("puma_torque"), "puma_torque_guest", {{"FREQ", kGuestFreq}}), "sim");
        run.on();
        in_process = hold_measured_again_if_disturbed(run, "in-process", {});
        EXPECT_EQ(in_process.robot_state, chimera::State::ON) << in_process.robot_error;
    }
    std::printf("hold error after 1 s: over CAN %.5f rad, in-process simulation %.5f rad\n", over_can.max_error,
                in_process.max_error);
    // The same subsystem holds the arm through either robot interface.
    for (const HoldResult* h : {&over_can, &in_process}) {
        EXPECT_LT(h->max_error, 0.05);
        ASSERT_FALSE(h->window_errors.empty());
        EXPECT_LT(h->window_errors.back(), 0.005);
    }
}

TEST(CanRobotGuest, PositionModeHoldsWithTheDrivesOwnLoop) {
    REQUIRE_VCAN();
    Sniffer bus(env("CHIMERA_VCAN"));
    const std::string rmod = guest_puma_can("puma_can_position", {{"MODE", "position"},
                                                                  {"INVAR", "Q_REF Q^_REF"},
                                                                  {"DESC", "PUMA 560 over CAN, position mode"}});
    DriveProcess drives(rmod, bus);
    ASSERT_TRUE(drives.ready());
    Fig37Run run(rmod, "pos", /*with_pid=*/false);
    run.on();
    ASSERT_TRUE(bus.wait_for([&] { return bus.seen(cob_id(kTpdo1, 1)); }, 2s));
    EXPECT_EQ(static_cast<std::int16_t>(bus.u16(cob_id(kTpdo1, 1), 2)), kModeCsp);
    const HoldResult r = run.hold(1.0, 2.0, [&] { bus.drain(); });
    EXPECT_EQ(r.robot_state, chimera::State::ON) << r.robot_error << "\n" << bus_summary(bus);
    EXPECT_LT(r.max_error, 0.02);
    EXPECT_GT(bus.count(cob_id(kRpdo2, 3)), 20u);  // targets went out in RPDO2
}

TEST(CanRobotGuest, ADriveThatDiesPutsTheTaskInErrorNamingItAndTheOthersRunOn) {
    REQUIRE_VCAN();
    Sniffer bus(env("CHIMERA_VCAN"));
    const std::string rmod = guest_puma_can("puma_can_die", {{"FEEDBACK_MISSES", "25"}});
    DriveProcess drives(rmod, bus);
    ASSERT_TRUE(drives.ready());
    Fig37Run run(rmod, "die");
    run.on();
    std::this_thread::sleep_for(500ms);
    ASSERT_EQ(run.sbs().status(run.robot()).state, chimera::State::ON);
    drives.stop(SIGKILL);

    chimera::sbs::TaskStatus st;
    const auto end = Clock::now() + 10s;
    do {
        std::this_thread::sleep_for(20ms);
        bus.drain();
        st = run.sbs().status(run.robot());
    } while (st.state != chimera::State::ERROR && Clock::now() < end);
    ASSERT_EQ(st.state, chimera::State::ERROR);
    // One process runs all six drives, so all six fall silent at once; which
    // one the module names first depends on where in a SYNC's burst of TPDOs
    // the kill landed (CI saw node 3: nodes 1 and 2 had sent that cycle's).
    EXPECT_TRUE(std::regex_search(st.error, std::regex(R"(node ([1-6]) \(joint \1\) on )"))) << st.error;
    EXPECT_TRUE(st.error.find("no position (TPDO2)") != std::string::npos ||
                st.error.find("no heartbeat") != std::string::npos)
        << st.error;
    // The controller and the trajectory generator are still running.
    EXPECT_EQ(run.sbs().status(run.traj()).state, chimera::State::ON);
    EXPECT_EQ(run.sbs().status(run.pid()).state, chimera::State::ON);
    // The module's error handler stopped the drives: a quick stop for each.
    bus.drain();
    EXPECT_EQ(bus.u16(cob_id(kRpdo1, 4), 0), kCwQuickStop);
}

TEST(CanRobotGuest, AMasterThatDiesLeavesTheDrivesFaultedOnTheirRpdoTimeout) {
    REQUIRE_VCAN();
    Sniffer bus(env("CHIMERA_VCAN"));
    const std::string rmod = guest_puma_can("puma_can_master");
    DriveProcess drives(rmod, bus);
    ASSERT_TRUE(drives.ready());
    const pid_t master = ::fork();
    if (master == 0) {
        try {
            Fig37Run run(rmod, "master");
            run.on();
            for (;;) ::pause();
        } catch (...) {
        }
        std::_Exit(1);
    }
    // The master runs when SYNCs flow and every drive is enabled.
    const bool running = bus.wait_for([&] {
        if (bus.count(kSync) < 20) return false;
        for (int n = 1; n <= 6; ++n)
            if (!bus.seen(cob_id(kTpdo1, n)) ||
                decode_statusword(bus.u16(cob_id(kTpdo1, n), 0)) != DriveState::operation_enabled)
                return false;
        return true;
    }, 20s);
    ::kill(master, SIGKILL);
    ::waitpid(master, nullptr, 0);
    ASSERT_TRUE(running) << "the master subsystem never ran";
    bus.forget();
    EXPECT_TRUE(bus.wait_for([&] {
        for (int n = 1; n <= 6; ++n)
            if (!bus.seen(cob_id(kTpdo1, n)) ||
                decode_statusword(bus.u16(cob_id(kTpdo1, n), 0)) != DriveState::fault ||
                bus.u16(cob_id(kTpdo1, n), 4) != kErrRpdoTimeout)
                return false;
        return true;
    }, 5s)) << "every drive reports fault 0x8250 (RPDO timeout)";
}

// --- speed and torque-rate limits (issue #29.6) ------------------------------------

// The limits of examples/two_machines/puma_limited.rmod (rad/s, N m/s), and
// what puma_can.rmod declares of the bus (rated torque, N m; counts per rev).
const std::array<double, kDof> kVlimit{1, 1, 1, 2, 2, 2};
const std::array<double, kDof> kTrate{1000, 2000, 1000, 200, 200, 200};
const std::array<double, kDof> kRated{10, 10, 10, 1, 1, 1};
constexpr double kCountsPerRev = 1048576;
constexpr double kGuestPeriod = 1.0 / 200;  // kGuestFreq
// Where the arm starts (puma_can's Q0) and where the reference jumps to: 0.6 rad
// away on every joint at once.
const std::array<double, kDof> kQ0{0, 0.785398, 3.141593, 0, 0.785398, 0};
constexpr double kJump = 0.6;
// "2 s after": counted in the bus's cycles (SYNCs at FREQ 200), not in the
// guest's wall time, which a starved TCG guest stretches.
constexpr std::uint64_t kCyclesAfter = 400;

// A trajectory generator whose reference jumps, on `on`, to Q0 + kJump and
// stays there: a reference that arrives late, all at once (a link that comes
// back with a reference far from the arm).
std::string jump_trajectory() {
    std::ostringstream s;
    s << "MODULE trajgen\nDESC jump\nSVARALIAS Z=Q_REF\nSVARALIAS Z^=Q^_REF\nSVARALIAS Z^^=Q^^_REF\n"
         "INCONST NDOF\nOUTVAR Z Z^ Z^^\nTASKTYPE periodic\nFREQ 100\nLOCAL\nPROFILE quintic\nCYCLIC no\n"
         "START first\nPOINT1 1.0";
    for (double q : kQ0) s << " " << q + kJump;
    s << "\nEOF\n";
    std::ofstream("/tmp/jjump.rmod") << s.str();
    return "/tmp/jjump.rmod";
}

// What the bus carried from the jump until kCyclesAfter SYNCs after the arm
// arrived, per joint: the drives' velocity actual (TPDO2, latched at every
// SYNC) and the change of the target torque canrobot sent (RPDO1, CST) from
// one cycle to the next, in the bus's unit (1/1000 of the rated torque).
struct JumpEpisode {
    std::array<double, kDof> peak_speed{};             // rad/s
    std::array<int, kDof> peak_step{};                 // permille per cycle, every step
    std::array<int, kDof> peak_step_not_braking{};     // the steps that do not brake the joint
    std::array<std::uint64_t, kDof> speed_samples{}, steps{};
    std::uint64_t syncs = 0, csp_frames = 0, gaps = 0;
    std::uint64_t syncs_to_arrive = 0;  // 0: never arrived (every joint within 0.05 rad)
    std::uint64_t robot_misses = 0;     // the robot task's deadline misses in the window
    double seconds = 0;                 // the window, wall time (printed only)
    std::string limits_before, limits_after;  // `get LIMITS`
    chimera::State robot_state = chimera::State::NOT_CREATED;
    std::string robot_error;
};

JumpEpisode jump_episode(const std::string& rmod, const char* name) {
    JumpEpisode ep;
    Sniffer bus(env("CHIMERA_VCAN"));
    DriveProcess drives(rmod, bus);
    EXPECT_TRUE(drives.ready()) << "candrive did not announce its drives";
    if (!drives.ready()) return ep;
    Fig37Run run(rmod, name);
    // Spawned before anything runs: loading a module into the controller's
    // process stalled the guest past the drives' RPDO timeout once, mid-run.
    const TaskId jump = run.sbs().spawn(jump_trajectory(), "ctrl");
    run.on();
    // Settled at Q0 first, within 0.05 rad over a whole second. A starved
    // guest (tasks missing deadlines) lets the arm sag meanwhile, as the hold
    // test sees: it is measured again, up to 5 times.
    HoldResult settled;
    for (int i = 0; i < 5 && !(settled.max_error >= 0 && settled.max_error < 0.05); ++i)
        settled = run.hold(0.5, 1.0, [&] { bus.drain(); });
    EXPECT_LT(settled.max_error, 0.05) << "the arm did not settle before the jump";
    if (run.sbs().status(run.robot()).state != chimera::State::ON) {
        ADD_FAILURE() << "before the jump: " << run.sbs().status(run.robot()).error << "\n" << bus_summary(bus);
        return ep;
    }
    ep.limits_before = run.sbs().get(run.robot(), "LIMITS");
    const std::uint64_t misses_before = run.sbs().status(run.robot()).misses;

    std::vector<can_frame> frames;
    frames.reserve(1 << 17);
    bus.record(&frames);
    const auto t0 = Clock::now();
    const auto r = run.sbs().reconfig({{run.traj(), Control::off}, {jump, Control::on}});
    EXPECT_TRUE(r.ok) << r.message;
    // Until every joint is within 0.05 rad of the new reference, then
    // kCyclesAfter more cycles (at most 4000 cycles, or 10 minutes).
    std::array<double, kDof> q = kQ0;
    std::size_t seen = 0;
    std::uint64_t syncs = 0, end = 4000;
    while (syncs < end && Clock::now() < t0 + 600s) {
        std::this_thread::sleep_for(5ms);
        bus.drain();
        for (; seen < frames.size(); ++seen) {
            const can_frame& f = frames[seen];
            syncs += f.can_id == kSync;
            if (f.can_id > kTpdo2 && f.can_id <= kTpdo2 + kDof) {
                std::int32_t c;
                std::memcpy(&c, f.data, 4);
                q[f.can_id - kTpdo2 - 1] = from_counts(c, kCountsPerRev);
            }
        }
        if (!ep.syncs_to_arrive) {
            double e = 0;
            for (std::size_t j = 0; j < kDof; ++j) e = std::max(e, std::fabs(q[j] - (kQ0[j] + kJump)));
            if (e < 0.05) {
                ep.syncs_to_arrive = syncs;
                end = syncs + kCyclesAfter;
            }
        }
        if (run.sbs().status(run.robot()).state != chimera::State::ON) break;
    }
    bus.record(nullptr);
    ep.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
    ep.limits_after = run.sbs().get(run.robot(), "LIMITS");
    const auto st = run.sbs().status(run.robot());
    ep.robot_state = st.state;
    ep.robot_error = st.error;
    ep.robot_misses = st.misses - misses_before;

    // The frames in bus order: each cycle the RPDO1s, the SYNC, then the
    // TPDO2s latched at it — the speeds canrobot reads for the next cycle.
    std::array<int, kDof> last_permille{};
    std::array<std::int64_t, kDof> last_sync;
    last_sync.fill(-1);
    std::array<double, kDof> qd{};
    std::int64_t sync = 0;
    for (const can_frame& f : frames) {
        if (f.can_id == kSync) {
            ++sync;
            ++ep.syncs;
        } else if (f.can_id > kTpdo2 && f.can_id <= kTpdo2 + kDof) {
            const std::size_t j = f.can_id - kTpdo2 - 1;
            std::int32_t c;
            std::memcpy(&c, f.data + 4, 4);
            qd[j] = from_counts(c, kCountsPerRev);
            ep.peak_speed[j] = std::max(ep.peak_speed[j], std::fabs(qd[j]));
            ++ep.speed_samples[j];
        } else if (f.can_id > kRpdo1 && f.can_id <= kRpdo1 + kDof) {
            const std::size_t j = f.can_id - kRpdo1 - 1;
            std::uint16_t cw;
            std::int16_t mode, permille;
            std::memcpy(&cw, f.data, 2);
            std::memcpy(&mode, f.data + 2, 2);
            std::memcpy(&permille, f.data + 4, 2);
            if (mode != kModeCst || cw != kCwEnableOperation) {
                ++ep.csp_frames;  // a hold (CSP) or a state change: the rate limit starts again after it
                last_sync[j] = -1;
                continue;
            }
            if (last_sync[j] >= 0) {
                if (sync - last_sync[j] == 1) {
                    const int step = permille - last_permille[j];
                    ep.peak_step[j] = std::max(ep.peak_step[j], std::abs(step));
                    // The speed envelope only ever cuts the torque against the motion.
                    const bool braking = (qd[j] > 0 && step < 0) || (qd[j] < 0 && step > 0);
                    if (!braking) ep.peak_step_not_braking[j] = std::max(ep.peak_step_not_braking[j], std::abs(step));
                    ++ep.steps[j];
                } else {
                    ++ep.gaps;  // a frame the sniffer did not see: that pair is not one cycle's step
                }
            }
            last_permille[j] = permille;
            last_sync[j] = sync;
        }
    }
    std::printf("%s: jump of %.1f rad; arrived (every joint within 0.05 rad) %llu cycles after it; window %llu "
                "cycles (SYNCs), %.1f s of guest wall time; robot deadline misses %llu; %llu CSP/state frames, "
                "%llu gaps\n",
                name, kJump, static_cast<unsigned long long>(ep.syncs_to_arrive),
                static_cast<unsigned long long>(ep.syncs), ep.seconds, static_cast<unsigned long long>(ep.robot_misses),
                static_cast<unsigned long long>(ep.csp_frames), static_cast<unsigned long long>(ep.gaps));
    for (std::size_t j = 0; j < kDof; ++j)
        std::printf("  joint %zu: peak |speed| %.3f rad/s (VLIMIT %.0f; %llu samples); peak torque step %.3f N m per "
                    "cycle, %.3f not braking (TRATE x period %.3f; %llu steps)\n",
                    j + 1, ep.peak_speed[j], kVlimit[j], static_cast<unsigned long long>(ep.speed_samples[j]),
                    ep.peak_step[j] * kRated[j] / 1000, ep.peak_step_not_braking[j] * kRated[j] / 1000,
                    kTrate[j] * kGuestPeriod, static_cast<unsigned long long>(ep.steps[j]));
    std::printf("  get LIMITS before the jump: '%s', after: '%s'\n", ep.limits_before.c_str(), ep.limits_after.c_str());
    return ep;
}

std::string vector_text(const std::array<double, kDof>& v) {
    std::ostringstream s;
    for (std::size_t j = 0; j < kDof; ++j) s << (j ? " " : "") << v[j];
    return s.str();
}

// Issue #29.6 over CAN: the reference jumps 0.6 rad on every joint at once (a
// link that comes back with a reference far from the arm), and the PID asks
// for its torque limits: without VLIMIT and TRATE that drives every joint past
// its VLIMIT (CanRobotLimits.AJumpingReference..., exactly, on the host).
// With puma_limited.rmod's limits declared, sampled at every cycle (each
// SYNC's TPDO2, each RPDO1; FREQ 200) from the jump until 400 cycles after
// the arm arrived:
//   - both limits acted (`get LIMITS`);
//   - every torque step within TRATE x period (plus one unit of the bus's
//     torque, for rounding), except steps that brake the joint: the speed
//     envelope comes after the rate limit and wins (robotics/limits.hpp);
//   - every joint's speed within VLIMIT, always: canrobot downloaded VLIMIT
//     into the drives at init (0x6080 max motor speed, rounded down to
//     counts/s), and the drives hold it at every integration step whatever
//     the master does. Before that download, a starved TCG guest whose master
//     ran late let joint 3 reach 3.4 rad/s in one run (the master's limit
//     uses the speed latched a cycle before; CanRobotLimits.TheDrivesOwnLimits...,
//     exactly, on the host);
//   - the arm at the new reference (every joint within 0.05 rad) within the
//     4000 cycles the window may last — asserted when the robot task missed
//     no deadline in the window (a starved run's controller may run at a
//     quarter of its rate and never settle; it prints its peaks).
TEST(CanRobotGuest, AReferenceThatJumpsMovesTheArmWithinVlimitAndTrate) {
    REQUIRE_VCAN();
    const JumpEpisode lim = jump_episode(
        // The drives' heartbeats are not the subject here: a TCG guest on a
        // loaded host starved candrive for 5.5 s once, past the 2 s of the others.
        guest_puma_can("puma_can_limited",
                       {{"VLIMIT", vector_text(kVlimit)}, {"TRATE", vector_text(kTrate)}, {"HEARTBEAT_TIMEOUT", "10.0"}}),
        "limited");
    EXPECT_EQ(lim.robot_state, chimera::State::ON) << lim.robot_error;
    EXPECT_GE(lim.syncs, lim.syncs_to_arrive + kCyclesAfter);
    const bool on_time = lim.robot_misses == 0;
    if (on_time) {
        EXPECT_GT(lim.syncs_to_arrive, 0u) << "the arm never arrived at the new reference";
    } else {
        std::printf("limited: the robot task missed %llu deadlines in the window: arrival not judged\n",
                    static_cast<unsigned long long>(lim.robot_misses));
    }
    for (std::size_t j = 0; j < kDof; ++j) {
        // Sampled at every cycle: a TPDO2 per SYNC, a torque step per cycle
        // (the few cycles of the reconfiguration's hold aside).
        EXPECT_GE(lim.speed_samples[j] + 2, lim.syncs) << "joint " << j + 1;
        EXPECT_GE(lim.steps[j] + lim.gaps + lim.csp_frames + 2, lim.syncs) << "joint " << j + 1;
        EXPECT_LE(lim.peak_step_not_braking[j], kTrate[j] * kGuestPeriod * 1000 / kRated[j] + 1 + 1e-9)
            << "joint " << j + 1;
        EXPECT_LE(lim.peak_speed[j], kVlimit[j]) << "joint " << j + 1 << (on_time ? "" : " (robot task missed deadlines)");
    }
    unsigned long long speed0 = 0, rate0 = 0, speed1 = 0, rate1 = 0;
    ASSERT_EQ(std::sscanf(lim.limits_before.c_str(), "speed_clamps %llu rate_clamps %llu", &speed0, &rate0), 2)
        << lim.limits_before;
    ASSERT_EQ(std::sscanf(lim.limits_after.c_str(), "speed_clamps %llu rate_clamps %llu", &speed1, &rate1), 2)
        << lim.limits_after;
    EXPECT_GT(speed1, speed0) << "the speed limit never acted";
    EXPECT_GT(rate1, rate0) << "the torque-rate limit never acted";
}

TEST(CanRobotGuest, WithNoDriveOnTheBusInitFailsNamingTheNodes) {
    REQUIRE_VCAN();
    const std::string rmod = guest_puma_can("puma_can_nobody", {{"ENABLE_TIMEOUT", "0.5"}});
    auto sbs = Subsystem::init(fig3_7::load_sbs(nullptr, unique_name("nobody")));
    fig3_7::add_module_dirs(*sbs);
    try {
        sbs->spawn(rmod, "robot");
        FAIL() << "spawned with no drive on the bus";
    } catch (const chimera::sbs::Error& e) {
        const std::string m = e.what();
        EXPECT_NE(m.find("node 1 (joint 1)"), std::string::npos) << m;
        EXPECT_NE(m.find("node 6 (joint 6)"), std::string::npos) << m;
        EXPECT_NE(m.find("no answer"), std::string::npos) << m;
    }
    EXPECT_TRUE(sbs->status_all().empty());
    // Nothing stays reserved: once the drives are there, the same rmod spawns.
    Sniffer bus(env("CHIMERA_VCAN"));
    DriveProcess drives(rmod, bus);
    ASSERT_TRUE(drives.ready());
    EXPECT_NO_THROW(sbs->spawn(rmod, "robot"));
}

}  // namespace
