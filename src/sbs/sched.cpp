// A task's place in its RTPU's scheduler (docs/architecture.md §9, §10): the
// Pacer of internal.hpp on top of muf::RtpuScheduler. Periodic tasks are
// released by wait_release and completed by cycle_complete; their timing
// failures go to the modules' timing_failure() hooks (and to the soft-task
// component of Listing 2); aperiodic tasks run under a server of servers.hpp;
// synchronous tasks stay at the RTPU's idle level, timed by their sync().
#include "internal.hpp"
#include "servers.hpp"

#include <pthread.h>
#include <sched.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>

namespace chimera::sbs::detail {

namespace {

std::int64_t seconds_to_ns(double s) { return static_cast<std::int64_t>(std::llround(s * 1e9)); }

class RtpuPacer final : public Pacer {
public:
    RtpuPacer(TaskCore& task, muf::RtpuScheduler& scheduler) : task_(task), sched_(scheduler) {
        const RmodFile& f = task.objects.front().rmod;
        // A combined task runs its objects one after the other: C and E add up.
        for (const auto& o : task.objects) {
            wcet_ns_ += seconds_to_ns(o.rmod.wcet);
            effective_ns_ += seconds_to_ns(o.rmod.effective > 0 ? o.rmod.effective : o.rmod.wcet);
            if (o.rmod.crit) crit_ = std::max(crit_.value_or(0), *o.rmod.crit);
        }
        bool soft = false;
        for (const auto& o : task.objects) soft = soft || o.rmod.effective > 0;
        if (!soft) effective_ns_ = 0;
        server_period_ns_ = f.period > 0 ? seconds_to_ns(f.period) : 0;
        muf_ = sched_.options().policy == muf::Policy::muf;
        if (task.type == TaskType::periodic && soft)
            soft_ = std::make_unique<SoftTask>(muf_ ? muf::crit::non_critical : muf::crit::non_real_time);
    }
    ~RtpuPacer() override { stop(); }

    std::string_view idle() override {
        const muf::RtpuOptions& o = sched_.options();
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(o.cpu, &set);
        const int pin = pthread_setaffinity_np(pthread_self(), sizeof set, &set);
        char policy[80];
        sched_param sp{};
        if (o.backend == muf::Backend::other || !sched_.privileged()) {
            pthread_setschedparam(pthread_self(), SCHED_OTHER, &sp);
            std::snprintf(policy, sizeof policy, "%s",
                          o.backend == muf::Backend::other ? "SCHED_OTHER" : "SCHED_OTHER (no real-time privilege)");
        } else {
            sp.sched_priority = o.fifo_low - 1;
            const int rc = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
            if (rc == 0) {
                std::snprintf(policy, sizeof policy, "SCHED_FIFO %d (idle)", sp.sched_priority);
            } else {
                sp.sched_priority = 0;
                pthread_setschedparam(pthread_self(), SCHED_OTHER, &sp);
                std::snprintf(policy, sizeof policy, "SCHED_OTHER (SCHED_FIFO refused: %s)", strerrordesc_np(rc));
                task_.sbs.warn_no_privilege(std::string("SCHED_FIFO refused for task ") + task_.name + ": " +
                                            strerrordesc_np(rc));
            }
        }
        char where[80];
        if (pin == 0)
            std::snprintf(where, sizeof where, " CPU %d", o.cpu);
        else
            std::snprintf(where, sizeof where, " (not pinned to CPU %d: %s)", o.cpu, strerrordesc_np(pin));
        idle_text_.assign({policy, where});
        return idle_text_.view();
    }

    std::string_view idle_policy() const noexcept override { return idle_text_.view(); }

