// The task thread: the state machine of Figure 3.10, with the SVAR transfers
// around each method (§3.5, §3.6). TaskLoop::run is the figure; each state and
// each step of it is one member function named after the thesis.
#include "internal.hpp"

#include "chimera/cfg.hpp"
#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/futex.hpp"
#include "chimera/muf/rt.hpp"
#include "chimera/trace.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <mutex>
#include <optional>
#include <sys/syscall.h>
#include <unistd.h>
#include <vector>

namespace chimera::sbs::detail {

namespace {

// What a method call came to, after error routing (§3.6).
enum class Outcome : std::uint8_t {
    ok,          // returned OK (or an error was handled with CONTINUE)
    off,         // returned OFF (on: stay OFF; cycle: goal reached, turn off)
    error_off,   // error(), and error() said OFF
    error_halt,  // error() said ERROR, or an error where error() is not called
};

bool ok_or_off(Outcome o) noexcept { return o == Outcome::ok || o == Outcome::off; }

enum class Phase : std::uint8_t { init, reinit, on, cycle, off, kill, sync, clear, set, get };

const char* phase_name(Phase p) noexcept {
    switch (p) {
        case Phase::init: return "init";
        case Phase::reinit: return "reinit";
        case Phase::on: return "on";
        case Phase::cycle: return "cycle";
        case Phase::off: return "off";
        case Phase::kill: return "kill";
        case Phase::sync: return "sync";
        case Phase::clear: return "clear";
        case Phase::set: return "set";
        case Phase::get: return "get";
    }
    return "?";
}

// Errors in these methods go to the module's error() (§3.6); elsewhere they
// fail the request (init: kill and NOT-CREATED; clear: stay in ERROR).
bool routes_to_error(Phase p) noexcept {
    return p == Phase::on || p == Phase::cycle || p == Phase::off || p == Phase::sync || p == Phase::reinit;
}

// The marks below are set with sigsetjmp(mark, 0): saving the signal mask
// would cost a system call on every cycle. A jump out of a signal handler
// leaves that handler's signals blocked, so the (rare) jumped-to path puts
// back the mask the thread runs with, `normal_mask`, taken once at its start.

// Runs `body` (the objects' cycle methods) with the cycle abortable: a timing
// failure handler answering abort_cycle jumps back here (siglongjmp to the mark)
// and the call returns false. Kept apart so that nothing of the caller's frame
// lives across the jump; the abort is disarmed as soon as cycle returns.
template <typename Body>
[[gnu::noinline]] bool run_abortable(Pacer& pacer, sigjmp_buf& mark, const sigset_t& normal_mask, Body& body) {
    if (sigsetjmp(mark, 0) != 0) {
        pthread_sigmask(SIG_SETMASK, &normal_mask, nullptr);
        // An abort an errInvoke recorded in the abandoned method is not the next one's.
        err::clear_pending();
        return false;
    }
    pacer.arm_abort();
    body();
    pacer.disarm_abort();
    return true;
}

// Crash containment (the thesis's "a task that faults is suspended, the others
// run on"): while a module method runs, SIGSEGV/SIGBUS/SIGFPE/SIGILL raised by
// that thread jump back to the runtime, which halts the task in ERROR. The
// handler runs on a per-thread alternate stack, so a stack overflow is caught
// too. Outside module methods (or in threads that are not tasks) the previous
// disposition is restored and the fault happens again, as it would have.
// Best effort by nature: a module that corrupted shared state (the heap, a
// lock it held) can still bring the process down later.
// Initial-exec, as muf's per-thread state: read around every module call.
[[gnu::tls_model("initial-exec")]] constinit thread_local sigjmp_buf* t_crash_mark = nullptr;
constexpr int kCrashSignals[] = {SIGSEGV, SIGBUS, SIGFPE, SIGILL};
struct sigaction g_previous_action[NSIG];

void on_crash_signal(int signo, siginfo_t*, void*) {
    if (sigjmp_buf* mark = t_crash_mark) {
        t_crash_mark = nullptr;
        siglongjmp(*mark, signo);
    }
    sigaction(signo, &g_previous_action[signo], nullptr);  // not ours: fault again, as before
}

void install_crash_handlers() {
    static std::once_flag once;
    std::call_once(once, [] {
        struct sigaction sa {};
        sa.sa_sigaction = &on_crash_signal;
        sa.sa_flags = SA_SIGINFO | SA_ONSTACK;
        sigemptyset(&sa.sa_mask);
        for (int sig : kCrashSignals) sigaction(sig, &sa, &g_previous_action[sig]);
    });
}

// Runs `body` with crash containment; returns the signal that stopped it, or 0.
template <typename Body>
[[gnu::noinline]] int run_contained(sigjmp_buf& mark, const sigset_t& normal_mask, Body& body) {
    if (const int signo = sigsetjmp(mark, 0); signo != 0) {
        pthread_sigmask(SIG_SETMASK, &normal_mask, nullptr);
        return signo;
    }
    sigjmp_buf* const outer = t_crash_mark;
    t_crash_mark = &mark;
    body();
    t_crash_mark = outer;
    return 0;
}

// An SVAR transfer under the table lock: timing-failure handlers are held off
// until it is released (docs/architecture.md §10), so an aborted cycle never
// leaves the lock held.
template <typename Copy>
svar::Status guarded(Copy&& copy) noexcept {
    muf::enter_critical();
    const svar::Status st = copy();
    muf::leave_critical();
    return st;
}

// The module methods, as the callables TaskLoop::call takes.
constexpr auto kInit = [](Module& m, Task& t) { return m.init(t); };
constexpr auto kReinit = [](Module& m, Task& t) { return m.reinit(t); };
constexpr auto kOn = [](Module& m, Task& t) { return m.on(t); };
constexpr auto kCycle = [](Module& m, Task& t) { return m.cycle(t); };
constexpr auto kOff = [](Module& m, Task& t) { return m.off(t); };
constexpr auto kKill = [](Module& m, Task& t) { return m.kill(t); };
constexpr auto kSync = [](Module& m, Task& t) { return m.sync(t); };
constexpr auto kSet = [](Module& m, Task& t) { return m.set(t); };
constexpr auto kGet = [](Module& m, Task& t) { return m.get(t); };

// The states a request is valid in (Figure 3.10); set, get and freq in any.
bool valid_in(CmdKind k, State s) noexcept {
    switch (k) {
        case CmdKind::on: return s == State::OFF;
        case CmdKind::off: return s == State::ON;
        case CmdKind::kill: return s != State::NOT_CREATED;
        case CmdKind::clear: return s == State::ERROR;
        case CmdKind::reinit: return s != State::NOT_CREATED && s != State::ERROR;
        default: return true;
    }
}

const char* request_name(CmdKind k) noexcept {
    switch (k) {
        case CmdKind::on: return "on";
        case CmdKind::off: return "off";
        case CmdKind::kill: return "kill";
        case CmdKind::clear: return "clear";
        case CmdKind::reinit: return "reinit";
        case CmdKind::set: return "set";
        case CmdKind::get: return "get";
        case CmdKind::freq: return "freq";
        case CmdKind::none: break;
    }
    return "?";
}

// One request from the master, copied out of the mailbox.
struct Request {
    CmdKind kind = CmdKind::none;
    std::string key;
    double hz = 0;
};

// What the request came to: "" or the failure, and get's reply.
struct Answer {
    std::string result, reply;
};

class TaskLoop {
public:
    TaskLoop(TaskCore& task, const sigset_t& normal_mask);
    void run();

private:
    // ---- states and transitions of Figure 3.10 ----
    bool spawn();                 // NOT-CREATED -> OFF: in-consts, init, out-consts
    void serve(const Request& q);  // a request from the master, in any state
    void answer(Answer& a);
    Answer on();                  // OFF -> ON: in-vars and out-vars, on, out-vars, join the scheduler
    Answer off();                 // ON -> OFF
    Answer kill();                // OFF (ON: off first) -> NOT-CREATED
    Answer clear();               // ERROR -> OFF
    Answer reinit();              // in-consts, reinit; the state stays
    Answer set(const std::string& key);
    Answer get(const std::string& key);
    Answer freq(double hz);
    void run_on_state(std::uint32_t seen);  // ON: wait for the release (or event), then one job
    void periodic_release(std::uint32_t seen);
    void synchronous_release();
    void aperiodic_release(std::uint32_t seen);
    // Sleeps until the request word moves from `seen` (returns at once when it has).
    void wait_for_request(std::uint32_t seen) noexcept {
        ipc::futex_wait(t_.word, seen, -1, ipc::FutexScope::process);
    }

