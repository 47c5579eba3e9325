"""The pure simulation: one race of the roster's cars (race.roster: RD3G, MPC, pure pursuit) in
sim.Simulator, run by the one race loop (race.loop.RaceLoop) on a simulated clock. Used by
`python -m app race`, `python -m app batch`, sysid's closed loop and the race benches. Conventions and
entity paths: docs/racing.md.

* :class:`SimWorld` is the simulator behind the loop's World and Link interfaces (race.world): each
  poll advances the physics to the clock's time in whole control periods with the commands the
  link was last given, and reports the true states, the simulator's events (laps, finish,
  collisions with the car at fault, off-track: race.referee.Referee) and the winner once the race is
  decided (the first car home, or every car home: ``RaceSetup.finish``). The loop perceives the true states
  (race.perception.TruthPerception).
* Timing (:func:`simulation_config`): one loop tick per control period (``RaceSetup.control_period_s``)
  and lock-step planning: the plan made from the states observed at tick k is applied at tick k and
  acts from then until tick k + 1 (``plan_ticks = 0``, ``command_delay_s = 0``); the planner's own
  prediction covers the car's actuation delay (race.planning.plan_step). The clock
  (race.world.SimulatedClock) moves only between ticks, so results do not depend on how long a plan
  takes: the same seed gives the same race on any machine load. Planner wall times are still
  measured (``solve_ms``).
* A car whose planner raised drives its fallback plan and the step is logged as ``planner_error``
  (``LoopConfig.hold_on_planner_error = False``; race.planning has the one failure policy).
"""
from __future__ import annotations

import dataclasses
import math
import signal
import threading
from dataclasses import dataclass, field

import numpy as np

from planning import ProgressUnwrapper
from race.commands import physical_command
from race.config import LoopConfig
from race.loop import CarBinding, PlannerErrorRecord, RaceLoop, SimulatedDeadlineMonitor
from race.perception import TruthPerception
from race.planning import RacePlanners, SyncPlanRunner
from race.recording import SETUP_ENTITY, RaceRecorder
from race.referee import CarResult, CollisionRecord, Referee
from race.setup import RaceSetup, start_states
from race.summary import fleet_keys, race_summary
from race.world import CLOCK_ROUNDING_S, SimulatedClock, WorldPacket, WorldSummary
from sim import Simulator
from vehicles.protocol import check_command_value

__all__ = ["PlannerErrorRecord", "RaceOutcome", "SimWorld", "run_race", "simulation_config"]



def sim_cars(setup: RaceSetup) -> list[CarBinding]:
    """The loop's binding of each simulated car (roster order): the roster's marker and radio ids (the
    loop addresses cars by them)."""
    return [CarBinding(c.name, c.marker_id, c.radio_id) for c in setup.cars]


