"""Tests for tracks/: geometry against closed-form references, Frenet round trips, validation, laps."""
from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

import tracks
from sim.race import LapBookkeeper
from tracks import TrackFormatError, load_track, track_from_dict

RNG_SEED = 20240607


def wrap_reference(a):
    """(-pi, pi] wrap via complex numbers: independent of tracks.wrap_angle."""
    out = np.angle(np.exp(1j * np.asarray(a, dtype=float)))
    return np.where(np.isclose(out, -np.pi), np.pi, out)


# --------------------------------------------------------------------------- oval reference
# Analytic oval: centres of the turns at (1.5, 1.5) and (3.5, 1.5), radius 1, straights y = 0.5
# (eastbound, start line at x = 2.5) and y = 2.5 (westbound).
OVAL_L = 4.0 + 2.0 * math.pi
OVAL_BREAKS = [1.0, 1.0 + math.pi, 3.0 + math.pi, 3.0 + 2 * math.pi]


def oval_reference(s):
    """(x, y, heading, curvature) of the analytic oval centre line at s in [0, L)."""
    s = np.mod(np.asarray(s, dtype=float), OVAL_L)
    x, y, h, k = (np.empty_like(s) for _ in range(4))
    b1, b2, b3, b4 = OVAL_BREAKS
    m = s < b1
    x[m], y[m], h[m], k[m] = 2.5 + s[m], 0.5, 0.0, 0.0
    m = (s >= b1) & (s < b2)
    phi = -np.pi / 2 + (s[m] - b1)
    x[m], y[m], h[m], k[m] = 3.5 + np.cos(phi), 1.5 + np.sin(phi), phi + np.pi / 2, 1.0
    m = (s >= b2) & (s < b3)
    x[m], y[m], h[m], k[m] = 3.5 - (s[m] - b2), 2.5, np.pi, 0.0
    m = (s >= b3) & (s < b4)
    phi = np.pi / 2 + (s[m] - b3)
    x[m], y[m], h[m], k[m] = 1.5 + np.cos(phi), 1.5 + np.sin(phi), phi + np.pi / 2, 1.0
    m = s >= b4
    x[m], y[m], h[m], k[m] = 1.5 + (s[m] - b4), 0.5, 0.0, 0.0
    return x, y, wrap_reference(h), k


