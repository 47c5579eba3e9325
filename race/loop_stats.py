"""Statistics of the race loop (race.loop.RaceLoop), kept apart from its control flow: tick and stage
timing with deadline misses (:class:`TickStats`), the planners' solves, fallbacks, failures and
latencies (:class:`PlanStats`), the HIL tracking errors against the simulator's truth
(:class:`TrackingStats`) and the world's frames (:class:`FeedStats`). The loop feeds them;
race.loop.LoopOutcome reports them."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from race.config import STAGES, StageBudgets


@dataclass
class PlannerErrorRecord:
    time_s: float   # race time of the plan (its t_plan)
    car: str        # car name
    message: str    # "ExceptionType: message"


class TickStats:
    """Per tick: the period between tick starts, each stage's wall time (perf_counter) against its
    budget (an overrun is counted, not an event), the busy time until the command, deadline misses."""

    def __init__(self, budgets: StageBudgets) -> None:
        self.budgets = budgets
        self.period_ms: list[float] = []
        self.busy_ms: list[float] = []
        self.stage_ms: dict[str, list[float]] = {s: [] for s in STAGES}
        self.overruns = {s: 0 for s in STAGES}
        self.deadline_misses = 0
        self._prev_start: float | None = None

    def tick_started(self, start: float) -> None:
        if self._prev_start is not None:
            self.period_ms.append(1e3 * (start - self._prev_start))
        self._prev_start = start

    def stage(self, name: str, t0: float, times: dict) -> float:
        """Stage ``name`` ran from perf_counter ``t0`` until now: its time goes into ``times`` (this tick's)
        and the statistics. Returns now (the next stage's t0)."""
        t1 = time.perf_counter()
        ms = 1e3 * (t1 - t0)
        times[name] = ms
        self.stage_ms[name].append(ms)
        if ms > getattr(self.budgets, name):
            self.overruns[name] += 1
        return t1

    def commanded(self, start: float, t_cmd: float) -> None:
        self.busy_ms.append(1e3 * (t_cmd - start))


class FeedStats:
    """What the world reports of its frames per poll: render times (HIL: outside the loop's budget) and
    the frames it dropped so far (the world's summary has the final counts; these stand in without one)."""

    def __init__(self) -> None:
        self.render_ms: list[float] = []
        self.frames_dropped = 0

    def polled(self, packet) -> None:
        self.render_ms.extend(packet.render_ms)
        self.frames_dropped = max(self.frames_dropped, packet.dropped)


class PlanStats:
    """The planners' side: wall time of every plan per car after the cold one, the cold plan's time,
    applied RD3G fallbacks, failed car plans, plans applied and failed, each plan's lag (applied minus
    its t_plan) and each plan's new commands (for the HIL command lag). ``planners``: car -> planner."""

    def __init__(self, planners: dict[str, str]) -> None:
        self.planners = dict(planners)
        self.solve_ms: dict[str, list[float]] = {name: [] for name in self.planners}
        self.prestart_ms = 0.0
        self.fallbacks = 0
        self.errors: list[PlannerErrorRecord] = []
        self.plan_lag_ms: list[float] = []
        self.plans = 0
        self.failures = 0
        self._commands: list[tuple[float, int, float, float]] = []  # (t_plan, car index, throttle, steering)

    def car_plan(self, name: str, car_plan, cold: bool) -> None:
        """One car's part of an applied plan (race.planning.CarPlan)."""
        rd3g = self.planners.get(name) == "rd3g"
        if cold:  # the cold plan is made on the grid before the start, outside the real-time budget
            if rd3g:
                self.prestart_ms = max(self.prestart_ms, car_plan.solve_ms)
        elif car_plan.plan is not None:  # pure pursuit has no planning call to time
            self.solve_ms[name].append(car_plan.solve_ms)
            self.fallbacks += rd3g and car_plan.plan.used == "fallback"

    def new_command(self, t_plan: float, car_index: int, throttle: float, steering_rad: float) -> None:
        """A plan's command that differs from the car's previous one, as sent."""
        self._commands.append((t_plan, car_index, throttle, steering_rad))

    def command_lags(self, applied, plan_latency_s: float) -> np.ndarray:
        """For each plan's new command: the first time the simulated car got those values (HIL world's
        applied_changes, same clock) minus the plan's t_plan, in ms. Values match within 2e-3 (rd3g's int16
        steps are 3e-5 of full scale; buzzracer-fhss rounds to 1 us, half a step is 1.25e-3 of throttle and
        5e-4 rad of steering); searched from the job's creation on."""
        lags = []
        by_car: dict[int, list] = {}
        for t, i, throttle, steer in applied:
            by_car.setdefault(i, []).append((t, throttle, steer))
        for t_plan, i, throttle, steer in self._commands:
            t_job = t_plan - plan_latency_s
            for t, th, st in by_car.get(i, []):
                if t >= t_job and abs(th - throttle) < 2e-3 and abs(st - steer) < 2e-3:
                    lags.append(1e3 * (t - t_plan))
                    break
        return np.array(lags)


@dataclass
class TrackingStats:
    """HIL: raw detections and the estimator's posterior against the simulator's truth (mm)."""

    detection_error_mm: list[float] = field(default_factory=list)
    tracking_error_mm: list[float] = field(default_factory=list)
    tracking_heading_error_deg: list[float] = field(default_factory=list)  # the posterior's heading (deg)

    @staticmethod
    def error_mm(x: float, y: float, truth) -> float:
        return 1e3 * math.hypot(x - truth[0], y - truth[1])

    @staticmethod
    def heading_error_deg(heading: float, truth) -> float:
        return abs(math.degrees(math.remainder(heading - truth[2], 2 * math.pi)))
