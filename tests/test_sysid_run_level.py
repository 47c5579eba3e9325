"""Run-level parameters (docs/sysid.md, "Run-level parameters"): a speed set-point car whose speed loop responds
at a different rate in each run. The runs are simulated here, independently of the fitter's predictor: the car's
equations (vehicles.dynamic_bicycle.derivative) integrated by classic RK4 at 1 ms with the commands held between
40 Hz command ticks and the steering rate-limited, then sampled at 40 Hz with noise on the poses and the wheel
speed. The truth of each run's speed loop is known."""

import math
from dataclasses import replace

import numpy as np
import pytest

from sysid.data import build_trajectory, common_grid_step, concatenate
from sysid.diagnose import (SysidSettings, candidates_for, evaluate, fit_other, identify, other_cross_run, split_starts,
                            with_corrections)
from sysid.log import CommandUnits, DriveLog
from sysid.model import ModelSetup
from sysid.run_level import RUN_LEVEL_EFFECTS, calibration_masks, population, RunValue
from vehicles.dynamic_bicycle import derivative
from vehicles.params import load_car_params

F110 = load_car_params("f110")
SCALES = (0.3, 0.45, 0.7, 1.0, 0.5)  # speed_response_scale per run; the last one is held out
HELD = len(SCALES) - 1
DURATION_S = 30.0
SETTINGS = SysidSettings(fit_max_starts=80, heldout_max_starts=800, n_bootstrap=200)


def simulate_runs(scales, seed: int, duration_s: float = DURATION_S, cmd_dt: float = 0.025,
                  torque_steer=None, cornering_drag=None) -> list[DriveLog]:
    """Drives on open ground, one per scale (simulated side by side): set-points redrawn in 1-3 m/s every 1.5-3 s,
    sine steering; RK4 at 5 ms (the speed loop's and the tyres' time constants are >= 30 ms). Effects outside the
    named candidates, per run: ``torque_steer`` c adds c * set-point * speed to the heading rate, ``cornering_drag``
    c adds -c * (wheel angle * speed)^2 to the speed's rate."""
    zeros = np.zeros(len(scales))
    torque = zeros if torque_steer is None else np.asarray(torque_steer, dtype=float)
    drag = zeros if cornering_drag is None else np.asarray(cornering_drag, dtype=float)
    rng = np.random.default_rng(seed)
    cars = [with_corrections(F110, {"speed_response_scale": sc}) for sc in scales]
    m = len(scales)
    h = 0.005
    n_cmd, per = int(round(duration_s / cmd_dt)), int(round(cmd_dt / h))
    t_cmd = np.arange(n_cmd) * cmd_dt
    setpoint = np.empty((m, n_cmd))
    for j in range(m):
        k = 0
        while k < n_cmd:
            n = int(rng.uniform(1.5, 3.0) / cmd_dt)
            setpoint[j, k:k + n] = rng.uniform(1.0, 3.0)
            k += n
    period, phase = rng.uniform(3.0, 5.0, m), rng.uniform(0, 2 * math.pi, m)
    steering = 0.12 * np.sin(2 * math.pi * t_cmd[None] / period[:, None] + phase[:, None])
    state = np.zeros((m, 6))
    state[:, 3] = setpoint[:, 0]
    wheel = np.zeros(m)
    rate = F110.actuators.steering_rate_limit_radps * h
    poses = np.empty((m, n_cmd, 4))
    for i in range(n_cmd):
        poses[:, i] = state[:, :4]
        for _ in range(per):
            wheel += np.clip(steering[:, i] - wheel, -rate, rate)
            u = np.stack([setpoint[:, i], wheel], axis=1)

            def rates(x: np.ndarray) -> np.ndarray:
                xdot = derivative(x, u, cars)
                xdot[:, 2] += torque * setpoint[:, i] * x[:, 3]
                xdot[:, 3] -= drag * (wheel * x[:, 3]) ** 2
                return xdot

            k1 = rates(state)
            k2 = rates(state + 0.5 * h * k1)
            k3 = rates(state + 0.5 * h * k2)
            k4 = rates(state + h * k3)
            state = state + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    poses += rng.normal(size=poses.shape) * np.array([0.005, 0.005, 0.005, 0.03])
    return [DriveLog(f"<run {j}: scale {sc}>", t_cmd, np.zeros(n_cmd, dtype=int), *poses[j, :, :3].T, setpoint[j],
                     steering[j], np.abs(poses[j, :, 3]), np.arange(2, n_cmd + 2), units=CommandUnits("rad", "speed"))
            for j, sc in enumerate(scales)]


