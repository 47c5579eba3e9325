#include "rd3g/solver.hpp"

#include "rd3g/second_order.hpp"

#include <Eigen/IterativeLinearSolvers>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <stdexcept>
#include <string>

namespace rd3g {

namespace {
using Clock = std::chrono::steady_clock;
inline double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}
void require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument(what);
}
bool finite(const Vec& v) { return v.allFinite(); }
}  // namespace

std::string status_name(Status s) {
  switch (s) {
    case Status::Converged: return "converged";
    case Status::MaxIterations: return "max_iterations";
    case Status::LineSearchFailed: return "line_search_failed";
    case Status::NumericalError: return "numerical_error";
    case Status::TimeLimit: return "time_limit";
    case Status::Stalled: return "stalled";
    case Status::Saddle: return "saddle";
  }
  return "unknown";
}

// -------------------------------------------------------------------------------------------------
void Solver::setup(const Problem& p, const Settings& s) {
  N_ = p.num_agents();
  T_ = p.horizon;
  require(N_ >= 1, "problem needs at least one agent");
  require(T_ >= 1, "horizon must be >= 1");
  require(p.dt > 0 && std::isfinite(p.dt), "dt must be positive and finite");
  for (int i = 0; i < N_; ++i)
    require(p.dynamics[i] != nullptr, "agents[" + std::to_string(i) + "].dynamics is missing");
  require(static_cast<int>(p.x0.size()) == N_, "x0 must have one entry per agent");
  require(static_cast<int>(p.costs.size()) == N_, "costs must have one entry per agent");
  require(p.lead.empty() || static_cast<int>(p.lead.size()) == N_, "lead must be empty or have one entry per agent");
  nx_ = p.dynamics[0]->nx();
  nu_ = p.dynamics[0]->nu();
  for (int i = 0; i < N_; ++i) {
    const std::string a = "agents[" + std::to_string(i) + "]";
    require(p.dynamics[i] != nullptr, a + ".dynamics is missing");
    require(p.dynamics[i]->nx() == nx_ && p.dynamics[i]->nu() == nu_, a + ".dynamics: all agents must share state/control sizes");
    require(static_cast<int>(p.x0.size()) == N_ && p.x0[i].size() == nx_ && finite(p.x0[i]), a + ".x0 must have nx finite values");
    const QuadraticCost& c = p.costs.at(i);
    for (auto* v : {&c.x_ref, &c.Q_ref, &c.Q, &c.Qf_ref, &c.Qf})
      require(v->size() == nx_ && finite(*v), a + ".cost: state-sized weights must have nx finite values");
    require(c.R.size() == nu_ && finite(c.R), a + ".cost.R must have nu finite values");
    require((c.R.array() >= 0).all() && (c.Q.array() >= 0).all() && (c.Q_ref.array() >= 0).all(),
            a + ".cost: weights must be non-negative");
  }
  require(s.tol > 0, "solver.tol must be positive");
  require(s.max_iter >= 0, "solver.max_iter must be >= 0");
  require(s.time_limit >= 0, "solver.time_limit must be >= 0 (0 = none)");
  require(s.rho_init > 0, "solver.rho_init must be positive");
  require(s.rho_kappa > 0 && s.rho_kappa < 1, "solver.rho_kappa must be in (0, 1)");
  require(s.rho_beta > 1, "solver.rho_beta must be > 1");
  require(s.rho_progress >= 0, "solver.rho_progress must be >= 0");
  require(s.rho_floor_factor > 0 && s.rho_floor_factor <= 1, "solver.rho_floor_factor must be in (0, 1]");
  require(s.ls_alpha > 0 && s.ls_alpha < 1, "solver.ls_alpha must be in (0, 1)");
  require(s.ls_beta > 0 && s.ls_beta < 1, "solver.ls_beta must be in (0, 1)");
  require(s.ls_max_steps >= 1, "solver.ls_max_steps must be >= 1");
  require(s.violation_tol >= 0, "solver.violation_tol must be >= 0");
  require(s.dynamics_tol > 0, "solver.dynamics_tol must be positive");
  require(s.multiplier_tol >= 0, "solver.multiplier_tol must be >= 0");
  require(s.barrier_margin >= 0, "solver.barrier_margin must be >= 0");
  require(s.fraction_to_boundary > 0 && s.fraction_to_boundary < 1, "solver.fraction_to_boundary must be in (0, 1)");
  require(s.lm_tries >= 0 && s.lm_nu_init > 0, "solver.lm_tries must be >= 0 and solver.lm_nu_init positive");
  require(s.restarts >= 0, "solver.restarts must be >= 0");
  require(s.stall_window >= 0, "solver.stall_window must be >= 0 (0 = never)");
  require(s.restart_u_std >= 0, "solver.restart_u_std must be >= 0");
  require(s.polish_gap >= 0, "solver.polish_gap must be >= 0 (0 = off)");
  require(s.lscg_tol > 0 && s.lscg_max_iter >= 1, "solver.lscg_tol must be positive and solver.lscg_max_iter >= 1");
  require(s.second_order_tol > 0, "solver.second_order_tol must be positive");
  prob_ = p;
  if (prob_.lead.empty()) prob_.lead.assign(N_, LeadCost{});
  auto fill_bounds = [&](std::vector<Vec>& b, int n, double val, const char* name) {
    if (b.empty()) b.assign(N_, Vec::Constant(n, val));
    require(static_cast<int>(b.size()) == N_, std::string(name) + " must have one entry per agent");
    for (int i = 0; i < N_; ++i) {
      require(b[i].size() == n, std::string(name) + " has the wrong length");
      for (int q = 0; q < n; ++q) require(!std::isnan(b[i][q]), std::string(name) + " has NaN");
    }
  };
  fill_bounds(prob_.u_min, nu_, -kInf, "u_min");
  fill_bounds(prob_.u_max, nu_, kInf, "u_max");
  fill_bounds(prob_.x_min, nx_, -kInf, "x_min");
  fill_bounds(prob_.x_max, nx_, kInf, "x_max");
  for (int i = 0; i < N_; ++i)
    for (int q = 0; q < nu_; ++q) require(prob_.u_min[i][q] < prob_.u_max[i][q], "u_min must be below u_max");
  for (const auto& o : prob_.obstacles) {
    require(o.positions.rows() == T_ + 1 && o.positions.cols() == 2 && o.positions.allFinite() && o.min_distance > 0,
            "obstacle positions must be (T+1) x 2 finite with min_distance > 0");
    require(o.min_distance_steps.size() == 0 ||
                (o.min_distance_steps.size() == T_ && o.min_distance_steps.allFinite() && o.min_distance_steps.minCoeff() > 0),
            "obstacle min_distance_steps must be empty or T positive values");
  }
  if (prob_.collision.enabled && N_ > 1)
    require(prob_.collision.min_distance > 0 && prob_.collision.pos_x >= 0 && prob_.collision.pos_x < nx_ &&
                prob_.collision.pos_y >= 0 && prob_.collision.pos_y < nx_,
            "collision.min_distance must be positive and position indices valid");
  if (prob_.collision.enabled && N_ > 1)
    require(prob_.collision.min_distance_steps.size() == 0 ||
                (prob_.collision.min_distance_steps.size() == T_ && prob_.collision.min_distance_steps.allFinite() &&
                 prob_.collision.min_distance_steps.minCoeff() > 0),
            "collision.min_distance_steps must be empty or T positive values");
  settings_ = s;
  per_agent_multipliers_ = s.linear_solver == LinearSolver::LSCG || s.linear_solver == LinearSolver::SparseQR;

  // Constraint list, in time order (keeps the multiplier numbering close to the stage ordering).
  cons_.clear();
  using K = Constraint::Kind;
  for (int k = 0; k <= T_; ++k) {
    if (k >= 1) {
      if (prob_.collision.enabled)
        for (int i = 0; i < N_; ++i)
          for (int j = i + 1; j < N_; ++j) cons_.push_back({K::Pair, i, j, k, -1});
      for (int i = 0; i < N_; ++i) {
        for (int o = 0; o < static_cast<int>(prob_.obstacles.size()); ++o) cons_.push_back({K::Obstacle, i, o, k, -1});
        for (int q = 0; q < nx_; ++q) {
          if (std::isfinite(prob_.x_max[i][q])) cons_.push_back({K::StateMax, i, -1, k, q});
          if (std::isfinite(prob_.x_min[i][q])) cons_.push_back({K::StateMin, i, -1, k, q});
        }
      }
    }
    if (k < T_)
      for (int i = 0; i < N_; ++i)
        for (int q = 0; q < nu_; ++q) {
          if (std::isfinite(prob_.u_max[i][q])) cons_.push_back({K::ControlMax, i, -1, k, q});
          if (std::isfinite(prob_.u_min[i][q])) cons_.push_back({K::ControlMin, i, -1, k, q});
        }
  }
  const int C = static_cast<int>(cons_.size());
  n_primal_ = N_ * T_ * stage_size();

  for (Iterate* it : {&y_, &trial_, &best_}) {
    it->x.assign(N_, Mat::Zero(nx_, T_ + 1));
    it->u.assign(N_, Mat::Zero(nu_, T_));
    it->lam.assign(N_, Mat::Zero(nx_, T_));
    it->mu = Vec::Zero(C);
    it->mu2 = Vec::Zero(C);
    it->z = Vec::Zero(C);
  }
  A_.assign(N_, std::vector<Mat>(T_, Mat::Zero(nx_, nx_)));
  B_.assign(N_, std::vector<Mat>(T_, Mat::Zero(nx_, nu_)));
  fx_ = Mat::Zero(nx_, 1);
  Hl_ = Mat::Zero(nx_ + nu_, nx_ + nu_);
  Atmp_ = Mat::Zero(nx_, nx_);
  Btmp_ = Mat::Zero(nx_, nu_);
  h_ = Vec::Zero(C);
  h_trial_ = Vec::Zero(C);
  rc_ = Vec::Zero(C);
  rc_trial_ = Vec::Zero(C);
  dz_ = Vec::Zero(C);
  state_.assign(C, ConstraintState::Barrier);
  pattern_state_.clear();
  mu_col_.assign(C, -1);
  mu2_col_.assign(C, -1);
  const int max_vars = n_primal_ + 2 * C;
  r_ = Vec::Zero(max_vars);
  r_trial_ = Vec::Zero(max_vars);
  rhs_ = Vec::Zero(max_vars);
  dy_ = Vec::Zero(max_vars);
  // Per stage and agent: dense (nx+nu)^2 Hessian, A, B, identities; per constraint up to ~20 entries.
  trip_.reserve(static_cast<size_t>(N_) * T_ * (3 * (nx_ + nu_) * (nx_ + nu_) + 4 * nx_) + 24 * C);
  lu_analyzed_ = false;
  riccati_.setup(N_, T_, nx_, nu_);
  if (!second_order_) second_order_ = std::make_shared<SecondOrderCheck>();
  second_order_->setup(N_, T_, nx_, nu_);
}

