// Structured solve of RD3G's Newton system: with the variables ordered stage by stage, the primal part
// is block-tridiagonal in time, and a backward recursion on lambda_k = P_{k+1} dx_{k+1} + p_{k+1} (the
// coupled, nonsymmetric Riccati recursion of an open-loop game) solves it in O(T (N nx)^3) instead of a
// general sparse LU. The dynamics Jacobians (Fx, Fu) and the costate columns of the stationarity rows (Rul, Qxl)
// are block-diagonal by agent and are multiplied block by block. Constraints held as equalities add a few
// multiplier rows and columns; they are eliminated by a Schur complement (one Riccati back-substitution per
// multiplier column, then a small dense solve), so the structured solve is kept while track limits or speed bounds
// are active.
#pragma once
#include <Eigen/Dense>
#include <Eigen/Sparse>
#include <vector>

namespace rd3g {

class StageRiccati {
 public:
  StageRiccati() = default;
  StageRiccati(const StageRiccati&) = delete;  // the scatter plan points into this object's stage blocks
  StageRiccati& operator=(const StageRiccati&) = delete;
  /// N agents, horizon T, sizes nx, nu; variables per stage and agent ordered [u, lambda, x_{k+1}].
  void setup(int N, int T, int nx, int nu);
  /// Solves J dy = -rhs (J of size n, given by its triplets; the first n_primal = N T (nu + 2 nx) variables
  /// are the primal ones, the rest multipliers). Returns false when the primal block does not have the
  /// stage structure (including an entry across agents in Fx, Fu, Rul or Qxl) or a stage or Schur matrix is
  /// singular; the caller then uses a general solver.
  bool solve(const std::vector<Eigen::Triplet<double>>& trip, int n, const Eigen::VectorXd& rhs, Eigen::VectorXd& dy);

 private:
  /// Stage blocks of the primal-primal triplets and the rhs-independent part of the recursion.
  bool factor(const std::vector<Eigen::Triplet<double>>& trip);
  /// The stage blocks from the triplets (through the plan); false if the primal block lacks the stage structure.
  bool scatter(const std::vector<Eigen::Triplet<double>>& trip);
  /// out = -K^{-1} b for the primal block K factored last (b, out of length n_primal).
  void back_substitute(const Eigen::Ref<const Eigen::VectorXd>& b, Eigen::Ref<Eigen::VectorXd> out);
  void stage_segment(const Eigen::Ref<const Eigen::VectorXd>& b, int k, int kind, Eigen::VectorXd& out) const;
  /// out = A B for B block-diagonal by agent (N blocks br x bc); out sized A.rows() x N bc.
  void times_block_diagonal(const Eigen::MatrixXd& A, const Eigen::MatrixXd& B, int br, int bc,
                            Eigen::MatrixXd& out) const;
  /// out += sign A C for A block-diagonal by agent (N blocks ar x ac).
  void add_block_diagonal_times(const Eigen::MatrixXd& A, const Eigen::Ref<const Eigen::MatrixXd>& C, int ar, int ac,
                                Eigen::Ref<Eigen::MatrixXd> out, double sign = 1.0) const;

  int N_ = 0, T_ = 0, nx_ = 0, nu_ = 0, X_ = 0, U_ = 0, n_primal_ = 0;
  /// Where primal variable g sits: stage k, kind (0 = u, 1 = lambda, 2 = x_{k+1}), position in the stage's
  /// stacked block and agent. A table, not divisions: factor decodes every triplet's row and column (most of its
  /// time).
  struct Slot {
    int k, kind, pos, agent;
  };
  std::vector<Slot> slots_;
  /// Where triplet (row, col) is added: dest points into a stage block, is nullptr for an entry of a -I block
  /// (its value is checked instead), or is &discarded_ for a multiplier row or column (the Schur complement's).
  bool decode(int row, int col, double*& dest);
  /// The destinations of the last factorisation's triplets, in their order: the assembly emits the stage terms
  /// first, in an order fixed by the models, so most of the plan holds from one Newton step to the next and the
  /// scatter skips the decoding.
  struct PlannedEntry {
    int row, col;
    double* dest;
  };
  std::vector<PlannedEntry> plan_;
  double discarded_ = 0.0;
  // Per stage k = 0..T-1 (x-row blocks Q* belong to time k+1 and are stored at index k):
  std::vector<Eigen::MatrixXd> Ruu_, Rux_, Rul_, Fx_, Fu_, Qxx_, Qxu_, Qxl_, P_, K_, W_;
  std::vector<Eigen::PartialPivLU<Eigen::MatrixXd>> lu_;
  Eigen::PartialPivLU<Eigen::MatrixXd> slu_;  // Schur matrix
  std::vector<Eigen::VectorXd> p_, kap_;
  // Work vectors (sized in setup; the multiplier blocks reallocate only when the number of equality rows changes).
  Eigen::VectorXd g_, e_, h_, pe_, x_, u_, xn_, lam_, rhs_mu_;
  Eigen::MatrixXd Bm_, Cm_, Z_, S_;  // multiplier columns, rows, K^{-1} columns, Schur matrix
  Eigen::MatrixXd PFx_, PFu_, G_, Pn_;
};

}  // namespace rd3g
