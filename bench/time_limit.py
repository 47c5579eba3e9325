"""How well `time_limit` holds on the slow linear-solver paths (docs/solver.md, "Time limit"):
`python -m bench.time_limit [--cars 6] [--seeds 3] [--limits 0.05,0.2]` solves the merging games with
SparseQR and with LSCG at a tolerance it cannot reach, and prints status and wall time per solve."""
from __future__ import annotations

import argparse
import time

from bench.merging import merging_problem
from solver_cpp import solve

PATHS = {"sparse_qr": {}, "lscg": {"lscg_tol": 1e-16, "lscg_max_iter": 10**6}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cars", type=int, default=6)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--limits", default="0.05,0.2", help="time limits (s), comma-separated")
    args = p.parse_args()
    limits = [float(x) for x in args.limits.split(",")]
    print("linear_solver  limit_s  seed  status      wall_s  overshoot_s")
    for name, extra in PATHS.items():
        for limit in limits:
            for seed in range(args.seeds):
                t0 = time.perf_counter()
                r = solve(merging_problem(args.cars, seed), linear_solver=name, time_limit=limit, **extra)
                wall = time.perf_counter() - t0
                print(f"{name:<13}  {limit:7.3f}  {seed:4d}  {r.status:<10}  {wall:6.3f}  {wall - limit:11.3f}")


if __name__ == "__main__":
    main()
