#include "rd3g/ilqgames.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include "rd3g/clock.hpp"
#include "rd3g/stage_terms.hpp"
#include "rd3g/validate.hpp"

namespace rd3g {

// -------------------------------------------------------------------------------------------------
void LQGameSolver::setup(int n, const std::vector<int>& control_dims, int T) {
  if (n < 1 || T < 1 || control_dims.empty()) throw std::invalid_argument("LQ game needs n >= 1, T >= 1 and players");
  n_ = n;
  T_ = T;
  N_ = static_cast<int>(control_dims.size());
  dims_ = control_dims;
  off_.assign(N_, 0);
  m_ = 0;
  for (int i = 0; i < N_; ++i) {
    if (control_dims[i] < 1) throw std::invalid_argument("control_dims must be positive");
    off_[i] = m_;
    m_ += control_dims[i];
  }
  P_.assign(T, Mat::Zero(m_, n_));
  alpha_.assign(T, Vec::Zero(m_));
  Z_.assign(N_, Mat::Zero(n_, n_));
  ZB_.assign(N_, Mat::Zero(n_, m_));
  zeta_.assign(N_, Vec::Zero(n_));
  S_ = Mat::Zero(m_, m_);
  Y_ = Mat::Zero(m_, n_ + 1);
  F_ = Mat::Zero(n_, n_);
  ZF_ = Mat::Zero(n_, n_);
  RP_ = Mat::Zero(m_, n_);
  beta_ = Vec::Zero(n_);
  tmp_ = Vec::Zero(n_);
  lu_ = Eigen::PartialPivLU<Mat>(m_);
}

bool LQGameSolver::solve(const LQGame& g) {
  for (int i = 0; i < N_; ++i) {
    Z_[i] = g.QT[i];
    zeta_[i] = g.lT[i];
  }
  for (int k = T_ - 1; k >= 0; --k) {
    const Mat& A = g.A[k];
    const Mat& B = g.B[k];
    // Player i's first-order condition, with every player on u = -P x - alpha:
    //   sum_j (R^i_ij + B_i' Z^i B_j) P_j = B_i' Z^i A,   sum_j (R^i_ij + B_i' Z^i B_j) alpha_j = B_i' zeta^i + r^i_i.
    for (int i = 0; i < N_; ++i) {
      const int o = off_[i], mi = dims_[i];
      ZB_[i].noalias() = Z_[i] * B;
      S_.middleRows(o, mi) = g.R[k][i].middleRows(o, mi);
      S_.middleRows(o, mi).noalias() += B.middleCols(o, mi).transpose() * ZB_[i];
      Y_.block(o, 0, mi, n_).noalias() = ZB_[i].middleCols(o, mi).transpose() * A;
      Y_.block(o, n_, mi, 1).noalias() = B.middleCols(o, mi).transpose() * zeta_[i];
      Y_.block(o, n_, mi, 1) += g.r[k][i].segment(o, mi);
    }
    lu_.compute(S_);
    P_[k].noalias() = lu_.solve(Y_.leftCols(n_));
    alpha_[k].noalias() = lu_.solve(Y_.col(n_));
    if (!P_[k].allFinite() || !alpha_[k].allFinite()) return false;
    // Residual check: PartialPivLU does not report singularity.
    if ((S_ * alpha_[k] - Y_.col(n_)).norm() > 1e-6 * (1.0 + Y_.col(n_).norm())) return false;
    // Closed loop x_{k+1} = F x + beta, and each player's value function.
    F_ = A;
    F_.noalias() -= B * P_[k];
    beta_.noalias() = -B * alpha_[k];
    for (int i = 0; i < N_; ++i) {
      const Mat& R = g.R[k][i];
      // zeta^i <- l^i + P'(R alpha - r^i) + F'(zeta^i + Z^i beta)
      tmp_ = zeta_[i];
      tmp_.noalias() += Z_[i] * beta_;
      Vec Ra = R * alpha_[k] - g.r[k][i];
      zeta_[i] = g.l[k][i];
      zeta_[i].noalias() += P_[k].transpose() * Ra;
      zeta_[i].noalias() += F_.transpose() * tmp_;
      // Z^i <- Q^i + P'R P + F' Z^i F
      ZF_.noalias() = Z_[i] * F_;
      RP_.noalias() = R * P_[k];
      Z_[i] = g.Q[k][i];
      Z_[i].noalias() += P_[k].transpose() * RP_;
      Z_[i].noalias() += F_.transpose() * ZF_;
      Z_[i] = 0.5 * (Z_[i] + Z_[i].transpose()).eval();
    }
  }
  return true;
}

// -------------------------------------------------------------------------------------------------
void ILQGamesSolver::setup(const Problem& problem, const ILQGamesSettings& s) {
  validate_problem(problem);
  prob_ = with_defaults(problem);
  if (!(s.tol > 0 && s.max_iter >= 0 && s.time_limit >= 0 && s.max_state_change > 0 && s.ls_beta > 0 && s.ls_beta < 1 &&
        s.ls_max_steps >= 0 && s.violation_tol >= 0 && s.rho_init > 0 && s.rho_growth >= 1 && s.rho_max >= s.rho_init &&
        s.round_max_iter >= 1))
    throw std::invalid_argument("ILQGamesSettings out of range (tol, max_state_change, rho_init > 0; 0 < ls_beta < 1; rho_growth >= 1)");
  settings_ = s;
  N_ = prob_.num_agents();
  T_ = prob_.horizon;
  nx_ = prob_.dynamics[0]->nx();
  nu_ = prob_.dynamics[0]->nu();
  n_ = N_ * nx_;
  m_ = N_ * nu_;
  cons_ = list_constraints(prob_, s.bounds);
  cons_at_.assign(T_ + 1, {});
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) cons_at_[cons_[c].k].push_back(c);
  const int C = static_cast<int>(cons_.size());
  lambda_ = Vec::Zero(C);
  h_ = Vec::Zero(C);
  h_trial_ = Vec::Zero(C);
  x_.assign(N_, Mat::Zero(nx_, T_ + 1));
  trial_x_ = x_;
  u_.assign(N_, Mat::Zero(nu_, T_));
  trial_u_ = u_;
  lq_.control_dims.assign(N_, nu_);
  lq_.A.assign(T_, Mat::Zero(n_, n_));
  lq_.B.assign(T_, Mat::Zero(n_, m_));
  lq_.Q.assign(T_, std::vector<Mat>(N_, Mat::Zero(n_, n_)));
  lq_.l.assign(T_, std::vector<Vec>(N_, Vec::Zero(n_)));
  lq_.R.assign(T_, std::vector<Mat>(N_, Mat::Zero(m_, m_)));
  lq_.r.assign(T_, std::vector<Vec>(N_, Vec::Zero(m_)));
  lq_.QT.assign(N_, Mat::Zero(n_, n_));
  lq_.lT.assign(N_, Vec::Zero(n_));
  lq_solver_.setup(n_, lq_.control_dims, T_);
  Ai_ = Mat::Zero(nx_, nx_);
  Bi_ = Mat::Zero(nx_, nu_);
  xn_ = Vec::Zero(nx_);
  dx_ = Vec::Zero(n_);
  du_ = Vec::Zero(m_);
}

