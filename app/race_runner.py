"""One simulated race: our car (RD3G racing planner) against an opponent (MPC or pure pursuit) in
sim.Simulator, with optional rerun telemetry. Used by `python -m app race` and `python -m app batch`.
Conventions and entity paths: docs/racing.md."""
from __future__ import annotations

import dataclasses
import math
import signal
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from planning import CommandMapper, FrenetTrackModel, MPCOpponent, PlannerConfig, ProgressUnwrapper, RacingPlanner, frenet_state
from planning.frenet import EY, S, V
from sim import PurePursuitController, SimEffects, Simulator
from sim.collision import footprint_corners, rectangles_overlap
from vehicles.params import CarParams

CAR_NAMES = ("rd3g", "opponent")  # car 0 is ours, car 1 the opponent
OPPONENTS = ("mpc", "pursuit")
STARTS = ("front", "rear")


@dataclass(frozen=True)
class RaceSetup:
    """Everything that defines one race. Speeds are the planners' top speeds (m/s)."""

    track: object
    car: CarParams                      # both cars' planners (and, by default, the simulated cars) use this file
    seed: int = 0
    laps: int = 1
    opponent: str = "mpc"               # "mpc" or "pursuit"
    start: str = "front"                # where our car starts: "front" or "rear"
    rd3g_top_speed_mps: float = 2.0
    opponent_top_speed_mps: float = 2.0
    control_period_s: float = 1.0 / 30.0
    physics_dt_s: float = 0.001
    max_time_s: float = 60.0            # a race not won by then is "unfinished"
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    start_s_m: tuple[float, float] = (0.25, 0.45)   # front car's start s range (just after the line)
    start_gap_car_lengths: tuple[float, float] = (1.75, 2.25)  # centre-to-centre along the track: about one car length of free space
    start_ey_m: float = 0.12            # |ey| of each car at the start, uniform in [-start_ey_m, start_ey_m]
    # The physical cars in the simulator, when they differ from what the planners believe (closing the
    # model-identification loop, docs/sysid.md): sim_car (default: car) plus hidden sim_effects, both cars.
    sim_car: CarParams | None = None
    sim_effects: SimEffects = field(default_factory=SimEffects)

    def __post_init__(self) -> None:
        if self.opponent not in OPPONENTS:
            raise ValueError(f"opponent: must be one of {OPPONENTS}, got {self.opponent!r}")
        if self.start not in STARTS:
            raise ValueError(f"start: must be one of {STARTS}, got {self.start!r}")
        if not isinstance(self.sim_effects, SimEffects):
            raise ValueError(f"sim_effects: must be a SimEffects, got {type(self.sim_effects).__name__}")
        if not isinstance(self.laps, int) or self.laps < 1:
            raise ValueError(f"laps: must be an integer >= 1, got {self.laps!r}")
        for name in ("rd3g_top_speed_mps", "opponent_top_speed_mps", "control_period_s", "max_time_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: must be a positive number, got {v!r}")


@dataclass
class CollisionRecord:
    time_s: float
    at_fault: str  # car name, see fault_of


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
    interrupted: bool = False       # stopped by Ctrl-C: the record covers the race up to race_time_s

    @property
    def clean_winner(self) -> str | None:
        """The winner if it never left the track, else None: a car off the drivable area may cut the
        infield (its progress jumps), so such a win does not count."""
        if self.winner is None or self.off_track[self.winner] > 0:
            return None
        return self.winner

    def summary(self) -> dict:
        """The `race --json` record (docs/racing.md)."""
        p = _percentiles(self.solve_ms)
        return {"winner": self.winner, "clean_winner": self.clean_winner, "lap_times_s": self.lap_times_s,
                "min_gap_m": self.min_gap_m, "collisions": len(self.collisions),
                "rd3g_at_fault": sum(c.at_fault == "rd3g" for c in self.collisions), "off_track": self.off_track,
                "fallbacks": self.fallbacks, "solve_ms_p50": p[0], "solve_ms_p99": p[1],
                "prestart_ms": self.prestart_ms, "control_period_ms": self.control_period_ms,
                "planner_errors": len(self.planner_errors), "interrupted": self.interrupted,
                "race_time_s": self.race_time_s}


def _percentiles(ms: np.ndarray) -> tuple[float | None, float | None]:
    if len(ms) == 0:
        return None, None
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99))


