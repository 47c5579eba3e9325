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
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from sysid.data import Trajectory
from vehicles.dynamic_bicycle import ModelCoefficients, body_rates, drive_force, input_terms, pose_rates
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
    # Run-level values (sysid.run_level): a [corrections] field's value per run (index into Trajectory.runs), used
    # for the windows of that run instead of the car's. Supported: speed_response_scale.
    run_values: tuple[tuple[str, tuple[float, ...]], ...] = ()


def _piece_weights(delay_s, dt: float, pieces: int) -> tuple[np.ndarray, np.ndarray]:
    """Per piece p of a sample split into ``pieces``: index offset o_p and weight w_p such that the mean
    of the held command shifted by delay_s over piece p of sample k is w_p u[k + o_p] + (1 - w_p) u[k + o_p + 1].
    One delay gives arrays of shape (pieces,), an array of S delays (S, pieces)."""
    shift = np.arange(pieces) / pieces - np.asarray(delay_s, dtype=float)[..., None] / dt
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


def _segment(a: np.ndarray, target: np.ndarray, rate: float, length, w: np.ndarray | None = None, half=0.0):
    """An actuator moving from a toward a constant target at <= rate over ``length`` seconds (a ramp, then
    held): (end, exact mean). With a play of half-width ``half`` behind it, starting at linkage angle w:
    (end, mean, linkage end, exact linkage mean); the linkage holds until the ramp reaches w +- half.
    ``length`` and ``half`` may be arrays (one per car of a batch); a zero length returns end = a and
    linkage end = w, and means that are finite (the caller weighs them by the zero length)."""
    if isinstance(length, float) and length <= 0.0:
        return (a, a) if w is None else (a, a, w, w)
    gap = target - a
    reach = rate * length
    end = a + np.minimum(np.maximum(gap, -reach), reach)  # np.clip, without its Python-level overhead
    moving = np.minimum(np.abs(gap) / np.maximum(reach, 1e-300), 1.0)  # fraction of the piece on the ramp
    mean = np.where(np.abs(gap) <= reach, target - 0.5 * gap * moving, 0.5 * (a + end))
    if w is None:
        return end, mean
    up = end >= a
    catch = np.where(up, w + half, w - half)  # servo angle at which the play is taken up
    span = end - a
    before = np.minimum(np.maximum((catch - a) / np.where(span == 0.0, 1.0, span), 0.0), 1.0)  # ramp fraction with w held
    follow = np.where(up, 0.5 * (np.maximum(catch, a) + end) - half, 0.5 * (np.minimum(catch, a) + end) + half)
    w_end = np.minimum(np.maximum(w, end - half), end + half)
    w_mean = moving * (before * w + (1.0 - before) * follow) + (1.0 - moving) * w_end
    return end, mean, w_end, w_mean


# The actuator chain up to the play (delays, limits, rate limits, play), per channel and per (trajectory,
# windows, the channel's parameters): the throttle, the linkage angle. The asymmetry and the motor drift act
# after it and are applied per car, so a fit of those, or of the other channel, reuses it. The trajectory is
# held weakly so a new one with the id of a collected one cannot hit.
_CHAIN_CACHE: dict[tuple, tuple[weakref.ref, np.ndarray]] = {}
THROTTLE, STEERING = "throttle", "steering"
SETPOINT_RATE_LIMIT = 1e9  # speed set-points jump (the speed loop behind them is the model's)


def _chain_key(traj: Trajectory, first: np.ndarray, steps: int, car: CarParams, n_sub: int, channel: str) -> tuple:
    c, a = car.corrections, car.actuators
    where = (id(traj), first.tobytes(), steps, n_sub, channel)
    if channel == THROTTLE:
        return where + (c.throttle_delay_s, a.throttle_min, a.throttle_max, a.throttle_rate_limit_per_s,
                        car.speed_control)
    return where + (c.steering_delay_s, c.steering_backlash_rad, a.max_steering_rad, a.steering_rate_limit_radps)


def actuation(traj: Trajectory, first: np.ndarray, steps: int, car: CarParams, n_sub: int) -> Actuation:
    """The car's command chain for every window (docs/sysid.md, "The model being checked"): delay (exact
    mean of the shifted held command), limits, rate limits, steering play, left/right asymmetry, motor drift.

    The actuators start at the delayed, limited command ACTUATOR_RUN_IN_S before ``first`` (or at the
    segment start) and run over the run-in unrecorded. Cached on the actuator parameters: a fit that
    varies only gain, offset, drag, grip, asymmetry or drift reuses the chain.
    """
    return actuations(traj, first, steps, [car], n_sub)[0]


