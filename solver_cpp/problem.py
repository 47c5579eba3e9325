"""Game description: agents (dynamics, initial state, cost, bounds), pairwise collision avoidance,
moving obstacles. `to_core()` converts the types into the C++ structs; the one validation routine is
C++ (solver_cpp/src/validate.cpp), shared by RD3G and the baselines, and names the field at fault."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from . import _core
from .models import Model


def _floats(where: str, value, ndim: int = 1) -> np.ndarray:
    """Type conversion only: an array of floats with ndim dimensions. Sizes and values (finite,
    non-negative, within bounds) are checked once, by the C++ validation (solver_cpp/src/validate.cpp)."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where} must be {'a list' if ndim == 1 else 'a table'} of numbers, got {value!r:.80}") from None
    if arr.ndim != ndim:
        raise ValueError(f"{where} must be {'a list' if ndim == 1 else 'a table'} of numbers, got shape {arr.shape}")
    return arr


def _integer(where: str, value) -> int:
    """An integer that fits the C++ int (indices, horizon)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{where} must be an integer, got {value!r:.80}")
    if not -2**31 < int(value) < 2**31:
        raise ValueError(f"{where} is out of range, got {value!r}")
    return int(value)


def _float(where: str, value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where} must be a number, got {value!r:.80}") from None


def _optional_floats(where: str, value) -> np.ndarray:
    """None = not given (empty: the C++ default, e.g. unbounded)."""
    return np.zeros(0) if value is None else _floats(where, value)


@dataclass
class QuadraticCost:
    """J = sum_k u'Ru + sum_{k>=1} (x_k-r_k)'Q_ref(x_k-r_k) + x_k'Qx_k (diagonal weights); terminal
    weights Qf_ref/Qf default to Q_ref/Q. The reference r_k is x_ref at every step, or row k-1 of
    x_ref_steps (T rows of nx, steps k = 1..T) when given: a stage-varying reference."""

    x_ref: Sequence[float]
    Q_ref: Sequence[float]
    R: Sequence[float]
    Q: Sequence[float] | None = None
    Qf_ref: Sequence[float] | None = None
    Qf: Sequence[float] | None = None
    x_ref_steps: Sequence[Sequence[float]] | None = None

    def to_core(self, where: str) -> _core.QuadraticCost:
        c = _core.QuadraticCost()
        c.x_ref = _floats(f"{where}.x_ref", self.x_ref)
        c.Q_ref = _floats(f"{where}.Q_ref", self.Q_ref)
        c.Q = _floats(f"{where}.Q", self.Q) if self.Q is not None else np.zeros(c.Q_ref.shape)
        c.R = _floats(f"{where}.R", self.R)
        c.Qf_ref = _floats(f"{where}.Qf_ref", self.Qf_ref) if self.Qf_ref is not None else c.Q_ref
        c.Qf = _floats(f"{where}.Qf", self.Qf) if self.Qf is not None else c.Q
        if self.x_ref_steps is not None:  # C++ holds one column per step
            c.x_ref_steps = np.asfortranarray(_floats(f"{where}.x_ref_steps", self.x_ref_steps, ndim=2).T)
        return c


@dataclass
class Agent:
    dynamics: Model
    x0: Sequence[float]
    cost: QuadraticCost
    u_min: Sequence[float] | None = None
    u_max: Sequence[float] | None = None
    x_min: Sequence[float] | None = None  # bounds on x_1..x_T; +-inf entries mean unbounded
    x_max: Sequence[float] | None = None
    lead_weight: float = 0.0  # racing: pays lead_weight * (x^j[lead_index] - x^i[lead_index]) per step and opponent
    lead_index: int = 0


def _min_distance(where: str, value) -> tuple[float, np.ndarray]:
    """d_min (m) as (scalar, per-step array for k = 1..T or empty): one number, or one number per step
    k = 1..T (e.g. a separation to recover over the horizon); the values are checked in C++."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where} must be a positive number or one positive number per step, got {value!r:.80}") from None
    if arr.ndim == 0:
        return float(arr), np.zeros(0)
    if arr.ndim != 1:
        raise ValueError(f"{where} must be a positive number or one positive number per step, got shape {arr.shape}")
    return (float(np.max(arr)) if arr.size else math.nan), arr


