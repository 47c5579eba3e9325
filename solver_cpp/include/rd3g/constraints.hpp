// The inequality constraints h <= 0 of a game (collision pairs, obstacles, state and control bounds), their
// list and their values and derivatives: one definition used by RD3G and the baselines (iLQGames, ALGames).
#pragma once
#include <Eigen/Dense>
#include <vector>

#include "rd3g/problem.hpp"

namespace rd3g {

/// One inequality constraint h <= 0 of the game, in a fixed order established at set-up.
struct Constraint {
  enum class Kind { Pair, Obstacle, StateMax, StateMin, ControlMax, ControlMin };
  Kind kind;
  int i;    ///< agent
  int j;    ///< other agent (Pair) or obstacle index (Obstacle), else -1
  int k;    ///< time step: states k = 1..T, controls k = 0..T-1
  int idx;  ///< state/control component for bounds, else -1
  /// True if the constraint is one of agent a's: its own (i == a) or a pair with a as the other agent.
  bool involves(int a) const { return i == a || (kind == Kind::Pair && j == a); }
};

/// The constraints of a validated problem with its defaults filled in (rd3g::with_defaults), in time order
/// (pairs, obstacles, state bounds at k = 1..T; control bounds at k = 0..T-1; only finite bounds), which
/// keeps RD3G's multiplier numbering close to its stage ordering. Bounds are listed only if with_bounds.
std::vector<Constraint> list_constraints(const Problem& p, bool with_bounds = true);

/// h = dmin - |A d| (Distance) or dmin^2 - |A d|^2 (Squared) with d the separation (p_i - p_j or p_i - o_k) and
/// A = diag(sx, 1) (CollisionSpec::x_scale), g = dh/dd and H = d2h/dd2, each only where non-null (the line
/// search's trials need h alone, or h and g).
void distance_constraint(CollisionForm form, const Eigen::Vector2d& d, double dmin, double& h, Eigen::Vector2d* g,
                         Eigen::Matrix2d* H, double sx = 1.0);

/// A constraint's value and derivatives with respect to the (at most 4) scalar variables it touches:
/// variable a is component comp[a] of agent agent[a]'s state x_k (or control u_k if on_u).
struct ConstraintValue {
  double h = 0;
  int n = 0;
  bool on_u = false;
  int agent[4] = {0, 0, 0, 0};
  int comp[4] = {0, 0, 0, 0};
  double g[4] = {0, 0, 0, 0};
  Eigen::Matrix4d H = Eigen::Matrix4d::Zero();
};

/// x: per agent nx x (T+1) (column k = x_k), u: per agent nu x T.
void eval_constraint(const Problem& p, const Constraint& c, const std::vector<Mat>& x, const std::vector<Mat>& u,
                     ConstraintValue& out);

}  // namespace rd3g
