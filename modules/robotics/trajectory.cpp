// Trajectory profiles: linear, parabolic blend (LSPB), quintic.
#include "robotics/trajectory.hpp"

#include <cmath>
#include <stdexcept>
#include <string>

namespace chimera::robotics {

bool parse_profile(std::string_view name, Profile& out) noexcept {
    if (name == "linear") {
        out = Profile::linear;
    } else if (name == "lspb" || name == "parabolic") {
        out = Profile::lspb;
    } else if (name == "quintic") {
        out = Profile::quintic;
    } else {
        return false;
    }
    return true;
}

void profile_eval(Profile profile, double blend, double p0, double p1, double T, double t,
                  double& p, double& v, double& a) noexcept {
    const double dp = p1 - p0;
    if (t <= 0) t = 0;
    if (t >= T) t = T;
    switch (profile) {
        case Profile::linear:
            p = p0 + dp * t / T;
            v = dp / T;
            a = 0;
            // At the end of a non-cyclic motion the velocity drops to zero.
            if (t >= T) v = 0;
            return;
        case Profile::lspb: {
            const double tb = blend * T;
            const double vmax = dp / (T - tb);
            const double acc = vmax / tb;
            if (t < tb) {
                p = p0 + 0.5 * acc * t * t;
                v = acc * t;
                a = acc;
            } else if (t <= T - tb) {
                p = p0 + 0.5 * acc * tb * tb + vmax * (t - tb);
                v = vmax;
                a = 0;
            } else {
                const double r = T - t;
                p = p1 - 0.5 * acc * r * r;
                v = acc * r;
                a = -acc;
            }
            return;
        }
        case Profile::quintic: {
            const double s = t / T;
            const double s2 = s * s, s3 = s2 * s;
            p = p0 + dp * (10 * s3 - 15 * s3 * s + 6 * s3 * s2);
            v = dp * (30 * s2 - 60 * s3 + 30 * s3 * s) / T;
            a = dp * (60 * s - 180 * s2 + 120 * s3) / (T * T);
            return;
        }
    }
}

Trajectory::Trajectory(std::size_t dim, std::vector<Eigen::VectorXd> points,
                       std::vector<double> durations, Profile profile, bool cyclic, double blend)
    : dim_(dim),
      points_(std::move(points)),
      durations_(std::move(durations)),
      profile_(profile),
      cyclic_(cyclic),
      blend_(blend) {
    if (points_.empty()) throw std::invalid_argument("trajectory has no via point");
    for (std::size_t i = 0; i < points_.size(); ++i) {
        if (static_cast<std::size_t>(points_[i].size()) != dim_) {
            throw std::invalid_argument("via point " + std::to_string(i + 1) + " has " +
                                        std::to_string(points_[i].size()) + " values, expected " +
                                        std::to_string(dim_));
        }
    }
    const std::size_t segments = cyclic_ ? points_.size() : points_.size() - 1;
    if (durations_.size() != segments) {
        throw std::invalid_argument("trajectory with " + std::to_string(points_.size()) +
                                    " via points needs " + std::to_string(segments) +
                                    " durations, has " + std::to_string(durations_.size()));
    }
    for (std::size_t i = 0; i < durations_.size(); ++i) {
        if (!(durations_[i] > 0)) {
            throw std::invalid_argument("duration " + std::to_string(i + 1) + " must be > 0");
        }
        total_ += durations_[i];
    }
    if (profile_ == Profile::lspb && !(blend_ > 0 && blend_ <= 0.5)) {
        throw std::invalid_argument("parabolic blend fraction must be in (0, 0.5]");
    }
}

void Trajectory::set_start(const Eigen::Ref<const Eigen::VectorXd>& p0) noexcept {
    if (static_cast<std::size_t>(p0.size()) == dim_) points_.front() = p0;
}

void Trajectory::set_point(std::size_t i, const Eigen::Ref<const Eigen::VectorXd>& p) noexcept {
    if (i < points_.size() && static_cast<std::size_t>(p.size()) == dim_) points_[i] = p;
}

void Trajectory::set_duration(std::size_t i, double seconds) noexcept {
    if (i >= durations_.size() || !(seconds > 0)) return;
    total_ += seconds - durations_[i];
    durations_[i] = seconds;
}

Trajectory::Span Trajectory::segment_at(double t) const noexcept {
    if (durations_.empty()) return {0, 0};
    if (t < 0) t = 0;
    double pass_start = 0;  // the start of the pass (of a cyclic trajectory) t is in
    if (cyclic_) {
        pass_start = t - std::fmod(t, total_);
    } else if (t >= total_) {
        return {total_, total_};
    }
    double start = pass_start;
    for (std::size_t seg = 0; seg < durations_.size(); ++seg) {
        const double end = start + durations_[seg];
        if (t < end || seg + 1 == durations_.size()) return {start, end};
        start = end;
    }
    return {start, start};  // not reached
}

void Trajectory::evaluate(double t, Eigen::Ref<Eigen::VectorXd> p, Eigen::Ref<Eigen::VectorXd> v,
                          Eigen::Ref<Eigen::VectorXd> a) const noexcept {
    if (durations_.empty()) {
        p = points_.front();
        v.setZero();
        a.setZero();
        return;
    }
    if (t < 0) t = 0;
    if (cyclic_) {
        t = std::fmod(t, total_);
    } else if (t >= total_) {
        p = points_.back();
        v.setZero();
        a.setZero();
        return;
    }
    std::size_t seg = 0;
    while (seg + 1 < durations_.size() && t >= durations_[seg]) {
        t -= durations_[seg];
        ++seg;
    }
    const Eigen::VectorXd& from = points_[seg];
    const Eigen::VectorXd& to = points_[(seg + 1) % points_.size()];
    for (std::size_t i = 0; i < dim_; ++i) {
        const auto k = static_cast<Eigen::Index>(i);
        profile_eval(profile_, blend_, from[k], to[k], durations_[seg], t, p[k], v[k], a[k]);
    }
}

}  // namespace chimera::robotics