// -------------------------------------------------------------------------------------------------
void Solver::eval_constraint(const Iterate& y, int c, double& h, Eigen::Vector2d& g, Eigen::Matrix2d& H) const {
  const Constraint& cn = cons_[c];
  using K = Constraint::Kind;
  g.setZero();
  H.setZero();
  auto distance_like = [&](const Eigen::Vector2d& d, double dmin) {
    // h = dmin - |d| (Distance) or dmin^2 - |d|^2 (Squared); g = dh/dd, H = d2h/dd2.
    if (prob_.collision.form == CollisionForm::Squared) {
      h = dmin * dmin - d.squaredNorm();
      g = -2.0 * d;
      H = -2.0 * Eigen::Matrix2d::Identity();
    } else {
      const double n = std::max(d.norm(), 1e-12);
      const Eigen::Vector2d e = d / n;
      h = dmin - n;
      g = -e;
      H = -(Eigen::Matrix2d::Identity() - e * e.transpose()) / n;
    }
  };
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  switch (cn.kind) {
    case K::Pair: {
      const Eigen::Vector2d d(y.x[cn.i](px, cn.k) - y.x[cn.j](px, cn.k), y.x[cn.i](py, cn.k) - y.x[cn.j](py, cn.k));
      distance_like(d, prob_.collision.at(cn.k));
      break;
    }
    case K::Obstacle: {
      const Obstacle& o = prob_.obstacles[cn.j];
      const Eigen::Vector2d d(y.x[cn.i](px, cn.k) - o.positions(cn.k, 0), y.x[cn.i](py, cn.k) - o.positions(cn.k, 1));
      distance_like(d, o.at(cn.k));
      break;
    }
    case K::StateMax: h = y.x[cn.i](cn.idx, cn.k) - prob_.x_max[cn.i][cn.idx]; g[0] = 1; break;
    case K::StateMin: h = prob_.x_min[cn.i][cn.idx] - y.x[cn.i](cn.idx, cn.k); g[0] = -1; break;
    case K::ControlMax: h = y.u[cn.i](cn.idx, cn.k) - prob_.u_max[cn.i][cn.idx]; g[0] = 1; break;
    case K::ControlMin: h = prob_.u_min[cn.i][cn.idx] - y.u[cn.i](cn.idx, cn.k); g[0] = -1; break;
  }
}

