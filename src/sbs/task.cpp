// The task runtime: one pthread per task running the state machine of
// Figure 3.10 with the SVAR transfers around each method (§3.5, §3.6).
#include "internal.hpp"

#include "chimera/ipc/clock.hpp"
#include "chimera/muf/rt.hpp"
#include "chimera/ipc/futex.hpp"
#include "chimera/trace.hpp"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <mutex>
#include <optional>
#include <sched.h>
#include <set>
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

std::string join_names(const std::vector<std::string>& v, const char* sep) {
    std::string s;
    for (std::size_t i = 0; i < v.size(); ++i) {
        if (i) s += sep;
        s += v[i];
    }
    return s;
}

void add_unique(std::vector<std::string>& v, const std::string& s) {
    if (std::find(v.begin(), v.end(), s) == v.end()) v.push_back(s);
}

// Criticality from frequency, scaled logarithmically between the RTPU's
// MINFREQ and MAXFREQ onto 1..62 (0 and 63 reserved, §4.5.1).
int crit_for(const RtpuSpec& r, TaskType type, double freq) {
    if (type == TaskType::background || freq <= 0) return 1;
    if (freq <= r.minfreq) return 1;
    if (freq > r.maxfreq) return 62;
    const double x = (std::log(freq) - std::log(r.minfreq)) / (std::log(r.maxfreq) - std::log(r.minfreq));
    return std::clamp(1 + static_cast<int>(std::lround(x * 61.0)), 1, 62);
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
thread_local sigjmp_buf* t_crash_mark = nullptr;
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
// until it is released (ARCHITECTURE §6), so an aborted cycle never leaves the
// lock held.
template <typename Copy>
svar::Status guarded(Copy&& copy) noexcept {
    muf::enter_critical();
    const svar::Status st = copy();
    muf::leave_critical();
    return st;
}

}  // namespace

// ------------------------------------------------------------------ TaskCore

TaskCore::TaskCore(SubsystemCore& s, int task_id, const RtpuSpec& r, std::vector<RmodFile> rmods)
    : sbs(s), id(task_id), rtpu(r) {
    if (rmods.empty()) throw Error("spawn: no .rmod given");
    std::vector<std::string> names;
    for (const auto& f : rmods) names.push_back(f.name);
    name = join_names(names, "+");
    type = rmods.front().type;
    const double freq = rmods.front().freq;
    for (const auto& f : rmods) {
        if (f.type != type || std::fabs(f.freq - freq) > 1e-9 * std::max(1.0, freq))
            throw Error("combined task " + name + ": " + f.name + " has TASKTYPE " + std::string(to_string(f.type)) +
                        " at " + std::to_string(f.freq) + " Hz, " + rmods.front().name + " has " +
                        std::string(to_string(type)) + " at " + std::to_string(freq) +
                        " Hz; combined objects must run at one rate (§3.8.1)");
    }
    period_ns.store(freq > 0 ? static_cast<std::int64_t>(std::llround(1e9 / freq)) : 0);
    crit.store(crit_for(rtpu, type, freq));

    // Every port must be a variable of the global table.
    for (const auto& f : rmods) {
        const std::pair<const char*, const std::vector<std::string>*> lists[] = {
            {"INCONST", &f.in_consts}, {"OUTCONST", &f.out_consts}, {"INVAR", &f.in_vars}, {"OUTVAR", &f.out_vars}};
        for (auto [kw, list] : lists) {
            for (const auto& port : *list) {
                const std::string g = f.global_name(port);
                if (!sbs.table.find(g))
                    throw Error(f.path + ": " + kw + " " + port + (g != port ? " (SVARALIAS " + g + ")" : "") +
                                " is not a variable of the state variable table " + sbs.file.svarfile);
            }
        }
    }

    // Combined objects: a variable produced by one and read by another stays
    // in the shared local table (§3.8.1).
    std::vector<std::string> all_in_vars, all_out_vars;
    for (const auto& f : rmods) {
        for (const auto& v : f.global_out_vars()) {
            if (std::find(all_out_vars.begin(), all_out_vars.end(), v) != all_out_vars.end())
                throw Error("combined task " + name + ": variable " + v + " is produced by two of its objects");
            all_out_vars.push_back(v);
        }
        for (const auto& v : f.global_in_vars()) add_unique(all_in_vars, v);
        for (const auto& v : f.global_in_consts()) add_unique(in_consts, v);
        for (const auto& v : f.global_out_consts()) add_unique(out_consts, v);
    }
    if (rmods.size() > 1) {
        for (const auto& v : all_out_vars)
            if (std::find(all_in_vars.begin(), all_in_vars.end(), v) != all_in_vars.end()) internal.push_back(v);
    }
    auto is_internal = [&](const std::string& v) {
        return std::find(internal.begin(), internal.end(), v) != internal.end();
    };
    for (const auto& v : all_in_vars)
        if (!is_internal(v)) in_vars.push_back(v);
    for (const auto& v : all_out_vars)
        if (!is_internal(v)) out_vars.push_back(v);

    std::vector<std::string> all;
    for (const auto* l : {&in_consts, &out_consts, &in_vars, &out_vars, &internal})
        for (const auto& v : *l) add_unique(all, v);
    try {
        local = std::make_unique<svar::LocalTable>(sbs.table, all);
        set_in_consts = local->make_set(in_consts);
        set_out_consts = local->make_set(out_consts);
        set_in_vars = local->make_set(in_vars);
        set_out_vars = local->make_set(out_vars);
        std::vector<std::string> on_names = in_vars;
        for (const auto& v : out_vars) add_unique(on_names, v);
        set_on = local->make_set(on_names);
    } catch (const svar::Error& e) {
        throw Error("task " + name + ": " + e.what());
    }

    // Load the modules and create one instance per object.
    std::vector<std::string> dirs = sbs.module_dirs;
    objects.reserve(rmods.size());
    try {
        for (auto& f : rmods) {
            const ChimeraModuleAbi& abi = load_module(f.module, module_search_dirs(f, dirs));
            Object o;
            o.abi = &abi;
            o.rmod = std::move(f);
            o.module = abi.create();
            if (!o.module) throw Error("module " + o.rmod.module + ": create() returned no object");
            objects.push_back(std::move(o));
            objects.back().view = std::make_unique<Task>(this, objects.size() - 1);
            // What chimcfg check refuses never starts: the same check, before init().
            check_local_section(objects.back().module->local_keys(), objects.back().rmod.module,
                                objects.back().rmod.local);
        }
    } catch (const cfg::ParseError& e) {
        for (auto& o : objects) o.abi->destroy(o.module);
        objects.clear();
        throw Error(std::string("spawn: ") + e.what());
    } catch (...) {
        for (auto& o : objects) o.abi->destroy(o.module);
        objects.clear();
        throw;
    }
    for (const auto& o : objects) abortable = abortable && o.module->abortable();
}

