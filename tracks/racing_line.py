"""A racing line for any closed track: the minimum-curvature line within the track limits and its
lap-time speed profile at the car's limits, computed once per track and car and cached.

    limits = limits_for_car(car, top_speed_mps=2.0, half_width_m=0.047, margin_m=0.03)
    line = racing_line(track, limits)          # cached under runs/cache/racing_lines/
    ey, v = line.lateral_offset(s), line.speed(s)   # s: centre-line arc length (m)

**Line.** The line is the centre line shifted by ``ey(s)`` along its left normal. ``ey`` at N
samples (about every 4 cm of centre line) minimises the discrete bending energy of the line,
sum_i phi_i^2 / m_i (phi_i the turning angle at sample i, m_i half the two adjacent edges:
the integral of curvature^2 over the line's own arc length), within
``|ey| <= width/2 - half_width_m - margin_m``. Weighting by the line's own length matters: a sum of
squared second differences at a fixed number of points, or a curvature linearised about the
centre line, prefers the inside of a constant-radius turn, where the true minimum-curvature line
is the outside (every closed line turns 2 pi, so its integral of curvature^2 is at least
(2 pi)^2 / length). scipy's L-BFGS-B solves the bound-constrained problem with the exact gradient.

TUM's ``trajectory-planning-helpers`` (the library made for this) is not used: 0.79 pins
``quadprog==0.1.7``, which has no wheel for Python 3.11 (it builds from source with a C compiler
and Cython), and its ``opt_min_curv`` linearises the curvature about the reference line, which
on a constant-radius annulus prefers the inside edge (above).

**Speed.** The line's curvature comes from the Frenet form of the offset curve (exact for a C2
``ey(s)`` on a C2 centre line; the curvature jumps of straight/arc chains enter as jumps). The
speed profile is the classic forward-backward pass on a friction circle of radius
``lateral_accel_mps2``: the cornering limit ``sqrt(a_lat / |kappa|)`` (and the top speed), a
forward pass accelerating with the drive limit and the friction left after cornering, and a
backward pass braking with ``brake_mps2`` and the same friction budget. The lap time integrates
ds / v with v linear between samples.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import asdict, dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from threadpoolctl import threadpool_limits

import fileio

from .geometry import SplineCenterline
from .track import Track

GRAVITY_MPS2 = 9.81
# Bumped whenever the line or profile computed for the same inputs changes, so old cache files are not reused.
ALGORITHM_VERSION = 5
DEFAULT_CACHE_DIR = Path(__file__).resolve().parents[1] / "runs" / "cache" / "racing_lines"
CACHE_ENV = "RD3G_RACING_LINE_CACHE"   # overrides DEFAULT_CACHE_DIR
_OPTIMISATION_STEP_M = 0.1    # centre-line spacing of the optimised offsets
_PROFILE_STEP_M = 0.01        # centre-line spacing of the stored line and speed profile
# Weights w of the squared length in the blended line objective (compute_racing_line): 0 is the
# minimum-curvature line, 1 the shortest line. Both terms are scaled by their centre-line values; the
# length varies far less with the offsets than the bending energy, hence the weights near 1.
LENGTH_WEIGHTS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.98, 1.0)


class RacingLineError(ValueError):
    """No racing line on this track for this car (open track, car wider than the track, ...)."""


@dataclass(frozen=True)
class RacingLineLimits:
    """What the line and its speed profile assume of the car. Units: m, m/s, m/s^2, 1/s."""

    lateral_accel_mps2: float       # friction circle: the largest total acceleration the tyres give
    accel_mps2: float               # drive acceleration from rest
    brake_mps2: float               # braking limit
    top_speed_mps: float
    half_width_m: float             # room the car takes either side of its path
    margin_m: float = 0.0           # extra clearance to the track edges
    accel_speed_loss_per_s: float = 0.0  # the drive acceleration falls by this per m/s of speed (motor back-EMF)

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            low_ok = value >= 0 if name in ("margin_m", "accel_speed_loss_per_s", "half_width_m") else value > 0
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and low_ok):
                raise RacingLineError(f"racing-line limits: {name} must be a finite {'non-negative' if name in ('margin_m', 'accel_speed_loss_per_s', 'half_width_m') else 'positive'} number, got {value!r}")

    def drive_accel(self, v):
        """Drive acceleration limit (m/s^2) at speed ``v`` (m/s), before the friction budget."""
        return np.maximum(self.accel_mps2 - self.accel_speed_loss_per_s * np.asarray(v, dtype=float), 0.0)


def limits_for_car(car, *, top_speed_mps: float, half_width_m: float, margin_m: float,
                   grip_fraction: float = 0.4, brake_mps2: float = 4.0) -> RacingLineLimits:
    """Limits of a car file (vehicles.params.CarParams) for its racing line.

    The friction circle is ``grip_fraction`` of the weaker axle's peak friction (0.4 x 1.1 g =
    4.3 m/s^2 for the BuzzRacer car, about the planners' cornering cap of 4.2 m/s^2: the peak is
    not something a planner tracks); the drive limit is the full-throttle motor force less rolling
    resistance over the mass, falling with the motor's back-EMF loss; ``brake_mps2`` is the
    planners' braking bound (PlannerConfig.max_brake_mps2). ``half_width_m`` and ``margin_m`` are the
    planner's lateral half-extent of the footprint and its track margin (planning.frenet).
    """
    grip = min(car.front_tire.d, car.rear_tire.d) * car.corrections.tire_grip_scale
    lon, mass = car.longitudinal, car.inertia.mass_kg
    return RacingLineLimits(
        lateral_accel_mps2=grip_fraction * grip * GRAVITY_MPS2,
        accel_mps2=(lon.motor_force_n - lon.rolling_resistance_n) / mass,
        accel_speed_loss_per_s=lon.motor_speed_loss_n_per_mps / mass,
        brake_mps2=brake_mps2,
        top_speed_mps=top_speed_mps,
        half_width_m=half_width_m,
        margin_m=margin_m,
    )


# --------------------------------------------------------------------------- the line
def bending_residuals(offsets: np.ndarray, points: np.ndarray, normals: np.ndarray, jacobian: bool = False):
    """Residuals ``r_i = phi_i / sqrt(m_i)`` of the closed polygon ``points + offsets * normals``,
    whose squares sum to its discrete bending energy (an integral of curvature^2 over arc length,
    1/m): phi_i is the turning angle at vertex i and m_i = (|e_{i-1}| + |e_i|) / 2. With
    ``jacobian``, also d r / d offsets as its three cyclic bands (n x 3): column 0 is d r_i / d offset_{i-1},
    1 d r_i / d offset_i, 2 d r_i / d offset_{i+1} (r_i depends on no other offset)."""
    p = points + offsets[:, None] * normals
    a = p - np.roll(p, 1, axis=0)        # edge into vertex i
    b = np.roll(p, -1, axis=0) - p       # edge out of vertex i
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    dot = np.sum(a * b, axis=1)
    la, lb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    phi = np.arctan2(cross, dot)
    m = 0.5 * (la + lb)
    r = phi / np.sqrt(m)
    if not jacobian:
        return r
    # phi = atan2(a x b, a . b) with (a x b)^2 + (a . b)^2 = |a|^2 |b|^2.
    denominator = ((la * lb) ** 2)[:, None]
    dphi_da = (dot[:, None] * np.stack([b[:, 1], -b[:, 0]], axis=1) - cross[:, None] * b) / denominator
    dphi_db = (dot[:, None] * np.stack([-a[:, 1], a[:, 0]], axis=1) - cross[:, None] * a) / denominator
    w_phi = (1.0 / np.sqrt(m))[:, None]
    w_m = (-0.25 * phi / m**1.5)[:, None]   # d r / d m times d m / d |e| = 1/2
    dr_da = w_phi * dphi_da + w_m * a / la[:, None]
    dr_db = w_phi * dphi_db + w_m * b / lb[:, None]
    # a_i = p_i - p_{i-1} and b_i = p_{i+1} - p_i; each point moves along its normal.
    bands = np.column_stack([-np.sum(dr_da * np.roll(normals, 1, axis=0), axis=1),
                             np.sum((dr_da - dr_db) * normals, axis=1),
                             np.sum(dr_db * np.roll(normals, -1, axis=0), axis=1)])
    return r, bands


def _bending_energy(offsets: np.ndarray, points: np.ndarray, normals: np.ndarray):
    """The bending energy and its gradient, 2 J' r summed band by band (J is cyclic tridiagonal: no n x n
    matrix per evaluation)."""
    r, bands = bending_residuals(offsets, points, normals, jacobian=True)
    grad = bands[:, 1] * r + np.roll(bands[:, 2] * r, 1) + np.roll(bands[:, 0] * r, -1)
    return float(np.sum(r * r)), 2.0 * grad


def squared_length(offsets: np.ndarray, points: np.ndarray, normals: np.ndarray):
    """Sum of the squared edges of the closed polygon ``points + offsets * normals`` (m^2; smallest
    for the shortest line at evenly spread vertices) and its gradient in the offsets."""
    p = points + offsets[:, None] * normals
    e = np.roll(p, -1, axis=0) - p          # edge out of vertex i
    grad = 2.0 * np.sum((np.roll(e, 1, axis=0) - e) * normals, axis=1)
    return float(np.sum(e * e)), grad


def _blended_objective(offsets, points, normals, weight: float, scale_energy: float, scale_length: float):
    """(1 - weight) bending energy / scale_energy + weight squared length / scale_length, and its gradient."""
    energy, g_energy = _bending_energy(offsets, points, normals)
    length, g_length = squared_length(offsets, points, normals)
    return ((1.0 - weight) * energy / scale_energy + weight * length / scale_length,
            (1.0 - weight) * g_energy / scale_energy + weight * g_length / scale_length)


def min_curvature_offsets(track: Track, bound_m: np.ndarray | float, n: int):
    """``(s, ey)``: the lateral offsets at ``n`` equally spaced centre-line arc lengths ``s`` of the
    closed line of least bending energy with ``|ey| <= bound_m`` (m; one value or one per sample).

    scipy's L-BFGS-B with the exact gradient (about 2000 iterations at 100 points: bending energy
    is a fourth-difference problem). The energy is not convex in the offsets (on buzzracer:full
    the centre-line start ends 4 % above the other), so it is solved twice, from the centre line
    and from the solution at a quarter of the points, and the lower minimum is kept.
    """
    bound = np.broadcast_to(np.asarray(bound_m, dtype=float), (n,))
    s = np.arange(n) * (track.length / n)
    coarse_n = max(16, n // 4)
    s_coarse = np.arange(coarse_n) * (track.length / coarse_n)
    coarse, _ = _minimise_bending(track, s_coarse, np.interp(s_coarse, s, bound), np.zeros(coarse_n))
    warm = np.clip(np.interp(s, np.append(s_coarse, track.length), np.append(coarse, coarse[0])), -bound, bound)
    best = min((_minimise_bending(track, s, bound, start) for start in (np.zeros(n), warm)), key=lambda r: r[1])
    return s, best[0]


def _minimise_bending(track: Track, s: np.ndarray, bound: np.ndarray, start: np.ndarray, length_weight: float = 0.0):
    """(offsets, objective) of L-BFGS-B on the bending energy from ``start``; with ``length_weight``
    w > 0, on the blend (1 - w) energy + w squared length, each scaled by its centre-line value."""
    heading = track.heading(s)
    points = track.position(s)
    normals = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    if length_weight > 0.0:
        zero = np.zeros(len(s))
        scales = (max(_bending_energy(zero, points, normals)[0], 1e-9), squared_length(zero, points, normals)[0])
        objective, args = _blended_objective, (points, normals, length_weight, *scales)
    else:
        objective, args = _bending_energy, (points, normals)
    result = minimize(objective, start, args=args, jac=True, method="L-BFGS-B",
                      bounds=np.column_stack([-bound, bound]),
                      options={"maxiter": 50_000, "maxfun": 100_000, "ftol": 1e-13, "gtol": 1e-9, "maxcor": 30})
    return result.x, float(result.fun)


# --------------------------------------------------------------------------- the speed
def speed_profile(step_m: np.ndarray, curvature: np.ndarray, limits: RacingLineLimits, closed: bool = True):
    """Fastest speeds (m/s) at samples along a path, forward-backward on a friction circle.

    ``curvature`` (1/m) at M samples; ``step_m`` the path length from sample j to j+1 (M values on
    a closed path, the last back to sample 0; M-1 on an open one, which starts and ends at the
    cornering limit). Each step uses the friction left after cornering at its start sample.
    """
    kappa = np.abs(np.asarray(curvature, dtype=float))
    step = np.asarray(step_m, dtype=float)
    m = len(kappa)
    a_lat = limits.lateral_accel_mps2
    with np.errstate(divide="ignore"):
        v_corner = np.minimum(np.sqrt(a_lat / kappa), limits.top_speed_mps)
    # A closed lap starts at its slowest corner (where the speed is the cornering limit) and runs twice round.
    start = int(np.argmin(v_corner)) if closed else 0
    laps = 2 if closed else 1
    n_steps = laps * m if closed else m - 1

    def run(direction: int, accel) -> np.ndarray:
        v = v_corner.copy()
        j = start if direction > 0 else (start if closed else m - 1)
        speed = v[j]
        for _ in range(n_steps):
            k = (j + direction) % m
            ds = step[j] if direction > 0 else step[k]
            lateral = speed * speed * kappa[j]
            budget = math.sqrt(max(a_lat * a_lat - lateral * lateral, 0.0))
            reach = math.sqrt(speed * speed + 2.0 * min(accel(speed), budget) * ds)
            speed = min(v[k], reach)
            v[k] = speed
            j = k
        return v

    forward = run(+1, lambda v: float(limits.drive_accel(v)))
    backward = run(-1, lambda v: limits.brake_mps2)
    return np.minimum(forward, backward)


def lap_time_s(step_m: np.ndarray, speed: np.ndarray) -> float:
    """Time (s) to drive a closed path at ``speed`` (m/s, per sample), linear in between."""
    v = np.asarray(speed, dtype=float)
    return float(np.sum(2.0 * np.asarray(step_m, dtype=float) / (v + np.roll(v, -1))))


# --------------------------------------------------------------------------- the result
@dataclass(frozen=True)
class RacingLine:
    """A racing line tabulated on the centre line's arc length.

    Arrays hold M samples at ``s = i * length / M`` (no repeat of s = 0): ``ey`` (m, left
    positive), ``speed`` (m/s), ``curvature`` (1/m, of the line) and ``step`` (m of line from
    sample i to i+1). Look-ups by centre-line ``s`` interpolate linearly and wrap.
    """

    track_name: str
    track_length_m: float
    limits: RacingLineLimits
    ey: np.ndarray
    speed_mps: np.ndarray
    curvature: np.ndarray
    step_m: np.ndarray

    @property
    def s(self) -> np.ndarray:
        """Centre-line arc length (m) of the samples."""
        return np.arange(len(self.ey)) * (self.track_length_m / len(self.ey))

    @property
    def length_m(self) -> float:
        """Length of the racing line (m)."""
        return float(np.sum(self.step_m))

    @property
    def lap_time_s(self) -> float:
        """Lap time (s) along the line at the speed profile."""
        return lap_time_s(self.step_m, self.speed_mps)

    @property
    def min_radius_m(self) -> float:
        """Tightest turn radius of the line (m)."""
        return float(1.0 / max(np.max(np.abs(self.curvature)), 1e-12))

    @cached_property
    def _closed_tables(self) -> dict[str, np.ndarray]:
        """The samples closed by a repeat at s = length (look-ups at every plan stage reuse them)."""
        tables = {name: np.append(values, values[0])
                  for name, values in (("ey", self.ey), ("speed", self.speed_mps), ("curvature", self.curvature))}
        tables["s"] = np.append(self.s, self.track_length_m)
        return tables

    def _lookup(self, name: str, s):
        tables = self._closed_tables
        return np.interp(np.mod(s, self.track_length_m), tables["s"], tables[name])

    def lateral_offset(self, s):
        """Lateral offset ey (m, left of the centre line) of the line at centre-line arc length ``s`` (m)."""
        return self._lookup("ey", s)

    def speed(self, s):
        """Speed (m/s) of the profile at centre-line arc length ``s`` (m)."""
        return self._lookup("speed", s)

    def line_curvature(self, s):
        """Curvature (1/m, left positive) of the line at centre-line arc length ``s`` (m)."""
        return self._lookup("curvature", s)

    def to_json(self) -> dict:
        return {"version": ALGORITHM_VERSION, "track_name": self.track_name, "track_length_m": self.track_length_m,
                "limits": asdict(self.limits), "ey": self.ey.tolist(), "speed_mps": self.speed_mps.tolist(),
                "curvature": self.curvature.tolist(), "step_m": self.step_m.tolist()}

    @classmethod
    def from_json(cls, data: dict) -> "RacingLine":
        arrays = {k: np.asarray(data[k], dtype=float) for k in ("ey", "speed_mps", "curvature", "step_m")}
        return cls(data["track_name"], float(data["track_length_m"]), RacingLineLimits(**data["limits"]), **arrays)


def compute_racing_line(track: Track, limits: RacingLineLimits) -> RacingLine:
    """The racing line of a closed track and its speed profile (no cache; see racing_line): of the
    minimum-curvature line and the blends of bending energy and length (LENGTH_WEIGHTS, each solved
    from the previous one's offsets), the one of the shortest lap time at ``limits``."""
    if not track.closed:
        raise RacingLineError(f"{track.name}: a racing line needs a closed track")
    # L-BFGS-B's BLAS calls round differently on 1 and 2 OpenBLAS threads, and its 1000-odd iterations
    # amplify that into lines that differ by micrometres: one cache key would hold whichever line the first
    # process computed (`python -m app` runs BLAS on one thread, a bare `import planning` on every core).
    with threadpool_limits(limits=1):
        return _compute_racing_line(track, limits)


def _compute_racing_line(track: Track, limits: RacingLineLimits) -> RacingLine:
    n = max(32, int(math.ceil(track.length / _OPTIMISATION_STEP_M)))
    s_opt = np.arange(n) * (track.length / n)
    bound = 0.5 * track.width(s_opt) - limits.half_width_m - limits.margin_m
    if np.min(bound) <= 0.0:
        worst = int(np.argmin(bound))
        raise RacingLineError(f"{track.name}: at s = {s_opt[worst]:.3f} m the track is {float(track.width(s_opt[worst])):.3f} m "
                              f"wide, the car needs {2 * (limits.half_width_m + limits.margin_m):.3f} m "
                              "(half-width and margin either side)")
    s_opt, ey_opt = min_curvature_offsets(track, bound, n)
    best = _line_through(track, limits, s_opt, ey_opt)
    for weight in LENGTH_WEIGHTS[1:]:
        ey_opt, _ = _minimise_bending(track, s_opt, bound, ey_opt, length_weight=weight)
        try:
            candidate = _line_through(track, limits, s_opt, ey_opt)
        except RacingLineError:
            continue  # this blend doubles back; the others stand
        if candidate.lap_time_s < best.lap_time_s:
            best = candidate
    return best


def _line_through(track: Track, limits: RacingLineLimits, s_opt: np.ndarray, ey_opt: np.ndarray) -> RacingLine:
    """The RacingLine through the offsets ``ey_opt`` at centre-line arc lengths ``s_opt``, with its speed profile."""
    n = len(s_opt)
    # The line itself: a periodic quintic spline through the optimised points in the world frame
    # (smooth where the line is, also across the curvature jumps of straight/arc centre lines).
    x, y = track.to_cartesian(s_opt, ey_opt)
    line = SplineCenterline(np.column_stack([x, y]), closed=True, widths=np.ones(n))
    m = max(n, int(math.ceil(line.length / _PROFILE_STEP_M)))
    sigma = np.arange(m) * (line.length / m)
    sample = line.evaluate(sigma)
    s_line, ey, _ = track.to_frenet(sample.x, sample.y)
    # Centre-line s of the line samples, unwrapped from the first (the line starts on the start line).
    s_unwrapped = s_opt[0] + np.unwrap(s_line - s_opt[0], period=track.length)
    if np.any(np.diff(s_unwrapped) <= 0.0):
        raise RacingLineError(f"{track.name}: the racing line doubles back against the centre line "
                              f"near s = {float(s_line[int(np.argmin(np.diff(s_unwrapped)))]):.3f} m")
    step = np.full(m, line.length / m)
    speed = speed_profile(step, sample.curvature, limits, closed=True)
    # Tabulated on the centre line's arc length, which is what the planners look up.
    s_grid = np.arange(m) * (track.length / m)
    dsigma_ds = (line.length / m) / np.diff(np.append(s_unwrapped, s_unwrapped[0] + track.length))

    def on_grid(values):
        return np.interp(s_grid, s_line, values, period=track.length)

    grid_step = on_grid(dsigma_ds) * (track.length / m)
    grid_step *= line.length / np.sum(grid_step)   # the table's steps add up to the line's length
    # The spline through the points bulges up to ~2 mm past the limit where the line touches it: clip.
    room = 0.5 * track.width(s_grid) - limits.half_width_m - limits.margin_m
    ey_grid = np.clip(on_grid(ey), -room, room)
    return RacingLine(track.name, track.length, limits, ey_grid, on_grid(speed), on_grid(sample.curvature), grid_step)


def cache_key(track: Track, limits: RacingLineLimits) -> str:
    """Hash of what the line depends on: the track definition, the limits and the algorithm version."""
    text = repr((ALGORITHM_VERSION, track.definition, sorted(asdict(limits).items())))
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def racing_line(track: Track, limits: RacingLineLimits, cache_dir: str | os.PathLike | None = None) -> RacingLine:
    """The racing line of ``track`` at ``limits``, computed once and cached as JSON in ``cache_dir``
    (default: $RD3G_RACING_LINE_CACHE or runs/cache/racing_lines/ of this checkout), one file per
    track definition and limits. A cache file that cannot be read is recomputed and rewritten."""
    directory = Path(cache_dir or os.environ.get(CACHE_ENV) or DEFAULT_CACHE_DIR)
    safe_name = "".join(c if c.isalnum() or c in "-_" else "_" for c in track.name)[:60]
    path = directory / f"{safe_name}-{cache_key(track, limits)}.json"
    if path.is_file():
        try:
            data = json.loads(path.read_text())
            if data.get("version") == ALGORITHM_VERSION:
                return RacingLine.from_json(data)
        except (OSError, ValueError, KeyError, TypeError, RacingLineError):
            pass  # a damaged cache entry is recomputed
    line = compute_racing_line(track, limits)
    fileio.atomic_write_text(path, json.dumps(line.to_json()))
    return line
