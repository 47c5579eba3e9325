"""The planning step of every race mode: each roster car's planner (race.roster: RD3G, MPC, pure
pursuit, or none for a human-driven car).

* :func:`make_planner` builds a planner from the race set-up; :func:`plan_step` is one planning step
  (predict the own car over its actuation delay, plan, map the planned [a, delta] to [throttle,
  steering angle]).
* Which cars an RD3G car plans with (:func:`interacting_cars`): its game has the cars that can come
  within the collision distance of it within its horizon, i.e. whose gap along the track is at most
  the faster car's top speed times the horizon plus the collision distance (at least the nearest car:
  the lead term against it is the car's progress reward), the nearest game_players - 1 of them
  players, the others constant-speed obstacles unless inside a player's collision distance (then
  players too: RacePlanners._with_close_obstacles); an MPC car avoids every
  other car (one moving obstacle each). Every car's s is taken in the planning car's frame (the
  other car's nearest image along the track), so a car a lap ahead is where it is on the track.
* Planner failure, one policy: a planning call that raises (an invalid problem, a solver error) never
  escapes :func:`plan_step`; that step gets the planner's fallback plan (closed-loop tracking of the
  previous plan, neutral before the first one) with the exception text in ``plan.error``
  (:func:`planner_errors`). What the race loop does with such a plan is its configuration
  (race.config.LoopConfig.hold_on_planner_error): HIL and hardware, where any fault sends neutral
  first, hold every car neutral until a good plan arrives; the simulated race applies the fallback and
  logs ``planner_error``. A non-finite command is always a planner fault (:class:`SolverFailure`).
* :class:`PlannerWorker` runs the steps of the real-time loop asynchronously in a worker thread; the
  loop applies the latest plan. The C++ solver releases the GIL, so a solve does not stall the loop.
* Several cars on several cores: :class:`RacePlanners` gives every car's plan of one step to a pool
  of ``RaceSetup.planner_threads`` threads (1: in turn, in the calling thread). Each car's inputs are
  fixed before the step's plans start and each planner (solver, warm start, rollout models) belongs to one car, so a
  car's plan does not depend on which thread ran it or when; the C++ solves run in parallel.
"""
from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
import numpy as np

from planning import CommandMapper, FrenetTrackModel, MPCOpponent, ProgressUnwrapper, PurePursuitController, RacingPlanner, frenet_state
from planning.commands import rollout_controls
from planning.frenet import EY, S, V, frenet_separation
from race.command_history import CommandHistory, controls_between  # noqa: F401 (controls_between: race.planning's name)
from race.config import lower_realtime_priority
from race.setup import RaceSetup

OPPONENT_MODES = ("mpc", "pursuit", "human")
# Under --rt-priority the planner thread runs this far below the loop thread: above the HIL world
# process (5 below, the emulated camera and cars) so that on a small machine the emulation, not the
# product, gives way (it drops camera frames, which the loop reports), and below the HIL box (3 below).
PLANNER_PRIORITY_BELOW_LOOP = 4


def make_planner(cls, setup: RaceSetup, top: float, car=None, reference: float | None = None, **kw):
    """A RacingPlanner or MPCOpponent (``cls``) with the race's planner settings, top speed and speed
    reference (m/s; None: the top speed), for car file ``car`` (default: the race's)."""
    car = setup.car if car is None else car
    cfg = dataclasses.replace(setup.planner, top_speed_mps=top, reference_speed_mps=reference)
    tm = FrenetTrackModel(setup.track, car, cfg)
    mapper = CommandMapper(car, setup.control_period_s, cfg.max_brake_mps2, cfg.steering_margin)
    return cls(tm, mapper, cfg, setup.control_period_s, **kw)