TaskCore::~TaskCore() {
    join();
    for (auto& o : objects)
        if (o.module) o.abi->destroy(o.module);
}

void TaskCore::join() noexcept {
    if (joinable) {
        pthread_join(thread, nullptr);
        joinable = false;
    }
    if (slot.valid() && state.load() == State::NOT_CREATED) {
        try {
            sbs.status.release(slot);  // the task is gone: chimtop stops showing it
        } catch (const std::exception& e) {
            std::fprintf(stderr, "chimera: task %s: releasing its status slot: %s\n", name.c_str(), e.what());
        }
    }
}

void* TaskCore::thread_main(void* self) noexcept {
    static_cast<TaskCore*>(self)->run();
    return nullptr;
}

namespace {
prof::TaskState prof_state(State s) noexcept {
    switch (s) {
        case State::NOT_CREATED: return prof::TaskState::not_created;
        case State::OFF: return prof::TaskState::off;
        case State::ON: return prof::TaskState::on;
        case State::ERROR: return prof::TaskState::error;
    }
    return prof::TaskState::not_created;
}
}  // namespace

void TaskCore::set_state(State s) noexcept {
    const State from = state.exchange(s);
    if (from != s) CHIMERA_TRACE_STATE_TRANSITION(name.c_str(), static_cast<int>(prof_state(from)),
                                                  static_cast<int>(prof_state(s)));
    if (slot.valid()) slot.set_state(prof_state(s));
    // Leaving ON (off, error, a cycle that turned the task off): no more releases.
    if (from == State::ON && s != State::ON) stop_running();
}