def start_states(setup: RaceSetup) -> np.ndarray:
    """Seeded standing start: the front car just after the line, the other about one car
    lengths of free space (2 +- 0.25 car lengths centre to centre) behind along the track, each at a random lateral offset, aligned with
    the track, at rest. Rows: [x, y, heading, vx, vy, yaw_rate] for (rd3g, opponent)."""
    rng = np.random.default_rng(setup.seed)
    tr = setup.track
    s_front = rng.uniform(*setup.start_s_m)
    gap = rng.uniform(*setup.start_gap_car_lengths) * setup.car.geometry.footprint_length_m
    ey = rng.uniform(-setup.start_ey_m, setup.start_ey_m, size=2)
    s = np.array([s_front, s_front - gap]) if setup.start == "front" else np.array([s_front - gap, s_front])
    s = np.mod(s, tr.length)
    x, y, heading = tr.to_cartesian(s, ey, np.zeros(2))
    return np.column_stack([x, y, heading, np.zeros((2, 3))])


def fault_of(states: np.ndarray) -> int:
    """The car whose front hit the other: the one that has the other further ahead of it along its
    own heading (the rear car in a rear-end contact, the car that turned in on the other in a side
    contact)."""
    ahead = []
    for i, j in ((0, 1), (1, 0)):
        d = states[j, :2] - states[i, :2]
        ahead.append(d[0] * math.cos(states[i, 2]) + d[1] * math.sin(states[i, 2]))
    return 0 if ahead[0] >= ahead[1] else 1


def footprint_gap(states: np.ndarray, car: CarParams) -> float:
    """Smallest distance (m) between the two footprint rectangles (0 when they overlap)."""
    g = car.geometry
    corners = footprint_corners(states[:, 0], states[:, 1], states[:, 2], g.footprint_length_m,
                                g.footprint_width_m, g.footprint_offset_m)  # (2, 4, 2)
    centers = corners.mean(axis=1)
    half = np.array([g.footprint_length_m / 2, g.footprint_width_m / 2])
    if bool(rectangles_overlap(centers[0], states[0, 2], half, centers[1], states[1, 2], half)):
        return 0.0
    best = math.inf
    for a, b in ((0, 1), (1, 0)):
        p = corners[a][:, None, :]                      # corners of a (4, 1, 2)
        q0 = corners[b]; q1 = np.roll(corners[b], -1, axis=0)  # edges of b (4, 2)
        e = q1 - q0
        t = np.clip(np.einsum("ikj,kj->ik", p - q0[None], e) / np.einsum("kj,kj->k", e, e), 0.0, 1.0)
        closest = q0[None] + t[..., None] * e[None]
        best = min(best, float(np.min(np.linalg.norm(p - closest, axis=-1))))
    return best


