"""Model identification building blocks: log format, preprocessing, predictors and the sparse
regression, each against an independent reference (known geometry, the simulator's actuators,
solver_cpp's kinematic bicycle, a known sparse system)."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from sim import SimEffects, Simulator
from sysid.data import build_trajectory
from sysid.generate import generate_log, parse_effects
from tracks import load_track
from sysid.log import DriveLog, LogFormatError, read_log, write_log_csv
from sysid.model import ModelSetup, delayed_command, predict
from sysid.sparse import stlsq
from vehicles.dynamic_bicycle import ModelCoefficients, drive_force
from vehicles.params import CarParams

CAR = CarParams()
HEADER = "t,car,x,y,heading,throttle,steering"


def write(tmp_path: Path, text: str, name: str = "log.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def good_rows(n: int = 5) -> list[str]:
    return [f"{0.05 * i:.2f},0,{0.1 * i:.2f},0.0,0.0,0.2,0.0" for i in range(n)]


# ----------------------------------------------------------------------------- malformed logs
@pytest.mark.parametrize(
    "lines, where",
    [
        ([HEADER.replace(",steering", "")], "missing column(s) ['steering']"),
        ([HEADER, "0.0,0,0,0,0,0.2"], "row 2: expected 7 fields, got 6"),
        ([HEADER, *good_rows(2), "0.10,0,abc,0,0,0.2,0"], "row 4, column x: not a number"),
        ([HEADER, *good_rows(3), "0.15,0,0,nan,0,0.2,0"], "row 5, column y: must be finite"),
        ([HEADER, *good_rows(1), "0.05,0,0,0,0,1.5,0"], "row 3, column throttle"),
        ([HEADER, "0.05,0,0,0,0,0.5,2.0"], "row 2, column steering"),
        ([HEADER, "0.05,1.5,0,0,0,0.5,0.1"], "row 2, column car"),
        ([HEADER, *good_rows(3), "0.01,0,0,0,0,0.2,0"], "row 5, column t: time goes backwards"),
        ([HEADER + ",speed", "0.0,0,0,0,0,0.2,0,-1"], "row 2, column speed"),
        ([HEADER], "no data rows"),
    ],
)
def test_malformed_logs_name_row_and_column(tmp_path, lines, where):
    path = write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(LogFormatError) as err:
        read_log(path)
    assert where in str(err.value)
    assert str(path) in str(err.value)


def test_row_numbers_count_comment_and_blank_lines(tmp_path):
    path = write(tmp_path, "# recorded on the oval\n" + HEADER + "\n\n" + good_rows(1)[0] + "\n0.1,0,x,0,0,0,0\n")
    with pytest.raises(LogFormatError, match="row 5, column x"):
        read_log(path)


def test_damaged_rrd_and_unknown_formats_are_rejected_clearly(tmp_path):
    with pytest.raises(LogFormatError, match="corrupt recording .*Not an RRD file"):
        read_log(write(tmp_path, "not a recording", "run.rrd"))
    with pytest.raises(LogFormatError, match="recording not found"):
        read_log(tmp_path / "missing.rrd")
    with pytest.raises(LogFormatError, match="unknown log format '.txt'"):
        read_log(write(tmp_path, "", "run.txt"))


def test_csv_round_trip_and_car_selection(tmp_path):
    rows = [HEADER] + [f"{0.1 * i:.1f},{i % 2},{i},{-i},0.1,0.0,0.05" for i in range(6)]
    log = read_log(write(tmp_path, "\n".join(rows)))
    assert log.cars == [0, 1]
    car1 = log.select_car(1)
    np.testing.assert_allclose(car1.x, [1, 3, 5])
    np.testing.assert_array_equal(car1.row, [3, 5, 7])
    with pytest.raises(LogFormatError, match="no rows for car 7"):
        log.select_car(7)
    again = read_log(write_log_csv(tmp_path / "again.csv", log))
    np.testing.assert_allclose(again.x, log.x)
    np.testing.assert_array_equal(again.car, log.car)


# ----------------------------------------------------------------------------- preprocessing
def circle_log(t: np.ndarray, radius=0.8, speed=1.2, duplicate_at=(), extra_columns=False) -> DriveLog:
    """A car on a circle at constant speed (counter-clockwise): heading = angle + pi/2."""
    angle = speed / radius * t
    x, y = radius * np.cos(angle), radius * np.sin(angle)
    heading = np.angle(np.exp(1j * (angle + math.pi / 2)))
    steer = np.full(t.size, math.atan(CAR.geometry.wheelbase_m / radius))
    return DriveLog("<circle>", t, np.zeros(t.size, dtype=int), x, y, heading, np.full(t.size, 0.3), steer, None,
                    np.arange(2, t.size + 2))


def test_speed_and_yaw_rate_of_a_circle_with_uneven_sampling_and_a_gap():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.028, 0.039, 600))  # ~30 Hz with jitter
    t = np.concatenate([t[:300], t[300:] + 0.5])  # 0.5 s gap
    traj = build_trajectory(circle_log(t))
    assert traj.n_gaps == 1 and np.unique(traj.segment).size == 2
    np.testing.assert_allclose(traj.dt, np.mean(np.diff(t)[np.diff(t) < 0.1]), rtol=1e-12)
    np.testing.assert_allclose(traj.speed, 1.2, rtol=2e-3)
    np.testing.assert_allclose(traj.yaw_rate, 1.5, rtol=2e-3)
    np.testing.assert_allclose(traj.vy, 0.0, atol=3e-3)
    assert traj.position_noise_m < 1e-4


def test_duplicate_timestamps_are_merged():
    t = np.arange(100) / 30.0
    log = circle_log(t)
    # Repeat row 10 with a pose shifted by +2 mm and a different command: poses average, last command wins.
    keep = np.insert(np.arange(100), 11, 10)
    dup = DriveLog(log.source, log.t[keep], log.car[keep], log.x[keep].copy(), log.y[keep], log.heading[keep],
                   log.throttle[keep].copy(), log.steering[keep], None, np.arange(2, 103))
    dup.x[11] += 0.002
    dup.throttle[11] = 0.9
    traj = build_trajectory(dup)
    assert traj.n_duplicates_merged == 1 and traj.n == 100
    assert traj.x[10] == pytest.approx(log.x[10] + 0.001)
    assert traj.throttle[10] == 0.9 and traj.throttle[9] == 0.3


def test_too_short_log_is_rejected():
    with pytest.raises(LogFormatError, match="no stretch of the log is long enough"):
        build_trajectory(circle_log(np.arange(10) / 30.0))


# ----------------------------------------------------------------------------- predictors
def test_delayed_command_is_the_mean_of_the_shifted_held_command_and_matches_the_simulator():
    dt, delay, n = 1 / 30, 0.08, 40
    cmds = np.random.default_rng(1).uniform(-0.3, 0.3, n)

    class Grid:  # the two fields delayed_command reads
        seg_start = np.zeros(n, dtype=int)

    Grid.dt = dt
    ours = delayed_command(Grid, cmds, np.arange(n), delay)
    # Reference: the zero-order-hold command shifted by the delay, averaged on a fine time grid.
    k = np.arange(3, n)
    fine = (np.arange(200) + 0.5) / 200
    ref = [np.mean(cmds[np.floor(((i + fine) * dt - delay) / dt + 1e-9).astype(int)]) for i in k]
    np.testing.assert_allclose(ours[k], ref, atol=1e-9)

    # The simulator's FIFO: with no rate limit the servo angle at the end of interval i is the
    # command sent 0.08 s = 2.4 intervals earlier, i.e. at i - 2.
    fast = CarParams(actuators=dataclasses.replace(CarParams().actuators, steering_rate_limit_radps=1e6))
    sim = Simulator(load_track("oval"), [fast], effects=SimEffects(steering_delay_s=delay))
    sim.reset([[2.5, 0.5, 0, 0.5, 0, 0]])
    servo = []
    for c in cmds:
        sim.step([[0.1, c]], dt)
        servo.append(sim.applied_inputs(0)[1])
    np.testing.assert_allclose(servo[2:], cmds[:-2], atol=1e-12)


def test_kinematic_prediction_matches_solver_cpp_kinematic_bicycle_at_fine_steps():
    solver_cpp = pytest.importorskip("solver_cpp")
    t = np.arange(300) / 30.0
    log = circle_log(t)
    rng = np.random.default_rng(3)
    log.throttle[:] = np.clip(0.3 + 0.3 * rng.standard_normal(t.size), -1, 1)
    log.steering[:] = 0.2 * np.sin(t * 2.0)
    traj = build_trajectory(log)
    # Actuators without rate limits: this checks the integration (the actuator chain has its own test).
    car = CarParams(actuators=dataclasses.replace(CarParams().actuators, steering_rate_limit_radps=1e6,
                                                  throttle_rate_limit_per_s=1e6))
    start, horizon = np.array([40]), 30
    ours = predict(traj, start, horizon, ModelSetup(car))[0]
    # Reference: solver_cpp's (Euler) kinematic bicycle at 1/100 of the sample period, acceleration
    # from the drive model re-evaluated every fine step; converges to the ODE the predictor solves.
    n_fine = 100
    model = solver_cpp.KinematicBicycle(car.geometry.lf_m, car.geometry.lr_m).build(traj.dt / n_fine)
    k = ModelCoefficients.from_params(car)
    x = np.array([traj.xs[40], traj.ys[40], traj.speed[40], traj.headings[40]])
    for j in range(horizon):
        for _ in range(n_fine):
            a = float(drive_force(np.array(x[2]), np.array(traj.throttle[40 + j]), k, partials=False)[0])
            x = model.eval(x, np.array([a / car.inertia.mass_kg, traj.steering[40 + j]]))[0]
    assert np.hypot(ours[-1, 0] - x[0], ours[-1, 1] - x[1]) < 2e-3  # Euler error at dt/100
    assert abs(ours[-1, 2] - x[3]) < 1e-3 and abs(ours[-1, 3] - x[2]) < 1e-3


@pytest.fixture(scope="module")
def noise_free_traj():
    """15 s of the nominal car, no measurement noise (shared by the predictor tests)."""
    log = generate_log(CAR, {}, 0.25, seed=5, position_noise_m=0.0, heading_noise_rad=0.0, physics_dt=0.002)
    return build_trajectory(log)


def test_dynamic_prediction_reproduces_a_noise_free_simulation(noise_free_traj):
    # Generated with the nominal car: the predictor's dynamic model is the simulator's physics, so
    # one-second predictions from the estimated states land within millimetres (actuator rate limits
    # and state estimation from poses are the only differences).
    traj = noise_free_traj
    starts = np.arange(10, 190, 5)
    pred = predict(traj, starts, 30, ModelSetup(CAR, dynamic=True))
    err = np.hypot(pred[:, -1, 0] - traj.x[starts + 30], pred[:, -1, 1] - traj.y[starts + 30])
    kin = predict(traj, starts, 30, ModelSetup(CAR))
    err_kin = np.hypot(kin[:, -1, 0] - traj.x[starts + 30], kin[:, -1, 1] - traj.y[starts + 30])
    assert np.sqrt(np.mean(err**2)) < 0.01
    assert np.sqrt(np.mean(err_kin**2)) > 5 * np.sqrt(np.mean(err**2))  # the planner's model misses tyre slip


def test_hot_path_rates_and_batched_setups_equal_the_model_one_at_a_time(noise_free_traj):
    """The predictor's rates (input terms once per sub-step, vx/vy/yaw-rate rates without the pose) equal
    vehicles.dynamic_bicycle.derivative in all three speed regimes, and stacked setups (different delays,
    play, asymmetry, drift, gain, throttle curvature, [other_terms]) predict what each predicts alone."""
    from vehicles.dynamic_bicycle import body_rates, derivative, input_terms
    from vehicles.extra_terms import LIBRARY, terms_from_coefficients

    assert {"u*v", "d*v"} <= set(LIBRARY)

    rng = np.random.default_rng(6)
    for lo, hi in ((-0.5, 0.14), (0.16, 0.34), (0.4, 3.5), (-0.5, 3.5)):  # kinematic, blend, dynamic, mixed
        n = 400
        state = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(-4, 4, n),
                                 rng.uniform(lo, hi, n), rng.uniform(-0.4, 0.4, n), rng.uniform(-6, 6, n)])
        u = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-0.47, 0.47, n)])
        k = ModelCoefficients.from_params(CAR)
        want = derivative(state, u, k)[:, 3:]
        got = np.column_stack(body_rates(state[:, 3], state[:, 4], state[:, 5], input_terms(u[:, 0], u[:, 1], k), k))
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)

    traj = noise_free_traj
    starts = np.arange(20, 180, 7)
    cars = [dataclasses.replace(CAR, corrections=dataclasses.replace(CAR.corrections, **c)) for c in (
        {}, {"steering_delay_s": 0.03, "throttle_delay_s": 0.011}, {"steering_backlash_rad": 0.05},
        {"steering_gain_asymmetry": 0.1, "steering_gain": 0.9}, {"motor_force_drift_per_s": 0.002})]
    cars.append(dataclasses.replace(CAR, corrections=dataclasses.replace(CAR.corrections, throttle_curvature=0.4)))
    # [other_terms] may differ between stacked setups too (one term shared with another value, one not).
    cars += [dataclasses.replace(CAR, other_terms=terms_from_coefficients(a, y)) for a, y in (
        ({"u*v": 0.3}, {}), ({"u*v": -0.2}, {"d*v": 0.5}))]
    import sysid.model

    for dynamic in (True, False):
        sysid.model._PREDICTION_CACHE.clear()
        alone = [predict(traj, starts, 30, ModelSetup(c, dynamic)) for c in cars]
        sysid.model._PREDICTION_CACHE.clear()
        together = predict(traj, starts, 30, [ModelSetup(c, dynamic) for c in cars])
        for want, pred in zip(alone, together):
            np.testing.assert_allclose(pred, want, rtol=0, atol=1e-12)


def test_fits_side_by_side_equal_the_fits_alone(monkeypatch):
    """sysid.lockstep runs independent fits with their predictions batched per round: the fitted values
    are those of each fit run alone, and the rounds need fewer prediction calls than the fits alone."""
    import sysid.model
    from sysid.diagnose import CANDIDATES, SysidSettings, fit_candidates, split_starts
    from sysid.lockstep import side_by_side

    log = generate_log(CAR, parse_effects("actuation_delay=0.05"), 0.3, seed=9, physics_dt=0.002)
    traj = build_trajectory(log)
    settings = SysidSettings(fit_max_starts=30, heldout_max_starts=100)
    split = split_starts(traj, 30, settings)
    base = ModelSetup(CAR, dynamic=True)
    cands = [c for c in CANDIDATES if c.effect in ("steering_offset", "actuation_delay", "steering_backlash")]
    calls = []
    real = sysid.model.predict
    monkeypatch.setattr(sysid.model, "predict", lambda *a: calls.append(1) or real(*a))

    def fits():
        return [lambda c=c: fit_candidates(traj, split, 30, base, [c], settings) for c in cands]

    sysid.model._PREDICTION_CACHE.clear()
    alone = [f() for f in fits()]
    n_alone = len(calls)
    sysid.model._PREDICTION_CACHE.clear()
    calls.clear()
    together = side_by_side(fits())
    assert len(calls) < 0.6 * n_alone
    for a, b in zip(alone, together):
        assert a.values.keys() == b.values.keys()
        for name in a.values:
            assert b.values[name] == pytest.approx(a.values[name], rel=1e-6, abs=1e-9), name
    delay = next(f for f in alone if "steering_delay_s" in f.values)
    assert delay.values["steering_delay_s"] == pytest.approx(0.05, rel=0.3)  # the fit itself worked


# ----------------------------------------------------------------------------- sparse regression
def test_stlsq_recovers_a_known_sparse_law():
    rng = np.random.default_rng(4)
    theta = rng.normal(size=(2000, 8))
    truth = np.array([0.0, 1.5, 0.0, 0.0, -0.7, 0.0, 0.0, 0.0])
    target = theta @ truth + 0.05 * rng.normal(size=2000)
    coef = stlsq(theta, target, threshold=0.1)
    assert np.array_equal(coef != 0, truth != 0)
    np.testing.assert_allclose(coef, truth, atol=0.01)


def test_generator_effect_names_are_checked():
    assert parse_effects("steering_offset=0.03, actuation_delay=0.08") == {"steering_offset": 0.03,
                                                                        "actuation_delay": 0.08}
    for bad, msg in (("grip=0.5", "unknown effect 'grip'"), ("steering_gain", "must look like name=value"),
                     ("steering_gain=x", "not a number"), ("tire_slip=0.5,tire_slip=0.6", "given twice")):
        with pytest.raises(ValueError, match=msg):
            parse_effects(bad)
