"""Closing the loop: the race-level effect of racing with identified corrections (docs/sysid.md).

The simulator carries hidden effects (``sim.SimEffects``) on the nominal car; the same seeded races are
run with the planners using (a) the nominal car file and (b) the corrected one (written by ``sysid``),
plus (c) the clean reference: nominal planners on a car without the effects. Each race is recorded
(``race.simulation.run_race``) and measured from its recording with the race stack's reader:

* lap time of the RD3G car (a race ends when the first car finishes, so a losing RD3G has none) and its
  mean progress speed along the track over the race (always defined; a car off the track may cut the
  infield, so read it with the off-track count), winner, collisions (and how many RD3G caused),
  off-track excursions, planner fallbacks;
* planner tracking error: every RD3G plan (``world/cars/rd3g/plan``, T+1 points plan_dt apart, starting
  at the state the planner predicted over its car file's actuation delay d) against where the car
  actually was (``world/cars/rd3g/position``, linear in time between control steps): plan point j
  predicts the position at t_plan + d + j * plan_dt. Reported for j = 1 (one planning step) and
  j = T (the end of the horizon) as RMS over all plans whose time is inside the race.
"""
from __future__ import annotations

import dataclasses
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import fileio
from race.recording import load_recording
from race.roster import two_car_roster
from race.setup import RaceSpec
from race.simulation import run_race
from sim import SimEffects
from vehicles.params import CarParams

# The RD3G car of the two-car race these closed loops run (race.roster.two_car_roster).
PLANNER_CAR = next(c.name for c in two_car_roster("mpc", 2.0, 1.8) if c.planner == "rd3g")
VARIANTS = ("clean", "nominal", "corrected")
VARIANT_TEXT = {
    "clean": "no effect, nominal parameters (reference)",
    "nominal": "effect, nominal parameters",
    "corrected": "effect, corrected parameters",
}


@dataclass(frozen=True)
class RaceMeasurement:
    variant: str
    seed: int
    winner: str | None
    rd3g_lap_time_s: float | None        # first completed lap, None if it did not complete one
    rd3g_progress_speed_mps: float       # unwrapped track progress over the race / race duration
    race_time_s: float
    collisions: int
    rd3g_at_fault: int
    rd3g_off_track: int
    fallbacks: int
    one_step_errors_m: np.ndarray         # per plan, plan point 1
    horizon_errors_m: np.ndarray          # per plan, plan point T
    errors_by_step_m: tuple = ()          # per plan point j = 0..T: the errors of all plans
    rd3g_plan_start_s: float = 0.0        # plans start this far ahead (the planner car's actuation delay)
    error: str | None = None              # planner errors during the race (counted, not measured)


@dataclass(frozen=True)
class VariantSummary:
    variant: str
    races: int
    lap_time_mean_s: float | None         # over the races in which RD3G completed a lap
    laps_completed: int
    progress_speed_mean_mps: float        # over all measured races
    wins: int
    collisions: int
    rd3g_at_fault: int
    off_track: int
    fallbacks: int
    failed: int                           # races with planner errors (fallback steps), not measured
    one_step_rmse_m: float
    horizon_rmse_m: float
    horizon_p95_m: float
    plans: int

    def json_dict(self) -> dict:
        """JSON-safe: NaN (nothing measured) becomes null."""
        return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in dataclasses.asdict(self).items()}


def plan_errors_by_step(data, car: str, start_delay_s: float, plan_dt_s: float) -> list[np.ndarray]:
    """For every plan point j = 0..T: the errors (m) of all logged plans of ``car`` whose point j lies
    within the logged positions (see the module doc)."""
    t_pos, pts = data.points(f"world/cars/{car}/position")
    t_plan, strips = data.strips(f"world/cars/{car}/plan")
    if t_pos.size < 2 or not strips:
        raise ValueError(f"{data.path}: no positions or plans of car {car!r} to compare")
    xy = np.array([p[0] for p in pts])
    plans = np.array([s[0] for s in strips])          # (n_plans, T+1, 2)
    out = []
    for j in range(plans.shape[1]):
        t_pred = t_plan + start_delay_s + j * plan_dt_s
        inside = t_pred <= t_pos[-1]
        actual = np.column_stack([np.interp(t_pred[inside], t_pos, xy[:, 0]), np.interp(t_pred[inside], t_pos, xy[:, 1])])
        out.append(np.hypot(*(plans[inside, j] - actual).T))
    return out


