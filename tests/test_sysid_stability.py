"""Leave-one-run-out: claims fitted on several runs must agree across folds within their reported uncertainties,
survive leaving out any one training run, and a run that differs must not move them (docs/sysid.md, "Stable under
leaving out a run"). Logs from the project's simulator (sysid.generate), not from the fitter."""

import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sysid.agreement import jackknife_std
from sysid.data import common_grid_step, build_trajectory, concatenate
from sysid.diagnose import SysidSettings, identify
from sysid.generate import generate_log, parse_effects
from vehicles.params import load_car_params

NOMINAL = load_car_params("buzzracer")
SETTINGS = SysidSettings(fit_max_starts=80, heldout_max_starts=300, n_bootstrap=200)
TRUE_OFFSET = 0.03
ODD = 4  # the run whose steering offset differs


def test_jackknife_std_of_a_mean_is_the_standard_error():
    # For the sample mean, the leave-one-out means give exactly s / sqrt(n) (Efron and Stein 1981).
    x = np.array([1.0, 4.0, 2.5, 7.0, 3.0])
    loo = [(x.sum() - xi) / (x.size - 1) for xi in x]
    assert jackknife_std(loo) == pytest.approx(np.std(x, ddof=1) / math.sqrt(x.size))
    # By hand: values 1, 2, 3, 4 -> mean 2.5, squared deviations 5, sqrt(3/4 * 5).
    assert jackknife_std([1.0, 2.0, 3.0, 4.0]) == pytest.approx(math.sqrt(3.75))
    assert jackknife_std([0.7]) == 0.0


@pytest.fixture(scope="module")
def folds():
    """Four 20 s runs of a car with a 0.03 rad steering offset and one with -0.01 rad (run ODD); each run held
    out in turn, identified on the other four."""
    specs = [(TRUE_OFFSET, 51), (TRUE_OFFSET, 52), (TRUE_OFFSET, 53), (TRUE_OFFSET, 54), (-0.01, 55)]
    logs = [generate_log(NOMINAL, parse_effects(f"steering_offset={off}"), 1 / 3, seed=seed, physics_dt=0.002)
            for off, seed in specs]
    dt = common_grid_step(logs)
    traj = concatenate([build_trajectory(log, dt) for log in logs])
    return {k: identify(traj, NOMINAL, replace(SETTINGS, heldout_runs=(k,))) for k in range(len(specs))}


def _claim(result, param):
    for e in result.selected:
        if param in e.params:
            return e.params[param], e.params_std[param]
    return None


def test_claims_agree_across_folds_and_survive_leaving_out_a_run(folds):
    claims = {k: _claim(r, "steering_offset_rad") for k, r in folds.items() if k != ODD}
    # Every fold trained on the odd run and three shared ones claims the offset; the odd run is excluded from it.
    assert all(c is not None for c in claims.values())
    for k, r in folds.items():
        if k == ODD:
            continue
        verdict = next(a for a in r.run_agreement if a.param == "steering_offset_rad")
        assert verdict.excluded_runs == (ODD,)
        checks = [c for c in r.claim_stability if c.effect == "steering_offset"]
        # Each shared training run left out in turn (the odd one is excluded from the fit anyway): still claimed.
        assert sorted(c.dropped_run for c in checks) == sorted(set(range(5)) - {k, ODD})
        assert all(c.significant for c in checks)
        # ... and the refit without a shared run predicts that run too (the truth there is the same 0.03).
        assert all(c.on_run is not None and c.on_run.significant for c in checks)
        assert claims[k][1] >= jackknife_std([c.values["steering_offset_rad"] for c in checks])
    # Pairwise agreement within the reported uncertainties, and with the truth.
    for a in claims.values():
        assert a[0] == pytest.approx(TRUE_OFFSET, abs=3 * a[1] + 1e-3)
        for b in claims.values():
            assert abs(a[0] - b[0]) <= 2 * math.hypot(a[1], b[1])


def test_a_run_that_differs_is_not_predicted_by_the_shared_claim(folds):
    # Held out, the odd run (offset -0.01) is made worse by the others' 0.03: nothing is claimed from them.
    r = folds[ODD]
    assert _claim(r, "steering_offset_rad") is None
    verdict = next(a for a in r.run_agreement if a.param == "steering_offset_rad")
    assert verdict.agreement.verdict == "runs agree"
    assert verdict.agreement.pooled.mean == pytest.approx(TRUE_OFFSET, abs=0.005)


# ----------------------------------------------------------------------------- the shared F1/10 runs
SHARED = Path(os.environ.get("RD3G_SHARED_DIR") or Path(__file__).resolve().parents[2] / "shared")
F110_RUNS = SHARED / "data" / "real-drive-logs" / "frictionmaps-f110"


