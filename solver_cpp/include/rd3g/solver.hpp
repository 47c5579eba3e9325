// RD3G: Newton's method on the open-loop generalised Nash equilibrium conditions of an N-agent game
// (Zhang & Tsiotras), with constraint partitioning: violated/active constraints are equalities with
// multipliers, satisfied ones are kept satisfied by a log barrier whose weight rho shrinks superlinearly.
#pragma once
#include <Eigen/Sparse>
#include <Eigen/SparseLU>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseQR>
#include <chrono>
#include <memory>
#include <random>
#include <utility>
#include <vector>

#include "rd3g/clock.hpp"
#include "rd3g/constraints.hpp"
#include "rd3g/normal_matrix.hpp"
#include "rd3g/problem.hpp"
#include "rd3g/riccati.hpp"
#include "rd3g/shifted_ldlt.hpp"
#include "rd3g/stage_terms.hpp"

namespace rd3g {

class SecondOrderCheck;

/// An equality-held constraint's multiplier below -kMultiplierTol has the wrong sign: the constraint is released, and
/// the point is not an equilibrium.
constexpr double kMultiplierTol = 1e-6;

/// How a constraint enters the current Newton system.
enum class ConstraintState : char {
  Barrier,  ///< satisfied: -rho log(-h) in the Lagrangian, no multiplier variable
  Active,   ///< violated or held at h = 0: equality with a multiplier variable
  Free,     ///< released (multiplier had the wrong sign) and not yet inside the barrier margin
};

class Solver {
 public:
  /// Validates the problem and the settings (rd3g/validate.hpp), lists the constraints and allocates every
  /// buffer the solves need. Its duration is reported in Info::timings.setup.
  void setup(const Problem& problem, const Settings& settings);

  // Updates without a new set-up (OSQP/proxsuite style). Each validates what it changes (same messages as
  // setup) and leaves the solver unchanged if it throws. Their time is reported in Info::timings.update of
  // the next solve. Only a bound that changes between finite and infinite changes the constraint list; the
  // list and its buffers are then rebuilt (counted in Info::setups).
  void update_settings(const Settings& settings);
  void update_initial_state(int agent, const Vec& x0);
  void update_cost(int agent, const QuadraticCost& cost);
  void update_lead(int agent, const LeadCost& lead);
  /// Empty vectors mean unbounded, as in Problem.
  void update_bounds(int agent, const Vec& u_min, const Vec& u_max, const Vec& x_min, const Vec& x_max);
  /// Pairwise d_min (m) and its optional per-step values (k = 1..T; empty = min_distance at every step).
  void update_collision_distance(double min_distance, const Vec& steps);
  void update_obstacle(int index, const Eigen::MatrixXd& positions, double min_distance, const Vec& steps);
  /// Everything but the structure at once: the problem must have the set-up's horizon, agents, state and
  /// control sizes, collision form and position indices and number of obstacles; an empty dynamics list
  /// keeps the set-up's models.
  void update(const Problem& problem);

  /// Solves from zero controls or from a warm start; the initial states are the rollout of the controls.
  Result solve(const WarmStart* warm = nullptr);

  /// Iterated best response alone (the guess of Settings::best_response.rounds): `rounds` (>= 1) Gauss-Seidel sweeps
  /// from the warm start's controls (zero without), the sub-solves' iterations together at most N max_iter (max_iter
  /// game-iteration equivalents, as in the restart). Result: x, u and info (iterations = best_response_iterations,
  /// timings.total); no multipliers.
  Result best_response(int rounds, const WarmStart* warm = nullptr);

  /// The pairs whose rolled-out initial guess (the warm start's controls, zero without) comes closer than their
  /// collision distance, and the order trajectories x (per agent (T+1) x nx, e.g. a Result's) give them. A solve
  /// fills Info::passing_order only when its passing-order search ran; this computes it for any other result, on
  /// demand (a rollout and a scan of every pair at every step that the solve itself no longer pays).
  std::vector<PassingPair> passing_order(const std::vector<Mat>& x, const WarmStart* warm = nullptr);

