"""`python -m app bench ...`: benchmarks (results in docs/benchmarks.md). Every benchmark is a subcommand here;
the modules that own their options (`add_arguments(parser)`, `run(args)`) are listed in MODULE_BENCHES."""
from __future__ import annotations

import json
import math
import shlex
import sys
import time

from app.cli import UserError
from app.realtime import bench as loop_bench
from app.realtime import live_bench
from fileio import atomic_write_text, check_output_dir, check_output_path
from bench import (baselines, camera_profiles, charuco_coverage, merge_bench, planner_threads, problem_size,
                   race_perturbations, saddles, solver_bench, time_limit, track_video, tracking_bench)
from bench.families import FAMILIES, family_names
from bench.report import machine_description, write_section
from solver_cpp import make_settings, merge_settings


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


# (name, module, help) of the benchmarks whose module defines its options and its run.
MODULE_BENCHES = [
    ("loop", loop_bench, "HIL loop: the same seeds as pure simulation and as --hil races (rate, deadline misses, "
                         "stage timings, tracking error, winners)"),
    ("live-view", live_bench, "HIL races without and with --viewer (a local headless Rerun server): the viewer's "
                              "cost on the loop's tick time"),
    ("race-perturbations", race_perturbations, "simulated races with the loop's control-path imperfections (late "
                                               "commands, neutral pulses, solver cap): which change the winners"),
    ("planner-threads", planner_threads, "simulated fleet races planned in turn and in a thread pool: per-planner "
                                         "and per-control-period times, identical races"),
    ("baselines", baselines, "RD3G, iLQGames and ALGames on merging seeds: convergence count and median time"),
    ("time-limit", time_limit, "how well the solver's time_limit holds, per linear-solver path"),
    ("tracking", tracking_bench, "rendering, marker detection and EKF update times on synthetic frames"),
    ("track-video", track_video, "python -m app track on a rendered 1280x800 clip of cars on known trajectories: "
                                 "frames per second and pose errors"),
    ("camera-profiles", camera_profiles, "HIL camera profiles (sim/camera_profile.py): tracking error of each "
                                         "realistic effect alone and of all together (docs/tracking.md)"),
    ("charuco", charuco_coverage, "calibrate-camera on rendered ChArUco views with known intrinsics: largest errors "
                                  "and how often the reported standard deviations cover them"),
]


