"""The interfaces the race loop runs against (docs/race-stack.md): what it observes of the world, the
parts it drives, and time. The simulated world (``race.simulation.SimWorld``), the HIL world
(``race.hil``), the hardware camera feed (``app.realtime.hardware``, in ``race.feed_world.FeedWorld``)
and the tests' fakes implement them; the loop knows nothing else. Perception (:class:`Perceiver`) sees
the sensors only as timed poses per car (:class:`Observation`, from any :class:`PoseSource`: camera
markers, motion capture).

Time is injected: :class:`MonotonicClock` for real time (HIL, hardware); :class:`SimulatedClock`
(the pure simulation, the fake-clock tests) advances at once on ``sleep``, so the loop runs as fast
as the CPU allows.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


@dataclass
class WorldPacket:
    """What the loop gets per poll: the newest frame and everything the world reported since the last
    poll."""

    frame: object | None = None              # tracking.camera.Frame
    # (n cars, 6) true states, roster order, at the frame's capture time (HIL) or at the poll (simulation);
    # race.feed_world.FeedWorld's answer: the perceived states (NaN rows: cars without a state)
    truth: np.ndarray | None = None
    t_race: float | None = None              # race time of ``truth``
    t_truth: float | None = None             # clock time of ``truth`` (simulation: race.perception.TruthPerception)
    # HIL: (snapshot index, true states, race time) of every snapshot delivered since the last poll, oldest
    # first (race.mocap_feed pairs each mocap frame with its own snapshot by frame number)
    truths: list[tuple] = field(default_factory=list)
    render_ms: list[float] = field(default_factory=list)
    events: list[tuple] = field(default_factory=list)   # (race time s, kind, text)
    winner: str | None = None                # the world's own referee decided the race
    box_corrupt: int = 0                     # HIL: frames the transmitter box rejected so far
    box_failsafe_events: int = 0
    dropped: int = 0


@dataclass
class WorldSummary:
    """A world's account of the race at its close (race.loop.RaceLoop folds it into the outcome)."""

    winner: str | None
    lap_times_s: dict[str, list[float]]
    min_gap_m: float | None
    collisions: list                                  # race.referee.CollisionRecord
    race_time_s: float
    finish_order: list[str] = field(default_factory=list)
    results: list = field(default_factory=list)       # race.referee.CarResult per car
    off_track: dict[str, int] = field(default_factory=dict)
    frames_rendered: int = 0
    frames_dropped: int = 0
    render_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # HIL: (clock time, car index, throttle, steering rad) whenever a simulated car's command changed
    applied_changes: list[tuple[float, int, float, float]] = field(default_factory=list)
    box: dict | None = None                           # HIL: virtual box and relay counters
    events: list[tuple] = field(default_factory=list)  # (race time s, kind, text) not reported by polls


class Clock(Protocol):
    def now(self) -> float:
        """Seconds on a monotonic clock (the frames' capture times use the same clock)."""

    def sleep(self, seconds: float) -> None:
        """Wait (real time) or advance (simulated time) by ``seconds``."""


class MonotonicClock:
    """Real time: ``time.monotonic`` and ``time.sleep``."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)


# Two readings of one instant on a simulated clock differ by rounding only (t_go + k T - t_go vs k T).
CLOCK_ROUNDING_S = 1e-9


class SimulatedClock:
    """Simulated time: ``sleep`` advances the clock at once, so a loop on it runs as fast as the CPU
    allows. ``watchers`` are called after every advance (a deadline monitor on simulated time checks
    its deadline there instead of waiting in a thread)."""

    def __init__(self, t0: float = 0.0) -> None:
        self.t = float(t0)
        self.watchers: list = []

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.advance(seconds)

    def advance(self, seconds: float) -> None:
        self.t += max(float(seconds), 0.0)
        for watch in list(self.watchers):
            watch()


class Feed(Protocol):
    def poll(self, timeout: float = 0.0) -> WorldPacket:
        """The newest frame and reports; waits up to ``timeout`` s for a frame. RuntimeError: the world failed."""


class World(Feed, Protocol):
    """A feed that is a whole simulated world (race.simulation.SimWorld, the HIL world): it starts the race
    and reports its end."""

    def go(self, t_go: float) -> None:
        """The race starts at clock time ``t_go``."""

    def observe(self, t_race: float, states: dict) -> WorldPacket:
        """The loop's perceived states of a tick; a world that judges the race from them
        (race.feed_world.FeedWorld) answers with its events and winner, a simulated world with nothing."""

    def close(self) -> WorldSummary | None:
        """Stop; the world's own race summary (None if it could not be collected)."""


@dataclass(frozen=True)
class TimedPose:
    """One car's measured pose: where a sensor saw it and when (clock time, the loop's clock)."""

    t_s: float
    x: float        # m, track frame
    y: float
    heading: float  # rad


