"""`python -m app solve PROBLEM.json --out RESULT.json`: solve a game from a problem file."""
from __future__ import annotations

import json
import sys

from app.cli import UserError


def register(sub) -> None:
    p = sub.add_parser("solve", help="solve a game described in a JSON problem file (docs/problem-format.md)")
    p.add_argument("problem", help="problem file (JSON)")
    p.add_argument("--out", help="write the result here (JSON); default: print a summary only")
    p.set_defaults(func=run)


def run(args) -> int:
    from solver_cpp import Solver
    from solver_cpp.problem_file import ProblemFileError, load_problem, result_to_dict

    try:
        problem, settings, warm = load_problem(args.problem)
    except ProblemFileError as exc:
        raise UserError(str(exc)) from None
    result = Solver(problem, **settings).solve(warm)
    print(f"status {result.status}  iterations {result.iterations}  |r| {result.residual_norm:.2e}  "
          f"max violation {result.max_violation:.2e}  solve time {1e3 * result.solve_time_s:.1f} ms")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result_to_dict(result), f)
        print(f"wrote {args.out}", file=sys.stderr)
    return 0 if result.converged else 1
