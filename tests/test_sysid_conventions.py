"""Real input conventions: normalised and pulse-width commands mapped through the car file, commands outside the
declared convention refused, the speed set-point car's speed loop against its analytic response, and the
F1/10 run folders of ../shared (skipped when absent)."""

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from sysid.conventions import to_physical
from sysid.data import build_trajectory
from sysid.log import CommandUnits, DriveLog, LogFormatError, read_log
from sysid.model import ModelSetup, predict
from vehicles.params import load_car_params

BUZZ = load_car_params("buzzracer")
F110 = load_car_params("f110")
SHARED = Path(os.environ.get("RD3G_SHARED_DIR") or Path(__file__).resolve().parents[2] / "shared")
F110_RUNS = SHARED / "data" / "real-drive-logs" / "frictionmaps-f110"
needs_f110 = pytest.mark.skipif(not F110_RUNS.is_dir(), reason="F1/10 runs not found (shared/ beside the "
                                                               "repository, or set RD3G_SHARED_DIR)")


def csv_log(tmp_path: Path, steering, throttle, name="log.csv") -> Path:
    n = len(steering)
    lines = ["t,car,x,y,heading,throttle,steering"]
    lines += [f"{0.02 * i:.2f},0,{0.02 * i:.3f},0,0,{throttle[i]},{steering[i]}" for i in range(n)]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_normalised_and_pulse_width_commands_map_through_the_car_file(tmp_path):
    m = BUZZ.actuators.max_steering_rad  # 27 deg
    log = read_log(csv_log(tmp_path, [0.5, -1.0, 0.0], [0.25, -1.0, 1.0]), CommandUnits("normalized", "normalized"))
    phys = to_physical(log, BUZZ, "buzzracer")
    np.testing.assert_allclose(phys.steering, [0.5 * m, -m, 0.0])  # the race link: fraction of max_steering_rad
    np.testing.assert_allclose(phys.throttle, [0.25, -1.0, 1.0])
    # Pulse widths through [radio] (defaults: steering 1100 left / 1500 / 2000 right, throttle 1100 / 1500 / 1900).
    log = read_log(csv_log(tmp_path, [1300, 1750, 1500], [1700, 1300, 1900]), CommandUnits("us", "us"))
    phys = to_physical(log, BUZZ, "buzzracer")
    np.testing.assert_allclose(phys.steering, [m * 200 / 400, -m * 250 / 500, 0.0])  # left positive
    np.testing.assert_allclose(phys.throttle, [0.5, -0.5, 1.0])


@pytest.mark.parametrize("units, steering, throttle, where", [
    (CommandUnits("normalized", "normalized"), [0.1, 1.3, 0.0], [0.1, 0.1, 0.1], "row 3, column steering: declared normalised"),
    (CommandUnits("us", "normalized"), [1500, 1500, 900], [0.1, 0.1, 0.1], "row 4, column steering: declared as pulse widths"),
    (CommandUnits("rad", "us"), [0.1, 0.1, 0.1], [1500, 2100, 1500], "row 3, column throttle: declared as pulse widths"),
    (CommandUnits("rad", "normalized"), [0.1, 1.3, 0.0], [0.1, 0.1, 0.1], "declare them"),
])
def test_commands_outside_the_declared_convention_name_row_and_column(tmp_path, units, steering, throttle, where):
    path = csv_log(tmp_path, steering, throttle)
    with pytest.raises(LogFormatError) as err:
        read_log(path, units)
    assert where in str(err.value) and str(path) in str(err.value)


def test_a_speed_set_point_log_needs_a_speed_set_point_car_and_back(tmp_path, capsys):
    path = csv_log(tmp_path, [0.0] * 3, [1.0] * 3)
    speed_log = read_log(path, CommandUnits("rad", "speed"))
    with pytest.raises(LogFormatError, match="speed_control.gain_per_s = 0"):
        to_physical(speed_log, BUZZ, "buzzracer")
    with pytest.raises(LogFormatError, match="declare --throttle-units speed"):
        to_physical(read_log(path), F110, "f110")
    assert main(["sysid", str(path), "--car-params", "f110", "--report", str(tmp_path / "r.md")]) == 2
    assert str(path) in capsys.readouterr().err


