// robotics/trajectory.hpp — point-to-point trajectory profiles through a list
// of via points, per axis, for joint (q) or Cartesian (pose 6-vector) space.
//
// Profiles over a segment from p0 to p1 of duration T, s = t/T:
//   linear:   p = p0 + (p1-p0) s                       (constant velocity)
//   lspb:     linear segment with parabolic blends of duration tb = blend*T at
//             both ends (velocity V = (p1-p0)/(T-tb), acceleration V/tb);
//   quintic:  p = p0 + (p1-p0)(10s^3 - 15s^4 + 6s^5)   (zero velocity and
//             acceleration at both ends).
// The via points are visited in order; when `cyclic`, the last goes back to the
// first and the sequence repeats; otherwise the trajectory holds the last point.
#pragma once

#include <cstddef>
#include <string_view>
#include <vector>

#include <Eigen/Core>

namespace chimera::robotics {

enum class Profile { linear, lspb, quintic };

/// "linear", "lspb" (also "parabolic"), "quintic"; false when unknown.
bool parse_profile(std::string_view name, Profile& out) noexcept;

class Trajectory {
public:
    /// `points` each of size `dim`, `durations[i]` the time from point i to i+1
    /// (or from the last back to the first when cyclic). Throws
    /// std::invalid_argument naming the bad item.
    Trajectory(std::size_t dim, std::vector<Eigen::VectorXd> points, std::vector<double> durations,
               Profile profile, bool cyclic, double blend = 0.2);

    std::size_t dim() const noexcept { return dim_; }
    /// Total time of one pass (the period when cyclic).
    double total_time() const noexcept { return total_; }
    /// Position, velocity and acceleration at time t >= 0 since the start.
    void evaluate(double t, Eigen::Ref<Eigen::VectorXd> p, Eigen::Ref<Eigen::VectorXd> v,
                  Eigen::Ref<Eigen::VectorXd> a) const noexcept;
    /// Replaces the first via point (the start), e.g. with the current position
    /// read on `on`, so the trajectory starts where the robot is.
    void set_start(const Eigen::Ref<const Eigen::VectorXd>& p0) noexcept;
    /// Replaces via point i and the duration of segment i (from point i to the
    /// next): re-plans a preallocated trajectory without touching the heap.
    /// Out of range, a wrong size or a duration <= 0 changes nothing.
    void set_point(std::size_t i, const Eigen::Ref<const Eigen::VectorXd>& p) noexcept;
    void set_duration(std::size_t i, double seconds) noexcept;
    /// The segment under way at time t (as evaluate sees it), as the times it
    /// started and ends, counted like t (a cyclic trajectory's later passes
    /// included). Past the end of a non-cyclic one: [total_time, total_time].
    struct Span { double start, end; };
    Span segment_at(double t) const noexcept;

private:
    std::size_t dim_;
    std::vector<Eigen::VectorXd> points_;
    std::vector<double> durations_;
    Profile profile_;
    bool cyclic_;
    double blend_;
    double total_ = 0;
};

/// One scalar segment of a profile (exposed for tests).
void profile_eval(Profile profile, double blend, double p0, double p1, double T, double t,
                  double& p, double& v, double& a) noexcept;

}  // namespace chimera::robotics
