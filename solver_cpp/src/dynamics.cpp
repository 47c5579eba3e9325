#include "rd3g/dynamics.hpp"

#include <cmath>
#include <limits>
#include <stdexcept>

#include "rd3g/jet.hpp"

namespace rd3g {

LinearDynamics::LinearDynamics(Mat A, Mat B) : A_(std::move(A)), B_(std::move(B)) {
  if (A_.rows() != A_.cols()) throw std::invalid_argument("A must be square");
  if (B_.rows() != A_.rows()) throw std::invalid_argument("B must have as many rows as A");
}

void LinearDynamics::eval(const CVecRef& x, const CVecRef& u, VecRef x_next, MatRef A, MatRef B) const {
  x_next.noalias() = A_ * x + B_ * u;
  A = A_;
  B = B_;
}

void Dynamics::derivative_pattern(Pattern& A, Pattern& B, Pattern& H) const {
  A.setConstant(nx(), nx(), true);
  B.setConstant(nx(), nu(), true);
  H.setConstant(nx() + nu(), nx() + nu(), true);
}

void LinearDynamics::derivative_pattern(Pattern& A, Pattern& B, Pattern& H) const {
  A = A_.array() != 0.0;
  B = B_.array() != 0.0;
  H.setConstant(nx() + nu(), nx() + nu(), false);
}

std::shared_ptr<Dynamics> make_linear(const Mat& A, const Mat& B) { return std::make_shared<LinearDynamics>(A, B); }

void steering_domain(VecRef lo, VecRef hi) {
  const double inf = std::numeric_limits<double>::infinity(), half_pi = 0.5 * M_PI;
  lo << -inf, -half_pi;
  hi << inf, half_pi;
}

// ---------------------------------------------------------------------------------------------
KinematicBicycle::KinematicBicycle(double lf, double lr, double dt) : lf_(lf), lr_(lr), dt_(dt) {
  if (!(lf > 0) || !(lr > 0)) throw std::invalid_argument("lf and lr must be positive");
  if (!(dt > 0)) throw std::invalid_argument("dt must be positive");
}

namespace {
// Slip angle beta(delta) = atan(c tan(delta)), c = lr / (lf + lr), and its first two derivatives.
struct Slip {
  double b, db, ddb;
};
inline Slip slip_angle(double delta, double c) {
  const double t = std::tan(delta), s = 1.0 + t * t, q = 1.0 + c * c * t * t;
  return {std::atan(c * t), c * s / q, 2.0 * c * t * s * (1.0 - c * c) / (q * q)};
}
}  // namespace

void KinematicBicycle::eval(const CVecRef& x, const CVecRef& u, VecRef xn, MatRef A, MatRef B) const {
  const double v = x[2], th = x[3], a = u[0];
  const Slip sl = slip_angle(u[1], lr_ / (lf_ + lr_));
  const double phi = th + sl.b, c = std::cos(phi), s = std::sin(phi);
  const double sb = std::sin(sl.b), cb = std::cos(sl.b);
  xn[0] = x[0] + dt_ * v * c;
  xn[1] = x[1] + dt_ * v * s;
  xn[2] = v + dt_ * a;
  xn[3] = th + dt_ * v * sb / lr_;
  A.setIdentity();
  A(0, 2) = dt_ * c;
  A(0, 3) = -dt_ * v * s;
  A(1, 2) = dt_ * s;
  A(1, 3) = dt_ * v * c;
  A(3, 2) = dt_ * sb / lr_;
  B.setZero();
  B(0, 1) = -dt_ * v * s * sl.db;
  B(1, 1) = dt_ * v * c * sl.db;
  B(2, 0) = dt_;
  B(3, 1) = dt_ * v * cb * sl.db / lr_;
}

void KinematicBicycle::derivative_pattern(Pattern& A, Pattern& B, Pattern& H) const {
  // As eval and lambda_hessian write them; z = (px, py, v, theta, a, delta).
  A.setConstant(4, 4, false);
  A.diagonal().setConstant(true);
  A(0, 2) = A(0, 3) = A(1, 2) = A(1, 3) = A(3, 2) = true;
  B.setConstant(4, 2, false);
  B(0, 1) = B(1, 1) = B(2, 0) = B(3, 1) = true;
  H.setConstant(6, 6, false);
  for (int r : {2, 3, 5})
    for (int c : {2, 3, 5}) H(r, c) = true;
  H(2, 2) = false;  // v enters each term linearly
}

void KinematicBicycle::lambda_hessian(const CVecRef& x, const CVecRef& u, const CVecRef& l, MatRef H) const {
  // Variables z = (px, py, v, theta, a, delta) = indices 0..5. Only v, theta, delta enter nonlinearly.
  const double v = x[2], th = x[3];
  const Slip sl = slip_angle(u[1], lr_ / (lf_ + lr_));
  const double phi = th + sl.b, c = std::cos(phi), s = std::sin(phi);
  const double sb = std::sin(sl.b), cb = std::cos(sl.b);
  const double b1 = sl.db, b2 = sl.ddb;
  H.setZero();
  // f0 = px + dt v cos(phi), f1 = py + dt v sin(phi), f3 = theta + dt v sin(beta) / lr
  const double vth = dt_ * (-l[0] * s + l[1] * c);
  const double vde = dt_ * (-l[0] * s * b1 + l[1] * c * b1 + l[3] * cb * b1 / lr_);
  const double thth = dt_ * v * (-l[0] * c - l[1] * s);
  const double thde = dt_ * v * (-l[0] * c * b1 - l[1] * s * b1);
  const double dede = dt_ * v *
                      (l[0] * (-c * b1 * b1 - s * b2) + l[1] * (-s * b1 * b1 + c * b2) +
                       l[3] * (-sb * b1 * b1 + cb * b2) / lr_);
  H(2, 3) = H(3, 2) = vth;
  H(2, 5) = H(5, 2) = vde;
  H(3, 3) = thth;
  H(3, 5) = H(5, 3) = thde;
  H(5, 5) = dede;
}

// ---------------------------------------------------------------------------------------------
KinematicBicycleFrenet::KinematicBicycleFrenet(double lf, double lr, double dt, Vec kappa, double ds, bool closed)
    : lf_(lf), lr_(lr), dt_(dt), kappa_(std::move(kappa)), ds_(ds), closed_(closed) {
  if (!(lf > 0) || !(lr > 0)) throw std::invalid_argument("lf and lr must be positive");
  if (!(dt > 0)) throw std::invalid_argument("dt must be positive");
  if (kappa_.size() < 2) throw std::invalid_argument("curvature table needs at least 2 samples");
  if (!(ds > 0)) throw std::invalid_argument("curvature table spacing ds must be positive");
  if (!kappa_.allFinite()) throw std::invalid_argument("curvature table has non-finite values");
}

void KinematicBicycleFrenet::curvature(double s, double& kappa, double& dkappa) const {
  const int n = static_cast<int>(kappa_.size());
  if (!std::isfinite(s)) {  // propagate instead of indexing the table with garbage
    kappa = dkappa = std::numeric_limits<double>::quiet_NaN();
    return;
  }
  double q = s / ds_;
  int i0;
  double w;
  if (closed_) {
    // Table covers [0, n ds) periodically: sample n wraps to sample 0.
    q = std::fmod(q, static_cast<double>(n));
    if (q < 0) q += n;
    i0 = std::min(static_cast<int>(std::floor(q)), n - 1);
    w = q - i0;
    const int i1 = (i0 + 1) % n;
    kappa = (1 - w) * kappa_[i0] + w * kappa_[i1];
    dkappa = (kappa_[i1] - kappa_[i0]) / ds_;
  } else {
    // Open table covers [0, (n-1) ds]; constant extrapolation beyond the ends.
    if (q <= 0) { kappa = kappa_[0]; dkappa = 0; return; }
    if (q >= n - 1) { kappa = kappa_[n - 1]; dkappa = 0; return; }
    i0 = static_cast<int>(std::floor(q));
    w = q - i0;
    kappa = (1 - w) * kappa_[i0] + w * kappa_[i0 + 1];
    dkappa = (kappa_[i0 + 1] - kappa_[i0]) / ds_;
  }
}

namespace {
// One Euler step on jets J (Jet2<6> for value, Jacobian and Hessian, Jet1<6> for value and Jacobian).
template <class J>
void frenet_step(const J (&z)[6], double kappa0, double dkappa, double s0, double lf, double lr, double dt,
                 J (&out)[4]) {
  // kappa is linear in s within a table cell: kappa(s) = kappa0 + dkappa (s - s0).
  const J kap = J::constant(kappa0) + dkappa * (z[0] - s0);
  const J beta = atan((lr / (lf + lr)) * tan(z[5]));
  const J phi = z[3] + beta;
  const J sdot = z[2] * cos(phi) / (1.0 - kap * z[1]);
  out[0] = z[0] + dt * sdot;
  out[1] = z[1] + dt * (z[2] * sin(phi));
  out[2] = z[2] + dt * z[4];
  out[3] = z[3] + dt * (z[2] * sin(beta) * (1.0 / lr) - kap * sdot);
}
}  // namespace

template <class J>
void KinematicBicycleFrenet::step_jets(const CVecRef& x, const CVecRef& u, J (&out)[4]) const {
  J z[6];
  for (int i = 0; i < 4; ++i) z[i] = J::variable(x[i], i);
  z[4] = J::variable(u[0], 4);
  z[5] = J::variable(u[1], 5);
  double k0, dk;
  curvature(x[0], k0, dk);
  frenet_step(z, k0, dk, x[0], lf_, lr_, dt_, out);
}

void KinematicBicycleFrenet::eval(const CVecRef& x, const CVecRef& u, VecRef xn, MatRef A, MatRef B) const {
  Jet1<6> out[4];  // no Hessian needed here (line search, rollouts)
  step_jets(x, u, out);
  for (int r = 0; r < 4; ++r) {
    xn[r] = out[r].v;
    A.row(r) = out[r].g.head<4>().transpose();
    B.row(r) = out[r].g.tail<2>().transpose();
  }
}

void KinematicBicycleFrenet::eval_with_hessian(const CVecRef& x, const CVecRef& u, const CVecRef& l, VecRef xn,
                                               MatRef A, MatRef B, MatRef H) const {
  Jet2<6> out[4];
  step_jets(x, u, out);
  H.setZero();
  for (int r = 0; r < 4; ++r) {
    xn[r] = out[r].v;
    A.row(r) = out[r].g.head<4>().transpose();
    B.row(r) = out[r].g.tail<2>().transpose();
    H += l[r] * out[r].h;
  }
}

void KinematicBicycleFrenet::lambda_hessian(const CVecRef& x, const CVecRef& u, const CVecRef& l, MatRef H) const {
  Jet2<6> out[4];
  step_jets(x, u, out);
  H.setZero();
  for (int r = 0; r < 4; ++r) H += l[r] * out[r].h;
}

}  // namespace rd3g
