"""The generated identification cases of docs/sysid.md as one benchmark (`python -m app sysid-bench`).

Each case drives the simulator (sim/, 1 ms physics) with effects the tool is not told, writes the log,
runs the identification with default settings and checks the verdict against the truth: the right
names (``other`` for an effect outside the list), no false named effect, magnitudes within 20 %, at
least 50 % held-out horizon position error reduction against the nominal dynamic model where an
effect is present, nothing significant on clean logs. Wall and CPU time of the identification
are measured per case.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from sysid.data import build_trajectory
from sysid.diagnose import SysidResult, SysidSettings, identify
from sysid.generate import ExcitationSettings, effects_as_corrections, generate_log, parse_effects
from sysid.log import read_log, write_log_csv
from vehicles.params import CarParams, OtherTermsParams

HARD_THROTTLE = ExcitationSettings(throttle_dither=0.3, dither_corner_hz=8.0)


@dataclass(frozen=True)
class BenchCase:
    name: str
    effects: str  # sysid-generate --effects
    seed: int
    expected: tuple[str, ...]  # effect names the tool must report
    track: str = "oval"
    driver: str = "pursuit"
    hard_throttle: bool = False  # throttle steps the declared rate limit shapes
    other_terms: dict[str, float] = field(default_factory=dict)  # [other_terms] of the simulated car


CASES: tuple[BenchCase, ...] = (
    BenchCase("clean, rate limits only, hard throttle steps", "", 1, (), hard_throttle=True),
    BenchCase("backlash", "steering_backlash=0.06", 2, ("steering_backlash",)),
    BenchCase("asymmetry", "steering_asymmetry=0.15", 3, ("steering_asymmetry",)),
    BenchCase("battery drift", "motor_drift=0.0007", 4, ("motor_drift",)),
    BenchCase("backlash + offset", "steering_backlash=0.06,steering_offset=0.03", 5,
              ("steering_backlash", "steering_offset")),
    BenchCase("asymmetry + drag", "steering_asymmetry=0.15,longitudinal_drag=0.03", 6,
              ("steering_asymmetry", "longitudinal_drag")),
    BenchCase("drift + gain", "motor_drift=0.0007,steering_gain=0.8", 7, ("motor_drift", "steering_gain")),
    BenchCase("gain + drag, hard throttle steps", "steering_gain=0.8,longitudinal_drag=0.03", 8,
              ("steering_gain", "longitudinal_drag"), hard_throttle=True),
    BenchCase("twisty, Stanley driver: backlash + asymmetry + delay",
              "steering_backlash=0.05,steering_asymmetry=0.1,actuation_delay=0.05", 9,
              ("steering_backlash", "steering_asymmetry", "actuation_delay"), track="twisty", driver="stanley"),
    BenchCase("torque steer (outside the names)", "", 10, ("other",), other_terms={"yaw_rate_u_v": 0.5}),
)


@dataclass
class BenchOutcome:
    case: BenchCase
    result: SysidResult
    wall_s: float
    cpu_s: float
    load: float
    failures: list[str]

    @property
    def passed(self) -> bool:
        return not self.failures


def _deviation(field_name: str, value: float) -> float:
    return value - 1.0 if field_name in ("steering_gain", "tire_grip_scale") else value


def check(case: BenchCase, result: SysidResult) -> list[str]:
    """The goals of docs/sysid.md for one case; empty when all are met."""
    failures = []
    names = {e.effect for e in result.selected}
    if names != set(case.expected):
        failures.append(f"names {sorted(names)} != {sorted(case.expected)}")
    neutral = CarParams().corrections
    truth = {k: v for k, v in effects_as_corrections(parse_effects(case.effects)).items()
             if v != getattr(neutral, k)}
    for name, value in truth.items():
        got = getattr(result.car_out.corrections, name)
        if abs(_deviation(name, got) - _deviation(name, value)) > 0.2 * abs(_deviation(name, value)):
            failures.append(f"{name} {got:.5g} vs {value}")
    for name, value in case.other_terms.items():
        got = getattr(result.car_out.other_terms, name)
        if abs(got - value) > 0.2 * abs(value):
            failures.append(f"other_terms.{name} {got:.5g} vs {value}")
    if case.expected and result.heldout_error_reduction < 0.5:
        failures.append(f"reduction {100 * result.heldout_error_reduction:.0f} % < 50 %")
    if not case.expected and result.significant:
        failures.append("clean log: significant")
    return failures


def run_case(case: BenchCase, out_dir: Path, minutes: float, rate_hz: float, car: CarParams,
             settings: SysidSettings) -> BenchOutcome:
    """Generate the case's log (kept in out_dir and reused when present) and identify it."""
    index = CASES.index(case) + 1 if case in CASES else 0
    log_path = out_dir / f"case{index}_{minutes:g}min_{rate_hz:g}hz.csv"
    if not log_path.exists():
        sim_car = dataclasses.replace(car, other_terms=OtherTermsParams(**case.other_terms))
        excitation = dataclasses.replace(HARD_THROTTLE if case.hard_throttle else ExcitationSettings(),
                                         control_rate_hz=rate_hz)
        log = generate_log(sim_car, parse_effects(case.effects), minutes, case.seed, excitation=excitation,
                           track=case.track, driver=case.driver)
        write_log_csv(log_path, log)
    wall, cpu = time.perf_counter(), time.process_time()
    result = identify(build_trajectory(read_log(log_path)), car, settings)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return BenchOutcome(case, result, wall, cpu, os.getloadavg()[0], check(case, result))


def run_benchmark(cases: list[BenchCase], out_dir: Path, minutes: float, rate_hz: float, car: CarParams,
                  settings: SysidSettings, progress: Callable[[BenchOutcome], None] | None = None) -> list[BenchOutcome]:
    out_dir.mkdir(parents=True, exist_ok=True)
    outcomes = []
    for case in cases:
        outcome = run_case(case, out_dir, minutes, rate_hz, car, settings)
        outcomes.append(outcome)
        if progress:
            progress(outcome)
    return outcomes


def _fitted(result: SysidResult) -> str:
    parts = []
    for e in result.selected:
        parts += [f"`{k}` {v:.4g}" for k, v in e.params.items()]
    return "; ".join(parts) or "—"


def markdown_table(outcomes: list[BenchOutcome]) -> str:
    lines = ["| # | case | generated | verdict | fitted | horizon pos RMSE: planner / nominal dynamic → final | "
             "reduction vs nominal dynamic | sysid wall / CPU (load) | goals |",
             "|---|---|---|---|---|---|---|---|---|"]
    for o in outcomes:
        r = o.result
        generated = o.case.effects or "(none)"
        if o.case.other_terms:
            generated += " + sim car `[other_terms]` " + ", ".join(f"{k}={v}" for k, v in o.case.other_terms.items())
        verdict = ", ".join(e.effect for e in r.selected) or "no significant effect"
        lines.append(
            f"| {CASES.index(o.case) + 1 if o.case in CASES else '-'} | {o.case.name} | `{generated}` | {verdict} | "
            f"{_fitted(r)} | {100 * r.planner.heldout.horizon_pos_rmse_m:.1f} / "
            f"{100 * r.dynamic_nominal.heldout.horizon_pos_rmse_m:.1f} → {100 * r.final.heldout.horizon_pos_rmse_m:.1f} cm"
            f" | {100 * r.heldout_error_reduction:.0f} % | {o.wall_s:.1f} / {o.cpu_s:.1f} s ({o.load:.1f}) | "
            f"{'met' if o.passed else '; '.join(o.failures)} |")
    return "\n".join(lines) + "\n"
