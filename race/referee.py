"""The referee of every race mode: who caused each collision, the closest approach of any two
footprints, off-track excursions per car and (where no simulator judges the race, i.e. on hardware)
laps, off-track excursions and the finishing order from the cars' states; then each car's result
(:meth:`Referee.results`).

Laps and excursions are counted with the simulator's own rules (``sim.race.LapBookkeeper``: forward
crossings of s = 0, a car starting in the second half of the lap is on the grid behind the line, progress
made off the track does not count beyond the allowance), off the track is the simulator's (a footprint
corner outside the drivable area, ``sim.race.footprint_excess_m``), gaps with the one footprint-gap
function (``sim.collision.footprint_gap``). Cars are rows in roster order (``names``)."""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from sim.collision import footprint_corners, footprint_gap
from sim.race import OFF_TRACK_ALLOWANCE_CAR_LENGTHS, LapBookkeeper, SimEvent, footprint_excess_m
from vehicles.params import CarParams


@dataclass
class CollisionRecord:
    time_s: float
    at_fault: str | None           # car name (fault_of), None when the referee could not tell
    cars: tuple[str, ...] = ()     # the two cars in contact


def fault_of(states: np.ndarray) -> int:
    """Of two cars (rows), the one whose front hit the other: the one that has the other further
    ahead of it along its own heading (the rear car in a rear-end contact, the car that turned in on
    the other in a side contact)."""
    ahead = []
    for i, j in ((0, 1), (1, 0)):
        d = states[j, :2] - states[i, :2]
        ahead.append(d[0] * math.cos(states[i, 2]) + d[1] * math.sin(states[i, 2]))
    return 0 if ahead[0] >= ahead[1] else 1


def event_text(ev: SimEvent, names, at_fault: str | None = None) -> str:
    """A simulator event's text in the race's event log (kind ``ev.kind``): the car first, then the lap
    and its time (``lap``), the other car and the car at fault (``collision``) or where the car left and
    rejoined the track and the distance not counted (``not_counted``): ``rd3g lap 1 in 5.123 s``,
    ``opponent with rd3g (fault rd3g)``, ``mpc3 left at s = 0.61 m, rejoined at s = 5.40 m: 4.63 m not
    counted``. race.review reads the car as the first word."""
    text = names[ev.car]
    if ev.kind == "lap":
        text += f" lap {ev.lap} in {ev.lap_time:.3f} s"
    elif ev.kind == "not_counted":
        text += (f" left at s = {ev.left_s_m:.2f} m, rejoined at s = {ev.rejoined_s_m:.2f} m: "
                 f"{ev.not_counted_m:.2f} m not counted")
    elif ev.kind == "collision":
        if ev.other is not None:
            text += f" with {names[ev.other]}"
        if at_fault is not None:
            text += f" (fault {at_fault})"
    return text


@dataclass(frozen=True)
class CarResult:
    """One car's race as the referee saw it."""

    name: str
    finish_position: int | None     # 1-based; None: unfinished
    lap_times_s: list[float]
    at_fault_collisions: int
    off_track: int
    not_counted_m: float = 0.0      # progress made off the track that did not count (sim.race)


