"""The race loop: frame -> detect -> estimate -> plan -> command -> telemetry at a fixed rate.

One loop for every mode; only the world behind it differs: the pure simulation
(``race.simulation.SimWorld`` on a ``SimulatedClock``, true states as the observation, lock-step
timing: ``plan_ticks = 0``), the hardware-in-the-loop simulation (``--hil``, ``race.hil.HilWorld``) and
real hardware (``--camera``, ``app.realtime.hardware.CameraFeed`` in ``race.feed_world.FeedWorld``),
both in real time. The loop's parts are interfaces (race.world: world, link, perception, planners,
clock); its statistics are race.loop_stats, its recording race.loop_recording.

* Tick k starts at t_go + k T (T = 1 / rate_hz) and must issue its command by t_go + (k+1) T (its
  deadline). Every stage is timed. A tick that starts more than a period late skips the ticks it
  missed (each counted as a deadline miss).
* :class:`DeadlineMonitor` (its own thread) sends neutral at the deadline of a tick that has not
  issued its command yet, and logs which stage was running.
* Safety holds: a lost car (no accepted measurement for ``lost_after_s``), a non-finite state, a
  failed or stale plan, an invalid command, and (HIL, where the box is observable) a corrupt serial
  stream each put every car to neutral: a neutral frame is written at once (not at the sender's
  next tick) and an event is logged; the race resumes when every hold has cleared, and stops
  (``held_neutral``) when holds have lasted ``stop_after_hold_s`` without a break. A serial link
  fault (device gone) ends the race: the link cannot be reopened (docs/serial-protocol.md); the
  transmitter box's failsafe keeps the cars neutral.
* Planning is asynchronous in real time (``race.planning.PlannerWorker``): a job every rate_hz / plan_hz
  ticks for the instant t_plan = its tick + ``plan_latency_s`` (plan_ticks periods + command_delay_s)
  when its command will act; the plan is applied at tick k + plan_ticks, not earlier, and its first
  control is held (zero-order hold) until the next plan is due. The commanded cars are predicted to
  t_plan through the controls the loop has sent them (race.command_history: the loop writes, the
  estimator and the planners read; ``PlanJob.in_flight``). With plan_ticks = 0
  the job is submitted before the tick's plan is chosen, so a synchronous runner
  (``race.planning.SyncPlanRunner``, the simulated race) applies the plan of a tick's observation at
  that tick.
* A planner's failure (race.planning, one policy) holds the cars neutral or applies the failing car's
  fallback plan, as ``LoopConfig.hold_on_planner_error`` says; planner wall times (``solve_ms``) are
  measured on the wall clock whatever the loop's clock.
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from race.command_history import CommandHistory
from race.commands import link_command
from race.config import STAGES, FaultSpec, LoopConfig
from race.faults import FailingPlanners, NanStateEstimator
from race.feed_world import FeedWorld
from race.loop_recording import LoopRecording, NoRecording
from race.loop_stats import FeedStats, PlannerErrorRecord, PlanStats, TickStats, TrackingStats
from race.operator import END_REASON as OPERATOR_STOP, OperatorInput, OperatorStop
from race.perception import Perception
from race.planning import PlanJob, PlannerWorker, PlanResult, planner_errors
from race.safety import SafetyHolds
from race.summary import fleet_keys, percentile, race_summary
from race.world import (CLOCK_ROUNDING_S, Clock, Feed, Link, MonotonicClock, Perceiver, Planners, PlanRunner, Tracker,
                        World, WorldPacket, WorldSummary)

__all__ = ["CarBinding", "DeadlineMonitor", "LoopError", "LoopOutcome", "PlannerErrorRecord", "RaceLoop",
           "SimulatedDeadlineMonitor", "setup_document"]
from tracking.estimator import EstimatorConfig
from vehicles.protocol import CarCommand, ProtocolError


class LoopError(RuntimeError):
    """The race could not start or had to stop for a reason the operator must see."""


@dataclass(frozen=True)
class CarBinding:
    name: str          # the roster's name of the car
    marker_id: int     # ArUco id on the roof
    radio_id: int      # id in the serial protocol


class DeadlineMonitor:
    """Watchdog thread: if the armed tick has not finished its command by the deadline, call
    ``on_miss(tick, stage)`` (which sends neutral) from this thread. Real time only: the thread waits
    on the clock's time (a simulated clock's race has no deadlines to watch)."""

    def __init__(self, on_miss, clock: Clock | None = None) -> None:
        self.on_miss = on_miss
        self.clock = clock if clock is not None else MonotonicClock()
        self.stage = "-"
        self._cv = threading.Condition()
        self._deadline: float | None = None
        self._tick = -1
        self._fired = False
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="DeadlineMonitor", daemon=True)
        self._thread.start()

    def arm(self, tick: int, deadline: float) -> None:
        with self._cv:
            self._tick, self._deadline, self._fired = tick, deadline, False
            self._cv.notify()

    def disarm(self) -> bool:
        """Returns True if the monitor fired for the armed tick."""
        with self._cv:
            self._deadline = None
            return self._fired

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        with self._cv:
            while not self._stop:
                if self._deadline is None:
                    self._cv.wait()
                    continue
                remaining = self._deadline - self.clock.now()
                if remaining > 0:
                    self._cv.wait(remaining)
                    continue
                self._fired = True
                self._deadline = None
                tick, stage = self._tick, self.stage
                self._cv.release()
                try:
                    self.on_miss(tick, stage)
                finally:
                    self._cv.acquire()


class SimulatedDeadlineMonitor:
    """DeadlineMonitor on a race.world.SimulatedClock: fires when the clock is advanced past the armed
    deadline (checked by the clock's watchers, no thread). The simulated race's clock only moves
    between ticks, so there it never fires; the fake-clock tests advance it inside a tick."""

    def __init__(self, on_miss, clock) -> None:
        self.on_miss, self.clock, self.stage = on_miss, clock, "-"
        self._deadline = None
        self._fired = False
        self._tick = -1
        clock.watchers.append(self._check)

    def arm(self, tick: int, deadline: float) -> None:
        self._tick, self._deadline, self._fired = tick, deadline, False

    def disarm(self) -> bool:
        self._deadline = None
        return self._fired

    def _check(self) -> None:
        if self._deadline is not None and self.clock.now() > self._deadline:
            self._deadline, self._fired = None, True
            self.on_miss(self._tick, self.stage)

    def stop(self) -> None:
        self.clock.watchers.remove(self._check)


@dataclass
class LoopOutcome:
    # finished, time_limit, held_neutral, serial_fault, interrupted, operator_stop, world_error
    reason: str
    mode: str
    winner: str | None = None
    lap_times_s: dict = field(default_factory=dict)
    min_gap_m: float | None = None
    collisions: list = field(default_factory=list)
    race_time_s: float = 0.0
    ticks: int = 0
    deadline_misses: int = 0
    period_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stage_ms: dict = field(default_factory=dict)
    busy_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stage_overruns: dict = field(default_factory=dict)
    solve_ms: dict = field(default_factory=dict)  # per car, planning wall time (ms) of every plan after the cold one
    prestart_ms: float = 0.0                     # the cold plan before the start (wall time, ms)
    fallbacks: int = 0                           # applied RD3G plans (every RD3G car) that were the planner's fallback
    planner_errors: list = field(default_factory=list)  # PlannerErrorRecord of every failed car plan
    # Per plan: when the loop first applied it minus the instant its states were predicted to
    # (t_plan = job tick + plan_latency_s); >= -command_delay_s when applied at its tick, > 0 when late.
    plan_lag_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # HIL: per plan, when the simulated car got its first command minus the plan's t_plan (the whole path
    # loop -> serial link -> box -> car); ~0 when command_delay_s is right. Empty on hardware.
    command_lag_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    plans: int = 0
    plan_failures: int = 0
    frames: int = 0
    frames_dropped: int = 0
    render_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tracking_error_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tracking_heading_error_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    detection_error_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    events: list = field(default_factory=list)   # (race time s, kind, text)
    control_period_ms: float = 0.0
    recording: str | None = None
    load_average: tuple | None = None
    box: dict | None = None                      # HIL: virtual box and relay counters (diagnostics)
    planners: dict = field(default_factory=dict)  # roster order: car name -> planner
    results: list = field(default_factory=list)   # race.referee.CarResult per car
    finish_order: list = field(default_factory=list)

    def summary(self) -> dict:
        """The `race --hil/--camera --json` record: the simulated race's keys plus loop statistics."""
        pct = percentile
        rd3g = [name for name, kind in self.planners.items() if kind == "rd3g"]
        solve = np.concatenate([self.solve_ms.get(name, np.zeros(0)) for name in rd3g] or [np.zeros(0)])
        others = [name for name, kind in self.planners.items() if kind == "mpc"]
        other_solve = np.concatenate([self.solve_ms.get(name, np.zeros(0)) for name in others] or [np.zeros(0)])
        kinds: dict[str, int] = {}
        for _, kind, _ in self.events:
            kinds[kind] = kinds.get(kind, 0) + 1
        return {
            **race_summary(winner=self.winner, lap_times_s=self.lap_times_s, min_gap_m=self.min_gap_m,
                           collisions=len(self.collisions), solve_ms=solve, control_period_ms=self.control_period_ms),
            "mode": self.mode, "end_reason": self.reason, "race_time_s": self.race_time_s, "ticks": self.ticks,
            "loop_hz_median": 1e3 / float(np.median(self.period_ms)) if len(self.period_ms) else None,
            "loop_period_p99_ms": pct(self.period_ms, 99), "deadline_misses": self.deadline_misses,
            "deadline_miss_rate": self.deadline_misses / self.ticks if self.ticks else None,
            "stage_ms_p50": {k: pct(v, 50) for k, v in self.stage_ms.items()},
            "stage_ms_p99": {k: pct(v, 99) for k, v in self.stage_ms.items()},
            "busy_ms_p50": pct(self.busy_ms, 50), "busy_ms_p99": pct(self.busy_ms, 99),
            "stage_overruns": self.stage_overruns,
            "opponent_solve_ms_p50": pct(other_solve, 50),
            "plans": self.plans, "plan_failures": self.plan_failures,
            "plan_lag_ms_p50": pct(self.plan_lag_ms, 50), "plan_lag_ms_p99": pct(self.plan_lag_ms, 99),
            "command_lag_ms_p50": pct(self.command_lag_ms, 50), "command_lag_ms_p99": pct(self.command_lag_ms, 99),
            "frames": self.frames, "frames_dropped": self.frames_dropped,
            "render_ms_p50": pct(self.render_ms, 50), "render_ms_p99": pct(self.render_ms, 99),
            "tracking_error_mm_median": pct(self.tracking_error_mm, 50),
            "tracking_error_mm_p95": pct(self.tracking_error_mm, 95),
            "tracking_heading_error_deg_median": pct(self.tracking_heading_error_deg, 50),
            "tracking_heading_error_deg_p95": pct(self.tracking_heading_error_deg, 95),
            "detection_error_mm_median": pct(self.detection_error_mm, 50),
            "events": kinds, "recording": self.recording,
            "load_average": list(self.load_average) if self.load_average else None,
            "box": self.box,
            "rd3g_at_fault": sum(self.planners.get(c.at_fault) == "rd3g" for c in self.collisions),
            **fleet_keys(self.results, self.planners, {n: v for n, v in self.solve_ms.items()
                                                       if self.planners.get(n) in ("rd3g", "mpc")},
                         self.finish_order, self.collisions),
        }




class RaceLoop:
    """One race on the clock. ``world`` (race.world.World: ``poll``, ``go``, ``observe``, ``close``) is the
    simulated world or the HIL world; without one (hardware), ``feed`` (``poll(timeout) -> WorldPacket``)
    is wrapped in race.feed_world.FeedWorld, which referees the perceived states. ``link`` drives the
    cars. ``perception`` (race.world.Perceiver) defaults to race.perception.Perception(tracker,
    estimator) on the loop's command history ``commands`` (race.command_history.CommandHistory: the loop
    writes what it sends, the estimator and the planners read it; default: an injected perception's
    own ``commands``, else a new one). ``faults`` are injected by wrapping the estimator and the planners (race.faults); ``clock``
    defaults to real time, ``worker_factory(planners, clock)`` to a PlannerWorker thread
    (race.planning.SyncPlanRunner plans in the loop's thread) and ``monitor_factory(on_miss, clock)`` to
    the DeadlineMonitor thread. ``operator`` (race.operator) is polled once a tick for the operator's
    stop key (None: no stop key, the simulated race). Statistics: race.loop_stats; recording:
    race.loop_recording."""

    def __init__(self, *, setup, config: LoopConfig, feed: Feed, link: Link, planners: Planners,
                 cars: list[CarBinding], tracker: Tracker | None = None, estimator=None,
                 perception: Perceiver | None = None, recorder=None, faults: tuple[FaultSpec, ...] = (),
                 world: World | None = None, mode: str = "hil", clock: Clock | None = None, worker_factory=None,
                 monitor_factory=DeadlineMonitor, commands: CommandHistory | None = None,
                 operator: OperatorInput | None = None) -> None:
        self.setup, self.cfg, self.feed = setup, config, feed
        self.link, self.cars, self.mode = link, cars, mode
        self.clock = clock if clock is not None else MonotonicClock()
        if commands is None:  # an injected Perception brings the history its estimator reads
            commands = getattr(perception, "commands", None) or CommandHistory()
        self.commands = commands
        self.faults = tuple(faults)
        if any(f.kind == "nan_state" for f in self.faults):
            estimator = NanStateEstimator(estimator, self.faults, {c.name: c.marker_id for c in cars}, self.race_time,
                                          lambda text: self._event("fault_injected", text))
        if any(f.kind == "solver_fail" for f in self.faults):
            planners = FailingPlanners(planners, self.faults, self.race_time)
        self.estimator, self.planners = estimator, planners
        self.perception: Perceiver = perception if perception is not None else Perception(
            tracker, estimator, cars, config.lost_search_every, commands=self.commands)
        self.names = [c.name for c in cars]
        self.world: World = world if world is not None else FeedWorld(feed, setup, self.names,
                                                                      self.perception.states_at)
        self.rec = recorder  # race.recording.RaceRecorder or None
        self.recording = (LoopRecording(recorder, setup.car.geometry, config.image_log_every, config.image_downscale)
                          if recorder is not None else NoRecording())
        self.safety = SafetyHolds(self._neutral_now, self._event, config.stop_after_hold_s)
        self.operator_stop = None if operator is None else OperatorStop(operator, self._neutral_now, self._event)
        self.track = setup.track
        self.car = setup.car
        self.commanded = [c for c in cars if c.name in planners.commanded]
        self.worker: PlanRunner = (worker_factory or PlannerWorker)(planners, self.clock)
        self._monitor_factory = monitor_factory
        self.t_go: float | None = None
        self.events: list[tuple] = []
        self.k = 0
        self._link_fault: BaseException | None = None
        self._active: PlanResult | None = None
        self._last_seq = 0
        self._last_corrupt = 0
        self._last_corrupt_t = -float("inf")
        self._lock = threading.Lock()
        self._misses_by_monitor: set[int] = set()
        self.monitor: DeadlineMonitor | None = None
        self.planner_kinds = {c.name: c.planner for c in getattr(planners, "cars", setup.cars)}
        self.ticks = TickStats(config.budgets)
        self.planning = PlanStats({name: self.planner_kinds.get(name) for name in self.names})
        self.tracking = TrackingStats()
        self._last_sent: dict[str, tuple[float, float]] = {}
        self.feed_stats = FeedStats()
        self.winner_seen: str | None = None

    # ------------------------------------------------------------------ helpers
    def race_time(self, t_abs: float | None = None) -> float:
        t_abs = self.clock.now() if t_abs is None else t_abs
        return t_abs - self.t_go if self.t_go is not None else 0.0

    def _event(self, kind: str, text: str, t_race: float | None = None) -> None:
        t_race = self.race_time() if t_race is None else t_race
        with self._lock:
            self.events.append((t_race, kind, text))
        self.recording.event(t_race, kind, text, step=self.k)

    def _neutral_now(self) -> None:
        try:
            self.link.neutral()
        except Exception as exc:  # never let the safety action raise into the loop
            self._event("error", f"sending neutral failed: {exc}")

    @property
    def holds(self) -> dict[str, str]:
        return self.safety.holds

    @property
    def frames(self) -> int:
        return self.perception.frames

    def _on_link_fault(self, exc: BaseException) -> None:
        self._link_fault = exc

    def _on_deadline_miss(self, tick: int, stage: str) -> None:
        self._neutral_now()
        with self._lock:
            self._misses_by_monitor.add(tick)
        self._event("deadline_miss", f"tick {tick}: no command by the deadline (stage {stage} running) - neutral sent")

    def _world_report(self, packet: WorldPacket) -> str | None:
        """The events a world reported (a poll, or its answer to the tick's states); "finished" once
        its referee has decided the race."""
        for t_ev, kind, text in packet.events:
            self._event(kind, text, t_race=t_ev)
        if packet.winner is not None and self.winner_seen is None:
            self.winner_seen = packet.winner
            return "finished"
        return None

    # ------------------------------------------------------------------ phases
    def run(self) -> LoopOutcome:
        reason = "interrupted"
        old_switch = sys.getswitchinterval()
        sys.setswitchinterval(0.001)  # background threads (telemetry, planner glue) yield the GIL sooner
        try:
            self._acquire()
            self._cold_start()
            reason = self._race()
        except KeyboardInterrupt:
            reason = "interrupted"
            self._event("stop", "interrupted by the operator")
        finally:
            sys.setswitchinterval(old_switch)
            summary = self._shutdown()
        return self._outcome(reason, summary)

    def _acquire(self) -> None:
        """Before the start: full searches until every car has enough accepted measurements."""
        deadline = self.clock.now() + self.cfg.acquire_timeout_s
        while True:
            packet = self.world.poll(0.1)
            self.perception.acquire(packet)
            missing = self.perception.acquired(self.cfg.acquire_measurements)
            if not missing:
                return
            if self.clock.now() > deadline:
                names = ", ".join(f"{c.name} (marker {c.marker_id})" for c in missing)
                raise LoopError(f"camera did not find {names} within {self.cfg.acquire_timeout_s:.0f} s; "
                                f"check the markers, the lighting and the calibration")

    def _cold_start(self) -> None:
        """First plan with the solver's full globalisation, before the clock starts."""
        t = self.clock.now()
        result = self.worker.run_sync(PlanJob(-1, t, self.perception.states_at(t)))
        failed = result.error or (self.cfg.hold_on_planner_error and self._errors_text(result))
        if failed:
            raise LoopError(f"cold-start planning failed: {failed}")
        self.worker.start()
        self.t_go = self.clock.now() + 2 * self.cfg.period_s
        result.job.t_plan = self.t_go  # the cold-start plan is the plan for the start
        self._take_plan(result, self.clock.now())
        for c in self.commanded:  # on the grid: at rest and neutral until tick 0's command acts
            self.commands.record(c.name, t - 1.0, self.planners.executed_control(c.name, None, 0.0))
        self.world.go(self.t_go)
        self._event("start", f"race started ({self.mode}, loop {self.cfg.rate_hz:g} Hz, "
                             f"planning {self.cfg.plan_hz:g} Hz)", t_race=0.0)

    def _job(self, k: int, t_plan: float, states: dict) -> PlanJob:
        """A planning job with the commanded cars' last measured poses and the commands sent so far."""
        measured = {c.name: m for c in self.commanded if (m := self.perception.last_measurement(c.name)) is not None}
        return PlanJob(k, t_plan, states, measured=measured, commands=self.commands.snapshot())

    @staticmethod
    def _errors_text(result: PlanResult) -> str:
        return "; ".join(f"{name}: {text}" for name, text in planner_errors(result).items())

    def _take_plan(self, result: PlanResult, now: float) -> None:
        self._last_seq = result.seq
        t_race = self.race_time(result.job.t_plan) if self.t_go is not None else 0.0
        errors = planner_errors(result)
        for name, text in errors.items():
            self.planning.errors.append(PlannerErrorRecord(t_race, name, text))
        if result.error or (errors and self.cfg.hold_on_planner_error):
            self.planning.failures += 1
            self.safety.set("planner", True, f"planner failed: {result.error or self._errors_text(result)}")
            return
        for name, text in errors.items():  # the fallback plan is applied (LoopConfig.hold_on_planner_error)
            self._event("planner_error", f"{name}: {text}", t_race=t_race)
        self._active = result
        self.planning.plans += 1
        self.safety.set("planner", False)
        cold = self.t_go is None or result.job.tick < 0
        step = max(self.k, 0)
        if not cold:
            lag = 1e3 * (now - result.job.t_plan)
            self.planning.plan_lag_ms.append(lag)
            self.recording.plan_lag(step, t_race, lag)
        for name, cp in result.cars.items():
            self.planning.car_plan(name, cp, cold)
            # The cold plan is recorded where the loop drives it (its first plan_ticks ticks); in
            # lock-step the tick-0 plan replaces it before any command.
            if cp.plan is not None and not (cold and self.cfg.plan_ticks == 0):
                self.recording.plan(step, t_race, self.track, name, cp)

    # ------------------------------------------------------------------ the race
    def _race(self) -> str:
        cfg = self.cfg
        T = cfg.period_s
        self.monitor = self._monitor_factory(self._on_deadline_miss, self.clock)
        self.k = 0
        while True:
            t_k = self.t_go + self.k * T
            now = self.clock.now()
            if now < t_k:
                self.clock.sleep(t_k - now)
            start = self.clock.now()
            if start > t_k + T:  # more than a period late: skip the ticks that are already past
                skipped = int((start - t_k) / T)
                self.ticks.deadline_misses += skipped
                self._event("deadline_miss", f"{skipped} tick(s) skipped: loop {1e3 * (start - t_k):.1f} ms late")
                self._neutral_now()  # the last command is stale by now
                self.k += skipped
                t_k = self.t_go + self.k * T
            self.ticks.tick_started(start)
            if self.operator_stop is not None and self.operator_stop.check(start - self.t_go):
                return OPERATOR_STOP
            self.monitor.arm(self.k, t_k + T)
            end_reason = self._tick(start, t_k + T)
            if end_reason:
                return end_reason
            self.k += 1

    def _stage(self, name: str, t0: float, times: dict) -> float:
        t1 = self.ticks.stage(name, t0, times)
        if self.monitor is not None:
            self.monitor.stage = next((s for s in STAGES[STAGES.index(name) + 1:]), "-")
        return t1

    def _tick(self, start: float, deadline: float) -> str | None:
        """One tick: frame, perception (detect + estimate), safety checks, plan, command, telemetry, end
        of race. Returns the end reason, or None to go on."""
        k = self.k
        t_race = start - self.t_go
        times: dict[str, float] = {}
        self.monitor.stage = "frame"
        if self._link_fault is not None:
            self._event("serial_fault", f"serial link failed ({self._link_fault}); the box failsafe holds the cars "
                                        f"neutral - race stopped")
            return "serial_fault"
        t0 = time.perf_counter()
        try:
            packet = self.world.poll(0.0)
        except RuntimeError as exc:
            self._event("world_error", str(exc).splitlines()[0])
            return "world_error"
        self.feed_stats.polled(packet)
        if self._world_report(packet):  # the world's referee ended the race
            return "finished"
        if t_race >= self.setup.max_time_s - CLOCK_ROUNDING_S:  # nothing more is planned
            self._event("stop", f"time limit {self.setup.max_time_s:.0f} s reached")
            return "time_limit"
        t0 = self._stage("frame", t0, times)
        t_tick = deadline - self.cfg.period_s  # the tick's scheduled start: plans are timed from it, not from `now`
        t_plan = t_tick + self.cfg.plan_latency_s
        marks = [t0]

        def detected() -> None:
            marks[0] = self._stage("detect", marks[0], times)

        perceived = self.perception.perceive(packet, t_plan, self.clock.now(), after_detect=detected)
        if packet.truth is not None and perceived.observation is not None:
            self._tracking_errors(k, packet, perceived)
        now = self.clock.now()
        self._safety_checks(perceived, packet, now)
        t0 = self._stage("estimate", marks[0], times)
        commands, sent = self._plan_stage(k, now, t_tick, t_plan, perceived.states)
        t0 = self._stage("plan", t0, times)
        sent = self._command_stage(k, start, deadline, commands, sent)
        t0 = self._stage("command", t0, times)
        answer = self.world.observe(self.race_time(t_plan), perceived.states)  # the states are at t_plan
        seen = packet if packet.truth is not None and packet.t_race is not None else answer
        truth = None if seen.truth is None else {name: seen.truth[i] for i, name in enumerate(self.names)}
        self.recording.tick(k, t_race, times=times, stats=self.ticks, perceived=perceived,
                            estimated=self.perception.estimated, sent=sent, holds=len(self.holds),
                            now=self.clock.now(), race_time=self.race_time, frames=self.frames,
                            render_ms=packet.render_ms, truth=truth, t_truth=seen.t_race)
        self._stage("telemetry", t0, times)
        self.recording.telemetry_time(k, t_race, times["telemetry"])
        return self._end_of_race(answer, now)

    def _tracking_errors(self, k: int, packet, perceived) -> None:
        """HIL: raw poses and the estimates at their times vs the simulator's truth at the frame's capture time."""
        t_cap = self.race_time(perceived.observation.t_s)
        for name, pose in perceived.observation.poses.items():
            truth = packet.truth[self.names.index(name)]
            det_err = self.tracking.error_mm(pose.x, pose.y, truth)
            self.tracking.detection_error_mm.append(det_err)
            est = perceived.accepted.get(name)
            err = None if est is None else self.tracking.error_mm(est[0], est[1], truth)
            if err is not None:
                self.tracking.tracking_error_mm.append(err)
                self.tracking.tracking_heading_error_deg.append(self.tracking.heading_error_deg(est[2], truth))
            self.recording.tracking_errors(k, t_cap, name, det_err, err)

    def _safety_checks(self, perceived, packet, now: float) -> None:
        """The tracking, state and serial-stream holds of this tick (race.safety)."""
        lost_ms = 1e3 * self.perception.lost_after_s
        for c in self.cars:
            self.safety.set(f"lost:{c.name}", perceived.lost[c.name],
                            f"car {c.name} lost (no marker {c.marker_id} for {lost_ms:.0f} ms)")
            if perceived.lost[c.name]:
                continue
            nonfinite = c.name in perceived.nonfinite
            self.safety.set(f"nan:{c.name}", nonfinite, f"non-finite state of car {c.name}; estimator reset")
        if packet.box_corrupt > self._last_corrupt:  # HIL: the box reports rejected frames
            self._last_corrupt = packet.box_corrupt
            self._last_corrupt_t = now
        self.safety.set("serial", now - self._last_corrupt_t < self.cfg.serial_quiet_s,
                        "serial stream corrupt (box rejects frames)")

    def _plan_stage(self, k: int, now: float, t_tick: float, t_plan: float, states: dict):
        """Apply the plan due at this tick, check its age, decide this tick's commands (neutral while a
        hold is active), write them to the command history and submit the next planning job.
        Returns ({radio id: CarCommand}, {car: (throttle, steering rad) sent})."""
        cfg = self.cfg
        submit = k % cfg.plan_every == 0 and len(states) == len(self.cars)
        if submit and cfg.plan_ticks == 0:  # lock-step: plan from this tick's observation, for this tick
            self.worker.submit(self._job(k, t_plan, states))
        result = self.worker.latest()
        # A plan is applied at its scheduled tick, not earlier: every plan then acts plan_latency_s after
        # its job, whatever its solve time (a failure is taken at once: it is a fault).
        if result is not None and result.seq != self._last_seq and (
                result.error or result.job.tick < 0 or k >= result.job.tick + cfg.plan_ticks):
            self._take_plan(result, now)
        if self._active is not None:
            age = now - self._active.job.t_plan
            self.safety.set("planner_stale", age > cfg.max_plan_age_s,
                            f"no new plan for {1e3 * age:.0f} ms (limit {1e3 * cfg.max_plan_age_s:.0f} ms)")
        # This tick's commands (sent in the command stage), in the history as the controls the cars execute
        # from t_tick + command_delay_s on: the next job predicts its own cars through them.
        commands: dict[int, CarCommand] = {}
        sent = {c.name: (0.0, 0.0) for c in self.commanded}
        driving = not self.safety and self._active is not None
        for c in self.commanded:
            cp = self._active.cars[c.name] if driving else None
            if cp is not None:
                commands[c.radio_id] = link_command(self.car, cp.throttle, cp.steering_rad)
                sent[c.name] = (cp.throttle, cp.steering_rad)
                if self._last_sent.get(c.name) != sent[c.name] and self._active.job.tick >= 0:
                    self.planning.new_command(self._active.job.t_plan, self.names.index(c.name), *sent[c.name])
            else:
                commands[c.radio_id] = CarCommand(0.0, 0.0)
            speed = float(states[c.name][3]) if c.name in states else 0.0
            self.commands.record(c.name, t_tick + cfg.command_delay_s,
                                 self.planners.executed_control(c.name, cp, speed))
        if driving:
            self._last_sent = dict(sent)
        if submit and cfg.plan_ticks > 0:
            self.worker.submit(self._job(k, t_plan, states))
        return commands, sent

    def _command_stage(self, k: int, start: float, deadline: float, commands: dict, sent: dict) -> dict:
        """Send the commands (an invalid one is a hold), then account for the tick's deadline."""
        try:
            self.link.set_commands(commands)
            self.safety.set("command", False)
        except ProtocolError as exc:
            self.safety.set("command", True, f"invalid command: {exc}")
            sent = {c.name: (0.0, 0.0) for c in self.commanded}
        t_cmd = self.clock.now()
        fired = self.monitor.disarm()
        with self._lock:
            missed = fired or k in self._misses_by_monitor
        if missed or t_cmd > deadline:
            self.ticks.deadline_misses += 1
            if not missed:
                self._event("deadline_miss", f"tick {k}: command {1e3 * (t_cmd - deadline):.1f} ms after the deadline")
        self.ticks.commanded(start, t_cmd)
        return sent

    def _end_of_race(self, answer: WorldPacket, now: float) -> str | None:
        if self._world_report(answer):
            return "finished"
        stop = self.safety.stop_reason(now)
        if stop is not None:
            self._event("stop", stop)
            return "held_neutral"
        return None

    # ------------------------------------------------------------------ shutdown
    def _shutdown(self) -> WorldSummary | None:
        if self.monitor is not None:
            self.monitor.stop()
        self._neutral_now()
        try:
            self.link.stop()
        except Exception:
            pass
        self.worker.stop()
        # Keep reading the world briefly: the box's failsafe (100 ms) and the cars' reaction to the
        # final neutral happen after the loop has stopped and belong in the recording.
        t_end = self.clock.now() + self.cfg.linger_s
        while self.clock.now() < t_end:
            try:
                packet = self.world.poll(0.02)
            except RuntimeError:
                break
            for t_ev, kind, text in packet.events:
                self._event(kind, text, t_race=t_ev)
        summary = self.world.close()
        if summary is not None:
            for t_ev, kind, text in summary.events:
                self._event(kind, text, t_race=t_ev)
        return summary

    def _outcome(self, reason: str, summary: WorldSummary | None) -> LoopOutcome:
        ticks, plans, tracking = self.ticks, self.planning, self.tracking
        out = LoopOutcome(reason=reason, mode=self.mode, ticks=self.k + (1 if self.t_go else 0),
                          deadline_misses=ticks.deadline_misses, period_ms=np.array(ticks.period_ms),
                          stage_ms={s: np.array(v) for s, v in ticks.stage_ms.items()},
                          busy_ms=np.array(ticks.busy_ms), stage_overruns=dict(ticks.overruns),
                          solve_ms={n: np.array(v) for n, v in plans.solve_ms.items()}, plans=plans.plans,
                          prestart_ms=plans.prestart_ms, fallbacks=plans.fallbacks,
                          planner_errors=list(plans.errors), plan_lag_ms=np.array(plans.plan_lag_ms),
                          command_lag_ms=plans.command_lags(summary.applied_changes if summary else [],
                                                            self.cfg.plan_latency_s),
                          plan_failures=plans.failures, frames=self.frames,
                          render_ms=np.array(self.feed_stats.render_ms), frames_dropped=self.feed_stats.frames_dropped,
                          tracking_error_mm=np.array(tracking.tracking_error_mm),
                          tracking_heading_error_deg=np.array(tracking.tracking_heading_error_deg),
                          detection_error_mm=np.array(tracking.detection_error_mm), events=list(self.events),
                          control_period_ms=1e3 * self.cfg.period_s, load_average=os.getloadavg(),
                          planners=dict(self.planner_kinds),
                          recording=None if self.rec is None else str(self.rec.path))
        if summary is not None:
            out.winner = summary.winner
            out.lap_times_s = summary.lap_times_s
            out.min_gap_m = summary.min_gap_m
            out.collisions = summary.collisions
            out.race_time_s = summary.race_time_s
            out.frames_dropped = summary.frames_dropped
            out.render_ms = np.asarray(summary.render_ms, dtype=float)
            out.box = summary.box
            out.finish_order = list(summary.finish_order)
            out.results = list(summary.results)
        else:  # the world's summary was lost (a HIL world process that died)
            out.winner = self.winner_seen
            out.race_time_s = self.race_time() if self.t_go else 0.0
        return out


def setup_document(setup, config: LoopConfig, mode: str, cars: list[CarBinding], opponent: str, faults,
                   estimator: EstimatorConfig = EstimatorConfig(), planners: dict | None = None) -> str:
    """The race/setup TextDocument of a real-time race (JSON); ``loop.lost_after_s`` is the estimator's,
    ``planners`` {car: planner} (default: the set-up's roster)."""
    doc = {"mode": mode, "track": setup.track.name, "car": setup.car.name, "seed": setup.seed, "laps": setup.laps,
           "start": setup.start, "opponent": opponent, "rd3g_top_speed_mps": setup.rd3g_top_speed_mps,
           "opponent_top_speed_mps": setup.opponent_top_speed_mps, "max_time_s": setup.max_time_s,
           "planning_period_s": setup.control_period_s,
           "off_track_allowance_car_lengths": setup.off_track_allowance_car_lengths,
           "loop": {**dataclasses.asdict(config), "lost_after_s": estimator.lost_after_s},
           "cars": [dataclasses.asdict(c) for c in cars], "faults": [dataclasses.asdict(f) for f in faults],
           "planners": planners or {c.name: c.planner for c in setup.cars}}
    return json.dumps(doc, indent=2)
