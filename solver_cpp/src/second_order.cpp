#include "rd3g/second_order.hpp"

#include <Eigen/Eigenvalues>
#include <Eigen/QR>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>

#include "rd3g/stage_terms.hpp"

namespace rd3g {

namespace {
// The escape from a saddle: the first step along the unit direction (control units), and rho at its restart (at its
// floor the barrier would hold the agent at the saddle's contacts).
constexpr double kEscapeStep = 1.0;
constexpr double kEscapeRho = 1e-2;

// Three points per interval, six independent Sturm sequences per sweep: a sweep is bound by the division's latency,
// so six cost little more than two, and each narrows its interval four-fold.
constexpr int kPoints = 3, kSeq = 2 * kPoints;

// An interval holding the whole spectrum: Gershgorin's bounds, widened as dstebz does; pivmin keeps a Sturm pivot
// away from 0.
void gershgorin_interval(const Eigen::Ref<const Vec>& d, const Eigen::Ref<const Vec>& e, double& gl, double& gu,
                         double& pivmin) {
  const int n = static_cast<int>(d.size());
  double e2max = 0;
  gl = kInf;
  gu = -kInf;
  for (int i = 0; i < n; ++i) {
    const double r = (i > 0 ? std::abs(e[i - 1]) : 0.0) + (i + 1 < n ? std::abs(e[i]) : 0.0);
    gl = std::min(gl, d[i] - r);
    gu = std::max(gu, d[i] + r);
    if (i + 1 < n) e2max = std::max(e2max, e[i] * e[i]);
  }
  const double eps = std::numeric_limits<double>::epsilon();
  pivmin = std::numeric_limits<double>::min() * std::max(1.0, e2max);
  const double widen = 2.1 * eps * n * std::max(std::abs(gl), std::abs(gu)) + 2.1 * pivmin;
  gl -= widen;
  gu += widen;
}

// Sturm counts: the number of negative pivots of T - x I (its LDL' pivots) is the number of eigenvalues below x.
void sturm_counts(const Eigen::Ref<const Vec>& d, const Eigen::Ref<const Vec>& e, const double (&x)[kSeq],
                  double pivmin, int (&c)[kSeq]) {
  double q[kSeq];
  for (int p = 0; p < kSeq; ++p) {
    q[p] = d[0] - x[p];
    if (std::abs(q[p]) < pivmin) q[p] = -pivmin;
    c[p] = q[p] < 0;
  }
  for (int i = 1; i < static_cast<int>(d.size()); ++i) {
    const double e2 = e[i - 1] * e[i - 1];
    for (int p = 0; p < kSeq; ++p) {
      q[p] = (d[i] - x[p]) - e2 / q[p];
      if (std::abs(q[p]) < pivmin) q[p] = -pivmin;
      c[p] += q[p] < 0;
    }
  }
}
}  // namespace

void tridiagonal_extreme_eigenvalues(const Eigen::Ref<const Vec>& d, const Eigen::Ref<const Vec>& e, double& lo,
                                     double& hi) {
  const int n = static_cast<int>(d.size());
  if (!d.allFinite() || !e.allFinite()) {
    lo = hi = std::numeric_limits<double>::quiet_NaN();
    return;
  }
  if (n == 1) {
    lo = hi = d[0];
    return;
  }
  double gl, gu, pivmin;
  gershgorin_interval(d, e, gl, gu, pivmin);
  // [a[0], b[0]] holds the smallest eigenvalue (no eigenvalue below a[0], at least one below b[0]); [a[1], b[1]]
  // the largest (at most n - 1 below a[1], all n below b[1]). Each is narrowed to the accuracy of the counts
  // themselves (a few ulps of the matrix's norm; dstebz's default abstol), about 26 sweeps.
  const double atol = 4 * std::numeric_limits<double>::epsilon() * std::max(std::abs(gl), std::abs(gu)) + pivmin;
  double a[2] = {gl, gl}, b[2] = {gu, gu};
  bool done[2] = {false, false};  // narrowed to atol, or no representable point left inside
  for (int it = 0; it < 200; ++it) {
    bool more[2];
    double x[kSeq];
    for (int s = 0; s < 2; ++s) {
      more[s] = !done[s] && b[s] - a[s] > atol;
      for (int p = 0; p < kPoints; ++p) x[s * kPoints + p] = a[s] + (b[s] - a[s]) * (p + 1) / (kPoints + 1);
    }
    if (!more[0] && !more[1]) break;
    int c[kSeq];
    sturm_counts(d, e, x, pivmin, c);
    // Interval 0 brackets the first eigenvalue (count >= 1 at its top), interval 1 the last (count n at its top).
    for (int s = 0; s < 2; ++s) {
      if (!more[s]) continue;
      const int need = s == 0 ? 1 : n;
      double na = a[s], nb = b[s];
      for (int p = kPoints - 1; p >= 0; --p)
        if (c[s * kPoints + p] >= need) nb = x[s * kPoints + p];
      for (int p = 0; p < kPoints; ++p)
        if (c[s * kPoints + p] < need) na = x[s * kPoints + p];
      if (na >= nb || (na == a[s] && nb == b[s])) {
        done[s] = true;
        continue;
      }
      a[s] = na;
      b[s] = nb;
    }
  }
  lo = 0.5 * (a[0] + b[0]);
  hi = 0.5 * (a[1] + b[1]);
}

void SecondOrderCheck::setup(int num_agents, int horizon, int nx, int nu) {
  N_ = num_agents;
  T_ = horizon;
  nx_ = nx;
  nu_ = nu;
  const int m = T_ * nu_;
  S_.assign(T_ + 1, Mat::Zero(nx_, m));
  A_.assign(T_, Mat::Zero(nx_, nx_));
  B_.assign(T_, Mat::Zero(nx_, nu_));
  Q_.assign(T_ + 1, Mat::Zero(nx_, nx_));
  M_.assign(T_, Mat::Zero(nx_, nu_));
  R_.assign(T_, Mat::Zero(nu_, nu_));
  Hr_ = Mat::Zero(m, m);
  Hl_ = Mat::Zero(nx_ + nu_, nx_ + nu_);
  P_ = Mat::Zero(nx_, nx_);
  PA_ = Mat::Zero(nx_, nx_);
  PB_ = Mat::Zero(nx_, nu_);
  W_ = Mat::Zero(nx_, nu_);
  C_ = Mat::Zero(0, m);
  fx_ = Vec::Zero(nx_);
  out_.assign(N_, SecondOrderAgent{});
}

const std::vector<SecondOrderAgent>& SecondOrderCheck::check(const Problem& p, const std::vector<Constraint>& cons,
                                                             const ConstraintEval& eval, const std::vector<Mat>& x,
                                                             const std::vector<Mat>& u, const std::vector<Mat>& lam,
                                                             const Vec& w_i, const Vec& w_j, double active_gap, double tol) {
  for (int a = 0; a < N_; ++a) {
    stage_hessians(p, a, x, u, lam);
    const int na = add_constraints(p, a, cons, eval, w_i, w_j, active_gap);
    condense_hessian();
    reduced_spectrum(a, na, tol);
  }
  return out_;
}

// Stages k = 0..T-1: d2L/d(x_k,u_k)^2 = lambda_k' d2f + cost, split into Q_k (xx), M_k (xu), R_k (uu); x_0 is fixed,
// so Q_0 never enters. Q_T is x_T's cost. S_k = dx_k/dU alongside.
void SecondOrderCheck::stage_hessians(const Problem& p, int a, const std::vector<Mat>& x, const std::vector<Mat>& u,
                                      const std::vector<Mat>& lam) {
  const Dynamics& f = *p.dynamics[a];
  const QuadraticCost& cost = p.costs[a];
  S_[0].setZero();
  for (int k = 0; k < T_; ++k) {
    const int n = (k + 1) * nu_;  // S_{k+1} only touches the controls u_0..u_k
    f.eval(x[a].col(k), u[a].col(k), fx_, A_[k], B_[k]);
    f.lambda_hessian(x[a].col(k), u[a].col(k), lam[a].col(k), Hl_);
    Q_[k] = Hl_.topLeftCorner(nx_, nx_);
    if (k >= 1) Q_[k].diagonal() += state_cost_hessian(cost, k, T_);
    M_[k] = Hl_.topRightCorner(nx_, nu_);
    R_[k] = Hl_.bottomRightCorner(nu_, nu_);
    R_[k].diagonal() += control_cost_hessian(cost);
    S_[k + 1].setZero();
    S_[k + 1].leftCols(n).noalias() = A_[k] * S_[k].leftCols(n);
    S_[k + 1].block(0, k * nu_, nx_, nu_) += B_[k];
  }
  Q_[T_].setZero();
  Q_[T_].diagonal() = state_cost_hessian(cost, T_, T_);
}

// Constraints of agent a: curvature w_c d2h_c onto Q_k, and the Jacobian rows of the ones held as equalities into
// C_'s first rows (their count is returned).
int SecondOrderCheck::add_constraints(const Problem& p, int a, const std::vector<Constraint>& cons,
                                      const ConstraintEval& eval, const Vec& w_i, const Vec& w_j, double active_gap) {
  using K = Constraint::Kind;
  const int px = p.collision.pos_x, py = p.collision.pos_y;
  Eigen::Vector2d g;
  Eigen::Matrix2d H;
  double h;
  int na = 0;
  for (int c = 0; c < static_cast<int>(cons.size()); ++c) {
    const Constraint& cn = cons[c];
    if (!cn.involves(a)) continue;
    eval(c, h, g, H);
    const bool own = cn.i == a;
    const double w = own ? w_i[c] : w_j[c];
    const bool active = h >= -active_gap && w > 0;
    if (active && na >= C_.rows()) C_.conservativeResize(std::max<Eigen::Index>(8, 2 * C_.rows()), T_ * nu_);
    switch (cn.kind) {
      case K::Pair:
      case K::Obstacle: {
        // h depends on d = p_i - p_j (or p_i - o): dh/dp_j = -g, d2h/dp_j^2 = H.
        const Mat& S = S_[cn.k];
        const double s = own ? 1.0 : -1.0;
        if (w != 0.0) {  // curvature on the agent's position at stage k
          Q_[cn.k](px, px) += w * H(0, 0);
          Q_[cn.k](px, py) += w * H(0, 1);
          Q_[cn.k](py, px) += w * H(1, 0);
          Q_[cn.k](py, py) += w * H(1, 1);
        }
        if (active) C_.row(na++) = s * (g[0] * S.row(px) + g[1] * S.row(py));
        break;
      }
      case K::StateMax:
      case K::StateMin:
        if (active) C_.row(na++) = g[0] * S_[cn.k].row(cn.idx);
        break;
      case K::ControlMax:
      case K::ControlMin:
        if (active) {
          C_.row(na).setZero();
          C_(na++, cn.k * nu_ + cn.idx) = g[0];
        }
        break;
    }
  }
  return na;
}

// H_U by a backward recursion (single shooting's condensed Hessian, O(T^2 nx nu^2) instead of O(T^3)): with
// P_{j+1} = sum_{k>j} Phi(k,j+1)' Q_k Phi(k,j+1) (Phi the state transition), block (j, j) is R_j + B_j' P_{j+1} B_j
// and block (i, j), i < j, is (dx_j/du_i)' (A_j' P_{j+1} B_j + M_j).
void SecondOrderCheck::condense_hessian() {
  P_ = Q_[T_];
  for (int j = T_ - 1; j >= 0; --j) {
    PB_.noalias() = P_ * B_[j];
    W_ = M_[j];
    W_.noalias() += A_[j].transpose() * PB_;
    Hr_.block(j * nu_, j * nu_, nu_, nu_) = R_[j];
    Hr_.block(j * nu_, j * nu_, nu_, nu_).noalias() += B_[j].transpose() * PB_;
    if (j > 0) {
      Hr_.block(0, j * nu_, j * nu_, nu_).noalias() = S_[j].leftCols(j * nu_).transpose() * W_;
      Hr_.block(j * nu_, 0, nu_, j * nu_) = Hr_.block(0, j * nu_, j * nu_, nu_).transpose();
    }
    PA_.noalias() = P_ * A_[j];
    P_ = Q_[j];
    P_.noalias() += A_[j].transpose() * PA_;
  }
  Hr_ = 0.5 * (Hr_ + Hr_.transpose()).eval();
}

// Orthonormal basis Z of the na active rows' null space, then the extreme eigenvalues of Z' H_U Z into out_[a] (and
// the eigenvector of the smallest when the agent fails).
void SecondOrderCheck::reduced_spectrum(int a, int na, double tol) {
  const int m = T_ * nu_;
  SecondOrderAgent& out = out_[a];
  out.active = na;
  Mat Z;  // empty if na == 0 (Z = I)
  if (na > 0) {
    Eigen::ColPivHouseholderQR<Mat> qr(C_.topRows(na).transpose());
    qr.setThreshold(1e-9);
    const int r = static_cast<int>(qr.rank());
    const Mat Q = qr.householderQ();
    Z = Q.rightCols(m - r);
  }
  out.free_directions = na > 0 ? static_cast<int>(Z.cols()) : m;
  out.direction.resize(0, 0);
  if (out.free_directions == 0) {
    out.min_eigenvalue = kInf;
    out.max_abs_eigenvalue = 0;
    return;
  }
  // The two extreme eigenvalues only (the test needs no others): the tridiagonal form, then bisection; an implicit
  // QL sweep for the whole spectrum cost several times the tridiagonalisation. The eigenvector is needed only by an
  // agent that fails.
  if (na > 0) Rz_.noalias() = Z.transpose() * Hr_ * Z;
  const Mat& R = na > 0 ? Rz_ : Hr_;
  tri_.compute(R);
  diag_ = tri_.diagonal();
  subdiag_ = tri_.subDiagonal();
  double lo, hi;
  tridiagonal_extreme_eigenvalues(diag_, subdiag_, lo, hi);
  out.min_eigenvalue = lo;  // NaN for a non-finite Hessian: the agent fails, with no direction
  out.max_abs_eigenvalue = std::isnan(lo) ? 0.0 : std::max(std::abs(lo), std::abs(hi));
  if (std::isnan(lo) || agent_passes(a, tol)) return;
  es_.compute(R);
  if (es_.info() != Eigen::Success) return;
  const Vec d = na > 0 ? Vec(Z * es_.eigenvectors().col(0)) : Vec(es_.eigenvectors().col(0));
  out.direction = Eigen::Map<const Mat>(d.data(), nu_, T_);
}

bool SecondOrderCheck::agent_passes(int a, double tol) const {
  const SecondOrderAgent& s = out_[a];
  return s.min_eigenvalue >= -tol * std::max(1.0, s.max_abs_eigenvalue);
}

bool SecondOrderCheck::passes(double tol) const {
  for (int a = 0; a < static_cast<int>(out_.size()); ++a)
    if (!agent_passes(a, tol)) return false;
  return true;
}

}  // namespace rd3g

