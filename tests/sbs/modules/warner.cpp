// The `warner` test module: every cycle raises one warning and nothing else
// (no allocation of its own), so a test can count what the runtime does on
// the task thread for a warning. LOCAL (N a cycle number):
//   THROW_AT N          cycle N throws instead;
//   FAIL_AT N           cycle N returns ERROR instead;
//   INVOKE_AT N         cycle N raises an error through task.error() (errInvoke),
//                       INVOKE_BYTES long (default 300), which the task's error()
//                       answers ERROR: an abort;
//   HANDLER_ERROR_AT N  cycle N raises an error that the module's own err handler
//                       catches, and that handler raises an error of its own
//                       (the default handler's case, err.hpp).
#include "chimera/module.hpp"

#include <stdexcept>
#include <string>

namespace {

constexpr int kInvoked = chimera::err::code::user + 7;
constexpr int kHandled = chimera::err::code::user + 8;
constexpr int kInHandler = chimera::err::code::user + 9;

class Warner : public chimera::Module {
public:
    chimera::Result init(chimera::Task& t) override {
        throw_at_ = at(t, "THROW_AT");
        fail_at_ = at(t, "FAIL_AT");
        invoke_at_ = at(t, "INVOKE_AT");
        handler_error_at_ = at(t, "HANDLER_ERROR_AT");
        // The message is made here: the cycle that raises it allocates nothing of its own.
        const auto bytes = static_cast<std::size_t>(t.local().number("INVOKE_BYTES", 300));
        invoke_text_ = "joint 3 following error exceeds its limit:";
        for (int k = 0; invoke_text_.size() < bytes; ++k) invoke_text_ += " " + std::to_string(k);
        invoke_text_.resize(bytes);
        if (handler_error_at_ != 0) {
            handler_ = chimera::err::install(chimera::err::Match{kHandled, ""}, [](const chimera::err::Error&) {
                // The handler's own check fails: an error inside a handler.
                (void)chimera::err::invoke(kInHandler, "warner-handler", "the handler's own check failed");
                return chimera::err::Outcome::resume();
            });
        }
        return chimera::Result::OK;
    }
    chimera::Result cycle(chimera::Task& t) override {
        if (++n_ == throw_at_) throw std::runtime_error("joint 3 encoder lost");
        if (n_ == fail_at_) return chimera::Result::ERROR;
        if (n_ == invoke_at_) return t.error(kInvoked, invoke_text_);
        if (n_ == handler_error_at_) return t.error(kHandled, "drive 2 reports a fault");
        t.warning("joint 3 clipped to its limit");
        return chimera::Result::OK;
    }
    chimera::Result kill(chimera::Task&) override {
        if (handler_ != 0) chimera::err::remove(handler_);  // kill runs on the task's thread, as init did
        return chimera::Result::OK;
    }

private:
    static long at(chimera::Task& t, const char* key) { return static_cast<long>(t.local().number(key, 0.0)); }
    long n_ = 0, throw_at_ = 0, fail_at_ = 0, invoke_at_ = 0, handler_error_at_ = 0;
    std::string invoke_text_;
    chimera::err::HandlerId handler_ = 0;
};

}  // namespace

CHIMERA_MODULE(warner, Warner)
