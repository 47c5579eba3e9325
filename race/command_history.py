"""The commands the cars execute, one shared history (docs/race-stack.md, "Latency"): the loop writes
each commanded car's planning-model control [a m/s^2, delta rad] from the instant it acts on (the tick
plus LoopConfig.command_delay_s); the state estimator reads the accelerations (CarEKF.accel_input) and
the planners read the controls from a car's last measured pose to their planning instant
(race.planning.RacePlanners, through the snapshot a PlanJob carries). One second of history is kept."""
from __future__ import annotations

import bisect
from typing import Callable

KEEP_S = 1.0


def controls_between(log, t0: float, t1: float) -> list[tuple[float, float, float]]:
    """The piecewise-constant controls of ``log`` ([(t_on s, a, delta), ...], ascending t_on, each acting
    until the next one's t_on, the last until t1) that act in [t0, t1), as [(duration s, a, delta), ...];
    the part before the first entry is not covered."""
    out = []
    # Called several times a tick (EKF predictions): start at the entry acting at t0.
    for j in range(max(bisect.bisect_right(log, t0, key=lambda e: e[0]) - 1, 0), len(log)):
        t_on, a, delta = log[j]
        if t_on >= t1:
            break
        t_off = log[j + 1][0] if j + 1 < len(log) else t1
        lo, hi = max(t_on, t0), min(t_off, t1)
        if hi > lo:
            out.append((hi - lo, a, delta))
    return out


class CommandHistory:
    """Per car, [(t_effect, a, delta), ...] with a new entry only when the control changes. A car whose
    command has no planning-model control (pure pursuit) has an empty history: nothing to predict with.
    Written, read by the estimator and snapshotted in the loop's thread; a planner thread reads only its
    job's snapshot."""

    def __init__(self, logs: dict | None = None) -> None:
        self._logs: dict[str, list[tuple[float, float, float]]] = logs if logs is not None else {}

    def record(self, name: str, t_effect: float, control: tuple[float, float] | None) -> None:
        """Car ``name`` executes ``control`` from ``t_effect`` on (None: not a model control)."""
        log = self._logs.setdefault(name, [])
        if control is None:
            log.clear()
            return
        if not log or log[-1][1:] != control:
            log.append((t_effect, *control))
        while len(log) > 1 and log[1][0] < t_effect - KEEP_S:
            log.pop(0)

    def has(self, name: str) -> bool:
        """The loop has commanded car ``name`` (its history exists, perhaps empty)."""
        return name in self._logs

    def covers(self, name: str, t: float) -> bool:
        """The history of car ``name`` reaches back to ``t``."""
        log = self._logs.get(name)
        return bool(log) and log[0][0] <= t

    def between(self, name: str, t0: float, t1: float) -> list[tuple[float, float, float]]:
        """:func:`controls_between` of car ``name``'s history."""
        return controls_between(self._logs.get(name, []), t0, t1)

    def accel_input(self, name: str) -> Callable[[float, float], list[tuple[float, float]]]:
        """CarEKF.accel_input of car ``name``: [(duration s, a m/s^2), ...] in [t0, t1)."""
        return lambda t0, t1: [(d, a) for d, a, _ in self.between(name, t0, t1)]

    def snapshot(self) -> "CommandHistory":
        """A copy that later records do not change (a planning job's view of what was sent)."""
        return CommandHistory({name: list(log) for name, log in self._logs.items()})
