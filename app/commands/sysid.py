"""`python -m app sysid LOG ...` (model identification) and `python -m app sysid-generate ...`
(synthetic logs with hidden effects). Formats, method and results: docs/sysid.md."""
from __future__ import annotations

import dataclasses
import math
import shlex
import sys
import time
from pathlib import Path

from app.cli import UserError
from fileio import atomic_write_text, check_output_dir, check_output_path
from planning import PlannerConfig
from race.setup import RaceSpec
from sim import SimEffectsError
from sysid.generate import (CAMERA_HEADING_NOISE_RAD, CAMERA_POSITION_NOISE_M, ExcitationSettings, generate_log,
                            parse_effects, sim_effects)
from sysid.log import STEERING_UNITS, THROTTLE_UNITS, CommandUnits, LogFormatError, read_log, write_log_csv
from vehicles.params import CarParamsError, load_car_params, resolve_car_path, save_car_params


def register(sub) -> None:
    p = sub.add_parser("sysid", help="check the car model against a drive log; fit and write corrections")
    p.add_argument("log", nargs="+", help="drive log(s), one per run: .csv, a race recording .rrd (python -m app race "
                                         "--out ...); several runs of the same car are fitted jointly; docs/sysid.md")
    p.add_argument("--car-params", default="buzzracer", help="car file (or bare name in vehicles/); default buzzracer")
    p.add_argument("--report", required=True, help="Markdown report to write")
    p.add_argument("--json", help="JSON summary to write")
    p.add_argument("--params-out", help="car file with the identified corrections (default: <report stem>.toml "
                                        "next to the report)")
    p.add_argument("--figures", help="folder for the PNG plots (default: the report's folder)")
    p.add_argument("--car", type=int, help="car id in the log (needed when the log has several cars; in a race "
                                           "recording the marker id, in a simulated race 0 = rd3g, 1 = opponent)")
    p.add_argument("--horizon", type=float, default=1.0, help="prediction horizon in seconds (default 1.0)")
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap")
    p.add_argument("--fit-windows", type=int, default=300,
                   help="training windows per fit (default 300; fewer is faster and less precise)")
    p.add_argument("--block-length", type=float, default=None,
                   help="time blocks of the train/held-out split of one run, s (default duration/9 in [3, 10] s)")
    p.add_argument("--calibration-block", type=float, default=20.0, metavar="S",
                   help="with several runs: the run-level parameters of a held-out run are also calibrated on its "
                        "first S s and scored on the windows after them (default 20 s; docs/sysid.md)")
    p.add_argument("--heldout-run", action="append", default=None, metavar="LOG",
                   help="with several runs: a run (as given) to hold out whole; repeatable (default: every 3rd run "
                        "in content order, at least one)")
    p.add_argument("--steering-units", choices=STEERING_UNITS, default=None,
                   help="CSV logs: steering column as a wheel angle command in rad (default), the race link's "
                        "normalised command (x max_steering_rad) or a pulse width in us (the car file's [radio])")
    p.add_argument("--throttle-units", choices=THROTTLE_UNITS, default=None,
                   help="CSV logs: throttle column as normalised throttle (default), a pulse width in us, or a "
                        "speed set-point in m/s (a car file with [speed_control])")
    p.add_argument("--frame-period", type=float, default=None,
                   help="the pose sensor's frame period, s: time stamps are snapped to its clock (jittered arrival "
                        "times), rows on one frame merged; docs/sysid.md")
    p.set_defaults(func=run)

    g = sub.add_parser("sysid-generate", help="simulate a car with hidden effects and write an identification log")
    g.add_argument("--effects", default="", help='e.g. "steering_offset=0.03,actuation_delay=0.08" (names in '
                                                 "docs/sysid.md); empty for a clean log")
    g.add_argument("--minutes", type=float, default=5.0)
    g.add_argument("--out", required=True, help="CSV log to write")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--car-params", default="buzzracer", help="nominal car the effects are added to")
    g.add_argument("--track", default="oval", help="track name or file for tracks.load_track (default oval)")
    g.add_argument("--position-noise", type=float, default=None, help="camera position noise std [m] (default 0.002)")
    g.add_argument("--heading-noise", type=float, default=None, help="camera heading noise std [rad] (default 0.01)")
    g.add_argument("--rate", type=float, default=30.0, help="command and camera rate [Hz] (default 30)")
    g.add_argument("--driver", choices=("pursuit", "stanley"), default="pursuit",
                   help="the generator's driver: pure pursuit + PI speed (default) or Stanley + P speed")
    g.set_defaults(func=run_generate)

    b = sub.add_parser("sysid-bench", help="the generated identification cases of docs/sysid.md: verdicts, goals, timing")
    b.add_argument("--out", default="runs/sysid/bench", help="folder for the logs (reused when present), "
                                                             "bench.md and bench.json (default runs/sysid/bench)")
    b.add_argument("--cases", default="", help="case numbers, comma-separated (default all; list in docs/sysid.md)")
    b.add_argument("--minutes", type=float, default=5.0)
    b.add_argument("--rate", type=float, default=60.0, help="command and camera rate [Hz] (default 60)")
    b.add_argument("--car-params", default="buzzracer")
    b.set_defaults(func=run_bench)

    c = sub.add_parser("sysid-closed-loop",
                       help="race with nominal vs corrected car parameters while the simulator carries the effects")
    c.add_argument("--effects", required=True, help='hidden effects of the simulated cars, e.g. "steering_offset=0.03" '
                                                    "(names as in sysid-generate)")
    c.add_argument("--corrected", required=True, help="car file with the identified corrections (written by sysid)")
    c.add_argument("--car-params", default="buzzracer", help="nominal car file: the simulated car, and the planners' "
                                                             "car in the nominal runs (default buzzracer)")
    c.add_argument("--seeds", default="0,1,2", help="race seeds, comma-separated (default 0,1,2)")
    c.add_argument("--laps", type=int, default=1)
    c.add_argument("--track", default="oval")
    c.add_argument("--opponent", choices=("mpc", "pursuit"), default="mpc")
    c.add_argument("--max-time", type=float, default=None, help="stop each race after this many seconds of race time")
    c.add_argument("--json", help="JSON summary and per-race results to write")
    c.add_argument("--plot", help="PNG figure to write")
    c.add_argument("--recordings", help="keep the race recordings (.rrd) in this folder")
    c.set_defaults(func=run_closed_loop_command)


