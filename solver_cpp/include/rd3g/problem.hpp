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
///   J = sum_{k=0}^{T-1} u_k' R u_k + sum_{k=1}^{T-1} [(x_k-x_ref)' Q_ref (x_k-x_ref) + x_k' Q x_k]
///       + (x_T-x_ref)' Qf_ref (x_T-x_ref) + x_T' Qf x_T.
struct QuadraticCost {
  Vec x_ref;   ///< reference state (state units)
  Vec Q_ref;   ///< weights on x - x_ref (1/state unit^2)
  Vec Q;       ///< weights on x itself
  Vec R;       ///< weights on u (1/control unit^2)
  Vec Qf_ref;  ///< terminal weights on x_T - x_ref
  Vec Qf;      ///< terminal weights on x_T
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
///   Distance: h = d_min - ||p^i - p^j|| <= 0;  Squared: h = d_min^2 - ||p^i - p^j||^2 <= 0,
/// with p the state components (pos_x, pos_y) and d_min the pair's entry of pair_distances, else min_distance.
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
/// h = d_min - ||p^i_k - o_k|| <= 0 for k = 1..T (form as in CollisionSpec).
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
  SparseLU,  ///< variational multipliers (mu_ij = mu_ji), square system, Eigen SparseLU with reused symbolic analysis
  LSCG,      ///< paper: per-agent multipliers, least-squares conjugate gradient, SparseQR fallback
  SparseQR,  ///< paper's fallback alone: per-agent multipliers, Eigen SparseQR
};