  const std::vector<Constraint>& constraints() const { return cons_; }
  /// Changes whenever the constraint list does (set-up, or an update that made a bound finite or infinite).
  int structure_version() const { return structure_version_; }

  /// For tests: residual r and dense Newton matrix J at a given primal-dual point (x per agent (T+1) x nx,
  /// u T x nu, lambda T x nx, mu one per constraint) and barrier weight rho, with the constraints
  /// partitioned as at the first iteration (h >= 0 active). Returns the multiplier column of each constraint.
  std::vector<int> debug_residual(const std::vector<Mat>& x, const std::vector<Mat>& u, const std::vector<Mat>& lam,
                                  const Vec& mu, double rho, Vec& r, Mat& J);
  /// Column of every primal variable: (agent, k, kind 0=u,1=lambda,2=x_{k+1}) -> first index.
  int column_of(int i, int k, int kind) const { return kind == 0 ? col_u(i, k) : kind == 1 ? col_lam(i, k) : col_x(i, k + 1); }
  Settings& settings() { return settings_; }
  const Problem& problem() const { return prob_; }

 private:
  using SpMat = Eigen::SparseMatrix<double>;
  using Triplet = Eigen::Triplet<double>;

  struct Iterate {
    std::vector<Mat> x;    // per agent nx x (T+1), column k = x_k
    std::vector<Mat> u;    // per agent nu x T
    std::vector<Mat> lam;  // per agent nx x T
    Vec mu, mu2;           // per constraint; mu2 = other agent's multiplier for Pair (per-agent formulation)
    Vec z;                 // per constraint: barrier dual (primal-dual mode), -rho/h on the central path
  };

  // index helpers
  int stage_size() const { return layout_.stage_size(); }
  int col_u(int i, int k) const { return layout_.col_u(i, k); }
  int col_lam(int i, int k) const { return layout_.col_lam(i, k); }
  int col_x(int i, int k) const { return layout_.col_x(i, k); }  // k = 1..T

  /// Why an attempt (one pass of Newton iterations from the initial guess) ended.
  enum class AttemptEnd { Finished, Restart };

  /// Attempt from an iterated-best-response guess (Settings::best_response.rounds): y_ from the initial controls,
  /// the sweeps (at most `budget` sub-solve iterations), then rho_init and attempt 0's rules. Returns the iterations.
  int start_best_response_attempt(int budget);
  /// Gauss-Seidel sweeps on y_'s controls (best_response.cpp); returns the sub-solves' iterations (<= budget).
  int best_response_sweeps(int rounds, int budget);
  /// The single-agent sub-solvers of the best response (br_), built if stale.
  void prepare_sub_solvers();
  /// Agent i's sub-solve (obstacles already set) from its controls in y_, with at most max_iter iterations and
  /// `restarts` restart attempts; y_ takes its controls if finite. Returns its iterations.
  int sub_solve(int i, int max_iter, int restarts, double time_limit);
  /// Agent i's sub-solve for the passing-order search (solo plan or ordered guess): order.max_iter iterations, at most
  /// `left`, and one restart (not best_response.restarts: an ordered guess must reach its requested order).
  int order_sub_solve(int i, int left, double time_limit);
  /// (d_min, per-step d_min) at which a sub-solve keeps agent j away from agent i (best_response.margin beyond).
  std::pair<double, Vec> sub_solve_distance(int i, int j) const;