class _Telemetry:
    """rerun recording of one race (entity paths in docs/racing.md)."""

    def __init__(self, path, track, car: CarParams, setup: RaceSetup) -> None:
        import rerun as rr

        self.rr = rr
        self.car = car
        self.track = track
        self.rec = rr.RecordingStream("rd3g_race", recording_id=f"race-seed{setup.seed}")
        self.rec.save(str(path))
        left, right = track.boundaries(0.02)
        centre = track.position(np.linspace(0, track.length, 400))
        self.rec.log("world/track/left", rr.LineStrips2D([np.vstack([left, left[:1]])]), static=True)
        self.rec.log("world/track/right", rr.LineStrips2D([np.vstack([right, right[:1]])]), static=True)
        self.rec.log("world/track/centre", rr.LineStrips2D([centre], colors=[[120, 120, 120]]), static=True)
        sim_car = None if setup.sim_car is None else setup.sim_car.name
        self.rec.log("race/setup", rr.TextDocument(str(dataclasses.asdict(dataclasses.replace(
            setup, track=track.name, car=car.name, sim_car=sim_car)))), static=True)
        self.colors = {"rd3g": [230, 60, 40], "opponent": [40, 110, 230]}

    def step(self, k: int, t: float, states: np.ndarray, plans: dict, commands: np.ndarray, solve_ms: dict) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("control_step", sequence=k)
        rec.set_time("sim_time", duration=t)
        g = self.car.geometry
        corners = footprint_corners(states[:, 0], states[:, 1], states[:, 2], g.footprint_length_m,
                                    g.footprint_width_m, g.footprint_offset_m)
        for i, name in enumerate(CAR_NAMES):
            col = self.colors[name]
            rec.log(f"world/cars/{name}/footprint", rr.LineStrips2D([np.vstack([corners[i], corners[i][:1]])], colors=[col]))
            rec.log(f"world/cars/{name}/position", rr.Points2D([states[i, :2]], colors=[col], radii=[0.01]))
            rec.log(f"cars/{name}/speed_mps", rr.Scalars(float(math.hypot(states[i, 3], states[i, 4]))))
            rec.log(f"cars/{name}/command/throttle", rr.Scalars(float(commands[i, 0])))
            rec.log(f"cars/{name}/command/steering_rad", rr.Scalars(float(commands[i, 1])))
            plan = plans.get(name)
            if plan is not None:
                x, y = self.track.to_cartesian(plan.x[0, :, S], plan.x[0, :, EY])
                rec.log(f"world/cars/{name}/plan", rr.LineStrips2D([np.column_stack([x, y])], colors=[col]))
                x, y = self.track.to_cartesian(plan.x[1, :, S], plan.x[1, :, EY])
                rec.log(f"world/cars/{name}/predicted_other", rr.LineStrips2D([np.column_stack([x, y])], colors=[[150, 150, 150]]))
                rec.log(f"cars/{name}/planned/accel_mps2", rr.Scalars(float(plan.u[0, 0])))
                rec.log(f"cars/{name}/planned/delta_rad", rr.Scalars(float(plan.u[0, 1])))
                rec.log(f"planner/{name}/solve_ms", rr.Scalars(solve_ms[name]))
                rec.log(f"planner/{name}/iterations", rr.Scalars(float(plan.iterations)))

    def event(self, t: float, text: str) -> None:
        self.rec.set_time("sim_time", duration=t)
        self.rec.log("race/events", self.rr.TextLog(text))

    def close(self) -> None:
        self.rec.flush()


def _make_planner(cls, setup: RaceSetup, top: float, **kw):
    cfg = dataclasses.replace(setup.planner, top_speed_mps=top)
    tm = FrenetTrackModel(setup.track, setup.car, cfg)
    mapper = CommandMapper(setup.car, setup.control_period_s, cfg.max_brake_mps2, cfg.steering_margin)
    return cls(tm, mapper, cfg, setup.control_period_s, **kw)


def _plan_and_command(planner, own_state, other_state):
    """Plan from the own state predicted over the actuation delay; returns (plan, [throttle, steering], wall ms).
    A race never stops on a planner exception (an invalid problem, a solver error): that step gets the
    planner's fallback plan (closed-loop tracking of the previous plan, or neutral before the first
    one) with the exception in plan.error."""
    t0 = time.perf_counter()
    x = np.asarray(own_state, dtype=float)
    try:
        x = planner.mapper.predict(planner.tm, own_state)
        plan = planner.plan(x, other_state)
    except Exception as exc:  # noqa: BLE001 - any planner failure is one fallback step, logged by the caller
        plan = planner.fallback_plan(x, other_state, f"{type(exc).__name__}: {exc}")
    command = planner.mapper.commands(*plan.control, speed=float(x[V]) if math.isfinite(x[V]) else 0.0)
    return plan, command, 1e3 * (time.perf_counter() - t0)


def _plan_or_fallback(planner, own_state, other_state):
    """The cold plan before the start, with the same never-raise rule as _plan_and_command."""
    try:
        return planner.plan(own_state, other_state)
    except Exception as exc:  # noqa: BLE001
        return planner.fallback_plan(own_state, other_state, f"{type(exc).__name__}: {exc}")


class _InterruptRequest:
    """While active (main thread only), the first Ctrl-C sets ``requested`` instead of raising, so the
    race loop can stop between steps with its telemetry and summary whole; a second Ctrl-C raises."""

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


def run_race(setup: RaceSetup, telemetry_path=None, progress=None, simulator_cls=Simulator) -> RaceOutcome:
    """Simulate one race until a car completes `laps` laps (or max_time_s, or Ctrl-C: ``interrupted``).
    ``simulator_cls``: a Simulator subclass that perturbs how commands reach the cars
    (bench/race_perturbations.py)."""
    with _InterruptRequest() as stop:
        return _run_race(setup, telemetry_path, progress, simulator_cls, stop)


