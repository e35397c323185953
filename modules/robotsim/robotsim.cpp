// robotsim — simulated manipulator as a robot-interface SAI module (thesis §7.3,
// "transparent simulation"): it integrates the arm's rigid-body dynamics at its
// own rate and publishes measured joint positions and velocities, and the NDOF
// and DH out-consts other modules configure themselves from (§3.5).
//
// Ports (internal names; SVARALIAS may rename them):
//   OUTCONST NDOF (int), DH (double[18*(NDOF+1)], layout in robotics/model.hpp)
//   INVAR    torque mode:   T_REF            joint torques (N m)
//            position mode: Q_REF            reference joint positions (rad)
//                           [Q^_REF]         reference joint velocities (rad/s), optional
//                           [T_GRAV]         gravity feed-forward (N m), optional; without
//                                            it the simulated servo uses its own model
//   OUTVAR   Q_MEZ, [Q^_MEZ]  measured joint positions (rad) and velocities (rad/s)
//            [T_MEZ]          the joint torques applied (N m), after every limit
// LOCAL: see README.md. With VLIMIT or TRATE every torque the arm gets (the
// command, the position servo's, the hold loop's) goes through a JointLimiter
// (robotics/limits.hpp); `get LIMITS` answers how often each limit acted.
#include <chimera/module.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <optional>

