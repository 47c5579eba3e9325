#include "rd3g/stage_terms.hpp"

namespace rd3g {

void StageWorkspace::resize(int nx, int nu) {
  A = Mat::Zero(nx, nx);
  B = Mat::Zero(nx, nu);
  Hl = Mat::Zero(nx + nu, nx + nu);
  Huu = Mat::Zero(nu, nu);
  fx = Vec::Zero(nx);
  Btl = Vec::Zero(nu);
  Atl = Vec::Zero(nx);
  gu = Vec::Zero(nu);
  gx = Vec::Zero(nx);
}

namespace {
StagePattern::Entries entries_of(const Pattern& m, bool transposed) {
  StagePattern::Entries e;
  const int rows = static_cast<int>(transposed ? m.cols() : m.rows());
  const int cols = static_cast<int>(transposed ? m.rows() : m.cols());
  for (int r = 0; r < rows; ++r)
    for (int c = 0; c < cols; ++c)
      if (transposed ? m(c, r) : m(r, c)) e.push_back({r, c});
  return e;
}
}  // namespace

StagePattern::StagePattern(const Dynamics& f) {
  const int nx = f.nx(), nu = f.nu();
  Pattern a, b, h;
  f.derivative_pattern(a, b, h);
  Pattern huu = h.bottomRightCorner(nu, nu);
  huu.diagonal().setConstant(true);
  Huu = entries_of(huu, false);
  Bt = entries_of(b, true);
  B = entries_of(b, false);
  Hux = entries_of(h.bottomLeftCorner(nu, nx), false);
  Hxu = entries_of(h.topRightCorner(nx, nu), false);
  Hxx = entries_of(h.topLeftCorner(nx, nx), false);
  At = entries_of(a, true);
  A = entries_of(a, false);
}

bool StagePattern::same_as(const StagePattern& o) const {
  return Huu == o.Huu && Bt == o.Bt && B == o.B && Hux == o.Hux && Hxu == o.Hxu && Hxx == o.Hxx && At == o.At &&
         A == o.A;
}

std::vector<StagePattern> stage_patterns(const std::vector<std::shared_ptr<const Dynamics>>& dynamics) {
  std::vector<StagePattern> out;
  for (const auto& f : dynamics) out.emplace_back(*f);
  return out;
}

void control_cost_gradient(const QuadraticCost& cost, const Eigen::Ref<const Vec>& u_k, Eigen::Ref<Vec> g) {
  g = control_cost_hessian(cost).cwiseProduct(u_k);
}

void state_cost_gradient(const QuadraticCost& cost, int k, int T, const Eigen::Ref<const Vec>& x_k, Eigen::Ref<Vec> g) {
  const bool terminal = (k == T);
  const Vec& qr = terminal ? cost.Qf_ref : cost.Q_ref;
  const Vec& q = terminal ? cost.Qf : cost.Q;
  g = 2.0 * (qr.cwiseProduct(x_k - cost.reference(k)) + q.cwiseProduct(x_k));
}

void add_stage_terms(const StageLayout& L, int i, int k, int T, const Dynamics& f, const StagePattern& pattern,
                     const QuadraticCost& cost, const LeadCost& lead, const Mat& x, const Mat& u,
                     const Eigen::Ref<const Vec>& lk, Vec& r, std::vector<Eigen::Triplet<double>>* trip,
                     StageWorkspace& w) {
  const int nx = L.nx, nu = L.nu;
  const int ru = L.col_u(i, k), rf = L.col_lam(i, k), rx1 = L.col_x(i, k + 1);
  if (trip) f.eval_with_hessian(x.col(k), u.col(k), lk, w.fx, w.A, w.B, w.Hl);
  else f.eval(x.col(k), u.col(k), w.fx, w.A, w.B);
  control_cost_gradient(cost, u.col(k), w.gu);
  state_cost_gradient(cost, k + 1, T, x.col(k + 1), w.gx);
  // dL/du_k = 2 R u_k + B' lambda_k
  w.Btl.noalias() = w.B.transpose() * lk;
  r.segment(ru, nu) = w.gu + w.Btl;
  // F_k = f(x_k, u_k) - x_{k+1}
  r.segment(rf, nx) = w.fx - x.col(k + 1);
  // dL/dx_{k+1}: cost gradient - lambda_k (+ A_{k+1}' lambda_{k+1}, added at stage k+1)
  r.segment(rx1, nx) += w.gx - lk;
  if (const double g = lead_gradient(lead, L.N); g != 0.0) r[rx1 + lead.index] += g;
  if (k >= 1) {
    w.Atl.noalias() = w.A.transpose() * lk;
    r.segment(L.col_x(i, k), nx) += w.Atl;
  }
  if (!trip) return;

  auto add_entries = [&](int r0, int c0, const auto& M, const StagePattern::Entries& entries) {
    for (const auto& e : entries) trip->emplace_back(r0 + e[0], c0 + e[1], M(e[0], e[1]));
  };
  auto add_neg_identity = [&](int r0, int c0, int n) {
    for (int a = 0; a < n; ++a) trip->emplace_back(r0 + a, c0 + a, -1.0);
  };
  // rows dL/du_k
  w.Huu = w.Hl.bottomRightCorner(nu, nu);
  w.Huu.diagonal() += control_cost_hessian(cost);
  add_entries(ru, ru, w.Huu, pattern.Huu);
  add_entries(ru, rf, w.B.transpose(), pattern.Bt);
  // rows F_k
  add_entries(rf, ru, w.B, pattern.B);
  add_neg_identity(rf, rx1, nx);
  // rows dL/dx_{k+1}
  add_neg_identity(rx1, rf, nx);
  const auto state_hessian = state_cost_hessian(cost, k + 1, T);  // the cost's Hessian in x_{k+1}: a diagonal
  for (int a = 0; a < nx; ++a) trip->emplace_back(rx1 + a, rx1 + a, state_hessian[a]);
  if (k >= 1) {
    const int rxk = L.col_x(i, k);
    add_entries(ru, rxk, w.Hl.bottomLeftCorner(nu, nx), pattern.Hux);
    add_entries(rxk, ru, w.Hl.topRightCorner(nx, nu), pattern.Hxu);
    add_entries(rxk, rxk, w.Hl.topLeftCorner(nx, nx), pattern.Hxx);
    add_entries(rxk, rf, w.A.transpose(), pattern.At);
    add_entries(rf, rxk, w.A, pattern.A);
  }
}

}  // namespace rd3g