struct Settings {
  double tol = 5e-4;             ///< stop when ||r||_2 < tol (and the other conditions hold)
  int max_iter = 1000;           ///< Newton iterations, all restart attempts together (hard instances need several attempts)
  /// (s), 0 = none. Checked every iteration, between Levenberg-Marquardt tries, inside LSCG (in chunks of 50
  /// iterations) and before a SparseQR factorisation, which is started only if this solver's previous QR
  /// took less than the time left (never before one was measured); otherwise a regularised least-squares step
  /// (LDLT of J'J + delta I, started only if its flop count fits) takes its place. The overshoot is at most
  /// one line search, one LSCG chunk or one factorisation. On time_limit the result is the iterate with the
  /// lowest merit seen.
  double time_limit = 0.0;
  double rho_init = 0.01;        ///< initial barrier weight rho
  /// rho never goes below tol * rho_floor_factor (paper: 0.1; 0.01 was measured to pass the benchmark's
  /// stationarity check on 2-3 car merges that the paper's floor failed). The barrier leaves a force of about
  /// rho/|h| on constraints near activity, i.e. the answer is an equilibrium of a game perturbed by O(rho).
  double rho_floor_factor = 0.01;
  double rho_kappa = 0.2;        ///< rho <- max(tol * rho_floor_factor, min(kappa rho, rho^beta))
  double rho_beta = 1.5;
  /// Globalisation rules of attempt 0 (docs/solver.md, "Globalisation"); restart attempts use the restart_* rules.
  /// 0: update rho every iteration (paper). > 0: update only once ||r|| <= rho_progress * rho, i.e. the
  /// barrier subproblem is nearly solved (IPOPT's monotone rule); keeps iterates near the central path.
  double rho_progress = 0.0;
  /// With rho_progress > 0: an attempt that stalls (stall_window) above rho's floor lowers rho instead of
  /// polishing or restarting (its ||r|| may never reach rho_progress * rho).
  bool rho_on_stall = false;
  /// The rules of every restart attempt (>= 1), and of attempt 0 when its initial guess overlaps deeply (below):
  /// rho_progress = restart_rho_progress, violation_memory = restart_violation_memory and
  /// rho_on_stall = restart_rho_on_stall.
  double restart_rho_progress = 10.0;
  int restart_violation_memory = 4;
  bool restart_rho_on_stall = true;
  /// Attempt 0 uses the restart rules when the rolled-out initial guess brings two agents (or an agent and an
  /// obstacle) closer than (1 - deep_overlap) * d_min at some step (dimensionless, a fraction of the collision
  /// distance; > 1: never). The zero-control starts of bench/families.py, cars 2-8, seeds 0-7, overlap by at most
  /// 0.45 d_min in the authors' merge, 0.25-0.96 d_min in crossing and up to 0.96 d_min in head-on.
  double deep_overlap = 0.5;
  double ls_alpha = 1e-2;        ///< sufficient decrease: ||r(y+t dy)|| <= (1 - alpha t) ||r(y)||
  double ls_beta = 0.5;          ///< step shrink factor
  int ls_max_steps = 30;         ///< backtracking steps before the line search fails
  double violation_tol = 1e-6;   ///< converged only if every h <= violation_tol (constraint units)
  double dynamics_tol = 1e-7;    ///< converged only if every dynamics defect |f(x_k,u_k) - x_{k+1}| <= dynamics_tol (state units)
  double multiplier_tol = 1e-6;  ///< active constraints need mu >= -multiplier_tol (true equilibrium)
  double barrier_margin = 1e-4;  ///< released constraints re-enter the barrier once h < -barrier_margin
  /// When the Newton step fails the line search (near-singular Jacobian), try Levenberg-Marquardt steps
  /// d = -(J'J + nu I)^-1 J' r, a descent direction for ||r||^2, with nu = lm_nu_init * 10^q ||r||, q = 0..lm_tries-1
  /// (the first that passes the line search is taken). After a Newton step shorter than lm_below_step they compete
  /// with it instead: q from lm_tries-1 down while the merit keeps falling, the best step taken.
  int lm_tries = 4;
  double lm_below_step = 1e-2;  ///< also try LM when the accepted Newton step t is below this
  double lm_nu_init = 1e-6;
  LinearSolver linear_solver = LinearSolver::Riccati;
  int refinement_steps = 2;      ///< iterative refinement steps after each sparse LU solve
  BarrierMode barrier = BarrierMode::PrimalDual;
  double fraction_to_boundary = 0.99;  ///< primal-dual: keep z >= (1 - tau) z along a step
  /// Keep the controls in their models' domains (Dynamics::control_domain; the bicycles: |delta| < pi/2, where the
  /// slip angle jumps by pi): a step (Newton or Levenberg-Marquardt) is shortened so that no control leaves its
  /// domain's box shrunk about the centre to domain_fraction of its half-width (the bicycles at 0.99: |delta| <=
  /// 1.555 rad); a step that points out of the box from its edge fails the line search. Dimensionless, in [0, 1);
  /// 0 = off (docs/solver.md, "Staying in the model's domain"). Controls outside the box (a warm
  /// start) and components whose domain is one-sided are not held.
  double domain_fraction = 0.99;
  double lscg_tol = 1e-10;       ///< LSCG relative tolerance
  int lscg_max_iter = 2000;
  /// Globalisation for nonconvex games: when an attempt stalls (merit down < 1% over stall_window
  /// iterations; see polish_gap first) or its line search fails, restart from the initial guess with
  /// rho_init * 10 (attempt 1), the other barrier form (2), both (3), then the same four again and again
  /// from the initial controls plus a seeded constant offset per agent and control of std restart_u_std
  /// (attempts 4..restarts), all with the restart rules (restart_rho_progress). Before attempt
  /// best_response_attempt an extra attempt from an iterated-best-response guess runs (best_response_rounds, below).
  /// Every attempt counts towards iterations, max_iter and the reported time. More restarts change only
  /// solves that would otherwise end with every restart used (a failure or a saddle).
  int restarts = 19;
  int stall_window = 8;
  /// A quicker stall with rho at its floor: an attempt whose ||r|| fell by less than 1e-4 of itself over
  /// stall_floor_window iterations there has stalled too (polish, then restart), since no rho decrease is left to
  /// help it (0 = off).
  int stall_floor_window = 3;
  /// A crawl is a stall too: an attempt whose ||r|| is still above crawl_ratio times its value crawl_window
  /// iterations earlier (0 = never). Barrier subproblems that accept tiny steps for hundreds of iterations, each
  /// lowering ||r|| by a fraction of a percent, then lower rho or end the attempt as a stall does.
  int crawl_window = 40;
  double crawl_ratio = 0.5;  ///< in (0, 1]
  /// On a stall, before restarting, barrier constraints with h >= -polish_gap (constraint units) are held as
  /// equalities (once per attempt); the usual partition rules release them again. 0 = off.
  double polish_gap = 1e-3;
  double restart_u_std = 0.2;  ///< (control units)
  /// Second-order test after convergence (rd3g/second_order.hpp): each agent's constraints with
  /// h >= -second_order_gap (constraint units) and a positive multiplier are held as equalities; the agent passes
  /// if the smallest eigenvalue of its reduced Hessian is >= -second_order_tol * max(1, its largest |eigenvalue|).
  /// A converged point that fails is reported as Status::Saddle. second_order_gap < 0 turns the test off.
  double second_order_gap = 1e-2;
  double second_order_tol = 1e-6;
  /// A converged attempt that fails the second-order test is kept aside and the restart schedule (restarts)
  /// goes on, looking for a point that passes; if none is found the kept saddle is returned (status saddle).
  bool restart_on_saddle = true;
  /// Restart from a saddle along negative curvature (with restart_on_saddle; docs/solver.md, "Second-order test"):
  /// each agent that fails the test moves its controls from the saddle along +-its unit eigenvector of the smallest
  /// eigenvalue (SecondOrderAgent::direction), the others fixed: steps saddle_step, saddle_step * ls_beta, ... (at
  /// most ls_max_steps), the first at which either sign lowers the agent's shooting Lagrangian by at least a tenth
  /// of the quadratic model's 0.5 step^2 |eigenvalue| while every one of its constraints keeps h < -barrier_margin
  /// (the better sign if both do). Its states are rolled out and Newton runs again from there (the other agents'
  /// variables and multipliers kept, rho = saddle_rho, barrier constraints on the central path) before the ordinary
  /// restart schedule goes on. At most saddle_escapes such attempts per solve (0 = off); they count in attempts,
  /// iterations, max_iter and time.
  int saddle_escapes = 2;
  double saddle_step = 1.0;  ///< (control units) first step length along the unit direction
  double saddle_rho = 1e-2;  ///< barrier weight rho at the restart from a saddle
  /// Per-agent inertia correction in the attempts from a saddle (IPOPT's, one agent at a time): every agent that
  /// has failed the test gets delta = saddle_inertia * |its smallest eigenvalue| (the largest seen in this solve)
  /// added on its control rows of the Newton matrix, scaled by min(1, ||r|| / ||r|| at the attempt's first
  /// iteration): a proximal term delta |u - u_k|^2 about the current iterate, which changes the step but not the
  /// residual or its roots, and vanishes at convergence. With saddle_inertia > 1 the agent's reduced Hessian at the
  /// saddle is positive definite after the shift. Dimensionless factor; 0 = off.
  double saddle_inertia = 1.5;
  /// Also in the ordinary restarts (from the initial guess) that follow a saddle (measured: rescues one more
  /// merge-long instance, slows the authors' 4-car seed 15 by 76 %; docs/benchmarks.md "Saddles").
  bool saddle_inertia_restarts = false;
  /// Iterated best response as a restart variant (docs/solver.md, "Restarts"): an extra attempt, inserted before
  /// attempt best_response_attempt of the schedule (>= 1: attempt 0 is never changed; the schedule then goes on
  /// where it was), starts from the controls that best_response_rounds Gauss-Seidel sweeps over the agents reach from
  /// the initial controls: each agent in turn solves its own problem alone (a single-agent sub-solver built once,
  /// with its dynamics, cost, bounds, the problem's obstacles and the others' current rolled-out positions as moving
  /// obstacles at (1 + best_response_margin) times the collision distance), warm-started from its current controls,
  /// and keeps the controls the sub-solve returns if they are finite (converged or not). Each sub-solve has these
  /// settings with at most best_response_max_iter iterations (and what is left of the budget and time_limit), one
  /// restart and no best response of its own. A sub-solve iteration (one agent's Newton system) counts 1/N of a game iteration in
  /// Info::iterations and max_iter (rounded up per attempt); Info::best_response_iterations reports them unscaled;
  /// their time is the solve's. The attempt itself runs from rho_init with attempt 0's rules (the first-attempt
  /// rules, or the restart rules if the guess overlaps deeply). Rounds 0 = off; an attempt past restarts never runs
  /// (restarts = 0: never).
  int best_response_rounds = 1;
  int best_response_attempt = 1;
  int best_response_max_iter = 100;  ///< per single-agent sub-solve (Newton iterations)
  /// The sub-solves keep the others at (1 + best_response_margin) times their pair's collision distance (per step
  /// too), so that the guess starts strictly inside every collision constraint: a guess whose contacts sit exactly at
  /// d_min leaves the barrier no room, and the attempt from it stalls within a few iterations (docs/solver.md).
  double best_response_margin = 0.1;  ///< fraction of the collision distance, >= 0
  /// Non-monotone violation test (attempt 0; restarts use restart_violation_memory): a trial may not raise the
  /// total violation above the largest of the last violation_memory iterates' (1 = monotone, the paper's rule).
  int violation_memory = 1;
  bool verbose = false;
};