def register(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark and record it in docs/benchmarks.md")
    kinds = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    s = kinds.add_parser("solver", help="RD3G on merging games for each linear-solver option")
    s.add_argument("--cars", default="2-8")
    s.add_argument("--instances", type=int, default=50)
    s.add_argument("--linear-solvers", default="riccati,sparse_lu,lscg,sparse_qr")
    s.add_argument("--time-limit", type=float, default=5.0, help="per solve, seconds")
    s.add_argument("--no-docs", action="store_true", help="print only; do not update docs/benchmarks.md")
    s.set_defaults(func=run_solver)

    m = kinds.add_parser("merge", help="RD3G vs iLQGames vs ALGames on the paper's merging games (Table I)")
    m.add_argument("--cars", default="2-8")
    m.add_argument("--instances", type=int, help="seeds 0..N-1, or --seed-start..+N-1 (default 100)")
    m.add_argument("--seeds", metavar="A:B", help="seeds A..B-1 (instead of --instances/--seed-start)")
    m.add_argument("--seed-start", type=int, help="first seed of --instances (default 0)")
    m.add_argument("--max-iter", type=int, help="RD3G's max_iter per solve (default: the solver's, "
                                                 "solver_cpp/include/rd3g/problem.hpp)")
    m.add_argument("--rd3g-setting", action="append", default=[], metavar="NAME=VALUE",
                   help="override one RD3G setting (solver_cpp/include/rd3g/problem.hpp), e.g. domain_fraction=0 or "
                        "stall.window=8 (GROUP.FIELD); "
                        "repeatable")
    m.add_argument("--solvers", help="comma-separated (default: rd3g,ilqgames,algames; rd3g with --family)")
    m.add_argument("--family", help="run seeded game families instead of the Table I comparison: comma-separated names "
                                    "from bench/families.py (docs/merging.md) or the groups 'tuned' (the six the "
                                    "defaults were tuned on), 'held-out' or 'all'; reports success, second-order "
                                    "confirmation, time and iteration tails per family and size")
    m.add_argument("--workers", type=int, default=2, help="processes (each solve runs on one core)")
    m.add_argument("--time-limit", type=float, default=5.0, help="per solve, seconds (same for every solver); 0 = "
                                                                  "none, so results do not depend on machine load")
    m.add_argument("--best-response-rounds", type=int, default=0,
                   help="with --family: start RD3G from this many rounds of iterated best response "
                        "(solver_cpp/best_response.py, the C++ sweeps of the solver's best_response_rounds restart; its time "
                        "counts; the restarts start from it too)")
    m.add_argument("--best-response-check", type=int, default=-1, metavar="STARTS",
                   help="with --family: check every solved RD3G result by each player's SLSQP best response "
                        "(bench/verify.py) from the result and STARTS seeded perturbations of it (0: from the result "
                        "only); a player lowering its cost by more than 1e-3 of it refutes the equilibrium; not timed")
    m.add_argument("--steering-bound", type=float, metavar="RAD",
                   help="with --family: bound every car's steering at |delta| <= RAD as well (the tighter of it and "
                        "the family's own bound): a variant of the families, for asking what a physical steering "
                        "limit changes; none by default")
    m.add_argument("--repeat", type=int, default=3,
                   help="run each solve faster than 200 ms CPU (and than a tenth of --time-limit) up to this many "
                        "times and report its fastest run's times (the results are identical; the noise of a shared "
                        "machine is not)")
    m.add_argument("--json", help="write the per-solver, per-size figures here")
    m.add_argument("--figures", help="folder for the PNG figures (default: docs/figures, none with --no-docs)")
    m.add_argument("--no-docs", action="store_true", help="do not update docs/benchmarks.md")
    m.set_defaults(func=run_merge)

    d = kinds.add_parser("saddles", help="steering away from saddles: the methods compared on the family instances "
                                         "that converge to a saddle")
    d.add_argument("--family", default="tuned", help="comma-separated names from bench/families.py, or the groups "
                                                     "'tuned', 'held-out', 'all'")
    d.add_argument("--cars", default="2-8")
    d.add_argument("--seeds", type=int, default=16, help="seeds 0..N-1 per family and size")
    d.add_argument("--cases", help="skip the scan: FAMILY:CARS:SEED,... (e.g. head-on:2:2)")
    d.add_argument("--methods", default=",".join(saddles.METHODS), help="comma-separated, from bench/saddles.py")
    d.add_argument("--best-response", type=int, default=6, help="SLSQP best-response test on the first N cases")
    d.add_argument("--workers", type=int, default=2, help="processes (each solve runs on one core)")
    d.add_argument("--json", help="write the per-run records here")
    d.add_argument("--no-docs", action="store_true", help="do not update docs/benchmarks.md")
    d.set_defaults(func=run_saddles)

    z = kinds.add_parser("size", help="measured memory and time per iteration vs the problem-size estimate")
    z.add_argument("--no-docs", action="store_true", help="print only; do not update docs/benchmarks.md")
    z.set_defaults(func=run_size)

    f = kinds.add_parser("fuzz", help="property-based fuzzing of a loader, the frame decoder or the solver API")
    f.add_argument("--target", required=True, help="problem, car, track, fixed_markers, intrinsics, calibration, "
                                                   "sysid_csv, rd3g_decoder, link_capture, solver_api")
    f.add_argument("--examples", type=int, default=100_000, help="generated inputs (default 100000)")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--out", default="runs/fuzz", help="folder for reproducer files of failures")
    f.add_argument("--replay", metavar="FILE", help="run the target on one reproducer file instead")
    f.add_argument("--no-docs", action="store_true", help="print only; do not update docs/benchmarks.md")
    f.set_defaults(func=run_fuzz)

    for name, module, text in MODULE_BENCHES:
        b = kinds.add_parser(name, help=text, description=text)
        module.add_arguments(b)
        b.set_defaults(func=module.run)

    g = kinds.add_parser("malformed", help="the project's real files, mutated by hand-written rules, through the "
                                           "command line (app/malformed_cli.py, docs/file-formats.md)")
    g.add_argument("--formats", default="all", help="comma-separated, or all: problem, car, track, fixed_markers, "
                                                    "intrinsics, calibration, sysid_csv, link_capture, recording, mocap_survey")
    g.add_argument("--per-format", type=int, default=0, help="at most this many cases per format (0 = all)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--offsets", type=int, default=40, help="truncation offsets per file")
    g.add_argument("--workdir", help="keep the failures' inputs here (default: a temporary folder)")
    g.add_argument("--json", help="write the report here")
    g.add_argument("--verbose", action="store_true")
    g.set_defaults(func=run_malformed)


def run_solver(args) -> int:
    cars = parse_range(args.cars)
    options = [x.strip() for x in args.linear_solvers.split(",") if x.strip()]
    for o in options:
        if o not in ("riccati", "sparse_lu", "lscg", "sparse_qr"):
            raise UserError(f"--linear-solvers: unknown option {o!r} (riccati, sparse_lu, lscg, sparse_qr)")
    if args.instances < 1:
        raise UserError("--instances must be at least 1")
    t0 = time.perf_counter()
    rows = solver_bench.run(cars, args.instances, options, args.time_limit)
    command = "python -m app " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:2] == ["bench"] else \
        f"python -m app bench solver --cars {args.cars} --instances {args.instances} --linear-solvers {args.linear_solvers}"
    md = solver_bench.markdown(rows, command, machine_description(), time.perf_counter() - t0)
    print(md)
    if not args.no_docs:
        print(f"\nrecorded in {write_section('solver-bench-' + '-'.join(options), md)}")
    return 0


