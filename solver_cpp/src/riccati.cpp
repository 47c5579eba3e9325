#include "rd3g/riccati.hpp"

#include <cmath>

namespace rd3g {

void StageRiccati::setup(int N, int T, int nx, int nu) {
  N_ = N; T_ = T; nx_ = nx; nu_ = nu; X_ = N * nx; U_ = N * nu;
  auto alloc = [&](std::vector<Eigen::MatrixXd>& v, int r, int c) { v.assign(T, Eigen::MatrixXd::Zero(r, c)); };
  alloc(Ruu_, U_, U_); alloc(Rux_, U_, X_); alloc(Rul_, U_, X_);
  alloc(Fx_, X_, X_); alloc(Fu_, X_, U_);
  alloc(Qxx_, X_, X_); alloc(Qxu_, X_, U_); alloc(Qxl_, X_, X_);
  alloc(P_, X_, X_); alloc(K_, U_, X_);
  p_.assign(T + 1, Eigen::VectorXd::Zero(X_));
  kap_.assign(T, Eigen::VectorXd::Zero(U_));
}

bool StageRiccati::solve(const std::vector<Eigen::Triplet<double>>& trip, const Eigen::VectorXd& rhs, Eigen::VectorXd& dy) {
  const int ss = nu_ + 2 * nx_, stage = N_ * ss;
  for (int k = 0; k < T_; ++k) {
    Ruu_[k].setZero(); Rux_[k].setZero(); Rul_[k].setZero(); Fx_[k].setZero(); Fu_[k].setZero();
    Qxx_[k].setZero(); Qxu_[k].setZero(); Qxl_[k].setZero();
  }
  // Decode a global index into (stage k, kind 0=u 1=lambda 2=x_{k+1}, position in the stacked block).
  auto decode = [&](int g, int& k, int& kind, int& pos) {
    k = g / stage;
    const int rem = g % stage, i = rem / ss, loc = rem % ss;
    if (loc < nu_) { kind = 0; pos = i * nu_ + loc; }
    else if (loc < nu_ + nx_) { kind = 1; pos = i * nx_ + loc - nu_; }
    else { kind = 2; pos = i * nx_ + loc - nu_ - nx_; }
  };
  for (const auto& t : trip) {
    if (t.row() >= stage * T_ || t.col() >= stage * T_) return false;  // a multiplier row or column
    int kr, rk, pr, kc, ck, pc;
    decode(t.row(), kr, rk, pr);
    decode(t.col(), kc, ck, pc);
    const double v = t.value();
    if (rk == 0) {  // u-stationarity rows of stage kr
      if (ck == 0 && kc == kr) Ruu_[kr](pr, pc) += v;
      else if (ck == 2 && kc == kr - 1) Rux_[kr](pr, pc) += v;
      else if (ck == 1 && kc == kr) Rul_[kr](pr, pc) += v;
      else return false;
    } else if (rk == 1) {  // dynamics rows of stage kr
      if (ck == 2 && kc == kr - 1) Fx_[kr](pr, pc) += v;
      else if (ck == 0 && kc == kr) Fu_[kr](pr, pc) += v;
      else if (ck == 2 && kc == kr) { if (pr != pc || v != -1.0) return false; }
      else return false;
    } else {  // x-stationarity rows of time kr+1
      if (ck == 2 && kc == kr) Qxx_[kr](pr, pc) += v;
      else if (ck == 0 && kc == kr + 1) Qxu_[kr](pr, pc) += v;
      else if (ck == 1 && kc == kr + 1) Qxl_[kr](pr, pc) += v;
      else if (ck == 1 && kc == kr) { if (pr != pc || v != -1.0) return false; }
      else return false;
    }
  }
  // Right-hand sides of J dy = -rhs, stacked per stage.
  auto seg = [&](int k, int kind, Eigen::VectorXd& out) {
    const int n = kind == 0 ? nu_ : nx_, off = kind == 0 ? 0 : kind == 1 ? nu_ : nu_ + nx_;
    out.resize(N_ * n);
    for (int i = 0; i < N_; ++i) out.segment(i * n, n) = -rhs.segment(k * stage + i * ss + off, n);
  };
  Eigen::VectorXd g, e, h;
  // Terminal: -lambda_{T-1} + Qxx_T x_T = h_T  =>  lambda_{T-1} = Qxx_T x_T - h_T.
  seg(T_ - 1, 2, h);
  Eigen::MatrixXd P = Qxx_[T_ - 1];
  Eigen::VectorXd p = -h;
  P_[T_ - 1] = P;
  p_[T_] = p;
  Eigen::MatrixXd G, PFx, PFu, W;
  for (int k = T_ - 1; k >= 0; --k) {
    // lambda_k = P x_{k+1} + p, with P = P_[k] (for x_{k+1}); x_{k+1} = Fx x_k + Fu u_k + e.
    seg(k, 0, g);
    seg(k, 1, e);
    e = -e;  // dynamics rows read Fx x + Fu u - x_{k+1} = -rhs_F, so x_{k+1} = Fx x + Fu u + rhs_F
    PFx.noalias() = P * Fx_[k];
    PFu.noalias() = P * Fu_[k];
    G = Ruu_[k];
    G.noalias() += Rul_[k] * PFu;
    Eigen::PartialPivLU<Eigen::MatrixXd> lu(G);
    if (!(std::abs(lu.determinant()) > 1e-300) || !std::isfinite(lu.determinant())) return false;
    const Eigen::VectorXd Pe_p = P * e + p;
    kap_[k] = lu.solve(g - Rul_[k] * Pe_p);
    K_[k] = -lu.solve(Rux_[k] + Rul_[k] * PFx);
    if (k == 0) break;
    // x-rows of time k: Qxx x_k + Qxu u_k + Qxl lambda_k - lambda_{k-1} = h_k (stored at index k-1).
    seg(k - 1, 2, h);
    W = Qxu_[k - 1];
    W.noalias() += Qxl_[k - 1] * PFu;
    Eigen::MatrixXd Pn = Qxx_[k - 1];
    Pn.noalias() += Qxl_[k - 1] * PFx;
    Pn.noalias() += W * K_[k];
    p = W * kap_[k] + Qxl_[k - 1] * Pe_p - h;
    P = std::move(Pn);
    P_[k - 1] = P;
    p_[k] = p;
  }
  // Forward pass from dx_0 = 0.
  Eigen::VectorXd x = Eigen::VectorXd::Zero(X_), u, xn, lam;
  for (int k = 0; k < T_; ++k) {
    u = K_[k] * x + kap_[k];
    seg(k, 1, e);
    xn = Fx_[k] * x + Fu_[k] * u - e;
    lam = P_[k] * xn + p_[k + 1];
    for (int i = 0; i < N_; ++i) {
      dy.segment(k * stage + i * ss, nu_) = u.segment(i * nu_, nu_);
      dy.segment(k * stage + i * ss + nu_, nx_) = lam.segment(i * nx_, nx_);
      dy.segment(k * stage + i * ss + nu_ + nx_, nx_) = xn.segment(i * nx_, nx_);
    }
    x = xn;
  }
  return dy.head(stage * T_).allFinite();
}

}  // namespace rd3g
