"""Solver-independent checks of a claimed open-loop (generalised) Nash equilibrium of a GameProblem.

Everything here works from the returned trajectories (x, u) alone, plus the C++ models' `eval` for the
dynamics (the only shared code with the solver; the models' derivatives are checked against finite
differences in tests/test_derivatives.py). Costs, constraint values and their gradients are written
here from the definitions in solver_cpp/problem.py, not taken from the solver. The benchmark harness
applies `verify_equilibrium` to every solver's output; the tests use the individual checks.

Conventions: x has shape (N, T+1, nx) with x[:, 0] the initial states, u has shape (N, T, nu).
Collision and obstacle constraints are imposed at k = 1..T (the initial states are given data), state
bounds on x_1..x_T, control bounds on u_0..u_{T-1}. Violations of collision constraints are reported in
metres (d_min - distance) whatever the constraint form the solver used.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import lsq_linear, minimize

from solver_cpp import GameProblem

# Recommended default tolerances (see verify_equilibrium's docstring for the reasoning).
DYNAMICS_TOL = 1e-5  # state units
VIOLATION_TOL_M = 1e-6  # m, collision/obstacle; the same number in state/control units for bounds
ACTIVE_TOL = 1e-2  # m (collision) or state/control units (bounds): "nearly active" for the KKT check
STATIONARITY_REL_TOL = 1e-3  # stationarity residual / norm of all players' stacked cost gradients
BEST_RESPONSE_TOL = 1e-3  # relative cost decrease a player may find by deviating alone


# ------------------------------------------------------------------------------------------------
# Problem data in plain numpy
@dataclass(frozen=True)
class _CostData:
    x_ref: np.ndarray
    Q_ref: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    Qf_ref: np.ndarray
    Qf: np.ndarray
    lead_weight: float
    lead_index: int


def _cost_data(problem: GameProblem, i: int, nx: int, nu: int) -> _CostData:
    a = problem.agents[i]
    c = a.cost
    vec = lambda v, n: np.zeros(n) if v is None else np.asarray(v, dtype=float).reshape(n)  # noqa: E731
    Q_ref, Q = vec(c.Q_ref, nx), vec(c.Q, nx)
    return _CostData(x_ref=vec(c.x_ref, nx), Q_ref=Q_ref, Q=Q, R=vec(c.R, nu),
                     Qf_ref=Q_ref if c.Qf_ref is None else vec(c.Qf_ref, nx),
                     Qf=Q if c.Qf is None else vec(c.Qf, nx),
                     lead_weight=float(a.lead_weight), lead_index=int(a.lead_index))


def _bounds(values, n: int, fill: float) -> np.ndarray:
    return np.full(n, fill) if values is None else np.asarray(values, dtype=float).reshape(n)


def _check_shapes(problem: GameProblem, x: np.ndarray, u: np.ndarray | None = None) -> tuple[int, int, int, int]:
    N, T = problem.num_agents, int(problem.horizon)
    nx, nu = problem.agents[0].dynamics.nx, problem.agents[0].dynamics.nu
    if x.shape != (N, T + 1, nx):
        raise ValueError(f"x must have shape ({N}, {T + 1}, {nx}), got {x.shape}")
    if u is not None and u.shape != (N, T, nu):
        raise ValueError(f"u must have shape ({N}, {T}, {nu}), got {u.shape}")
    return N, T, nx, nu


def _distance_steps(value, T: int) -> np.ndarray:
    """d_min (m) for k = 1..T as an array (T,): one number for every step, or T per-step numbers."""
    return np.broadcast_to(np.asarray(value, dtype=float), (T,)).copy()


def _collision_settings(problem: GameProblem) -> tuple[bool, np.ndarray, int, int]:
    """(pairs enabled, d_min of agents i and j for k = 1..T (N, N, T), pos_x, pos_y); positions default to state
    components 0, 1."""
    N, T = problem.num_agents, int(problem.horizon)
    col = problem.collision
    if col is None:
        return False, np.zeros((N, N, T)), 0, 1
    enabled = bool(col.enabled) and N >= 2
    d_min = col.pair_min_distances(N, T) if enabled else np.zeros((N, N, T))
    return enabled, d_min, int(col.pos_x), int(col.pos_y)


# ------------------------------------------------------------------------------------------------
def dynamics_defect(problem: GameProblem, x, u) -> float:
    """max |f(x_k, u_k) - x_{k+1}| over agents, steps and components, plus |x_0 - x0 given|."""
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    N, T, _, _ = _check_shapes(problem, x, u)
    worst = 0.0
    for i, agent in enumerate(problem.agents):
        f = agent.dynamics.build(problem.dt)
        worst = max(worst, float(np.max(np.abs(x[i, 0] - np.asarray(agent.x0, dtype=float)))))
        for k in range(T):
            x_next = f.eval(x[i, k], u[i, k])[0]
            worst = max(worst, float(np.max(np.abs(x_next - x[i, k + 1]))))
    return worst


def control_domain_margin(problem: GameProblem, u) -> float:
    """The smallest distance (control units) of any control to the edge of its model's domain, the open box on which
    the model is smooth (`control_domain()`; the bicycles: |delta| < pi/2, where the slip angle jumps by pi).
    Positive inside, <= 0 at or beyond the edge, inf for models without limits."""
    u = np.asarray(u, dtype=float)
    N, T, nu = problem.num_agents, int(problem.horizon), problem.agents[0].dynamics.nu
    if u.shape != (N, T, nu):
        raise ValueError(f"u must have shape ({N}, {T}, {nu}), got {u.shape}")
    worst = float("inf")
    for i, agent in enumerate(problem.agents):
        lo, hi = (np.asarray(b, dtype=float) for b in agent.dynamics.build(problem.dt).control_domain())
        ui = u[i]
        with np.errstate(invalid="ignore"):
            margin = np.minimum(ui - lo, hi - ui)
        if margin.size:
            worst = min(worst, float(np.min(np.where(np.isnan(margin), -np.inf, margin))))
    return worst


def collision_gaps_m(problem: GameProblem, x) -> np.ndarray:
    """d_min - distance (m) of every pair (i < j) and every agent-obstacle pair at k = 1..T, flattened;
    positive = violated. Empty if the problem has no such constraint."""
    x = np.asarray(x, dtype=float)
    N, T, _, _ = _check_shapes(problem, x)
    enabled, d_min, px, py = _collision_settings(problem)
    p = x[:, 1:, [px, py]]  # (N, T, 2)
    gaps = []
    if enabled:
        iu, ju = np.triu_indices(N, k=1)
        gaps.append((d_min[iu, ju] - np.linalg.norm(p[iu] - p[ju], axis=-1)).ravel())
    for o in problem.obstacles:
        pos = np.asarray(o.positions, dtype=float)[1:]  # (T, 2)
        gaps.append((_distance_steps(o.min_distance, T) - np.linalg.norm(p - pos[None], axis=-1)).ravel())
    return np.concatenate(gaps) if gaps else np.zeros(0)


def max_collision_violation_m(problem: GameProblem, x) -> float:
    """Largest d_min - distance (m) over pairs and obstacles at k = 1..T (positive = violated);
    -inf if the problem has no collision or obstacle constraint."""
    gaps = collision_gaps_m(problem, x)
    return float(gaps.max()) if gaps.size else -np.inf


def max_bound_violation(problem: GameProblem, x, u) -> float:
    """Largest violation of the state (x_1..x_T) and control bounds, in their own units (<= 0 = fine);
    -inf if there are no bounds."""
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    N, T, nx, nu = _check_shapes(problem, x, u)
    worst = -np.inf
    for i, a in enumerate(problem.agents):
        for lo, hi, vals in ((_bounds(a.x_min, nx, -np.inf), _bounds(a.x_max, nx, np.inf), x[i, 1:]),
                             (_bounds(a.u_min, nu, -np.inf), _bounds(a.u_max, nu, np.inf), u[i])):
            with np.errstate(invalid="ignore"):
                v = np.concatenate([(vals - hi)[:, np.isfinite(hi)].ravel(), (lo - vals)[:, np.isfinite(lo)].ravel()])
            if v.size:
                worst = max(worst, float(v.max()))
    return worst


def player_cost(problem: GameProblem, x, u, i: int) -> float:
    """J^i from the definition in solver_cpp.QuadraticCost (no 1/2 factor) plus the lead term
    lead_weight * sum_{k=1..T} sum_{j != i} (x^j_k[idx] - x^i_k[idx])."""
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    N, T, nx, nu = _check_shapes(problem, x, u)
    c = _cost_data(problem, i, nx, nu)
    xi = x[i]
    e = xi[1:T] - c.x_ref
    J = float(np.sum(u[i] ** 2 * c.R))
    J += float(np.sum(e ** 2 * c.Q_ref) + np.sum(xi[1:T] ** 2 * c.Q))
    J += float(np.sum((xi[T] - c.x_ref) ** 2 * c.Qf_ref) + np.sum(xi[T] ** 2 * c.Qf))
    if c.lead_weight != 0.0 and N > 1:
        others = np.delete(x[:, 1:, c.lead_index], i, axis=0)  # (N-1, T)
        J += c.lead_weight * float(np.sum(others - xi[None, 1:, c.lead_index]))
    return J


def _cost_gradient(problem: GameProblem, x: np.ndarray, u: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
    """(dJ^i/dx^i_{1..T} as (T, nx), dJ^i/du^i as (T, nu))."""
    N, T, nx, nu = _check_shapes(problem, x, u)
    c = _cost_data(problem, i, nx, nu)
    gx = np.empty((T, nx))
    gx[:T - 1] = 2.0 * (c.Q_ref * (x[i, 1:T] - c.x_ref) + c.Q * x[i, 1:T])
    gx[T - 1] = 2.0 * (c.Qf_ref * (x[i, T] - c.x_ref) + c.Qf * x[i, T])
    if c.lead_weight != 0.0 and N > 1:
        gx[:, c.lead_index] -= c.lead_weight * (N - 1)
    return gx, 2.0 * c.R * u[i]


# ------------------------------------------------------------------------------------------------
# Player i's inequality constraints as rows g(z) <= 0 with gradients, z = (x^i_1..T, u^i_0..T-1)
def _player_inequalities(problem: GameProblem, x: np.ndarray, u: np.ndarray, i: int):
    """Yields (value, step k (1..T states / 0..T-1 controls), 'x' or 'u', gradient wrt that block)."""
    N, T, nx, nu = _check_shapes(problem, x, u)
    enabled, d_min, px, py = _collision_settings(problem)
    others = [(x[j, :, [px, py]].T, d_min[i, j]) for j in range(N) if enabled and j != i]
    others += [(np.asarray(o.positions, dtype=float), _distance_steps(o.min_distance, T)) for o in problem.obstacles]
    for other, dmin in others:
        for k in range(1, T + 1):
            d = x[i, k, [px, py]] - other[k]
            dist = max(float(np.linalg.norm(d)), 1e-12)
            g = np.zeros(nx)
            g[px], g[py] = -d / dist
            yield float(dmin[k - 1]) - dist, k, "x", g
    a = problem.agents[i]
    for name, lo, hi, vals, n, first in (("x", _bounds(a.x_min, nx, -np.inf), _bounds(a.x_max, nx, np.inf), x[i], nx, 1),
                                         ("u", _bounds(a.u_min, nu, -np.inf), _bounds(a.u_max, nu, np.inf), u[i], nu, 0)):
        for q in range(n):
            for k in range(first, first + T):
                if np.isfinite(hi[q]):
                    yield vals[k, q] - hi[q], k, name, np.eye(n)[q]
                if np.isfinite(lo[q]):
                    yield lo[q] - vals[k, q], k, name, -np.eye(n)[q]


def _player_kkt(problem: GameProblem, x: np.ndarray, u: np.ndarray, i: int, active_tol: float):
    """Cost gradient g, and the matrix whose columns are the equality / nearly-active inequality
    gradients, for player i's optimal-control problem with the other players fixed."""
    N, T, nx, nu = _check_shapes(problem, x, u)
    nz = T * (nx + nu)
    col_x = lambda k: (k - 1) * nx  # noqa: E731  (x_k, k = 1..T)
    col_u = lambda k: T * nx + k * nu  # noqa: E731  (u_k, k = 0..T-1)
    gx, gu = _cost_gradient(problem, x, u, i)
    g = np.concatenate([gx.ravel(), gu.ravel()])
    f = problem.agents[i].dynamics.build(problem.dt)
    # Dynamics F_k = f(x_k, u_k) - x_{k+1} = 0, k = 0..T-1: rows of G_eq.
    G_eq = np.zeros((T * nx, nz))
    for k in range(T):
        _, A, B = f.eval(x[i, k], u[i, k])
        rows = slice(k * nx, (k + 1) * nx)
        G_eq[rows, col_x(k + 1):col_x(k + 1) + nx] = -np.eye(nx)
        if k >= 1:
            G_eq[rows, col_x(k):col_x(k) + nx] = A
        G_eq[rows, col_u(k):col_u(k) + nu] = B
    G_in = []
    for h, k, block, grad in _player_inequalities(problem, x, u, i):
        if h > -active_tol:
            row = np.zeros(nz)
            c0 = col_x(k) if block == "x" else col_u(k)
            row[c0:c0 + grad.size] = grad
            G_in.append(row)
    G_in = np.array(G_in).reshape(-1, nz)
    return g, G_eq, G_in