SEED_MAX = 2**32 - 1  # numpy RandomState's seed range


def parse_seeds(args) -> list[int]:
    """The seeds of a `bench merge` run: --seeds A:B (A..B-1), or --instances N from --seed-start S (default 100
    from 0)."""
    if args.seeds is not None:
        if args.instances is not None or args.seed_start is not None:
            raise UserError("--seeds replaces --instances and --seed-start; give one or the other")
        try:
            a, b = (int(v) for v in args.seeds.split(":"))
        except ValueError:
            raise UserError(f"--seeds must look like A:B (seeds A..B-1), got {args.seeds!r}") from None
        if not 0 <= a < b <= SEED_MAX + 1:
            raise UserError(f"--seeds A:B needs 0 <= A < B <= 2^32, got {args.seeds!r}")
        return list(range(a, b))
    n = 100 if args.instances is None else args.instances
    start = 0 if args.seed_start is None else args.seed_start
    if n < 1:
        raise UserError("--instances must be at least 1")
    if not 0 <= start <= SEED_MAX + 1 - n:
        raise UserError(f"--seed-start must be in 0..2^32 - N (N = --instances), got {start}")
    return list(range(start, start + n))


def _merge_options(args, default_solvers: str) -> tuple[list[str], list[int]]:
    """The solvers and seeds of a `bench merge` run, with its budgets, counts and --json path checked before the
    long run."""
    solvers = [x.strip() for x in (args.solvers or default_solvers).split(",") if x.strip()]
    for s in solvers:
        if s not in merge_bench.SOLVERS:
            raise UserError(f"--solvers: unknown solver {s!r} (choose from {', '.join(merge_bench.SOLVERS)})")
    seeds = parse_seeds(args)
    if args.workers < 1:
        raise UserError("--workers must be at least 1")
    if not args.time_limit >= 0 or args.time_limit == float("inf"):
        raise UserError(f"--time-limit must be a finite number of seconds >= 0 (0 = none), got {args.time_limit}")
    if args.max_iter is not None and not 1 <= args.max_iter < 2**31:
        raise UserError(f"--max-iter must be an integer from 1 to 2^31 - 1, got {args.max_iter}")
    args.rd3g_settings = _rd3g_settings(args.rd3g_setting)
    if args.json:
        check_output_path(args.json, stream=True)  # fail before the long run, not after it
    if getattr(args, "figures", None):
        check_output_dir(args.figures)
    return solvers, seeds