def oval_frenet_reference(x, y):
    """(s, ey) of points near the analytic oval, by region."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    s, ey = np.empty_like(x), np.empty_like(x)
    bottom = (x >= 1.5) & (x <= 3.5) & (y < 1.5)
    top = (x >= 1.5) & (x <= 3.5) & (y >= 1.5)
    right, left = x > 3.5, x < 1.5
    s[bottom], ey[bottom] = np.mod(x[bottom] - 2.5, OVAL_L), y[bottom] - 0.5
    s[top], ey[top] = OVAL_BREAKS[1] + (3.5 - x[top]), 2.5 - y[top]
    phi = np.arctan2(y[right] - 1.5, x[right] - 3.5)
    s[right], ey[right] = OVAL_BREAKS[0] + phi + np.pi / 2, 1.0 - np.hypot(x[right] - 3.5, y[right] - 1.5)
    phi = np.mod(np.arctan2(y[left] - 1.5, x[left] - 1.5), 2 * np.pi)
    s[left], ey[left] = OVAL_BREAKS[2] + phi - np.pi / 2, 1.0 - np.hypot(x[left] - 1.5, y[left] - 1.5)
    return s, ey


@pytest.fixture(scope="module")
def oval():
    return load_track("oval")


@pytest.fixture(scope="module")
def twisty():
    return load_track("twisty")


@pytest.fixture(scope="module")
def merge_road():
    return load_track("merge_road")


def seam_distance(a, b, length):
    d = np.mod(np.asarray(a) - np.asarray(b) + length / 2, length) - length / 2
    return np.abs(d)


# --------------------------------------------------------------------------- shipped tracks
def test_available_tracks_lists_shipped_files():
    names = tracks.available_tracks()
    assert {"oval", "twisty", "merge_road"} <= set(names)
    for name in names:
        assert load_track(name).name == name


def test_oval_length_is_two_straights_plus_circle(oval):
    assert oval.closed
    assert oval.length == pytest.approx(2 * 2.0 + 2 * math.pi * 1.0, rel=1e-12)


def test_oval_centerline_matches_analytic_geometry(oval):
    rng = np.random.default_rng(RNG_SEED)
    s = np.concatenate([rng.uniform(-2 * OVAL_L, 3 * OVAL_L, 500), [0.0, OVAL_L - 1e-9, -1e-12]])
    x, y, h, _ = oval_reference(s)
    np.testing.assert_allclose(oval.position(s), np.stack([x, y], -1), atol=1e-12)
    np.testing.assert_allclose(wrap_reference(oval.heading(s) - h), 0.0, atol=1e-12)
    assert np.all(oval.heading(s) <= np.pi) and np.all(oval.heading(s) > -np.pi)


def test_oval_curvature_is_inverse_radius_on_arcs_and_zero_on_straights(oval):
    b1, b2, b3, b4 = OVAL_BREAKS
    eps = 1e-6
    on_straights = np.concatenate([np.linspace(0, b1 - eps, 20), np.linspace(b2 + eps, b3 - eps, 20), np.linspace(b4 + eps, OVAL_L - eps, 20)])
    on_arcs = np.concatenate([np.linspace(b1 + eps, b2 - eps, 20), np.linspace(b3 + eps, b4 - eps, 20)])
    np.testing.assert_array_equal(oval.curvature(on_straights), 0.0)
    np.testing.assert_allclose(oval.curvature(on_arcs), 1.0 / 1.0, rtol=1e-12)
    np.testing.assert_array_equal(oval.curvature_derivative(np.concatenate([on_arcs, on_straights])), 0.0)
    # Curvature also agrees with the finite-difference rate of turn of the heading.
    h = 1e-5
    inner = on_arcs[(np.min(np.abs(on_arcs[:, None] - np.array(OVAL_BREAKS)), axis=1)) > 2 * h]
    dtheta = wrap_reference(oval.heading(inner + h) - oval.heading(inner - h)) / (2 * h)
    np.testing.assert_allclose(dtheta, oval.curvature(inner), atol=1e-6)


def test_oval_curvature_of_one_arc_length_matches_the_analytic_oval(oval):
    """The one-value look-up (the planners' per-stage path) against the analytic oval, over two laps,
    negative arc lengths, and at each joint and on either side of it."""
    eps = 1e-9
    s = np.concatenate([np.linspace(-OVAL_L, 2 * OVAL_L, 301), [b + d for b in OVAL_BREAKS for d in (-eps, eps)]])
    expected = oval_reference(s)[3]
    assert [float(oval.curvature(float(v))) for v in s] == pytest.approx(expected.tolist(), abs=1e-12)
    # At a joint the segment starting there holds (the documented convention), as for arrays.
    assert [float(oval.curvature(b)) for b in OVAL_BREAKS] == oval.curvature(np.array(OVAL_BREAKS)).tolist()


def test_oval_fits_arena_with_its_width(oval):
    assert oval.min_width == oval.max_width == 0.6
    left, right = oval.boundaries(0.005)
    pts = np.vstack([left, right])
    # Outer extent of the surface: 4 m + width by 2 m + width, centred in the 5 m x 3 m arena.
    np.testing.assert_allclose(pts.min(axis=0), [0.2, 0.2], atol=1e-4)
    np.testing.assert_allclose(pts.max(axis=0), [4.8, 2.8], atol=1e-4)
    assert oval.arena is not None and oval.arena.size == (5.0, 3.0)


def test_oval_counter_clockwise_with_start_line_on_straight(oval):
    assert oval.curvature(0.0) == 0.0 and oval.heading(0.0) == 0.0
    # Counter-clockwise: positive signed area (shoelace) of the centre line.
    p = oval.position(np.linspace(0, oval.length, 1000, endpoint=False))
    area = 0.5 * np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])
    assert area == pytest.approx(4.0 * 2.0 / 2 * 2 / 2 + math.pi, rel=1e-4)  # 2 m x 2 m box + unit circle


# --------------------------------------------------------------------------- Frenet frame
def test_oval_to_frenet_matches_analytic_projection(oval):
    rng = np.random.default_rng(RNG_SEED + 1)
    s_true = rng.uniform(0, OVAL_L, 2000)
    ey_true = rng.uniform(-0.3, 0.3, 2000)
    x_c, y_c, h_c, _ = oval_reference(s_true)
    # Points built from the analytic normal (left of travel), then compared with the region formulae.
    x = x_c - ey_true * np.sin(h_c)
    y = y_c + ey_true * np.cos(h_c)
    s_ref, ey_ref = oval_frenet_reference(x, y)
    heading = rng.uniform(-np.pi, np.pi, 2000)
    s, ey, epsi = oval.to_frenet(x, y, heading)
    assert np.max(seam_distance(s, s_ref, OVAL_L)) < 1e-9
    np.testing.assert_allclose(ey, ey_ref, atol=1e-9)
    np.testing.assert_allclose(ey, ey_true, atol=1e-9)
    np.testing.assert_allclose(epsi, wrap_reference(heading - h_c), atol=1e-9)
    assert np.all((s >= 0) & (s < OVAL_L))


def test_heading_error_wraps_to_half_open_pi_interval(oval):
    # On the bottom straight the track heading is 0; a car pointing west has epsi = pi, not -pi.
    _, _, epsi = oval.to_frenet([2.0, 2.0, 2.0, 2.0], [0.5, 0.5, 0.5, 0.5], [np.pi, -np.pi, 3 * np.pi / 2, 0.1])
    np.testing.assert_allclose(epsi, [np.pi, np.pi, -np.pi / 2, 0.1], atol=1e-12)
    # On the top straight (track heading pi) a car heading 0.1 rad has epsi = 0.1 - pi.
    _, _, epsi = oval.to_frenet(2.5, 2.5, 0.1)
    assert float(epsi) == pytest.approx(0.1 - np.pi)


@pytest.mark.parametrize("name", ["oval", "twisty"])
def test_frenet_round_trip_including_seam_and_edges(name):
    track = load_track(name)
    L, half = track.length, 0.5 * track.min_width
    rng = np.random.default_rng(RNG_SEED + 2)
    s = np.concatenate([
        rng.uniform(0, L, 3000),
        [0.0, 1e-9, 1e-4, L - 1e-4, L - 1e-9],  # around the start/finish seam
        rng.uniform(L - 0.05, L, 50), rng.uniform(0, 0.05, 50),
    ])
    ey = np.concatenate([rng.uniform(-half, half, 3000), np.tile([half, -half], 60)[: len(s) - 3000]])
    ey[::7] = half  # exactly on the edges too
    ey[1::7] = -half
    epsi = rng.uniform(-np.pi, np.pi, len(s))
    x, y, heading = track.to_cartesian(s, ey, epsi)
    s2, ey2, epsi2 = track.to_frenet(x, y, heading)
    assert np.max(seam_distance(s2, s, L)) < 1e-9
    np.testing.assert_allclose(ey2, ey, atol=1e-9)
    np.testing.assert_allclose(wrap_reference(epsi2 - epsi), 0.0, atol=1e-9)
    # And Cartesian -> Frenet -> Cartesian for random points on the surface.
    pts = rng.uniform([0, 0], [5, 3], size=(4000, 2))
    inside = track.is_inside(pts[:, 0], pts[:, 1])
    s3, ey3, _ = track.to_frenet(pts[inside, 0], pts[inside, 1])
    x3, y3 = track.to_cartesian(s3, ey3)
    np.testing.assert_allclose(np.stack([x3, y3], -1), pts[inside], atol=1e-9)


def test_frenet_projection_is_nearest_point_of_dense_centerline(twisty):
    # Independent reference: brute-force nearest point on a 0.5 mm polyline of the centre line.
    rng = np.random.default_rng(RNG_SEED + 3)
    s_dense = np.linspace(0, twisty.length, int(twisty.length / 5e-4), endpoint=False)
    c = twisty.position(s_dense)
    s_true = rng.uniform(0, twisty.length, 200)
    ey_true = rng.uniform(-0.25, 0.25, 200)
    x, y = twisty.to_cartesian(s_true, ey_true)
    d2 = (x[:, None] - c[None, :, 0]) ** 2 + (y[:, None] - c[None, :, 1]) ** 2
    nearest = np.argmin(d2, axis=1)
    s, ey, _ = twisty.to_frenet(x, y)
    assert np.max(seam_distance(s, s_dense[nearest], twisty.length)) < 1e-3
    # Distance to the polyline: project onto the two polyline pieces at the nearest vertex.
    q = np.stack([x, y], -1)
    dist = np.full(200, np.inf)
    for step in (-1, 1):
        a, b = c[nearest], c[(nearest + step) % len(c)]
        u = np.clip(np.sum((q - a) * (b - a), -1) / np.sum((b - a) ** 2, -1), 0, 1)
        dist = np.minimum(dist, np.hypot(*(q - a - u[:, None] * (b - a)).T))
    np.testing.assert_allclose(np.abs(ey), dist, atol=1e-6)


def test_frenet_shapes_and_scalars(oval):
    s, ey, epsi = oval.to_frenet(2.5, 0.6)
    assert np.ndim(s) == 0 and float(s) == pytest.approx(0.0) and float(ey) == pytest.approx(0.1) and epsi is None
    X, Y = np.meshgrid(np.linspace(2, 3, 4), np.linspace(0.3, 0.7, 3))
    s, ey, epsi = oval.to_frenet(X, Y, 0.0)
    assert s.shape == ey.shape == epsi.shape == (3, 4)
    assert oval.position(np.zeros((2, 5))).shape == (2, 5, 2)


def test_progress_difference_takes_shortest_way_round(oval, merge_road):
    L = oval.length
    assert float(oval.progress_difference(0.1, L - 0.1)) == pytest.approx(0.2)
    assert float(oval.progress_difference(L - 0.1, 0.1)) == pytest.approx(-0.2)
    assert float(oval.progress_difference(3.0, 1.0)) == pytest.approx(2.0)
    assert float(oval.progress_difference(1.0 + 0.75 * L, 1.0)) == pytest.approx(-0.25 * L)
    np.testing.assert_allclose(oval.progress_difference([0.5, 2 * L + 0.5], [0.0, 0.0]), [0.5, 0.5])
    assert float(merge_road.progress_difference(200.0, 10.0)) == 190.0


# --------------------------------------------------------------------------- surface
def test_oval_boundaries_at_half_width_on_correct_side(oval):
    left, right = oval.boundaries(0.01)
    assert left.shape == right.shape and left.shape[1] == 2
    assert len(left) == round(oval.length / 0.01)  # closed: the first point is not repeated
    _, ey_left = oval_frenet_reference(left[:, 0], left[:, 1])
    _, ey_right = oval_frenet_reference(right[:, 0], right[:, 1])
    np.testing.assert_allclose(ey_left, 0.3, atol=1e-12)
    np.testing.assert_allclose(ey_right, -0.3, atol=1e-12)
    # Counter-clockwise: the left edge is the inner one (radius 0.7 on the turns).
    assert np.min(np.hypot(left[:, 0] - 3.5, left[:, 1] - 1.5)[left[:, 0] > 3.5]) == pytest.approx(0.7)


def test_twisty_boundaries_at_half_width_from_dense_centerline(twisty):
    left, right = twisty.boundaries(0.02)
    c = twisty.position(np.linspace(0, twisty.length, 20000, endpoint=False))
    for edge in (left, right):
        d = np.sqrt(np.min((edge[:, None, 0] - c[None, :, 0]) ** 2 + (edge[:, None, 1] - c[None, :, 1]) ** 2, axis=1))
        np.testing.assert_allclose(d, 0.25, atol=2e-4)


def test_is_inside_known_points_oval(oval):
    pts = {
        (2.5, 0.5): True,  # on the centre line
        (2.5, 0.79): True,
        (2.5, 0.81): False,  # just past the inner edge of the bottom straight
        (2.5, 0.21): True,
        (2.5, 0.19): False,
        (2.5, 1.5): False,  # infield
        (0.21, 1.5): True,  # outer edge of the left turn is x = 0.2
        (0.19, 1.5): False,
        (4.1, 1.5): False,  # inside the inner edge (radius 0.7) of the right turn
        (4.25, 1.5): True,
        (3.5 + 1.3 * math.cos(0.3), 1.5 + 1.3 * math.sin(0.3) - 1e-6): True,
        (0.0, 0.0): False,
    }
    xy = np.array(list(pts))
    np.testing.assert_array_equal(oval.is_inside(xy[:, 0], xy[:, 1]), list(pts.values()))
    # Margins shrink (or, negative, grow) the surface.
    assert not oval.is_inside(2.5, 0.75, margin=0.1)
    assert oval.is_inside(2.5, 0.65, margin=0.1)
    assert oval.is_inside(2.5, 0.85, margin=-0.1)


def test_is_inside_matches_polygon_reference_on_twisty(twisty):
    # Reference: even-odd point-in-polygon on the two edge rings (matplotlib), no Frenet involved.
    from matplotlib.path import Path

    left, right = twisty.boundaries(0.004)
    rng = np.random.default_rng(RNG_SEED + 4)
    pts = rng.uniform([0, 0], [5, 3], size=(8000, 2))
    in_ring = Path(left).contains_points(pts) ^ Path(right).contains_points(pts)
    s, ey, _ = twisty.to_frenet(pts[:, 0], pts[:, 1])
    clear = np.abs(np.abs(ey) - 0.25) > 1e-4  # polygon chords deviate < 0.3e-4 m from the edges  # skip points within the polygon discretisation error
    np.testing.assert_array_equal(twisty.is_inside(pts[clear, 0], pts[clear, 1]), in_ring[clear])
    assert 0.2 < in_ring.mean() < 0.6


def test_curvature_table_uniform_grid(oval):
    s, kappa = oval.curvature_table(0.01)
    n = round(oval.length / 0.01)
    assert s.shape == kappa.shape == (n + 1,)
    np.testing.assert_allclose(np.diff(s), oval.length / n, rtol=1e-12)
    assert s[0] == 0.0 and s[-1] == pytest.approx(oval.length)
    assert kappa[-1] == kappa[0]
    _, _, _, k_ref = oval_reference(s[:-1])
    # Grid points exactly on a joint may take either side's value; all others must match.
    off_joint = np.min(np.abs(s[:-1, None] - np.array(OVAL_BREAKS)[None, :]), axis=1) > 1e-9
    np.testing.assert_array_equal(kappa[:-1][off_joint], k_ref[off_joint])
    with pytest.raises(ValueError, match="ds"):
        oval.curvature_table(0.0)


# --------------------------------------------------------------------------- twisty track
def _segments_intersect(a0, a1, b0, b1):
    """Proper intersection of segments a0-a1 and b0-b1 (broadcast arrays of 2-D points)."""

    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    d1, d2 = orient(b0, b1, a0), orient(b0, b1, a1)
    d3, d4 = orient(a0, a1, b0), orient(a0, a1, b1)
    return (d1 * d2 < 0) & (d3 * d4 < 0)


def test_twisty_is_not_self_intersecting(twisty):
    left, right = twisty.boundaries(0.02)
    rings = [np.vstack([left, left[:1]]), np.vstack([right, right[:1]]), np.vstack([twisty.position(np.linspace(0, twisty.length, 556))])]
    for ring in rings:
        a0, a1 = ring[:-1], ring[1:]
        hit = _segments_intersect(a0[:, None], a1[:, None], a0[None, :], a1[None, :])
        n = len(a0)
        i, j = np.nonzero(hit)
        adjacent = (np.abs(i - j) <= 1) | (np.abs(i - j) == n - 1)
        assert not np.any(~adjacent), "a track edge crosses itself"
    # The two edges never cross each other either.
    a0, a1, b0, b1 = rings[0][:-1], rings[0][1:], rings[1][:-1], rings[1][1:]
    assert not np.any(_segments_intersect(a0[:, None], a1[:, None], b0[None, :], b1[None, :]))
    # Neighbouring sections keep a gap: centre-line points more than a half-turn apart along the
    # track are at least one width + 0.25 m apart.
    s = np.linspace(0, twisty.length, 2000, endpoint=False)
    p = twisty.position(s)
    dist = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
    along = seam_distance(s[:, None], s[None, :], twisty.length)
    assert np.min(dist[along > math.pi * 0.4 + 0.05]) > 0.5 + 0.25


def test_twisty_fits_arena_and_is_drivable_by_a_1_28_car(twisty):
    assert twisty.closed and twisty.min_width >= 0.5
    left, right = twisty.boundaries(0.005)
    pts = np.vstack([left, right])
    assert np.all(pts >= [0.0, 0.0]) and np.all(pts <= [5.0, 3.0])
    s = np.linspace(0, twisty.length, 20000)
    assert np.max(np.abs(twisty.curvature(s))) <= 1 / 0.35
    # Heading turns exactly once round (counter-clockwise loop) and the chain closes.
    dtheta = wrap_reference(np.diff(twisty.heading(s)))
    assert np.sum(dtheta) == pytest.approx(2 * np.pi, abs=1e-9)
    np.testing.assert_allclose(twisty.position(twisty.length - 1e-12), twisty.position(0.0), atol=1e-6)


# --------------------------------------------------------------------------- merge road
def test_merge_road_lanes_and_frenet(merge_road):
    assert not merge_road.closed and merge_road.length == pytest.approx(220.0)
    assert merge_road.lane("main").offset == 1.1 and merge_road.lane("merge").offset == -1.1
    assert merge_road.lane("main").width == merge_road.lane("merge").width == 2.2
    assert merge_road.min_width == pytest.approx(4.4)
    with pytest.raises(KeyError, match="main"):
        merge_road.lane("shoulder")
    rng = np.random.default_rng(RNG_SEED + 5)
    x, y = rng.uniform(-30, 210, 500), rng.uniform(-3, 3, 500)
    s, ey, epsi = merge_road.to_frenet(x, y, 0.2)
    np.testing.assert_allclose(s, x + 20.0, atol=1e-9)  # open track: s continues past the ends
    np.testing.assert_allclose(ey, y, atol=1e-12)
    np.testing.assert_allclose(epsi, 0.2)
    inside = merge_road.is_inside(x, y)
    np.testing.assert_array_equal(inside, (x >= -20) & (x <= 200) & (np.abs(y) <= 2.2))
    px, py = merge_road.to_cartesian(50.0, merge_road.lane("merge").offset)
    assert (float(px), float(py)) == pytest.approx((30.0, -1.1))


# --------------------------------------------------------------------------- spline tracks
def circle_points(n, radius=1.0, centre=(0.0, 0.0)):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)], -1)


def test_spline_circle_matches_circle():
    track = track_from_dict({"name": "c", "closed": True, "width": 0.4, "centerline": circle_points(48).tolist()})
    assert track.length == pytest.approx(2 * np.pi, rel=1e-5)
    s = np.linspace(-1, 2 * track.length, 777)
    np.testing.assert_allclose(track.curvature(s), 1.0, atol=2e-3)
    np.testing.assert_allclose(np.hypot(*track.position(s).T), 1.0, atol=1e-5)
    pos = track.position(s)
    np.testing.assert_allclose(wrap_reference(track.heading(s) - (np.arctan2(pos[:, 1], pos[:, 0]) + np.pi / 2)), 0, atol=1e-4)
    r = np.random.default_rng(RNG_SEED + 6).uniform(0.8, 1.2, 100)
    a = np.random.default_rng(RNG_SEED + 7).uniform(-np.pi, np.pi, 100)
    _, ey, _ = track.to_frenet(r * np.cos(a), r * np.sin(a))
    np.testing.assert_allclose(ey, 1.0 - r, atol=1e-5)


def test_spline_derivatives_match_finite_differences_and_are_continuous_at_seam():
    # Ellipse with per-point widths: heading = d(position)/ds, curvature = d(heading)/ds,
    # curvature_derivative = d(curvature)/ds, all by central differences.
    a = np.linspace(0, 2 * np.pi, 30, endpoint=False)
    pts = np.stack([1.5 * np.cos(a), 1.0 * np.sin(a)], -1)
    widths = (0.4 + 0.1 * np.cos(a)).tolist()
    track = track_from_dict({"name": "e", "closed": True, "width": widths, "centerline": pts.tolist()})
    s = np.linspace(0, track.length, 200)
    h = 1e-4
    dp = (track.position(s + h) - track.position(s - h)) / (2 * h)
    np.testing.assert_allclose(np.hypot(*dp.T), 1.0, atol=1e-6)  # unit speed: s is arc length
    np.testing.assert_allclose(wrap_reference(np.arctan2(dp[:, 1], dp[:, 0]) - track.heading(s)), 0, atol=1e-6)
    np.testing.assert_allclose(wrap_reference(track.heading(s + h) - track.heading(s - h)) / (2 * h), track.curvature(s), atol=1e-5)
    np.testing.assert_allclose((track.curvature(s + h) - track.curvature(s - h)) / (2 * h), track.curvature_derivative(s), atol=1e-3)
    # Ellipse curvature range (analytic): 1/1.5^2*1.0 .. 1.5/1.0^2 (approximated by the spline).
    k = track.curvature(np.linspace(0, track.length, 5000))
    assert k.min() == pytest.approx(1.0 / 2.25, rel=2e-2) and k.max() == pytest.approx(1.5, rel=2e-2)
    for f in (track.position, track.heading, track.curvature, track.curvature_derivative, track.width):
        np.testing.assert_allclose(f(track.length - 1e-9), f(0.0), atol=1e-6)
    np.testing.assert_allclose(track.width(0.0), 0.5)
    left, right = track.boundaries(0.01)
    np.testing.assert_allclose(np.hypot(*(left - right).T), track.width(np.linspace(0, track.length, len(left) + 1)[:-1]), rtol=1e-9)


def test_closed_centerline_with_repeated_first_point_is_accepted():
    pts = circle_points(20).tolist()
    a = track_from_dict({"name": "c", "closed": True, "width": 0.4, "centerline": pts})
    b = track_from_dict({"name": "c", "closed": True, "width": 0.4, "centerline": pts + [pts[0]]})
    assert a.length == pytest.approx(b.length, rel=1e-12)


def test_open_spline_track_extends_straight_past_the_ends():
    x = np.linspace(0, 10, 11)
    track = track_from_dict({"name": "o", "closed": False, "width": 1.0, "centerline": np.stack([x, np.sin(x / 3)], -1).tolist()})
    p0, h0 = track.position(0.0), float(track.heading(0.0))
    np.testing.assert_allclose(track.position(-2.0), p0 - 2.0 * np.array([np.cos(h0), np.sin(h0)]), atol=1e-12)
    assert float(track.curvature(-2.0)) == 0.0
    np.testing.assert_allclose(track.position(track.length), [10, np.sin(10 / 3)], atol=1e-9)
    assert not track.is_inside(-0.5, 0.0) and track.is_inside(0.5, np.sin(0.5 / 3))


# --------------------------------------------------------------------------- lap counter
def test_lap_counter_with_jitter_and_backward_excursion(oval):
    L, v, dt = oval.length, 1.5, 0.01
    s0 = L - 0.5  # start half a metre behind the line
    t = np.arange(0, (3.3 * L) / v, dt)
    progress = s0 + v * t
    rng = np.random.default_rng(RNG_SEED + 8)
    noisy = progress + rng.uniform(-0.02, 0.02, len(t))
    # Around the second crossing the car backs up 0.3 m over the line and drives on again.
    k = np.searchsorted(progress, 2 * L + 0.1)
    noisy[k : k + 40] -= np.linspace(0, 0.4, 40)
    noisy[k + 40 : k + 80] -= np.linspace(0.4, 0, 40)
    book = LapBookkeeper(L, laps_to_win=3, initial_s=np.array([s0]))  # s0 > L/2: on the grid behind the line
    laps = [e for ti, si in zip(t, np.mod(noisy, L)) for e in book.update(ti, np.array([si])) if e.kind == "lap"]
    crossings = (np.arange(1, 5) * L - s0) / v  # analytic crossing times of the unperturbed car
    # The first crossing leaves the grid (lap 1 starts), each later one completes a lap, the back-and-forth
    # over the line at the second crossing is not counted twice.
    assert [e.lap for e in laps] == [1, 2, 3] and book.laps[0] == 3
    np.testing.assert_allclose([e.time for e in laps], crossings[1:], atol=0.02 / v + dt)
    np.testing.assert_allclose(book.lap_times[0], L / v, atol=2 * (0.02 / v + dt))
    assert book.winner == 0 and book.finish_times[0] == pytest.approx(crossings[3], abs=0.02 / v + dt)


def test_lap_counter_from_positions_with_start_time(oval):
    v, dt = 2.0, 0.02
    t = np.arange(0, 2.5 * oval.length / v, dt)
    x, y, _, _ = oval_reference(v * t)  # standing start on the line at t = 0
    s = oval.to_frenet(x, y)[0]
    book = LapBookkeeper(oval.length, laps_to_win=5, initial_s=s[:1], start_time=0.0)
    for ti, si in zip(t[1:], s[1:]):
        book.update(ti, np.array([si]))
    assert book.laps[0] == 2
    np.testing.assert_allclose(book.lap_times[0], oval.length / v, atol=1e-6)
    assert book.progress[0] == pytest.approx(v * t[-1], abs=1e-6)


def test_lap_counter_rejects_bad_track_length_and_lap_count():
    with pytest.raises(ValueError, match="track_length"):
        LapBookkeeper(0.0, 1, np.zeros(1))
    with pytest.raises(ValueError, match="laps_to_win"):
        LapBookkeeper(10.0, 0, np.zeros(1))


# --------------------------------------------------------------------------- validation
def valid_segment_track():
    return {
        "name": "square",
        "closed": True,
        "width": 0.4,
        "start": [0.0, 0.0, 0.0],
        "segments": [
            seg for _ in range(4) for seg in ({"type": "straight", "length": 1.0}, {"type": "arc", "radius": 0.5, "angle_deg": 90})
        ],
    }


def valid_point_track():
    return {"name": "circle", "closed": True, "width": 0.4, "centerline": circle_points(12).tolist()}


def _set(path, value):
    def mutate(d):
        target = d
        for key in path[:-1]:
            target = target[key]
        if value is _DELETE:
            del target[path[-1]]
        else:
            target[path[-1]] = value

    return mutate


_DELETE = object()

SEGMENT_CASES = [
    (_set(["name"], _DELETE), "name"),
    (_set(["name"], ""), "name"),
    (_set(["closed"], "yes"), "closed"),
    (_set(["closed"], _DELETE), "closed"),
    (_set(["width"], 0.0), "width"),
    (_set(["width"], -0.4), "width"),
    (_set(["width"], float("nan")), "width"),
    (_set(["width"], True), "width"),
    (_set(["width"], [0.4, 0.4]), "width"),
    (_set(["width"], _DELETE), "width"),
    (_set(["start"], [0.0, 0.0]), "start"),
    (_set(["start", 2], float("inf")), "start[2]"),
    (_set(["segments"], []), "segments"),
    (_set(["segments", 1, "radius"], -0.5), "segments[1].radius"),
    (_set(["segments", 1, "radius"], _DELETE), "segments[1].radius"),
    (_set(["segments", 3, "angle_deg"], 0), "segments[3].angle_deg"),
    (_set(["segments", 0, "length"], float("nan")), "segments[0].length"),
    (_set(["segments", 2, "type"], "spiral"), "segments[2].type"),
    (_set(["segments", 2, "lenght"], 1.0), "segments[2].lenght"),
    (_set(["segments", 0, "length"], 1.002), "segments"),  # chain misses the start by 2 mm
    (_set(["segments", 1, "angle_deg"], 90.5), "segments"),  # does not close (position and heading)
    (_set(["widht"], 0.4), "widht"),
    (_set(["centerline"], [[0, 0], [1, 0], [1, 1]]), "centerline"),  # both forms given
    (_set(["width"], 1.2), "width"),  # half width 0.6 > turn radius 0.5
    (_set(["lanes"], [{"name": "a", "offset": 0.15, "width": 0.2}]), "lanes[0].offset"),
    (_set(["lanes"], [{"name": "a", "offset": 0.1, "width": 0.2}, {"name": "a", "offset": -0.1, "width": 0.2}]), "lanes[1].name"),
    (_set(["arena"], {"x_min": -1, "x_max": 1, "y_min": -1, "y_max": 2}), "arena"),  # track spans x to 2.2
    (_set(["arena"], {"x_min": 1, "x_max": 0, "y_min": 0, "y_max": 1}), "arena.x_max"),
]


@pytest.mark.parametrize("mutate,field", SEGMENT_CASES)
def test_segment_track_validation_names_the_field(mutate, field):
    data = valid_segment_track()
    track_from_dict(copy.deepcopy(data))  # the unmodified definition is valid
    mutate(data)
    with pytest.raises(TrackFormatError) as info:
        track_from_dict(data)
    assert info.value.field == field
    assert field in str(info.value)


POINT_CASES = [
    (_set(["centerline"], [[0, 0], [1, 0]]), "centerline"),
    (_set(["centerline", 3], [1.0, float("nan")]), "centerline[3][1]"),
    (_set(["centerline", 4], [1.0]), "centerline[4]"),
    (_set(["centerline", 5], _DELETE), None),  # still valid: 11 points
    (_set(["width"], [0.4] * 11), "width"),
    (_set(["width"], [0.4] * 11 + [-0.1]), "width[11]"),
    (_set(["width"], 2.5), "width"),
    (_set(["start"], [0, 0, 0]), "centerline"),
]


@pytest.mark.parametrize("mutate,field", POINT_CASES)
def test_point_track_validation_names_the_field(mutate, field):
    data = valid_point_track()
    mutate(data)
    if field is None:
        track_from_dict(data)
        return
    with pytest.raises(TrackFormatError) as info:
        track_from_dict(data)
    assert info.value.field == field


def test_duplicate_point_and_self_overlap_are_rejected():
    data = valid_point_track()
    data["centerline"].insert(3, list(data["centerline"][2]))
    with pytest.raises(TrackFormatError, match=r"centerline\[3\]"):
        track_from_dict(data)
    # Figure-of-eight: the two lobes cross at the origin.
    a = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    eight = np.stack([2 * np.sin(a), np.sin(2 * a)], -1)
    with pytest.raises(TrackFormatError, match="overlaps itself") as info:
        track_from_dict({"name": "eight", "closed": True, "width": 0.3, "centerline": eight.tolist()})
    assert info.value.field == "centerline"
    # Two parallel straights 0.5 m apart cannot carry a 0.6 m wide track.
    hairpin = {
        "name": "h", "closed": False, "width": 0.6, "start": [0, 0, 0],
        "segments": [{"type": "straight", "length": 2}, {"type": "arc", "radius": 0.31, "angle_deg": 180}, {"type": "straight", "length": 2}],
    }
    track_from_dict(hairpin)  # 0.62 m apart: fine
    hairpin["segments"][1]["radius"] = 0.25
    hairpin["segments"].insert(1, {"type": "arc", "radius": 0.4, "angle_deg": -10})
    with pytest.raises(TrackFormatError):
        track_from_dict(hairpin)


def test_load_track_by_path_and_errors(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(valid_segment_track()))
    track = load_track(path)
    assert track.name == "square" and track.length == pytest.approx(4 + 4 * 0.5 * np.pi / 2)
    assert load_track(str(path)).length == track.length
    with pytest.raises(tracks.UnknownTrackError, match="oval"):
        load_track("no_such_track")
    with pytest.raises(TrackFormatError, match="missing.json: <file>: track file not found") as info:
        load_track(tmp_path / "missing.json")
    assert info.value.field == "<file>"
    bad = tmp_path / "bad.json"
    bad.write_text('{"name": "x",\n "closed": tru}')
    with pytest.raises(TrackFormatError, match="line 2") as info:
        load_track(bad)
    assert info.value.field == "<json>" and "bad.json" in str(info.value)


# --------------------------------------------------------------------------- plotting
def test_draw_track_fills_the_surface(oval, merge_road):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2)
    try:
        artists = tracks.draw_track(ax1, oval, surface_color="black", show_centerline=False, show_arena=False)
        ax1.set_xlim(0, 5)
        ax1.set_ylim(0, 3)
        fig.canvas.draw()
        image = np.asarray(fig.canvas.buffer_rgba())
        height = image.shape[0]

        def pixel(x, y):
            px, py = ax1.transData.transform((x, y))
            return image[int(round(height - py)), int(round(px)), :3]

        # Rendered: surface filled, infield (a hole in the compound path) and outside left empty.
        assert np.all(pixel(2.0, 0.5) == 0) and np.all(pixel(0.35, 1.5) == 0)
        assert np.all(pixel(2.5, 1.5) == 255) and np.all(pixel(0.1, 0.1) == 255)
        sx, sy = artists["start_line"].get_data()
        np.testing.assert_allclose(sx, [2.5, 2.5])
        np.testing.assert_allclose(sorted(sy), [0.2, 0.8])
        artists = tracks.draw_track(ax2, merge_road)
        assert len(artists["lane_dividers"]) == 1
        np.testing.assert_allclose(artists["lane_dividers"][0].get_data()[1], 0.0, atol=1e-12)
        assert artists["surface"].get_path().contains_point((100.0, -2.0))
    finally:
        plt.close(fig)