def plan_step(planner, own_state, other_states, **others) -> tuple[object, np.ndarray, float]:
    """One planning step from Frenet states [s, ey, v, epsi] (other_states: one per row; ``others``:
    the planner's other_tops / other_ids): the own state predicted over the car's actuation delay, the
    plan (the fallback plan if planning raised, see the module doc) and its command [throttle,
    steering angle rad]. Returns (plan, command, wall time ms)."""
    t0 = time.perf_counter()
    x = np.asarray(own_state, dtype=float)
    try:
        x = planner.mapper.predict(planner.tm, own_state)
        plan = planner.plan(x, other_states, **others)
    except Exception as exc:  # noqa: BLE001 - any planner failure is one fallback step (module doc)
        plan = planner.fallback_plan(x, other_states, f"{type(exc).__name__}: {exc}")
    command = planner.mapper.commands(*plan.control, speed=float(x[V]) if math.isfinite(x[V]) else 0.0)
    return plan, command, 1e3 * (time.perf_counter() - t0)


class SolverFailure(RuntimeError):
    """A planning call failed (raised, or produced non-finite output)."""


@dataclass
class PlanJob:
    tick: int
    t_plan: float                     # absolute time (monotonic) the states are predicted to
    states: dict[str, np.ndarray]     # car name -> [x, y, heading, vx, vy, yaw_rate]
    # Commanded cars: (clock time, state) of the car's last measured pose (race.world.Perceiver.last_measurement)
    measured: dict[str, tuple[float, np.ndarray]] = field(default_factory=dict)
    # The commands sent until the job (race.command_history.CommandHistory.snapshot)
    commands: CommandHistory | None = None

    def in_flight(self, name: str) -> tuple[np.ndarray, list] | None:
        """Car ``name``'s (finite) state at its last measured pose and the controls it executes from then
        to t_plan ([(duration s, a m/s^2, delta rad), ...]) when the command history reaches back to that
        pose, else None. The planner then predicts its own car with the planning model and these controls
        rather than taking ``states`` (the estimator's constant-turn-rate prediction, which cannot know
        the commands)."""
        last = self.measured.get(name)
        if last is None or self.commands is None or not (self.commands.covers(name, last[0]) and last[0] < self.t_plan):
            return None
        t_s, state = last
        if not np.all(np.isfinite(state)):
            return None
        return state, self.commands.between(name, t_s, self.t_plan)


@dataclass
class CarPlan:
    throttle: float
    steering_rad: float
    plan: object | None = None        # planning.Plan (None for pursuit)
    solve_ms: float = 0.0
    cpu_ms: float = 0.0               # CPU time of the thread that planned it, during this plan


@dataclass
class PlanResult:
    job: PlanJob
    cars: dict[str, CarPlan] = field(default_factory=dict)
    error: str | None = None
    t_done: float = 0.0
    seq: int = 0
    progress: np.ndarray | None = None  # unwrapped s of every car (roster order)
    wall_ms: float = 0.0                # wall time of the whole job (every car's plan)


def interacting_cars(i: int, progress, tops, horizon_s: float, d_min: float, length: float) -> list[int]:
    """The cars RD3G car i plans its game with (module doc): every j != i whose gap along the track
    (nearest image, ``length`` the lap) is at most max(top_i, top_j) * horizon_s + d_min, nearest first;
    with none that close, the nearest car (the game's lead term is then the car's progress reward)."""
    gaps = sorted((abs(math.remainder(float(progress[j]) - float(progress[i]), length)), j)
                  for j in range(len(progress)) if j != i)
    near = [j for gap, j in gaps if gap <= max(tops[i], tops[j]) * horizon_s + d_min]
    return near or [gaps[0][1]]  # alone: the nearest car, whose lead term is the game's progress reward


