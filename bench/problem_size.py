"""Measured memory and time per Newton iteration of RD3G against the size estimate in
solver_cpp/limits.py (`python -m app bench size`; docs/benchmarks.md). Each size runs in its own
process so its peak resident memory is its own."""
from __future__ import annotations

import json
import subprocess
import sys

from bench.merging import merging_problem
from solver_cpp import Solver
from solver_cpp.limits import estimate_size

SIZES = [(2, 20), (2, 400), (2, 2000), (4, 100), (8, 20), (8, 200), (16, 20), (24, 20), (32, 20)]


def measure_one(cars: int, horizon: int, iterations: int = 3) -> dict:
    """In this process: solve a merging game of the given size for a few iterations."""
    import dataclasses
    import resource

    problem = dataclasses.replace(merging_problem(cars, 0), horizon=horizon)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    result = Solver(problem, max_iter=iterations, restart=dict(count=0)).solve()
    size = estimate_size(problem)
    return {"cars": cars, "horizon": horizon, "block": size.block,
            "peak_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, "bytes_before": rss_before,
            "estimated_bytes": size.memory_bytes, "iterations": result.iterations,
            "seconds_per_iteration": result.solve_time_s / max(result.iterations, 1),
            "estimated_seconds_per_iteration": size.seconds_per_iteration}


def run(sizes=SIZES) -> list[dict]:
    rows = []
    for cars, horizon in sizes:
        out = subprocess.run([sys.executable, "-m", "bench.problem_size", str(cars), str(horizon)],
                             capture_output=True, text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"{cars} cars, horizon {horizon}: peak {r['peak_bytes'] / 2**20:.0f} MiB (estimate "
              f"{r['estimated_bytes'] / 2**20:.0f}), {1e3 * r['seconds_per_iteration']:.1f} ms/iteration (estimate "
              f"{1e3 * r['estimated_seconds_per_iteration']:.1f})", file=sys.stderr)
    return rows


def markdown(rows: list[dict], command: str, machine: str, load: tuple) -> str:
    lines = ["### Problem size estimate vs measurement", "", f"`{command}`", "",
             "| cars | horizon | block b | peak memory | estimate | ms / iteration | estimate |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['cars']} | {r['horizon']} | {r['block']} | {r['peak_bytes'] / 2**20:.0f} MiB | "
                     f"{r['estimated_bytes'] / 2**20:.0f} MiB | {1e3 * r['seconds_per_iteration']:.1f} | "
                     f"{1e3 * r['estimated_seconds_per_iteration']:.1f} |")
    lines += ["", f"{machine}; load average {load[0]:.1f} (shared machine: times are upper bounds)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # run()'s child process (one measurement per fresh process), not a user command
    print(json.dumps(measure_one(int(sys.argv[1]), int(sys.argv[2]))))