@dataclass
class RaceOutcome:
    winner: str | None
    lap_times_s: dict[str, list[float]]
    min_gap_m: float
    collisions: list[CollisionRecord]
    solve_ms: np.ndarray            # wall time of every RD3G planning call (ms), every RD3G car pooled
    opponent_solve_ms: np.ndarray   # same for the other solving planners (MPC; empty for pursuit)
    control_period_ms: float
    race_time_s: float
    fallbacks: int                  # RD3G steps that applied the fallback tracking control
    off_track: dict[str, int]       # excursions per car (a footprint corner outside the drivable area)
    start_states: np.ndarray
    trace_t: np.ndarray = field(default_factory=lambda: np.zeros(0))       # (n,) s, every control step
    trace_states: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 6)))  # (n, 2, 6) true states
    trace_progress: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))   # (n, 2) unwrapped s (m)
    prestart_ms: float = 0.0        # RD3G's first (cold) plan, computed on the grid before the start
    planner_errors: list[PlannerErrorRecord] = field(default_factory=list)  # steps whose planning raised (either car)
    interrupted: bool = False       # stopped by Ctrl-C: the record covers the race up to race_time_s
    planners: dict[str, str] = field(default_factory=dict)        # roster order: car name -> planner
    results: list[CarResult] = field(default_factory=list)         # per car (race.referee.CarResult)
    finish_order: list[str] = field(default_factory=list)
    car_solve_ms: dict[str, np.ndarray] = field(default_factory=dict)  # per solving car

    @property
    def clean_winner(self) -> str | None:
        """The winner if it never left the track, else None: a car off the drivable area may cut the
        infield (its progress jumps), so such a win does not count."""
        if self.winner is None or self.off_track[self.winner] > 0:
            return None
        return self.winner

    def summary(self) -> dict:
        """The `race --json` record (docs/racing.md)."""
        return {**race_summary(winner=self.winner, lap_times_s=self.lap_times_s, min_gap_m=self.min_gap_m,
                               collisions=len(self.collisions), solve_ms=self.solve_ms,
                               control_period_ms=self.control_period_ms),
                "clean_winner": self.clean_winner,
                "rd3g_at_fault": sum(self.planners.get(c.at_fault) == "rd3g" for c in self.collisions),
                "off_track": self.off_track, "fallbacks": self.fallbacks, "prestart_ms": self.prestart_ms,
                "planner_errors": len(self.planner_errors), "interrupted": self.interrupted,
                "race_time_s": self.race_time_s, **fleet_keys(self.results, self.planners, self.car_solve_ms,
                                                              self.finish_order, self.collisions)}


