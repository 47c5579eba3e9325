"""The referee: who caused a collision, the closest approach of the two footprints, and (where no
simulator judges the race, i.e. on hardware) laps and the finishing order from the cars' states.

Laps are counted with the simulator's own rules (``sim.race.LapBookkeeper``: forward crossings of
s = 0, a car starting in the second half of the lap is on the grid behind the line), gaps with the one
footprint-gap function (``sim.collision.footprint_gap``)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from race.setup import CAR_NAMES
from sim.collision import footprint_gap
from sim.race import LapBookkeeper, SimEvent
from vehicles.params import CarParams


@dataclass
class CollisionRecord:
    time_s: float
    at_fault: str  # car name, see fault_of


def fault_of(states: np.ndarray) -> int:
    """The car whose front hit the other: the one that has the other further ahead of it along its
    own heading (the rear car in a rear-end contact, the car that turned in on the other in a side
    contact)."""
    ahead = []
    for i, j in ((0, 1), (1, 0)):
        d = states[j, :2] - states[i, :2]
        ahead.append(d[0] * math.cos(states[i, 2]) + d[1] * math.sin(states[i, 2]))
    return 0 if ahead[0] >= ahead[1] else 1


def event_text(ev: SimEvent, at_fault: str | None = None) -> str:
    """A simulator event's text in the race's event log (kind ``ev.kind``): the car first, then the lap
    and its time (``lap``) or the car at fault (``collision``): ``rd3g lap 1 in 5.123 s``,
    ``opponent (fault rd3g)``. race.review reads the car as the first word."""
    text = CAR_NAMES[ev.car]
    if ev.kind == "lap":
        text += f" lap {ev.lap} in {ev.lap_time:.3f} s"
    elif ev.kind == "collision" and at_fault is not None:
        text += f" (fault {at_fault})"
    return text


@dataclass
class Referee:
    """Judges one two-car race from its states (rows [x, y, heading, ...], CAR_NAMES order).

    ``observe(t, states)`` at every sample: the minimum footprint gap and, when ``laps_to_win`` is
    given, laps from the states (returns the lap/finished events); ``collision(t, states)`` records a
    contact and who caused it."""

    track: object
    car: CarParams
    laps_to_win: int | None = None      # None: the simulator counts laps, the referee does not
    min_gap_m: float = math.inf
    collisions: list[CollisionRecord] = field(default_factory=list)
    _laps: LapBookkeeper | None = field(default=None, init=False, repr=False)

    def observe(self, t: float, states: np.ndarray) -> list[SimEvent]:
        states = np.asarray(states, dtype=float)
        self.min_gap_m = min(self.min_gap_m, footprint_gap(states, self.car.geometry))
        if self.laps_to_win is None:
            return []
        s = self.track.to_frenet(states[:, 0], states[:, 1])[0]
        if self._laps is None:  # the first sample is the grid
            self._laps = LapBookkeeper(float(self.track.length), self.laps_to_win, np.asarray(s, float), start_time=t)
            return []
        return self._laps.update(t, np.asarray(s, float))

    def collision(self, t: float, states: np.ndarray) -> CollisionRecord:
        record = CollisionRecord(t, CAR_NAMES[fault_of(np.asarray(states, dtype=float))])
        self.collisions.append(record)
        return record

    @property
    def winner(self) -> str | None:
        if self._laps is None or self._laps.winner is None:
            return None
        return CAR_NAMES[self._laps.winner]

    @property
    def lap_times_s(self) -> dict[str, list[float]]:
        if self._laps is None:
            return {name: [] for name in CAR_NAMES}
        return {name: list(self._laps.lap_times[i]) for i, name in enumerate(CAR_NAMES)}
