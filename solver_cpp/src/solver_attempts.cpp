// The solve's attempt schedule: initial guess, restarts (barrier variants, perturbed controls, best response,
// escapes from saddles), the passing-order rescue among them, the globalisation rules of an attempt, stall handling
// and the result.
#include "rd3g/solver.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <stdexcept>
#include <string>

#include "rd3g/clock.hpp"
#include "rd3g/second_order.hpp"
#include "rd3g/validate.hpp"

namespace rd3g {

namespace {
// The best-response attempt is inserted before restart attempt 1 (attempt 0 keeps the initial guess).
constexpr int kBestResponseAttempt = 1;
// The passing-order search (the rescue) runs after this restart attempt if no equilibrium was found yet: after
// attempt 0, the best-response attempt and the first barrier variant, before the other variants and the seeded
// offsets, which change the passing order only by chance (merging_problem(7, 70): none of 21 attempts finds the
// equilibrium, five stall at the same non-equilibrium of one pair; the search's ordered guess reaches it). The later
// barrier variants stall for 100-200 iterations each where the order is what is wrong.
constexpr int kOrderSearchAfterAttempt = 1;
// Std of the seeded constant control offsets of restart attempts 4.. (control units).
constexpr double kRestartOffsetStd = 0.2;
// The stationarity test lowers rho's floor at most to this fraction of tol * barrier.rho_floor_factor.
constexpr double kMinRhoFloorScale = 1e-3;
}  // namespace

// -------------------------------------------------------------------------------------------------
Result Solver::solve(const WarmStart* warm) {
  if (N_ == 0) throw std::logic_error("setup() must be called before solve()");
  Result res;
  Info& info = res.info;
  begin_solve(info, warm);
  Schedule sc;
  Result found;
  if (settings_.order.before_newton && settings_.order.candidates > 0) {
    initial_conflicts();
    if (search_orders(found, info, sc.total_iter)) return found;
  }
  if (run_schedule(res, sc, warm)) return res;
  // No attempt of the schedule found an equilibrium: the passing-order search as its last stage (the rescue), unless
  // it already ran between the restarts.
  Info searched = info;
  if (!sc.searched && rescue_wanted(info) && rescue(found, searched, sc.total_iter)) return found;
  take_counters(info, searched);
  // Some attempt was stopped at a model's domain edge: the same game with the domain box as bounds (domain rescue).
  Result bounded;
  const bool edge_point = domain_rescue_wanted(info) && domain_rescue(bounded, info, sc.total_iter);
  if (edge_point && bounded.info.status == Status::Converged) return bounded;
  // Still none: the schedule again from the equilibrium of a game with the steering bounded (bounded start).
  Result started;
  if (bounded_start_wanted(info) && bounded_start(started, info, sc)) return started;
  if (sc.have_saddle && info.status != Status::Converged) return saddle_result(sc, info);
  if (edge_point) {
    take_counters(bounded.info, info);
    return bounded;
  }
  return res;
}

bool Solver::run_schedule(Result& res, Schedule& sc, const WarmStart* warm) {
  Info& info = res.info;
  for (int attempt = 0; attempt <= settings_.restart.count; ++attempt) {
    const bool br_now = !sc.from_saddle && sc.br_attempts == 0 && settings_.best_response.rounds > 0 &&
                        attempt == kBestResponseAttempt;
    bool repeat = br_now;  // an inserted attempt: the schedule resumes at this attempt afterwards
    info.attempts = sc.prior_attempts + attempt + 1 + sc.escapes + sc.br_attempts + info.order_attempts;
    info.saddle_escapes = sc.prior_escapes + sc.escapes;
    start_scheduled_attempt(attempt, br_now, warm, sc, info);
    if (run_attempt(info, sc.total_iter) == AttemptEnd::Finished) {
      // Steer away from a saddle: keep it, and let the remaining restarts look for a local equilibrium.
      if (!look_past_saddle(attempt, br_now, sc, info)) break;
      Result cand = res;
      write_result(cand, cand.info);
      if (cand.info.status != Status::Saddle) { res = std::move(cand); return true; }
      if (settings_.verbose) std::printf("converged to a saddle, restarting\n");
      if (!sc.have_saddle) { sc.saddle = std::move(cand); sc.have_saddle = true; }
      if (leave_saddle(sc.escapes)) {
        ++sc.escapes;
        sc.from_saddle = true;
        repeat = true;  // same place in the restart schedule
      }
    }
    ++sc.total_iter;
    if (repeat) --attempt;
    else if (attempt == kOrderSearchAfterAttempt && attempt < settings_.restart.count && search_between_restarts(res, sc))
      return true;
  }
  write_result(res, info);
  return info.status == Status::Converged;
}

bool Solver::search_between_restarts(Result& res, Schedule& sc) {
  if (!rescue_wanted(res.info)) return false;
  sc.searched = true;
  Info searched = res.info;
  Result found;
  const int limit = iter_limit_, start = sc.total_iter;
  if (rescue(found, searched, sc.total_iter)) {
    res = std::move(found);
    return true;
  }
  take_counters(res.info, searched);
  iter_limit_ = limit + (sc.total_iter - start);  // the search had its own budget: the restarts keep theirs
  return false;
}

bool Solver::rescue_wanted(const Info& info) const {
  // Not after the clock stopped the schedule (time_limit): the result is then the best iterate seen.
  return settings_.order.candidates > 0 && !settings_.order.before_newton && settings_.restart.count > 0 &&
         info.status != Status::TimeLimit && !past_deadline();
}

bool Solver::rescue(Result& found, Info& info, int& total_iter) {
  // Its own budget beyond max_iter: order.max_iter game iterations for the solo plans and per guess,
  // order.polish_iter per polish, and never more than max_iter (within twice max_iter; the domain rescue, if it follows, has its own).
  const PassingOrderSettings& po = settings_.order;
  const int own = (po.candidates + 1) * po.max_iter + po.polish * (po.polish_iter + 1);
  iter_limit_ = total_iter + std::min(own, settings_.max_iter);
  if (settings_.verbose) std::printf("no equilibrium after the restarts: passing-order search\n");
  // The pairs whose paths conflict: each agent's plan alone (the others ignored), from the initial controls. The
  // rolled-out initial guess misses most (a merge's cars collide only once they steer into the target lane).
  const int used = solo_plans(N_ * (iter_limit_ - total_iter));
  total_iter += (used + N_ - 1) / N_;
  info.order_iterations += used;
  order_from_ = y_.u;
  find_conflicts(y_);
  return search_orders(found, info, total_iter);
}

// The counters of a whole solve (every attempt and the search) onto a result kept from part of it.
void Solver::take_counters(Info& to, const Info& from) const {
  to.iterations = from.iterations;
  to.attempts = from.attempts;
  to.saddle_escapes = from.saddle_escapes;
  to.best_response_attempts = from.best_response_attempts;
  to.best_response_iterations = from.best_response_iterations;
  to.orders = from.orders;
  to.order_attempts = from.order_attempts;
  to.order_iterations = from.order_iterations;
  to.domain_iterations = from.domain_iterations;
  to.bounded_start_iterations = from.bounded_start_iterations;
  to.residual_history = from.residual_history;
  to.step_history = from.step_history;
  to.timings = from.timings;
  to.timings.total = seconds_since(t_start_);
}

void Solver::begin_solve(Info& info, const WarmStart* warm) {
  t_start_ = Clock::now();
  info.timings.setup = setup_time_;
  info.timings.update = update_time_;
  info.setups = setups_;
  update_time_ = 0;
  setups_ = 0;
  load_initial_guess(warm);
  rng_.seed(12345);
  noise_.reset();
  timed_out_ = false;
  have_iteration_start_ = false;
  last_iteration_seconds_ = 0;
  best_merit_ = kInf;
  inertia_delta_.assign(N_, 0.0);
  attempt_cap_ = 0;
  iter_limit_ = settings_.max_iter;
  // The conflicting pairs are found only when the passing-order search runs (initial_conflicts, rescue); a result
  // reports them then, and Solver::passing_order computes them for any other result when asked.
  conflicts_.clear();
  conflicts_known_ = false;
  edge_attempts_ = 0;
}

void Solver::start_scheduled_attempt(int attempt, bool best_response, const WarmStart* warm, Schedule& sc,
                                     Info& info) {
  if (best_response) {
    ++sc.br_attempts;
    ++info.best_response_attempts;
    // A sub-solve iteration (one agent's Newton system, N times smaller) counts 1/N of a game iteration.
    const int used = start_best_response_attempt(N_ * (iter_limit_ - sc.total_iter));
    sc.total_iter += (used + N_ - 1) / N_;
    info.best_response_iterations += used;
  } else if (!sc.from_saddle) {
    start_attempt(attempt, warm);
  }
  inertia_on_ = sc.from_saddle;
  sc.from_saddle = false;
}

bool Solver::look_past_saddle(int attempt, bool best_response, const Schedule& sc, const Info& info) const {
  const SecondOrderSettings& so = settings_.second_order;
  const bool attempt_left = attempt < settings_.restart.count || best_response || sc.escapes < so.escapes;
  return so.restart_on_saddle && info.status == Status::Converged && so.gap >= 0 && attempt_left &&
         sc.total_iter < iter_limit_ && !past_deadline();
}

// No later attempt found an equilibrium: the saddle (feasible, first-order stationary) beats a failure.
Result Solver::saddle_result(Schedule& sc, const Info& info) const {
  Result saddle = std::move(sc.saddle);
  take_counters(saddle.info, info);
  return saddle;
}

void Solver::load_initial_guess(const WarmStart* warm) {
  // Given (or zero) controls and dynamics multipliers; the states are their rollout (start_attempt).
  const bool warm_u = warm && static_cast<int>(warm->u.size()) == N_;
  const bool warm_lam = warm && static_cast<int>(warm->lambda.size()) == N_;
  for (int i = 0; i < N_; ++i) {
    if (warm_u)
      require(warm->u[i].rows() == T_ && warm->u[i].cols() == nu_ && warm->u[i].allFinite(),
              "warm start u has the wrong shape or non-finite values");
    if (warm_lam)
      require(warm->lambda[i].rows() == T_ && warm->lambda[i].cols() == nx_ && warm->lambda[i].allFinite(),
              "warm start lambda has the wrong shape or non-finite values");
  }
  for (int i = 0; i < N_; ++i) {
    if (warm_u) u_init_[i] = warm->u[i].transpose();
    else u_init_[i].setZero();
    if (warm_lam) lam_init_[i] = warm->lambda[i].transpose();
    else lam_init_[i].setZero();
  }
  have_mu_ = warm && warm->mu.size() == static_cast<int>(cons_.size());
  if (have_mu_) require(warm->mu.allFinite(), "warm start mu has non-finite values");
}

void Solver::start_attempt(int attempt, const WarmStart* warm) {
  for (int i = 0; i < N_; ++i) {
    y_.x[i].col(0) = prob_.x0[i];
    y_.u[i] = u_init_[i];
    if (attempt >= 4) {
      // A constant offset per agent and control component (not white noise, which averages out):
      // it changes the order in which agents reach a contested region, i.e. the equilibrium's basin.
      for (int q = 0; q < nu_; ++q) {
        const double offset = kRestartOffsetStd * noise_(rng_);
        double lo, hi;
        const bool held = settings_.domain_fraction > 0 && domain_box(i, q, lo, hi);
        for (int k = 0; k < T_; ++k) {
          const double u = y_.u[i](q, k);
          // A control inside its domain box stays there (a warm start near the edge plus an offset could leave it,
          // and the line search holds only controls inside); one outside already (a warm start) is not held.
          y_.u[i](q, k) = held && u >= lo && u <= hi ? std::clamp(u + offset, lo, hi) : u + offset;
        }
      }
    }
    if (attempt == 0) y_.lam[i] = lam_init_[i];
    else y_.lam[i].setZero();
    roll_out(y_, i);
  }
  y_.mu.setZero();
  y_.mu2.setZero();
  y_.z.setZero();
  if (have_mu_ && attempt == 0) { y_.mu = warm->mu; y_.mu2 = warm->mu; }
  // Restart schedule (measured on the merging games, each variant rescues different instances):
  // attempt 1: 10x rho_init; 2: the other barrier form; 3: both; >= 4: the same four with perturbed controls.
  const int variant = attempt % 4;
  // Globalisation rules: the settings' own (by default the paper's) in attempt 0, unless its initial guess overlaps
  // deeply; the restart rules (rho lowered only near the central path or on a stall, non-monotone violation test)
  // in every later attempt. With a deep overlap the paper's rule puts rho at its floor within 3 iterations while
  // the violation is still ~1 m, and the barrier then admits only tiny steps (crossing, docs/solver.md).
  const bool restart_rules = attempt > 0 || deep_overlap();
  use_rules(restart_rules);
  rho_ = settings_.barrier.rho_init * ((variant == 1 || variant == 3) ? 10.0 : 1.0);
  barrier_ = settings_.barrier.mode;
  if (variant >= 2)
    barrier_ = settings_.barrier.mode == BarrierMode::PrimalDual ? BarrierMode::Primal : BarrierMode::PrimalDual;
  // The LU's symbolic analysis is kept across attempts and solves: it depends only on the sparsity pattern,
  // i.e. on the partition (pattern_state_) and the constraint list, and is redone when either changes.
}

void Solver::use_rules(bool restart_rules) {
  rules_.rho_progress = restart_rules ? settings_.restart.rho_progress : settings_.barrier.rho_progress;
  rules_.violation_memory = restart_rules ? settings_.restart.violation_memory : settings_.line_search.violation_memory;
  rules_.rho_on_stall = restart_rules && settings_.restart.rho_on_stall;
  // Not in the sub-solves that build guesses (docs/solver.md).
  rules_.backtrack_to_crossing = role_ == Role::Game && settings_.line_search.to_crossing;
}

void Solver::roll_out(Iterate& y, int i) {
  for (int k = 0; k < T_; ++k) {
    prob_.dynamics[i]->eval(y.x[i].col(k), y.u[i].col(k), fx_.col(0), Atmp_, Btmp_);
    y.x[i].col(k + 1) = fx_.col(0);
  }
}

bool Solver::deep_overlap() const {
  if (settings_.restart.deep_overlap > 1) return false;
  const int px = prob_.collision.pos_x, py = prob_.collision.pos_y;
  for (const Constraint& cn : cons_) {
    double dmin;
    Eigen::Vector2d d;
    if (cn.kind == Constraint::Kind::Pair) {
      dmin = prob_.collision.at(cn.i, cn.j, cn.k);
      d << y_.x[cn.i](px, cn.k) - y_.x[cn.j](px, cn.k), y_.x[cn.i](py, cn.k) - y_.x[cn.j](py, cn.k);
    } else if (cn.kind == Constraint::Kind::Obstacle) {
      const Obstacle& o = prob_.obstacles[cn.j];
      dmin = o.at(cn.k);
      d << y_.x[cn.i](px, cn.k) - o.positions(cn.k, 0), y_.x[cn.i](py, cn.k) - o.positions(cn.k, 1);
    } else {
      continue;
    }
    d[0] *= prob_.collision.x_scale(cn.k);
    if (d.norm() < (1.0 - settings_.restart.deep_overlap) * dmin) return true;
  }
  return false;
}

bool Solver::assemble(bool first, Info& info) {
  const auto t0 = Clock::now();
  eval_all_constraints(y_, h_);
  classify(h_, first);
  number_multipliers();
  const bool ok = evaluate(y_, h_, true, r_, rc_);
  info.timings.assembly += seconds_since(t0);
  return ok;
}

bool Solver::converged(double rnorm) {
  const int C = static_cast<int>(cons_.size());
  for (int c = 0; c < C; ++c)
    if (state_[c] == ConstraintState::Active &&
        (y_.mu[c] < -kMultiplierTol || (mu2_col_[c] >= 0 && y_.mu2[c] < -kMultiplierTol)))
      return false;  // an active constraint pushes the wrong way: not an equilibrium
  const double maxviol = C ? std::max(0.0, h_.maxCoeff()) : 0.0;
  double max_defect = 0;
  for (int i = 0; i < N_; ++i)
    for (int k = 0; k < T_; ++k) max_defect = std::max(max_defect, r_.segment(col_lam(i, k), nx_).cwiseAbs().maxCoeff());
  if (!(rnorm < settings_.tol && maxviol <= settings_.violation_tol && max_defect <= settings_.dynamics_tol &&
        (C == 0 || at_rho_floor())))
    return false;
  if (settings_.stationarity_tol <= 0 || role_ == Role::SubSolve ||
      relative_stationarity() <= settings_.stationarity_tol)
    return true;
  // The far constraints' barrier force is about rho / |h|: lower the floor (at most to kMinRhoFloorScale of it).
  if (C > 0) rho_floor_scale_ = std::max(kMinRhoFloorScale, rho_floor_scale_ * settings_.barrier.rho_kappa);
  return false;
}

double Solver::relative_stationarity() {
  stationarity_ = r_.head(n_primal_);
  const double gap = settings_.second_order.gap;
  const bool pd = barrier_ == BarrierMode::PrimalDual;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    if (state_[c] != ConstraintState::Barrier || h_[c] >= -gap) continue;
    double hv;
    Eigen::Vector2d g;
    eval_constraint(y_, c, hv, &g, nullptr);
    const double w = pd ? y_.z[c] : -rho_ / hv;
    const ConstraintRows q = constraint_rows(c);
    for (int a = 0; a < q.n; ++a) stationarity_[q.ci[a]] -= w * g[a];
    if (q.pair)
      for (int a = 0; a < q.n; ++a) stationarity_[q.cj[a]] += w * g[a];
  }
  double worst = 0;
  for (int i = 0; i < N_; ++i) {
    double sq = 0;
    for (int k = 0; k < T_; ++k)
      sq += stationarity_.segment(col_u(i, k), nu_).squaredNorm() + stationarity_.segment(col_x(i, k + 1), nx_).squaredNorm();
    worst = std::max(worst, sq);
  }
  return std::sqrt(worst) / std::max(cost_gradient_norm(), 1e-300);
}