  // Passing-order search (passing_order.cpp; Settings::order).
  /// A pair whose rolled-out initial guess comes closer than d_min: its deepest step k, the unit normal n of the
  /// relative motion there (winding +1 puts p_j - p_i on n's side) and the guess's own winding.
  struct ConflictPair {
    int i = 0, j = 0, k = 0;
    Eigen::Vector2d n = Eigen::Vector2d::Zero();
    int natural = 1;
  };
  /// The conflicting pairs of y (rolled-out trajectories) into conflicts_.
  void find_conflicts(const Iterate& y);
  /// The conflicting pairs of the rolled-out initial controls u_init_ (into conflicts_; trial_ as scratch), from
  /// which the ordered guesses start.
  void initial_conflicts();
  /// y_ = each agent's own plan with the others ignored (one sub-solve each from the initial controls); returns the
  /// sub-solve iterations (<= budget).
  int solo_plans(int budget);
  /// The candidate orders (winding per conflicting pair) into order_signs_.
  void candidate_orders();
  /// y_ from order_from_ and one ordered sweep for the given windings; returns sub-solve iterations.
  int ordered_guess(const std::vector<int>& winding, int budget);
  /// The order of every conflicting pair at y.
  void passing_of(const Iterate& y, std::vector<PassingPair>& out) const;
  int winding_of(const Iterate& y, int i, int j) const;
  /// Builds, ranks and polishes the candidates; true if `found` holds an equilibrium to return.
  bool search_orders(Result& found, Info& info, int& total_iter);
  /// The ordered guess of every candidate (order_u_) and its residual (info.orders); returns how many were built.
  int build_ordered_guesses(Info& info, int& total_iter);
  /// Newton from candidate c's guess (one attempt, order.polish_iter); true if it reached an equilibrium, then in out.
  bool polish_candidate(int c, Result& out, Info& info, int& total_iter);
  std::vector<ConflictPair> conflicts_;
  bool conflicts_known_ = false;           // conflicts_ was found in this solve (the search ran or was asked for)
  std::vector<std::vector<int>> order_signs_;
  std::vector<std::vector<Mat>> order_u_;  // per candidate: the ordered guess's controls (nu x T per agent)
  std::vector<Mat> order_from_;            // controls the ordered guesses start from (initial, or the solo plans)
  int attempt_cap_ = 0;                    // > 0: the current attempt ends at this total iteration count
  int iter_limit_ = 0;                     // the solve stops at this total iteration count (max_iter; the rescue's own)
  // Set-up steps.
  void list_and_allocate();  // constraint list of prob_ and every buffer sized by it
  void finish_update(Clock::time_point t0);
  // Solve steps, in the order solve() calls them.
  void load_initial_guess(const WarmStart* warm);
  void start_attempt(int attempt, const WarmStart* warm);
  /// States x_1..x_T of agent i in y from x_0 and its controls (the dynamics then hold exactly).
  void roll_out(Iterate& y, int i);
  AttemptEnd run_attempt(Info& info, int& total_iter);
  /// Where the solve is in its restart schedule (solve()).
  struct Schedule {
    int total_iter = 0;
    int escapes = 0;           // attempts started from a saddle (leave_saddle); they do not use up the schedule
    int br_attempts = 0;       // attempts from the best-response guess (inserted, as the escapes)
    bool from_saddle = false;  // the next attempt starts where leave_saddle left y_
    bool have_saddle = false;
    bool searched = false;     // the passing-order search ran between the restarts (search_between_restarts)
    int prior_attempts = 0;    // attempts of the solve before this schedule (the bounded start's), orders' aside
    int prior_escapes = 0;     // escapes from saddles before this schedule
    Result saddle;             // the first converged attempt the second-order test rejected (restart_on_saddle)
  };
  /// The restart schedule's attempts; true if res holds an equilibrium (converged, second-order test passed),
  /// otherwise res holds the last attempt's point and sc the first saddle, if any.
  bool run_schedule(Result& res, Schedule& sc, const WarmStart* warm);
  /// The passing-order search runs as a stage of the schedule (Settings::order, not before_newton): after restart
  /// attempt 3 (search_between_restarts) or, with fewer restarts, after the last one, given the result so far.
  bool rescue_wanted(const Info& info) const;
  /// The search after restart attempt 3 when no attempt found an equilibrium: true if it found one (then in res);
  /// otherwise the restarts go on with their own iteration budget.
  bool search_between_restarts(Result& res, Schedule& sc);
  /// The search as the rescue, with its own iteration budget; true if `found` holds an equilibrium.
  bool rescue(Result& found, Info& info, int& total_iter);
  /// The counters and timings of the whole solve (from) onto a result kept from part of it (to).
  void take_counters(Info& to, const Info& from) const;
  /// The settings allow the domain rescue (a domain box and a restart schedule, in a solver that is not itself a
  /// bounded game's): its nested solver is set up; the bounded start also runs only in the caller's game (role_).
  bool domain_rescue_enabled() const;
  /// Some attempt ended at a model's domain edge and none found an equilibrium: the domain rescue is worth running.
  bool domain_rescue_wanted(const Info& info) const;
  /// The domain rescue (solver_domain.cpp): the same game with every control whose model has a two-sided domain bounded
  /// to the domain box, solved by a nested solver from the initial guess (its own iteration budget, at most max_iter),
  /// then checked in this game from the bounded equilibrium and its multipliers (at most order.polish_iter
  /// iterations). `found` is converged if that point is an equilibrium of this game, otherwise `domain_edge` with the
  /// bounded game's equilibrium (feasible, some domain bound holding it). False if the bounded game has none.
  bool domain_rescue(Result& found, Info& info, int& total_iter);
  /// No stage before found an equilibrium: the bounded start is worth running.
  bool bounded_start_wanted(const Info& info) const;
  /// The bounded start (solver_domain.cpp): the same game with every two-sided domain control bounded to
  /// kBoundedStartFraction of the box its domain and its own bounds leave, solved by a nested solver from the initial
  /// guess (its own budget, at most max_iter), then this game's restart schedule again from that solve's controls and
  /// dynamics multipliers (its own budget, max_iter). True if `found` holds an equilibrium; otherwise info gets the
  /// counters, and `outer` that schedule's first saddle if it had none of its own.
  bool bounded_start(Result& found, Info& info, Schedule& outer);
  /// p = this game with each control that has a two-sided domain box bounded to `fraction` of the part of that box
  /// its own bounds leave (shrunk about that part's centre) where that is tighter than its own bounds (p null: only
  /// the answer); false if no bound changed. fraction 1: the domain box where it is tighter than the control's bounds.
  bool bounded_problem(Problem* p, double fraction);
  /// Which bounded games can run (domain_game_, start_game_), at the set-up and every update; their problems and the
  /// nested solver are built only when a solve first needs one (bounded_stale_: a failed schedule's rare path, which
  /// kept off the set-up 0.05 ms of a 2-car solve's 0.6 ms). Only a game's own solver has them (domain_rescue_enabled).
  void prepare_domain_rescue();
  /// domain_problem_, start_problem_ and the nested solver for the current problem and settings.
  void set_up_bounded_games();
  /// The nested solve of bounded game p (one of the two) from this solve's initial guess; its iterations and
  /// attempts count in total_iter and info.
  Result solve_bounded_game(const Problem& p, Info& info, int& total_iter);
  /// y_, the partition and the multipliers of this game's constraints from a result of a bounded game.
  void load_bounded_point(const Result& b);
  /// Timings, counters, initial guess and the restart offsets' random sequence at the start of a solve.
  void begin_solve(Info& info, const WarmStart* warm);
  /// y_, rho_ and the rules of the next attempt: from the best-response guess, the schedule's start or a saddle.
  void start_scheduled_attempt(int attempt, bool best_response, const WarmStart* warm, Schedule& sc, Info& info);
  /// A finished attempt converged and an attempt is left to look for a point that passes the second-order test.
  bool look_past_saddle(int attempt, bool best_response, const Schedule& sc, const Info& info) const;
  /// The kept saddle with the solve's counters and time.
  Result saddle_result(Schedule& sc, const Info& info) const;
  /// Appends an iterate's merit to the histories (and keeps the best one under a time limit).
  void record_iterate(double rnorm, int total_iter, Info& info);
  /// rho <- max(floor, min(rho_kappa rho, rho^rho_beta)).
  void lower_rho();
  /// One of the stall rules (Settings::stall) fires at this iteration's merit.
  bool stalling(double rnorm) const;
  /// On a stall: lower rho (restart rules) or polish; false ends the attempt (stalled or a numerical error).
  bool handle_stall(bool& polished, double& merit_now, bool& stalled, Info& info);
  /// The rolled-out iterate y_ brings two agents (or an agent and an obstacle) closer than
  /// (1 - settings_.restart.deep_overlap) times their collision distance at some step.
  bool deep_overlap() const;
  /// The globalisation rules of an attempt: the settings' first-attempt ones or the restart ones (rules_).
  void use_rules(bool restart_rules);
  /// Partition, multiplier numbering, residual and Jacobian at y_; false if the residual is undefined.
  bool assemble(bool first, Info& info);
  /// The stopping test: ||r|| < tol, feasibility, dynamics, rho at its floor and relative_stationarity() <=
  /// stationarity_tol (Settings::stationarity_tol; where that alone fails, the floor is lowered).
  bool converged(double rnorm);
  /// The largest over agents of the norm of its stationarity rows of r_, without the barrier forces of constraints
  /// with h < -second_order.gap, divided by cost_gradient_norm().
  double relative_stationarity();
  /// sqrt(sum over agents of ||dJ^i / d(x^i_1..T, u^i_0..T-1)||^2) at y_ (cost units per variable unit).
  double cost_gradient_norm();
  /// rho's floor, tol * barrier.rho_floor_factor (times rho_floor_scale_), and whether rho has reached it (to rounding).
  double rho_floor() const;
  bool at_rho_floor() const;
  /// Newton (or Levenberg-Marquardt) step from y_ into y_ with the line search; the accepted t, or 0.
  double take_step(double rnorm, Info& info);
  void write_result(Result& res, Info& info);
  bool past_deadline() const;
  bool qr_would_overrun() const;  // with a time limit: no QR of this solver measured yet, or the last one does not fit
  bool next_iteration_overruns();  // with a time limit: the deadline passed or the next iteration would pass it
  double time_left() const;  // (s) until the time limit (only meaningful with one)
  // The regularised least-squares step (after LU; under a time limit also in place of SparseQR) and its cost.
  double flop_rate() const;
  double normal_matrix_flops() const;
  bool bounded_least_squares(Vec& dy);