    void start() override {
        if (running_) return;
        running_ = true;
        if (task_.type == TaskType::synchronous) return;  // timed by sync(), at the idle level
        const bool periodic = task_.type == TaskType::periodic;
        const bool server = !periodic && wcet_ns_ > 0 && server_period_ns_ > 0 && task_.type != TaskType::background;
        muf::RtTaskParams p;
        p.name = task_.name;
        // The data flow of the configuration orders tasks of equal criticality
        // and deadline (§6.2.4): producers before their consumers.
        for (const auto& o : task_.objects) {
            for (auto& v : o.rmod.global_in_vars()) p.inputs.push_back(std::move(v));
            for (auto& v : o.rmod.global_out_vars()) p.outputs.push_back(std::move(v));
        }
        if (periodic) {
            p.period_ns = task_.period_ns.load();
            p.wcet_ns = wcet_ns_;
            p.effective_ns = effective_ns_;
            p.crit = crit_;
        } else if (server) {
            // §6.5.2: a server is a periodic task of period T and capacity C;
            // it keeps its own budget and deadline (maxexec_check off).
            p.period_ns = server_period_ns_;
            p.wcet_ns = wcet_ns_;
            p.maxexec_check = false;
            if (muf_) p.crit = crit_.value_or(muf::crit::server);
        } else {
            // Background service: ranked, never released, no share of the analysis.
            p.period_ns = server_period_ns_ > 0 ? server_period_ns_ : 1'000'000'000;
            p.maxexec_check = false;
            if (muf_) p.crit = crit_.value_or(muf::crit::background_server);
        }
        const std::string who = "task " + task_.name + " on RTPU " + task_.rtpu.name + ": ";
        muf::TaskHandle h = -1;
        try {
            h = sched_.add_task(p);
            sched_.attach_current_thread(h);
        } catch (const muf::SchedError& e) {
            if (h >= 0) sched_.remove_task(h);
            running_ = false;
            idle();
            throw Error(who + e.what());
        }
        handle_.store(h, std::memory_order_release);
        if (periodic) {
            muf::set_dfhandler(&RtpuPacer::periodic_failure, 0, this);
        } else {
            // Under RM and EDF the server's high level is what the analysis gave it.
            const int high = muf_ ? sched_.status(h).crit : std::max(sched_.status(h).crit, 1);
            const int low = muf_ ? muf::crit::server_exhausted : muf::crit::non_real_time;
            if (server && task_.type == TaskType::deferrable)
                server_ = std::make_unique<DeferrableServer>(wcet_ns_, server_period_ns_, high, low);
            else if (server)
                server_ = std::make_unique<SporadicServer>(wcet_ns_, server_period_ns_, high, low);
            else
                server_ = std::make_unique<BackgroundServer>(muf_ ? high : muf::crit::non_real_time);
            server_->begin();
        }
    }

    void stop() noexcept override {
        if (!running_) return;
        running_ = false;
        const muf::TaskHandle h = handle_.load(std::memory_order_acquire);
        if (h < 0) return;
        muf::set_dfhandler(nullptr, 0, nullptr);
        const muf::RtTaskStatus st = sched_.status(h);
        // Kept before the handle goes, so counts() never loses them.
        saved_[0].fetch_add(st.deadline_failures);
        saved_[1].fetch_add(st.maxexec_failures);
        saved_[2].fetch_add(st.minexec_failures);
        saved_[3].fetch_add(st.aborted);
        handle_.store(-1, std::memory_order_release);
        try {
            sched_.remove_task(h);
        } catch (const std::exception&) {
        }
        sched_.detach_current_thread(h);
        server_.reset();
        try {
            idle();
        } catch (const std::exception&) {
        }
    }

    bool running() const noexcept override { return running_; }

    void set_period(std::int64_t period_ns) override {
        const muf::TaskHandle h = handle_.load(std::memory_order_acquire);
        if (h < 0 || task_.type != TaskType::periodic) return;  // taken at the next start()
        try {
            sched_.set_period(h, period_ns);
        } catch (const muf::SchedError& e) {
            throw Error(e.what());
        }
    }

