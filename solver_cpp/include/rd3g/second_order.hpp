// Second-order test of a first-order point of the game: is it a local equilibrium, i.e. is every agent's own
// problem (its dynamics and constraints, the other agents' trajectories fixed) at a strict local minimum?
//
// For agent a the controls U = (u_0..u_{T-1}) parametrise its dynamics' null space (x_k = x_k(U), single
// shooting), so the reduced Hessian of its Lagrangian L^a = J^a + sum_k lambda_k'(f(x_k,u_k) - x_{k+1})
// + sum_c w_c h_c on the dynamics' null space is
//   H_U = sum_k [S_k; E_k]' d2L^a/d(x_k,u_k)^2 [S_k; E_k],   S_k = dx_k/dU, E_k = du_k/dU,
// the Hessian of U -> J^a(x(U), U) + sum_c w_c h_c(x(U), U) when lambda is the adjoint (at a first-order point).
// Constraints of agent a with h_c >= -active_gap and a positive multiplier w_c are held as equalities: the test
// is on the null space N of their Jacobian rows dh_c/dU, with an orthonormal basis Z (control units). Every
// constraint's multiplier-weighted curvature w_c d2h_c enters H_U (the barrier's own rho/h^2 term does not: the
// question is about the agent's constrained problem, not the barrier's approximation of it).
#pragma once
#include <Eigen/Eigenvalues>
#include <functional>
#include <vector>

#include "rd3g/problem.hpp"
#include "rd3g/solver.hpp"

namespace rd3g {

struct SecondOrderAgent {
  /// Smallest eigenvalue of Z' H_U Z (cost units per control unit^2); +inf if N = {0} (the active constraints
  /// fix every control).
  double min_eigenvalue = kInf;
  double max_abs_eigenvalue = 0;  ///< largest |eigenvalue| of Z' H_U Z, the scale of the relative test
  int free_directions = 0;        ///< dim N
  int active = 0;                 ///< constraints held as equalities in the test
  /// Unit eigenvector of min_eigenvalue as controls, nu x T: a direction of negative curvature, computed only when
  /// the agent fails the test (empty otherwise).
  Mat direction;
};

/// Smallest and largest eigenvalue of the symmetric tridiagonal matrix with diagonal d (length n >= 1) and
/// off-diagonal e (length n - 1), by bisection on Sturm counts (LAPACK dstebz's method), to about machine precision
/// times the matrix's norm. The two searches share each sweep (independent Sturm sequences, whose divisions overlap).
/// NaN if d or e is not finite.
void tridiagonal_extreme_eigenvalues(const Eigen::Ref<const Vec>& d, const Eigen::Ref<const Vec>& e, double& lo,
                                     double& hi);

/// Value h, gradient g (w.r.t. the agent's own position or bounded component) and Hessian H of constraint c at the
/// point being checked (the solver's own evaluation, so that both agree on forms and units).
using ConstraintEval = std::function<void(int c, double& h, Eigen::Vector2d& g, Eigen::Matrix2d& H)>;

/// Buffers are sized in setup(); check() reuses them.
class SecondOrderCheck {
 public:
  void setup(int num_agents, int horizon, int nx, int nu);
  /// x per agent nx x (T+1) (column k = x_k), u per agent nu x T, lam per agent nx x T (dynamics multipliers, sign
  /// as above); w_i[c] / w_j[c] is the multiplier of constraint c for its agent i / its other agent j (pairs).
  /// tol is the relative test's (passes). Returns one entry per agent.
  const std::vector<SecondOrderAgent>& check(const Problem& p, const std::vector<Constraint>& cons,
                                             const ConstraintEval& eval, const std::vector<Mat>& x,
                                             const std::vector<Mat>& u, const std::vector<Mat>& lam, const Vec& w_i,
                                             const Vec& w_j, double active_gap, double tol);
  /// True if every agent's min_eigenvalue >= -tol * max(1, max_abs_eigenvalue) (relative test; tol > 0).
  bool passes(double tol) const;
  /// The last check's agents.
  const std::vector<SecondOrderAgent>& agents() const { return out_; }
  /// Whether agent a passed the last check (as in passes).
  bool agent_passes(int a, double tol) const;

 private:
  void stage_hessians(const Problem& p, int a, const std::vector<Mat>& x, const std::vector<Mat>& u,
                      const std::vector<Mat>& lam);
  int add_constraints(const Problem& p, int a, const std::vector<Constraint>& cons, const ConstraintEval& eval,
                      const Vec& w_i, const Vec& w_j, double active_gap);
  void condense_hessian();
  void reduced_spectrum(int a, int na, double tol);

  int N_ = 0, T_ = 0, nx_ = 0, nu_ = 0;
  std::vector<Mat> S_;  // S_k = dx_k/dU, nx x (T nu), k = 0..T
  std::vector<Mat> A_, B_, Q_, M_, R_;  // per stage: dynamics Jacobians; Lagrangian Hessian blocks xx, xu, uu
  Mat Hr_, Rz_, Hl_, P_, PA_, PB_, W_, C_;
  Vec fx_, diag_, subdiag_;
  Eigen::Tridiagonalization<Mat> tri_;  // the extreme eigenvalues: tridiagonal form, then Sturm bisection
  Eigen::SelfAdjointEigenSolver<Mat> es_;  // the eigenvector of a failing agent
  std::vector<SecondOrderAgent> out_;
};

}  // namespace rd3g
