// RD3G: Newton's method on the open-loop generalised Nash equilibrium conditions of an N-agent game
// (Zhang & Tsiotras), with constraint partitioning: violated/active constraints are equalities with
// multipliers, satisfied ones are kept satisfied by a log barrier whose weight rho shrinks superlinearly.
#pragma once
#include <Eigen/Sparse>
#include <Eigen/SparseLU>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseQR>
#include <memory>
#include <vector>

#include "rd3g/problem.hpp"
#include "rd3g/riccati.hpp"

namespace rd3g {

class SecondOrderCheck;

/// One inequality constraint h <= 0 of the game, in a fixed order established at setup.
struct Constraint {
  enum class Kind { Pair, Obstacle, StateMax, StateMin, ControlMax, ControlMin };
  Kind kind;
  int i;    ///< agent
  int j;    ///< other agent (Pair) or obstacle index (Obstacle), else -1
  int k;    ///< time step: states k = 1..T, controls k = 0..T-1
  int idx;  ///< state/control component for bounds, else -1
};

/// How a constraint enters the current Newton system.
enum class ConstraintState : char {
  Barrier,  ///< satisfied: -rho log(-h) in the Lagrangian, no multiplier variable
  Active,   ///< violated or held at h = 0: equality with a multiplier variable
  Free,     ///< released (multiplier had the wrong sign) and not yet inside the barrier margin
};

class Solver {
 public:
  /// Validates the problem and allocates every buffer the solve needs.
  void setup(const Problem& problem, const Settings& settings);
  /// Solves from zero controls or from a warm start; the initial states are the rollout of the controls.
  Result solve(const WarmStart* warm = nullptr);

  const std::vector<Constraint>& constraints() const { return cons_; }

  /// For tests: residual r and dense Newton matrix J at a given primal-dual point (x per agent (T+1) x nx,
  /// u T x nu, lambda T x nx, mu one per constraint) and barrier weight rho, with the constraints
  /// partitioned as at the first iteration (h >= 0 active). Returns the multiplier column of each constraint.
  std::vector<int> debug_residual(const std::vector<Mat>& x, const std::vector<Mat>& u, const std::vector<Mat>& lam,
                                  const Vec& mu, double rho, Vec& r, Mat& J);
  /// Column of every primal variable: (agent, k, kind 0=u,1=lambda,2=x_{k+1}) -> first index.
  int column_of(int i, int k, int kind) const { return kind == 0 ? col_u(i, k) : kind == 1 ? col_lam(i, k) : col_x(i, k + 1); }
  Settings& settings() { return settings_; }
  const Problem& problem() const { return prob_; }

 private:
  using SpMat = Eigen::SparseMatrix<double>;
  using Triplet = Eigen::Triplet<double>;

  struct Iterate {
    std::vector<Mat> x;    // per agent nx x (T+1), column k = x_k
    std::vector<Mat> u;    // per agent nu x T
    std::vector<Mat> lam;  // per agent nx x T
    Vec mu, mu2;           // per constraint; mu2 = other agent's multiplier for Pair (per-agent formulation)
    Vec z;                 // per constraint: barrier dual (primal-dual mode), -rho/h on the central path
  };

  // index helpers
  int stage_size() const { return nu_ + 2 * nx_; }
  int col_u(int i, int k) const { return (k * N_ + i) * stage_size(); }
  int col_lam(int i, int k) const { return col_u(i, k) + nu_; }
  int col_x(int i, int k) const { return col_u(i, k - 1) + nu_ + nx_; }  // k = 1..T

  void eval_constraint(const Iterate& y, int c, double& h, Eigen::Vector2d& g, Eigen::Matrix2d& H) const;
  void eval_all_constraints(const Iterate& y, Vec& h) const;
  void classify(const Vec& h, bool first);
  void number_multipliers();
  /// Residual (and, if jac, the Jacobian triplets) at y with the current partition and rho.
  /// Returns false if a barrier constraint is not strictly satisfied (residual undefined).
  /// Also fills rc (complementarity (-h) z - rho of barrier constraints, primal-dual mode) and, if jac,
  /// rhs_ (the condensed right-hand side, i.e. the paper's barrier residual) and the triplets.
  bool evaluate(const Iterate& y, const Vec& h, bool jac, Vec& r, Vec& rc);
  double merit(const Vec& r, const Vec& rc) const { return std::sqrt(r.head(n_vars_).squaredNorm() + rc.squaredNorm()); }
  /// Primal-dual: recover dz of the barrier constraints from the condensed step.
  void recover_dual_step(const Iterate& y, const Vec& h, const Vec& rc, const Vec& dy, Vec& dz) const;
  bool solve_linear(Vec& dy);
  bool solve_levenberg_marquardt(double nu, Vec& dy);
  /// Backtracking line search along dy_ from y_ into trial_; returns the accepted t or 0.
  double line_search(double merit0);
  void apply_step(const Iterate& y, const Vec& dy, double t, Iterate& out) const;
  double violation_sum(const Vec& h) const;
  /// On a stall: barrier constraints with h >= -polish_gap become equalities, their multiplier the barrier's
  /// estimate. Returns false if there is none.
  bool polish(const Vec& h);

  Problem prob_;
  Settings settings_;
  int N_ = 0, T_ = 0, nx_ = 0, nu_ = 0, n_primal_ = 0;
  bool per_agent_multipliers_ = false;
  std::vector<Constraint> cons_;
  std::vector<ConstraintState> state_, pattern_state_;
  std::vector<int> mu_col_, mu2_col_;  // variable/row index of each constraint's multiplier(s), -1 if none
  int n_vars_ = 0;
  double rho_ = 0;
  BarrierMode barrier_ = BarrierMode::PrimalDual;  // barrier form of the current attempt

  // buffers (allocated in setup)
  Iterate y_, trial_, best_;
  std::vector<std::vector<Mat>> A_, B_;
  Mat fx_, Hl_, Atmp_, Btmp_;
  Vec h_, h_trial_, r_, r_trial_, dy_, rc_, rc_trial_, rhs_, dz_;
  std::vector<Triplet> trip_;
  SpMat J_;
  Eigen::SparseLU<SpMat, Eigen::COLAMDOrdering<int>> lu_;
  bool lu_analyzed_ = false;
  bool J_built_ = false;  // J_ holds this iteration's matrix (the Riccati path does not need it)
  StageRiccati riccati_;
  void build_J();
  Info* info_ = nullptr;
  /// Second-order test of y_ (defined in second_order.cpp): fills info.second_order; true if every agent passes.
  bool check_second_order(Info& info);
  std::shared_ptr<SecondOrderCheck> second_order_;
};

}  // namespace rd3g
