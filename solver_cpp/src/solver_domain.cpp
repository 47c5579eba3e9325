// The domain rescue (docs/solver.md, "Staying in the model's domain"): when attempts were stopped at a model's
// domain edge (status domain_edge), the same game with the domain box as control bounds. The line search's hard stop
// at the box ends an attempt as soon as Newton's direction points out of it; a barrier on the box instead bends the
// steps inside, so Newton can reach an equilibrium in the interior (which is then this game's) or one held by the box
// (which says that this game, as posed, has none there).
#include <algorithm>
#include <array>
#include <cstdio>
#include <map>

#include "rd3g/clock.hpp"
#include "rd3g/solver.hpp"

namespace rd3g {

namespace {
using ConstraintKey = std::array<int, 5>;
ConstraintKey key_of(const Constraint& c) { return {static_cast<int>(c.kind), c.i, c.j, c.k, c.idx}; }
}  // namespace

bool Solver::domain_rescue_enabled() const {
  // Not in receding-horizon solves (no restarts), nor without a domain box.
  return settings_.domain_fraction > 0 && settings_.restart.count > 0;
}

bool Solver::domain_rescue_wanted(const Info& info) const {
  // Only after an attempt stopped at a domain edge and no equilibrium was found, and not after the clock stopped
  // the schedule.
  return edge_attempts_ > 0 && domain_rescue_enabled() && info.status != Status::Converged &&
         info.status != Status::TimeLimit && !past_deadline();
}

bool Solver::domain_bounded_problem(Problem& p) {
  p = prob_;
  bool any = false;
  for (int i = 0; i < N_; ++i) {
    prob_.dynamics[i]->control_domain(dom_lo_, dom_hi_);
    for (int q = 0; q < nu_; ++q) {
      double lo, hi;
      if (!domain_box(q, lo, hi)) continue;
      if (lo > p.u_min[i][q]) { p.u_min[i][q] = lo; any = true; }
      if (hi < p.u_max[i][q]) { p.u_max[i][q] = hi; any = true; }
    }
  }
  return any;
}

void Solver::prepare_domain_rescue() {
  Problem bounded_problem;
  if (!domain_rescue_enabled() || !domain_bounded_problem(bounded_problem)) {
    domain_solver_.reset();  // the rescue cannot run (domain_rescue_wanted) or has nothing to bound
    return;
  }
  Settings s = settings_;
  s.verbose = false;
  if (!domain_solver_) {
    domain_solver_ = std::make_unique<Solver>();
    domain_solver_->setup(bounded_problem, s);
  } else {
    domain_solver_->update_settings(s);
    domain_solver_->update(bounded_problem);
  }
  domain_start_.u.assign(N_, Mat::Zero(T_, nu_));
  domain_start_.lambda.assign(N_, Mat::Zero(T_, nx_));
  std::map<ConstraintKey, int> index;
  const std::vector<Constraint>& bounded_cons = domain_solver_->cons_;
  for (int c = 0; c < static_cast<int>(bounded_cons.size()); ++c) index[key_of(bounded_cons[c])] = c;
  domain_index_.resize(cons_.size());
  for (size_t c = 0; c < cons_.size(); ++c) domain_index_[c] = index.at(key_of(cons_[c]));  // each is one of them
}

bool Solver::domain_rescue(Result& found, Info& info, int& total_iter) {
  if (!domain_solver_) return false;
  if (settings_.verbose) std::printf("attempts stopped at a model's domain edge: the game with the domain box as bounds\n");
  Solver& bounded = *domain_solver_;
  bounded.settings().time_limit = settings_.time_limit > 0 ? time_left() : 0.0;
  for (int i = 0; i < N_; ++i) {  // this solve's initial guess
    domain_start_.u[i] = u_init_[i].transpose();
    domain_start_.lambda[i] = lam_init_[i].transpose();
  }
  const Result b = bounded.solve(&domain_start_);
  total_iter += b.info.iterations;
  info.domain_iterations += b.info.iterations;
  info.attempts += b.info.attempts;
  info.iterations = total_iter;
  info.timings.total = seconds_since(t_start_);
  if (b.info.status != Status::Converged) return false;  // the schedule's result stays, with these counters
  // In this game, from the bounded equilibrium with its multipliers and partition: an equilibrium here converges at
  // once; one that a domain bound holds is pushed back to the edge.
  load_bounded_point(b);
  use_rules(false);
  inertia_on_ = false;
  keep_partition_ = true;
  ++info.attempts;
  iter_limit_ = total_iter + settings_.order.polish_iter;
  const size_t at_point = info.residual_history.size();
  run_attempt(info, total_iter);
  if (info.status == Status::Converged) {
    found.info = info;
    write_result(found, found.info);  // the second-order test decides converged or saddle
    return true;
  }
  // Not an equilibrium of this game: report the bounded game's equilibrium, at the edge.
  load_bounded_point(b);
  found.info = info;
  found.info.status = Status::DomainEdge;
  found.info.residual_norm = info.residual_history[at_point];  // this game's ||r|| at the bounded equilibrium
  write_result(found, found.info);
  return true;
}

void Solver::load_bounded_point(const Result& b) {
  for (int i = 0; i < N_; ++i) {
    y_.x[i] = b.x[i].transpose();
    y_.u[i] = b.u[i].transpose();
    y_.lam[i] = b.lambda[i].transpose();
  }
  rho_ = b.info.rho;
  barrier_ = settings_.barrier.mode;
  const double margin = settings_.barrier.margin;
  for (int c = 0; c < static_cast<int>(cons_.size()); ++c) {
    const int m = domain_index_[c];
    const double h = b.h[m], mu = b.mu[m];
    y_.mu[c] = y_.mu2[c] = y_.z[c] = 0;
    if (h < -margin) {
      state_[c] = ConstraintState::Barrier;
      y_.z[c] = mu > 0 ? mu : rho_ / -h;  // the barrier dual (b.mu reports it for barrier constraints)
    } else if (mu > 0) {
      state_[c] = ConstraintState::Active;
      y_.mu[c] = y_.mu2[c] = mu;
    } else {
      state_[c] = ConstraintState::Free;
    }
  }
  number_multipliers();
}

}  // namespace rd3g