double Solver::cost_gradient_norm() {
  double sq = 0;
  for (int i = 0; i < N_; ++i) {
    const double lead = lead_gradient(prob_.lead[i], N_);
    for (int k = 0; k < T_; ++k) {
      control_cost_gradient(prob_.costs[i], y_.u[i].col(k), stage_.gu);
      state_cost_gradient(prob_.costs[i], k + 1, T_, y_.x[i].col(k + 1), stage_.gx);
      stage_.gx[prob_.lead[i].index] += lead;
      sq += stage_.gu.squaredNorm() + stage_.gx.squaredNorm();
    }
  }
  return std::sqrt(sq);
}

double Solver::rho_floor() const {
  return settings_.tol * settings_.barrier.rho_floor_factor * rho_floor_scale_;
}

bool Solver::at_rho_floor() const { return rho_ <= rho_floor() * (1 + 1e-9); }

Solver::AttemptEnd Solver::run_attempt(Info& info, int& total_iter) {
  merits_.clear();
  violations_.clear();
  rho_floor_scale_ = 1;
  bool first = !keep_partition_, stalled = false, polished = false;
  keep_partition_ = false;
  newton_at_edge_ = false;
  info.status = Status::MaxIterations;
  for (;; ++total_iter) {
    const bool ok = assemble(first, info);
    first = false;
    start_holds_contacts_ = false;
    if (!ok) { info.status = Status::NumericalError; break; }
    const double rnorm = merit(r_, rc_);
    record_iterate(rnorm, total_iter, info);
    if (converged(rnorm)) { info.status = Status::Converged; break; }
    if (total_iter >= iter_limit_ || (attempt_cap_ > 0 && total_iter >= attempt_cap_)) {
      info.status = Status::MaxIterations;
      break;
    }
    if (next_iteration_overruns()) { info.status = Status::TimeLimit; break; }
    double merit_now = rnorm;
    if (stalling(rnorm) && !handle_stall(polished, merit_now, stalled, info)) break;
    const double t = take_step(merit_now, info);
    if (timed_out_) { info.status = Status::TimeLimit; break; }
    if (t < 0) { info.status = Status::NumericalError; break; }
    if (t == 0.0) { info.status = Status::LineSearchFailed; break; }
    info.step_history.push_back(t);
    if (rules_.rho_progress <= 0 ? t >= settings_.barrier.rho_after_step : rnorm <= rules_.rho_progress * rho_)
      lower_rho();
  }
  if (info.status == Status::Converged || info.status == Status::TimeLimit || info.status == Status::NumericalError ||
      total_iter >= iter_limit_)
    return AttemptEnd::Finished;
  if (polished && info.status == Status::LineSearchFailed) stalled = true;  // the polish was the stall's last resort
  if (stalled) info.status = Status::Stalled;  // reported if no attempt is left
  // Stopped because Newton's direction leaves the model's domain at a control on the edge: say so.
  if (newton_at_edge_) {
    info.status = Status::DomainEdge;
    ++edge_attempts_;
  }
  if (settings_.verbose)
    std::printf("attempt ended (%s), restarting\n", stalled ? "stalled" : status_name(info.status).c_str());
  return AttemptEnd::Restart;
}

