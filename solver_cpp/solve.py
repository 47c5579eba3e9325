"""solve(): run RD3G on a GameProblem and return numpy results; settings map one-to-one onto the
C++ Settings struct (defaults live only there, in solver_cpp/include/rd3g/problem.hpp)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from . import _core
from .problem import GameProblem



def make_settings(**overrides) -> _core.Settings:
    """C++ defaults, with keyword overrides; unknown names, bad types or values out of range raise
    ValueError naming them."""
    s = fill_settings(_core.Settings(), "solver", overrides)
    _core.validate_settings(s)  # ranges, with the C++ set-up's messages
    return s


def fill_settings(s, where: str, overrides: dict):
    """Set the fields of a C++ settings struct (RD3G's or a baseline's) from keyword overrides, converting
    each to the field's type; unknown names, wrong types, non-finite floats and integers beyond the C++
    int raise ValueError naming ``where.name`` (never pybind11's own TypeError)."""
    for name, value in overrides.items():
        if name.startswith("_") or not hasattr(s, name):
            raise ValueError(f"{where}.{name} is not a {where} setting")
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


def settings_dict(settings: _core.Settings) -> dict:
    out = {}
    for name in dir(settings):
        if name.startswith("_"):
            continue
        v = getattr(settings, name)
        if callable(v):
            continue
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
    saddle_escapes: int = 0  # attempts started from a saddle along negative curvature (setting saddle_escapes)
    best_response_attempts: int = 0    # attempts started from an iterated-best-response guess (best_response_rounds)
    best_response_iterations: int = 0  # Newton iterations of its single-agent sub-solves (1/N each in iterations)
    # Per agent: smallest eigenvalue of the reduced Hessian of its Lagrangian at the returned point (cost units per
    # control unit^2, inf = no free direction; empty if the test is off). Negative = a saddle of that agent's problem.
    second_order: np.ndarray = field(default_factory=lambda: np.zeros(0))
    constraints: list = field(repr=False, default_factory=list)
    setup_time_s: float = 0.0   # the solver's last set-up (validation, constraint list, allocation), maybe older
    update_time_s: float = 0.0  # update calls since the previous solve
    setups: int = 0             # set-ups since the previous solve (1 after Solver(), or a bound made (in)finite)

    @property
    def converged(self) -> bool:
        return self.status == "converged"

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

    def update_settings(self, settings: _core.Settings | None = None, **overrides) -> None:
        """New settings: a complete Settings, or keyword overrides of the current ones."""
        if settings is None:
            settings = make_settings(**{**settings_dict(self.settings), **overrides})
        self._solver.update_settings(settings)
        self.settings = settings

    def solve(self, warm_start: WarmStart | None = None) -> GameResult:
        ws = None
        if warm_start is not None:
            ws = _to_core_warm(warm_start, self._sizes, len(self.constraints))
        r = self._solver.solve(ws)
        i = r.info
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
            second_order=np.asarray(i.second_order, dtype=float))

    def best_response(self, rounds: int, warm_start: WarmStart | None = None) -> WarmStart:
        """Controls (N, T, nu) after `rounds` (>= 1) Gauss-Seidel sweeps of iterated best response from the warm
        start's controls (zero without), with the C++ sweeps of the best-response restart (best_response_rounds)."""
        ws = None if warm_start is None else _to_core_warm(warm_start, self._sizes, len(self.constraints))
        return WarmStart(u=np.stack(self._solver.best_response(int(rounds), ws).u))


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
    """Solve a game once. Keyword overrides are solver settings (tol, max_iter, linear_solver, ...)."""
    return Solver(problem, settings, **overrides).solve(warm_start)
