"""`python -m app race`: one simulated race, RD3G vs the MPC opponent (or pure pursuit), or a fleet of 2
to 6 cars (--cars, --roster); docs/racing.md."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from app.cli import UserError
from app.live_view import add_live_arguments, announce, live_view
from app.race_plots import plot_grid
from app.realtime.run import add_realtime_arguments, open_capture, plan_link, run_realtime, wants_realtime
from fileio import atomic_write_text, check_output_path
from planning.config import LINES
from race.roster import RosterError, RosterFileError, load_roster, parse_cars
from race.setup import GRIDS, OPPONENTS, SPEED_MODELS, STARTS, RaceSetupError, RaceSpec
from race.simulation import run_race
from sim import Simulator
from vehicles.link_capture import SimulatedLink

DEFAULT_OUT = "runs/race.rrd"


# The flag of each RaceSpec field, for error messages.
FLAGS = {"track": "--track", "car_params": "--car-params", "seed": "--seed", "laps": "--laps", "opponent": "--opponent",
         "start": "--start", "rd3g_top_speed_mps": "--rd3g-speed", "opponent_top_speed_mps": "--opponent-speed",
         "control_hz": "--control-hz", "control_period_s": "--control-hz", "raceline_ey_m": "--raceline-ey",
         "max_time_s": "--max-time", "sim_car_params": "--sim-car-params", "sim_effects": "--sim-effects",
         "roster": "--cars/--roster", "grid": "--grid", "game_players": "--game-players",
         "speed_model": "--speed-model", "planner_threads": "--planner-threads", "line": "--line",
         "lateral_clearance_m": "--lateral-clearance"}


def add_race_arguments(p) -> None:
    """The race options `race`, `batch` and the benches share; defaults from race.setup.RaceSpec."""
    p.add_argument("--track", default=RaceSpec.track, help=f"track name or file (default: {RaceSpec.track})")
    p.add_argument("--car-params", default=RaceSpec.car_params,
                   help=f"car parameter file for both cars (default: {RaceSpec.car_params})")
    p.add_argument("--opponent", choices=OPPONENTS, default=RaceSpec.opponent)
    p.add_argument("--rd3g-speed", type=float, default=RaceSpec.rd3g_top_speed_mps, help="RD3G car's top speed (m/s)")
    p.add_argument("--opponent-speed", type=float, default=RaceSpec.opponent_top_speed_mps, help="opponent's top speed (m/s)")
    p.add_argument("--speed-model", choices=SPEED_MODELS, default=RaceSpec.speed_model,
                   help="how the two cars' speeds differ: limits = the slower car has a lower hard top speed, "
                        "standing start (default); preference = the authors' code: one hard top speed (the "
                        "higher one), soft speed references 1.1 / 1.0 m/s in the cost for the faster / slower "
                        "car, rolling start at those speeds (docs/racing.md)")
    p.add_argument("--control-hz", type=float, default=RaceSpec.control_hz,
                   help=f"control rate (default {RaceSpec.control_hz:g} Hz)")
    p.add_argument("--raceline-ey", type=float, default=RaceSpec.raceline_ey_m, metavar="M",
                   help="with --line centre, lateral reference of both cars' racing cost (m, left positive; default 0, the centre line); "
                        "on the oval 0.05 (inside) won more slow-car races but had one RD3G-at-fault contact in "
                        "400 batch races (docs/racing.md)")
    p.add_argument("--line", choices=LINES, default=RaceSpec.line,
                   help=f"the reference both model planners race (default: {RaceSpec.line}): racing = the track's "
                        "racing line, its offset and speed profile at every horizon stage; centre = the constant "
                        "--raceline-ey and top speed with a cornering cap (docs/racing.md)")
    p.add_argument("--lateral-clearance", type=float, default=RaceSpec.lateral_clearance_m, metavar="M",
                   help="side by side, the planners keep the cars' centres at least this far apart (m) when it is "
                        "more than the footprint distance (2 radii + 2 cm, 0.195 m for buzzracer), which they keep "
                        f"along the track; 0 = the footprint distance (default {RaceSpec.lateral_clearance_m:g}; "
                        "docs/racing.md)")


def add_fleet_arguments(p, roster_file: bool = True,
                        grid_default: str = "roster for --cars/--roster; without them the two-car race starts "
                                            "in single file, --start") -> None:
    """--cars / --roster / --grid / --game-players: a fleet race (docs/racing.md, "Fleet races")."""
    fleet = p.add_mutually_exclusive_group() if roster_file else p
    fleet.add_argument("--cars", metavar="PLANNERS",
                       help="a fleet race of 2-6 cars, one planner each (rd3g, mpc, pursuit, human), e.g. "
                            "rd3g,mpc,mpc,pursuit; names are planner + position (rd3g1, mpc2, ...). Replaces "
                            "--opponent/--start/--rd3g-speed/--opponent-speed (docs/racing.md, Fleet races)")
    if roster_file:
        fleet.add_argument("--roster", metavar="FILE.toml",
                           help="a fleet race from a roster file, one [[car]] table per car (docs/file-formats.md)")
    p.add_argument("--grid", choices=GRIDS[1:], default=None,
                   help=f"start grid of rows of two: slots in roster order or shuffled by the seed (default {grid_default})")
    p.add_argument("--game-players", type=int, default=RaceSpec.game_players, metavar="N",
                   help=f"players in each RD3G car's game: itself and its nearest cars within reach of the horizon; "
                        f"further cars are constant-speed obstacles (a car inside a player's collision distance plays too); "
                        f"0: every car within reach "
                        f"(default {RaceSpec.game_players})")
    p.add_argument("--planner-threads", type=int, default=RaceSpec.planner_threads, metavar="N",
                   help=f"threads planning the cars of one control step; each car's plan is the same whatever the "
                        f"count (default {RaceSpec.planner_threads}; 1: in turn; docs/racing.md, Fleet races)")


def register(sub) -> None:
    p = sub.add_parser("race", help="simulate one race RD3G vs MPC and record telemetry (rerun .rrd)")
    p.add_argument("--laps", type=int, default=RaceSpec.laps)
    p.add_argument("--seed", type=int, default=RaceSpec.seed)
    p.add_argument("--start", choices=STARTS, default=RaceSpec.start, help="where the RD3G car starts")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"rerun recording (default {DEFAULT_OUT})")
    p.add_argument("--json", help="also write the race summary as JSON here")
    p.add_argument("--max-time", type=float, default=None,
                   help="give up after this many seconds of race time (default 30 s per lap + 30 s)")
    add_race_arguments(p)
    add_fleet_arguments(p)
    p.add_argument("--grid-plot", metavar="FILE.png", help="draw this race's start grid as a PNG and exit (no race)")
    # --- closing the model-identification loop (docs/sysid.md): the planners use --car-params (e.g. a
    # file written by `sysid`), the simulator runs the physical car below
    p.add_argument("--sim-car-params", default=None,
                   help="car file the simulator runs (default: --car-params); pure simulation only")
    p.add_argument("--sim-effects", default="",
                   help='hidden effects the simulator adds to both cars, e.g. "steering_offset=0.03,actuation_delay=0.08" '
                        "(names as in sysid-generate, docs/sysid.md); pure simulation only")
    # --- end closing the loop
    # --- real-time race stack (race/, app/realtime, docs/race-stack.md): --hil / --camera --serial --calibration
    add_realtime_arguments(p)
    # --- end real-time race stack
    add_live_arguments(p)
    p.set_defaults(func=run)


def roster_of(args):
    """The roster of --cars or --roster (None without either); UserError naming the flag, car and field."""
    try:
        if getattr(args, "cars", None):
            return parse_cars(args.cars)
        if getattr(args, "roster", None):
            return load_roster(args.roster)
    except RosterError as exc:
        raise UserError(f"--cars: {exc}") from None
    except RosterFileError as exc:
        raise UserError(f"--roster: {exc}") from None
    return None


def race_spec(args, seed: int, start: str, rd3g_speed: float, opponent_speed: float, laps: int = 1,
              max_time=None) -> RaceSpec:
    """The RaceSpec of parsed race options (batch's arguments have no --raceline-ey/--sim-* of their own)."""
    return RaceSpec(roster=roster_of(args), grid=getattr(args, "grid", None),
                    game_players=getattr(args, "game_players", RaceSpec.game_players),track=args.track, car_params=args.car_params, seed=seed, laps=laps, opponent=args.opponent,
                    start=start, rd3g_top_speed_mps=rd3g_speed, opponent_top_speed_mps=opponent_speed,
                    control_hz=args.control_hz, raceline_ey_m=getattr(args, "raceline_ey", RaceSpec.raceline_ey_m),
                    max_time_s=max_time or None, sim_car_params=getattr(args, "sim_car_params", None),
                    sim_effects=getattr(args, "sim_effects", "") or "",
                    speed_model=getattr(args, "speed_model", RaceSpec.speed_model),
                    planner_threads=getattr(args, "planner_threads", RaceSpec.planner_threads),
                    line=getattr(args, "line", RaceSpec.line),
                    lateral_clearance_m=getattr(args, "lateral_clearance", RaceSpec.lateral_clearance_m))


def make_setup(args, seed: int, start: str, rd3g_speed: float, opponent_speed: float, laps: int = 1, max_time=None):
    """The RaceSetup of parsed race options; a bad value is a UserError naming its flag."""
    try:
        return race_spec(args, seed, start, rd3g_speed, opponent_speed, laps, max_time).load()
    except RaceSetupError as exc:
        flag = FLAGS.get(exc.field, exc.field)
        if exc.field == "roster" and getattr(args, "roster", None):  # a car of the roster file: name the file
            flag = f"--roster: {args.roster}"
        raise UserError(f"{flag}: {exc.message}") from None


def _simulated_link(args, setup):
    """--link-capture in a pure simulation: (Simulator subclass that records each control step's frame at
    the simulated time, the SimulatedLink, the capture), or Nones without the flag."""
    if not args.link_capture:
        return None, None, None

    plan = plan_link(args, "sim", setup, link_hz=1.0 / setup.control_period_s)
    capture = open_capture(args)
    link = SimulatedLink(capture, plan.encoder, [c.radio_id for c in plan.cars], setup.car.actuators.max_steering_rad)

    class CapturingSimulator(Simulator):
        def step(self, commands, dt_control):
            link.send(self.time, commands)
            return super().step(commands, dt_control)

    return CapturingSimulator, link, capture


def run(args) -> int:
    # --- real-time race stack: --hil or hardware mode runs the loop in app/realtime instead
    if wants_realtime(args):
        if args.sim_car_params or args.sim_effects.strip():
            raise UserError("--sim-car-params and --sim-effects apply to the pure simulation only (not --hil or hardware)")
        return run_realtime(args)
    # --- end real-time race stack
    if args.laps < 1:
        raise UserError(f"--laps must be at least 1, got {args.laps}")
    for name in ("rd3g_speed", "opponent_speed"):
        if not getattr(args, name) > 0:
            raise UserError(f"--{name.replace('_', '-')} must be positive")
    out = Path(args.out)
    if out.suffix != ".rrd":
        raise UserError(f"--out must be a .rrd file, got {args.out!r}")
    check_output_path(out)
    if args.json:
        check_output_path(args.json, stream=True)
    setup = make_setup(args, args.seed, args.start, args.rd3g_speed, args.opponent_speed, args.laps, args.max_time)
    if getattr(args, "grid_plot", None):
        check_output_path(args.grid_plot)
        print(f"start grid: {plot_grid(setup, Path(args.grid_plot))}")
        return 0
    human = [c.name for c in setup.cars if c.planner == "human"]
    if human:
        raise UserError(f"--cars/--roster: car {human[0]}: planner: human drives real cars only (--hil or --camera)")
    live = live_view(args)
    simulator_cls, link, capture = _simulated_link(args, setup)
    announce(live)
    try:
        o = run_race(setup, telemetry_path=out, live=live, **({"simulator_cls": simulator_cls} if link else {}))
        if link is not None:
            link.neutral(o.race_time_s)  # the race is over: what the link sends when it stops
    finally:
        if capture is not None:
            capture.close()
    s = o.summary()
    if setup.roster is None:
        rd3g, opp = setup.cars
        speeds = ((f"({rd3g.top_speed_mps:g} m/s) vs {args.opponent} ({opp.top_speed_mps:g} m/s)")
                  if rd3g.reference_speed_mps is None else
                  (f"(reference {rd3g.reference_speed_mps:g} m/s) vs {args.opponent} (reference "
                   f"{opp.reference_speed_mps:g} m/s), top speed {rd3g.top_speed_mps:g} m/s both"))
        print(f"race: {setup.track.name}, {args.laps} lap(s), seed {args.seed}, RD3G starts {args.start} "
              f"{speeds}, control {s['control_period_ms']:.1f} ms")
    else:
        print(f"race: {setup.track.name}, {args.laps} lap(s), seed {args.seed}, {len(setup.cars)} cars, grid {setup.grid}: "
              + ", ".join(f"{c.name} ({c.planner}, {c.top_speed_mps:g} m/s)" for c in setup.cars)
              + f", control {s['control_period_ms']:.1f} ms")
    if setup.sim_car is not None or setup.sim_effects != type(setup.sim_effects)():
        hidden = {k: v for k, v in dataclasses.asdict(setup.sim_effects).items()
                  if v != getattr(type(setup.sim_effects)(), k)}
        print(f"planners: car {setup.car.name}; simulator: car {(setup.sim_car or setup.car).name}, hidden effects {hidden or 'none'}")
    print(f"winner: {s['winner'] or 'none (time limit)'}"
          + (" (NOT a clean win: it left the track)" if s["winner"] and not s["clean_winner"] else ""))
    lost = {r.name: r.not_counted_m for r in o.results}  # progress made off the track, not counted (sim.race)
    print("off-track excursions: " + ", ".join(f"{name} {n}" + (f" ({lost[name]:.2f} m not counted)" if lost.get(name) else "")
                                               for name, n in s["off_track"].items()))
    for car in s["cars"]:
        place = f"P{car['finish_position']}" if car["finish_position"] else "unfinished"
        print(f"  {car['name']:9s} {place:10s} lap times: {', '.join(f'{t:.3f} s' for t in car['lap_times_s']) or '-'}")
    faults = ", ".join(f"{c.at_fault} at fault at {c.time_s:.2f} s" for c in o.collisions)
    print(f"minimum gap between footprints: {s['min_gap_m']:.3f} m; collisions: {s['collisions']}" + (f" ({faults})" if faults else ""))
    # a race interrupted before its first control step has no planner times
    times = (f"p50 {s['solve_ms_p50']:.1f} ms, p99 {s['solve_ms_p99']:.1f} ms, max {o.solve_ms.max():.1f} ms"
             if o.solve_ms.size else "no control step yet")
    print(f"RD3G planner{'s' if sum(c.planner == 'rd3g' for c in setup.cars) > 1 else ''} "
          f"(wall time per control step): {times}; control period {s['control_period_ms']:.1f} ms; fallbacks {o.fallbacks}; "
          f"first (cold) plan before the start {s['prestart_ms']:.0f} ms")
    if o.planner_errors:
        first = o.planner_errors[0]
        print(f"planner errors (those steps fell back, the race went on): {len(o.planner_errors)}; "
              f"first: {first.car} at {first.time_s:.2f} s: {first.message}")
    print(f"telemetry: {out}")
    if args.json:
        atomic_write_text(args.json, json.dumps(s, indent=2) + "\n", stream=True)
    if o.interrupted:
        print(f"interrupted (Ctrl-C) after {o.race_time_s:.2f} s of race time; the summary covers the race so far")
        return 130
    return 0
