"""Perception for the race loop (the race.world.Perceiver protocol): one call (``perceive``) that returns
every car's state at the planning instant and which cars are lost or had a non-finite state.
:class:`Perception` is a pose source and the state estimator (HIL, hardware); :class:`TruthPerception`
takes the simulated world's true states (the pure simulation, race.simulation).

* The sensor is seen only as timed poses per car (race.world.PoseSource -> race.world.Observation):
  :class:`MarkerPoses` is the camera and the marker tracker; a motion-capture client plugs in the same
  way with poses and no image.
* Region-of-interest search (a source with ``regions``, the camera): the tracker looks only around the
  estimator's predictions of the cars it tracks; while a car is lost, a full-frame search runs every
  ``lost_search_every`` readings.
* A car is lost when its filter has had no accepted measurement for the estimator's ``lost_after_s``
  (tracking.estimator.EstimatorConfig, one timeout for the filter and the loop's safety rule).
* A commanded car's filter predicts its speed with the accelerations the loop sent it
  (race.command_history.CommandHistory, CarEKF.accel_input).
* A non-finite state (a diverged or corrupted filter) drops the car's filter; the next detection
  starts a new one.
* States are the simulator's [x, y, heading, vx, vy, yaw_rate] (body-frame velocity), the one state
  the planners take (race.planning.PlanJob)."""
from __future__ import annotations

import math

import numpy as np

from race.command_history import CommandHistory
from race.world import CLOCK_ROUNDING_S, Observation, Perceived, PoseSource, TimedPose

__all__ = ["MarkerPoses", "Perceived", "Perception", "TruthPerception", "body_state"]


def body_state(st) -> np.ndarray:
    """Estimator state (tracking.estimator.CarState) -> [x, y, heading, vx, vy, yaw_rate]."""
    return np.array([st.x, st.y, st.heading, st.speed * math.cos(st.sideslip),
                     st.speed * math.sin(st.sideslip), st.yaw_rate])


class MarkerPoses:
    """The camera as a pose source: the packet's frame (race.world.WorldPacket.frame), each new one once,
    through the marker tracker (race.world.Tracker). ``cars``: objects with ``name`` and ``marker_id``."""

    regions = True

    def __init__(self, tracker, cars) -> None:
        self.tracker = tracker
        self.by_marker = {c.marker_id: c.name for c in cars}
        self.marker_of = {c.name: c.marker_id for c in cars}
        self._last_frame_index = -1

    def next_reading(self, packet) -> float | None:
        frame = packet.frame
        if frame is None or frame.index == self._last_frame_index:
            return None
        self._last_frame_index = frame.index
        return frame.t_capture_s

    def read(self, packet, predictions) -> Observation:
        frame = packet.frame
        rois = None if predictions is None else {self.marker_of[name]: xy for name, xy in predictions.items()}
        det = self.tracker.process(frame, rois)
        t = frame.t_capture_s
        poses = {self.by_marker[m.marker_id]: TimedPose(t, m.x, m.y, m.heading)
                 for m in det.cars.values() if m.marker_id in self.by_marker}
        centres = (np.array([c.reshape(-1, 2).mean(axis=0) for c in det.markers.values()]) if det.markers
                   else np.zeros((0, 2)))
        return Observation(t, poses, image=frame.image, image_points=centres, full_search=det.full_search)