// The solver's hook: each constraint's multiplier per agent at y_ (equality multiplier, barrier dual, or 0 if
// released), then the test.
namespace rd3g {

void Solver::constraint_weights(Vec& w_i, Vec& w_j) const {
  const int C = static_cast<int>(cons_.size());
  w_i = Vec::Zero(C);
  w_j = Vec::Zero(C);
  for (int c = 0; c < C; ++c) {
    if (state_[c] == ConstraintState::Active) {
      w_i[c] = y_.mu[c];
      w_j[c] = mu2_col_[c] >= 0 ? y_.mu2[c] : y_.mu[c];
    } else if (state_[c] == ConstraintState::Barrier && h_[c] < 0) {
      w_i[c] = w_j[c] = barrier_ == BarrierMode::PrimalDual ? y_.z[c] : -rho_ / h_[c];
    }
  }
}

bool Solver::check_second_order(Info& info) {
  Vec w_i, w_j;
  constraint_weights(w_i, w_j);
  const auto& agents = second_order_->check(
      prob_, cons_, [&](int c, double& h, Eigen::Vector2d& g, Eigen::Matrix2d& H) { eval_constraint(y_, c, h, &g, &H); },
      y_.x, y_.u, y_.lam, w_i, w_j, settings_.second_order.gap, settings_.second_order.tol);
  info.second_order.resize(N_);
  for (int a = 0; a < N_; ++a) info.second_order[a] = agents[a].min_eigenvalue;
  return second_order_->passes(settings_.second_order.tol);
}

}  // namespace rd3g