void Solver::eval_all_constraints(const Iterate& y, Vec& h) const {
  Eigen::Vector2d g;
  Eigen::Matrix2d H;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) eval_constraint(y, c, h[c], g, H);
}

double Solver::violation_sum(const Vec& h) const { return h.cwiseMax(0.0).sum(); }

// Partition (paper, Sec. III-A) with two safeguards: an active constraint stays an equality while it
// sits at h ~ 0 (the barrier is undefined there), and one whose multiplier turns negative is released
// (Free) until it is far enough inside to be handed to the barrier.
void Solver::classify(const Vec& h, bool first) {
  const double margin = settings_.barrier_margin;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    ConstraintState& st = state_[c];
    if (first) {
      // Duals start at zero (warm-start multipliers aside): the first Newton step carries no barrier
      // curvature, and z is then driven towards rho/(-h) by the complementarity rows. (Starting on the
      // central path was measured to converge less often on the merging games.)
      st = h[c] >= 0 ? ConstraintState::Active : (h[c] < -margin ? ConstraintState::Barrier : ConstraintState::Free);
      continue;
    }
    switch (st) {
      case ConstraintState::Barrier:
        if (h[c] >= 0) st = ConstraintState::Active;  // only possible if the line search was bypassed
        break;
      case ConstraintState::Active: {
        const bool wrong_sign = y_.mu[c] < -settings_.multiplier_tol ||
                                (mu2_col_[c] >= 0 && y_.mu2[c] < -settings_.multiplier_tol);
        if (h[c] < -margin) st = ConstraintState::Barrier;
        else if (wrong_sign && h[c] <= settings_.violation_tol) st = ConstraintState::Free;
        break;
      }
      case ConstraintState::Free:
        if (h[c] < -margin) st = ConstraintState::Barrier;
        else if (h[c] > settings_.violation_tol) st = ConstraintState::Active;
        break;
    }
    if (st != ConstraintState::Active) { y_.mu[c] = 0; y_.mu2[c] = 0; }
    if (st != ConstraintState::Barrier) y_.z[c] = 0;
    else if (!(y_.z[c] > 0)) y_.z[c] = rho_ / -h[c];  // a constraint handed to the barrier later enters on the central path
  }
}

void Solver::number_multipliers() {
  int next = n_primal_;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    mu_col_[c] = mu2_col_[c] = -1;
    if (state_[c] != ConstraintState::Active) continue;
    mu_col_[c] = next++;
    if (per_agent_multipliers_ && cons_[c].kind == Constraint::Kind::Pair) mu2_col_[c] = next++;
  }
  n_vars_ = next;
}

