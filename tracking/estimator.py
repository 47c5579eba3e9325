"""Per-car extended Kalman filter on the CTRV model with sideslip (tracking.motion) with pose
measurements.

State ``[x, y, heading, speed, yaw_rate, sideslip]``: the car moves along heading + sideslip (a
cornering car's velocity is not along its heading; at 1/28 scale about -2 degrees in the oval's
turns, which a model moving along the heading turned into a 5 mm lateral bias 40 ms ahead).
Measurement ``[x, y, heading]`` from a car marker; the sideslip is observed through the positions.
A commanded car's known acceleration (``CarEKF.accel_input``) drives the speed in the prediction.
Process noise: white longitudinal acceleration (``accel_noise`` = square root of its spectral
density, m/s^1.5), white yaw acceleration (``yaw_accel_noise``) and a random walk of the sideslip
(``sideslip_noise``, rad/s^0.5), held constant over each step.
Heading innovations are wrapped to [-pi, pi). Measurements whose squared Mahalanobis distance
exceeds ``gate_chi2`` (chi-square, 3 dof; default 99.9 %) are rejected and counted. A run of
``reacquire_after`` gated measurements that agree with one another (the car moved in a way the
model did not predict: a swerve, a knock from the other car) re-initialises the filter from them,
with speed and yaw rate from their differences. A filter with no accepted measurement for
``lost_after_s`` is lost; the next measurement restarts it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tracking.motion import slip_jacobian, slip_transition
from tracks.geometry import wrap_angle


@dataclass(frozen=True)
class EstimatorConfig:
    position_std_m: float = 0.003  # measurement noise of x and y
    heading_std_rad: float = math.radians(1.0)
    accel_noise: float = 2.0  # sqrt of the white-acceleration spectral density, m/s^1.5
    # Same for yaw acceleration, rad/s^1.5. A 1/28-scale car reverses a 4 rad/s yaw rate in ~0.1 s
    # when it swerves; at 5 the gate rejected such swerves (343 gated measurements in 20 HIL races, 100 at 10).
    yaw_accel_noise: float = 10.0
    initial_speed_std: float = 2.0
    initial_yaw_rate_std: float = 3.0
    # Random walk of the sideslip angle, rad/s^0.5; it builds up over a turn entry (~0.3 s). Replaying
    # 20 HIL races' detections, 0.1-1 all remove the lateral bias; 0.3 predicts best 40 ms ahead.
    sideslip_noise: float = 0.3
    initial_sideslip_std: float = 0.05  # rad
    gate_chi2: float = 16.27  # chi2(3 dof).ppf(0.999)
    # Also the race loop's safety rule: a lost car holds every car neutral (docs/race-stack.md).
    lost_after_s: float = 0.25
    # Gated measurements in a row that re-initialise the filter when they agree with one another:
    # consecutive ones imply at most ``max_speed_mps`` and ``max_yaw_rate_rps``. A lone outlier
    # (a misread marker) does not agree with the next measurement and stays rejected.
    reacquire_after: int = 3
    max_speed_mps: float = 6.0  # above the 1/28-scale car's ~3.5 m/s top speed
    max_yaw_rate_rps: float = 15.0  # v tan(27 deg) / wheelbase at 2.6 m/s; more only in a spin

    def __post_init__(self):
        for name in ("position_std_m", "heading_std_rad", "accel_noise", "yaw_accel_noise", "sideslip_noise",
                     "initial_speed_std", "initial_yaw_rate_std", "initial_sideslip_std", "gate_chi2", "lost_after_s",
                     "max_speed_mps", "max_yaw_rate_rps"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"EstimatorConfig.{name}: must be a positive finite number, got {value!r}")
        if not (isinstance(self.reacquire_after, int) and self.reacquire_after >= 2):
            raise ValueError(f"EstimatorConfig.reacquire_after: must be an integer >= 2, got {self.reacquire_after!r}")


@dataclass
class CarState:
    t_s: float
    x: float
    y: float
    heading: float
    speed: float
    yaw_rate: float
    sideslip: float  # rad: direction of travel minus heading
    covariance: np.ndarray = field(repr=False)

    @property
    def vector(self) -> np.ndarray:
        return np.array([self.x, self.y, self.heading, self.speed, self.yaw_rate, self.sideslip])


@dataclass(frozen=True)
class UpdateResult:
    accepted: bool
    reason: str  # "initialized", "reacquired", "accepted", "gated", "nan", "out_of_order"
    mahalanobis_sq: float = float("nan")


_N = 6  # state size
_H = np.hstack([np.eye(3), np.zeros((3, _N - 3))])


class CarEKF:
    def __init__(self, config: EstimatorConfig = EstimatorConfig()):
        self.config = config
        self._r = np.diag([config.position_std_m ** 2] * 2 + [config.heading_std_rad ** 2])
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.t_s: float | None = None
        self.t_last_accepted_s: float | None = None
        self.counts = {"initialized": 0, "reacquired": 0, "accepted": 0, "gated": 0, "nan": 0, "out_of_order": 0}
        self._gated: list[tuple[float, np.ndarray]] = []  # the current run of gated measurements
        # Known longitudinal acceleration (a commanded car: the real-time loop's logged controls), a
        # callable (t0, t1) -> [(duration s, a m/s^2), ...] acting from t0 on. Without it the speed is
        # a random walk, which lags a launching car (5 m/s^2) by ~0.1 m/s and its position by ~1 cm.
        self.accel_input = None

    @property
    def initialized(self) -> bool:
        return self.x is not None

    def process_noise(self, state: np.ndarray, dt: float) -> np.ndarray:
        """Q for white acceleration / yaw acceleration / sideslip rate over ``dt`` (noise input
        matrix G q G^T); the acceleration acts along the direction of travel."""
        course = state[2] + state[5]
        g = np.array([
            [0.5 * dt * dt * math.cos(course), 0.0, 0.0],
            [0.5 * dt * dt * math.sin(course), 0.0, 0.0],
            [0.0, 0.5 * dt * dt, 0.0],
            [dt, 0.0, 0.0],
            [0.0, dt, 0.0],
            [0.0, 0.0, dt],
        ])
        c = self.config
        q = np.diag([c.accel_noise ** 2 / dt, c.yaw_accel_noise ** 2 / dt, c.sideslip_noise ** 2 / dt] if dt > 0
                    else [0.0, 0.0, 0.0])
        # Spectral density -> discrete: variance of the mean acceleration over dt is S/dt.
        return g @ q @ g.T

    def _predicted(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        dt = t_s - self.t_s
        if dt <= 0:
            return self.x.copy(), self.P.copy()
        f = slip_jacobian(self.x, dt)
        x = slip_transition(self.x, dt)
        if self.accel_input is not None:
            # The known acceleration adds speed and, along the mean course, the distance beyond v dt.
            gain = dist = 0.0
            for d, a in self.accel_input(self.t_s, t_s):
                dist += gain * d + 0.5 * a * d * d
                gain += a * d
            course = self.x[2] + self.x[5] + 0.5 * self.x[4] * dt
            x[0] += dist * math.cos(course)
            x[1] += dist * math.sin(course)
            x[3] += gain
        p = f @ self.P @ f.T + self.process_noise(self.x, dt)
        return x, 0.5 * (p + p.T)

    def predict_to(self, t_s: float) -> CarState:
        """State predicted to ``t_s`` (e.g. when a command will take effect); the filter is unchanged."""
        if not self.initialized:
            raise RuntimeError("predict_to: filter has no measurement yet")
        x, p = self._predicted(max(t_s, self.t_s))
        return CarState(max(t_s, self.t_s), *map(float, x), covariance=p)

    def is_lost(self, t_s: float) -> bool:
        return self.t_last_accepted_s is None or t_s - self.t_last_accepted_s > self.config.lost_after_s

    def _initialize(self, t_s, z):
        c = self.config
        self.x = np.array([z[0], z[1], float(wrap_angle(z[2])), 0.0, 0.0, 0.0])
        self.P = np.diag([c.position_std_m ** 2, c.position_std_m ** 2, c.heading_std_rad ** 2,
                          c.initial_speed_std ** 2, c.initial_yaw_rate_std ** 2, c.initial_sideslip_std ** 2])
        self.t_s = self.t_last_accepted_s = t_s
        self._gated = []
        self.counts["initialized"] += 1
        return UpdateResult(True, "initialized")

    def _reacquire(self, d2: float) -> UpdateResult | None:
        """Re-initialise from the run of gated measurements if they agree with one another: the
        newest pose; speed, yaw rate and sideslip (direction of travel minus the mean heading) from
        the run's first and last poses."""
        c = self.config
        run = self._gated
        for (t0, z0), (t1, z1) in zip(run[:-1], run[1:]):
            dt = t1 - t0
            if dt <= 0 or (np.hypot(*(z1[:2] - z0[:2])) > c.max_speed_mps * dt
                           or abs(wrap_angle(z1[2] - z0[2])) > c.max_yaw_rate_rps * dt):
                del run[:-1]  # not one car's motion: keep only the newest as a possible new start
                return None
        (t0, z0), (t1, z1) = run[0], run[-1]
        dt = t1 - t0
        dheading = float(wrap_angle(z1[2] - z0[2]))
        mean_heading = z0[2] + 0.5 * dheading
        step = z1[:2] - z0[:2]
        speed = float(np.hypot(*step)) / dt
        sideslip = float(wrap_angle(math.atan2(step[1], step[0]) - mean_heading))
        if abs(sideslip) > math.pi / 2:  # moving backwards: negative speed along the heading
            speed, sideslip = -speed, float(wrap_angle(sideslip + math.pi))
        # Differences of two poses: their variance is twice the measurement's over dt^2.
        self.x = np.array([z1[0], z1[1], float(wrap_angle(z1[2])), speed, dheading / dt, sideslip])
        self.P = np.diag([c.position_std_m ** 2, c.position_std_m ** 2, c.heading_std_rad ** 2,
                          2 * (c.position_std_m / dt) ** 2 + (c.accel_noise ** 2) * dt,
                          2 * (c.heading_std_rad / dt) ** 2 + (c.yaw_accel_noise ** 2) * dt,
                          2 * (c.position_std_m / (dt * max(abs(speed), 0.1))) ** 2 + c.initial_sideslip_std ** 2])
        self.t_s = self.t_last_accepted_s = t1
        self._gated = []
        self.counts["reacquired"] += 1
        return UpdateResult(True, "reacquired", d2)

    def update(self, t_s: float, x: float, y: float, heading: float) -> UpdateResult:
        """Fuse a pose measured at ``t_s``; predicts through any missed frames first."""
        z = np.array([x, y, heading], float)
        if not (np.all(np.isfinite(z)) and math.isfinite(t_s)):
            self.counts["nan"] += 1
            return UpdateResult(False, "nan")
        if not self.initialized or self.is_lost(t_s):
            return self._initialize(t_s, z)
        if t_s < self.t_s:
            self.counts["out_of_order"] += 1
            return UpdateResult(False, "out_of_order")
        x_pred, p_pred = self._predicted(t_s)
        innovation = z - _H @ x_pred
        innovation[2] = wrap_angle(innovation[2])
        s = _H @ p_pred @ _H.T + self._r
        d2 = float(innovation @ np.linalg.solve(s, innovation))
        # The prediction is kept even when the measurement is rejected (time moves on).
        self.x, self.P, self.t_s = x_pred, p_pred, t_s
        if d2 > self.config.gate_chi2:
            self._gated.append((t_s, z))
            if len(self._gated) >= self.config.reacquire_after:
                result = self._reacquire(d2)
                if result is not None:
                    return result
            self.counts["gated"] += 1
            return UpdateResult(False, "gated", d2)
        self._gated = []
        gain = np.linalg.solve(s, _H @ p_pred).T  # P H^T S^-1 (S symmetric)
        self.x = x_pred + gain @ innovation
        self.x[2] = wrap_angle(self.x[2])
        i_kh = np.eye(_N) - gain @ _H
        self.P = i_kh @ p_pred @ i_kh.T + gain @ self._r @ gain.T  # Joseph form keeps P symmetric PD
        self.t_last_accepted_s = t_s
        self.counts["accepted"] += 1
        return UpdateResult(True, "accepted", d2)


