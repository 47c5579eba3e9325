"""Constant-turn-rate-and-velocity (CTRV) car motion model and its analytic Jacobian, and the
same motion with a sideslip angle (the estimator's model).

State vector: ``[x, y, heading, speed, yaw_rate]`` (m, m, rad, m/s, rad/s) in the track frame;
with sideslip ``[x, y, heading, speed, yaw_rate, sideslip]``, where the car moves along
``heading + sideslip`` (rad; a cornering car's velocity is not along its heading).
The position update is written with ``sin(a)/a`` and ``(1 - cos(a))/a`` (``a = yaw_rate * dt``),
which are smooth at ``a = 0``; near zero their Taylor series are used, so straight-line motion
needs no special case and the Jacobian stays continuous.
"""
from __future__ import annotations

import numpy as np

STATE_NAMES = ("x", "y", "heading", "speed", "yaw_rate")
_SMALL_ANGLE = 1e-3


def _sinc_terms(a: float) -> tuple[float, float, float, float]:
    """``s1 = sin(a)/a``, ``c1 = (1-cos(a))/a`` and their derivatives with respect to ``a``."""
    if abs(a) < _SMALL_ANGLE:
        a2 = a * a
        s1 = 1.0 - a2 / 6.0 + a2 * a2 / 120.0
        c1 = a / 2.0 - a * a2 / 24.0 + a * a2 * a2 / 720.0
        ds1 = -a / 3.0 + a * a2 / 30.0
        dc1 = 0.5 - a2 / 8.0 + a2 * a2 / 144.0
        return s1, c1, ds1, dc1
    sa, ca = np.sin(a), np.cos(a)
    s1 = sa / a
    c1 = (1.0 - ca) / a
    ds1 = (a * ca - sa) / (a * a)
    dc1 = (a * sa - (1.0 - ca)) / (a * a)
    return s1, c1, ds1, dc1


def ctrv_transition(state: np.ndarray, dt: float) -> np.ndarray:
    """State after ``dt`` seconds of constant speed and yaw rate (exact for that motion)."""
    x, y, th, v, w = state
    s1, c1, _, _ = _sinc_terms(w * dt)
    ct, st = np.cos(th), np.sin(th)
    return np.array([
        x + v * dt * (ct * s1 - st * c1),
        y + v * dt * (st * s1 + ct * c1),
        th + w * dt,
        v,
        w,
    ])


def ctrv_jacobian(state: np.ndarray, dt: float) -> np.ndarray:
    """Analytic Jacobian d ctrv_transition / d state (5x5)."""
    _, _, th, v, w = state
    s1, c1, ds1, dc1 = _sinc_terms(w * dt)
    ct, st = np.cos(th), np.sin(th)
    jac = np.eye(5)
    jac[0, 2] = v * dt * (-st * s1 - ct * c1)
    jac[1, 2] = v * dt * (ct * s1 - st * c1)
    jac[0, 3] = dt * (ct * s1 - st * c1)
    jac[1, 3] = dt * (st * s1 + ct * c1)
    jac[0, 4] = v * dt * dt * (ct * ds1 - st * dc1)
    jac[1, 4] = v * dt * dt * (st * ds1 + ct * dc1)
    jac[2, 4] = dt
    return jac


def slip_transition(state: np.ndarray, dt: float) -> np.ndarray:
    """State after ``dt`` seconds of constant speed, yaw rate and sideslip: the position moves as
    CTRV along the course angle ``heading + sideslip``, which turns at the yaw rate like the heading."""
    x, y, th, v, w, beta = state
    moved = ctrv_transition(np.array([x, y, th + beta, v, w]), dt)
    return np.array([moved[0], moved[1], th + w * dt, v, w, beta])


def slip_jacobian(state: np.ndarray, dt: float) -> np.ndarray:
    """Analytic Jacobian d slip_transition / d state (6x6): the CTRV Jacobian at the course angle,
    whose column for the angle applies to heading and sideslip alike."""
    x, y, th, v, w, beta = state
    ctrv = ctrv_jacobian(np.array([x, y, th + beta, v, w]), dt)
    jac = np.eye(6)
    jac[:2, :5] = ctrv[:2]
    jac[:2, 5] = ctrv[:2, 2]
    jac[2, 4] = dt
    return jac