def actuations(traj: Trajectory, first: np.ndarray, steps: int, cars: Sequence[CarParams],
               n_sub: int) -> list[Actuation]:
    """:func:`actuation` of several cars; the channels not cached run in one batch (cars x windows)."""
    chains: dict[tuple, np.ndarray] = {}
    for channel in (THROTTLE, STEERING):
        todo: dict[tuple, CarParams] = {}
        for car in cars:
            key = _chain_key(traj, first, steps, car, n_sub, channel)
            hit = _CHAIN_CACHE.get(key)
            if hit is not None and hit[0]() is traj:
                chains[key] = hit[1]
            elif key not in chains:
                todo.setdefault(key, car)
        if not todo:
            continue
        for key, chain in zip(todo, _actuation_batch(traj, first, steps, list(todo.values()), n_sub, channel)):
            chains[key] = chain
            if len(_CHAIN_CACHE) > 256:
                _CHAIN_CACHE.clear()
            _CHAIN_CACHE[key] = (weakref.ref(traj), chain)
    out = []
    for car in cars:
        c = car.corrections
        throttle = chains[_chain_key(traj, first, steps, car, n_sub, THROTTLE)]
        steering = chains[_chain_key(traj, first, steps, car, n_sub, STEERING)]
        if c.steering_gain_asymmetry != 0.0:
            steering = asymmetric(steering, c.steering_gain_asymmetry)
        motor_scale = None
        if c.motor_force_drift_per_s != 0.0:
            t_mid = traj.elapsed[first[:, None] + np.arange(steps)[None, :]] + 0.5 * traj.dt
            motor_scale = motor_force_scale(c.motor_force_drift_per_s, t_mid)
        out.append(Actuation(throttle, steering, motor_scale))
    return out


def _actuation_batch(traj: Trajectory, first: np.ndarray, steps: int, cars: list[CarParams], n_sub: int,
                     channel: str) -> list[np.ndarray]:
    """One channel of :func:`actuation`'s chain, up to the play, for S cars (computed on arrays (S, N)):
    per car the mean throttle or linkage angle (before the asymmetry) per sub-step, (N, steps, n_sub)."""
    groups: dict[tuple, list[int]] = {}  # limits and rate are scalars within a batch
    for i, car in enumerate(cars):
        a = car.actuators
        if channel == THROTTLE and car.speed_control.active:  # a speed set-point: clipped, not rate-limited
            m = car.speed_control.max_setpoint_mps
            limits = (-m, m, SETPOINT_RATE_LIMIT)
        elif channel == THROTTLE:
            limits = (a.throttle_min, a.throttle_max, a.throttle_rate_limit_per_s)
        else:
            limits = (-a.max_steering_rad, a.max_steering_rad, a.steering_rate_limit_radps)
        groups.setdefault(limits, []).append(i)
    out: list = [None] * len(cars)
    for (lo, hi, rate), members in groups.items():
        corr = [cars[i].corrections for i in members]
        if channel == THROTTLE:
            chain = _chain(traj, first, steps, n_sub, traj.throttle, [c.throttle_delay_s for c in corr], lo, hi, rate,
                           None)
        else:
            chain = _chain(traj, first, steps, n_sub, traj.steering, [c.steering_delay_s for c in corr], lo, hi, rate,
                           [c.steering_backlash_rad for c in corr])
        for i, c in zip(members, chain):
            out[i] = c
    return out


