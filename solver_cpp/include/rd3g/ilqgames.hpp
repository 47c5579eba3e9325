// iLQGames baseline (Fridovich-Keil, Ratner, Peters, Dragan, Tomlin, ICRA 2020): iterated linear-quadratic
// approximations of the game around the current trajectory, each solved for its FEEDBACK Nash equilibrium
// with the coupled Riccati recursion; inequality constraints (collisions, bounds) enter every involved
// player's cost as an augmented-Lagrangian penalty whose weight grows between rounds.
//
// Validation (rd3g/validate.hpp) and the constraints (rd3g/constraints.hpp) are RD3G's.
#pragma once
#include <Eigen/Dense>
#include <vector>

#include "rd3g/constraints.hpp"
#include "rd3g/problem.hpp"
#include "rd3g/solver.hpp"  // Result, WarmStart, status_name

namespace rd3g {


// -------------------------------------------------------------------------------------------------
/// A finite-horizon LQ game in joint coordinates: x_{k+1} = A_k x_k + B_k u_k with u the stacked controls
/// of all players (player i owns columns [offset_i, offset_i + m_i) of B_k). Player i minimises
///   J^i = sum_{k=0}^{T-1} [1/2 x_k'Q^i_k x_k + l^i_k'x_k + 1/2 u_k'R^i_k u_k + r^i_k'u_k] + 1/2 x_T'QT^i x_T + lT^i'x_T.
/// (Basar & Olsder, Cor. 6.1). Feedback Nash strategies: u_k = -P_k x_k - alpha_k (joint P_k: m x n).
struct LQGame {
  std::vector<int> control_dims;          ///< m_i per player
  std::vector<Mat> A;                     ///< [k] n x n
  std::vector<Mat> B;                     ///< [k] n x m
  std::vector<std::vector<Mat>> Q;        ///< [k][i] n x n
  std::vector<std::vector<Vec>> l;        ///< [k][i] n
  std::vector<std::vector<Mat>> R;        ///< [k][i] m x m (player i's weights on the joint control)
  std::vector<std::vector<Vec>> r;        ///< [k][i] m
  std::vector<Mat> QT;                    ///< [i] n x n
  std::vector<Vec> lT;                    ///< [i] n
};

/// Coupled Riccati recursion for the feedback Nash equilibrium of an LQGame.
class LQGameSolver {
 public:
  /// Allocates for n joint states, the given control sizes and horizon T.
  void setup(int n, const std::vector<int>& control_dims, int T);
  /// Fills P()[k] (m x n) and alpha()[k] (m). Returns false if a stage's coupled system is singular
  /// or produces non-finite values.
  bool solve(const LQGame& game);
  const std::vector<Mat>& P() const { return P_; }
  const std::vector<Vec>& alpha() const { return alpha_; }

 private:
  int n_ = 0, m_ = 0, N_ = 0, T_ = 0;
  std::vector<int> off_, dims_;
  std::vector<Mat> P_, Z_, ZB_;
  std::vector<Vec> alpha_, zeta_;
  Mat S_, Y_, PA_, F_, ZF_, RP_;
  Vec beta_, tmp_;
  Eigen::PartialPivLU<Mat> lu_;
};

// -------------------------------------------------------------------------------------------------
/// iLQGames settings. Units: state/control units of the model unless stated.
struct ILQGamesSettings {
  /// Converged when the full step of the current LQ game would change no state or control by more than
  /// tol (inf-norm over agents, steps and components) and every constraint satisfies h <= violation_tol.
  double tol = 1e-4;
  int max_iter = 500;             ///< LQ game solves (= iterations) in total, over all penalty rounds
  double time_limit = 0.0;        ///< (s), 0 = none
  /// Trust region of the line search: a step is accepted only if no state moves by more than this
  /// (inf-norm; m, m/s, rad for the bicycle models).
  double max_state_change = 1.0;
  /// Feedforward step size: step <- ls_beta * step while rejected; also the factor by which the starting
  /// step of the next iterations shrinks when the full-step change did not decrease (and grows back).
  double ls_beta = 0.5;
  int ls_max_steps = 20;          ///< shrinks before the line search fails; the smallest step is ls_beta^ls_max_steps
  double violation_tol = 1e-4;    ///< constraint units (m for the distance form, m^2 for the squared form)
  double rho_init = 10.0;         ///< initial penalty weight (cost units per constraint unit^2)
  double rho_growth = 10.0;       ///< rho <- min(rho_max, rho_growth * rho) after every penalty round
  double rho_max = 1e8;
  /// A penalty round (multiplier update lambda <- max(0, lambda + rho h), penalty growth) ends when the
  /// iterates converged to tol or after this many iterations.
  int round_max_iter = 50;
  bool bounds = true;             ///< include control/state bounds as penalised constraints
  bool verbose = false;
};

/// iLQGames on an rd3g::Problem. setup() validates and allocates; solve() starts from zero controls
/// (or warm->u; lambda/mu of the warm start are ignored). Result: x, u, info (residual_norm = the
/// full-step change at the last iterate, the convergence measure; max_violation = max(0, max h)), h, and
/// mu = the penalty multipliers lambda (one per constraint); lambda (dynamics multipliers) is left empty.
class ILQGamesSolver {
 public:
  void setup(const Problem& problem, const ILQGamesSettings& settings);
  Result solve(const WarmStart* warm = nullptr);
  const std::vector<Constraint>& constraints() const { return cons_; }
  ILQGamesSettings& settings() { return settings_; }

 private:
  void linearize_and_quadratize();
  void rollout(double step);  // trial_x_/trial_u_ from the current strategies
  double max_violation(const std::vector<Mat>& x, const std::vector<Mat>& u, Vec& h);

  Problem prob_;
  ILQGamesSettings settings_;
  int N_ = 0, T_ = 0, nx_ = 0, nu_ = 0, n_ = 0, m_ = 0;
  std::vector<Constraint> cons_;
  std::vector<std::vector<int>> cons_at_;  // constraint indices per stage k = 0..T
  Vec lambda_, h_, h_trial_;
  double rho_ = 0;
  std::vector<Mat> x_, u_, trial_x_, trial_u_;  // per agent nx x (T+1), nu x T
  LQGame lq_;
  LQGameSolver lq_solver_;
  Mat Ai_, Bi_;
  Vec xn_, dx_, du_;
};

}  // namespace rd3g