void Solver::record_iterate(double rnorm, int total_iter, Info& info) {
  info.residual_history.push_back(rnorm);
  merits_.push_back(rnorm);
  violations_.push_back(violation_sum(h_));
  info.residual_norm = rnorm;
  info.iterations = total_iter;
  if (settings_.time_limit > 0 && rnorm < best_merit_) {
    best_merit_ = rnorm;
    best_seen_ = y_;
  }
  if (settings_.verbose)
    std::printf("it %3d  |r| %.3e  rho %.2e  viol %.2e  active %d\n", total_iter, rnorm, rho_,
                cons_.empty() ? 0.0 : std::max(0.0, h_.maxCoeff()), n_vars_ - n_primal_);
}

void Solver::lower_rho() {
  rho_ = std::max(rho_floor(), std::min(settings_.barrier.rho_kappa * rho_, std::pow(rho_, settings_.barrier.rho_beta)));
}

bool Solver::stalling(double rnorm) const {
  // ||r|| is still above `ratio` times its value `window` iterations ago (window 0: never).
  auto fell_less = [&](int window, double ratio) {
    return window > 0 && static_cast<int>(merits_.size()) > window && rnorm > ratio * merits_[merits_.size() - 1 - window];
  };
  const StallSettings& s = settings_.stall;
  return (at_rho_floor() && fell_less(s.floor_window, 1.0 - 1e-4)) || fell_less(s.crawl_window, s.crawl_ratio) ||
         fell_less(s.window, 0.99);
}

