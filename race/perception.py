"""Perception for the race loop: the marker tracker and the state estimator behind one call that
returns every car's state at the planning instant and which cars are lost or had a non-finite state.

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

    def __init__(self, tracker, estimator, cars, lost_search_every: int) -> None:
        self.tracker, self.estimator, self.cars = tracker, estimator, list(cars)
        self.by_marker = {c.marker_id: c for c in self.cars}
        self.lost_search_every = lost_search_every
        self.frames = 0
        # Commanded cars: name -> CarEKF.accel_input (their logged accelerations drive the prediction)
        self.accel_inputs: dict = {}
        self._frames_since_full = 0
        self._last_frame_index = -1

    def filter_of(self, name: str):
        marker = next(c.marker_id for c in self.cars if c.name == name)
        return self.estimator.filters.get(marker)

    def detect(self, frame, predictions):
        """Detections of our cars in ``frame`` (``predictions`` None: full-frame search)."""
        det = self.tracker.process(frame, predictions)
        return [m for m in det.cars.values() if m.marker_id in self.by_marker], det

    def acquired(self, measurements_needed: int) -> list:
        """The cars without ``measurements_needed`` accepted measurements yet (pre-race acquisition)."""
        return [c for c in self.cars if c.marker_id not in self.estimator.filters
                or self.estimator.filters[c.marker_id].counts["accepted"] < measurements_needed]

    def perceive(self, frame, t_plan: float, now: float, after_detect=None) -> Perceived:
        """Detect the cars in ``frame`` (None or already seen: no detection), update the estimator at the
        frame's capture time, and predict every car to ``t_plan``; lost cars are judged at ``now``.
        ``after_detect()`` is called between detection and estimation (stage timing)."""
        out = Perceived()
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
        """ROI centres of the tracked cars at the capture time; None for a full-frame search (every
        ``lost_search_every`` frames while a car is not tracked)."""
        filters = self.estimator.filters
        tracked = {c.marker_id: filters[c.marker_id] for c in self.cars
                   if c.marker_id in filters and not filters[c.marker_id].is_lost(t_capture)
                   and np.all(np.isfinite(filters[c.marker_id].x))}
        self._frames_since_full += 1
        if len(tracked) < len(self.cars) and self._frames_since_full >= self.lost_search_every:
            self._frames_since_full = 0
            return None
        return {m: tuple(f.predict_to(t_capture).vector[:2]) for m, f in tracked.items()}