// Steering away from a saddle: a restart along negative curvature (Settings::second_order.escapes) and the per-agent
// inertia correction (Settings::second_order.inertia).
namespace rd3g {

double Solver::agent_lagrangian(int a, const Iterate& y, const Vec& w_i, const Vec& w_j, double& max_h) const {
  // J^a as in QuadraticCost / LeadCost (problem.hpp); the dynamics hold by rollout, so their multiplier term is 0.
  const QuadraticCost& c = prob_.costs[a];
  const Mat& x = y.x[a];
  double J = 0;
  for (int k = 0; k < T_; ++k) J += c.R.dot(y.u[a].col(k).cwiseAbs2());
  for (int k = 1; k < T_; ++k)
    J += c.Q_ref.dot((x.col(k) - c.reference(k)).cwiseAbs2()) + c.Q.dot(x.col(k).cwiseAbs2());
  J += c.Qf_ref.dot((x.col(T_) - c.reference(T_)).cwiseAbs2()) + c.Qf.dot(x.col(T_).cwiseAbs2());
  const LeadCost& lead = prob_.lead[a];
  if (lead.weight != 0.0)
    for (int j = 0; j < N_; ++j)
      if (j != a)
        for (int k = 1; k <= T_; ++k) J += lead.weight * (y.x[j](lead.index, k) - x(lead.index, k));
  max_h = -kInf;
  for (int ci = 0; ci < static_cast<int>(cons_.size()); ++ci) {
    const Constraint& cn = cons_[ci];
    if (!cn.involves(a)) continue;
    const double h = constraint_value(y, ci);
    J += (cn.i == a ? w_i[ci] : w_j[ci]) * h;
    max_h = std::max(max_h, h);
  }
  return J;
}

bool Solver::leave_saddle(int escapes) {
  const auto& agents = second_order_->agents();
  const double tol = settings_.second_order.tol;
  if (settings_.second_order.inertia > 0)
    for (int a = 0; a < N_; ++a)
      if (!second_order_->agent_passes(a, tol) && std::isfinite(agents[a].min_eigenvalue))
        inertia_delta_[a] = std::max(inertia_delta_[a], settings_.second_order.inertia * std::abs(agents[a].min_eigenvalue));
  if (escapes >= settings_.second_order.escapes) return false;

  Vec w_i, w_j;
  constraint_weights(w_i, w_j);
  const Vec h0 = h_;  // the saddle's constraint values (write_result evaluated them at y_)
  trial_ = y_;
  bool moved = false;
  for (int a = 0; a < N_; ++a) moved = escape_agent(a, h0, w_i, w_j) || moved;
  if (!moved) return false;
  std::swap(y_, trial_);
  start_escape_partition();
  return true;
}

bool Solver::escape_agent(int a, const Vec& h0, const Vec& w_i, const Vec& w_j) {
  const SecondOrderAgent& ag = second_order_->agents()[a];
  if (second_order_->agent_passes(a, settings_.second_order.tol) || !(ag.min_eigenvalue < 0) ||
      ag.direction.cols() != T_)
    return false;
  const double margin = settings_.barrier.margin;
  // Agent a's constraints stay feasible: those inside by more than the barrier margin stay so (the restart hands
  // them to the barrier), the nearly active ones (the test's null space, moved along to first order only) may
  // not become violated.
  auto feasible = [&] {
    for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
      if (!cons_[c].involves(a)) continue;
      const double h = constraint_value(trial_, c);
      if (h0[c] < -margin ? !(h < -margin) : !(h <= std::max(0.0, h0[c]))) return false;
    }
    return true;
  };
  double max_h;
  const double L0 = agent_lagrangian(a, trial_, w_i, w_j, max_h);
  const Mat u0 = trial_.u[a];
  double step = kEscapeStep, best_sign = 0;
  for (int q = 0; q < settings_.line_search.max_steps && best_sign == 0; ++q, step *= settings_.line_search.beta) {
    // Along +-d the quadratic model predicts L0 + 0.5 step^2 lambda_min; ask for a tenth of that decrease.
    double best_L = L0 + 0.05 * step * step * ag.min_eigenvalue;
    for (const double sign : {1.0, -1.0}) {
      trial_.u[a] = u0 + sign * step * ag.direction;
      roll_out(trial_, a);
      const double L = agent_lagrangian(a, trial_, w_i, w_j, max_h);
      if (L <= best_L && feasible()) { best_L = L; best_sign = sign; }
    }
    if (best_sign != 0) {
      trial_.u[a] = u0 + best_sign * step * ag.direction;
      if (settings_.verbose)
        std::printf("saddle: agent %d moves %.3g along %s its negative curvature (eigenvalue %.3e), L %.6e -> %.6e\n",
                    a, step, best_sign > 0 ? "+" : "-", ag.min_eigenvalue, L0, best_L);
    }
  }
  if (best_sign == 0) trial_.u[a] = u0;  // no acceptable move: this agent stays
  roll_out(trial_, a);
  return best_sign != 0;
}

