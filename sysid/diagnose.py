"""Residual, diagnosis and model update (docs/sysid.md).

1. Predict from every measured state over the horizon with the planner's model (kinematic
   bicycle + longitudinal model + current corrections); split starts into training and
   held-out time blocks.
2. Reference model: the planner's model, or the car's own dynamic model (same parameters) if
   that predicts the training data significantly better (the car slides as its tyre
   parameters say; that is model structure, not a parameter deviation).
3. Candidates: each fitted on training data by least squares on the multi-step prediction
   error; kept by forward selection when the held-out improvement is significant (block
   bootstrap) and large enough (``min_reduction``). The sparse-regression fallback "other"
   is tried last, on top of the physical effects.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from sysid.agreement import Agreement, agreement, jackknife_std
from sysid.data import Trajectory
from sysid.excitation import Excitation, excitation
from sysid.lockstep import predict, side_by_side
from sysid.run_level import (RUN_LEVEL_EFFECTS, Calibration, HeldoutRun, RunLevelParam, RunValue,
                              calibration_masks, population)
from sysid.model import WARMUP_S, ModelSetup, PredictionErrors, actuation, prediction_errors, substeps
from sysid.sparse import coefficient_std, stlsq
from vehicles.extra_terms import LIBRARY, terms_from_coefficients
from vehicles.params import CarParams, OtherTermsParams

EFFECT_NAMES = ("actuation_delay", "steering_offset", "steering_gain", "tire_slip", "longitudinal_drag",
                "steering_backlash", "steering_asymmetry", "motor_drift", "throttle_map", "speed_map", "speed_response",
                "throttle_curvature", "other")


@dataclass(frozen=True)
class Candidate:
    effect: str
    params: tuple[str, ...]  # fields of [corrections]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    scale: tuple[float, ...]  # typical size, for the optimiser's scaling
    dynamic: bool = False  # needs the dynamic model
    drive: str = "any"  # "throttle": only for throttle cars (the motor law); "speed": only for speed set-point cars
    excluded_runs: tuple[int, ...] = ()  # runs that disagree with the others on it (sysid.agreement): not fitted on


CANDIDATES: tuple[Candidate, ...] = (
    Candidate("actuation_delay", ("steering_delay_s", "throttle_delay_s"), (0.0, 0.0), (0.4, 0.4), (0.03, 0.03)),
    Candidate("steering_offset", ("steering_offset_rad",), (-0.3,), (0.3,), (0.01,)),
    Candidate("steering_gain", ("steering_gain",), (0.2,), (5.0,), (0.05,)),
    Candidate("tire_slip", ("tire_grip_scale",), (0.05,), (5.0,), (0.1,), dynamic=True),
    Candidate("longitudinal_drag", ("extra_drag_n_per_mps2",), (-1.0,), (10.0,), (0.01,), drive="throttle"),
    Candidate("steering_backlash", ("steering_backlash_rad",), (0.0,), (0.3,), (0.01,)),
    Candidate("steering_asymmetry", ("steering_gain_asymmetry",), (-0.5,), (0.5,), (0.02,)),
    Candidate("motor_drift", ("motor_force_drift_per_s",), (-0.01,), (0.01,), (1e-4,), drive="throttle"),
    # The throttle-to-force map of a throttle car, apart from drag: gain and dead band.
    Candidate("throttle_map", ("throttle_gain", "throttle_dead_band"), (0.2, 0.0), (5.0, 0.5), (0.05, 0.02),
              drive="throttle"),
    # Its shape: progressive or degressive between no throttle and full throttle (the full-scale force stays).
    Candidate("throttle_curvature", ("throttle_curvature",), (-1.0,), (1.0,), (0.05,), drive="throttle"),
    # Speed set-point cars: the speed reached per commanded m/s, and the speed loop's response rate.
    Candidate("speed_map", ("speed_setpoint_gain",), (0.2,), (5.0,), (0.05,), drive="speed"),
    Candidate("speed_response", ("speed_response_scale",), (0.05,), (20.0,), (0.1,), drive="speed"),
)


def candidates_for(car: CarParams) -> tuple[Candidate, ...]:
    """The candidates that apply to the car's drive (throttle or speed set-point)."""
    drive = "speed" if car.speed_control.active else "throttle"
    return tuple(c for c in CANDIDATES if c.drive in ("any", drive))


@dataclass(frozen=True)
class NotIdentifiable:
    """Parameters of an effect the logs do not excite: not fitted, not claimed, not written."""

    effect: str
    params: tuple[str, ...]
    reasons: tuple[str, ...]


def _with_params(c: Candidate, ok: list[int]) -> Candidate:
    pick = lambda v: tuple(v[i] for i in ok)  # noqa: E731
    return dataclasses.replace(c, params=pick(c.params), lower=pick(c.lower), upper=pick(c.upper), scale=pick(c.scale))


def restrict(cands: tuple[Candidate, ...], exc: dict[str, Excitation]
             ) -> tuple[tuple[Candidate, ...], list[NotIdentifiable]]:
    """The candidates with only their excited parameters, and what was left out and why."""
    kept, left_out = [], []
    for c in cands:
        ok = [i for i, p in enumerate(c.params) if exc[p].identifiable]
        bad = [i for i in range(len(c.params)) if i not in ok]
        if bad:
            left_out.append(NotIdentifiable(c.effect, tuple(c.params[i] for i in bad),
                                            tuple(exc[c.params[i]].reason for i in bad)))
        if ok:
            kept.append(_with_params(c, ok))
    return tuple(kept), left_out
# Parameters whose cost is not convex from the neutral value: the fit starts from the best of these.
_START_GRID = {"steering_backlash_rad": (0.01, 0.02, 0.04, 0.08)}

GEOMETRY_GAIN_TOLERANCE = 0.15  # a steering gain further from 1 is reported as a geometry/steering-scale misfit
MIN_BOOTSTRAP_BLOCKS = 2  # held-out windows in fewer bootstrap blocks than this: no significance claimed
# Bounds of an `other` term's contribution over the data: beyond them a term is a fit artefact, not a car.
OTHER_MAX_ACCEL_MPS2 = 20.0
OTHER_MAX_YAW_RATE_RADPS = 5.0

# Scales of the fit residual: errors are divided by these so position, heading and speed weigh alike.
POSITION_SCALE_M = 0.01
HEADING_SCALE_RAD = 0.02
SPEED_SCALE_MPS = 0.05


@dataclass(frozen=True)
class SysidSettings:
    horizon_s: float = 1.0  # planning horizon over which predictions are compared
    block_s: float | None = None  # time blocks of the split; None: duration / 9, clamped to [3, 10] s
    heldout_every: int = 3  # every third block (one run: time blocks) or run (several runs) is held out
    # Several runs: indices (canonical order, Trajectory.runs) of the runs held out whole; None: every
    # heldout_every-th run (at least one). One run: time blocks.
    heldout_runs: tuple[int, ...] | None = None
    fit_max_starts: int = 300  # training windows used per fit (evenly spaced)
    heldout_max_starts: int = 2000
    fit_steps: int = 6  # horizon steps entering the fit residual (evenly spaced, last = horizon)
    min_reduction: float = 0.10  # smallest held-out horizon RMSE reduction that counts as an effect
    confidence: float = 0.95  # one-sided bootstrap confidence that the MSE reduction is > 0
    max_worsening: float = 0.05  # a claim may not raise the held-out horizon heading or speed RMSE by more
    bootstrap_block_s: float = 2.0
    n_bootstrap: int = 1000
    max_effects: int = 3
    sparse_threshold: float = 0.2  # STLSQ threshold, fraction of the target's standard deviation
    seed: int = 0
    # Run-level parameters: a held-out run is also calibrated on its own first block of this length (its own time)
    # and scored on the windows after it (sysid.run_level).
    calibration_s: float = 20.0


@dataclass(frozen=True)
class ErrorSummary:
    one_step_pos_rmse_m: float
    horizon_pos_rmse_m: float
    horizon_heading_rmse_rad: float
    horizon_speed_rmse_mps: float
    one_step_pos_p50_m: float
    one_step_pos_p95_m: float
    horizon_pos_p50_m: float
    horizon_pos_p90_m: float
    horizon_pos_p95_m: float

    def json_dict(self) -> dict[str, float]:
        keys = ("one_step_pos_rmse_m", "horizon_pos_rmse_m", "horizon_heading_rmse_rad", "horizon_speed_rmse_mps")
        return {k: float(getattr(self, k)) for k in keys}


