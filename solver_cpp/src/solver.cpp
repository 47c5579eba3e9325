#include "rd3g/solver.hpp"

#include "rd3g/second_order.hpp"

#include <Eigen/IterativeLinearSolvers>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <stdexcept>
#include <string>

#include "rd3g/clock.hpp"
#include "rd3g/validate.hpp"

namespace rd3g {

namespace {
// LSCG iterations between deadline checks when a time limit is set.
constexpr int kLscgChunk = 50;
// Sparse factorisation speed assumed before this solver has measured its own (flop/s): low, so that a
// prediction errs towards not starting a factorisation that might overrun the time limit.
constexpr double kDefaultFlopRate = 2e8;

// Sparse LDLT that reports the flops of its numeric factorisation once its pattern is analysed, so the
// cost of a factorisation is known before it starts (sum over columns of c^2 + c, c = entries below
// the diagonal of L; the counts are Eigen's own, kept in a protected member after analyzePattern).
class CountedLDLT : public Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Lower> {
 public:
  double factor_flops() const {
    double f = 0;
    for (Eigen::Index j = 0; j < this->m_nonZerosPerCol.size(); ++j) {
      const double c = this->m_nonZerosPerCol[j];
      f += c * c + c;
    }
    return f;
  }
};
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
  const auto t0 = Clock::now();
  validate_settings(s);
  validate_problem(p);
  prob_ = with_defaults(p);
  settings_ = s;
  N_ = prob_.num_agents();
  T_ = prob_.horizon;
  nx_ = prob_.dynamics[0]->nx();
  nu_ = prob_.dynamics[0]->nu();
  per_agent_multipliers_ = s.linear_solver == LinearSolver::LSCG || s.linear_solver == LinearSolver::SparseQR;
  layout_ = StageLayout{N_, nx_, nu_};
  n_primal_ = N_ * T_ * stage_size();

  // Buffers that depend only on the sizes.
  stage_.resize(nx_, nu_);
  fx_ = Mat::Zero(nx_, 1);
  Atmp_ = Mat::Zero(nx_, nx_);
  Btmp_ = Mat::Zero(nx_, nu_);
  dom_lo_ = Vec::Zero(nu_);
  dom_hi_ = Vec::Zero(nu_);
  u_init_.assign(N_, Mat::Zero(nu_, T_));
  lam_init_.assign(N_, Mat::Zero(nx_, T_));
  riccati_.setup(N_, T_, nx_, nu_);
  if (!second_order_) second_order_ = std::make_shared<SecondOrderCheck>();
  second_order_->setup(N_, T_, nx_, nu_);
  list_and_allocate();
  br_stale_ = true;
  setups_ = 1;
  setup_time_ = seconds_since(t0);
  update_time_ = 0;
}

void Solver::list_and_allocate() {
  cons_ = list_constraints(prob_);
  const int C = static_cast<int>(cons_.size());
  for (Iterate* it : {&y_, &trial_, &best_, &best_seen_}) {
    it->x.assign(N_, Mat::Zero(nx_, T_ + 1));
    it->u.assign(N_, Mat::Zero(nu_, T_));
    it->lam.assign(N_, Mat::Zero(nx_, T_));
    it->mu = Vec::Zero(C);
    it->mu2 = Vec::Zero(C);
    it->z = Vec::Zero(C);
  }
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
  neg_rhs_ = Vec::Zero(max_vars);
  lin_res_ = Vec::Zero(max_vars);
  // Per stage and agent: dense (nx+nu)^2 Hessian, A, B, identities; per constraint up to ~20 entries.
  trip_.clear();
  trip_.reserve(static_cast<size_t>(N_) * T_ * (3 * (nx_ + nu_) * (nx_ + nu_) + 4 * nx_) + 24 * C);
  merits_.reserve(static_cast<size_t>(settings_.max_iter) + 2);
  violations_.reserve(static_cast<size_t>(settings_.max_iter) + 2);
  lu_analyzed_ = false;
  lm_analyzed_ = false;
  ++structure_version_;
}

// ---- updates --------------------------------------------------------------------------------------
namespace {
std::string agent_path(int i) { return "agents[" + std::to_string(i) + "]"; }
/// True if the bounds admit the same finite components (the constraint list depends only on that).
bool same_finite_pattern(const Vec& a, const Vec& b) {
  for (int q = 0; q < a.size(); ++q)
    if (std::isfinite(a[q]) != std::isfinite(b[q])) return false;
  return true;
}
}  // namespace

void Solver::finish_update(Clock::time_point t0) {
  br_stale_ = true;  // the best response's sub-solvers copy the problem and the settings
  update_time_ += seconds_since(t0);
}

void Solver::update_settings(const Settings& s) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update_settings()");
  const auto t0 = Clock::now();
  validate_settings(s);
  const bool per_agent = s.linear_solver == LinearSolver::LSCG || s.linear_solver == LinearSolver::SparseQR;
  if (per_agent != per_agent_multipliers_) lu_analyzed_ = lm_analyzed_ = false;  // another multiplier layout
  per_agent_multipliers_ = per_agent;
  settings_ = s;
  merits_.reserve(static_cast<size_t>(s.max_iter) + 2);
  violations_.reserve(static_cast<size_t>(s.max_iter) + 2);
  finish_update(t0);
}

