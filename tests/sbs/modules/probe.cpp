// A test module that records what it saw: every method call, the state, and
// the values of its ports in the local table at that moment. Its behaviour is
// chosen by LOCAL keys (read at every call, so sbsSet can change them):
//   INIT/ON/CYCLE/OFFM/KILL/SYNC  OK | ERROR | THROW | INVOKE | OFF | CRASH   (what the method does)
//   ERROR_RET / CLEAR_RET         OK | OFF | CONTINUE | ERROR          (error()/clear() answer)
//   COUT_VALUE v                  written to the out-const by init
//   OUT_ON v / OUT_OFF v          written to the out-var by on / off
//   ADD v                         cycle writes OUT = IN + ADD (default 1)
//   OFF_AFTER n                   cycle returns OFF at its n-th cycle
//   SIGNAL n                      cycle sends SBS signal n
//   SYNC_MS n                     sync() sleeps n ms (synchronous tasks)
//   BUSY_US n                     cycle() burns n us of the thread's own CPU time
//   SLEEP_MS n                    cycle() then sleeps n ms (read at init and set)
//   ON_MS n                       on() sleeps n ms before it records (a slow on)
//   FAILURE resume|skip|abort     timing_failure()'s answer (read at init and set)
// get FAILURES answers "deadline maxexec minexec wrong_thread": the timing
// failures timing_failure() saw, and how many of them ran outside the task's
// own thread (counted with atomics only: it runs from a signal handler).
// Records go to chimera_test_record(), defined by the test program.
#include <chimera/module.hpp>
#include <chimera/svar.hpp>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <unistd.h>
#include <stdexcept>
#include <string>
#include <thread>
#include <time.h>

extern "C" void chimera_test_record(const char* line);

namespace {

using chimera::Result;
using chimera::Task;

// Spins until the calling thread has used `ns` of CPU time (not wall time),
// so the profiled CPU time of a cycle has a known lower bound.
void burn_cpu_ns(double ns) {
    timespec a{}, b{};
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a);
    do {
        clock_gettime(CLOCK_THREAD_CPUTIME_ID, &b);
    } while (static_cast<double>(b.tv_sec - a.tv_sec) * 1e9 + static_cast<double>(b.tv_nsec - a.tv_nsec) < ns);
}

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kProbeLocalKeys[] = {
    {"*", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, true, "the test probe takes any key", ""},
};

class Probe : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kProbeLocalKeys; }

    Result init(Task& t) override {
        const auto& f = t.rmod_file();
        if (!f.in_vars.empty()) in_ = t.translate<double>(f.in_vars[0]);
        if (!f.out_vars.empty()) out_ = t.translate<double>(f.out_vars[0]);
        if (!f.in_consts.empty()) cin_ = t.translate<double>(f.in_consts[0]);
        if (!f.out_consts.empty()) cout_ = t.translate<double>(f.out_consts[0]);
        if (cout_) *cout_ = t.local().number("COUT_VALUE", 0.0);
        task_tid_ = static_cast<long>(::syscall(SYS_gettid));
        read_timing(t);
        record(t, "init");
        return act(t, "INIT");
    }
    Result reinit(Task& t) override {
        record(t, "reinit");
        return Result::OK;
    }
    Result on(Task& t) override {
        if (const double ms = t.local().number("ON_MS", 0.0); ms > 0)
            std::this_thread::sleep_for(std::chrono::microseconds(static_cast<long>(ms * 1e3)));
        record(t, "on");
        if (out_ && t.local().has("OUT_ON")) *out_ = t.local().number("OUT_ON", 0.0);
        return act(t, "ON");
    }
    Result cycle(Task& t) override {
        ++n_;
        record(t, "cycle");
        if (out_ && in_) *out_ = *in_ + t.local().number("ADD", 1.0);
        else if (out_) *out_ = static_cast<double>(n_);
        if (t.local().has("SIGNAL")) t.send_signal(static_cast<int>(t.local().number("SIGNAL", 0)));
        if (const double busy_us = t.local().number("BUSY_US", 0.0); busy_us > 0) burn_cpu_ns(busy_us * 1e3);
        // Last, with nothing held: a timing failure may abandon the cycle here.
        if (sleep_ms_ > 0) std::this_thread::sleep_for(std::chrono::milliseconds(sleep_ms_));
        const double off_after = t.local().number("OFF_AFTER", 0.0);
        if (off_after > 0 && static_cast<double>(n_) >= off_after) return Result::OFF;
        return act(t, "CYCLE");
    }
    Result off(Task& t) override {
        record(t, "off");
        if (out_ && t.local().has("OUT_OFF")) *out_ = t.local().number("OUT_OFF", 0.0);
        return act(t, "OFFM");
    }
    Result kill(Task& t) override {
        record(t, "kill");
        return act(t, "KILL");
    }
    Result error(Task& t, const chimera::err::Error& e) override {
        std::string line = std::string(t.rmod()) + " error code=" + std::to_string(e.code) + " msg=" +
                           std::string(e.message);
        chimera_test_record(line.c_str());
        return result_of(t.local().text("ERROR_RET").value_or("ERROR"));
    }
    Result clear(Task& t, const chimera::err::Error& e) override {
        std::string line = std::string(t.rmod()) + " clear code=" + std::to_string(e.code) + " msg=" +
                           std::string(e.message);
        chimera_test_record(line.c_str());
        return result_of(t.local().text("CLEAR_RET").value_or("OFF"));
    }
    Result set(Task& t) override {
        std::string line = std::string(t.rmod()) + " set " + std::string(t.arg());
        chimera_test_record(line.c_str());
        // A value a module cannot take: refused (the runtime must restore LOCAL).
        if (t.arg().find("REFUSE") != std::string_view::npos) {
            return t.error(7, "probe refuses " + std::string(t.arg()));
        }
        read_timing(t);
        return Result::OK;
    }
    Result get(Task& t) override {
        if (t.arg() == "CYCLES") t.reply(std::to_string(n_));
        if (t.arg() == "FAILURES")
            t.reply(std::to_string(failures_[1].load()) + " " + std::to_string(failures_[2].load()) + " " +
                    std::to_string(failures_[3].load()) + " " + std::to_string(wrong_thread_.load()));
        return Result::OK;
    }
    Result sync(Task& t) override {
        std::this_thread::sleep_for(std::chrono::milliseconds(static_cast<int>(t.local().number("SYNC_MS", 5))));
        return act(t, "SYNC");
    }

    chimera::muf::FailureAction timing_failure(Task&, chimera::muf::Failure kind) noexcept override {
        failures_[static_cast<int>(kind) & 3].fetch_add(1, std::memory_order_relaxed);
        if (static_cast<long>(::syscall(SYS_gettid)) != task_tid_) wrong_thread_.fetch_add(1, std::memory_order_relaxed);
        return action_;
    }