def run(args) -> int:
    # here, not at the top: these import scipy.signal (sysid.data), about 0.3 s on every CLI start
    from sysid.conventions import to_physical
    from sysid.data import build_runs, canonical_order
    from sysid.diagnose import SysidSettings, identify
    from sysid.report import (disagreement_notes, instability_notes, make_plots, markdown_report, other_cross_run_notes,
                              run_level_notes, write_json)

    if not args.horizon > 0:
        raise UserError(f"--horizon must be > 0, got {args.horizon}")
    if args.fit_windows < 20:
        raise UserError(f"--fit-windows must be >= 20, got {args.fit_windows}")
    for flag, value in (("--block-length", args.block_length), ("--frame-period", args.frame_period),
                        ("--calibration-block", args.calibration_block)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise UserError(f"{flag} must be a positive number of seconds, got {value}")
    started = time.perf_counter()
    for out, stream in ((args.report, False), (args.params_out or Path(args.report).with_suffix(".toml"), False),
                        (args.json, True)):
        if out:
            check_output_path(out, stream=stream)  # before the identification, not after it
    if args.figures:
        check_output_dir(args.figures)
    if len(set(args.log)) != len(args.log):
        raise UserError(f"a run is given twice: {sorted({a for a in args.log if args.log.count(a) > 1})[0]}")
    for run in args.heldout_run or ():
        if run not in args.log:
            raise UserError(f"--heldout-run {run}: not one of the runs given ({', '.join(args.log)})")
    car = load_car_params(args.car_params)
    car_source = str(resolve_car_path(args.car_params))
    units = None
    if args.steering_units or args.throttle_units:
        units = CommandUnits(steering=args.steering_units or "rad", throttle=args.throttle_units or "normalized")
    car_logs, notes = [], []
    for path in args.log:
        log = read_log(path, units)
        if args.car is None:
            if len(log.cars) > 1:
                raise UserError(f"{path}: the log has cars {log.describe_cars()}; choose one with --car")
            car_id = log.cars[0]
        else:
            car_id = args.car
        car_log = to_physical(log.select_car(car_id), car, car_source)
        if car_id in car_log.pose_sources:
            notes.append(f"car {car_id} ({car_log.car_labels.get(car_id, '?')}) of {path}; poses from "
                         f"{car_log.pose_sources[car_id]}")
            print(notes[-1])
        car_logs.append((path, car_id, car_log))
    ids = {car_id for _, car_id, _ in car_logs}
    if len(ids) > 1:
        first = car_logs[0]
        other = next(c for c in car_logs if c[1] != first[1])
        raise UserError(f"{other[0]}: runs of different cars: car {other[1]} here, car {first[1]} in {first[0]} "
                        "(choose one car with --car)")
    log_note = "; ".join(notes) or None
    try:
        logs = [c[2] for c in car_logs]
        order = canonical_order(logs)
        held = None
        if args.heldout_run:
            held = tuple(order.index(args.log.index(r)) for r in args.heldout_run)
        traj = build_runs(logs, frame_period=args.frame_period)
        result = identify(traj, car, SysidSettings(horizon_s=args.horizon, seed=args.seed,
                                                   fit_max_starts=args.fit_windows, block_s=args.block_length,
                                                   heldout_runs=held, calibration_s=args.calibration_block))
    except LogFormatError:
        raise  # names its file and row
    except ValueError as exc:  # the logs loaded but do not support the fit (too short, too few moving samples)
        raise UserError(f"{', '.join(args.log)}: {exc}") from None

    report = Path(args.report)
    params_out = Path(args.params_out) if args.params_out else report.with_suffix(".toml")
    out_car = dataclasses.replace(result.car_out, name=f"{car.name}-identified")
    save_car_params(out_car, params_out)
    figures = Path(args.figures) if args.figures else report.parent
    plots = make_plots(result, figures, f"sysid_{report.stem}")
    json_path = None
    if args.json:
        json_path = Path(args.json)
        write_json(result, json_path, str(params_out))
    command = "python -m app " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:2] == ["sysid"] else None
    atomic_write_text(report, markdown_report(result, ", ".join(args.log), str(resolve_car_path(args.car_params)), str(params_out),
                                              str(json_path) if json_path else None, plots, report.parent, command,
                                              log_note))
    elapsed = time.perf_counter() - started
    for note in (disagreement_notes(result) + instability_notes(result) + other_cross_run_notes(result)
                 + run_level_notes(result)):
        print(note)
    if result.selected:
        summary = ", ".join(f"{e.effect} ({100 * e.reduction_vs_nominal:.0f} %)" for e in result.selected)
        if result.unnamed_effect_remains:
            summary += " -- an effect the tool cannot name remains (`other`)"
    else:
        summary = "no significant effect"
    print(f"{summary}; held-out horizon position RMSE {100 * result.planner.heldout.horizon_pos_rmse_m:.1f} cm "
          f"(planner) / {100 * result.dynamic_nominal.heldout.horizon_pos_rmse_m:.1f} cm (nominal dynamic) -> "
          f"{100 * result.final.heldout.horizon_pos_rmse_m:.1f} cm ({100 * result.heldout_error_reduction:.0f} % "
          f"vs nominal dynamic); wrote {report}, {params_out}"
          + (f", {json_path}" if json_path else "") + f" in {elapsed:.1f} s")
    return 0


