"""Model identification from race-stack recordings (.rrd) and closing the loop (docs/sysid.md).

References are independent of the code under test: the simulator's own trace of the race, a replay of
the extracted commands in a fresh simulator, hand-built recordings with known content, and the
[corrections] applied by hand to the planner's wheel angles."""
import dataclasses
import json
import math
import tomllib

import numpy as np
import pytest

from app.cli import main as cli_main
from sim import SimEffects, Simulator
from sysid.log import LogFormatError, read_log
from vehicles.params import load_car_params, save_car_params

NOMINAL = load_car_params("buzzracer")
OFFSET = 0.03
EFFECT = SimEffects(steering_offset_rad=OFFSET)


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


@pytest.fixture(scope="module")
def offset_race(tmp_path_factory):
    """Two laps (about 10 s) against pure pursuit; both simulated cars carry a 0.03 rad steering offset
    the planners do not know about."""
    from race.setup import RaceSetup
    from race.simulation import run_race
    from tracks import load_track

    setup = RaceSetup(track=load_track("oval"), car=NOMINAL, seed=0, laps=2, opponent="pursuit", start="rear",
                      opponent_top_speed_mps=1.8, sim_effects=EFFECT)
    path = tmp_path_factory.mktemp("rrd") / "offset.rrd"
    outcome = run_race(setup, telemetry_path=path)
    return setup, outcome, path


def replay(setup, car, effects, throttle, steering, steps):
    """Positions of both cars after each of `steps` control periods in a fresh simulator."""
    from race.setup import start_states

    sim = Simulator(setup.track, [car, car], effects=effects, seed=setup.seed)
    sim.reset(start_states(setup))
    out = []
    for k in range(steps):
        sim.step(np.column_stack([throttle[:, k], steering[:, k]]), setup.control_period_s)
        out.append(sim.states[:, :2])
    return np.array(out)  # (steps, 2 cars, 2)


def test_rows_from_a_simulated_race_match_the_simulator(offset_race):
    setup, outcome, path = offset_race
    log = read_log(path)
    assert log.cars == [0, 1] and log.car_labels == {0: "rd3g", 1: "opponent"}
    assert "world/cars/rd3g/position" in log.pose_sources[0] and "footprint" in log.pose_sources[0]
    n = outcome.trace_t.size
    rows = [log.select_car(i) for i in (0, 1)]
    for i, r in enumerate(rows):
        assert r.t.size == n
        np.testing.assert_allclose(r.t, outcome.trace_t, atol=1e-8)
        truth = outcome.trace_states[:, i]
        np.testing.assert_allclose(r.x, truth[:, 0], atol=1e-5)  # float32 in the recording
        np.testing.assert_allclose(r.y, truth[:, 1], atol=1e-5)
        assert np.max(np.abs(wrap(r.heading - truth[:, 2]))) < 2e-5
        np.testing.assert_allclose(r.speed, np.hypot(truth[:, 3], truth[:, 4]), rtol=1e-9, atol=1e-12)
    # Commands: the extracted rows, replayed in a fresh simulator carrying the effect, reproduce the race;
    # without the effect they do not (so the race's simulator carried it).
    throttle = np.array([r.throttle for r in rows])
    steering = np.array([r.steering for r in rows])
    steps = 45
    logged = np.array([[r.x[1:steps + 1], r.y[1:steps + 1]] for r in rows]).transpose(2, 0, 1)
    same = replay(setup, NOMINAL, EFFECT, throttle, steering, steps)
    assert np.max(np.abs(same - logged)) < 1e-5
    clean = replay(setup, NOMINAL, SimEffects(), throttle, steering, steps)
    assert np.max(np.hypot(*(clean - logged).transpose(2, 0, 1))) > 0.02


