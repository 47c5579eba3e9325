// J'J for a sequence of matrices J with one sparsity pattern: the Levenberg-Marquardt matrix of successive
// iterations while the constraint partition (J's pattern) is unchanged.
//
// The first J of a pattern is multiplied by Eigen (J'J + 0 I, so that every diagonal entry is stored), and for each
// entry of the lower triangle the pairs of J's entries whose products sum to it are kept. For a later J of the same
// pattern, only the lower triangle's values are recomputed, from the pairs, summed in the order Eigen's product
// sums them (J's rows ascending), so they equal a fresh product's bit for bit; the upper triangle keeps the first
// product's values (the LDLT reads the lower triangle only). This skips the product's allocation and symbolic work.
#pragma once
#include <Eigen/Sparse>
#include <vector>

#include "rd3g/sparsity_pattern.hpp"

namespace rd3g {

class NormalMatrix {
 public:
  using SpMat = Eigen::SparseMatrix<double>;
  /// A = J'J (J compressed). Returns true if J had the pattern of the previous call: then A kept its pattern and
  /// only its lower triangle was updated; false if A was formed afresh (its pattern may have changed).
  bool compute(const SpMat& J, SpMat& A);

 private:
  void plan(const SpMat& J, const SpMat& A);
  SparsityPattern pattern_;         // J's pattern of the last call
  std::vector<int> start_;          // per stored entry p of A: its pairs are [start_[p], start_[p + 1])
  std::vector<int> lhs_, rhs_;      // per pair: the value indices in J of J(k, i) and J(k, j)
};

}  // namespace rd3g
