"""Track geometry as the planners see it: the Frenet kinematic bicycle on the track's curvature
table, track limits as bounds on ey, the collision distance, continuous (unwrapped) progress."""
from __future__ import annotations

import math
import numpy as np

from solver_cpp import KinematicBicycleFrenet
from vehicles.params import CarParams

from .config import PlannerConfig

S, EY, V, EPSI = range(4)


def frenet_state(track, state) -> np.ndarray:
    """Simulator/estimator state [x, y, heading, vx, vy, yaw_rate] -> planner state [s, ey, v, epsi]
    with s wrapped to [0, length) and v the speed of the CG (the kinematic model's v), negative when the
    car rolls backwards (vx < 0): a reversing car seen as moving forward would be braked further back."""
    x, y, heading, vx, vy = (float(c) for c in np.asarray(state, dtype=float)[:5])
    s, ey, epsi = track.to_frenet(np.array([x]), np.array([y]), np.array([heading]))
    return np.array([float(s[0]), float(ey[0]), math.copysign(math.hypot(vx, vy), vx), float(epsi[0])])


class ProgressUnwrapper:
    """Continuous progress along a closed track for several cars.

    The planners work with unwrapped s (it grows past the track length instead of jumping back
    to 0), so the lead term s_j - s_i and the collision constraint stay correct across the
    start/finish line. The curvature table is periodic, so the model accepts any s.
    """

    def __init__(self, track, s0) -> None:
        s0 = np.asarray(s0, dtype=float).reshape(-1)
        self.track = track
        # Place every car within half a lap of car 0, so a car just behind the line is behind.
        self.s = s0[0] + np.asarray(track.progress_difference(s0, s0[0]), dtype=float)
        self._last = np.mod(s0, track.length)

    def update(self, s_wrapped) -> np.ndarray:
        """Feed wrapped arc lengths (one per car); returns the unwrapped ones. Samples must be less
        than half a lap apart in time."""
        s_wrapped = np.mod(np.asarray(s_wrapped, dtype=float).reshape(-1), self.track.length)
        self.s = self.s + np.asarray(self.track.progress_difference(s_wrapped, self._last), dtype=float)
        self._last = s_wrapped
        return self.s.copy()


def lateral_half_extent(g, heading_allowance_rad: float) -> float:
    """Half the lateral room (m) the car's footprint (geometry ``g``) takes at up to the allowed heading error."""
    a = heading_allowance_rad
    return 0.5 * g.footprint_width_m * math.cos(a) + (0.5 * g.footprint_length_m + abs(g.footprint_offset_m)) * math.sin(a)


