"""The racing line (tracks/racing_line.py) against analytic references: the minimum-curvature line
of an annulus and its fastest line, the speed profile of a straight-and-turn path, the lap time of a
circle; the bending-energy Jacobian and the squared-length gradient against finite differences; the cache."""
from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from tracks import track_from_dict
from tracks import racing_line as rl
from tracks.racing_line import RacingLineError, RacingLineLimits, bending_residuals, racing_line, speed_profile

R, WIDTH = 1.0, 0.6


def ring(radius=R, width=WIDTH):
    """Constant-radius annulus: one 360 deg left arc (counter-clockwise), centre (0, 0)."""
    return track_from_dict({"name": "ring", "closed": True, "width": width, "start": [0.0, -radius, 0.0],
                            "segments": [{"type": "arc", "radius": radius, "angle_deg": 360}]})


def limits(**kw):
    base = dict(lateral_accel_mps2=4.0, accel_mps2=2.0, brake_mps2=3.0, top_speed_mps=100.0, half_width_m=0.05,
                margin_m=0.05)
    return RacingLineLimits(**{**base, **kw})


def test_annulus_min_curvature_is_the_outer_limit_and_the_fastest_line_the_inner(tmp_path):
    # Every closed line in the annulus turns 2 pi, so its integral of curvature^2 is at least
    # (2 pi)^2 / length, reached by the longest circle: the outer limit, radius R + w/2 - 0.1.
    # (Not the centre, and not the inside: curvature 1/r falls with r.)
    track = ring()
    n = 100
    s, ey = rl.min_curvature_offsets(track, WIDTH / 2 - 0.1, n)
    outer = R + WIDTH / 2 - 0.1
    assert ey == pytest.approx(np.full(n, -(outer - R)), abs=2e-3)
    # At the cornering limit all the way round (v = sqrt(a r)) a circle's lap takes 2 pi r / v = 2 pi sqrt(r / a):
    # the smaller circle is faster, so the racing line (the fastest candidate) is the inner limit.
    line = racing_line(track, limits(), cache_dir=tmp_path)
    inner = R - (WIDTH / 2 - 0.1)
    assert line.ey == pytest.approx(np.full(len(line.ey), R - inner), abs=2e-3)
    assert line.length_m == pytest.approx(2 * math.pi * inner, rel=1e-3)
    assert line.curvature == pytest.approx(np.full(len(line.ey), 1 / inner), rel=1e-2)
    assert line.speed_mps == pytest.approx(np.full(len(line.ey), math.sqrt(4.0 * inner)), rel=1e-2)
    assert line.lap_time_s == pytest.approx(2 * math.pi * inner / math.sqrt(4.0 * inner), rel=1e-2)
    assert np.all(np.abs(line.ey) <= WIDTH / 2 - 0.1 + 1e-3)


def ring_samples(seed: int, n: int = 30):
    """(points, normals, random offsets) at n samples of the ring."""
    track = ring()
    s = np.arange(n) * track.length / n
    h = track.heading(s)
    return track.position(s), np.stack([-np.sin(h), np.cos(h)], axis=1), np.random.default_rng(seed).uniform(-0.2, 0.2, n)


def test_squared_length_gradient_matches_finite_differences():
    points, normals, offsets = ring_samples(4)
    _, grad = rl.squared_length(offsets, points, normals)
    numeric = approx_fprime(offsets, lambda a: rl.squared_length(a, points, normals)[0], 1e-7)
    assert grad == pytest.approx(numeric, abs=1e-5 * np.abs(grad).max())


def test_bending_jacobian_matches_finite_differences():
    points, normals, offsets = ring_samples(3)
    n = len(offsets)
    _, bands = bending_residuals(offsets, points, normals, jacobian=True)
    i = np.arange(n)
    jac = np.zeros((n, n))
    for k, shift in enumerate((-1, 0, 1)):
        jac[i, (i + shift) % n] = bands[:, k]
    numeric = np.array([approx_fprime(offsets, lambda a, i=i: bending_residuals(a, points, normals)[i], 1e-7)
                        for i in range(n)])
    assert jac == pytest.approx(numeric, abs=1e-5 * np.abs(jac).max())


def test_bending_energy_gradient_matches_finite_differences():
    points, normals, offsets = ring_samples(5)
    energy, grad = rl._bending_energy(offsets, points, normals)
    assert energy == pytest.approx(np.sum(bending_residuals(offsets, points, normals) ** 2))
    numeric = approx_fprime(offsets, lambda a: rl._bending_energy(a, points, normals)[0], 1e-7)
    assert grad == pytest.approx(numeric, abs=1e-5 * np.abs(grad).max())