/// stalled: every attempt (see restarts) stopped making progress before max_iter.
/// saddle: the first-order conditions hold but some agent's own problem is not at a local minimum there
/// (Info::second_order), i.e. the point is not a local equilibrium.
enum class Status { Converged, MaxIterations, LineSearchFailed, NumericalError, TimeLimit, Stalled, Saddle };
std::string status_name(Status s);

/// Timings in seconds. total, assembly, linear_solve and line_search are accumulated over the whole solve
/// (total = the solve's wall time); setup is the duration of the solver's last set-up (validation,
/// constraint list, allocation; the set-up may be older than this solve) and update the time spent in
/// update calls since the previous solve.
struct Timings {
  double total = 0, assembly = 0, linear_solve = 0, line_search = 0;
  double setup = 0, update = 0;
};

struct Info {
  Status status = Status::MaxIterations;
  int iterations = 0;
  double residual_norm = 0;    ///< final ||r||_2
  double max_violation = 0;    ///< max(0, max h) over all constraints (constraint units)
  double rho = 0;              ///< final barrier weight
  int active_constraints = 0;  ///< constraints held as equalities at the end
  int symbolic_factorizations = 0;  ///< how often the sparse pattern was analysed
  int qr_fallbacks = 0;        ///< linear solves that fell back to SparseQR
  int riccati_solves = 0;      ///< Newton steps solved by the stage-wise Riccati recursion
  int lm_steps = 0;            ///< iterations that took a Levenberg-Marquardt step instead of Newton
  int attempts = 0;            ///< 1 + restarts used (escapes from saddles included)
  int saddle_escapes = 0;      ///< attempts started from a saddle along negative curvature (Settings::saddle_escapes)
  int best_response_attempts = 0;    ///< attempts started from an iterated-best-response guess (0 or 1)
  /// Newton iterations of its single-agent sub-solves, unscaled (iterations includes them divided by N, rounded up)
  int best_response_iterations = 0;
  int setups = 0;              ///< set-ups since the previous solve (setup, or an update that changed the constraint list)
  /// Per agent: smallest eigenvalue of the reduced Hessian of its Lagrangian at the returned point (cost units per
  /// control unit^2; +inf = its active constraints leave no free direction); empty if the test is off.
  std::vector<double> second_order;
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
