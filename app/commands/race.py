"""`python -m app race`: one simulated race, RD3G vs the MPC opponent (or pure pursuit); docs/racing.md."""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from app.cli import UserError

DEFAULT_OUT = "runs/race.rrd"


def add_race_arguments(p) -> None:
    p.add_argument("--track", default="oval", help="track name or file (default: oval)")
    p.add_argument("--car-params", default="buzzracer", help="car parameter file for both cars (default: buzzracer)")
    p.add_argument("--opponent", choices=("mpc", "pursuit"), default="mpc")
    p.add_argument("--rd3g-speed", type=float, default=2.0, help="RD3G car's top speed (m/s)")
    p.add_argument("--opponent-speed", type=float, default=1.8, help="opponent's top speed (m/s)")
    p.add_argument("--control-hz", type=float, default=30.0, help="control rate (default 30 Hz)")
    p.add_argument("--raceline-ey", type=float, default=0.0, metavar="M",
                   help="lateral reference of both cars' racing cost (m, left positive; default 0, the centre line); "
                        "on the oval 0.05 (inside) won more slow-car races but had one RD3G-at-fault contact in "
                        "400 batch races (docs/racing.md)")


def register(sub) -> None:
    p = sub.add_parser("race", help="simulate one race RD3G vs MPC and record telemetry (rerun .rrd)")
    p.add_argument("--laps", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--start", choices=("front", "rear"), default="rear", help="where the RD3G car starts")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"rerun recording (default {DEFAULT_OUT})")
    p.add_argument("--json", help="also write the race summary as JSON here")
    p.add_argument("--max-time", type=float, default=None, help="give up after this many seconds of race time")
    add_race_arguments(p)
    # --- closing the model-identification loop (docs/sysid.md): the planners use --car-params (e.g. a
    # file written by `sysid`), the simulator runs the physical car below
    p.add_argument("--sim-car-params", default=None,
                   help="car file the simulator runs (default: --car-params); pure simulation only")
    p.add_argument("--sim-effects", default="",
                   help='hidden effects the simulator adds to both cars, e.g. "steering_offset=0.03,actuation_delay=0.08" '
                        "(names as in sysid-generate, docs/sysid.md); pure simulation only")
    # --- end closing the loop
    # --- real-time race stack (app/realtime, docs/race-stack.md): --hil / --camera --serial --calibration
    from app.realtime.run import add_realtime_arguments
    add_realtime_arguments(p)
    # --- end real-time race stack
    p.set_defaults(func=run)


def make_setup(args, seed: int, start: str, rd3g_speed: float, opponent_speed: float, laps: int = 1, max_time=None):
    from app.race_runner import RaceSetup
    from planning import PlannerConfig
    from tracks import load_track
    from tracks.io import UnknownTrackError
    from vehicles.params import CarParamsError, load_car_params

    try:
        track = load_track(args.track)
    except (UnknownTrackError, FileNotFoundError) as exc:
        raise UserError(f"--track: {exc}") from None
    try:
        car = load_car_params(args.car_params)
    except CarParamsError as exc:
        raise UserError(f"--car-params: {exc}") from None
    if not args.control_hz > 0:
        raise UserError(f"--control-hz must be positive, got {args.control_hz}")
    sim_car, sim_effects = _simulated_car(args)
    period = 1.0 / args.control_hz
    raceline = getattr(args, "raceline_ey", 0.0)
    if not math.isfinite(raceline) or abs(raceline) >= track.min_width / 2:
        raise UserError(f"--raceline-ey must be a finite offset inside the track "
                        f"(|M| < {track.min_width / 2:g} m), got {raceline}")
    # The simulator needs a whole number of 1 ms physics steps per control period on average; it keeps
    # the control clock exactly, so any rate works.
    return RaceSetup(track=track, car=car, seed=seed, laps=laps, opponent=args.opponent, start=start,
                     rd3g_top_speed_mps=rd3g_speed, opponent_top_speed_mps=opponent_speed,
                     control_period_s=period, max_time_s=max_time or 30.0 * laps + 30.0,
                     sim_car=sim_car, sim_effects=sim_effects, planner=PlannerConfig(raceline_ey_m=raceline))


def _simulated_car(args):
    """(sim_car or None, SimEffects) from --sim-car-params / --sim-effects (absent in batch's arguments)."""
    from sim import SimEffects, SimEffectsError
    from sysid.generate import parse_effects, sim_effects
    from vehicles.params import CarParamsError, load_car_params

    sim_car = None
    if getattr(args, "sim_car_params", None):
        try:
            sim_car = load_car_params(args.sim_car_params)
        except CarParamsError as exc:
            raise UserError(f"--sim-car-params: {exc}") from None
    text = getattr(args, "sim_effects", "") or ""
    try:
        effects = sim_effects(parse_effects(text, flag="--sim-effects"), 0.0, 0.0) if text.strip() else SimEffects()
    except SimEffectsError as exc:
        raise UserError(f"--sim-effects: {exc}") from None
    return sim_car, effects


def _simulated_link(args, setup):
    """--link-capture in a pure simulation: (Simulator subclass that records each control step's frame at
    the simulated time, the SimulatedLink, the capture), or Nones without the flag."""
    if not args.link_capture:
        return None, None, None
    from app.realtime.run import open_capture, plan_link
    from sim import Simulator
    from vehicles.link_capture import SimulatedLink

    plan = plan_link(args, "sim", setup, link_hz=1.0 / setup.control_period_s)
    capture = open_capture(args)
    link = SimulatedLink(capture, plan.encoder, [c.radio_id for c in plan.cars], setup.car.actuators.max_steering_rad)

    class CapturingSimulator(Simulator):
        def step(self, commands, dt_control):
            link.send(self.time, commands)
            return super().step(commands, dt_control)

    return CapturingSimulator, link, capture


def run(args) -> int:
    from app.race_runner import run_race

    # --- real-time race stack: --hil or hardware mode runs the loop in app/realtime instead
    from app.realtime.run import run_realtime, wants_realtime
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
    out.parent.mkdir(parents=True, exist_ok=True)
    setup = make_setup(args, args.seed, args.start, args.rd3g_speed, args.opponent_speed, args.laps, args.max_time)
    simulator_cls, link, capture = _simulated_link(args, setup)
    try:
        o = run_race(setup, telemetry_path=out, **({"simulator_cls": simulator_cls} if link else {}))
        if link is not None:
            link.neutral(o.race_time_s)  # the race is over: what the link sends when it stops
    finally:
        if capture is not None:
            capture.close()
    s = o.summary()
    print(f"race: {setup.track.name}, {args.laps} lap(s), seed {args.seed}, RD3G starts {args.start} "
          f"({args.rd3g_speed} m/s) vs {args.opponent} ({args.opponent_speed} m/s), control {s['control_period_ms']:.1f} ms")
    if setup.sim_car is not None or setup.sim_effects != type(setup.sim_effects)():
        hidden = {k: v for k, v in dataclasses.asdict(setup.sim_effects).items()
                  if v != getattr(type(setup.sim_effects)(), k)}
        print(f"planners: car {setup.car.name}; simulator: car {(setup.sim_car or setup.car).name}, hidden effects {hidden or 'none'}")
    print(f"winner: {s['winner'] or 'none (time limit)'}"
          + (" (NOT a clean win: it left the track)" if s["winner"] and not s["clean_winner"] else ""))
    print(f"off-track excursions: rd3g {s['off_track']['rd3g']}, opponent {s['off_track']['opponent']}")
    for name, laps in s["lap_times_s"].items():
        print(f"  {name:9s} lap times: {', '.join(f'{t:.3f} s' for t in laps) or '-'}")
    faults = ", ".join(f"{c.at_fault} at fault at {c.time_s:.2f} s" for c in o.collisions)
    print(f"minimum gap between footprints: {s['min_gap_m']:.3f} m; collisions: {s['collisions']}" + (f" ({faults})" if faults else ""))
    print(f"RD3G planner (wall time per control step): p50 {s['solve_ms_p50']:.1f} ms, p99 {s['solve_ms_p99']:.1f} ms, "
          f"max {o.solve_ms.max():.1f} ms; control period {s['control_period_ms']:.1f} ms; fallbacks {o.fallbacks}; "
          f"first (cold) plan before the start {s['prestart_ms']:.0f} ms")
    if o.planner_errors:
        first = o.planner_errors[0]
        print(f"planner errors (those steps fell back, the race went on): {len(o.planner_errors)}; "
              f"first: {first.car} at {first.time_s:.2f} s: {first.message}")
    print(f"telemetry: {out}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(s, indent=2) + "\n")
    return 0
