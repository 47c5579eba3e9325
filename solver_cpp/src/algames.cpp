#include "rd3g/algames.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include "rd3g/clock.hpp"
#include "rd3g/validate.hpp"

namespace rd3g {

void ALGamesSolver::setup(const Problem& problem, const ALGamesSettings& s) {
  validate_problem(problem);
  prob_ = with_defaults(problem);
  if (!(s.tol > 0 && s.max_iter >= 0 && s.time_limit >= 0 && s.violation_tol >= 0 && s.dynamics_tol > 0 && s.rho_init > 0 &&
        s.rho_growth >= 1 && s.rho_max >= s.rho_init && s.inner_max_iter >= 1 && s.ls_alpha > 0 && s.ls_alpha < 1 &&
        s.ls_beta > 0 && s.ls_beta < 1 && s.ls_max_steps >= 0))
    throw std::invalid_argument("ALGamesSettings out of range (tol, rho_init > 0; rho_growth >= 1; 0 < ls_alpha, ls_beta < 1)");
  settings_ = s;
  N_ = prob_.num_agents();
  T_ = prob_.horizon;
  nx_ = prob_.dynamics[0]->nx();
  nu_ = prob_.dynamics[0]->nu();
  layout_ = StageLayout{N_, nx_, nu_};
  stage_patterns_ = stage_patterns(prob_.dynamics);
  n_vars_ = N_ * T_ * stage_size();
  cons_ = list_constraints(prob_, s.bounds);
  const int C = static_cast<int>(cons_.size());
  lambda_ = Vec::Zero(C);
  h_ = Vec::Zero(C);
  h_trial_ = Vec::Zero(C);
  y_ = Vec::Zero(n_vars_);
  y_trial_ = Vec::Zero(n_vars_);
  G_ = Vec::Zero(n_vars_);
  G_trial_ = Vec::Zero(n_vars_);
  dy_ = Vec::Zero(n_vars_);
  X_.assign(N_, Mat::Zero(nx_, T_ + 1));
  U_.assign(N_, Mat::Zero(nu_, T_));
  A_ = Mat::Zero(nx_, nx_);
  B_ = Mat::Zero(nx_, nu_);
  fx_ = Vec::Zero(nx_);
  stage_.resize(nx_, nu_);
  const size_t ss = static_cast<size_t>(nx_ + nu_);
  trip_.reserve(static_cast<size_t>(N_) * T_ * (ss * ss + 4 * nx_ * (nx_ + nu_) + 3 * nx_) + 16 * C);
  J_.resize(n_vars_, n_vars_);
  analyzed_ = false;
}

void ALGamesSolver::unpack(const Vec& y) {
  for (int i = 0; i < N_; ++i) {
    X_[i].col(0) = prob_.x0[i];
    for (int k = 0; k < T_; ++k) {
      U_[i].col(k) = y.segment(col_u(i, k), nu_);
      X_[i].col(k + 1) = y.segment(col_x(i, k + 1), nx_);
    }
  }
}

// G = [dL^i/du^i_k; f(x^i_k, u^i_k) - x^i_{k+1}; dL^i/dx^i_{k+1}] for every player i and step k (cost and
// dynamics terms: rd3g::add_stage_terms, shared with RD3G), with
// L^i = J^i + sum_k nu^i_k'(f(x^i_k, u^i_k) - x^i_{k+1}) + sum_c (1/(2 rho)) (max(0, lambda_c + rho h_c)^2 - lambda_c^2)
// over the constraints c involving player i. The Jacobian is exact (dynamics curvature via lambda_hessian,
// constraint curvature included) and always has the same sparsity pattern (zeros where a penalty is off),
// so SparseLU's symbolic analysis is done once.
bool ALGamesSolver::evaluate(const Vec& y, bool jac, Vec& G, Vec& h) {
  unpack(y);
  G.setZero();
  if (jac) trip_.clear();
  for (int i = 0; i < N_; ++i)
    for (int k = 0; k < T_; ++k)
      add_stage_terms(layout_, i, k, T_, *prob_.dynamics[i], stage_patterns_[i], prob_.costs[i], prob_.lead[i],
                      X_[i], U_[i], y.segment(col_nu(i, k), nx_), G, jac ? &trip_ : nullptr, stage_);
  // Constraints: each involved player's stationarity gets w grad h, w = max(0, lambda + rho h). A variable
  // belongs to exactly one player, so the rows of a constraint's variables are those players' rows.
  ConstraintValue cv;
  const double rho = rho_;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    eval_constraint(prob_, cons_[c], X_, U_, cv);
    h[c] = cv.h;
    const double w = std::max(0.0, lambda_[c] + rho * cv.h);
    const int k = cons_[c].k;
    int idx[4];
    for (int a = 0; a < cv.n; ++a)
      idx[a] = (cv.on_u ? col_u(cv.agent[a], k) : col_x(cv.agent[a], k)) + cv.comp[a];
    for (int a = 0; a < cv.n; ++a) G[idx[a]] += w * cv.g[a];
    if (!jac) continue;
    for (int a = 0; a < cv.n; ++a)
      for (int b = 0; b < cv.n; ++b)
        trip_.emplace_back(idx[a], idx[b], w > 0 ? rho * cv.g[a] * cv.g[b] + w * cv.H(a, b) : 0.0);
  }
  return G.allFinite();
}