  /// h of constraint c at y; g = dh/d(own position or component) and H = its Hessian (set, not added to) where
  /// non-null.
  void eval_constraint(const Iterate& y, int c, double& h, Eigen::Vector2d* g, Eigen::Matrix2d* H) const;
  /// h of constraint c at y alone (eval_constraint without its derivatives).
  double constraint_value(const Iterate& y, int c) const;
  void eval_all_constraints(const Iterate& y, Vec& h) const;
  void classify(const Vec& h, bool first);
  void number_multipliers();
  /// Residual (and, if jac, the Jacobian triplets) at y with the current partition and rho.
  /// Returns false if a barrier constraint is not strictly satisfied (residual undefined).
  /// Also fills rc (complementarity (-h) z - rho of barrier constraints, primal-dual mode) and, if jac,
  /// rhs_ (the condensed right-hand side, i.e. the paper's barrier residual) and the triplets.
  bool evaluate(const Iterate& y, const Vec& h, bool jac, Vec& r, Vec& rc);
  /// Rows of the variables constraint c acts on: agent i's position (or bounded component) and, for a pair, agent j's.
  struct ConstraintRows {
    int ci[2] = {-1, -1}, cj[2] = {-1, -1};
    int n = 1;          // 2 for a position, 1 for a bounded component
    bool pair = false;  // cj is used
    bool pos = false;   // acts on a position (pairs and obstacles): has a Hessian
  };
  ConstraintRows constraint_rows(int c) const;
  /// Constraint c's terms of evaluate (c not released); false if it is a barrier constraint with h >= 0.
  bool add_constraint_terms(const Iterate& y, int c, bool jac, Vec& r, Vec& rc);
  void add_active_jacobian(int c, const ConstraintRows& q, const Eigen::Vector2d& g, const Eigen::Matrix2d& H,
                           double wi, double wj);
  void add_barrier_jacobian(const Iterate& y, int c, const ConstraintRows& q, double hv, const Eigen::Vector2d& g,
                            const Eigen::Matrix2d& H, double wi);
  double merit(const Vec& r, const Vec& rc) const { return std::sqrt(r.head(n_vars_).squaredNorm() + rc.squaredNorm()); }
  /// Primal-dual: recover dz of the barrier constraints from the condensed step.
  void recover_dual_step(const Iterate& y, const Vec& h, const Vec& rc, const Vec& dy, Vec& dz) const;
  /// Newton step into dy; false if every linear solver failed (or, with a time limit, the deadline passed
  /// before the least-squares fallback, or it would not fit: then timed_out_ is set).
  bool solve_linear(Vec& dy, Info& info);
  /// The linear solvers of solve_linear on rhs_ (Riccati) or neg_rhs_ and J_ (the others); false if one fails.
  bool solve_riccati(Vec& dy, Info& info);  // also false if its step fails the residual check
  bool solve_lu(Vec& dy, Info& info);
  bool solve_lscg(Vec& dy, bool& timed_out);
  bool solve_least_squares(Vec& dy, Info& info);  // the regularised least-squares step (bounded_least_squares)
  bool solve_qr(Vec& dy, Info& info);  // or the bounded least-squares step under a time limit
  bool solve_levenberg_marquardt(double nu, Vec& dy);
  /// Backtracking line search along dy_ from y_ into trial_; returns the accepted t or 0.
  double line_search(double merit0);
  /// The step, of the trial t, at which the first constraint satisfied at y_ and violated at the trial crosses
  /// (secant estimate); 0 if a constraint violated at y_ grew (line_search.cpp).
  double step_to_first_crossing(double t) const;
  /// The largest t' <= t at which every state and control bound in the barrier keeps 1 - 0.99 of its slack along dy_
  /// (the bounds are linear in the variables, so this is exact).
  double bound_step(double t) const;
  void apply_step(const Iterate& y, const Vec& dy, double t, Iterate& out) const;
  /// The largest t' <= t at which y_'s held controls stay in their models' domain boxes along dy_ (domain_fraction).
  double domain_step(double t);
  /// Agent i's control component q's domain box (Dynamics::control_domain shrunk to domain_fraction); false if the
  /// domain is one-sided or free.
  bool domain_box(int i, int q, double& lo, double& hi);
  double violation_sum(const Vec& h) const;
  /// Barrier constraints with h >= -gap become equalities, their multiplier the barrier's dual estimate (the stall's
  /// polish, and the nearly active contacts of a saddle an escape leaves). True if any did.
  bool hold_near_contacts(const Vec& h, double gap);