def test_sysid_finds_the_race_cars_steering_offset(offset_race):
    from sysid.data import build_trajectory
    from sysid.diagnose import SysidSettings, identify

    _, _, path = offset_race
    traj = build_trajectory(read_log(path).select_car(0))
    result = identify(traj, NOMINAL, SysidSettings(horizon_s=0.5, fit_max_starts=20, heldout_max_starts=200,
                                                   n_bootstrap=100, max_effects=1))
    assert result.selected and result.selected[0].effect == "steering_offset"
    assert result.car_out.corrections.steering_offset_rad == pytest.approx(OFFSET, rel=0.2)


def test_cli_names_the_cars_of_a_recording(offset_race, tmp_path, capsys):
    _, _, path = offset_race
    assert cli_main(["sysid", str(path), "--report", str(tmp_path / "r.md")]) == 2
    assert "cars [0 (rd3g), 1 (opponent)]; choose one with --car" in capsys.readouterr().err


# ---------------------------------------------------------------- real-time layouts (hand-built recordings)
def _realtime_recording(path, mode, with_heading=True, with_commands=True):
    """A HIL/hardware-style recording: detections at 60 fps capture times offset by 4 ms from the 60 Hz
    loop ticks; commands from tick 2 on; 'truth' entities 1 m away from the detections."""
    from race.recording import RaceRecorder

    rec = RaceRecorder(path, recording_id="test")
    cars = [{"name": "rd3g", "marker_id": 7, "radio_id": 3}, {"name": "opponent", "marker_id": 9, "radio_id": 4}]
    rec.static_document("race/setup", json.dumps({"mode": mode, "track": "oval", "cars": cars}))
    n = 60
    t_cap = 0.004 + np.arange(n) / 60.0
    t_tick = np.arange(n) / 60.0
    expected = {}
    for c, car in enumerate(("rd3g", "opponent")):
        x, y, heading = 1.0 + 0.5 * np.cos(t_cap) + c, 0.5 * np.sin(t_cap), t_cap + np.pi / 2
        for j in range(n):
            rec.points(f"world/cars/{car}/detection", j, t_cap[j], [x[j], y[j]])
            if with_heading:
                rec.scalar(f"cars/{car}/detection_heading_rad", j, t_cap[j], heading[j])
            rec.points(f"world/cars/{car}/position", j, t_cap[j], [x[j] + 1.0, y[j]])
            rec.strip(f"world/cars/{car}/footprint", j, t_cap[j],
                      np.array([[x[j] + 1.1, y[j] + 0.1], [x[j] + 1.1, y[j] - 0.1], [x[j] + 0.9, y[j] - 0.1],
                                [x[j] + 0.9, y[j] + 0.1], [x[j] + 1.1, y[j] + 0.1]]))
        throttle, steering = 0.01 * np.arange(n) + 0.1 * c, -0.002 * np.arange(n)
        for k in range(2, n):
            if with_commands:
                rec.scalar(f"cars/{car}/command/throttle", k, t_tick[k], throttle[k])
                rec.scalar(f"cars/{car}/command/steering_rad", k, t_tick[k], steering[k])
        # by hand: row j takes the last tick at or before the middle of [t_cap[j], t_cap[j+1])
        rows = []
        for j in range(n):
            mid = 0.5 * (t_cap[j] + t_cap[j + 1]) if j + 1 < n else t_cap[j]
            ticks = [k for k in range(2, n) if t_tick[k] <= mid + 1e-12]
            if ticks:
                rows.append((t_cap[j], x[j], y[j], heading[j], throttle[ticks[-1]], steering[ticks[-1]]))
        expected[car] = np.array(rows)
    rec.close()
    return expected


def test_hil_recording_uses_the_camera_detections(tmp_path):
    path = tmp_path / "hil.rrd"
    expected = _realtime_recording(path, "hil")
    log = read_log(path)
    assert log.cars == [7, 9] and log.car_labels == {7: "rd3g", 9: "opponent"}  # the marker ids
    assert log.speed is None
    for car_id, name in ((7, "rd3g"), (9, "opponent")):
        r = log.select_car(car_id)
        assert "camera detections" in r.pose_sources[car_id]
        got = np.column_stack([r.t, r.x, r.y, r.heading, r.throttle, r.steering])
        assert got.shape == expected[name].shape  # rows before the first command are dropped
        np.testing.assert_allclose(got, expected[name], atol=2e-6)  # float32 points, ns time stamps