    // ---- the steps of one job and of off ----
    void job();                   // read in-vars, cycle, write out-vars
    Outcome read_in_vars();
    bool cycle(Outcome& r);       // false when a timing-failure handler aborted it
    Outcome write_out_vars();
    void after_job(Outcome r, bool aborted);
    Outcome turn_off();           // off, out-vars
    void settle(Outcome r);       // an error outcome moves the state
    void enter_error();

    // ---- method calls and error routing (§3.6) ----
    template <typename Fn> Outcome call(Phase p, std::size_t i, Fn&& fn);
    template <typename Fn> Outcome call_all(Phase p, Fn&& fn);
    Outcome crashed(Phase p, std::size_t i, int signo);
    Outcome take_abort();
    Outcome route(const err::Error& e);
    err::Outcome handle(const err::Error& e);
    void record(const err::Error& e);
    Outcome transfer(svar::Status st, const char* what);
    svar::Status copy_in(const svar::VarSet& set);
    svar::Status copy_out(const svar::VarSet& set);

    // The two seams to the master: an error line and a signal. Every report
    // and every signal of the loop goes through one of them.
    void report_error(std::string_view object, std::string_view message, const char* phase = nullptr, int code = 0);
    void post(int signal) noexcept { t_.sbs.post_signal(t_, signal); }
    static void print_line(void* loop, std::string_view line) noexcept {
        TaskCore& t = static_cast<TaskLoop*>(loop)->t_;
        t.sbs.print(t.rtpu, true, {line});
    }

