// The task runtime: a task's objects and transfer sets, its requests from the
// master and the Task view its modules see. The thread itself, the state
// machine of Figure 3.10, is task_loop.cpp.
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

}  // namespace

int crit_for(const RtpuSpec& r, TaskType type, double freq) {
    if (type == TaskType::background || freq <= 0) return 1;
    if (freq <= r.minfreq) return 1;
    if (freq > r.maxfreq) return 62;
    const double x = (std::log(freq) - std::log(r.minfreq)) / (std::log(r.maxfreq) - std::log(r.minfreq));
    return std::clamp(1 + static_cast<int>(std::lround(x * 61.0)), 1, 62);
}

// ------------------------------------------------------------------ TaskCore

TaskCore::TaskCore(SubsystemCore& s, int task_id, const RtpuSpec& r, std::vector<RmodFile> rmods)
    : sbs(s), id(task_id), rtpu(r) {
    if (rmods.empty()) throw Error("spawn: no .rmod given");
    std::vector<std::string> names;
    for (const auto& f : rmods) names.push_back(f.name);
    name = join_names(names, "+");
    type = rmods.front().type;
    const double freq = rmods.front().freq;
    if (const std::string why = combined_problem(rmods); !why.empty()) throw Error(why);
    period_ns.store(freq > 0 ? static_cast<std::int64_t>(std::llround(1e9 / freq)) : 0);
    crit.store(crit_for(rtpu, type, freq));

    // Every port must be a variable of the global table.
    for (const auto& f : rmods) {
        const std::string why =
            port_problem(f, [&](const std::string& g) { return sbs.table.find(g).has_value(); }, sbs.file.svarfile);
        if (!why.empty()) throw Error(why);
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
        // A peer task stands for a process outside the master (a Python
        // program, sbs.hpp kPeerModule) that reads and writes the table
        // itself: its ports count for §3.3.1 and status, but the runtime
        // copies none of them, so it never overwrites what the process wrote.
        peer = rmods.size() == 1 && rmods.front().module == kPeerModule;
        const std::vector<std::string> none;
        set_in_vars = local->make_set(peer ? none : in_vars);
        set_out_vars = local->make_set(peer ? none : out_vars);
        std::vector<std::string> on_names = peer ? none : in_vars;
        for (const auto& v : peer ? none : out_vars) add_unique(on_names, v);
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
    wait_answer(started);
    if (start_failed) {
        join();
        throw Error("spawn " + name + ": " + start_error);
    }
}

std::string TaskCore::request(CmdKind kind, std::string a, std::string key, double hz, std::string* out) {
    std::unique_lock<ipc::PiMutex> lock(cmd_mu);
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
    ipc::futex_wake_all(word, ipc::FutexScope::process);
    wait_answer(cmd_done);
    lock.lock();
    if (out) *out = cmd_reply;
    return cmd_result;
}

// The master, until the task thread set `done` (under cmd_mu) and told it.
void TaskCore::wait_answer(const bool& done) {
    for (;;) {
        const std::uint32_t seen = answered.load(std::memory_order_acquire);
        {
            std::lock_guard<ipc::PiMutex> lock(cmd_mu);
            if (done) return;
        }
        ipc::futex_wait(answered, seen);
    }
}

// The task thread, after setting the flag the master waits for.
void TaskCore::tell_master() noexcept {
    answered.fetch_add(1, std::memory_order_release);
    ipc::futex_wake_all(answered);
}

void TaskCore::publish_policy(std::string_view text) noexcept {
    std::lock_guard<ipc::PiMutex> lock(msg_mu);
    policy.assign(text);
    if (slot.valid()) slot.set_policy(policy.view());
}

void TaskCore::stop_running() noexcept {
    if (!pacer || !pacer->running()) return;
    pacer->stop();
    publish_policy(pacer->idle_policy());  // no allocation: a task thread stops so on an error
}

}  // namespace chimera::sbs::detail

// ------------------------------------------------------------------ Task view

namespace chimera {

using sbs::detail::TaskCore;

std::string_view Task::rmod() const noexcept { return core_->objects[object_].rmod.name; }
std::string_view Task::module() const noexcept { return core_->objects[object_].rmod.module; }
std::string_view Task::rtpu() const noexcept { return core_->rtpu.name; }
std::string_view Task::subsystem() const noexcept { return core_->sbs.file.subsystem; }
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
Result Task::error(int code, std::string_view message, const char* file, int line) const {
    // Timing-failure handlers are held off while the error chain runs: an
    // abandoned cycle would jump over a handler half-way (its depth count, an
    // abort half recorded).
    struct Critical {
        Critical() noexcept { muf::enter_critical(); }
        ~Critical() { muf::leave_critical(); }
    } critical;
    return err::invoke(code, module(), message, file, line) ? Result::CONTINUE : Result::ERROR;
}
namespace {
// Into a fixed buffer, cut to fit: the warning path never allocates.
template <std::size_t N>
void copy_cut(char (&to)[N], std::string_view from) noexcept {
    const std::size_t n = std::min(from.size(), N - 1);
    std::memcpy(to, from.data(), n);
    to[n] = '\0';
}
}  // namespace

void Task::warning(std::string_view message) noexcept {
    // Locks and allocation: a timing-failure handler (an abort) waits until they are done.
    muf::enter_critical();
    [&]() noexcept {
        TaskCore& c = *core_;
        c.warnings.fetch_add(1, std::memory_order_relaxed);
        if (c.slot.valid()) c.slot.warning(message);
        {
            std::unique_lock<ipc::PiMutex> lock(c.msg_mu, std::try_to_lock);
            if (lock.owns_lock()) {
                copy_cut(c.last_msg, message);
                c.last_num.store(-1);
                if (c.first_warning[0] == '\0') copy_cut(c.first_warning, message);
            }
        }
        c.sbs.print(c.rtpu, false, {"WARNING> ", rmod(), ": ", message});
    }();
    muf::leave_critical();
    send_signal(sig::WARNING);
}

}  // namespace chimera