  Problem prob_;
  Settings settings_;
  int N_ = 0, T_ = 0, nx_ = 0, nu_ = 0, n_primal_ = 0;
  bool per_agent_multipliers_ = false;
  std::vector<Constraint> cons_;
  std::vector<ConstraintState> state_, pattern_state_;
  std::vector<int> mu_col_, mu2_col_;  // variable/row index of each constraint's multiplier(s), -1 if none
  int n_vars_ = 0;
  double rho_ = 0;
  BarrierMode barrier_ = BarrierMode::PrimalDual;  // barrier form of the current attempt
  /// Globalisation rules of the current attempt (start_attempt): barrier.rho_progress and
  /// line_search.violation_memory (rho never lowered on a stall) in attempt 0, the restart group's in later attempts;
  /// the backtracking to just before a crossing in every attempt of the game itself.
  struct AttemptRules {
    double rho_progress = 0;
    int violation_memory = 1;
    bool rho_on_stall = false;
    // In the game's attempts, not its sub-solves: the first trial stops before the bounds (bound_step), a trial that
    // crosses constraints is followed by one just before the crossing (step_to_first_crossing).
    bool backtrack_to_crossing = false;
  };
  AttemptRules rules_;

  double setup_time_ = 0, update_time_ = 0;  // (s) last set-up; updates since the last solve
  int structure_version_ = 0;
  int setups_ = 0;                            // set-ups since the last solve (setup + structural updates)