class _InterruptRequest:
    """While active (main thread only), the first Ctrl-C sets ``requested`` instead of raising, so the
    simulated world can stop the race at its next poll (between ticks) with the recording and the
    summary whole; a second Ctrl-C raises at once."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = None

    def _handle(self, signum, frame) -> None:
        self.requested = True
        signal.signal(signal.SIGINT, self._previous)

    def __enter__(self) -> "_InterruptRequest":
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        if self._previous is not None and not self.requested:
            signal.signal(signal.SIGINT, self._previous)


class SimWorld:
    """sim.Simulator behind the loop's World (``poll``, ``go``, ``close``) and Link (``set_commands``,
    ``neutral``, ``stop``) interfaces, on a SimulatedClock. ``cars``: the loop's CarBinding of each
    simulated car (roster order, default sim_cars(setup); commands are addressed by radio id). ``interrupt``: an object whose
    ``requested`` flag ends the race at the next poll (KeyboardInterrupt, as a real Ctrl-C)."""

    def __init__(self, sim: Simulator, clock: SimulatedClock, setup: RaceSetup, cars=None, progress=None,
                 interrupt=None) -> None:
        self.sim, self.clock, self.setup = sim, clock, setup
        self.period = setup.control_period_s
        cars = sim_cars(setup) if cars is None else cars
        self.names = tuple(c.name for c in cars)
        self.radio_index = {c.radio_id: i for i, c in enumerate(cars)}
        # minimum gap, the car at fault in a collision, off-track per car
        self.referee = Referee(setup.track, setup.car, self.names)
        self.commands = np.zeros((sim.n_cars, 2))        # (throttle, steering rad) in effect
        self.t_go: float | None = None
        self.steps = 0
        self.progress, self.interrupt = progress, interrupt
        self._events: list[tuple] = []
        self._observed = -1
        self._unwrap = ProgressUnwrapper(setup.track, self._arc_lengths(sim.states))
        self.trace_t: list[float] = []
        self.trace_states: list[np.ndarray] = []
        self.trace_progress: list[np.ndarray] = []

    # ---- World
    def go(self, t_go: float) -> None:
        self.t_go = t_go

    def poll(self, timeout: float = 0.0) -> WorldPacket:
        """The true states now (the physics caught up in whole control periods) and the events since the
        last poll. The simulated world answers at once; after the start a ``timeout`` lets that much
        simulated time pass (what waiting would do)."""
        if self.interrupt is not None and self.interrupt.requested:
            raise KeyboardInterrupt
        if timeout > 0 and self.t_go is not None:
            self.clock.advance(timeout)
        self._advance()
        winner = self._decided()
        started = self.t_go is not None
        racing = started and winner is None and self.clock.now() - self.t_go < self.setup.max_time_s - CLOCK_ROUNDING_S
        if racing and self.steps != self._observed:  # a control step the loop will command: referee and trace
            self._observed = self.steps
            states = self.sim.states
            self.referee.observe(self.sim.time, states)
            self.trace_t.append(self.sim.time)
            self.trace_states.append(states)
            self.trace_progress.append(self._unwrap.update(self._arc_lengths(states)).copy())
        events, self._events = self._events, []
        return WorldPacket(truth=self.sim.states, t_race=self.sim.time if started else None,
                           t_truth=self.clock.now(), events=events, winner=winner)

    def _decided(self) -> str | None:
        """The winner once the race is decided (RaceSetup.finish: the first car home, or every car)."""
        status = self.sim.race_status()
        if status.winner is None or (self.setup.finish == "all" and len(status.finish_order) < self.sim.n_cars):
            return None
        return self.names[status.winner]

    def _arc_lengths(self, states: np.ndarray) -> np.ndarray:
        """Every car's s along the track (one vectorised projection, as planning.frenet_state's s)."""
        return self.setup.track.to_frenet(states[:, 0], states[:, 1], states[:, 2])[0]

    def _advance(self) -> None:
        if self.t_go is None:
            return
        due = math.floor((self.clock.now() - self.t_go) / self.period + 1e-6)  # whole periods (clock rounding)
        while self.steps < due:
            for ev in self.sim.step(self.commands, self.period):
                entry = self.referee.sim_event(ev, self.sim.states)
                if entry is not None:
                    self._events.append((ev.time, *entry))
            if self.progress:
                self.progress(self.steps)
            self.steps += 1

    def observe(self, t_race: float, states: dict) -> WorldPacket:
        """Nothing to add: the race is judged on the simulator's true states (race.world.World)."""
        return WorldPacket()

    def close(self) -> WorldSummary:
        """The race summary the loop takes (as from race.hil.HilWorld.close)."""
        status = self.sim.race_status()
        order, results = self.results()
        return WorldSummary(winner=None if status.winner is None else self.names[status.winner],
                            finish_order=order, results=results,
                            lap_times_s={name: list(status.lap_times[i]) for i, name in enumerate(self.names)},
                            min_gap_m=float(self.referee.min_gap_m), collisions=list(self.referee.collisions),
                            race_time_s=self.sim.time, off_track=self.off_track())

    def off_track(self) -> dict[str, int]:
        """Off-track excursions per car so far."""
        counts = self.sim.race_status().off_track_count
        return {name: int(counts[i]) for i, name in enumerate(self.names)}

    def results(self) -> tuple[list[str], list[CarResult]]:
        """(finishing order, each car's result) as the simulator's laps and the referee have them."""
        status = self.sim.race_status()
        order = [self.names[i] for i in status.finish_order]
        times = {name: list(status.lap_times[i]) for i, name in enumerate(self.names)}
        return order, self.referee.results(order, times, self.setup.laps)

    # ---- Link
    def set_commands(self, commands: dict) -> None:
        """{radio id: vehicles.protocol.CarCommand}, in effect from now until the next call; a car not
        named gets neutral. A non-finite value is a ProtocolError, as on the serial link."""
        out = np.zeros_like(self.commands)
        for radio_id, cmd in commands.items():
            check_command_value(radio_id, "steering", cmd.steering)
            check_command_value(radio_id, "throttle", cmd.throttle)
            out[self.radio_index[radio_id]] = physical_command(self.setup.car, cmd)
        self.commands = out

    def neutral(self) -> None:
        self.commands = np.zeros_like(self.commands)

    def stop(self) -> None:
        self.neutral()