@dataclass
class PairDistance:
    """The collision distance of one pair of agents, in place of Collision.min_distance for that pair
    (e.g. relaxed for the one pair that starts too close): agents = two agent indices (either order),
    min_distance in m, one number or T numbers (k = 1..T) as in Collision."""

    agents: Sequence[int]
    min_distance: float | Sequence[float]


@dataclass
class Collision:
    """Pairwise h = d_min - |A (p_i - p_j)| ("distance") or d_min^2 - |A (p_i - p_j)|^2 ("squared") <= 0.
    min_distance: d_min in m, one number for every step or a sequence of T numbers (k = 1..T), for every
    pair not in pair_distances (at most one entry per pair). pos_x_scale: None (A = identity) or T positive
    numbers a_k, A = diag(a_k, 1) at step k, for pairs and obstacles alike (an ellipse: e.g. the Frenet
    along-track stretch 1 - kappa ey, planning.frenet)."""

    min_distance: float | Sequence[float]
    form: str = "distance"
    enabled: bool = True
    pos_x: int = 0
    pos_y: int = 1
    pair_distances: list[PairDistance] = field(default_factory=list)
    pos_x_scale: Sequence[float] | None = None

    def pair_min_distances(self, num_agents: int, horizon: int) -> np.ndarray:
        """d_min (m) of every pair of agents for k = 1..T, shape (N, N, T), symmetric: the pair's entry of
        pair_distances, else min_distance (the diagonal, which constrains nothing, is 0)."""
        d = np.empty((num_agents, num_agents, horizon))
        d[:] = np.asarray(self.min_distance, dtype=float)
        for q in self.pair_distances:
            i, j = q.agents
            d[i, j] = d[j, i] = np.asarray(q.min_distance, dtype=float)
        d[np.arange(num_agents), np.arange(num_agents)] = 0.0
        return d


def _pair_distances(entries) -> list:
    """Collision.pair_distances as C++ PairDistance entries (types only; indices and values are checked in C++)."""
    if not isinstance(entries, (list, tuple)):
        raise ValueError(f"collision.pair_distances must be a list of PairDistance, got {type(entries).__name__}")
    out = []
    for n, q in enumerate(entries):
        w = f"collision.pair_distances[{n}]"
        if not isinstance(q, PairDistance):
            raise ValueError(f"{w} must be a PairDistance, got {type(q).__name__}")
        if isinstance(q.agents, (str, bytes)) or not hasattr(q.agents, "__len__") or len(q.agents) != 2:
            raise ValueError(f"{w}.agents must be two agent indices, got {q.agents!r:.80}")
        c = _core.PairDistance()
        c.i, c.j = (_integer(f"{w}.agents[{a}]", q.agents[a]) for a in range(2))
        c.min_distance, c.min_distance_steps = _min_distance(f"{w}.min_distance", q.min_distance)
        out.append(c)
    return out


@dataclass
class Obstacle:
    """A moving disc every agent avoids: positions (T+1, 2) in agent position coordinates; min_distance
    in m, one number or T numbers (k = 1..T) as in Collision."""

    positions: np.ndarray
    min_distance: float | Sequence[float]


