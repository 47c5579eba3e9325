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

from dataclasses import dataclass, field

import numpy as np

from sysid.data import Trajectory
from vehicles.dynamic_bicycle import ModelCoefficients, derivative, drive_force
from vehicles.params import CarParams

WARMUP_S = 0.2  # model run-in before each dynamic prediction (>> the ~0.03 s lateral/yaw time constants)

# Library of the sparse-regression fallback ("other"): functions of speed v, throttle u and wheel angle d.
LIBRARY_TERMS: dict[str, callable] = {
    "1": lambda v, u, d: np.ones_like(v),
    "v": lambda v, u, d: v,
    "v|v|": lambda v, u, d: v * np.abs(v),
    "u": lambda v, u, d: u,
    "u*v": lambda v, u, d: u * v,
    "d": lambda v, u, d: d,
    "d*v": lambda v, u, d: d * v,
    "d*v^2": lambda v, u, d: d * v * v,
    "d|d|*v": lambda v, u, d: d * np.abs(d) * v,
    "d^2*v^2": lambda v, u, d: d * d * v * v,
}


@dataclass(frozen=True)
class ExtraTerms:
    """Sparse additive corrections: d(speed)/dt += sum accel[i] * term_i, d(heading)/dt += sum yaw[i] * term_i."""

    names: tuple[str, ...]
    accel: np.ndarray
    yaw: np.ndarray

    def evaluate(self, v: np.ndarray, u: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dv = np.zeros_like(v)
        dth = np.zeros_like(v)
        for name, ca, cy in zip(self.names, self.accel, self.yaw):
            if ca == 0.0 and cy == 0.0:
                continue
            term = LIBRARY_TERMS[name](v, u, d)
            dv = dv + ca * term
            dth = dth + cy * term
        return dv, dth


@dataclass(frozen=True)
class ModelSetup:
    """What a prediction runs: the car (with its corrections), the model family, extra terms."""

    car: CarParams
    dynamic: bool = False
    extra: ExtraTerms | None = None
    substeps: int = field(default=0)  # RK4 steps per sample; 0: 2 (h = 17 ms at 30 Hz, well inside RK4 stability)


def delayed_command(traj: Trajectory, command: np.ndarray, idx: np.ndarray, delay_s: float) -> np.ndarray:
    """Mean over sample idx's interval of the zero-order-hold command shifted by delay_s.

    With delay = (m + f) dt this is (1 - f) u[idx - m] + f u[idx - m - 1]; before the segment
    start the first command of the segment is used.
    """
    if delay_s <= 0.0:
        return command[idx]
    steps = delay_s / traj.dt
    m = int(np.floor(steps))
    f = steps - m
    first = traj.seg_start[idx]
    a = command[np.maximum(idx - m, first)]
    b = command[np.maximum(idx - m - 1, first)]
    return (1.0 - f) * a + f * b


def inputs_at(traj: Trajectory, idx: np.ndarray, car: CarParams) -> tuple[np.ndarray, np.ndarray]:
    """(throttle, steering command) acting during sample idx, after the car's delays."""
    c = car.corrections
    return (
        delayed_command(traj, traj.throttle, idx, c.throttle_delay_s),
        delayed_command(traj, traj.steering, idx, c.steering_delay_s),
    )


def predict(traj: Trajectory, starts: np.ndarray, horizon: int, setup: ModelSetup) -> np.ndarray:
    """Predicted [x, y, heading, speed] at steps 0..horizon from each start: shape (N, horizon+1, 4).

    Every start must have ``start + horizon`` inside its segment.
    """
    starts = np.asarray(starts, dtype=int)
    if np.any(starts + horizon >= traj.seg_end[starts]):
        raise ValueError("predict: a prediction window runs past the end of its segment")
    if setup.dynamic:
        return _predict_dynamic(traj, starts, horizon, setup)
    return _predict_kinematic(traj, starts, horizon, setup)


def _predict_kinematic(traj: Trajectory, starts: np.ndarray, horizon: int, setup: ModelSetup) -> np.ndarray:
    car = setup.car
    k = ModelCoefficients.from_params(car)
    lr, wheelbase, mass = car.geometry.lr_m, car.geometry.wheelbase_m, car.inertia.mass_kg
    n_sub = setup.substeps or 2
    h = traj.dt / n_sub
    out = np.empty((starts.size, horizon + 1, 4))
    x, y, th, v = traj.xs[starts], traj.ys[starts], traj.headings[starts], traj.speed[starts]
    out[:, 0] = np.stack([x, y, th, v], axis=-1)
    for j in range(horizon):
        idx = starts + j
        throttle, steering = inputs_at(traj, idx, car)
        delta = k.steering_gain * steering + k.steering_offset
        beta = np.arctan(lr / wheelbase * np.tan(delta))
        yaw_per_speed = np.sin(beta) / lr
        if setup.extra is not None:
            extra = setup.extra

            def rates(v_):
                dv, dth = extra.evaluate(v_, throttle, delta)
                return drive_force(v_, throttle, k, partials=False)[0] / mass + dv, v_ * yaw_per_speed + dth
        else:

            def rates(v_):
                return drive_force(v_, throttle, k, partials=False)[0] / mass, v_ * yaw_per_speed

        for _ in range(n_sub):
            # RK4 on (x, y, heading, speed); inputs constant over the sample.
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
    return out


def _measured_state(traj: Trajectory, idx: np.ndarray) -> np.ndarray:
    return np.stack([traj.xs[idx], traj.ys[idx], traj.headings[idx], traj.vx[idx], traj.vy[idx],
                     traj.yaw_rate[idx]], axis=-1)


def _predict_dynamic(traj: Trajectory, starts: np.ndarray, horizon: int, setup: ModelSetup) -> np.ndarray:
    car = setup.car
    k = ModelCoefficients.from_params(car)
    n_sub = setup.substeps or 2
    h = traj.dt / n_sub
    # Lateral velocity and yaw rate are not measured and their derivative estimates are poor under
    # fast steering, so they come from running the model over the preceding WARMUP_S from the
    # (smoothed) measured state; pose and forward speed are then reset to the measurements.
    warm = min(int(round(WARMUP_S / traj.dt)), int(np.min(starts - traj.seg_start[starts])))
    state = _measured_state(traj, starts - warm)
    for j in range(warm):
        state = _rk4_steps(state, traj, starts - warm + j, setup, k, h, n_sub)
    measured = _measured_state(traj, starts)
    state[:, :4] = measured[:, :4]
    out = np.empty((starts.size, horizon + 1, 4))

    def record(j: int) -> None:
        speed = np.hypot(state[:, 3], state[:, 4]) * np.sign(state[:, 3])
        out[:, j] = np.stack([state[:, 0], state[:, 1], state[:, 2], speed], axis=-1)

    record(0)
    for j in range(horizon):
        state = _rk4_steps(state, traj, starts + j, setup, k, h, n_sub)
        record(j + 1)
    return out


def _rk4_steps(state: np.ndarray, traj: Trajectory, idx: np.ndarray, setup: ModelSetup, k: ModelCoefficients,
               h: float, n_sub: int) -> np.ndarray:
    """Advance the dynamic model over sample idx (n_sub RK4 steps of h, inputs held)."""
    throttle, steering = inputs_at(traj, idx, setup.car)
    u = np.stack([throttle, steering], axis=-1)
    if setup.extra is not None:
        extra, delta = setup.extra, k.steering_gain * steering + k.steering_offset

        def f(s):
            xdot = derivative(s, u, k)
            dv, dth = extra.evaluate(s[:, 3], throttle, delta)
            xdot[:, 3] += dv
            xdot[:, 2] += dth
            return xdot
    else:

        def f(s):
            return derivative(s, u, k)

    for _ in range(n_sub):
        k1 = f(state)
        k2 = f(state + 0.5 * h * k1)
        k3 = f(state + 0.5 * h * k2)
        k4 = f(state + h * k3)
        state = state + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return state


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
