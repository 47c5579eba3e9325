// The cost and dynamics part of the Newton system of an open-loop game, shared by RD3G (solver.cpp) and
// ALGames (algames.cpp). Both stack, per stage k and agent i, the variables [u_k, lambda_k, x_{k+1}] and
// the rows [dL^i/du_k; f(x_k, u_k) - x_{k+1}; dL^i/dx_{k+1}] of L^i = J^i + sum_k lambda_k'(f(x_k, u_k) - x_{k+1});
// each adds its constraint terms on top.
#pragma once
#include <Eigen/Sparse>
#include <array>
#include <memory>
#include <vector>

#include "rd3g/dynamics.hpp"
#include "rd3g/problem.hpp"

namespace rd3g {

/// Column (and row) offsets of the stage-wise layout: stages in time order, agents within a stage.
struct StageLayout {
  int N = 0, nx = 0, nu = 0;
  int stage_size() const { return nu + 2 * nx; }
  int col_u(int i, int k) const { return (k * N + i) * stage_size(); }
  int col_lam(int i, int k) const { return col_u(i, k) + nu; }
  int col_x(int i, int k) const { return col_u(i, k - 1) + nu + nx; }  // k = 1..T
};

/// The Jacobian entries add_stage_terms emits for one agent's stage: its model's derivative pattern
/// (Dynamics::derivative_pattern) as (row, col) lists of each block, row-major; the control block also holds its
/// diagonal (the cost's R), and the state block's diagonal (the cost's Q) is emitted besides these.
struct StagePattern {
  using Entries = std::vector<std::array<int, 2>>;
  Entries Huu, Bt, B, Hux, Hxu, Hxx, At, A;  // Bt, At: B' and A' (rows u and x, columns lambda)
  explicit StagePattern(const Dynamics& f);
  bool same_as(const StagePattern& o) const;
};

/// One StagePattern per agent's model.
std::vector<StagePattern> stage_patterns(const std::vector<std::shared_ptr<const Dynamics>>& dynamics);

/// Scratch space of add_stage_terms (and of the cost gradients Solver::cost_gradient_norm sums), sized once (no
/// allocation per stage).
struct StageWorkspace {
  Mat A, B, Hl, Huu;
  Vec fx;
  Vec Btl, Atl;  // B' lambda_k and A' lambda_k (products into these instead of temporaries: no allocation)
  Vec gu, gx;    // cost gradients in u_k and x_{k+1}
  void resize(int nx, int nu);
};

/// The quadratic cost's gradient in one control, dJ/du_k = 2 R u_k (cost units per control unit).
void control_cost_gradient(const QuadraticCost& cost, const Eigen::Ref<const Vec>& u_k, Eigen::Ref<Vec> g);

/// The quadratic cost's gradient in the state of step k (1..T), dJ/dx_k = 2 (Q_ref (x_k - ref_k) + Q x_k), with
/// Qf_ref and Qf at k = T (cost units per state unit). The lead term adds lead_gradient on component lead.index.
void state_cost_gradient(const QuadraticCost& cost, int k, int T, const Eigen::Ref<const Vec>& x_k, Eigen::Ref<Vec> g);

/// The quadratic cost's Hessian in one control, d2J/du_k^2 = 2 R (the diagonal; cost units per control unit^2).
inline auto control_cost_hessian(const QuadraticCost& cost) { return 2.0 * cost.R; }

/// The quadratic cost's Hessian in the state of step k (1..T), d2J/dx_k^2 = 2 (Q_ref + Q), with Qf_ref and Qf at
/// k = T (the diagonal; cost units per state unit^2).
inline auto state_cost_hessian(const QuadraticCost& cost, int k, int T) {
  return k == T ? 2.0 * (cost.Qf_ref + cost.Qf) : 2.0 * (cost.Q_ref + cost.Q);
}

/// The lead term's constant gradient on its state component, -weight (N - 1) (0 in a one-agent game).
inline double lead_gradient(const LeadCost& lead, int N) { return N > 1 ? -lead.weight * (N - 1) : 0.0; }

/// Adds agent i's terms of stage k (0..T-1) to the residual r (rows of the layout; r must be zero there
/// before stage 0, and the stage-k terms of x_k are added at stage k) and, if trip, the Jacobian's triplets: the
/// entries of pattern (f's), explicit zeros included, so the Newton matrix's pattern depends only on the models.
/// x: nx x (T+1) with column k = x_k, u: nu x T, lam_k: the dynamics multiplier of stage k.
void add_stage_terms(const StageLayout& layout, int i, int k, int T, const Dynamics& f, const StagePattern& pattern,
                     const QuadraticCost& cost, const LeadCost& lead, const Mat& x, const Mat& u,
                     const Eigen::Ref<const Vec>& lam_k, Vec& r, std::vector<Eigen::Triplet<double>>* trip,
                     StageWorkspace& w);

}  // namespace rd3g
