"""The race loop's safety rules on a simulated clock (race.loop.RaceLoop with race.world.Clock injected).

The world is faked: cars drive along the oval's centre line at constant speed, a fake tracker reports
their exact poses (and stalls or hides a car on request), the link records what it is sent, the
planners answer at once (race.planning.SyncPlanRunner) with a fixed driving command. The estimator is
the real one. Each test injects one fault and checks, against the fault's own timing (the rule's
threshold from the configuration), that every car got neutral at once (``link.neutral()`` and neutral
commands while held), that the ``fault`` event names the rule, and that the race resumes or stops as
the rule says. A race of a few seconds runs in a fraction of a second of CPU."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from race.config import FaultSpec, LoopConfig
from race.loop import CarBinding, RaceLoop, SimulatedDeadlineMonitor
from race.planning import CarPlan, PlanResult, SyncPlanRunner
from race.setup import RaceSetup
from race.world import SimulatedClock
from tracking.estimator import EstimatorConfig, MultiCarEstimator
from tracking.markers import CarMeasurement
from tracks import load_track
from vehicles.params import load_car_params
from vehicles.protocol import CarCommand, ProtocolError

T0 = 1000.0                 # the fake clock's start (s)
FPS = 60.0
FRAME_OFFSET_S = 0.004      # frames are not aligned with the loop's ticks
SPEED_MPS = 1.0
DRIVE = CarPlan(throttle=0.4, steering_rad=0.05)
CARS = [CarBinding("rd3g", 0, 0), CarBinding("opponent", 1, 1)]
LOST_AFTER_S = EstimatorConfig().lost_after_s


@dataclass
class Frame:
    index: int
    t_capture_s: float
    image: object = None


@dataclass
class Detections:
    cars: dict
    markers: dict
    full_search: bool


class World:
    """Cars on the centre line, 0.5 m apart, at SPEED_MPS; frames every 1/FPS on the fake clock."""

    def __init__(self, clock: SimulatedClock, track, n_cars: int = 2) -> None:
        self.clock, self.track, self.n_cars = clock, track, n_cars
        self.t_go = None           # set by the test from the loop once it started
        self.box_corrupt_at = None  # race time the box starts reporting corrupt frames
        self._index = -1

    def race_time(self, t_abs: float) -> float:
        return t_abs - (self.t_go if self.t_go is not None else math.inf)

    def pose(self, car: int, t_abs: float):
        s = 1.5 - 0.5 * car + SPEED_MPS * (t_abs - T0)
        x, y = self.track.position(s)
        return float(x), float(y), float(self.track.heading(s))

    def poll(self, timeout: float = 0.0):
        from race.world import WorldPacket

        newest = math.floor((self.clock.now() - T0 - FRAME_OFFSET_S) * FPS)
        if newest <= self._index and timeout > 0:  # acquisition: wait for the next frame
            self.clock.advance(T0 + FRAME_OFFSET_S + (self._index + 1) / FPS - self.clock.now())
            newest = self._index + 1
        packet = WorldPacket()
        if newest > self._index:
            self._index = newest
            packet.frame = Frame(newest, T0 + FRAME_OFFSET_S + newest / FPS)
        if self.box_corrupt_at is not None and self.race_time(self.clock.now()) >= self.box_corrupt_at:
            packet.box_corrupt = 1 + int((self.race_time(self.clock.now()) - self.box_corrupt_at) * 10)
        return packet


class Tracker:
    """Exact poses of the visible cars; ``hidden[marker] = (t0, t1)`` race times; ``stall = (t, s)``: the
    first frame captured at race time >= t takes s seconds to process (the fake clock advances)."""

    def __init__(self, world: World) -> None:
        self.world, self.hidden, self.stall = world, {}, None

    def process(self, frame, predictions):
        if self.stall is not None and self.world.race_time(frame.t_capture_s) >= self.stall[0]:
            self.world.clock.advance(self.stall[1])
            self.stall = None
        cars = {}
        for marker in range(self.world.n_cars):
            t0, t1 = self.hidden.get(marker, (math.inf, math.inf))
            if t0 <= self.world.race_time(frame.t_capture_s) < t1:
                continue
            x, y, heading = self.world.pose(marker, frame.t_capture_s)
            cars[marker] = CarMeasurement(marker, x, y, heading, frame.t_capture_s, 0.0)
        return Detections(cars=cars, markers={}, full_search=predictions is None)


class Link:
    """Records every command frame (race time, {radio id: CarCommand}) and every immediate neutral."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.sent: list[tuple[float, dict]] = []
        self.neutrals: list[float] = []
        self.reject = (math.inf, math.inf)  # race-time window in which set_commands raises ProtocolError

    def set_commands(self, commands: dict) -> None:
        t = self.world.race_time(self.world.clock.now())
        if self.reject[0] <= t < self.reject[1]:
            raise ProtocolError("steering 1.7 of car 0 is outside [-1, 1]")
        self.sent.append((t, dict(commands)))

    def neutral(self) -> None:
        self.neutrals.append(self.world.race_time(self.world.clock.now()))

    def stop(self) -> None:
        pass


