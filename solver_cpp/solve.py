"""solve(): run RD3G on a GameProblem and return numpy results; settings map one-to-one onto the
C++ Settings struct and its groups (defaults live only there, in solver_cpp/include/rd3g/problem.hpp)."""
from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from . import _core
from .problem import GameProblem



# Settings are grouped by concern as in the C++ struct (solver_cpp/include/rd3g/problem.hpp): top-level
# tol, max_iter, time_limit, ... and one group per concern, given as a mapping, e.g.
# make_settings(tol=1e-4, stall=dict(window=8), restart=dict(count=3)); problem files use the same nesting.
SETTING_GROUPS = ("barrier", "line_search", "linear", "stall", "restart", "best_response", "second_order", "order")

# The flat names of the previous release, accepted with a DeprecationWarning until the next one.
FLAT_SETTING_NAMES = {
    "rho_init": "barrier.rho_init", "rho_floor_factor": "barrier.rho_floor_factor", "rho_kappa": "barrier.rho_kappa",
    "rho_beta": "barrier.rho_beta", "rho_progress": "barrier.rho_progress", "barrier_margin": "barrier.margin",
    "barrier": "barrier.mode",
    "ls_alpha": "line_search.alpha", "ls_beta": "line_search.beta", "ls_max_steps": "line_search.max_steps",
    "violation_memory": "line_search.violation_memory", "lm_tries": "line_search.lm_tries",
    "linear_solver": "linear.solver", "lscg_tol": "linear.lscg_tol",
    "lscg_max_iter": "linear.lscg_max_iter",
    "stall_window": "stall.window", "stall_floor_window": "stall.floor_window", "crawl_window": "stall.crawl_window",
    "crawl_ratio": "stall.crawl_ratio", "polish_gap": "stall.polish_gap",
    "restarts": "restart.count", "restart_rho_progress": "restart.rho_progress",
    "restart_violation_memory": "restart.violation_memory", "restart_rho_on_stall": "restart.rho_on_stall",
    "deep_overlap": "restart.deep_overlap",
    "best_response_rounds": "best_response.rounds",
    "best_response_max_iter": "best_response.max_iter", "best_response_margin": "best_response.margin",
    "second_order_gap": "second_order.gap", "second_order_tol": "second_order.tol",
    "restart_on_saddle": "second_order.restart_on_saddle", "saddle_escapes": "second_order.escapes",
    "saddle_inertia": "second_order.inertia",
}

# Settings of the previous release that are now fixed constants of the solver (no caller ever set them), by their
# flat names, with the value the solver uses: accepted with a DeprecationWarning and ignored until the next release.
REMOVED_SETTING_NAMES = {
    "multiplier_tol": 1e-6, "fraction_to_boundary": 0.99, "lm_below_step": 0.01, "lm_nu_init": 1e-6,
    "refinement_steps": 2, "restart_u_std": 0.2, "saddle_step": 1.0, "saddle_rho": 0.01,
}
# Removed settings whose rule is gone altogether (no fixed value stands in for them): what the solver does instead.
REMOVED_RULES = {
    "lm_below_step": "Levenberg-Marquardt steps run only after a failed line search, never beside a short Newton step",
}


def grouped_settings(overrides: Mapping, where: str = "solver", stacklevel: int = 3, source: str = "") -> dict:
    """Overrides in the grouped form: a flat name of the previous release moves into its group with a
    DeprecationWarning naming the new name (``barrier="primal"`` becomes ``barrier={"mode": "primal"}``); a removed
    setting (REMOVED_SETTING_NAMES) is dropped with a DeprecationWarning giving the value the solver uses, or what it
    does instead where the rule is gone (REMOVED_RULES)."""
    out: dict = {}
    for name, value in overrides.items():
        if name in REMOVED_SETTING_NAMES:
            instead = REMOVED_RULES.get(name, f"the solver uses the fixed value {REMOVED_SETTING_NAMES[name]}")
            warnings.warn(f"{source}{where}.{name} is deprecated and ignored: {instead}", DeprecationWarning,
                          stacklevel=stacklevel)
        elif name in SETTING_GROUPS and isinstance(value, Mapping):
            out.setdefault(name, {}).update(value)
        elif name in FLAT_SETTING_NAMES:
            group, field_name = FLAT_SETTING_NAMES[name].split(".")
            warnings.warn(f"{source}{where}.{name} is deprecated: use {where}.{group}.{field_name}", DeprecationWarning,
                          stacklevel=stacklevel)
            out.setdefault(group, {})[field_name] = value
        else:
            out[name] = value
    return out


