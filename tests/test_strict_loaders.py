"""Every malformed input listed in issue 17 ends in a one-line error naming the file and the field,
exit code 2; valid files that loaded before still load; resource limits, output errors and Ctrl-C."""
from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from app.cli import main

ROOT = Path(__file__).resolve().parent.parent

BASE = {"dt": 0.1, "horizon": 5, "collision": {"min_distance": 1.0},
        "agents": [{"dynamics": {"type": "kinematic_bicycle", "lf": 1.0, "lr": 1.0}, "x0": [0, 1, 2, 0],
                    "cost": {"x_ref": [0, 1, 2, 0], "Q_ref": [0, 1, 1, 0], "R": [0.1, 0.1]}},
                   {"dynamics": {"type": "kinematic_bicycle", "lf": 1.0, "lr": 1.0}, "x0": [3, -1, 2, 0],
                    "cost": {"x_ref": [0, 1, 2, 0], "Q_ref": [0, 1, 1, 0], "R": [0.1, 0.1]}}]}


def _with(path: tuple, value, doc=BASE) -> dict:
    d = copy.deepcopy(doc)
    c = d
    for k in path[:-1]:
        c = c[k]
    c[path[-1]] = value
    return d


def _cli(argv, capsys) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    return code, err


# The messages are written out by hand from docs/problem-format.md's field names.
PROBLEM_CASES = [
    (("agents", 0, "dynamics", "lf"), [1.0], "agents[0].dynamics.lf: expected a finite number > 0, got [1.0]"),
    (("agents", 0, "dynamics", "lf"), None, "agents[0].dynamics.lf: expected a finite number > 0, got null"),
    (("agents", 0, "dynamics", "lf"), True, "agents[0].dynamics.lf: expected a finite number > 0, got true"),
    (("collision", "min_distance"), {"d": 2}, "collision.min_distance: expected a finite number > 0 or a list"),
    (("obstacles",), 5, "obstacles: expected a list, got 5"),
    (("agents", 0, "lead_index"), float("inf"), "agents[0].lead_index: expected an integer >= 0 and <= 2147483647, got Infinity"),
    (("agents", 0, "lead_index"), 1.5, "agents[0].lead_index: expected an integer >= 0 and <= 2147483647, got 1.5"),
    (("horizon",), 2**31, "horizon: expected an integer >= 1 and <= 2147483647, got 2147483648"),
    (("horizon",), 2**63, "horizon: expected an integer >= 1 and <= 2147483647"),
    (("agents", 0, "x0"), [True, False, True, False], "agents[0].x0[0]: expected a finite number, got true"),
    (("agents", 0, "x0"), [0, 1, "2", 3], "agents[0].x0[2]: expected a finite number, got \"2\""),
    (("collision", "enabled"), "no", "collision.enabled: expected true or false, got \"no\""),
    (("solver",), {"verbose": "false"}, "solver.verbose: expected true or false, got \"false\""),
    (("solver",), {"max_iter": 2**40}, "solver.max_iter: expected an integer"),
    (("solver",), {"linear": {"solver": "sparse-lu"}}, "solver.linear.solver: expected one of"),
    (("dtt",), 0.1, "dtt: unknown key 'dtt'; did you mean 'dt'?"),
    (("agents", 0, "x_0"), [0, 0, 0, 0], "agents[0].x_0: unknown key 'x_0'; did you mean 'x0'?"),
    (("agents", 0, "cost", "Rr"), [1, 1], "agents[0].cost.Rr: unknown key 'Rr'; did you mean 'R'?"),
    (("agents", 0, "cost", "R"), [0.1], "agents[0].cost.R must have 2 values"),
    (("agents", 1, "dynamics", "type"), "bicycle", "agents[1].dynamics.type: expected one of 'kinematic_bicycle', 'linear'"),
    (("agents", 0, "dynamics"), {"type": "linear", "A": [[1, 0], [0]], "B": [[1], [1]]}, "agents[0].dynamics.A[1]: rows must all have 2 values"),
    (("agents", 0, "u_init"), [[0, 0]] * 4, "agents[0].u_init: expected shape [5, 2]"),
]


@pytest.mark.parametrize("path, value, message", PROBLEM_CASES, ids=[c[2][:40] for c in PROBLEM_CASES])
def test_malformed_problem_files_name_file_and_field(tmp_path, capsys, path, value, message):
    f = tmp_path / "p.json"
    f.write_text(json.dumps(_with(path, value)))
    code, err = _cli(["solve", f], capsys)
    assert code == 2
    assert err.startswith(f"error: {f}: {message}"), err
    assert "\n" not in err and "Traceback" not in err