def summarize(e: PredictionErrors) -> ErrorSummary:
    def rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(a * a)))

    one, end = e.position[:, 0], e.position[:, -1]
    return ErrorSummary(
        one_step_pos_rmse_m=rms(one),
        horizon_pos_rmse_m=rms(end),
        horizon_heading_rmse_rad=rms(e.heading[:, -1]),
        horizon_speed_rmse_mps=rms(e.speed[:, -1]),
        one_step_pos_p50_m=float(np.percentile(one, 50)),
        one_step_pos_p95_m=float(np.percentile(one, 95)),
        horizon_pos_p50_m=float(np.percentile(end, 50)),
        horizon_pos_p90_m=float(np.percentile(end, 90)),
        horizon_pos_p95_m=float(np.percentile(end, 95)),
    )


@dataclass(frozen=True)
class Split:
    train: np.ndarray  # start indices of training windows
    heldout: np.ndarray
    fit: np.ndarray  # subset of train used by the fits


def block_length(traj: Trajectory, s: SysidSettings) -> float:
    """Time blocks of the split of one run: ``block_s``, or duration / 9 clamped to [3, 10] s; a run too
    short for one held-out block of that length gets shorter blocks (never below the horizon + run-in)."""
    if s.block_s is not None:
        return float(s.block_s)
    duration = float(max(r.duration_s for r in traj.runs))
    block = float(np.clip(duration / 9.0, 3.0, 10.0))
    if duration < s.heldout_every * block:
        block = max(duration / (s.heldout_every + 0.5), s.horizon_s + WARMUP_S + 0.2)
    return block


def heldout_runs(traj: Trajectory, s: SysidSettings) -> tuple[int, ...]:
    """Runs held out whole (several runs), in canonical order; () for one run."""
    if traj.n_runs < 2:
        return ()
    if s.heldout_runs is not None:
        return tuple(sorted(set(s.heldout_runs)))
    picked = tuple(i for i in range(traj.n_runs) if i % s.heldout_every == s.heldout_every - 1)
    return picked or (traj.n_runs - 1,)


def split_starts(traj: Trajectory, horizon: int, s: SysidSettings) -> Split:
    """Windows that stay inside one segment (and, with one run, one time block). Several runs: the
    held-out runs are held out whole (cross-run validation); one run: time blocks alternate train /
    held-out."""
    k = np.arange(traj.n)
    end = k + horizon
    # Windows start WARMUP_S into a segment (the dynamic model's run-in) and end inside it.
    valid = (end < traj.seg_end) & (k - traj.seg_start >= int(round(WARMUP_S / traj.dt)))
    held = heldout_runs(traj, s)
    if held:
        if len(held) >= traj.n_runs:
            raise ValueError(f"every run is held out ({traj.n_runs} runs); leave at least one for the fit")
        heldout_mask = np.isin(traj.run, held)
        where = f"runs {', '.join(str(i + 1) for i in held)} held out whole"
    else:
        block_s = block_length(traj, s)
        block = traj.blocks(k, block_s)
        valid[valid] &= block[end[valid]] == block[valid]
        heldout_mask = (np.floor(traj.elapsed / block_s).astype(int) % s.heldout_every) == s.heldout_every - 1
        where = f"blocks of {block_s:.1f} s, every {s.heldout_every}rd held out; --block-length sets the length"
    train = k[valid & ~heldout_mask]
    heldout = k[valid & heldout_mask]
    if train.size < 20 or heldout.size < 20:
        raise ValueError(
            f"too little data for identification: {train.size} training and {heldout.size} held-out windows of "
            f"{horizon} steps (need >= 20 each; {where})"
        )
    return Split(train=train, heldout=thin(heldout, s.heldout_max_starts), fit=thin(train, s.fit_max_starts))