// -------------------------------------------------------------------------------------------------
bool Solver::evaluate(const Iterate& y, const Vec& h, bool jac, Vec& r, Vec& rc) {
  const bool pd = barrier_ == BarrierMode::PrimalDual;
  rc.setZero();
  const int ss = stage_size();
  r.head(n_vars_).setZero();
  if (jac) {
    trip_.clear();
    rhs_.head(n_vars_).setZero();
  }
  auto add_block = [&](int r0, int c0, const Mat& M) {
    for (int a = 0; a < M.rows(); ++a)
      for (int b = 0; b < M.cols(); ++b) trip_.emplace_back(r0 + a, c0 + b, M(a, b));
  };
  auto add_neg_identity = [&](int r0, int c0, int n) {
    for (int a = 0; a < n; ++a) trip_.emplace_back(r0 + a, c0 + a, -1.0);
  };
  (void)ss;

  for (int i = 0; i < N_; ++i) {
    const Dynamics& f = *prob_.dynamics[i];
    const QuadraticCost& cost = prob_.costs[i];
    const LeadCost& lead = prob_.lead[i];
    for (int k = 0; k < T_; ++k) {
      const int ru = col_u(i, k), rf = col_lam(i, k), rx1 = col_x(i, k + 1);
      Mat& A = A_[i][k];
      Mat& B = B_[i][k];
      f.eval(y.x[i].col(k), y.u[i].col(k), fx_.col(0), A, B);
      const auto lk = y.lam[i].col(k);
      // dL/du_k = 2 R u_k + B' lambda_k
      r.segment(ru, nu_) = 2.0 * cost.R.cwiseProduct(y.u[i].col(k)) + B.transpose() * lk;
      // F_k = f(x_k, u_k) - x_{k+1}
      r.segment(rf, nx_) = fx_.col(0) - y.x[i].col(k + 1);
      // dL/dx_{k+1}: cost gradient - lambda_k (+ A_{k+1}' lambda_{k+1}, added at stage k+1)
      const bool terminal = (k + 1 == T_);
      const Vec& qr = terminal ? cost.Qf_ref : cost.Q_ref;
      const Vec& q = terminal ? cost.Qf : cost.Q;
      const auto x1 = y.x[i].col(k + 1);
      r.segment(rx1, nx_) += 2.0 * (qr.cwiseProduct(x1 - cost.x_ref) + q.cwiseProduct(x1)) - lk;
      if (lead.weight != 0.0 && N_ > 1) r[rx1 + lead.index] += -lead.weight * (N_ - 1);
      if (k >= 1) r.segment(col_x(i, k), nx_) += A.transpose() * lk;

      if (jac) {
        f.lambda_hessian(y.x[i].col(k), y.u[i].col(k), lk, Hl_);
        // rows dL/du_k
        Mat Huu = Hl_.bottomRightCorner(nu_, nu_);
        Huu.diagonal() += 2.0 * cost.R;
        add_block(ru, ru, Huu);
        add_block(ru, rf, B.transpose());
        // rows F_k
        add_block(rf, ru, B);
        add_neg_identity(rf, rx1, nx_);
        // rows dL/dx_{k+1}
        add_neg_identity(rx1, rf, nx_);
        Mat Hc = Mat::Zero(nx_, nx_);
        Hc.diagonal() = 2.0 * (qr + q);
        add_block(rx1, rx1, Hc);
        if (k >= 1) {
          const int rxk = col_x(i, k);
          add_block(ru, rxk, Hl_.bottomLeftCorner(nu_, nx_));
          add_block(rxk, ru, Hl_.topRightCorner(nx_, nu_));
          add_block(rxk, rxk, Hl_.topLeftCorner(nx_, nx_));
          add_block(rxk, rf, A.transpose());
          add_block(rf, rxk, A);
        }
      }
    }
  }

  // Constraints: equality rows + multiplier columns (Active), barrier terms (Barrier), nothing (Free).
  using Kd = Constraint::Kind;
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  const double rho = rho_;
  Eigen::Vector2d g;
  Eigen::Matrix2d H;
  double hv;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    const ConstraintState st = state_[c];
    if (st == ConstraintState::Free) continue;
    const Constraint& cn = cons_[c];
    eval_constraint(y, c, hv, g, H);
    if (st == ConstraintState::Barrier && !(hv < 0)) return false;
    const bool pos = cn.kind == Kd::Pair || cn.kind == Kd::Obstacle;
    const bool on_u = cn.kind == Kd::ControlMax || cn.kind == Kd::ControlMin;
    // Row offset of the variable block the constraint acts on, for agent i (and j for pairs).
    const int base_i = on_u ? col_u(cn.i, cn.k) : col_x(cn.i, cn.k);
    const int base_j = cn.kind == Kd::Pair ? col_x(cn.j, cn.k) : -1;
    int ci[2], cj[2];
    int nidx = 1;
    if (pos) { ci[0] = base_i + px; ci[1] = base_i + py; nidx = 2; }
    else ci[0] = base_i + cn.idx;
    if (base_j >= 0) { cj[0] = base_j + px; cj[1] = base_j + py; }
    // g is dh/d(own position) (or dh/d(component)); for pairs dh/dp_j = -g.
    double wi, wj;  // stationarity weights of agent i and j
    if (st == ConstraintState::Active) {
      wi = y.mu[c];
      wj = mu2_col_[c] >= 0 ? y.mu2[c] : y.mu[c];
    } else {
      wi = wj = pd ? y.z[c] : -rho / hv;
      if (pd) rc[c] = -hv * y.z[c] - rho;
    }
    for (int a = 0; a < nidx; ++a) r[ci[a]] += wi * g[a];
    if (base_j >= 0)
      for (int a = 0; a < nidx; ++a) r[cj[a]] += -wj * g[a];
    if (st == ConstraintState::Active) {
      r[mu_col_[c]] = hv;
      if (mu2_col_[c] >= 0) r[mu2_col_[c]] = hv;
    }
    if (!jac) continue;
    if (st == ConstraintState::Active) {
      const int m1 = mu_col_[c], m2 = mu2_col_[c] >= 0 ? mu2_col_[c] : mu_col_[c];
      for (int a = 0; a < nidx; ++a) {
        trip_.emplace_back(ci[a], m1, g[a]);
        trip_.emplace_back(m1, ci[a], g[a]);
        if (mu2_col_[c] >= 0) trip_.emplace_back(m2, ci[a], g[a]);
        if (base_j >= 0) {
          trip_.emplace_back(cj[a], m2, -g[a]);
          trip_.emplace_back(m1, cj[a], -g[a]);
          if (mu2_col_[c] >= 0) trip_.emplace_back(m2, cj[a], -g[a]);
        }
      }
      if (pos)
        for (int a = 0; a < 2; ++a)
          for (int b = 0; b < 2; ++b) {
            trip_.emplace_back(ci[a], ci[b], wi * H(a, b));
            if (base_j >= 0) {
              trip_.emplace_back(ci[a], cj[b], -wi * H(a, b));
              trip_.emplace_back(cj[a], cj[b], wj * H(a, b));
              trip_.emplace_back(cj[a], ci[b], -wj * H(a, b));
            }
          }
    } else {
      // Primal: d/dx of (-rho/h) grad h = rho/h^2 grad h grad h' + (-rho/h) hess h.
      // Primal-dual (z eliminated): z/(-h) grad h grad h' + z hess h, and the right-hand side becomes the
      // paper's barrier residual: shift the rows by (-rho/h - z) grad h.
      const double s2 = pd ? y.z[c] / -hv : rho / (hv * hv);
      if (pd) {
        const double shift = -rho / hv - y.z[c];
        for (int a = 0; a < nidx; ++a) rhs_[ci[a]] += shift * g[a];
        if (base_j >= 0)
          for (int a = 0; a < nidx; ++a) rhs_[cj[a]] -= shift * g[a];
      }
      for (int a = 0; a < nidx; ++a)
        for (int b = 0; b < nidx; ++b) {
          const double v = s2 * g[a] * g[b] + (pos ? wi * H(a, b) : 0.0);
          trip_.emplace_back(ci[a], ci[b], v);
          if (base_j >= 0) {
            trip_.emplace_back(ci[a], cj[b], -v);
            trip_.emplace_back(cj[a], cj[b], v);
            trip_.emplace_back(cj[a], ci[b], -v);
          }
        }
    }
  }
  (void)h;
  if (jac) {
    // rhs_ collected only the barrier shifts so far; add the residual itself.
    rhs_.head(n_vars_) += r.head(n_vars_);
  }
  return r.head(n_vars_).allFinite() && rc.allFinite();
}