void TaskCore::start() {
    if (sbs.status.valid() && !slot.valid()) {
        prof::TaskIdentity who;
        who.rmod = name;
        who.rtpu = sbs.rtpu_index(rtpu);
        who.cpu = rtpu.cpu;
        who.type = static_cast<prof::TaskType>(status_letter(type));
        const std::int64_t p = period_ns.load();
        who.ref_freq = p > 0 ? 1e9 / static_cast<double>(p) : 0.0;
        who.crit = crit.load();
        const std::string inputs = join_names(in_vars, ","), outputs = join_names(out_vars, ",");
        who.inputs = inputs;
        who.outputs = outputs;
        slot = sbs.status.claim(who);  // throws StatusError when the segment is full: spawn fails cleanly
        slot.set_state(prof::TaskState::spawning);
    }
    if (!scheduler) throw Error("spawn " + name + ": no scheduler for RTPU " + rtpu.name);
    if (!pacer) pacer = make_rtpu_pacer(*this, *scheduler);
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    pthread_attr_setstacksize(&attr, 1u << 20);
    const int rc = pthread_create(&thread, &attr, &TaskCore::thread_main, this);
    pthread_attr_destroy(&attr);
    if (rc != 0) throw Error("spawn " + name + ": pthread_create failed: " + std::strerror(rc));
    joinable = true;
    std::unique_lock<std::mutex> lock(cmd_mu);
    cmd_cv.wait(lock, [&] { return started; });
    if (start_failed) {
        lock.unlock();
        join();
        throw Error("spawn " + name + ": " + start_error);
    }
}

std::string TaskCore::request(CmdKind kind, std::string a, std::string key, double hz, std::string* out) {
    std::unique_lock<std::mutex> lock(cmd_mu);
    cmd = kind;
    cmd_arg = std::move(a);
    cmd_key = std::move(key);
    cmd_hz = hz;
    cmd_done = false;
    cmd_result.clear();
    cmd_reply.clear();
    cmd_pending.store(true, std::memory_order_release);
    lock.unlock();
    word.fetch_add(1, std::memory_order_release);
    ipc::futex_wake_all(word);
    lock.lock();
    cmd_cv.wait(lock, [&] { return cmd_done; });
    if (out) *out = cmd_reply;
    return cmd_result;
}

void TaskCore::publish_policy(std::string text) noexcept {
    std::lock_guard<std::mutex> lock(msg_mu);
    policy = std::move(text);
    if (slot.valid()) slot.set_policy(policy);
}

void TaskCore::stop_running() noexcept {
    if (!pacer || !pacer->running()) return;
    pacer->stop();
    try {
        publish_policy(pacer->policy());
    } catch (const std::exception&) {
    }
}