def first_order_response_scale(traj, run: int, nominal_gain: float, horizon_s: float = 0.2, seed: int = 0):
    """An estimate of the speed loop's gain independent of the identification: windows of ``horizon_s`` with a
    constant set-point V and |V - v| > 0.3 m/s, the wheel speed's first-order response
    v(t + h) = V + (v(t) - V) exp(-g h) fitted by a grid search over g (no delay modelled), over ``nominal_gain``;
    the p5-p95 range of a bootstrap over 2 s blocks. Returns (scale, p5, p95, windows)."""
    m = np.flatnonzero(traj.run == run)
    v_set, v, seg = traj.throttle[m], np.abs(traj.speed[m]), traj.segment[m]
    n = max(1, int(round(horizon_s / traj.dt)))
    i = np.arange(v_set.size - n)
    held = np.ptp(np.stack([v_set[i + j] for j in range(n + 1)]), axis=0) < 0.05
    i = i[(seg[i] == seg[i + n]) & held & (np.abs(v_set[i] - v[i]) > 0.3)]
    gains = np.linspace(0.05, 40.0, 800)
    decay = np.exp(-gains * n * traj.dt)[:, None]

    def best(j):
        pred = v_set[j][None] + (v[j] - v_set[j])[None] * decay
        return gains[int(np.argmin(np.mean((pred - v[j + n][None]) ** 2, axis=1)))]

    block = (traj.elapsed[m][i] // 2.0).astype(int)
    blocks = np.unique(block)
    rng = np.random.default_rng(seed)
    boot = [best(np.concatenate([i[block == b] for b in rng.choice(blocks, blocks.size)])) for _ in range(200)]
    p5, p95 = np.percentile(boot, [5, 95]) / nominal_gain
    return best(i) / nominal_gain, p5, p95, i.size


@pytest.mark.skipif(not F110_RUNS.is_dir(), reason="F1/10 runs not found (shared/ beside the repository, or set "
                                                     "RD3G_SHARED_DIR)")
def test_f110_speed_loop_response_differs_between_runs():
    """Why speed_response is not claimed on the F1/10 runs (docs/sysid.md, "Fit on four, predict the fifth"): an
    estimate independent of the fitter puts DS1's loop near the nominal gain and DS5's at about half of it (their
    bootstrap ranges do not overlap), and DS3's VESC hardly follows its set-point at all."""
    from sysid.data import build_runs
    from sysid.f110 import read_f110_run

    names = [f"DS{k}" for k in range(1, 6)]
    traj = build_runs([read_f110_run(F110_RUNS / n) for n in names])
    by_name = {Path(r.source).name: i for i, r in enumerate(traj.runs)}
    gain = load_car_params("f110").speed_control.gain_per_s
    est = {n: first_order_response_scale(traj, by_name[n], gain) for n in names}
    for n, (scale, p5, p95, windows) in est.items():
        print(f"{n}: speed_response_scale {scale:.2f} (p5-p95 {p5:.2f}-{p95:.2f}, {windows} windows)")
    assert est["DS1"][1] > est["DS5"][2]  # DS1's p5 above DS5's p95
    assert 0.7 < est["DS1"][0] < 1.2 and 0.3 < est["DS5"][0] < 0.65
    assert est["DS3"][2] < 0.05


@pytest.mark.skipif(not F110_RUNS.is_dir(), reason="F1/10 runs not found (shared/ beside the repository, or set "
                                                     "RD3G_SHARED_DIR)")
def test_f110_runs_want_different_speed_loops():
    """The fit residual of each training run of the DS3 fold at fixed speed_response_scale (the dynamic model of
    vehicles/f110.toml): DS1 and DS2 fit a loop at or above the nominal gain and get clearly worse at a third of it;
    DS4 and DS5 the reverse. No single value of the grid fits all four within 9 % of each run's best."""
    from sysid.data import build_runs
    from sysid.diagnose import SysidSettings, _fit_steps, _residual, split_starts, with_corrections
    from sysid.f110 import read_f110_run
    from sysid.model import ModelSetup, predict

    names = [f"DS{k}" for k in range(1, 6)]
    traj = build_runs([read_f110_run(F110_RUNS / n) for n in names])
    by_name = {Path(r.source).name: i for i, r in enumerate(traj.runs)}
    s = SysidSettings(heldout_runs=(by_name["DS3"],))
    horizon = int(round(s.horizon_s / traj.dt))
    split = split_starts(traj, horizon, s)
    car = load_car_params("f110")
    values = np.array([0.2, 0.33, 0.45, 0.56, 0.7, 1.0, 1.5, 2.0, 3.0])
    setups = [ModelSetup(with_corrections(car, {"speed_response_scale": v}), dynamic=True) for v in values]
    steps = _fit_steps(horizon, s.fit_steps)
    rel = {}
    for n in ("DS1", "DS2", "DS4", "DS5"):
        starts = split.fit[traj.run[split.fit] == by_name[n]]
        cost = np.array([np.mean(_residual(traj, starts, p, steps) ** 2) for p in predict(traj, starts, horizon, setups)])
        rel[n] = cost / cost.min()
        print(n, " ".join(f"{v:g}: {c:.3f}" for v, c in zip(values, rel[n])))
    at = {v: i for i, v in enumerate(values)}
    assert rel["DS1"][at[0.33]] > 1.15 and rel["DS2"][at[0.33]] > 1.15
    assert rel["DS4"][at[1.0]] > 1.15 and rel["DS5"][at[1.0]] > 1.15
    assert np.all(np.max(np.stack(list(rel.values())), axis=0) > 1.09)