def merge_settings(*layers: Mapping) -> dict:
    """Grouped overrides from layers of overrides (flat names warned about), a later layer overriding an earlier
    one field by field; a None value means the solver's default (the key is dropped)."""
    merged: dict = {}
    for layer in layers:
        for name, value in grouped_settings(layer, stacklevel=4).items():
            if isinstance(value, Mapping):
                merged.setdefault(name, {}).update(value)
            else:
                merged[name] = value
    out = {}
    for name, value in merged.items():
        if isinstance(value, Mapping):
            value = {k: v for k, v in value.items() if v is not None}
        if value is not None:
            out[name] = value
    return out


def make_settings(**overrides) -> _core.Settings:
    """C++ defaults, with keyword overrides in the grouped form (``make_settings(tol=1e-4, stall=dict(window=8))``;
    flat names of the previous release are accepted with a DeprecationWarning); unknown names, bad types or values
    out of range raise ValueError naming them (``solver.stall.window``)."""
    s = _core.Settings()
    for name, value in grouped_settings(overrides).items():
        if name in SETTING_GROUPS:
            if not isinstance(value, Mapping):
                raise ValueError(f"solver.{name} must be a mapping of {name} settings, got {value!r:.80}")
            fill_settings(getattr(s, name), f"solver.{name}", value, kind="solver")
        else:
            fill_settings(s, "solver", {name: value})
    _core.validate_settings(s)  # ranges, with the C++ set-up's messages
    return s


def fill_settings(s, where: str, overrides: Mapping, kind: str | None = None):
    """Set the fields of a C++ settings struct (RD3G's, one of its groups or a baseline's) from keyword overrides,
    converting each to the field's type; unknown names, wrong types, non-finite floats and integers beyond the C++
    int raise ValueError naming ``where.name`` (never pybind11's own TypeError)."""
    for name, value in overrides.items():
        if name.startswith("_") or not hasattr(s, name) or (where == "solver" and name in SETTING_GROUPS):
            raise ValueError(f"{where}.{name} is not a {kind or where} setting")
        current = getattr(s, name)
        try:
            if hasattr(type(current), "__members__"):  # a C++ enum: accept its value names
                choices = tuple(type(current).__members__)
                if not isinstance(value, str) or value not in choices:
                    raise ValueError(f"{where}.{name} must be one of {choices}, got {value!r}")
                value = type(current).__members__[value]
            elif isinstance(current, bool):
                value = bool(value)
            elif isinstance(current, int):
                if isinstance(value, bool) or int(value) != value:
                    raise ValueError(f"{where}.{name} must be an integer, got {value!r}")
                if not -2**31 < int(value) < 2**31:
                    raise ValueError(f"{where}.{name} must be an integer below 2^31 in magnitude, got {value!r}")
                value = int(value)
            elif isinstance(current, float):
                value = float(value)
                if not np.isfinite(value):
                    raise ValueError(f"{where}.{name} must be finite, got {value!r}")
            setattr(s, name, value)
        except (TypeError, ValueError, OverflowError) as exc:
            if str(exc).startswith(f"{where}.{name}"):
                raise
            raise ValueError(f"{where}.{name}: invalid value {value!r:.80}") from None
    return s


def settings_dict(settings) -> dict:
    """The settings as a dict in the grouped form (enums by their value names), e.g. for make_settings(**d)."""
    out = {}
    for name in dir(settings):
        if name.startswith("_"):
            continue
        v = getattr(settings, name)
        if callable(v):
            continue
        if name in SETTING_GROUPS:
            out[name] = settings_dict(v)
        else:
            out[name] = v.name if hasattr(type(v), "__members__") else v
    return out


