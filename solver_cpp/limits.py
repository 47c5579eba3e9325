"""Problem size before any allocation: how much memory and time one Newton iteration of RD3G is
expected to need, and the limits beyond which a caller (the `solve` CLI) refuses to start.

The Newton system couples every agent's stage variables and every constraint at a time step into one
block of size b = N (2 nx + nu) + (constraints per step), T blocks in all. A factorisation of the
block-banded system holds about T b^2 numbers and costs about T b^3 operations; when the solver
falls back to sparse LU on the whole system the time also grows like (T b)^2 (8 cars: 100x the
time per iteration for 10x the horizon). The constants are fitted to measured peak memory and
iteration times (`python -m app bench size`, docs/benchmarks.md) as upper envelopes: the estimate
separates "seconds and megabytes" from "hours and gigabytes"; it is not a prediction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .problem import GameProblem

# Documented limits (docs/problem-format.md): beyond either, `solve` refuses unless --allow-large.
MAX_MEMORY_BYTES = 2 * 2**30
MAX_SECONDS_PER_ITERATION = 30.0
# Fitted constants (see module docstring).
BYTES_PER_BLOCK_ENTRY = 48.0        # per entry of T b^2: doubles times the fill and workspace factor
BASE_BYTES = 40 * 2**20             # the Python process with the extension loaded
SECONDS_PER_BLOCK_FLOP = 1e-9       # per T b^3
SECONDS_PER_UNKNOWN_PAIR = 5e-9     # per (T b)^2, the sparse-LU fallback


class ProblemTooLargeError(ValueError):
    """The problem's estimated memory or time exceeds the limits; the message says by how much."""


@dataclass(frozen=True)
class ProblemSize:
    agents: int
    horizon: int
    nx: int
    nu: int
    constraints_per_step: int      # pairwise, obstacle and finite bound entries
    block: int                     # unknowns per time step in the Newton system
    memory_bytes: float            # estimated peak
    seconds_per_iteration: float   # estimated


def _finite_entries(bounds) -> int:
    """Bound components that make a constraint (infinite ones do not)."""
    return 0 if bounds is None else int(np.isfinite(np.asarray(bounds, dtype=float)).sum())


def estimate_size(problem: GameProblem) -> ProblemSize:
    """Size of a problem that has passed validation (problem.to_core())."""
    N, T = len(problem.agents), int(problem.horizon)
    nx, nu = int(problem.agents[0].dynamics.nx), int(problem.agents[0].dynamics.nu)
    per_step = len(problem.obstacles) * N
    if problem.collision is not None and problem.collision.enabled and N >= 2:
        per_step += N * (N - 1) // 2
    for a in problem.agents:
        per_step += sum(_finite_entries(b) for b in (a.u_min, a.u_max, a.x_min, a.x_max))
    block = N * (2 * nx + nu) + per_step
    return ProblemSize(
        agents=N, horizon=T, nx=nx, nu=nu, constraints_per_step=per_step, block=block,
        memory_bytes=BASE_BYTES + BYTES_PER_BLOCK_ENTRY * T * float(block) ** 2,
        seconds_per_iteration=SECONDS_PER_BLOCK_FLOP * T * float(block) ** 3
        + SECONDS_PER_UNKNOWN_PAIR * (T * float(block)) ** 2)


def check_size(size: ProblemSize, max_memory_bytes: float = MAX_MEMORY_BYTES,
               max_seconds_per_iteration: float = MAX_SECONDS_PER_ITERATION) -> None:
    """Raise ProblemTooLargeError if the estimate exceeds a limit."""
    what = (f"{size.agents} agents, horizon {size.horizon}, nx {size.nx}, nu {size.nu}, "
            f"{size.constraints_per_step} constraints per step")
    if size.memory_bytes > max_memory_bytes:
        raise ProblemTooLargeError(
            f"problem too large: {what} needs an estimated {_gib(size.memory_bytes)} of memory, "
            f"more than the limit of {_gib(max_memory_bytes)}")
    if size.seconds_per_iteration > max_seconds_per_iteration:
        raise ProblemTooLargeError(
            f"problem too large: {what} needs an estimated {_duration(size.seconds_per_iteration)} per Newton "
            f"iteration, more than the limit of {_duration(max_seconds_per_iteration)}")


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def _duration(s: float) -> str:
    return f"{s:.3g} s" if s < 3600 or not math.isfinite(s) else f"{s / 3600:.3g} h"
