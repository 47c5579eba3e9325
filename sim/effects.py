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


# Generator effect names (docs/sysid.md) -> SimEffects fields they set.
GENERATOR_EFFECTS: dict[str, tuple[str, ...]] = {
    "actuation_delay": ("steering_delay_s", "throttle_delay_s"),
    "steering_delay": ("steering_delay_s",),
    "throttle_delay": ("throttle_delay_s",),
    "steering_offset": ("steering_offset_rad",),
    "steering_gain": ("steering_gain",),
    "longitudinal_drag": ("extra_drag_n_per_mps2",),
    "tire_slip": ("grip_scale",),
    "steering_backlash": ("steering_backlash_rad",),
    "steering_asymmetry": ("steering_gain_asymmetry",),
    "motor_drift": ("motor_force_drift_per_s",),
}


def parse_effects(text: str, flag: str | None = "--effects") -> dict[str, float]:
    """'steering_offset=0.03,actuation_delay=0.08' -> {name: value}; names from GENERATOR_EFFECTS.
    ``flag`` names the option in error messages (None: the caller names it)."""
    out: dict[str, float] = {}
    flag = f"{flag}: " if flag else ""
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep:
            raise ValueError(f"{flag}{part!r} must look like name=value")
        if name not in GENERATOR_EFFECTS:
            raise ValueError(f"{flag}unknown effect {name!r}; known: {sorted(GENERATOR_EFFECTS)}")
        try:
            v = float(value)
        except ValueError:
            raise ValueError(f"{flag}{name}: not a number: {value.strip()!r}") from None
        if not math.isfinite(v):
            raise ValueError(f"{flag}{name}: must be finite, got {value.strip()!r}")
        if name in out:
            raise ValueError(f"{flag}{name} given twice")
        out[name] = v
    return out


def sim_effects(effects: dict[str, float], position_noise_m: float, heading_noise_rad: float) -> SimEffects:
    """The SimEffects of parsed generator effects plus camera noise (m, rad)."""
    values: dict[str, float] = {"position_noise_m": position_noise_m, "heading_noise_rad": heading_noise_rad}
    for name, v in effects.items():
        for f in GENERATOR_EFFECTS[name]:
            values[f] = v
    return SimEffects(**values)
