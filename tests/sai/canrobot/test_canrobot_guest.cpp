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
        }
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
            EXPECT_TRUE(chimera::svar::transferred(local.copy_from_global(set)));
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
        std::printf("\n");
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