def test_problem_file_level_errors(tmp_path, capsys):
    cases = {"deep.json": ('{"dt": ' + "[" * 100_000 + "]" * 100_000 + "}", "line 1, column 39: nested more than 32 levels"),  # { is level 1; the 32nd [ (column 8 + 31) is 33
             "undecodable.json": (b'{"dt": 0.1, "x": "\xff"}', "not UTF-8 text: byte 18"),
             "empty.json": ("", "not valid JSON: Expecting value at line 1, column 1 (byte 0)"),
             "list.json": ("[]", "<top level>: expected an object")}
    for name, (content, message) in cases.items():
        f = tmp_path / name
        f.write_bytes(content if isinstance(content, bytes) else content.encode())
        code, err = _cli(["solve", f], capsys)
        assert code == 2 and f"{f}: {message}" in err, err
    os.mkfifo(tmp_path / "fifo.json")
    code, err = _cli(["solve", tmp_path / "fifo.json"], capsys)
    assert code == 2 and "FIFO" in err
    code, err = _cli(["solve", tmp_path], capsys)
    assert code == 2 and "is a directory, not a regular file" in err


def test_valid_problem_files_still_load(tmp_path, capsys):
    from bench.merging import merging_problem
    from solver_cpp.problem_file import load_problem

    # A file written by `scenario merge` loads back into the problem it was written from.
    out = tmp_path / "merge.json"
    assert main(["scenario", "merge", "--cars", "3", "--seed", "2", "--out", str(out)]) == 0
    problem, settings, warm = load_problem(out)
    ref = merging_problem(3, 2)
    assert settings == {"tol": 5e-4, "max_iter": 100} and warm is None
    np.testing.assert_array_equal([a.x0 for a in problem.agents], [np.asarray(a.x0) for a in ref.agents])
    assert (problem.dt, problem.horizon, problem.collision.min_distance) == (ref.dt, ref.horizon, ref.collision.min_distance)
    # The documented optional forms: null for optional fields, Infinity in bounds, per-step distances.
    doc = _with(("agents", 0, "x_max"), [float("inf"), 5, 10, float("inf")])
    doc["agents"][0]["cost"]["Q"] = None
    doc["collision"]["min_distance"] = [1.0] * 5
    doc["agents"][1]["u_init"] = [[0.0, 0.0]] * 5
    doc["obstacles"] = None
    doc["solver"] = None
    f = tmp_path / "p.json"
    f.write_text(json.dumps(doc))
    problem, _, warm = load_problem(f)
    assert problem.agents[0].x_max[0] == np.inf and warm.u.shape == (2, 5, 2)
    code, _ = _cli(["solve", f, "--out", tmp_path / "r.json"], capsys)
    assert code in (0, 1) and json.loads((tmp_path / "r.json").read_text())["x"]


def test_problem_size_limits(tmp_path, capsys, monkeypatch):
    from solver_cpp import limits

    big_t = tmp_path / "long.json"
    big_t.write_text(json.dumps(_with(("horizon",), 100_000)))
    code, err = _cli(["solve", big_t], capsys)
    assert code == 2 and "problem too large: 2 agents, horizon 100000" in err and "--allow-large" in err
    many = copy.deepcopy(BASE)
    many["agents"] = [copy.deepcopy(BASE["agents"][0]) for _ in range(100)]
    for i, a in enumerate(many["agents"]):
        a["x0"] = [3.0 * i, 0, 2, 0]
    f = tmp_path / "many.json"
    f.write_text(json.dumps(many))
    code, err = _cli(["solve", f], capsys)
    assert code == 2 and "problem too large: 100 agents, horizon 5, nx 4, nu 2, 4950 constraints per step" in err
    # The flag skips the check: shown with a limit that refuses even the small base problem.
    small = tmp_path / "small.json"
    small.write_text(json.dumps(BASE))
    monkeypatch.setattr(limits, "MAX_MEMORY_BYTES", 1.0)
    monkeypatch.setattr(limits.check_size, "__defaults__", (1.0, limits.MAX_SECONDS_PER_ITERATION))
    assert _cli(["solve", small], capsys)[0] == 2
    assert _cli(["solve", small, "--allow-large"], capsys)[0] in (0, 1)


def test_solve_time_limit_flag(tmp_path, capsys):
    from bench.merging import merging_problem
    from solver_cpp.problem_file import problem_to_dict

    f = tmp_path / "m.json"
    f.write_text(json.dumps(problem_to_dict(merging_problem(8, 0))))
    out = tmp_path / "r.json"
    code, _ = _cli(["solve", f, "--time-limit", "1e-4", "--out", out], capsys)
    assert code == 1 and json.loads(out.read_text())["status"] == "time_limit"
    assert _cli(["solve", f, "--time-limit", "-1"], capsys)[0] == 2