def _chain(traj: Trajectory, first: np.ndarray, steps: int, n_sub: int, command: np.ndarray, delay: list[float],
           lo: float, hi: float, rate: float, backlash: list[float] | None) -> np.ndarray:
    """Delay, limits, rate limit and (``backlash`` given) play of one command for S cars: (S, N, steps, n_sub)."""
    run_in = np.minimum(int(round(ACTUATOR_RUN_IN_S / traj.dt)), first - traj.seg_start[first])
    begin = first - run_in
    n_run = int(run_in.max()) if run_in.size else 0
    pieces = n_sub * PIECES_PER_SUBSTEP
    length = traj.dt / pieces
    last = command.size - 1
    seg_first = traj.seg_start[first]
    js = np.arange(-n_run, steps)
    offset, weight = _piece_weights(delay, traj.dt, pieces)  # (S, pieces)
    limited = np.clip(command, lo, hi)
    # Per piece p: the held command at the piece's start and after its switch, for every step of every
    # window of every car (steps, S, N), and the fraction f of the piece before the switch (S, 1).
    base = first[None, None, :] + js[:, None, None]
    pieces_of = []
    for p in range(pieces):
        at = base + offset[None, :, p, None]
        f = weight[:, p, None]
        pieces_of.append((limited[np.clip(at, seg_first, last)], limited[np.clip(at + 1, seg_first, last)],
                          f, bool(np.all(f >= 1.0)), f * length, (1.0 - f) * length))

    def move(a: np.ndarray, i: int, p: int, w=None, half=0.0):
        """_segment over piece p of step i: the held command switches once inside the piece, after
        the fraction f of it (exact for the shifted zero-order hold; continuous in the delay).
        Cars whose command does not switch (f = 1) get a zero-length second part."""
        targets, targets_after, f, whole, f_length, rest_length = pieces_of[p]
        if whole:
            return _segment(a, targets[i], rate, length, w, half)
        one = _segment(a, targets[i], rate, f_length, w, half)
        two = _segment(one[0], targets_after[i], rate, rest_length, None if w is None else one[2], half)
        if w is None:
            return two[0], f * one[1] + (1.0 - f) * two[1]
        return two[0], f * one[1] + (1.0 - f) * two[1], two[2], f * one[3] + (1.0 - f) * two[3]

    # Windows with a shorter run-in (near a segment start) hold their first target until their own start.
    k0 = np.maximum(begin, first - n_run)
    s = limited[np.clip(k0 + offset[:, 0, None] + (weight[:, 0, None] <= 0.0), seg_first, last)]
    w = s.copy()
    half = 0.5 * np.array(backlash or [0.0] * len(delay))[:, None]
    play = half > 0.0  # cars without play: the linkage is the servo (the plain path, not a zero play)
    any_play = bool(play.any())
    out = np.empty((len(delay), first.size, steps, n_sub))
    acc = np.zeros((len(delay), first.size))
    for i, j in enumerate(js):
        # Before its own run-in a window's actuators hold; from j = 0 on every window is running.
        active = None if j >= 0 else first + j >= begin
        for p in range(pieces):
            if any_play:
                s_end, s_mean, w_end, w_mean = move(s, i, p, w, half)
                w = w_end if active is None else np.where(active, w_end, w)
                if not play.all():
                    w_mean = np.where(play, w_mean, s_mean)
            else:
                s_end, w_mean = move(s, i, p)
            s = s_end if active is None else np.where(active, s_end, s)
            if j >= 0:
                if PIECES_PER_SUBSTEP == 1:
                    out[:, :, j, p] = w_mean
                    continue
                acc += w_mean
                if (p + 1) % PIECES_PER_SUBSTEP == 0:
                    out[:, :, j, p // PIECES_PER_SUBSTEP] = acc / PIECES_PER_SUBSTEP
                    acc[:] = 0.0
    return out


MAX_SUBSTEP_S = 0.0175  # longest RK4 sub-step: 2 per sample at 30 Hz, 1 at 60 Hz


def substeps(setup: ModelSetup, dt: float) -> int:
    return setup.substeps or max(1, int(np.ceil(dt / MAX_SUBSTEP_S - 1e-9)))


def _stack(setups: Sequence[ModelSetup], traj: Trajectory, first: np.ndarray, steps: int, n_sub: int):
    """Coefficients and actuation of several setups, windows of setup 0 first: coefficients that differ
    between setups are arrays (one per window), the others floats; inputs (steps, n_sub, S * N), the
    motor scale (steps, S * N) or None, laid out so each sub-step's inputs are contiguous; and the
    [other_terms] (``vehicles.extra_terms.coefficients``, coefficients that differ as arrays per window)."""
    n = first.size
    cars = [s.car for s in setups]
    if any(c.geometry != cars[0].geometry for c in cars[1:]):
        raise ValueError("predict: stacked setups may differ in [corrections] and [other_terms] only")
    per_car = [dict((fn, (ca, cy)) for fn, ca, cy in car_extra_terms(c)) for c in cars]
    extra = []
    for fn in dict.fromkeys(fn for terms in per_car for fn in terms):
        coef = np.array([terms.get(fn, (0.0, 0.0)) for terms in per_car])
        extra.append((fn, *(float(c[0]) if np.all(c == c[0]) else np.repeat(c, n) for c in coef.T)))
    acts = actuations(traj, first, steps, cars, n_sub)
    k = ModelCoefficients.from_params(cars)
    k = ModelCoefficients(**{f.name: float(v[0]) if np.all(v == v[0]) else np.repeat(v, n)
                             for f in dataclasses.fields(k) for v in (getattr(k, f.name),)})

    if any(s.run_values for s in setups):
        k = dataclasses.replace(k, speed_gain=np.concatenate([_speed_gain(s, traj.run[first]) for s in setups]))

    def inputs(a: list[np.ndarray]) -> np.ndarray:
        return np.ascontiguousarray((a[0] if len(a) == 1 else np.concatenate(a)).transpose(1, 2, 0))

    scale = None
    if any(a.motor_scale is not None for a in acts):
        scale = np.concatenate([np.ones((n, steps)) if a.motor_scale is None else a.motor_scale for a in acts]).T
        scale = np.ascontiguousarray(scale)
    return k, inputs([a.throttle for a in acts]), inputs([a.steering for a in acts]), scale, tuple(extra)


def _speed_gain(setup: ModelSetup, runs: np.ndarray) -> np.ndarray:
    """The speed loop's gain per window (of runs ``runs``), with the setup's run-level values."""
    scale = np.full(runs.size, setup.car.corrections.speed_response_scale)
    for name, values in setup.run_values:
        if name != "speed_response_scale":
            raise ValueError(f"predict: run-level values of {name} are not supported")
        scale = np.asarray(values, dtype=float)[runs]
    return setup.car.speed_control.gain_per_s * scale


def _with_motor_scale(k: ModelCoefficients, scale: np.ndarray | None) -> ModelCoefficients:
    return k if scale is None else dataclasses.replace(k, motor_force=k.motor_force * scale)


# Predictions per (trajectory, windows, horizon, setup), least recently used dropped beyond the byte cap: a
# selection evaluates the same model on the same windows several times (a fit's start, refits from the same
# point, the judged models). Arrays are read-only; the trajectory is held weakly (see _CHAIN_CACHE).
_PREDICTION_CACHE: OrderedDict[tuple, tuple[weakref.ref, np.ndarray]] = OrderedDict()
PREDICTION_CACHE_BYTES = 64 * 2 ** 20


def predict(traj: Trajectory, starts: np.ndarray, horizon: int, setup: ModelSetup | Sequence[ModelSetup]) -> np.ndarray:
    """Predicted [x, y, heading, speed] at steps 0..horizon from each start: shape (N, horizon+1, 4).

    Given a sequence of S setups (same model family, differing in ``[corrections]`` only), all are run
    in one batch and the result has shape (S, N, horizon+1, 4). Every start must have
    ``start + horizon`` inside its segment. Results are read-only (they may be shared with later calls).
    """
    starts = np.asarray(starts, dtype=int)
    if np.any(starts + horizon >= traj.seg_end[starts]):
        raise ValueError("predict: a prediction window runs past the end of its segment")
    setups = [setup] if isinstance(setup, ModelSetup) else list(setup)
    if len({s.dynamic for s in setups}) != 1 or len({s.substeps for s in setups}) != 1:
        raise ValueError("predict: stacked setups must share the model family and sub-steps")
    where = (id(traj), starts.tobytes(), horizon)
    found: dict[ModelSetup, np.ndarray] = {}
    for s in setups:
        hit = _PREDICTION_CACHE.get(where + (s,))
        if hit is not None and hit[0]() is traj:
            found[s] = hit[1]
            _PREDICTION_CACHE.move_to_end(where + (s,))
    todo = list(dict.fromkeys(s for s in setups if s not in found))  # each distinct setup once
    if todo:
        run = _predict_dynamic if todo[0].dynamic else _predict_kinematic
        for s, pred in zip(todo, run(traj, starts, horizon, todo)):
            pred.flags.writeable = False
            found[s] = pred
            _PREDICTION_CACHE[where + (s,)] = (weakref.ref(traj), pred)
        size = sum(v[1].nbytes for v in _PREDICTION_CACHE.values())
        while size > PREDICTION_CACHE_BYTES and len(_PREDICTION_CACHE) > 1:
            size -= _PREDICTION_CACHE.popitem(last=False)[1][1].nbytes
    if isinstance(setup, ModelSetup):
        return found[setup]
    return np.stack([found[s] for s in setups])


def _predict_kinematic(traj: Trajectory, starts: np.ndarray, horizon: int, setups: list[ModelSetup]) -> np.ndarray:
    car = setups[0].car
    lr, wheelbase, mass = car.geometry.lr_m, car.geometry.wheelbase_m, car.inertia.mass_kg
    n_sub = substeps(setups[0], traj.dt)
    h = traj.dt / n_sub
    k_all, thr, steer, motor_scale, extra = _stack(setups, traj, starts, horizon, n_sub)
    idx = np.tile(starts, len(setups))
    out = np.empty((idx.size, horizon + 1, 4))
    x, y, th, v = traj.xs[idx], traj.ys[idx], traj.headings[idx], traj.speed[idx]
    out[:, 0] = np.stack([x, y, th, v], axis=-1)
    for j in range(horizon):
        k = _with_motor_scale(k_all, None if motor_scale is None else motor_scale[j])
        for q in range(n_sub):
            throttle = thr[j, q]
            delta = k.steering_gain * steer[j, q] + k.steering_offset
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


def _predict_dynamic(traj: Trajectory, starts: np.ndarray, horizon: int, setups: list[ModelSetup]) -> np.ndarray:
    n_sub = substeps(setups[0], traj.dt)
    h = traj.dt / n_sub
    # Lateral velocity and yaw rate are not measured and their derivative estimates are poor under
    # fast steering, so they come from running the model over the preceding WARMUP_S from the
    # (smoothed) measured state; pose and forward speed are then reset to the measurements.
    warm = min(int(round(WARMUP_S / traj.dt)), int(np.min(starts - traj.seg_start[starts])))
    k_all, thr, steer, motor_scale, extra = _stack(setups, traj, starts - warm, warm + horizon, n_sub)
    idx = np.tile(starts, len(setups))
    # The state as separate contiguous arrays [x, y, heading, vx, vy, yaw rate]; the inputs' terms are
    # computed once per sub-step (they are held over it), the state's for each RK4 stage.
    at = idx - warm
    x, y, th, vx, vy, r = (a[at] for a in (traj.xs, traj.ys, traj.headings, traj.vx, traj.vy, traj.yaw_rate))
    out = np.empty((4, horizon + 1, idx.size))
    hh, h6 = 0.5 * h, h / 6.0

    def record(j: int) -> None:
        out[0, j], out[1, j], out[2, j] = x, y, th
        out[3, j] = np.sqrt(vx * vx + vy * vy) * np.sign(vx)

    for j in range(warm + horizon):
        if j == warm:
            x, y, th, vx = traj.xs[idx], traj.ys[idx], traj.headings[idx], traj.vx[idx]
            record(0)
        k = _with_motor_scale(k_all, None if motor_scale is None else motor_scale[j])
        for q in range(n_sub):
            inp = input_terms(thr[j, q], steer[j, q], k)

            def f(th_, vx_, vy_, r_, inp=inp, k=k):
                dx, dy, dth = pose_rates(th_, vx_, vy_, r_)
                dvx, dvy, dr = body_rates(vx_, vy_, r_, inp, k)
                if extra:
                    dv, dth_extra = extra_rates(vx_, inp.throttle, inp.delta, extra)
                    dvx, dth = dvx + dv, dth + dth_extra
                return dx, dy, dth, dvx, dvy, dr

            # RK4 with the input held; x and y do not enter the rates, so only their slopes are kept.
            k1 = f(th, vx, vy, r)
            k2 = f(th + hh * k1[2], vx + hh * k1[3], vy + hh * k1[4], r + hh * k1[5])
            k3 = f(th + hh * k2[2], vx + hh * k2[3], vy + hh * k2[4], r + hh * k2[5])
            k4 = f(th + h * k3[2], vx + h * k3[3], vy + h * k3[4], r + h * k3[5])
            x, y, th, vx, vy, r = (s + h6 * (a + 2 * b + 2 * c + d)
                                   for s, a, b, c, d in zip((x, y, th, vx, vy, r), k1, k2, k3, k4))
        if j >= warm:
            record(j - warm + 1)
    return out.transpose(2, 1, 0).reshape(len(setups), starts.size, horizon + 1, 4)


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
