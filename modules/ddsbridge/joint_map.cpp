// joint_map.cpp — a JointState matched by name, and the consumer-side limits (joint_map.hpp).
#include "joint_map.hpp"

#include <algorithm>
#include <stdexcept>

namespace ddsbridge {

const char* to_string(Refusal r) noexcept {
    switch (r) {
        case Refusal::none: return "none";
        case Refusal::length: return "length";
        case Refusal::unnamed: return "unnamed";
        case Refusal::unknown: return "unknown";
        case Refusal::duplicate: return "duplicate";
        case Refusal::partial: return "partial";
        case Refusal::reordered: return "reordered";
    }
    return "?";
}

JointMap::JointMap(std::vector<std::string> names, JointOptions options)
    : names_(std::move(names)), options_(options) {
    for (std::size_t j = 0; j < names_.size(); ++j) sorted_.emplace_back(names_[j], j);
    std::sort(sorted_.begin(), sorted_.end());
    for (std::size_t j = 1; j < sorted_.size(); ++j)
        if (sorted_[j].first == sorted_[j - 1].first)
            throw std::invalid_argument("joint name '" + std::string(sorted_[j].first) + "' is given twice");
    // A message of more names than joints names one twice or an unknown one
    // within its first size() + 1 names: the scratch never needs more.
    target_.assign(names_.size() + 1, 0);
    named_in_.assign(names_.size(), 0);
    reset();
}

void JointMap::reset() noexcept {
    known_.assign(names_.size(), false);  // same size: no allocation
    unknown_left_ = names_.size();
}

std::size_t JointMap::index_of(std::string_view name) const noexcept {
    const auto it = std::lower_bound(sorted_.begin(), sorted_.end(), name,
                                     [](const auto& entry, std::string_view n) { return entry.first < n; });
    return it != sorted_.end() && it->first == name ? it->second : names_.size();
}

Applied JointMap::apply(std::span<const char* const> names, std::span<const double> values, double* joints) noexcept {
    const Applied a = check(names, values);
    return a.refusal != Refusal::none ? a : commit(names, values, joints);
}

Applied JointMap::check(std::span<const char* const> names, std::span<const double> values) noexcept {
    if (names.empty()) {
        if (!options_.accept_unnamed) return {Refusal::unnamed, 0, false};
        if (values.size() != names_.size()) return {Refusal::length, 0, false};
        return {};
    }
    if (values.size() != names.size()) return {Refusal::length, 0, false};
    // Every name before any value: a refused message changes nothing.
    if (++generation_ == 0) {  // wrapped: forget every old generation
        std::fill(named_in_.begin(), named_in_.end(), 0u);
        generation_ = 1;
    }
    for (std::size_t i = 0; i < names.size(); ++i) {
        const std::size_t joint = index_of(names[i] ? std::string_view(names[i]) : std::string_view());
        if (joint == names_.size()) return {Refusal::unknown, i, false};
        if (named_in_[joint] == generation_) return {Refusal::duplicate, i, false};
        named_in_[joint] = generation_;
        target_[i] = joint;  // i < size(): the checks above end a longer message before its last name
    }
    if (options_.refuse_subset && names.size() != names_.size()) return {Refusal::partial, 0, false};
    return {};
}

Applied JointMap::commit(std::span<const char* const> names, std::span<const double> values, double* joints) noexcept {
    if (names.empty()) {
        std::copy(values.begin(), values.end(), joints);
        known_.assign(names_.size(), true);
        unknown_left_ = 0;
        return {Refusal::none, 0, true};
    }
    for (std::size_t i = 0; i < names.size(); ++i) {
        const std::size_t joint = target_[i];
        joints[joint] = values[i];
        if (!known_[joint]) {
            known_[joint] = true;
            --unknown_left_;
        }
    }
    return {Refusal::none, 0, unknown_left_ == 0};
}

JointLimiter::JointLimiter(Kind kind, std::vector<double> limits)
    : kind_(kind), limits_(std::move(limits)), step_(limits_), reference_(limits_.size(), 0.0) {
    for (const double l : limits_)
        if (!(l > 0)) throw std::invalid_argument("a limit must be > 0");
}

void JointLimiter::set_period(double seconds) noexcept {
    for (std::size_t j = 0; j < limits_.size(); ++j) step_[j] = limits_[j] * seconds;
}

void JointLimiter::start_from(const double* from) noexcept {
    std::copy(from, from + reference_.size(), reference_.begin());
    has_reference_ = true;
}

void JointLimiter::start_from_zero() noexcept {
    std::fill(reference_.begin(), reference_.end(), 0.0);
    has_reference_ = true;
}

std::size_t JointLimiter::apply(const double* target, double* out) noexcept {
    std::size_t clamped = 0;
    const std::size_t n = limits_.size();
    for (std::size_t j = 0; j < n; ++j) {
        double v = target[j];
        if (kind_ == Kind::magnitude) {
            if (v > limits_[j] || v < -limits_[j]) {
                v = std::clamp(v, -limits_[j], limits_[j]);
                ++clamped;
            }
        } else if (kind_ == Kind::rate && has_reference_) {
            const double lo = reference_[j] - step_[j], hi = reference_[j] + step_[j];
            if (v > hi || v < lo) {
                v = std::clamp(v, lo, hi);
                ++clamped;
            }
        }
        out[j] = v;
    }
    if (kind_ == Kind::rate) start_from(out);
    return clamped;
}

}  // namespace ddsbridge