// The thread: spawn, then the state machine until kill.
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
    {
        std::string tn = name.substr(0, 15);
        pthread_setname_np(pthread_self(), tn.c_str());
    }
    try {
        publish_policy(pacer->idle());
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
        std::lock_guard<std::mutex> lock(msg_mu);
        slot.set_policy(policy);
    }
    // Sizes for the svar_copy tracepoint, known once.
    auto bytes_of = [&](const std::vector<std::string>& names) {
        std::uint64_t n = 0;
        for (const auto& v : names) n += sbs.table.var(sbs.table.index_of(v)).bytes();
        return n;
    };
    [[maybe_unused]] const auto in_var_bytes = static_cast<unsigned>(bytes_of(in_vars));
    [[maybe_unused]] const auto out_var_bytes = static_cast<unsigned>(bytes_of(out_vars));
    struct ProfilerDetach {
        prof::TaskProfiler*& p;
        ~ProfilerDetach() { p = nullptr; }
    } profiler_detach{profiler};

    // ---- error routing: the task's own handler at the bottom of its chain ----
    Phase phase = Phase::init;
    std::size_t current = 0;
    std::optional<Outcome> decided;
    std::string err_owned_module, err_owned_message;
    int err_code = 0;

    auto record = [&](const err::Error& e) {
        err_code = e.code;
        err_owned_module = std::string(e.module);
        err_owned_message = std::string(e.message);
        std::lock_guard<std::mutex> lock(msg_mu);
        const std::size_t n = std::min(e.message.size(), sizeof(last_msg) - 1);
        std::memcpy(last_msg, e.message.data(), n);
        last_msg[n] = '\0';
        last_num.store(e.code);
        error_code = e.code;
        error_module = err_owned_module;
        error_text = err_owned_message;
    };
    // error() of the current object; its answer mapped to an outcome.
    auto route = [&](const err::Error& e) -> Outcome {
        // Error handling allocates and calls error(): a cycle that failed is
        // no longer abandoned by a timing-failure handler.
        pacer->disarm_abort();
        record(e);
        sbs.print(rtpu, true,
                  "ERROR> " + objects[current].rmod.name + ": " + std::string(e.message) + " (code " +
                      std::to_string(e.code) + ", in " + phase_name(phase) + ")");
        if (!routes_to_error(phase)) return Outcome::error_halt;
        Object& o = objects[current];
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
    };
    err::HandlerScope task_handler([&](const err::Error& e) -> err::Outcome {
        Outcome o = route(e);
        if (o == Outcome::ok) return err::Outcome::resume();  // CONTINUE: after the errInvoke
        decided = o;
        return err::Outcome::abort();
    });

    // Calls one method of object `i` and turns every kind of failure into an outcome.
    auto call = [&](Phase p, std::size_t i, auto&& fn) -> Outcome {
        phase = p;
        current = i;
        decided.reset();
        Result r = Result::OK;
        try {
            auto method = [&] { r = fn(*objects[i].module, *objects[i].view); };
            sigjmp_buf crash_mark;
            if (const int signo = run_contained(crash_mark, normal_mask, method); signo != 0) {
                // The module's state is unknown: error() is not called, the task halts.
                pacer->disarm_abort();
                const std::string msg = std::string("crashed with ") + sigabbrev_np(signo) + " (" +
                                        strsignal(signo) + ") in " + phase_name(p) + "()";
                record(err::Error{err::code::exception, objects[i].rmod.module, msg, nullptr, 0});
                sbs.print(rtpu, true, "ERROR> " + objects[i].rmod.name + ": " + msg);
                return Outcome::error_halt;
            }
        } catch (const err::Aborted& a) {
            if (decided) return *decided;
            return route(a.error());  // a user handler aborted: still the module's error()
        } catch (const std::exception& ex) {
            return route(err::Error{err::code::exception, objects[i].rmod.module,
                                    std::string("exception: ") + ex.what(), nullptr, 0});
        } catch (...) {
            return route(err::Error{err::code::exception, objects[i].rmod.module, "unknown exception", nullptr, 0});
        }
        switch (r) {
            case Result::OK:
            case Result::CONTINUE: return Outcome::ok;
            case Result::OFF: return Outcome::off;
            case Result::ERROR: {
                const std::string msg = std::string(phase_name(p)) + "() returned ERROR";
                return route(err::Error{err::code::method_failed, objects[i].rmod.module, msg, nullptr, 0});
            }
        }
        return Outcome::error_halt;
    };
    // Runs a method over every object in order; stops at the first non-ok.
    auto call_all = [&](Phase p, auto&& fn) -> Outcome {
        for (std::size_t i = 0; i < objects.size(); ++i) {
            Outcome o = call(p, i, fn);
            if (o != Outcome::ok) return o;
        }
        return Outcome::ok;
    };
    auto transfer = [&](svar::Status st, const char* what) -> Outcome {
        if (svar::transferred(st)) return Outcome::ok;
        current = 0;
        return route(err::Error{err::code::timeout, "svar",
                                std::string("state variable transfer of ") + what + " failed: " + svar::to_string(st),
                                nullptr, 0});
    };
    auto copy_in = [&](const svar::VarSet& set) { return guarded([&] { return local->copy_from_global(set); }); };
    auto copy_out = [&](const svar::VarSet& set) { return guarded([&] { return local->copy_to_global(set); }); };
    auto last_error = [&]() { return err::Error{err_code, err_owned_module, err_owned_message, nullptr, 0}; };

    auto enter_error = [&]() {
        if (slot.valid()) slot.error(err_owned_message);
        set_state(State::ERROR);
        next_state.store(State::ERROR);
        sbs.refresh_error_flag();
        sbs.post_signal(*this, sig::ERROR);
    };

    // ---- spawn: in-consts, init, out-consts (Figure 3.10) ----
    next_state.store(State::OFF);
    Outcome o = transfer(copy_in(set_in_consts), "in-consts");
    if (o == Outcome::ok) o = call_all(Phase::init, [](Module& m, Task& t) { return m.init(t); });
    if (o == Outcome::ok) o = transfer(copy_out(set_out_consts), "out-consts");
    else if (o == Outcome::off) o = route(err::Error{err::code::method_failed, objects[current].rmod.module,
                                                      "init() returned OFF", nullptr, 0});
    if (o != Outcome::ok) {
        // No recovery for init (§4.5.2): kill frees what init allocated; NOT-CREATED.
        const std::string why = err_owned_message;
        for (std::size_t i = 0; i < objects.size(); ++i) call(Phase::kill, i, [](Module& m, Task& t) { return m.kill(t); });
        set_state(State::NOT_CREATED);
        std::lock_guard<std::mutex> lock(cmd_mu);
        start_failed = true;
        start_error = "init failed: " + why + "; kill() called, the task is NOT-CREATED";
        started = true;
        cmd_cv.notify_all();
        return;
    }
    set_state(State::OFF);
    {
        std::lock_guard<std::mutex> lock(cmd_mu);
        started = true;
        cmd_cv.notify_all();
    }

    // ---- the state machine ----
    auto do_off_method = [&]() -> Outcome {  // off, out-vars
        next_state.store(State::OFF);
        Outcome r = call_all(Phase::off, [](Module& m, Task& t) { return m.off(t); });
        if (r == Outcome::ok || r == Outcome::off) r = transfer(copy_out(set_out_vars), "out-vars");
        return r;
    };
    auto apply_error_outcome = [&](Outcome r) {
        if (r == Outcome::error_off) {
            set_state(State::OFF);
            next_state.store(State::OFF);
        } else if (r == Outcome::error_halt) {
            enter_error();
        }
    };
    auto run_cycle = [&]() {
        if (profiler) profiler->cycle_begin();
        const std::int64_t t0 = ipc::now_ns();
        last_release_ns.store(t0, std::memory_order_relaxed);
        Outcome r = transfer(copy_in(set_in_vars), "in-vars");
        CHIMERA_TRACE_SVAR_COPY(name.c_str(), 0, static_cast<std::uint32_t>(set_in_vars.size()), in_var_bytes);
        bool aborted = false;
        if (r == Outcome::ok) {
            auto cycle_all = [&] { r = call_all(Phase::cycle, [](Module& m, Task& t) { return m.cycle(t); }); };
            if (sigjmp_buf* mark = pacer->cycle_mark())
                aborted = !run_abortable(*pacer, *mark, normal_mask, cycle_all);
            else
                cycle_all();
            t_crash_mark = nullptr;  // an aborted cycle jumped past its containment frame
        }
        // An aborted cycle publishes nothing: its outputs are half-made.
        if (!aborted && (r == Outcome::ok || r == Outcome::off)) {
            const Outcome w = transfer(copy_out(set_out_vars), "out-vars");
            CHIMERA_TRACE_SVAR_COPY(name.c_str(), 1, static_cast<std::uint32_t>(set_out_vars.size()), out_var_bytes);
            cycles.fetch_add(1, std::memory_order_relaxed);
            if (w != Outcome::ok) r = w;
        }
        pacer->cycle_done();
        const std::int64_t dt = ipc::now_ns() - t0;
        if (dt > max_cycle_ns.load(std::memory_order_relaxed)) max_cycle_ns.store(dt, std::memory_order_relaxed);
        if (profiler) profiler->cycle_end();
        if (const int c = pacer->crit(); c != 0 && c != crit.load(std::memory_order_relaxed)) {
            crit.store(c, std::memory_order_relaxed);  // a handler moved it (soft task, server)
            if (slot.valid()) slot.set_crit(c);
        }
        if (aborted) return;
        if (r == Outcome::off) {
            // Goal reached: the task turns itself off and tells the master.
            const Outcome f = do_off_method();
            if (f == Outcome::ok || f == Outcome::off) {
                set_state(State::OFF);
                sbs.post_signal(*this, sig::OFF);
            } else {
                apply_error_outcome(f);
            }
        } else {
            apply_error_outcome(r);
        }
    };

    bool alive = true;
    std::uint64_t missed = 0;
    while (alive) {
        const std::uint32_t seen = word.load(std::memory_order_acquire);
        if (cmd_pending.load(std::memory_order_acquire)) {
            std::unique_lock<std::mutex> lock(cmd_mu);
            const CmdKind k = cmd;
            arg = cmd_arg;
            const std::string key = cmd_key;
            const double hz = cmd_hz;
            lock.unlock();
            std::string result, rep;
            const State s = state.load();
            auto refuse = [&](const char* what) {
                result = "refused: " + std::string(what) + " is not valid in state " + std::string(to_string(s));
            };
            switch (k) {
                case CmdKind::on: {
                    if (s != State::OFF) {
                        refuse("on");
                        break;
                    }
                    next_state.store(State::ON);
                    Outcome r = transfer(copy_in(set_on), "in-vars and out-vars");
                    if (r == Outcome::ok) r = call_all(Phase::on, [](Module& m, Task& t) { return m.on(t); });
                    if (r == Outcome::ok) r = transfer(copy_out(set_out_vars), "out-vars");
                    std::string refused_by_scheduler;
                    if (r == Outcome::ok) {
                        // Join the RTPU's scheduler (admission on the deadline
                        // backend); the first release is one period from now.
                        try {
                            pacer->start();
                        } catch (const std::exception& e) {
                            refused_by_scheduler = e.what();
                        }
                        if (!refused_by_scheduler.empty()) {
                            const Outcome f = do_off_method();  // undo on()
                            if (f != Outcome::ok && f != Outcome::off) apply_error_outcome(f);
                            else next_state.store(State::OFF);
                            result = "refused by the scheduler: " + refused_by_scheduler;
                            break;
                        }
                        publish_policy(pacer->policy());
                        if (const int c = pacer->crit(); c != 0) {
                            crit.store(c);
                            if (slot.valid()) slot.set_crit(c);
                        }
                    }
                    if (r == Outcome::ok) {
                        cycles.store(0);
                        misses.store(0);
                        warnings.store(0);
                        max_cycle_ns.store(0);
                        missed = 0;
                        const std::int64_t now = ipc::now_ns();
                        on_since_ns.store(now);
                        if (profiler) profiler->start();  // profiling restarts on the RTPU (§6.7)
                        set_state(State::ON);
                    } else if (r == Outcome::off) {
                        next_state.store(State::OFF);
                        result = "on() returned OFF: the task stays OFF";
                    } else {
                        apply_error_outcome(r);
                        result = "error in on(): " + err_owned_message + (r == Outcome::error_halt
                                                                              ? "; the task is in ERROR"
                                                                              : "; error() returned OFF");
                    }
                    break;
                }
                case CmdKind::off: {
                    if (s != State::ON) {
                        refuse("off");
                        break;
                    }
                    Outcome r = do_off_method();
                    if (r == Outcome::ok || r == Outcome::off) {
                        set_state(State::OFF);
                    } else {
                        apply_error_outcome(r);
                        result = "error in off(): " + err_owned_message;
                    }
                    break;
                }
                case CmdKind::kill: {
                    if (s == State::NOT_CREATED) {
                        refuse("kill");
                        break;
                    }
                    if (s == State::ON) {
                        const Outcome r = do_off_method();
                        if (r != Outcome::ok && r != Outcome::off) result = "error in off(): " + err_owned_message + "; ";
                        set_state(State::OFF);  // kill runs from OFF (Figure 3.10)
                    }
                    next_state.store(State::NOT_CREATED);
                    bool failed = false;
                    for (std::size_t i = 0; i < objects.size(); ++i) {
                        if (call(Phase::kill, i, [](Module& m, Task& t) { return m.kill(t); }) != Outcome::ok)
                            failed = true;
                    }
                    if (failed) result += "error in kill(): " + err_owned_message;
                    set_state(State::NOT_CREATED);
                    sbs.refresh_error_flag();
                    alive = false;
                    break;
                }
                case CmdKind::clear: {
                    if (s != State::ERROR) {
                        refuse("clear");
                        break;
                    }
                    next_state.store(State::OFF);
                    const err::Error e = last_error();
                    bool still = false;
                    for (std::size_t i = 0; i < objects.size() && !still; ++i) {
                        phase = Phase::clear;
                        current = i;
                        Result r = Result::ERROR;
                        try {
                            r = objects[i].module->clear(*objects[i].view, e);
                        } catch (...) {
                            r = Result::ERROR;
                        }
                        if (r != Result::OFF) still = true;
                    }
                    if (still) {
                        next_state.store(State::ERROR);
                        result = "clear() returned ERROR: the task stays in ERROR";
                    } else {
                        set_state(State::OFF);
                        if (slot.valid()) slot.clear_error();
                        std::lock_guard<std::mutex> ml(msg_mu);
                        error_text.clear();
                        error_module.clear();
                        error_code = 0;
                    }
                    sbs.refresh_error_flag();
                    break;
                }
                case CmdKind::reinit: {
                    if (s == State::NOT_CREATED || s == State::ERROR) {
                        refuse("reinit");
                        break;
                    }
                    next_state.store(s);
                    Outcome r = transfer(copy_in(set_in_consts), "in-consts");
                    if (r == Outcome::ok) r = call_all(Phase::reinit, [](Module& m, Task& t) { return m.reinit(t); });
                    if (r != Outcome::ok && r != Outcome::off) {
                        apply_error_outcome(r);
                        result = "error in reinit(): " + err_owned_message;
                    }
                    break;
                }
                case CmdKind::set: {
                    bool any = false;
                    for (auto& ob : objects)
                        if (ob.rmod.local.has(key)) any = true;
                    std::vector<std::string> values;
                    {
                        std::string v = arg;
                        std::size_t i = 0;
                        while (i < v.size()) {
                            while (i < v.size() && (v[i] == ' ' || v[i] == '\t')) ++i;
                            std::size_t j = i;
                            while (j < v.size() && v[j] != ' ' && v[j] != '\t') ++j;
                            if (j > i) values.push_back(v.substr(i, j - i));
                            i = j;
                        }
                    }
                    arg = key + " " + arg;
                    for (std::size_t i = 0; i < objects.size(); ++i) {
                        if (any && !objects[i].rmod.local.has(key)) continue;
                        LocalConfig& local = objects[i].rmod.local;
                        std::optional<LocalConfig::Entry> before;
                        if (const LocalConfig::Entry* e = local.find(key)) before = *e;
                        local.set(key, values);
                        if (call(Phase::set, i, [](Module& m, Task& t) { return m.set(t); }) != Outcome::ok) {
                            // Refused: LOCAL keeps what the module runs with.
                            if (before) local.set(key, before->values, before->line);
                            else local.erase(key);
                            result = "set " + key + ": " + err_owned_message;
                            break;
                        }
                        if (!any) break;
                    }
                    break;
                }
                case CmdKind::get: {
                    arg = key;
                    reply_set = false;
                    reply.clear();
                    bool known = false;
                    for (std::size_t i = 0; i < objects.size(); ++i) {
                        if (auto t = objects[i].rmod.local.text(key); t && !reply_set) {
                            reply = *t;
                            known = true;
                        }
                        if (call(Phase::get, i, [](Module& m, Task& t) { return m.get(t); }) != Outcome::ok) {
                            result = "get " + key + ": " + err_owned_message;
                            break;
                        }
                        if (reply_set) known = true;
                    }
                    if (result.empty() && !known) result = "task " + name + " has no LOCAL key " + key;
                    rep = reply;
                    break;
                }
                case CmdKind::freq: {
                    const std::int64_t p = static_cast<std::int64_t>(std::llround(1e9 / hz));
                    try {
                        pacer->set_period(p);  // from the next release
                    } catch (const std::exception& e) {
                        result = std::string("the scheduler refused the new period: ") + e.what();
                        break;
                    }
                    period_ns.store(p);
                    for (auto& ob : objects) {
                        ob.rmod.freq = hz;
                        ob.rmod.period = 1.0 / hz;
                    }
                    const int c = pacer->running() && pacer->crit() != 0 ? pacer->crit() : crit_for(rtpu, type, hz);
                    crit.store(c);
                    if (slot.valid()) {
                        slot.set_ref_freq(hz);
                        slot.set_crit(c);
                    }
                    if (pacer->running()) publish_policy(pacer->policy());
                    break;
                }
                case CmdKind::none: break;
            }
            arg.clear();
            lock.lock();
            cmd_result = std::move(result);
            cmd_reply = std::move(rep);
            cmd = CmdKind::none;
            cmd_done = true;
            cmd_pending.store(false, std::memory_order_release);
            cmd_cv.notify_all();
            continue;
        }

        if (state.load(std::memory_order_relaxed) != State::ON) {
            ipc::futex_wait(word, seen);
            continue;
        }
        switch (type) {
            case TaskType::periodic: {
                if (!pacer->wait(word, seen, missed)) {  // a request came in
                    ipc::futex_wait(word, seen);  // (returns at once when it did)
                    continue;
                }
                if (const std::uint64_t before = misses.load(std::memory_order_relaxed); missed != before) {
                    if (profiler) profiler->missed(static_cast<std::uint32_t>(missed - before));
                    misses.store(missed, std::memory_order_relaxed);
                }
                run_cycle();
                break;
            }
            case TaskType::synchronous: {
                // sync() blocks until the external event; the cycle follows at once.
                Outcome r = call_all(Phase::sync, [](Module& m, Task& t) { return m.sync(t); });
                if (r == Outcome::ok) {
                    run_cycle();
                } else if (r == Outcome::off) {
                    continue;  // sync gave up waiting (e.g. a request is pending)
                } else {
                    apply_error_outcome(r);
                }
                break;
            }
            case TaskType::sporadic:
            case TaskType::deferrable:
            case TaskType::background: {
                std::uint32_t ev = events.load(std::memory_order_acquire);
                if (ev == 0) {
                    ipc::futex_wait(word, seen);
                    continue;
                }
                events.fetch_sub(1, std::memory_order_acq_rel);
                pacer->event_begin();
                run_cycle();
                pacer->event_end();
                break;
            }
        }
    }
}

}  // namespace chimera::sbs::detail