def cost_gradient_scale(problem: GameProblem, x, u) -> float:
    """Norm of all players' stacked own-variable cost gradients, the scale against which stationarity
    residuals are judged (a game-wide scale: a player sitting at its reference has a tiny gradient of
    its own, while a solver's tolerance is on the residual of the whole game)."""
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    N = _check_shapes(problem, x, u)[0]
    sq = sum(float(np.sum(gx ** 2) + np.sum(gu ** 2)) for gx, gu in (_cost_gradient(problem, x, u, i) for i in range(N)))
    return float(np.sqrt(sq))


def stationarity_residual(problem: GameProblem, x, u, active_tol: float = ACTIVE_TOL,
                          relative: bool = False) -> np.ndarray:
    """Per player i: min over multipliers (dynamics free, inequalities >= 0) of
    || grad J^i + G_eq' lam + G_in' mu ||_2, the open-loop KKT stationarity residual of player i's
    optimal-control problem with the others' trajectories fixed, over z = (x^i_1..T, u^i_0..T-1).
    G_eq holds the dynamics f(x_k, u_k) - x_{k+1}; G_in the collision (distance form, metres),
    obstacle and bound constraints with h > -active_tol. With relative=True the entries are divided by
    cost_gradient_scale (recommended tolerance: STATIONARITY_REL_TOL, see verify_equilibrium)."""
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    N = _check_shapes(problem, x, u)[0]
    out = np.empty(N)
    for i in range(N):
        g, G_eq, G_in = _player_kkt(problem, x, u, i, active_tol)
        M = np.vstack([G_eq, G_in]).T
        lo = np.concatenate([np.full(G_eq.shape[0], -np.inf), np.zeros(G_in.shape[0])])
        sol = lsq_linear(M, -g, bounds=(lo, np.full(M.shape[1], np.inf)), method="bvls", tol=1e-14)
        out[i] = float(np.linalg.norm(M @ sol.x + g))
    if relative:
        out /= max(cost_gradient_scale(problem, x, u), 1e-300)
    return out


