// RD3G set-up and updates (validation, constraint list, allocation). The solve is split along its seams:
// solver_attempts.cpp (attempt schedule, restarts, stall rules), solver_residual.cpp (KKT residual and Newton
// matrix), solver_linear.cpp (the linear solve and its fallbacks), solver_line_search.cpp (step and line search).
#include "rd3g/solver.hpp"

#include <cmath>
#include <string>

#include "rd3g/clock.hpp"
#include "rd3g/second_order.hpp"
#include "rd3g/validate.hpp"

namespace rd3g {

std::string status_name(Status s) {
  switch (s) {
    case Status::Converged: return "converged";
    case Status::MaxIterations: return "max_iterations";
    case Status::LineSearchFailed: return "line_search_failed";
    case Status::NumericalError: return "numerical_error";
    case Status::TimeLimit: return "time_limit";
    case Status::Stalled: return "stalled";
    case Status::Saddle: return "saddle";
    case Status::DomainEdge: return "domain_edge";
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
  per_agent_multipliers_ = s.linear.solver == LinearSolver::LSCG || s.linear.solver == LinearSolver::SparseQR;
  layout_ = StageLayout{N_, nx_, nu_};
  stage_patterns_ = stage_patterns(prob_.dynamics);
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
  prepare_domain_rescue();
  setups_ = 1;
  setup_time_ = seconds_since(t0);
  update_time_ = 0;
}

void Solver::list_and_allocate() {
  cons_ = list_constraints(prob_);
  const int C = static_cast<int>(cons_.size());
  for (Iterate* it : {&y_, &trial_, &best_seen_}) {
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
  stationarity_ = Vec::Zero(n_primal_);
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
  prepare_domain_rescue();
  update_time_ += seconds_since(t0);
}

void Solver::update_settings(const Settings& s) {
  if (N_ == 0) throw std::logic_error("setup() must be called before update_settings()");
  const auto t0 = Clock::now();
  validate_settings(s);
  const bool per_agent = s.linear.solver == LinearSolver::LSCG || s.linear.solver == LinearSolver::SparseQR;
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
  validate_cost(cost, nx_, nu_, T_, agent_path(agent) + ".cost");
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
  for (int i = 0; i < N_; ++i) {
    if (q.dynamics[i] == prob_.dynamics[i]) continue;  // the same model object (a per-step update keeps it)
    StagePattern pattern(*q.dynamics[i]);
    if (pattern.same_as(stage_patterns_[i])) continue;
    stage_patterns_[i] = std::move(pattern);  // another model's pattern: the Newton matrix's pattern changes
    lu_analyzed_ = lm_analyzed_ = false;
  }
  prob_ = std::move(q);
  if (!same) {
    list_and_allocate();
    ++setups_;
    setup_time_ = seconds_since(t0);
  }
  finish_update(t0);
}

}  // namespace rd3g
