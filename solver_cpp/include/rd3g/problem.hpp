// Plain structs describing a game, the solver settings and the result (OSQP/proxsuite style).
#pragma once
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "rd3g/dynamics.hpp"

namespace rd3g {

constexpr double kInf = std::numeric_limits<double>::infinity();

/// Quadratic tracking cost of one agent, all weights diagonal (stored as vectors):
///   J = sum_{k=0}^{T-1} u_k' R u_k + sum_{k=1}^{T-1} [(x_k-r_k)' Q_ref (x_k-r_k) + x_k' Q x_k]
///       + (x_T-r_T)' Qf_ref (x_T-r_T) + x_T' Qf x_T,
/// with r_k = x_ref, or column k-1 of x_ref_steps when given (a stage-varying reference, e.g. a racing line).
struct QuadraticCost {
  Vec x_ref;   ///< reference state (state units)
  Mat x_ref_steps;  ///< optional reference per step k = 1..T, nx x T (column k-1); empty = x_ref at every step
  Vec Q_ref;   ///< weights on x - x_ref (1/state unit^2)
  Vec Q;       ///< weights on x itself
  Vec R;       ///< weights on u (1/control unit^2)
  Vec Qf_ref;  ///< terminal weights on x_T - x_ref
  Vec Qf;      ///< terminal weights on x_T
  /// Reference r_k of x_k (k = 1..T).
  Eigen::Ref<const Vec> reference(int k) const {
    if (x_ref_steps.cols()) return x_ref_steps.col(k - 1);
    return x_ref;
  }
};

/// Cost coupling agents: agent i pays weight * (x^j[index] - x^i[index]) summed over k = 1..T for every
/// other agent j (the racing "lead" term Q_d (s_j - s_i) with index = progress coordinate).
/// Linear, so its Hessian is zero; it changes the equilibrium through the gradient.
struct LeadCost {
  double weight = 0.0;  ///< Q_d (cost units per state unit)
  int index = 0;        ///< state component measuring progress (e.g. s in Frenet coordinates)
};

enum class CollisionForm { Distance, Squared };

/// d_min of one pair of agents, replacing CollisionSpec::min_distance (and its per-step values) for that pair: e.g.
/// a receding-horizon planner relaxes the one pair that starts closer than d_min and keeps the others nominal.
struct PairDistance {
  int i = 0, j = 0;           ///< the two agents (distinct, either order: the pair is unordered)
  double min_distance = 0.0;  ///< d_min (m)
  Vec min_distance_steps;     ///< optional d_min per step k = 1..T (m), length T; empty = min_distance at every step
  /// d_min at step k (1..T), m.
  double at(int k) const { return min_distance_steps.size() ? min_distance_steps[k - 1] : min_distance; }
};

/// Pairwise collision avoidance between every pair of agents at k = 1..T:
///   Distance: h = d_min - ||A_k (p^i - p^j)|| <= 0;  Squared: h = d_min^2 - ||A_k (p^i - p^j)||^2 <= 0,
/// with p the state components (pos_x, pos_y), d_min the pair's entry of pair_distances, else min_distance, and
/// A_k = diag(pos_x_scale_steps[k-1], 1) (identity when empty): an ellipse, e.g. in Frenet coordinates (s, ey) an
/// arc-length gap is only (1 - kappa ey) times as long in the plane, a lateral gap is exact.
struct CollisionSpec {
  bool enabled = true;
  double min_distance = 0.0;  ///< d_min (m) of every pair not in pair_distances
  /// Optional d_min per step k = 1..T (m), length T; empty = min_distance at every step. Lets a
  /// receding-horizon planner start from a separation below d_min and demand its recovery.
  Vec min_distance_steps;
  /// Pairs with their own d_min (at most one entry per pair); usually empty or a few entries, so looked up by a scan.
  std::vector<PairDistance> pair_distances;
  CollisionForm form = CollisionForm::Distance;
  int pos_x = 0, pos_y = 1;   ///< state indices of the position used by the constraint
  /// Optional scale (> 0) of the pos_x separation per step k = 1..T, length T; empty = 1. Applies to pairs and
  /// obstacles alike.
  Vec pos_x_scale_steps;
  /// The scale of the pos_x separation at step k (1..T).
  double x_scale(int k) const { return pos_x_scale_steps.size() ? pos_x_scale_steps[k - 1] : 1.0; }
  /// The entry of pair_distances for agents i and j, or nullptr (the pair uses min_distance).
  const PairDistance* pair_distance(int i, int j) const {
    for (const PairDistance& q : pair_distances)
      if ((q.i == i && q.j == j) || (q.i == j && q.j == i)) return &q;
    return nullptr;
  }
  /// d_min of agents i and j at step k (1..T), m.
  double at(int i, int j, int k) const {
    if (const PairDistance* q = pair_distance(i, j)) return q->at(k);
    return min_distance_steps.size() ? min_distance_steps[k - 1] : min_distance;
  }
};

/// A moving obstacle every agent avoids (used by a single-agent MPC that predicts its opponent):
/// h = d_min - ||A_k (p^i_k - o_k)|| <= 0 for k = 1..T (form and A_k as in CollisionSpec).
struct Obstacle {
  Eigen::MatrixXd positions;  ///< (T+1) x 2, o_k in the same coordinates as the agents' positions
  double min_distance = 0.0;  ///< (m)
  Vec min_distance_steps;     ///< optional d_min per step k = 1..T (m), as in CollisionSpec
  /// d_min at step k (1..T), m.
  double at(int k) const { return min_distance_steps.size() ? min_distance_steps[k - 1] : min_distance; }
};

struct Problem {
  int horizon = 0;  ///< T, number of control steps
  double dt = 0.0;  ///< (s), informational: each Dynamics carries its own discretisation
  std::vector<std::shared_ptr<const Dynamics>> dynamics;  ///< per agent; all agents share nx, nu
  std::vector<Vec> x0;                                    ///< per agent initial state
  std::vector<QuadraticCost> costs;                       ///< per agent
  std::vector<LeadCost> lead;                             ///< per agent (weight 0 = none)
  CollisionSpec collision;
  std::vector<Vec> u_min, u_max;  ///< per agent control bounds (+-inf = none), length nu
  std::vector<Vec> x_min, x_max;  ///< per agent state bounds on x_1..x_T (+-inf = none), length nx
  std::vector<Obstacle> obstacles;

