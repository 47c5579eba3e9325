"""Perception for the race loop: one call (``perceive``) that returns every car's state at the planning
instant and which cars are lost or had a non-finite state. :class:`Perception` is the marker tracker
and the state estimator (HIL, hardware); :class:`TruthPerception` takes the simulated world's true
states (the pure simulation, race.simulation).

* Region-of-interest search: the tracker looks only around the estimator's predictions of the cars
  it tracks; while a car is lost, a full-frame search runs every ``lost_search_every`` frames.
* A car is lost when its filter has had no accepted measurement for the estimator's ``lost_after_s``
  (tracking.estimator.EstimatorConfig, one timeout for the filter and the loop's safety rule).
* A non-finite state (a diverged or corrupted filter) drops the car's filter; the next detection
  starts a new one.
* States are the simulator's [x, y, heading, vx, vy, yaw_rate] (body-frame velocity), the one state
  the planners take (race.planning.PlanJob)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from race.world import CLOCK_ROUNDING_S


def body_state(st) -> np.ndarray:
    """Estimator state (tracking.estimator.CarState) -> [x, y, heading, vx, vy, yaw_rate]."""
    return np.array([st.x, st.y, st.heading, st.speed * math.cos(st.sideslip),
                     st.speed * math.sin(st.sideslip), st.yaw_rate])


@dataclass
class Perceived:
    states: dict[str, np.ndarray] = field(default_factory=dict)  # cars with a finite state at t_plan
    lost: dict[str, bool] = field(default_factory=dict)
    nonfinite: list[str] = field(default_factory=list)        # cars whose filter was dropped this tick
    measurements: list = field(default_factory=list)         # this frame's detections of our cars
    detections: object | None = None                         # tracking.markers.FrameDetections (None: no new frame)
    results: dict = field(default_factory=dict)              # estimator update results by marker id


class Perception:
    """``cars``: objects with ``name`` and ``marker_id`` (race.loop.CarBinding)."""

    estimated = True  # the states are estimates (recorded beside the truth)

    def __init__(self, tracker, estimator, cars, lost_search_every: int) -> None:
        self.tracker, self.estimator, self.cars = tracker, estimator, list(cars)
        self.by_marker = {c.marker_id: c for c in self.cars}
        self.lost_search_every = lost_search_every
        self.frames = 0
        # Commanded cars: name -> CarEKF.accel_input (their logged accelerations drive the prediction)
        self.accel_inputs: dict = {}
        self._frames_since_full = 0
        self._last_frame_index = -1

    @property
    def lost_after_s(self) -> float:
        return self.estimator.config.lost_after_s

    def states_at(self, t_abs: float) -> dict[str, np.ndarray]:
        """Every car's estimate predicted to ``t_abs`` (the cold-start plan)."""
        return {c.name: body_state(self.estimator.filters[c.marker_id].predict_to(t_abs)) for c in self.cars}

    def last_measurement(self, name: str) -> tuple[float, np.ndarray] | None:
        """(time, state) of car ``name``'s last accepted measurement, None if it has no filter."""
        f = self.filter_of(name)
        if f is None or f.t_s is None:
            return None
        return f.t_s, body_state(f.predict_to(f.t_s))

    def filter_of(self, name: str):
        marker = next(c.marker_id for c in self.cars if c.name == name)
        return self.estimator.filters.get(marker)

    def detect(self, frame, predictions):
        """Detections of our cars in ``frame`` (``predictions`` None: full-frame search)."""
        det = self.tracker.process(frame, predictions)
        return [m for m in det.cars.values() if m.marker_id in self.by_marker], det

    def acquire(self, packet) -> None:
        """Before the start: a full-frame search of the packet's frame and an estimator update."""
        if packet.frame is not None:
            meas, _ = self.detect(packet.frame, None)
            self.estimator.update(packet.frame.t_capture_s, meas)

    def acquired(self, measurements_needed: int) -> list:
        """The cars without ``measurements_needed`` accepted measurements yet (pre-race acquisition)."""
        return [c for c in self.cars if c.marker_id not in self.estimator.filters
                or self.estimator.filters[c.marker_id].counts["accepted"] < measurements_needed]

    def perceive(self, packet, t_plan: float, now: float, after_detect=None) -> Perceived:
        """Detect the cars in the packet's frame (None or already seen: no detection), update the estimator
        at the frame's capture time, and predict every car to ``t_plan``; lost cars are judged at ``now``.
        ``after_detect()`` is called between detection and estimation (stage timing)."""
        out = Perceived()
        frame = packet.frame
        if frame is not None and frame.index != self._last_frame_index:
            self._last_frame_index = frame.index
            self.frames += 1
            predictions = self._predictions(frame.t_capture_s)
            if predictions is None or predictions:
                out.measurements, out.detections = self.detect(frame, predictions)
        if after_detect is not None:
            after_detect()
        if out.detections is not None:
            for c in self.cars:
                f = self.estimator.filters.get(c.marker_id)
                if f is not None and f.accel_input is None and c.name in self.accel_inputs:
                    f.accel_input = self.accel_inputs[c.name]
            out.results = self.estimator.update(frame.t_capture_s, out.measurements)
        for c in self.cars:
            f = self.estimator.filters.get(c.marker_id)
            out.lost[c.name] = f is None or f.is_lost(now)
            if out.lost[c.name]:
                continue
            state = body_state(f.predict_to(t_plan))
            if not np.all(np.isfinite(state)):
                out.nonfinite.append(c.name)
                self.estimator.forget(c.marker_id)
                continue
            out.states[c.name] = state
        return out

    def _predictions(self, t_capture: float):
        """Predicted (x, y, heading) of the tracked cars at the capture time (the tracker searches around them
        and aligns an undecodable marker from them); None for a full-frame search (every
        ``lost_search_every`` frames while a car is not tracked)."""
        filters = self.estimator.filters
        tracked = {c.marker_id: filters[c.marker_id] for c in self.cars
                   if c.marker_id in filters and not filters[c.marker_id].is_lost(t_capture)
                   and np.all(np.isfinite(filters[c.marker_id].x))}
        self._frames_since_full += 1
        if len(tracked) < len(self.cars) and self._frames_since_full >= self.lost_search_every:
            self._frames_since_full = 0
            return None
        return {m: tuple(f.predict_to(t_capture).vector[:3]) for m, f in tracked.items()}