def test_speed_loop_prediction_is_the_analytic_first_order_response():
    """A straight run with a set-point step: the speed loop (unsaturated) gives v = vs + (v0 - vs) exp(-g t)."""
    g, v0, vs = F110.speed_control.gain_per_s, 1.0, 2.0
    dt = 0.01
    t = np.arange(0, 6.0, dt)
    step = 1.0  # set-point goes from v0 to vs at t = 1 s
    tau = np.clip(t - step, 0, None)
    v = np.where(t < step, v0, vs + (v0 - vs) * np.exp(-g * tau))
    x = np.where(t < step, v0 * t, v0 * step + vs * tau + (v0 - vs) * (1 - np.exp(-g * tau)) / g)
    setpoint = np.where(t < step, v0, vs)
    log = DriveLog("<step>", t, np.zeros(t.size, dtype=int), x, np.zeros(t.size), np.zeros(t.size), setpoint,
                   np.zeros(t.size), v, np.arange(2, t.size + 2), units=CommandUnits("rad", "speed"))
    traj = build_trajectory(log)
    start, horizon = 80, 100  # from 0.2 s before the step to 0.8 s after it
    pred = predict(traj, np.array([start]), horizon, ModelSetup(F110))[0]
    k = start + np.arange(horizon + 1)
    np.testing.assert_allclose(pred[:, 3], v[k], atol=2e-3)
    np.testing.assert_allclose(pred[:, 0], x[k], atol=2e-3)


# ----------------------------------------------------------------------------- the shared F1/10 runs
@needs_f110
def test_f110_run_folder_is_read_with_commands_on_their_own_clock():
    log = read_log(F110_RUNS / "DS1")
    assert log.units == CommandUnits("rad", "speed")
    pose = np.genfromtxt(F110_RUNS / "DS1" / "pfPoseData.csv", delimiter=",", skip_header=1)
    cmd = np.genfromtxt(F110_RUNS / "DS1" / "commandData.csv", delimiter=",", skip_header=1)
    t_pose, t_cmd = pose[:, 1] + 1e-9 * pose[:, 2], cmd[:, 1] + 1e-9 * cmd[:, 2]
    kept = t_pose >= t_cmd[0]
    assert log.t.size == kept.sum()
    # Row 100 (of the kept poses): heading 2 atan2(q.z, q.w) wrapped, command = last one sent before the pose.
    row = np.flatnonzero(kept)[100]
    assert math.isclose(math.cos(log.heading[100]), math.cos(2 * math.atan2(pose[row, 7], pose[row, 8])), abs_tol=1e-12)
    last = np.flatnonzero(t_cmd <= t_pose[row])[-1]
    assert log.steering[100] == cmd[last, 4] and log.throttle[100] == cmd[last, 3]
    np.testing.assert_array_equal(log.commands.t, t_cmd)
    assert np.all(log.speed >= 0) and log.speed.max() < 6.0


