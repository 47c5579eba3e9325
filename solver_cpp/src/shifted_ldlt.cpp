#include "rd3g/shifted_ldlt.hpp"

#include <Eigen/OrderingMethods>
#include <algorithm>
#include <numeric>

namespace rd3g {

namespace {
// Where the loader can choose an implementation by CPU (GCC/Clang on x86-64 Linux: ifunc), this kernel is also
// compiled for AVX2 (4 doubles per instruction instead of SSE2's 2) and the faster one runs. AVX2 without FMA: every
// element is computed with the same operations in the same order, so both give the same bits.
#if defined(__x86_64__) && defined(__linux__) && (defined(__GNUC__) || defined(__clang__))
#define RD3G_AVX2_CLONE __attribute__((target_clones("avx2", "default")))
#else
#define RD3G_AVX2_CLONE
#endif

// acc[a] += sum_k L[k ld + a] L[k ld] D[k], a < len, k < w: the columns of a panel (L points at the first row used,
// ld is the panel's height) weighted by their entries in that first row and D. Four columns per pass over acc.
RD3G_AVX2_CLONE void axpy_columns(const double* L, int ld, const double* D, int w, int len, double* acc) {
  int k = 0;
  for (; k + 4 <= w; k += 4) {
    const double* L0 = L + static_cast<long>(k) * ld;
    const double *L1 = L0 + ld, *L2 = L1 + ld, *L3 = L2 + ld;
    const double c0 = L0[0] * D[k], c1 = L1[0] * D[k + 1], c2 = L2[0] * D[k + 2], c3 = L3[0] * D[k + 3];
    for (int a = 0; a < len; ++a) acc[a] += (L0[a] * c0 + L1[a] * c1) + (L2[a] * c2 + L3[a] * c3);
  }
  for (; k < w; ++k) {
    const double* Lk = L + static_cast<long>(k) * ld;
    const double c = Lk[0] * D[k];
    for (int a = 0; a < len; ++a) acc[a] += Lk[a] * c;
  }
}

// Elimination tree of the ordered matrix, given for each column k the columns c < k with B(k, c) != 0 (row k of the
// lower triangle): Liu's algorithm with path compression.
void elimination_tree(int n, const std::vector<int>& uptr, const std::vector<int>& ucol, std::vector<int>& parent) {
  std::vector<int> ancestor(n, -1);
  parent.assign(n, -1);
  for (int k = 0; k < n; ++k)
    for (int q = uptr[k]; q < uptr[k + 1]; ++q)
      for (int i = ucol[q]; i != -1 && i < k;) {
        const int up = ancestor[i];
        ancestor[i] = k;
        if (up == -1) parent[i] = k;
        i = up;
      }
}
}  // namespace

bool ShiftedLDLT::analyze(const SpMat& A) {
  if (A.rows() != A.cols()) return false;
  n_ = static_cast<int>(A.rows());
  pattern_.assign(A);
  order(A);
  permute_lower();
  std::vector<int> parent, count, lptr, lrow;
  symbolic(parent, count, lptr, lrow);
  make_supernodes(parent, count, lptr, lrow);
  return true;
}

void ShiftedLDLT::order(const SpMat& A) {
  // The ordering Eigen's SimplicialLDLT uses: AMD on the symmetric pattern, P = its inverse.
  Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, int> pinv;
  {
    SpMat C;
    C = A.selfadjointView<Eigen::Lower>();
    Eigen::AMDOrdering<int> amd;
    amd(C, pinv);
  }
  new_of_old_.resize(n_);
  if (pinv.size() == n_) {
    for (int i = 0; i < n_; ++i) new_of_old_[pinv.indices()[i]] = i;
  } else {
    std::iota(new_of_old_.begin(), new_of_old_.end(), 0);
  }
}

void ShiftedLDLT::permute_lower() {
  // Lower triangle of P A P' by columns, rows ascending, with the index of each value in A.
  const int n = n_;
  bptr_.assign(n + 1, 0);
  for (int j = 0; j < n; ++j)
    for (int p = pattern_.outer[j]; p < pattern_.outer[j + 1]; ++p)
      if (pattern_.inner[p] >= j) ++bptr_[std::min(new_of_old_[pattern_.inner[p]], new_of_old_[j]) + 1];
  for (int j = 0; j < n; ++j) bptr_[j + 1] += bptr_[j];
  brow_.resize(bptr_[n]);
  map_.resize(bptr_[n]);
  bval_.assign(bptr_[n], 0.0);
  std::vector<int> fill(bptr_.begin(), bptr_.end() - 1);
  for (int j = 0; j < n; ++j)
    for (int p = pattern_.outer[j]; p < pattern_.outer[j + 1]; ++p) {
      if (pattern_.inner[p] < j) continue;
      const int a = new_of_old_[pattern_.inner[p]], b = new_of_old_[j];
      const int at = fill[std::min(a, b)]++;
      brow_[at] = std::max(a, b);
      map_[at] = p;
    }
  std::vector<std::pair<int, int>> col;
  for (int c = 0; c < n; ++c) {
    col.clear();
    for (int q = bptr_[c]; q < bptr_[c + 1]; ++q) col.emplace_back(brow_[q], map_[q]);
    std::sort(col.begin(), col.end());
    for (int q = bptr_[c]; q < bptr_[c + 1]; ++q) std::tie(brow_[q], map_[q]) = col[q - bptr_[c]];
  }
}

void ShiftedLDLT::symbolic(std::vector<int>& parent, std::vector<int>& count, std::vector<int>& lptr,
                           std::vector<int>& lrow) const {
  const int n = n_;
  // Rows of the lower triangle (for each k, the columns c < k with B(k, c) != 0).
  std::vector<int> uptr(n + 1, 0), ucol;
  for (int c = 0; c < n; ++c)
    for (int q = bptr_[c]; q < bptr_[c + 1]; ++q)
      if (brow_[q] > c) ++uptr[brow_[q] + 1];
  for (int k = 0; k < n; ++k) uptr[k + 1] += uptr[k];
  ucol.resize(uptr[n]);
  {
    std::vector<int> fill(uptr.begin(), uptr.end() - 1);
    for (int c = 0; c < n; ++c)
      for (int q = bptr_[c]; q < bptr_[c + 1]; ++q)
        if (brow_[q] > c) ucol[fill[brow_[q]]++] = c;
  }
  elimination_tree(n, uptr, ucol, parent);
  // Pattern of L by columns: row k of L is the union of the tree paths from each c in row k of B up to k.
  count.assign(n, 0);
  std::vector<int> mark(n, -1);
  auto for_row = [&](int k, auto&& visit) {
    mark[k] = k;
    for (int q = uptr[k]; q < uptr[k + 1]; ++q)
      for (int i = ucol[q]; mark[i] != k; i = parent[i]) {
        mark[i] = k;
        visit(i);
      }
  };
  for (int k = 0; k < n; ++k) for_row(k, [&](int i) { ++count[i]; });
  lptr.assign(n + 1, 0);
  for (int j = 0; j < n; ++j) lptr[j + 1] = lptr[j] + count[j];
  lrow.resize(lptr[n]);
  std::vector<int> fill(lptr.begin(), lptr.end() - 1);
  std::fill(mark.begin(), mark.end(), -1);
  for (int k = 0; k < n; ++k) for_row(k, [&](int i) { lrow[fill[i]++] = k; });  // rows ascending per column
}

void ShiftedLDLT::make_supernodes(const std::vector<int>& parent, const std::vector<int>& count,
                                  const std::vector<int>& lptr, const std::vector<int>& lrow) {
  // Column j + 1 continues j's supernode when it is j's parent and L(:, j) below j + 1 is L(:, j + 1).
  const int n = n_;
  sn_first_.assign(1, 0);
  for (int j = 1; j < n; ++j)
    if (!(parent[j - 1] == j && count[j - 1] == count[j] + 1)) sn_first_.push_back(j);
  sn_first_.push_back(n);
  const int S = static_cast<int>(sn_first_.size()) - 1;
  sn_of_.resize(n);
  rptr_.assign(S + 1, 0);
  vptr_.assign(S + 1, 0);
  rows_.clear();
  int max_rows = 0;
  for (int s = 0; s < S; ++s) {
    const int f = sn_first_[s], l = sn_first_[s + 1] - 1, w = l - f + 1;
    for (int j = f; j <= l; ++j) sn_of_[j] = s;
    for (int j = f; j <= l; ++j) rows_.push_back(j);
    rows_.insert(rows_.end(), lrow.begin() + lptr[l], lrow.begin() + lptr[l + 1]);
    rptr_[s + 1] = static_cast<int>(rows_.size());
    vptr_[s + 1] = vptr_[s] + static_cast<long>(rptr_[s + 1] - rptr_[s]) * w;
    max_rows = std::max(max_rows, rptr_[s + 1] - rptr_[s]);
  }
  lx_.assign(vptr_[S], 0.0);
  d_.assign(n, 0.0);
  pos_.assign(n, 0);
  head_.assign(S, -1);
  link_.assign(S, -1);
  next_.assign(S, 0);
  acc_.assign(max_rows, 0.0);
  y_.assign(n, 0.0);
}

bool ShiftedLDLT::same_pattern(const SpMat& A) const { return pattern_.matches(A); }

void ShiftedLDLT::load(const SpMat& A) {
  const double* a = A.valuePtr();
  for (size_t q = 0; q < map_.size(); ++q) bval_[q] = a[map_[q]];
}

bool ShiftedLDLT::factorize_shifted(double shift) {
  const int S = supernodes();
  if (S < 0) return false;
  std::fill(lx_.begin(), lx_.end(), 0.0);
  std::fill(head_.begin(), head_.end(), -1);
  for (int s = 0; s < S; ++s) {
    const int f = sn_first_[s], w = sn_first_[s + 1] - f;
    const int* R = rows_.data() + rptr_[s];
    const int m = rptr_[s + 1] - rptr_[s];
    double* F = lx_.data() + vptr_[s];
    for (int a = 0; a < m; ++a) pos_[R[a]] = a;
    // A's columns of this supernode (lower triangle, its rows are in R by construction).
    for (int c = 0; c < w; ++c) {
      double* Fc = F + static_cast<long>(c) * m;
      for (int q = bptr_[f + c]; q < bptr_[f + c + 1]; ++q) Fc[pos_[brow_[q]]] += bval_[q];
      Fc[c] += shift;
    }
    update_panel(s);
    if (!factor_panel(s)) return false;
    if (w < m) {  // s updates the supernode of its first row below its own columns next
      next_[s] = w;
      const int t = sn_of_[R[w]];
      link_[s] = head_[t];
      head_[t] = s;
    }
  }
  return true;
}

void ShiftedLDLT::update_panel(int s) {
  // Updates from every supernode d whose rows reach columns f..f+w-1 of s: rows [p1, p2) of d are in them. pos_
  // holds the positions of s's rows.
  const int f = sn_first_[s], w = sn_first_[s + 1] - f;
  const int m = rptr_[s + 1] - rptr_[s];
  double* F = lx_.data() + vptr_[s];
  for (int d = head_[s]; d != -1;) {
    const int next_d = link_[d];
    const int fd = sn_first_[d], wd = sn_first_[d + 1] - fd;
    const int* Rd = rows_.data() + rptr_[d];
    const int md = rptr_[d + 1] - rptr_[d];
    const double* L = lx_.data() + vptr_[d];
    const double* D = d_.data() + fd;
    const int p1 = next_[d];
    int p2 = p1;
    while (p2 < md && Rd[p2] < f + w) ++p2;
    for (int b = p1; b < p2; ++b) {
      // acc = L(b.., :) D L(b, :)' over rows b..md-1 of d, subtracted from column Rd[b] - f of F.
      const int len = md - b;
      double* acc = acc_.data();
      std::fill(acc, acc + len, 0.0);
      axpy_columns(L + b, md, D, wd, len, acc);
      double* Fc = F + static_cast<long>(Rd[b] - f) * m;
      for (int a = 0; a < len; ++a) Fc[pos_[Rd[b + a]]] -= acc[a];
    }
    next_[d] = p2;
    if (p2 < md) {  // d updates the supernode of its next row later
      const int t = sn_of_[Rd[p2]];
      link_[d] = head_[t];
      head_[t] = d;
    }
    d = next_d;
  }
}

bool ShiftedLDLT::factor_panel(int s) {
  // Dense LDL' of the panel, column by column (left-looking within it); false on a zero pivot.
  const int f = sn_first_[s], w = sn_first_[s + 1] - f;
  const int m = rptr_[s + 1] - rptr_[s];
  double* F = lx_.data() + vptr_[s];
  for (int c = 0; c < w; ++c) {
    double* Fc = F + static_cast<long>(c) * m;
    std::fill(acc_.begin(), acc_.begin() + (m - c), 0.0);
    axpy_columns(F + c, m, d_.data() + f, c, m - c, acc_.data());
    for (int a = c; a < m; ++a) Fc[a] -= acc_[a - c];
    const double dc = Fc[c];
    if (dc == 0.0) return false;
    d_[f + c] = dc;
    const double inv = 1.0 / dc;
    for (int a = c + 1; a < m; ++a) Fc[a] *= inv;
  }
  return true;
}

void ShiftedLDLT::solve(const Eigen::Ref<const Eigen::VectorXd>& b, Eigen::Ref<Eigen::VectorXd> x) const {
  const int S = supernodes();
  double* y = y_.data();
  for (int i = 0; i < n_; ++i) y[new_of_old_[i]] = b[i];
  for (int s = 0; s < S; ++s) {  // L y = P b
    const int f = sn_first_[s], w = sn_first_[s + 1] - f;
    const int* R = rows_.data() + rptr_[s];
    const int m = rptr_[s + 1] - rptr_[s];
    const double* F = lx_.data() + vptr_[s];
    for (int c = 0; c < w; ++c) {
      const double yc = y[f + c];
      const double* Fc = F + static_cast<long>(c) * m;
      for (int a = c + 1; a < m; ++a) y[R[a]] -= Fc[a] * yc;
    }
  }
  for (int j = 0; j < n_; ++j) y[j] /= d_[j];
  for (int s = S - 1; s >= 0; --s) {  // L' z = y
    const int f = sn_first_[s], w = sn_first_[s + 1] - f;
    const int* R = rows_.data() + rptr_[s];
    const int m = rptr_[s + 1] - rptr_[s];
    const double* F = lx_.data() + vptr_[s];
    for (int c = w - 1; c >= 0; --c) {
      const double* Fc = F + static_cast<long>(c) * m;
      double sum = y[f + c];
      for (int a = c + 1; a < m; ++a) sum -= Fc[a] * y[R[a]];
      y[f + c] = sum;
    }
  }
  for (int i = 0; i < n_; ++i) x[i] = y[new_of_old_[i]];
}

}  // namespace rd3g