class Planners:
    def __init__(self, cars=CARS) -> None:
        self.commanded = tuple(c.name for c in cars)

    def plan(self, job):
        return PlanResult(job=job, cars={name: DRIVE for name in self.commanded})

    def executed_control(self, name, car_plan, speed):
        return None


class StallingRunner(SyncPlanRunner):
    """Stops planning (jobs are dropped) from race time ``from_s``: the plan goes stale."""

    def __init__(self, planners, clock, world: World, from_s: float) -> None:
        super().__init__(planners, clock)
        self.world, self.from_s = world, from_s

    def submit(self, job) -> None:
        if self.world.race_time(self.clock.now()) < self.from_s:
            super().submit(job)


@pytest.fixture(scope="module")
def setup():
    return RaceSetup(track=load_track("oval"), car=load_car_params("buzzracer"), max_time_s=2.0)


def make_loop(setup, faults=(), runner=None, config=LoopConfig(), cars=CARS):
    clock = SimulatedClock(T0)
    world = World(clock, setup.track, len(cars))
    tracker, link = Tracker(world), Link(world)
    planners = Planners(cars)
    loop = RaceLoop(setup=setup, config=config, feed=world, tracker=tracker, estimator=MultiCarEstimator(),
                    link=link, planners=planners, cars=cars, faults=faults, mode="hardware", clock=clock,
                    worker_factory=(lambda p, c: runner(p, c, world)) if runner else SyncPlanRunner,
                    monitor_factory=SimulatedDeadlineMonitor)
    original_cold_start = loop._cold_start

    def cold_start():  # the world needs the race clock's zero to place faults in race time
        original_cold_start()
        world.t_go = loop.t_go

    loop._cold_start = cold_start
    return loop, world, tracker, link


MAX_STEER_RAD = math.radians(27.0)  # buzzracer's [actuators] max_steering_rad


def driving(commands: dict, n_cars: int = 2) -> bool:
    """The planners' command to every car, steering normalised by the car's steering range."""
    expected = CarCommand(steering=DRIVE.steering_rad / MAX_STEER_RAD, throttle=DRIVE.throttle)
    return set(commands) == set(range(n_cars)) and all(c.throttle == expected.throttle and
                                           abs(c.steering - expected.steering) < 1e-12 for c in commands.values())


def neutral(commands: dict, n_cars: int = 2) -> bool:
    return all(c == CarCommand(0.0, 0.0) for c in commands.values()) and set(commands) == set(range(n_cars))


def events(outcome, kind: str) -> list[tuple[float, str]]:
    return [(t, text) for t, k, text in outcome.events if k == kind]


def check_held(link: Link, t_fault: float, t_clear: float, n_cars: int = 2) -> None:
    """Neutral sent at once when the hold began, every frame neutral (every car) while it lasted,
    driving before."""
    assert any(abs(t - t_fault) < 1e-9 for t in link.neutrals)
    before = [c for t, c in link.sent if 0.2 < t < t_fault - 1e-9]
    held = [c for t, c in link.sent if t_fault - 1e-9 <= t < t_clear - 1e-9]
    assert before and all(driving(c, n_cars) for c in before)
    assert held and all(neutral(c, n_cars) for c in held)


def test_max_steering_of_the_car_file_scales_the_link_command(setup):
    assert setup.car.actuators.max_steering_rad == pytest.approx(MAX_STEER_RAD)


