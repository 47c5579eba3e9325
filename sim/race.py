"""Lap and race bookkeeping from a sequence of arc-length samples (Frenet s) per car.

Laps are counted at the start/finish line s = 0 (docs/simulator.md, "Laps and races"):
a forward crossing completes a lap, a backward crossing takes one back. A car that starts
in the second half of the lap (s0 >= L/2) is taken to be on the grid behind the line, so its
first crossing starts lap 1 instead of completing one. Crossing times are interpolated
linearly between samples, so lap times are finer than the sampling period.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class SimEvent:
    time: float
    kind: str  # "lap", "finished", "collision", "collision_cleared", "off_track", "on_track"
    car: int
    other: int | None = None  # the other car of a collision
    lap: int | None = None  # laps completed, for "lap" and "finished"
    lap_time: float | None = None


@dataclass(frozen=True)
class RaceStatus:
    time: float
    laps_to_win: int
    laps: tuple[int, ...]  # completed laps per car
    lap_times: tuple[tuple[float, ...], ...]  # per car; the first is from the race start
    progress_m: tuple[float, ...]  # arc length travelled since reset (signed)
    finish_times: tuple[float | None, ...]  # time each car completed laps_to_win
    finish_order: tuple[int, ...]
    winner: int | None
    collisions: int  # collision onsets, all pairs
    off_track: tuple[bool, ...]  # currently outside the drivable area
    off_track_count: tuple[int, ...]  # times each car left the drivable area
    min_center_distance_m: float  # closest approach of any two cars' centres of gravity


@dataclass
class LapBookkeeper:
    track_length: float
    laps_to_win: int
    initial_s: np.ndarray
    start_time: float = 0.0
    laps: np.ndarray = field(init=False)
    last_s: np.ndarray = field(init=False)
    last_t: float = field(init=False)
    progress: np.ndarray = field(init=False)
    lap_start: list[float | None] = field(init=False)
    lap_times: list[list[float]] = field(init=False)
    finish_times: list[float | None] = field(init=False)
    finish_order: list[int] = field(init=False)

    def __post_init__(self) -> None:
        if self.track_length <= 0:
            raise ValueError(f"track_length: must be > 0, got {self.track_length}")
        if self.laps_to_win < 1:
            raise ValueError(f"laps_to_win: must be >= 1, got {self.laps_to_win}")
        s0 = np.mod(np.asarray(self.initial_s, dtype=float), self.track_length)
        n = s0.shape[0]
        on_grid = s0 >= self.track_length / 2.0
        self.laps = np.where(on_grid, -1, 0).astype(int)
        self.last_s = s0
        self.last_t = self.start_time
        self.progress = np.zeros(n)
        self.lap_start = [None if g else self.start_time for g in on_grid]
        self.lap_times = [[] for _ in range(n)]
        self.finish_times = [None] * n
        self.finish_order = []

    def update(self, t: float, s: np.ndarray) -> list[SimEvent]:
        """Feed the cars' arc lengths at time t; returns lap/finish events in time order."""
        length = self.track_length
        s = np.mod(np.asarray(s, dtype=float), length)
        ds = s - self.last_s
        # The shortest signed step; a jump of more than half a lap is a wrap through s = 0.
        ds = np.where(ds > length / 2, ds - length, np.where(ds < -length / 2, ds + length, ds))
        crossings = []
        for i in np.nonzero((self.last_s + ds >= length) | (self.last_s + ds < 0.0))[0]:
            forward = bool(ds[i] > 0)
            # Fraction of the step at which the car was on the line.
            dist_to_line = (length - self.last_s[i]) if forward else self.last_s[i]
            frac = dist_to_line / abs(ds[i]) if ds[i] != 0 else 1.0
            crossings.append((float(self.last_t + min(max(frac, 0.0), 1.0) * (t - self.last_t)), int(i), forward))
        events: list[SimEvent] = []
        for t_cross, i, forward in sorted(crossings):  # time order decides who finishes first
            events.extend(self._cross(i, t_cross, forward))
        self.progress += ds
        self.last_s = s
        self.last_t = t
        return events

    def _cross(self, i: int, t: float, forward: bool) -> list[SimEvent]:
        if not forward:
            self.laps[i] -= 1
            return []
        self.laps[i] += 1
        if self.laps[i] <= 0:
            if self.laps[i] == 0:
                self.lap_start[i] = t  # left the grid: lap 1 starts now
            return []
        # Only the lap that reaches a new maximum is a timed lap (a back-and-forth is not).
        if len(self.lap_times[i]) >= self.laps[i]:
            return []
        start = self.lap_start[i] if self.lap_start[i] is not None else self.start_time
        lap_time = t - start
        self.lap_times[i].append(lap_time)
        self.lap_start[i] = t
        events = [SimEvent(time=t, kind="lap", car=i, lap=int(self.laps[i]), lap_time=lap_time)]
        if self.laps[i] >= self.laps_to_win and self.finish_times[i] is None:
            self.finish_times[i] = t
            self.finish_order.append(i)
            events.append(SimEvent(time=t, kind="finished", car=i, lap=int(self.laps[i])))
        return events

    @property
    def winner(self) -> int | None:
        return self.finish_order[0] if self.finish_order else None