double ILQGamesSolver::max_violation(const std::vector<Mat>& x, const std::vector<Mat>& u, Vec& h) {
  ConstraintValue cv;
  double v = 0.0;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    eval_constraint(prob_, cons_[c], x, u, cv);
    h[c] = cv.h;
    v = std::max(v, cv.h);
  }
  return v;
}

// LQ approximation of the game around (x_, u_): dynamics linearised (first order, as in iLQGames), each
// player's cost quadratised in the joint state and controls. Penalty terms use the Gauss-Newton Hessian
// rho grad h grad h' (the curvature of h is dropped, so the LQ costs stay convex); their gradient
// max(0, lambda + rho h) grad h is exact, so fixed points are unaffected.
void ILQGamesSolver::linearize_and_quadratize() {
  const double rho = rho_;
  ConstraintValue cv;
  for (int k = 0; k <= T_; ++k) {
    const bool terminal = k == T_;
    std::vector<Mat>& Q = terminal ? lq_.QT : lq_.Q[k];
    std::vector<Vec>& l = terminal ? lq_.lT : lq_.l[k];
    for (int i = 0; i < N_; ++i) {
      Q[i].setZero();
      l[i].setZero();
      if (!terminal) {
        lq_.R[k][i].setZero();
        lq_.r[k][i].setZero();
      }
    }
    if (!terminal) {
      for (int i = 0; i < N_; ++i) {
        prob_.dynamics[i]->eval(x_[i].col(k), u_[i].col(k), xn_, Ai_, Bi_);
        lq_.A[k].block(i * nx_, i * nx_, nx_, nx_) = Ai_;
        lq_.B[k].block(i * nx_, i * nu_, nx_, nu_) = Bi_;
        const QuadraticCost& cost = prob_.costs[i];
        const int o = i * nu_;
        lq_.R[k][i].block(o, o, nu_, nu_).diagonal() = control_cost_hessian(cost);
        control_cost_gradient(cost, u_[i].col(k), lq_.r[k][i].segment(o, nu_));
      }
    }
    if (k >= 1) {
      for (int i = 0; i < N_; ++i) {
        const QuadraticCost& cost = prob_.costs[i];
        const auto xi = x_[i].col(k);
        const int o = i * nx_;
        Q[i].block(o, o, nx_, nx_).diagonal() = state_cost_hessian(cost, k, T_);
        state_cost_gradient(cost, k, T_, xi, l[i].segment(o, nx_));
        const LeadCost& lead = prob_.lead[i];
        if (lead.weight != 0.0)  // w * sum_{j != i} (x^j[idx] - x^i[idx]): couples the players through the gradient
          for (int j = 0; j < N_; ++j) l[i][j * nx_ + lead.index] += j == i ? lead_gradient(lead, N_) : lead.weight;
      }
    }
    for (int c : cons_at_[k]) {
      eval_constraint(prob_, cons_[c], x_, u_, cv);
      const double w = lambda_[c] + rho * cv.h;
      if (w <= 0) continue;
      // The penalty lambda h + rho/2 h^2 (PHR form) is part of the cost of every player the constraint involves.
      for (int a = 0; a < cv.n; ++a) {
        const int pl = cv.agent[a];
        if (a > 0 && cv.agent[a] == cv.agent[a - 1]) continue;  // each involved player once
        for (int b = 0; b < cv.n; ++b) {
          const int rb = cv.on_u ? cv.agent[b] * nu_ + cv.comp[b] : cv.agent[b] * nx_ + cv.comp[b];
          if (cv.on_u) lq_.r[k][pl][rb] += w * cv.g[b];
          else l[pl][rb] += w * cv.g[b];
          for (int d = 0; d < cv.n; ++d) {
            const int rd = cv.on_u ? cv.agent[d] * nu_ + cv.comp[d] : cv.agent[d] * nx_ + cv.comp[d];
            if (cv.on_u) lq_.R[k][pl](rb, rd) += rho * cv.g[b] * cv.g[d];
            else Q[pl](rb, rd) += rho * cv.g[b] * cv.g[d];
          }
        }
      }
    }
  }
}

