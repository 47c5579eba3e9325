"""Identifiability before a claim (docs/sysid.md, "Excitation tests"): a parameter is fitted only when the
training windows excite it; otherwise it is "not identifiable from these logs", with the measured reason.

Each test measures one property of the logged commands and estimated states on the training windows
and compares it with a threshold; all are cheap numpy reductions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sysid.data import Trajectory
from vehicles.params import CarParams

MOVING_MPS = 0.3  # below this the car is treated as standing (no yaw response to steering)
MIN_WINDOWS = 20  # windows showing a command change (delays, play, speed response)
MIN_SECONDS = 3.0  # seconds of samples showing a property (gain, offset, grip, drag, set-point map)
STEERING_CHANGE_RAD = 0.03  # a steering step a delay can be timed on
THROTTLE_CHANGE = {"throttle": 0.1, "speed": 0.3}  # normalised throttle; m/s of speed set-point
SATURATION = 0.95  # |command| above this fraction of its limit (the car's or the log's largest) is saturated
TURNING_SHARE = 0.1  # |steering command| below this share of the largest logged one is not turning (gain)
STRAIGHT_STEERING_RAD, STRAIGHT_YAW_RATE = 0.1, 0.5  # straight driving (drag): |command| and |yaw rate| below
DRAG_FORCE_RATIO = 1.4  # the drag force v^2 must vary by this factor over straight driving (p90 / p10)
PILE_UP = 0.02  # this share of moving samples at +- the largest logged steering command (each side): a limit
LATERAL_ACCEL_MPS2 = 1.0  # tyres load up enough for grip to show
DRIFT_SPAN_S = 20.0  # a battery drift needs this much run time
DEAD_BAND_PROBE = 0.2  # throttles below this probe a dead band
CURVE_SPREAD = 0.15  # the map's shape shows when moving |throttle| spreads this much (p90 - p10)


@dataclass(frozen=True)
class Excitation:
    param: str
    identifiable: bool
    reason: str  # what was measured, against which threshold


def _windows(traj: Trajectory, starts: np.ndarray, horizon: int) -> np.ndarray:
    return starts[:, None] + np.arange(horizon + 1)[None, :]


def excitation(traj: Trajectory, starts: np.ndarray, horizon: int, car: CarParams) -> dict[str, Excitation]:
    """Per ``[corrections]`` field: whether the training windows ``starts`` excite it, and why (not)."""
    w = _windows(traj, starts, horizon)
    speed = np.abs(traj.speed)
    moving_w = np.all(speed[w] > MOVING_MPS, axis=1)
    steer_w, thr_w = traj.steering[w], traj.throttle[w]
    idx = np.unique(w.ravel())  # samples covered by training windows
    seconds = lambda mask: float(np.count_nonzero(mask)) * traj.dt  # noqa: E731
    moving = speed[idx] > MOVING_MPS
    steer = traj.steering[idx]
    out: dict[str, Excitation] = {}

    def put(param: str, value: float, need: float, what: str, unit: str = "") -> None:
        ok = value >= need
        out[param] = Excitation(param, ok, f"{what}: {value:.3g}{unit} (need >= {need:g}{unit})")

    n_steer = int(np.count_nonzero(moving_w & (np.ptp(steer_w, axis=1) > STEERING_CHANGE_RAD)))
    put("steering_delay_s", n_steer, MIN_WINDOWS,
        f"training windows moving with a steering change > {STEERING_CHANGE_RAD} rad")
    drive = "speed" if car.speed_control.active else "throttle"
    change = THROTTLE_CHANGE[drive]
    n_thr = int(np.count_nonzero(np.ptp(thr_w, axis=1) > change))
    put("throttle_delay_s", n_thr, MIN_WINDOWS, f"training windows with a {drive} command change > {change:g}")
    # Steering: unsaturated = off the car's limit, and off the largest command in the logs when commands pile
    # up there on both sides (a joystick's symmetric range: whether the wheels follow there is unknown).
    largest = float(np.max(np.abs(traj.steering)))
    on_move = steer[moving]
    piled = on_move.size > 0 and all(np.mean(side * on_move >= 0.99 * largest) >= PILE_UP for side in (1, -1))
    limit = SATURATION * (min(car.actuators.max_steering_rad, largest) if piled else car.actuators.max_steering_rad)
    turning = TURNING_SHARE * largest  # commands smaller than this share of the largest hardly turn the car
    unsat = moving & (np.abs(steer) > turning) & (np.abs(steer) < limit)
    put("steering_gain", seconds(unsat), MIN_SECONDS, f"s of moving, turning, unsaturated steering (|command| in "
        f"({turning:.3f}, {limit:.3f}) rad)", " s")
    put("steering_gain_asymmetry", min(seconds(unsat & (steer > 0)), seconds(unsat & (steer < 0))), MIN_SECONDS / 2,
        "s of unsaturated steering on the less used side", " s")
    put("steering_offset_rad", seconds(moving), MIN_SECONDS, f"s moving faster than {MOVING_MPS} m/s", " s")
    d = np.diff(steer_w, axis=1)
    reversal = (np.max(d, axis=1) > STEERING_CHANGE_RAD / 3) & (np.min(d, axis=1) < -STEERING_CHANGE_RAD / 3)
    put("steering_backlash_rad", int(np.count_nonzero(moving_w & reversal)), MIN_WINDOWS,
        "training windows moving with a steering reversal")
    lateral = np.abs(traj.speed[idx] * traj.yaw_rate[idx])
    put("tire_grip_scale", seconds(lateral > LATERAL_ACCEL_MPS2), MIN_SECONDS,
        f"s with lateral acceleration > {LATERAL_ACCEL_MPS2} m/s^2", " s")
    straight = moving & (np.abs(steer) < STRAIGHT_STEERING_RAD) & (np.abs(traj.yaw_rate[idx]) < STRAIGHT_YAW_RATE)
    if seconds(straight) < MIN_SECONDS:
        out["extra_drag_n_per_mps2"] = Excitation("extra_drag_n_per_mps2", False, f"s of straight driving: "
                                                  f"{seconds(straight):.3g} s (need >= {MIN_SECONDS:g} s)")
    else:
        lo, hi = np.percentile(speed[idx][straight], [10, 90])
        put("extra_drag_n_per_mps2", (hi / lo) ** 2, DRAG_FORCE_RATIO,
            f"ratio of v^2 (drag force) between p90 and p10 of the straight-line speed ({lo:.2f}, {hi:.2f} m/s)")
    # Throttle map: a gain shows in accelerations (throttle changes; a steady speed trades it against drag),
    # a dead band needs small throttles and larger ones.
    put("throttle_gain", n_thr, MIN_WINDOWS, f"training windows with a {drive} command change > {change:g}")
    thr = np.abs(traj.throttle[idx])
    small = seconds(moving & (thr > 0) & (thr < DEAD_BAND_PROBE))
    large = seconds(moving & (thr >= DEAD_BAND_PROBE))
    put("throttle_dead_band", min(small, large), MIN_SECONDS,
        f"s moving with 0 < |throttle| < {DEAD_BAND_PROBE} and with |throttle| >= {DEAD_BAND_PROBE} (the fewer)", " s")
    driving = moving & (thr > 0)
    spread = float(np.ptp(np.percentile(thr[driving], [10, 90]))) if seconds(driving) >= MIN_SECONDS else 0.0
    put("throttle_curvature", spread, CURVE_SPREAD,
        f"spread of |throttle| while moving, p90 - p10 (needs >= {MIN_SECONDS:g} s moving with throttle)")
    span = float(np.ptp(traj.elapsed[starts])) if starts.size else 0.0
    put("motor_force_drift_per_s", span, DRIFT_SPAN_S, "s of run time spanned by the training windows", " s")
    steady = moving_w & (np.ptp(thr_w, axis=1) < 0.1) & (np.abs(thr_w[:, 0]) > 0.5)
    put("speed_setpoint_gain", float(np.count_nonzero(steady)) * traj.dt, MIN_SECONDS,
        "s of windows with a steady speed set-point above 0.5 m/s", " s")
    put("speed_response_scale", n_thr, MIN_WINDOWS, f"training windows with a set-point change > {change:g} m/s")
    return out
