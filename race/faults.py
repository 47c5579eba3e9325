"""Fault injection (``race --hil --fault KIND@START[+DURATION][:CAR]``, docs/race-stack.md) as wrappers
around the loop's parts, so the loop itself has no fault branches. Camera and serial faults
(``occlude``, ``serial_corrupt``, ``serial_vanish``) act in the HIL world (race.hil); the two
below act on the loop's own parts. ``race_time(t_abs)`` maps the clock's time to race time."""
from __future__ import annotations

from typing import Callable

import numpy as np

from race.config import FaultSpec
from race.planning import SolverFailure


class NanStateEstimator:
    """``nan_state``: once the race time reaches the fault's start, the estimated state of the faulted
    cars becomes NaN (after the estimator's next update); ``on_inject(text)`` logs it."""

    def __init__(self, estimator, faults: tuple[FaultSpec, ...], marker_of: dict[str, int],
                 race_time: Callable[[float], float], on_inject: Callable[[str], None]) -> None:
        self.inner = estimator
        self._pending = [f for f in faults if f.kind == "nan_state"]
        self._marker_of = marker_of
        self._race_time = race_time
        self._on_inject = on_inject

    def __getattr__(self, name):  # everything else is the estimator's
        return getattr(self.inner, name)

    def update(self, t_s: float, measurements) -> dict:
        results = self.inner.update(t_s, measurements)
        for f in [f for f in self._pending if self._race_time(t_s) >= f.start_s]:
            self._pending.remove(f)
            for name, marker in self._marker_of.items():
                if f.applies_to(name) and marker in self.inner.filters:
                    self.inner.filters[marker].x[:] = np.nan
            self._on_inject(f"estimator state of {f.car or 'all cars'} set to NaN")
        return results


class FailingPlanners:
    """``solver_fail``: a planning job whose t_plan falls in the fault's window raises SolverFailure."""

    def __init__(self, planners, faults: tuple[FaultSpec, ...], race_time: Callable[[float], float]) -> None:
        self.inner = planners
        self._faults = [f for f in faults if f.kind == "solver_fail"]
        self._race_time = race_time

    def __getattr__(self, name):  # commanded, executed_control, ... are the planners'
        return getattr(self.inner, name)

    def plan(self, job):
        t = self._race_time(job.t_plan)
        if any(f.active(t) for f in self._faults):
            raise SolverFailure("injected solver failure")
        return self.inner.plan(job)