def test_fault_free_race_drives_until_the_time_limit(setup):
    loop, world, _, link = make_loop(setup)
    o = loop.run()
    assert o.reason == "time_limit" and o.deadline_misses == 0
    assert not events(o, "fault") and loop.link.neutrals == [pytest.approx(o.race_time_s, abs=0.05)]  # shutdown
    assert all(driving(c) for t, c in link.sent if t > 0.1)
    assert len(o.period_ms) > 0 and np.allclose(o.period_ms, 1e3 / 60, atol=1e-6)  # the simulated clock keeps time


def test_lost_car(setup):
    loop, world, tracker, link = make_loop(setup)
    tracker.hidden[1] = (1.0, 1.6)
    o = loop.run()
    (t_fault, text), *later = events(o, "fault")
    assert "car opponent lost" in text and f"{1e3 * LOST_AFTER_S:.0f} ms" in text
    # lost once no measurement was accepted for lost_after_s: the last visible frame is at most one frame
    # before the occlusion, the hold comes at the first tick after the timeout
    assert 1.0 - 1 / FPS + LOST_AFTER_S < t_fault <= 1.0 + LOST_AFTER_S + 1 / FPS + 1e-9
    # without both cars' states no job is planned: the plan goes stale too, and clears after the car is back
    assert later and all(text.startswith("no new plan") for _, text in later)
    recovered = events(o, "recovered")
    assert recovered[0][1] == "lost:opponent cleared" and 1.6 <= recovered[0][0] < 1.6 + 2 / FPS + 1e-9
    t_back, text = recovered[-1]
    assert text.endswith("racing again") and t_back - recovered[0][0] < LoopConfig().plan_latency_s + 2 / FPS
    check_held(link, t_fault, t_back)


def test_nan_state(setup):
    loop, world, _, link = make_loop(setup, faults=(FaultSpec("nan_state", 1.0, car="rd3g"),))
    o = loop.run()
    (t_inj, text), = events(o, "fault_injected")
    assert "rd3g" in text and 1.0 <= t_inj < 1.0 + 2 / FPS
    faults = events(o, "fault")
    assert "non-finite state of car rd3g" in faults[0][1] and faults[0][0] - t_inj < 1 / FPS + 1e-9
    # the filter was dropped: the car is lost until its next detection re-starts it
    assert all(t - faults[0][0] < 2 / FPS + 1e-9 for t, _ in faults)
    t_back = max(t for t, _ in events(o, "recovered"))
    assert t_back - faults[0][0] < 0.1 and o.reason == "time_limit"
    check_held(link, faults[0][0], t_back)


def test_stale_plan(setup):
    cfg = LoopConfig()
    loop, world, _, link = make_loop(setup, runner=lambda p, c, w: StallingRunner(p, c, w, 1.0))
    o = loop.run()
    (t_fault, text), = events(o, "fault")
    assert text.startswith("no new plan for") and f"limit {1e3 * cfg.max_plan_age_s:.0f} ms" in text
    # the last plan (job before 1.0 s) was for t_plan = its tick + plan_latency_s; stale max_plan_age_s later
    last_job_tick = (math.ceil(1.0 * cfg.rate_hz / cfg.plan_every) - 1) * cfg.plan_every / cfg.rate_hz
    t_stale = last_job_tick + cfg.plan_latency_s + cfg.max_plan_age_s
    assert t_stale < t_fault <= t_stale + 1 / cfg.rate_hz + 1e-9
    check_held(link, t_fault, math.inf)
    assert o.reason == "time_limit" or o.reason == "held_neutral"


def test_planner_failure(setup):
    cfg = LoopConfig()
    loop, world, _, link = make_loop(setup, faults=(FaultSpec("solver_fail", 1.0, 0.3),))
    o = loop.run()
    (t_fault, text), *later = events(o, "fault")
    assert text == "planner failed: SolverFailure: injected solver failure - all cars neutral"
    # a job is planned for t_plan = its tick + plan_latency_s, every plan_every ticks; the first one whose
    # t_plan is in the fault window fails, and a failure is taken at the next tick
    period = cfg.plan_every / cfg.rate_hz

    def first_job_for(t: float) -> float:
        return math.ceil((t - cfg.plan_latency_s) / period - 1e-9) * period

    assert t_fault == pytest.approx(first_job_for(1.0) + 1 / cfg.rate_hz, abs=1e-6)
    assert all(text.startswith("no new plan") for _, text in later)  # no good plan meanwhile
    # the first good plan again: made for a t_plan after the window, applied plan_ticks after its job
    t_back, text = events(o, "recovered")[-1]
    assert text.endswith("racing again")
    assert t_back == pytest.approx(first_job_for(1.3) + cfg.plan_ticks / cfg.rate_hz, abs=1e-6)
    check_held(link, t_fault, t_back)