private:
    void read_timing(Task& t) {
        sleep_ms_ = static_cast<int>(t.local().number("SLEEP_MS", 0.0));
        const std::string f = t.local().text("FAILURE").value_or("resume");
        action_ = f == "abort"  ? chimera::muf::FailureAction::abort_cycle
                  : f == "skip" ? chimera::muf::FailureAction::skip_next
                                : chimera::muf::FailureAction::resume;
    }
    static Result result_of(const std::string& s) {
        if (s == "OK") return Result::OK;
        if (s == "OFF") return Result::OFF;
        if (s == "CONTINUE") return Result::CONTINUE;
        return Result::ERROR;
    }
    Result act(Task& t, const char* key) {
        const std::string what = t.local().text(key).value_or("OK");
        if (what == "THROW") throw std::runtime_error(std::string(key) + " threw");
        if (what == "CRASH") {
            // A module bug: a store the kernel refuses, SIGSEGV in the task's own
            // thread. Into a page with no access rather than through nullptr, which
            // is undefined behaviour that the sanitizer build stops at before the store.
            static void* const no_access = mmap(nullptr, 4096, PROT_NONE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
            *static_cast<volatile int*>(no_access) = 1;
        }
        if (what == "INVOKE") {
            if (t.error(chimera::err::code::user + 1, std::string(key) + " invoked an error") != Result::CONTINUE)
                return Result::OK;  // aborted: returns at once (module.hpp); what it returns does not count
            std::string line = std::string(t.rmod()) + " after-invoke";
            chimera_test_record(line.c_str());
            return Result::OK;
        }
        return result_of(what);
    }
    void record(Task& t, const char* method) {
        char buf[256];
        std::snprintf(buf, sizeof buf, "%.*s %s state=%.*s next=%.*s IN=%g OUT=%g CIN=%g COUT=%g ILL=%d",
                      static_cast<int>(t.rmod().size()), t.rmod().data(), method,
                      static_cast<int>(to_string(t.state()).size()), to_string(t.state()).data(),
                      static_cast<int>(to_string(t.next_state()).size()), to_string(t.next_state()).data(),
                      in_ ? *in_ : -1.0, out_ ? *out_ : -1.0, cin_ ? *cin_ : -1.0, cout_ ? *cout_ : -1.0, t.illegal_configuration() ? 1 : 0);
        chimera_test_record(buf);
    }

    double* in_ = nullptr;
    double* out_ = nullptr;
    double* cin_ = nullptr;
    double* cout_ = nullptr;
    long n_ = 0;
    long task_tid_ = 0;
    int sleep_ms_ = 0;
    chimera::muf::FailureAction action_ = chimera::muf::FailureAction::resume;
    std::atomic<long> failures_[4] = {};
    std::atomic<long> wrong_thread_{0};
};

}  // namespace

CHIMERA_MODULE(probe, Probe)
