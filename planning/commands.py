"""From a planned [a (m/s^2), delta (wheel angle, rad)] to the car's [throttle, steering command].

* Throttle: the inverse of the car's longitudinal model (vehicles/dynamic_bicycle.drive_force),
  m a = Cm1 u - Cm2 v |u| - Cr0 tanh(v/v_s) - (Cd + extra drag) v |v|, solved for u at the
  current (delay-predicted) speed.
* Steering: the car's [corrections] map command -> wheel angle = gain * command + offset, so the
  command for a planned wheel angle is (delta - offset) / gain; the planner's steering bounds are
  the wheel angles reachable with |command| <= max_steering_rad.
* Delay: commands take effect corrections.*_delay_s later, so the state the plan starts from is
  the measured state predicted over the delay with the commands already in flight.
* Identified linkage and motor effects (docs/sysid.md): a left/right gain asymmetry is inverted per
  side; steering play (backlash) is compensated by overshooting the wanted linkage angle by half the
  play in the direction it has to move (the play model then puts the linkage exactly there); a motor
  force drift scales the motor force with the time since the mapper started (one control period
  per issued command). The `[other_terms]` of an unnamed effect are not applied here.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

import dataclasses

from vehicles.dynamic_bicycle import ModelCoefficients, drive_force
from vehicles.linkage import inverse_asymmetric, play
from vehicles.params import CarParams, motor_force_scale


class CommandMapper:
    """Per-car command conversion; keeps the issued controls for delay compensation."""

    def __init__(self, car: CarParams, control_period_s: float, max_brake_mps2: float = 4.0,
                 steering_margin: float = 0.95) -> None:
        if not (math.isfinite(control_period_s) and control_period_s > 0):
            raise ValueError(f"control_period_s: must be > 0, got {control_period_s!r}")
        self.car = car
        self.period = float(control_period_s)
        self.coeffs = ModelCoefficients.from_params(car)
        self._nominal_coeffs = self.coeffs
        self.max_brake = float(max_brake_mps2)
        corr = car.corrections
        # Both channels are predicted over the longer delay (the plan starts when steering and
        # throttle both act); with different delays the faster channel acts slightly early.
        self.delay_s = max(corr.steering_delay_s, corr.throttle_delay_s)
        reach = steering_margin * car.actuators.max_steering_rad * corr.steering_gain
        self.delta_min = corr.steering_offset_rad - reach * (1.0 - corr.steering_gain_asymmetry)
        self.delta_max = corr.steering_offset_rad + reach * (1.0 + corr.steering_gain_asymmetry)
        self._steps_issued = 0
        self._linkage = 0.0  # estimated linkage angle behind the play (servo angle units)
        self.n_in_flight = math.ceil(self.delay_s / self.period - 1e-9) if self.delay_s > 0 else 0
        self._issued: deque = deque(maxlen=max(self.n_in_flight, 1))

    # ------------------------------------------------------------- longitudinal model
    def acceleration(self, throttle, speed) -> np.ndarray:
        """Longitudinal acceleration (m/s^2) of the car's drive model at throttle u and speed v."""
        force, _, _ = drive_force(np.asarray(speed, dtype=float), np.asarray(throttle, dtype=float),
                                  self.coeffs, np, False)
        return force / self.coeffs.mass

    def acceleration_bounds(self, speed: float) -> tuple[float, float]:
        """(a_min, a_max) the planner may use at this speed: full throttle / full reverse of the
        drive model, braking further capped at max_brake_mps2."""
        act = self.car.actuators
        a_max = float(self.acceleration(act.throttle_max, speed))
        a_min = max(float(self.acceleration(act.throttle_min, speed)), -self.max_brake)
        if a_max <= a_min + 1e-3:  # beyond the car's top speed: only braking/coasting is possible
            a_max = a_min + 1e-3
        return a_min, a_max

    def throttle_for_acceleration(self, accel, speed):
        """Throttle giving longitudinal acceleration `accel` at `speed` in the drive model
        (vectorised). Closed form for the unsmoothed |u| on the matching side of zero, then Newton
        steps on the exact (smoothed) model; clipped to the throttle range."""
        a = np.asarray(accel, dtype=float)
        v = np.asarray(speed, dtype=float)
        k = self.coeffs
        resist = k.rolling_resistance * np.tanh(v / k.rolling_smoothing_speed) + k.drag * v * np.abs(v)
        need = k.mass * a + resist  # = Cm1 u - Cm2 v |u|
        u = np.where(need >= 0, need / np.maximum(k.motor_force - k.motor_speed_loss * v, 1e-6),
                     need / (k.motor_force + k.motor_speed_loss * v))
        act = self.car.actuators
        lo, hi = act.throttle_min, act.throttle_max
        u = np.clip(u, lo, hi)
        for _ in range(6):
            force, _, d_u = drive_force(v, u, k, np, True)
            u = np.clip(u - (force - k.mass * a) / np.where(np.abs(d_u) > 1e-9, d_u, 1e-9), lo, hi)
        return u if u.ndim else float(u)

    # ------------------------------------------------------------- steering
    def steering_command(self, delta):
        """Servo command (rad) for wheel angle delta, inverting the [corrections] gain/offset and the
        left/right asymmetry (stateless; the play is compensated in :meth:`commands`)."""
        corr = self.car.corrections
        cmd = (np.asarray(delta, dtype=float) - corr.steering_offset_rad) / corr.steering_gain
        if corr.steering_gain_asymmetry != 0.0:
            cmd = inverse_asymmetric(cmd, corr.steering_gain_asymmetry)
        m = self.car.actuators.max_steering_rad
        cmd = np.clip(cmd, -m, m)
        return cmd if cmd.ndim else float(cmd)

    def neutral_control(self, speed: float) -> tuple[float, float]:
        """Planning-model control [a, delta] of the neutral command (zero throttle and steering) at
        ``speed``: the drive model's coasting deceleration and the steering offset."""
        return float(self.acceleration(0.0, speed)), float(self.car.corrections.steering_offset_rad)

    def commands(self, accel: float, delta: float, speed: float) -> tuple[float, float]:
        """(throttle, steering command) for the planned control at the speed the plan starts from;
        records the planned control as in flight."""
        self._issued.append((float(accel), float(delta)))
        corr = self.car.corrections
        if corr.motor_force_drift_per_s != 0.0:
            scale = motor_force_scale(corr.motor_force_drift_per_s, self._steps_issued * self.period)
            self.coeffs = dataclasses.replace(self._nominal_coeffs,
                                              motor_force=self._nominal_coeffs.motor_force * scale)
        self._steps_issued += 1
        steering = float(self.steering_command(delta))
        backlash = corr.steering_backlash_rad
        if backlash > 0.0:
            # Push the linkage to the wanted angle from the side it has to move to (it then ends there).
            if steering > self._linkage:
                steering = steering + 0.5 * backlash
            elif steering < self._linkage:
                steering = steering - 0.5 * backlash
            m = self.car.actuators.max_steering_rad
            steering = min(max(steering, -m), m)
            self._linkage = float(play(self._linkage, steering, backlash))
        return float(self.throttle_for_acceleration(accel, speed)), steering

    # ------------------------------------------------------------- delay
    def predict(self, frenet_model, x) -> np.ndarray:
        """Planner state [s, ey, v, epsi] predicted over the actuation delay: the controls issued
        in the last delay_s seconds are still to act (the oldest only for the part of its period
        that lies beyond now). Returns x unchanged without delay or history."""
        x = np.asarray(x, dtype=float)
        if self.n_in_flight == 0 or not self._issued:
            return x
        issued = list(self._issued)[-self.n_in_flight:]
        first = self.delay_s - (self.n_in_flight - 1) * self.period  # oldest command's remaining time
        segments = [(first if (j == 0 and len(issued) == self.n_in_flight) else self.period, a, delta)
                    for j, (a, delta) in enumerate(issued)]
        return rollout_controls(frenet_model, x, segments)

    def reset(self) -> None:
        self._issued.clear()
        self._linkage = 0.0


def rollout_controls(frenet_model, x, segments) -> np.ndarray:
    """Planner state [s, ey, v, epsi] after piecewise-constant controls: ``segments`` is a sequence of
    (duration s, a m/s^2, delta rad), applied in order; durations <= 1 ns are skipped."""
    x = np.asarray(x, dtype=float)
    for dt, a, delta in segments:
        if dt <= 1e-9:
            continue
        x = np.asarray(frenet_model.rollout_model(round(dt, 9)).rollout(x, np.array([[a, delta]]))[-1])
    return x
