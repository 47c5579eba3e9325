"""Dynamic bicycle model with a simplified Pacejka tyre and a DC-motor/drag drive model.

State ``[x, y, heading, vx, vy, yaw_rate]`` (world position of the centre of gravity, heading
in rad, body-frame velocities at the CG, yaw rate), input ``[throttle, steering]`` (throttle
-1..1, steering command in rad). Everything is vectorised: ``state`` has shape (..., 6), ``u``
(..., 2), and the coefficients broadcast against the leading dimensions (one value, or one per
car along the last leading axis). Equations and the low-speed blend: docs/vehicles.md.

The model applies the static part of ``CarParams.corrections`` (steering gain/offset, extra drag,
grip scale); actuation delays, actuator limits and rate limits are not part of ``f`` (the
simulator and the planner handle them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Sequence

import numpy as np

from vehicles.params import GRAVITY_MPS2, CarParams

# The equations are written once against this small set of functions, so they run either on
# numpy arrays (batches, Jacobians) or on plain floats: for a handful of cars, float math avoids
# numpy's per-call overhead and is several times faster in the simulator's 1 kHz loop.
_FLOAT_MATH = SimpleNamespace(
    arctan=math.atan, sin=math.sin, cos=math.cos, tan=math.tan, tanh=math.tanh, sqrt=math.sqrt,
    abs=abs, maximum=max, minimum=min,
)

STATE_DIM = 6
INPUT_DIM = 2
IX, IY, IHEADING, IVX, IVY, IYAW_RATE = range(STATE_DIM)
ITHROTTLE, ISTEERING = range(INPUT_DIM)


@dataclass(frozen=True)
class ModelCoefficients:
    """Flat numeric coefficients of the model; each is a float or an array (one per car)."""

    mass: np.ndarray
    yaw_inertia: np.ndarray
    lf: np.ndarray
    lr: np.ndarray
    front_b: np.ndarray
    front_c: np.ndarray
    front_peak_force: np.ndarray  # D * grip * static normal load [N]
    front_e: np.ndarray
    rear_b: np.ndarray
    rear_c: np.ndarray
    rear_peak_force: np.ndarray
    rear_e: np.ndarray
    motor_force: np.ndarray
    motor_speed_loss: np.ndarray
    rolling_resistance: np.ndarray
    drag: np.ndarray
    rolling_smoothing_speed: np.ndarray
    throttle_smoothing: np.ndarray
    steering_gain: np.ndarray
    steering_offset: np.ndarray
    blend_low: np.ndarray
    blend_high: np.ndarray
    relax_time: np.ndarray
    # Speed set-point cars (CarParams.speed_control); speed_gain 0: a throttle car.
    speed_gain: np.ndarray = 0.0
    speed_setpoint_gain: np.ndarray = 1.0
    speed_max_accel: np.ndarray = 1.0
    speed_max_decel: np.ndarray = 1.0
    # Throttle map of a throttle car (corrections): gain, dead band and curvature.
    throttle_gain: np.ndarray = 1.0
    throttle_dead_band: np.ndarray = 0.0
    throttle_curvature: np.ndarray = 0.0

    @classmethod
    def from_params(
        cls,
        params: CarParams | Sequence[CarParams],
        *,
        steering_gain_scale: float | Sequence[float] = 1.0,
        steering_offset_add: float | Sequence[float] = 0.0,
        extra_drag_add: float | Sequence[float] = 0.0,
        grip_scale: float | Sequence[float] = 1.0,
    ) -> "ModelCoefficients":
        """Coefficients for one car (floats) or a list of cars (arrays of shape (n,)).

        The keyword arguments stack further deviations on top of ``params.corrections``
        (the simulator passes its hidden effects through them).
        """
        single = isinstance(params, CarParams)
        plist = [params] if single else list(params)
        if not plist:
            raise ValueError("params: need at least one CarParams")

        def arr(values: list[float]) -> np.ndarray:
            return np.asarray(values, dtype=float)

        def per_car(v: float | Sequence[float], what: str) -> np.ndarray:
            a = np.broadcast_to(np.asarray(v, dtype=float), (len(plist),))
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{what}: must be finite")
            return a

        grip = arr([p.corrections.tire_grip_scale for p in plist]) * per_car(grip_scale, "grip_scale")
        mass = arr([p.inertia.mass_kg for p in plist])
        lf = arr([p.geometry.lf_m for p in plist])
        lr = arr([p.geometry.lr_m for p in plist])
        weight = mass * GRAVITY_MPS2
        # Static axle loads: the CG splits the weight in inverse proportion to the axle distances.
        front_load = weight * lr / (lf + lr)
        rear_load = weight * lf / (lf + lr)
        values = dict(
            mass=mass,
            yaw_inertia=arr([p.inertia.yaw_inertia_kgm2 for p in plist]),
            lf=lf,
            lr=lr,
            front_b=arr([p.front_tire.b for p in plist]),
            front_c=arr([p.front_tire.c for p in plist]),
            front_peak_force=arr([p.front_tire.d for p in plist]) * grip * front_load,
            front_e=arr([p.front_tire.e for p in plist]),
            rear_b=arr([p.rear_tire.b for p in plist]),
            rear_c=arr([p.rear_tire.c for p in plist]),
            rear_peak_force=arr([p.rear_tire.d for p in plist]) * grip * rear_load,
            rear_e=arr([p.rear_tire.e for p in plist]),
            motor_force=arr([p.longitudinal.motor_force_n for p in plist]),
            motor_speed_loss=arr([p.longitudinal.motor_speed_loss_n_per_mps for p in plist]),
            rolling_resistance=arr([p.longitudinal.rolling_resistance_n for p in plist]),
            drag=arr([p.longitudinal.drag_n_per_mps2 + p.corrections.extra_drag_n_per_mps2 for p in plist])
            + per_car(extra_drag_add, "extra_drag_add"),
            rolling_smoothing_speed=arr([p.longitudinal.rolling_smoothing_speed_mps for p in plist]),
            throttle_smoothing=arr([p.longitudinal.throttle_smoothing for p in plist]),
            steering_gain=arr([p.corrections.steering_gain for p in plist])
            * per_car(steering_gain_scale, "steering_gain_scale"),
            steering_offset=arr([p.corrections.steering_offset_rad for p in plist])
            + per_car(steering_offset_add, "steering_offset_add"),
            blend_low=arr([p.model.blend_speed_low_mps for p in plist]),
            blend_high=arr([p.model.blend_speed_high_mps for p in plist]),
            relax_time=arr([p.model.kinematic_relax_time_s for p in plist]),
            speed_gain=arr([p.speed_control.gain_per_s * p.corrections.speed_response_scale for p in plist]),
            speed_setpoint_gain=arr([p.corrections.speed_setpoint_gain for p in plist]),
            speed_max_accel=arr([p.speed_control.max_accel_mps2 for p in plist]),
            speed_max_decel=arr([p.speed_control.max_decel_mps2 for p in plist]),
            throttle_gain=arr([p.corrections.throttle_gain for p in plist]),
            throttle_dead_band=arr([p.corrections.throttle_dead_band for p in plist]),
            throttle_curvature=arr([p.corrections.throttle_curvature for p in plist]),
        )
        if np.any(values["drag"] < 0):
            raise ValueError("drag: total drag coefficient (nominal + corrections + extra) must be >= 0")
        if single:
            values = {k: float(v[0]) for k, v in values.items()}
        return cls(**values)

    @property
    def wheelbase(self) -> np.ndarray:
        return self.lf + self.lr


def as_coefficients(params: CarParams | Sequence[CarParams] | ModelCoefficients) -> ModelCoefficients:
    if isinstance(params, ModelCoefficients):
        return params
    return ModelCoefficients.from_params(params)


def _cos_sin(x, xp):
    """(cos x, sin x). For numpy arrays from tan(x/2) (cos = (1 - t^2)/(1 + t^2), sin = 2t/(1 + t^2)): numpy's
    float64 tan is vectorised where its sin and cos are not, and this is ~2x faster than both (within
    1 ulp of np.cos/np.sin, also near the poles of tan(x/2), where t is large but finite)."""
    if xp is not np:
        return xp.cos(x), xp.sin(x)
    t = np.tan(0.5 * x)
    t2 = t * t
    inv = 1.0 / (1.0 + t2)
    return (1.0 - t2) * inv, 2.0 * t * inv


def _is_zero(value) -> bool:
    """True for a coefficient that is one plain zero (not an array of per-car values)."""
    return isinstance(value, (float, int)) and value == 0.0


def pacejka(slip, b, c, peak, e, xp=np, slope: bool = True):
    """Lateral force and its slope dF/dslip (None if not asked) of the simplified magic formula."""
    bs = b * slip
    # E = 0 (the BuzzRacer tyres) leaves phi = bs exactly; skipping the arctan saves a third of the time.
    phi = bs if _is_zero(e) else bs - e * (bs - xp.arctan(bs))
    angle = c * xp.arctan(phi)
    if not slope:
        if xp is np:  # sin from tan(angle/2) as in _cos_sin; |angle| < C pi/2 keeps it well-conditioned
            t = np.tan(0.5 * angle)
            return peak * (2.0 * t / (1.0 + t * t)), None
        return peak * xp.sin(angle), None
    cos_a, sin_a = _cos_sin(angle, xp)
    force = peak * sin_a
    dphi = b - e * (b - b / (1.0 + bs * bs))
    slope = peak * cos_a * c / (1.0 + phi * phi) * dphi
    return force, slope


class _Inputs:
    """Quantities of the input alone (constant while the input is held, e.g. over an RK4 step)."""

    __slots__ = ("throttle", "delta", "cos_d", "sin_d", "tan_d", "root", "abs_u", "motor", "map_slope")


def input_terms(throttle, steering, k: ModelCoefficients, xp=np) -> _Inputs:
    """The input-only part of f: wheel angle and its trigonometry, smoothed |throttle|, motor force.

    Computed once per held input and passed to :func:`body_rates` for each RK4 stage."""
    i = _Inputs()
    i.delta = delta = k.steering_gain * steering + k.steering_offset
    if xp is np:
        i.cos_d, i.sin_d = _cos_sin(delta, xp)
        i.tan_d = i.sin_d / i.cos_d
    else:
        i.cos_d, i.sin_d, i.tan_d = xp.cos(delta), xp.sin(delta), xp.tan(delta)
    return _throttle_terms(i, throttle, k, xp)


def _throttle_terms(i: _Inputs, throttle, k: ModelCoefficients, xp) -> _Inputs:
    """Fill the throttle part of ``i``: the throttle, smoothed |throttle| (root, abs_u) and the motor force."""
    eps = k.throttle_smoothing
    i.map_slope = 1.0
    if not (_is_one(k.throttle_gain) and _is_zero(k.throttle_dead_band) and _is_zero(k.throttle_curvature)):
        throttle, i.map_slope = throttle_map(throttle, k, xp)
    i.throttle = throttle
    i.root = xp.sqrt(throttle * throttle + eps * eps)
    i.abs_u = i.root - eps
    i.motor = k.motor_force * throttle
    return i


def _is_one(value) -> bool:
    return isinstance(value, (float, int)) and value == 1.0


def throttle_map(throttle, k: ModelCoefficients, xp=np):
    """The throttle the motor sees for a commanded throttle u (corrections.throttle_gain g, throttle_dead_band b,
    throttle_curvature c): g * sign(u) * x (1 + c (x - 1)) with x = max(|u| - b, 0), and its slope d/du. The shape
    keeps x = 0 and x = 1 in place and is monotonic for |c| <= 1: c > 0 a progressive map, c < 0 a degressive one."""
    over = xp.maximum(xp.abs(throttle) - k.throttle_dead_band, 0.0)
    sign = (throttle > 0) * 1.0 - (throttle < 0) * 1.0
    c = k.throttle_curvature
    shape = over * (1.0 + c * (over - 1.0))
    return k.throttle_gain * sign * shape, k.throttle_gain * (1.0 - c + 2.0 * c * over) * (over > 0)


def drive_force(vx, throttle, k: ModelCoefficients, xp=np, partials: bool = True):
    """Longitudinal force at the rear axle and its partials (dF/dvx, dF/dthrottle).

    F = Cm1*u - Cm2*vx*|u| - Cr0*tanh(vx/v_s) - Cd*vx*|vx|, with |u| smoothed so the
    force is differentiable at zero throttle.
    """
    return _drive_force(vx, _throttle_terms(_Inputs(), throttle, k, xp), k, xp, partials)


def _drive_force(vx, i: _Inputs, k: ModelCoefficients, xp, partials: bool):
    if _is_zero(k.speed_gain):
        return _motor_force(vx, i, k, xp, partials)
    if isinstance(k.speed_gain, float) or bool(np.all(k.speed_gain > 0)):
        return _speed_loop_force(vx, i, k, xp, partials)
    # A batch of throttle and speed set-point cars: each its own law.
    speed_car = k.speed_gain > 0
    a, b = _motor_force(vx, i, k, xp, partials), _speed_loop_force(vx, i, k, xp, partials)
    return tuple(None if x is None else np.where(speed_car, y, x) for x, y in zip(a, b))


def _speed_loop_force(vx, i: _Inputs, k: ModelCoefficients, xp, partials: bool):
    """Speed set-point car (the throttle input is the set-point, m/s): m * clip(g (s u - vx), -dec, acc)."""
    want = k.speed_gain * (k.speed_setpoint_gain * i.throttle - vx)
    accel = xp.minimum(xp.maximum(want, -k.speed_max_decel), k.speed_max_accel)
    force = k.mass * accel
    if not partials:
        return force, None, None
    inside = (want > -k.speed_max_decel) * (want < k.speed_max_accel) * 1.0
    return force, -k.mass * k.speed_gain * inside, k.mass * k.speed_gain * k.speed_setpoint_gain * inside


def _motor_force(vx, i: _Inputs, k: ModelCoefficients, xp, partials: bool):
    tanh_v = xp.tanh(vx / k.rolling_smoothing_speed)
    abs_vx = xp.abs(vx)
    force = (
        i.motor
        - k.motor_speed_loss * vx * i.abs_u
        - k.rolling_resistance * tanh_v
        - k.drag * vx * abs_vx
    )
    if not partials:
        return force, None, None
    d_vx = (
        -k.motor_speed_loss * i.abs_u
        - k.rolling_resistance / k.rolling_smoothing_speed * (1.0 - tanh_v * tanh_v)
        - 2.0 * k.drag * abs_vx
    )
    d_u = (k.motor_force - k.motor_speed_loss * vx * i.throttle / i.root) * i.map_slope
    return force, d_vx, d_u


def _blend_weight(vx, k: ModelCoefficients, xp=np, slope: bool = True):
    """Smoothstep weight of the dynamic model (0 below blend_low, 1 above blend_high) and its slope."""
    width = k.blend_high - k.blend_low
    z = xp.minimum(xp.maximum((vx - k.blend_low) / width, 0.0), 1.0)
    return z * z * (3.0 - 2.0 * z), (6.0 * z * (1.0 - z) / width if slope else None)


def _check_shapes(state: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    state = np.asarray(state, dtype=float)
    u = np.asarray(u, dtype=float)
    if state.shape[-1:] != (STATE_DIM,):
        raise ValueError(f"state: last dimension must be {STATE_DIM}, got shape {state.shape}")
    if u.shape[-1:] != (INPUT_DIM,):
        raise ValueError(f"u: last dimension must be {INPUT_DIM}, got shape {u.shape}")
    return state, u


class _Terms(SimpleNamespace):
    """Intermediate quantities shared by the derivative and the Jacobians."""


def _terms(vx, vy, r, i: _Inputs, k: ModelCoefficients, xp, slopes: bool, kinematic: bool = True) -> _Terms:
    """Dynamic and (if ``kinematic``) kinematic parts of the vx, vy, yaw-rate rates, and the blend weight."""
    t = _Terms()
    m, iz, lf, lr = k.mass, k.yaw_inertia, k.lf, k.lr
    cos_d, sin_d = i.cos_d, i.sin_d

    t.fx, t.fx_vx, t.fx_u = _drive_force(vx, i, k, xp, slopes)

    # Dynamic part. Below blend_low its weight is zero, so clamping vx there only keeps it finite.
    t.vxs = xp.maximum(vx, k.blend_low)
    t.a_f = (vy + lf * r) / t.vxs
    t.a_r = (vy - lr * r) / t.vxs
    slip_f = i.delta - xp.arctan(t.a_f)
    slip_r = -xp.arctan(t.a_r)
    t.fy_f, t.fy_f_slope = pacejka(slip_f, k.front_b, k.front_c, k.front_peak_force, k.front_e, xp, slopes)
    t.fy_r, t.fy_r_slope = pacejka(slip_r, k.rear_b, k.rear_c, k.rear_peak_force, k.rear_e, xp, slopes)
    t.dyn_vx = (t.fx - t.fy_f * sin_d) / m + vy * r
    t.dyn_vy = (t.fy_r + t.fy_f * cos_d) / m - vx * r
    t.dyn_r = (lf * t.fy_f * cos_d - lr * t.fy_r) / iz
    if not kinematic:
        return t

    # Kinematic part: vx from the drive force alone; vy and r relax to the no-slip values.
    r_kin = vx * i.tan_d / (lf + lr)
    t.kin_vx = t.fx / m
    t.kin_vy = (lr * r_kin - vy) / k.relax_time
    t.kin_r = (r_kin - r) / k.relax_time
    t.w, t.dw = _blend_weight(vx, k, xp, slopes)
    return t


def pose_rates(heading, vx, vy, r, xp=np):
    """World-frame velocity of the CG and the heading rate."""
    cos_h, sin_h = _cos_sin(heading, np) if xp is np else (xp.cos(heading), xp.sin(heading))
    return vx * cos_h - vy * sin_h, vx * sin_h + vy * cos_h, r


def body_rates(vx, vy, r, i: _Inputs, k: ModelCoefficients):
    """Rates of (vx, vy, yaw rate) for numpy batches, no Jacobians: the hot path of batched rollouts
    (sysid). Where every sample is above blend_high the blend weight is 1 and the kinematic part is
    skipped; otherwise the same blend as :func:`derivative`."""
    all_dynamic = bool(np.all(vx >= k.blend_high))
    t = _terms(vx, vy, r, i, k, np, False, kinematic=not all_dynamic)
    if all_dynamic:
        return t.dyn_vx, t.dyn_vy, t.dyn_r
    return _blended(t)


def _blended(t: _Terms):
    """Rates of (vx, vy, yaw rate): written as kin + w*(dyn - kin), the blend with fewer operations."""
    w = t.w
    return t.kin_vx + w * (t.dyn_vx - t.kin_vx), t.kin_vy + w * (t.dyn_vy - t.kin_vy), t.kin_r + w * (t.dyn_r - t.kin_r)


def derivative_one(state: Sequence[float], u: Sequence[float], k: ModelCoefficients) -> tuple[float, ...]:
    """f for one car with float coefficients (``ModelCoefficients.from_params(car)``), in plain
    float math: the same equations as :func:`derivative`, without numpy overhead."""
    _, _, heading, vx, vy, r = state
    t = _terms(vx, vy, r, input_terms(u[0], u[1], k, _FLOAT_MATH), k, _FLOAT_MATH, False)
    return (*pose_rates(heading, vx, vy, r, _FLOAT_MATH), *_blended(t))


def _evaluate(state, u, params, with_jacobians: bool):
    state, u = _check_shapes(state, u)
    k = as_coefficients(params)
    heading, vx, vy, r = state[..., IHEADING], state[..., IVX], state[..., IVY], state[..., IYAW_RATE]
    i = input_terms(u[..., ITHROTTLE], u[..., ISTEERING], k, np)
    t = _terms(vx, vy, r, i, k, np, with_jacobians)
    cos_d, sin_d, tan_d = i.cos_d, i.sin_d, i.tan_d
    m, iz, lf, lr = k.mass, k.yaw_inertia, k.lf, k.lr
    wheelbase, tau = lf + lr, k.relax_time
    fx_vx, fx_u, fy_f = t.fx_vx, t.fx_u, t.fy_f
    dyn_vx, dyn_vy, dyn_r, kin_vx, kin_vy, kin_r = t.dyn_vx, t.dyn_vy, t.dyn_r, t.kin_vx, t.kin_vy, t.kin_r
    vxs, a_f, a_r = t.vxs, t.a_f, t.a_r
    w, dw = t.w, t.dw
    xdot = np.empty(np.broadcast_shapes(state.shape, dyn_r.shape + (STATE_DIM,)))
    xdot[..., IX], xdot[..., IY], xdot[..., IHEADING] = pose_rates(heading, vx, vy, r)
    xdot[..., IVX], xdot[..., IVY], xdot[..., IYAW_RATE] = _blended(t)
    if not with_jacobians:
        return xdot

    shape = xdot.shape[:-1]
    A = np.zeros(shape + (STATE_DIM, STATE_DIM))
    B = np.zeros(shape + (STATE_DIM, INPUT_DIM))
    cos_h, sin_h = _cos_sin(heading, np)
    A[..., IX, IHEADING] = -vx * sin_h - vy * cos_h
    A[..., IX, IVX] = cos_h
    A[..., IX, IVY] = -sin_h
    A[..., IY, IHEADING] = vx * cos_h - vy * sin_h
    A[..., IY, IVX] = sin_h
    A[..., IY, IVY] = cos_h
    A[..., IHEADING, IYAW_RATE] = 1.0

    # Slip-angle partials (vx partial vanishes where vx is clamped).
    active = (vx > k.blend_low).astype(float)
    inv_f = 1.0 / (1.0 + a_f * a_f)
    inv_r = 1.0 / (1.0 + a_r * a_r)
    sf_vx, sf_vy, sf_r = inv_f * a_f / vxs * active, -inv_f / vxs, -inv_f * lf / vxs
    sr_vx, sr_vy, sr_r = inv_r * a_r / vxs * active, -inv_r / vxs, inv_r * lr / vxs
    gf, gr = t.fy_f_slope, t.fy_r_slope

    # Partials of the dynamic part: rows (vx, vy, r) x columns (vx, vy, r, throttle, delta).
    dvx = [(fx_vx - gf * sf_vx * sin_d) / m, -gf * sf_vy * sin_d / m + r, -gf * sf_r * sin_d / m + vy,
           fx_u / m, (-gf * sin_d - fy_f * cos_d) / m]
    dvy = [(gr * sr_vx + gf * sf_vx * cos_d) / m - r, (gr * sr_vy + gf * sf_vy * cos_d) / m,
           (gr * sr_r + gf * sf_r * cos_d) / m - vx, 0.0, (gf * cos_d - fy_f * sin_d) / m]
    dr = [(lf * gf * sf_vx * cos_d - lr * gr * sr_vx) / iz, (lf * gf * sf_vy * cos_d - lr * gr * sr_vy) / iz,
          (lf * gf * sf_r * cos_d - lr * gr * sr_r) / iz, 0.0, lf * (gf * cos_d - fy_f * sin_d) / iz]
    # Kinematic part, same layout.
    sec2 = 1.0 + tan_d * tan_d
    kvx = [fx_vx / m, 0.0, 0.0, fx_u / m, 0.0]
    kvy = [lr * tan_d / (wheelbase * tau), -1.0 / tau, 0.0, 0.0, lr * vx * sec2 / (wheelbase * tau)]
    kr = [tan_d / (wheelbase * tau), 0.0, -1.0 / tau, 0.0, vx * sec2 / (wheelbase * tau)]

    for row, d_dyn, d_kin, dyn_val, kin_val in (
        (IVX, dvx, kvx, dyn_vx, kin_vx),
        (IVY, dvy, kvy, dyn_vy, kin_vy),
        (IYAW_RATE, dr, kr, dyn_r, kin_r),
    ):
        blended = [w * a + (1.0 - w) * b for a, b in zip(d_dyn, d_kin)]
        A[..., row, IVX] = blended[0] + dw * (dyn_val - kin_val)
        A[..., row, IVY] = blended[1]
        A[..., row, IYAW_RATE] = blended[2]
        B[..., row, ITHROTTLE] = blended[3]
        B[..., row, ISTEERING] = blended[4] * k.steering_gain
    return xdot, A, B


def derivative(state, u, params: CarParams | Sequence[CarParams] | ModelCoefficients) -> np.ndarray:
    """Continuous-time state derivative f(state, u), shape (..., 6)."""
    return _evaluate(state, u, params, with_jacobians=False)


f = derivative


def jacobians(state, u, params: CarParams | Sequence[CarParams] | ModelCoefficients):
    """Return (f, df/dstate (..., 6, 6), df/du (..., 6, 2)), all analytic."""
    return _evaluate(state, u, params, with_jacobians=True)

