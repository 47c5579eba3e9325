"""Synthetic identification logs: a simulated car with hidden effects, driven with excitation.

The car (nominal parameters) runs in ``sim.Simulator`` with the requested ``SimEffects`` and
camera noise. A pure-pursuit controller drives half the time counter-clockwise and half
clockwise (two stints, separated by a pause that leaves a gap in the log), with a randomly
changing speed target, a weaving lateral offset (left and right turns on the straights) and a
small band-limited dither on both commands. The log holds only what a real logger records:
time, pose measurements and the commands sent; the generating effects are not written.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from planning import PurePursuitController
from sim import SimEffects, Simulator
from sim.effects import GENERATOR_EFFECTS, parse_effects, sim_effects  # noqa: F401 - re-exported for sysid callers
from sysid.log import DriveLog
from tracks import load_track
from vehicles.params import CarParams

CAMERA_POSITION_NOISE_M = 0.002
CAMERA_HEADING_NOISE_RAD = 0.01


class ReversedTrack:
    """The same track driven the other way round (clockwise for a counter-clockwise track)."""

    def __init__(self, track: Any) -> None:
        self.base = track
        self.length = track.length

    def position(self, s):
        return self.base.position(np.mod(self.length - np.asarray(s, dtype=float), self.length))

    def heading(self, s):
        return np.asarray(self.base.heading(np.mod(self.length - np.asarray(s, dtype=float), self.length))) + math.pi

    def curvature(self, s):
        return -np.asarray(self.base.curvature(np.mod(self.length - np.asarray(s, dtype=float), self.length)))

    def to_frenet(self, x, y, heading=None):
        s, ey, epsi = self.base.to_frenet(x, y, None if heading is None else np.asarray(heading) + math.pi)
        return np.mod(self.length - np.asarray(s), self.length), -np.asarray(ey), epsi

    def is_inside(self, x, y, margin=0.0):
        return self.base.is_inside(x, y, margin)

    def limit_excess_frenet(self, s, ey):
        """Same surface as the base track: s and ey are mirrored back to the base's coordinates."""
        return self.base.limit_excess_frenet(np.mod(self.length - np.asarray(s), self.length), -np.asarray(ey))


class StanleyDriver(PurePursuitController):
    """A second driver for generated logs: Stanley steering (heading error + atan(k e / (v + v0)) at the
    front axle, plus the curvature's feed-forward wheel angle) and a proportional speed loop; the
    speed reference and feed-forward throttle are the pure-pursuit driver's."""

    gain = 2.5  # 1/s: cross-track gain k
    softening_mps = 0.3  # v0

    def command(self, state, dt: float) -> tuple[float, float]:
        x, y, heading, vx = (float(v) for v in state[:4])
        geo, act = self.params.geometry, self.params.actuators
        fx, fy = x + geo.lf_m * math.cos(heading), y + geo.lf_m * math.sin(heading)
        s, ey, epsi = self.track.to_frenet(np.array([fx]), np.array([fy]), np.array([heading]))
        s, ey, epsi = (float(np.asarray(v).reshape(-1)[0]) for v in (s, ey, epsi))
        kappa = float(np.asarray(self.track.curvature(np.array([s]))).reshape(-1)[0])
        steering = (math.atan(geo.wheelbase_m * kappa) - epsi
                    - math.atan2(self.gain * (ey - self.lateral_offset_m), max(vx, 0.0) + self.softening_mps))
        corr = self.params.corrections
        steering = (steering - corr.steering_offset_rad) / corr.steering_gain
        steering = min(max(steering, -act.max_steering_rad), act.max_steering_rad)
        v_ref = self.speed_reference(s)
        throttle = self.feedforward_throttle(v_ref) + 1.2 * self.speed_kp * (v_ref - vx)
        return min(max(throttle, act.throttle_min), act.throttle_max), steering


DRIVERS = {"pursuit": PurePursuitController, "stanley": StanleyDriver}


@dataclass(frozen=True)
class ExcitationSettings:
    """How the generator excites the car; defaults keep lateral acceleration moderate."""

    control_rate_hz: float = 30.0
    speed_min_mps: float = 0.7
    speed_max_mps: float = 1.8
    speed_hold_s: tuple[float, float] = (2.0, 5.0)
    max_lateral_accel_mps2: float = 2.5
    weave_amplitude_m: float = 0.08
    weave_period_s: tuple[float, float] = (1.5, 3.5)
    steering_dither_rad: float = 0.03
    throttle_dither: float = 0.08
    dither_corner_hz: float = 3.0
    stint_pause_s: float = 1.0


def _dither(rng: np.random.Generator, n: int, sigma: float, corner_hz: float, rate_hz: float) -> np.ndarray:
    """First-order low-pass filtered white noise with standard deviation sigma."""
    a = math.exp(-2 * math.pi * corner_hz / rate_hz)
    w = rng.normal(size=n) * sigma * math.sqrt(1 - a * a)
    out = np.empty(n)
    acc = 0.0
    for i in range(n):
        acc = a * acc + w[i]
        out[i] = acc
    return out