def test_output_path_errors(tmp_path, capsys):
    f = tmp_path / "p.json"
    f.write_text(json.dumps(BASE))
    (tmp_path / "plain").write_text("x")
    for out, why in ((tmp_path, "it is a directory"),
                     (tmp_path / "plain" / "r.json", f"{tmp_path / 'plain'} is a file, not a directory")):
        code, err = _cli(["solve", f, "--out", out], capsys)
        assert code == 2 and err == f"error: cannot write {out}: {why}"
        code, err = _cli(["scenario", "merge", "--out", out], capsys)
        assert code == 2 and why in err


# --------------------------------------------------------------------------- car files
def test_car_files(tmp_path, capsys):
    from vehicles.params import CarParams, load_car_params, save_car_params

    shipped = (ROOT / "vehicles" / "buzzracer.toml").read_text()
    assert load_car_params("buzzracer") == CarParams()
    saved = save_car_params(CarParams(name="red"), tmp_path / "red.toml")
    assert load_car_params(saved).name == "red"
    cases = {"empty.toml": ("", "empty car parameter file"),
             "cut.toml": (shipped[: len(shipped) // 2], "missing (a car file has name and every table"),
             "typo.toml": (shipped.replace("lf_m =", "lf =", 1), "geometry.lf: unknown key 'lf'; did you mean 'lf_m'?"),
             "section.toml": (shipped.replace("[inertia]", "[inertial]"), "inertial: unknown key 'inertial'; did you mean 'inertia'?"),
             "bool.toml": (shipped.replace("mass_kg = 0.1667", "mass_kg = true"), "inertia.mass_kg: must be a number, got True"),
             "string.toml": (shipped.replace("mass_kg = 0.1667", 'mass_kg = "0.1667"'), "inertia.mass_kg: must be a number"),
             "deep.toml": ("x = " + "[" * 40 + "]" * 40, "nested more than 32 levels deep")}
    for name, (text, message) in cases.items():
        f = tmp_path / name
        f.write_text(text)
        code, err = _cli(["race", "--car-params", f, "--out", tmp_path / "r.rrd"], capsys)
        assert code == 2 and f"{f}: " in err and message in err, (name, err)


def test_track_and_tracking_files(tmp_path, capsys):
    from tracks import TrackFormatError, available_tracks, load_track
    from tracking.calibration import (CameraCalibration, load_calibration, load_fixed_markers, load_intrinsics,
                                      save_calibration)
    from tracking.geometry import PinholeCamera
    from tracking.markers import ArucoTracker

    for name in available_tracks():
        assert load_track(name).length > 0
    doc = json.loads((ROOT / "tracks" / "data" / "oval.json").read_text())
    doc["widht"] = doc.pop("width")
    f = tmp_path / "t.json"
    f.write_text(json.dumps(doc))
    with pytest.raises(TrackFormatError, match="t.json: widht: unknown key 'widht'; did you mean 'width'?"):
        load_track(f)
    # Found by `bench fuzz --target track`: positive but subnormal sizes made the curvature infinite
    # and the lookup table's size overflow; huge coordinates overflow the geometry.
    oval = json.loads((ROOT / "tracks" / "data" / "oval.json").read_text())
    for path, value, message in ((("width",), 1e-320, "width: must be >= 0.001 m, got 1e-320"),
                                 (("segments", 1, "radius"), 1e-320, r"segments\[1\].radius: must be >= 0.001 m"),
                                 (("start", 0), 1e300, r"start\[0\]: must be within \+-1e\+06 \(m or degrees\)")):
        f.write_text(json.dumps(_with(path, value, oval)))
        with pytest.raises(TrackFormatError, match=message):
            load_track(f)
    # 100 km of 1 cm road: 20 samples per cm would be 2e8 (the limit is 2e6).
    f.write_text(json.dumps({"name": "long", "closed": False, "width": 0.01, "start": [0, 0, 0],
                             "segments": [{"type": "straight", "length": 1e5}]}))
    with pytest.raises(TrackFormatError, match="width: the track is 100000 m long and 0.01 m wide: 200000000 lookup samples"):
        load_track(f)

    cam = PinholeCamera(np.array([[900.0, 0, 640], [0, 900, 360], [0, 0, 1]]), np.zeros(5), np.diag([1.0, -1, -1]),
                        np.array([-2.5, 1.5, 3.0]), (1280, 720))
    cal = CameraCalibration(cam, marker_errors_px={40: 0.25}, reprojection_rms_px=0.25, reprojection_max_px=0.5)
    path = tmp_path / "cal.json"
    save_calibration(path, cal)
    back = load_calibration(path)
    np.testing.assert_allclose(back.camera.position, cam.position, atol=1e-12)
    assert back.marker_errors_px == {40: 0.25}
    data = json.loads(path.read_text())
    data["rvecc"] = data.pop("rvec")
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="cal.json: rvecc: unknown key 'rvecc'; did you mean 'rvec'?"):
        load_calibration(path)
    intrinsics = tmp_path / "k.json"
    intrinsics.write_text(json.dumps({"image_width": 1280, "image_height": 720, "camera_matrix": cam.camera_matrix.tolist(),
                                      "dist_coeffs": [0.0] * 5, "rms_px": 0.2}))  # as another tool may write it
    with pytest.warns(UserWarning, match="k.json: ignoring unknown key 'rms_px'"):
        assert load_intrinsics(intrinsics).image_size == (1280, 720)
    markers = tmp_path / "m.json"
    markers.write_text(json.dumps({"markers": {"40": {"x": 1, "y": 2, "size": True}}}))
    with pytest.raises(ValueError, match=r"m.json: markers\['40'\].size: must be a finite number, got True"):
        load_fixed_markers(markers)
    # DICT_4X4_50 has ids 0..49: a car wearing id 300 could never be seen.
    with pytest.raises(ValueError, match=r"car_ids: marker id 300 is not in the ArUco dictionary in use \(ids 0..49\)"):
        ArucoTracker(cal, 0.055, car_ids=[300])


def test_csv_logs(tmp_path):
    from sysid.log import LogFormatError, read_log

    header = "t,car,x,y,heading,throttle,steering\n"
    f = tmp_path / "long.csv"
    f.write_text(header + "0," * 5_000_000 + "\n")  # a 10 MB line
    with pytest.raises(LogFormatError, match="long.csv: line 2 is 10000000 characters long, more than the limit of 4096"):
        read_log(f)
    f = tmp_path / "nul.csv"
    f.write_text(header + "0,0,1,1,0,0,0\n0,0,1,1\x00,0,0,0\n")
    with pytest.raises(LogFormatError, match=r"nul.csv: row 3, column y: not a number: .1\\x00."):
        read_log(f)
    f = tmp_path / "ok.csv"
    f.write_text(header + "0,0,1,1,0,0.5,0\n0.1,0,1.1,1,0,0.5,0\n")
    assert read_log(f).x.tolist() == [1.0, 1.1]


def test_review_plots_onto_a_file(tmp_path, capsys):
    from test_review import _synthetic_recording
    from tracks import load_track

    rec = tmp_path / "run.rrd"
    _synthetic_recording(rec, load_track("oval"), 2.0, n_ticks=30)
    (tmp_path / "plots").write_text("in the way")
    code, err = _cli(["review", rec, "--plots", tmp_path / "plots"], capsys)
    assert code == 2 and err == f"error: --plots: {tmp_path / 'plots'} is a file, not a folder for the plots"


def test_ctrl_c_during_a_simulated_race_keeps_summary_and_recording(tmp_path):
    """SIGINT to a real `race --json` process: no traceback, exit 130, the JSON summary of the race so
    far, and a recording that `review` reads."""
    rrd, js = tmp_path / "race.rrd", tmp_path / "race.json"
    proc = subprocess.Popen([sys.executable, "-m", "app", "race", "--out", str(rrd), "--json", str(js), "--max-time", "60"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    sizes = [0]
    # The recording grows once the race is running; its set-up alone can pass 20 kB on a loaded machine
    # (a SIGINT then arrives at race time 0), so wait until it has grown once more after that.
    while time.monotonic() < deadline and proc.poll() is None:
        size = rrd.stat().st_size if rrd.exists() else 0
        if size > sizes[-1]:
            sizes.append(size)
        if len([z for z in sizes if z > 20_000]) >= 2:
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert "interrupted (Ctrl-C) after" in out
    summary = json.loads(js.read_text())
    assert summary["interrupted"] is True and 0 < summary["race_time_s"] < 60
    assert summary["winner"] is None
    review = subprocess.run([sys.executable, "-m", "app", "review", str(rrd), "--no-plots"], cwd=ROOT,
                            capture_output=True, text=True, timeout=120)
    assert review.returncode == 0, review.stderr


def test_calibrate_image_that_is_a_fifo(tmp_path, capsys):
    os.mkfifo(tmp_path / "frame.png")  # cv2.imread would block on it forever
    markers = tmp_path / "m.json"
    markers.write_text(json.dumps({"markers": {"40": {"x": 0.1, "y": 0.1, "size": 0.1, "heading_deg": 0}}}))
    code, err = _cli(["calibrate", "--image", tmp_path / "frame.png", "--fixed-markers", markers,
                      "--out", tmp_path / "cal.json"], capsys)
    assert code == 2 and "frame.png: image is a FIFO (named pipe), not a regular file" in err