class RacePlanners:
    """Every roster car's planner with the race's settings (make_planner): RD3G (RacingPlanner), MPC
    (MPCOpponent), pure pursuit; a human-driven car has none and is not commanded. ``roster``
    defaults to the set-up's."""

    def __init__(self, setup, roster=None) -> None:
        self.setup = setup
        self.track = setup.track
        self.cars = tuple(setup.cars if roster is None else roster)
        self.names = tuple(c.name for c in self.cars)
        self.tops = [c.top_speed_mps for c in self.cars]
        self.refs = [c.top_speed_mps if c.reference_speed_mps is None else c.reference_speed_mps for c in self.cars]
        self.models: dict[str, object] = {}      # name -> RacingPlanner / MPCOpponent
        self.pursuit: dict[str, PurePursuitController] = {}
        for i, c in enumerate(self.cars):
            car = setup.car_file(i)
            if c.planner == "rd3g":
                self.models[c.name] = make_planner(RacingPlanner, setup, c.top_speed_mps, car=car,
                                                   reference=c.reference_speed_mps,
                                                   opponent_top_speed_mps=setup.opponent_top_speed_mps)
            elif c.planner == "mpc":
                self.models[c.name] = make_planner(MPCOpponent, setup, c.top_speed_mps, car=car,
                                                   reference=c.reference_speed_mps)
            elif c.planner == "pursuit":
                self.pursuit[c.name] = PurePursuitController(setup.track, car, target_speed_mps=c.top_speed_mps)
        self.unwrap: ProgressUnwrapper | None = None
        self.commanded = tuple(c.name for c in self.cars if c.planner != "human")
        threads = min(setup.planner_threads, len(self.models))
        # Pool threads run at the planner thread's priority whichever thread first submits (the cold
        # start runs in the loop thread): the priority of this (the loop's) thread less PlannerWorker's.
        self._pool = (ThreadPoolExecutor(threads, thread_name_prefix="planner", initializer=_planner_priority,
                                         initargs=(_fifo_priority(),)) if threads > 1 else None)

    def close(self) -> None:
        """Stop the planning threads (idle between plans; a pool of one thread has none)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None  # later plans (if any) run in turn in the calling thread

    def plan(self, job: PlanJob) -> PlanResult:
        """One planning step for every commanded car; a car whose planner failed has its fallback plan
        (:func:`planner_errors`). Raises SolverFailure on a non-finite command."""
        t0 = time.perf_counter()
        fs = np.array([frenet_state(self.track, job.states[name]) for name in self.names])
        if self.unwrap is None:
            self.unwrap = ProgressUnwrapper(self.track, fs[:, S])
        fs[:, S] = self.unwrap.update(fs[:, S])
        result = PlanResult(job=job, progress=fs[:, S].copy())
        # Every car at t_plan; a commanded car through the controls it executes (PlanJob.in_flight).
        at_plan = np.array([self._own_state(job, name, fs[i]) for i, name in enumerate(self.names)])
        steps = {c.name: self._step_inputs(i, at_plan) for i, c in enumerate(self.cars) if c.name in self.models}

        def run(name):
            cpu = time.thread_time()
            return *plan_step(self.models[name], *steps[name][:2], **steps[name][2]), time.thread_time() - cpu

        planned = dict(zip(steps, self._pool.map(run, steps) if self._pool is not None else map(run, steps)))
        for c in self.cars:
            if c.name in planned:
                plan, (throttle, steer), ms, cpu = planned[c.name]
                result.cars[c.name] = CarPlan(float(throttle), float(steer), plan, ms, 1e3 * cpu)
            elif c.name in self.pursuit:
                throttle, steer = self.pursuit[c.name].command(job.states[c.name], self.setup.control_period_s)
                result.cars[c.name] = CarPlan(float(throttle), float(steer))
        for name, cp in result.cars.items():
            if not (math.isfinite(cp.throttle) and math.isfinite(cp.steering_rad)):
                raise SolverFailure(f"{name}: planner produced a non-finite command "
                                    f"(throttle {cp.throttle}, steering {cp.steering_rad})")
        result.wall_ms = 1e3 * (time.perf_counter() - t0)
        return result

    def _step_inputs(self, i: int, at_plan: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        """Car i's plan_step arguments (own state, the other cars' rows in its frame, keywords): an RD3G
        car's players and obstacles (_others), every other car for MPC."""
        planner, extra = self.models[self.names[i]], {}
        if self.cars[i].planner == "rd3g":
            others, far = self._others(i, planner, at_plan)
            extra = {"obstacles": self._in_frame(at_plan, i, far)} if far else {}
        else:
            others = [j for j in range(len(self.cars)) if j != i]
        return at_plan[i], self._in_frame(at_plan, i, others), dict(
            other_tops=[self.tops[j] for j in others], other_refs=[self.refs[j] for j in others],
            other_ids=tuple(self.names[j] for j in others), **extra)

    def _others(self, i: int, planner, at_plan: np.ndarray) -> tuple[list[int], list[int]]:
        """(players, obstacles) of car i's game: interacting_cars at the plan's states (nominal collision
        distance on the straight), the nearest PlannerConfig.game_players - 1 of them players, the rest
        constant-speed obstacles."""
        cfg = planner.config
        if not np.all(np.isfinite(at_plan[:, S])):
            near = [j for j in range(len(self.cars)) if j != i]
        else:
            d_min = 2.0 * planner.tm.footprint_radius + cfg.collision_margin_m
            near = interacting_cars(i, at_plan[:, S], self.tops, cfg.horizon * cfg.plan_dt_s, d_min,
                                    float(self.track.length))
        keep = len(near) if cfg.game_players == 0 else cfg.game_players - 1
        return self._with_close_obstacles(i, planner, at_plan, near[:keep], near[keep:])

    def _with_close_obstacles(self, i: int, planner, at_plan: np.ndarray, players: list[int],
                              far: list[int]) -> tuple[list[int], list[int]]:
        """(players, obstacles) with every obstacle that starts within the collision distance (+2 cm for
        the first planning step) of a player made a player too, until none is. Why: an obstacle has one
        distance for every agent of the game and only agent pairs are relaxed one by one
        (_feasible_limits), so a player inside an obstacle's distance made the game infeasible from the
        first step (1-vs-3 races: two MPC cars side by side 0.248 m apart, one the player, one an
        obstacle, and RD3G's solves failing behind them)."""
        if not far or not np.all(np.isfinite(at_plan[:, :2])):
            return players, far
        players, far = list(players), list(far)
        rows = dict(zip(players + far, self._in_frame(at_plan, i, players + far)))
        scale = planner.tm.along_track_scale([at_plan[i, S], *(r[S] for r in rows.values())],
                                             [at_plan[i, EY], *(r[EY] for r in rows.values())])
        d = planner.tm.collision_distance()

        def near(o: int, p: int) -> bool:  # measured as the collision constraint does
            return float(frenet_separation(*(rows[o][:2] - rows[p][:2]), scale)) < d + 0.02

        close = [o for o in far if any(near(o, p) for p in players)]
        while close:
            players.append(close[0])
            far.remove(close[0])
            close = [o for o in far if any(near(o, p) for p in players)]
        return players, far

    def _in_frame(self, at_plan: np.ndarray, i: int, others: list[int]) -> np.ndarray:
        """The states of cars ``others`` with s moved to their nearest image from car i's s (a car more
        than half a lap away in unwrapped progress is a lap ahead or behind)."""
        rows = at_plan[others].copy()
        half = 0.5 * float(self.track.length)
        for row in rows:
            d = float(row[S] - at_plan[i, S])
            if abs(d) > half:
                row[S] = at_plan[i, S] + math.remainder(d, float(self.track.length))
        return rows

    def _planner_of(self, name: str):
        """The model planner commanding car `name` (None: pure pursuit or a human)."""
        return self.models.get(name)

    def executed_control(self, name: str, car_plan: CarPlan | None, speed: float) -> tuple[float, float] | None:
        """The planning-model control [a m/s^2, delta rad] car `name` executes when it gets `car_plan`'s
        command (None: neutral, at `speed` m/s); None for a car without a planning model (pursuit, human)."""
        planner = self._planner_of(name)
        if planner is None:
            return None
        if car_plan is None or car_plan.plan is None:
            return planner.mapper.neutral_control(speed)
        a, delta = car_plan.plan.control
        return float(a), float(delta)

    def _own_state(self, job: PlanJob, name: str, at_plan: np.ndarray) -> np.ndarray:
        """Frenet state of a commanded car at t_plan: from its last measured state through the controls
        it executes (job.in_flight), with the progress unwrapped like ``at_plan`` (the estimator's
        prediction to t_plan, used when the job has no in-flight record for the car)."""
        flight = job.in_flight(name)
        if flight is None:
            return at_plan
        state, segments = flight
        x = rollout_controls(self._planner_of(name).tm, frenet_state(self.track, state), segments)
        length = float(self.track.length)
        ds = math.remainder(float(x[S]) - float(at_plan[S]), length)  # same lap as the unwrapped progress
        x[S] = at_plan[S] + ds
        return x


