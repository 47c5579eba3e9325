"""The :class:`Track`: centre line by arc length, Frenet coordinates, boundaries and drivable area.

Units: metres, radians, 1/m for curvature, 1/m^2 for its derivative. Angles returned are wrapped
to (-pi, pi]. Every method is vectorised over its array arguments (numpy broadcasting) and returns
arrays of the broadcast shape (0-d numpy values for scalar inputs).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from .definition import (
    CLOSURE_TOLERANCE,
    ArcSegment,
    Arena,
    Lane,
    TrackDefinition,
    TrackFormatError,
)
from .geometry import CenterlineSample, SegmentCenterline, SplineCenterline, wrap_angle
from .tiles import tile_chain

# Closed segment chains must also end with the start heading, within this (rad, ~0.1 deg).
_CLOSURE_HEADING_TOLERANCE = math.radians(0.1)
# Newton projection onto the centre line stops when the arc-length update is below this (m).
_PROJECTION_TOLERANCE = 1e-11
_PROJECTION_MAX_ITERATIONS = 30
# The nearest-sample lookup table of to_frenet holds this many points at most (~50 MB with its tree).
MAX_LOOKUP_SAMPLES = 2_000_000


class Track:
    """Immutable track geometry built from a :class:`TrackDefinition` (see ``tracks.load_track``).

    Frenet coordinates: ``s`` is the arc length along the centre line from the start line (m),
    ``ey`` the signed lateral offset from the centre line (m, positive to the LEFT of the
    direction of travel) and ``epsi`` the heading relative to the centre line (rad).
    On closed tracks ``s`` is wrapped to ``[0, length)``. On open tracks ``s`` is not wrapped:
    outside ``[0, length]`` the centre line continues straight along the end tangents.
    """

    __slots__ = (
        "_definition",
        "_centerline",
        "_length",
        "_lookup_s",
        "_lookup_tree",
    )

    def __init__(self, definition: TrackDefinition, source: str = "<track>"):
        """Build the geometry and check it (closure, width vs. curvature, self-overlap, arena fit).

        Raises :class:`TrackFormatError` naming the field at fault.
        """
        self._definition = definition
        if definition.centerline is not None:
            widths = definition.width if isinstance(definition.width, tuple) else [definition.width] * len(
                definition.centerline
            )
            self._centerline = SplineCenterline(definition.centerline, definition.closed, widths)
        else:
            if definition.tiles is not None:
                start, segments = tile_chain(definition.tiles, source)
            else:
                assert definition.start is not None and definition.segments is not None
                start, segments = definition.start, definition.segments
            lengths = [seg.length for seg in segments]
            curvatures = [seg.curvature if isinstance(seg, ArcSegment) else 0.0 for seg in segments]
            self._centerline = SegmentCenterline(start, lengths, curvatures)
            if definition.closed:
                _check_segment_closure(self._centerline, start, source)
        self._length = float(self._centerline.length)

        # Dense lookup table: the nearest sample seeds the Newton projection in to_frenet.
        spacing = min(self._length / 256.0, self.min_width / 20.0)
        n = int(np.ceil(self._length / spacing))
        if n > MAX_LOOKUP_SAMPLES:  # a resource limit: the table would not fit in memory
            raise TrackFormatError("width", f"the track is {self._length:.6g} m long and {self.min_width:.6g} m wide: "
                                            f"{n} lookup samples, more than {MAX_LOOKUP_SAMPLES}", source)
        self._lookup_s = np.linspace(0.0, self._length, n, endpoint=not self.closed)
        self._lookup_tree = cKDTree(self.position(self._lookup_s))

        self._check_width_against_curvature(source)
        self._check_self_overlap(source)
        if definition.arena is not None:
            self._check_arena(definition.arena, source)

    # ----------------------------------------------------------------- properties
    @property
    def name(self) -> str:
        return self._definition.name

    @property
    def description(self) -> str:
        return self._definition.description

    @property
    def closed(self) -> bool:
        """True for a loop (s wraps at ``length``), False for an open road."""
        return self._definition.closed

    @property
    def length(self) -> float:
        """Centre-line length (m)."""
        return self._length

    @property
    def lanes(self) -> tuple[Lane, ...]:
        """Lanes declared in the file (may be empty); each has a centre offset ey (m) and a width (m)."""
        return self._definition.lanes

    @property
    def arena(self) -> Arena | None:
        """Rectangle the track must fit in (m, world frame), if the file declares one."""
        return self._definition.arena

    @property
    def definition(self) -> TrackDefinition:
        """The validated file contents this track was built from."""
        return self._definition

    @property
    def min_width(self) -> float:
        """Smallest track width (m)."""
        w = self._definition.width
        return float(min(w)) if isinstance(w, tuple) else float(w)

    @property
    def max_width(self) -> float:
        """Largest track width (m)."""
        w = self._definition.width
        return float(max(w)) if isinstance(w, tuple) else float(w)

    def lane(self, name: str) -> Lane:
        """The lane called ``name``; KeyError listing the lanes if there is none."""
        for lane in self.lanes:
            if lane.name == name:
                return lane
        raise KeyError(f"track {self.name!r} has no lane {name!r} (lanes: {[l.name for l in self.lanes]})")

    def __repr__(self) -> str:
        kind = "closed" if self.closed else "open"
        return f"Track({self.name!r}, {kind}, length={self._length:.4f} m, width={self.min_width:g}..{self.max_width:g} m)"

    # ------------------------------------------------------------ centre line
    def wrap_s(self, s):
        """Arc length (m) wrapped to [0, length) on closed tracks; unchanged on open tracks. One arc length
        in, one float out (the planners wrap single values every step: numpy's per-call overhead)."""
        if np.ndim(s) == 0:
            s = float(s)
            if not self.closed:
                return s
            wrapped = s % self._length
            return 0.0 if wrapped >= self._length else wrapped  # % gives `length` for tiny negative s
        s = np.asarray(s, dtype=float)
        if not self.closed:
            return s
        wrapped = np.mod(s, self._length)
        return np.where(wrapped >= self._length, 0.0, wrapped)  # as above

    def _sample(self, s) -> CenterlineSample:
        s = np.asarray(s, dtype=float)
        if self.closed:
            return self._centerline.evaluate(self.wrap_s(s))
        inside = np.clip(s, 0.0, self._length)
        c = self._centerline.evaluate(inside)
        beyond = s - inside  # straight extension past either end
        zero = np.zeros_like(s)
        return CenterlineSample(
            c.x + beyond * np.cos(c.heading),
            c.y + beyond * np.sin(c.heading),
            c.heading,
            np.where(beyond == 0.0, c.curvature, zero),
            np.where(beyond == 0.0, c.curvature_derivative, zero),
        )

    def position(self, s):
        """Centre-line point(s) (m) at arc length ``s`` (m): array of shape ``s.shape + (2,)``."""
        c = self._sample(s)
        return np.stack([c.x, c.y], axis=-1)

    def heading(self, s):
        """Centre-line direction of travel (rad, wrapped to (-pi, pi]) at arc length ``s`` (m)."""
        return wrap_angle(self._sample(s).heading)

    def curvature(self, s):
        """Signed centre-line curvature (1/m, positive = turning left) at arc length ``s`` (m).

        Segment tracks: at a joint between segments the value of the segment starting there is returned.
        """
        if self.closed:
            return self._centerline.curvature(self.wrap_s(s))
        s = np.asarray(s, dtype=float)
        inside = np.clip(s, 0.0, self._length)
        return np.where(s - inside == 0.0, self._centerline.curvature(inside), 0.0)  # 0 on the extensions (_sample)

    def curvature_derivative(self, s):
        """d(curvature)/ds (1/m^2) at arc length ``s`` (m); 0 inside straights/arcs of segment tracks."""
        return self._sample(s).curvature_derivative

    def width(self, s):
        """Full drivable width (m) at arc length ``s`` (m)."""
        s = np.asarray(s, dtype=float)
        if isinstance(self._centerline, SplineCenterline):
            inside = self.wrap_s(s) if self.closed else np.clip(s, 0.0, self._length)
            return self._centerline.width(inside)
        return np.full(s.shape, float(self._definition.width))

    # ------------------------------------------------------------ Frenet frame
    def to_frenet(self, x, y, heading=None):
        """World pose(s) -> Frenet coordinates ``(s, ey, epsi)``.

        ``x``, ``y`` in m (any broadcastable shapes); ``heading`` in rad or None. Returns ``s`` (m,
        wrapped to [0, length) on closed tracks), ``ey`` (m, positive left of the direction of
        travel) and ``epsi`` = heading - track heading wrapped to (-pi, pi] (None if ``heading`` is
        None). ``s`` is the foot of the perpendicular to the nearest centre-line point, found by
        Newton iterations seeded from a dense lookup table, so it is exact (to ~1e-11 m) for points
        within the track and continuous across the start/finish seam.
        """
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        shape = x.shape
        q = np.stack([x.ravel(), y.ravel()], axis=-1)
        if not np.all(np.isfinite(q)):
            raise ValueError("to_frenet: x and y must be finite")
        _, nearest = self._lookup_tree.query(q)
        s = self._lookup_s[nearest]
        active = np.arange(len(s))  # points still iterating
        for _ in range(_PROJECTION_MAX_ITERATIONS):
            c = self._sample(s[active])
            cos_h, sin_h = np.cos(c.heading), np.sin(c.heading)
            dx, dy = q[active, 0] - c.x, q[active, 1] - c.y
            along = dx * cos_h + dy * sin_h
            lateral = -dx * sin_h + dy * cos_h
            # Newton on f(s) = (q - p(s)) . t(s); f'(s) = -(1 - kappa * ey). The clamp keeps the
            # step sane for points beyond the centre of curvature (far outside any valid track).
            step = along / np.maximum(1.0 - c.curvature * lateral, 0.05)
            s[active] = self.wrap_s(s[active] + step)
            active = active[np.abs(step) >= _PROJECTION_TOLERANCE]
            if len(active) == 0:
                break
        c = self._sample(s)
        ey = -(q[:, 0] - c.x) * np.sin(c.heading) + (q[:, 1] - c.y) * np.cos(c.heading)
        s, ey = s.reshape(shape), ey.reshape(shape)
        if heading is None:
            return s, ey, None
        epsi = wrap_angle(np.asarray(heading, dtype=float) - c.heading.reshape(shape))
        return s, ey, epsi

    def to_cartesian(self, s, ey, epsi=None):
        """Frenet coordinates -> world ``(x, y)`` in m, or ``(x, y, heading)`` (rad, wrapped) if ``epsi`` is given."""
        s, ey = np.broadcast_arrays(np.asarray(s, dtype=float), np.asarray(ey, dtype=float))
        c = self._sample(s)
        x = c.x - ey * np.sin(c.heading)
        y = c.y + ey * np.cos(c.heading)
        if epsi is None:
            return x, y
        return x, y, wrap_angle(c.heading + np.asarray(epsi, dtype=float))

    def progress_difference(self, s_a, s_b):
        """Signed along-track distance ``s_a - s_b`` (m).

        On closed tracks the shortest way round, in [-length/2, length/2): e.g. 0.1 m past the
        line minus 0.1 m before it is +0.2 m. On open tracks the plain difference.
        """
        diff = np.asarray(s_a, dtype=float) - np.asarray(s_b, dtype=float)
        if not self.closed:
            return diff
        half = 0.5 * self._length
        return np.mod(diff + half, self._length) - half

    # ------------------------------------------------------------ surface
    def _s_grid(self, ds: float) -> np.ndarray:
        if not (isinstance(ds, (int, float)) and math.isfinite(ds) and ds > 0):
            raise ValueError(f"ds must be a positive number of metres, got {ds!r}")
        n = max(1, int(round(self._length / ds)))
        return np.linspace(0.0, self._length, n + 1)

    def boundaries(self, ds: float = 0.01):
        """Left and right track edges, each an (M, 2) array (m), sampled every ~``ds`` m of centre line.

        Points are the centre line offset by +-width/2 along the normal, in the direction of
        travel. Closed tracks: the first point is not repeated at the end (close the polygon
        yourself if needed). Open tracks: both end points are included.
        """
        s = self._s_grid(ds)
        if self.closed:
            s = s[:-1]
        half = 0.5 * self.width(s)
        c = self._sample(s)
        nx, ny = -np.sin(c.heading), np.cos(c.heading)
        left = np.stack([c.x + half * nx, c.y + half * ny], axis=-1)
        right = np.stack([c.x - half * nx, c.y - half * ny], axis=-1)
        return left, right

    def is_inside(self, x, y, margin: float = 0.0):
        """True where the point (m) is on the drivable surface with at least ``margin`` m to the edges.

        A negative margin enlarges the surface. Open tracks end at s = 0 and s = length.
        """
        s, ey, _ = self.to_frenet(x, y)
        return self.is_inside_frenet(s, ey, margin)

    def is_inside_frenet(self, s, ey, margin: float = 0.0):
        """``is_inside`` for points already in Frenet coordinates (s, ey from ``to_frenet``), for
        callers that project the points anyway (the simulator's checks: one projection per check)."""
        return self.limit_excess_frenet(s, ey) <= -margin

    def limit_excess_frenet(self, s, ey):
        """How far (m) points in Frenet coordinates are outside the drivable surface: > 0 outside, and
        inside minus the distance to the nearer edge (open tracks: to the nearer edge or end). A
        continuous measure, so callers can interpolate where a path crosses the track limit."""
        s, ey = np.asarray(s, dtype=float), np.asarray(ey, dtype=float)
        excess = np.abs(ey) - 0.5 * self.width(s)
        if not self.closed:
            excess = np.maximum(excess, np.maximum(-s, s - self._length) - 1e-12)
        return excess

    def curvature_table(self, ds: float):
        """Uniformly sampled curvature for table look-up: ``(s_grid, kappa)``, both (N+1,).

        ``s_grid`` runs from 0 to ``length`` inclusive in N = round(length/ds) equal steps (the
        spacing is length/N, the closest to ``ds`` that divides the track evenly); ``kappa`` is
        in 1/m. On closed tracks ``kappa[-1] == kappa[0]`` (the same point), so linear
        interpolation with index wrap-around needs no special case.
        """
        s = self._s_grid(ds)
        return s, self.curvature(s)

    # ------------------------------------------------------------ validation
    def _check_width_against_curvature(self, source: str) -> None:
        # The inner edge folds over itself where the turn radius is below half the width.
        s = np.linspace(0.0, self._length, max(2000, int(self._length / 0.005)))
        tightness = np.abs(self.curvature(s)) * 0.5 * self.width(s)
        worst = int(np.argmax(tightness))
        if tightness[worst] >= 1.0:
            radius = 1.0 / abs(float(self.curvature(s[worst])))
            raise TrackFormatError(
                "width",
                f"half width {0.5 * float(self.width(s[worst])):g} m is not below the centre-line turn "
                f"radius {radius:.4g} m at s = {s[worst]:.3f} m (the inner edge would fold over)",
                source,
            )

    def _check_self_overlap(self, source: str) -> None:
        # Two centre-line points closer than the track width but further apart along the track
        # than a half turn at the tightest allowed radius (pi * w/2) mean the surface overlaps itself.
        spacing = self.min_width / 10.0
        s = np.linspace(0.0, self._length, int(np.ceil(self._length / spacing)) + 1)
        if self.closed:
            s = s[:-1]
        points = self.position(s)
        pairs = cKDTree(points).query_pairs(self.max_width, output_type="ndarray")
        if len(pairs) == 0:
            return
        i, j = pairs[:, 0], pairs[:, 1]
        along = np.abs(self.progress_difference(s[i], s[j]))
        widths = 0.5 * (self.width(s[i]) + self.width(s[j]))
        dist = np.hypot(*(points[i] - points[j]).T)
        bad = (along > 0.5 * np.pi * widths + 2 * spacing) & (dist < widths * (1 - 1e-9))
        if np.any(bad):
            k = int(np.argmax(bad))
            field = ("centerline" if self._definition.centerline is not None
                     else "tiles.path" if self._definition.tiles is not None else "segments")
            raise TrackFormatError(
                field,
                f"track overlaps itself: centre line at s = {s[i[k]]:.3f} m and s = {s[j[k]]:.3f} m is only "
                f"{dist[k]:.3f} m apart, less than the width {widths[k]:g} m",
                source,
            )

    def _check_arena(self, arena: Arena, source: str) -> None:
        left, right = self.boundaries(ds=min(0.01, self._length / 1000))
        edges = np.vstack([left, right])
        lo, hi = edges.min(axis=0), edges.max(axis=0)
        tol = 1e-9
        if lo[0] < arena.x_min - tol or hi[0] > arena.x_max + tol or lo[1] < arena.y_min - tol or hi[1] > arena.y_max + tol:
            raise TrackFormatError(
                "arena",
                f"track surface spans x [{lo[0]:.3f}, {hi[0]:.3f}] m, y [{lo[1]:.3f}, {hi[1]:.3f}] m, outside the "
                f"arena x [{arena.x_min:g}, {arena.x_max:g}], y [{arena.y_min:g}, {arena.y_max:g}]",
                source,
            )


def _check_segment_closure(centerline: SegmentCenterline, start, source: str) -> None:
    x_end, y_end, th_end = centerline.end_pose
    gap = math.hypot(x_end - start[0], y_end - start[1])
    if gap > CLOSURE_TOLERANCE:
        raise TrackFormatError(
            "segments",
            f"closed track does not close: the chain ends at ({x_end:.4f}, {y_end:.4f}) m, {gap * 1000:.2f} mm "
            f"from the start (tolerance {CLOSURE_TOLERANCE * 1000:g} mm)",
            source,
        )
    heading_gap = abs(float(wrap_angle(th_end - start[2])))
    if heading_gap > _CLOSURE_HEADING_TOLERANCE:
        raise TrackFormatError(
            "segments",
            f"closed track does not close: it ends heading {math.degrees(heading_gap):.3f} deg away from the start heading",
            source,
        )
