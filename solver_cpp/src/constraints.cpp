#include "rd3g/constraints.hpp"

#include <algorithm>
#include <cmath>

namespace rd3g {

std::vector<Constraint> list_constraints(const Problem& p, bool with_bounds) {
  using K = Constraint::Kind;
  const int N = p.num_agents(), T = p.horizon, nx = p.dynamics[0]->nx(), nu = p.dynamics[0]->nu();
  std::vector<Constraint> out;
  for (int k = 0; k <= T; ++k) {
    if (k >= 1) {
      if (p.collision.enabled)
        for (int i = 0; i < N; ++i)
          for (int j = i + 1; j < N; ++j) out.push_back({K::Pair, i, j, k, -1});
      for (int i = 0; i < N; ++i) {
        for (int o = 0; o < static_cast<int>(p.obstacles.size()); ++o) out.push_back({K::Obstacle, i, o, k, -1});
        if (!with_bounds) continue;
        for (int q = 0; q < nx; ++q) {
          if (std::isfinite(p.x_max[i][q])) out.push_back({K::StateMax, i, -1, k, q});
          if (std::isfinite(p.x_min[i][q])) out.push_back({K::StateMin, i, -1, k, q});
        }
      }
    }
    if (k < T && with_bounds)
      for (int i = 0; i < N; ++i)
        for (int q = 0; q < nu; ++q) {
          if (std::isfinite(p.u_max[i][q])) out.push_back({K::ControlMax, i, -1, k, q});
          if (std::isfinite(p.u_min[i][q])) out.push_back({K::ControlMin, i, -1, k, q});
        }
  }
  return out;
}

void distance_constraint(CollisionForm form, const Eigen::Vector2d& d_raw, double dmin, double& h, Eigen::Vector2d* g,
                         Eigen::Matrix2d* H, double sx) {
  const Eigen::Vector2d d(sx * d_raw[0], d_raw[1]);
  if (form == CollisionForm::Squared) {
    h = dmin * dmin - d.squaredNorm();
    if (g) *g = -2.0 * d;
    if (H) *H = -2.0 * Eigen::Matrix2d::Identity();
  } else {
    const double n = std::max(d.norm(), 1e-12);
    h = dmin - n;
    if (!g && !H) return;
    const Eigen::Vector2d e = d / n;
    if (g) *g = -e;
    if (H) *H = -(Eigen::Matrix2d::Identity() - e * e.transpose()) / n;
  }
  // Chain rule through A = diag(sx, 1): g <- A g, H <- A H A.
  if (g) (*g)[0] *= sx;
  if (H) {
    H->row(0) *= sx;
    H->col(0) *= sx;
  }
}

void eval_constraint(const Problem& p, const Constraint& c, const std::vector<Mat>& x, const std::vector<Mat>& u,
                     ConstraintValue& out) {
  using K = Constraint::Kind;
  out.H.setZero();
  out.on_u = false;
  const int px = p.collision.pos_x, py = p.collision.pos_y;
  Eigen::Vector2d gd;
  Eigen::Matrix2d Hd;
  switch (c.kind) {
    case K::Pair: {
      const Eigen::Vector2d d(x[c.i](px, c.k) - x[c.j](px, c.k), x[c.i](py, c.k) - x[c.j](py, c.k));
      distance_constraint(p.collision.form, d, p.collision.at(c.i, c.j, c.k), out.h, &gd, &Hd, p.collision.x_scale(c.k));
      out.n = 4;
      const int ag[4] = {c.i, c.i, c.j, c.j}, cp[4] = {px, py, px, py};
      const double gg[4] = {gd[0], gd[1], -gd[0], -gd[1]};
      for (int a = 0; a < 4; ++a) { out.agent[a] = ag[a]; out.comp[a] = cp[a]; out.g[a] = gg[a]; }
      out.H.topLeftCorner<2, 2>() = Hd;
      out.H.bottomRightCorner<2, 2>() = Hd;
      out.H.topRightCorner<2, 2>() = -Hd;
      out.H.bottomLeftCorner<2, 2>() = -Hd;
      break;
    }
    case K::Obstacle: {
      const Obstacle& o = p.obstacles[c.j];
      const Eigen::Vector2d d(x[c.i](px, c.k) - o.positions(c.k, 0), x[c.i](py, c.k) - o.positions(c.k, 1));
      distance_constraint(p.collision.form, d, o.at(c.k), out.h, &gd, &Hd, p.collision.x_scale(c.k));
      out.n = 2;
      out.agent[0] = out.agent[1] = c.i;
      out.comp[0] = px;
      out.comp[1] = py;
      out.g[0] = gd[0];
      out.g[1] = gd[1];
      out.H.topLeftCorner<2, 2>() = Hd;
      break;
    }
    case K::StateMax:
    case K::StateMin:
    case K::ControlMax:
    case K::ControlMin: {
      const bool upper = c.kind == K::StateMax || c.kind == K::ControlMax;
      out.on_u = c.kind == K::ControlMax || c.kind == K::ControlMin;
      const double v = out.on_u ? u[c.i](c.idx, c.k) : x[c.i](c.idx, c.k);
      const double b = out.on_u ? (upper ? p.u_max[c.i][c.idx] : p.u_min[c.i][c.idx])
                                : (upper ? p.x_max[c.i][c.idx] : p.x_min[c.i][c.idx]);
      out.h = upper ? v - b : b - v;
      out.n = 1;
      out.agent[0] = c.i;
      out.comp[0] = c.idx;
      out.g[0] = upper ? 1.0 : -1.0;
      break;
    }
  }
}

}  // namespace rd3g