def close_planners(planners) -> None:
    """Stop the planners' threads if they hold any (RacePlanners.close; other Planners have none)."""
    close = getattr(planners, "close", None)
    if close is not None:
        close()


def _fifo_priority() -> int | None:
    """This thread's SCHED_FIFO priority (None under normal scheduling)."""
    try:
        return os.sched_getparam(0).sched_priority if os.sched_getscheduler(0) == os.SCHED_FIFO else None
    except (AttributeError, OSError):
        return None


def _planner_priority(loop_priority: int | None) -> None:
    """A planning pool thread: SCHED_FIFO PLANNER_PRIORITY_BELOW_LOOP below the loop (as PlannerWorker),
    or normal scheduling when the loop has it."""
    try:
        if loop_priority is None:
            if os.sched_getscheduler(0) == os.SCHED_FIFO:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        else:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(1, loop_priority - PLANNER_PRIORITY_BELOW_LOOP)))
    except (AttributeError, OSError):
        pass


def planner_errors(result: PlanResult) -> dict[str, str]:
    """{car: "Type: message"} of the cars whose planning raised in this result (they got the fallback plan)."""
    return {name: cp.plan.error for name, cp in result.cars.items() if cp.plan is not None and cp.plan.error is not None}


def run_job(planners, job: PlanJob, t_done: float, seq: int) -> PlanResult:
    """One planning job; any exception (a planner fault, race.faults' injected failure) becomes the
    result's ``error`` (module doc)."""
    try:
        result = planners.plan(job)
    except Exception as exc:  # any planner exception is a planner fault for the loop
        result = PlanResult(job=job, error=f"{type(exc).__name__}: {exc}")
    result.t_done = t_done
    result.seq = seq
    return result


