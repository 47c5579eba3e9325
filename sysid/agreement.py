"""Do the runs agree on a parameter? (docs/sysid.md, "Agreement between runs").

Each training run gives its own estimate of a parameter with its own standard deviation. The runs are pooled
as in a random-effects meta-analysis (DerSimonian and Laird 1986): Cochran's Q tests whether the estimates
scatter more than their standard deviations allow; tau^2 is the spread between runs beyond that. When Q
rejects, a run whose estimate lies more than ``OUTLIER_Z`` standard deviations from the random-effects pool of
the *other* runs (its own std, the others' spread tau and the pool's std combined) disagrees; the most extreme
one is excluded and the test repeated on the rest, as long as a strict majority of the runs remains. If more
runs than that would have to go, the runs disagree and nothing is claimed for the parameter. The rule knows
nothing about particular runs or parameters.

A claim fitted jointly on several runs is also checked with each training run left out in turn (the jackknife,
Quenouille 1956 and Tukey 1958): ``jackknife_std`` turns those leave-one-run-out values into the standard
deviation of the estimate, which contains the spread between runs whether or not the Q test saw it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

HETEROGENEITY_P = 0.01  # Cochran's Q below this p-value: the runs scatter more than their uncertainties allow
OUTLIER_Z = 3.0  # a run this many combined standard deviations from the other runs' pool disagrees


@dataclass(frozen=True)
class Pool:
    """Random-effects pool of per-run estimates."""

    mean: float
    std: float  # of the pooled mean, spread between runs included
    tau: float  # spread between runs beyond their own standard deviations
    q: float  # Cochran's Q against the fixed-effect mean
    p_value: float  # of Q under homogeneity (chi-square, k - 1 degrees of freedom); 1 for one run


def pool(values: np.ndarray, stds: np.ndarray) -> Pool:
    """DerSimonian-Laird random-effects pool of ``values`` with standard deviations ``stds``."""
    values, stds = np.asarray(values, dtype=float), np.asarray(stds, dtype=float)
    var = np.maximum(stds, 1e-12 * np.maximum(np.abs(values), 1.0)) ** 2
    w = 1.0 / var
    fixed = float(np.sum(w * values) / np.sum(w))
    q = float(np.sum(w * (values - fixed) ** 2))
    k = values.size
    tau2 = 0.0
    if k > 1:
        tau2 = max(0.0, (q - (k - 1)) / (np.sum(w) - np.sum(w * w) / np.sum(w)))
    w_re = 1.0 / (var + tau2)
    mean = float(np.sum(w_re * values) / np.sum(w_re))
    p = float(chi2.sf(q, k - 1)) if k > 1 else 1.0
    return Pool(mean, float(np.sqrt(1.0 / np.sum(w_re))), float(np.sqrt(tau2)), q, p)


@dataclass(frozen=True)
class Agreement:
    """The verdict on one parameter across runs (indices into the estimates given)."""

    pooled: Pool  # of the agreeing runs
    agreeing: tuple[int, ...]
    excluded: tuple[int, ...]  # runs that disagree with the others, most extreme first
    disagree: bool  # no majority of the runs agrees: nothing is claimed for the parameter

    @property
    def verdict(self) -> str:
        return "runs disagree" if self.disagree else ("runs excluded" if self.excluded else "runs agree")


def outlier_z(values: np.ndarray, stds: np.ndarray, i: int) -> float:
    """How far run ``i`` lies from the random-effects pool of the other runs, in combined standard deviations."""
    rest = np.arange(values.size) != i
    others = pool(values[rest], stds[rest])
    return float((values[i] - others.mean) / np.sqrt(stds[i] ** 2 + others.tau ** 2 + others.std ** 2))


def agreement(values, stds) -> Agreement:
    """Which runs agree on a parameter (module docstring): Q test, then the most extreme run excluded while Q
    rejects and it lies more than OUTLIER_Z from the others, keeping a strict majority of the runs."""
    values, stds = np.asarray(values, dtype=float), np.asarray(stds, dtype=float)
    k = values.size
    keep = list(range(k))
    excluded: list[int] = []
    while True:
        pooled = pool(values[keep], stds[keep])
        if len(keep) < 2 or pooled.p_value >= HETEROGENEITY_P:
            return Agreement(pooled, tuple(keep), tuple(excluded), False)
        z = [abs(outlier_z(values[keep], stds[keep], j)) for j in range(len(keep))]
        worst = int(np.argmax(z))
        if z[worst] <= OUTLIER_Z:  # a spread between runs, no odd one: it is in the pooled std (tau)
            return Agreement(pooled, tuple(keep), tuple(excluded), False)
        if 2 * (len(keep) - 1) <= k:  # excluding it would leave no strict majority
            return Agreement(pooled, tuple(keep), tuple(excluded), True)
        excluded.append(keep.pop(worst))


def jackknife_std(loo_values) -> float:
    """Jackknife standard deviation of an estimate from its values with each of k runs left out in turn:
    sqrt((k - 1) / k * sum_i (theta_(-i) - mean)^2); 0 for fewer than two values."""
    v = np.asarray(loo_values, dtype=float)
    if v.size < 2:
        return 0.0
    return float(np.sqrt((v.size - 1) / v.size * np.sum((v - v.mean()) ** 2)))
