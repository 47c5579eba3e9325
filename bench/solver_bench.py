"""`python -m app bench solver`: RD3G on the merging games, for each linear-solver option."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from bench.merging import merging_problem
from solver_cpp import solve

PAPER_RD3G_MS = {2: 18, 3: 29, 4: 83, 5: 137, 6: 226, 7: 339, 8: 430}


@dataclass
class SolverBenchRow:
    linear_solver: str
    cars: int
    instances: int
    converged: int
    median_ms: float
    mean_ms: float
    p90_ms: float
    mean_iterations: float
    ms_per_iteration: float  # median total time / iteration over converged runs
    linear_ms_per_iteration: float  # median linear-solve time / iteration over converged runs


def run(cars: list[int], instances: int, linear_solvers: list[str], time_limit_s: float) -> list[SolverBenchRow]:
    rows = []
    total = len(cars) * instances * len(linear_solvers)
    with tqdm(total=total, desc="bench solver", unit="solve") as bar:
        for ls in linear_solvers:
            for n in cars:
                times, iters, per_it, lin_it, conv = [], [], [], [], 0
                for seed in range(instances):
                    r = solve(merging_problem(n, seed), time_limit=time_limit_s, linear=dict(solver=ls))
                    bar.update()
                    if r.converged:
                        conv += 1
                        times.append(1e3 * r.solve_time_s)
                        iters.append(r.iterations)
                        per_it.append(1e3 * r.solve_time_s / max(r.iterations, 1))
                        lin_it.append(1e3 * r.linear_solve_time_s / max(r.iterations, 1))
                nan = float("nan")
                rows.append(SolverBenchRow(
                    ls, n, instances, conv,
                    float(np.median(times)) if times else nan, float(np.mean(times)) if times else nan,
                    float(np.percentile(times, 90)) if times else nan, float(np.mean(iters)) if iters else nan,
                    float(np.median(per_it)) if per_it else nan, float(np.median(lin_it)) if lin_it else nan))
    return rows


def markdown(rows: list[SolverBenchRow], command: str, machine: str, seconds: float) -> str:
    lines = [
        "## RD3G solver: merging games, linear-solver options",
        "",
        f"Command: `{command}` ({seconds:.0f} s). Machine: {machine}. One process, one core.",
        "Instances: the paper's merging scenario (docs/merging.md), seeds 0..instances-1. Times are the solver's own",
        "wall time over converged runs; 'per it.' is the median of time / Newton iterations; 'lin. per it.' the",
        "linear-solve part of it. Paper: mean RD3G time from Table I (i7-7700K).",
        "",
        "| linear solver | cars | converged | median ms | mean ms | p90 ms | mean it. | ms per it. | lin. ms per it. | paper mean ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r.linear_solver} | {r.cars} | {r.converged}/{r.instances} ({100 * r.converged / r.instances:.0f}%) | "
                     f"{r.median_ms:.1f} | {r.mean_ms:.1f} | {r.p90_ms:.1f} | {r.mean_iterations:.1f} | "
                     f"{r.ms_per_iteration:.2f} | {r.linear_ms_per_iteration:.2f} | {PAPER_RD3G_MS.get(r.cars, '')} |")
    by = {(r.linear_solver, r.cars): r for r in rows}
    ratios = []
    for n in sorted({r.cars for r in rows}):
        a, b = by.get(("riccati", n)), by.get(("lscg", n))
        if a and b and a.ms_per_iteration == a.ms_per_iteration and b.ms_per_iteration == b.ms_per_iteration:
            ratios.append(f"{n} cars: {b.ms_per_iteration / a.ms_per_iteration:.1f}x")
    if ratios:
        lines += ["", "Time per Newton iteration, LSCG+SparseQR (paper) / Riccati (default), same run: " + ", ".join(ratios) + "."]
    return "\n".join(lines)