def plan_tracking_errors(data, car: str, start_delay_s: float, plan_dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(errors at plan point 1, errors at plan point T) in m; see plan_errors_by_step."""
    by_step = plan_errors_by_step(data, car, start_delay_s, plan_dt_s)
    return by_step[1], by_step[-1]


def measure_race(variant: str, seed: int, outcome, recording: Path, planner_car: CarParams, plan_dt_s: float) -> RaceMeasurement:
    delay = max(planner_car.corrections.steering_delay_s, planner_car.corrections.throttle_delay_s)
    by_step = plan_errors_by_step(load_recording(recording), PLANNER_CAR, delay, plan_dt_s)
    one, horizon = by_step[1], by_step[-1]
    laps = outcome.lap_times_s[PLANNER_CAR]
    progress = outcome.trace_progress[:, 0]
    progress_speed = float((progress[-1] - progress[0]) / (outcome.trace_t[-1] - outcome.trace_t[0]))
    return RaceMeasurement(
        variant=variant, seed=seed, winner=outcome.winner, rd3g_lap_time_s=float(laps[0]) if laps else None,
        rd3g_progress_speed_mps=progress_speed,
        race_time_s=float(outcome.race_time_s), collisions=len(outcome.collisions),
        rd3g_at_fault=sum(c.at_fault == PLANNER_CAR for c in outcome.collisions),
        rd3g_off_track=int(outcome.off_track[PLANNER_CAR]), fallbacks=int(outcome.fallbacks),
        one_step_errors_m=one, horizon_errors_m=horizon, errors_by_step_m=tuple(by_step), rd3g_plan_start_s=delay)


def race_setups(nominal: CarParams, corrected: CarParams, effects: SimEffects, seed: int, race: RaceSpec):
    """{variant: RaceSetup} for one seed: the planners' car file and what the simulator runs (``race``
    names the track, laps, opponent, start and speeds; its car files and effects are replaced)."""
    base = dataclasses.replace(race, seed=seed, sim_car_params=None, sim_effects="").load()
    return {
        "clean": dataclasses.replace(base, car=nominal, sim_car=nominal, sim_effects=SimEffects()),
        "nominal": dataclasses.replace(base, car=nominal, sim_car=nominal, sim_effects=effects),
        "corrected": dataclasses.replace(base, car=corrected, sim_car=nominal, sim_effects=effects),
    }


def run_closed_loop(nominal: CarParams, corrected: CarParams, effects: SimEffects, seeds: list[int],
                    race: RaceSpec = RaceSpec(), recordings_dir: Path | None = None,
                    progress=None) -> list[RaceMeasurement]:
    """Every variant for every seed; recordings go to ``recordings_dir`` (kept) or a temporary folder."""
    out = []
    with tempfile.TemporaryDirectory(prefix="sysid_closed_loop_") as tmp:
        folder = Path(recordings_dir) if recordings_dir is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for seed in seeds:
            for variant, setup in race_setups(nominal, corrected, effects, seed, race).items():
                path = folder / f"{variant}-seed{seed}.rrd"
                outcome = run_race(setup, telemetry_path=path)
                m = measure_race(variant, seed, outcome, path, setup.car, setup.planner.plan_dt_s)
                if outcome.planner_errors:  # steps whose planning raised ran the fallback: counted, not measured
                    first = outcome.planner_errors[0]
                    m = dataclasses.replace(m, error=f"{len(outcome.planner_errors)} planner error(s), first at {first.time_s:.2f} s: "
                                         f"{first.message}")
                out.append(m)
                if progress:
                    progress(out[-1])
    return out


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a ** 2))) if a.size else math.nan


def summarize(races: list[RaceMeasurement]) -> dict[str, VariantSummary]:
    out = {}
    for variant in VARIANTS:
        everything = [r for r in races if r.variant == variant]
        rs = [r for r in everything if r.error is None]
        if not everything:
            continue
        laps = [r.rd3g_lap_time_s for r in rs if r.rd3g_lap_time_s is not None]
        one = np.concatenate([r.one_step_errors_m for r in rs])
        hor = np.concatenate([r.horizon_errors_m for r in rs])
        out[variant] = VariantSummary(
            variant=variant, races=len(everything), lap_time_mean_s=float(np.mean(laps)) if laps else None,
            laps_completed=len(laps),
            progress_speed_mean_mps=float(np.mean([r.rd3g_progress_speed_mps for r in rs])) if rs else math.nan,
            wins=sum(r.winner == PLANNER_CAR for r in rs),
            collisions=sum(r.collisions for r in rs), rd3g_at_fault=sum(r.rd3g_at_fault for r in rs),
            off_track=sum(r.rd3g_off_track for r in rs), fallbacks=sum(r.fallbacks for r in rs),
            failed=len(everything) - len(rs),
            one_step_rmse_m=_rms(one), horizon_rmse_m=_rms(hor),
            horizon_p95_m=float(np.percentile(hor, 95)) if hor.size else math.nan, plans=int(hor.size))
    return out


def format_table(summary: dict[str, VariantSummary], horizon_s: float, plan_dt_s: float) -> str:
    """Markdown table, one row per variant."""
    head = (f"| variant | races | RD3G lap time (mean) | RD3G progress speed | RD3G wins | collisions (RD3G at fault) | off-track | fallbacks "
            f"| tracking RMSE {plan_dt_s:g} s | tracking RMSE {horizon_s:g} s | p95 {horizon_s:g} s |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for v in summary.values():
        lap = "—" if v.lap_time_mean_s is None else f"{v.lap_time_mean_s:.3f} s"
        if v.laps_completed < v.races:
            lap += f" ({v.laps_completed}/{v.races} completed)"
        if v.failed:
            lap += f"; {v.failed} with planner errors (not measured)"
        rows.append(f"| {VARIANT_TEXT[v.variant]} | {v.races} | {lap} | {v.progress_speed_mean_mps:.3f} m/s | {v.wins} | {v.collisions} ({v.rd3g_at_fault}) "
                    f"| {v.off_track} | {v.fallbacks} | {100 * v.one_step_rmse_m:.2f} cm | {100 * v.horizon_rmse_m:.1f} cm "
                    f"| {100 * v.horizon_p95_m:.1f} cm |")
    return "\n".join([head] + rows)


def plot(races: list[RaceMeasurement], summary: dict[str, VariantSummary], title: str, path: Path,
         plan_dt_s: float = 0.1) -> Path:
    """Two panels: planner tracking error against the time ahead (RMS and p95 over all plans) and the
    RD3G car's mean progress speed per race."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"clean": "tab:gray", "nominal": "tab:red", "corrected": "tab:green"}
    variants = [v for v in VARIANTS if v in summary]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    for v in variants:
        rs = [r for r in races if r.variant == v and r.error is None and r.errors_by_step_m]
        if not rs:
            continue
        steps = len(rs[0].errors_by_step_m)
        delay = rs[0].rd3g_plan_start_s
        ahead = delay + plan_dt_s * np.arange(steps)
        for q, style in (("rms", "-"), ("p95", "--")):
            values = []
            for j in range(steps):
                e = np.concatenate([r.errors_by_step_m[j] for r in rs])
                values.append(100 * (np.sqrt(np.mean(e ** 2)) if q == "rms" else np.percentile(e, 95)))
            ax1.plot(ahead, values, style, color=colors[v], label=f"{VARIANT_TEXT[v]} ({q})")
    ax1.set_xlabel("time ahead of the plan's measurement (s)")
    ax1.set_ylabel("RD3G plan vs actual position (cm)")
    ax1.set_title("planner tracking error (all plans)", fontsize=9)
    ax1.legend(fontsize=6)
    for i, v in enumerate(variants):
        rs = [r for r in races if r.variant == v and r.error is None]
        for r in rs:  # filled: RD3G finished its lap (won); open: the race ended before
            ax2.plot(i + 1, r.rd3g_progress_speed_mps, "o", color=colors[v], alpha=0.8,
                     mfc=colors[v] if r.rd3g_lap_time_s is not None else "none")
        if rs:
            ax2.plot([i + 0.75, i + 1.25], [summary[v].progress_speed_mean_mps] * 2, color="k", lw=2)
        off = summary[v].off_track
        if off:
            ax2.annotate(f"{off} off-track", (i + 1, summary[v].progress_speed_mean_mps), textcoords="offset points",
                         xytext=(0, -14), ha="center", fontsize=7)
    ax2.set_xticks(range(1, len(variants) + 1), [VARIANT_TEXT[v].replace(", ", ",\n") for v in variants], fontsize=8)
    ax2.set_xlim(0.5, len(variants) + 0.5)
    ax2.set_ylabel("RD3G mean progress speed (m/s)")
    ax2.set_title("per race (filled: RD3G finished first; bar = mean)", fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fileio.atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=100, format=path.suffix.lstrip(".") or "png"))
    plt.close(fig)
    return path