def run_generate(args) -> int:
    if not args.minutes > 0:
        raise UserError(f"--minutes must be > 0, got {args.minutes}")
    if not 1.0 <= args.rate <= 1000.0:
        raise UserError(f"--rate must be in [1, 1000] Hz, got {args.rate}")
    effects = parse_effects(args.effects)
    car = load_car_params(args.car_params)
    check_output_path(args.out)
    pos = CAMERA_POSITION_NOISE_M if args.position_noise is None else args.position_noise
    head = CAMERA_HEADING_NOISE_RAD if args.heading_noise is None else args.heading_noise
    started = time.perf_counter()
    log = generate_log(car, effects, args.minutes, args.seed, position_noise_m=pos, heading_noise_rad=head,
                       track=args.track, excitation=ExcitationSettings(control_rate_hz=args.rate),
                       driver=args.driver)
    out = Path(args.out)
    write_log_csv(out, log)
    print(f"wrote {out}: {log.t.size} rows, {log.t[-1] - log.t[0]:.1f} s, in {time.perf_counter() - started:.1f} s")
    return 0


def run_bench(args) -> int:
    import json

    # here, not at the top: these import scipy.signal (sysid.data), about 0.3 s on every CLI start
    from sysid.benchmark import CASES, markdown_table, run_benchmark
    from sysid.diagnose import SysidSettings

    try:
        picked = [int(v) for v in args.cases.split(",") if v.strip()] or list(range(1, len(CASES) + 1))
    except ValueError:
        raise UserError(f"--cases: expected case numbers like 1,3, got {args.cases!r}") from None
    bad = [i for i in picked if not 1 <= i <= len(CASES)]
    if bad:
        raise UserError(f"--cases: no case {bad[0]} (cases 1..{len(CASES)})")
    if not args.minutes > 0:
        raise UserError(f"--minutes must be > 0, got {args.minutes}")
    if not 1.0 <= args.rate <= 1000.0:
        raise UserError(f"--rate must be in [1, 1000] Hz, got {args.rate}")
    car = load_car_params(args.car_params)
    out = Path(args.out)

    def progress(o) -> None:
        verdict = ", ".join(e.effect for e in o.result.selected) or "no significant effect"
        print(f"case {CASES.index(o.case) + 1} ({o.case.name}): {verdict}; "
              f"{100 * o.result.heldout_error_reduction:.0f} % vs nominal dynamic; sysid {o.wall_s:.1f} s wall, "
              f"{o.cpu_s:.1f} s CPU (load {o.load:.1f}); {'goals met' if o.passed else 'FAILED: ' + '; '.join(o.failures)}",
              flush=True)

    outcomes = run_benchmark([CASES[i - 1] for i in picked], out, args.minutes, args.rate, car, SysidSettings(),
                             progress)
    table = markdown_table(outcomes)
    atomic_write_text(out / "bench.md", table)
    atomic_write_text(out / "bench.json", json.dumps([
        {"case": CASES.index(o.case) + 1, "name": o.case.name, "effects": o.case.effects,
         "other_terms": o.case.other_terms, "verdict": [e.effect for e in o.result.selected],
         "params": {k: v for e in o.result.selected for k, v in e.params.items()},
         "heldout_error_reduction": o.result.heldout_error_reduction, "wall_s": o.wall_s, "cpu_s": o.cpu_s,
         "load": o.load, "failures": o.failures} for o in outcomes], indent=2) + "\n")
    print(table)
    print(f"wrote {out / 'bench.md'}, {out / 'bench.json'}")
    return 0 if all(o.passed for o in outcomes) else 1