@dataclass
class GameResult:
    """Solution of a game. Shapes: x (N, T+1, nx), u (N, T, nu), lam (N, T, nx); mu and h hold one
    entry per constraint (see `constraints`): the equality multiplier of an active constraint or the
    barrier-implied -rho/h of an inactive one. Times in seconds."""

    status: str
    x: np.ndarray
    u: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    h: np.ndarray
    iterations: int
    residual_norm: float
    max_violation: float
    residual_history: np.ndarray
    solve_time_s: float
    assembly_time_s: float
    linear_solve_time_s: float
    line_search_time_s: float
    active_constraints: int
    symbolic_factorizations: int
    attempts: int = 1  # 1 + restarts used (escapes from saddles included)
    saddle_escapes: int = 0  # attempts started from a saddle along negative curvature (setting second_order.escapes)
    best_response_attempts: int = 0    # attempts started from an iterated-best-response guess (best_response.rounds)
    best_response_iterations: int = 0  # Newton iterations of its single-agent sub-solves (1/N each in iterations)
    # Per agent: smallest eigenvalue of the reduced Hessian of its Lagrangian at the returned point (cost units per
    # control unit^2, inf = no free direction; empty if the test is off). Negative = a saddle of that agent's problem.
    second_order: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # See the passing_order property: filled by the solver when its passing-order search ran, else computed on
    # first use by passing_order_report (the solve itself no longer rolls out and scans the initial guess for it).
    passing_order_found: list = field(default_factory=list)
    passing_order_report: Callable[[], list] | None = field(default=None, repr=False, compare=False)
    # The passing-order search's candidates (setting order.candidates; empty if it did not run): dicts requested and
    # found (winding per pair of passing_order), guess_residual, polished, status, iterations, equilibrium, returned,
    # u (N, T, nu): the polished point's controls if it converged, else None (warm-start a solve from them).
    orders: list = field(default_factory=list)
    order_attempts: int = 0     # polish attempts of the passing-order search
    order_iterations: int = 0   # Newton iterations of its ordered guesses' single-agent sub-solves (1/N each)
    domain_iterations: int = 0  # Newton iterations of the domain rescue's bounded game (docs/solver.md; in iterations)
    bounded_start_iterations: int = 0  # Newton iterations of the bounded start's bounded game (docs/solver.md; in iterations)
    constraints: list = field(repr=False, default_factory=list)
    setup_time_s: float = 0.0   # the solver's last set-up (validation, constraint list, allocation), maybe older
    update_time_s: float = 0.0  # update calls since the previous solve
    setups: int = 0             # set-ups since the previous solve (1 after Solver(), or a bound made (in)finite)

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    @property
    def passing_order(self) -> list:
        """The pairs whose rolled-out initial guess comes closer than d_min (in a point the passing-order rescue
        returns: whose solo plans do), with the order the returned point gives them: dicts i, j, winding (+1: p_j - p_i
        turns counterclockwise over the horizon), first (the agent ahead at their closest approach), side
        ("left"/"right": where the other passes first), gap (m)."""
        if not self.passing_order_found and self.passing_order_report is not None:
            self.passing_order_found = self.passing_order_report()
            self.passing_order_report = None
        return self.passing_order_found

    @property
    def other_orders(self) -> list:
        """Windings (one per pair of passing_order) of the other local equilibria the passing-order search found:
        equilibria whose order differs from the returned point's."""
        mine = [p["winding"] for p in self.passing_order]
        out: list = []
        for c in self.orders:
            if c["equilibrium"] and c["found"] != mine and c["found"] not in out:
                out.append(c["found"])
        return out

    def pair_multipliers(self) -> np.ndarray:
        """mu for the pairwise collision constraints as an array (T, N, N) for k = 1..T (symmetric)."""
        N = self.x.shape[0]
        T = self.u.shape[1]
        out = np.zeros((T, N, N))
        for c, con in enumerate(self.constraints):
            if con.kind == _core.ConstraintKind.pair:
                out[con.k - 1, con.i, con.j] = out[con.k - 1, con.j, con.i] = self.mu[c]
        return out