def _run_race(setup: RaceSetup, telemetry_path, progress, simulator_cls, stop: _InterruptRequest) -> RaceOutcome:
    track, car = setup.track, setup.car
    sim_car = car if setup.sim_car is None else setup.sim_car
    sim = simulator_cls(track, [sim_car, sim_car], effects=setup.sim_effects, seed=setup.seed, physics_dt=setup.physics_dt_s,
                    laps_to_win=setup.laps)
    x0 = start_states(setup)
    sim.reset(x0)
    ours = _make_planner(RacingPlanner, setup, setup.rd3g_top_speed_mps,
                         opponent_top_speed_mps=setup.opponent_top_speed_mps)
    if setup.opponent == "mpc":
        theirs = _make_planner(MPCOpponent, setup, setup.opponent_top_speed_mps)
        pursuit = None
    else:
        theirs = None
        pursuit = PurePursuitController(track, car, target_speed_mps=setup.opponent_top_speed_mps)
    tel = _Telemetry(telemetry_path, track, car, setup) if telemetry_path else None
    unwrap = ProgressUnwrapper(track, [frenet_state(track, x0[i])[S] for i in range(2)])
    solve_ms, opp_ms, collisions = [], [], []
    min_gap = math.inf
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
    note_error("rd3g", _plan_or_fallback(ours, fs0[0], fs0[1]), 0.0)
    prestart_ms = 1e3 * (time.perf_counter() - t0)
    if theirs is not None:
        note_error("opponent", _plan_or_fallback(theirs, fs0[1], fs0[0]), 0.0)
    n_steps = int(math.ceil(setup.max_time_s / period))
    interrupted = False
    k = 0
    for k in range(n_steps):
        if stop.requested:  # Ctrl-C: end the race here; the outcome covers what happened so far
            interrupted = True
            break
        states = sim.states
        fs = np.array([frenet_state(track, states[i]) for i in range(2)])
        fs[:, S] = unwrap.update(fs[:, S])
        min_gap = min(min_gap, footprint_gap(states, car))
        trace_t.append(sim.time); trace_x.append(states); trace_s.append(fs[:, S].copy())
        plans, ms = {}, {}
        commands = np.zeros((2, 2))
        # Our car: plan from the state predicted over the actuation delay.
        plan, commands[0], ms["rd3g"] = _plan_and_command(ours, fs[0], fs[1])
        solve_ms.append(ms["rd3g"])
        fallbacks += plan.used == "fallback"
        plans["rd3g"] = plan
        note_error("rd3g", plan, sim.time)
        if theirs is not None:
            plans["opponent"], commands[1], ms["opponent"] = _plan_and_command(theirs, fs[1], fs[0])
            opp_ms.append(ms["opponent"])
            note_error("opponent", plans["opponent"], sim.time)
        else:
            commands[1] = pursuit.command(states[1], period)
        if tel:
            tel.step(k, sim.time, states, plans, commands, ms)
        events = sim.step(commands, period)
        for ev in events:
            if ev.kind == "collision":
                who = CAR_NAMES[fault_of(sim.states)]
                collisions.append(CollisionRecord(ev.time, who))
            if tel and ev.kind in ("collision", "lap", "finished", "off_track"):
                tel.event(ev.time, f"{ev.kind}: {CAR_NAMES[ev.car]}" + (f" (fault {collisions[-1].at_fault})" if ev.kind == "collision" else ""))
        if progress:
            progress(k)
        if sim.race_status().winner is not None:
            break
    status = sim.race_status()
    if tel:
        if interrupted:
            tel.event(sim.time, "interrupted: Ctrl-C")
        tel.close()
    return RaceOutcome(
        winner=None if status.winner is None else CAR_NAMES[status.winner],
        lap_times_s={name: list(status.lap_times[i]) for i, name in enumerate(CAR_NAMES)},
        min_gap_m=float(min_gap), collisions=collisions, solve_ms=np.array(solve_ms), opponent_solve_ms=np.array(opp_ms),
        control_period_ms=1e3 * period, race_time_s=sim.time, fallbacks=int(fallbacks),
        off_track={name: int(status.off_track_count[i]) for i, name in enumerate(CAR_NAMES)}, start_states=x0,
        trace_t=np.array(trace_t), trace_states=np.array(trace_x), trace_progress=np.array(trace_s),
        prestart_ms=prestart_ms, planner_errors=planner_errors, interrupted=interrupted)
