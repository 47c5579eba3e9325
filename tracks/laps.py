"""Lap counting from a stream of track positions."""
from __future__ import annotations

import math

import numpy as np

from .track import Track


class LapCounter:
    """Counts forward crossings of the start line (s = 0) of a closed track and times the laps.

    Feed samples in time order with :meth:`update` (t in s, arc length s in m), :meth:`update_xy`
    (t, x m, y m) or :meth:`update_many` (arrays). The counter integrates the car's progress
    (shortest along-track difference between consecutive samples, so samples must be less than
    half a lap apart) and registers crossing k when the progress first reaches the k-th start
    line ahead of the first sample. Backward jitter or driving back over the line and forward
    again therefore never counts twice: a line already passed must be re-earned by a full lap.
    Crossing times are interpolated linearly between the two samples around the crossing.

    ``lap_times`` are the times between consecutive crossings; with ``start_time`` (e.g. a
    standing start on or behind the line) the first lap is timed from ``start_time`` instead of
    starting at the first crossing.
    """

    def __init__(self, track: Track, start_time: float | None = None):
        if not track.closed:
            raise ValueError(f"LapCounter needs a closed track; {track.name!r} is open")
        if start_time is not None and not math.isfinite(start_time):
            raise ValueError(f"start_time must be finite, got {start_time!r}")
        self._track = track
        self._start_time = start_time
        self._t_last: float | None = None
        self._s_last = 0.0
        self._progress = 0.0  # m, unwrapped along-track position; starts at the first sample's s
        self._next_line = track.length  # progress (m) at which the next crossing happens
        self._crossing_times: list[float] = []

    @property
    def crossings(self) -> int:
        """Number of forward crossings of the start line so far."""
        return len(self._crossing_times)

    @property
    def crossing_times(self) -> tuple[float, ...]:
        """Times (s) of the forward crossings of the start line."""
        return tuple(self._crossing_times)

    @property
    def lap_times(self) -> tuple[float, ...]:
        """Durations (s) of the completed laps."""
        times = self._crossing_times if self._start_time is None else [self._start_time, *self._crossing_times]
        return tuple(np.diff(times).tolist())

    @property
    def laps(self) -> int:
        """Number of completed (timed) laps."""
        return len(self.lap_times)

    @property
    def progress(self) -> float:
        """Unwrapped distance along the track (m) of the last sample, counted from s = 0 of the first lap."""
        return self._progress

    def update(self, t: float, s: float) -> int:
        """Add one sample (t in s, s in m). Returns how many crossings it completed (0 or 1)."""
        return self.update_many([t], [s])

    def update_xy(self, t: float, x: float, y: float) -> int:
        """Add one sample given as a world position (m), projected onto the track."""
        s, _, _ = self._track.to_frenet(x, y)
        return self.update(t, float(s))

    def update_many(self, t, s) -> int:
        """Add samples (arrays of times in s and arc lengths in m). Returns the number of new crossings."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        s = np.atleast_1d(np.asarray(s, dtype=float))
        if t.shape != s.shape or t.ndim != 1:
            raise ValueError(f"t and s must be 1-D arrays of equal length, got shapes {t.shape} and {s.shape}")
        if len(t) == 0:
            return 0
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(s))):
            raise ValueError("t and s must be finite")
        prev_t = -np.inf if self._t_last is None else self._t_last
        if np.any(np.diff(np.concatenate([[prev_t], t])) < 0):
            raise ValueError("sample times must not decrease")
        s = self._track.wrap_s(s)
        if self._t_last is None:
            # First sample ever: progress starts at its s (0 <= s < length).
            steps = np.concatenate([[s[0]], self._track.progress_difference(s[1:], s[:-1])])
            base = 0.0
            t_prev_all = np.concatenate([[t[0]], t[:-1]])
        else:
            steps = self._track.progress_difference(s, np.concatenate([[self._s_last], s[:-1]]))
            base = self._progress
            t_prev_all = np.concatenate([[self._t_last], t[:-1]])
        progress = base + np.cumsum(steps)
        progress_prev = progress - steps
        new = 0
        # Each start line is passed at most once per sample (samples are < half a lap apart),
        # so a loop over crossings (a handful per race) is all that is needed.
        while True:
            hits = np.nonzero(progress >= self._next_line)[0]
            if len(hits) == 0:
                break
            k = int(hits[0])
            p0, p1 = progress_prev[k], progress[k]
            frac = 1.0 if p1 == p0 else (self._next_line - p0) / (p1 - p0)
            self._crossing_times.append(float(t_prev_all[k] + np.clip(frac, 0.0, 1.0) * (t[k] - t_prev_all[k])))
            self._next_line += self._track.length
            new += 1
        self._progress = float(progress[-1])
        self._s_last = float(s[-1])
        self._t_last = float(t[-1])
        return new
