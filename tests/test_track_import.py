"""track-import (tracks/importers.py): small TUM and f1tenth files written here, scaled and checked
against hand-worked geometry, and every bad input named by file and line with exit code 2."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from app.cli import main
from tracks import load_track
from tracks.importers import CarEnvelope, TrackImportError, import_track

CAR = CarEnvelope(footprint_width_m=0.07, min_turn_radius_m=0.18)
TUM_HEADER = "# x_m,y_m,w_tr_right_m,w_tr_left_m"


def circle(radius, n=60, cx=0.0, cy=0.0):
    a = np.arange(n) * 2 * math.pi / n        # counter-clockwise: left is the inside
    return np.column_stack([cx + radius * np.cos(a), cy + radius * np.sin(a)])


def write_tum(path, points, right, left, header=TUM_HEADER, sep=","):
    rows = [header] + [sep.join(f"{v:.6f}" for v in (x, y, right, left)) for x, y in points]
    path.write_text("\n".join(rows) + "\n")
    return path


def test_tum_circle_fitted_into_the_arena(tmp_path):
    f = write_tum(tmp_path / "ring.csv", circle(100.0, cx=300, cy=-50), 5.0, 5.0)
    data = import_track(f, car=CAR, width_m=0.5, fit_arena=True)
    track = load_track(_save(tmp_path, data))
    # 200 m across into 3 m less 2 x (0.25 m half width + 0.1 m wall margin): radius 1.15 m, centred.
    assert track.length == pytest.approx(2 * math.pi * 1.15, rel=1e-5)
    assert track.min_width == track.max_width == 0.5
    assert np.mean(track.position(np.linspace(0, track.length, 400, endpoint=False)), axis=0) == pytest.approx([2.5, 1.5], abs=1e-6)
    assert "scaled 1:87.0" in data["description"]


def test_asymmetric_tum_widths_move_the_centre_line(tmp_path):
    # 4 m to the right (outside), 6 m to the left (inside): the surface runs from r = 100 - 6 = 94
    # to 100 + 4 = 104, so its middle is r = 99 and its width 10 m.
    f = write_tum(tmp_path / "ring.csv", circle(100.0, n=200), 4.0, 6.0)
    track = load_track(_save(tmp_path, import_track(f, car=CAR)))
    assert track.length == pytest.approx(2 * math.pi * 99.0, rel=1e-5)
    assert track.min_width == pytest.approx(10.0)


def test_f1tenth_raceline_needs_a_width(tmp_path):
    f = tmp_path / "line.csv"
    rows = ["# some comment", "# s_m; x_m; y_m; psi_rad; kappa_radpm; vx_mps; ax_mps2"]
    rows += [f"{i * 0.1:.3f}; {x:.6f}; {y:.6f}; 0.0; 0.5; 2.0; 0.0" for i, (x, y) in enumerate(circle(2.0, n=80))]
    f.write_text("\n".join(rows) + "\n")
    with pytest.raises(TrackImportError, match="line.csv: an f1tenth raceline has no track widths: give --width"):
        import_track(f, car=CAR)
    track = load_track(_save(tmp_path, import_track(f, car=CAR, width_m=0.6)))
    assert track.length == pytest.approx(2 * math.pi * 2.0, rel=1e-5)


def _save(tmp_path, data):
    out = tmp_path / "track.json"
    out.write_text(json.dumps(data))
    return out


def _tum_lines(tmp_path, lines):
    f = tmp_path / "bad.csv"
    f.write_text("\n".join(lines) + "\n")
    return f


GOOD = [f"{x:.4f},{y:.4f},5.0,5.0" for x, y in circle(100.0, n=12)]


@pytest.mark.parametrize("lines, kwargs, message", [
    (["# x_m,y_m,w_tr_right_m"] + [r.rsplit(",", 1)[0] for r in GOOD], {}, "bad.csv: line 1: missing column(s) w_tr_left_m"),
    (["# x_m;y_m;w_tr_right_m;w_tr_left_m"] + [r.replace(",", ";") for r in GOOD], {"fmt": "tum"},
     "bad.csv: line 1: columns separated by ';'; the tum format separates them by ','"),
    ([TUM_HEADER] + GOOD[:3] + ["1.0,abc,5.0,5.0"] + GOOD[4:], {}, "bad.csv: line 5: y_m: 'abc' is not a number"),
    ([TUM_HEADER] + GOOD[:6] + ["1.0,2.0,-5.0,5.0"] + GOOD[7:], {}, "bad.csv: line 8: w_tr_right_m: -5 m; widths must be positive"),
    ([TUM_HEADER] + GOOD[:2] + ["1.0;2.0;5.0;5.0"] + GOOD[3:], {}, "bad.csv: line 4: 1 column(s), expected 4"),
    ([TUM_HEADER] + GOOD[:3], {}, "bad.csv: 3 point(s); a circuit needs at least 4"),
    # 2 m wide, 202 m across with its width: scaled by (3 - 2 x 0.1 m wall margin) / 202, 0.028 m wide.
    ([TUM_HEADER] + [r.replace(",5.0,5.0", ",1.0,1.0") for r in GOOD], {"fit_arena": True},
     "bad.csv: line 2: the track is 0.028 m wide there, less than the car's footprint width 0.070 m"),
    ([TUM_HEADER] + GOOD, {"fit_arena": True, "width_m": 3.5}, "does not fit the arena 5 x 3 m"),
])
def test_bad_circuit_files_are_named_by_line(tmp_path, lines, kwargs, message):
    with pytest.raises(TrackImportError) as info:
        import_track(_tum_lines(tmp_path, lines), car=CAR, **kwargs)
    assert message in str(info.value)


def test_sharp_corner_and_crossing_are_named(tmp_path):
    # A square of side 2 m with points every 0.25 m: the spline turns its corners far tighter than
    # the car's 0.18 m radius.
    side = np.linspace(0, 2, 9)[:-1]
    square = np.concatenate([np.column_stack([side, 0 * side]), np.column_stack([2 + 0 * side, side]),
                             np.column_stack([2 - side, 2 + 0 * side]), np.column_stack([0 * side, 2 - side])])
    f = write_tum(tmp_path / "square.csv", square, 0.2, 0.2)
    with pytest.raises(TrackImportError, match=r"square.csv: line \d+: turn radius 0\.\d+ m is below"):
        import_track(f, car=CAR)
    # A figure of eight (lemniscate of Gerono, 10 m): the centre line crosses itself at the origin.
    t = np.arange(80) * 2 * math.pi / 80 + 0.01
    eight = np.column_stack([10 * np.sin(t), 5 * np.sin(2 * t)])
    f = write_tum(tmp_path / "eight.csv", eight, 0.5, 0.5)
    with pytest.raises(TrackImportError, match=r"eight.csv: line \d+: the centre line from here crosses the one from line \d+"):
        import_track(f, car=CAR)


def test_cli_import_writes_a_track_and_prints_its_numbers(tmp_path, capsys, monkeypatch):
    f = write_tum(tmp_path / "ring.csv", circle(100.0), 5.0, 5.0)
    out = tmp_path / "ring.json"
    monkeypatch.setenv("RD3G_RACING_LINE_CACHE", str(tmp_path / "cache"))
    code = main(["track-import", str(f), "--fit-arena", "--width", "0.5", "--out", str(out)])
    text = capsys.readouterr().out
    assert code == 0 and out.is_file()
    assert "length 7.226 m" in text and "width 0.500 .. 0.500 m" in text and "tightest centre-line turn radius 1.150 m" in text
    assert "lap time" in text
    # Bad input on the command line: exit 2, file and line named, nothing written.
    bad = _tum_lines(tmp_path, [TUM_HEADER] + GOOD[:3] + ["1.0,abc,5.0,5.0"] + GOOD[4:])
    code = main(["track-import", str(bad), "--out", str(tmp_path / "bad.json")])
    assert code == 2 and "bad.csv: line 5: y_m: 'abc' is not a number" in capsys.readouterr().err
    assert not (tmp_path / "bad.json").exists()


def test_imported_circuit_races_in_simulation(tmp_path):
    """A bean-shaped 2.8 km circuit written for the test, imported with --fit-arena: both cars race
    on it (4 s of a simulated race: each makes over 3 m of progress, no collision, no planner error)."""
    from race.setup import RaceSetup
    from race.simulation import run_race
    from vehicles.params import load_car_params

    t = np.arange(150) * 2 * math.pi / 150
    r = 300 * (1 + 0.25 * np.cos(2 * t) + 0.1 * np.sin(3 * t))
    f = write_tum(tmp_path / "bean.csv", np.column_stack([1.6 * r * np.cos(t), r * np.sin(t)]), 6.0, 6.5)
    track = load_track(_save(tmp_path, import_track(f, car=CAR, width_m=0.5, fit_arena=True)))
    o = run_race(RaceSetup(track=track, car=load_car_params("buzzracer"), seed=1, max_time_s=4.0))
    assert o.collisions == [] and o.planner_errors == []
    assert np.all(o.trace_progress[-1] - o.trace_progress[0] > 3.0)
