"""Game description: agents (dynamics, initial state, cost, bounds), pairwise collision avoidance,
moving obstacles. Validation happens here and names the field at fault; `to_core()` builds the C++
structs."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from . import _core
from .models import Model


def _vector(where: str, value, n: int, allow_inf: bool = False) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where} must be a list of {n} numbers") from None
    if arr.shape != (n,):
        raise ValueError(f"{where} must have {n} values, got shape {arr.shape}")
    bad = np.isnan(arr) if allow_inf else ~np.isfinite(arr)
    if bad.any():
        raise ValueError(f"{where}[{int(np.flatnonzero(bad)[0])}] is not a finite number")
    return arr


def _bounds(where: str, name: str, lower, upper, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Optional box bounds (None = unbounded; +-inf entries allowed), lower strictly below upper."""
    lo = _vector(f"{where}.{name}_min", lower, n, True) if lower is not None else np.full(n, -np.inf)
    hi = _vector(f"{where}.{name}_max", upper, n, True) if upper is not None else np.full(n, np.inf)
    if not (lo < hi).all():
        raise ValueError(f"{where}.{name}_min must be below {where}.{name}_max in every component")
    return lo, hi


@dataclass
class QuadraticCost:
    """J = sum_k u'Ru + sum_{k>=1} (x-x_ref)'Q_ref(x-x_ref) + x'Qx (diagonal weights); terminal
    weights Qf_ref/Qf default to Q_ref/Q."""

    x_ref: Sequence[float]
    Q_ref: Sequence[float]
    R: Sequence[float]
    Q: Sequence[float] | None = None
    Qf_ref: Sequence[float] | None = None
    Qf: Sequence[float] | None = None

    def to_core(self, nx: int, nu: int, where: str) -> _core.QuadraticCost:
        c = _core.QuadraticCost()
        c.x_ref = _vector(f"{where}.x_ref", self.x_ref, nx)
        c.Q_ref = _vector(f"{where}.Q_ref", self.Q_ref, nx)
        c.Q = _vector(f"{where}.Q", self.Q if self.Q is not None else np.zeros(nx), nx)
        c.R = _vector(f"{where}.R", self.R, nu)
        c.Qf_ref = _vector(f"{where}.Qf_ref", self.Qf_ref if self.Qf_ref is not None else c.Q_ref, nx)
        c.Qf = _vector(f"{where}.Qf", self.Qf if self.Qf is not None else c.Q, nx)
        for name in ("Q_ref", "Q", "R", "Qf_ref", "Qf"):
            arr = getattr(c, name)
            if (arr < 0).any():
                raise ValueError(f"{where}.{name} must be non-negative")
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


def _min_distance(where: str, value, T: int) -> tuple[float, np.ndarray]:
    """d_min (m) as (scalar, per-step array for k = 1..T or empty): a positive number, or T positive
    numbers (one per step k = 1..T, e.g. a separation to recover over the horizon)."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        d = float(arr)
        if not np.isfinite(d) or d <= 0:
            raise ValueError(f"{where} must be positive, got {value!r}")
        return d, np.zeros(0)
    if arr.shape != (T,) or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"{where} must be a positive number or {T} positive numbers (one per step k = 1..T), "
                         f"got shape {arr.shape} with min {np.min(arr) if arr.size else None!r}")
    return float(np.max(arr)), arr


@dataclass
class Collision:
    """Pairwise h = d_min - |p_i - p_j| ("distance") or d_min^2 - |p_i - p_j|^2 ("squared") <= 0.
    min_distance: d_min in m, one number for every step or a sequence of T numbers (k = 1..T)."""

    min_distance: float | Sequence[float]
    form: str = "distance"
    enabled: bool = True
    pos_x: int = 0
    pos_y: int = 1


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

    def to_core(self) -> _core.Problem:
        if isinstance(self.horizon, bool) or not isinstance(self.horizon, (int, np.integer)) or self.horizon < 1:
            raise ValueError(f"horizon must be a positive integer, got {self.horizon!r}")
        try:
            dt = float(self.dt)
        except (TypeError, ValueError):
            raise ValueError(f"dt must be a positive number, got {self.dt!r}") from None
        if not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt must be a positive finite number, got {self.dt!r}")
        if not self.agents:
            raise ValueError("agents must contain at least one agent")
        T = int(self.horizon)
        p = _core.Problem()
        p.horizon = T
        p.dt = dt
        dyn, x0, costs, lead, umin, umax, xmin, xmax = [], [], [], [], [], [], [], []
        nx = nu = None
        for i, a in enumerate(self.agents):
            w = f"agents[{i}]"
            if not hasattr(a.dynamics, "build"):
                raise ValueError(f"{w}.dynamics is not a model description")
            d = a.dynamics.build(dt, where=f"{w}.dynamics")
            if nx is None:
                nx, nu = d.nx, d.nu
            elif (d.nx, d.nu) != (nx, nu):
                raise ValueError(f"{w}.dynamics: every agent must have nx={nx}, nu={nu} (got {d.nx}, {d.nu})")
            dyn.append(d)
            x0.append(_vector(f"{w}.x0", a.x0, nx))
            costs.append(a.cost.to_core(nx, nu, f"{w}.cost"))
            lc = _core.LeadCost()
            lc.weight = float(a.lead_weight)
            if not np.isfinite(lc.weight):
                raise ValueError(f"{w}.lead_weight must be finite")
            if not 0 <= int(a.lead_index) < nx:
                raise ValueError(f"{w}.lead_index must be a state index in [0, {nx})")
            lc.index = int(a.lead_index)
            lead.append(lc)
            lo, hi = _bounds(w, "u", a.u_min, a.u_max, nu)
            umin.append(lo)
            umax.append(hi)
            lo, hi = _bounds(w, "x", a.x_min, a.x_max, nx)
            xmin.append(lo)
            xmax.append(hi)
        p.dynamics, p.x0, p.costs, p.lead = dyn, x0, costs, lead
        p.u_min, p.u_max, p.x_min, p.x_max = umin, umax, xmin, xmax
        cs = _core.CollisionSpec()
        col = self.collision
        cs.enabled = False
        if col is not None:
            # The form also applies to obstacles, so it is read even for a single agent.
            if col.form not in ("distance", "squared"):
                raise ValueError(f"collision.form must be 'distance' or 'squared', got {col.form!r}")
            cs.form = getattr(_core.CollisionForm, col.form)
            for name in ("pos_x", "pos_y"):
                if not 0 <= int(getattr(col, name)) < nx:
                    raise ValueError(f"collision.{name} must be a state index in [0, {nx})")
            cs.pos_x, cs.pos_y = int(col.pos_x), int(col.pos_y)
            if col.enabled and len(self.agents) >= 2:
                cs.min_distance, cs.min_distance_steps = _min_distance("collision.min_distance", col.min_distance, T)
                cs.enabled = True
        p.collision = cs
        obs = []
        for n, o in enumerate(self.obstacles):
            pos = np.asarray(o.positions, dtype=float)
            if pos.shape != (T + 1, 2) or not np.all(np.isfinite(pos)):
                raise ValueError(f"obstacles[{n}].positions must be finite with shape ({T + 1}, 2), got {pos.shape}")
            co = _core.Obstacle()
            co.positions = pos
            co.min_distance, co.min_distance_steps = _min_distance(f"obstacles[{n}].min_distance", o.min_distance, T)
            obs.append(co)
        p.obstacles = obs
        return p