def _rd3g_settings(items: list[str]) -> tuple:
    """--rd3g-setting NAME=VALUE items (NAME grouped as GROUP.FIELD, e.g. stall.window, or top-level, e.g. tol) as
    (name, value) pairs in make_settings' grouped form (a group's value a dict), checked by solver_cpp.make_settings
    (values parsed as JSON where they can be: numbers, true/false; else kept as strings, e.g. enum names)."""
    pairs = []
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name.strip():
            raise UserError(f"--rd3g-setting: {item!r} is not NAME=VALUE")
        try:
            value = json.loads(text)
        except ValueError:
            value = text
        group, dot, field_name = name.strip().partition(".")
        pairs.append({group: {field_name: value}} if dot else {group: value})
    grouped = merge_settings(*pairs)
    try:
        make_settings(**grouped)
    except ValueError as exc:
        raise UserError(f"--rd3g-setting: {exc}") from None
    return tuple(grouped.items())


def _repeats(args) -> int:
    """Runs per short solve (--repeat; bench.merge_bench.REPEAT_BELOW_MS)."""
    if args.repeat < 1:
        raise UserError("--repeat must be >= 1")
    return args.repeat


def run_merge(args) -> int:
    from pathlib import Path

    cars = parse_range(args.cars)
    if args.family:
        return _run_families(args, cars)
    if args.steering_bound is not None:
        raise UserError("--steering-bound applies to --family runs only (the Table I games are the authors')")
    solvers, seeds = _merge_options(args, default_solvers="rd3g,ilqgames,algames")
    t0 = time.perf_counter()
    records = merge_bench.run(solvers, cars, seeds, args.workers, args.time_limit, max_iter=args.max_iter,
                              settings=args.rd3g_settings, repeats=_repeats(args))
    summary = merge_bench.summarize(records)
    # --no-docs leaves the repository untouched, the committed figures included.
    fig_dir = Path(args.figures) if args.figures else None if args.no_docs else Path("docs/figures")
    figures = []
    if fig_dir is not None:
        check_output_dir(fig_dir)
        figures = [merge_bench.plot_times(summary, str(fig_dir / "merge_times.png")),
                   merge_bench.plot_merge(3, 1, str(fig_dir / "merge_3cars.png")),
                   merge_bench.plot_merge(8, 1, str(fig_dir / "merge_8cars.png"))]
    command = "python -m app " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    docs_rel = [str(Path(f).resolve().relative_to(Path("docs").resolve())) if Path(f).resolve().is_relative_to(Path("docs").resolve()) else f
                for f in figures]
    md = merge_bench.markdown(summary, command, machine_description(), time.perf_counter() - t0, docs_rel)
    print(md)
    for r in summary:
        print(f"{r['solver']:9s} {r['cars']} cars: {r['converged']}/{r['instances']} successful")
    if args.json:
        atomic_write_text(args.json, json.dumps(merge_bench.records_json(summary), indent=1), stream=True)
        print(f"wrote {args.json}")
    if not args.no_docs:
        print(f"recorded in {write_section('merge-bench-' + '-'.join(solvers), md)}")
    return 0


