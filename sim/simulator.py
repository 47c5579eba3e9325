"""Multi-car race simulator: dynamic bicycle physics sub-stepped with RK4 under a slower
control loop, actuator delay/limits/rate limits, footprint collisions, track limits, laps.

Deterministic: the same seed, initial states and command sequence give the same trajectories,
events and measurements. Details and conventions: docs/simulator.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from sim.collision import rectangles_overlap
from sim.effects import SimEffects
from sim.race import OFF_TRACK_ALLOWANCE_CAR_LENGTHS, LapBookkeeper, RaceStatus, SimEvent
from tracks.geometry import wrap_angle
from vehicles.dynamic_bicycle import STATE_DIM, ModelCoefficients, derivative, derivative_one
from vehicles.extra_terms import car_extra_terms, extra_rates
from vehicles.linkage import asymmetric, play
from vehicles.params import CarParams, motor_force_scale


@dataclass(frozen=True)
class PoseMeasurement:
    """What an overhead camera reports for one car: pose of the CG and the capture time."""

    car: int
    x: float
    y: float
    heading: float  # wrapped to (-pi, pi]
    t: float


class Simulator:
    """Simulate several cars on one track.

    track: object with ``length``, ``to_frenet(x, y, heading=None) -> (s, ey, epsi)`` (epsi None
    without a heading) and ``limit_excess_frenet(s, ey)`` (m outside the drivable area, numpy-vectorised),
    as in tracks/.
    cars: one CarParams per car (corrections included). effects: one SimEffects for all cars
    or one per car. physics_dt: integration step; every control interval passed to step()
    must be a whole number of physics steps. check_dt: period of the lap, track-limit and
    collision checks (a whole number of physics steps). Below ``batch_threshold`` cars the
    physics runs per car in float math, above it on numpy batches (same equations).
    off_track_allowance_car_lengths: the gain an excursion may make before it is taken off the car's
    counted progress (sim.race.LapBookkeeper), in each car's footprint lengths.
    """

    def __init__(
        self,
        track: Any,
        cars: Sequence[CarParams],
        effects: SimEffects | Sequence[SimEffects] | None = None,
        seed: int = 0,
        physics_dt: float = 0.001,
        laps_to_win: int = 1,
        check_dt: float = 0.005,
        batch_threshold: int = 8,
        off_track_allowance_car_lengths: float = OFF_TRACK_ALLOWANCE_CAR_LENGTHS,
    ) -> None:
        cars = list(cars)
        if not cars or not all(isinstance(c, CarParams) for c in cars):
            raise ValueError("cars: must be a non-empty sequence of CarParams")
        n = len(cars)
        if effects is None:
            effects = SimEffects()
        if isinstance(effects, SimEffects):
            effects = [effects] * n
        effects = list(effects)
        if len(effects) != n or not all(isinstance(e, SimEffects) for e in effects):
            raise ValueError(f"effects: need one SimEffects or a list of {n}, got {len(effects)} items")
        if not (isinstance(physics_dt, (int, float)) and physics_dt > 0 and math.isfinite(physics_dt)):
            raise ValueError(f"physics_dt: must be a positive number, got {physics_dt!r}")
        if not isinstance(laps_to_win, int) or laps_to_win < 1:
            raise ValueError(f"laps_to_win: must be an integer >= 1, got {laps_to_win!r}")
        self.track = track
        self.cars = cars
        self.effects = effects
        self.n_cars = n
        self.physics_dt = float(physics_dt)
        self.laps_to_win = laps_to_win
        self.seed = seed
        self._check_every = self._whole_steps(check_dt, "check_dt")
        allowance = off_track_allowance_car_lengths
        if isinstance(allowance, bool) or not (isinstance(allowance, (int, float)) and math.isfinite(allowance)
                                               and allowance >= 0):
            raise ValueError(f"off_track_allowance_car_lengths: must be a number >= 0, got {allowance!r}")
        self._off_track_allowance_m = np.array([allowance * c.geometry.footprint_length_m for c in cars])
        self._batch = n > batch_threshold

        hidden = dict(
            steering_gain_scale=[e.steering_gain for e in effects],
            steering_offset_add=[e.steering_offset_rad for e in effects],
            extra_drag_add=[e.extra_drag_n_per_mps2 for e in effects],
            grip_scale=[e.grip_scale for e in effects],
        )
        self._coeffs_batch = ModelCoefficients.from_params(cars, **hidden)
        self._coeffs = [
            ModelCoefficients.from_params(
                p,
                steering_gain_scale=e.steering_gain,
                steering_offset_add=e.steering_offset_rad,
                extra_drag_add=e.extra_drag_n_per_mps2,
                grip_scale=e.grip_scale,
            )
            for p, e in zip(cars, effects)
        ]
        # Total dead time = identified delay of the car + hidden delay, rounded to physics steps.
        self._steer_delay_steps = [
            round((p.corrections.steering_delay_s + e.steering_delay_s) / self.physics_dt) for p, e in zip(cars, effects)
        ]
        self._throttle_delay_steps = [
            round((p.corrections.throttle_delay_s + e.throttle_delay_s) / self.physics_dt) for p, e in zip(cars, effects)
        ]
        # Steering linkage beyond gain/offset and motor drift: car's corrections + hidden effects.
        self._backlash = [p.corrections.steering_backlash_rad + e.steering_backlash_rad for p, e in zip(cars, effects)]
        self._asymmetry = [(p.corrections.steering_gain_asymmetry, e.steering_gain_asymmetry)
                           for p, e in zip(cars, effects)]
        self._drift = [(p.corrections.motor_force_drift_per_s + e.motor_force_drift_per_s, e.drift_start_s)
                       for p, e in zip(cars, effects)]
        self._drifting = any(rate != 0.0 for rate, _ in self._drift)
        self._base_coeffs, self._base_coeffs_batch = list(self._coeffs), self._coeffs_batch
        self._extra = [car_extra_terms(p) for p in cars]
        self._has_extra = any(self._extra)
        self._half_extents = np.array(
            [[p.geometry.footprint_length_m / 2, p.geometry.footprint_width_m / 2] for p in cars]
        )
        self._circumradius = np.hypot(self._half_extents[:, 0], self._half_extents[:, 1])
        self._offsets = np.array([p.geometry.footprint_offset_m for p in cars])
        # Corner order front-left, front-right, rear-right, rear-left (as footprint_corners).
        self._corner_signs = np.array([[1.0, 1.0, -1.0, -1.0], [1.0, -1.0, -1.0, 1.0]])
        self._pairs = np.triu_indices(n, k=1)
        self._ready = False

    def _whole_steps(self, dt: float, name: str) -> int:
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"{name}: must be a positive number, got {dt!r}")
        steps = round(dt / self.physics_dt)
        if steps < 1 or abs(steps * self.physics_dt - dt) > 1e-9 * max(1.0, dt):
            raise ValueError(f"{name}: {dt} s is not a whole multiple of physics_dt = {self.physics_dt} s")
        return steps

    # ------------------------------------------------------------------ setup
    def reset(self, initial_states: Any, initial_inputs: Any | None = None) -> None:
        """Place the cars. initial_states (n, 6) = [x, y, heading, vx, vy, yaw_rate] per car;
        initial_inputs (n, 2) = applied [throttle, steering] (default zero)."""
        states = np.asarray(initial_states, dtype=float)
        if states.shape != (self.n_cars, STATE_DIM):
            raise ValueError(f"initial_states: expected shape ({self.n_cars}, {STATE_DIM}), got {states.shape}")
        if not np.all(np.isfinite(states)):
            raise ValueError(f"initial_states: non-finite value in row {int(np.argwhere(~np.isfinite(states))[0, 0])}")
        inputs = np.zeros((self.n_cars, 2)) if initial_inputs is None else np.asarray(initial_inputs, dtype=float)
        if inputs.shape != (self.n_cars, 2) or not np.all(np.isfinite(inputs)):
            raise ValueError(f"initial_inputs: expected finite shape ({self.n_cars}, 2), got {inputs.shape}")
        self._x = states.tolist()
        self._target = [self._limit(i, row) for i, row in enumerate(inputs.tolist())]
        self._applied = [list(t) for t in self._target]
        self._linkage = [a[1] for a in self._applied]  # linkage angle after the play, per car
        self._effective = [self._linkage_output(i) for i in range(self.n_cars)]
        self._steer_fifo: list[deque] = [deque() for _ in range(self.n_cars)]
        self._throttle_fifo: list[deque] = [deque() for _ in range(self.n_cars)]
        self._steps = 0
        self._control_time = 0.0
        self._events: list[SimEvent] = []
        self._rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(self.seed).spawn(self.n_cars)]
        s0 = self._arc_lengths()
        self._laps = LapBookkeeper(float(self.track.length), self.laps_to_win, s0, start_time=0.0,
                                   allowance_m=self._off_track_allowance_m)
        self._colliding: set[tuple[int, int]] = set()
        self._collision_count = 0
        self._min_distance = math.inf
        self._ready = True
        self._apply_drift()
        self._check_contacts()

    # ------------------------------------------------------------------ stepping
    @property
    def time(self) -> float:
        return self._steps * self.physics_dt

    def step(self, commands: Any, dt_control: float) -> list[SimEvent]:
        """Issue one control command per car (throttle -1..1, steering rad) and advance the
        simulation by dt_control seconds. Returns the events that happened meanwhile."""
        if not self._ready:
            raise RuntimeError("Simulator.step called before reset()")
        cmd = np.asarray(commands, dtype=float)
        if cmd.shape != (self.n_cars, 2):
            raise ValueError(f"commands: expected shape ({self.n_cars}, 2), got {cmd.shape}")
        if not np.all(np.isfinite(cmd)):
            raise ValueError(f"commands: non-finite command for car {int(np.argwhere(~np.isfinite(cmd))[0, 0])}")
        if not (isinstance(dt_control, (int, float)) and math.isfinite(dt_control) and dt_control > 0):
            raise ValueError(f"dt_control: must be a positive number, got {dt_control!r}")
        # Physics runs in whole steps; the control clock is kept exactly, so e.g. 30 Hz control
        # on a 1 ms physics step alternates 33 and 34 sub-steps without drifting.
        self._control_time += float(dt_control)
        n_sub = max(0, round(self._control_time / self.physics_dt) - self._steps)
        for i, (throttle, steering) in enumerate(cmd.tolist()):
            self._throttle_fifo[i].append((self._steps + self._throttle_delay_steps[i], throttle))
            self._steer_fifo[i].append((self._steps + self._steer_delay_steps[i], steering))
        first_event = len(self._events)
        self._apply_drift()
        for _ in range(n_sub):
            self._update_actuators()
            self._integrate()
            self._steps += 1
            if self._steps % self._check_every == 0:
                self._check_contacts()
        return self._events[first_event:]

    def _limit(self, i: int, u: Sequence[float]) -> list[float]:
        a = self.cars[i].actuators
        return [
            min(max(u[0], a.throttle_min), a.throttle_max),
            min(max(u[1], -a.max_steering_rad), a.max_steering_rad),
        ]

    def _update_actuators(self) -> None:
        dt = self.physics_dt
        for i in range(self.n_cars):
            # Release delayed commands whose time has come (FIFO in sim time).
            tf, sf = self._throttle_fifo[i], self._steer_fifo[i]
            while tf and tf[0][0] <= self._steps:
                self._target[i][0] = tf.popleft()[1]
            while sf and sf[0][0] <= self._steps:
                self._target[i][1] = sf.popleft()[1]
            target = self._limit(i, self._target[i])
            a = self.cars[i].actuators
            applied = self._applied[i]
            max_du = a.throttle_rate_limit_per_s * dt
            max_ds = a.steering_rate_limit_radps * dt
            applied[0] += min(max(target[0] - applied[0], -max_du), max_du)
            applied[1] += min(max(target[1] - applied[1], -max_ds), max_ds)
            if self._backlash[i] > 0.0:
                self._linkage[i] = play(self._linkage[i], applied[1], self._backlash[i])
            else:
                self._linkage[i] = applied[1]
            self._effective[i] = self._linkage_output(i)

    def _linkage_output(self, i: int) -> list[float]:
        """[throttle, linkage angle] the physics sees: play, then the left/right asymmetry (the
        gain and offset are applied by the model)."""
        a_car, a_hidden = self._asymmetry[i]
        return [self._applied[i][0], asymmetric(asymmetric(float(self._linkage[i]), a_car), a_hidden)]

    def _apply_drift(self) -> None:
        """Motor force at the current time (updated once per control step; the drift is slow)."""
        if not self._drifting:
            return
        scales = [motor_force_scale(rate, self.time + start) for rate, start in self._drift]
        self._coeffs = [dataclasses.replace(k, motor_force=k.motor_force * sc)
                        for k, sc in zip(self._base_coeffs, scales)]
        b = self._base_coeffs_batch
        self._coeffs_batch = dataclasses.replace(b, motor_force=b.motor_force * np.asarray(scales))

    def _integrate(self) -> None:
        h = self.physics_dt
        if self._batch:
            x = np.array(self._x)
            u = np.array(self._effective)
            k = self._coeffs_batch
            f = self._derivative_batch
            k1 = f(x, u, k)
            k2 = f(x + 0.5 * h * k1, u, k)
            k3 = f(x + 0.5 * h * k2, u, k)
            k4 = f(x + h * k3, u, k)
            self._x = (x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)).tolist()
            return
        hh = 0.5 * h
        for i in range(self.n_cars):
            x, u, k = self._x[i], self._effective[i], self._coeffs[i]
            if self._extra[i]:
                extra = self._extra[i]

                def f(x_, u_, k_):
                    xdot = list(derivative_one(x_, u_, k_))
                    dv, dth = extra_rates(x_[3], u_[0], k_.steering_gain * u_[1] + k_.steering_offset, extra)
                    xdot[2] += dth
                    xdot[3] += dv
                    return xdot
            else:
                f = derivative_one
            k1 = f(x, u, k)
            k2 = f([a + hh * b for a, b in zip(x, k1)], u, k)
            k3 = f([a + hh * b for a, b in zip(x, k2)], u, k)
            k4 = f([a + h * b for a, b in zip(x, k3)], u, k)
            self._x[i] = [a + h / 6.0 * (b + 2.0 * c + 2.0 * d + e) for a, b, c, d, e in zip(x, k1, k2, k3, k4)]

    def _derivative_batch(self, x: np.ndarray, u: np.ndarray, k: ModelCoefficients) -> np.ndarray:
        xdot = derivative(x, u, k)
        if self._has_extra:
            for i, extra in enumerate(self._extra):
                if extra:
                    dv, dth = extra_rates(x[i, 3], u[i, 0], k.steering_gain[i] * u[i, 1] + k.steering_offset[i], extra)
                    xdot[i, 2] += dth
                    xdot[i, 3] += dv
        return xdot

    # ------------------------------------------------------------------ checks
    def _arc_lengths(self) -> np.ndarray:
        x = np.array(self._x)
        s, _, _ = self.track.to_frenet(x[:, 0], x[:, 1], x[:, 2])
        return np.asarray(s, dtype=float).reshape(self.n_cars)

    def _check_contacts(self) -> None:
        t = self.time
        x = np.array(self._x)
        n = self.n_cars
        cos_h, sin_h = np.cos(x[:, 2]), np.sin(x[:, 2])
        cx = x[:, 0] + self._offsets * cos_h
        cy = x[:, 1] + self._offsets * sin_h
        hl, hw = self._half_extents[:, :1], self._half_extents[:, 1:]
        corner_x = cx[:, None] + hl * self._corner_signs[0] * cos_h[:, None] - hw * self._corner_signs[1] * sin_h[:, None]
        corner_y = cy[:, None] + hl * self._corner_signs[0] * sin_h[:, None] + hw * self._corner_signs[1] * cos_h[:, None]
        # One projection onto the centre line for the cars (laps) and their corners (track limits):
        # the projection is most of the cost of a check.
        s, ey, _ = self.track.to_frenet(np.concatenate([x[:, 0], corner_x.ravel()]),
                                        np.concatenate([x[:, 1], corner_y.ravel()]))
        s, ey = np.asarray(s, dtype=float), np.asarray(ey, dtype=float)
        # Track limits: a car is off track while any footprint corner is outside the drivable area (the
        # bookkeeper's off-track and on-track events; what it counts of the laps, sim.race).
        excess = np.asarray(self.track.limit_excess_frenet(s[n:], ey[n:]), dtype=float).reshape(n, 4).max(axis=1)
        # The reset's check: the grid positions (no step yet), only the track limits.
        self._events.extend(self._laps.update(t, s[:n] if self._steps > 0 else self._laps.last_s, excess))

        # Car-to-car: bounding circles first, the exact rectangle test only for close pairs.
        if self.n_cars < 2:
            return
        ii, jj = self._pairs
        self._min_distance = min(self._min_distance, float(np.hypot(x[ii, 0] - x[jj, 0], x[ii, 1] - x[jj, 1]).min()))
        close = np.hypot(cx[ii] - cx[jj], cy[ii] - cy[jj]) <= self._circumradius[ii] + self._circumradius[jj]
        hit = np.zeros(len(ii), dtype=bool)
        if close.any():
            a, b = ii[close], jj[close]
            centers = np.column_stack([cx, cy])
            hit[close] = rectangles_overlap(
                centers[a], x[a, 2], self._half_extents[a], centers[b], x[b, 2], self._half_extents[b]
            )
        if not hit.any() and not self._colliding:
            return
        for p, (i, j) in enumerate(zip(ii.tolist(), jj.tolist())):
            pair = (i, j)
            if hit[p] and pair not in self._colliding:
                self._colliding.add(pair)
                self._collision_count += 1
                self._events.append(SimEvent(time=t, kind="collision", car=i, other=j))
            elif not hit[p] and pair in self._colliding:
                self._colliding.discard(pair)
                self._events.append(SimEvent(time=t, kind="collision_cleared", car=i, other=j))

    # ------------------------------------------------------------------ outputs
    def state(self, i: int) -> np.ndarray:
        """True state [x, y, heading, vx, vy, yaw_rate] of car i (heading not wrapped)."""
        return np.array(self._x[self._car_index(i)])

    @property
    def states(self) -> np.ndarray:
        return np.array(self._x)

    def applied_inputs(self, i: int) -> np.ndarray:
        """[throttle, steering servo angle] acting on car i now (after delay, limits, rate limits;
        before the steering gain/offset)."""
        return np.array(self._applied[self._car_index(i)])

    def measure(self, i: int) -> PoseMeasurement:
        """Pose of car i as the camera sees it now, with the configured Gaussian noise."""
        i = self._car_index(i)
        e = self.effects[i]
        noise = self._rngs[i].normal(size=3)
        x, y, heading = self._x[i][:3]
        return PoseMeasurement(
            car=i,
            x=x + e.position_noise_m * float(noise[0]),
            y=y + e.position_noise_m * float(noise[1]),
            heading=float(wrap_angle(heading + e.heading_noise_rad * float(noise[2]))),
            t=self.time,
        )

    def linkage_inputs(self, i: int) -> np.ndarray:
        """[throttle, linkage angle] the physics uses for car i now: the servo angle after the steering
        play and the left/right asymmetry (the wheel angle is gain * this + offset)."""
        return np.array(self._effective[self._car_index(i)])

    @property
    def events(self) -> list[SimEvent]:
        return list(self._events)

    def race_status(self) -> RaceStatus:
        laps = self._laps
        return RaceStatus(
            time=self.time,
            laps_to_win=self.laps_to_win,
            laps=tuple(max(int(v), 0) for v in laps.laps),
            lap_times=tuple(tuple(lt) for lt in laps.lap_times),
            progress_m=tuple(float(v) for v in laps.progress),
            finish_times=tuple(laps.finish_times),
            finish_order=tuple(laps.finish_order),
            winner=laps.winner,
            collisions=self._collision_count,
            off_track=tuple(bool(v) for v in laps.off_track),
            off_track_count=tuple(int(v) for v in laps.off_track_count),
            min_center_distance_m=self._min_distance,
            not_counted_m=tuple(float(v) for v in laps.not_counted),
        )

    def _car_index(self, i: int) -> int:
        if not self._ready:
            raise RuntimeError("Simulator used before reset()")
        if not isinstance(i, (int, np.integer)) or not 0 <= i < self.n_cars:
            raise IndexError(f"car index {i!r} out of range 0..{self.n_cars - 1}")
        return int(i)