    TaskCore& t_;
    const sigset_t& normal_mask_;
    unsigned in_var_bytes_ = 0, out_var_bytes_ = 0;  // for the svar_copy tracepoint
    Phase phase_ = Phase::init;
    std::size_t current_ = 0;           // the object whose method runs
    std::optional<Outcome> decided_;    // set by the task's error handler before it aborts
    err::Abort abort_;                  // an abort taken from the thread's slot, while error() runs
    // The last error, kept in place: the error path of a cycle allocates nothing.
    FixedText<64> err_module_;
    FixedText<1024> err_message_;
    FixedText<1024> failure_;  // the message of a failure the loop words itself
    int err_code_ = 0;
    std::uint64_t missed_ = 0;
    bool alive_ = true;
};

TaskLoop::TaskLoop(TaskCore& task, const sigset_t& normal_mask) : t_(task), normal_mask_(normal_mask) {
    auto bytes_of = [&](const std::vector<std::string>& names) {
        std::uint64_t n = 0;
        for (const auto& v : names) n += t_.sbs.table.var(t_.sbs.table.index_of(v)).bytes();
        return static_cast<unsigned>(n);
    };
    in_var_bytes_ = bytes_of(t_.in_vars);
    out_var_bytes_ = bytes_of(t_.out_vars);
}

// Figure 3.10: spawn, then OFF / ON / ERROR until kill. A request is served
// between jobs, whatever the state; ON runs jobs; OFF and ERROR sleep.
void TaskLoop::run() {
    err::HandlerScope task_handler([this](const err::Error& e) { return handle(e); });
    // The default handler (an error raised inside a handler) prints through the report ring.
    err::set_thread_printer(&TaskLoop::print_line, this);
    struct PrinterReset {
        ~PrinterReset() { err::set_thread_printer(nullptr, nullptr); }
    } printer_reset;
    if (!spawn()) return;
    while (alive_) {
        const std::uint32_t seen = t_.word.load(std::memory_order_acquire);
        if (t_.cmd_pending.load(std::memory_order_acquire)) {
            std::unique_lock<ipc::PiMutex> lock(t_.cmd_mu);
            const Request q{t_.cmd, t_.cmd_key, t_.cmd_hz};
            t_.arg = t_.cmd_arg;
            lock.unlock();
            serve(q);
        } else if (t_.state.load(std::memory_order_relaxed) == State::ON) {
            run_on_state(seen);
        } else {
            wait_for_request(seen);
        }
    }
}

bool TaskLoop::spawn() {
    t_.next_state.store(State::OFF);
    Outcome o = transfer(copy_in(t_.set_in_consts), "in-consts");
    if (o == Outcome::ok) o = call_all(Phase::init, kInit);
    if (o == Outcome::ok)
        o = transfer(copy_out(t_.set_out_consts), "out-consts");
    else if (o == Outcome::off)
        o = route(err::Error{err::code::method_failed, t_.objects[current_].rmod.module, "init() returned OFF",
                             nullptr, 0});
    std::string failure;
    if (o != Outcome::ok) {
        // No recovery for init (§4.5.2): kill frees what init allocated; NOT-CREATED.
        failure = "init failed: " + std::string(err_message_.view()) + "; kill() called, the task is NOT-CREATED";
        for (std::size_t i = 0; i < t_.objects.size(); ++i) call(Phase::kill, i, kKill);
        t_.set_state(State::NOT_CREATED);
    } else {
        t_.set_state(State::OFF);
    }
    {
        std::lock_guard<ipc::PiMutex> lock(t_.cmd_mu);
        t_.start_failed = o != Outcome::ok;
        t_.start_error = std::move(failure);
        t_.started = true;
    }
    t_.tell_master();
    return o == Outcome::ok;
}

void TaskLoop::serve(const Request& q) {
    Answer a;
    const State s = t_.state.load();
    if (!valid_in(q.kind, s)) {
        a.result = "refused: " + std::string(request_name(q.kind)) + " is not valid in state " + std::string(to_string(s));
        answer(a);
        return;
    }
    switch (q.kind) {
        case CmdKind::on: a = on(); break;
        case CmdKind::off: a = off(); break;
        case CmdKind::kill: a = kill(); break;
        case CmdKind::clear: a = clear(); break;
        case CmdKind::reinit: a = reinit(); break;
        case CmdKind::set: a = set(q.key); break;
        case CmdKind::get: a = get(q.key); break;
        case CmdKind::freq: a = freq(q.hz); break;
        case CmdKind::none: break;
    }
    answer(a);
}

// Hands the answer to the master waiting in request().
void TaskLoop::answer(Answer& a) {
    t_.arg.clear();
    {
        std::lock_guard<ipc::PiMutex> lock(t_.cmd_mu);
        t_.cmd_result = std::move(a.result);
        t_.cmd_reply = std::move(a.reply);
        t_.cmd = CmdKind::none;
        t_.cmd_done = true;
        t_.cmd_pending.store(false, std::memory_order_release);
    }
    t_.tell_master();
}

Answer TaskLoop::on() {
    Answer a;
    t_.next_state.store(State::ON);
    Outcome r = transfer(copy_in(t_.set_on), "in-vars and out-vars");
    if (r == Outcome::ok) r = call_all(Phase::on, kOn);
    if (r == Outcome::ok) r = transfer(copy_out(t_.set_out_vars), "out-vars");
    if (r == Outcome::off) {
        t_.next_state.store(State::OFF);
        a.result = "on() returned OFF: the task stays OFF";
        return a;
    }
    if (r != Outcome::ok) {
        settle(r);
        a.result = "error in on(): " + std::string(err_message_.view()) +
                   (r == Outcome::error_halt ? "; the task is in ERROR" : "; error() returned OFF");
        return a;
    }
    // Join the RTPU's scheduler (admission on the deadline backend); the first
    // release is the next instant of the RTPU's timeline.
    try {
        t_.pacer->start();
    } catch (const std::exception& e) {
        a.result = std::string("refused by the scheduler: ") + e.what();
        const Outcome f = turn_off();  // undo on()
        if (ok_or_off(f)) t_.next_state.store(State::OFF);
        else settle(f);
        return a;
    }
    t_.publish_policy(t_.pacer->policy());
    if (const int c = t_.pacer->crit(); c != 0) {
        t_.crit.store(c);
        if (t_.slot.valid()) t_.slot.set_crit(c);
    }
    t_.cycles.store(0);
    t_.misses.store(0);
    t_.warnings.store(0);
    t_.max_cycle_ns.store(0);
    missed_ = 0;
    t_.on_since_ns.store(ipc::now_ns());
    if (t_.profiler) t_.profiler->start();  // profiling restarts on the RTPU (§6.7)
    t_.set_state(State::ON);
    t_.sbs.refresh_error_flag();  // it may read what a peer in ERROR produced
    return a;
}

Answer TaskLoop::off() {
    Answer a;
    const Outcome r = turn_off();
    if (ok_or_off(r)) {
        t_.set_state(State::OFF);
        t_.sbs.refresh_error_flag();  // it may have been the last reader of a peer in ERROR
    } else {
        settle(r);
        a.result = "error in off(): " + std::string(err_message_.view());
    }
    return a;
}

Answer TaskLoop::kill() {
    Answer a;
    if (t_.state.load() == State::ON) {
        if (!ok_or_off(turn_off())) a.result = "error in off(): " + std::string(err_message_.view()) + "; ";
        t_.set_state(State::OFF);  // kill runs from OFF (Figure 3.10)
    }
    t_.next_state.store(State::NOT_CREATED);
    bool failed = false;
    for (std::size_t i = 0; i < t_.objects.size(); ++i)
        if (call(Phase::kill, i, kKill) != Outcome::ok) failed = true;
    if (failed) a.result += "error in kill(): " + std::string(err_message_.view());
    t_.set_state(State::NOT_CREATED);
    t_.sbs.refresh_error_flag();
    alive_ = false;
    return a;
}

Answer TaskLoop::clear() {
    Answer a;
    t_.next_state.store(State::OFF);
    const err::Error e{err_code_, err_module_.view(), err_message_.view(), nullptr, 0};
    bool still = false;
    for (std::size_t i = 0; i < t_.objects.size() && !still; ++i) {
        phase_ = Phase::clear;
        current_ = i;
        Result r = Result::ERROR;
        try {
            r = t_.objects[i].module->clear(*t_.objects[i].view, e);
        } catch (...) {
            r = Result::ERROR;
        }
        if (r != Result::OFF) still = true;
    }
    if (still) {
        t_.next_state.store(State::ERROR);
        a.result = "clear() returned ERROR: the task stays in ERROR";
    } else {
        t_.set_state(State::OFF);
        if (t_.slot.valid()) t_.slot.clear_error();
        std::lock_guard<ipc::PiMutex> ml(t_.msg_mu);
        t_.error_text.clear();
        t_.error_module.clear();
        t_.error_code = 0;
    }
    t_.sbs.refresh_error_flag();
    return a;
}

Answer TaskLoop::reinit() {
    Answer a;
    t_.next_state.store(t_.state.load());
    Outcome r = transfer(copy_in(t_.set_in_consts), "in-consts");
    if (r == Outcome::ok) r = call_all(Phase::reinit, kReinit);
    if (!ok_or_off(r)) {
        settle(r);
        a.result = "error in reinit(): " + std::string(err_message_.view());
    }
    return a;
}

// set KEY VALUE...: to the objects that declare KEY in LOCAL, else to the first.
Answer TaskLoop::set(const std::string& key) {
    Answer a;
    bool any = false;
    for (auto& ob : t_.objects)
        if (ob.rmod.local.has(key)) any = true;
    const std::vector<std::string> values = cfg::split_words(t_.arg);
    t_.arg = key + " " + t_.arg;
    for (std::size_t i = 0; i < t_.objects.size(); ++i) {
        if (any && !t_.objects[i].rmod.local.has(key)) continue;
        LocalConfig& local = t_.objects[i].rmod.local;
        std::optional<LocalConfig::Entry> before;
        if (const LocalConfig::Entry* e = local.find(key)) before = *e;
        local.set(key, values);
        if (call(Phase::set, i, kSet) != Outcome::ok) {
            // Refused: LOCAL keeps what the module runs with.
            if (before) local.set(key, before->values, before->line);
            else local.erase(key);
            a.result = "set " + key + ": " + std::string(err_message_.view());
            break;
        }
        if (!any) break;
    }
    return a;
}

Answer TaskLoop::get(const std::string& key) {
    Answer a;
    t_.arg = key;
    t_.reply_set = false;
    t_.reply.clear();
    bool known = false;
    for (std::size_t i = 0; i < t_.objects.size(); ++i) {
        if (auto text = t_.objects[i].rmod.local.text(key); text && !t_.reply_set) {
            t_.reply = *text;
            known = true;
        }
        if (call(Phase::get, i, kGet) != Outcome::ok) {
            a.result = "get " + key + ": " + std::string(err_message_.view());
            break;
        }
        if (t_.reply_set) known = true;
    }
    if (a.result.empty() && !known) a.result = "task " + t_.name + " has no LOCAL key " + key;
    a.reply = t_.reply;
    return a;
}

Answer TaskLoop::freq(double hz) {
    Answer a;
    const auto p = static_cast<std::int64_t>(std::llround(1e9 / hz));
    try {
        t_.pacer->set_period(p);  // from the next release
    } catch (const std::exception& e) {
        a.result = std::string("the scheduler refused the new period: ") + e.what();
        return a;
    }
    t_.period_ns.store(p);
    for (auto& ob : t_.objects) {
        ob.rmod.freq = hz;
        ob.rmod.period = 1.0 / hz;
    }
    const bool running = t_.pacer->running();
    const int c = running && t_.pacer->crit() != 0 ? t_.pacer->crit() : crit_for(t_.rtpu, t_.type, hz);
    t_.crit.store(c);
    if (t_.slot.valid()) {
        t_.slot.set_ref_freq(hz);
        t_.slot.set_crit(c);
    }
    if (running) t_.publish_policy(t_.pacer->policy());
    return a;
}

// `seen`: the request word read before the mailbox was found empty.
void TaskLoop::run_on_state(std::uint32_t seen) {
    switch (t_.type) {
        case TaskType::periodic: periodic_release(seen); break;
        case TaskType::synchronous: synchronous_release(); break;
        case TaskType::sporadic:
        case TaskType::deferrable:
        case TaskType::background: aperiodic_release(seen); break;
    }
}

// Sleeps until the next release (or a request), then runs the job.
void TaskLoop::periodic_release(std::uint32_t seen) {
    if (!t_.pacer->wait(t_.word, seen, missed_)) {  // a request came in
        wait_for_request(seen);                     // (returns at once when it did)
        return;
    }
    if (const std::uint64_t before = t_.misses.load(std::memory_order_relaxed); missed_ != before) {
        if (t_.profiler) t_.profiler->missed(static_cast<std::uint32_t>(missed_ - before));
        t_.misses.store(missed_, std::memory_order_relaxed);
    }
    job();
}

// sync() blocks until the external event; the job follows at once.
void TaskLoop::synchronous_release() {
    const Outcome r = call_all(Phase::sync, kSync);
    if (r == Outcome::ok) job();
    else if (r != Outcome::off) settle(r);  // OFF: sync gave up waiting (a request is pending)
}

// Sporadic, deferrable and background tasks: one job per event.
void TaskLoop::aperiodic_release(std::uint32_t seen) {
    if (t_.events.load(std::memory_order_acquire) == 0) {
        wait_for_request(seen);
        return;
    }
    t_.events.fetch_sub(1, std::memory_order_acq_rel);
    t_.pacer->event_begin();
    job();
    t_.pacer->event_end();
}

// One job of Figure 3.10's ON state: read in-vars, cycle, write out-vars.
void TaskLoop::job() {
    if (t_.profiler) t_.profiler->cycle_begin(t_.pacer->release_ns());
    const std::int64_t t0 = ipc::now_ns();
    t_.last_release_ns.store(t0, std::memory_order_relaxed);
    Outcome r = read_in_vars();
    bool aborted = false;
    if (r == Outcome::ok) aborted = !cycle(r);
    // An aborted cycle publishes nothing: its outputs are half-made.
    if (!aborted && ok_or_off(r)) {
        const Outcome w = write_out_vars();
        t_.cycles.fetch_add(1, std::memory_order_relaxed);
        if (w != Outcome::ok) r = w;
    }
    t_.pacer->cycle_done();
    const std::int64_t dt = ipc::now_ns() - t0;
    if (dt > t_.max_cycle_ns.load(std::memory_order_relaxed)) t_.max_cycle_ns.store(dt, std::memory_order_relaxed);
    if (t_.profiler) t_.profiler->cycle_end();
    after_job(r, aborted);
}

Outcome TaskLoop::read_in_vars() {
    const Outcome r = transfer(copy_in(t_.set_in_vars), "in-vars");
    CHIMERA_TRACE_SVAR_COPY(t_.name.c_str(), 0, static_cast<std::uint32_t>(t_.set_in_vars.size()), in_var_bytes_);
    return r;
}

bool TaskLoop::cycle(Outcome& r) {
    auto cycle_all = [&] { r = call_all(Phase::cycle, kCycle); };
    bool completed = true;
    if (sigjmp_buf* mark = t_.pacer->cycle_mark()) completed = run_abortable(*t_.pacer, *mark, normal_mask_, cycle_all);
    else cycle_all();
    t_crash_mark = nullptr;  // an aborted cycle jumped past its containment frame
    return completed;
}

Outcome TaskLoop::write_out_vars() {
    const Outcome r = transfer(copy_out(t_.set_out_vars), "out-vars");
    CHIMERA_TRACE_SVAR_COPY(t_.name.c_str(), 1, static_cast<std::uint32_t>(t_.set_out_vars.size()), out_var_bytes_);
    return r;
}

// After the job: a criticality a handler moved, then the state the job leads to.
void TaskLoop::after_job(Outcome r, bool aborted) {
    if (const int c = t_.pacer->crit(); c != 0 && c != t_.crit.load(std::memory_order_relaxed)) {
        t_.crit.store(c, std::memory_order_relaxed);  // a handler moved it (soft task, server)
        if (t_.slot.valid()) t_.slot.set_crit(c);
    }
    if (aborted) return;
    if (r != Outcome::off) {
        settle(r);
        return;
    }
    // Goal reached: the task turns itself off and tells the master.
    const Outcome f = turn_off();
    if (ok_or_off(f)) {
        t_.set_state(State::OFF);
        post(sig::OFF);
    } else {
        settle(f);
    }
}

Outcome TaskLoop::turn_off() {
    t_.next_state.store(State::OFF);
    Outcome r = call_all(Phase::off, kOff);
    if (ok_or_off(r)) r = transfer(copy_out(t_.set_out_vars), "out-vars");
    return r;
}

void TaskLoop::settle(Outcome r) {
    if (r == Outcome::error_off) {
        t_.set_state(State::OFF);
        t_.next_state.store(State::OFF);
    } else if (r == Outcome::error_halt) {
        enter_error();
    }
}

void TaskLoop::enter_error() {
    if (t_.slot.valid()) t_.slot.error(err_message_.view());
    t_.set_state(State::ERROR);
    t_.next_state.store(State::ERROR);
    t_.sbs.refresh_error_flag();
    post(sig::ERROR);
}

// Calls one method of object `i` and turns every kind of failure into an outcome.
template <typename Fn>
Outcome TaskLoop::call(Phase p, std::size_t i, Fn&& fn) {
    phase_ = p;
    current_ = i;
    decided_.reset();
    Result r = Result::OK;
    bool threw = false;
    try {
        auto method = [&] { r = fn(*t_.objects[i].module, *t_.objects[i].view); };
        sigjmp_buf crash_mark;
        if (const int signo = run_contained(crash_mark, normal_mask_, method); signo != 0) return crashed(p, i, signo);
    } catch (const std::exception& ex) {
        threw = true;
        failure_.assign({"exception: ", ex.what()});
    } catch (...) {
        threw = true;
        failure_.assign("unknown exception");
    }
    // An errInvoke that aborted the method comes first: it is the cause, and
    // what the method returned (or threw) after it does not count.
    if (err::pending()) return take_abort();
    if (threw) return route(err::Error{err::code::exception, t_.objects[i].rmod.module, failure_.view(), nullptr, 0});
    switch (r) {
        case Result::OK:
        case Result::CONTINUE: return Outcome::ok;
        case Result::OFF: return Outcome::off;
        case Result::ERROR:
            failure_.assign({phase_name(p), "() returned ERROR"});
            return route(err::Error{err::code::method_failed, t_.objects[i].rmod.module, failure_.view(), nullptr, 0});
    }
    return Outcome::error_halt;
}

// The method returned after an errInvoke aborted it (err.hpp: invoke() records
// the abort and returns false; nothing is thrown). The task's own handler has
// already routed it (decided_); an abort by a module's handler, or by the
// default handler for an error raised inside a handler, goes to error() now.
Outcome TaskLoop::take_abort() {
    if (decided_) {
        err::clear_pending();
        return *decided_;
    }
    abort_ = *err::pending();  // copied: error() may raise errors of its own
    err::clear_pending();
    const Outcome o = route(abort_.error());
    err::clear_pending();
    return o;
}

// Runs a method over every object in order; stops at the first non-ok.
template <typename Fn>
Outcome TaskLoop::call_all(Phase p, Fn&& fn) {
    for (std::size_t i = 0; i < t_.objects.size(); ++i) {
        const Outcome o = call(p, i, fn);
        if (o != Outcome::ok) return o;
    }
    return Outcome::ok;
}

// The module's state is unknown after a crash: error() is not called, the task halts.
Outcome TaskLoop::crashed(Phase p, std::size_t i, int signo) {
    t_.pacer->disarm_abort();
    err::clear_pending();
    failure_.assign({"crashed with ", sigabbrev_np(signo), " (", sigdescr_np(signo), ") in ", phase_name(p), "()"});
    record(err::Error{err::code::exception, t_.objects[i].rmod.module, failure_.view(), nullptr, 0});
    report_error(t_.objects[i].rmod.name, failure_.view());
    return Outcome::error_halt;
}

// error() of the current object; its answer mapped to an outcome.
Outcome TaskLoop::route(const err::Error& e) {
    // Error handling allocates and calls error(): a cycle that failed is
    // no longer abandoned by a timing-failure handler.
    t_.pacer->disarm_abort();
    record(e);
    report_error(t_.objects[current_].rmod.name, e.message, phase_name(phase_), e.code);
    if (!routes_to_error(phase_)) return Outcome::error_halt;
    Object& o = t_.objects[current_];
    Result r = Result::ERROR;
    try {
        r = o.module->error(*o.view, e);
    } catch (...) {
        r = Result::ERROR;
    }
    switch (r) {
        case Result::OK:
        case Result::CONTINUE: return Outcome::ok;
        case Result::OFF: return Outcome::error_off;
        case Result::ERROR: return Outcome::error_halt;
    }
    return Outcome::error_halt;
}

// The task's own handler, at the bottom of its error chain (errInvoke from a method).
err::Outcome TaskLoop::handle(const err::Error& e) {
    const Outcome o = route(e);
    if (o == Outcome::ok) return err::Outcome::resume();  // CONTINUE: after the errInvoke
    decided_ = o;
    return err::Outcome::abort();
}

void TaskLoop::record(const err::Error& e) {
    err_code_ = e.code;
    err_module_.assign(e.module);
    err_message_.assign(e.message);
    std::lock_guard<ipc::PiMutex> lock(t_.msg_mu);
    const std::size_t n = std::min(e.message.size(), sizeof(t_.last_msg) - 1);
    std::memcpy(t_.last_msg, e.message.data(), n);
    t_.last_msg[n] = '\0';
    t_.last_num.store(e.code);
    t_.error_code = e.code;
    t_.error_module.assign(err_module_.view());
    t_.error_text.assign(err_message_.view());
}

void TaskLoop::report_error(std::string_view object, std::string_view message, const char* phase, int code) {
    if (!phase) {
        t_.sbs.print(t_.rtpu, true, {"ERROR> ", object, ": ", message});
        return;
    }
    char num[16];
    const auto [end, ec] = std::to_chars(num, num + sizeof num, code);
    t_.sbs.print(t_.rtpu, true,
                 {"ERROR> ", object, ": ", message, " (code ", std::string_view(num, end - num), ", in ", phase, ")"});
}

Outcome TaskLoop::transfer(svar::Status st, const char* what) {
    if (svar::transferred(st)) return Outcome::ok;
    current_ = 0;
    failure_.assign({"state variable transfer of ", what, " failed: ", svar::to_string(st)});
    return route(err::Error{err::code::timeout, "svar", failure_.view(), nullptr, 0});
}

svar::Status TaskLoop::copy_in(const svar::VarSet& set) {
    return guarded([&] { return t_.local->copy_from_global(set); });
}
svar::Status TaskLoop::copy_out(const svar::VarSet& set) {
    return guarded([&] { return t_.local->copy_to_global(set); });
}

}  // namespace

// The thread: its own signal set-up and profiler, then the state machine until kill.
void TaskCore::run() {
    tid.store(static_cast<long>(::syscall(SYS_gettid)));
    // The crash handler's own stack (a module's stack overflow must still be caught).
    std::vector<char> crash_stack(std::max<std::size_t>(64 * 1024, static_cast<std::size_t>(SIGSTKSZ)));
    stack_t alt{};
    alt.ss_sp = crash_stack.data();
    alt.ss_size = crash_stack.size();
    sigaltstack(&alt, nullptr);
    install_crash_handlers();
    sigset_t normal_mask;  // restored after a jump out of a signal handler (see run_abortable)
    pthread_sigmask(SIG_SETMASK, nullptr, &normal_mask);
    struct AltStackOff {
        ~AltStackOff() {
            stack_t off{};
            off.ss_flags = SS_DISABLE;
            sigaltstack(&off, nullptr);
        }
    } alt_stack_off;
    pthread_setname_np(pthread_self(), name.substr(0, 15).c_str());
    try {
        publish_policy(std::string(pacer->idle()));
    } catch (const std::exception& e) {
        publish_policy(std::string("unknown (") + e.what() + ")");
    }
    struct StopAtExit {
        TaskCore& t;
        ~StopAtExit() { t.stop_running(); }
    } stop_at_exit{*this};

    // The profiler opens the thread's own CPU-time counter, so it is made here.
    std::optional<prof::TaskProfiler> task_profiler;
    if (slot.valid()) {
        try {
            task_profiler.emplace(slot);
            profiler = &*task_profiler;
        } catch (const std::exception& e) {
            std::fprintf(stderr, "chimera: task %s runs unprofiled: %s\n", name.c_str(), e.what());
        }
        slot.set_tid(static_cast<int>(tid.load()));
        std::lock_guard<ipc::PiMutex> lock(msg_mu);
        slot.set_policy(policy.view());
    }
    struct ProfilerDetach {
        prof::TaskProfiler*& p;
        ~ProfilerDetach() { p = nullptr; }
    } profiler_detach{profiler};

    TaskLoop(*this, normal_mask).run();
}

}  // namespace chimera::sbs::detail
