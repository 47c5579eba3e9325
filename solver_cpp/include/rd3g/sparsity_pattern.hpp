// The sparsity pattern of a compressed column-major matrix, kept to tell whether a later matrix has the same one
// (then work that depends only on the pattern, such as an ordering or a product plan, can be reused).
#pragma once
#include <Eigen/Sparse>
#include <algorithm>
#include <vector>

namespace rd3g {

struct SparsityPattern {
  std::vector<int> outer, inner;  // column starts (cols + 1) and row indices, as Eigen stores them

  void assign(const Eigen::SparseMatrix<double>& A) {
    outer.assign(A.outerIndexPtr(), A.outerIndexPtr() + A.outerSize() + 1);
    inner.assign(A.innerIndexPtr(), A.innerIndexPtr() + A.nonZeros());
  }
  /// True if A is compressed and has exactly this pattern. O(nnz).
  bool matches(const Eigen::SparseMatrix<double>& A) const {
    return A.isCompressed() && outer.size() == static_cast<size_t>(A.outerSize() + 1) &&
           inner.size() == static_cast<size_t>(A.nonZeros()) &&
           std::equal(outer.begin(), outer.end(), A.outerIndexPtr()) &&
           std::equal(inner.begin(), inner.end(), A.innerIndexPtr());
  }
};

}  // namespace rd3g
