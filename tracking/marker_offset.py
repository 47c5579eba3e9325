"""Where a car's marker is glued (the car file's ``marker.offset_forward_m``, ``offset_left_m``, ``yaw_rad``), from
slow circles driven in front of the camera (``python -m app measure-marker``; docs/tracking.md, "Measuring the
marker offset").

Driven slowly at a constant steering angle ``delta``, a car turns about one point fixed in its own frame: with
the kinematic bicycle (no tyre slip), ``c = (-lr, L / tan(delta))`` from the reference point (the CG, ``lr`` ahead
of the rear axle; ``L`` the wheelbase). Every point of the car, the marker's centre too, circles about it. The
marker's tracked poses (centre ``M``, heading ``psi``, tracked with no offset) give that centre (a circle fitted to
the marker's path) and, in the marker's frame, ``q = R(-psi) (c - M)`` (constant along the circle). The marker
frame is the car frame turned by ``yaw`` and moved by ``o``: ``R(yaw) q + o = c_body``. One circle leaves one
degree of freedom (turning the marker about the circle centre); circles at two or more steering angles (one left,
one right) fix ``o`` and ``yaw`` by a least-squares rigid fit (2-D Procrustes) of the ``q`` onto the ``c_body``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_STEERING_RAD = 0.05  # smaller angles circle too wide to fit in front of the camera
MIN_ARC_RAD = math.pi  # a circle is fitted from at least half a turn
MIN_POSES = 20


class MarkerOffsetError(ValueError):
    """The poses do not determine the marker offset (too few circles, too short an arc)."""


@dataclass(frozen=True)
class CircleFit:
    steering_rad: float
    poses: int
    centre: tuple[float, float]  # track frame, m
    radius_m: float  # of the marker's path
    rms_m: float  # the marker's distance from that circle
    arc_rad: float  # turned heading covered by the poses
    in_marker_frame: tuple[float, float]  # q: the circle centre seen from the marker (m)
    in_car_frame: tuple[float, float]  # c_body: where the kinematic bicycle puts it, seen from the reference point


@dataclass(frozen=True)
class MarkerOffset:
    offset_forward_m: float
    offset_left_m: float
    yaw_rad: float
    residual_m: float  # rms of R(yaw) q + o - c_body over the circles (0 with exactly two)
    circles: tuple[CircleFit, ...]


def fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Centre, radius and rms distance of points from the least-squares (algebraic, Kasa) circle."""
    a = np.column_stack([x, y, np.ones_like(x)])
    sol, *_ = np.linalg.lstsq(a, x ** 2 + y ** 2, rcond=None)
    centre = sol[:2] / 2
    radius = math.sqrt(max(sol[2] + centre @ centre, 0.0))
    rms = float(np.sqrt(np.mean((np.hypot(x - centre[0], y - centre[1]) - radius) ** 2)))
    return centre, radius, rms


def turning_centre(steering_rad: float, lf_m: float, lr_m: float) -> np.ndarray:
    """Body-frame (forward, left) turning centre of the reference point at a steady slow steering angle."""
    return np.array([-lr_m, (lf_m + lr_m) / math.tan(steering_rad)])


def circle_fit(steering_rad: float, x, y, heading, lf_m: float, lr_m: float) -> CircleFit:
    x, y, heading = (np.asarray(v, float) for v in (x, y, heading))
    centre, radius, rms = fit_circle(x, y)
    d = centre[None, :] - np.column_stack([x, y])
    c, s = np.cos(heading), np.sin(heading)
    q = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]]).mean(axis=0)
    turned = np.unwrap(heading)
    return CircleFit(float(steering_rad), len(x), (float(centre[0]), float(centre[1])), radius, rms,
                     float(turned.max() - turned.min()), (float(q[0]), float(q[1])),
                     tuple(float(v) for v in turning_centre(steering_rad, lf_m, lr_m)))


def marker_offset(circles: list[CircleFit]) -> MarkerOffset:
    """The marker's offset and yaw from circles at two or more steering angles (rigid 2-D fit)."""
    if len({round(c.steering_rad, 3) for c in circles}) < 2:
        raise MarkerOffsetError(f"circles at {len(circles)} steering angle(s); at least two different ones are needed "
                                "(drive one circle to the left and one to the right)")
    q = np.array([c.in_marker_frame for c in circles])
    b = np.array([c.in_car_frame for c in circles])
    qc, bc = q - q.mean(axis=0), b - b.mean(axis=0)
    yaw = math.atan2(float(np.sum(qc[:, 0] * bc[:, 1] - qc[:, 1] * bc[:, 0])), float(np.sum(qc * bc)))
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    o = b.mean(axis=0) - rot @ q.mean(axis=0)
    residual = float(np.sqrt(np.mean(np.sum((q @ rot.T + o - b) ** 2, axis=1))))
    return MarkerOffset(float(o[0]), float(o[1]), yaw, residual, tuple(circles))


def circles_from_poses(t, x, y, heading, steering, lf_m: float, lr_m: float,
                       steering_step_rad: float = 0.01) -> list[CircleFit]:
    """One circle per steady steering angle: poses grouped by their steering (rounded to ``steering_step_rad``),
    those below MIN_STEERING_RAD left out; a group needs MIN_POSES poses over at least MIN_ARC_RAD of heading.
    MarkerOffsetError names the groups that fall short."""
    t, x, y, heading, steering = (np.asarray(v, float) for v in (t, x, y, heading, steering))
    groups = np.round(steering / steering_step_rad) * steering_step_rad
    out, short = [], []
    for value in sorted(set(groups[np.abs(groups) >= MIN_STEERING_RAD].tolist())):
        pick = np.flatnonzero(groups == value)
        pick = pick[np.argsort(t[pick])]
        arc = float(np.ptp(np.unwrap(heading[pick]))) if len(pick) else 0.0
        if len(pick) < MIN_POSES or arc < MIN_ARC_RAD:
            short.append(f"steering {value:+.2f} rad: {len(pick)} poses over {math.degrees(arc):.0f} deg")
            continue
        out.append(circle_fit(float(np.mean(steering[pick])), x[pick], y[pick], heading[pick], lf_m, lr_m))
    if len(out) < 2:
        raise MarkerOffsetError(
            f"{len(out)} usable circle(s) (steering of at least {MIN_STEERING_RAD} rad, {MIN_POSES} poses, "
            f"{math.degrees(MIN_ARC_RAD):.0f} deg of turn each); two are needed, one left and one right"
            + (f"; too short: {'; '.join(short)}" if short else ""))
    return out