def test_invalid_command(setup):
    loop, world, _, link = make_loop(setup)
    link.reject = (1.0, 1.2)
    o = loop.run()
    (t_fault, text), = events(o, "fault")
    assert text.startswith("invalid command: steering 1.7") and 1.0 <= t_fault < 1.0 + 1 / FPS + 1e-9
    (t_back, _), = events(o, "recovered")
    assert 1.2 <= t_back < 1.2 + 1 / FPS + 1e-9
    assert any(abs(t - t_fault) < 1e-9 for t in link.neutrals)
    assert not [c for t, c in link.sent if t_fault <= t < 1.2]  # nothing went through while rejected
    assert all(driving(c) for t, c in link.sent if t >= t_back + 1e-9)


def test_corrupt_serial_stream(setup):
    cfg = LoopConfig()
    loop, world, _, link = make_loop(setup)
    world.box_corrupt_at = 1.0  # from 1 s on the box reports a new rejected frame every 0.1 s
    o = loop.run()
    (t_fault, text), = events(o, "fault")
    assert text == "serial stream corrupt (box rejects frames) - all cars neutral" and 1.0 <= t_fault < 1.0 + 1 / FPS
    check_held(link, t_fault, math.inf)
    assert o.reason == "time_limit"


def test_corrupt_stream_clears_serial_quiet_s_after_the_last_report(setup):
    cfg = LoopConfig()
    loop, world, _, link = make_loop(setup)
    original = world.poll

    def poll(timeout=0.0):
        packet = original(timeout)
        t = world.race_time(world.clock.now())
        packet.box_corrupt = 0 if t < 1.0 else (1 if t < 1.1 else 2)  # two reports, the last at 1.1 s
        return packet

    world.poll = poll
    o = loop.run()
    (t_fault, _), = events(o, "fault")
    (t_back, text), = events(o, "recovered")
    assert text == "serial cleared - racing again"
    assert 1.1 + cfg.serial_quiet_s <= t_back < 1.1 + cfg.serial_quiet_s + 2 / FPS
    check_held(link, t_fault, t_back)


def test_deadline_miss_sends_neutral_at_the_deadline(setup):
    cfg = LoopConfig()
    loop, world, tracker, link = make_loop(setup)
    tracker.stall = (1.0, 1.2 * cfg.period_s)  # detection takes longer than a period: this tick misses
    o = loop.run()
    misses = events(o, "deadline_miss")
    assert len(misses) == 1 and "no command by the deadline (stage detect running) - neutral sent" in misses[0][1]
    assert o.deadline_misses == 1
    t_miss = misses[0][0]
    assert any(abs(t - t_miss) < 1e-9 for t in link.neutrals)
    assert not events(o, "fault") and o.reason == "time_limit"


def test_ticks_skipped_after_a_long_stall(setup):
    cfg = LoopConfig()
    loop, world, tracker, link = make_loop(setup)
    tracker.stall = (1.0, 3.5 * cfg.period_s)
    o = loop.run()
    skipped = [e for e in events(o, "deadline_miss") if "skipped" in e[1]]
    assert len(skipped) == 1 and skipped[0][1].startswith("2 tick(s) skipped")
    # the stalled tick itself (monitor) and the 2 skipped ones
    assert o.deadline_misses == 3
    assert any(abs(t - skipped[0][0]) < 1e-9 for t in link.neutrals)


