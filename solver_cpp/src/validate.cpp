#include "rd3g/validate.hpp"

#include <cmath>
#include <cstdio>
#include <stdexcept>

namespace rd3g {

namespace {
std::string num(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

/// n finite values (or, with allow_inf, no NaN); names the first bad component.
void check_values(const Vec& v, int n, const std::string& where, bool allow_inf = false) {
  require(v.size() == n, where + " must have " + std::to_string(n) + " values, got " + std::to_string(v.size()));
  for (int q = 0; q < n; ++q)
    require(allow_inf ? !std::isnan(v[q]) : std::isfinite(v[q]),
            where + "[" + std::to_string(q) + "] is not a " + (allow_inf ? "number (NaN)" : "finite number"));
}

void check_non_negative(const Vec& v, const std::string& where) {
  for (int q = 0; q < v.size(); ++q)
    require(v[q] >= 0, where + " must be non-negative (" + where + "[" + std::to_string(q) + "] = " + num(v[q]) + ")");
}

void check_index(int index, int n, const std::string& where) {
  require(index >= 0 && index < n, where + " must be a state index in [0, " + std::to_string(n) + "), got " + std::to_string(index));
}
}  // namespace

void require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument(what);
}

void validate_initial_state(const Vec& x0, int nx, const std::string& where) { check_values(x0, nx, where); }

void validate_cost(const QuadraticCost& c, int nx, int nu, int horizon, const std::string& where) {
  check_values(c.x_ref, nx, where + ".x_ref");
  if (c.x_ref_steps.size()) {
    require(c.x_ref_steps.rows() == nx && c.x_ref_steps.cols() == horizon,
            where + ".x_ref_steps must have shape (" + std::to_string(nx) + ", " + std::to_string(horizon) +
                ") (one reference per step k = 1..T), got (" + std::to_string(c.x_ref_steps.rows()) + ", " +
                std::to_string(c.x_ref_steps.cols()) + ")");
    require(c.x_ref_steps.allFinite(), where + ".x_ref_steps must be finite");
  }
  const std::pair<const Vec*, const char*> weights[] = {{&c.Q_ref, "Q_ref"}, {&c.Q, "Q"}, {&c.Qf_ref, "Qf_ref"}, {&c.Qf, "Qf"}};
  for (const auto& [v, name] : weights) {
    check_values(*v, nx, where + "." + name);
    check_non_negative(*v, where + "." + name);
  }
  check_values(c.R, nu, where + ".R");
  check_non_negative(c.R, where + ".R");
}

void validate_lead(const LeadCost& lead, int nx, const std::string& where) {
  require(std::isfinite(lead.weight), where + ".lead_weight must be finite, got " + num(lead.weight));
  check_index(lead.index, nx, where + ".lead_index");
}

void validate_bounds(const Vec& lower, const Vec& upper, int n, const std::string& where, const char* name) {
  const std::string lo = where + "." + name + "_min", hi = where + "." + name + "_max";
  if (lower.size()) check_values(lower, n, lo, true);
  if (upper.size()) check_values(upper, n, hi, true);
  if (lower.size() && upper.size())
    for (int q = 0; q < n; ++q)
      require(lower[q] < upper[q], lo + " must be below " + hi + " in every component (component " + std::to_string(q) +
                                       ": " + num(lower[q]) + " >= " + num(upper[q]) + ")");
  // A single bound of +inf below or -inf above would admit nothing either.
  if (lower.size())
    for (int q = 0; q < n; ++q) require(lower[q] < kInf, lo + "[" + std::to_string(q) + "] must be below +inf");
  if (upper.size())
    for (int q = 0; q < n; ++q) require(upper[q] > -kInf, hi + "[" + std::to_string(q) + "] must be above -inf");
}

void validate_min_distance(double min_distance, const Vec& steps, int horizon, const std::string& where) {
  if (steps.size() == 0) {
    require(std::isfinite(min_distance) && min_distance > 0,
            where + " must be a positive finite number (m), got " + num(min_distance));
    return;
  }
  require(steps.size() == horizon, where + " must be a positive number or " + std::to_string(horizon) +
                                       " positive numbers (one per step k = 1..T), got " + std::to_string(steps.size()));
  for (int k = 0; k < horizon; ++k)
    require(std::isfinite(steps[k]) && steps[k] > 0,
            where + "[" + std::to_string(k) + "] (step k = " + std::to_string(k + 1) +
                ") must be a positive finite number (m), got " + num(steps[k]));
}

void validate_obstacle(const Obstacle& o, int horizon, const std::string& where) {
  require(o.positions.rows() == horizon + 1 && o.positions.cols() == 2,
          where + ".positions must have shape (" + std::to_string(horizon + 1) + ", 2), got (" +
              std::to_string(o.positions.rows()) + ", " + std::to_string(o.positions.cols()) + ")");
  require(o.positions.allFinite(), where + ".positions must be finite");
  validate_min_distance(o.min_distance, o.min_distance_steps, horizon, where + ".min_distance");
}

void validate_collision(const CollisionSpec& c, int num_agents, int horizon, int nx, bool has_obstacles) {
  const bool pairs = c.enabled && num_agents > 1;
  // Obstacles use the same position indices, so they are checked whenever either constraint exists.
  if (pairs || has_obstacles) {
    try {
      check_index(c.pos_x, nx, "collision.pos_x");
      check_index(c.pos_y, nx, "collision.pos_y");
      // One state for both coordinates would measure sqrt(2) |x_i - x_j| along a diagonal, not a distance.
      require(c.pos_x != c.pos_y, "collision.pos_x and collision.pos_y must be different states, got " +
                                      std::to_string(c.pos_x) + " for both");
    } catch (const std::invalid_argument& e) {
      if (pairs) throw;
      throw std::invalid_argument(std::string(e.what()) +
                                  " (obstacles use the collision block's position indices, default 0 and 1)");
    }
  }
  require(c.form == CollisionForm::Distance || c.form == CollisionForm::Squared, "collision.form is not a known form");
  if (c.pos_x_scale_steps.size()) {
    require(c.pos_x_scale_steps.size() == horizon, "collision.pos_x_scale must be empty or " + std::to_string(horizon) +
                                                       " numbers (one per step k = 1..T), got " +
                                                       std::to_string(c.pos_x_scale_steps.size()));
    for (int k = 0; k < horizon; ++k)
      require(std::isfinite(c.pos_x_scale_steps[k]) && c.pos_x_scale_steps[k] > 0,
              "collision.pos_x_scale[" + std::to_string(k) + "] (step k = " + std::to_string(k + 1) +
                  ") must be a positive finite number, got " + num(c.pos_x_scale_steps[k]));
  }
  if (!pairs) return;
  validate_min_distance(c.min_distance, c.min_distance_steps, horizon, "collision.min_distance");
  const auto& pd = c.pair_distances;
  for (size_t n = 0; n < pd.size(); ++n) {
    const PairDistance& q = pd[n];
    const std::string where = "collision.pair_distances[" + std::to_string(n) + "]";
    const std::string agents = "[" + std::to_string(q.i) + ", " + std::to_string(q.j) + "]";
    require(q.i >= 0 && q.i < num_agents && q.j >= 0 && q.j < num_agents,
            where + ".agents must be two agent indices in [0, " + std::to_string(num_agents) + "), got " + agents);
    require(q.i != q.j, where + ".agents must be two different agents, got " + agents);
    for (size_t m = 0; m < n; ++m)
      require(!((pd[m].i == q.i && pd[m].j == q.j) || (pd[m].i == q.j && pd[m].j == q.i)),
              where + ".agents: the pair " + agents + " already has a distance in collision.pair_distances[" +
                  std::to_string(m) + "]");
    try {
      validate_min_distance(q.min_distance, q.min_distance_steps, horizon, where + ".min_distance");
    } catch (const std::invalid_argument& e) {
      throw std::invalid_argument(std::string(e.what()) + " (agents " + agents + ")");
    }
  }
}

void validate_problem(const Problem& p) {
  const int N = p.num_agents();
  require(N >= 1, "agents must contain at least one agent");
  require(p.horizon >= 1, "horizon must be a positive integer, got " + std::to_string(p.horizon));
  require(p.dt > 0 && std::isfinite(p.dt), "dt must be a positive finite number, got " + num(p.dt));
  for (int i = 0; i < N; ++i)
    require(p.dynamics[i] != nullptr, "agents[" + std::to_string(i) + "].dynamics is missing");
  const int nx = p.dynamics[0]->nx(), nu = p.dynamics[0]->nu();
  require(nx >= 1 && nu >= 0, "agents[0].dynamics must have at least one state");
  auto per_agent = [&](size_t n, const char* name, bool may_be_empty) {
    require(static_cast<int>(n) == N || (may_be_empty && n == 0),
            std::string(name) + " must have one entry per agent (" + std::to_string(N) + "), got " + std::to_string(n));
  };
  per_agent(p.x0.size(), "x0", false);
  per_agent(p.costs.size(), "costs", false);
  per_agent(p.lead.size(), "lead", true);
  per_agent(p.u_min.size(), "u_min", true);
  per_agent(p.u_max.size(), "u_max", true);
  per_agent(p.x_min.size(), "x_min", true);
  per_agent(p.x_max.size(), "x_max", true);
  for (int i = 0; i < N; ++i) {
    const std::string a = "agents[" + std::to_string(i) + "]";
    require(p.dynamics[i]->nx() == nx && p.dynamics[i]->nu() == nu,
            a + ".dynamics: every agent must have nx=" + std::to_string(nx) + ", nu=" + std::to_string(nu) + " (got " +
                std::to_string(p.dynamics[i]->nx()) + ", " + std::to_string(p.dynamics[i]->nu()) + ")");
    validate_initial_state(p.x0[i], nx, a + ".x0");
    validate_cost(p.costs[i], nx, nu, p.horizon, a + ".cost");
    if (!p.lead.empty()) validate_lead(p.lead[i], nx, a);
    validate_bounds(p.u_min.empty() ? Vec() : p.u_min[i], p.u_max.empty() ? Vec() : p.u_max[i], nu, a, "u");
    validate_bounds(p.x_min.empty() ? Vec() : p.x_min[i], p.x_max.empty() ? Vec() : p.x_max[i], nx, a, "x");
  }
  validate_collision(p.collision, N, p.horizon, nx, !p.obstacles.empty());
  for (size_t o = 0; o < p.obstacles.size(); ++o) validate_obstacle(p.obstacles[o], p.horizon, "obstacles[" + std::to_string(o) + "]");
}

Problem with_defaults(const Problem& p) {
  Problem out = p;
  const int N = p.num_agents(), nx = p.dynamics[0]->nx(), nu = p.dynamics[0]->nu();
  if (out.lead.empty()) out.lead.assign(N, LeadCost{});
  auto fill = [&](std::vector<Vec>& b, int n, double value) {
    if (b.empty()) b.assign(N, Vec());
    for (Vec& v : b)
      if (v.size() == 0) v = Vec::Constant(n, value);
  };
  fill(out.u_min, nu, -kInf);
  fill(out.u_max, nu, kInf);
  fill(out.x_min, nx, -kInf);
  fill(out.x_max, nx, kInf);
  return out;
}

void validate_settings(const Settings& s) {
  require(s.tol > 0, "solver.tol must be positive");
  require(s.max_iter >= 0, "solver.max_iter must be >= 0");
  require(s.time_limit >= 0, "solver.time_limit must be >= 0 (0 = none)");
  require(s.barrier.rho_init > 0, "solver.barrier.rho_init must be positive");
  require(s.barrier.rho_kappa > 0 && s.barrier.rho_kappa < 1, "solver.barrier.rho_kappa must be in (0, 1)");
  require(s.barrier.rho_beta > 1, "solver.barrier.rho_beta must be > 1");
  require(s.barrier.rho_progress >= 0, "solver.barrier.rho_progress must be >= 0");
  require(s.barrier.rho_after_step >= 0 && s.barrier.rho_after_step <= 1,
          "solver.barrier.rho_after_step must be in [0, 1] (0 = after every step)");
  require(s.barrier.rho_floor_factor > 0 && s.barrier.rho_floor_factor <= 1, "solver.barrier.rho_floor_factor must be in (0, 1]");
  require(s.line_search.alpha > 0 && s.line_search.alpha < 1, "solver.line_search.alpha must be in (0, 1)");
  require(s.line_search.beta > 0 && s.line_search.beta < 1, "solver.line_search.beta must be in (0, 1)");
  require(s.line_search.max_steps >= 1, "solver.line_search.max_steps must be >= 1");
  require(s.violation_tol >= 0, "solver.violation_tol must be >= 0");
  require(s.dynamics_tol > 0, "solver.dynamics_tol must be positive");
  require(s.stationarity_tol >= 0, "solver.stationarity_tol must be >= 0 (0 = off)");
  require(s.barrier.margin >= 0, "solver.barrier.margin must be >= 0");
  require(s.domain_fraction >= 0 && s.domain_fraction < 1, "solver.domain_fraction must be in [0, 1) (0 = off)");
  require(s.line_search.lm_tries >= 0, "solver.line_search.lm_tries must be >= 0 (0 = off)");
  require(s.restart.count >= 0, "solver.restart.count must be >= 0");
  require(s.stall.window >= 0, "solver.stall.window must be >= 0 (0 = never)");
  require(s.stall.floor_window >= 0, "solver.stall.floor_window must be >= 0 (0 = never)");
  require(s.stall.crawl_window >= 0, "solver.stall.crawl_window must be >= 0 (0 = never)");
  require(s.stall.crawl_ratio > 0 && s.stall.crawl_ratio <= 1, "solver.stall.crawl_ratio must be in (0, 1]");
  require(s.stall.polish_gap >= 0, "solver.stall.polish_gap must be >= 0 (0 = off)");
  require(s.line_search.violation_memory >= 1, "solver.line_search.violation_memory must be >= 1");
  require(s.restart.violation_memory >= 1, "solver.restart.violation_memory must be >= 1");
  require(s.restart.rho_progress >= 0, "solver.restart.rho_progress must be >= 0");
  require(s.restart.deep_overlap >= 0, "solver.restart.deep_overlap must be >= 0");
  require(s.linear.lscg_tol > 0 && s.linear.lscg_max_iter >= 1, "solver.linear.lscg_tol must be positive and solver.linear.lscg_max_iter >= 1");
  require(s.second_order.tol > 0, "solver.second_order.tol must be positive");
  require(s.best_response.rounds >= 0, "solver.best_response.rounds must be >= 0 (0 = off)");
  require(s.best_response.max_iter >= 1, "solver.best_response.max_iter must be >= 1");
  require(s.best_response.restarts >= 0, "solver.best_response.restarts must be >= 0");
  require(std::isfinite(s.best_response.margin) && s.best_response.margin >= 0,
          "solver.best_response.margin must be finite and >= 0 (a fraction of the collision distance)");
  require(s.order.candidates >= 0, "solver.order.candidates must be >= 0 (0 = off)");
  require(s.order.polish >= 1, "solver.order.polish must be >= 1");
  require(s.order.polish_iter >= 1, "solver.order.polish_iter must be >= 1");
  require(s.order.max_iter >= 1, "solver.order.max_iter must be >= 1");
  require(std::isfinite(s.order.offset) && s.order.offset >= 0,
          "solver.order.offset must be finite and >= 0 (a fraction of the collision distance)");
  require(s.second_order.escapes >= 0, "solver.second_order.escapes must be >= 0 (0 = off)");
  require(std::isfinite(s.second_order.inertia) && s.second_order.inertia >= 0, "solver.second_order.inertia must be finite and >= 0 (0 = off)");
}

}  // namespace rd3g
