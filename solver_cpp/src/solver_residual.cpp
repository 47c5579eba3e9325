// RD3G's residual of the first-order conditions and its Newton matrix: constraint values, the partition into
// equality / barrier / released constraints, and the assembly of r and J.
#include "rd3g/solver.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

#include "rd3g/validate.hpp"

namespace rd3g {

void Solver::eval_constraint(const Iterate& y, int c, double& h, Eigen::Vector2d* g, Eigen::Matrix2d* H) const {
  // The 2-variable form of rd3g::eval_constraint (g, H with respect to agent i's own position or component;
  // for pairs dh/dp_j = -g), without its 4 x 4 Hessian: this runs for every constraint at every evaluation.
  const Constraint& cn = cons_[c];
  using K = Constraint::Kind;
  if (g) g->setZero();
  if (H) H->setZero();
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  double sign = 0;  // dh/d(component) of a bound
  switch (cn.kind) {
    case K::Pair: {
      const Eigen::Vector2d d(y.x[cn.i](px, cn.k) - y.x[cn.j](px, cn.k), y.x[cn.i](py, cn.k) - y.x[cn.j](py, cn.k));
      distance_constraint(prob_.collision.form, d, prob_.collision.at(cn.i, cn.j, cn.k), h, g, H, prob_.collision.x_scale(cn.k));
      return;
    }
    case K::Obstacle: {
      const Obstacle& o = prob_.obstacles[cn.j];
      const Eigen::Vector2d d(y.x[cn.i](px, cn.k) - o.positions(cn.k, 0), y.x[cn.i](py, cn.k) - o.positions(cn.k, 1));
      distance_constraint(prob_.collision.form, d, o.at(cn.k), h, g, H, prob_.collision.x_scale(cn.k));
      return;
    }
    case K::StateMax: h = y.x[cn.i](cn.idx, cn.k) - prob_.x_max[cn.i][cn.idx]; sign = 1; break;
    case K::StateMin: h = prob_.x_min[cn.i][cn.idx] - y.x[cn.i](cn.idx, cn.k); sign = -1; break;
    case K::ControlMax: h = y.u[cn.i](cn.idx, cn.k) - prob_.u_max[cn.i][cn.idx]; sign = 1; break;
    case K::ControlMin: h = prob_.u_min[cn.i][cn.idx] - y.u[cn.i](cn.idx, cn.k); sign = -1; break;
  }
  if (g) (*g)[0] = sign;
}

double Solver::constraint_value(const Iterate& y, int c) const {
  double h = 0;
  eval_constraint(y, c, h, nullptr, nullptr);
  return h;
}

void Solver::eval_all_constraints(const Iterate& y, Vec& h) const {
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) h[c] = constraint_value(y, c);
}

double Solver::violation_sum(const Vec& h) const { return h.cwiseMax(0.0).sum(); }