bool Solver::handle_stall(bool& polished, double& merit_now, bool& stalled, Info& info) {
  if (rules_.rho_on_stall && rules_.rho_progress > 0 && !at_rho_floor()) {
    // With rho_progress, a barrier subproblem can stall above rho_progress * rho, and rho would never be
    // lowered: lower it now (merging_problem(7, 12), rho_progress 10: rho stuck at 0.01 with ||r|| 0.13).
    lower_rho();
    if (!evaluate(y_, h_, true, r_, rc_)) { info.status = Status::NumericalError; return false; }
    merit_now = merit(r_, rc_);
    merits_.assign(1, merit_now);
    if (settings_.verbose) std::printf("stall: rho lowered to %.2e\n", rho_);
    return true;
  }
  // Before giving the attempt up: hold the nearly active barrier constraints as equalities (once per
  // attempt). A stall with rho at its floor is often the barrier's ill-conditioning around a contact
  // that the equilibrium needs; the equality form has no such curvature.
  if (polished || settings_.stall.polish_gap <= 0 || !hold_near_contacts(h_, settings_.stall.polish_gap)) {
    stalled = true;
    return false;
  }
  polished = true;
  number_multipliers();
  evaluate(y_, h_, true, r_, rc_);
  merits_.assign(1, merit(r_, rc_));
  if (settings_.verbose) std::printf("stall: %d nearly active constraints held as equalities\n", n_vars_ - n_primal_);
  return true;
}

