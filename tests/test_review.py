"""`python -m app review`: recordings are read back with rerun's reader and the summary is checked
against independent references (analytic geometry and lap times, the simulated race's own outcome).
The real --hil recording is reviewed in tests/test_faults.py."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from race.review import SUMMARY_KEYS
from sim.collision import rectangle_gap
from test_loop_support import run_cli


def _rect(cx, cy, heading, length, width):
    c, s = math.cos(heading), math.sin(heading)
    local = np.array([[length / 2, width / 2], [length / 2, -width / 2], [-length / 2, -width / 2], [-length / 2, width / 2]])
    return local @ np.array([[c, s], [-s, c]]) + [cx, cy]


def test_rectangle_gap_matches_geometry():
    a = _rect(0, 0, 0, 0.16, 0.07)
    cases = [
        (_rect(0.16 + 0.05, 0, 0, 0.16, 0.07), 0.05),                       # nose to tail, 5 cm
        (_rect(0, 0.07 + 0.02, 0, 0.16, 0.07), 0.02),                       # side by side, 2 cm
        (_rect(0.05, 0.01, 0.3, 0.16, 0.07), 0.0),                          # overlapping
        # rotated 45 deg, corner pointing at a's right side: gap = dx - half length - half diagonal
        (_rect(0.3, 0, math.pi / 4, 0.1, 0.1), 0.3 - 0.08 - 0.05 * math.sqrt(2)),
    ]
    got = rectangle_gap(np.array([a] * len(cases)), np.array([b for b, _ in cases]))
    np.testing.assert_allclose(got, [g for _, g in cases], atol=1e-9)


def _synthetic_recording(path, track, speed, n_ticks=200, period_ms=None):
    """A recording as the loop writes it: one car on the centre line at constant speed."""
    from race.recording import RaceRecorder

    rec = RaceRecorder(path, recording_id="synthetic")
    rec.static_document("race/setup", json.dumps({"mode": "hil", "track": track.name, "laps": 2, "loop": {"rate_hz": 60}}))
    dt = 1 / 60
    s0 = 0.3
    for k in range(n_ticks):
        t = k * dt
        x, y = track.position((s0 + speed * t) % track.length)
        rec.points("world/cars/rd3g/position", k, t, [x, y])
        if period_ms is not None:
            rec.scalar("loop/period_ms", k, t, period_ms[k % len(period_ms)])
            rec.scalar("camera/latency_ms", k, t, 20.0)
            rec.scalar("tracking/rd3g/error_mm", k, t, 1.0 + (k % 3))
            rec.scalar("planner/rd3g/solve_ms", k, t, 5.0 + (k % 5))
    rec.event(0.5, "deadline_miss", "tick 30: no command by the deadline (stage detect running) - neutral sent")
    rec.event(0.7, "deadline_miss", "3 tick(s) skipped: loop 52.0 ms late")
    rec.event(0.9, "collision", "rd3g (fault opponent)")
    rec.close()


def test_review_of_a_loop_recording(tmp_path):
    from tracks import load_track

    track = load_track("oval")
    speed = 2.0
    n = int(60 * (track.length / speed) * 1.6)  # 1.6 laps
    path = tmp_path / "synthetic.rrd"
    _synthetic_recording(path, track, speed, n_ticks=n, period_ms=[16.0, 17.0, 16.5, 40.0])
    js = tmp_path / "s.json"
    assert run_cli(["review", str(path), "--json", str(js), "--plots", str(tmp_path / "plots")]) == 0
    s = json.loads(js.read_text())
    assert tuple(s) == SUMMARY_KEYS
    # started at s0 = 0.3 (first half: lap 1 is timed from t = 0): first crossing after (L - 0.3) / v
    assert s["laps"] == {"rd3g": 1}
    assert s["lap_times_s"]["rd3g"][0] == pytest.approx((track.length - 0.3) / speed, abs=2e-3)
    written = np.array([[16.0, 17.0, 16.5, 40.0][k % 4] for k in range(n)])
    assert s["loop_hz_median"] == pytest.approx(1e3 / np.median(written))
    assert s["loop_period_p99_ms"] == pytest.approx(np.percentile(written, 99))
    assert s["deadline_misses"] == 1 + 3
    assert s["collisions"] == 1
    assert s["frames"] == n
    assert s["tracking_error_mm_median"] == 2.0
    assert s["min_gap_m"] is None  # one car only
    assert {p.name for p in (tmp_path / "plots").iterdir()} == {"track.png", "speed.png", "timing.png"}


def test_review_of_a_simulated_race(tmp_path):
    """The simulated race's recording: laps, lap times and the minimum gap agree with the race's own
    outcome; loop-only fields are null."""
    from race.setup import RaceSetup
    from race.simulation import run_race
    from tracks import load_track
    from vehicles.params import load_car_params

    setup = RaceSetup(track=load_track("oval"), car=load_car_params("buzzracer"), seed=1, start="rear",
                      opponent_top_speed_mps=1.8, max_time_s=2.5)
    path = tmp_path / "sim.rrd"
    outcome = run_race(setup, telemetry_path=path)
    js = tmp_path / "sim.json"
    assert run_cli(["review", str(path), "--json", str(js), "--no-plots"]) == 0
    s = json.loads(js.read_text())
    assert tuple(s) == SUMMARY_KEYS
    for key in ("loop_hz_median", "loop_period_p99_ms", "deadline_misses", "frames", "tracking_error_mm_median",
                "tracking_error_mm_p95"):
        assert s[key] is None
    assert s["lap_times_s"] == {name: pytest.approx(v, abs=2e-3) for name, v in outcome.lap_times_s.items()}
    assert s["min_gap_m"] == pytest.approx(outcome.min_gap_m, abs=1e-4)  # float32 footprints in the file
    assert s["collisions"] == len(outcome.collisions)
    assert s["solve_ms_p50"] == pytest.approx(float(np.percentile(outcome.solve_ms, 50)), rel=1e-6)


def test_review_errors(tmp_path, monkeypatch):
    with pytest.raises(SystemExit, match="recording not found"):
        run_cli(["review", str(tmp_path / "missing.rrd")])
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"not a recording")
    with pytest.raises(SystemExit, match="not a readable rerun recording|holds no rerun recording"):
        run_cli(["review", str(bad), "--no-plots"])
    from tracks import load_track

    path = tmp_path / "ok.rrd"
    _synthetic_recording(path, load_track("oval"), 2.0, n_ticks=30)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(SystemExit, match="--viewer: no"):
        run_cli(["review", str(path), "--no-plots", "--viewer"])
