// ALGames baseline (Le Cleac'h, Schwager, Manchester, RSS 2020): Newton's method on the stacked first-order
// conditions of every player's augmented Lagrangian, i.e. an OPEN-LOOP (generalised) Nash equilibrium.
// Inequality constraints h <= 0 (collisions, obstacles, bounds) enter each involved player's augmented
// Lagrangian in PHR form  (1/(2 rho)) (max(0, lambda + rho h)^2 - lambda^2); an outer loop does dual ascent
// lambda <- max(0, lambda + rho h) and grows rho.
#pragma once
#include <Eigen/Sparse>
#include <Eigen/SparseLU>
#include <vector>

#include "rd3g/constraints.hpp"
#include "rd3g/problem.hpp"
#include "rd3g/solver.hpp"
#include "rd3g/stage_terms.hpp"

namespace rd3g {

/// ALGames settings. Units: residual in cost units per variable unit; violations in constraint units.
struct ALGamesSettings {
  /// Converged when ||G||_2 < tol, every h <= violation_tol and every dynamics defect
  /// |f(x_k, u_k) - x_{k+1}| <= dynamics_tol (ALGames counts the dynamics among the constraints).
  double tol = 1e-4;
  double dynamics_tol = 1e-6;     ///< (state units)
  int max_iter = 200;             ///< Newton iterations in total, over all outer (dual) iterations
  double time_limit = 0.0;        ///< (s), 0 = none
  double violation_tol = 1e-4;    ///< constraint units (m for the distance form, m^2 for the squared form)
  double rho_init = 1.0;          ///< initial penalty (cost units per constraint unit^2)
  double rho_growth = 10.0;       ///< rho <- min(rho_max, rho_growth * rho) after every dual update
  double rho_max = 1e8;
  /// Newton iterations per outer iteration: the inner loop ends at ||G|| < tol, after inner_max_iter
  /// iterations or when its line search fails; then the multipliers and the penalty are updated.
  int inner_max_iter = 20;
  double ls_alpha = 1e-4;         ///< accept step t when ||G(y + t dy)|| <= (1 - ls_alpha t) ||G(y)||
  double ls_beta = 0.5;           ///< t <- ls_beta t while rejected
  int ls_max_steps = 20;
  bool bounds = true;             ///< include control/state bounds as constraints
  bool verbose = false;
};

/// ALGames on an rd3g::Problem. Decision vector: all players' states x_1..x_T and controls u_0..u_{T-1}
/// plus the dynamics multipliers nu (one per player per step, on the player's own dynamics: with the
/// decoupled dynamics of rd3g::Problem a player's multipliers on the other players' dynamics do not enter
/// its stationarity in u, so they are not carried; see docs/baselines.md). Result: x, u, lambda = nu,
/// mu = inequality multipliers max(0, lambda + rho h), h; residual_norm = ||G||_2.
class ALGamesSolver {
 public:
  void setup(const Problem& problem, const ALGamesSettings& settings);
  Result solve(const WarmStart* warm = nullptr);
  const std::vector<Constraint>& constraints() const { return cons_; }
  ALGamesSettings& settings() { return settings_; }

 private:
  using SpMat = Eigen::SparseMatrix<double>;
  int stage_size() const { return layout_.stage_size(); }
  int col_u(int i, int k) const { return layout_.col_u(i, k); }
  int col_nu(int i, int k) const { return layout_.col_lam(i, k); }
  int col_x(int i, int k) const { return layout_.col_x(i, k); }  // k = 1..T
  void unpack(const Vec& y);                                           // y -> X_, U_
  /// G(y) (and the Jacobian's values in trip_ if jac) with the current lambda and rho; fills h.
  bool evaluate(const Vec& y, bool jac, Vec& G, Vec& h);

  Problem prob_;
  ALGamesSettings settings_;
  int N_ = 0, T_ = 0, nx_ = 0, nu_ = 0, n_vars_ = 0;
  std::vector<Constraint> cons_;
  Vec lambda_, h_, h_trial_;
  double rho_ = 0;
  Vec y_, y_trial_, G_, G_trial_, dy_;
  std::vector<Mat> X_, U_;
  StageLayout layout_;
  std::vector<StagePattern> stage_patterns_;  // per agent: its model's Jacobian entries
  StageWorkspace stage_;
  Mat A_, B_;
  Vec fx_;
  std::vector<Eigen::Triplet<double>> trip_;
  SpMat J_;
  Eigen::SparseLU<SpMat, Eigen::COLAMDOrdering<int>> lu_;
  bool analyzed_ = false;
};

}  // namespace rd3g
