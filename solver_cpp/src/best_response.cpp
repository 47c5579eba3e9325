// Iterated best response (Settings::best_response.rounds): each agent in turn solves its own problem alone, the
// others' current rolled-out positions as moving obstacles (best_response.margin beyond each pair's collision
// distance), with the same solver (one agent). Used as the initial guess of one restart attempt (docs/solver.md,
// "Restarts") and, through Solver::best_response, by solver_cpp.best_response_guess.
#include <algorithm>
#include <string>
#include <stdexcept>
#include <tuple>
#include <utility>

#include "rd3g/clock.hpp"
#include "rd3g/solver.hpp"
#include "rd3g/validate.hpp"

namespace rd3g {

std::pair<double, Vec> Solver::sub_solve_distance(int i, int j) const {
  // The others are kept at their pair's collision distance plus the margin: the guess then starts strictly inside.
  const double inflate = 1.0 + settings_.best_response.margin;
  const PairDistance* q = prob_.collision.pair_distance(i, j);
  const Vec& steps = q ? q->min_distance_steps : prob_.collision.min_distance_steps;
  return std::make_pair(inflate * (q ? q->min_distance : prob_.collision.min_distance), Vec(inflate * steps));
}

void Solver::prepare_sub_solvers() {
  const bool others = prob_.collision.enabled && N_ > 1;  // the others are obstacles only if collisions count
  if (br_stale_ || static_cast<int>(br_.size()) != N_) {
    // One single-agent problem per agent: its model, cost, bounds and the problem's obstacles, then one moving
    // obstacle per other agent at the inflated distance (positions filled before each sub-solve). The lead term
    // sums over the other agents and is absent from a one-agent problem: being linear in their states, it does not
    // change agent i's best response except through its own -(N-1) weight x_i[index] term, which the guess omits.
    Settings sub = settings_;
    sub.best_response.rounds = 0;
    sub.order.candidates = 0;
    sub.restart.count = 0;  // set per sub-solve (sub_solve)
    sub.max_iter = settings_.best_response.max_iter;
    sub.time_limit = 0;
    sub.verbose = false;
    br_.resize(N_);
    br_positions_ = Eigen::MatrixXd::Zero(T_ + 1, 2);
    for (int i = 0; i < N_; ++i) {
      Problem p;
      p.horizon = T_;
      p.dt = prob_.dt;
      p.dynamics = {prob_.dynamics[i]};
      p.x0 = {prob_.x0[i]};
      p.costs = {prob_.costs[i]};
      p.lead = {prob_.lead[i]};
      p.collision = prob_.collision;  // its form and position indices are the obstacles'; no pairs with one agent
      p.u_min = {prob_.u_min[i]};
      p.u_max = {prob_.u_max[i]};
      p.x_min = {prob_.x_min[i]};
      p.x_max = {prob_.x_max[i]};
      p.obstacles = prob_.obstacles;
      if (others)
        for (int j = 0; j < N_; ++j) {
          if (j == i) continue;
          Obstacle o;
          o.positions = br_positions_;
          std::tie(o.min_distance, o.min_distance_steps) = sub_solve_distance(i, j);
          p.obstacles.push_back(std::move(o));
        }
      if (!br_[i]) {
        br_[i] = std::make_unique<Solver>();
        br_[i]->role_ = Role::SubSolve;
      }
      br_[i]->setup(p, sub);
    }
    br_warm_.u.assign(1, Mat::Zero(T_, nu_));
    br_stale_ = false;
  }
}

int Solver::best_response_sweeps(int rounds, int budget) {
  const bool others = prob_.collision.enabled && N_ > 1;
  const int n_obs = static_cast<int>(prob_.obstacles.size());
  prepare_sub_solvers();
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  int used = 0;
  for (int round = 0; round < rounds; ++round)
    for (int i = 0; i < N_; ++i) {
      const int left = budget - used;
      const double time = settings_.time_limit > 0 ? time_left() : 0.0;
      if (left <= 0 || (settings_.time_limit > 0 && time <= 0)) return used;
      Solver& s = *br_[i];
      if (others)
        for (int j = 0, o = n_obs; j < N_; ++j) {
          if (j == i) continue;
          br_positions_.col(0) = y_.x[j].row(px).transpose();
          br_positions_.col(1) = y_.x[j].row(py).transpose();
          const auto [d, steps] = sub_solve_distance(i, j);
          s.update_obstacle(o++, br_positions_, d, steps);
        }
      used += sub_solve(i, std::min(settings_.best_response.max_iter, left), settings_.best_response.restarts, time);
    }
  return used;
}

int Solver::sub_solve(int i, int max_iter, int restarts, double time_limit) {
  Solver& s = *br_[i];
  s.settings_.max_iter = max_iter;
  s.settings_.restart.count = restarts;
  s.settings_.time_limit = time_limit;
  br_warm_.u[0] = y_.u[i].transpose();
  const Result r = s.solve(&br_warm_);
  // A failed sub-solve still returns controls (its last attempt's): keep them if finite, as a guess.
  if (r.u[0].allFinite()) {
    y_.u[i] = r.u[0].transpose();
    roll_out(y_, i);
  }
  return r.info.iterations;
}

int Solver::start_best_response_attempt(int budget) {
  for (int i = 0; i < N_; ++i) {
    y_.x[i].col(0) = prob_.x0[i];
    y_.u[i] = u_init_[i];
    y_.lam[i].setZero();
    roll_out(y_, i);
  }
  const int used = best_response_sweeps(settings_.best_response.rounds, budget);
  start_holds_contacts_ = true;
  y_.mu.setZero();
  y_.mu2.setZero();
  y_.z.setZero();
  // Attempt 0's choice of rules: the guess is usually collision free, and from there the first-attempt rules are
  // faster (measured: the restart rules here lost merge-long 7 cars seed 4, docs/solver.md).
  const bool restart_rules = deep_overlap();
  use_rules(restart_rules);
  rho_ = settings_.barrier.rho_init;
  barrier_ = settings_.barrier.mode;
  return used;
}

Result Solver::best_response(int rounds, const WarmStart* warm) {
  if (N_ == 0) throw std::logic_error("setup() must be called before best_response()");
  require(rounds >= 1, "best_response: rounds must be >= 1, got " + std::to_string(rounds));
  t_start_ = Clock::now();
  load_initial_guess(warm);
  for (int i = 0; i < N_; ++i) {
    y_.x[i].col(0) = prob_.x0[i];
    y_.u[i] = u_init_[i];
    roll_out(y_, i);
  }
  Result res;
  res.info.best_response_iterations = res.info.iterations = best_response_sweeps(rounds, N_ * settings_.max_iter);
  res.x.resize(N_);
  res.u.resize(N_);
  for (int i = 0; i < N_; ++i) {
    res.x[i] = y_.x[i].transpose();
    res.u[i] = y_.u[i].transpose();
  }
  res.info.timings.total = seconds_since(t_start_);
  return res;
}

}  // namespace rd3g