void Solver::recover_dual_step(const Iterate& y, const Vec& h, const Vec& rc, const Vec& dy, Vec& dz) const {
  // From the complementarity row: -z grad h' dp - h dz = -rc  =>  dz = (z grad h' dp - rc) / (-h).
  using Kd = Constraint::Kind;
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  Eigen::Vector2d g;
  Eigen::Matrix2d H;
  double hv;
  dz.setZero();
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    if (state_[c] != ConstraintState::Barrier) continue;
    const Constraint& cn = cons_[c];
    eval_constraint(y, c, hv, g, H);
    double gdp;
    if (cn.kind == Kd::Pair || cn.kind == Kd::Obstacle) {
      const int bi = col_x(cn.i, cn.k);
      gdp = g[0] * dy[bi + px] + g[1] * dy[bi + py];
      if (cn.kind == Kd::Pair) {
        const int bj = col_x(cn.j, cn.k);
        gdp -= g[0] * dy[bj + px] + g[1] * dy[bj + py];
      }
    } else {
      const bool on_u = cn.kind == Kd::ControlMax || cn.kind == Kd::ControlMin;
      gdp = g[0] * dy[(on_u ? col_u(cn.i, cn.k) : col_x(cn.i, cn.k)) + cn.idx];
    }
    dz[c] = (y.z[c] * gdp - rc[c]) / -h[c];
  }
}

// -------------------------------------------------------------------------------------------------
void Solver::build_J() {
  if (J_built_) return;
  J_.resize(n_vars_, n_vars_);
  J_.setFromTriplets(trip_.begin(), trip_.end());
  J_.makeCompressed();
  J_built_ = true;
}

bool Solver::solve_linear(Vec& dy) {
  J_built_ = false;
  if (settings_.linear_solver == LinearSolver::Riccati && n_vars_ == n_primal_) {
    if (riccati_.solve(trip_, rhs_, dy)) {
      // Check the step against the assembled system (O(nnz)); a poorly conditioned recursion falls back to LU.
      Vec res = rhs_.head(n_vars_);
      for (const auto& t : trip_) res[t.row()] += t.value() * dy[t.col()];
      if (res.norm() <= 1e-9 * std::max(1.0, rhs_.head(n_vars_).norm())) {
        info_->riccati_solves++;
        return true;
      }
      if (settings_.verbose) std::printf("   Riccati residual %.2e: falling back to sparse LU\n", res.norm());
    }
  }
  build_J();
  const Vec rhs = -rhs_.head(n_vars_);
  auto qr_solve = [&]() -> bool {
    Eigen::SparseQR<SpMat, Eigen::COLAMDOrdering<int>> qr;
    qr.compute(J_);
    if (qr.info() != Eigen::Success) return false;
    dy.head(n_vars_) = qr.solve(rhs);
    info_->qr_fallbacks++;
    return qr.info() == Eigen::Success && dy.head(n_vars_).allFinite();
  };
  switch (settings_.linear_solver) {
    case LinearSolver::Riccati:
    case LinearSolver::SparseLU: {
      // The sparsity pattern depends only on which constraints are equalities: analyse it only when that changes.
      if (!lu_analyzed_ || pattern_state_ != state_) {
        lu_.analyzePattern(J_);
        pattern_state_ = state_;
        lu_analyzed_ = true;
        info_->symbolic_factorizations++;
      }
      lu_.factorize(J_);
      if (lu_.info() == Eigen::Success) {
        dy.head(n_vars_) = lu_.solve(rhs);
        // Iterative refinement with the same factors: the Newton matrix can be badly scaled (barrier
        // curvature z/(-h) next to O(1) entries), and an inaccurate step is not a descent direction.
        for (int ref = 0; ref < settings_.refinement_steps; ++ref) {
          const Vec res = rhs - J_ * dy.head(n_vars_);
          if (settings_.verbose) std::printf("   linear residual %.2e (rhs %.2e)\n", res.norm(), rhs.norm());
          if (res.norm() <= 1e-12 * rhs.norm()) break;
          dy.head(n_vars_) += lu_.solve(res);
        }
        if (lu_.info() == Eigen::Success && dy.head(n_vars_).allFinite()) return true;
      }
      lu_analyzed_ = false;  // a failed factorisation may leave the symbolic data unusable
      return qr_solve();
    }
    case LinearSolver::LSCG: {
      Eigen::LeastSquaresConjugateGradient<SpMat> cg;
      cg.setTolerance(settings_.lscg_tol);
      cg.setMaxIterations(settings_.lscg_max_iter);
      cg.compute(J_);
      dy.head(n_vars_) = cg.solve(rhs);
      if (cg.info() == Eigen::Success && dy.head(n_vars_).allFinite()) return true;
      return qr_solve();
    }
    case LinearSolver::SparseQR: {
      const bool ok = qr_solve();
      info_->qr_fallbacks--;  // not a fallback when QR is the chosen method
      return ok;
    }
  }
  return false;
}