// ------------------------------------------------------------------ Task view

namespace chimera {

using sbs::detail::TaskCore;

std::string_view Task::rmod() const noexcept { return core_->objects[object_].rmod.name; }
std::string_view Task::module() const noexcept { return core_->objects[object_].rmod.module; }
std::string_view Task::rtpu() const noexcept { return core_->rtpu.name; }
TaskType Task::type() const noexcept { return core_->type; }
const LocalConfig& Task::local() const noexcept { return core_->objects[object_].rmod.local; }
const RmodFile& Task::rmod_file() const noexcept { return core_->objects[object_].rmod; }
State Task::state() const noexcept { return core_->state.load(std::memory_order_relaxed); }
State Task::next_state() const noexcept { return core_->next_state.load(std::memory_order_relaxed); }
int Task::crit() const noexcept { return core_->crit.load(std::memory_order_relaxed); }
std::uint64_t Task::cycle_count() const noexcept { return core_->cycles.load(std::memory_order_relaxed); }
std::uint32_t Task::warnings() const noexcept { return core_->warnings.load(std::memory_order_relaxed); }
double Task::freq() const noexcept {
    const std::int64_t p = core_->period_ns.load(std::memory_order_relaxed);
    return p > 0 ? 1e9 / static_cast<double>(p) : 0.0;
}
double Task::period() const noexcept {
    return static_cast<double>(core_->period_ns.load(std::memory_order_relaxed)) * 1e-9;
}
int Task::error_number() const noexcept { return core_->last_num.load(std::memory_order_relaxed); }
std::string_view Task::error_message() const noexcept { return core_->last_msg; }
std::string Task::global_name(std::string_view port) const { return core_->objects[object_].rmod.global_name(port); }
void* Task::local_table_ptr() const noexcept { return core_->local.get(); }
std::uint32_t Task::signals() const noexcept { return core_->signals_sent.load(std::memory_order_relaxed); }
std::uint32_t Task::signal_mask() const noexcept {
    return core_->own_sigmask.load() ? core_->sigmask.load() : core_->sbs.wide_mask.load();
}
void Task::send_signal(int signal) noexcept {
    muf::enter_critical();  // the signal queue's lock
    core_->sbs.post_signal(*core_, signal);
    muf::leave_critical();
}
std::string_view Task::arg() const noexcept { return core_->arg; }
void Task::reply(std::string text) {
    core_->reply = std::move(text);
    core_->reply_set = true;
}
bool Task::illegal_configuration() const noexcept { return core_->sbs.table.illegal_configuration() != 0; }
void Task::set_illegal_configuration(bool illegal) noexcept {
    muf::enter_critical();  // the flag's lock
    core_->sbs.set_flag(sbs::detail::SubsystemCore::kIllegalTask, illegal);
    muf::leave_critical();
    send_signal(illegal ? sig::ILLEGAL : sig::LEGAL);
}
bool Task::command_pending() const noexcept {
    return core_->cmd_pending.load(std::memory_order_acquire) || core_->stopping.load(std::memory_order_relaxed);
}
void Task::error(int code, std::string_view message, const char* file, int line) const {
    err::invoke(code, module(), message, file, line);
}
void Task::warning(std::string_view message) noexcept {
    // Locks and allocation: a timing-failure handler (an abort) waits until they are done.
    muf::enter_critical();
    [&]() noexcept {
        TaskCore& c = *core_;
        c.warnings.fetch_add(1, std::memory_order_relaxed);
        if (c.slot.valid()) c.slot.warning(message);
        {
            std::unique_lock<std::mutex> lock(c.msg_mu, std::try_to_lock);
            if (lock.owns_lock()) {
                const std::size_t n = std::min(message.size(), sizeof(c.last_msg) - 1);
                std::memcpy(c.last_msg, message.data(), n);
                c.last_msg[n] = '\0';
                c.last_num.store(-1);
                if (c.first_warning.empty()) {
                    try {
                        c.first_warning.assign(message);
                    } catch (...) {
                    }
                }
            }
        }
        if (c.rtpu.errprint == ErrPrint::warnings) {
            try {
                c.sbs.print(c.rtpu, false, "WARNING> " + std::string(rmod()) + ": " + std::string(message));
            } catch (...) {
            }
        }
    }();
    muf::leave_critical();
    send_signal(sig::WARNING);
}

}  // namespace chimera