@dataclass
class Referee:
    """Judges one race of the cars ``names`` from their states (rows [x, y, heading, ...], ``names``
    order).

    ``observe(t, states)`` at every sample: the minimum footprint gap over every pair and, when
    ``laps_to_win`` is given, laps and off-track excursions from the states (returns the bookkeeper's
    events: lap, finished, off_track, on_track, not_counted); ``sim_event(ev, states)`` takes a
    simulator's event (a collision gets the car at fault, off-track and finishes are counted) and returns
    its log entry (kind, text) or None; ``log_entry(ev)`` is that entry for any other event."""

    track: object
    car: CarParams
    names: tuple[str, ...]
    laps_to_win: int | None = None      # None: the simulator counts laps, the referee does not
    # The gain an excursion may make before it is taken off the car's counted laps (sim.race), in car
    # lengths: used where the referee counts the laps (race.setup.RaceSetup.off_track_allowance_car_lengths).
    off_track_allowance_car_lengths: float = OFF_TRACK_ALLOWANCE_CAR_LENGTHS
    min_gap_m: float = math.inf
    collisions: list[CollisionRecord] = field(default_factory=list)
    off_track: dict[str, int] = field(default_factory=dict)
    not_counted_m: dict[str, float] = field(default_factory=dict)
    _laps: LapBookkeeper | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.names = tuple(self.names)
        self.off_track = {name: 0 for name in self.names}
        self.not_counted_m = {name: 0.0 for name in self.names}
        self._pairs = list(itertools.combinations(range(len(self.names)), 2))

    def observe(self, t: float, states: np.ndarray) -> list[SimEvent]:
        states = np.asarray(states, dtype=float)
        for i, j in self._pairs:
            self.min_gap_m = min(self.min_gap_m, footprint_gap(states[[i, j]], self.car.geometry))
        if self.laps_to_win is None:
            return []
        s = np.asarray(self.track.to_frenet(states[:, 0], states[:, 1])[0], dtype=float)
        g = self.car.geometry
        excess = footprint_excess_m(self.track, footprint_corners(states[:, 0], states[:, 1], states[:, 2],
                                                                  g.footprint_length_m, g.footprint_width_m,
                                                                  g.footprint_offset_m))
        if self._laps is None:  # the first sample is the grid (only the track limits are judged on it)
            self._laps = LapBookkeeper(float(self.track.length), self.laps_to_win, s, start_time=t,
                                       allowance_m=self.off_track_allowance_car_lengths * g.footprint_length_m)
        events = self._laps.update(t, s, excess)
        for ev in events:
            self._count(ev)
        return events

    def _count(self, ev: SimEvent) -> None:
        if ev.kind == "off_track":
            self.off_track[self.names[ev.car]] += 1
        elif ev.kind == "not_counted":
            self.not_counted_m[self.names[ev.car]] += ev.not_counted_m

    def collision(self, t: float, states: np.ndarray, i: int = 0, j: int = 1) -> CollisionRecord:
        """Cars i and j (rows of ``states``) are in contact from time t: record it and who caused it."""
        pair = np.asarray(states, dtype=float)[[i, j]]
        at_fault = (i, j)[fault_of(pair)] if np.all(np.isfinite(pair[:, :3])) else None
        record = CollisionRecord(t, None if at_fault is None else self.names[at_fault], (self.names[i], self.names[j]))
        self.collisions.append(record)
        return record

    def sim_event(self, ev: SimEvent, states: np.ndarray) -> tuple[str, str] | None:
        """A simulator event as the race's event log entry (kind, text); collisions and off-track
        excursions are recorded. None for events the log does not keep (cleared, back on track)."""
        if ev.kind == "collision":
            record = self.collision(ev.time, states, ev.car, ev.other if ev.other is not None else 1 - ev.car)
            return ev.kind, event_text(ev, self.names, record.at_fault)
        self._count(ev)
        return self.log_entry(ev)

    def log_entry(self, ev: SimEvent) -> tuple[str, str] | None:
        """A lap, finish, off-track or not-counted event as the race's event log entry (kind, text)."""
        if ev.kind in ("lap", "finished", "off_track", "not_counted"):
            return ev.kind, event_text(ev, self.names)
        return None

    def at_fault(self, name: str) -> int:
        return sum(c.at_fault == name for c in self.collisions)

    @property
    def finish_order(self) -> list[str]:
        return [] if self._laps is None else [self.names[i] for i in self._laps.finish_order]

    @property
    def winner(self) -> str | None:
        order = self.finish_order
        return order[0] if order else None

    @property
    def all_finished(self) -> bool:
        return len(self.finish_order) == len(self.names)

    @property
    def lap_times_s(self) -> dict[str, list[float]]:
        if self._laps is None:
            return {name: [] for name in self.names}
        return {name: list(self._laps.lap_times[i]) for i, name in enumerate(self.names)}

    def results(self, finish_order, lap_times_s: dict, laps: int | None = None) -> list[CarResult]:
        """Each car's result (``names`` order) from the finishing order and lap times (the simulator's,
        or :attr:`finish_order` / :attr:`lap_times_s` where the referee counted laps itself); ``laps``:
        the race's laps (a car that has finished drives on until the race ends: its later laps are not
        its race's)."""
        position = {name: k + 1 for k, name in enumerate(finish_order)}
        return [CarResult(name, position.get(name), list(lap_times_s.get(name, []))[:laps], self.at_fault(name),
                          self.off_track.get(name, 0), self.not_counted_m.get(name, 0.0)) for name in self.names]
