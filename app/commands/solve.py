"""`python -m app solve PROBLEM.json --out RESULT.json`: solve a game from a problem file."""
from __future__ import annotations

import json
import sys
import warnings

from app.cli import UserError
from fileio import atomic_write_text, check_output_path
from solver_cpp import Solver
from solver_cpp.limits import check_size, estimate_size
from solver_cpp.problem_file import load_problem, result_to_dict

DEFAULT_TIME_LIMIT_S = 60.0


def register(sub) -> None:
    p = sub.add_parser("solve", help="solve a game described in a JSON problem file (docs/problem-format.md)")
    p.add_argument("problem", help="problem file (JSON)")
    p.add_argument("--out", help="write the result here (JSON); default: print a summary only")
    p.add_argument("--time-limit", type=float, default=None, metavar="S",
                   help=f"solver time limit in seconds (default: the file's solver.time_limit, else "
                        f"{DEFAULT_TIME_LIMIT_S:g}; 0 = none)")
    p.add_argument("--allow-large", action="store_true",
                   help="solve even if the estimated memory or time per iteration exceeds the documented limits")
    p.set_defaults(func=run)


def run(args) -> int:
    import math

    if args.time_limit is not None and not (math.isfinite(args.time_limit) and args.time_limit >= 0):
        raise UserError(f"--time-limit must be a number of seconds >= 0, got {args.time_limit}")
    if args.out:
        check_output_path(args.out, stream=True)  # before the solve, not after it
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DeprecationWarning)
        problem, settings, warm = load_problem(args.problem)
    for w in caught:  # flat setting names of the previous release: shown to the user, who edits the file
        print(f"warning: {w.message}", file=sys.stderr)
    if not args.allow_large:
        try:
            check_size(estimate_size(problem))
        except ValueError as exc:
            raise UserError(f"{args.problem}: {exc} (docs/problem-format.md; --allow-large to solve anyway)") from None
    if args.time_limit is not None:
        settings["time_limit"] = args.time_limit
    else:
        settings.setdefault("time_limit", DEFAULT_TIME_LIMIT_S)
    try:
        solver = Solver(problem, **settings)  # the C++ set-up checks the settings' ranges
    except ValueError as exc:
        raise UserError(f"{args.problem}: {exc}") from None
    result = solver.solve(warm)
    print(f"status {result.status}  iterations {result.iterations}  |r| {result.residual_norm:.2e}  "
          f"max violation {result.max_violation:.2e}  solve time {1e3 * result.solve_time_s:.1f} ms")
    if args.out:
        atomic_write_text(args.out, json.dumps(result_to_dict(result)), stream=True)
        print(f"wrote {args.out}", file=sys.stderr)
    return 0 if result.converged else 1
