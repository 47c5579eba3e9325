"""Effects the simulator applies that the planner's nominal model does not know about.

They stack on top of ``CarParams.corrections`` (which describe the car as identified); all are
off by default. docs/simulator.md explains each one and how it enters the physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


class SimEffectsError(ValueError):
    """An effect value is invalid; the message names the field."""


@dataclass(frozen=True)
class SimEffects:
    steering_delay_s: float = 0.0  # command FIFO in sim time before the steering servo
    throttle_delay_s: float = 0.0  # command FIFO in sim time before the ESC
    steering_offset_rad: float = 0.0  # wheel angle = gain * servo angle + offset
    steering_gain: float = 1.0
    extra_drag_n_per_mps2: float = 0.0  # added quadratic drag, F = c * vx * |vx|
    grip_scale: float = 1.0  # multiplies the Pacejka D (peak friction) of both axles
    steering_backlash_rad: float = 0.0  # play between servo and wheels (vehicles.linkage.play)
    steering_gain_asymmetry: float = 0.0  # left servo angles * (1 + a), right * (1 - a)
    motor_force_drift_per_s: float = 0.0  # motor force * (1 - rate * (sim time + drift_start_s)), >= 0.2
    drift_start_s: float = 0.0  # battery age at reset (a log continued over several simulator runs)
    position_noise_m: float = 0.0  # std of Gaussian noise on measured x and y
    heading_noise_rad: float = 0.0  # std of Gaussian noise on measured heading

    def __post_init__(self) -> None:
        limits = {
            "steering_delay_s": (0.0, 1.0),
            "throttle_delay_s": (0.0, 1.0),
            "steering_offset_rad": (-0.3, 0.3),
            "steering_gain": (0.2, 5.0),
            "extra_drag_n_per_mps2": (-1.0, 10.0),
            "grip_scale": (0.05, 5.0),
            "steering_backlash_rad": (0.0, 0.3),
            "steering_gain_asymmetry": (-0.5, 0.5),
            "motor_force_drift_per_s": (-0.01, 0.01),
            "drift_start_s": (0.0, 1e6),
            "position_noise_m": (0.0, 1.0),
            "heading_noise_rad": (0.0, 1.0),
        }
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise SimEffectsError(f"SimEffects.{f.name}: must be a finite number, got {v!r}")
            lo, hi = limits[f.name]
            if not lo <= v <= hi:
                raise SimEffectsError(f"SimEffects.{f.name}: must be in [{lo}, {hi}], got {v!r}")
