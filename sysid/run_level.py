"""Run-level parameters (docs/sysid.md, "Run-level parameters").

Some parameters belong to a session, not to the car: the VESC's speed loop of the F1/10 runs responds at a
different rate in each run. Such a parameter is fitted per training run: first on the nominal model, so that the
shared parameters are fitted with each run's own value (``sysid.model.ModelSetup.run_values``), then again on top of
the final shared model. The runs' values are pooled as a random-effects population (DerSimonian-Laird, ``sysid.agreement.pool``) in the logarithm of
the parameter (a rate scale is positive and its spread multiplicative). The population's uncertainty includes the
spread between runs (tau), so a new run is predicted with the population value and an honest +-.

A held-out run is predicted with the population value (pure prediction). Separately, it can be calibrated on its
own first block (the first ``calibration_s`` of the run's own time): the parameter fitted on windows that end inside
that block, scored only on the windows that start after it, against the shared and the population model on those
same windows. The population value is written to the car file only if it passes the keep test on the held-out runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from sysid.agreement import Pool, pool

if TYPE_CHECKING:
    from sysid.diagnose import CandidateResult, ErrorSummary

# Effects whose parameters are fitted per run when there are several training runs.
RUN_LEVEL_EFFECTS = ("speed_response",)


@dataclass(frozen=True)
class RunValue:
    run: int  # run index (Trajectory.runs)
    value: float
    std: float
    windows: int  # fit windows of the run


@dataclass(frozen=True)
class Population:
    """Random-effects pool of per-run values, on the log scale."""

    log_pool: Pool

    @property
    def value(self) -> float:
        return math.exp(self.log_pool.mean)

    @property
    def std(self) -> float:
        """Of the population value (the pool's std, spread between runs included), in the parameter's units."""
        return self.value * self.log_pool.std

    @property
    def spread_factor(self) -> float:
        """A run's value lies within a factor of this of the population value with ~68 % probability (exp tau)."""
        return math.exp(self.log_pool.tau)

    @property
    def run_std(self) -> float:
        """Predictive std of a new run's value (tau and the pool's std), in the parameter's units (delta method)."""
        return self.value * math.hypot(self.log_pool.tau, self.log_pool.std)


def population(values: list[RunValue]) -> Population:
    """Pool of per-run values in log space; std(log v) = std(v) / v (a value at zero has no log: floored)."""
    v = np.array([max(r.value, 1e-9) for r in values])
    s = np.array([r.std for r in values]) / v
    return Population(pool(np.log(v), s))


def calibration_masks(elapsed_start: np.ndarray, elapsed_end: np.ndarray, calibration_s: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Windows of a held-out run: (calibration = those that end inside its first block, later = those that start
    after it). Windows that straddle the block's end are in neither, so no calibration sample is scored."""
    return elapsed_end < calibration_s, elapsed_start >= calibration_s


@dataclass(frozen=True)
class Calibration:
    """A held-out run calibrated on its own first block; errors on the windows that start after the block."""

    block_s: float  # the block: [0, block_s) of the run's own time
    windows: int  # later windows scored
    value: float | None = None  # None: not calibrated (``reason`` says why)
    std: float | None = None
    reason: str | None = None
    shared: ErrorSummary | None = None  # the shared model (the parameter at the car file's value)
    population: ErrorSummary | None = None
    calibrated: ErrorSummary | None = None


@dataclass(frozen=True)
class HeldoutRun:
    """A held-out run predicted with the shared model and with the population value (all its held-out windows)."""

    run: int
    windows: int
    shared: ErrorSummary
    population: ErrorSummary
    calibration: Calibration


@dataclass(frozen=True)
class RunLevelParam:
    """A run-level parameter: per training run, the population, and what it does on the held-out runs."""

    effect: str
    param: str
    nominal: float  # the car file's value (what the shared model uses)
    runs: tuple[RunValue, ...]
    not_excited: tuple[tuple[int, str], ...]  # training runs without an estimate, and why
    population: Population
    verdict: CandidateResult  # population value vs the shared model on the held-out data (the keep test)
    heldout: tuple[HeldoutRun, ...]

    @property
    def written(self) -> bool:
        """The population value goes into the car file only if it passes the keep test held out."""
        return self.verdict.significant