class MultiCarEstimator:
    """One :class:`CarEKF` per marker id, created on the id's first measurement."""

    def __init__(self, config: EstimatorConfig = EstimatorConfig()):
        self.config = config
        self.filters: dict[int, CarEKF] = {}

    def update(self, t_s: float, measurements) -> dict[int, UpdateResult]:
        """``measurements``: iterable of objects with marker_id, x, y, heading (e.g. CarMeasurement)
        or of (marker_id, x, y, heading) tuples, all captured at ``t_s``."""
        results = {}
        for m in measurements:
            marker_id, x, y, heading = (m.marker_id, m.x, m.y, m.heading) if hasattr(m, "marker_id") else m
            ekf = self.filters.setdefault(int(marker_id), CarEKF(self.config))
            results[int(marker_id)] = ekf.update(t_s, x, y, heading)
        return results

    def forget(self, marker_id: int) -> None:
        """Drop the filter of ``marker_id`` (e.g. after a non-finite state); its next measurement starts a new one."""
        self.filters.pop(int(marker_id), None)

    def states_at(self, t_s: float, include_lost: bool = False) -> dict[int, CarState]:
        """Every tracked car predicted to ``t_s`` (lost cars left out unless ``include_lost``)."""
        return {i: f.predict_to(t_s) for i, f in self.filters.items()
                if f.initialized and (include_lost or not f.is_lost(t_s))}

    def lost_ids(self, t_s: float) -> list[int]:
        return sorted(i for i, f in self.filters.items() if f.is_lost(t_s))
