"""`python -m app demo`: solve one 3-car merging game and print what each car does."""
from __future__ import annotations

import numpy as np

from bench.merging import lane_counts, merging_problem
from solver_cpp import solve


def register(sub) -> None:
    p = sub.add_parser("demo", help="solve a 3-car merging game and print the equilibrium")
    p.add_argument("--cars", type=int, default=3)
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(func=run)


def run(args) -> int:
    problem = merging_problem(args.cars, args.seed)
    result = solve(problem)
    n_main, _ = lane_counts(args.cars)
    print(f"{args.cars}-car merge (seed {args.seed}): {result.status} in {result.iterations} Newton iterations, "
          f"{1e3 * result.solve_time_s:.1f} ms, |r| = {result.residual_norm:.1e}")
    d = np.linalg.norm(result.x[:, None, 1:, :2] - result.x[None, :, 1:, :2], axis=-1)
    d[np.arange(args.cars), np.arange(args.cars)] = np.inf
    print(f"closest approach {d.min():.3f} m (limit {problem.collision.min_distance} m)")
    for i in range(args.cars):
        x0, xT = result.x[i, 0], result.x[i, -1]
        lane = "main" if i < n_main else "merging"
        print(f"  car {i} ({lane:7s} lane): x {x0[0]:6.2f} -> {xT[0]:6.2f} m, y {x0[1]:+.2f} -> {xT[1]:+.2f} m, "
              f"v {x0[2]:.2f} -> {xT[2]:.2f} m/s")
    return 0 if result.converged else 1
