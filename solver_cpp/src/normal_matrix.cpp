#include "rd3g/normal_matrix.hpp"

namespace rd3g {

bool NormalMatrix::compute(const SpMat& J, SpMat& A) {
  if (!pattern_.matches(J)) {
    A = J.transpose() * J;
    SpMat eye(J.cols(), J.cols());
    eye.setIdentity();
    A = A + 0.0 * eye;  // every diagonal entry stored: a shift lands on stored entries
    A.makeCompressed();
    pattern_.assign(J);
    plan(J, A);
    return false;
  }
  const double* v = J.valuePtr();
  double* a = A.valuePtr();
  const Eigen::Index nnz = A.nonZeros();
  for (Eigen::Index p = 0; p < nnz; ++p) {
    const int q0 = start_[p], q1 = start_[p + 1];
    if (q0 == q1) continue;  // upper triangle (kept), or a diagonal entry no row of J reaches (0)
    double s = 0.0;
    for (int q = q0; q < q1; ++q) s += v[lhs_[q]] * v[rhs_[q]];
    a[p] = s + 0.0;  // as Eigen's J'J + 0 I: a -0 sum is stored as +0
  }
  return true;
}

void NormalMatrix::plan(const SpMat& J, const SpMat& A) {
  const int m = static_cast<int>(J.rows()), n = static_cast<int>(J.cols());
  const int* jo = J.outerIndexPtr();
  const int* ji = J.innerIndexPtr();
  // J by rows: row k's entries (column, value index), columns ascending.
  std::vector<int> rptr(m + 1, 0), rcol(J.nonZeros()), rval(J.nonZeros());
  for (int p = 0; p < jo[n]; ++p) ++rptr[ji[p] + 1];
  for (int k = 0; k < m; ++k) rptr[k + 1] += rptr[k];
  std::vector<int> next(rptr.begin(), rptr.end() - 1);
  for (int i = 0; i < n; ++i)
    for (int p = jo[i]; p < jo[i + 1]; ++p) {
      const int s = next[ji[p]]++;
      rcol[s] = i;
      rval[s] = p;
    }
  // Entry (i, j), i >= j, of J'J sums J(k, i) J(k, j) over the rows k of column j, ascending (Eigen's order).
  const int* ao = A.outerIndexPtr();
  const int* ai = A.innerIndexPtr();
  std::vector<int> pos(n, -1);
  start_.assign(A.nonZeros() + 1, 0);
  std::vector<int> fill;
  for (int pass = 0; pass < 2; ++pass) {
    for (int j = 0; j < n; ++j) {
      for (int p = ao[j]; p < ao[j + 1]; ++p) pos[ai[p]] = p;
      for (int q = jo[j]; q < jo[j + 1]; ++q) {
        const int k = ji[q];
        for (int s = rptr[k]; s < rptr[k + 1]; ++s) {
          if (rcol[s] < j) continue;
          const int p = pos[rcol[s]];
          if (pass == 0) {
            ++start_[p + 1];
          } else {
            const int at = fill[p]++;
            lhs_[at] = rval[s];
            rhs_[at] = q;
          }
        }
      }
    }
    if (pass == 0) {
      for (Eigen::Index p = 0; p < A.nonZeros(); ++p) start_[p + 1] += start_[p];
      fill.assign(start_.begin(), start_.end() - 1);
      lhs_.resize(start_.back());
      rhs_.resize(start_.back());
    }
  }
}

}  // namespace rd3g
