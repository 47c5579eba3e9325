// One Newton (or Levenberg-Marquardt) step: the backtracking line search, the fraction-to-boundary and
// model-domain step limits.
#include "rd3g/solver.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "rd3g/clock.hpp"

namespace rd3g {

namespace {
// Fixed constants (settings before; never set by any caller): the primal-dual barrier keeps z >= (1 - 0.99) z along a
// step (IPOPT's fraction to the boundary), and a step backtracked to a crossing stops at 0.99 of it;
// Levenberg-Marquardt's nu = 1e-6 10^q ||r||.
constexpr double kFractionToBoundary = 0.99;
constexpr double kLmNuInit = 1e-6;
}  // namespace

void Solver::apply_step(const Iterate& y, const Vec& dy, double t, Iterate& out) const {
  // Plain loops over the stage blocks (this runs for every line-search trial; Eigen's expressions on 2- and
  // 4-element dynamic columns cost several times the arithmetic).
  const double* d = dy.data();
  for (int i = 0; i < N_; ++i) {
    const double *yu = y.u[i].data(), *yl = y.lam[i].data(), *yx = y.x[i].data();
    double *ou = out.u[i].data(), *ol = out.lam[i].data(), *ox = out.x[i].data();
    for (int q = 0; q < nx_; ++q) ox[q] = yx[q];
    for (int k = 0; k < T_; ++k) {
      const double *du = d + col_u(i, k), *dl = d + col_lam(i, k), *dx = d + col_x(i, k + 1);
      for (int q = 0; q < nu_; ++q) ou[k * nu_ + q] = yu[k * nu_ + q] + t * du[q];
      for (int q = 0; q < nx_; ++q) ol[k * nx_ + q] = yl[k * nx_ + q] + t * dl[q];
      for (int q = 0; q < nx_; ++q) ox[(k + 1) * nx_ + q] = yx[(k + 1) * nx_ + q] + t * dx[q];
    }
  }
  const int C = static_cast<int>(cons_.size());
  for (int c = 0; c < C; ++c) {
    out.mu[c] = mu_col_[c] >= 0 ? y.mu[c] + t * d[mu_col_[c]] : y.mu[c];
    out.mu2[c] = mu2_col_[c] >= 0 ? y.mu2[c] + t * d[mu2_col_[c]] : y.mu2[c];
    out.z[c] = y.z[c] + t * dz_[c];
  }
}

// Backtracking line search (paper, Algorithm 1), with the partition and rho of this iteration:
// accept t when ||r(y + t dy)|| <= (1 - alpha t) ||r(y)|| and the total violation does not exceed the
// largest of the last violation_memory iterates' (1: does not grow). In the game's attempts the first trial stops just
// before the first bound it would cross, and a rejected t shrinks by beta, or after a trial that crossed constraints,
// once rho has fallen, to just before the first crossing.
double Solver::line_search(double merit0) {
  double hsum = violation_sum(h_);
  const int mem = std::min<int>(rules_.violation_memory, static_cast<int>(violations_.size()));
  for (int q = 0; q < mem; ++q) hsum = std::max(hsum, violations_[violations_.size() - 1 - q]);
  double t = 1.0;
  if (barrier_ == BarrierMode::PrimalDual) {
    recover_dual_step(y_, h_, rc_, dy_, dz_);
    // Fraction to the boundary: barrier duals stay positive.
    for (int c = 0; c < static_cast<int>(cons_.size()); ++c)
      if (state_[c] == ConstraintState::Barrier && dz_[c] < 0)
        t = std::min(t, -kFractionToBoundary * y_.z[c] / dz_[c]);
  } else {
    dz_.setZero();
  }
  if (rules_.backtrack_to_crossing) t = bound_step(t);
  domain_blocked_ = false;
  if (settings_.domain_fraction > 0) {
    t = domain_step(t);
    domain_blocked_ = t <= 0;
    if (domain_blocked_) return 0.0;  // a held control is at its box and the step points out of it
  }
  const double beta = settings_.line_search.beta;
  for (int ls = 0; ls < settings_.line_search.max_steps; ++ls) {
    apply_step(y_, dy_, t, trial_);
    eval_all_constraints(trial_, h_trial_);
    if (violation_sum(h_trial_) > hsum + 1e-12) {
      if (settings_.verbose) std::printf("   t %.2e rejected: violation %.3e > %.3e\n", t, violation_sum(h_trial_), hsum);
      const bool to_crossing = rules_.backtrack_to_crossing && rho_ < settings_.barrier.rho_init;
      t = to_crossing ? std::max(beta * t, kFractionToBoundary * step_to_first_crossing(t)) : beta * t;
      continue;
    }
    if (!evaluate(trial_, h_trial_, false, r_trial_, rc_trial_)) {
      if (settings_.verbose) std::printf("   t %.2e rejected: barrier constraint crossed\n", t);
      t *= beta;
      continue;
    }
    const double mt = merit(r_trial_, rc_trial_);
    if (mt <= (1.0 - settings_.line_search.alpha * t) * merit0) return t;
    if (settings_.verbose) std::printf("   t %.2e rejected: |r| %.3e vs %.3e\n", t, mt, merit0);
    t *= beta;
  }
  return 0.0;
}

// Fraction to the boundary of the state and control bounds in the barrier (IPOPT's rule for its bounds): they are
// linear in the variables, so the step at which each would be crossed is exact, and a trial past it would only be
// rejected by the violation test and halved, several times per iteration while a bound is near.
double Solver::bound_step(double t) const {
  using K = Constraint::Kind;
  Eigen::Vector2d g;
  double h;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    const K kind = cons_[c].kind;
    if (state_[c] != ConstraintState::Barrier || kind == K::Pair || kind == K::Obstacle) continue;
    eval_constraint(y_, c, h, &g, nullptr);  // a bound: g[0] = dh/d(its component), +-1
    const double dh = g[0] * dy_[constraint_rows(c).ci[0]];
    if (dh > 0 && h < 0) t = std::min(t, kFractionToBoundary * (-h) / dh);
  }
  return t;
}

