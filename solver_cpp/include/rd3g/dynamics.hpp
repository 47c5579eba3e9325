// Discrete-time agent dynamics x_{k+1} = f(x_k, u_k) with analytic first and second derivatives.
#pragma once
#include <Eigen/Dense>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "rd3g/jet.hpp"

namespace rd3g {

using Vec = Eigen::VectorXd;
using Mat = Eigen::MatrixXd;
using VecRef = Eigen::Ref<Vec>;
using MatRef = Eigen::Ref<Mat>;
using CVecRef = Eigen::Ref<const Vec>;
using Pattern = Eigen::Matrix<bool, Eigen::Dynamic, Eigen::Dynamic>;

/// A discrete-time model. Implementations keep value and derivatives together in one place,
/// and must not allocate in eval()/lambda_hessian() (the solver calls them in its hot loop).
class Dynamics {
 public:
  virtual ~Dynamics() = default;
  virtual int nx() const = 0;  ///< state dimension
  virtual int nu() const = 0;  ///< control dimension
  virtual std::string name() const = 0;
  /// x_next = f(x, u); A = df/dx (nx x nx), B = df/du (nx x nu).
  virtual void eval(const CVecRef& x, const CVecRef& u, VecRef x_next, MatRef A, MatRef B) const = 0;
  /// H = d^2 (lambda^T f) / d(x,u)^2, (nx+nu) x (nx+nu), ordered [x; u].
  virtual void lambda_hessian(const CVecRef& x, const CVecRef& u, const CVecRef& lambda, MatRef H) const = 0;
  /// eval and lambda_hessian at one point (the Newton assembly needs both); a model whose derivatives
  /// share one evaluation overrides it to evaluate once.
  virtual void eval_with_hessian(const CVecRef& x, const CVecRef& u, const CVecRef& lambda, VecRef x_next, MatRef A,
                                 MatRef B, MatRef H) const {
    eval(x, u, x_next, A, B);
    lambda_hessian(x, u, lambda, H);
  }
  /// Which entries of A (nx x nx), B (nx x nu) and H ((nx+nu) x (nx+nu), ordered [x; u]) can be nonzero at some
  /// (x, u, lambda); every other entry must be exactly 0 everywhere. The Newton matrix holds only these (one pattern
  /// per model, so its symbolic analyses are reused). Default: every entry.
  virtual void derivative_pattern(Pattern& A, Pattern& B, Pattern& H) const;
  /// The open box lo < u < hi of controls on which the model is smooth (control units; +-inf: no limit, the
  /// default). The solver keeps its steps inside it (Settings::domain_fraction).
  virtual void control_domain(VecRef lo, VecRef hi) const {
    lo.setConstant(-std::numeric_limits<double>::infinity());
    hi.setConstant(std::numeric_limits<double>::infinity());
  }
};

/// Controls [a, delta] of the bicycle models: a free, |delta| < pi/2 (the slip angle's jump).
void steering_domain(VecRef lo, VecRef hi);

/// x_{k+1} = A x_k + B u_k (for linear-quadratic games).
class LinearDynamics final : public Dynamics {
 public:
  LinearDynamics(Mat A, Mat B);
  int nx() const override { return static_cast<int>(A_.rows()); }
  int nu() const override { return static_cast<int>(B_.cols()); }
  std::string name() const override { return "linear"; }
  void eval(const CVecRef& x, const CVecRef& u, VecRef x_next, MatRef A, MatRef B) const override;
  void lambda_hessian(const CVecRef&, const CVecRef&, const CVecRef&, MatRef H) const override { H.setZero(); }
  /// A's and B's nonzero entries; H is zero.
  void derivative_pattern(Pattern& A, Pattern& B, Pattern& H) const override;
  const Mat& A() const { return A_; }
  const Mat& B() const { return B_; }

 private:
  Mat A_, B_;
};

/// Kinematic bicycle, explicit Euler. State [px (m), py (m), v (m/s), theta (rad)],
/// control [a (m/s^2), delta (rad)]. beta = atan(lr tan(delta) / (lf + lr)),
/// px' = v cos(theta + beta), py' = v sin(theta + beta), v' = a, theta' = v sin(beta) / lr.
class KinematicBicycle final : public Dynamics {
 public:
  KinematicBicycle(double lf, double lr, double dt);
  int nx() const override { return 4; }
  int nu() const override { return 2; }
  std::string name() const override { return "kinematic_bicycle"; }
  void eval(const CVecRef& x, const CVecRef& u, VecRef x_next, MatRef A, MatRef B) const override;
  void lambda_hessian(const CVecRef& x, const CVecRef& u, const CVecRef& lambda, MatRef H) const override;
  /// px and py enter linearly and a only in v': A has 9 entries, B 4, H 8 (among v, theta, delta).
  void derivative_pattern(Pattern& A, Pattern& B, Pattern& H) const override;
  /// |delta| < pi/2: beta = atan(c tan(delta)) jumps by pi there (sin(beta) from +1 to -1).
  void control_domain(VecRef lo, VecRef hi) const override { steering_domain(lo, hi); }
  double lf() const { return lf_; }
  double lr() const { return lr_; }
  double dt() const { return dt_; }

 private:
  double lf_, lr_, dt_;
};

/// Kinematic bicycle in track (Frenet) coordinates, explicit Euler.
/// State [s (m along the centre line), ey (m, left of the centre line), v (m/s), epsi (rad, heading
/// minus track heading)], control [a (m/s^2), delta (rad)]. Curvature kappa(s) (1/m) is a
/// piecewise-linear table on a uniform grid (periodic when closed), so the model is exact for the
/// table it is given:  s' = v cos(epsi + beta) / (1 - kappa ey),  ey' = v sin(epsi + beta),
/// v' = a,  epsi' = v sin(beta) / lr - kappa s'.
class KinematicBicycleFrenet final : public Dynamics {
 public:
  KinematicBicycleFrenet(double lf, double lr, double dt, Vec kappa, double ds, bool closed);
  int nx() const override { return 4; }
  int nu() const override { return 2; }
  std::string name() const override { return "kinematic_bicycle_frenet"; }
  void eval(const CVecRef& x, const CVecRef& u, VecRef x_next, MatRef A, MatRef B) const override;
  void lambda_hessian(const CVecRef& x, const CVecRef& u, const CVecRef& lambda, MatRef H) const override;
  void eval_with_hessian(const CVecRef& x, const CVecRef& u, const CVecRef& lambda, VecRef x_next, MatRef A,
                         MatRef B, MatRef H) const override;
  /// |delta| < pi/2, as KinematicBicycle.
  void control_domain(VecRef lo, VecRef hi) const override { steering_domain(lo, hi); }
  /// kappa(s) and dkappa/ds (piecewise constant slope of the linear interpolation).
  void curvature(double s, double& kappa, double& dkappa) const;

 private:
  /// The Euler step with exact derivatives wrt (x, u) on jets J (Jet1<6>: first, Jet2<6>: first and second):
  /// one place for eval, eval_with_hessian and lambda_hessian.
  template <class J>
  void step_jets(const CVecRef& x, const CVecRef& u, J (&out)[4]) const;
  double lf_, lr_, dt_;
  Vec kappa_;
  double ds_;
  bool closed_;
};

std::shared_ptr<Dynamics> make_linear(const Mat& A, const Mat& B);

}  // namespace rd3g