def _start_state(track: Any, s: float) -> list[float]:
    xy = np.asarray(track.position(np.array([s])), dtype=float).reshape(2)
    heading = float(np.asarray(track.heading(np.array([s]))).reshape(-1)[0])
    return [xy[0], xy[1], heading, 0.3, 0.0, 0.0]


def generate_log(
    car: CarParams,
    effects: dict[str, float],
    minutes: float,
    seed: int,
    position_noise_m: float = CAMERA_POSITION_NOISE_M,
    heading_noise_rad: float = CAMERA_HEADING_NOISE_RAD,
    excitation: ExcitationSettings = ExcitationSettings(),
    track: str | Any = "oval",
    physics_dt: float = 0.001,
    driver: str = "pursuit",
) -> DriveLog:
    """A log of ``minutes`` of driving on ``track`` (a tracks/ name or a Track object) by ``driver``
    (a name of DRIVERS). ``car`` is the simulated car (its ``[corrections]`` and ``[other_terms]``
    included); the effects are added on top."""
    if driver not in DRIVERS:
        raise ValueError(f"driver: unknown {driver!r}; known: {sorted(DRIVERS)}")
    if not (math.isfinite(minutes) and minutes > 0):
        raise ValueError(f"minutes: must be > 0, got {minutes!r}")
    if isinstance(track, str):
        track = load_track(track)
    eff = sim_effects(effects, position_noise_m, heading_noise_rad)
    rng = np.random.default_rng(seed)
    dt = 1.0 / excitation.control_rate_hz
    stint_steps = int(round(minutes * 60.0 / 2 / dt))
    rows: list[tuple[float, float, float, float, float, float]] = []
    t_offset = 0.0
    for stint, path in enumerate((track, ReversedTrack(track))):
        # The battery keeps discharging over the pause: the second stint starts with the drift so far.
        stint_eff = dataclasses.replace(eff, drift_start_s=t_offset)
        sim = Simulator(path, [car], effects=stint_eff, seed=int(rng.integers(2**31)) + stint, physics_dt=physics_dt,
                        check_dt=0.01)
        sim.reset([_start_state(path, float(rng.uniform(0, path.length)))])
        ctrl = DRIVERS[driver](path, car, target_speed_mps=excitation.speed_min_mps,
                               max_lateral_accel_mps2=excitation.max_lateral_accel_mps2)
        steer_dither = _dither(rng, stint_steps, excitation.steering_dither_rad, excitation.dither_corner_hz,
                               excitation.control_rate_hz)
        throttle_dither = _dither(rng, stint_steps, excitation.throttle_dither, excitation.dither_corner_hz,
                                  excitation.control_rate_hz)
        next_speed_change = 0.0
        weave_phase, weave_freq, weave_amp = 0.0, 0.0, 0.0
        act = car.actuators
        for i in range(stint_steps):
            t = sim.time
            if t >= next_speed_change:
                ctrl.target_speed_mps = float(rng.uniform(excitation.speed_min_mps, excitation.speed_max_mps))
                next_speed_change = t + float(rng.uniform(*excitation.speed_hold_s))
                weave_freq = 1.0 / float(rng.uniform(*excitation.weave_period_s))
                weave_amp = float(rng.uniform(0.3, 1.0)) * excitation.weave_amplitude_m
            weave_phase += 2 * math.pi * weave_freq * dt
            ctrl.lateral_offset_m = weave_amp * math.sin(weave_phase)
            meas = sim.measure(0)
            throttle, steering = ctrl.command(sim.state(0), dt)
            throttle = min(max(throttle + throttle_dither[i], act.throttle_min), act.throttle_max)
            steering = min(max(steering + steer_dither[i], -act.max_steering_rad), act.max_steering_rad)
            rows.append((t_offset + meas.t, meas.x, meas.y, meas.heading, throttle, steering))
            sim.step([[throttle, steering]], dt)
        t_offset += sim.time + excitation.stint_pause_s
    data = np.array(rows)
    n = data.shape[0]
    return DriveLog(
        source="<generated>", t=data[:, 0], car=np.zeros(n, dtype=int), x=data[:, 1], y=data[:, 2],
        heading=data[:, 3], throttle=data[:, 4], steering=data[:, 5], speed=None, row=np.arange(2, n + 2),
    )


def effects_as_corrections(effects: dict[str, float]) -> dict[str, float]:
    """The [corrections] values that describe generator effects (for comparisons in tests/docs)."""
    mapping = {"steering_delay_s": "steering_delay_s", "throttle_delay_s": "throttle_delay_s",
               "steering_offset_rad": "steering_offset_rad", "steering_gain": "steering_gain",
               "extra_drag_n_per_mps2": "extra_drag_n_per_mps2", "grip_scale": "tire_grip_scale",
               "steering_backlash_rad": "steering_backlash_rad", "steering_gain_asymmetry": "steering_gain_asymmetry",
               "motor_force_drift_per_s": "motor_force_drift_per_s"}
    eff = sim_effects(effects, 0.0, 0.0)
    return {mapping[f.name]: getattr(eff, f.name) for f in fields(eff) if f.name in mapping}
