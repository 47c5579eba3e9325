"""One simulated race: our car (RD3G racing planner) against an opponent (MPC or pure pursuit) in
sim.Simulator, with optional rerun telemetry. Used by `python -m app race` and `python -m app batch`.
Conventions and entity paths: docs/racing.md."""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from planning import MPCOpponent, ProgressUnwrapper, PurePursuitController, RacingPlanner, frenet_state
from planning.frenet import S
from race.planning import cold_plan, make_planner, plan_step
from race.recording import SETUP_ENTITY, RaceRecorder, record_car, record_plan
from race.referee import CollisionRecord, Referee
from race.setup import CAR_NAMES, RaceSetup, start_states
from race.summary import race_summary
from sim import Simulator
from vehicles.params import CarParams


@dataclass
class PlannerErrorRecord:
    time_s: float
    car: str        # car name
    message: str    # "ExceptionType: message"


@dataclass
class RaceOutcome:
    winner: str | None
    lap_times_s: dict[str, list[float]]
    min_gap_m: float
    collisions: list[CollisionRecord]
    solve_ms: np.ndarray            # wall time of every RD3G planning call (ms)
    opponent_solve_ms: np.ndarray   # same for the MPC opponent (empty for pursuit)
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
                "clean_winner": self.clean_winner, "rd3g_at_fault": sum(c.at_fault == "rd3g" for c in self.collisions),
                "off_track": self.off_track, "fallbacks": self.fallbacks, "prestart_ms": self.prestart_ms,
                "planner_errors": len(self.planner_errors)}


class _Telemetry:
    """The simulated race's recording through the one writer (race.recording.RaceRecorder, synchronous
    mode); entity paths in docs/racing.md."""

    def __init__(self, path, track, car: CarParams, setup: RaceSetup) -> None:
        self.car, self.track = car, track
        self.rec = RaceRecorder(path, recording_id=f"race-seed{setup.seed}", background=False)
        self.rec.static_track(track)
        sim_car = None if setup.sim_car is None else setup.sim_car.name
        self.rec.static_document(SETUP_ENTITY, str(dataclasses.asdict(dataclasses.replace(
            setup, track=track.name, car=car.name, sim_car=sim_car))))
        self.rec.static_car_colors()

    def step(self, k: int, t: float, states: np.ndarray, plans: dict, commands: np.ndarray, solve_ms: dict) -> None:
        rec = self.rec
        for i, name in enumerate(CAR_NAMES):
            record_car(rec, k, t, name, states[i], self.car.geometry)
            rec.scalar(f"cars/{name}/command/throttle", k, t, commands[i, 0])
            rec.scalar(f"cars/{name}/command/steering_rad", k, t, commands[i, 1])
            if plans.get(name) is not None:
                record_plan(rec, k, t, self.track, name, plans[name], solve_ms[name])

    def event(self, t: float, text: str) -> None:
        kind, _, rest = text.partition(": ")
        self.rec.event(t, kind, rest)

    def close(self) -> None:
        self.rec.close()