void ILQGamesSolver::rollout(double step) {
  const auto& P = lq_solver_.P();
  const auto& alpha = lq_solver_.alpha();
  for (int i = 0; i < N_; ++i) trial_x_[i].col(0) = prob_.x0[i];
  for (int k = 0; k < T_; ++k) {
    for (int i = 0; i < N_; ++i) dx_.segment(i * nx_, nx_) = trial_x_[i].col(k) - x_[i].col(k);
    du_.noalias() = -P[k] * dx_;
    du_ -= step * alpha[k];
    for (int i = 0; i < N_; ++i) {
      trial_u_[i].col(k) = u_[i].col(k) + du_.segment(i * nu_, nu_);
      prob_.dynamics[i]->eval(trial_x_[i].col(k), trial_u_[i].col(k), xn_, Ai_, Bi_);
      trial_x_[i].col(k + 1) = xn_;
    }
  }
}

Result ILQGamesSolver::solve(const WarmStart* warm) {
  if (N_ == 0) throw std::logic_error("setup() must be called before solve()");
  const auto t_start = Clock::now();
  Result res;
  Info& info = res.info;
  for (int i = 0; i < N_; ++i) {
    if (warm && static_cast<int>(warm->u.size()) == N_) {
      if (warm->u[i].rows() != T_ || warm->u[i].cols() != nu_ || !warm->u[i].allFinite())
        throw std::invalid_argument("warm start u has the wrong shape or non-finite values");
      u_[i] = warm->u[i].transpose();
    } else {
      u_[i].setZero();
    }
    x_[i].col(0) = prob_.x0[i];
    for (int k = 0; k < T_; ++k) {
      prob_.dynamics[i]->eval(x_[i].col(k), u_[i].col(k), xn_, Ai_, Bi_);
      x_[i].col(k + 1) = xn_;
    }
  }
  lambda_.setZero();
  rho_ = settings_.rho_init;
  double viol = max_violation(x_, u_, h_);
  // Step scale on the feedforward term, adapted across iterations: iLQGames' fixed-point iteration can
  // cycle, so when the full step's trajectory change does not shrink the next steps start smaller
  // (and recover slowly, by 25% per iteration that makes progress, so that damping is not undone at once).
  double scale = 1.0, prev_full = kInf, full = kInf;
  int round_iter = 0;
  info.status = Status::MaxIterations;
  for (int it = 0;; ++it) {
    info.iterations = it;
    if (settings_.time_limit > 0 && seconds_since(t_start) > settings_.time_limit) { info.status = Status::TimeLimit; break; }
    auto t0 = Clock::now();
    linearize_and_quadratize();
    const bool ok = lq_solver_.solve(lq_);
    info.timings.assembly += seconds_since(t0);
    if (!ok) { info.status = Status::NumericalError; break; }
    t0 = Clock::now();
    // Convergence measure: how far the full LQ step would move the trajectory (0 at a fixed point).
    rollout(1.0);
    full = 0.0;
    for (int i = 0; i < N_; ++i)
      full = std::max({full, (trial_x_[i] - x_[i]).cwiseAbs().maxCoeff(), (trial_u_[i] - u_[i]).cwiseAbs().maxCoeff()});
    if (!std::isfinite(full)) full = kInf;
    info.residual_history.push_back(full);
    if (settings_.verbose) std::printf("it %3d  full-step change %.3e  scale %.2e  rho %.1e  viol %.3e\n", it, full, scale, rho_, viol);
    if (full < settings_.tol && viol <= settings_.violation_tol) { info.status = Status::Converged; break; }
    if (it >= settings_.max_iter) { info.status = Status::MaxIterations; break; }
    if (full < settings_.tol || round_iter >= settings_.round_max_iter) {
      // End of a penalty round: first-order multiplier update and a stiffer penalty; the LQ game is rebuilt.
      for (int c = 0; c < static_cast<int>(cons_.size()); ++c) lambda_[c] = std::max(0.0, lambda_[c] + rho_ * h_[c]);
      rho_ = std::min(settings_.rho_max, settings_.rho_growth * rho_);
      round_iter = 0;
      prev_full = kInf;
      info.timings.line_search += seconds_since(t0);
      continue;
    }
    if (full >= prev_full) scale = std::max(scale * settings_.ls_beta, std::pow(settings_.ls_beta, settings_.ls_max_steps));
    else scale = std::min(1.0, scale * 1.25);
    prev_full = full;
    // Line search on the feedforward step: accept the first step whose trajectory stays finite and inside
    // the trust region.
    double step = scale;
    bool accepted = false;
    for (int ls = 0; ls <= settings_.ls_max_steps; ++ls, step *= settings_.ls_beta) {
      if (step != 1.0) rollout(step);
      double dmax = 0.0;
      bool finite = true;
      for (int i = 0; i < N_ && finite; ++i) {
        finite = trial_x_[i].allFinite() && trial_u_[i].allFinite();
        if (finite) dmax = std::max(dmax, (trial_x_[i] - x_[i]).cwiseAbs().maxCoeff());
      }
      if (finite && dmax <= settings_.max_state_change) { accepted = true; break; }
      if (settings_.verbose) std::printf("   step %.2e rejected: max state change %.3e\n", step, dmax);
    }
    info.timings.line_search += seconds_since(t0);
    if (!accepted) { info.status = Status::LineSearchFailed; break; }
    std::swap(x_, trial_x_);
    std::swap(u_, trial_u_);
    viol = max_violation(x_, u_, h_);
    info.step_history.push_back(step);
    ++round_iter;
  }
  res.x.resize(N_);
  res.u.resize(N_);
  for (int i = 0; i < N_; ++i) {
    res.x[i] = x_[i].transpose();
    res.u[i] = u_[i].transpose();
  }
  res.h = h_;
  res.mu = lambda_;
  info.residual_norm = full;
  info.max_violation = std::max(0.0, viol);
  info.rho = rho_;
  info.attempts = 1;
  info.timings.total = seconds_since(t_start);
  return res;
}

}  // namespace rd3g