def thin(a: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` evenly spaced elements of ``a``."""
    return a if a.size <= n else a[np.round(np.linspace(0, a.size - 1, n)).astype(int)]


def with_corrections(car: CarParams, values: dict[str, float]) -> CarParams:
    return dataclasses.replace(car, corrections=dataclasses.replace(car.corrections, **values))


@dataclass(frozen=True)
class Fit:
    effects: tuple[str, ...]
    values: dict[str, float]  # fitted [corrections] fields
    std: dict[str, float]
    setup: ModelSetup
    heldout_errors: PredictionErrors
    heldout: ErrorSummary


@dataclass(frozen=True)
class CandidateResult:
    effect: str
    params: dict[str, float]
    params_std: dict[str, float]
    heldout_error_reduction: float  # 1 - RMSE_after / RMSE_before of the held-out horizon position error
    confidence: float  # bootstrap probability that the held-out MSE reduction is > 0
    significant: bool
    # Claimed effects: (RMSE of the final model refitted without it - RMSE final) / RMSE of the nominal
    # dynamic model, held-out horizon position error (docs/sysid.md, "Outputs").
    reduction_vs_nominal: float | None = None
    heading_reduction: float = 0.0  # 1 - RMSE_after / RMSE_before of the held-out horizon heading error
    speed_reduction: float = 0.0  # the same for the speed error


@dataclass
class SysidResult:
    settings: SysidSettings
    horizon_steps: int
    traj: Trajectory
    split: Split
    car_in: CarParams
    car_out: CarParams
    planner: Fit  # the planner's model, current corrections
    dynamic_nominal: Fit  # the dynamic model, current corrections
    reference: Fit  # what effects are measured against
    reference_is_dynamic: bool
    structure: CandidateResult  # dynamic model at current parameters vs the planner's model
    candidates: list[CandidateResult]  # each alone on top of the reference
    selected: list[CandidateResult]  # claimed effects in the order chosen; reductions are marginal
    final: Fit
    planner_after: Fit  # the planner's (kinematic) model with the new corrections
    effect_steps: list[tuple[Fit, Fit]] = field(default_factory=list)  # (before, after) per selected effect
    switched_after: list[str] | None = None  # effects chosen before the switch to the dynamic model
    families_compared: bool = False  # forward selection ran on both the kinematic and the dynamic model
    unnamed_effect_remains: bool = False  # `other` is significant: an effect the library cannot name
    dropped_after_other: list[str] = field(default_factory=list)  # named effects dropped once `other` was in
    not_identifiable: list[NotIdentifiable] = field(default_factory=list)  # not excited by the logs: not fitted
    run_agreement: list[RunAgreement] = field(default_factory=list)  # per parameter: do the training runs agree
    claim_stability: list[RunStability] = field(default_factory=list)  # each claim refitted without each training run
    run_level: list[RunLevelParam] = field(default_factory=list)  # per-run parameters, their population, held-out use
    other_cross_run: list[OtherCrossRun] = field(default_factory=list)  # `other` without each training run, on it
    numeric_warnings: int = 0  # numpy RuntimeWarnings of trial predictions, counted instead of printed

    @property
    def geometry_diagnosis(self) -> dict | None:
        """A steering response far from the car file's (gain fitted alone or claimed, |gain - 1| > 15 %): at small
        angles a steering gain g and a wheelbase L / g are the same, so the file's geometry or steering scale
        (max_steering_rad, the normalised or pulse-width mapping) is the likely cause, not the servo."""
        gains = [c.params.get("steering_gain") for c in self.selected + self.candidates if c.effect == "steering_gain"]
        gains = [g for g in gains if g is not None]
        if not gains or abs(gains[0] - 1.0) <= GEOMETRY_GAIN_TOLERANCE:
            return None
        g, wheelbase = gains[0], self.car_in.geometry.wheelbase_m
        return {"steering_gain": g, "wheelbase_m": wheelbase, "equivalent_wheelbase_m": wheelbase / g,
                "note": f"geometry/steering scale does not fit: the car turns {g:.2f} x as sharply as the car file says; "
                        f"at small angles that is a wheelbase of {wheelbase / g:.3f} m instead of {wheelbase:.3f} m, or "
                        f"a steering scale off by {g:.2f} (max_steering_rad, normalised or pulse-width mapping)"}

    @property
    def heldout_error_reduction(self) -> float:
        """Headline: 1 - RMSE_final / RMSE_nominal-dynamic of the held-out horizon position error."""
        return 1.0 - self.final.heldout.horizon_pos_rmse_m / self.dynamic_nominal.heldout.horizon_pos_rmse_m

    @property
    def significant(self) -> bool:
        return bool(self.selected)


def _subset(e: PredictionErrors, keep: np.ndarray) -> PredictionErrors:
    return PredictionErrors(**{f.name: getattr(e, f.name)[keep] for f in dataclasses.fields(e)})


def per_run_summaries(result: "SysidResult") -> list[tuple[int, int, ErrorSummary, ErrorSummary, ErrorSummary]]:
    """Per run with held-out windows: (run index, windows, nominal dynamic, planner, final) held-out errors."""
    run = result.traj.run[result.split.heldout]
    out = []
    for i in np.unique(run).tolist():
        keep = run == i
        out.append((i, int(keep.sum()), *(summarize(_subset(f.heldout_errors, keep))
                                          for f in (result.dynamic_nominal, result.planner, result.final))))
    return out


# ----------------------------------------------------------------------------- fitting
def _fit_steps(horizon: int, n: int) -> np.ndarray:
    return np.unique(np.round(np.linspace(horizon / n, horizon, n)).astype(int))


def _residual(traj: Trajectory, starts: np.ndarray, pred: np.ndarray, steps: np.ndarray) -> np.ndarray:
    idx = starts[:, None] + steps[None, :]
    p = pred[:, steps]
    dth = np.angle(np.exp(1j * (p[..., 2] - traj.heading[idx])))
    r = np.stack([
        (p[..., 0] - traj.x[idx]) / POSITION_SCALE_M,
        (p[..., 1] - traj.y[idx]) / POSITION_SCALE_M,
        dth / HEADING_SCALE_RAD,
        (p[..., 3] - traj.speed[idx]) / SPEED_SCALE_MPS,
    ], axis=-1)
    # A trial parameter vector whose prediction overflowed costs a large finite residual (least_squares
    # then steps back from it instead of stopping on a non-finite cost).
    return np.nan_to_num(r.reshape(-1), nan=1e6, posinf=1e6, neginf=-1e6)


def _clusters(traj: Trajectory, starts: np.ndarray, per_start: int, block_s: float) -> np.ndarray:
    return np.repeat(traj.blocks(starts, block_s), per_start)


def _sandwich_std(jac: np.ndarray, resid: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """Cluster-robust standard errors: windows overlap in time, so residuals are correlated within a block."""
    bread = np.linalg.pinv(jac.T @ jac)
    _, inverse = np.unique(clusters, return_inverse=True)
    g = np.zeros((inverse.max() + 1, jac.shape[1]))
    np.add.at(g, inverse, jac * resid[:, None])
    cov = bread @ (g.T @ g) @ bread
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def evaluate(traj: Trajectory, split: Split, horizon: int, setup: ModelSetup, effects: tuple[str, ...] = (),
             values: dict[str, float] | None = None, std: dict[str, float] | None = None) -> Fit:
    pred = predict(traj, split.heldout, horizon, setup)
    errors = prediction_errors(traj, split.heldout, pred)
    return Fit(effects, dict(values or {}), dict(std or {}), setup, errors, summarize(errors))


def fit_candidates(traj: Trajectory, split: Split, horizon: int, base: ModelSetup, cands: list[Candidate],
                   s: SysidSettings, base_effects: tuple[str, ...] = ()) -> Fit:
    """Least-squares fit of the parameters of ``cands`` (jointly) on top of ``base``."""
    names = [p for c in cands for p in c.params]
    lower = np.array([v for c in cands for v in c.lower])
    upper = np.array([v for c in cands for v in c.upper])
    scale = np.array([v for c in cands for v in c.scale])
    # The total drag (nominal + correction) must stay >= 0.
    for i, n in enumerate(names):
        if n == "extra_drag_n_per_mps2":
            lower[i] = max(lower[i], -base.car.longitudinal.drag_n_per_mps2)
    dynamic = base.dynamic or any(c.dynamic for c in cands)
    corr = base.car.corrections
    x0 = np.clip(np.array([getattr(corr, n) for n in names], dtype=float), lower, upper)
    steps = _fit_steps(horizon, s.fit_steps)
    starts = split.fit
    excluded = [r for c in cands for r in c.excluded_runs]
    if excluded:  # runs that disagree with the others on an effect of the fit do not enter it
        starts = starts[~np.isin(traj.run[starts], excluded)]

    def setup_for(theta: np.ndarray) -> ModelSetup:
        return dataclasses.replace(base, car=with_corrections(base.car, dict(zip(names, theta.tolist()))), dynamic=dynamic)

    def resid_many(thetas: list[np.ndarray]) -> np.ndarray:
        """Residuals of several parameter vectors, predicted in one batch: shape (len(thetas), M)."""
        preds = predict(traj, starts, horizon, [setup_for(t) for t in thetas])
        return np.stack([_residual(traj, starts, p, steps) for p in preds])

    # Delays and the play make the cost non-convex from the neutral value: start from the best of a
    # coarse grid per such parameter (all trials in one batch).
    trials = [x0]
    delay_idx = [i for i, n in enumerate(names) if n.endswith("_delay_s")]
    if delay_idx:
        for d in np.arange(1, 6) * traj.dt * 1.5:
            trial = x0.copy()
            trial[delay_idx] = np.clip(x0[delay_idx] + d, lower[delay_idx], upper[delay_idx])
            trials.append(trial)
    for i, n in enumerate(names):
        for v in _START_GRID.get(n, ()):
            trial = x0.copy()
            trial[i] = np.clip(v, lower[i], upper[i])
            trials.append(trial)
    if len(trials) > 1:
        costs = np.sum(resid_many(trials) ** 2, axis=1)
        x0 = trials[int(np.argmin(costs))]
    # Forward differences, all parameters in one batch, only where least_squares asks for the Jacobian
    # (at accepted points; most fits also try steps they reject).
    step = 0.05 * scale
    last: dict[str, np.ndarray] = {}

    def fun(theta: np.ndarray) -> np.ndarray:
        if "x" not in last or not np.array_equal(last["x"], theta):
            last.clear()
            last["x"], last["f"] = theta.copy(), resid_many([theta])[0]
        return last["f"]

    def jac(theta: np.ndarray) -> np.ndarray:
        f = fun(theta)
        if "jac" not in last:
            h = np.where(theta + step <= upper, step, -step)
            r = resid_many([theta + h[i] * np.eye(theta.size)[i] for i in range(theta.size)])
            last["jac"] = ((r - f) / h[:, None]).T
        return last["jac"]

    res = least_squares(fun, x0, jac=jac, bounds=(lower, upper), x_scale=scale, max_nfev=30, xtol=1e-6,
                        ftol=1e-8)
    n_per = steps.size * 4
    std = _sandwich_std(res.jac, res.fun, _clusters(traj, starts, n_per, s.bootstrap_block_s))
    # Back to physical units: residuals were scaled, parameters were not.
    values = dict(zip(names, res.x.tolist()))
    effects = tuple(base_effects) + tuple(c.effect for c in cands if c.effect not in base_effects)
    return evaluate(traj, split, horizon, setup_for(res.x), effects, values, dict(zip(names, std.tolist())))


def improvement(traj: Trajectory, split: Split, before: Fit, after: Fit, s: SysidSettings) -> tuple[float, float]:
    """(relative held-out horizon RMSE reduction, bootstrap confidence that the MSE reduction > 0)."""
    e0 = before.heldout_errors.position[:, -1] ** 2
    e1 = after.heldout_errors.position[:, -1] ** 2
    reduction = 1.0 - math.sqrt(e1.mean() / e0.mean()) if e0.mean() > 0 else 0.0
    blocks = traj.blocks(split.heldout, s.bootstrap_block_s)
    _, inverse = np.unique(blocks, return_inverse=True)
    if inverse.max() + 1 < MIN_BOOTSTRAP_BLOCKS:  # one block cannot show the spread between blocks
        return reduction, 0.0
    diff_sum = np.bincount(inverse, weights=e0 - e1)
    counts = np.bincount(inverse).astype(float)
    rng = np.random.default_rng(s.seed)
    pick = rng.integers(0, diff_sum.size, size=(s.n_bootstrap, diff_sum.size))
    boot = diff_sum[pick].sum(axis=1) / counts[pick].sum(axis=1)
    return reduction, float(np.mean(boot > 0))


def _judge(traj, split, before: Fit, after: Fit, effect: str, s: SysidSettings, params=None, std=None,
           channels: bool = False) -> CandidateResult:
    """Significant: the held-out position error drops enough and beyond noise; with ``channels`` (the keep
    test of a claim in the final model) also neither the held-out heading nor the speed error at the
    horizon gets worse (a claim must fit all three, not position alone). Forward selection judges on position:
    an effect that is right can worsen another channel while a second effect is still missing."""
    reduction, conf = improvement(traj, split, before, after, s)
    heading = 1.0 - after.heldout.horizon_heading_rmse_rad / max(before.heldout.horizon_heading_rmse_rad, 1e-12)
    speed = 1.0 - after.heldout.horizon_speed_rmse_mps / max(before.heldout.horizon_speed_rmse_mps, 1e-12)
    return CandidateResult(
        effect=effect,
        params=dict(after.values if params is None else params),
        params_std=dict(after.std if std is None else std),
        heldout_error_reduction=reduction,
        confidence=conf,
        significant=bool(reduction >= s.min_reduction and conf >= s.confidence
                         and (not channels or (heading >= -s.max_worsening and speed >= -s.max_worsening))),
        heading_reduction=heading,
        speed_reduction=speed,
    )


# ----------------------------------------------------------------------------- agreement between runs
MIN_RUN_WINDOWS = 20  # fit windows a training run needs for an estimate of its own


@dataclass(frozen=True)
class RunAgreement:
    """One parameter fitted alone on each training run, and whether the runs agree on it (sysid.agreement)."""

    effect: str
    param: str
    runs: tuple[int, ...]  # run indices (Trajectory.runs) with an estimate
    values: tuple[float, ...]
    stds: tuple[float, ...]
    agreement: Agreement

    @property
    def excluded_runs(self) -> tuple[int, ...]:
        return tuple(self.runs[i] for i in self.agreement.excluded)

    @property
    def agreeing_runs(self) -> tuple[int, ...]:
        return tuple(self.runs[i] for i in self.agreement.agreeing)


def run_agreement(traj: Trajectory, split: Split, horizon: int, base: ModelSetup, cands: tuple[Candidate, ...],
                  car: CarParams, s: SysidSettings) -> tuple[tuple[Candidate, ...], list[RunAgreement]]:
    """Each candidate fitted alone on top of ``base`` on each training run that excites it; per parameter the
    runs' estimates are tested for agreement. Returns the candidates without the parameters the runs disagree
    on and with the runs that disagree excluded from their fits, and the per-parameter verdicts."""
    runs = [r for r in np.unique(traj.run[split.train]).tolist()
            if np.count_nonzero(traj.run[split.fit] == r) >= MIN_RUN_WINDOWS]
    if len(runs) < 2:
        return cands, []
    jobs = []
    for r in runs:
        fit_r = split.fit[traj.run[split.fit] == r]
        exc_r = excitation(traj, split.train[traj.run[split.train] == r], horizon, car)
        for c in restrict(cands, exc_r)[0]:
            jobs.append((r, c, Split(train=fit_r, heldout=fit_r, fit=fit_r)))
    fits = side_by_side([lambda r=r, c=c, sp=sp: fit_candidates(traj, sp, horizon, base, [c], s) for r, c, sp in jobs])
    verdicts: list[RunAgreement] = []
    out = []
    for c in cands:
        ok, excluded = [], []
        for i, p in enumerate(c.params):
            est = [(r, f.values[p], f.std[p]) for (r, cj, _), f in zip(jobs, fits) if cj.effect == c.effect
                   and p in f.values]
            if len(est) < 2:
                ok.append(i)
                continue
            a = agreement([v for _, v, _ in est], [e for _, _, e in est])
            v = RunAgreement(c.effect, p, tuple(r for r, _, _ in est), tuple(v for _, v, _ in est),
                             tuple(e for _, _, e in est), a)
            verdicts.append(v)
            if not a.disagree:
                ok.append(i)
                excluded += [r for r in v.excluded_runs if r not in excluded]
        if ok:
            out.append(dataclasses.replace(_with_params(c, ok), excluded_runs=tuple(sorted(excluded))))
    return tuple(out), verdicts


@dataclass(frozen=True)
class RunStability:
    """A claimed effect refitted with one training run left out, judged on the same held-out data."""

    effect: str
    dropped_run: int  # run index (Trajectory.runs)
    values: dict[str, float]  # the effect's parameters without that run
    verdict: CandidateResult  # against the model without the effect, fitted without that run
    on_run: CandidateResult | None = None  # the same two models on the dropped run's windows (None: run excluded)

    @property
    def significant(self) -> bool:
        return self.verdict.significant and (self.on_run is None or self.on_run.significant)


def claim_stability(traj: Trajectory, split: Split, horizon: int, chosen: list[Candidate],
                    effect_steps: list[tuple[Fit, Fit]], current: Fit, s: SysidSettings) -> list[RunStability]:
    """Each claimed effect of the final named model ``current`` refitted with each training run left out (the
    other effects refitted too), judged by the keep test against the model without it fitted on the same runs, on the
    held-out data and on the left-out run's own windows (unless the agreement test excluded that run from the effect).
    A claim that needs one particular run is not a property of the car (docs/sysid.md, "Stable under leaving
    out a run"). Runs with fewer than MIN_RUN_WINDOWS fit windows, or excluded from every chosen effect, are
    not left out (their absence changes nothing)."""
    excluded_everywhere = set.intersection(*(set(c.excluded_runs) for c in chosen)) if chosen else set()
    runs = [r for r in np.unique(traj.run[split.train]).tolist()
            if np.count_nonzero(traj.run[split.fit] == r) >= MIN_RUN_WINDOWS and r not in excluded_everywhere]
    if len(runs) < 2 or not chosen:
        return []

    def without_run(r: int) -> Split:
        return Split(train=split.train[traj.run[split.train] != r], heldout=split.heldout,
                     fit=split.fit[traj.run[split.fit] != r])

    def checks(r: int) -> list[RunStability]:
        sp = without_run(r)
        full = fit_candidates(traj, sp, horizon, current.setup, chosen, s, current.effects)

        def check(i: int) -> RunStability:
            before, rest = effect_steps[i][0], chosen[:i] + chosen[i + 1:]
            if rest:  # the model without the effect, its other effects fitted without run r too
                before = fit_candidates(traj, sp, horizon, before.setup, rest, s, before.effects)
            verdict = _judge(traj, sp, before, full, chosen[i].effect, s, channels=True)
            on_run = None
            if r not in chosen[i].excluded_runs:  # a claim of the car also predicts a run it was not fitted on
                own = Split(train=sp.train, heldout=thin(split.train[traj.run[split.train] == r], s.heldout_max_starts),
                            fit=sp.fit)
                on_run = _judge(traj, own, evaluate(traj, own, horizon, before.setup),
                                evaluate(traj, own, horizon, full.setup), chosen[i].effect, s, channels=True)
            return RunStability(chosen[i].effect, r, {p: full.values[p] for p in chosen[i].params}, verdict, on_run)

        return side_by_side([lambda i=i: check(i) for i in range(len(chosen))])

    return [k for per_run in side_by_side([lambda r=r: checks(r) for r in runs]) for k in per_run]


# ----------------------------------------------------------------------------- run-level parameters
def _calibrate(traj: Trajectory, split: Split, horizon: int, current: Fit, pop_fit: Fit, cand: Candidate,
               car: CarParams, r: int, s: SysidSettings) -> Calibration:
    """Held-out run ``r`` calibrated on its own first block: the parameter fitted on the windows that end inside
    it, scored (with the shared and the population model) on the windows that start after it."""
    (param,) = cand.params
    in_run = traj.run[split.heldout] == r
    idx = split.heldout[in_run]
    cal, later = calibration_masks(traj.elapsed[idx], traj.elapsed[idx + horizon], s.calibration_s)
    n_later = int(np.count_nonzero(later))
    if np.count_nonzero(cal) < MIN_RUN_WINDOWS or n_later < MIN_RUN_WINDOWS:
        return Calibration(s.calibration_s, n_later, reason=f"{np.count_nonzero(cal)} windows in the first block, "
                           f"{n_later} after it (need >= {MIN_RUN_WINDOWS} each)")
    exc = excitation(traj, idx[cal], horizon, car)[param]
    if not exc.identifiable:
        return Calibration(s.calibration_s, n_later, reason=f"not excited in the first block: {exc.reason}")
    sp = Split(train=idx[cal], heldout=idx[later], fit=thin(idx[cal], s.fit_max_starts))
    f = fit_candidates(traj, sp, horizon, current.setup, [cand], s, current.effects)
    pos = np.flatnonzero(in_run)[later]  # positions in split.heldout, as the held-out errors are stored
    return Calibration(s.calibration_s, n_later, f.values[param], f.std[param], None,
                       summarize(_subset(current.heldout_errors, pos)), summarize(_subset(pop_fit.heldout_errors, pos)),
                       f.heldout)


def per_run_values(traj: Trajectory, split: Split, horizon: int, base: ModelSetup, cand: Candidate, car: CarParams,
                   s: SysidSettings) -> tuple[tuple[RunValue, ...], tuple[tuple[int, str], ...]]:
    """A run-level parameter fitted alone on top of ``base`` on each training run that has enough fit windows and
    excites it; and the training runs left without an estimate, with the reason."""
    (param,) = cand.params
    jobs, not_excited = [], []
    for r in np.unique(traj.run[split.train]).tolist():
        fit_r = split.fit[traj.run[split.fit] == r]
        if fit_r.size < MIN_RUN_WINDOWS:
            not_excited.append((r, f"{fit_r.size} fit windows (need >= {MIN_RUN_WINDOWS})"))
            continue
        exc = excitation(traj, split.train[traj.run[split.train] == r], horizon, car)[param]
        if not exc.identifiable:
            not_excited.append((r, exc.reason))
            continue
        jobs.append((r, Split(train=fit_r, heldout=fit_r, fit=fit_r)))
    fits = side_by_side([lambda sp=sp: fit_candidates(traj, sp, horizon, base, [cand], s) for _, sp in jobs])
    return (tuple(RunValue(r, f.values[param], f.std[param], sp.fit.size) for (r, sp), f in zip(jobs, fits)),
            tuple(not_excited))


def with_run_values(traj: Trajectory, setup: ModelSetup, param: str, values: tuple[RunValue, ...]) -> ModelSetup:
    """``setup`` with each run's own value of ``param``; runs without one (held out, not excited) keep the car's."""
    per_run = [getattr(setup.car.corrections, param)] * traj.n_runs
    for v in values:
        per_run[v.run] = v.value
    return dataclasses.replace(setup, run_values=((param, tuple(per_run)),))


def fit_run_level(traj: Trajectory, split: Split, horizon: int, current: Fit, cand: Candidate, car: CarParams,
                  s: SysidSettings) -> tuple[RunLevelParam | None, Fit]:
    """A run-level parameter (sysid.run_level): fitted alone on top of the shared model ``current`` (its run-level
    values removed) on each training run that excites it, pooled as a population; the population value judged by
    the keep test on the held-out runs (the model returned: with it if it passes, the shared model otherwise) and
    each held-out run also calibrated on its own first block. None when fewer than two training runs give an
    estimate. The held-out runs use the car's value in ``current``, so its held-out errors are the shared model's."""
    (param,) = cand.params
    current = dataclasses.replace(current, setup=dataclasses.replace(current.setup, run_values=()))
    values, not_excited = per_run_values(traj, split, horizon, current.setup, cand, car, s)
    if len(values) < 2:
        return None, current
    pop = population(list(values))
    pop_setup = dataclasses.replace(current.setup, car=with_corrections(current.setup.car, {param: pop.value}))
    pop_fit = evaluate(traj, split, horizon, pop_setup, current.effects + (cand.effect,),
                       {**current.values, param: pop.value}, {**current.std, param: pop.std})
    verdict = _judge(traj, split, current, pop_fit, cand.effect, s, {param: pop.value}, {param: pop.std},
                     channels=True)
    held = np.unique(traj.run[split.heldout]).tolist()
    cals = side_by_side([lambda r=r: _calibrate(traj, split, horizon, current, pop_fit, cand, car, r, s) for r in held])
    heldout = []
    for r, c in zip(held, cals):
        keep = traj.run[split.heldout] == r
        heldout.append(HeldoutRun(r, int(keep.sum()), summarize(_subset(current.heldout_errors, keep)),
                                  summarize(_subset(pop_fit.heldout_errors, keep)), c))
    result = RunLevelParam(cand.effect, param, float(getattr(current.setup.car.corrections, param)), values,
                           not_excited, pop, verdict, tuple(heldout))
    return result, (pop_fit if result.written else current)


# ----------------------------------------------------------------------------- sparse fallback
def without_other_terms(setup: ModelSetup) -> ModelSetup:
    return dataclasses.replace(setup, car=dataclasses.replace(setup.car, other_terms=OtherTermsParams()))


_RUN_LEVEL_STEP = 0.05  # relative change of a run-level value for its regressor in `other`'s regression


def _run_level_regressors(traj: Trajectory, starts: np.ndarray, lag: int, setup: ModelSetup, pred: np.ndarray
                          ) -> tuple[np.ndarray, list[int]]:
    """Per run in ``starts`` with a run-level value in ``setup`` (at most one run-level parameter): the change of the
    predicted speed rate over ``lag`` steps when the run's value grows by _RUN_LEVEL_STEP (relative), zero outside
    the run; and the runs of the columns. No run-level values: no column."""
    cols, runs = [], []
    for name, values in setup.run_values:
        bumped = dataclasses.replace(setup, run_values=((name, tuple(v * (1 + _RUN_LEVEL_STEP) for v in values)),))
        rate = (predict(traj, starts, lag, bumped)[:, -1, 3] - pred[:, -1, 3]) / (lag * traj.dt)
        for r in np.unique(traj.run[starts]).tolist():
            col = np.where(traj.run[starts] == r, rate, 0.0)
            if np.any(col != 0.0):
                cols.append(col)
                runs.append(r)
    return (np.stack(cols, axis=1) if cols else np.zeros((starts.size, 0))), runs


def _shift_run_values(setup: ModelSetup, nuisance: np.ndarray, runs: list[int], terms_rate: np.ndarray) -> ModelSetup:
    """``setup`` with each run's run-level value moved as in the joint fit: by minus the least-squares share of the
    terms' speed rate along the run's regressor (a relative step), kept at >= 10 % of the value."""
    if not runs:
        return setup
    share = -np.linalg.lstsq(nuisance, terms_rate, rcond=None)[0] * _RUN_LEVEL_STEP
    ((name, values),) = setup.run_values
    factors = np.ones(len(values))
    factors[runs] = np.maximum(1.0 + share, 0.1)
    return dataclasses.replace(setup, run_values=((name, tuple(v * f for v, f in zip(values, factors))),))


def fit_other(traj: Trajectory, split: Split, horizon: int, base: Fit, s: SysidSettings) -> tuple[Fit, dict, dict]:
    """STLSQ on the short-term rate residuals of speed and heading against the library terms
    (vehicles.extra_terms.LIBRARY); the terms go into the car's ``[other_terms]``."""
    lag = max(1, int(round(0.1 / traj.dt)))
    starts = split.train[split.train + lag < traj.seg_end[split.train]]
    plain = without_other_terms(base.setup)
    pred = predict(traj, starts, lag, plain)
    end = starts + lag
    r_v = (traj.speed[end] - pred[:, -1, 3]) / (lag * traj.dt)
    r_th = (traj.headings[end] - pred[:, -1, 2]) / (lag * traj.dt)
    car = plain.car
    # Terms at the mean inputs and speed over the 0.1 s the residual accumulates over.
    acts = actuation(traj, starts, lag, car, substeps(plain, traj.dt))
    throttle = acts.throttle.mean(axis=(1, 2))
    delta = car.corrections.steering_gain * acts.steering.mean(axis=(1, 2)) + car.corrections.steering_offset_rad
    v = traj.speed[starts[:, None] + np.arange(lag + 1)[None, :]].mean(axis=1)
    names = tuple(LIBRARY)
    theta_all = np.stack([LIBRARY[n][1](v, throttle, delta) for n in names], axis=1)
    clusters = traj.blocks(starts, s.bootstrap_block_s)
    # Each training run's own run-level value is a named effect fitted beside the terms, not under them: the speed
    # terms are fitted jointly with one regressor per run (the speed rate's change per relative change of that run's
    # value), by projecting those regressors out (Frisch-Waugh-Lovell: the terms' coefficients and standard
    # deviations are those of the joint fit). The runs' values then move by the joint fit's share.
    nuisance, nuisance_runs = _run_level_regressors(traj, starts, lag, plain, pred)
    basis = np.linalg.qr(nuisance)[0]

    def project(a: np.ndarray) -> np.ndarray:
        return a - basis @ (basis.T @ a)

    def sparse_fit(target: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        coef = stlsq(theta, target, s.sparse_threshold * float(np.std(target)))
        # Also drop terms that are not distinguishable from zero (|c| < 3 std), then refit the rest.
        for _ in range(len(names)):
            std = coefficient_std(theta, target, coef, clusters)
            weak = (coef != 0) & (np.abs(coef) < 3.0 * std)
            if not weak.any():
                return coef, std
            keep = (coef != 0) & ~weak
            coef = np.zeros_like(coef)
            if keep.any():
                coef[keep] = np.linalg.lstsq(theta[:, keep], target, rcond=None)[0]
        return coef, coefficient_std(theta, target, coef, clusters)

    ca, sa = sparse_fit(project(r_v), project(theta_all))
    cy, sy = sparse_fit(r_th, theta_all)
    theta = theta_all
    # Bounded terms: a coefficient whose term reaches more than a physical rate anywhere in the data is dropped.
    reach = np.max(np.abs(theta), axis=0)
    ca[np.abs(ca) * reach > OTHER_MAX_ACCEL_MPS2] = 0.0
    cy[np.abs(cy) * reach > OTHER_MAX_YAW_RATE_RADPS] = 0.0
    steps = _fit_steps(horizon, s.fit_steps)

    def with_terms(a: np.ndarray, y: np.ndarray) -> ModelSetup:
        terms = terms_from_coefficients({n: c for n, c in zip(names, a) if c != 0.0},
                                        {n: c for n, c in zip(names, y) if c != 0.0})
        shifted = _shift_run_values(plain, nuisance, nuisance_runs, theta @ a)
        return dataclasses.replace(shifted, car=dataclasses.replace(car, other_terms=terms))

    def training_costs(setups: list[ModelSetup]) -> list[float]:
        """Multi-step costs on the training windows, all setups predicted in one batch."""
        preds = predict(traj, split.fit, horizon, setups)
        return [float(r @ r) for r in (_residual(traj, split.fit, p, steps) for p in preds)]

    # The 0.1 s regression can pick up terms that do not help over the whole horizon (e.g. where the
    # smoothed speed misses fast throttle changes): drop, one at a time, any term whose removal lowers
    # the multi-step cost on the training windows (each round's removals predicted in one batch).
    cost = training_costs([with_terms(ca, cy)])[0]
    while np.count_nonzero(ca) + np.count_nonzero(cy) > 0:
        trials, setups = [], []
        for coef in (ca, cy):
            for i in np.flatnonzero(coef):
                saved, coef[i] = coef[i], 0.0
                setups.append(with_terms(ca, cy))
                trials.append((coef, i))
                coef[i] = saved
        costs = training_costs(setups)
        best = int(np.argmin(costs))
        if costs[best] >= cost:
            break
        coef, i = trials[best]
        coef[i], cost = 0.0, costs[best]
    setup = with_terms(ca, cy)
    fit = evaluate(traj, split, horizon, setup, base.effects + ("other",), base.values, base.std)
    params = {f"accel[{n}]": float(c) for n, c in zip(names, ca) if c != 0.0}
    params |= {f"yaw_rate[{n}]": float(c) for n, c in zip(names, cy) if c != 0.0}
    stds = {f"accel[{n}]": float(e) for n, c, e in zip(names, ca, sa) if c != 0.0}
    stds |= {f"yaw_rate[{n}]": float(e) for n, c, e in zip(names, cy, sy) if c != 0.0}
    return fit, params, stds


@dataclass(frozen=True)
class OtherCrossRun:
    """`other` fitted without one training run and judged on that run (its own run-level values in place)."""

    run: int  # run index (Trajectory.runs)
    params: dict[str, float]  # the terms fitted without the run
    verdict: CandidateResult  # on the run's windows, against the model without the terms

    @property
    def significant(self) -> bool:
        return self.verdict.significant


def other_cross_run(traj: Trajectory, split: Split, horizon: int, base: Fit, run_level_cands: tuple[Candidate, ...],
                    s: SysidSettings) -> list[OtherCrossRun]:
    """`other` is one set of terms for every run, so with several training runs it must predict each training run it
    was not fitted on: refitted on top of ``base`` without run r, judged by the keep test on run r's training windows,
    where each run has its own run-level values. A held-out run is predicted with the population's (or the car file's)
    run-level value; terms that only make up for a held-out run's own session (a VESC that does not follow its
    set-point) help there and nowhere else. Runs with fewer than MIN_RUN_WINDOWS fit windows are not left out."""
    runs = [r for r in np.unique(traj.run[split.train]).tolist()
            if np.count_nonzero(traj.run[split.fit] == r) >= MIN_RUN_WINDOWS]
    if len(runs) < 2:
        return []

    def check(r: int) -> OtherCrossRun:
        own = split.train[traj.run[split.train] == r]
        sp = Split(train=split.train[traj.run[split.train] != r], heldout=thin(own, s.heldout_max_starts),
                   fit=split.fit[traj.run[split.fit] != r])
        without = evaluate(traj, sp, horizon, base.setup, base.effects, base.values, base.std)
        fit, params, std = fit_other(traj, sp, horizon, without, s)
        for cand in run_level_cands:  # run r's own value refitted on its windows with the speed terms in place
            (param,) = cand.params
            runs_values = dict(fit.setup.run_values)
            if param in runs_values and any(p.startswith("accel[") for p in params):  # speed terms share with it
                setup = dataclasses.replace(fit.setup, run_values=(),
                                            car=with_corrections(fit.setup.car, {param: runs_values[param][r]}))
                fit = fit_candidates(traj, Split(train=own, heldout=sp.heldout, fit=thin(own, s.fit_max_starts)),
                                     horizon, setup, [cand], s, fit.effects)
        return OtherCrossRun(r, params, _judge(traj, sp, without, fit, "other", s, params, std, channels=True))

    return side_by_side([lambda r=r: check(r) for r in runs])


# ----------------------------------------------------------------------------- driver
@dataclass
class _Selection:
    reference: Fit
    candidates: list[CandidateResult]
    selected: list[CandidateResult]
    chosen: list[Candidate]
    effect_steps: list[tuple[Fit, Fit]]
    current: Fit
    reference_is_dynamic: bool
    switched_after: list[str] | None


_SCORE_TOP = 2  # candidates the score test adds to a forward-selection round
_SCORE_MIN = 0.01  # smallest predicted relative drop of the training cost that counts


def _score_test(traj: Trajectory, split: Split, horizon: int, base: ModelSetup, cands: list[Candidate],
                s: SysidSettings) -> dict[str, float]:
    """Predicted relative drop of the training cost per candidate: one Gauss-Newton step from the current
    values (secants over each parameter's typical size, all in one batch; bounds respected)."""
    steps = _fit_steps(horizon, s.fit_steps)
    corr = base.car.corrections
    setups, cols = [base], []
    for c in cands:
        for p, lo, hi, size in zip(c.params, c.lower, c.upper, c.scale):
            v = getattr(corr, p)
            h = size if v + size <= hi else -size
            setups.append(dataclasses.replace(base, car=with_corrections(base.car, {p: v + h})))
            cols.append((c.effect, v, h, lo, hi))
    preds = predict(traj, split.fit, horizon, setups)
    r0 = _residual(traj, split.fit, preds[0], steps)
    jac = np.stack([(_residual(traj, split.fit, pr, steps) - r0) / h
                    for pr, (_, _, h, _, _) in zip(preds[1:], cols)], axis=1)
    cost0 = float(r0 @ r0)
    out = {}
    for c in cands:
        idx = [i for i, col in enumerate(cols) if col[0] == c.effect]
        step = np.linalg.lstsq(jac[:, idx], -r0, rcond=None)[0]
        step = np.clip(step, [cols[i][3] - cols[i][1] for i in idx], [cols[i][4] - cols[i][1] for i in idx])
        r1 = r0 + jac[:, idx] @ step
        out[c.effect] = 1.0 - float(r1 @ r1) / cost0 if cost0 > 0 else 0.0
    return out


def _leave_one_out(traj: Trajectory, split: Split, horizon: int, chosen: list[Candidate], named: Fit, full: Fit,
                   reference: Fit, s: SysidSettings, with_other: bool) -> list[tuple[CandidateResult, int, Fit, Fit]]:
    """Each chosen effect judged against ``full`` refitted without it: (verdict, index, model without it,
    named effects without it). ``named`` holds the named effects' fit; with_other: `other` refitted on top."""
    def refit(i: int) -> tuple[CandidateResult, int, Fit, Fit]:
        cand, rest = chosen[i], chosen[:i] + chosen[i + 1:]
        neutral = {p: getattr(reference.setup.car.corrections, p) for p in cand.params}
        base = dataclasses.replace(named.setup, car=with_corrections(named.setup.car, neutral))
        if with_other:
            base = without_other_terms(base)
        named_rest = (fit_candidates(traj, split, horizon, base, rest, s, tuple(c.effect for c in rest)) if rest
                      else evaluate(traj, split, horizon, base))
        without = fit_other(traj, split, horizon, named_rest, s)[0] if with_other else named_rest
        return _judge(traj, split, without, full, cand.effect, s, channels=True), i, without, named_rest

    return side_by_side([lambda i=i: refit(i) for i in range(len(chosen))])


def _forward_select(traj: Trajectory, split: Split, horizon: int, reference: Fit, s: SysidSettings,
                    cands: tuple[Candidate, ...]) -> _Selection:
    """Candidates alone on top of ``reference``, then forward selection (docs/sysid.md)."""
    candidates: list[CandidateResult] = []
    alone: dict[str, Fit] = {}
    fits = side_by_side([lambda c=cand: fit_candidates(traj, split, horizon, reference.setup, [c], s)
                         for cand in cands])
    for cand, fit in zip(cands, fits):
        alone[cand.effect] = fit
        candidates.append(_judge(traj, split, reference, fit, cand.effect, s))
    candidates.sort(key=lambda c: c.heldout_error_reduction, reverse=True)

    reference_is_dynamic = reference.setup.dynamic
    current = reference
    switched_after: list[str] | None = [] if reference_is_dynamic else None
    effect_steps: list[tuple[Fit, Fit]] = []
    chosen: list[Candidate] = []
    selected: list[CandidateResult] = []
    by_name = {c.effect: c for c in cands}
    while len(chosen) < s.max_effects:
        # Later rounds refit jointly only the candidates that helped on their own and the ones a score
        # test on top of the current model ranks highest: an effect masked by a larger one (a play
        # hidden behind an offset) may not help alone, but it does once the larger one is in.
        pool = [by_name[c.effect] for c in candidates if by_name[c.effect] not in chosen
                and c.heldout_error_reduction > 0]
        if chosen:
            rest = [c for c in cands if c not in chosen and (current.setup.dynamic or not c.dynamic)]
            scores = _score_test(traj, split, horizon, current.setup, rest, s)
            ranked = sorted(scores, key=scores.get, reverse=True)
            pool += [by_name[e] for e in ranked[:_SCORE_TOP] if scores[e] > _SCORE_MIN and by_name[e] not in pool]
        if not pool:
            break
        fits = [alone[c.effect] for c in pool] if not chosen else side_by_side(
            [lambda c=c: fit_candidates(traj, split, horizon, current.setup, chosen + [c], s) for c in pool])
        trials = [(_judge(traj, split, current, fit, cand.effect, s), cand, fit) for cand, fit in zip(pool, fits)]
        # The best significant trial: a larger position gain that worsens heading or speed does not block it.
        trials = [t for t in trials if t[0].significant]
        if not trials:
            break
        verdict, cand, fit = max(trials, key=lambda t: t[0].heldout_error_reduction)
        if cand.dynamic and not current.setup.dynamic:
            # Switching to the dynamic model can help even at the current grip: that part is model
            # structure (the car slides as its tyre parameters say), not a tyre deviation. Switch,
            # then claim tire_slip only if the fitted grip adds a significant improvement on top.
            base = dataclasses.replace(current.setup, dynamic=True)
            switched = (fit_candidates(traj, split, horizon, base, chosen, s, current.effects) if chosen
                        else evaluate(traj, split, horizon, base, current.effects, current.values, current.std))
            switch_verdict = _judge(traj, split, current, switched, "tire_slip", s, {}, {})
            if switch_verdict.significant:
                reference_is_dynamic = True
                switched_after = [c.effect for c in chosen]
                current = switched
                verdict = _judge(traj, split, switched, fit, cand.effect, s)
                if not verdict.significant:
                    continue
                before = switched
            else:
                before = current
        else:
            before = current
        chosen.append(cand)
        selected.append(verdict)
        effect_steps.append((before, fit))
        current = fit
    # Backward elimination: an effect chosen early can become superfluous once a later one is in
    # (e.g. grip and steering gain both change the yaw response). Each effect is judged against the
    # final model refitted without it; the weakest insignificant one goes, until all are significant.
    while len(chosen) >= 2:
        loo = [(v, i, without) for v, i, without, _ in
               _leave_one_out(traj, split, horizon, chosen, current, current, reference, s, with_other=False)]
        failing = [t for t in loo if not t[0].significant]
        if not failing:
            selected = [v for v, _, _ in loo]
            effect_steps = [(without, current) for _, _, without in loo]
            break
        _, i, without = min(failing, key=lambda t: t[0].heldout_error_reduction)
        del chosen[i]
        current = without
        selected = [dataclasses.replace(v, significant=True) for v in selected[:i] + selected[i + 1:]]
        effect_steps = effect_steps[:i] + effect_steps[i + 1:]
        if len(chosen) == 1:
            single = evaluate(traj, split, horizon, dataclasses.replace(
                current.setup, car=with_corrections(current.setup.car, {
                    p: getattr(reference.setup.car.corrections, p) for p in chosen[0].params})))
            selected = [_judge(traj, split, single, current, chosen[0].effect, s, channels=True)]
            effect_steps = [(single, current)]
    if len(chosen) == 1:
        # The keep test of a single claim: against the model without it, on position, heading and speed.
        before, after = effect_steps[0]
        verdict = _judge(traj, split, before, after, chosen[0].effect, s, channels=True)
        if verdict.significant:
            selected = [verdict]
        else:
            chosen, selected, effect_steps, current = [], [], [], before
    return _Selection(reference, candidates, selected, chosen, effect_steps, current, reference_is_dynamic,
                      switched_after)


def _training_mse(traj: Trajectory, split: Split, horizon: int, setup: ModelSetup) -> float:
    pred = predict(traj, split.fit, horizon, setup)
    return float(np.mean(prediction_errors(traj, split.fit, pred).position[:, -1] ** 2))


def identify(traj: Trajectory, car: CarParams, settings: SysidSettings = SysidSettings()) -> SysidResult:
    """Identify the effects in ``traj`` (docs/sysid.md). Trial parameter vectors of a fit can overflow a
    prediction (the fit rejects them): numpy's warnings about it are counted in ``numeric_warnings``,
    not printed."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        result = _identify(traj, car, settings)
    numeric = [w for w in caught if issubclass(w.category, RuntimeWarning)]
    for w in caught:
        if not issubclass(w.category, RuntimeWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    result.numeric_warnings = len(numeric)
    return result


def _identify(traj: Trajectory, car: CarParams, settings: SysidSettings) -> SysidResult:
    s = settings
    horizon = max(1, int(round(s.horizon_s / traj.dt)))
    split = split_starts(traj, horizon, s)

    planner = evaluate(traj, split, horizon, ModelSetup(car))
    dynamic_nominal = evaluate(traj, split, horizon, ModelSetup(car, dynamic=True))
    structure = _judge(traj, split, planner, dynamic_nominal, "tire_slip", s, {}, {})
    # Forward selection from both model families; the one whose final model predicts the training
    # windows better wins (held-out data stays out of the choice). An effect can hide the
    # structural difference (e.g. a larger steering gain cancels the tyres' understeer), so the
    # choice is made after the effects, not only before.
    # When the dynamic model is already significantly better on the training windows at the current
    # parameters, the kinematic family cannot win and is skipped (saves half the fits).
    train_split = Split(train=split.train, heldout=split.fit, fit=split.fit)
    structure_train = _judge(traj, train_split, evaluate(traj, train_split, horizon, planner.setup),
                             evaluate(traj, train_split, horizon, dynamic_nominal.setup), "tire_slip", s, {}, {})
    references = (dynamic_nominal,) if structure_train.significant else (dynamic_nominal, planner)
    # Identifiability before a claim: only parameters the training windows excite are fitted.
    exc = excitation(traj, split.train, horizon, car)
    cands, not_identifiable = restrict(candidates_for(car), exc)
    # Several training runs: run-level parameters are not shared; each run gets its own, fitted on top of the shared
    # model once that is selected, and pooled as a population (sysid.run_level).
    run_level_cands: tuple[Candidate, ...] = ()
    if np.unique(traj.run[split.train]).size >= 2:
        run_level_cands = tuple(c for c in cands if c.effect in RUN_LEVEL_EFFECTS)
        cands = tuple(c for c in cands if c.effect not in RUN_LEVEL_EFFECTS)
    # The shared parameters are fitted with each training run's own run-level values (fitted alone on top of the
    # nominal dynamic model first); the held-out runs keep the car's values until the population is judged.
    for c in run_level_cands:
        first, _ = per_run_values(traj, split, horizon, dynamic_nominal.setup, c, car, s)
        if len(first) >= 2:
            references = tuple(evaluate(traj, split, horizon, with_run_values(traj, r.setup, c.params[0], first))
                               for r in references)
    # Several training runs: they must agree on an effect before it is fitted on them jointly.
    cands, agreements = run_agreement(traj, split, horizon, references[0].setup, cands, car, s)
    # Several training runs: a claim must survive leaving out any one of them; the least stable failing one is
    # taken out of the candidates and the selection repeated.
    stability: dict[str, list[RunStability]] = {}
    unstable: list[CandidateResult] = []  # the candidates taken out, as fitted alone before
    while True:
        families = side_by_side([lambda ref=ref: _forward_select(traj, split, horizon, ref, s, cands)
                                 for ref in references])
        sel = min(families, key=lambda f: _training_mse(traj, split, horizon, f.current.setup))
        sel.candidates.extend(unstable)
        checks = claim_stability(traj, split, horizon, sel.chosen, sel.effect_steps, sel.current, s)
        for c in sel.chosen:
            stability[c.effect] = [k for k in checks if k.effect == c.effect]
        failing = [k for k in checks if not k.significant]
        if not failing:
            break
        worst = min(failing, key=lambda k: k.verdict.heldout_error_reduction).effect
        unstable.append(next(c for c in sel.candidates if c.effect == worst))
        cands = tuple(c for c in cands if c.effect != worst)
    # Kept: the checks of the claims and of the effects taken out as unstable.
    stability = {e: v for e, v in stability.items()
                 if e in {c.effect for c in sel.chosen} or any(not k.significant for k in v)}
    reference, candidates, selected = sel.reference, sel.candidates, sel.selected
    effect_steps, current = sel.effect_steps, sel.current
    reference_is_dynamic, switched_after = sel.reference_is_dynamic, sel.switched_after
    # Best first: order the claimed effects by their held-out reduction.
    order = sorted(range(len(selected)), key=lambda i: selected[i].heldout_error_reduction, reverse=True)
    selected, effect_steps = [selected[i] for i in order], [effect_steps[i] for i in order]
    by_name = {c.effect: c for c in cands}

    def run_level_on(base: Fit) -> tuple[list[RunLevelParam], list[CandidateResult], list[tuple[Fit, Fit]], Fit]:
        """The run-level parameters on top of ``base``: their results, the claimed ones (population written) and
        their steps, and ``base`` with the population where written and each training run's own value."""
        params, claims, steps = [], [], []
        for c in run_level_cands:
            (param,) = c.params
            file_value = getattr(car.corrections, param)
            if getattr(base.setup.car.corrections, param) != file_value:  # a second pass: judged from the file's value
                setup = dataclasses.replace(base.setup, car=with_corrections(base.setup.car, {param: file_value}))
                base = evaluate(traj, split, horizon, setup, tuple(e for e in base.effects if e != c.effect),
                                {k: v for k, v in base.values.items() if k != param},
                                {k: v for k, v in base.std.items() if k != param})
            rl, with_rl = fit_run_level(traj, split, horizon, base, c, car, s)
            by_name[c.effect] = c
            if rl is not None:
                params.append(rl)
                if rl.written:  # the population value passed the keep test held out: claimed
                    claims.append(rl.verdict)
                    steps.append((base, with_rl))
                with_rl = evaluate(traj, split, horizon, with_run_values(traj, with_rl.setup, param, rl.runs),
                                   with_rl.effects, with_rl.values, with_rl.std)
            base = with_rl
        return params, claims, steps, base

    # Run-level parameters are named effects too: fitted per training run on top of the shared named model before
    # `other`, so `other` is fitted with each training run's own value and judged with the population's.
    run_level, rl_selected, rl_steps, current = run_level_on(current)
    # `other` on top of the named effects. When it earns its place, every named effect is re-tested with
    # it in the model (the terms can take over part of what a named effect explained, or show that the
    # named effect was a stand-in for something the library cannot name): leave-one-out against the
    # model refitted without the effect, `other` refitted too; the weakest insignificant one goes.
    chosen = list(sel.chosen)
    named, named_selected, named_steps = current, selected, effect_steps
    other_fit, other_params, other_std = fit_other(traj, split, horizon, named, s)
    other_verdict = _judge(traj, split, named, other_fit, "other", s, other_params, other_std, channels=True)
    other_base = named
    dropped_after_other: list[str] = []
    if not other_verdict.significant and chosen:
        # A named effect can stand in for one the library cannot name (torque steer, a heading rate
        # ~ throttle x speed, looks like a steering offset at the mean throttle; the offset then takes
        # the mean and the rest is too small for `other` on top). So the terms are also fitted on the
        # model without the named effects: if they alone predict held-out data significantly better
        # than the named effects (same rule as any effect: a named effect wins a tie), the named
        # effects go into the model on top of the terms and are re-tested below like any others.
        neutral = {p: getattr(reference.setup.car.corrections, p) for c in chosen for p in c.params}
        bare = evaluate(traj, split, horizon, without_other_terms(dataclasses.replace(
            named.setup, car=with_corrections(named.setup.car, neutral))))
        alone_fit, alone_params, alone_std = fit_other(traj, split, horizon, bare, s)
        if alone_params and _judge(traj, split, named, alone_fit, "other", s).significant:
            joint = fit_candidates(traj, split, horizon, alone_fit.setup, chosen, s, alone_fit.effects)
            joint_verdict = _judge(traj, split, named, joint, "other", s, alone_params, alone_std, channels=True)
            if joint_verdict.significant:
                other_fit, other_params, other_std, other_verdict = joint, alone_params, alone_std, joint_verdict
                other_base = bare
    cross_run: list[OtherCrossRun] = []
    if other_verdict.significant:
        cross_run = other_cross_run(traj, split, horizon, other_base, run_level_cands, s)
        if not all(k.significant for k in cross_run):
            other_verdict = dataclasses.replace(other_verdict, significant=False)
    if other_verdict.significant:
        while chosen:
            loo = _leave_one_out(traj, split, horizon, chosen, named, other_fit, reference, s, with_other=True)
            failing = [t for t in loo if not t[0].significant]
            if not failing:
                named_selected = [v for v, _, _, _ in loo]
                named_steps = [(without, other_fit) for _, _, without, _ in loo]
                break
            _, i, _, named_rest = min(failing, key=lambda t: t[0].heldout_error_reduction)
            new_other, new_params, new_std = fit_other(traj, split, horizon, named_rest, s)
            new_verdict = _judge(traj, split, named_rest, new_other, "other", s, new_params, new_std, channels=True)
            if not new_verdict.significant:
                # The named effect and the terms explain the same thing: the named effect stays.
                other_verdict = dataclasses.replace(other_verdict, significant=False)
                loo = _leave_one_out(traj, split, horizon, chosen, named, named, reference, s, with_other=False)
                named_selected = [v for v, _, _, _ in loo]
                named_steps = [(without, named) for _, _, without, _ in loo]
                break
            dropped_after_other.append(chosen[i].effect)
            del chosen[i]
            named, other_fit, other_verdict = named_rest, new_other, new_verdict
        else:
            named_selected, named_steps = [], []
    candidates.append(other_verdict)
    selected, effect_steps, current = named_selected + rl_selected, named_steps + rl_steps, named
    if other_verdict.significant:
        if chosen:
            # One more pass over the named parameters with the terms in place (they were fitted without).
            refit = fit_candidates(traj, split, horizon, other_fit.setup, chosen, s, other_fit.effects)
            if (_training_mse(traj, split, horizon, refit.setup) < _training_mse(traj, split, horizon, other_fit.setup)
                    and refit.heldout.horizon_pos_rmse_m <= other_fit.heldout.horizon_pos_rmse_m):
                other_fit = dataclasses.replace(refit, effects=other_fit.effects)
        selected = named_selected + [other_verdict]
        effect_steps = named_steps + [(named, other_fit)]
        current = other_fit
        if run_level_cands:
            # `other` holds on every training run (other_cross_run): it belongs to the car, so the run-level
            # parameters are fitted again on top of it, like the named parameters above.
            run_level, rl_selected, rl_steps, current = run_level_on(current)
            selected, effect_steps = selected + rl_selected, effect_steps + rl_steps
    unnamed_remains = any(e.effect == "other" for e in selected)
    # The final model holds no training run's own values (held-out runs never used them).
    current = dataclasses.replace(current, setup=dataclasses.replace(current.setup, run_values=()))

    # Reported parameters of each claimed physical effect come from the final joint fit; with several runs their
    # standard deviation is at least that of the agreeing runs' random-effects pool (spread between runs included).
    final_values = dict(current.values)
    final_std = dict(current.std)
    for a in agreements:
        if a.param in final_std:
            final_std[a.param] = max(final_std[a.param], a.agreement.pooled.std)
    # ... and at least the jackknife's over the training runs (each left out in turn).
    for checks in stability.values():
        for p in (checks[0].values if checks else {}):
            if p in final_std:
                final_std[p] = max(final_std[p], jackknife_std([k.values[p] for k in checks]))
    for i, sel_i in enumerate(selected):
        if sel_i.effect != "other":
            keys = by_name[sel_i.effect].params
            selected[i] = dataclasses.replace(sel_i, params={k: final_values[k] for k in keys},
                                              params_std={k: final_std[k] for k in keys})
    # Against the nominal dynamic model: the part of its held-out error each effect removes (the model
    # without the effect minus the final model, in units of the nominal dynamic model's error).
    nominal_rmse = dynamic_nominal.heldout.horizon_pos_rmse_m
    final_rmse = current.heldout.horizon_pos_rmse_m
    for i, (before, _) in enumerate(effect_steps):
        selected[i] = dataclasses.replace(
            selected[i], reduction_vs_nominal=(before.heldout.horizon_pos_rmse_m - final_rmse) / nominal_rmse)
    # Named effects best first, `other` (the remainder) last.
    order = sorted(range(len(selected)), key=lambda i: (selected[i].effect == "other",
                                                        -selected[i].reduction_vs_nominal))
    selected, effect_steps = [selected[i] for i in order], [effect_steps[i] for i in order]
    car_out = dataclasses.replace(with_corrections(car, {k: v for k, v in final_values.items()}),
                                  other_terms=current.setup.car.other_terms)
    # What a planner gets from the new file: its command mapping inverts the named effects; it has no
    # [other_terms] (docs/sysid.md, "Fallback `other`").
    planner_after = evaluate(traj, split, horizon, without_other_terms(ModelSetup(car_out)), tuple(final_values),
                             final_values, final_std)
    return SysidResult(
        settings=s, horizon_steps=horizon, traj=traj, split=split, car_in=car, car_out=car_out,
        planner=planner, dynamic_nominal=dynamic_nominal, reference=reference,
        reference_is_dynamic=reference_is_dynamic, structure=structure, candidates=candidates,
        selected=selected, final=current, planner_after=planner_after, effect_steps=effect_steps,
        switched_after=switched_after, families_compared=len(references) == 2,
        unnamed_effect_remains=unnamed_remains, dropped_after_other=dropped_after_other,
        not_identifiable=not_identifiable, run_agreement=agreements, run_level=run_level,
        claim_stability=[k for checks in stability.values() for k in checks], other_cross_run=cross_run,
    )