@dataclass
class Observation:
    """One sensor reading of the cars, whatever the sensor: the timed pose of every car it saw. A camera
    adds its image and where it found the markers; a motion-capture system gives the poses only."""

    t_s: float                                                   # clock time of the reading (frame capture)
    poses: dict[str, TimedPose] = field(default_factory=dict)     # car name -> pose (the cars seen)
    image: np.ndarray | None = None                              # camera image (None: no camera)
    image_points: np.ndarray | None = None                       # (n, 2) px: centres of the detected markers
    full_search: bool | None = None                              # camera: the whole image was searched


@dataclass
class Perceived:
    """What perception gives the loop per tick (:class:`Perceiver`)."""

    states: dict[str, np.ndarray] = field(default_factory=dict)  # cars with a finite state at t_plan
    lost: dict[str, bool] = field(default_factory=dict)
    nonfinite: list[str] = field(default_factory=list)           # cars whose estimate was dropped this tick
    observation: Observation | None = None                       # this tick's reading (None: nothing new)
    # cars whose pose the estimator accepted this tick -> its estimate [x, y, heading] at the pose's time
    accepted: dict[str, np.ndarray] = field(default_factory=dict)


class PoseSource(Protocol):
    """A sensor that reads timed poses of the cars (race.perception.MarkerPoses: the camera and the
    marker tracker; a motion-capture client gives poses without an image). race.perception.Perception
    runs the estimator on any source."""

    regions: bool  # True: a reading searches only around the predictions (a camera's regions of interest)

    def next_reading(self, packet: WorldPacket) -> float | None:
        """Clock time of a new reading (in ``packet`` or the source's own stream), None if there is none;
        the reading counts as taken (:meth:`read` returns its poses)."""

    def read(self, packet: WorldPacket, predictions: dict[str, tuple[float, ...]] | None) -> Observation:
        """The poses of the reading :meth:`next_reading` announced. ``predictions``: car name -> (x, y, heading)
        expected at the reading's time (the tracked cars); None: search for every car."""


class Perceiver(Protocol):
    """Perception as the loop uses it (race.perception.Perception: a pose source and the state estimator;
    race.perception.TruthPerception: the simulated world's true states). States are the simulator's
    [x, y, heading, vx, vy, yaw_rate] (body-frame velocity) per car name; the sensor behind them is
    seen only as timed poses per car (:class:`Observation`), so any pose source plugs in."""

    lost_after_s: float   # a car is lost after this long without an accepted pose
    estimated: bool       # the states are estimates (recorded beside the truth)
    frames: int           # readings taken during the race

    def acquire(self, packet: WorldPacket) -> None:
        """Before the start: search every car in the packet's reading."""

    def acquired(self, measurements_needed: int) -> list:
        """The cars not found often enough yet (pre-race acquisition)."""

    def states_at(self, t_abs: float) -> dict[str, np.ndarray]:
        """Every car's state at clock time ``t_abs`` (the cold-start plan)."""

    def last_measurement(self, name: str) -> tuple[float, np.ndarray] | None:
        """(clock time, state) of car ``name``'s last accepted pose; None if unknown."""

    def perceive(self, packet: WorldPacket, t_plan: float, now: float, after_detect=None) -> Perceived:
        """Take the packet's reading and every car's state at ``t_plan``; lost cars judged at ``now``;
        ``after_detect()`` between the reading and the estimation (stage timing)."""


class Tracker(Protocol):
    def process(self, frame, predictions):
        """Marker detections of one frame (tracking.markers.FrameDetections); ``predictions`` {marker id:
        (x, y, heading)} restricts the search to regions of interest, None searches the whole frame."""


class Estimator(Protocol):
    """tracking.estimator.MultiCarEstimator: one filter per marker id."""

    filters: dict

    def update(self, t_s: float, measurements) -> dict: ...

    def forget(self, marker_id: int) -> None: ...


class Link(Protocol):
    """Normalised commands to the cars: vehicles.serial_link.SerialCarLink, race.simulation.SimWorld."""

    def set_commands(self, commands: dict) -> None:
        """{radio id: vehicles.protocol.CarCommand}; ProtocolError for a command the protocol rejects."""

    def neutral(self) -> None:
        """Every car neutral now (written at once, not at the sender's next tick)."""

    def stop(self) -> None: ...


class Planners(Protocol):
    """race.planning.RacePlanners: one planning step for every commanded car."""

    commanded: tuple[str, ...]

    def plan(self, job): ...

    def executed_control(self, name: str, car_plan, speed: float) -> tuple[float, float] | None: ...


class PlanRunner(Protocol):
    """Runs planning jobs (race.planning.PlannerWorker in a thread, SyncPlanRunner in the caller's)."""

    def start(self, first=None) -> None: ...

    def run_sync(self, job): ...

    def submit(self, job) -> None: ...

    def latest(self): ...

    def stop(self) -> None: ...
