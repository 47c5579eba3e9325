"""`python -m app bench ...`: benchmarks (results in docs/benchmarks.md)."""
from __future__ import annotations

import shlex
import sys
import time

from app.cli import UserError


def parse_range(text: str) -> list[int]:
    """'2-8' -> [2..8], '2,4,8' -> [2, 4, 8]."""
    out: list[int] = []
    try:
        for part in text.split(","):
            if "-" in part:
                a, b = part.split("-")
                out += list(range(int(a), int(b) + 1))
            else:
                out.append(int(part))
    except ValueError:
        raise UserError(f"--cars must look like 2-8 or 2,3,5, got {text!r}") from None
    if not out or min(out) < 2:
        raise UserError("--cars needs car counts of at least 2")
    return out


def register(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark and record it in docs/benchmarks.md")
    kinds = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    s = kinds.add_parser("solver", help="RD3G on merging games for each linear-solver option")
    s.add_argument("--cars", default="2-8")
    s.add_argument("--instances", type=int, default=50)
    s.add_argument("--linear-solvers", default="sparse_lu,lscg,sparse_qr")
    s.add_argument("--time-limit", type=float, default=5.0, help="per solve, seconds")
    s.add_argument("--no-docs", action="store_true", help="print only; do not update docs/benchmarks.md")
    s.set_defaults(func=run_solver)


def run_solver(args) -> int:
    from bench import solver_bench
    from bench.report import machine_description, write_section

    cars = parse_range(args.cars)
    options = [x.strip() for x in args.linear_solvers.split(",") if x.strip()]
    for o in options:
        if o not in ("sparse_lu", "lscg", "sparse_qr"):
            raise UserError(f"--linear-solvers: unknown option {o!r} (sparse_lu, lscg, sparse_qr)")
    if args.instances < 1:
        raise UserError("--instances must be at least 1")
    t0 = time.perf_counter()
    rows = solver_bench.run(cars, args.instances, options, args.time_limit)
    command = "python -m app " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:2] == ["bench"] else \
        f"python -m app bench solver --cars {args.cars} --instances {args.instances} --linear-solvers {args.linear_solvers}"
    md = solver_bench.markdown(rows, command, machine_description(), time.perf_counter() - t0)
    print(md)
    if not args.no_docs:
        print(f"\nrecorded in {write_section('solver-bench', md)}")
    return 0
