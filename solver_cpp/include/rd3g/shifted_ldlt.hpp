// Sparse LDLT of A + shift I for a sequence of matrices A with one sparsity pattern (the Levenberg-Marquardt
// tries: J'J + nu I for several nu per iteration, and J'J keeps its pattern while the constraint partition does).
// Eigen's SimplicialLDLT with three costs taken out of the repeated numeric factorisation: the ordering and the
// elimination tree are computed once per pattern (analyze), the symmetric permutation P A P' is a value copy
// through a precomputed index map (no allocation), and the shift is Eigen's own setShift, i.e. d_kk = a_kk + shift
// inside the factorisation. The arithmetic is Eigen's factorize() on the same permuted matrix, so the factors
// are bit for bit those of SimplicialLDLT::compute(A + shift I) when A stores its whole diagonal.
#pragma once
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <vector>

namespace rd3g {

class ShiftedLDLT : public Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Lower> {
 public:
  using SpMat = Eigen::SparseMatrix<double>;
  /// Ordering (AMD) and symbolic factorisation of A's pattern (A compressed, lower triangle used, every
  /// diagonal entry stored). False if the analysis failed.
  bool analyze(const SpMat& A) {
    analyzePattern(A);
    if (info() != Eigen::Success) return false;
    // Permute a copy whose values are the entry indices: where each stored entry of A lands in P A P'.
    // The copy has exactly the layout factorize() would build, so the factorisation visits entries in
    // the same order.
    SpMat idx = A;
    for (Eigen::Index p = 0; p < idx.nonZeros(); ++p) idx.valuePtr()[p] = static_cast<double>(p);
    ap_.resize(A.rows(), A.cols());
    ap_.selfadjointView<Eigen::Upper>() = idx.selfadjointView<Eigen::Lower>().twistedBy(m_P);
    map_.resize(ap_.nonZeros());
    for (Eigen::Index q = 0; q < ap_.nonZeros(); ++q) map_[q] = static_cast<int>(ap_.valuePtr()[q]);
    outer_.assign(A.outerIndexPtr(), A.outerIndexPtr() + A.outerSize() + 1);
    inner_.assign(A.innerIndexPtr(), A.innerIndexPtr() + A.nonZeros());
    return true;
  }
  /// True if A (compressed) has exactly the pattern of the last analyze(): then load() and factorize_shifted()
  /// may be used on it. O(nnz), against the O(nnz(L) * column length) of a factorisation.
  bool same_pattern(const SpMat& A) const {
    return A.isCompressed() && A.outerSize() + 1 == static_cast<Eigen::Index>(outer_.size()) &&
           A.nonZeros() == static_cast<Eigen::Index>(inner_.size()) &&
           std::equal(outer_.begin(), outer_.end(), A.outerIndexPtr()) &&
           std::equal(inner_.begin(), inner_.end(), A.innerIndexPtr());
  }
  /// Loads the values of A (the analysed pattern, see same_pattern) into the permuted copy; once per A.
  void load(const SpMat& A) {
    const double* a = A.valuePtr();
    double* v = ap_.valuePtr();
    for (size_t q = 0; q < map_.size(); ++q) v[q] = a[map_[q]];
  }
  /// Numeric LDLT of (the loaded A) + shift I. False on a zero pivot.
  bool factorize_shifted(double shift) {
    setShift(shift);
    factorize_preordered<true>(ap_);
    return info() == Eigen::Success;
  }

 private:
  SpMat ap_;              // P A P', upper triangle, as factorize() would build it
  std::vector<int> map_;  // entry q of ap_ is entry map_[q] of A
  std::vector<int> outer_, inner_;  // the analysed pattern
};

}  // namespace rd3g