  // Solve state.
  Clock::time_point t_start_;
  std::vector<Mat> u_init_, lam_init_;  // initial guess (per agent nu x T, nx x T)
  bool have_mu_ = false;
  std::mt19937 rng_;                    // restart offsets: the same sequence in every solve
  std::normal_distribution<double> noise_{0.0, 1.0};
  std::vector<double> merits_;          // merit per iteration of the current attempt
  std::vector<double> violations_;      // total violation per iteration of the current attempt
  bool timed_out_ = false;              // the deadline passed inside a step
  int edge_attempts_ = 0;               // attempts of this solve that ended domain_edge
  // The next attempt's first partition holds constraints within barrier.margin as equalities (attempts from a
  // guess built by single-agent sub-solves: the best-response attempt, the ordered guesses' polishes).
  bool start_holds_contacts_ = false;
  bool keep_partition_ = false;         // the next attempt starts with the partition as set (domain rescue)
  bool domain_blocked_ = false;         // the last line search: a control at its domain box's edge, the step out
  bool newton_at_edge_ = false;         // this iteration's Newton step was blocked so (domain_edge if it ends here)
  double last_qr_seconds_ = 0;          // duration of this solver's last SparseQR factorisation (s)
  double ldlt_flop_rate_ = 0;           // measured speed of its last regularised LDLT factorisation (flop/s)
  Clock::time_point iteration_start_;   // with a time limit: when the current iteration began
  bool have_iteration_start_ = false;
  double last_iteration_seconds_ = 0;
  mutable Vec row_count_;               // entries per row of J_ (cost of forming J'J)
  double best_merit_ = 0;               // with a time limit: lowest merit seen, its iterate in best_seen_

