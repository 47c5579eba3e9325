"""Centre-line geometry by arc length: exact straight/arc chains and smooth splines through points.

Both classes evaluate the centre line at arc lengths ``s`` in ``[0, length]`` (metres); wrapping on
closed tracks and extrapolation past the ends of open tracks are done by :class:`tracks.Track`.
All methods are vectorised over ``s``.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicHermiteSpline, make_interp_spline


def wrap_angle(angle):
    """Wrap angles (rad) to the interval (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(angle, dtype=float), 2.0 * np.pi)


@dataclass(frozen=True)
class CenterlineSample:
    """Centre-line values at a set of arc lengths (all arrays share the shape of ``s``)."""

    x: np.ndarray  # m
    y: np.ndarray  # m
    heading: np.ndarray  # rad, direction of travel, not wrapped (continuous within a piece)
    curvature: np.ndarray  # 1/m, positive = turning left
    curvature_derivative: np.ndarray  # 1/m^2, d(curvature)/ds


class SegmentCenterline:
    """Exact centre line made of straights and circular arcs chained from a start pose.

    ``start`` is (x m, y m, heading rad); ``lengths`` are segment arc lengths (m) and
    ``curvatures`` the constant signed curvature of each segment (1/m, 0 for straights).
    Curvature is piecewise constant, so d(curvature)/ds is 0 inside every segment; the jumps at
    segment joints are not represented (they are Dirac impulses).
    """

    def __init__(self, start: tuple[float, float, float], lengths, curvatures):
        self.lengths = np.asarray(lengths, dtype=float)
        self.curvatures = np.asarray(curvatures, dtype=float)
        n = len(self.lengths)
        self.s_start = np.concatenate([[0.0], np.cumsum(self.lengths)[:-1]])
        self.length = float(np.sum(self.lengths))
        # Pose at the start of every segment (and the end pose of the chain).
        x0 = np.empty(n + 1)
        y0 = np.empty(n + 1)
        th0 = np.empty(n + 1)
        x0[0], y0[0], th0[0] = start
        for i in range(n):
            x, y, th = _advance(x0[i], y0[i], th0[i], self.curvatures[i], self.lengths[i])
            x0[i + 1], y0[i + 1], th0[i + 1] = x, y, th
        self.x0, self.y0, self.th0 = x0[:n], y0[:n], th0[:n]
        self.end_pose = (float(x0[n]), float(y0[n]), float(th0[n]))
        # For one arc length at a time (the planners' per-stage look-ups): numpy's per-call overhead
        # is ten times the bisection's.
        self._s_start_list = self.s_start.tolist()

    def _segment(self, s):
        """Index of the segment holding each arc length ``s``: the last start <= s, clamped to the chain
        (one arc length: an int, by bisection)."""
        if np.ndim(s) == 0:
            return min(max(bisect.bisect_right(self._s_start_list, float(s)) - 1, 0), len(self._s_start_list) - 1)
        return np.clip(np.searchsorted(self.s_start, s, side="right") - 1, 0, len(self.lengths) - 1)

    def evaluate(self, s) -> CenterlineSample:
        s = np.asarray(s, dtype=float)
        i = self._segment(s)
        sigma = s - self.s_start[i]
        k = self.curvatures[i]
        x, y, th = _advance(self.x0[i], self.y0[i], self.th0[i], k, sigma)
        return CenterlineSample(x, y, th, k.copy(), np.zeros_like(s))

    def curvature(self, s) -> np.ndarray:
        """``evaluate(s).curvature`` without the poses (the planners look curvature up every step)."""
        return self.curvatures[self._segment(s)]


def _advance(x0, y0, th0, k, sigma):
    """Pose after driving arc length ``sigma`` (m) at constant curvature ``k`` (1/m); vectorised."""
    k = np.asarray(k, dtype=float)
    sigma = np.asarray(sigma, dtype=float)
    th = th0 + k * sigma
    straight = np.abs(k) < 1e-12
    k_safe = np.where(straight, 1.0, k)
    dx = np.where(straight, sigma * np.cos(th0), (np.sin(th) - np.sin(th0)) / k_safe)
    dy = np.where(straight, sigma * np.sin(th0), (np.cos(th0) - np.cos(th)) / k_safe)
    return x0 + dx, y0 + dy, th