  int num_agents() const { return static_cast<int>(dynamics.size()); }
};

enum class BarrierMode {
  Primal,      ///< paper: Newton on the barrier gradient -rho/h grad h (Hessian term rho/h^2 grad h grad h')
  PrimalDual,  ///< default: the same log barrier in primal-dual form: dual z with (-h) z = rho, Hessian term
               ///< z/(-h) grad h grad h' (IPOPT); better conditioned off the central path, same solutions
};

enum class LinearSolver {
  Riccati,   ///< default: variational multipliers; a stage-wise (coupled, nonsymmetric) Riccati recursion, with
             ///< the multipliers of equality-held constraints eliminated by a Schur complement; SparseLU if it
             ///< fails its residual check
  SparseLU,  ///< variational multipliers (mu_ij = mu_ji), square system, Eigen SparseLU with reused symbolic analysis;
             ///< a regularised least-squares step (LDLT of J'J + delta I) where LU finds the matrix singular
  LSCG,      ///< paper: per-agent multipliers, least-squares conjugate gradient, SparseQR fallback
  SparseQR,  ///< paper's fallback alone: per-agent multipliers, Eigen SparseQR
};

/// Barrier weight rho and the barrier's form (Settings::barrier).
struct BarrierSettings {
  BarrierMode mode = BarrierMode::PrimalDual;
  double rho_init = 0.01;  ///< initial barrier weight rho (measured: 0.1 and 1.0 stall more often on the merges)
  /// rho never goes below tol * rho_floor_factor (paper: 0.1; 0.01 passes the benchmark's stationarity check on 2-3
  /// car merges that the paper's floor failed). The barrier leaves a force of about rho/|h| on constraints near
  /// activity, i.e. the answer is an equilibrium of a game perturbed by O(rho).
  double rho_floor_factor = 0.01;
  double rho_kappa = 0.2;  ///< rho <- max(tol * rho_floor_factor, min(rho_kappa rho, rho^rho_beta))
  double rho_beta = 1.5;
  /// Attempt 0 (restarts: RestartSettings::rho_progress). 0: lower rho after each step (see rho_after_step). > 0:
  /// only once ||r|| <= rho_progress * rho, i.e. the barrier subproblem is nearly solved (IPOPT's monotone rule).
  double rho_progress = 0.0;
  /// Where the rho_progress in force is 0: rho is lowered after a step the line search took at least this fraction
  /// of (dimensionless, in [0, 1]; 0 = after every step, the paper). After a shorter step rho keeps its weight: the
  /// line search cut the step at constraints that a weaker barrier would let the next step cross too.
  double rho_after_step = 0.5;
  double margin = 1e-4;  ///< (constraint units) released constraints re-enter the barrier once h < -margin
};

/// Backtracking line search on ||r|| and its Levenberg-Marquardt fallback (Settings::line_search).
struct LineSearchSettings {
  double alpha = 1e-2;  ///< sufficient decrease: ||r(y+t dy)|| <= (1 - alpha t) ||r(y)||
  double beta = 0.5;    ///< step shrink factor, in (0, 1)
  /// Trials before the line search fails (the smallest t is beta^(max_steps-1), 2e-3 at beta 0.5): a shorter step
  /// lowers ||r|| by under alpha t = 2e-5 of itself, and trials below it are where a hopeless attempt spends its
  /// time before Levenberg-Marquardt, a stall or a restart takes over (docs/benchmarks.md, "Ten line-search steps").
  int max_steps = 10;
  /// Non-monotone violation test of attempt 0 (restarts: RestartSettings::violation_memory): a trial may not raise
  /// the total violation above the largest of the last violation_memory iterates' (1 = monotone, the paper's rule).
  int violation_memory = 1;
  /// When the Newton step fails the line search (near-singular Jacobian), try Levenberg-Marquardt steps
  /// d = -(J'J + nu I)^-1 J' r, a descent direction for ||r||^2, with nu = 1e-6 * 10^q ||r||, q = 0..lm_tries-1
  /// (the first that passes the line search is taken). 0 = off.
  int lm_tries = 4;
  /// Steps stop just before a crossing (docs/solver.md, "Backtracking to just before a crossing"): the first trial
  /// at 0.99 of the step to the first state or control bound in the barrier (bounds are linear: exact), and after a
  /// trial t that crosses constraints satisfied at the current point, once rho has fallen below barrier.rho_init,
  /// the next trial is the larger of beta t and 0.99 of the secant estimate of the first crossing. false = the
  /// full step, then beta t, the paper's. In the game's own attempts only, not in its best-response and
  /// passing-order sub-solves.
  bool to_crossing = true;
};

/// The Newton system's linear solver (Settings::linear).
struct LinearSettings {
  LinearSolver solver = LinearSolver::Riccati;
  double lscg_tol = 1e-10;   ///< LSCG relative tolerance
  int lscg_max_iter = 2000;
};

/// When an attempt has stopped making progress (Settings::stall); 0 = off for each window.
struct StallSettings {
  /// An attempt whose merit fell by less than 1% over window iterations has stalled (polish, then lower rho with
  /// the restart rules, or restart).
  int window = 8;
  /// With rho at its floor: ||r|| fell by less than 1e-4 of itself over floor_window iterations (no rho decrease
  /// is left to help).
  int floor_window = 3;
  /// A crawl: ||r|| still above crawl_ratio times its value crawl_window iterations earlier (barrier subproblems
  /// that accept tiny steps for hundreds of iterations).
  int crawl_window = 40;
  double crawl_ratio = 0.5;  ///< in (0, 1]
  /// On a stall, before restarting, barrier constraints with h >= -polish_gap (constraint units) are held as
  /// equalities (once per attempt); the usual partition rules release them again. 0 = off.
  double polish_gap = 1e-3;
};

/// The restart schedule (Settings::restart; docs/solver.md, "Restarts"). When an attempt stalls or its line search
/// fails, restart from the initial guess with rho_init * 10 (attempt 1), the other barrier form (2), both (3), then
/// the same four again and again from the initial controls plus a seeded constant offset per agent and control of
/// std 0.2 control units (attempts 4..count). Every attempt counts towards iterations, max_iter and the reported time.
struct RestartSettings {
  int count = 19;           ///< restart attempts after attempt 0 (0 = none)
  /// The rules of every restart attempt, and of attempt 0 when its initial guess overlaps deeply (deep_overlap):
  /// BarrierSettings::rho_progress, LineSearchSettings::violation_memory, and lowering rho on a stall above its
  /// floor instead of polishing or restarting (rho_on_stall; attempt 0 never does).
  double rho_progress = 10.0;
  int violation_memory = 4;
  bool rho_on_stall = true;
  /// Attempt 0 uses the restart rules when the rolled-out initial guess brings two agents (or an agent and an
  /// obstacle) closer than (1 - deep_overlap) * d_min at some step (fraction of the collision distance; > 1: never).
  double deep_overlap = 0.5;
};

/// Iterated best response as a restart variant (Settings::best_response; docs/solver.md, "Restarts"): an extra
/// attempt, inserted before restart attempt 1, starts from the controls that `rounds` Gauss-Seidel
/// sweeps over the agents reach from the initial controls: each agent in turn solves its own problem alone (with
/// the others' current rolled-out positions as moving obstacles at (1 + margin) times the collision distance),
/// warm-started, with at most max_iter iterations, `restarts` restarts and no best response of its own. A sub-solve
/// iteration counts 1/N of a game iteration in Info::iterations and max_iter (rounded up per attempt). The attempt
/// runs from rho_init with attempt 0's rules. rounds 0 = off; never with restart.count 0.
struct BestResponseSettings {
  int rounds = 1;
  int max_iter = 100;   ///< per single-agent sub-solve (Newton iterations)
  double margin = 0.1;  ///< fraction of the collision distance, >= 0: the guess starts strictly inside the barrier
  /// Restart attempts per best-response sub-solve, >= 0. 0: a sub-solve that stalls returns its controls as they
  /// are, a guess that the game's attempt corrects (docs/benchmarks.md, "No restarts in the best-response
  /// sub-solves"). The passing-order search's solo plans and ordered guesses keep one restart: an ordered guess
  /// must reach its requested order.
  int restarts = 0;
};

/// Second-order test after convergence and steering away from saddles (Settings::second_order).
struct SecondOrderSettings {
  /// Each agent's constraints with h >= -gap (constraint units) and a positive multiplier are held as equalities;
  /// the agent passes if the smallest eigenvalue of its reduced Hessian is >= -tol * max(1, its largest
  /// |eigenvalue|). A converged point that fails is reported as Status::Saddle. gap < 0 turns the test off.
  double gap = 1e-2;
  double tol = 1e-6;
  /// A converged attempt that fails the test is kept aside and the restart schedule goes on, looking for a point
  /// that passes; if none is found the kept saddle is returned (status saddle).
  bool restart_on_saddle = true;
  /// Attempts from a saddle along negative curvature (with restart_on_saddle; docs/solver.md, "Second-order test"):
  /// each failing agent moves its controls along +-its eigenvector of the smallest eigenvalue, steps of 1 control
  /// unit, line_search.beta, beta^2, ... until its shooting Lagrangian falls enough with its constraints kept
  /// inside the barrier margin; Newton runs again from there at rho = 0.01. At most `escapes` per solve
  /// (0 = off); they count in attempts, iterations, max_iter and time.
  int escapes = 2;
  /// Per-agent inertia correction in the attempts from a saddle: every agent that has failed the test gets
  /// delta = inertia * |its smallest eigenvalue| added on its control rows of the Newton matrix, scaled by
  /// min(1, ||r|| / ||r|| at the attempt's first iteration) (a proximal term that vanishes at convergence).
  /// Dimensionless factor; 0 = off.
  double inertia = 1.5;
};

/// Passing-order search (Settings::order; docs/solver.md, "Passing order"). The conflicting pairs are those whose
/// rolled-out initial guess comes closer than their collision distance; an order gives each the sign of its winding
/// (+1: p_j - p_i turns counterclockwise over the horizon, i < j), which says who passes first and on which side. Per
/// candidate order an ordered guess is built by one Gauss-Seidel sweep of single-agent sub-solves (the best-response
/// sub-solvers) in agent order, in which the lower agent of a conflicting pair ignores the higher, and the higher sees
/// the lower's disc moved by `offset` d_min towards the side it must not take (radius grown by as much). The `polish`
/// candidates with the lowest residual ||r|| at their guess are polished by Newton, each an attempt of at most
/// `polish_iter` iterations; the first (by guess residual) that converges and passes the second-order test is
/// returned, the others are reported in Info::orders. Sub-solve iterations count 1/N of a game iteration, as in the
/// best-response restart.
/// By default the search is a stage of the restart schedule, the rescue: it runs when attempt 0, the best-response
/// attempt, restart 1 and the escapes from saddles have ended without an equilibrium, before restarts 2.. (after the
/// last restart if restart.count < 2; never with restart.count 0), so a solve the schedule finishes within restart 1
/// is unchanged, and if the search finds nothing the later restarts run as without it.
/// The rescue has its own iteration budget beyond Settings::max_iter: at most max_iter (of this group) game
/// iterations for the agents' solo plans (which define the conflicting pairs) and per guess, polish_iter per polished
/// candidate, and never more than Settings::max_iter; the time limit bounds it as every attempt.
/// With before_newton the search runs before attempt 0 instead, within max_iter, and the schedule runs after it
/// (with the iterations left) only if no candidate reached an equilibrium.
struct PassingOrderSettings {
  /// Candidate orders built (0 = off): every one of the 2^P orders of P conflicting pairs if 2^P <= candidates,
  /// else the rolled-out guess's own order, its single flips, then seeded random orders, up to `candidates`.
  int candidates = 4;
  int polish = 2;          ///< candidates polished by Newton (best guess residual first), >= 1 (at most candidates)
  int polish_iter = 150;   ///< Newton iterations per polished candidate (game iterations), >= 1
  int max_iter = 50;       ///< Newton iterations per single-agent sub-solve of an ordered guess, >= 1
  double offset = 1.0;     ///< displacement of a leader's disc, fraction of the collision distance, finite, >= 0
  bool before_newton = false;  ///< search before attempt 0 (every solve with a conflicting pair), not as the rescue
};

/// Every setting of RD3G, grouped by concern (OSQP/proxsuite style); one documented default per field.
struct Settings {
  double tol = 5e-4;   ///< stop when ||r||_2 < tol (and the other conditions hold)
  /// Newton iterations of the restart schedule, all attempts together. The stages after a schedule that found no
  /// equilibrium have budgets of their own: the order rescue up to as many, the domain rescue's and the bounded
  /// start's bounded games a nested solve each, and the bounded start's second schedule max_iter again.
  int max_iter = 1000;
  /// (s), 0 = none. Checked every iteration, between Levenberg-Marquardt tries, inside LSCG (in chunks of 50
  /// iterations) and before a least-squares step or a SparseQR factorisation. The least-squares step (LDLT of
  /// J'J + delta I; the fallback of a singular Newton matrix on the Riccati / SparseLU path, with or without a
  /// limit) is started only if its flop count fits; SparseQR (LSCG's fallback, SparseQR) only if this solver's
  /// previous QR took less than the time left (never before one was measured), else the least-squares step takes
  /// its place. The overshoot is at most one line search, one LSCG chunk or one factorisation. On time_limit the
  /// result is the iterate with the lowest merit seen.
  double time_limit = 0.0;
  double violation_tol = 1e-6;   ///< converged only if every h <= violation_tol (constraint units)
  double dynamics_tol = 1e-7;    ///< converged only if every dynamics defect <= dynamics_tol (state units)
  /// Converged only if every agent's stationarity rows of the residual, without the barrier forces of constraints
  /// farther than second_order.gap from activity, have a norm <= stationarity_tol times the norm of all agents' own
  /// cost gradients (dimensionless; 0 = off). tol alone is absolute: a game whose cost gradients are small (0.07)
  /// stopped at a relative stationarity of 1e-3 and above. While this test fails with rho at its floor, the floor is
  /// lowered by barrier.rho_kappa (the far constraints' barrier force is about rho / |h|). Not in sub-solves.
  double stationarity_tol = 5e-4;
  /// Keep the controls in their models' domains (Dynamics::control_domain; the bicycles: |delta| < pi/2): a step is
  /// shortened so that no control leaves its domain's box shrunk about the centre to domain_fraction of its
  /// half-width. Dimensionless, in [0, 1); 0 = off (docs/solver.md, "Staying in the model's domain").
  double domain_fraction = 0.99;
  bool verbose = false;
  BarrierSettings barrier;
  LineSearchSettings line_search;
  LinearSettings linear;
  StallSettings stall;
  RestartSettings restart;
  BestResponseSettings best_response;
  SecondOrderSettings second_order;
  PassingOrderSettings order;
};

/// stalled: every attempt (see restarts) stopped making progress before max_iter.
/// saddle: the first-order conditions hold but some agent's own problem is not at a local minimum there
/// (Info::second_order), i.e. the point is not a local equilibrium.
/// domain_edge: the last attempt stopped (its line search failed, or it stalled) because its Newton step pointed out
/// of a model's control domain (Dynamics::control_domain, held by domain_fraction) at a control already at the
/// domain box's edge: the iterates are pushed against the model's singular point (the bicycles' |delta| = pi/2), so
/// the game as posed has no equilibrium there that the solver can reach inside the domain; bound that control
/// (u_min/u_max) inside the domain to pose one whose equilibrium may hold the bound.
enum class Status { Converged, MaxIterations, LineSearchFailed, NumericalError, TimeLimit, Stalled, Saddle, DomainEdge };
std::string status_name(Status s);

/// Timings in seconds. total, assembly, linear_solve and line_search are accumulated over the whole solve
/// (total = the solve's wall time); setup is the duration of the solver's last set-up (validation,
/// constraint list, allocation; the set-up may be older than this solve) and update the time spent in
/// update calls since the previous solve.
struct Timings {
  double total = 0, assembly = 0, linear_solve = 0, line_search = 0;
  double setup = 0, update = 0;
};

/// The order of one conflicting pair (its rolled-out initial guess comes closer than d_min) at a returned point.
struct PassingPair {
  int i = 0, j = 0;  ///< the agents, i < j
  int winding = 0;   ///< +1: p_j - p_i turns counterclockwise over k = 0..T, -1: clockwise (identifies the order)
  int first = 0;     ///< the agent ahead of the other along its own heading at their closest approach
  int side = 0;      ///< +1: the other agent passes on first's left, -1: on its right
  double gap = 0;    ///< (m) their smallest distance over k = 1..T
};

/// One candidate order of the passing-order search (Settings::order).
struct OrderCandidate {
  std::vector<int> requested;  ///< winding per conflicting pair (Info::passing_order's pairs) asked of its guess
  std::vector<int> found;      ///< winding per pair at the polished point (empty unless it is an equilibrium)
  double guess_residual = 0;   ///< ||r|| at the ordered guess (rho_init, no multipliers): the ranking
  bool polished = false;
  Status status = Status::MaxIterations;  ///< of the polish (converged, saddle, stalled, ...), if polished
  int iterations = 0;          ///< Newton iterations of the polish
  bool equilibrium = false;    ///< converged and passed the second-order test
  bool returned = false;       ///< the solve returned this candidate's point
  std::vector<Mat> u;          ///< per agent T x nu: the polished point's controls if it converged (else empty)
};

struct Info {
  Status status = Status::MaxIterations;
  int iterations = 0;
  double residual_norm = 0;    ///< final ||r||_2
  double max_violation = 0;    ///< max(0, max h) over all constraints (constraint units)
  double rho = 0;              ///< final barrier weight
  int active_constraints = 0;  ///< constraints held as equalities at the end
  int symbolic_factorizations = 0;  ///< how often the sparse pattern was analysed
  int qr_fallbacks = 0;        ///< linear solves that fell back to a least-squares step (after LU or LSCG failed)
  int riccati_solves = 0;      ///< Newton steps solved by the stage-wise Riccati recursion
  int lm_steps = 0;            ///< iterations that took a Levenberg-Marquardt step instead of Newton
  int attempts = 0;            ///< 1 + restarts used (escapes from saddles included)
  int saddle_escapes = 0;      ///< attempts started from a saddle along negative curvature (Settings::second_order.escapes)
  int best_response_attempts = 0;    ///< attempts started from an iterated-best-response guess (0 or 1)
  /// Newton iterations of its single-agent sub-solves, unscaled (iterations includes them divided by N, rounded up)
  int best_response_iterations = 0;
  int setups = 0;              ///< set-ups since the previous solve (setup, or an update that changed the constraint list)
  /// Per agent: smallest eigenvalue of the reduced Hessian of its Lagrangian at the returned point (cost units per
  /// control unit^2; +inf = its active constraints leave no free direction); empty if the test is off.
  std::vector<double> second_order;
  /// The conflicting pairs of the initial guess (of the solo plans in a point the order rescue returns) and the order
  /// the returned point gives them; filled only when the passing-order search ran (else empty: Solver::passing_order
  /// computes it on demand).
  std::vector<PassingPair> passing_order;
  std::vector<OrderCandidate> orders;  ///< the passing-order search's candidates (empty if it did not run)
  int order_attempts = 0;              ///< polish attempts of the passing-order search
  int order_iterations = 0;            ///< Newton iterations of its ordered guesses' sub-solves, unscaled
  /// Newton iterations of the domain rescue's bounded game (0 if it did not run; iterations includes them)
  int domain_iterations = 0;
  /// Newton iterations of the bounded start's bounded game (0 if it did not run; iterations includes them, and the
  /// schedule run after it counts as every attempt)
  int bounded_start_iterations = 0;
  std::vector<double> residual_history;  ///< ||r|| at the start of every iteration (and the final one)
  std::vector<double> step_history;      ///< accepted line-search step t per iteration
  Timings timings;
};

/// Initial guess / warm start. Empty members mean "use the default" (zero controls, zero multipliers).
struct WarmStart {
  std::vector<Mat> u;       ///< per agent T x nu
  std::vector<Mat> lambda;  ///< per agent T x nx
  Vec mu;                   ///< one per constraint in Solver::constraint order
};

struct Result {
  std::vector<Mat> x;       ///< per agent (T+1) x nx
  std::vector<Mat> u;       ///< per agent T x nu
  std::vector<Mat> lambda;  ///< per agent T x nx, dynamics multipliers
  Vec mu;                   ///< per constraint: equality multiplier (active) or barrier-implied -rho/h (inactive)
  Vec h;                    ///< per constraint value at the solution
  Info info;
};

}  // namespace rd3g