# ------------------------------------------------------------------------------------------------
def _rollout_sensitivities(f, x0: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """States X (T+1, nx) of the rollout of controls U (T, nu) from x0 through the C++ model f, and the forward
    sensitivities S (T+1, nx, T nu) = dX_k / dU (U flattened step-major)."""
    T, nu = U.shape
    nx = x0.size
    X = np.empty((T + 1, nx))
    S = np.zeros((T + 1, nx, T * nu))
    X[0] = x0
    for k in range(T):
        X[k + 1], A, B = f.eval(X[k], U[k])
        S[k + 1] = A @ S[k]
        S[k + 1][:, k * nu:(k + 1) * nu] += B
    return X, S


class _ShootingProblem:
    """Player i's optimal-control problem over its controls alone (single shooting through the C++
    rollout, so the dynamics hold exactly), others fixed. Constraints c(U) >= 0 with analytic
    gradients via forward sensitivities S_k = dx_k/dU."""

    def __init__(self, problem: GameProblem, x: np.ndarray, u: np.ndarray, i: int):
        self.problem, self.i = problem, i
        self.N, self.T, self.nx, self.nu = _check_shapes(problem, x, u)
        self.x_all, self.u_all = x.copy(), u.copy()
        self.f = problem.agents[i].dynamics.build(problem.dt)
        self.x0 = np.asarray(problem.agents[i].x0, dtype=float)
        a = problem.agents[i]
        self.u_lo, self.u_hi = _bounds(a.u_min, self.nu, -np.inf), _bounds(a.u_max, self.nu, np.inf)
        self.x_lo, self.x_hi = _bounds(a.x_min, self.nx, -np.inf), _bounds(a.x_max, self.nx, np.inf)
        enabled, d_min, self.px, self.py = _collision_settings(problem)
        # Points to keep away from at k = 1..T: (positions (T, 2), d_min (T,)).
        self.avoid = [(x[j, 1:][:, [self.px, self.py]], d_min[i, j]) for j in range(self.N) if enabled and j != i]
        self.avoid += [(np.asarray(o.positions, dtype=float)[1:], _distance_steps(o.min_distance, self.T))
                       for o in problem.obstacles]
        self._key = None

    def _eval(self, z: np.ndarray) -> None:
        key = z.tobytes()
        if key == self._key:
            return
        self.X, self.S = _rollout_sensitivities(self.f, self.x0, z.reshape(self.T, self.nu))
        self._key = key

    def trajectories(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self._eval(z)
        x, u = self.x_all.copy(), self.u_all.copy()
        x[self.i] = self.X
        u[self.i] = z.reshape(self.T, self.nu)
        return x, u

    def cost(self, z: np.ndarray) -> float:
        x, u = self.trajectories(z)
        return player_cost(self.problem, x, u, self.i)

    def cost_grad(self, z: np.ndarray) -> np.ndarray:
        x, u = self.trajectories(z)
        gx, gu = _cost_gradient(self.problem, x, u, self.i)
        return np.einsum("kx,kxz->z", gx, self.S[1:]) + gu.ravel()

    def constraints(self, z: np.ndarray) -> np.ndarray:
        """c >= 0: |p - o|^2 - d_min^2 (smooth), x_max - x, x - x_min."""
        self._eval(z)
        p = self.X[1:, [self.px, self.py]]
        c = [np.sum((p - o) ** 2, axis=1) - d ** 2 for o, d in self.avoid]
        hi, lo = np.isfinite(self.x_hi), np.isfinite(self.x_lo)
        c += [(self.x_hi[hi] - self.X[1:, hi]).ravel(), (self.X[1:, lo] - self.x_lo[lo]).ravel()]
        return np.concatenate(c)

    def constraints_jac(self, z: np.ndarray) -> np.ndarray:
        self._eval(z)
        Sp = self.S[1:, [self.px, self.py]]  # (T, 2, nz)
        p = self.X[1:, [self.px, self.py]]
        rows = [np.einsum("kc,kcz->kz", 2.0 * (p - o), Sp) for o, _ in self.avoid]
        hi, lo = np.isfinite(self.x_hi), np.isfinite(self.x_lo)
        rows += [-self.S[1:, hi].reshape(-1, self.S.shape[-1]), self.S[1:, lo].reshape(-1, self.S.shape[-1])]
        return np.concatenate(rows, axis=0)


def _player_violation(problem: GameProblem, x: np.ndarray, u: np.ndarray, i: int) -> float:
    """Largest violation of player i's own constraints (collision in m, bounds in their units)."""
    worst = -np.inf
    for h, _, _, _ in _player_inequalities(problem, x, u, i):
        worst = max(worst, h)
    return worst


def best_response_gap(problem: GameProblem, x, u, i: int, starts: int = 2, perturbation: float = 0.05,
                      seed: int = 0, feasibility_tol: float = VIOLATION_TOL_M, max_iter: int = 200) -> float:
    """Best relative decrease (J^i(sol) - J^i(best)) / |J^i(sol)| of player i's cost that SLSQP finds
    over player i's controls alone (others' trajectories fixed, dynamics by rollout, collision,
    obstacle and bound constraints), started from the solution and from `starts` seeded perturbations
    of it (Gaussian, std `perturbation` in control units). Only points violating player i's
    constraints by at most feasibility_tol count. <= ~0 means no profitable unilateral deviation was
    found (a local check: SLSQP finds local optima near its starts). NaN if no feasible point was found."""
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    _check_shapes(problem, x, u)
    sp = _ShootingProblem(problem, x, u, i)
    J_sol = player_cost(problem, x, u, i)
    scale = max(abs(J_sol), 1e-12)
    rng = np.random.default_rng(seed)
    z_sol = u[i].ravel().copy()
    bounds = list(zip(np.tile(sp.u_lo, sp.T), np.tile(sp.u_hi, sp.T)))
    bounds = [(None if not np.isfinite(lo) else lo, None if not np.isfinite(hi) else hi) for lo, hi in bounds]
    lo_arr = np.tile(sp.u_lo, sp.T)
    hi_arr = np.tile(sp.u_hi, sp.T)
    cons = [{"type": "ineq", "fun": sp.constraints, "jac": sp.constraints_jac}] if sp.constraints(z_sol).size else []
    best = np.nan
    candidates = [z_sol] + [np.clip(z_sol + perturbation * rng.standard_normal(z_sol.size), lo_arr, hi_arr)
                            for _ in range(starts)]
    for z0 in candidates:
        res = minimize(sp.cost, z0, jac=sp.cost_grad, method="SLSQP", bounds=bounds, constraints=cons,
                       options={"maxiter": max_iter, "ftol": 1e-12})
        for z in (res.x, z0):  # the start itself counts too (e.g. the solution when SLSQP wanders off)
            if _player_violation(problem, *sp.trajectories(z), i) <= feasibility_tol:
                gap = (J_sol - sp.cost(z)) / scale
                best = gap if np.isnan(best) else max(best, gap)
    return float(best)


# ------------------------------------------------------------------------------------------------
@dataclass
class EquilibriumReport:
    """Outcome of verify_equilibrium. Units: dynamics_defect in state units, collision in metres,
    bounds in their own units; stationarity relative to cost_gradient_scale."""

    dynamics_defect: float
    max_collision_violation_m: float
    max_bound_violation: float
    stationarity: np.ndarray  # absolute, per player
    stationarity_relative: np.ndarray  # per player
    best_response_gaps: np.ndarray | None  # per player, relative cost decrease; None if not run
    passed: bool
    failures: list[str] = field(default_factory=list)
    control_domain_margin: float = float("inf")  # control units; <= 0: a control outside its model's domain


def verify_equilibrium(problem: GameProblem, result_x, result_u, *, dynamics_tol: float = DYNAMICS_TOL,
                       violation_tol_m: float = VIOLATION_TOL_M, active_tol: float = ACTIVE_TOL,
                       stationarity_tol: float = STATIONARITY_REL_TOL, best_response: bool = True,
                       best_response_tol: float = BEST_RESPONSE_TOL, best_response_starts: int = 2,
                       seed: int = 0) -> EquilibriumReport:
    """Check a claimed equilibrium: dynamics, feasibility, per-player KKT stationarity and (optionally)
    unilateral best responses.

    Recommended tolerances (the defaults), calibrated on the merging game (3-5 cars):
    - dynamics defect 1e-5 (state units) and collision/bound violation 1e-6 m: a Newton solve holds
      the dynamics to about its residual tolerance, and keeps constraints to its violation_tol.
    - stationarity 1e-3 of cost_gradient_scale: the dynamics multipliers must cancel the cost
      gradient, so an absolute residual means nothing without that scale. RD3G reaches <= 1e-3 at its
      default tol 5e-4 and ~1e-5 at tol 1e-5; the margin covers the barrier terms (about
      rho/|h| |grad h| each, rho ~ tol/10) that a solver leaves on constraints farther than
      active_tol (1e-2 m: a barrier solution sits about rho/mu inside an active constraint).
    - best-response gap 1e-3: no player finds a feasible unilateral deviation worth more than 0.1% of
      its cost. This one is sensitive to solve accuracy: RD3G at tol 5e-4 leaves gaps up to ~1e-2
      on 4-5 car merges, at tol 1e-5 below 2e-4; solve at tol <= 1e-5 before asking for it."""
    x, u = np.asarray(result_x, dtype=float), np.asarray(result_u, dtype=float)
    N = _check_shapes(problem, x, u)[0]
    failures = []
    defect = dynamics_defect(problem, x, u)
    coll = max_collision_violation_m(problem, x)
    bnd = max_bound_violation(problem, x, u)
    domain = control_domain_margin(problem, u)
    stat = stationarity_residual(problem, x, u, active_tol)
    stat_rel = stat / max(cost_gradient_scale(problem, x, u), 1e-300)
    if not np.isfinite(defect) or defect > dynamics_tol:
        failures.append(f"dynamics defect {defect:.3e} > {dynamics_tol:.1e}")
    if not coll <= violation_tol_m:
        failures.append(f"collision violation {coll:.3e} m > {violation_tol_m:.1e} m")
    if not bnd <= violation_tol_m:
        failures.append(f"bound violation {bnd:.3e} > {violation_tol_m:.1e}")
    if not domain > 0:
        failures.append(f"a control is outside its model's domain by {-domain:.3e} (control units)")
    for i in np.flatnonzero(~(stat_rel <= stationarity_tol)):
        failures.append(f"player {i}: stationarity residual {stat[i]:.3e} "
                        f"({stat_rel[i]:.3e} of the cost-gradient scale) > {stationarity_tol:.1e}")
    gaps = None
    if best_response:
        gaps = np.array([best_response_gap(problem, x, u, i, starts=best_response_starts, seed=seed + i)
                         for i in range(N)])
        for i in np.flatnonzero(~(gaps <= best_response_tol)):
            failures.append(f"player {i}: unilateral deviation lowers its cost by {gaps[i]:.3e} (relative)")
    return EquilibriumReport(dynamics_defect=defect, max_collision_violation_m=coll, max_bound_violation=bnd,
                             stationarity=stat, stationarity_relative=stat_rel, best_response_gaps=gaps,
                             passed=not failures, failures=failures, control_domain_margin=domain)


# ------------------------------------------------------------------------------------------------
# Is the game feasible at all? (The benchmark asks this of every instance a solver fails on.)
FEASIBILITY_TOL_M = 1e-3  # m: a point violating no collision constraint by more than this counts as feasible


@dataclass
class FeasibilityReport:
    """status: 'infeasible' (proven: states no control can change already violate a constraint), 'feasible' (x, u
    hold a point whose rollout violates no constraint by more than the tolerance) or 'unknown' (neither found).
    max_violation_m: of the best point the search saw (collision in m, bounds in their units; nan if none)."""

    status: str
    detail: str
    x: np.ndarray | None = None
    u: np.ndarray | None = None
    max_violation_m: float = float("nan")


def control_independent_states(problem: GameProblem, seed: int = 0) -> np.ndarray:
    """(N, T+1, nx) bool: state components x^i_k that no control sequence changes. Decided on the models themselves
    (nothing assumed about their form): from a zero and two seeded random control sequences (clipped to the control
    bounds), every control component at every step is moved by 1e-3 and by 1 (inside the bounds) and the rollout
    repeated; a component is control-independent if it stays bit-identical in every one of these rollouts. x_0 is
    always independent. A component marked independent could still depend on a control only if that dependence
    vanished at every probe, which no model in solver_cpp allows (where a state depends on a control it does so for
    an open set of controls); e.g. the kinematic bicycle's position at k = 1 is independent exactly when v_0 = 0."""
    N, T = problem.num_agents, int(problem.horizon)
    nx, nu = problem.agents[0].dynamics.nx, problem.agents[0].dynamics.nu
    rng = np.random.default_rng(seed)
    fixed = np.ones((N, T + 1, nx), dtype=bool)
    for i, a in enumerate(problem.agents):
        f = a.dynamics.build(problem.dt)
        x0 = np.asarray(a.x0, dtype=float)
        lo, hi = _bounds(a.u_min, nu, -np.inf), _bounds(a.u_max, nu, np.inf)
        bases = [np.zeros((T, nu))] + [rng.normal(0.0, scale, (T, nu)) for scale in (0.3, 3.0)]
        for U in (np.clip(b, lo, hi) for b in bases):
            X = np.asarray(f.rollout(x0, U))
            for k in range(T):
                for c in range(nu):
                    for h in (1e-3, 1.0):
                        Up = U.copy()
                        # step inside the bounds (downwards if the upper bound is closer)
                        Up[k, c] = U[k, c] + h if U[k, c] + h <= hi[c] else max(U[k, c] - h, lo[c])
                        if Up[k, c] == U[k, c]:
                            continue
                        fixed[i] &= np.asarray(f.rollout(x0, Up)) == X
    return fixed


def fixed_state_infeasibility(problem: GameProblem, tol_m: float = FEASIBILITY_TOL_M) -> list[str]:
    """Exact infeasibility certificates: constraints at steps k >= 1 whose every variable is control-independent
    (control_independent_states) and that are violated by more than tol_m there (collision and obstacle gaps in m,
    state bounds in their units). Empty if there is none (which does not prove feasibility)."""
    N, T = problem.num_agents, int(problem.horizon)
    nu = problem.agents[0].dynamics.nu
    fixed = control_independent_states(problem)
    x = problem.rollout(np.zeros((N, T, nu)))
    enabled, d_min, px, py = _collision_settings(problem)
    pos_fixed = fixed[:, :, px] & fixed[:, :, py]  # (N, T+1)
    reasons = []
    for k in range(1, T + 1):
        for i in range(N):
            if not pos_fixed[i, k]:
                continue
            p = x[i, k, [px, py]]
            for j in range(i + 1, N) if enabled else ():
                gap = d_min[i, j, k - 1] - float(np.linalg.norm(p - x[j, k, [px, py]]))
                if pos_fixed[j, k] and gap > tol_m:
                    reasons.append(f"agents {i} and {j} at step {k}: positions no control changes are "
                                   f"{d_min[i, j, k - 1] - gap:.3f} m apart < d_min {d_min[i, j, k - 1]:g} m")
            for o, obs in enumerate(problem.obstacles):
                dmin_o = _distance_steps(obs.min_distance, T)[k - 1]
                gap = dmin_o - float(np.linalg.norm(p - np.asarray(obs.positions, dtype=float)[k]))
                if gap > tol_m:
                    reasons.append(f"agent {i} and obstacle {o} at step {k}: a position no control changes is "
                                   f"{dmin_o - gap:.3f} m from it < {dmin_o:g} m")
    nx = x.shape[2]
    for i, a in enumerate(problem.agents):
        for name, lim, sign in (("x_max", _bounds(a.x_max, nx, np.inf), 1.0), ("x_min", _bounds(a.x_min, nx, -np.inf), -1.0)):
            with np.errstate(invalid="ignore"):
                bad = fixed[i, 1:] & np.isfinite(lim) & (sign * (x[i, 1:] - lim) > tol_m)
            for k, q in zip(*np.nonzero(bad)):
                reasons.append(f"agent {i} at step {k + 1}: state component {q} = {x[i, k + 1, q]:.4g}, which no "
                               f"control changes, violates {name} {lim[q]:g}")
    return reasons


class _FoundFeasible(Exception):
    def __init__(self, z: np.ndarray):
        self.z = z


class _JointShooting:
    """All players' controls U (N, T, nu) as one vector; states by rollout (so the dynamics hold exactly). Constraint
    rows c >= 0 over a working set of (agent, other, step) collision/obstacle pairs, (|p - q|^2 - D^2) / (2 D) with D =
    d_min + margin (about metres near the boundary, smooth), plus every finite state bound. Every evaluation checks the
    whole problem and raises _FoundFeasible at the first point violating nothing (the search wants any such point)."""

    def __init__(self, problem: GameProblem, margin_m: float):
        self.problem = problem
        self.N, self.T = problem.num_agents, int(problem.horizon)
        self.nx, self.nu = problem.agents[0].dynamics.nx, problem.agents[0].dynamics.nu
        self.fs = [a.dynamics.build(problem.dt) for a in problem.agents]
        self.x0 = [np.asarray(a.x0, dtype=float) for a in problem.agents]
        enabled, d_min, self.px, self.py = _collision_settings(problem)
        # "others": agents 0..N-1 (moving with their controls), then obstacles (fixed positions), with D per agent,
        # other and step (N, N + obstacles, T).
        self.n_pairs_agents = self.N if enabled else 0
        self.obs_pos = np.array([np.asarray(o.positions, dtype=float) for o in problem.obstacles]).reshape(-1, self.T + 1, 2)
        obs_d = np.array([_distance_steps(o.min_distance, self.T) for o in problem.obstacles]).reshape(-1, self.T)
        self.D = np.concatenate([d_min, np.broadcast_to(obs_d, (self.N, *obs_d.shape))], axis=1) + margin_m
        self.x_lo = [_bounds(a.x_min, self.nx, -np.inf) for a in problem.agents]
        self.x_hi = [_bounds(a.x_max, self.nx, np.inf) for a in problem.agents]
        self.work = np.zeros((0, 3), dtype=int)  # rows (agent a, other b, step k): b >= N is obstacle b - N
        self._key = None
        self.best = (np.inf, None)  # (violation, z) of the least-violating point seen

    def _eval(self, z: np.ndarray) -> None:
        key = z.tobytes()
        if key == self._key:
            return
        U = z.reshape(self.N, self.T, self.nu)
        out = [_rollout_sensitivities(f, x0, U[i]) for i, (f, x0) in enumerate(zip(self.fs, self.x0))]
        self.X = np.stack([o[0] for o in out])
        self.S = np.stack([o[1] for o in out])  # (N, T+1, nx, T nu)
        self._key = key
        x, u = self.X, U
        viol = max(max_collision_violation_m(self.problem, x), max_bound_violation(self.problem, x, u))
        if viol < self.best[0]:
            self.best = (viol, z.copy())
        if viol <= 0.0:
            raise _FoundFeasible(z.copy())

    def positions(self) -> np.ndarray:
        """(N + obstacles, T+1, 2) at the last evaluated point."""
        return np.concatenate([self.X[:, :, [self.px, self.py]], self.obs_pos], axis=0)

    def gaps(self, z: np.ndarray) -> np.ndarray:
        """D - distance for every (a, b > a, k) as an array (N, N + obstacles, T+1) (nan where no constraint)."""
        self._eval(z)
        P = self.positions()
        g = self.D - np.linalg.norm(P[None, :, 1:] - P[:self.N, None, 1:], axis=-1)  # (N, N+O, T)
        mask = np.zeros(g.shape, dtype=bool)
        mask[:, self.N:] = True
        mask[:, :self.N] = np.triu(np.ones((self.N, self.N), dtype=bool), 1)[:, :, None] & (self.n_pairs_agents > 0)
        return np.where(mask, g, np.nan)

    def add_to_work(self, z: np.ndarray, within_m: float) -> None:
        """Add every pair within within_m of its D (or violating it) at z to the working set."""
        with np.errstate(invalid="ignore"):
            a, b, k = np.nonzero(self.gaps(z) > -within_m)
        new = np.stack([a, b, k + 1], axis=1)
        self.work = np.unique(np.vstack([self.work, new]), axis=0)

    def constraints(self, z: np.ndarray) -> np.ndarray:
        self._eval(z)
        P = self.positions()
        a, b, k = self.work.T
        d = self.D[a, b, k - 1]
        c = [(np.sum((P[a, k] - P[b, k]) ** 2, axis=1) - d ** 2) / (2.0 * d)]
        for i in range(self.N):
            hi, lo = np.isfinite(self.x_hi[i]), np.isfinite(self.x_lo[i])
            # component-major (q, then k), as in constraints_jac
            c += [(self.x_hi[i][hi][:, None] - self.X[i, 1:][:, hi].T).ravel(),
                  (self.X[i, 1:][:, lo].T - self.x_lo[i][lo][:, None]).ravel()]
        return np.concatenate(c)

    def constraints_jac(self, z: np.ndarray) -> np.ndarray:
        self._eval(z)
        P = self.positions()
        a, b, k = self.work.T
        n_z = self.T * self.nu
        grad = (P[a, k] - P[b, k]) / self.D[a, b, k - 1][:, None]  # dc/dp_a; dc/dp_b = -grad
        Sp = self.S[:, :, [self.px, self.py]]  # (N, T+1, 2, T nu)
        J = np.zeros((len(a), self.N, n_z))
        r = np.arange(len(a))
        J[r, a] = np.einsum("rc,rcz->rz", grad, Sp[a, k])
        moving = b < self.N
        J[r[moving], b[moving]] -= np.einsum("rc,rcz->rz", grad[moving], Sp[b[moving], k[moving]])
        rows = [J.reshape(len(a), -1)]
        for i in range(self.N):
            hi, lo = np.isfinite(self.x_hi[i]), np.isfinite(self.x_lo[i])
            for sel, sign in ((hi, -1.0), (lo, 1.0)):
                block = sign * self.S[i, 1:][:, sel].transpose(1, 0, 2).reshape(-1, n_z)  # rows (q, k)
                full = np.zeros((block.shape[0], self.N, n_z))
                full[:, i] = block
                rows.append(full.reshape(block.shape[0], self.N * n_z))
        return np.concatenate(rows, axis=0)


def find_feasible_point(problem: GameProblem, starts=(), seeded_starts: int = 2, seed: int = 0,
                        tol_m: float = FEASIBILITY_TOL_M, max_iter: int = 100, rounds: int = 3,
                        margin_m: float = 1e-3, within_m: float = 1.0) -> FeasibilityReport:
    """Search for a point of the joint single-shooting problem (all players' controls; states by rollout) that violates
    no collision, obstacle or bound constraint by more than tol_m: SLSQP minimising the sum of squared controls
    subject to every constraint (kept with a margin margin_m), from zero controls, then the given starts (each (N, T,
    nu), e.g. a solver's failed answer), then `seeded_starts` Gaussian ones (std 0.3, seeded). Each start runs up to
    `rounds` SLSQP solves of max_iter iterations over a working set of the pairs within within_m of their distance,
    growing it by the pairs violated at the end of each. Stops at the first point that violates nothing. 'feasible'
    (with x, u, verified by collision_gaps_m / max_bound_violation on the rollout) or 'unknown'; never 'infeasible'
    (a local search proves nothing about infeasibility)."""
    N, T = problem.num_agents, int(problem.horizon)
    nu = problem.agents[0].dynamics.nu
    lo = np.concatenate([np.tile(_bounds(a.u_min, nu, -np.inf), T) for a in problem.agents])
    hi = np.concatenate([np.tile(_bounds(a.u_max, nu, np.inf), T) for a in problem.agents])
    bounds = [(None if not np.isfinite(l) else l, None if not np.isfinite(h) else h) for l, h in zip(lo, hi)]
    rng = np.random.default_rng(seed)
    candidates = [("zero controls", np.zeros(N * T * nu))]
    candidates += [(f"given start {n + 1}", np.asarray(s, dtype=float).reshape(-1)) for n, s in enumerate(starts)]
    candidates += [(f"seeded start {n + 1}", rng.normal(0.0, 0.3, N * T * nu)) for n in range(seeded_starts)]
    sp = _JointShooting(problem, margin_m)
    z_found, how = None, ""
    tried = 0
    for label, z0 in candidates:
        if z0.size != N * T * nu or not np.all(np.isfinite(z0)):
            continue
        tried += 1
        z = np.clip(z0, lo, hi)
        how = f"{label} (no SLSQP needed)"
        try:
            sp.work = np.zeros((0, 3), dtype=int)
            for r in range(rounds):
                sp.add_to_work(z, within_m)
                how = f"SLSQP from {label} (round {r + 1})"
                cons = [{"type": "ineq", "fun": sp.constraints, "jac": sp.constraints_jac}] if sp.constraints(z).size else []
                res = minimize(lambda v: 0.5 * float(v @ v), z, jac=lambda v: v, method="SLSQP", bounds=bounds,
                               constraints=cons, options={"maxiter": max_iter, "ftol": 1e-10})
                z = np.clip(res.x, lo, hi)
                sp._eval(z)
        except _FoundFeasible as found:
            z_found = found.z
            break
    best_viol, best_z = sp.best
    if z_found is None and best_z is not None and best_viol <= tol_m:
        z_found, how = best_z, "the least-violating point SLSQP visited"
    if z_found is None:
        return FeasibilityReport("unknown", f"no point violating at most {tol_m:g} m found from {tried} starts "
                                            f"(least violation {best_viol:.3g} m)", max_violation_m=float(best_viol))
    u = z_found.reshape(N, T, nu)
    x = problem.rollout(u)
    viol = max(max_collision_violation_m(problem, x), max_bound_violation(problem, x, u))
    verdict = "no constraint violated" if viol <= 0 else f"largest violation {viol:.1e}"
    return FeasibilityReport("feasible", f"{how}: {verdict}", x=x, u=u, max_violation_m=float(viol))


def problem_feasibility(problem: GameProblem, starts=(), tol_m: float = FEASIBILITY_TOL_M, **search) -> FeasibilityReport:
    """Decide whether a game has a point violating no constraint by more than tol_m: first the exact certificate of
    fixed_state_infeasibility ('infeasible'), otherwise find_feasible_point ('feasible' or 'unknown')."""
    reasons = fixed_state_infeasibility(problem, tol_m)
    if reasons:
        more = f" (and {len(reasons) - 1} more)" if len(reasons) > 1 else ""
        return FeasibilityReport("infeasible", reasons[0] + more)
    return find_feasible_point(problem, starts, tol_m=tol_m, **search)