// Partition (paper, Sec. III-A) with two safeguards: an active constraint stays an equality while it
// sits at h ~ 0 (the barrier is undefined there), and one whose multiplier turns negative is released
// (Free) until it is far enough inside to be handed to the barrier.
void Solver::classify(const Vec& h, bool first) {
  const double margin = settings_.barrier.margin;
  // A guess built by single-agent sub-solves has each agent's own constraints a hair inside (its barrier at the
  // sub-solve's floor): held as equalities, not left Free where Newton would not see them.
  const double active_from = start_holds_contacts_ ? -margin : 0.0;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    ConstraintState& st = state_[c];
    if (first) {
      // Duals start at zero (warm-start multipliers aside): the first Newton step carries no barrier
      // curvature, and z is then driven towards rho/(-h) by the complementarity rows. (Starting on the
      // central path was measured to converge less often on the merging games.)
      st = h[c] >= active_from ? ConstraintState::Active
                               : (h[c] < -margin ? ConstraintState::Barrier : ConstraintState::Free);
      continue;
    }
    switch (st) {
      case ConstraintState::Barrier:
        if (h[c] >= 0) st = ConstraintState::Active;  // only possible if the line search was bypassed
        break;
      case ConstraintState::Active: {
        const bool wrong_sign = y_.mu[c] < -kMultiplierTol ||
                                (mu2_col_[c] >= 0 && y_.mu2[c] < -kMultiplierTol);
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
  rc.setZero();
  r.head(n_vars_).setZero();
  if (jac) {
    trip_.clear();
    rhs_.head(n_vars_).setZero();
  }
  for (int i = 0; i < N_; ++i)
    for (int k = 0; k < T_; ++k)
      add_stage_terms(layout_, i, k, T_, *prob_.dynamics[i], stage_patterns_[i], prob_.costs[i], prob_.lead[i],
                      y.x[i], y.u[i], y.lam[i].col(k), r, jac ? &trip_ : nullptr, stage_);
  // Constraints: equality rows + multiplier columns (Active), barrier terms (Barrier), nothing (Free).
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c)
    if (state_[c] != ConstraintState::Free && !add_constraint_terms(y, c, jac, r, rc)) return false;
  (void)h;
  if (jac) {
    // rhs_ collected only the barrier shifts so far; add the residual itself.
    rhs_.head(n_vars_) += r.head(n_vars_);
  }
  return r.head(n_vars_).allFinite() && rc.allFinite();
}

Solver::ConstraintRows Solver::constraint_rows(int c) const {
  using Kd = Constraint::Kind;
  const Constraint& cn = cons_[c];
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  ConstraintRows q;
  q.pos = cn.kind == Kd::Pair || cn.kind == Kd::Obstacle;
  const bool on_u = cn.kind == Kd::ControlMax || cn.kind == Kd::ControlMin;
  // Row offset of the variable block the constraint acts on, for agent i (and j for pairs).
  const int base_i = on_u ? col_u(cn.i, cn.k) : col_x(cn.i, cn.k);
  const int base_j = cn.kind == Kd::Pair ? col_x(cn.j, cn.k) : -1;
  if (q.pos) { q.ci[0] = base_i + px; q.ci[1] = base_i + py; q.n = 2; }
  else q.ci[0] = base_i + cn.idx;
  q.pair = base_j >= 0;
  if (q.pair) { q.cj[0] = base_j + px; q.cj[1] = base_j + py; }
  return q;
}

bool Solver::add_constraint_terms(const Iterate& y, int c, bool jac, Vec& r, Vec& rc) {
  const ConstraintState st = state_[c];
  const bool pd = barrier_ == BarrierMode::PrimalDual;
  Eigen::Vector2d g;
  Eigen::Matrix2d H;
  double hv;
  eval_constraint(y, c, hv, &g, jac ? &H : nullptr);
  if (st == ConstraintState::Barrier && !(hv < 0)) return false;
  const ConstraintRows q = constraint_rows(c);
  // g is dh/d(own position) (or dh/d(component)); for pairs dh/dp_j = -g.
  double wi, wj;  // stationarity weights of agent i and j
  if (st == ConstraintState::Active) {
    wi = y.mu[c];
    wj = mu2_col_[c] >= 0 ? y.mu2[c] : y.mu[c];
  } else {
    wi = wj = pd ? y.z[c] : -rho_ / hv;
    if (pd) rc[c] = -hv * y.z[c] - rho_;
  }
  for (int a = 0; a < q.n; ++a) r[q.ci[a]] += wi * g[a];
  if (q.pair)
    for (int a = 0; a < q.n; ++a) r[q.cj[a]] += -wj * g[a];
  if (st == ConstraintState::Active) {
    r[mu_col_[c]] = hv;
    if (mu2_col_[c] >= 0) r[mu2_col_[c]] = hv;
  }
  if (!jac) return true;
  if (st == ConstraintState::Active) add_active_jacobian(c, q, g, H, wi, wj);
  else add_barrier_jacobian(y, c, q, hv, g, H, wi);
  return true;
}

void Solver::add_active_jacobian(int c, const ConstraintRows& q, const Eigen::Vector2d& g, const Eigen::Matrix2d& H,
                                 double wi, double wj) {
  const int m1 = mu_col_[c], m2 = mu2_col_[c] >= 0 ? mu2_col_[c] : mu_col_[c];
  for (int a = 0; a < q.n; ++a) {
    trip_.emplace_back(q.ci[a], m1, g[a]);
    trip_.emplace_back(m1, q.ci[a], g[a]);
    if (mu2_col_[c] >= 0) trip_.emplace_back(m2, q.ci[a], g[a]);
    if (q.pair) {
      trip_.emplace_back(q.cj[a], m2, -g[a]);
      trip_.emplace_back(m1, q.cj[a], -g[a]);
      if (mu2_col_[c] >= 0) trip_.emplace_back(m2, q.cj[a], -g[a]);
    }
  }
  if (!q.pos) return;
  for (int a = 0; a < 2; ++a)
    for (int b = 0; b < 2; ++b) {
      trip_.emplace_back(q.ci[a], q.ci[b], wi * H(a, b));
      if (q.pair) {
        trip_.emplace_back(q.ci[a], q.cj[b], -wi * H(a, b));
        trip_.emplace_back(q.cj[a], q.cj[b], wj * H(a, b));
        trip_.emplace_back(q.cj[a], q.ci[b], -wj * H(a, b));
      }
    }
}

// Primal: d/dx of (-rho/h) grad h = rho/h^2 grad h grad h' + (-rho/h) hess h.
// Primal-dual (z eliminated): z/(-h) grad h grad h' + z hess h, and the right-hand side becomes the
// paper's barrier residual: shift the rows by (-rho/h - z) grad h.
void Solver::add_barrier_jacobian(const Iterate& y, int c, const ConstraintRows& q, double hv, const Eigen::Vector2d& g,
                                  const Eigen::Matrix2d& H, double wi) {
  const bool pd = barrier_ == BarrierMode::PrimalDual;
  const double s2 = pd ? y.z[c] / -hv : rho_ / (hv * hv);
  if (pd) {
    const double shift = -rho_ / hv - y.z[c];
    for (int a = 0; a < q.n; ++a) rhs_[q.ci[a]] += shift * g[a];
    if (q.pair)
      for (int a = 0; a < q.n; ++a) rhs_[q.cj[a]] -= shift * g[a];
  }
  for (int a = 0; a < q.n; ++a)
    for (int b = 0; b < q.n; ++b) {
      const double v = s2 * g[a] * g[b] + (q.pos ? wi * H(a, b) : 0.0);
      trip_.emplace_back(q.ci[a], q.ci[b], v);
      if (q.pair) {
        trip_.emplace_back(q.ci[a], q.cj[b], -v);
        trip_.emplace_back(q.cj[a], q.cj[b], v);
        trip_.emplace_back(q.cj[a], q.ci[b], -v);
      }
    }
}

void Solver::recover_dual_step(const Iterate& y, const Vec& h, const Vec& rc, const Vec& dy, Vec& dz) const {
  // From the complementarity row: -z grad h' dp - h dz = -rc  =>  dz = (z grad h' dp - rc) / (-h).
  using Kd = Constraint::Kind;
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  Eigen::Vector2d g;
  double hv;
  dz.setZero();
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    if (state_[c] != ConstraintState::Barrier) continue;
    const Constraint& cn = cons_[c];
    eval_constraint(y, c, hv, &g, nullptr);
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
  barrier_ = settings_.barrier.mode;
  rho_ = rho;
  eval_all_constraints(y_, h_);
  classify(h_, true);
  number_multipliers();
  evaluate(y_, h_, true, r_, rc_);
  r = r_.head(n_vars_);
  SpMat Js(n_vars_, n_vars_);
  Js.setFromTriplets(trip_.begin(), trip_.end());
  J = Mat(Js);
  return mu_col_;
}

}  // namespace rd3g
