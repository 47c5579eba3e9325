// Passing-order search (Settings::order; docs/solver.md, "Passing order"), the restart schedule's rescue or a search
// before Newton: the pairs whose rolled-out initial guess collides, candidate orders (the winding of each such pair:
// who passes first and on which side), an ordered guess per candidate from the best-response sub-solvers, and
// Newton's polish of the best-ranked ones.
#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>
#include <stdexcept>
#include <utility>

#include "rd3g/clock.hpp"
#include "rd3g/solver.hpp"
#include "rd3g/validate.hpp"

namespace rd3g {

namespace {
// A leader that ignores its follower in an ordered guess sees it this far away (m): its barrier term is negligible.
constexpr double kFar = 1e6;
constexpr unsigned kOrderSeed = 12345;  // the random candidates: the same sequence in every solve

Eigen::Vector2d position(const Mat& x, int px, int py, int k) { return {x(px, k), x(py, k)}; }
double cross(const Eigen::Vector2d& a, const Eigen::Vector2d& b) { return a.x() * b.y() - a.y() * b.x(); }
}  // namespace

void Solver::initial_conflicts() {
  // trial_ is scratch here: every line-search trial overwrites all of it.
  for (int i = 0; i < N_; ++i) {
    trial_.x[i].col(0) = prob_.x0[i];
    trial_.u[i] = u_init_[i];
    roll_out(trial_, i);
  }
  find_conflicts(trial_);
  order_from_ = u_init_;
}

std::vector<PassingPair> Solver::passing_order(const std::vector<Mat>& x, const WarmStart* warm) {
  if (N_ == 0) throw std::logic_error("setup() must be called before passing_order()");
  require(static_cast<int>(x.size()) == N_, "passing_order: x must hold one trajectory per agent");
  for (const Mat& xi : x)
    require(xi.rows() == T_ + 1 && xi.cols() == nx_ && xi.allFinite(),
            "passing_order: every trajectory must be finite, (horizon + 1) x nx");
  load_initial_guess(warm);  // the next solve loads its own
  initial_conflicts();
  for (int i = 0; i < N_; ++i) trial_.x[i] = x[i].transpose();
  std::vector<PassingPair> out;
  passing_of(trial_, out);
  return out;
}

void Solver::find_conflicts(const Iterate& y) {
  conflicts_.clear();
  conflicts_known_ = true;
  if (!prob_.collision.enabled || N_ < 2) return;
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  for (int i = 0; i < N_; ++i)
    for (int j = i + 1; j < N_; ++j) {
      int deepest = 0;
      double depth = 0;  // largest d_min - |p_j - p_i| over k = 1..T
      for (int k = 1; k <= T_; ++k) {
        Eigen::Vector2d d = position(y.x[j], px, py, k) - position(y.x[i], px, py, k);
        d[0] *= prob_.collision.x_scale(k);
        const double dk = prob_.collision.at(i, j, k) - d.norm();
        if (dk > depth) { depth = dk; deepest = k; }
      }
      if (deepest == 0) continue;
      ConflictPair c;
      c.i = i;
      c.j = j;
      c.k = deepest;
      const int k0 = deepest < T_ ? deepest : deepest - 1;
      const Eigen::Vector2d d = position(y.x[j], px, py, deepest) - position(y.x[i], px, py, deepest);
      const Eigen::Vector2d w = (position(y.x[j], px, py, k0 + 1) - position(y.x[i], px, py, k0 + 1)) -
                                (position(y.x[j], px, py, k0) - position(y.x[i], px, py, k0));
      const double scale = std::max(prob_.collision.at(i, j, deepest), 1e-12);
      // The relative motion's normal, on the side where cross(d, w) > 0 (a counterclockwise winding); with no
      // relative motion (cars abreast), the counterclockwise tangent of d: the follower moving along it winds +1.
      if (w.norm() > 1e-6 * scale) c.n = Eigen::Vector2d(w.y(), -w.x()) / w.norm();
      else if (d.norm() > 1e-9 * scale) c.n = Eigen::Vector2d(-d.y(), d.x()) / d.norm();
      else c.n = Eigen::Vector2d(1.0, 0.0);
      c.natural = d.dot(c.n) >= 0 ? 1 : -1;
      conflicts_.push_back(c);
    }
}

void Solver::candidate_orders() {
  const int P = static_cast<int>(conflicts_.size());
  const int K = settings_.order.candidates;
  std::vector<int> natural(P);
  for (int p = 0; p < P; ++p) natural[p] = conflicts_[p].natural;
  order_signs_.clear();
  auto add = [&](const std::vector<bool>& flip) {
    std::vector<int> s = natural;
    for (int p = 0; p < P; ++p)
      if (flip[p]) s[p] = -s[p];
    if (std::find(order_signs_.begin(), order_signs_.end(), s) == order_signs_.end()) order_signs_.push_back(s);
  };
  std::vector<bool> flip(P, false);
  if (P < 20 && (1L << P) <= K) {
    // Every order: the guess's own first, then by the number of pairs flipped.
    for (int flips = 0; flips <= P; ++flips)
      for (long mask = 0; mask < (1L << P); ++mask) {
        if (__builtin_popcountl(mask) != flips) continue;
        for (int p = 0; p < P; ++p) flip[p] = (mask >> p) & 1;
        add(flip);
      }
    return;
  }
  add(flip);
  for (int p = 0; p < P && static_cast<int>(order_signs_.size()) < K; ++p) {
    std::fill(flip.begin(), flip.end(), false);
    flip[p] = true;
    add(flip);
  }
  std::mt19937 rng(kOrderSeed);
  std::bernoulli_distribution coin(0.5);
  for (int tries = 0; static_cast<int>(order_signs_.size()) < K && tries < 20 * K; ++tries) {
    for (int p = 0; p < P; ++p) flip[p] = coin(rng);
    add(flip);
  }
}

int Solver::order_sub_solve(int i, int left, double time_limit) {
  return sub_solve(i, std::min(settings_.order.max_iter, left), std::min(settings_.restart.count, 1), time_limit);
}

int Solver::solo_plans(int budget) {
  for (int i = 0; i < N_; ++i) {
    y_.x[i].col(0) = prob_.x0[i];
    y_.u[i] = u_init_[i];
    roll_out(y_, i);
  }
  prepare_sub_solvers();
  const int n_obs = static_cast<int>(prob_.obstacles.size());
  int used = 0;
  for (int i = 0; i < N_; ++i) {
    const int left = budget - used;
    const double time = settings_.time_limit > 0 ? time_left() : 0.0;
    if (left <= 0 || (settings_.time_limit > 0 && time <= 0)) break;
    br_positions_.setConstant(kFar);
    for (int j = 0, o = n_obs; j < N_; ++j) {
      if (j == i) continue;
      auto [d, steps] = sub_solve_distance(i, j);
      br_[i]->update_obstacle(o++, br_positions_, d, steps);
    }
    used += order_sub_solve(i, left, time);
  }
  return used;
}

int Solver::ordered_guess(const std::vector<int>& winding, int budget) {
  for (int i = 0; i < N_; ++i) {
    y_.x[i].col(0) = prob_.x0[i];
    y_.u[i] = order_from_[i];
    y_.lam[i].setZero();
    roll_out(y_, i);
  }
  prepare_sub_solvers();
  const int n_obs = static_cast<int>(prob_.obstacles.size());
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  const double offset = settings_.order.offset;
  int used = 0;
  // Gauss-Seidel in agent order: the lower agent of a conflicting pair plans first and ignores the higher one, which
  // then sees the lower one's disc moved by offset d_min towards the side it must not take (radius grown by as much).
  for (int i = 0; i < N_; ++i) {
    const int left = budget - used;
    const double time = settings_.time_limit > 0 ? time_left() : 0.0;
    if (left <= 0 || (settings_.time_limit > 0 && time <= 0)) break;
    Solver& s = *br_[i];
    for (int j = 0, o = n_obs; j < N_; ++j) {
      if (j == i) continue;
      auto [d, steps] = sub_solve_distance(i, j);
      br_positions_.col(0) = y_.x[j].row(px).transpose();
      br_positions_.col(1) = y_.x[j].row(py).transpose();
      int p = 0;
      while (p < static_cast<int>(conflicts_.size()) &&
             !(conflicts_[p].i == std::min(i, j) && conflicts_[p].j == std::max(i, j)))
        ++p;
      if (p < static_cast<int>(conflicts_.size()) && i < j) {
        br_positions_.array() += kFar;
      } else if (p < static_cast<int>(conflicts_.size())) {
        const Eigen::Vector2d shift = -winding[p] * offset * conflicts_[p].n;  // i = the pair's j, the follower
        for (int k = 0; k <= T_; ++k) {
          const double dk = (k > 0 && steps.size()) ? steps[k - 1] : d;
          br_positions_.row(k) += dk * shift.transpose();
        }
        d *= 1.0 + offset;
        steps *= 1.0 + offset;
      }
      s.update_obstacle(o++, br_positions_, d, steps);
    }
    used += order_sub_solve(i, left, time);
  }
  return used;
}

int Solver::winding_of(const Iterate& y, int i, int j) const {
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  double angle = 0;
  Eigen::Vector2d prev = position(y.x[j], px, py, 0) - position(y.x[i], px, py, 0);
  for (int k = 1; k <= T_; ++k) {
    const Eigen::Vector2d d = position(y.x[j], px, py, k) - position(y.x[i], px, py, k);
    angle += std::atan2(cross(prev, d), prev.dot(d));
    prev = d;
  }
  return angle >= 0 ? 1 : -1;
}

void Solver::passing_of(const Iterate& y, std::vector<PassingPair>& out) const {
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  out.resize(conflicts_.size());
  for (size_t p = 0; p < conflicts_.size(); ++p) {
    const int i = conflicts_[p].i, j = conflicts_[p].j;
    PassingPair& q = out[p];
    q.i = i;
    q.j = j;
    q.winding = winding_of(y, i, j);
    int closest = 1;
    q.gap = kInf;
    for (int k = 1; k <= T_; ++k) {
      const double g = (position(y.x[j], px, py, k) - position(y.x[i], px, py, k)).norm();
      if (g < q.gap) { q.gap = g; closest = k; }
    }
    const int k0 = closest < T_ ? closest : closest - 1;
    auto heading = [&](int a) {
      const Eigen::Vector2d v = position(y.x[a], px, py, k0 + 1) - position(y.x[a], px, py, k0);
      return v.norm() > 0 ? Eigen::Vector2d(v / v.norm()) : v;
    };
    const Eigen::Vector2d d = position(y.x[j], px, py, closest) - position(y.x[i], px, py, closest);
    // How far each is ahead of the other along its own heading (i is at -d from j).
    const double ahead_i = -d.dot(heading(i)), ahead_j = d.dot(heading(j));
    q.first = ahead_i >= ahead_j ? i : j;
    const Eigen::Vector2d to_other = q.first == i ? d : Eigen::Vector2d(-d);
    q.side = cross(heading(q.first), to_other) >= 0 ? 1 : -1;
  }
}

int Solver::build_ordered_guesses(Info& info, int& total_iter) {
  const int K = static_cast<int>(order_signs_.size());
  order_u_.resize(K);
  info.orders.assign(K, OrderCandidate{});
  int built = 0;
  for (; built < K; ++built) {
    if (total_iter >= iter_limit_ || past_deadline()) break;
    const int used = ordered_guess(order_signs_[built], N_ * (iter_limit_ - total_iter));
    total_iter += (used + N_ - 1) / N_;  // a sub-solve iteration counts 1/N of a game iteration
    info.order_iterations += used;
    order_u_[built] = y_.u;
    y_.mu.setZero();
    y_.mu2.setZero();
    y_.z.setZero();
    rho_ = settings_.barrier.rho_init;
    barrier_ = settings_.barrier.mode;
    OrderCandidate& oc = info.orders[built];
    oc.requested = order_signs_[built];
    oc.guess_residual = assemble(true, info) ? merit(r_, rc_) : kInf;
  }
  info.orders.resize(built);
  return built;
}

bool Solver::polish_candidate(int c, Result& found, Info& info, int& total_iter) {
  for (int i = 0; i < N_; ++i) {
    y_.u[i] = order_u_[c][i];
    y_.lam[i].setZero();
    roll_out(y_, i);
  }
  y_.mu.setZero();
  y_.mu2.setZero();
  y_.z.setZero();
  use_rules(deep_overlap());
  rho_ = settings_.barrier.rho_init;
  barrier_ = settings_.barrier.mode;
  inertia_on_ = false;
  start_holds_contacts_ = true;
  ++info.attempts;
  ++info.order_attempts;
  const int start = total_iter;
  attempt_cap_ = std::min(iter_limit_, total_iter + settings_.order.polish_iter);
  run_attempt(info, total_iter);
  attempt_cap_ = 0;
  OrderCandidate& oc = info.orders[c];
  oc.polished = true;
  oc.status = info.status;
  oc.iterations = total_iter - start;
  if (info.status != Status::Converged) return false;
  Result cand;
  cand.info = info;
  write_result(cand, cand.info);  // the second-order test decides converged or saddle
  oc.status = cand.info.status;
  oc.equilibrium = cand.info.status == Status::Converged;
  if (!oc.equilibrium) return false;
  oc.u = cand.u;
  oc.found.resize(conflicts_.size());
  for (size_t q = 0; q < conflicts_.size(); ++q) oc.found[q] = winding_of(y_, conflicts_[q].i, conflicts_[q].j);
  found = std::move(cand);
  return true;
}

bool Solver::search_orders(Result& found, Info& info, int& total_iter) {
  if (settings_.order.candidates <= 0 || conflicts_.empty()) return false;
  candidate_orders();
  const int built = build_ordered_guesses(info, total_iter);
  std::vector<int> rank(built);
  std::iota(rank.begin(), rank.end(), 0);
  std::stable_sort(rank.begin(), rank.end(),
                   [&](int a, int b) { return info.orders[a].guess_residual < info.orders[b].guess_residual; });
  int best = -1;
  Result cand;
  for (int p = 0; p < std::min(settings_.order.polish, built); ++p) {
    if (total_iter >= iter_limit_ || past_deadline()) break;
    if (polish_candidate(rank[p], best < 0 ? found : cand, info, total_iter) && best < 0) best = rank[p];
    if (info.status == Status::TimeLimit) break;
    ++total_iter;
  }
  if (best < 0) return false;
  info.orders[best].returned = true;
  // The kept point with the whole search's counters.
  take_counters(found.info, info);
  found.info.iterations = total_iter - 1;
  return true;
}

}  // namespace rd3g