#include "robotics/dynamics.hpp"
#include "robotics/limits.hpp"
#include "robotics/pid.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kRobotSimLocalKeys[] = {
    {"ROBOT", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, false, "puma560 | planar2 | urdf FILE ROOT-LINK TIP-LINK", "puma560"},
    {"MODE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "torque | position (joint servo inside the simulator)", "torque"},
    {"SUBSTEPS", chimera::LocalType::integer, 1.0, 10000.0, false, "integration steps per cycle", "10"},
    {"Q0", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "initial joint positions (rad)", "0"},
    {"SERVO_KP", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "position mode: servo proportional gain", "400"},
    {"SERVO_KI", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "position mode: servo integral gain", "0"},
    {"SERVO_KD", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "position mode: servo derivative gain", "40"},
    {"TLIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "torque limit per joint (N m)", "1e9"},
    {"VLIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "joint speed limit per joint (rad/s): torque-speed envelope; none: no limit", ""},
    {"TRATE", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "torque rate limit per joint (N m/s); none: no limit", ""},
    {"FRICTION_COMP", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "yes | no: position mode: the servo feeds the model's Coulomb friction forward", "yes"},
    {"STABILITY", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "hold | none: what the robot does while the configuration is illegal", "hold"},
};

class RobotSim : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kRobotSimLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        model_ = rb::robot_from_local(t);
        n_ = model_.ndof();
        const std::string mode = rb::local_word(t, "MODE", "torque");
        if (mode != "torque" && mode != "position") {
            rb::module_error(t, "LOCAL MODE '" + mode + "': expected torque or position");
        }
        position_mode_ = mode == "position";

        // Out-consts: written here, copied to the global table after init.
        if (rb::listed(t.rmod_file().out_consts, "NDOF")) {
            *t.translate<std::int32_t>("NDOF") = static_cast<std::int32_t>(n_);
        }
        if (rb::listed(t.rmod_file().out_consts, "DH")) {
            if (!model_.has_dh()) {
                rb::module_error(t, "robot " + model_.name() +
                                        " has no DH parameters; remove DH from OUTCONST");
            }
            model_.pack_dh(std::span<double>(rb::vec_port(t, "DH", rb::dh_size(n_)), rb::dh_size(n_)));
        }

        if (position_mode_) {
            q_ref_ = rb::vec_port(t, "Q_REF", n_);
            if (rb::has_in_var(t, "Q^_REF")) qd_ref_ = rb::vec_port(t, "Q^_REF", n_);
            if (rb::has_in_var(t, "T_GRAV")) t_grav_ = rb::vec_port(t, "T_GRAV", n_);
        } else {
            t_ref_ = rb::vec_port(t, "T_REF", n_);
        }
        q_mez_ = rb::vec_port(t, "Q_MEZ", n_);
        if (rb::has_out_var(t, "Q^_MEZ")) qd_mez_ = rb::vec_port(t, "Q^_MEZ", n_);
        if (rb::has_out_var(t, "T_MEZ")) t_mez_ = rb::vec_port(t, "T_MEZ", n_);

        substeps_ = static_cast<int>(rb::local_number(t, "SUBSTEPS", 10));
        if (substeps_ < 1 || substeps_ > 1000) rb::module_error(t, "LOCAL SUBSTEPS must be 1..1000");
        tlimit_ = rb::local_vector(t, "TLIMIT", n_, 1e9);
        init_limiter(t);
        // Servo of the simulated position-mode controller, and the local-stability
        // loop (§3.10) of both modes: PD on the held position plus gravity.
        rb::PidGains g{rb::local_vector(t, "SERVO_KP", n_, 400.0), rb::local_vector(t, "SERVO_KI", n_, 0.0),
                       rb::local_vector(t, "SERVO_KD", n_, 40.0), Eigen::VectorXd::Constant(n_, 1.0), tlimit_};
        servo_.emplace(n_, g);
        hold_servo_.emplace(n_, g);
        hold_on_illegal_ = rb::local_word(t, "STABILITY", "hold") == "hold";
        const std::string comp = rb::local_word(t, "FRICTION_COMP", "yes");
        if (comp != "yes" && comp != "no") rb::module_error(t, "LOCAL FRICTION_COMP '" + comp + "': expected yes or no");
        friction_comp_ = comp == "yes";

        sim_ = std::make_unique<rb::ArmSimulator>(model_);
        dyn_ = std::make_unique<rb::Dynamics>(model_);
        const Eigen::VectorXd q0 = rb::local_vector(t, "Q0", n_, 0.0);
        sim_->reset(q0, Eigen::VectorXd::Zero(n_));
        tau_.setZero(n_);
        q_ref_prev_.setZero(n_);
        grav_.setZero(n_);
        zero_.setZero(n_);
        hold_.setZero(n_);
        bias_.setZero(n_);
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task&) override {
        publish();  // the out-vars read on `on` are replaced by the arm's real state
        servo_->reset();
        if (q_ref_) q_ref_prev_ = Eigen::Map<const Eigen::VectorXd>(q_ref_, static_cast<Eigen::Index>(n_));
        holding_ = false;
        if (limiter_) {
            // The rate limit starts from the torque that holds the arm where it
            // is (a brake or a hold loop carried it until now), not from zero.
            dyn_->gravity(sim_->q(), bias_);
            limiter_->reset(bias_);
        }
        return chimera::Result::OK;
    }

    // get LIMITS: "speed_clamps N rate_clamps M" (joint-cycles each limit changed
    // the torque), or "none" without VLIMIT and TRATE.
    chimera::Result get(chimera::Task& t) override {
        if (t.arg() != "LIMITS") return chimera::Result::OK;
        t.reply(limiter_ ? "speed_clamps " + std::to_string(limiter_->speed_clamps()) + " rate_clamps " +
                               std::to_string(limiter_->rate_clamps())
                         : std::string("none"));
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        const Eigen::VectorXd& q = sim_->q();
        const Eigen::VectorXd& qd = sim_->qd();
        if (hold_on_illegal_ && t.illegal_configuration()) {
            // Locally stable execution: ignore the inputs, hold where we are.
            if (!holding_) {
                hold_ = q;
                hold_servo_->reset();
                holding_ = true;
            }
            dyn_->gravity(q, grav_);
            hold_servo_->update(hold_, zero_, q, qd, grav_, t.period(), tau_);
        } else {
            holding_ = false;
            if (position_mode_) {
                const Eigen::Map<const Eigen::VectorXd> qr(q_ref_, n);
                if (t_grav_) {
                    grav_ = Eigen::Map<const Eigen::VectorXd>(t_grav_, n);
                } else {
                    dyn_->gravity(q, grav_);
                }
                if (qd_ref_) {
                    servo_->update(qr, Eigen::Map<const Eigen::VectorXd>(qd_ref_, n), q, qd, grav_,
                                   t.period(), tau_);
                } else {
                    servo_->update(qr, zero_, q, qd, grav_, t.period(), tau_);
                }
                if (friction_comp_) add_friction_compensation(qr, q, t.period());
                q_ref_prev_ = qr;
            } else {
                tau_ = Eigen::Map<const Eigen::VectorXd>(t_ref_, n).cwiseMax(-tlimit_).cwiseMin(tlimit_);
            }
        }
        if (limiter_) {
            dyn_->gravity(q, bias_);
            limiter_->apply(tau_, qd, bias_, t.period());
        }
        if (!sim_->step(tau_, t.period(), substeps_)) {
            return t.error(1, "simulation diverged (non-finite state): torques too large for the step size");
        }
        publish();
        return chimera::Result::OK;
    }

private:
    // VLIMIT and TRATE: optional, each absent meaning no limit of its kind.
    void init_limiter(chimera::Task& t) {
        if (!t.local().has("VLIMIT") && !t.local().has("TRATE")) return;
        constexpr double none = std::numeric_limits<double>::infinity();
        try {
            limiter_.emplace(rb::JointLimits{tlimit_, rb::local_vector(t, "VLIMIT", n_, none),
                                             rb::local_vector(t, "TRATE", n_, none)});
        } catch (const std::invalid_argument& e) {
            rb::module_error(t, std::string("LOCAL ") + e.what());
        }
    }

    // The drive's Coulomb friction feed-forward (a real position servo's, e.g.
    // Corke's for the PUMA): the model's Tc in the direction the reference
    // moves (Q^_REF, or Q_REF's change over the cycle); with the reference at
    // rest, in the direction of the position error, scaled down within 1 mrad
    // of it so the joint settles instead of chattering about the set-point.
    void add_friction_compensation(const Eigen::Ref<const Eigen::VectorXd>& qr, const Eigen::VectorXd& q,
                                   double period) noexcept {
        constexpr double settle_band = 1e-3;  // rad
        for (std::size_t j = 0; j < n_; ++j) {
            const auto i = static_cast<Eigen::Index>(j);
            const double v = qd_ref_ ? qd_ref_[j] : (qr[i] - q_ref_prev_[i]) / period;
            double f = dyn_->coulomb(j, v);
            if (v == 0) {
                const double e = qr[i] - q[i];
                f = dyn_->coulomb(j, e) * std::min(1.0, std::fabs(e) / settle_band);
            }
            tau_[i] = std::clamp(tau_[i] + f, -tlimit_[i], tlimit_[i]);
        }
    }

    void publish() noexcept {
        const auto n = static_cast<Eigen::Index>(n_);
        Eigen::Map<Eigen::VectorXd>(q_mez_, n) = sim_->q();
        if (qd_mez_) Eigen::Map<Eigen::VectorXd>(qd_mez_, n) = sim_->qd();
        if (t_mez_) Eigen::Map<Eigen::VectorXd>(t_mez_, n) = tau_;
    }

    rb::RobotModel model_;
    std::size_t n_ = 0;
    bool position_mode_ = false;
    bool hold_on_illegal_ = true;
    bool holding_ = false;
    bool friction_comp_ = true;
    int substeps_ = 10;
    double* q_ref_ = nullptr;
    double* qd_ref_ = nullptr;
    double* t_grav_ = nullptr;
    double* t_ref_ = nullptr;
    double* q_mez_ = nullptr;
    double* qd_mez_ = nullptr;
    double* t_mez_ = nullptr;
    std::optional<rb::JointLimiter> limiter_;
    std::unique_ptr<rb::ArmSimulator> sim_;
    std::unique_ptr<rb::Dynamics> dyn_;
    std::optional<rb::Pid> servo_, hold_servo_;
    Eigen::VectorXd tau_, grav_, zero_, hold_, tlimit_, q_ref_prev_, bias_;
};

}  // namespace

CHIMERA_MODULE(robotsim, RobotSim)