def run_race(setup: RaceSetup, telemetry_path=None, progress=None, simulator_cls=Simulator) -> RaceOutcome:
    """Simulate one race until a car completes `laps` laps (or max_time_s). ``simulator_cls``: a
    Simulator subclass that perturbs how commands reach the cars (bench/race_perturbations.py)."""
    track, car = setup.track, setup.car
    sim_car = car if setup.sim_car is None else setup.sim_car
    sim = simulator_cls(track, [sim_car, sim_car], effects=setup.sim_effects, seed=setup.seed, physics_dt=setup.physics_dt_s,
                    laps_to_win=setup.laps)
    x0 = start_states(setup)
    sim.reset(x0)
    ours = make_planner(RacingPlanner, setup, setup.rd3g_top_speed_mps,
                         opponent_top_speed_mps=setup.opponent_top_speed_mps)
    if setup.opponent == "mpc":
        theirs = make_planner(MPCOpponent, setup, setup.opponent_top_speed_mps)
        pursuit = None
    else:
        theirs = None
        pursuit = PurePursuitController(track, car, target_speed_mps=setup.opponent_top_speed_mps)
    tel = _Telemetry(telemetry_path, track, car, setup) if telemetry_path else None
    unwrap = ProgressUnwrapper(track, [frenet_state(track, x0[i])[S] for i in range(2)])
    referee = Referee(track, car)
    solve_ms, opp_ms = [], []
    trace_t, trace_x, trace_s = [], [], []
    fallbacks = 0
    period = setup.control_period_s
    # The first plans (cars at rest, no warm start) get the solver's full globalisation; they are
    # computed on the grid before the start, like on the real track, so they are outside the
    # real-time budget and reported separately. Each step's plan is then warm-started.
    fs0 = np.array([frenet_state(track, x0[i]) for i in range(2)])
    fs0[:, S] = unwrap.s
    planner_errors = []

    def note_error(name: str, plan, t: float) -> None:
        if plan.error is not None:
            planner_errors.append(PlannerErrorRecord(t, name, plan.error))
            if tel:
                tel.event(t, f"planner_error: {name}: {plan.error}")

    t0 = time.perf_counter()
    note_error("rd3g", cold_plan(ours, fs0[0], fs0[1]), 0.0)
    prestart_ms = 1e3 * (time.perf_counter() - t0)
    if theirs is not None:
        note_error("opponent", cold_plan(theirs, fs0[1], fs0[0]), 0.0)
    n_steps = int(math.ceil(setup.max_time_s / period))
    k = 0
    for k in range(n_steps):
        states = sim.states
        fs = np.array([frenet_state(track, states[i]) for i in range(2)])
        fs[:, S] = unwrap.update(fs[:, S])
        referee.observe(sim.time, states)
        trace_t.append(sim.time); trace_x.append(states); trace_s.append(fs[:, S].copy())
        plans, ms = {}, {}
        commands = np.zeros((2, 2))
        # Our car: plan from the state predicted over the actuation delay.
        plan, commands[0], ms["rd3g"] = plan_step(ours, fs[0], fs[1])
        solve_ms.append(ms["rd3g"])
        fallbacks += plan.used == "fallback"
        plans["rd3g"] = plan
        note_error("rd3g", plan, sim.time)
        if theirs is not None:
            plans["opponent"], commands[1], ms["opponent"] = plan_step(theirs, fs[1], fs[0])
            opp_ms.append(ms["opponent"])
            note_error("opponent", plans["opponent"], sim.time)
        else:
            commands[1] = pursuit.command(states[1], period)
        if tel:
            tel.step(k, sim.time, states, plans, commands, ms)
        events = sim.step(commands, period)
        for ev in events:
            if ev.kind == "collision":
                referee.collision(ev.time, sim.states)
            if tel and ev.kind in ("collision", "lap", "finished", "off_track"):
                tel.event(ev.time, f"{ev.kind}: {CAR_NAMES[ev.car]}" + (f" (fault {referee.collisions[-1].at_fault})" if ev.kind == "collision" else ""))
        if progress:
            progress(k)
        if sim.race_status().winner is not None:
            break
    status = sim.race_status()
    if tel:
        tel.close()
    return RaceOutcome(
        winner=None if status.winner is None else CAR_NAMES[status.winner],
        lap_times_s={name: list(status.lap_times[i]) for i, name in enumerate(CAR_NAMES)},
        min_gap_m=float(referee.min_gap_m), collisions=referee.collisions, solve_ms=np.array(solve_ms), opponent_solve_ms=np.array(opp_ms),
        control_period_ms=1e3 * period, race_time_s=sim.time, fallbacks=int(fallbacks),
        off_track={name: int(status.off_track_count[i]) for i, name in enumerate(CAR_NAMES)}, start_states=x0,
        trace_t=np.array(trace_t), trace_states=np.array(trace_x), trace_progress=np.array(trace_s),
        prestart_ms=prestart_ms, planner_errors=planner_errors)