class TruthPerception:
    """The simulated world's true states as the observation (race.world.WorldPacket.truth): no camera,
    no estimator, never lost. The states are those at the poll; the loop's simulated timing plans
    from them at once (LoopConfig.plan_ticks = 0, command_delay_s = 0: t_plan is the observation's
    time), so there is nothing to predict. ``cars``: objects with ``name`` (roster order, the rows of ``truth``)."""

    lost_after_s = math.inf
    estimated = False

    def __init__(self, cars) -> None:
        self.cars = list(cars)
        self.frames = 0  # no camera
        self.accel_inputs: dict = {}
        self._last: tuple[float, dict[str, np.ndarray]] | None = None

    def acquire(self, packet) -> None:
        """Take the packet's true states (race.world.WorldPacket.truth, rows in ``cars`` order) at the
        world's time (``packet.t_truth``)."""
        if packet.truth is None:
            raise RuntimeError("TruthPerception: the world sent no true states")
        self._last = (packet.t_truth, {c.name: np.array(packet.truth[i], dtype=float) for i, c in enumerate(self.cars)})

    def acquired(self, measurements_needed: int) -> list:
        return [] if self._last is not None else list(self.cars)

    def states_at(self, t_abs: float) -> dict[str, np.ndarray]:
        t, states = self._last
        if abs(t_abs - t) > CLOCK_ROUNDING_S:
            raise ValueError(f"TruthPerception: states are known at {t} s only, asked for {t_abs} s "
                             f"(set LoopConfig.plan_ticks and command_delay_s to 0)")
        return {name: st.copy() for name, st in states.items()}

    def last_measurement(self, name: str) -> tuple[float, np.ndarray] | None:
        t, states = self._last
        return t, states[name].copy()

    def perceive(self, packet, t_plan: float, now: float, after_detect=None) -> Perceived:
        """The packet's true states; ``t_plan`` must be the observation's time."""
        if after_detect is not None:
            after_detect()
        self.acquire(packet)
        states = self.states_at(t_plan)
        self._last = (t_plan, self._last[1])  # the observation is the plan's instant (nothing in flight)
        return Perceived(states=states, lost={c.name: False for c in self.cars})