void Solver::start_escape_partition() {
  const double margin = settings_.barrier.margin;
  // The attempt keeps this partition. Constraints still within the margin stay held: the active ones with their
  // multipliers, the barrier's nearly active contacts as equalities (their duals the multipliers). Released to the
  // first partition's Free state, they would be invisible to Newton, whose first step crosses them, and no step
  // length would keep the violation at 0.
  eval_all_constraints(y_, h_);
  hold_near_contacts(h_, margin);
  // Constraints inside the margin go to the barrier on the central path of a moderate rho (at rho's floor the
  // barrier would hold the moved agent near the saddle's contacts).
  rho_ = kEscapeRho;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    if (h_[c] >= -margin) continue;
    state_[c] = ConstraintState::Barrier;
    y_.mu[c] = y_.mu2[c] = 0;
    y_.z[c] = rho_ / -h_[c];
  }
  keep_partition_ = true;
}

void Solver::add_inertia_correction(double rnorm) {
  if (!inertia_on_ || settings_.second_order.inertia <= 0 || inertia_delta_.empty() || merits_.empty()) return;
  // Vanishes with the residual: superlinear convergence near the root is kept.
  const double scale = std::min(1.0, rnorm / std::max(merits_.front(), 1e-300));
  for (int a = 0; a < N_; ++a) {
    const double d = inertia_delta_[a] * scale;
    if (d <= 0) continue;
    for (int k = 0; k < T_; ++k)
      for (int q = 0; q < nu_; ++q) trip_.emplace_back(col_u(a, k) + q, col_u(a, k) + q, d);
  }
}

}  // namespace rd3g
