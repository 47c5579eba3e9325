"""Several runs per identification: own time bases, canonical order (no effect of the order the runs are
given in), whole runs held out, short runs in a set, the block length; time stamps snapped to a frame clock."""

import json
import math
from dataclasses import replace as dataclasses_replace

import numpy as np
import pytest

from app.cli import main
from sysid.data import build_runs, build_trajectory, snap_to_frames
from sysid.diagnose import SysidSettings, identify, split_starts
from sysid.generate import generate_log, parse_effects
from sysid.log import DriveLog, write_log_csv
from vehicles.params import load_car_params

NOMINAL = load_car_params("buzzracer")
SETTINGS = SysidSettings(fit_max_starts=80, heldout_max_starts=300, n_bootstrap=200)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Three runs of a car with a 0.03 rad steering offset: 25 s, 25 s and a short 6 s one."""
    d = tmp_path_factory.mktemp("runs")
    paths = []
    for seed, minutes in ((21, 25 / 60), (22, 25 / 60), (23, 0.1)):
        log = generate_log(NOMINAL, parse_effects("steering_offset=0.03"), minutes, seed=seed, physics_dt=0.002)
        paths.append(str(write_log_csv(d / f"run{seed}.csv", log)))
    return paths


def test_runs_keep_their_own_time_base_and_no_window_crosses_a_run(runs):
    from sysid.log import read_log

    traj = build_runs([read_log(p) for p in runs])
    assert traj.n_runs == 3
    for i in range(3):
        mine = traj.run == i
        assert traj.elapsed[mine][0] == 0.0  # each run starts its own clock
        assert np.all(np.diff(traj.elapsed[mine]) > 0)
    # Every segment lies inside one run.
    for seg in np.unique(traj.segment):
        assert np.unique(traj.run[traj.segment == seg]).size == 1
    split = split_starts(traj, 30, SETTINGS)
    # Whole runs are held out: no held-out run contributes training windows and vice versa.
    assert not set(traj.run[split.train]) & set(traj.run[split.heldout])
    # The short run is usable in a set (it has no held-out block of its own).
    assert split.train.size + split.heldout.size > 0


def test_the_order_of_the_runs_changes_nothing(runs, tmp_path):
    outputs = []
    for k, order in enumerate(([0, 1, 2], [2, 0, 1], [1, 2, 0])):
        out = tmp_path / f"r{k}.json"
        code = main(["sysid", *[runs[i] for i in order], "--report", str(tmp_path / f"r{k}.md"), "--json", str(out),
                     "--fit-windows", "80"])
        assert code == 0
        data = json.loads(out.read_text())
        data.pop("car_params_out")
        outputs.append(data)
    assert outputs[0] == outputs[1] == outputs[2]
    assert [e["effect"] for e in outputs[0]["effects"]] == ["steering_offset"]
    assert outputs[0]["effects"][0]["params"]["steering_offset_rad"] == pytest.approx(0.03, rel=0.2)
    # One held-out run, reported per run with its own errors.
    assert len(outputs[0]["heldout_runs"]) == 1
    per_run = outputs[0]["heldout_runs"][0]
    assert per_run["after"]["horizon_pos_rmse_m"] < 0.5 * per_run["dynamic_nominal"]["horizon_pos_rmse_m"]


def test_chosen_heldout_run_and_bad_choices(runs, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert main(["sysid", *runs, "--heldout-run", runs[0], "--report", str(tmp_path / "r.md"), "--json", str(out),
                 "--fit-windows", "60"]) == 0
    held = json.loads(out.read_text())["heldout_runs"]
    assert [h["source"] for h in held] == [runs[0]]
    assert main(["sysid", runs[0], "--heldout-run", runs[1], "--report", str(tmp_path / "x.md")]) == 2
    assert "not one of the runs given" in capsys.readouterr().err
    assert main(["sysid", runs[0], runs[0], "--report", str(tmp_path / "x.md")]) == 2
    assert "given twice" in capsys.readouterr().err


def test_a_short_single_run_gets_shorter_blocks_and_block_length_is_an_option(runs):
    from sysid.log import read_log

    short = build_trajectory(read_log(runs[2]))
    split = split_starts(short, 30, SETTINGS)  # 6 s: 3 s blocks would leave nothing held out
    assert split.heldout.size >= 20
    with pytest.raises(ValueError, match="--block-length sets the length"):
        split_starts(short, 30, SysidSettings(block_s=4.0))


def test_runs_of_different_cars_are_refused(runs, tmp_path, capsys):
    text = open(runs[1]).read().splitlines()
    header, rows = text[0], text[1:]
    col = header.split(",").index("car")
    moved = [",".join(v if i != col else "3" for i, v in enumerate(r.split(","))) for r in rows]
    other = tmp_path / "car3.csv"
    other.write_text("\n".join([header, *moved]) + "\n")
    assert main(["sysid", runs[0], str(other), "--report", str(tmp_path / "x.md")]) == 2
    err = capsys.readouterr().err
    assert str(other) in err and "runs of different cars" in err


# ----------------------------------------------------------------------------- time stamps
def test_jittered_arrival_times_snap_to_the_frame_clock():
    rng = np.random.default_rng(4)
    period, n = 0.01, 2000
    frames = np.arange(n)
    frames = frames[rng.uniform(size=n) > 0.05]  # 5 % of the frames never arrive
    truth = 3.0 + frames * period
    arrival = truth + rng.uniform(0.0, 0.004, frames.size)  # delivery latency 0-4 ms
    # Two messages delivered in one frame: the second's stamp lands on the first's frame.
    arrival[100] = arrival[99] + 0.0001
    snapped, missing = snap_to_frames(arrival, period)
    # The latency's mean (2 ms) is a constant offset of the clock, not an error of the frames.
    offset = np.median(snapped - truth)
    assert abs(offset - 0.002) < 0.001
    assert np.mean(np.abs(snapped - truth - offset) < 1e-9) > 0.99
    # One frame missing between two rows is interpolated (counted); two or more are a gap (2.5 periods).
    holes = np.diff(np.delete(frames, 100))  # row 100 now sits on row 99's frame: its own frame is empty
    assert missing == np.sum(holes == 2)

    # The same through build_trajectory: a circle sampled at the arrival times.
    radius, speed = 0.8, 1.2
    angle = speed / radius * (truth - truth[0])
    log = DriveLog("<jitter>", arrival, np.zeros(arrival.size, dtype=int), radius * np.cos(angle),
                   radius * np.sin(angle), np.angle(np.exp(1j * (angle + math.pi / 2))), np.full(arrival.size, 0.3),
                   np.full(arrival.size, 0.1), None, np.arange(2, arrival.size + 2))
    plain = build_trajectory(log)
    snapped_traj = build_trajectory(log, frame_period=period)
    assert snapped_traj.dt == period
    assert snapped_traj.runs[0].n_missing_frames > 0 and snapped_traj.runs[0].n_duplicates_merged >= 1
    assert snapped_traj.n_gaps == np.sum(holes >= 3)  # single dropped frames are interpolated, not gaps
    # Noise estimate: the true poses are exact, the jitter alone made the plain grid see noise.
    assert snapped_traj.position_noise_m < 0.3 * plain.position_noise_m


def test_bad_runs_in_a_set_name_their_file_and_row(runs, tmp_path, capsys):
    header = "t,car,x,y,heading,throttle,steering"
    rows = [f"{0.05 * i:.2f},0,{0.1 * i:.2f},0.0,0.0,0.2,0.0" for i in range(10)]
    backwards = tmp_path / "backwards.csv"
    backwards.write_text("\n".join([header, *rows[:5], "0.01,0,0,0,0,0.2,0", *rows[5:]]) + "\n")
    assert main(["sysid", runs[0], str(backwards), "--report", str(tmp_path / "x.md")]) == 2
    err = capsys.readouterr().err
    assert f"{backwards}: row 7, column t: time goes backwards" in err
    short = tmp_path / "short.csv"
    short.write_text("\n".join([header, *rows]) + "\n")  # 0.45 s
    assert main(["sysid", runs[0], str(short), "--report", str(tmp_path / "x.md")]) == 2
    err = capsys.readouterr().err
    assert f"{short}: no stretch of the log is long enough" in err


def test_random_effects_pool_and_outlier_rule_by_hand():
    from sysid.agreement import agreement, pool

    # Worked by hand: w = 100 each, fixed mean 1.0333, Q = 4.667, tau^2 = (Q - 2) / (300 - 100) = 0.01333,
    # chi-square with 2 degrees of freedom: p = exp(-Q / 2).
    p = pool([1.0, 1.2, 0.9], [0.1, 0.1, 0.1])
    assert p.q == pytest.approx(14 / 3)
    assert p.p_value == pytest.approx(math.exp(-7 / 3))
    assert p.tau == pytest.approx(math.sqrt(0.04 / 3))
    assert p.mean == pytest.approx(31 / 30)
    assert p.std == pytest.approx(math.sqrt((0.01 + 0.04 / 3) / 3))
    # Four runs agree, the fifth is far off: it is excluded and the four are pooled.
    a = agreement([0.95, 0.97, 0.31, 0.96, 0.94], [0.02] * 5)
    assert a.excluded == (2,) and not a.disagree and a.pooled.mean == pytest.approx(0.955)
    # A spread with no odd run is kept (in tau); two runs that disagree leave no majority.
    spread = agreement([0.90, 0.95, 1.00, 1.05, 1.10], [0.01] * 5)
    assert spread.excluded == () and not spread.disagree and spread.pooled.tau > 0.05
    assert agreement([0.3, 1.0], [0.02, 0.02]).disagree


@pytest.fixture(scope="module")
def five_runs(tmp_path_factory):
    """Four runs of the nominal car and one whose motor has 0.6 x the throttle gain (20 s each)."""
    import dataclasses

    odd = dataclasses.replace(NOMINAL, corrections=dataclasses.replace(NOMINAL.corrections, throttle_gain=0.6))
    from sysid.data import common_grid_step

    logs = [generate_log(car, {}, 1 / 3, seed=seed, physics_dt=0.002)
            for car, seed in ((NOMINAL, 31), (NOMINAL, 32), (NOMINAL, 33), (NOMINAL, 34), (odd, 40))]
    dt = common_grid_step(logs)
    return [build_trajectory(log, dt) for log in logs]


@pytest.mark.parametrize("odd_in_fit", [True, False])
def test_runs_that_disagree_are_named_and_consistent_runs_are_not(five_runs, odd_in_fit):
    from sysid.data import concatenate
    from sysid.diagnose import candidates_for, restrict, run_agreement
    from sysid.excitation import excitation
    from sysid.model import ModelSetup

    traj = concatenate(five_runs)
    odd = 4
    settings = dataclasses_replace(SETTINGS, heldout_runs=(3,) if odd_in_fit else (odd,))
    horizon = int(round(settings.horizon_s / traj.dt))
    split = split_starts(traj, horizon, settings)
    cands, _ = restrict(candidates_for(NOMINAL), excitation(traj, split.train, horizon, NOMINAL))
    kept, verdicts = run_agreement(traj, split, horizon, ModelSetup(NOMINAL, dynamic=True), cands, NOMINAL, settings)
    assert {v.param for v in verdicts} >= {"throttle_gain", "steering_offset_rad", "steering_gain"}
    assert not any(v.agreement.disagree for v in verdicts)
    excluded = {v.param: v.excluded_runs for v in verdicts if v.excluded_runs}
    if odd_in_fit:
        gain = next(v for v in verdicts if v.param == "throttle_gain")
        assert gain.excluded_runs == (odd,)
        assert gain.values[gain.runs.index(odd)] == pytest.approx(0.6, abs=0.1)
        assert gain.agreement.pooled.mean == pytest.approx(1.0, abs=0.05)
        assert all(runs == (odd,) for runs in excluded.values())  # only the odd run is ever named
        assert next(c for c in kept if c.effect == "throttle_map").excluded_runs == (odd,)
    else:
        assert excluded == {}
        assert all(c.excluded_runs == () for c in kept)