def run_fuzz(args) -> int:
    from pathlib import Path

    try:  # bench.fuzz needs hypothesis, an optional extra (.[test])
        from bench import fuzz
    except ImportError as exc:
        raise UserError(f"bench fuzz needs hypothesis (pip install -e '.[test]'): {exc}") from None

    names = [*fuzz.TARGETS, "solver_api"]
    if args.target not in names:
        raise UserError(f"--target: unknown target {args.target!r} (choose from {', '.join(names)})")
    if args.replay:
        try:
            print(fuzz.replay(args.target, Path(args.replay)))
        except fuzz.FuzzFailure as exc:
            print(f"failure: {exc}")
            return 1
        return 0
    if args.examples < 1:
        raise UserError("--examples must be at least 1")
    check_output_dir(args.out)
    report = fuzz.campaign(args.target, args.examples, args.seed, Path(args.out))
    command = "python -m app " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:2] == ["bench"] else \
        f"python -m app bench fuzz --target {args.target} --examples {args.examples} --seed {args.seed}"
    md = fuzz.markdown(report, command, machine_description())
    print(md)
    for failure in report["failures"]:
        print(f"failure (reproduce: python -m app bench fuzz --target {args.target} --replay FILE): {failure}")
    if not args.no_docs:
        print(f"recorded in {write_section('fuzz-' + args.target, md)}")
    return 1 if report["failures"] else 0


def run_malformed(args) -> int:
    try:  # app.malformed_cli renders TOML with bench.fuzz, which needs hypothesis (an optional extra, .[test])
        from app import malformed_cli
    except ImportError as exc:
        raise UserError(f"bench malformed needs hypothesis (pip install -e '.[test]'): {exc}") from None
    return malformed_cli.command(args)


def run_size(args) -> int:
    import os

    load = os.getloadavg()
    rows = problem_size.run()
    md = problem_size.markdown(rows, "python -m app bench size", machine_description(), load)
    print(md)
    if not args.no_docs:
        print(f"recorded in {write_section('problem-size', md)}")
    return 0


def _family_names(text: str) -> list[str]:
    try:
        return family_names(text)
    except ValueError as exc:
        raise UserError(f"--family: {exc}") from None


def _families_section(args, solvers: list[str], steering_bound: float) -> str:
    """The docs/benchmarks.md block a family run writes: one per family selection (the tuned group keeps the bare
    name), solver set, best-response start and steering bound, so that the tuned and held-out tables, and a variant
    of either, do not overwrite each other."""
    selection = "-".join(part.strip() for part in args.family.split(",") if part.strip())
    return ("merge-families" + ("" if selection == "tuned" else f"-{selection}")
            + ("" if solvers == ["rd3g"] else "-" + "-".join(solvers))
            + (f"-best-response-{args.best_response_rounds}" if args.best_response_rounds else "")
            + ("" if math.isinf(steering_bound) else f"-steering-bound-{steering_bound:g}"))