def test_stop_after_a_long_hold(setup):
    cfg = LoopConfig(stop_after_hold_s=0.5)
    loop, world, tracker, link = make_loop(setup, config=cfg)
    tracker.hidden[0] = (1.0, math.inf)
    o = loop.run()
    t_fault = events(o, "fault")[0][0]
    (t_stop, text), = events(o, "stop")
    assert o.reason == "held_neutral" and "car rd3g lost" in text
    assert t_fault + cfg.stop_after_hold_s < t_stop <= t_fault + cfg.stop_after_hold_s + 2 / cfg.rate_hz
    check_held(link, t_fault, math.inf)


def test_simulated_clock_advances_at_once_and_calls_watchers():
    clock = SimulatedClock(5.0)
    seen = []
    clock.watchers.append(lambda: seen.append(clock.now()))
    clock.sleep(0.25)
    clock.sleep(-1.0)             # a negative wait does not move time back
    assert clock.now() == 5.25
    assert seen == [5.25, 5.25]


# ----------------------------------------------------------------------------- four cars
CARS4 = [CarBinding(f"car{i}", i, i) for i in range(4)]


def test_four_cars_fault_free_race_drives_every_car(setup):
    loop, world, _, link = make_loop(setup, cars=CARS4)
    o = loop.run()
    assert o.reason == "time_limit" and o.deadline_misses == 0 and not events(o, "fault")
    assert all(driving(c, 4) for t, c in link.sent if t > 0.1)
    assert [r.name for r in o.results] == [c.name for c in CARS4]  # the referee judged every car


def test_four_cars_one_lost_holds_every_car_neutral(setup):
    loop, world, tracker, link = make_loop(setup, cars=CARS4)
    tracker.hidden[2] = (1.0, 1.4)
    o = loop.run()
    (t_fault, text), *later = events(o, "fault")
    assert "car car2 lost" in text and "marker 2" in text
    assert 1.0 - 1 / FPS + LOST_AFTER_S < t_fault <= 1.0 + LOST_AFTER_S + 1 / FPS + 1e-9
    (t_back, text), *_ = events(o, "recovered")
    assert text.startswith("lost:car2 cleared") and 1.4 <= t_back < 1.4 + 2 / FPS + 1e-9
    check_held(link, t_fault, t_back, n_cars=4)  # the three visible cars were held too


def test_four_cars_nan_state_of_one_holds_every_car(setup):
    loop, world, _, link = make_loop(setup, faults=(FaultSpec("nan_state", 1.0, car="car3"),), cars=CARS4)
    o = loop.run()
    faults = events(o, "fault")
    assert "non-finite state of car car3" in faults[0][1]
    t_back = max(t for t, _ in events(o, "recovered"))
    check_held(link, faults[0][0], t_back, n_cars=4)


def test_four_cars_deadline_miss_sends_neutral_at_the_deadline(setup):
    cfg = LoopConfig()
    loop, world, tracker, link = make_loop(setup, cars=CARS4)
    tracker.stall = (1.0, 1.2 * cfg.period_s)
    o = loop.run()
    misses = events(o, "deadline_miss")
    assert len(misses) == 1 and "stage detect running" in misses[0][1] and o.deadline_misses == 1
    assert any(abs(t - misses[0][0]) < 1e-9 for t in link.neutrals)  # one neutral for every car at once
    # the stalled tick's command frame (sent after the deadline) still names every car
    assert all(set(c) == {0, 1, 2, 3} for t, c in link.sent)
    assert not events(o, "fault") and o.reason == "time_limit"


def test_hardware_race_is_refereed_from_the_estimates(setup):
    """Without a simulated world the loop's FeedWorld judges the race on the perceived states: the
    leading car (1.5 m ahead of the line at T0, SPEED_MPS) finishes its lap when its s reaches the
    track's length, i.e. at clock time T0 + (L - 1.5) / SPEED_MPS."""
    import dataclasses

    long = dataclasses.replace(setup, max_time_s=12.0, laps=1)
    loop, world, _, link = make_loop(long, cars=CARS4)
    o = loop.run()
    assert o.reason == "finished" and o.winner == "car0" and o.finish_order[0] == "car0"
    t_line = T0 + (float(setup.track.length) - 1.5) / SPEED_MPS - loop.t_go
    assert o.race_time_s == pytest.approx(t_line, abs=1 / FPS + 1 / 60 + 1e-9)
    assert o.results[0].finish_position == 1 and all(r.finish_position is None for r in o.results[1:])