Result ALGamesSolver::solve(const WarmStart* warm) {
  if (N_ == 0) throw std::logic_error("setup() must be called before solve()");
  const auto t_start = Clock::now();
  Result res;
  Info& info = res.info;
  info.attempts = 1;
  // Initial guess: zero (or warm-start) controls rolled out, zero (or warm-start) dynamics multipliers.
  const bool warm_u = warm && static_cast<int>(warm->u.size()) == N_;
  const bool warm_nu = warm && static_cast<int>(warm->lambda.size()) == N_;
  for (int i = 0; i < N_; ++i) {
    if (warm_u && (warm->u[i].rows() != T_ || warm->u[i].cols() != nu_ || !warm->u[i].allFinite()))
      throw std::invalid_argument("warm start u has the wrong shape or non-finite values");
    if (warm_nu && (warm->lambda[i].rows() != T_ || warm->lambda[i].cols() != nx_ || !warm->lambda[i].allFinite()))
      throw std::invalid_argument("warm start lambda has the wrong shape or non-finite values");
    fx_ = prob_.x0[i];
    for (int k = 0; k < T_; ++k) {
      const Vec uk = warm_u ? Vec(warm->u[i].row(k).transpose()) : Vec::Zero(nu_);
      y_.segment(col_u(i, k), nu_) = uk;
      y_.segment(col_nu(i, k), nx_) = warm_nu ? Vec(warm->lambda[i].row(k).transpose()) : Vec::Zero(nx_);
      const Vec xk = fx_;
      prob_.dynamics[i]->eval(xk, uk, fx_, A_, B_);
      y_.segment(col_x(i, k + 1), nx_) = fx_;
    }
  }
  lambda_.setZero();
  rho_ = settings_.rho_init;
  int inner = 0, updates_in_a_row = 0;
  info.status = Status::MaxIterations;
  for (int it = 0;; ++it) {
    auto t0 = Clock::now();
    const bool ok = evaluate(y_, true, G_, h_);
    info.timings.assembly += seconds_since(t0);
    if (!ok) { info.status = Status::NumericalError; break; }
    const double gnorm = G_.norm();
    const double viol = h_.size() ? std::max(0.0, h_.maxCoeff()) : 0.0;
    info.iterations = it;
    info.residual_norm = gnorm;
    info.residual_history.push_back(gnorm);
    if (settings_.verbose) std::printf("it %3d  |G| %.3e  viol %.3e  rho %.1e\n", it, gnorm, viol, rho_);
    double defect = 0.0;
    for (int i = 0; i < N_; ++i)
      for (int k = 0; k < T_; ++k) defect = std::max(defect, G_.segment(col_nu(i, k), nx_).cwiseAbs().maxCoeff());
    if (gnorm < settings_.tol && viol <= settings_.violation_tol && defect <= settings_.dynamics_tol) {
      info.status = Status::Converged;
      break;
    }
    // Stationary but a violated constraint: dual update. (Stationary, feasible, but the dynamics not yet
    // tight enough: one more Newton step.)
    const bool inner_done = gnorm < settings_.tol && viol > settings_.violation_tol;
    if (settings_.time_limit > 0 && seconds_since(t_start) > settings_.time_limit) { info.status = Status::TimeLimit; break; }
    if (inner_done || inner >= settings_.inner_max_iter) {
      // Guard: multiplier updates that never move G above tol (e.g. a constraint with zero gradient).
      if (++updates_in_a_row > 50) { info.status = Status::Stalled; break; }
      // Outer iteration: dual ascent and penalty increase, then G changes and Newton continues.
      for (int c = 0; c < static_cast<int>(cons_.size()); ++c) lambda_[c] = std::max(0.0, lambda_[c] + rho_ * h_[c]);
      rho_ = std::min(settings_.rho_max, settings_.rho_growth * rho_);
      inner = 0;
      --it;  // no Newton step taken: the residual is re-evaluated with the new multipliers
      info.residual_history.pop_back();
      continue;
    }
    if (it >= settings_.max_iter) { info.status = Status::MaxIterations; break; }
    updates_in_a_row = 0;
    t0 = Clock::now();
    J_.setFromTriplets(trip_.begin(), trip_.end());
    if (!analyzed_) {
      lu_.analyzePattern(J_);
      analyzed_ = true;
      info.symbolic_factorizations++;
    }
    lu_.factorize(J_);
    bool solved = lu_.info() == Eigen::Success;
    if (solved) {
      dy_ = lu_.solve(-G_);
      solved = lu_.info() == Eigen::Success && dy_.allFinite();
    }
    info.timings.linear_solve += seconds_since(t0);
    if (!solved) { info.status = Status::NumericalError; break; }
    t0 = Clock::now();
    double t = 1.0;
    bool accepted = false;
    for (int ls = 0; ls <= settings_.ls_max_steps; ++ls, t *= settings_.ls_beta) {
      y_trial_ = y_ + t * dy_;
      if (evaluate(y_trial_, false, G_trial_, h_trial_) && G_trial_.norm() <= (1.0 - settings_.ls_alpha * t) * gnorm) {
        accepted = true;
        break;
      }
    }
    info.timings.line_search += seconds_since(t0);
    ++inner;
    if (!accepted) {
      // No decrease along the Newton direction for these multipliers: end the inner loop early.
      if (settings_.verbose) std::printf("   line search failed\n");
      inner = settings_.inner_max_iter;
      continue;
    }
    std::swap(y_, y_trial_);
    info.step_history.push_back(t);
  }
  unpack(y_);
  res.x.resize(N_);
  res.u.resize(N_);
  res.lambda.resize(N_);
  for (int i = 0; i < N_; ++i) {
    res.x[i] = X_[i].transpose();
    res.u[i] = U_[i].transpose();
    res.lambda[i] = Mat(T_, nx_);
    for (int k = 0; k < T_; ++k) res.lambda[i].row(k) = y_.segment(col_nu(i, k), nx_).transpose();
  }
  res.h = h_;
  res.mu = (lambda_ + rho_ * h_).cwiseMax(0.0);
  info.max_violation = h_.size() ? std::max(0.0, h_.maxCoeff()) : 0.0;
  info.rho = rho_;
  info.timings.total = seconds_since(t_start);
  return res;
}

}  // namespace rd3g