@dataclass
class WarmStart:
    """Controls (N, T, nu), dynamics multipliers (N, T, nx), constraint multipliers (one per constraint)."""

    u: np.ndarray
    lam: np.ndarray | None = None
    mu: np.ndarray | None = None

    @staticmethod
    def shifted(result: GameResult) -> "WarmStart":
        """Receding horizon: drop the first step and repeat the last one."""
        u = np.concatenate([result.u[:, 1:], result.u[:, -1:]], axis=1)
        lam = np.concatenate([result.lam[:, 1:], result.lam[:, -1:]], axis=1)
        return WarmStart(u=u, lam=lam, mu=None)


class Solver:
    """Set up once (validation, constraint list, allocation), then update and solve many times (OSQP style):

        solver = Solver(problem, tol=1e-4)
        result = solver.solve()
        solver.update(new_problem)             # same structure, new x0, costs, bounds, distances, obstacles
        solver.update_settings(max_iter=20)    # overrides of the current settings
        result = solver.solve(WarmStart.shifted(result))
    """

    def __init__(self, problem: GameProblem, settings: _core.Settings | None = None, **overrides):
        self.problem = problem
        self.settings = settings if settings is not None else make_settings(**overrides)
        self._solver = _core.Solver()
        core = problem.to_core(validate=False)  # setup validates
        self._solver.setup(core, self.settings)
        self._sizes = (len(core.x0), int(core.horizon), core.dynamics[0].nx, core.dynamics[0].nu)
        self._constraints = list(self._solver.constraints())
        self._structure = self._solver.structure_version()
        self._updates = 0  # problem updates since the set-up (a result's lazy report must see its own problem)

    @property
    def constraints(self):
        if self._structure != self._solver.structure_version():
            self._constraints = list(self._solver.constraints())
            self._structure = self._solver.structure_version()
        return self._constraints

    def update(self, problem: GameProblem) -> None:
        """New data without a new set-up: problem must have the set-up's agents, horizon, models,
        collision form and position indices and number of obstacles; everything else (x0, costs, lead
        terms, bounds, collision distances (per pair too), obstacle positions and distances) may change. ValueError
        names the field at fault, and the solver keeps its previous problem."""
        for i, (new, old) in enumerate(zip(problem.agents, self.problem.agents)):
            if new.dynamics is not old.dynamics and not _same_model(new.dynamics, old.dynamics):
                raise ValueError(f"agents[{i}].dynamics: update keeps the set-up's models; set up a new Solver "
                                 "for another model")
        self._solver.update(problem.to_core(validate=False, models=False))
        self.problem = problem
        self._updates += 1

    def update_settings(self, settings: _core.Settings | None = None, **overrides) -> None:
        """New settings: a complete Settings, or keyword overrides of the current ones."""
        if settings is None:
            settings = make_settings(**merge_settings(settings_dict(self.settings), overrides))
        self._solver.update_settings(settings)
        self.settings = settings

    def solve(self, warm_start: WarmStart | None = None) -> GameResult:
        ws = None
        if warm_start is not None:
            ws = _to_core_warm(warm_start, self._sizes, len(self.constraints))
        r = self._solver.solve(ws)
        i = r.info
        found = [_passing_pair(p) for p in i.passing_order]
        return GameResult(
            status=_core.status_name(i.status),
            x=np.stack(r.x), u=np.stack(r.u), lam=np.stack(r.lam), mu=np.asarray(r.mu), h=np.asarray(r.h),
            iterations=i.iterations, residual_norm=i.residual_norm, max_violation=i.max_violation,
            residual_history=np.asarray(i.residual_history), solve_time_s=i.timings.total,
            assembly_time_s=i.timings.assembly, linear_solve_time_s=i.timings.linear_solve,
            line_search_time_s=i.timings.line_search, active_constraints=i.active_constraints,
            symbolic_factorizations=i.symbolic_factorizations, attempts=i.attempts, saddle_escapes=i.saddle_escapes,
            best_response_attempts=i.best_response_attempts, best_response_iterations=i.best_response_iterations,
            constraints=self.constraints,
            setup_time_s=i.timings.setup, update_time_s=i.timings.update, setups=i.setups,
            second_order=np.asarray(i.second_order, dtype=float),
            orders=[_order_candidate(c) for c in i.orders],
            order_attempts=i.order_attempts, order_iterations=i.order_iterations,
            domain_iterations=i.domain_iterations, bounded_start_iterations=i.bounded_start_iterations,
            passing_order_found=found, passing_order_report=None if found else self._order_report(r.x, ws))

    def _order_report(self, x, ws) -> Callable[[], list]:
        """The passing order of trajectories x from this solve's initial guess, computed when first asked for: by this
        solver while its problem is unchanged, else by a fresh set-up of the problem it solved."""
        problem, updates = self.problem, self._updates

        def report() -> list:
            core = self._solver
            if self._updates != updates:
                core = _core.Solver()
                core.setup(problem.to_core(validate=False), self.settings)
            return [_passing_pair(p) for p in core.passing_order(x, ws)]
        return report

    def best_response(self, rounds: int, warm_start: WarmStart | None = None) -> WarmStart:
        """Controls (N, T, nu) after `rounds` (>= 1) Gauss-Seidel sweeps of iterated best response from the warm
        start's controls (zero without), with the C++ sweeps of the best-response restart (best_response.rounds)."""
        ws = None if warm_start is None else _to_core_warm(warm_start, self._sizes, len(self.constraints))
        return WarmStart(u=np.stack(self._solver.best_response(int(rounds), ws).u))