    bool wait(std::atomic<std::uint32_t>& word, std::uint32_t seen, std::uint64_t& missed) noexcept override {
        const muf::TaskHandle h = handle_.load(std::memory_order_relaxed);
        if (h < 0) return false;
        for (;;) {
            const muf::Wake w = sched_.wait_release(h, word, seen);
            missed = sched_.status(h).missed;
            switch (w) {
                case muf::Wake::release:
                    if (soft_) soft_->on_release();
                    return true;
                case muf::Wake::skipped: continue;  // MINEXEC or skip_next: the next one
                case muf::Wake::command:
                case muf::Wake::detached: return false;
            }
        }
    }

    sigjmp_buf* cycle_mark() noexcept override {
        const muf::TaskHandle h = handle_.load(std::memory_order_relaxed);
        if (h < 0 || task_.type != TaskType::periodic || !task_.abortable) return nullptr;
        return sched_.cycle_mark(h);
    }
    void arm_abort() noexcept override { sched_.arm_abort(handle_.load(std::memory_order_relaxed)); }
    void disarm_abort() noexcept override { sched_.disarm_abort(handle_.load(std::memory_order_relaxed)); }
    std::int64_t release_ns() const noexcept override {
        const muf::TaskHandle h = handle_.load(std::memory_order_relaxed);
        return h >= 0 && task_.type == TaskType::periodic ? sched_.job_release_ns(h) : 0;
    }
    void cycle_done() noexcept override {
        // A server's deadline is its replenishment time: only periodic jobs complete.
        const muf::TaskHandle h = handle_.load(std::memory_order_relaxed);
        if (h >= 0 && task_.type == TaskType::periodic) sched_.cycle_complete(h);
    }
    void event_begin() noexcept override {
        if (server_) server_->event_begin();
    }
    void event_end() noexcept override {
        if (server_) server_->event_end();
    }

    int crit() const noexcept override {
        const muf::TaskHandle h = handle_.load(std::memory_order_acquire);
        return h < 0 ? 0 : sched_.status(h).crit;
    }
    TimingCounts counts() const noexcept override {
        const muf::TaskHandle h = handle_.load(std::memory_order_acquire);
        TimingCounts c{saved_[0].load(), saved_[1].load(), saved_[2].load(), saved_[3].load()};
        if (h >= 0) {
            const muf::RtTaskStatus st = sched_.status(h);
            c.deadline += st.deadline_failures;
            c.maxexec += st.maxexec_failures;
            c.minexec += st.minexec_failures;
            c.aborted += st.aborted;
        }
        return c;
    }
    std::string policy() const override {
        const muf::TaskHandle h = handle_.load(std::memory_order_acquire);
        return h < 0 ? std::string(idle_text_.view()) : sched_.policy_of(h);
    }

private:
    // The failure handler of a periodic task: Listing 2's soft-task rule, then
    // every object's timing_failure(); the strongest answer wins.
    static muf::FailureAction periodic_failure(muf::Failure kind, void* self) noexcept {
        auto& p = *static_cast<RtpuPacer*>(self);
        if (p.soft_) p.soft_->on_failure(kind);
        muf::FailureAction action = muf::FailureAction::resume;
        for (auto& o : p.task_.objects) action = std::max(action, o.module->timing_failure(*o.view, kind));
        if (action == muf::FailureAction::abort_cycle && !p.task_.abortable) action = muf::FailureAction::resume;
        return action;
    }

    TaskCore& task_;
    muf::RtpuScheduler& sched_;
    std::int64_t wcet_ns_ = 0, effective_ns_ = 0, server_period_ns_ = 0;
    std::optional<int> crit_;
    bool muf_ = true;
    bool running_ = false;
    std::atomic<muf::TaskHandle> handle_{-1};
    std::unique_ptr<SoftTask> soft_;
    std::unique_ptr<AperiodicServer> server_;
    std::atomic<std::uint64_t> saved_[4] = {};  // DEADLINE, MAXEXEC, MINEXEC, aborted of earlier runs
    FixedText<160> idle_text_;
};

}  // namespace

std::unique_ptr<Pacer> make_rtpu_pacer(TaskCore& task, muf::RtpuScheduler& scheduler) {
    return std::make_unique<RtpuPacer>(task, scheduler);
}

}  // namespace chimera::sbs::detail