@needs_f110
def test_f110_time_going_backwards_names_file_and_row(tmp_path):
    run = tmp_path / "DS1"
    shutil.copytree(F110_RUNS / "DS1", run)
    for f in run.iterdir():
        f.chmod(0o644)
    lines = (run / "commandData.csv").read_text().splitlines()
    fields = lines[10].split(",")
    fields[1] = str(int(fields[1]) - 5)
    lines[10] = ",".join(fields)
    (run / "commandData.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(LogFormatError, match=r"commandData.csv: row 11, column s/ns: time goes backwards"):
        read_log(run)


@needs_f110
def test_f110_runs_fit_on_two_predict_a_third(tmp_path):
    runs = [str(F110_RUNS / d) for d in ("DS1", "DS4", "DS5")]
    out = tmp_path / "r.json"
    code = main(["sysid", *runs, "--heldout-run", runs[0], "--car-params", "f110", "--report", str(tmp_path / "r.md"),
                 "--json", str(out), "--fit-windows", "60"])
    assert code == 0
    data = json.loads(out.read_text())
    (held,) = data["heldout_runs"]
    assert held["source"] == runs[0] and held["windows"] >= 20
    # The identified model is never worse held out than the nominal one it started from.
    assert held["after"]["horizon_pos_rmse_m"] <= held["dynamic_nominal"]["horizon_pos_rmse_m"] * 1.0001


def test_a_car_file_with_inconsistent_geometry_is_refused(tmp_path, capsys):
    text = (Path(__file__).resolve().parents[1] / "vehicles" / "buzzracer.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("lf_m = 0.04824", "lf_m = 48.24"))  # millimetres written as metres
    log = csv_log(tmp_path, [0.0] * 3, [0.1] * 3)
    assert main(["sysid", str(log), "--car-params", str(bad), "--report", str(tmp_path / "r.md")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "geometry: the axles (lf_m 48.24" in err


def test_normalised_and_pulse_width_logs_identify_like_the_radian_log(tmp_path):
    """The same drive written in rad, as normalised commands and as pulse widths: the same identification."""
    from sysid.generate import generate_log, parse_effects
    from sysid.log import write_log_csv
    import dataclasses

    log = generate_log(BUZZ, parse_effects("steering_offset=0.03"), 0.4, seed=51, physics_dt=0.002)
    m = BUZZ.actuators.max_steering_rad
    variants = {"rad": (log, []),
                "normalized": (dataclasses.replace(log, steering=log.steering / m), ["--steering-units", "normalized"])}
    # Pulses: left (positive) 1500 -> 1100 us over m, right 1500 -> 2000 us; throttle 1500 -> 1900 / 1100.
    s, u = log.steering, log.throttle
    us_steer = np.where(s >= 0, 1500 - 400 * s / m, 1500 + 500 * -s / m)
    us_thr = np.where(u >= 0, 1500 + 400 * u, 1500 - 400 * -u)
    variants["us"] = (dataclasses.replace(log, steering=us_steer, throttle=us_thr),
                      ["--steering-units", "us", "--throttle-units", "us"])
    results = {}
    for name, (variant, flags) in variants.items():
        path = write_log_csv(tmp_path / f"{name}.csv", variant)
        out = tmp_path / f"{name}.json"
        assert main(["sysid", str(path), *flags, "--report", str(tmp_path / f"{name}.md"), "--json", str(out),
                     "--fit-windows", "60"]) == 0
        results[name] = json.loads(out.read_text())
    for name in ("normalized", "us"):
        a, b = results["rad"]["effects"], results[name]["effects"]
        assert [e["effect"] for e in a] == [e["effect"] for e in b] == ["steering_offset"]
        # The CSV keeps 6 decimals: the commands agree to ~1e-6 rad, the fits to far better than their spread.
        assert b[0]["params"]["steering_offset_rad"] == pytest.approx(a[0]["params"]["steering_offset_rad"], abs=2e-4)


def test_units_declared_in_the_file_header(tmp_path):
    path = csv_log(tmp_path, [0.5, -1.0, 0.0], [1700, 1300, 1900])
    path.write_text("# steering_units = normalized\n# throttle_units = us\n" + path.read_text())
    log = read_log(path)
    assert log.units == CommandUnits("normalized", "us")
    phys = to_physical(log, BUZZ, "buzzracer")
    np.testing.assert_allclose(phys.throttle, [0.5, -0.5, 1.0])
    # The option agrees: fine; it differs: the row of the declaration is named.
    assert read_log(path, CommandUnits("normalized", "us")).units == log.units
    with pytest.raises(LogFormatError, match="row 1: the file declares steering_units = normalized"):
        read_log(path, CommandUnits("rad", "us"))
    path.write_text(path.read_text().replace("throttle_units = us", "throttle_units = volts"))
    with pytest.raises(LogFormatError, match="row 2: throttle units: one of"):
        read_log(path)