bool Solver::hold_near_contacts(const Vec& h, double gap) {
  bool any = false;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    if (state_[c] != ConstraintState::Barrier || h[c] < -gap) continue;
    state_[c] = ConstraintState::Active;
    // The barrier dual (or -rho/h in the primal form) is the multiplier estimate.
    const double mu = barrier_ == BarrierMode::PrimalDual ? y_.z[c] : -rho_ / h[c];
    y_.mu[c] = y_.mu2[c] = mu;
    y_.z[c] = 0;
    any = true;
  }
  return any;
}

bool Solver::second_order_wanted(const Info& info) const {
  if (settings_.second_order.gap < 0 || info.status == Status::NumericalError) return false;
  // A converged point always gets the test (it decides converged vs saddle). Any other iterate only
  // reports its eigenvalues, which is not worth passing the deadline for (a dense eigenvalue problem per agent).
  return info.status == Status::Converged || !(info.status == Status::TimeLimit || past_deadline());
}

void Solver::write_result(Result& res, Info& info) {
  // With a time limit, the iterate with the lowest merit seen (a later restart attempt may be worse).
  if (info.status == Status::TimeLimit && best_merit_ < info.residual_norm) {
    std::swap(y_, best_seen_);
    info.residual_norm = best_merit_;
  }
  const int C = static_cast<int>(cons_.size());
  // Result: trajectories, multipliers (barrier-implied -rho/h for inactive constraints).
  eval_all_constraints(y_, h_);
  if (second_order_wanted(info) && !check_second_order(info) && info.status == Status::Converged)
    info.status = Status::Saddle;
  res.x.resize(N_);
  res.u.resize(N_);
  res.lambda.resize(N_);
  for (int i = 0; i < N_; ++i) {
    res.x[i] = y_.x[i].transpose();
    res.u[i] = y_.u[i].transpose();
    res.lambda[i] = y_.lam[i].transpose();
  }
  res.mu = Vec::Zero(C);
  int nact = 0;
  for (int c = 0; c < C; ++c) {
    if (state_[c] == ConstraintState::Active) {
      res.mu[c] = mu2_col_[c] >= 0 ? 0.5 * (y_.mu[c] + y_.mu2[c]) : y_.mu[c];
      ++nact;
    } else if (state_[c] == ConstraintState::Barrier && h_[c] < 0) {
      res.mu[c] = barrier_ == BarrierMode::PrimalDual ? y_.z[c] : -rho_ / h_[c];
    }
  }
  res.h = h_;
  if (conflicts_known_) passing_of(y_, info.passing_order);
  else info.passing_order.clear();
  info.active_constraints = nact;
  info.max_violation = C ? std::max(0.0, h_.maxCoeff()) : 0.0;
  info.rho = rho_;
  info.timings.total = seconds_since(t_start_);
}

}  // namespace rd3g