void Solver::update_initial_state(int agent, const Vec& x0) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update_initial_state()");
  const auto t0 = Clock::now();
  require(agent >= 0 && agent < N_, "agent index " + std::to_string(agent) + " is not in [0, " + std::to_string(N_) + ")");
  validate_initial_state(x0, nx_, agent_path(agent) + ".x0");
  prob_.x0[agent] = x0;
  finish_update(t0);
}

void Solver::update_cost(int agent, const QuadraticCost& cost) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update_cost()");
  const auto t0 = Clock::now();
  require(agent >= 0 && agent < N_, "agent index " + std::to_string(agent) + " is not in [0, " + std::to_string(N_) + ")");
  validate_cost(cost, nx_, nu_, agent_path(agent) + ".cost");
  prob_.costs[agent] = cost;
  finish_update(t0);
}

void Solver::update_lead(int agent, const LeadCost& lead) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update_lead()");
  const auto t0 = Clock::now();
  require(agent >= 0 && agent < N_, "agent index " + std::to_string(agent) + " is not in [0, " + std::to_string(N_) + ")");
  validate_lead(lead, nx_, agent_path(agent));
  prob_.lead[agent] = lead;
  finish_update(t0);
}

void Solver::update_bounds(int agent, const Vec& u_min, const Vec& u_max, const Vec& x_min, const Vec& x_max) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update_bounds()");
  const auto t0 = Clock::now();
  require(agent >= 0 && agent < N_, "agent index " + std::to_string(agent) + " is not in [0, " + std::to_string(N_) + ")");
  const std::string a = agent_path(agent);
  validate_bounds(u_min, u_max, nu_, a, "u");
  validate_bounds(x_min, x_max, nx_, a, "x");
  auto filled = [](const Vec& v, int n, double value) { return v.size() ? v : Vec(Vec::Constant(n, value)); };
  const Vec umin = filled(u_min, nu_, -kInf), umax = filled(u_max, nu_, kInf);
  const Vec xmin = filled(x_min, nx_, -kInf), xmax = filled(x_max, nx_, kInf);
  const bool same = same_finite_pattern(umin, prob_.u_min[agent]) && same_finite_pattern(umax, prob_.u_max[agent]) &&
                    same_finite_pattern(xmin, prob_.x_min[agent]) && same_finite_pattern(xmax, prob_.x_max[agent]);
  prob_.u_min[agent] = umin;
  prob_.u_max[agent] = umax;
  prob_.x_min[agent] = xmin;
  prob_.x_max[agent] = xmax;
  if (!same) {
    list_and_allocate();
    ++setups_;
    setup_time_ = seconds_since(t0);
  }
  finish_update(t0);
}

void Solver::update_collision_distance(double min_distance, const Vec& steps) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update_collision_distance()");
  const auto t0 = Clock::now();
  if (prob_.collision.enabled && N_ > 1) validate_min_distance(min_distance, steps, T_, "collision.min_distance");
  prob_.collision.min_distance = min_distance;
  prob_.collision.min_distance_steps = steps;
  finish_update(t0);
}

void Solver::update_obstacle(int index, const Eigen::MatrixXd& positions, double min_distance, const Vec& steps) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update_obstacle()");
  const auto t0 = Clock::now();
  const int n = static_cast<int>(prob_.obstacles.size());
  require(index >= 0 && index < n, "obstacle index " + std::to_string(index) + " is not in [0, " + std::to_string(n) + ")");
  Obstacle o;
  o.positions = positions;
  o.min_distance = min_distance;
  o.min_distance_steps = steps;
  validate_obstacle(o, T_, "obstacles[" + std::to_string(index) + "]");
  prob_.obstacles[index] = std::move(o);
  finish_update(t0);
}

void Solver::update(const Problem& p) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update()");
  const auto t0 = Clock::now();
  const int agents = static_cast<int>(p.dynamics.empty() ? p.x0.size() : p.dynamics.size());
  require(agents == N_, "update: agents must have the set-up's " + std::to_string(N_) + " agents, got " + std::to_string(agents));
  Problem q = p;
  if (q.dynamics.empty()) q.dynamics = prob_.dynamics;
  require(q.horizon == T_, "update: horizon must be the set-up's " + std::to_string(T_) + ", got " + std::to_string(q.horizon));
  validate_problem(q);
  require(q.dynamics[0]->nx() == nx_ && q.dynamics[0]->nu() == nu_, "update: agents[0].dynamics must keep nx and nu");
  require(q.obstacles.size() == prob_.obstacles.size(),
          "update: obstacles must keep the set-up's number (" + std::to_string(prob_.obstacles.size()) + ")");
  require(q.collision.enabled == prob_.collision.enabled && q.collision.form == prob_.collision.form &&
              q.collision.pos_x == prob_.collision.pos_x && q.collision.pos_y == prob_.collision.pos_y,
          "update: collision.enabled, form, pos_x and pos_y must stay as set up");
  q = with_defaults(q);
  bool same = true;
  for (int i = 0; i < N_; ++i)
    same = same && same_finite_pattern(q.u_min[i], prob_.u_min[i]) && same_finite_pattern(q.u_max[i], prob_.u_max[i]) &&
           same_finite_pattern(q.x_min[i], prob_.x_min[i]) && same_finite_pattern(q.x_max[i], prob_.x_max[i]);
  prob_ = std::move(q);
  if (!same) {
    list_and_allocate();
    ++setups_;
    setup_time_ = seconds_since(t0);
  }
  finish_update(t0);
}