class SyncPlanRunner:
    """Runs each planning job when it is submitted, in the caller's thread: the plan is ready at once
    (a race on a simulated clock, tests). Same interface as PlannerWorker."""

    def __init__(self, planners, clock) -> None:
        self.planners, self.clock = planners, clock
        self._latest: PlanResult | None = None
        self._seq = 0

    def start(self, first: PlanResult | None = None) -> None:
        if first is not None:
            self._latest = first

    def run_sync(self, job: PlanJob) -> PlanResult:
        self._seq += 1
        return run_job(self.planners, job, self.clock.now(), self._seq)

    def submit(self, job: PlanJob) -> None:
        self._latest = self.run_sync(job)

    def latest(self) -> PlanResult | None:
        return self._latest

    def stop(self) -> None:
        close_planners(self.planners)


class PlannerWorker:
    """Runs planning jobs in a background thread; the newest pending job replaces an older one."""

    def __init__(self, planners, clock) -> None:
        self.planners = planners
        self.clock = clock
        self._cv = threading.Condition()
        self._pending: PlanJob | None = None
        self._latest: PlanResult | None = None
        self._stop = False
        self._seq = 0
        self._thread = threading.Thread(target=self._run, name="PlannerWorker", daemon=True)

    def start(self, first: PlanResult | None = None) -> None:
        if first is not None:
            self._latest = first
        self._thread.start()

    def run_sync(self, job: PlanJob) -> PlanResult:
        """Plan in the caller's thread (cold start before the race)."""
        return self._execute(job)

    def submit(self, job: PlanJob) -> None:
        with self._cv:
            self._pending = job
            self._cv.notify()

    def latest(self) -> PlanResult | None:
        with self._cv:
            return self._latest

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        if not self._thread.is_alive():  # a plan still running keeps its pool (daemon worker, process exit)
            close_planners(self.planners)

    def _execute(self, job: PlanJob) -> PlanResult:
        self._seq += 1
        seq = self._seq
        result = run_job(self.planners, job, 0.0, seq)
        result.t_done = self.clock.now()
        return result

    def _run(self) -> None:
        lower_realtime_priority(PLANNER_PRIORITY_BELOW_LOOP)
        while True:
            with self._cv:
                while self._pending is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                job, self._pending = self._pending, None
            result = self._execute(job)
            with self._cv:
                self._latest = result
