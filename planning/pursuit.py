"""Reference controller: pure pursuit on the track centre line plus a speed PI loop.

Used for sanity checks and to drive cars when generating model-identification data; it is
not the racing planner.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from vehicles.params import CarParams


class PurePursuitController:
    """Steer toward a point ``lookahead`` metres ahead on the (optionally offset) centre line.

    Geometry is taken at the rear axle, where pure pursuit's arc construction is exact for a
    kinematic bicycle: steering = atan(2 L sin(alpha) / d) with alpha the bearing of the target
    point and d its distance. The speed reference is the lower of ``target_speed_mps`` and the
    curvature limit sqrt(max_lateral_accel / |kappa|) of the track ahead, braking at
    ``brake_decel_mps2`` to reach it (see speed_reference).
    Throttle = steady-state feed-forward of the drive model + PI on the speed error.
    """

    def __init__(
        self,
        track: Any,
        params: CarParams,
        target_speed_mps: float = 1.5,
        max_lateral_accel_mps2: float = 4.0,
        lookahead_min_m: float = 0.15,
        lookahead_time_s: float = 0.2,
        preview_m: float = 0.6,
        brake_decel_mps2: float = 3.0,
        speed_kp: float = 0.8,
        speed_ki: float = 0.3,
        lateral_offset_m: float = 0.0,
    ) -> None:
        for name, value in (
            ("target_speed_mps", target_speed_mps),
            ("max_lateral_accel_mps2", max_lateral_accel_mps2),
            ("lookahead_min_m", lookahead_min_m),
            ("brake_decel_mps2", brake_decel_mps2),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be > 0, got {value!r}")
        for name, value in (("lookahead_time_s", lookahead_time_s), ("preview_m", preview_m),
                            ("speed_kp", speed_kp), ("speed_ki", speed_ki)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: must be >= 0, got {value!r}")
        self.track = track
        self.params = params
        self.target_speed_mps = target_speed_mps
        self.max_lateral_accel_mps2 = max_lateral_accel_mps2
        self.lookahead_min_m = lookahead_min_m
        self.lookahead_time_s = lookahead_time_s
        self.preview_m = preview_m
        self.brake_decel_mps2 = brake_decel_mps2
        self.speed_kp = speed_kp
        self.speed_ki = speed_ki
        self.lateral_offset_m = lateral_offset_m
        self._integral = 0.0

    def reset(self) -> None:
        self._integral = 0.0

    def speed_reference(self, s: float) -> float:
        """Fastest speed from which every point of the preview can be reached at its cornering
        speed sqrt(a_lat / |kappa|) while braking at ``brake_decel_mps2``."""
        v = self.target_speed_mps
        horizon = max(self.preview_m, v * v / (2.0 * self.brake_decel_mps2) + self.lookahead_min_m)
        dist = np.linspace(0.0, horizon, 25)
        kappa = np.abs(np.asarray(self.track.curvature(np.mod(s + dist, self.track.length)), dtype=float))
        corner_v2 = self.max_lateral_accel_mps2 / np.maximum(kappa, 1e-9)
        reachable = np.sqrt(corner_v2 + 2.0 * self.brake_decel_mps2 * dist)
        return float(min(v, reachable.min()))

    def feedforward_throttle(self, speed: float) -> float:
        """Throttle that holds ``speed`` on a straight in the nominal drive model."""
        lon = self.params.longitudinal
        drag = lon.drag_n_per_mps2 + self.params.corrections.extra_drag_n_per_mps2
        resist = lon.rolling_resistance_n + drag * speed * speed
        available = lon.motor_force_n - lon.motor_speed_loss_n_per_mps * speed
        return resist / available if available > 0 else 1.0

    def command(self, state: Sequence[float], dt: float) -> tuple[float, float]:
        """(throttle, steering command in rad) for state [x, y, heading, vx, ...] over dt seconds."""
        x, y, heading, vx = (float(v) for v in state[:4])
        geo = self.params.geometry
        act = self.params.actuators
        wheelbase = geo.wheelbase_m
        rear_x = x - geo.lr_m * math.cos(heading)
        rear_y = y - geo.lr_m * math.sin(heading)
        s, _, _ = self.track.to_frenet(np.array([rear_x]), np.array([rear_y]), np.array([heading]))
        s = float(np.asarray(s).reshape(-1)[0])

        lookahead = self.lookahead_min_m + self.lookahead_time_s * max(vx, 0.0)
        s_target = np.array([(s + lookahead) % self.track.length])
        target = np.asarray(self.track.position(s_target), dtype=float).reshape(2)
        if self.lateral_offset_m:
            h = float(np.asarray(self.track.heading(s_target)).reshape(-1)[0])
            target = target + self.lateral_offset_m * np.array([-math.sin(h), math.cos(h)])
        dx, dy = target[0] - rear_x, target[1] - rear_y
        alpha = math.atan2(dy, dx) - heading
        dist = max(math.hypot(dx, dy), 1e-6)
        steering = math.atan2(2.0 * wheelbase * math.sin(alpha), dist)
        # Undo the identified steering gain/offset so the wheels get the intended angle.
        corr = self.params.corrections
        steering = (steering - corr.steering_offset_rad) / corr.steering_gain
        steering = min(max(steering, -act.max_steering_rad), act.max_steering_rad)

        v_ref = self.speed_reference(s)
        error = v_ref - vx
        throttle_unsat = self.feedforward_throttle(v_ref) + self.speed_kp * error + self.speed_ki * self._integral
        throttle = min(max(throttle_unsat, act.throttle_min), act.throttle_max)
        # Anti-windup: integrate only while the output is not saturated in the error's direction.
        if throttle == throttle_unsat or (throttle_unsat > throttle) != (error > 0):
            self._integral += error * dt
        return throttle, steering
