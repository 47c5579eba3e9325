"""The racing line as the planners' stage-varying reference (``PlannerConfig.line = "racing"``).

At each plan the horizon's stages k = 1..T get the line's lateral offset ey_ref(s_k) and speed
v_ref(s_k) at the centre-line arc lengths s_k the car reaches along the line: from the current
(s_0, v_0), the speed moves towards the line's speed within the planner's drive and brake limits,
and the car following the line at offset ey advances the centre-line arc length at
v / (1 - kappa(s) ey) (Frenet progress rate at zero heading error), step by step with the
planning step dt.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tracks.racing_line import RacingLine, limits_for_car, racing_line

from .config import PlannerConfig
from .frenet import lateral_half_extent


def planner_racing_line(track, car, top_speed_mps: float, config: PlannerConfig | None = None) -> RacingLine:
    """The racing line the planners follow: the car's limits (vehicles.params.CarParams) with the
    planner's lateral half-extent, track margin plus line margin and braking bound (PlannerConfig); cached."""
    config = config or PlannerConfig()
    limits = limits_for_car(car, top_speed_mps=top_speed_mps,
                            half_width_m=lateral_half_extent(car.geometry, config.heading_allowance_rad),
                            margin_m=config.track_margin_m + config.line_margin_m, brake_mps2=config.max_brake_mps2)
    return racing_line(track, limits)


@dataclass(frozen=True)
class StageReference:
    """References at the stages k = 1..T of one plan: s (centre-line arc length, m, unwrapped like
    the car's s), ey (m), v (m/s); each of shape (T,)."""

    s: np.ndarray
    ey: np.ndarray
    v: np.ndarray


def stage_reference(line: RacingLine, curvature, s0: float, v0: float, horizon: int, dt: float,
                    accel_mps2: float, brake_mps2: float) -> StageReference:
    """The line's references at the stages of a plan from centre-line arc length ``s0`` (m) at
    speed ``v0`` (m/s); ``curvature(s)``: the centre line's curvature (1/m) at an unwrapped arc length, as
    Track.curvature wraps it on a closed track."""
    s = np.empty(horizon + 1)
    v = np.empty(horizon + 1)
    s[0], v[0] = float(s0), max(float(v0), 0.0)
    for k in range(horizon):
        ey = float(line.lateral_offset(s[k]))
        stretch = max(1.0 - float(curvature(s[k])) * ey, 0.2)
        s[k + 1] = s[k] + dt * v[k] / stretch
        target = float(line.speed(s[k + 1]))
        v[k + 1] = min(max(target, v[k] - brake_mps2 * dt), v[k] + accel_mps2 * dt)
    return StageReference(s=s[1:], ey=np.asarray(line.lateral_offset(s[1:]), dtype=float),
                          v=np.asarray(line.speed(s[1:]), dtype=float))


def path_speed_bounds(v, curvature, dt: float, lateral_accel_mps2: float, brake_mps2: float) -> np.ndarray:
    """Tyre-aware speed bounds (m/s) along a planned path: segment k (k = 0..T-1, from stage k to k+1,
    at speed ``v[k]`` m/s for ``dt`` s on a path of curvature ``curvature[k]`` 1/m) may be driven at
    sqrt(lateral_accel / |curvature|) at most, and from stage k the car must be able to brake to every
    later segment's bound at ``brake_mps2``: bound_k = min over j >= k of
    sqrt(corner_j^2 + 2 brake d_kj), d_kj the path length from stage k to stage j (the plan's own
    speeds times dt). Returns (T,) bounds, +inf where no turn limits the speed."""
    v = np.maximum(np.asarray(v, dtype=float), 0.0)
    kappa = np.abs(np.asarray(curvature, dtype=float))
    with np.errstate(divide="ignore"):
        corner = np.where(kappa > 0, np.sqrt(lateral_accel_mps2 / np.where(kappa > 0, kappa, 1.0)), np.inf)
    bound = np.empty(len(corner))
    reach = math.inf
    for k in range(len(corner) - 1, -1, -1):  # backward pass: brake from stage k to every later segment's bound
        reach = min(float(corner[k]), math.sqrt(reach * reach + 2.0 * brake_mps2 * float(v[k]) * dt))
        bound[k] = reach
    return bound
