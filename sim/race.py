"""Lap and race bookkeeping from a sequence of arc-length samples (Frenet s) per car.

Laps are counted at the start/finish line s = 0 (docs/simulator.md, "Laps and races"):
a forward crossing completes a lap, a backward crossing takes one back. A car that starts
in the second half of the lap (s0 >= L/2) is taken to be on the grid behind the line, so its
first crossing starts lap 1 instead of completing one. Crossing times are interpolated
linearly between samples, so lap times are finer than the sampling period.

Progress made off the track does not count: while a car is off the track (a footprint corner outside
the drivable area) the arc length counted for its laps stays where it left; when it rejoins ahead of
that point, the gain beyond ``allowance_m`` (the room a brief excursion may gain) is not counted, so
the car drives that distance again before the line completes its lap. Where it left and rejoined are
interpolated between samples from how far the footprint is outside the track, so the distance not
counted does not depend on the sampling rate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# The gain a car may make in one excursion without it being taken off its counted progress, in its
# own footprint lengths (race.setup.RaceSetup.off_track_allowance_car_lengths, docs/racing.md).
OFF_TRACK_ALLOWANCE_CAR_LENGTHS = 1.0


@dataclass(frozen=True)
class SimEvent:
    time: float
    kind: str  # "lap", "finished", "collision", "collision_cleared", "off_track", "on_track", "not_counted"
    car: int
    other: int | None = None  # the other car of a collision
    lap: int | None = None  # laps completed, for "lap" and "finished"
    lap_time: float | None = None
    # "not_counted": where the car left and rejoined the track (s, m) and the distance not counted (m)
    left_s_m: float | None = None
    rejoined_s_m: float | None = None
    not_counted_m: float | None = None


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
    not_counted_m: tuple[float, ...] = ()  # progress made off the track that did not count, per car


def footprint_excess_m(track, corners) -> np.ndarray:
    """How far each footprint (corners (..., 4, 2), m) is outside the drivable area: the largest
    ``track.limit_excess_frenet`` of its corners (> 0: off the track)."""
    corners = np.asarray(corners, dtype=float)
    s, ey, _ = track.to_frenet(corners[..., 0], corners[..., 1])
    return np.asarray(track.limit_excess_frenet(s, ey), dtype=float).max(axis=-1)


@dataclass
class LapBookkeeper:
    """Laps and off-track excursions of every car from its samples: ``update(t, s, excess)``, with
    ``excess`` each car's footprint excess (``footprint_excess_m``; None: every car on the track).
    ``allowance_m``: the gain per excursion that is counted (one value or one per car)."""

    track_length: float
    laps_to_win: int
    initial_s: np.ndarray
    start_time: float = 0.0
    allowance_m: float | np.ndarray = 0.0
    laps: np.ndarray = field(init=False)
    last_s: np.ndarray = field(init=False)
    last_t: float = field(init=False)
    progress: np.ndarray = field(init=False)
    lap_start: list[float | None] = field(init=False)
    lap_times: list[list[float]] = field(init=False)
    finish_times: list[float | None] = field(init=False)
    finish_order: list[int] = field(init=False)
    counted_s: np.ndarray = field(init=False)  # the s laps are counted on: true s less not_counted (mod L)
    not_counted: np.ndarray = field(init=False)
    off_track: np.ndarray = field(init=False)
    off_track_count: np.ndarray = field(init=False)
    last_excess: np.ndarray = field(init=False)
    left: list[tuple[float, float, float] | None] = field(init=False)  # off track: (t, s, counted s) where it left

    def __post_init__(self) -> None:
        if self.track_length <= 0:
            raise ValueError(f"track_length: must be > 0, got {self.track_length}")
        if self.laps_to_win < 1:
            raise ValueError(f"laps_to_win: must be >= 1, got {self.laps_to_win}")
        s0 = np.mod(np.asarray(self.initial_s, dtype=float), self.track_length)
        n = s0.shape[0]
        allowance = np.broadcast_to(np.asarray(self.allowance_m, dtype=float), (n,)).copy()
        if not np.all(np.isfinite(allowance) & (allowance >= 0)):
            raise ValueError(f"allowance_m: must be finite and >= 0, got {self.allowance_m!r}")
        self.allowance_m = allowance
        on_grid = s0 >= self.track_length / 2.0
        self.laps = np.where(on_grid, -1, 0).astype(int)
        self.last_s = s0
        self.last_t = self.start_time
        self.progress = np.zeros(n)
        self.lap_start = [None if g else self.start_time for g in on_grid]
        self.lap_times = [[] for _ in range(n)]
        self.finish_times = [None] * n
        self.finish_order = []
        self.counted_s = s0.copy()
        self.not_counted = np.zeros(n)
        self.off_track = np.zeros(n, dtype=bool)
        self.off_track_count = np.zeros(n, dtype=int)
        self.last_excess = np.zeros(n)
        self.left = [None] * n

    def _step(self, a, b):
        """The shortest signed step from s = a to s = b; a jump of more than half a lap is a wrap."""
        length = self.track_length
        ds = b - a
        return np.where(ds > length / 2, ds - length, np.where(ds < -length / 2, ds + length, ds))

    def update(self, t: float, s: np.ndarray, excess: np.ndarray | None = None) -> list[SimEvent]:
        """Feed the cars' arc lengths (and footprint excesses) at time t; returns the lap/finish
        events in time order, then the off-track, on-track and not-counted events of this sample."""
        length = self.track_length
        s = np.mod(np.asarray(s, dtype=float), length)
        n = s.shape[0]
        excess = np.zeros(n) if excess is None else np.asarray(excess, dtype=float)
        if not np.all(np.isfinite(excess)):
            raise ValueError(f"excess: must be finite, got {excess}")
        outside = excess > 0.0
        ds = self._step(self.last_s, s)
        counted = np.mod(s - self.not_counted, length)  # an off-track car's is frozen below
        # Stretches of counted progress (car, t0, counted s at t0, t1, counted step): the car's own
        # step while on the track, nothing while off, the counted gain of an excursion when it rejoins.
        stretches = []
        later: list[SimEvent] = []
        for i in range(n):
            was_off, off = bool(self.off_track[i]), bool(outside[i])
            if not was_off and not off:
                stretches.append((i, self.last_t, self.counted_s[i], t, ds[i]))
                continue
            if was_off == off:  # still off the track: its counted s stays where it left
                counted[i] = self.left[i][2]
                continue
            # The footprint crossed the track limit between the samples: where its excess was zero.
            e0, e1 = self.last_excess[i], excess[i]
            f = min(max(e0 / (e0 - e1), 0.0), 1.0)
            t_x = self.last_t + f * (t - self.last_t)
            s_x = float(np.mod(self.last_s[i] + f * ds[i], length))
            if off:
                stretches.append((i, self.last_t, self.counted_s[i], t_x, f * ds[i]))
                self.left[i] = (t_x, s_x, float(np.mod(self.counted_s[i] + f * ds[i], length)))
                counted[i] = self.left[i][2]
                self.off_track_count[i] += 1
                later.append(SimEvent(time=t, kind="off_track", car=i))
                continue
            t_l, s_l, c_l = self.left[i]
            gain = float(self._step(s_l, s_x))
            lost = max(gain - float(self.allowance_m[i]), 0.0)
            self.not_counted[i] += lost
            counted[i] = np.mod(s[i] - self.not_counted[i], length)
            c_x = float(np.mod(c_l + gain - lost, length))
            stretches.append((i, t_l, c_l, t_x, gain - lost))
            stretches.append((i, t_x, c_x, t, (1.0 - f) * ds[i]))
            self.left[i] = None
            later.append(SimEvent(time=t, kind="on_track", car=i))
            if lost > 0.0:
                later.append(SimEvent(time=t, kind="not_counted", car=i, left_s_m=s_l, rejoined_s_m=s_x,
                                      not_counted_m=lost))
        crossings = []
        for i, t0, c0, t1, dc in stretches:
            if c0 + dc >= length or c0 + dc < 0.0:
                forward = bool(dc > 0)
                # Fraction of the stretch at which the car was on the line.
                dist_to_line = (length - c0) if forward else c0
                frac = dist_to_line / abs(dc) if dc != 0 else 1.0
                crossings.append((float(t0 + min(max(frac, 0.0), 1.0) * (t1 - t0)), int(i), forward))
        events: list[SimEvent] = []
        for t_cross, i, forward in sorted(crossings):  # time order decides who finishes first
            events.extend(self._cross(i, t_cross, forward))
        self.progress += ds
        self.counted_s = counted
        self.off_track = outside
        self.last_excess = excess
        self.last_s = s
        self.last_t = t
        return events + later

    def cross_line(self, i: int, t: float) -> list[SimEvent]:
        """Car i crossed the line forward at time t, seen by another bookkeeper (race.review: a lap the
        race completed after the last logged sample); returns the lap/finish events."""
        return self._cross(i, t, True)

    def _cross(self, i: int, t: float, forward: bool) -> list[SimEvent]:
        if not forward:
            self.laps[i] -= 1
            return []
        self.laps[i] += 1
        if self.laps[i] <= 0:
            if self.laps[i] == 0 and self.lap_start[i] is None:
                self.lap_start[i] = t  # left the grid: lap 1 starts now (once: backing over the line does not restart it)
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