@dataclass
class GameProblem:
    dt: float
    horizon: int
    agents: list[Agent]
    collision: Collision | None = None
    obstacles: list[Obstacle] = field(default_factory=list)

    @property
    def num_agents(self) -> int:
        return len(self.agents)

    def rollout(self, u) -> np.ndarray:
        """States (N, T+1, nx) of every agent from its x0 under controls u (N, T, nu), through the C++ models."""
        return np.stack([np.asarray(a.dynamics.build(self.dt).rollout(np.asarray(a.x0, dtype=float), u[i]))
                         for i, a in enumerate(self.agents)])

    def to_core(self, validate: bool = True, models: bool = True) -> _core.Problem:
        """The C++ problem. validate: run the C++ validation now (Solver.setup runs it anyway);
        models=False leaves the dynamics list empty (Solver.update keeps the set-up's models)."""
        if isinstance(self.horizon, bool) or not isinstance(self.horizon, (int, np.integer)):
            raise ValueError(f"horizon must be a positive integer, got {self.horizon!r:.80}")
        if not 0 < int(self.horizon) < 2**31:
            raise ValueError(f"horizon must be a positive integer below 2^31, got {self.horizon!r}")
        dt = _float("dt", self.dt)
        if not isinstance(self.agents, (list, tuple)):
            raise ValueError(f"agents must be a list of agents, got {type(self.agents).__name__}")
        p = _core.Problem()
        p.horizon = int(self.horizon)
        p.dt = dt
        dyn, x0, costs, lead, umin, umax, xmin, xmax = [], [], [], [], [], [], [], []
        for i, a in enumerate(self.agents):
            w = f"agents[{i}]"
            if not isinstance(a, Agent):
                raise ValueError(f"{w} must be an Agent, got {type(a).__name__}")
            if models:
                if not hasattr(a.dynamics, "build"):
                    raise ValueError(f"{w}.dynamics is not a model description")
                dyn.append(a.dynamics.build(dt, where=f"{w}.dynamics"))
            x0.append(_floats(f"{w}.x0", a.x0))
            if not isinstance(a.cost, QuadraticCost):
                raise ValueError(f"{w}.cost must be a QuadraticCost, got {type(a.cost).__name__}")
            costs.append(a.cost.to_core(f"{w}.cost"))
            lc = _core.LeadCost()
            lc.weight = _float(f"{w}.lead_weight", a.lead_weight)
            lc.index = _integer(f"{w}.lead_index", a.lead_index)
            lead.append(lc)
            umin.append(_optional_floats(f"{w}.u_min", a.u_min))
            umax.append(_optional_floats(f"{w}.u_max", a.u_max))
            xmin.append(_optional_floats(f"{w}.x_min", a.x_min))
            xmax.append(_optional_floats(f"{w}.x_max", a.x_max))
        p.dynamics, p.x0, p.costs, p.lead = dyn, x0, costs, lead
        p.u_min, p.u_max, p.x_min, p.x_max = umin, umax, xmin, xmax
        cs = _core.CollisionSpec()
        col = self.collision
        cs.enabled = False
        if col is not None:
            if not isinstance(col, Collision):
                raise ValueError(f"collision must be a Collision, got {type(col).__name__}")
            # The form and the position indices also apply to obstacles, so they are read even for one agent.
            if col.form not in ("distance", "squared"):
                raise ValueError(f"collision.form must be 'distance' or 'squared', got {col.form!r}")
            cs.form = getattr(_core.CollisionForm, col.form)
            cs.pos_x, cs.pos_y = _integer("collision.pos_x", col.pos_x), _integer("collision.pos_y", col.pos_y)
            cs.pos_x_scale_steps = _optional_floats("collision.pos_x_scale", col.pos_x_scale)
            if col.enabled and len(self.agents) >= 2:
                cs.min_distance, cs.min_distance_steps = _min_distance("collision.min_distance", col.min_distance)
                cs.pair_distances = _pair_distances(col.pair_distances)
                cs.enabled = True
        p.collision = cs
        if not isinstance(self.obstacles, (list, tuple)):
            raise ValueError(f"obstacles must be a list of obstacles, got {type(self.obstacles).__name__}")
        obs = []
        for n, o in enumerate(self.obstacles):
            if not isinstance(o, Obstacle):
                raise ValueError(f"obstacles[{n}] must be an Obstacle, got {type(o).__name__}")
            co = _core.Obstacle()
            co.positions = _floats(f"obstacles[{n}].positions", o.positions, ndim=2)
            co.min_distance, co.min_distance_steps = _min_distance(f"obstacles[{n}].min_distance", o.min_distance)
            obs.append(co)
        p.obstacles = obs
        if validate:
            _core.validate_problem(p)
        return p
