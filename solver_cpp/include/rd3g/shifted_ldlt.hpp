// Sparse LDL' of A + shift I for a sequence of symmetric matrices A with one sparsity pattern (the Levenberg-Marquardt
// tries: J'J + nu I for several nu per iteration; J'J keeps its pattern while the constraint partition does).
//
// analyze() orders A by approximate minimum degree (Eigen's AMD, as Eigen's SimplicialLDLT orders it), computes the
// elimination tree and the pattern of L, and groups L's columns into supernodes: runs of consecutive columns with
// the same pattern below their diagonal block, stored together as one dense column-major panel. load() copies A's
// values into the permuted lower triangle through a precomputed index map. factorize_shifted() is a left-looking
// supernodal LDL' without pivoting: each panel receives the updates of the panels below whose rows reach its
// columns (dense products over whole panel columns instead of Eigen's entry-by-entry up-looking LDLT), then is
// factored densely. Like Eigen's, it fails only on an exact zero pivot (A + shift I is positive definite for J'J and
// shift > 0). Buffers are sized in analyze(); factorize_shifted() and solve() do not allocate.
#pragma once
#include <Eigen/Sparse>
#include <vector>

#include "rd3g/sparsity_pattern.hpp"

namespace rd3g {

class ShiftedLDLT {
 public:
  using SpMat = Eigen::SparseMatrix<double>;
  /// Ordering, elimination tree, supernodes and storage for A's pattern (A square, compressed, symmetric with every
  /// diagonal entry stored; its lower triangle is used). False if A is not square.
  bool analyze(const SpMat& A);
  /// True if A (compressed) has exactly the pattern of the last analyze(): then load() may be used on it.
  bool same_pattern(const SpMat& A) const;
  /// Loads the lower triangle's values of A (the analysed pattern) for the factorisations that follow.
  void load(const SpMat& A);
  /// Numeric LDL' of (the loaded A) + shift I. False on a zero pivot or before analyze().
  bool factorize_shifted(double shift);
  /// x = (A + shift I)^{-1} b with the last successful factorisation (b and x of length n, may not alias).
  void solve(const Eigen::Ref<const Eigen::VectorXd>& b, Eigen::Ref<Eigen::VectorXd> x) const;
  /// Supernodes of the analysed pattern (-1 before analyze()).
  int supernodes() const { return static_cast<int>(sn_first_.size()) - 1; }

 private:
  // analyze()'s steps: the ordering; P A P''s lower triangle; the elimination tree (parent), the counts below the
  // diagonal and the rows (lrow[lptr[j] ..]) of L's columns; the supernodes and the factor's storage.
  void order(const SpMat& A);
  void permute_lower();
  void symbolic(std::vector<int>& parent, std::vector<int>& count, std::vector<int>& lptr,
                std::vector<int>& lrow) const;
  void make_supernodes(const std::vector<int>& parent, const std::vector<int>& count, const std::vector<int>& lptr,
                       const std::vector<int>& lrow);
  // factorize_shifted()'s steps for supernode s: the updates from the supernodes below it, then its dense LDL'.
  void update_panel(int s);
  bool factor_panel(int s);

  int n_ = 0;
  std::vector<int> new_of_old_;         // P: position in the ordered matrix of each original index
  SparsityPattern pattern_;             // the analysed pattern of A
  std::vector<int> bptr_, brow_, map_;  // lower triangle of P A P' by columns; value q is A's value map_[q]
  std::vector<double> bval_;
  std::vector<int> sn_first_;           // supernode s holds columns [sn_first_[s], sn_first_[s + 1])
  std::vector<int> sn_of_;              // supernode of each column
  std::vector<int> rptr_, rows_;        // supernode s's rows, its own columns first: rows_[rptr_[s] .. rptr_[s + 1])
  std::vector<long> vptr_;              // offset of supernode s's panel (rows x width, column-major) in lx_
  std::vector<double> lx_, d_;          // the panels (unit lower L; the diagonal holds D) and D
  std::vector<int> pos_, head_, link_, next_;  // factorisation work: row positions, update lists
  std::vector<double> acc_;
  mutable std::vector<double> y_;
};

}  // namespace rd3g