def test_realtime_recordings_without_detection_headings(tmp_path):
    hil = tmp_path / "hil_old.rrd"
    expected = _realtime_recording(hil, "hil", with_heading=False)
    log = read_log(hil)  # HIL: the simulator's truth, and the source says so
    r = log.select_car(7)
    assert "simulator truth" in r.pose_sources[7]
    np.testing.assert_allclose(r.x, expected["rd3g"][:, 1] + 1.0, atol=2e-6)
    np.testing.assert_allclose(r.heading, 0.0, atol=1e-6)  # the hand-built footprints point along +x
    hw = tmp_path / "hw.rrd"
    _realtime_recording(hw, "hardware", with_heading=False)
    with pytest.raises(LogFormatError, match="'cars/opponent/detection_heading_rad' is missing|"
                                             "'cars/rd3g/detection_heading_rad' is missing"):
        read_log(hw)
    none = tmp_path / "no_commands.rrd"
    _realtime_recording(none, "hil", with_commands=False)
    with pytest.raises(LogFormatError, match=r"no entity 'cars/<car>/command/throttle'"):
        read_log(none)


# ---------------------------------------------------------------- closing the loop
def test_plan_tracking_error_on_a_known_mismatch(tmp_path):
    """The car drives along x at 1.1 m/s; each plan starts at the position predicted over a 50 ms delay
    at 1.0 m/s and continues at 1.0 m/s, so plan point j is 0.1 m/s * (0.05 s + j * 0.1 s) short."""
    from race.recording import RaceRecorder, load_recording
    from sysid.closed_loop import plan_tracking_errors

    path = tmp_path / "plans.rrd"
    rec = RaceRecorder(path, recording_id="plans")
    t = np.arange(150) / 30.0
    for k, tk in enumerate(t):
        rec.points("world/cars/rd3g/position", k, tk, [1.1 * tk, 0.0])
        ahead = 0.05 + 0.1 * np.arange(11)
        rec.strip("world/cars/rd3g/plan", k, tk, np.column_stack([1.1 * tk + ahead, np.zeros(11)]))
    rec.close()
    one, horizon = plan_tracking_errors(load_recording(path), "rd3g", 0.05, 0.1)
    np.testing.assert_allclose(one, 0.1 * 0.15, atol=2e-5)
    np.testing.assert_allclose(horizon, 0.1 * 1.05, atol=5e-5)
    assert horizon.size == np.count_nonzero(t + 1.05 <= t[-1])  # plans reaching past the race are skipped


