// The SPP executive (chimexec, §7.4.2) and the per-task SPP object (§7.4.1).
#include "chimera/spp.hpp"

#include <pthread.h>
#include <sched.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <future>

namespace chimera::spp {

namespace {
std::atomic<bool> g_warned_no_privilege{false};
}  // namespace

// One task's command buffer: a single-producer (the task) single-consumer
// (the executive) ring, allocated at init so issuing a command never allocates.
// It holds QUEUE commands plus one entry kept for wait()'s WAKEUP, so that
// wait() always has room and never has to spin for it.
struct CHIMERA_LOCAL Processor::Slot {
    explicit Slot(int i, int capacity)
        : index(i), capacity(static_cast<std::size_t>(capacity)), ring(this->capacity + 1) {}
    const int index;
    const std::size_t capacity;  // QUEUE: commands other than the WAKEUP
    std::vector<Command> ring;
    std::atomic<std::uint64_t> head{0};   // next to run (executive)
    std::atomic<std::uint64_t> tail{0};   // next free (task)
    // WAKEUPs run, the word wait() sleeps on. 32 bits: std::atomic waits on
    // that size with a futex on its own address; on a 64-bit word libstdc++
    // sleeps on a word shared by every address of a hash bucket, and each
    // WAKEUP would wake all tasks sleeping in that bucket.
    std::atomic<std::uint32_t> wakeups{0};
    std::atomic<int> priority{0};
    std::atomic<bool> active{false};
    // Under lock_mutex_:
    bool in_use = false;
    bool waiting = false;        // for the lock
    std::atomic<std::uint32_t> granted{0};  // bumped when the lock is granted (lock() sleeps on it)
    std::uint64_t ticket = 0;    // order of lock requests (ties in priority)

