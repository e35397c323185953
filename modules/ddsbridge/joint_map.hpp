// joint_map.hpp — a received JointState, matched by name to a port's joints
// (issue #29.7), and the consumer-side limits on what the bridge writes to the
// table (issue #29.6). Pure logic, no DDS: tested exactly in
// tests/ddsbridge/test_joint_map.cpp.
//
// A JointState names its joints: name[i] goes with position[i], velocity[i]
// and effort[i], in whatever order the publisher chose. The port's joints have
// names too (JOINT_NAMES, default joint1..jointN). JointMap::apply puts each
// value on the joint of its name, in any order; a message naming a subset
// updates only those (unless JOINT_SUBSET refuse); a message without names is
// taken by position only with UNNAMED positional. A message is taken whole or
// refused whole: never half-applied.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace ddsbridge {

/// Why a received sample was refused (none: taken).
enum class Refusal : std::uint8_t {
    none,
    length,     ///< its values do not fit: not one per name, or (no names) not one per joint
    unnamed,    ///< it names no joint, and the .rmod takes no unnamed message (UNNAMED refuse)
    unknown,    ///< it names a joint the port does not have
    duplicate,  ///< it names a joint twice
    partial,    ///< it names a subset, and the .rmod requires every joint (JOINT_SUBSET refuse)
    reordered,  ///< it is older than the newest sample the port took (SampleOrder)
};
inline constexpr std::size_t kRefusals = 7;  ///< Refusal values, none included
const char* to_string(Refusal r) noexcept;

struct JointOptions {
    bool refuse_subset = false;   ///< JOINT_SUBSET refuse: every joint in every message
    bool accept_unnamed = false;  ///< UNNAMED positional: a message without names is taken by position
};

/// What apply() did with one message.
struct Applied {
    Refusal refusal = Refusal::none;
    std::size_t offender = 0;  ///< unknown, duplicate: the index in the message of the name refused
    bool complete = false;     ///< taken, and every joint of the port has had a value since the start
};

/// The port's joint names, indexed once (at spawn, off the real-time path);
/// apply() matches a message's names without allocating.
class JointMap {
public:
    JointMap(std::vector<std::string> names, JointOptions options);

    std::size_t size() const noexcept { return names_.size(); }
    const std::string& name(std::size_t joint) const noexcept { return names_[joint]; }
    /// The joint of `name`; size() when the port has none of that name.
    std::size_t index_of(std::string_view name) const noexcept;

    /// Puts `values` (value i goes with names[i]; no names: value j is joint j)
    /// on `joints` (size() doubles, the port's vector: the joints a message does
    /// not name keep what is there). Refused: `joints` untouched.
    /// No allocation, no system call. check() then commit().
    Applied apply(std::span<const char* const> names, std::span<const double> values, double* joints) noexcept;
    /// apply()'s checks alone: whether the message would be taken, or why not.
    /// Changes no joint, so that the listener can still refuse it for another
    /// reason (its age) before anything of it is applied.
    Applied check(std::span<const char* const> names, std::span<const double> values) noexcept;
    /// Applies the message check() took last (the same names and values).
    Applied commit(std::span<const char* const> names, std::span<const double> values, double* joints) noexcept;

    /// Starts again: no joint has had a value yet.
    void reset() noexcept;

private:
    std::vector<std::string> names_;
    std::vector<std::pair<std::string_view, std::size_t>> sorted_;  // (name, joint), by name: binary search
    JointOptions options_;
    std::vector<std::size_t> target_;      // per message name: its joint (apply's scratch, sized once)
    std::vector<std::uint32_t> named_in_;  // per joint: the message (generation_) that last named it
    std::uint32_t generation_ = 0;
    std::vector<bool> known_;              // per joint: had a value since the start
    std::size_t unknown_left_ = 0;         // joints still without a value
};

/// Who sent a received sample, and when.
struct SampleStamp {
    std::uint64_t writer = 0;    ///< its DDS writer (instance handle): a restarted writer is another one
    std::uint64_t counter = 0;   ///< StateVar: the sender's counter-stamp (0 for a writer's first value)
    std::int64_t source_ns = 0;  ///< header.stamp, ns
};

/// The newest sample a subscription took, and whether another one is older
/// (issue #29: a sample reordered by the network, or an old command replayed,
/// must not take the port back to an older value). From the writer of the
/// newest, a StateVar is compared by counter (by_counter: immune to the
/// sender's clock being set back); from another writer (one that restarted
/// from counter 0, say), or a JointState (no counter), by header.stamp.
/// Equal is not older: a publisher that leaves header.stamp at zero, or
/// splits its joints over messages of one stamp, is taken. Pure arithmetic.
class SampleOrder {
public:
    explicit SampleOrder(bool by_counter = false) noexcept : by_counter_(by_counter) {}
    /// Whether `s` is older than the newest taken (false before any).
    bool older(const SampleStamp& s) const noexcept {
        if (!any_) return false;
        if (by_counter_ && s.writer == newest_.writer) return s.counter < newest_.counter;
        return s.source_ns < newest_.source_ns;
    }
    /// `s` was taken: the newest now.
    void taken(const SampleStamp& s) noexcept {
        newest_ = s;
        any_ = true;
    }
    const SampleStamp& newest() const noexcept { return newest_; }
    bool by_counter(const SampleStamp& s) const noexcept { return any_ && by_counter_ && s.writer == newest_.writer; }

private:
    SampleStamp newest_;
    bool any_ = false;
    bool by_counter_ = false;
};

/// The consumer side's limits on one subscribed port (VLIMIT_<port>,
/// TRATE_<port>): either the magnitude of each joint's value (a velocity
/// port), or its change per cycle (a position port under a velocity limit, an
/// effort port under a torque-rate limit). Limits per joint; applied by the
/// cycle to what it writes to the table. No allocation after construction.
class JointLimiter {
public:
    enum class Kind : std::uint8_t { none, magnitude, rate };

    JointLimiter() = default;
    /// `limits`: per joint, > 0 (units, or units per second for a rate).
    JointLimiter(Kind kind, std::vector<double> limits);

    Kind kind() const noexcept { return kind_; }
    /// The task's period (s), known at on(): a rate's step per cycle. The
    /// step is limit * period, the nominal period, so that a late cycle
    /// never takes a bigger step.
    void set_period(double seconds) noexcept;
    /// Where the next step starts from: `from` (a vector of size()), or none
    /// (the next value is taken as it is and becomes the reference).
    void start_from(const double* from) noexcept;
    void start_from_zero() noexcept;
    void start_afresh() noexcept { has_reference_ = false; }
    /// Writes `target`, limited, to `out` (both size() doubles; may be the
    /// same); returns how many joints were clamped.
    std::size_t apply(const double* target, double* out) noexcept;

    std::size_t size() const noexcept { return limits_.size(); }

private:
    Kind kind_ = Kind::none;
    std::vector<double> limits_;
    std::vector<double> step_;       // rate: limit * period
    std::vector<double> reference_;  // rate: what apply() wrote last
    bool has_reference_ = false;
};

}  // namespace ddsbridge