def _run_families(args, cars: list[int]) -> int:
    from pathlib import Path

    names = _family_names(args.family)
    solvers, seeds = _merge_options(args, default_solvers="rd3g")
    import os

    if args.best_response_rounds < 0:
        raise UserError("--best-response-rounds must be >= 0")
    if args.best_response_check < -1:
        raise UserError("--best-response-check must be >= 0 (or -1: off)")
    steering_bound = math.inf if args.steering_bound is None else args.steering_bound
    if not steering_bound > 0:
        raise UserError(f"--steering-bound must be > 0 rad, got {args.steering_bound}")
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    repeats = _repeats(args)
    records = merge_bench.run(solvers, cars, seeds, args.workers, args.time_limit, tuple(names),
                              args.best_response_rounds, max_iter=args.max_iter, settings=args.rd3g_settings,
                              repeats=repeats, best_response_check=args.best_response_check,
                              steering_bound=steering_bound)
    summary = merge_bench.summarize_families(records)
    command = "python -m app " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    machine = f"{machine_description()}; 1-min load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end"
    budget = merge_bench.budget_text(args.max_iter, args.time_limit)
    md = merge_bench.family_markdown(summary, command, machine, time.perf_counter() - t0, args.best_response_rounds,
                                     budget, repeats)
    goal = None
    if len(solvers) > 1 and "rd3g" in solvers:  # the speed goal compares RD3G with the baselines
        if args.time_limit > 0:
            goal = merge_bench.speed_goal(records, args.time_limit)
            md += "\n" + "\n".join(merge_bench.speed_goal_markdown(goal, args.time_limit))
        else:
            md += ("\n\nSpeed goal: not evaluated (it counts every failure as the time limit; give --time-limit "
                   "above 0).")
    print(md)
    if args.json:
        failed = [f for r in summary for f in r["failed_instances"]]
        meta = {"max_iter": args.max_iter, "time_limit_s": args.time_limit, "seeds": [seeds[0], seeds[-1] + 1],
                "load_average_start": load0, "load_average_end": os.getloadavg()[0],
                "rd3g_settings": dict(args.rd3g_settings), "repeats": repeats,
                "steering_bound_rad": None if math.isinf(steering_bound) else steering_bound}
        atomic_write_text(args.json, json.dumps({"results": summary, "budget": meta, "failed_instances": failed,
                                                 "speed_goal": goal}, indent=1))
        print(f"wrote {args.json}")
    if not args.no_docs:
        print(f"recorded in {write_section(_families_section(args, solvers, steering_bound), md)}")
    return 0


def _parse_cases(text: str) -> list[tuple[str, int, int]]:
    cases = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        try:
            family, cars, seed = part.split(":")
            case = (family, int(cars), int(seed))
        except ValueError:
            raise UserError(f"--cases: {part!r} is not FAMILY:CARS:SEED") from None
        if family not in FAMILIES:
            raise UserError(f"--cases: unknown family {family!r} (choose from {', '.join(FAMILIES)})")
        if case[1] < 2 or case[2] < 0:
            raise UserError(f"--cases: {part!r} needs at least 2 cars and a seed >= 0")
        cases.append(case)
    if not cases:
        raise UserError("--cases is empty")
    return cases


def run_saddles(args) -> int:
    import dataclasses
    import os

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in saddles.METHODS:
            raise UserError(f"--methods: unknown method {m!r} (choose from {', '.join(saddles.METHODS)})")
    if args.seeds < 1 or args.workers < 1 or args.best_response < 0:
        raise UserError("--seeds and --workers must be >= 1, --best-response >= 0")
    if args.json:
        check_output_path(args.json, stream=True)  # fail before the long run, not after it
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    if args.cases:
        cases = _parse_cases(args.cases)
        scanned = None
    else:
        names = _family_names(args.family)
        grid = [(f, n, s) for f in names for n in parse_range(args.cars) for s in range(args.seeds)]
        scanned = len(grid)
        cases = saddles.scan(grid, args.workers)
        print("cases:", ",".join(f"{f}:{n}:{s}" for f, n, s in cases))
    if not cases:
        print("no instance converged to a saddle")
        return 0
    runs = saddles.compare(cases, methods, args.workers, args.best_response)
    summary = saddles.summarize(runs, methods)
    command = "python -m app " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    machine = f"{machine_description()}; 1-min load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end"
    md = saddles.markdown(summary, runs, command, machine, time.perf_counter() - t0, scanned)
    print(md)
    if args.json:
        atomic_write_text(args.json, json.dumps([dataclasses.asdict(r) for r in runs], indent=1), stream=True)
        print(f"wrote {args.json}")
    if not args.no_docs:
        print(f"recorded in {write_section('saddles', md)}")
    return 0