def simulation_config(setup: RaceSetup) -> LoopConfig:
    """The loop's timing for the simulated world (module doc): a tick per control period, lock-step
    planning, a failing planner's fallback applied, no linger after the race."""
    rate = 1.0 / setup.control_period_s
    return LoopConfig(rate_hz=rate, plan_hz=rate, plan_ticks=0, command_delay_s=0.0, linger_s=0.0,
                      hold_on_planner_error=False)


def run_race(setup: RaceSetup, telemetry_path=None, progress=None, simulator_cls=Simulator,
             live=None, planners_cls=RacePlanners) -> RaceOutcome:
    """Simulate one race until a car completes `laps` laps (or max_time_s, or Ctrl-C: ``interrupted``)
    through the race loop (module doc). ``simulator_cls``: a Simulator subclass that perturbs how
    commands reach the cars (bench/race_perturbations.py, `race --link-capture`); ``planners_cls``: a
    RacePlanners subclass (bench/planner_threads.py records each job's times); ``progress(step)`` is
    called after every control step; ``live`` (recording.live.LiveView) also streams the recording
    to Rerun viewers."""
    track, car = setup.track, setup.car
    cars = sim_cars(setup)
    sim = simulator_cls(track, [setup.sim_car_file(i) for i in range(len(setup.cars))], effects=setup.sim_effects,
                        seed=setup.seed, physics_dt=setup.physics_dt_s, laps_to_win=setup.laps,
                        off_track_allowance_car_lengths=setup.off_track_allowance_car_lengths)
    x0 = start_states(setup)
    sim.reset(x0)
    clock = SimulatedClock(0.0)
    rec = None
    if telemetry_path:
        rec = RaceRecorder(telemetry_path, recording_id=f"race-seed{setup.seed}", background=False,
                           car_names=setup.names, realtime=False, live=live)
        rec.static_track(track)
        if (line := setup.racing_line()) is not None:
            rec.static_racing_line(track, line)
        rec.static_document(SETUP_ENTITY, str(dataclasses.asdict(dataclasses.replace(
            setup, track=track.name, car=car.name, sim_car=None if setup.sim_car is None else setup.sim_car.name,
            roster=setup.cars,  # resolved: the review and sysid read each car's planner and ids
            car_files=None if setup.car_files is None else tuple(c.name for c in setup.car_files)))))
        rec.static_car_colors(setup.names)
    try:
        with _InterruptRequest() as stop:
            world = SimWorld(sim, clock, setup, progress=progress, interrupt=stop)
            loop = RaceLoop(setup=setup, config=simulation_config(setup), feed=world, link=world, world=world,
                            planners=planners_cls(setup), cars=cars,
                            perception=TruthPerception(cars), recorder=rec, mode="simulation", clock=clock,
                            worker_factory=SyncPlanRunner, monitor_factory=SimulatedDeadlineMonitor)
            out = loop.run()
    finally:
        if rec is not None:
            rec.close()
    planners = {c.name: c.planner for c in setup.cars}
    pooled = {kind: [out.solve_ms[c.name] for c in setup.cars if c.planner == kind] for kind in ("rd3g", "mpc")}
    n = len(setup.cars)
    return RaceOutcome(
        winner=out.winner, lap_times_s=out.lap_times_s, min_gap_m=out.min_gap_m, collisions=out.collisions,
        solve_ms=np.concatenate(pooled["rd3g"] or [np.zeros(0)]),
        opponent_solve_ms=np.concatenate(pooled["mpc"] or [np.zeros(0)]),
        control_period_ms=1e3 * setup.control_period_s, race_time_s=out.race_time_s, fallbacks=out.fallbacks,
        off_track=world.off_track(), start_states=x0, trace_t=np.array(world.trace_t),
        trace_states=np.array(world.trace_states).reshape(-1, n, 6),
        trace_progress=np.array(world.trace_progress).reshape(-1, n), prestart_ms=out.prestart_ms,
        planner_errors=out.planner_errors, interrupted=out.reason == "interrupted", planners=planners,
        results=out.results, finish_order=out.finish_order,
        car_solve_ms={c.name: out.solve_ms[c.name] for c in setup.cars if c.solves})