class Perception:
    """Poses from ``source`` (race.world.PoseSource; ``tracker``: a marker tracker, wrapped in
    :class:`MarkerPoses`) into the estimator (tracking.estimator.MultiCarEstimator, one filter per
    marker id). ``cars``: objects with ``name`` and ``marker_id`` (race.loop.CarBinding);
    ``commands``: the loop's command history (race.loop.RaceLoop.commands)."""

    estimated = True  # the states are estimates (recorded beside the truth)

    def __init__(self, tracker, estimator, cars, lost_search_every: int, commands: CommandHistory | None = None,
                 source: PoseSource | None = None) -> None:
        self.estimator, self.cars = estimator, list(cars)
        self.source = source if source is not None else MarkerPoses(tracker, self.cars)
        self.marker_of = {c.name: c.marker_id for c in self.cars}
        self.lost_search_every = lost_search_every
        self.commands = commands if commands is not None else CommandHistory()
        self.frames = 0
        self._frames_since_full = 0

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
        return self.estimator.filters.get(self.marker_of[name])

    def acquire(self, packet) -> None:
        """Before the start: a reading of every car (full-frame search) and an estimator update."""
        if self.source.next_reading(packet) is not None:
            self._update(self.source.read(packet, None))

    def acquired(self, measurements_needed: int) -> list:
        """The cars without ``measurements_needed`` accepted measurements yet (pre-race acquisition)."""
        return [c for c in self.cars if c.marker_id not in self.estimator.filters
                or self.estimator.filters[c.marker_id].counts["accepted"] < measurements_needed]

    def perceive(self, packet, t_plan: float, now: float, after_detect=None) -> Perceived:
        """Take the source's new reading (none: no update), update the estimator at the poses' times,
        and predict every car to ``t_plan``; lost cars are judged at ``now``. ``after_detect()`` is called
        between the reading and the estimation (stage timing)."""
        out = Perceived()
        t_reading = self.source.next_reading(packet)
        if t_reading is not None:
            self.frames += 1
            predictions = self._predictions(t_reading)
            if predictions is None or predictions or not self.source.regions:
                out.observation = self.source.read(packet, predictions)
        if after_detect is not None:
            after_detect()
        if out.observation is not None:
            for c in self.cars:
                f = self.estimator.filters.get(c.marker_id)
                if f is not None and f.accel_input is None and self.commands.has(c.name):
                    f.accel_input = self.commands.accel_input(c.name)
            out.accepted = self._update(out.observation)
        for c in self.cars:
            f = self.estimator.filters.get(c.marker_id)
            out.lost[c.name] = f is None or f.is_lost(now)
            if out.lost[c.name]:
                continue
            state = body_state(f.predict_to(t_plan))
            if not np.all(np.isfinite(state)):
                out.nonfinite.append(c.name)
                out.accepted.pop(c.name, None)
                self.estimator.forget(c.marker_id)
                continue
            out.states[c.name] = state
        return out

    def _update(self, obs: Observation) -> dict[str, np.ndarray]:
        """Estimator updates with the observation's poses (one per distinct pose time, in time order;
        none: an update without measurements at the reading's time). Returns {car: estimate [x, y] at
        its pose's time, [x, y, heading]} of the accepted poses."""
        times = sorted({p.t_s for p in obs.poses.values()}) or [obs.t_s]
        accepted = {}
        for t in times:
            names = [name for name, p in obs.poses.items() if p.t_s == t]
            results = self.estimator.update(t, [(self.marker_of[n], obs.poses[n].x, obs.poses[n].y,
                                                  obs.poses[n].heading) for n in names])
            for n in names:
                f = self.estimator.filters.get(self.marker_of[n])
                if results[self.marker_of[n]].accepted and f is not None:
                    accepted[n] = np.array(f.x[:3], dtype=float)
        return accepted

    def _predictions(self, t_reading: float):
        """Predicted poses (car name -> (x, y, heading)) of the tracked cars at the reading's time: the camera
        searches around them and aligns a marker it cannot decode from them; None for a full search (every
        ``lost_search_every`` readings while a car is not tracked)."""
        filters = self.estimator.filters
        tracked = {c.name: filters[c.marker_id] for c in self.cars
                   if c.marker_id in filters and not filters[c.marker_id].is_lost(t_reading)
                   and np.all(np.isfinite(filters[c.marker_id].x))}
        self._frames_since_full += 1
        if len(tracked) < len(self.cars) and self._frames_since_full >= self.lost_search_every:
            self._frames_since_full = 0
            return None
        return {name: tuple(f.predict_to(t_reading).vector[:3]) for name, f in tracked.items()}


class TruthPerception:
    """The simulated world's true states as the observation (race.world.WorldPacket.truth): no camera,
    no estimator, never lost. The states are those at the poll; the loop's simulated timing plans
    from them at once (LoopConfig.plan_ticks = 0, command_delay_s = 0: t_plan is the observation's
    time), so there is nothing to predict. ``cars``: objects with ``name`` (roster order, the rows of ``truth``)."""

    lost_after_s = math.inf
    estimated = False

    def __init__(self, cars) -> None:
        self.cars = list(cars)
        self.frames = 0  # no sensor readings
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