def test_race_accepts_the_sysid_car_file_and_the_simulator_keeps_the_effect(tmp_path):
    """The car file sysid writes (identified [corrections]) drives the planners' command mapping, while the
    simulator runs the nominal car with the hidden effect."""
    from app.commands.race import make_setup
    from app.cli import build_parser
    from planning import RacingPlanner
    from race.planning import make_planner
    from race.recording import load_recording

    # Written the way `sysid` writes it (save_car_params of the identified car), with values sysid fits.
    corrected = dataclasses.replace(NOMINAL, name="buzzracer-identified", corrections=dataclasses.replace(
        NOMINAL.corrections, steering_offset_rad=0.0297, steering_gain=0.93, steering_delay_s=0.081,
        throttle_delay_s=0.06))
    car_file = save_car_params(corrected, tmp_path / "identified.toml")
    by_hand = tomllib.loads(car_file.read_text())["corrections"]
    out = tmp_path / "race.rrd"
    argv = ["race", "--car-params", str(car_file), "--sim-car-params", "buzzracer", "--sim-effects",
            f"steering_offset={OFFSET}", "--opponent", "pursuit", "--max-time", "1.0", "--out", str(out)]
    args = build_parser().parse_args(argv)
    setup = make_setup(args, args.seed, args.start, args.rd3g_speed, args.opponent_speed, args.laps, args.max_time)
    assert setup.sim_car == NOMINAL and setup.sim_effects == EFFECT
    assert setup.car.corrections.steering_offset_rad == by_hand["steering_offset_rad"]
    mapper = make_planner(RacingPlanner, setup, 2.0, opponent_top_speed_mps=1.8).mapper
    assert mapper.delay_s == max(by_hand["steering_delay_s"], by_hand["throttle_delay_s"])
    assert mapper.steering_command(0.2) == pytest.approx((0.2 - by_hand["steering_offset_rad"]) / by_hand["steering_gain"])

    assert cli_main(argv) == 0
    data = load_recording(out)
    _, delta = data.scalars("cars/rd3g/planned/delta_rad")
    _, command = data.scalars("cars/rd3g/command/steering_rad")
    limit = NOMINAL.actuators.max_steering_rad
    np.testing.assert_allclose(command, np.clip((delta - by_hand["steering_offset_rad"]) / by_hand["steering_gain"],
                                                -limit, limit), atol=1e-9)
    # The simulator ran the nominal car plus the hidden offset (not the corrected file): a fresh replay agrees.
    from race.setup import start_states

    log = read_log(out)
    rows = [log.select_car(i) for i in (0, 1)]
    steps = rows[0].t.size - 1
    logged = np.array([[r.x[1:], r.y[1:]] for r in rows]).transpose(2, 0, 1)
    replayed = replay(setup, NOMINAL, EFFECT, np.array([r.throttle for r in rows]),
                      np.array([r.steering for r in rows]), steps)
    assert np.max(np.abs(replayed - logged)) < 1e-5
    assert not math.isclose(setup.car.corrections.steering_offset_rad, 0.0)


def test_race_rejects_bad_sim_flags(tmp_path, capsys):
    assert cli_main(["race", "--sim-effects", "steering_offset=0.5", "--out", str(tmp_path / "x.rrd")]) == 2
    assert "--sim-effects: SimEffects.steering_offset_rad: must be in [-0.3, 0.3]" in capsys.readouterr().err
    assert cli_main(["race", "--sim-effects", "wobble=1", "--out", str(tmp_path / "x.rrd")]) == 2
    assert "--sim-effects: unknown effect 'wobble'" in capsys.readouterr().err
    assert cli_main(["race", "--sim-car-params", str(tmp_path / "none.toml"), "--out", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err
    assert "--sim-car-params:" in err and "not found" in err
    assert cli_main(["race", "--hil", "--sim-effects", "steering_offset=0.01"]) == 2
    assert "pure simulation only" in capsys.readouterr().err


def test_closed_loop_command_runs_every_variant(tmp_path):
    car_file = save_car_params(dataclasses.replace(NOMINAL, corrections=dataclasses.replace(
        NOMINAL.corrections, steering_offset_rad=OFFSET)), tmp_path / "corrected.toml")
    js, png = tmp_path / "cl.json", tmp_path / "cl.png"
    assert cli_main(["sysid-closed-loop", "--effects", f"steering_offset={OFFSET}", "--corrected", str(car_file),
                     "--seeds", "4", "--opponent", "pursuit", "--max-time", "1.5", "--json", str(js),
                     "--plot", str(png), "--recordings", str(tmp_path / "rec")]) == 0
    record = json.loads(js.read_text())
    assert set(record["summary"]) == {"clean", "nominal", "corrected"}
    assert [r["variant"] for r in record["races"]] == ["clean", "nominal", "corrected"]
    assert all(r["horizon_rmse_m"] is not None and r["horizon_rmse_m"] > 0 for r in record["races"])
    assert png.stat().st_size > 0
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == ["clean-seed4.rrd", "corrected-seed4.rrd",
                                                                    "nominal-seed4.rrd"]