void Solver::apply_step(const Iterate& y, const Vec& dy, double t, Iterate& out) const {
  for (int i = 0; i < N_; ++i) {
    out.x[i].col(0) = y.x[i].col(0);
    for (int k = 0; k < T_; ++k) {
      out.u[i].col(k) = y.u[i].col(k) + t * dy.segment(col_u(i, k), nu_);
      out.lam[i].col(k) = y.lam[i].col(k) + t * dy.segment(col_lam(i, k), nx_);
      out.x[i].col(k + 1) = y.x[i].col(k + 1) + t * dy.segment(col_x(i, k + 1), nx_);
    }
  }
  out.mu = y.mu;
  out.mu2 = y.mu2;
  out.z = y.z + t * dz_;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    if (mu_col_[c] >= 0) out.mu[c] = y.mu[c] + t * dy[mu_col_[c]];
    if (mu2_col_[c] >= 0) out.mu2[c] = y.mu2[c] + t * dy[mu2_col_[c]];
  }
}

// Backtracking line search (paper, Algorithm 1), with the partition and rho of this iteration:
// accept t when ||r(y + t dy)|| <= (1 - alpha t) ||r(y)|| and the total violation does not grow.
double Solver::line_search(double merit0) {
  const double hsum = violation_sum(h_);
  double t = 1.0;
  if (barrier_ == BarrierMode::PrimalDual) {
    recover_dual_step(y_, h_, rc_, dy_, dz_);
    // Fraction to the boundary: barrier duals stay positive.
    for (int c = 0; c < static_cast<int>(cons_.size()); ++c)
      if (state_[c] == ConstraintState::Barrier && dz_[c] < 0)
        t = std::min(t, -settings_.fraction_to_boundary * y_.z[c] / dz_[c]);
  } else {
    dz_.setZero();
  }
  for (int ls = 0; ls < settings_.ls_max_steps; ++ls, t *= settings_.ls_beta) {
    apply_step(y_, dy_, t, trial_);
    eval_all_constraints(trial_, h_trial_);
    if (violation_sum(h_trial_) > hsum + 1e-12) {
      if (settings_.verbose) std::printf("   t %.2e rejected: violation %.3e > %.3e\n", t, violation_sum(h_trial_), hsum);
      continue;
    }
    if (!evaluate(trial_, h_trial_, false, r_trial_, rc_trial_)) {
      if (settings_.verbose) std::printf("   t %.2e rejected: barrier constraint crossed\n", t);
      continue;
    }
    const double mt = merit(r_trial_, rc_trial_);
    if (mt <= (1.0 - settings_.ls_alpha * t) * merit0) return t;
    if (settings_.verbose) std::printf("   t %.2e rejected: |r| %.3e vs %.3e\n", t, mt, merit0);
  }
  return 0.0;
}

// Levenberg-Marquardt direction on ||r||^2: (J'J + nu I) dy = -J' r, always a descent direction.
bool Solver::solve_levenberg_marquardt(double nu, Vec& dy) {
  build_J();
  SpMat JtJ = J_.transpose() * J_;
  for (int d = 0; d < n_vars_; ++d) JtJ.coeffRef(d, d) += nu;
  Eigen::SimplicialLDLT<SpMat> ldlt(JtJ);
  if (ldlt.info() != Eigen::Success) return false;
  dy.head(n_vars_) = ldlt.solve(-(J_.transpose() * rhs_.head(n_vars_)));
  if (settings_.verbose) std::printf("   Levenberg-Marquardt step, nu %.2e\n", nu);
  return ldlt.info() == Eigen::Success && dy.head(n_vars_).allFinite();
}

std::vector<int> Solver::debug_residual(const std::vector<Mat>& x, const std::vector<Mat>& u,
                                       const std::vector<Mat>& lam, const Vec& mu, double rho, Vec& r, Mat& J) {
  require(static_cast<int>(x.size()) == N_ && static_cast<int>(u.size()) == N_ && static_cast<int>(lam.size()) == N_,
          "debug_residual: x, u, lam need one entry per agent");
  for (int i = 0; i < N_; ++i)
    require(x[i].rows() == T_ + 1 && x[i].cols() == nx_ && u[i].rows() == T_ && u[i].cols() == nu_ &&
                lam[i].rows() == T_ && lam[i].cols() == nx_,
            "debug_residual: x (T+1, nx), u (T, nu), lam (T, nx) per agent");
  require(mu.size() == static_cast<int>(cons_.size()), "debug_residual: mu needs one entry per constraint");
  require(rho > 0, "debug_residual: rho must be positive");
  for (int i = 0; i < N_; ++i) {
    y_.x[i] = x[i].transpose();
    y_.u[i] = u[i].transpose();
    y_.lam[i] = lam[i].transpose();
  }
  y_.mu = mu;
  y_.mu2 = mu;
  y_.z.setZero();  // barrier duals start at zero, as in solve()
  barrier_ = settings_.barrier;
  rho_ = rho;
  eval_all_constraints(y_, h_);
  classify(h_, true);
  number_multipliers();
  Info info;
  info_ = &info;
  evaluate(y_, h_, true, r_, rc_);
  info_ = nullptr;
  r = r_.head(n_vars_);
  SpMat Js(n_vars_, n_vars_);
  Js.setFromTriplets(trip_.begin(), trip_.end());
  J = Mat(Js);
  return mu_col_;
}