    bool empty() const noexcept {
        return head.load(std::memory_order_relaxed) == tail.load(std::memory_order_acquire);
    }
};

std::size_t Memory::size_of(Handle h) const noexcept {
    if (h.kind != Handle::Kind::variable || h.index >= proc_->variables_.size()) return 0;
    return proc_->variables_[h.index].bytes;
}

std::byte* Memory::address(Handle h) const noexcept {
    if (h.kind != Handle::Kind::variable || h.index >= proc_->variables_.size()) return nullptr;
    return proc_->memory_.get() + proc_->offsets_[h.index];
}

Processor::Processor(const Config& config, const Library& library)
    : config_(config), routines_(library.routines()), variables_(library.variables()) {
    if (config.driver != "thread")
        throw Error("SPP " + config.name + ": unknown driver " + config.driver);
    // The ranges the file reader enforces, for a Config written in code.
    const std::string where = "SPP " + config.name + " (" + config.file + ":" + std::to_string(config.line) + "): ";
    const auto check = [&](bool ok, const std::string& rule, long long found) {
        if (!ok) throw Error(where + rule + ", found " + std::to_string(found));
    };
    check(config.memsize >= 1 && config.memsize <= (std::size_t{1} << 34), "MEMSIZE must be 1..16G bytes",
          static_cast<long long>(config.memsize));
    check(config.queue >= 2 && config.queue <= (1 << 16), "QUEUE must be 2..65536", config.queue);
    check(config.tasks >= 1 && config.tasks <= 256, "TASKS must be 1..256", config.tasks);
    check(config.cpu >= -1 && config.cpu <= 4095, "CPU must be 0..4095 (-1: not pinned)", config.cpu);
    check(config.priority >= 0 && config.priority <= 99, "PRIORITY must be 1..99 (0: not real-time)",
          config.priority);
    std::size_t at = 0;
    std::size_t base_align = 64;  // a cache line at least, for any routine's data
    for (const auto& v : variables_) {
        // In differences from MEMSIZE, which cannot wrap around as sums can
        // (at <= memsize throughout). An alignment beyond MEMSIZE does not fit
        // either: the memory itself would have to be that aligned.
        const std::size_t pad = (v.align - at % v.align) % v.align;
        if (v.align > config.memsize || pad > config.memsize - at || v.bytes > config.memsize - at - pad)
            throw Error(where + "library variable " + v.name + " does not fit in MEMSIZE " +
                        std::to_string(config.memsize));
        offsets_.push_back(at + pad);
        at += pad + v.bytes;
        base_align = std::max(base_align, v.align);
    }
    // Offsets are aligned relative to the base: the base must have the
    // largest alignment asked for. Zeroed like freshly initialised SPP memory.
    memory_ = {static_cast<std::byte*>(::operator new[](config.memsize, std::align_val_t{base_align})),
               AlignedDelete{base_align}};
    std::memset(memory_.get(), 0, config.memsize);
    for (int i = 0; i < config.tasks; ++i) slots_.push_back(std::make_unique<Slot>(i, config.queue));
    view_.proc_ = this;
}

std::unique_ptr<Processor> Processor::init(const Config& config, const Library& library) {
    std::unique_ptr<Processor> p(new Processor(config, library));
    // The executive takes its CPU and policy before init returns: realtime()
    // is settled for the caller, and a CPU it cannot have is an init error.
    std::promise<int> placed;
    std::future<int> pin_error = placed.get_future();
    // The promise moves into the thread: set_value may still be touching it
    // when init's get() returns.
    p->thread_ = std::thread([q = p.get(), placed = std::move(placed)]() mutable {
        const int rc = q->place();
        placed.set_value(rc);
        if (rc == 0) q->run();
    });
    if (const int rc = pin_error.get(); rc != 0) {
        p->thread_.join();
        throw Error("SPP " + config.name + " (" + config.file + ":" + std::to_string(config.line) +
                    "): cannot pin the executive to CPU " + std::to_string(config.cpu) + ": " +
                    std::strerror(rc));
    }
    return p;
}

Processor::~Processor() {
    int attached = 0;
    {
        std::lock_guard<ipc::PiMutex> lk(lock_mutex_);
        for (const auto& sp : slots_) attached += sp->in_use ? 1 : 0;
    }
    if (attached > 0) {
        // Their Spp objects point into this Processor: going on would leave
        // each task's next call, or its finish(), writing freed memory.
        std::fprintf(stderr, "spp %s: destroyed while %d task%s still attached (finish every Spp first)\n",
                     config_.name.c_str(), attached, attached == 1 ? " is" : "s are");
        std::abort();
    }
    stop_.store(true);
    kick();
    if (thread_.joinable()) thread_.join();
}

Handle Processor::lookup(std::string_view name) const noexcept {
    for (std::size_t i = 0; i < routines_.size(); ++i)
        if (routines_[i].name == name) return {Handle::Kind::routine, static_cast<std::uint32_t>(i)};
    for (std::size_t i = 0; i < variables_.size(); ++i)
        if (variables_[i].name == name) return {Handle::Kind::variable, static_cast<std::uint32_t>(i)};
    return {};
}

std::size_t Processor::queued() const noexcept {
    std::size_t n = 0;
    for (const auto& sp : slots_) {
        if (!sp->active.load(std::memory_order_acquire)) continue;
        // head first: it only grows towards tail, so the difference cannot underflow.
        const std::uint64_t head = sp->head.load(std::memory_order_acquire);
        n += static_cast<std::size_t>(sp->tail.load(std::memory_order_acquire) - head);
    }
    return n;
}

// A new command (or a lock grant, or stop): wake the executive if it sleeps.
// notify_one() alone is not enough to keep the promise of no system call
// while the executive is busy: libstdc++ makes the futex call whenever any
// thread waits on an address of work_'s hash bucket, not only the executive.
// So the kick counts itself and clears the idle bit in one exchange, and only
// the kick that cleared the bit wakes: the rest of a burst (write, call,
// read, wait) finds the executive already woken and makes no system call.
void Processor::kick() noexcept {
    std::uint32_t word = work_.load(std::memory_order_relaxed);
    while (!work_.compare_exchange_weak(word, (word + 2) & ~1u, std::memory_order_seq_cst)) {
    }
    if (word & 1u) work_.notify_one();
}

// The next task to serve. While a task holds the lock only its commands run;
// otherwise the highest-priority task with a pending command, ties going to
// the command issued first.
Processor::Slot* Processor::pick() noexcept {
    const int owner = owner_.load(std::memory_order_acquire);
    if (owner >= 0) {
        Slot* s = slots_[static_cast<std::size_t>(owner)].get();
        return s->empty() ? nullptr : s;
    }
    Slot* best = nullptr;
    int best_prio = 0;
    std::uint64_t best_seq = 0;
    for (auto& sp : slots_) {
        Slot* s = sp.get();
        if (!s->active.load(std::memory_order_acquire) || s->empty()) continue;
        const std::uint64_t h = s->head.load(std::memory_order_relaxed);
        const std::uint64_t seq = s->ring[h % s->ring.size()].seq;
        const int prio = s->priority.load(std::memory_order_relaxed);
        if (!best || prio > best_prio || (prio == best_prio && seq < best_seq)) {
            best = s;
            best_prio = prio;
            best_seq = seq;
        }
    }
    return best;
}

// Pins the executive thread (CPU) and raises it (PRIORITY). Returns the
// error of pinning, or 0; no SCHED_FIFO is not an error: best effort.
int Processor::place() noexcept {
    if (config_.cpu >= 0) {
        // Sized for the CPU, which may lie beyond a fixed cpu_set_t (CPU_SETSIZE).
        const auto cpu = static_cast<std::size_t>(config_.cpu);
        cpu_set_t* set = CPU_ALLOC(cpu + 1);
        if (!set) return ENOMEM;
        const std::size_t size = CPU_ALLOC_SIZE(cpu + 1);
        CPU_ZERO_S(size, set);
        CPU_SET_S(cpu, size, set);
        const int rc = pthread_setaffinity_np(pthread_self(), size, set);
        CPU_FREE(set);
        if (rc != 0) return rc;
    }
    if (config_.priority > 0) {
        sched_param sp{};
        sp.sched_priority = config_.priority;
        const int rc = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
        if (rc == 0) {
            realtime_.store(true);
        } else if (!g_warned_no_privilege.exchange(true)) {
            // Once per process, as the MUF scheduler does: each Processor's
            // realtime() tells which executives it applies to.
            std::fprintf(stderr,
                         "spp %s: no real-time privilege (SCHED_FIFO refused: %s); executives run "
                         "best effort under SCHED_OTHER\n",
                         config_.name.c_str(), std::strerror(rc));
        }
    }
    return 0;
}

void Processor::run() noexcept {
    for (;;) {
        std::uint32_t seen = work_.load(std::memory_order_acquire);
        Slot* s = pick();
        if (!s) {
            if (stop_.load()) return;
            // Sleep only if no kick came since seen (whose commands pick() saw):
            // the bit is set in the same change that checks it, and the next
            // kick clears it as it counts itself, and wakes.
            if (work_.compare_exchange_strong(seen, seen | 1u, std::memory_order_seq_cst))
                work_.wait(seen | 1u, std::memory_order_seq_cst);
            continue;
        }
        const std::uint64_t h = s->head.load(std::memory_order_relaxed);
        const Command c = s->ring[h % s->ring.size()];
        execute(c);
        // Retire the command before waking anybody (WAKEUP, RELEASE): a woken
        // task above the executive on its CPU runs before the executive's next
        // step, and must find the entry free and executed() up to date.
        s->head.store(h + 1, std::memory_order_release);
        executed_.fetch_add(1, std::memory_order_relaxed);
        if (c.type == CommandType::WAKEUP) {
            s->wakeups.fetch_add(1, std::memory_order_release);
            s->wakeups.notify_all();
        } else if (c.type == CommandType::RELEASE) {
            std::lock_guard<ipc::PiMutex> lk(lock_mutex_);
            if (owner_.load() == s->index) {
                owner_.store(-1, std::memory_order_release);
                grant_next_locked();
            }
        }
    }
}

void Processor::execute(const Command& c) noexcept {
    switch (c.type) {
    case CommandType::CALL:
        try {
            routines_[c.target.index].fn(view_, c.args);
        } catch (...) {
            // A routine has no caller to throw to (the call is asynchronous):
            // counted, and the executive goes on with the next command.
            faults_.fetch_add(1, std::memory_order_relaxed);
        }
        break;
    case CommandType::XFER_IN:
        std::memcpy(memory_.get() + offsets_[c.target.index] + c.offset, c.user, c.bytes);
        break;
    case CommandType::XFER_OUT:
        std::memcpy(c.user, memory_.get() + offsets_[c.target.index] + c.offset, c.bytes);
        break;
    case CommandType::WAKEUP:
    case CommandType::RELEASE:
        break;  // they wake a task: done by run() once the command is retired
    }
}

// Hands the free lock to the highest-priority waiting task (earliest request
// on ties). Called with lock_mutex_ held.
void Processor::grant_next_locked() {
    Slot* best = nullptr;
    for (auto& sp : slots_) {
        Slot* s = sp.get();
        if (!s->in_use || !s->waiting) continue;
        if (!best || s->priority.load() > best->priority.load() ||
            (s->priority.load() == best->priority.load() && s->ticket < best->ticket))
            best = s;
    }
    if (!best) return;
    best->waiting = false;
    owner_.store(best->index, std::memory_order_release);
    best->granted.fetch_add(1, std::memory_order_release);
    best->granted.notify_all();
    kick();
}

// --- the task's SPP object ----------------------------------------------------------

std::unique_ptr<Spp> Spp::init(Processor& p, int priority) {
    std::lock_guard<ipc::PiMutex> lk(p.lock_mutex_);
    for (auto& sp : p.slots_) {
        Processor::Slot& s = *sp;
        if (s.in_use) continue;
        s.in_use = true;
        s.waiting = false;
        s.priority.store(priority);
        const std::uint64_t h = s.head.load();
        s.tail.store(h);
        s.active.store(true, std::memory_order_release);
        return std::unique_ptr<Spp>(new Spp(p, s.index));
    }
    throw Error("SPP " + p.config_.name + ": all " + std::to_string(p.config_.tasks) +
                " task slots are in use (TASKS)");
}

Spp::~Spp() { finish(); }

int Spp::priority() const noexcept { return proc_->slots_[static_cast<std::size_t>(slot_)]->priority.load(); }

Handle Spp::translate(std::string_view name) const {
    const Handle h = proc_->lookup(name);
    if (!h) throw Error("SPP " + proc_->config_.name + ": no routine or variable named " + std::string(name));
    return h;
}

int Spp::push(Processor::Command c) noexcept {
    if (finished_) return -EPIPE;
    Processor::Slot& s = *proc_->slots_[static_cast<std::size_t>(slot_)];
    const std::uint64_t t = s.tail.load(std::memory_order_relaxed);
    if (t - s.head.load(std::memory_order_acquire) >= s.capacity) return -ENOSPC;
    c.seq = proc_->next_seq_.fetch_add(1, std::memory_order_relaxed);
    s.ring[t % s.ring.size()] = c;
    s.tail.store(t + 1, std::memory_order_release);
    proc_->kick();
    return 0;
}

int Spp::call(Handle routine, const Args& args) noexcept {
    if (routine.kind != Handle::Kind::routine || routine.index >= proc_->routines_.size() || !args.valid())
        return -EINVAL;
    return push({CommandType::CALL, routine, 0, args, nullptr, 0, 0});
}

int Spp::write(Handle v, const void* src, std::size_t bytes, std::size_t offset) noexcept {
    if (v.kind != Handle::Kind::variable || v.index >= proc_->variables_.size() ||
        offset > proc_->variables_[v.index].bytes || bytes > proc_->variables_[v.index].bytes - offset)
        return -EINVAL;
    return push({CommandType::XFER_IN, v, 0, {}, const_cast<void*>(src), bytes, offset});
}

int Spp::read(Handle v, void* dst, std::size_t bytes, std::size_t offset) noexcept {
    if (v.kind != Handle::Kind::variable || v.index >= proc_->variables_.size() ||
        offset > proc_->variables_[v.index].bytes || bytes > proc_->variables_[v.index].bytes - offset)
        return -EINVAL;
    return push({CommandType::XFER_OUT, v, 0, {}, dst, bytes, offset});
}

int Spp::wait() noexcept {
    if (finished_) return -EPIPE;
    Processor::Slot& s = *proc_->slots_[static_cast<std::size_t>(slot_)];
    // The entry kept for the WAKEUP is free: push() leaves it, and the last
    // WAKEUP has run (this task's previous wait() returned). No waiting for
    // room here: a task above the executive on its CPU would spin forever.
    // For the same reason no WAKEUP of this task is pending: the count stays
    // as read here until the executive runs the one issued now.
    const std::uint32_t before = s.wakeups.load(std::memory_order_acquire);
    const std::uint64_t t = s.tail.load(std::memory_order_relaxed);
    const std::uint64_t seq = proc_->next_seq_.fetch_add(1, std::memory_order_relaxed);
    s.ring[t % s.ring.size()] = {CommandType::WAKEUP, {}, seq, {}, nullptr, 0, 0};
    s.tail.store(t + 1, std::memory_order_release);
    proc_->kick();
    while (s.wakeups.load(std::memory_order_acquire) == before) s.wakeups.wait(before, std::memory_order_acquire);
    return 0;
}

void Spp::lock() {
    if (locked_ || finished_) return;
    Processor::Slot& s = *proc_->slots_[static_cast<std::size_t>(slot_)];
    std::unique_lock<ipc::PiMutex> lk(proc_->lock_mutex_);
    s.waiting = true;
    s.ticket = ++proc_->lock_ticket_;
    if (proc_->owner_.load() < 0) proc_->grant_next_locked();
    // Granted is "no longer waiting", not "owner is this slot": after release()
    // the task is still the owner until the executive reaches its RELEASE, and
    // that RELEASE may hand the SPP to a higher-priority locker first.
    if (s.waiting) {
        proc_->lock_waiters_.fetch_add(1);
        const std::uint32_t seen = s.granted.load(std::memory_order_relaxed);  // under the lock: no grant missed
        lk.unlock();
        while (s.granted.load(std::memory_order_acquire) == seen) s.granted.wait(seen, std::memory_order_acquire);
        proc_->lock_waiters_.fetch_sub(1);
    }
    locked_ = true;
}

int Spp::release() noexcept {
    if (!locked_) return -EINVAL;
    const int rc = push({CommandType::RELEASE, {}, 0, {}, nullptr, 0, 0});
    if (rc == 0) locked_ = false;
    return rc;
}

void Spp::finish() noexcept {
    if (finished_) return;
    if (locked_) {
        // wait() fails only once finished (-EPIPE), which finish() sets below.
        while (release() == -ENOSPC) (void)wait();
    }
    (void)wait();  // drains this task's commands
    finished_ = true;
    Processor::Slot& s = *proc_->slots_[static_cast<std::size_t>(slot_)];
    std::lock_guard<ipc::PiMutex> lk(proc_->lock_mutex_);
    s.active.store(false, std::memory_order_release);
    s.in_use = false;
}

}  // namespace chimera::spp