// -------------------------------------------------------------------------------------------------
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
      distance_constraint(prob_.collision.form, d, prob_.collision.at(cn.i, cn.j, cn.k), h, g, H);
      return;
    }
    case K::Obstacle: {
      const Obstacle& o = prob_.obstacles[cn.j];
      const Eigen::Vector2d d(y.x[cn.i](px, cn.k) - o.positions(cn.k, 0), y.x[cn.i](py, cn.k) - o.positions(cn.k, 1));
      distance_constraint(prob_.collision.form, d, o.at(cn.k), h, g, H);
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
  r.head(n_vars_).setZero();
  if (jac) {
    trip_.clear();
    rhs_.head(n_vars_).setZero();
  }
  for (int i = 0; i < N_; ++i)
    for (int k = 0; k < T_; ++k)
      add_stage_terms(layout_, i, k, T_, *prob_.dynamics[i], prob_.costs[i], prob_.lead[i], y.x[i], y.u[i],
                      y.lam[i].col(k), r, jac ? &trip_ : nullptr, stage_);

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
    eval_constraint(y, c, hv, &g, jac ? &H : nullptr);
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

// -------------------------------------------------------------------------------------------------
void Solver::build_J() {
  if (J_built_) return;
  J_.resize(n_vars_, n_vars_);
  J_.setFromTriplets(trip_.begin(), trip_.end());
  J_.makeCompressed();
  J_built_ = true;
}

bool Solver::solve_linear(Vec& dy, Info& info) {
  J_built_ = false;
  lm_ready_ = false;
  const int n = n_vars_;
  if (settings_.linear_solver == LinearSolver::Riccati) {
    if (riccati_.solve(trip_, n, rhs_, dy)) {
      // Check the step against the assembled system (O(nnz)); a poorly conditioned recursion falls back to LU.
      lin_res_.head(n) = rhs_.head(n);
      for (const auto& t : trip_) lin_res_[t.row()] += t.value() * dy[t.col()];
      if (lin_res_.head(n).norm() <= 1e-9 * std::max(1.0, rhs_.head(n).norm())) {
        info.riccati_solves++;
        return true;
      }
      if (settings_.verbose) std::printf("   Riccati residual %.2e: falling back to sparse LU\n", lin_res_.head(n).norm());
    }
  }
  build_J();
  neg_rhs_.head(n) = -rhs_.head(n);
  const auto rhs = neg_rhs_.head(n);
  auto qr_solve = [&]() -> bool {
    // SparseQR cannot be interrupted: with a time limit it is started only when this solver's last QR
    // fits into the time left; otherwise the bounded least-squares fallback takes its place.
    if (past_deadline()) {
      timed_out_ = true;
      return false;
    }
    if (settings_.time_limit > 0 && qr_would_overrun()) {
      if (settings_.verbose) std::printf("   SparseQR would overrun the time limit: regularised least squares\n");
      if (bounded_least_squares(dy)) return true;
      timed_out_ = true;
      return false;
    }
    const auto t_qr = Clock::now();
    Eigen::SparseQR<SpMat, Eigen::COLAMDOrdering<int>> qr;
    qr.compute(J_);
    last_qr_seconds_ = seconds_since(t_qr);
    if (settings_.verbose) std::printf("   SparseQR took %.3g s\n", last_qr_seconds_);
    if (qr.info() != Eigen::Success) return false;
    dy.head(n) = qr.solve(rhs);
    info.qr_fallbacks++;
    return qr.info() == Eigen::Success && dy.head(n).allFinite();
  };
  switch (settings_.linear_solver) {
    case LinearSolver::Riccati:
    case LinearSolver::SparseLU: {
      // The sparsity pattern depends only on which constraints are equalities: analyse it only when that changes.
      if (!lu_analyzed_ || pattern_state_ != state_) {
        lu_.analyzePattern(J_);
        pattern_state_ = state_;
        lu_analyzed_ = true;
        info.symbolic_factorizations++;
      }
      lu_.factorize(J_);
      if (lu_.info() == Eigen::Success) {
        dy.head(n) = lu_.solve(rhs);
        // Iterative refinement with the same factors: the Newton matrix can be badly scaled (barrier
        // curvature z/(-h) next to O(1) entries), and an inaccurate step is not a descent direction.
        for (int ref = 0; ref < settings_.refinement_steps; ++ref) {
          lin_res_.head(n) = rhs - J_ * dy.head(n);
          const double res_norm = lin_res_.head(n).norm();
          if (settings_.verbose) std::printf("   linear residual %.2e (rhs %.2e)\n", res_norm, rhs.norm());
          if (res_norm <= 1e-12 * rhs.norm()) break;
          dy.head(n) += lu_.solve(lin_res_.head(n));
        }
        if (lu_.info() == Eigen::Success && dy.head(n).allFinite()) return true;
      }
      lu_analyzed_ = false;  // a failed factorisation may leave the symbolic data unusable
      return qr_solve();
    }
    case LinearSolver::LSCG: {
      Eigen::LeastSquaresConjugateGradient<SpMat> cg;
      cg.setTolerance(settings_.lscg_tol);
      cg.compute(J_);
      if (settings_.time_limit <= 0) {
        cg.setMaxIterations(settings_.lscg_max_iter);
        dy.head(n) = cg.solve(rhs);
      } else {
        // In chunks, so that the deadline is checked inside a long solve (each chunk restarts from the last
        // iterate, which changes the iterates slightly compared with one run).
        dy.head(n).setZero();
        for (int done = 0; done < settings_.lscg_max_iter; done += kLscgChunk) {
          cg.setMaxIterations(std::min(kLscgChunk, settings_.lscg_max_iter - done));
          dy.head(n) = cg.solveWithGuess(rhs, dy.head(n));
          if (cg.info() == Eigen::Success) break;
          if (past_deadline()) {
            timed_out_ = true;
            return false;
          }
        }
      }
      if (cg.info() == Eigen::Success && dy.head(n).allFinite()) return true;
      return qr_solve();
    }
    case LinearSolver::SparseQR: {
      const int fallbacks = info.qr_fallbacks;
      const bool ok = qr_solve();
      info.qr_fallbacks = fallbacks;  // not a fallback when QR is the chosen method
      return ok;
    }
  }
  return false;
}

bool Solver::second_order_wanted(const Info& info) const {
  if (settings_.second_order_gap < 0 || info.status == Status::NumericalError) return false;
  // A converged point always gets the test (it decides converged vs saddle). Any other iterate only
  // reports its eigenvalues, which is not worth passing the deadline for (a dense eigenvalue problem per agent).
  return info.status == Status::Converged || !(info.status == Status::TimeLimit || past_deadline());
}

bool Solver::past_deadline() const {
  return settings_.time_limit > 0 && seconds_since(t_start_) > settings_.time_limit;
}

bool Solver::next_iteration_overruns() {
  // An iteration (assembly, linear solve, line search) cannot be cut short: with a time limit the next one
  // is not started when the last one, measured between these checks, would not fit into the time left.
  if (settings_.time_limit <= 0) return false;
  const auto now = Clock::now();
  if (have_iteration_start_) last_iteration_seconds_ = std::chrono::duration<double>(now - iteration_start_).count();
  iteration_start_ = now;
  have_iteration_start_ = true;
  return past_deadline() || last_iteration_seconds_ > time_left();
}

double Solver::time_left() const { return settings_.time_limit - seconds_since(t_start_); }

double Solver::flop_rate() const { return ldlt_flop_rate_ > 0 ? ldlt_flop_rate_ : kDefaultFlopRate; }

double Solver::normal_matrix_flops() const {
  // Forming J'J costs the sum over rows of (entries in the row)^2.
  row_count_.setZero(n_vars_);
  for (Eigen::Index k = 0; k < J_.outerSize(); ++k)
    for (SpMat::InnerIterator it(J_, k); it; ++it) row_count_[it.row()] += 1;
  return row_count_.squaredNorm();
}

bool Solver::qr_would_overrun() const {
  // SparseQR's duration cannot be predicted from the pattern: its Householder vectors fill in from about 80x
  // (10-car merge) to 1800x (a 4-agent fuzz problem) the flops of an LDLT of J'J. Under a time limit it is
  // started only when this solver's own last QR fits; otherwise the bounded least-squares step replaces it.
  return last_qr_seconds_ <= 0 || last_qr_seconds_ > time_left();
}

bool Solver::bounded_least_squares(Vec& dy) {
  // Tikhonov-regularised normal equations (J'J + delta I) dy = J'(-rhs) by sparse LDLT: the least-squares
  // step SparseQR would give (up to delta), at a cost known before the numeric factorisation starts, which
  // is skipped when it would not fit into the time left. Two refinement steps remove most of delta's bias.
  const int n = n_vars_;
  if (normal_matrix_flops() / flop_rate() > time_left()) return false;
  SpMat JtJ = J_.transpose() * J_;
  const double dmax = JtJ.diagonal().cwiseAbs().maxCoeff();
  SpMat eye(n, n);
  eye.setIdentity();
  const double delta = 1e-10 * (dmax > 0 ? dmax : 1.0);
  SpMat M = JtJ + delta * eye;
  CountedLDLT ldlt;
  ldlt.analyzePattern(M);
  const double flops = ldlt.factor_flops();
  if (flops / flop_rate() > time_left()) return false;
  const auto t0 = Clock::now();
  ldlt.factorize(M);
  const double sec = seconds_since(t0);
  if (settings_.verbose)
    std::printf("   regularised LDLT: %.3g flop predicted %.3g s, took %.3g s\n", flops, flops / flop_rate(), sec);
  if (sec > 1e-3) ldlt_flop_rate_ = flops / sec;  // too short a factorisation measures the overhead, not the rate
  if (ldlt.info() != Eigen::Success) return false;
  const Vec g = J_.transpose() * neg_rhs_.head(n);
  Vec x = ldlt.solve(g);
  for (int r = 0; r < 2 && x.allFinite(); ++r) x += ldlt.solve(g - JtJ * x);
  if (!x.allFinite()) return false;
  dy.head(n) = x;
  return true;
}

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
// largest of the last violation_memory iterates' (1: does not grow).
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
        t = std::min(t, -settings_.fraction_to_boundary * y_.z[c] / dz_[c]);
  } else {
    dz_.setZero();
  }
  if (settings_.domain_fraction > 0) {
    t = domain_step(t);
    if (t <= 0) return 0.0;  // a held control is at its box and the step points out of it
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

// The models' control domains: a full Newton step can carry a steering angle across |delta| = pi/2, where the
// bicycle's slip angle jumps by pi; the residual there is a different (wrong-way) car, and the iterates do not come
// back (merge-long, docs/solver.md "Staying in the model's domain"). Each held control stays in its domain's box
// shrunk about the centre to domain_fraction of its half-width (a fixed margin: a fraction of the distance left
// would let a control creep to the singular point itself).
bool Solver::domain_box(int q, double& lo, double& hi) const {
  if (!std::isfinite(dom_lo_[q]) || !std::isfinite(dom_hi_[q])) return false;  // one-sided: not held
  const double c = 0.5 * (dom_lo_[q] + dom_hi_[q]), w = 0.5 * settings_.domain_fraction * (dom_hi_[q] - dom_lo_[q]);
  lo = c - w;
  hi = c + w;
  return true;
}

double Solver::domain_step(double t) {
  for (int i = 0; i < N_; ++i) {
    prob_.dynamics[i]->control_domain(dom_lo_, dom_hi_);
    for (int q = 0; q < nu_; ++q) {
      double lo, hi;
      if (!domain_box(q, lo, hi)) continue;
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

// Levenberg-Marquardt direction on ||r||^2: (J'J + nu I) dy = -J' r, always a descent direction.
// The tries of one iteration (several nu) reuse J'J, J'r and the symbolic analysis: they were most of the
// line-search time on dense games (up to 4 full LDLTs per iteration).
bool Solver::solve_levenberg_marquardt(double nu, Vec& dy) {
  if (!lm_ready_) {
    build_J();
    lm_JtJ_ = J_.transpose() * J_;
    SpMat eye(n_vars_, n_vars_);
    eye.setIdentity();
    lm_JtJ_ = lm_JtJ_ + 0.0 * eye;  // every diagonal entry stored: the shift nu lands on stored entries
    lm_JtJ_.makeCompressed();
    if (!lm_analyzed_ || !lm_ldlt_.same_pattern(lm_JtJ_)) {
      lm_analyzed_ = false;
      if (!lm_ldlt_.analyze(lm_JtJ_)) return false;
      lm_analyzed_ = true;
    }
    lm_ldlt_.load(lm_JtJ_);
    lm_Jtr_ = J_.transpose() * rhs_.head(n_vars_);
    lm_ready_ = true;
  }
  if (!lm_ldlt_.factorize_shifted(nu)) return false;
  dy.head(n_vars_) = lm_ldlt_.solve(-lm_Jtr_);
  if (settings_.verbose) std::printf("   Levenberg-Marquardt step, nu %.2e\n", nu);
  return lm_ldlt_.info() == Eigen::Success && dy.head(n_vars_).allFinite();
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
  evaluate(y_, h_, true, r_, rc_);
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
  t_start_ = Clock::now();
  Result res;
  Info& info = res.info;
  info.timings.setup = setup_time_;
  info.timings.update = update_time_;
  info.setups = setups_;
  update_time_ = 0;
  setups_ = 0;
  load_initial_guess(warm);
  rng_.seed(12345);
  noise_.reset();
  timed_out_ = false;
  have_iteration_start_ = false;
  last_iteration_seconds_ = 0;
  best_merit_ = kInf;
  int total_iter = 0;
  Result saddle;  // the first converged attempt the second-order test rejected (restart_on_saddle)
  bool have_saddle = false;
  int escapes = 0;           // attempts started from a saddle (leave_saddle); they do not use up the schedule
  bool from_saddle = false;  // the next attempt starts where leave_saddle left y_
  int br_attempts = 0;       // attempts from the best-response guess (inserted, as the escapes)
  inertia_delta_.assign(N_, 0.0);
  for (int attempt = 0; attempt <= settings_.restarts; ++attempt) {
    const bool br_now = !from_saddle && br_attempts == 0 && settings_.best_response_rounds > 0 &&
                        attempt == settings_.best_response_attempt;
    bool repeat = br_now;  // an inserted attempt: the schedule resumes at this attempt afterwards
    info.attempts = attempt + 1 + escapes + br_attempts;
    info.saddle_escapes = escapes;
    if (br_now) {
      ++br_attempts;
      info.best_response_attempts = br_attempts;
      // A sub-solve iteration (one agent's Newton system, N times smaller) counts 1/N of a game iteration.
      const int used = start_best_response_attempt(N_ * (settings_.max_iter - total_iter));
      total_iter += (used + N_ - 1) / N_;
      info.best_response_iterations += used;
    } else if (!from_saddle) {
      start_attempt(attempt, warm);
    }
    inertia_on_ = from_saddle || settings_.saddle_inertia_restarts;
    from_saddle = false;
    if (run_attempt(info, total_iter) == AttemptEnd::Finished) {
      // Steer away from a saddle: keep it, and let the remaining restarts look for a local equilibrium.
      if (!(settings_.restart_on_saddle && info.status == Status::Converged && settings_.second_order_gap >= 0 &&
            (attempt < settings_.restarts || br_now || escapes < settings_.saddle_escapes) && total_iter < settings_.max_iter &&
            !past_deadline()))
        break;
      Result cand = res;
      write_result(cand, cand.info);
      if (cand.info.status != Status::Saddle) return cand;
      if (settings_.verbose) std::printf("converged to a saddle, restarting\n");
      if (!have_saddle) { saddle = std::move(cand); have_saddle = true; }
      if (leave_saddle(escapes)) {
        ++escapes;
        from_saddle = true;
        repeat = true;  // same place in the restart schedule
      }
    }
    ++total_iter;
    if (repeat) --attempt;
  }
  write_result(res, info);
  if (have_saddle && info.status != Status::Converged) {
    // No later attempt found an equilibrium: the saddle (feasible, first-order stationary) beats a failure.
    saddle.info.iterations = info.iterations;
    saddle.info.attempts = info.attempts;
    saddle.info.saddle_escapes = info.saddle_escapes;
    saddle.info.best_response_attempts = info.best_response_attempts;
    saddle.info.best_response_iterations = info.best_response_iterations;
    saddle.info.timings.total = seconds_since(t_start_);
    return saddle;
  }
  return res;
}

void Solver::load_initial_guess(const WarmStart* warm) {
  // Given (or zero) controls and dynamics multipliers; the states are their rollout (start_attempt).
  const bool warm_u = warm && static_cast<int>(warm->u.size()) == N_;
  const bool warm_lam = warm && static_cast<int>(warm->lambda.size()) == N_;
  for (int i = 0; i < N_; ++i) {
    if (warm_u)
      require(warm->u[i].rows() == T_ && warm->u[i].cols() == nu_ && warm->u[i].allFinite(),
              "warm start u has the wrong shape or non-finite values");
    if (warm_lam)
      require(warm->lambda[i].rows() == T_ && warm->lambda[i].cols() == nx_ && warm->lambda[i].allFinite(),
              "warm start lambda has the wrong shape or non-finite values");
  }
  for (int i = 0; i < N_; ++i) {
    if (warm_u) u_init_[i] = warm->u[i].transpose();
    else u_init_[i].setZero();
    if (warm_lam) lam_init_[i] = warm->lambda[i].transpose();
    else lam_init_[i].setZero();
  }
  have_mu_ = warm && warm->mu.size() == static_cast<int>(cons_.size());
  if (have_mu_) require(warm->mu.allFinite(), "warm start mu has non-finite values");
}

void Solver::start_attempt(int attempt, const WarmStart* warm) {
  for (int i = 0; i < N_; ++i) {
    y_.x[i].col(0) = prob_.x0[i];
    y_.u[i] = u_init_[i];
    if (attempt >= 4)
      // A constant offset per agent and control component (not white noise, which averages out):
      // it changes the order in which agents reach a contested region, i.e. the equilibrium's basin.
      for (int q = 0; q < nu_; ++q) {
        const double offset = settings_.restart_u_std * noise_(rng_);
        y_.u[i].row(q).array() += offset;
      }
    if (attempt == 0) y_.lam[i] = lam_init_[i];
    else y_.lam[i].setZero();
    roll_out(y_, i);
  }
  y_.mu.setZero();
  y_.mu2.setZero();
  y_.z.setZero();
  if (have_mu_ && attempt == 0) { y_.mu = warm->mu; y_.mu2 = warm->mu; }
  // Restart schedule (measured on the merging games, each variant rescues different instances):
  // attempt 1: 10x rho_init; 2: the other barrier form; 3: both; >= 4: the same four with perturbed controls.
  const int variant = attempt % 4;
  // Globalisation rules: the settings' own (by default the paper's) in attempt 0, unless its initial guess overlaps
  // deeply; the restart rules (rho lowered only near the central path or on a stall, non-monotone violation test)
  // in every later attempt. With a deep overlap the paper's rule puts rho at its floor within 3 iterations while
  // the violation is still ~1 m, and the barrier then admits only tiny steps (crossing, docs/solver.md).
  const bool restart_rules = attempt > 0 || deep_overlap();
  use_rules(restart_rules);
  rho_ = settings_.rho_init * ((variant == 1 || variant == 3) ? 10.0 : 1.0);
  barrier_ = settings_.barrier;
  if (variant >= 2)
    barrier_ = settings_.barrier == BarrierMode::PrimalDual ? BarrierMode::Primal : BarrierMode::PrimalDual;
  // The LU's symbolic analysis is kept across attempts and solves: it depends only on the sparsity pattern,
  // i.e. on the partition (pattern_state_) and the constraint list, and is redone when either changes.
}

void Solver::use_rules(bool restart_rules) {
  rules_.rho_progress = restart_rules ? settings_.restart_rho_progress : settings_.rho_progress;
  rules_.violation_memory = restart_rules ? settings_.restart_violation_memory : settings_.violation_memory;
  rules_.rho_on_stall = restart_rules ? settings_.restart_rho_on_stall : settings_.rho_on_stall;
}

void Solver::roll_out(Iterate& y, int i) {
  for (int k = 0; k < T_; ++k) {
    prob_.dynamics[i]->eval(y.x[i].col(k), y.u[i].col(k), fx_.col(0), Atmp_, Btmp_);
    y.x[i].col(k + 1) = fx_.col(0);
  }
}

bool Solver::deep_overlap() const {
  if (settings_.deep_overlap > 1) return false;
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  for (const Constraint& cn : cons_) {
    double dmin;
    Eigen::Vector2d d;
    if (cn.kind == Constraint::Kind::Pair) {
      dmin = prob_.collision.at(cn.i, cn.j, cn.k);
      d << y_.x[cn.i](px, cn.k) - y_.x[cn.j](px, cn.k), y_.x[cn.i](py, cn.k) - y_.x[cn.j](py, cn.k);
    } else if (cn.kind == Constraint::Kind::Obstacle) {
      const Obstacle& o = prob_.obstacles[cn.j];
      dmin = o.at(cn.k);
      d << y_.x[cn.i](px, cn.k) - o.positions(cn.k, 0), y_.x[cn.i](py, cn.k) - o.positions(cn.k, 1);
    } else {
      continue;
    }
    if (d.norm() < (1.0 - settings_.deep_overlap) * dmin) return true;
  }
  return false;
}

bool Solver::assemble(bool first, Info& info) {
  const auto t0 = Clock::now();
  eval_all_constraints(y_, h_);
  classify(h_, first);
  number_multipliers();
  const bool ok = evaluate(y_, h_, true, r_, rc_);
  info.timings.assembly += seconds_since(t0);
  return ok;
}

bool Solver::converged(double rnorm) const {
  const int C = static_cast<int>(cons_.size());
  for (int c = 0; c < C; ++c)
    if (state_[c] == ConstraintState::Active &&
        (y_.mu[c] < -settings_.multiplier_tol || (mu2_col_[c] >= 0 && y_.mu2[c] < -settings_.multiplier_tol)))
      return false;  // an active constraint pushes the wrong way: not an equilibrium
  const double maxviol = C ? std::max(0.0, h_.maxCoeff()) : 0.0;
  double max_defect = 0;
  for (int i = 0; i < N_; ++i)
    for (int k = 0; k < T_; ++k) max_defect = std::max(max_defect, r_.segment(col_lam(i, k), nx_).cwiseAbs().maxCoeff());
  return rnorm < settings_.tol && maxviol <= settings_.violation_tol && max_defect <= settings_.dynamics_tol &&
         (C == 0 || at_rho_floor());
}

double Solver::rho_floor() const { return settings_.tol * settings_.rho_floor_factor; }

bool Solver::at_rho_floor() const { return rho_ <= rho_floor() * (1 + 1e-9); }

Solver::AttemptEnd Solver::run_attempt(Info& info, int& total_iter) {
  merits_.clear();
  violations_.clear();
  bool first = true, stalled = false, polished = false;
  info.status = Status::MaxIterations;
  for (;; ++total_iter) {
    const bool ok = assemble(first, info);
    first = false;
    if (!ok) { info.status = Status::NumericalError; break; }
    const double rnorm = merit(r_, rc_);
    info.residual_history.push_back(rnorm);
    merits_.push_back(rnorm);
    violations_.push_back(violation_sum(h_));
    info.residual_norm = rnorm;
    info.iterations = total_iter;
    if (settings_.time_limit > 0 && rnorm < best_merit_) {
      best_merit_ = rnorm;
      best_seen_ = y_;
    }
    if (settings_.verbose)
      std::printf("it %3d  |r| %.3e  rho %.2e  viol %.2e  active %d\n", total_iter, rnorm, rho_,
                  cons_.empty() ? 0.0 : std::max(0.0, h_.maxCoeff()), n_vars_ - n_primal_);
    if (converged(rnorm)) { info.status = Status::Converged; break; }
    if (total_iter >= settings_.max_iter) { info.status = Status::MaxIterations; break; }
    if (next_iteration_overruns()) { info.status = Status::TimeLimit; break; }
    auto lower_rho = [&] { rho_ = std::max(rho_floor(), std::min(settings_.rho_kappa * rho_, std::pow(rho_, settings_.rho_beta))); };
    double merit_now = rnorm;
    // ||r|| is still above `ratio` times its value `window` iterations ago (window 0: never).
    auto fell_less = [&](int window, double ratio) {
      return window > 0 && static_cast<int>(merits_.size()) > window && rnorm > ratio * merits_[merits_.size() - 1 - window];
    };
    const bool stall = (at_rho_floor() && fell_less(settings_.stall_floor_window, 1.0 - 1e-4)) ||
                       fell_less(settings_.crawl_window, settings_.crawl_ratio) || fell_less(settings_.stall_window, 0.99);
    if (stall && rules_.rho_on_stall && rules_.rho_progress > 0 && !at_rho_floor()) {
      // With rho_progress, a barrier subproblem can stall above rho_progress * rho, and rho would never be
      // lowered: lower it now (merging_problem(7, 12), rho_progress 10: rho stuck at 0.01 with ||r|| 0.13).
      lower_rho();
      if (!evaluate(y_, h_, true, r_, rc_)) { info.status = Status::NumericalError; break; }
      merit_now = merit(r_, rc_);
      merits_.assign(1, merit_now);
      if (settings_.verbose) std::printf("stall: rho lowered to %.2e\n", rho_);
    } else if (stall) {
      // Before giving the attempt up: hold the nearly active barrier constraints as equalities (once per
      // attempt). A stall with rho at its floor is often the barrier's ill-conditioning around a contact
      // that the equilibrium needs; the equality form has no such curvature.
      if (polished || settings_.polish_gap <= 0 || !polish(h_)) { stalled = true; break; }
      polished = true;
      number_multipliers();
      evaluate(y_, h_, true, r_, rc_);
      merits_.assign(1, merit(r_, rc_));
      if (settings_.verbose) std::printf("stall: %d nearly active constraints held as equalities\n", n_vars_ - n_primal_);
    }
    const double t = take_step(merit_now, info);
    if (timed_out_) { info.status = Status::TimeLimit; break; }
    if (t < 0) { info.status = Status::NumericalError; break; }
    if (t == 0.0) { info.status = Status::LineSearchFailed; break; }
    info.step_history.push_back(t);
    if (rules_.rho_progress <= 0 || rnorm <= rules_.rho_progress * rho_) {
      lower_rho();
    }
  }
  if (info.status == Status::Converged || info.status == Status::TimeLimit || info.status == Status::NumericalError ||
      total_iter >= settings_.max_iter)
    return AttemptEnd::Finished;
  if (polished && info.status == Status::LineSearchFailed) stalled = true;  // the polish was the stall's last resort
  if (stalled) info.status = Status::Stalled;  // reported if no attempt is left
  if (settings_.verbose)
    std::printf("attempt ended (%s), restarting\n", stalled ? "stalled" : status_name(info.status).c_str());
  return AttemptEnd::Restart;
}

double Solver::take_step(double rnorm, Info& info) {
  add_inertia_correction(rnorm);
  auto t0 = Clock::now();
  const bool solved = solve_linear(dy_, info);
  info.timings.linear_solve += seconds_since(t0);
  if (!solved) return timed_out_ ? 0.0 : -1.0;

  t0 = Clock::now();
  double t = line_search(rnorm);
  if (t > 0 && t < settings_.lm_below_step) {
    // A tiny accepted Newton step means a nearly singular Newton matrix (huge step, merit only
    // decreasing for t -> 0). Keep it, but let Levenberg-Marquardt steps compete with it: from the
    // largest nu down (it wins most often), until a smaller nu no longer lowers the merit; each try
    // costs a factorisation.
    best_ = trial_;
    double best_m = merit(r_trial_, rc_trial_);
    double last_m = HUGE_VAL;
    bool lm_won = false;
    for (int q = settings_.lm_tries - 1; q >= 0 && !past_deadline(); --q) {
      if (!solve_levenberg_marquardt(settings_.lm_nu_init * std::pow(10.0, q) * rnorm, dy_)) break;
      const double tl = line_search(rnorm);
      const double m = tl > 0 ? merit(r_trial_, rc_trial_) : HUGE_VAL;
      if (m < best_m) { best_m = m; std::swap(best_, trial_); t = tl; lm_won = true; }
      if (m >= last_m) break;
      last_m = m;
    }
    std::swap(trial_, best_);
    if (lm_won) info.lm_steps++;
  }
  for (int q = 0; t == 0.0 && q < settings_.lm_tries; ++q) {
    if (past_deadline()) { timed_out_ = true; break; }
    if (!solve_levenberg_marquardt(settings_.lm_nu_init * std::pow(10.0, q) * rnorm, dy_)) break;
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

void Solver::write_result(Result& res, Info& info) {
  // With a time limit, the iterate with the lowest merit seen (a later restart attempt may be worse).
  if (info.status == Status::TimeLimit && best_merit_ < info.residual_norm) {
    std::swap(y_, best_seen_);
    info.residual_norm = best_merit_;
  }
  const int C = static_cast<int>(cons_.size());
  // Result: trajectories, multipliers (barrier-implied -rho/h for inactive constraints).
  eval_all_constraints(y_, h_);
  if (second_order_wanted(info) && !check_second_order(info) && info.status == Status::Converged)
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
  info.timings.total = seconds_since(t_start_);
}

}  // namespace rd3g