class SplineCenterline:
    """Smooth centre line: interpolating spline through points, reparametrised by arc length.

    Quintic (C4) so that curvature AND its derivative are continuous: with a cubic spline the
    curvature derivative jumps at every point. Closed tracks use a periodic spline (smooth across
    the start/finish seam); open tracks the default not-a-knot ends (lower degree when there are
    fewer than 6 points). The spline parameter is the cumulative chord length;
    arc length is integrated with 5-point Gauss-Legendre quadrature on a fine sub-grid and
    inverted with a cubic Hermite spline (du/ds = 1/|r'(u)| is known exactly), which keeps the
    arc-length error around 1e-9 m.
    """

    def __init__(self, points, closed: bool, widths):
        points = np.asarray(points, dtype=float)
        widths = np.asarray(widths, dtype=float)
        if closed:
            points = np.vstack([points, points[:1]])
            widths = np.concatenate([widths, widths[:1]])
        chord = np.hypot(*np.diff(points, axis=0).T)
        self.u_knots = np.concatenate([[0.0], np.cumsum(chord)])
        self.widths_at_knots = widths
        degree = 5 if len(points) >= 6 else (3 if len(points) >= 4 else 2)
        self.spline = make_interp_spline(self.u_knots, points, k=degree, axis=0, bc_type="periodic" if closed else None)
        self.d1 = self.spline.derivative(1)
        self.d2 = self.spline.derivative(2)
        self.d3 = self.spline.derivative(3) if degree >= 3 else None

        # Fine parameter grid: every knot interval cut into equal sub-intervals.
        n_sub = max(8, int(np.ceil(8000 / len(chord))))
        frac = np.linspace(0.0, 1.0, n_sub + 1)[:-1]
        u_fine = np.concatenate([(self.u_knots[:-1, None] + np.outer(chord, frac)).ravel(), self.u_knots[-1:]])
        nodes, weights = np.polynomial.legendre.leggauss(5)
        a, b = u_fine[:-1], u_fine[1:]
        u_gauss = 0.5 * (a + b)[:, None] + 0.5 * (b - a)[:, None] * nodes[None, :]
        seg_len = 0.5 * (b - a) * (self._speed(u_gauss) @ weights)
        s_fine = np.concatenate([[0.0], np.cumsum(seg_len)])
        self.length = float(s_fine[-1])
        self.u_of_s = CubicHermiteSpline(s_fine, u_fine, 1.0 / self._speed(u_fine))

    def _speed(self, u):
        d = self.d1(u)
        return np.hypot(d[..., 0], d[..., 1])

    def parameter(self, s):
        """Spline parameter u (m of chord length) at arc length s (m)."""
        return np.clip(self.u_of_s(np.asarray(s, dtype=float)), 0.0, self.u_knots[-1])

    def curvature(self, s) -> np.ndarray:
        """``evaluate(s).curvature`` without the position and the curvature derivative."""
        u = self.parameter(s)
        r1, r2 = self.d1(u), self.d2(u)
        xp, yp = r1[..., 0], r1[..., 1]
        speed = np.sqrt(xp * xp + yp * yp)
        return (xp * r2[..., 1] - yp * r2[..., 0]) / speed**3

    def evaluate(self, s) -> CenterlineSample:
        u = self.parameter(s)
        p, r1, r2 = self.spline(u), self.d1(u), self.d2(u)
        r3 = self.d3(u) if self.d3 is not None else np.zeros_like(r2)
        xp, yp = r1[..., 0], r1[..., 1]
        xpp, ypp = r2[..., 0], r2[..., 1]
        xppp, yppp = r3[..., 0], r3[..., 1]
        speed2 = xp * xp + yp * yp
        speed = np.sqrt(speed2)
        cross = xp * ypp - yp * xpp
        kappa = cross / speed**3
        # d(kappa)/du by the quotient rule, then chain rule ds = |r'| du.
        dcross = xp * yppp - yp * xppp
        dkappa_du = (dcross * speed2 - 3.0 * cross * (xp * xpp + yp * ypp)) / speed**5
        return CenterlineSample(p[..., 0], p[..., 1], np.arctan2(yp, xp), kappa, dkappa_du / speed)

    def width(self, s):
        """Track width (m) at arc length s, linear between the given points."""
        return np.interp(self.parameter(s), self.u_knots, self.widths_at_knots)