bool Solver::polish(const Vec& h) {
  bool any = false;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    if (state_[c] != ConstraintState::Barrier || h[c] < -settings_.polish_gap) continue;
    state_[c] = ConstraintState::Active;
    // The barrier dual (or -rho/h in the primal form) is the multiplier estimate.
    const double mu = barrier_ == BarrierMode::PrimalDual ? y_.z[c] : -rho_ / h[c];
    y_.mu[c] = y_.mu2[c] = mu;
    y_.z[c] = 0;
    any = true;
  }
  return any;
}

// -------------------------------------------------------------------------------------------------
Result Solver::solve(const WarmStart* warm) {
  if (N_ == 0) throw std::logic_error("setup() must be called before solve()");
  const auto t_start = Clock::now();
  Result res;
  Info& info = res.info;
  info_ = &info;
  const int C = static_cast<int>(cons_.size());

  // Initial guess: given (or zero) controls, rolled out so that the dynamics hold exactly.
  std::vector<Mat> u_init(N_), lam_init(N_);
  for (int i = 0; i < N_; ++i) {
    if (warm && static_cast<int>(warm->u.size()) == N_) {
      require(warm->u[i].rows() == T_ && warm->u[i].cols() == nu_ && warm->u[i].allFinite(), "warm start u has the wrong shape or non-finite values");
      u_init[i] = warm->u[i].transpose();
    } else {
      u_init[i] = Mat::Zero(nu_, T_);
    }
    if (warm && static_cast<int>(warm->lambda.size()) == N_) {
      require(warm->lambda[i].rows() == T_ && warm->lambda[i].cols() == nx_ && warm->lambda[i].allFinite(), "warm start lambda has the wrong shape or non-finite values");
      lam_init[i] = warm->lambda[i].transpose();
    } else {
      lam_init[i] = Mat::Zero(nx_, T_);
    }
  }
  const bool have_mu = warm && warm->mu.size() == C;
  if (have_mu) require(warm->mu.allFinite(), "warm start mu has non-finite values");
  const double rho_floor = settings_.tol * settings_.rho_floor_factor;
  std::mt19937 rng(12345);
  std::normal_distribution<double> noise(0.0, 1.0);
  int total_iter = 0;

  for (int attempt = 0; attempt <= settings_.restarts; ++attempt) {
    info.attempts = attempt + 1;
    for (int i = 0; i < N_; ++i) {
      y_.x[i].col(0) = prob_.x0[i];
      y_.u[i] = u_init[i];
      if (attempt >= 4)
        // A constant offset per agent and control component (not white noise, which averages out):
        // it changes the order in which agents reach a contested region, i.e. the equilibrium's basin.
        for (int q = 0; q < nu_; ++q) {
          const double offset = settings_.restart_u_std * noise(rng);
          y_.u[i].row(q).array() += offset;
        }
      y_.lam[i] = attempt == 0 ? lam_init[i] : Mat::Zero(nx_, T_);
      for (int k = 0; k < T_; ++k) {
        prob_.dynamics[i]->eval(y_.x[i].col(k), y_.u[i].col(k), fx_.col(0), Atmp_, Btmp_);
        y_.x[i].col(k + 1) = fx_.col(0);
      }
    }
    y_.mu.setZero();
    y_.mu2.setZero();
    y_.z.setZero();
    if (have_mu && attempt == 0) { y_.mu = warm->mu; y_.mu2 = warm->mu; }
    // Restart schedule (measured on the merging games, each variant rescues different instances):
    // attempt 1: 10x rho_init; 2: the other barrier form; 3: both; >= 4: the same four with perturbed controls.
    const int variant = attempt % 4;
    rho_ = settings_.rho_init * ((variant == 1 || variant == 3) ? 10.0 : 1.0);
    barrier_ = settings_.barrier;
    if (variant >= 2)
      barrier_ = settings_.barrier == BarrierMode::PrimalDual ? BarrierMode::Primal : BarrierMode::PrimalDual;
    lu_analyzed_ = false;
    std::vector<double> merits;
    bool first = true, stalled = false, polished = false;
    info.status = Status::MaxIterations;
    for (;; ++total_iter) {
      auto t0 = Clock::now();
      eval_all_constraints(y_, h_);
      classify(h_, first);
      first = false;
      number_multipliers();
      const bool ok = evaluate(y_, h_, true, r_, rc_);
      info.timings.assembly += seconds_since(t0);
      if (!ok) { info.status = Status::NumericalError; break; }
      const double rnorm = merit(r_, rc_);
      info.residual_history.push_back(rnorm);
      merits.push_back(rnorm);
      info.residual_norm = rnorm;
      info.iterations = total_iter;
      bool signs_ok = true;
      for (int c = 0; c < C; ++c)
        if (state_[c] == ConstraintState::Active &&
            (y_.mu[c] < -settings_.multiplier_tol || (mu2_col_[c] >= 0 && y_.mu2[c] < -settings_.multiplier_tol)))
          signs_ok = false;
      const double maxviol = C ? std::max(0.0, h_.maxCoeff()) : 0.0;
      if (settings_.verbose)
        std::printf("it %3d  |r| %.3e  rho %.2e  viol %.2e  active %d\n", total_iter, rnorm, rho_, maxviol, n_vars_ - n_primal_);
      double max_defect = 0;
      for (int i = 0; i < N_; ++i)
        for (int k = 0; k < T_; ++k) max_defect = std::max(max_defect, r_.segment(col_lam(i, k), nx_).cwiseAbs().maxCoeff());
      if (rnorm < settings_.tol && maxviol <= settings_.violation_tol && max_defect <= settings_.dynamics_tol && signs_ok &&
          (C == 0 || rho_ <= rho_floor * (1 + 1e-9))) {
        info.status = Status::Converged;
        break;
      }
      if (total_iter >= settings_.max_iter) { info.status = Status::MaxIterations; break; }
      if (settings_.time_limit > 0 && seconds_since(t_start) > settings_.time_limit) { info.status = Status::TimeLimit; break; }
      const int w = settings_.stall_window;
      if (w > 0 && static_cast<int>(merits.size()) > w && rnorm > 0.99 * merits[merits.size() - 1 - w]) {
        // Before giving the attempt up: hold the nearly active barrier constraints as equalities (once per
        // attempt). A stall with rho at its floor is often the barrier's ill-conditioning around a contact
        // that the equilibrium needs; the equality form has no such curvature.
        if (polished || settings_.polish_gap <= 0 || !polish(h_)) { stalled = true; break; }
        polished = true;
        number_multipliers();
        evaluate(y_, h_, true, r_, rc_);
        merits.assign(1, merit(r_, rc_));
        if (settings_.verbose) std::printf("stall: %d nearly active constraints held as equalities\n", n_vars_ - n_primal_);
      }

      t0 = Clock::now();
      const bool solved = solve_linear(dy_);
      info.timings.linear_solve += seconds_since(t0);
      if (!solved) { info.status = Status::NumericalError; break; }

      t0 = Clock::now();
      double t = line_search(rnorm);
      if (t > 0 && t < settings_.lm_below_step) {
        // A tiny accepted Newton step means a nearly singular Newton matrix (huge step, merit only
        // decreasing for t -> 0). Keep it, but let Levenberg-Marquardt steps compete with it.
        best_ = trial_;
        double best_m = merit(r_trial_, rc_trial_);
        bool lm_won = false;
        for (int q = 0; q < settings_.lm_tries; ++q) {
          if (!solve_levenberg_marquardt(settings_.lm_nu_init * std::pow(10.0, q) * rnorm, dy_)) break;
          const double tl = line_search(rnorm);
          if (tl > 0) {
            const double m = merit(r_trial_, rc_trial_);
            if (m < best_m) { best_m = m; std::swap(best_, trial_); t = tl; lm_won = true; }
          }
        }
        std::swap(trial_, best_);
        if (lm_won) info.lm_steps++;
      }
      for (int q = 0; t == 0.0 && q < settings_.lm_tries; ++q) {
        if (!solve_levenberg_marquardt(settings_.lm_nu_init * std::pow(10.0, q) * rnorm, dy_)) break;
        t = line_search(rnorm);
        if (t > 0) info.lm_steps++;
      }
      info.timings.line_search += seconds_since(t0);
      if (t == 0.0) { info.status = Status::LineSearchFailed; break; }
      std::swap(y_, trial_);
      info.step_history.push_back(t);
      if (settings_.rho_progress <= 0 || rnorm <= settings_.rho_progress * rho_)
        rho_ = std::max(rho_floor, std::min(settings_.rho_kappa * rho_, std::pow(rho_, settings_.rho_beta)));
    }
    if (info.status == Status::Converged || info.status == Status::TimeLimit || info.status == Status::NumericalError ||
        total_iter >= settings_.max_iter)
      break;
    if (polished && info.status == Status::LineSearchFailed) stalled = true;  // the polish was the stall's last resort
    if (stalled) info.status = Status::Stalled;  // reported if no attempt is left
    if (settings_.verbose) std::printf("attempt %d ended (%s), restarting\n", attempt, stalled ? "stalled" : status_name(info.status).c_str());
    ++total_iter;
  }

  // Result: trajectories, multipliers (barrier-implied -rho/h for inactive constraints).
  eval_all_constraints(y_, h_);
  if (settings_.second_order_gap >= 0 && info.status != Status::NumericalError && !check_second_order(info) &&
      info.status == Status::Converged)
    info.status = Status::Saddle;
  res.x.resize(N_);
  res.u.resize(N_);
  res.lambda.resize(N_);
  for (int i = 0; i < N_; ++i) {
    res.x[i] = y_.x[i].transpose();
    res.u[i] = y_.u[i].transpose();
    res.lambda[i] = y_.lam[i].transpose();
  }
  res.mu = Vec::Zero(C);
  int nact = 0;
  for (int c = 0; c < C; ++c) {
    if (state_[c] == ConstraintState::Active) {
      res.mu[c] = mu2_col_[c] >= 0 ? 0.5 * (y_.mu[c] + y_.mu2[c]) : y_.mu[c];
      ++nact;
    } else if (state_[c] == ConstraintState::Barrier && h_[c] < 0) {
      res.mu[c] = barrier_ == BarrierMode::PrimalDual ? y_.z[c] : -rho_ / h_[c];
    }
  }
  res.h = h_;
  info.active_constraints = nact;
  info.max_violation = C ? std::max(0.0, h_.maxCoeff()) : 0.0;
  info.rho = rho_;
  info.timings.total = seconds_since(t_start);
  info_ = nullptr;
  return res;
}

}  // namespace rd3g