class FrenetTrackModel:
    """The planning model of one car on one track and the geometric limits derived from it.

    * model: KinematicBicycleFrenet(lf, lr) of the car on the track's curvature table (periodic).
    * lateral bound: |ey| <= width/2 - (half the footprint width, plus the corner swing at
      heading_allowance_rad) - track_margin_m, at the narrowest point of the planning window;
      ey_limits also keeps the inside of every turn in the window drivable: a path at offset ey in
      a turn of curvature kappa has radius 1/|kappa| - |ey| on the inside, so ey <= 1/kappa - r_min
      (kappa > 0, left turn; mirrored for right turns), r_min the car's tightest radius.
    * collision distance: the cars are discs of the footprint's circumscribed radius, so in
      Cartesian coordinates they touch at d_fp = 2 r + collision_margin_m (footprint_distance). The
      constraint is evaluated on (s, ey): a lateral gap is exact, but an arc-length gap ds at lateral
      offset ey is only (1 - kappa ey) ds long on the inside of a curve. The solver measures the
      separation as |(a ds, dey)| >= D with D = max(d_fp, lateral_clearance_m) (collision_distance)
      and the along-track scale a = (D / d_fp) (1 - |kappa|max ey_max) over the window
      (along_track_scale, the collision's pos_x_scale): along the track it keeps d_fp, never
      over-stating the Cartesian distance, and sideways D.
    """

    def __init__(self, track, car: CarParams, config: PlannerConfig) -> None:
        if not track.closed:
            raise ValueError(f"track: racing needs a closed track, {track.name!r} is open")
        self.track = track
        self.car = car
        self.config = config
        s_grid, kappa = track.curvature_table(config.curvature_table_ds_m)
        self.table_ds = float(s_grid[1] - s_grid[0])
        self.kappa = np.asarray(kappa[:-1], dtype=float)  # periodic: sample N is sample 0
        self.model = KinematicBicycleFrenet(lf=car.geometry.lf_m, lr=car.geometry.lr_m, kappa=self.kappa,
                                            ds=self.table_ds, closed=True)
        g = car.geometry
        self.lateral_half_extent = lateral_half_extent(g, config.heading_allowance_rad)
        self.footprint_radius = math.hypot(0.5 * g.footprint_length_m + abs(g.footprint_offset_m),
                                           0.5 * g.footprint_width_m)
        self._window_key: tuple[float, float] | None = None  # the last window's (min, max) progress
        self._window_limits = (math.nan, math.nan, math.nan)
        self._rollout_models: dict[float, object] = {}  # dt -> this model's own C++ model (rollout_model)

    def rollout_model(self, dt: float):
        """C++ model with time step dt (for predicting the state over the actuation delay), built at the
        first call with that dt and kept by this track model. Why not a functools.lru_cache on the method:
        that is one cache of the class, shared by every car's track model, which the planners of one control
        step (race.planning.RacePlanners) would fill and evict concurrently, and it kept every model alive."""
        model = self._rollout_models.get(dt)
        if model is None:
            model = self._rollout_models[dt] = self.model.build(dt)
        return model

    def window(self, s_values) -> np.ndarray:
        """Arc lengths covering the planning window from the given progress values (1 cm spacing)."""
        s_values = np.asarray(s_values, dtype=float)
        reach = self.config.top_speed_mps * self.config.horizon * self.config.plan_dt_s + 0.5
        return np.arange(float(s_values.min()) - 0.2, float(s_values.max()) + reach, 0.01)

    def _limits(self, s_values) -> tuple[float, float, float]:
        """(smallest track width m, largest and smallest curvature 1/m) over the window of the given
        progress values; a plan asks for the limits and the along-track scale with the same values, so the
        last window's are kept."""
        s_values = np.asarray(s_values, dtype=float)
        key = (float(s_values.min()), float(s_values.max()))
        if key != self._window_key:
            s = np.mod(self.window(s_values), self.track.length)
            kappa = np.asarray(self.track.curvature(s), dtype=float)
            self._window_limits = (float(np.min(self.track.width(s))), float(np.max(kappa)), float(np.min(kappa)))
            self._window_key = key
        return self._window_limits

    def ey_bound(self, s_values) -> float:
        """Largest |ey| the planner allows over the window ahead of the given progress values (m)."""
        w = self._limits(s_values)[0]
        bound = 0.5 * w - self.lateral_half_extent - self.config.track_margin_m
        if bound <= 0:
            raise ValueError(f"track: {self.track.name!r} is too narrow for car {self.car.name!r} "
                             f"(half-width {0.5 * w:.3f} m, car needs {self.lateral_half_extent + self.config.track_margin_m:.3f} m)")
        return bound

    def ey_limits(self, s_values, min_radius_left: float, min_radius_right: float) -> tuple[float, float]:
        """(lowest, highest) ey the planner allows over the window ahead of the given progress values
        (m): the track-limit bound (ey_bound), and on the inside of every turn in the window the offset
        whose path radius is the car's tightest (min_radius_left for left turns, kappa > 0: ey <= 1/kappa -
        min_radius_left; min_radius_right for right turns: ey >= -(1/|kappa| - min_radius_right))."""
        bound = self.ey_bound(s_values)
        _, k_max, k_min = self._limits(s_values)
        k_left, k_right = max(k_max, 0.0), max(-k_min, 0.0)
        high = min(bound, 1.0 / k_left - min_radius_left) if k_left > 0 else bound
        low = max(-bound, min_radius_right - 1.0 / k_right) if k_right > 0 else -bound
        if high <= low:
            raise ValueError(f"track: {self.track.name!r} has a turn too tight for car {self.car.name!r} "
                             f"(radius {1.0 / max(k_left, k_right):.3f} m within the reach from s = {float(np.min(s_values)):.2f} m; the car "
                             f"turns {min(min_radius_left, min_radius_right):.3f} m at the least, its track-limit bound "
                             f"is {bound:.3f} m)")
        return low, high

    def along_track_scale(self, s_values, ey_values=None) -> float:
        """The along-track scale a (see class doc) over the window of the given progress values: with
        ey_values (the cars' current lateral offsets) ey_max is the largest of them plus lateral_reach_m
        (capped at the track-limit bound), else the bound. The curvature factor is never below 0.2."""
        _, k_max, k_min = self._limits(s_values)
        kappa_max = max(k_max, -k_min)
        ey_max = self.ey_bound(s_values)
        if ey_values is not None:
            ey_max = min(ey_max, float(np.max(np.abs(ey_values))) + self.config.lateral_reach_m)
        return self.collision_distance() / self.footprint_distance() * max(1.0 - kappa_max * ey_max, 0.2)

    def footprint_distance(self) -> float:
        """Cartesian distance (m) at which two cars' footprints (discs of footprint_radius) come within
        collision_margin_m: 2 footprint_radius + collision_margin_m; along the track the constraint keeps it."""
        return 2.0 * self.footprint_radius + self.config.collision_margin_m

    def collision_distance(self) -> float:
        """The collision constraint's d_min (m, see class doc): the separation it keeps, sideways in metres;
        the footprint distance or lateral_clearance_m, whichever is larger."""
        return max(self.footprint_distance(), self.config.lateral_clearance_m)


def frenet_separation(d_s, d_ey, along_track_scale: float):
    """The collision constraint's separation |(a ds, dey)| (m) of Frenet gaps (ds, dey) (arrays or
    numbers), a the along-track scale (FrenetTrackModel.along_track_scale)."""
    return np.hypot(along_track_scale * np.asarray(d_s, dtype=float), np.asarray(d_ey, dtype=float))


def path_curvature(delta, lf: float, lr: float):
    """Curvature (1/m, left positive) of the kinematic bicycle's CG path at wheel angle ``delta`` (rad,
    |delta| < pi/2): sin(beta) / lr, beta = atan(lr tan(delta) / (lf + lr)) the slip angle (the model's
    heading rate over its speed)."""
    beta = np.arctan(lr * np.tan(np.asarray(delta, dtype=float)) / (lf + lr))
    return np.sin(beta) / lr


def min_turn_radius(lf: float, lr: float, delta: float) -> float:
    """Radius (m) of the kinematic bicycle's CG path at wheel angle ``delta`` (rad, nonzero): the
    inverse of path_curvature, lr / |sin(beta)| = sqrt(lr^2 + ((lf + lr) / tan(delta))^2)."""
    return 1.0 / abs(float(path_curvature(delta, lf, lr)))