  // buffers (allocated in setup)
  Iterate y_, trial_, best_seen_;
  StageLayout layout_;
  std::vector<StagePattern> stage_patterns_;  // per agent: its model's Jacobian entries (set up and on update)
  StageWorkspace stage_;
  Mat fx_, Atmp_, Btmp_;
  Vec dom_lo_, dom_hi_;  // one agent's control domain (domain_box)
  Vec h_, h_trial_, r_, r_trial_, dy_, rc_, rc_trial_, rhs_, dz_, neg_rhs_, lin_res_;
  Vec stationarity_;  // relative_stationarity's copy of r_'s primal rows
  double rho_floor_scale_ = 1;  // < 1 once the stationarity test has failed at the floor in this attempt
  std::vector<Triplet> trip_;
  SpMat J_;
  Eigen::SparseLU<SpMat, Eigen::COLAMDOrdering<int>> lu_;
  bool lu_analyzed_ = false;
  bool J_built_ = false;  // J_ holds this iteration's matrix (the Riccati path does not need it)
  // Levenberg-Marquardt tries of one iteration share J'J (diagonal stored explicitly) and J'r; only the numeric
  // factorisation depends on nu. Invalidated with J_built_. The ordering and symbolic LDLT depend only on J'J's
  // pattern (in practice on the partition) and are kept while it is unchanged (checked entry by entry).
  SpMat lm_JtJ_;
  NormalMatrix lm_normal_;  // forms lm_JtJ_, reusing the product's plan while J's pattern is unchanged
  Vec lm_Jtr_;
  ShiftedLDLT lm_ldlt_;
  bool lm_ready_ = false;
  bool lm_analyzed_ = false;
  StageRiccati riccati_;
  void build_J();
  /// Second-order test of y_ (defined in second_order.cpp): fills info.second_order; true if every agent passes.
  bool check_second_order(Info& info);
  bool second_order_wanted(const Info& info) const;  // whether write_result runs check_second_order
  /// Each constraint's multiplier for its agent i (w_i) and its other agent j (w_j) at y_: equality multiplier,
  /// barrier dual (or -rho/h), 0 if released.
  void constraint_weights(Vec& w_i, Vec& w_j) const;
  /// Steering away from the saddle in y_, whose second-order test just failed (second_order.cpp): records the
  /// inertia correction of the failing agents (second_order.inertia) and, if an escape is left (escapes <
  /// second_order.escapes), moves them along negative curvature and prepares y_, rho_ and the partition for an attempt
  /// from there. Returns true if it did (y_ is unchanged otherwise).
  bool leave_saddle(int escapes);
  /// Moves agent a of trial_ along its direction of negative curvature, both signs, the step shortened until its
  /// Lagrangian (weights w_i, w_j) falls by a tenth of the quadratic model's prediction and its constraints stay as
  /// feasible as at the saddle (values h0); rolls a out either way. True if it moved.
  bool escape_agent(int a, const Vec& h0, const Vec& w_i, const Vec& w_j);
  /// The escape attempt's partition at y_ (kept by the attempt, keep_partition_): contacts within barrier.margin held
  /// as equalities, the other constraints in the barrier on the central path of rho = kEscapeRho.
  void start_escape_partition();
  /// Agent a's shooting Lagrangian J^a + sum_c w_c h_c at y (its constraints only) and the largest of their h.
  double agent_lagrangian(int a, const Iterate& y, const Vec& w_i, const Vec& w_j, double& max_h) const;
  /// Adds the inertia correction (second_order.inertia) to this iteration's Newton matrix (trip_).
  void add_inertia_correction(double rnorm);
  bool inertia_on_ = false;  // this attempt applies the inertia correction
  std::vector<double> inertia_delta_;  // per agent: delta of the inertia correction (cost units per control unit^2)
  std::shared_ptr<SecondOrderCheck> second_order_;
  /// Single-agent sub-solvers of the best response, one per agent, built at first use after a set-up or an update
  /// (br_stale_); each has the problem's obstacles followed by the N-1 others' positions (best_response.cpp).
  std::vector<std::unique_ptr<Solver>> br_;
  // The bounded games: both bound the same controls (their constraint lists are the same), so one nested solver
  // holds whichever is being solved (bounded_holds_start_) and is updated to the other when that one is needed.
  Problem domain_problem_;                   // the domain rescue's: bounded to the domain box
  Problem start_problem_;                    // the bounded start's: bounded to kBoundedStartFraction of it
  bool domain_game_ = false;                 // the domain rescue can run (domain_problem_ bounds some control)
  bool start_game_ = false;                  // the bounded start can run (start_problem_ bounds some control)
  std::unique_ptr<Solver> bounded_solver_;   // absent when neither can run
  bool bounded_holds_start_ = false;         // bounded_solver_ holds start_problem_ now (else domain_problem_)
  WarmStart bounded_warm_;                   // its initial guess: this solve's
  std::vector<int> bounded_index_;           // per constraint of this game: its index in the bounded games' list
  /// What this solver solves for: the caller's game; a bounded game (none of its own); a best-response
  /// sub-solve (the domain rescue, not the bounded start: a guess's sub-solve need not find an equilibrium).
  enum class Role { Game, BoundedGame, SubSolve };
  Role role_ = Role::Game;
  bool br_stale_ = true;
  bool bounded_stale_ = true;  // the bounded games and their solver predate the last set-up or update
  Eigen::MatrixXd br_positions_;  // (T+1) x 2 buffer: one other agent's rolled-out positions
  WarmStart br_warm_;             // the sub-solve's warm start (its agent's current controls)
};

}  // namespace rd3g
