// fuzz/harness.hpp — what every harness in fuzz/ shares: how an invariant
// fails, how a parser's documented error is told from any other exception,
// and the checks every shared-memory validator must pass.
//
// A harness aborts on a broken invariant (libFuzzer then keeps the input as a
// crash; the replay driver's test fails naming the file). It does not catch
// what it does not document: an exception of any other type escapes
// LLVMFuzzerTestOneInput and terminates, which counts as a crash as well.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <string_view>

#include "chimera/ipc/fault.hpp"

namespace chimera::fuzz {

[[noreturn]] inline void broken(const std::string& what) {
    std::fprintf(stderr, "fuzz invariant broken: %s\n", what.c_str());
    std::fflush(stderr);
    std::abort();
}

inline void require(bool ok, const std::string& what) {
    if (!ok) broken(what);
}

inline std::string_view text_of(const std::uint8_t* data, std::size_t size) {
    return {reinterpret_cast<const char*>(data), size};
}

/// Runs `parse` on the input; true when it returned, false when it threw the
/// documented `Error`, whose what() must then be "FILE:LINE: message" for
/// `file`. Any other exception type (std::bad_alloc, std::out_of_range...)
/// is not caught: it terminates the harness.
template <typename Error, typename Parse>
bool accepted(const std::string& file, Parse&& parse) {
    try {
        parse();
        return true;
    } catch (const Error& e) {
        const std::string what = e.what();
        require(what.rfind(file + ":", 0) == 0 && e.line() >= 0 && !e.message().empty(),
                "an error without FILE:LINE: message: " + what);
        return false;
    }
}

/// A validator's input laid out as a segment is: 64-byte aligned (segments
/// are page aligned; the validators may read atomics in place).
class Image {
public:
    Image(const std::uint8_t* data, std::size_t size)
        : bytes_(static_cast<std::byte*>(std::aligned_alloc(64, round_up(size)))), size_(size) {
        if (size) std::memcpy(bytes_.get(), data, size);
    }
    void* data() const noexcept { return bytes_.get(); }
    std::size_t size() const noexcept { return size_; }

private:
    struct Free {
        void operator()(std::byte* p) const noexcept { std::free(p); }
    };
    static std::size_t round_up(std::size_t n) { return (n + 64) / 64 * 64; }  // never 0
    std::unique_ptr<std::byte, Free> bytes_;
    std::size_t size_;
};

/// What every validator must do on any image: give the same answer twice
/// (a pure function of the bytes, so a reader's check cannot be raced into
/// a different verdict by the bytes alone), and name a fault it finds in a
/// message that names the segment and the field. Returns the fault.
template <typename Validate>
ipc::Fault checked_fault(const char* validator, const Image& image, Validate&& validate) {
    const ipc::Fault first = validate(image.data(), image.size());
    const ipc::Fault again = validate(image.data(), image.size());
    require((first.field == nullptr) == (again.field == nullptr) &&
                (!first || (std::strcmp(first.field, again.field) == 0 && first.index == again.index &&
                            first.value == again.value && first.limit == again.limit)),
            std::string(validator) + " gave two verdicts on the same bytes");
    if (first) {
        require(*first.field != '\0' && first.rule != nullptr,
                std::string(validator) + ": a fault without a field or rule");
        const std::string message = ipc::describe("/fuzz.image", first);
        require(message.find("/fuzz.image") != std::string::npos && message.find(first.field) != std::string::npos,
                std::string(validator) + ": the message does not name segment and field: " + message);
    } else {
        require(ipc::describe("/fuzz.image", first).empty(), std::string(validator) + ": a message without a fault");
    }
    return first;
}

}  // namespace chimera::fuzz
