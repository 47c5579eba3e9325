"""The interfaces the race loop runs against (docs/race-stack.md): what it observes of the world, the
parts it drives, and time. The simulated world (``race.simulation.SimWorld``), the HIL world
(``race.hil``), the hardware camera feed (``app.realtime.hardware``) and the tests' fakes implement
them; the loop knows nothing else.

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
    truth: np.ndarray | None = None          # (2, 6) true states at the frame's capture time (HIL) or at the poll (simulation)
    t_race: float | None = None              # race time of ``truth``
    t_truth: float | None = None             # clock time of ``truth`` (simulation: race.perception.TruthPerception)
    render_ms: list[float] = field(default_factory=list)
    events: list[tuple] = field(default_factory=list)   # (race time s, kind, text)
    winner: str | None = None                # the world's own referee (HIL simulator) decided the race
    box_corrupt: int = 0                     # HIL: frames the transmitter box rejected so far
    box_failsafe_events: int = 0
    dropped: int = 0


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

    def close(self) -> dict | None:
        """Stop; the world's own race summary (winner, lap times, gap, collisions, events, ...)."""


class Tracker(Protocol):
    def process(self, frame, predictions):
        """Marker detections of one frame (tracking.markers.FrameDetections); ``predictions`` {marker id:
        (x, y)} restricts the search to regions of interest, None searches the whole frame."""


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
