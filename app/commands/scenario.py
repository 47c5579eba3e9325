"""`python -m app scenario merge --cars N --seed S --out FILE`: write a standard scenario as a problem file."""
from __future__ import annotations

import json

from bench.merging import merging_problem
from fileio import atomic_write_text
from solver_cpp.problem_file import problem_to_dict


def register(sub) -> None:
    p = sub.add_parser("scenario", help="write a standard scenario as a problem file")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    m = kinds.add_parser("merge", help="the paper's car-merging game (docs/merging.md)")
    m.add_argument("--cars", type=int, default=3, help="number of cars, 2 or more (default 3)")
    m.add_argument("--seed", type=int, default=0, help="instance seed (default 0)")
    m.add_argument("--out", required=True, help="problem file to write (JSON)")
    m.set_defaults(func=run_merge)


def run_merge(args) -> int:
    problem = merging_problem(args.cars, args.seed)
    atomic_write_text(args.out, json.dumps(problem_to_dict(problem, solver={"tol": 5e-4, "max_iter": 100}), indent=1))
    print(f"wrote merging instance (cars {args.cars}, seed {args.seed}) to {args.out}")
    return 0