def run_closed_loop_command(args) -> int:
    import json

    import numpy as np

    # here, not at the top: these import scipy.signal (sysid.data), about 0.3 s on every CLI start
    from sysid.closed_loop import PLANNER_CAR, format_table, plot, run_closed_loop, summarize

    try:
        seeds = [int(v) for v in args.seeds.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"--seeds: expected integers like 0,1,2, got {args.seeds!r}") from None
    if not seeds:
        raise UserError("--seeds: give at least one seed")
    if args.json:
        check_output_path(args.json, stream=True)
    if args.plot:
        check_output_path(args.plot)
    if args.recordings:
        check_output_dir(args.recordings)
    if args.laps < 1:
        raise UserError(f"--laps must be at least 1, got {args.laps}")
    try:
        effects = sim_effects(parse_effects(args.effects, flag="--effects"), 0.0, 0.0)
    except SimEffectsError as exc:
        raise UserError(f"--effects: {exc}") from None
    cars = {}
    for flag, value in (("--car-params", args.car_params), ("--corrected", args.corrected)):
        try:
            cars[flag] = load_car_params(value)
        except CarParamsError as exc:
            raise UserError(f"{flag}: {exc}") from None
    if args.max_time is not None and not args.max_time > 0:
        raise UserError(f"--max-time must be positive, got {args.max_time}")
    race = RaceSpec(track=args.track, laps=args.laps, opponent=args.opponent, max_time_s=args.max_time)
    started = time.perf_counter()

    def progress(m) -> None:
        if m.error:
            print(f"  seed {m.seed:3d} {m.variant:9s} stopped: {m.error}", flush=True)
            return
        lap = "-" if m.rd3g_lap_time_s is None else f"{m.rd3g_lap_time_s:.3f} s"
        print(f"  seed {m.seed:3d} {m.variant:9s} winner {m.winner or '-':8s} RD3G lap {lap:8s} "
              f"progress {m.rd3g_progress_speed_mps:.3f} m/s "
              f"collisions {m.collisions} off-track {m.rd3g_off_track}", flush=True)

    races = run_closed_loop(cars["--car-params"], cars["--corrected"], effects, seeds, race,
                            Path(args.recordings) if args.recordings else None, progress)
    summary = summarize(races)

    cfg = PlannerConfig()
    print(format_table(summary, cfg.horizon * cfg.plan_dt_s, cfg.plan_dt_s))
    print(f"{len(races)} races in {time.perf_counter() - started:.0f} s")
    if args.json:
        def rms(a):
            return float(np.sqrt(np.mean(a ** 2))) if a.size else None

        out = Path(args.json)
        record = {
            "effects": args.effects, "corrected": args.corrected, "car_params": args.car_params, "seeds": seeds,
            "race": dataclasses.asdict(race), "planner_car": PLANNER_CAR,
            "summary": {k: v.json_dict() for k, v in summary.items()},
            "races": [{"variant": m.variant, "seed": m.seed, "winner": m.winner, "rd3g_lap_time_s": m.rd3g_lap_time_s,
                       "rd3g_progress_speed_mps": None if m.error else m.rd3g_progress_speed_mps,
                       "race_time_s": None if m.error else m.race_time_s, "collisions": m.collisions, "rd3g_at_fault": m.rd3g_at_fault,
                       "rd3g_off_track": m.rd3g_off_track, "fallbacks": m.fallbacks, "error": m.error,
                       "one_step_rmse_m": rms(m.one_step_errors_m), "horizon_rmse_m": rms(m.horizon_errors_m)}
                      for m in races],
        }
        atomic_write_text(out, json.dumps(record, indent=2) + "\n", stream=True)
        print(f"wrote {out}")
    if args.plot:
        print(f"wrote {plot(races, summary, f'{args.effects}: nominal vs corrected ({Path(args.corrected).name})', Path(args.plot), cfg.plan_dt_s)}")
    return 0