// Near a barrier solution every full Newton step crosses the nearest constraint by a little (its curvature), and
// halving t then takes half of the step per iteration: the residual falls by half per iteration instead of
// quadratically. After a trial t that crossed constraints satisfied at y_, the step just short of the first crossing
// is estimated from each such constraint's values at 0 and t (a secant in t; for a constraint convex along the step
// the true crossing is later). 0 when a constraint already violated at y_ grew (plain backtracking then).
double Solver::step_to_first_crossing(double t) const {
  double first = t;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    const double h0 = h_[c], ht = h_trial_[c];
    if (ht <= 0.0) continue;
    if (h0 > 0.0) {
      if (ht > h0) return 0.0;
      continue;
    }
    first = std::min(first, t * (-h0) / (ht - h0));
  }
  return first;
}

// The models' control domains: a full Newton step can carry a steering angle across |delta| = pi/2, where the
// bicycle's slip angle jumps by pi; the residual there is a different (wrong-way) car, and the iterates do not come
// back (merge-long, docs/solver.md "Staying in the model's domain"). Each held control stays in its domain's box
// shrunk about the centre to domain_fraction of its half-width (a fixed margin: a fraction of the distance left
// would let a control creep to the singular point itself).
bool Solver::domain_box(int i, int q, double& lo, double& hi) {
  prob_.dynamics[i]->control_domain(dom_lo_, dom_hi_);
  if (!std::isfinite(dom_lo_[q]) || !std::isfinite(dom_hi_[q])) return false;  // one-sided: not held
  const double c = 0.5 * (dom_lo_[q] + dom_hi_[q]), w = 0.5 * settings_.domain_fraction * (dom_hi_[q] - dom_lo_[q]);
  lo = c - w;
  hi = c + w;
  return true;
}

double Solver::domain_step(double t) {
  for (int i = 0; i < N_; ++i) {
    for (int q = 0; q < nu_; ++q) {
      double lo, hi;
      if (!domain_box(i, q, lo, hi)) continue;
      for (int k = 0; k < T_; ++k) {
        const double u = y_.u[i](q, k), du = dy_[col_u(i, k) + q];
        if (!(u >= lo && u <= hi)) continue;  // outside already (a warm start): not held
        if (du > 0) t = std::min(t, (hi - u) / du);
        else if (du < 0) t = std::min(t, (lo - u) / du);
      }
    }
  }
  return std::max(t, 0.0);
}

double Solver::take_step(double rnorm, Info& info) {
  add_inertia_correction(rnorm);
  auto t0 = Clock::now();
  const bool solved = solve_linear(dy_, info);
  info.timings.linear_solve += seconds_since(t0);
  if (!solved) return timed_out_ ? 0.0 : -1.0;

  t0 = Clock::now();
  double t = line_search(rnorm);
  newton_at_edge_ = domain_blocked_;
  // The Newton step failed the line search (a nearly singular Newton matrix: a huge step, the merit decreasing only
  // for t -> 0): Levenberg-Marquardt steps from the smallest nu up, the first that passes taken.
  for (int q = 0; t == 0.0 && q < settings_.line_search.lm_tries; ++q) {
    if (past_deadline()) { timed_out_ = true; break; }
    if (!solve_levenberg_marquardt(kLmNuInit * std::pow(10.0, q) * rnorm, dy_)) break;
    t = line_search(rnorm);
    if (t > 0) info.lm_steps++;
  }
  info.timings.line_search += seconds_since(t0);
  if (t > 0) {
    timed_out_ = false;  // a step was found after all: take it
    std::swap(y_, trial_);
  }
  return t;
}

}  // namespace rd3g