@pytest.fixture(scope="module")
def result():
    logs = simulate_runs(SCALES, seed=60)
    dt = common_grid_step(logs)
    traj = concatenate([build_trajectory(log, dt) for log in logs])
    # Runs are in canonical order in the trajectory: the truth goes by their source.
    truth = [SCALES[[log.source for log in logs].index(r.source)] for r in traj.runs]
    held = [r.source for r in traj.runs].index(logs[HELD].source)
    return identify(traj, F110, replace(SETTINGS, heldout_runs=(held,))), truth, held


def test_population_pool_is_the_log_scale_random_effects_mean():
    # Equal stds on the log scale, no spread beyond them: the pool is the geometric mean, its std sigma / sqrt(k).
    values = [RunValue(0, 0.5, 0.05, 100), RunValue(1, 0.5 * math.e ** 0.02, 0.05 * math.e ** 0.02, 100)]
    pop = population(values)
    assert pop.value == pytest.approx(0.5 * math.e ** 0.01, rel=1e-9)
    assert pop.log_pool.tau == 0.0 and pop.std == pytest.approx(pop.value * 0.1 / math.sqrt(2), rel=1e-9)
    # Runs far apart: the spread is in the population's std (a factor of e between two runs: tau ~ 0.7).
    far = population([RunValue(0, 0.3, 0.003, 100), RunValue(1, 0.3 * math.e, 0.003 * math.e, 100)])
    assert far.spread_factor == pytest.approx(math.exp(math.sqrt(0.5 - 0.01 ** 2)), rel=1e-6)
    assert far.std > 0.3 * far.value
    cal, later = calibration_masks(np.array([0.0, 19.0, 19.5, 20.0]), np.array([1.0, 20.0, 20.5, 21.0]), 20.0)
    assert cal.tolist() == [True, False, False, False] and later.tolist() == [False, False, False, True]


def test_per_run_speed_loops_and_their_population_come_back(result):
    result, scales, held = result
    (rl,) = result.run_level
    assert rl.param == "speed_response_scale" and not rl.not_excited
    got = {r.run: (r.value, r.std) for r in rl.runs}
    truth = {i: s for i, s in enumerate(scales) if i != held}
    assert set(got) == set(truth)
    for i, (v, sd) in got.items():
        print(f"run {i}: {v:.4f} ± {sd:.4f} (truth {truth[i]})")
        assert abs(v - truth[i]) <= 3 * sd + 0.02 * truth[i]
    # The population: the geometric mean of the training runs' truths within its std, which carries their spread.
    geo = math.exp(np.mean(np.log(list(truth.values()))))
    pop = rl.population
    print(f"population {pop.value:.4f} ± {pop.std:.4f} (geometric mean of the truths {geo:.4f}), "
          f"spread x{pop.spread_factor:.2f}")
    assert abs(pop.value - geo) <= 2 * pop.std
    assert pop.spread_factor > 1.3  # the runs really differ (0.3-1.0)
    # The held-out run's own loop lies within the population's spread for a new run.
    assert abs(SCALES[HELD] - pop.value) <= 2 * pop.run_std


def test_heldout_run_is_predicted_with_the_population_and_calibrated_on_its_first_block(result):
    result, _, held = result
    (rl,) = result.run_level
    (h,) = rl.heldout
    assert h.run == held
    # The population value (about 0.56) is closer to the held-out run's 0.5 than the file's 1.0: better speed.
    assert h.population.horizon_speed_rmse_mps < h.shared.horizon_speed_rmse_mps
    c = h.calibration
    assert c.value is not None and c.block_s == SETTINGS.calibration_s and c.windows >= 100
    print(f"calibrated on the first {c.block_s} s: {c.value:.4f} ± {c.std:.4f} (truth {SCALES[HELD]}); speed RMSE "
          f"after it {c.shared.horizon_speed_rmse_mps:.4f} / {c.population.horizon_speed_rmse_mps:.4f} / "
          f"{c.calibrated.horizon_speed_rmse_mps:.4f}")
    assert abs(c.value - SCALES[HELD]) <= 3 * c.std + 0.02 * SCALES[HELD]
    assert c.calibrated.horizon_speed_rmse_mps <= c.population.horizon_speed_rmse_mps * 1.02
    # What goes into the car file: the population value only if it passes the keep test held out.
    written = result.car_out.corrections.speed_response_scale
    assert written == (rl.population.value if rl.written else F110.corrections.speed_response_scale)
    assert ("speed_response" in [e.effect for e in result.selected]) == rl.written


