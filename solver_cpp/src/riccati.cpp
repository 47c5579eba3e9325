#include "rd3g/riccati.hpp"

#include <algorithm>
#include <cmath>

namespace rd3g {

void StageRiccati::setup(int N, int T, int nx, int nu) {
  N_ = N; T_ = T; nx_ = nx; nu_ = nu; X_ = N * nx; U_ = N * nu;
  n_primal_ = T * N * (nu + 2 * nx);
  auto alloc = [&](std::vector<Eigen::MatrixXd>& v, int r, int c) { v.assign(T, Eigen::MatrixXd::Zero(r, c)); };
  alloc(Ruu_, U_, U_); alloc(Rux_, U_, X_); alloc(Rul_, U_, X_);
  alloc(Fx_, X_, X_); alloc(Fu_, X_, U_);
  alloc(Qxx_, X_, X_); alloc(Qxu_, X_, U_); alloc(Qxl_, X_, X_);
  alloc(P_, X_, X_); alloc(K_, U_, X_); alloc(W_, X_, U_);
  lu_.assign(T, Eigen::PartialPivLU<Eigen::MatrixXd>(U_));
  p_.assign(T + 1, Eigen::VectorXd::Zero(X_));
  kap_.assign(T, Eigen::VectorXd::Zero(U_));
  g_.resize(U_); u_.resize(U_);
  for (Eigen::VectorXd* v : {&e_, &h_, &pe_, &x_, &xn_, &lam_}) v->resize(X_);
  PFx_.resize(X_, X_);
  PFu_.resize(X_, U_);
  plan_.clear();  // its destinations were the old stage blocks
  const int ss = nu_ + 2 * nx_, stage = N_ * ss;
  slots_.resize(n_primal_);
  for (int g = 0; g < n_primal_; ++g) {
    const int rem = g % stage, i = rem / ss, loc = rem % ss;
    Slot& s = slots_[g];
    s.k = g / stage;
    s.agent = i;
    if (loc < nu_) { s.kind = 0; s.pos = i * nu_ + loc; }
    else if (loc < nu_ + nx_) { s.kind = 1; s.pos = i * nx_ + loc - nu_; }
    else { s.kind = 2; s.pos = i * nx_ + loc - nu_ - nx_; }
  }
}

namespace {
// out = A B for B block-diagonal with n blocks BR x bc: out's columns of block i are A's columns of block i times it.
// BR is fixed at compile time, so each entry's BR products are summed in one unrolled pass.
template <int BR>
void times_block_diagonal_sized(const Eigen::MatrixXd& A, const Eigen::MatrixXd& B, int n, int bc,
                                Eigen::MatrixXd& out) {
  const int R = static_cast<int>(A.rows());
  for (int i = 0; i < n; ++i) {
    const double* a[BR];
    for (int q = 0; q < BR; ++q) a[q] = A.col(i * BR + q).data();
    for (int c = i * bc; c < (i + 1) * bc; ++c) {
      double f[BR];
      for (int q = 0; q < BR; ++q) f[q] = B(i * BR + q, c);
      double* o = out.col(c).data();
      for (int r = 0; r < R; ++r) {
        double sum = 0.0;
        for (int q = 0; q < BR; ++q) sum += a[q][r] * f[q];
        o[r] = sum;
      }
    }
  }
}
}  // namespace

void StageRiccati::times_block_diagonal(const Eigen::MatrixXd& A, const Eigen::MatrixXd& B, int br, int bc,
                                        Eigen::MatrixXd& out) const {
  // out = A B, B block-diagonal with N blocks br x bc. Each entry sums its br products in order of q on both paths.
  if (br == 4) return times_block_diagonal_sized<4>(A, B, N_, bc, out);
  const int R = static_cast<int>(A.rows());
  for (int i = 0; i < N_; ++i)
    for (int c = i * bc; c < (i + 1) * bc; ++c) {
      double* o = out.col(c).data();
      for (int r = 0; r < R; ++r) o[r] = 0.0;
      for (int q = i * br; q < (i + 1) * br; ++q) {
        const double f = B(q, c);
        const double* a = A.col(q).data();
        for (int r = 0; r < R; ++r) o[r] += a[r] * f;
      }
    }
}

namespace {
// out += sign A C for A block-diagonal with n blocks ar x ac. AR, AC > 0 fix the block size at compile time so the
// short inner loops unroll (the kinematic bicycle's 4 x 4 and 2 x 4 blocks); the sums run in the same order either
// way, so the results are the same bits.
template <int AR, int AC>
void add_block_diagonal_times_sized(const Eigen::MatrixXd& A, const Eigen::Ref<const Eigen::MatrixXd>& C, int n,
                                    int ar_runtime, int ac_runtime, Eigen::Ref<Eigen::MatrixXd> out, double sign) {
  const int ar = AR > 0 ? AR : ar_runtime, ac = AC > 0 ? AC : ac_runtime;
  const int M = static_cast<int>(C.cols());
  for (int j = 0; j < M; ++j)
    for (int i = 0; i < n; ++i) {
      double* o = &out(i * ar, j);
      const double* c = C.col(j).data() + i * ac;
      for (int q = 0; q < ac; ++q) {
        const double f = sign * c[q];
        const double* a = &A(i * ar, i * ac + q);
        for (int r = 0; r < ar; ++r) o[r] += a[r] * f;
      }
    }
}
}  // namespace

void StageRiccati::add_block_diagonal_times(const Eigen::MatrixXd& A, const Eigen::Ref<const Eigen::MatrixXd>& C,
                                            int ar, int ac, Eigen::Ref<Eigen::MatrixXd> out, double sign) const {
  // out's rows of block i get A's block i times C's rows of block i.
  if (ar == 4 && ac == 4) add_block_diagonal_times_sized<4, 4>(A, C, N_, ar, ac, out, sign);
  else if (ar == 2 && ac == 4) add_block_diagonal_times_sized<2, 4>(A, C, N_, ar, ac, out, sign);
  else if (ar == 4 && ac == 2) add_block_diagonal_times_sized<4, 2>(A, C, N_, ar, ac, out, sign);
  else add_block_diagonal_times_sized<0, 0>(A, C, N_, ar, ac, out, sign);
}

void StageRiccati::stage_segment(const Eigen::Ref<const Eigen::VectorXd>& b, int k, int kind,
                                 Eigen::VectorXd& out) const {
  const int ss = nu_ + 2 * nx_, stage = N_ * ss;
  const int n = kind == 0 ? nu_ : nx_, off = kind == 0 ? 0 : kind == 1 ? nu_ : nu_ + nx_;
  for (int i = 0; i < N_; ++i) out.segment(i * n, n) = -b.segment(k * stage + i * ss + off, n);
}

bool StageRiccati::decode(int row, int col, double*& dest) {
  if (row >= n_primal_ || col >= n_primal_) {  // multiplier rows/columns: Schur complement
    dest = &discarded_;
    return true;
  }
  const Slot& r = slots_[row];
  const Slot& c = slots_[col];
  const int kr = r.k, rk = r.kind, pr = r.pos, kc = c.k, ck = c.kind, pc = c.pos;
  dest = nullptr;  // an entry of a -I block
  if (rk == 0) {  // u-stationarity rows of stage kr
    if (ck == 0 && kc == kr) dest = &Ruu_[kr](pr, pc);
    else if (ck == 2 && kc == kr - 1) dest = &Rux_[kr](pr, pc);
    else if (ck == 1 && kc == kr && r.agent == c.agent) dest = &Rul_[kr](pr, pc);
    else return false;
  } else if (rk == 1) {  // dynamics rows of stage kr
    if (r.agent != c.agent) return false;  // each agent's dynamics involve only its own state and controls
    if (ck == 2 && kc == kr - 1) dest = &Fx_[kr](pr, pc);
    else if (ck == 0 && kc == kr) dest = &Fu_[kr](pr, pc);
    else if (ck == 2 && kc == kr) return pr == pc;
    else return false;
  } else {  // x-stationarity rows of time kr+1
    if (ck == 2 && kc == kr) dest = &Qxx_[kr](pr, pc);
    else if (ck == 0 && kc == kr + 1) dest = &Qxu_[kr](pr, pc);
    else if (ck == 1 && kc == kr + 1 && r.agent == c.agent) dest = &Qxl_[kr](pr, pc);
    else if (ck == 1 && kc == kr) return pr == pc;
    else return false;
  }
  return true;
}

bool StageRiccati::scatter(const std::vector<Eigen::Triplet<double>>& trip) {
  // Fx, Fu, Rul and Qxl never receive an entry across agents (the scatter declines first): their off-diagonal blocks
  // stay zero from setup, and only the diagonal blocks are cleared.
  auto zero_diagonal_blocks = [&](Eigen::MatrixXd& m, int br, int bc) {
    for (int i = 0; i < N_; ++i) m.block(i * br, i * bc, br, bc).setZero();
  };
  for (int k = 0; k < T_; ++k) {
    Ruu_[k].setZero(); Rux_[k].setZero(); Qxx_[k].setZero(); Qxu_[k].setZero();
    zero_diagonal_blocks(Rul_[k], nu_, nx_); zero_diagonal_blocks(Fx_[k], nx_, nx_);
    zero_diagonal_blocks(Fu_[k], nx_, nu_); zero_diagonal_blocks(Qxl_[k], nx_, nx_);
  }
  // The triplets that match the plan's (row, col) go to the destinations found when they were last decoded; from the
  // first that does not, the rest are decoded and the plan is rewritten. The same sums in the same order either way.
  auto add = [](double* dest, double v) {  // false for a -I block entry that is not -1
    if (!dest) return v == -1.0;
    *dest += v;
    return true;
  };
  const size_t n = trip.size();
  const size_t planned = std::min(n, plan_.size());
  size_t j = 0;
  for (; j < planned; ++j) {
    const auto& t = trip[j];
    const PlannedEntry& e = plan_[j];
    if (e.row != t.row() || e.col != t.col()) break;
    if (!add(e.dest, t.value())) return false;
  }
  plan_.resize(j);
  for (; j < n; ++j) {
    const auto& t = trip[j];
    double* dest = nullptr;
    if (!decode(t.row(), t.col(), dest)) return false;
    plan_.push_back({t.row(), t.col(), dest});
    if (!add(dest, t.value())) return false;
  }
  return true;
}

bool StageRiccati::factor(const std::vector<Eigen::Triplet<double>>& trip) {
  if (!scatter(trip)) return false;
  // Terminal: -lambda_{T-1} + Qxx_T x_T = h_T  =>  lambda_{T-1} = Qxx_T x_T - h_T.
  P_[T_ - 1] = Qxx_[T_ - 1];
  for (int k = T_ - 1; k >= 0; --k) {
    // lambda_k = P x_{k+1} + p, with P = P_[k] (for x_{k+1}); x_{k+1} = Fx x_k + Fu u_k + e.
    // Fx, Fu, Rul and Qxl are block-diagonal by agent (checked in the scatter above): their products are taken
    // block by block, N times fewer flops than dense.
    const Eigen::MatrixXd& P = P_[k];
    times_block_diagonal(P, Fx_[k], nx_, nx_, PFx_);
    times_block_diagonal(P, Fu_[k], nx_, nu_, PFu_);
    G_ = Ruu_[k];
    add_block_diagonal_times(Rul_[k], PFu_, nu_, nx_, G_);
    lu_[k].compute(G_);
    const double det = lu_[k].determinant();
    if (!(std::abs(det) > 1e-300) || !std::isfinite(det)) return false;
    K_[k] = Rux_[k];
    add_block_diagonal_times(Rul_[k], PFx_, nu_, nx_, K_[k]);
    K_[k] = -lu_[k].solve(K_[k]);
    if (k == 0) break;
    // x-rows of time k: Qxx x_k + Qxu u_k + Qxl lambda_k - lambda_{k-1} = h_k (stored at index k-1).
    W_[k - 1] = Qxu_[k - 1];
    add_block_diagonal_times(Qxl_[k - 1], PFu_, nx_, nx_, W_[k - 1]);
    Pn_ = Qxx_[k - 1];
    add_block_diagonal_times(Qxl_[k - 1], PFx_, nx_, nx_, Pn_);
    Pn_.noalias() += W_[k - 1] * K_[k];
    P_[k - 1] = Pn_;
  }
  return true;
}

void StageRiccati::back_substitute(const Eigen::Ref<const Eigen::VectorXd>& b, Eigen::Ref<Eigen::VectorXd> out) {
  const int ss = nu_ + 2 * nx_, stage = N_ * ss;
  stage_segment(b, T_ - 1, 2, h_);
  p_[T_] = -h_;
  for (int k = T_ - 1; k >= 0; --k) {
    stage_segment(b, k, 0, g_);
    stage_segment(b, k, 1, e_);
    e_ = -e_;  // dynamics rows read Fx x + Fu u - x_{k+1} = -b_F, so x_{k+1} = Fx x + Fu u + b_F
    pe_ = p_[k + 1];
    pe_.noalias() += P_[k] * e_;
    add_block_diagonal_times(Rul_[k], pe_, nu_, nx_, g_, -1.0);
    kap_[k] = lu_[k].solve(g_);
    if (k == 0) break;
    stage_segment(b, k - 1, 2, h_);
    p_[k] = -h_;
    p_[k].noalias() += W_[k - 1] * kap_[k];
    add_block_diagonal_times(Qxl_[k - 1], pe_, nx_, nx_, p_[k]);
  }
  // Forward pass from dx_0 = 0.
  x_.setZero();
  for (int k = 0; k < T_; ++k) {
    u_ = kap_[k];
    u_.noalias() += K_[k] * x_;
    stage_segment(b, k, 1, e_);
    xn_ = -e_;
    add_block_diagonal_times(Fx_[k], x_, nx_, nx_, xn_);
    add_block_diagonal_times(Fu_[k], u_, nx_, nu_, xn_);
    lam_ = p_[k + 1];
    lam_.noalias() += P_[k] * xn_;
    for (int i = 0; i < N_; ++i) {
      out.segment(k * stage + i * ss, nu_) = u_.segment(i * nu_, nu_);
      out.segment(k * stage + i * ss + nu_, nx_) = lam_.segment(i * nx_, nx_);
      out.segment(k * stage + i * ss + nu_ + nx_, nx_) = xn_.segment(i * nx_, nx_);
    }
    x_ = xn_;
  }
}

bool StageRiccati::solve(const std::vector<Eigen::Triplet<double>>& trip, int n, const Eigen::VectorXd& rhs,
                         Eigen::VectorXd& dy) {
  if (!factor(trip)) return false;
  const int np = n_primal_, m = n - np;
  back_substitute(rhs.head(np), dy.head(np));  // a = -K^{-1} rhs_p
  if (m == 0) return dy.head(np).allFinite();
  // [K B; C D] [dp; dmu] = -[rhs_p; rhs_mu]:  (D - C K^{-1} B) dmu = -rhs_mu - C a,  dp = a - K^{-1} B dmu.
  Bm_.setZero(np, m);
  Cm_.setZero(m, np);
  S_.setZero(m, m);
  for (const auto& t : trip) {
    const bool pr = t.row() < np, pc = t.col() < np;
    if (pr && !pc) Bm_(t.row(), t.col() - np) += t.value();
    else if (!pr && pc) Cm_(t.row() - np, t.col()) += t.value();
    else if (!pr && !pc) S_(t.row() - np, t.col() - np) += t.value();
  }
  Z_.resize(np, m);
  for (int j = 0; j < m; ++j) back_substitute(Bm_.col(j), Z_.col(j));  // Z = -K^{-1} B
  S_.noalias() += Cm_ * Z_;
  rhs_mu_ = -rhs.segment(np, m);
  rhs_mu_.noalias() -= Cm_ * dy.head(np);
  slu_.compute(S_);
  const double det = slu_.determinant();
  if (!(std::abs(det) > 1e-300) || !std::isfinite(det)) return false;
  dy.segment(np, m) = slu_.solve(rhs_mu_);
  dy.head(np).noalias() += Z_ * dy.segment(np, m);
  return dy.head(n).allFinite();
}

}  // namespace rd3g