def _passing_pair(p) -> dict:
    return {"i": p.i, "j": p.j, "winding": p.winding, "first": p.first, "side": "left" if p.side > 0 else "right",
            "gap": p.gap}


def _order_candidate(c) -> dict:
    return {"requested": list(c.requested), "found": list(c.found), "guess_residual": c.guess_residual,
            "polished": c.polished, "status": _core.status_name(c.status) if c.polished else None,
            "iterations": c.iterations, "equilibrium": c.equilibrium, "returned": c.returned,
            "u": np.stack(c.u) if len(c.u) else None}


def _same_model(a, b) -> bool:
    """Model descriptions with equal fields (arrays compared by value)."""
    if type(a) is not type(b) or not dataclasses.is_dataclass(a):
        return False
    return all(np.array_equal(np.asarray(getattr(a, f.name)), np.asarray(getattr(b, f.name)))
               for f in dataclasses.fields(a))


def _to_core_warm(w: WarmStart, sizes: tuple[int, int, int, int], n_constraints: int) -> _core.WarmStart:
    N, T, nx, nu = sizes
    ws = _core.WarmStart()
    u = np.asarray(w.u, dtype=float)
    if u.shape != (N, T, nu) or not np.all(np.isfinite(u)):
        raise ValueError(f"warm_start.u must be finite with shape ({N}, {T}, {nu}), got {u.shape}")
    ws.u = list(u)
    if w.lam is not None:
        lam = np.asarray(w.lam, dtype=float)
        if lam.shape != (N, T, nx) or not np.all(np.isfinite(lam)):
            raise ValueError(f"warm_start.lam must be finite with shape ({N}, {T}, {nx}), got {lam.shape}")
        ws.lam = list(lam)
    if w.mu is not None:
        mu = np.asarray(w.mu, dtype=float)
        if mu.shape != (n_constraints,) or not np.all(np.isfinite(mu)):
            raise ValueError(f"warm_start.mu must be finite with shape ({n_constraints},), got {mu.shape}")
        ws.mu = mu
    return ws


def solve(problem: GameProblem, settings: _core.Settings | None = None, warm_start: WarmStart | None = None,
          **overrides) -> GameResult:
    """Solve a game once. Keyword overrides are solver settings, grouped as in make_settings
    (tol=1e-4, linear=dict(solver="sparse_lu"), ...)."""
    return Solver(problem, settings, **overrides).solve(warm_start)
