"""Multi-step prediction from measured states with the planner's model or the dynamic model.

Planner's model (docs/sysid.md, "The model being checked"): the kinematic bicycle of
``solver_cpp.KinematicBicycle`` (state [x, y, speed, heading] of the centre of gravity, slip
angle beta = atan(lr/L tan delta)), driven by the longitudinal model of ``vehicles.dynamic_bicycle``
(acceleration = drive force / mass) and the car's ``[corrections]``:
wheel angle = gain * steering(t - steering_delay) + offset, throttle(t - throttle_delay),
extra drag. Here it is integrated as a continuous-time ODE (RK4 sub-steps), batched over all
start points; the planner's own time discretisation is its business, not the car's.

With ``dynamic=True`` the dynamic bicycle (Pacejka tyres, ``vehicles.dynamic_bicycle``) replaces
the kinematic one; that is the "tire_slip" candidate.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from sysid.data import Trajectory
from vehicles.dynamic_bicycle import ModelCoefficients, derivative, drive_force
from vehicles.extra_terms import car_extra_terms, extra_rates
from vehicles.linkage import asymmetric
from vehicles.params import CarParams, motor_force_scale

WARMUP_S = 0.2  # model run-in before each dynamic prediction (>> the ~0.03 s lateral/yaw time constants)
# Actuator run-in before a prediction (rate limits and play have memory; the servo crosses its whole
# range in 2 * 0.47 rad / 10.5 rad/s = 0.09 s): the actuators start at the delayed command this long before.
ACTUATOR_RUN_IN_S = 0.2
PIECES_PER_SUBSTEP = 1  # actuator pieces per RK4 sub-step (the rate-limited path is exact per piece; 2 changed 1-s predictions by < 0.1 mm)


@dataclass(frozen=True)
class ModelSetup:
    """What a prediction runs: the car (corrections and ``[other_terms]`` included) and the model family."""

    car: CarParams
    dynamic: bool = False
    substeps: int = field(default=0)  # RK4 steps per sample; 0: sub-steps of <= MAX_SUBSTEP_S (2 at 30 Hz, 1 at 60 Hz)


def _piece_weights(delay_s: float, dt: float, pieces: int) -> tuple[np.ndarray, np.ndarray]:
    """Per piece p of a sample split into ``pieces``: index offset o_p and weight w_p such that the mean
    of the held command shifted by delay_s over piece p of sample k is w_p u[k + o_p] + (1 - w_p) u[k + o_p + 1]."""
    shift = np.arange(pieces) / pieces - delay_s / dt
    offset = np.floor(shift + 1e-12)
    weight = np.minimum(1.0, (offset + 1.0 - shift) * pieces)
    return offset.astype(int), weight


def delayed_command(traj: Trajectory, command: np.ndarray, idx: np.ndarray, delay_s: float) -> np.ndarray:
    """Mean over sample idx's interval of the zero-order-hold command shifted by delay_s.

    With delay = (m + f) dt this is (1 - f) u[idx - m] + f u[idx - m - 1]; before the segment
    start the first command of the segment is used.
    """
    if delay_s <= 0.0:
        return command[idx]
    offset, weight = _piece_weights(delay_s, traj.dt, 1)
    first = traj.seg_start[idx]
    a = command[np.maximum(idx + offset[0], first)]
    b = command[np.maximum(idx + offset[0] + 1, first)]
    return weight[0] * a + (1.0 - weight[0]) * b


@dataclass(frozen=True)
class Actuation:
    """Inputs acting on the car over samples first..first+steps-1 of each window, per RK4 sub-step."""

    throttle: np.ndarray  # (N, steps, n_sub): mean applied throttle over the sub-step
    steering: np.ndarray  # (N, steps, n_sub): linkage angle after play and asymmetry (before gain/offset)
    motor_scale: np.ndarray | None  # (N, steps) motor force scale (battery drift); None without drift


def _segment(a: np.ndarray, target: np.ndarray, rate: float, length: float, w: np.ndarray | None = None,
             half: float = 0.0):
    """An actuator moving from a toward a constant target at <= rate over ``length`` seconds (a ramp, then
    held): (end, exact mean). With a play of half-width ``half`` behind it, starting at linkage angle w:
    (end, mean, linkage end, exact linkage mean); the linkage holds until the ramp reaches w +- half."""
    if length <= 0.0:
        return (a, a) if w is None else (a, a, w, w)
    gap = target - a
    reach = rate * length
    end = a + np.clip(gap, -reach, reach)
    moving = np.minimum(np.abs(gap) / max(reach, 1e-300), 1.0)  # fraction of the piece on the ramp
    mean = np.where(np.abs(gap) <= reach, target - 0.5 * gap * moving, 0.5 * (a + end))
    if w is None:
        return end, mean
    up = end >= a
    catch = np.where(up, w + half, w - half)  # servo angle at which the play is taken up
    span = end - a
    before = np.clip((catch - a) / np.where(span == 0.0, 1.0, span), 0.0, 1.0)  # ramp fraction with w held
    follow = np.where(up, 0.5 * (np.maximum(catch, a) + end) - half, 0.5 * (np.minimum(catch, a) + end) + half)
    w_end = np.clip(w, end - half, end + half)
    w_mean = moving * (before * w + (1.0 - before) * follow) + (1.0 - moving) * w_end
    return end, mean, w_end, w_mean


_ACTUATION_CACHE: dict[tuple, Actuation] = {}


def actuation(traj: Trajectory, first: np.ndarray, steps: int, car: CarParams, n_sub: int) -> Actuation:
    """The car's command chain for every window (docs/sysid.md, "The model being checked"): delay (exact
    mean of the shifted held command), limits, rate limits, steering play, left/right asymmetry, motor drift.

    The actuators start at the delayed, limited command ACTUATOR_RUN_IN_S before ``first`` (or at the
    segment start) and run over the run-in unrecorded. Cached on the actuator parameters: a fit that
    varies only gain, offset, drag or grip reuses it.
    """
    c, act = car.corrections, car.actuators
    key = (id(traj), first.tobytes(), steps, n_sub, c.steering_delay_s, c.throttle_delay_s,
           c.steering_backlash_rad, c.steering_gain_asymmetry, c.motor_force_drift_per_s, act)
    hit = _ACTUATION_CACHE.get(key)
    if hit is not None:
        return hit
    run_in = np.minimum(int(round(ACTUATOR_RUN_IN_S / traj.dt)), first - traj.seg_start[first])
    begin = first - run_in
    n_run = int(run_in.max()) if run_in.size else 0
    pieces = n_sub * PIECES_PER_SUBSTEP
    length = traj.dt / pieces
    last = traj.throttle.size - 1
    seg_first = traj.seg_start[first]
    channels = []
    for command, delay, lo, hi, rate in (
            (traj.throttle, c.throttle_delay_s, act.throttle_min, act.throttle_max, act.throttle_rate_limit_per_s),
            (traj.steering, c.steering_delay_s, -act.max_steering_rad, act.max_steering_rad,
             act.steering_rate_limit_radps)):
        offset, weight = _piece_weights(delay, traj.dt, pieces)
        limited = np.clip(command, lo, hi)

        def move(a: np.ndarray, k: np.ndarray, p: int, w=None, half=0.0, offset=offset, weight=weight,
                 limited=limited, rate=rate):
            """_segment over piece p of sample k: the held command switches once inside the piece, after
            the fraction weight[p] of it (exact for the shifted zero-order hold; continuous in the delay)."""
            first_target = limited[np.clip(k + offset[p], seg_first, last)]
            f = weight[p]
            if f >= 1.0:
                return _segment(a, first_target, rate, length, w, half)
            one = _segment(a, first_target, rate, f * length, w, half)
            two = _segment(one[0], limited[np.clip(k + offset[p] + 1, seg_first, last)], rate, (1.0 - f) * length,
                           None if w is None else one[2], half)
            if w is None:
                return two[0], f * one[1] + (1.0 - f) * two[1]
            return two[0], f * one[1] + (1.0 - f) * two[1], two[2], f * one[3] + (1.0 - f) * two[3]

        def start_value(k: np.ndarray, offset=offset, weight=weight, limited=limited) -> np.ndarray:
            return limited[np.clip(k + offset[0] + (weight[0] <= 0.0), seg_first, last)]

        channels.append((move, start_value))
    (throttle_move, throttle_start), (steer_move, steer_start) = channels
    # Windows with a shorter run-in (near a segment start) hold their first target until their own start.
    k0 = np.maximum(begin, first - n_run)
    u = throttle_start(k0)
    s = steer_start(k0)
    w = s.copy()
    backlash, asym = c.steering_backlash_rad, c.steering_gain_asymmetry
    thr_out = np.empty((first.size, steps, n_sub))
    steer_out = np.empty((first.size, steps, n_sub))
    thr_acc = np.zeros(first.size)
    steer_acc = np.zeros(first.size)
    for j in range(-n_run, steps):
        k = first + j
        active = k >= begin
        for p in range(pieces):
            u_end, u_mean = throttle_move(u, k, p)
            if backlash > 0.0:
                s_end, s_mean, w_end, w_mean = steer_move(s, k, p, w, 0.5 * backlash)
                w = np.where(active, w_end, w)
            else:
                s_end, s_mean = steer_move(s, k, p)
                w_mean = s_mean
            u = np.where(active, u_end, u)
            s = np.where(active, s_end, s)
            if j >= 0:
                thr_acc += u_mean
                steer_acc += w_mean
                if (p + 1) % PIECES_PER_SUBSTEP == 0:
                    q = p // PIECES_PER_SUBSTEP
                    thr_out[:, j, q] = thr_acc / PIECES_PER_SUBSTEP
                    steer_out[:, j, q] = steer_acc / PIECES_PER_SUBSTEP
                    thr_acc[:] = 0.0
                    steer_acc[:] = 0.0
    if asym != 0.0:
        steer_out = asymmetric(steer_out, asym)
    motor_scale = None
    if c.motor_force_drift_per_s != 0.0:
        t_mid = traj.t[first[:, None] + np.arange(steps)[None, :]] + 0.5 * traj.dt - traj.t[0]
        motor_scale = motor_force_scale(c.motor_force_drift_per_s, t_mid)
    out = Actuation(thr_out, steer_out, motor_scale)
    if len(_ACTUATION_CACHE) > 64:
        _ACTUATION_CACHE.clear()
    _ACTUATION_CACHE[key] = out
    return out


MAX_SUBSTEP_S = 0.0175  # longest RK4 sub-step: 2 per sample at 30 Hz, 1 at 60 Hz


def substeps(setup: ModelSetup, dt: float) -> int:
    return setup.substeps or max(1, int(np.ceil(dt / MAX_SUBSTEP_S - 1e-9)))


def _stack(setups: Sequence[ModelSetup], traj: Trajectory, first: np.ndarray, steps: int, n_sub: int):
    """Coefficients (one per window, windows of setup 0 first) and actuation of several setups."""
    n = first.size
    cars = [s.car for s in setups]
    if any(c.other_terms != cars[0].other_terms or c.geometry != cars[0].geometry for c in cars[1:]):
        raise ValueError("predict: stacked setups may differ in [corrections] only")
    acts = [actuation(traj, first, steps, c, n_sub) for c in cars]
    k = ModelCoefficients.from_params(cars)
    if len(cars) == 1:
        k = ModelCoefficients(**{f.name: float(getattr(k, f.name)[0]) for f in dataclasses.fields(k)})
        return k, acts[0].throttle, acts[0].steering, acts[0].motor_scale
    k = ModelCoefficients(**{f.name: np.repeat(getattr(k, f.name), n) for f in dataclasses.fields(k)})
    scale = None
    if any(a.motor_scale is not None for a in acts):
        scale = np.concatenate([np.ones((n, steps)) if a.motor_scale is None else a.motor_scale for a in acts])
    return (k, np.concatenate([a.throttle for a in acts]), np.concatenate([a.steering for a in acts]), scale)


def _with_motor_scale(k: ModelCoefficients, scale: np.ndarray | None) -> ModelCoefficients:
    return k if scale is None else dataclasses.replace(k, motor_force=k.motor_force * scale)


def predict(traj: Trajectory, starts: np.ndarray, horizon: int, setup: ModelSetup | Sequence[ModelSetup]) -> np.ndarray:
    """Predicted [x, y, heading, speed] at steps 0..horizon from each start: shape (N, horizon+1, 4).

    Given a sequence of S setups (same model family, differing in ``[corrections]`` only), all are run
    in one batch and the result has shape (S, N, horizon+1, 4). Every start must have
    ``start + horizon`` inside its segment.
    """
    starts = np.asarray(starts, dtype=int)
    if np.any(starts + horizon >= traj.seg_end[starts]):
        raise ValueError("predict: a prediction window runs past the end of its segment")
    setups = [setup] if isinstance(setup, ModelSetup) else list(setup)
    if len({s.dynamic for s in setups}) != 1 or len({s.substeps for s in setups}) != 1:
        raise ValueError("predict: stacked setups must share the model family and sub-steps")
    run = _predict_dynamic if setups[0].dynamic else _predict_kinematic
    out = run(traj, starts, horizon, setups)
    return out[0] if isinstance(setup, ModelSetup) else out


def _predict_kinematic(traj: Trajectory, starts: np.ndarray, horizon: int, setups: list[ModelSetup]) -> np.ndarray:
    car = setups[0].car
    lr, wheelbase, mass = car.geometry.lr_m, car.geometry.wheelbase_m, car.inertia.mass_kg
    n_sub = substeps(setups[0], traj.dt)
    h = traj.dt / n_sub
    k_all, thr, steer, motor_scale = _stack(setups, traj, starts, horizon, n_sub)
    extra = car_extra_terms(car)
    idx = np.tile(starts, len(setups))
    out = np.empty((idx.size, horizon + 1, 4))
    x, y, th, v = traj.xs[idx], traj.ys[idx], traj.headings[idx], traj.speed[idx]
    out[:, 0] = np.stack([x, y, th, v], axis=-1)
    for j in range(horizon):
        k = _with_motor_scale(k_all, None if motor_scale is None else motor_scale[:, j])
        for q in range(n_sub):
            throttle = thr[:, j, q]
            delta = k.steering_gain * steer[:, j, q] + k.steering_offset
            beta = np.arctan(lr / wheelbase * np.tan(delta))
            yaw_per_speed = np.sin(beta) / lr

            def rates(v_):
                a = drive_force(v_, throttle, k, partials=False)[0] / mass
                w = v_ * yaw_per_speed
                if extra:
                    dv, dth = extra_rates(v_, throttle, delta, extra)
                    return a + dv, w + dth
                return a, w

            # RK4 on (x, y, heading, speed); inputs constant over the sub-step.
            a1, w1 = rates(v)
            c1x, c1y = v * np.cos(th + beta), v * np.sin(th + beta)
            v2, th2 = v + 0.5 * h * a1, th + 0.5 * h * w1
            a2, w2 = rates(v2)
            c2x, c2y = v2 * np.cos(th2 + beta), v2 * np.sin(th2 + beta)
            v3, th3 = v + 0.5 * h * a2, th + 0.5 * h * w2
            a3, w3 = rates(v3)
            c3x, c3y = v3 * np.cos(th3 + beta), v3 * np.sin(th3 + beta)
            v4, th4 = v + h * a3, th + h * w3
            a4, w4 = rates(v4)
            c4x, c4y = v4 * np.cos(th4 + beta), v4 * np.sin(th4 + beta)
            x = x + h / 6.0 * (c1x + 2 * c2x + 2 * c3x + c4x)
            y = y + h / 6.0 * (c1y + 2 * c2y + 2 * c3y + c4y)
            th = th + h / 6.0 * (w1 + 2 * w2 + 2 * w3 + w4)
            v = v + h / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
        out[:, j + 1] = np.stack([x, y, th, v], axis=-1)
    return out.reshape(len(setups), starts.size, horizon + 1, 4)


def _measured_state(traj: Trajectory, idx: np.ndarray) -> np.ndarray:
    return np.stack([traj.xs[idx], traj.ys[idx], traj.headings[idx], traj.vx[idx], traj.vy[idx],
                     traj.yaw_rate[idx]], axis=-1)


def _predict_dynamic(traj: Trajectory, starts: np.ndarray, horizon: int, setups: list[ModelSetup]) -> np.ndarray:
    car = setups[0].car
    n_sub = substeps(setups[0], traj.dt)
    h = traj.dt / n_sub
    extra = car_extra_terms(car)
    # Lateral velocity and yaw rate are not measured and their derivative estimates are poor under
    # fast steering, so they come from running the model over the preceding WARMUP_S from the
    # (smoothed) measured state; pose and forward speed are then reset to the measurements.
    warm = min(int(round(WARMUP_S / traj.dt)), int(np.min(starts - traj.seg_start[starts])))
    k_all, thr, steer, motor_scale = _stack(setups, traj, starts - warm, warm + horizon, n_sub)
    idx = np.tile(starts, len(setups))
    state = _measured_state(traj, idx - warm)
    out = np.empty((idx.size, horizon + 1, 4))

    def record(j: int) -> None:
        speed = np.hypot(state[:, 3], state[:, 4]) * np.sign(state[:, 3])
        out[:, j] = np.stack([state[:, 0], state[:, 1], state[:, 2], speed], axis=-1)

    for j in range(warm + horizon):
        if j == warm:
            state[:, :4] = _measured_state(traj, idx)[:, :4]
            record(0)
        k = _with_motor_scale(k_all, None if motor_scale is None else motor_scale[:, j])
        for q in range(n_sub):
            throttle, steering = thr[:, j, q], steer[:, j, q]
            u = np.stack([throttle, steering], axis=-1)
            if extra:
                delta = k.steering_gain * steering + k.steering_offset

                def f(s):
                    xdot = derivative(s, u, k)
                    dv, dth = extra_rates(s[:, 3], throttle, delta, extra)
                    xdot[:, 3] += dv
                    xdot[:, 2] += dth
                    return xdot
            else:

                def f(s):
                    return derivative(s, u, k)

            k1 = f(state)
            k2 = f(state + 0.5 * h * k1)
            k3 = f(state + 0.5 * h * k2)
            k4 = f(state + h * k3)
            state = state + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        if j >= warm:
            record(j - warm + 1)
    return out.reshape(len(setups), starts.size, horizon + 1, 4)


@dataclass(frozen=True)
class PredictionErrors:
    """Errors of predictions against the measurements, shape (N, horizon): steps 1..horizon."""

    position: np.ndarray  # m, Euclidean
    heading: np.ndarray  # rad, wrapped
    speed: np.ndarray  # m/s (against the estimated speed)
    along: np.ndarray  # signed position error along the measured heading at the predicted step (m)
    lateral: np.ndarray  # signed, left of that heading positive (m)


def prediction_errors(traj: Trajectory, starts: np.ndarray, pred: np.ndarray) -> PredictionErrors:
    horizon = pred.shape[1] - 1
    idx = starts[:, None] + np.arange(1, horizon + 1)[None, :]
    dx = pred[:, 1:, 0] - traj.x[idx]
    dy = pred[:, 1:, 1] - traj.y[idx]
    dth = np.angle(np.exp(1j * (pred[:, 1:, 2] - traj.heading[idx])))
    c, s = np.cos(traj.headings[idx]), np.sin(traj.headings[idx])
    return PredictionErrors(
        position=np.hypot(dx, dy),
        heading=dth,
        speed=pred[:, 1:, 3] - traj.speed[idx],
        along=c * dx + s * dy,
        lateral=-s * dx + c * dy,
    )