def test_speed_profile_of_straight_and_turn_is_analytic():
    # Open path: 3 m straight, 1 m arc of radius 0.5 m, 3 m straight; 1 mm samples.
    ds = 1e-3
    s = np.arange(0.0, 7.0 + ds / 2, ds)
    kappa = np.where((s > 3.0) & (s < 4.0), 1 / 0.5, 0.0)
    lim = limits(lateral_accel_mps2=4.0, accel_mps2=2.0, brake_mps2=3.0)
    v = speed_profile(np.full(len(s) - 1, ds), kappa, lim, closed=False)
    v_turn = math.sqrt(4.0 * 0.5)                       # v = sqrt(mu g R)
    turn = (s > 3.01) & (s < 3.99)
    assert v[turn] == pytest.approx(np.full(turn.sum(), v_turn), rel=1e-6)
    after = s > 4.05                                    # v^2 = v0^2 + 2 a s, accelerating out
    assert v[after] == pytest.approx(np.sqrt(v_turn**2 + 2 * 2.0 * (s[after] - 4.0)), rel=2e-3)
    before = (s > 0.5) & (s < 2.95)                     # braking in: v^2 = v0^2 + 2 b (distance to go)
    assert v[before] == pytest.approx(np.sqrt(v_turn**2 + 2 * 3.0 * (3.0 - s[before])), rel=2e-3)


def test_speed_profile_drive_limit_falls_with_speed():
    # A corner (v = sqrt(4 / 16) = 0.5 m/s) at s = 0, then a straight; drive limit 3 - v (m/s^2), so
    # dv/ds = (3 - v) / v and s(v) = [-u - 3 ln(3 - u)] from 0.5 to v, until the 2.5 m/s top speed.
    ds = 1e-3
    s = np.arange(0.0, 4.0, ds)
    kappa = np.zeros(len(s))
    kappa[0] = 16.0
    lim = limits(accel_mps2=3.0, accel_speed_loss_per_s=1.0, top_speed_mps=2.5)
    v = speed_profile(np.full(len(s) - 1, ds), kappa, lim, closed=False)

    def distance(u):
        return (-u - 3 * np.log(3 - u)) - (-0.5 - 3 * math.log(2.5))

    climbing = (v > 0.6) & (v < 2.45)
    assert distance(v[climbing]) == pytest.approx(s[climbing], abs=3 * ds)
    assert v.max() == pytest.approx(2.5) and s[np.argmax(v >= 2.5)] == pytest.approx(distance(2.5), abs=3 * ds)


def test_cache_is_reused_and_keyed_by_limits(tmp_path, monkeypatch):
    track = ring()
    first = racing_line(track, limits(), cache_dir=tmp_path)
    assert len(list(tmp_path.glob("ring-*.json"))) == 1

    def fail(*_):
        raise AssertionError("recomputed despite the cache")

    monkeypatch.setattr(rl, "compute_racing_line", fail)
    again = racing_line(track, limits(), cache_dir=tmp_path)
    assert np.array_equal(again.ey, first.ey) and again.lap_time_s == first.lap_time_s
    with pytest.raises(AssertionError, match="recomputed"):
        racing_line(track, limits(top_speed_mps=1.0), cache_dir=tmp_path)


def test_lookups_wrap_and_interpolate(tmp_path):
    line = racing_line(ring(), limits(), cache_dir=tmp_path)
    L = line.track_length_m
    s = np.array([0.1, 1.234, 5.0])
    assert line.lateral_offset(s + L) == pytest.approx(line.lateral_offset(s))
    assert line.speed(-0.5) == pytest.approx(line.speed(L - 0.5))


def test_car_wider_than_the_track_is_refused(tmp_path):
    with pytest.raises(RacingLineError, match="the car needs 0.700 m"):
        racing_line(ring(), limits(half_width_m=0.3), cache_dir=tmp_path)
    with pytest.raises(RacingLineError, match="closed track"):
        racing_line(track_from_dict({"name": "road", "closed": False, "width": 1.0, "start": [0, 0, 0],
                                     "segments": [{"type": "straight", "length": 5}]}), limits(), cache_dir=tmp_path)


def test_racing_line_is_recorded_as_a_static_strip(tmp_path):
    from race.recording import RaceRecorder, load_recording

    track = ring()
    line = racing_line(track, limits(), cache_dir=tmp_path)
    rec = RaceRecorder(tmp_path / "r.rrd", "test", background=False)
    rec.static_racing_line(track, line)
    rec.close()
    data = load_recording(tmp_path / "r.rrd")
    strips = data.static["world/track/racing_line"]["LineStrips2D:strips"][-1]
    starts = np.array([np.asarray(s, dtype=float).reshape(-1, 2)[0] for s in strips])
    assert len(strips) == len(line.s)
    # On the annulus the line is the circle of radius R - (w/2 - 0.1) about the origin.
    assert np.hypot(starts[:, 0], starts[:, 1]) == pytest.approx(np.full(len(starts), R - (WIDTH / 2 - 0.1)), abs=3e-3)


_LINE_DIGEST = ("import hashlib, json; from tracks import load_track; from tests.test_racing_line import limits; "
                "from tracks.racing_line import compute_racing_line; "
                "line = compute_racing_line(load_track('oval'), limits(half_width_m=0.06, margin_m=0.02)); "
                "print(hashlib.sha256(json.dumps(line.to_json()).encode()).hexdigest())")


def test_the_line_is_the_same_on_one_and_two_blas_threads():
    """One cache key must hold one line: the optimiser's BLAS calls round differently per thread count, so the
    line is computed on one thread whatever the process runs on (without that the oval's line differs here)."""
    digests = set()
    for threads in ("1", "2"):
        env = dict(os.environ, OPENBLAS_NUM_THREADS=threads)
        out = subprocess.run([sys.executable, "-c", _LINE_DIGEST], env=env, capture_output=True, text=True, check=True,
                             cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        digests.add(out.stdout.strip())
    assert len(digests) == 1
