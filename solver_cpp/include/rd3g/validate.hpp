// The one validation routine of a game problem and of RD3G's settings, shared by RD3G (Solver::setup and
// the update_* calls) and the baselines (iLQGames, ALGames). Every index a problem carries is checked
// against the size it refers to, whatever combination of blocks is present, so that no later access can
// leave its buffer. Errors are std::invalid_argument (ValueError in Python) naming the field, with the
// paths of the Python API and the problem file: "agents[1].x0[2]", "collision.pos_x", "obstacles[0].positions".
#pragma once
#include <string>

#include "rd3g/problem.hpp"

namespace rd3g {

/// Throws std::invalid_argument(what) unless ok.
void require(bool ok, const std::string& what);

/// Checks every field of the problem; empty bound vectors (per agent) and an empty lead list mean "none".
void validate_problem(const Problem& p);
/// The problem with its defaults filled in: unbounded +-inf bounds for empty bound vectors, no lead cost
/// for an empty lead list. Call after validate_problem.
Problem with_defaults(const Problem& p);
void validate_settings(const Settings& s);

// The pieces validate_problem is made of (also used by the Solver's update calls). `where` is the field's path.
void validate_initial_state(const Vec& x0, int nx, const std::string& where);
void validate_cost(const QuadraticCost& c, int nx, int nu, int horizon, const std::string& where);
void validate_lead(const LeadCost& lead, int nx, const std::string& where);
/// Box bounds of one agent (`name` "u" or "x"): each empty (= unbounded) or n values, no NaN, lower < upper.
void validate_bounds(const Vec& lower, const Vec& upper, int n, const std::string& where, const char* name);
/// d_min (m) and its optional per-step values (k = 1..T).
void validate_min_distance(double min_distance, const Vec& steps, int horizon, const std::string& where);
void validate_obstacle(const Obstacle& o, int horizon, const std::string& where);
/// Position indices of pairs and obstacles, checked whenever either kind of constraint exists; with pairs, d_min
/// and every entry of pair_distances (agents in [0, num_agents), distinct, one entry per pair, d_min > 0).
void validate_collision(const CollisionSpec& c, int num_agents, int horizon, int nx, bool has_obstacles);

}  // namespace rd3g