# ----------------------------------------------------------------------------- `other` beside a run-level parameter
def _runs_at_their_true_loops(seed, torque_steer=None):
    """The five runs with the held-out one held out, and the dynamic model with each run's true loop in place."""
    logs = simulate_runs(SCALES, seed=seed, torque_steer=torque_steer)
    dt = common_grid_step(logs)
    traj = concatenate([build_trajectory(log, dt) for log in logs])
    order = [[log.source for log in logs].index(r.source) for r in traj.runs]  # canonical order -> given order
    horizon = int(round(SETTINGS.horizon_s / dt))
    split = split_starts(traj, horizon, replace(SETTINGS, heldout_runs=(order.index(HELD),)))
    truth = tuple(SCALES[i] for i in order)
    setup = ModelSetup(F110, dynamic=True, run_values=(("speed_response_scale", truth),))
    return traj, split, horizon, evaluate(traj, split, horizon, setup), order


LOOP = tuple(c for c in candidates_for(F110) if c.effect in RUN_LEVEL_EFFECTS)


def test_other_that_every_run_has_holds_on_each_run_it_was_not_fitted_on():
    # Torque steer (heading rate 0.1 x set-point x speed) in every run, each with its own speed loop: fitted without
    # any one training run, `other` finds the term and predicts that run by the keep test.
    traj, split, horizon, base, order = _runs_at_their_true_loops(64, [0.1] * len(SCALES))
    checks = other_cross_run(traj, split, horizon, base, LOOP, SETTINGS)
    for k in checks:
        print(order[k.run], k.params, round(k.verdict.heldout_error_reduction, 3))
    assert sorted(order[k.run] for k in checks) == [0, 1, 2, 3]
    assert all(k.significant for k in checks)
    assert all(abs(k.params["yaw_rate[u*v]"] - 0.1) <= 0.02 for k in checks)


def test_other_that_only_some_sessions_have_does_not_hold_across_runs():
    # The same torque steer in three of the four training runs (and the held-out run), none in the fourth: a session,
    # not the car. Fitted on all four, `other` finds the term; fitted without the fourth it finds it at full strength
    # and makes the fourth run worse, so the check fails there and `other` would not be claimed.
    torque = [0.1] * len(SCALES)
    torque[3] = 0.0
    traj, split, horizon, base, order = _runs_at_their_true_loops(65, torque)
    assert "yaw_rate[u*v]" in fit_other(traj, split, horizon, base, SETTINGS)[1]
    checks = {order[k.run]: k for k in other_cross_run(traj, split, horizon, base, LOOP, SETTINGS)}
    for r, k in checks.items():
        print(r, k.params, round(k.verdict.heldout_error_reduction, 3))
    fourth = checks[3]
    assert abs(fourth.params["yaw_rate[u*v]"] - 0.1) <= 0.02
    assert not fourth.significant and fourth.verdict.heldout_error_reduction < 0


def test_other_does_not_take_the_run_level_loops_share():
    # Each run's speed loop at the file's value 1.0 where the truths are 0.3-1.0: the speed residual is all speed loop
    # (the simulated cars have nothing else). Alone, `other` explains it with loop-like terms (accel[u], accel[v]);
    # fitted beside the runs' own values, whose regressors are projected out of its speed terms, it finds nothing.
    logs = simulate_runs(SCALES[:HELD], seed=63)
    dt = common_grid_step(logs)
    traj = concatenate([build_trajectory(log, dt) for log in logs])
    horizon = int(round(SETTINGS.horizon_s / dt))
    split = split_starts(traj, horizon, replace(SETTINGS, heldout_runs=(0,)))
    nominal = (F110.corrections.speed_response_scale,) * traj.n_runs
    base = ModelSetup(F110, dynamic=True)
    alone = fit_other(traj, split, horizon, evaluate(traj, split, horizon, base), SETTINGS)[1]
    beside, terms, _ = fit_other(traj, split, horizon, evaluate(traj, split, horizon, replace(
        base, run_values=(("speed_response_scale", nominal),))), SETTINGS)
    print("alone:", alone, "beside the runs' values:", terms)
    assert any(t in alone for t in ("accel[u]", "accel[v]", "accel[u*v]"))  # the loop, if nothing else takes it
    assert not any(t.startswith("accel[") for t in terms)
    assert beside.setup.run_values == (("speed_response_scale", nominal),)  # no terms, no share to move
