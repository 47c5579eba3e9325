"""`python -m app check`: the pre-race hardware check (docs/race-stack.md, "Pre-race check").

Same hardware flags as `race` (--camera, --serial, --calibration, --link-protocol, --car-files, ...),
or --hil against the emulated hardware, where --hil-fault sets up a faulty world to see the check
catch it. Prints a checklist with the measured numbers; exit code 1 if any item fails."""
from __future__ import annotations

import re
import sys
import time

from app.cli import UserError
from app.commands.race import add_fleet_arguments, add_race_arguments, make_setup
from app.realtime.check import CheckTiming, PreRaceCheck
from fileio import check_output_path
from race.hil import FIXED_MARKERS
from app.realtime.mocap import add_mocap_arguments
from app.realtime.run import _check_mode, _open_hardware, _open_hil, add_link_arguments, open_capture, plan_link
from race.config import LoopConfig
from tracking.calibration import CalibrationError, load_fixed_markers
from vehicles.serial_link import SerialCarLink

SETUP_FAULTS = ("swapped_radio_ids", "reversed_throttle:CAR", "missing_marker:CAR", "covered_fixed_marker:ID")
_SETUP_FAULT = re.compile(r"^(swapped_radio_ids|reversed_throttle:[a-z0-9_]+|missing_marker:[a-z0-9_]+"
                          r"|covered_fixed_marker:[0-9]+)$")


def register(sub) -> None:
    p = sub.add_parser("check", help="pre-race hardware check: camera, markers, calibration, serial port, "
                                     "each car's radio and the box failsafe (exit 1 on any failure)")
    p.add_argument("--hil", action="store_true", help="check the emulated hardware (HIL world)")
    p.add_argument("--camera", help="camera index or stream URL")
    p.add_argument("--serial", help="serial device of the transmitter box, e.g. /dev/ttyUSB0")
    p.add_argument("--calibration", help="camera calibration JSON (python -m app calibrate)")
    p.add_argument("--fixed-markers", default=None,
                   help="surveyed fixed markers JSON (default: the track's, if it has one)")
    p.add_argument("--fps", type=float, default=60.0, help="expected camera frame rate (default 60)")
    p.add_argument("--camera-latency-ms", type=float, default=0.0)
    p.add_argument("--marker-ids", default="0,1", help="ArUco ids of the RD3G car and the opponent (default 0,1)")
    p.add_argument("--radio-ids", default=None, help="link ids of the two cars (default: the marker ids, or the "
                                                     "modem ids of --car-files)")
    p.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    p.add_argument("--seed", type=int, default=0, help="HIL: world seed")
    p.add_argument("--throttle", type=float, default=0.15, help="throttle of the short pulse (default 0.15)")
    p.add_argument("--hil-fault", action="append", default=[], metavar="|".join(SETUP_FAULTS),
                   help="HIL: a faulty set-up for the check to catch (repeatable)")
    add_link_arguments(p)
    add_mocap_arguments(p)
    add_race_arguments(p)
    add_fleet_arguments(p)
    p.set_defaults(func=run)


def _world_options(args, link_plan, cars, fixed_ids) -> dict:
    """WorldSpec fields of the --hil-fault set-up faults."""
    import dataclasses

    options: dict = {}
    receivers = list(link_plan.calibrations)
    radio_ids = [c.radio_id for c in cars]
    for text in args.hil_fault:
        if not _SETUP_FAULT.match(text):
            raise UserError(f"--hil-fault {text!r}: expected one of {', '.join(SETUP_FAULTS)}")
        kind, _, arg = text.partition(":")
        index = {c.name: i for i, c in enumerate(cars)}.get(arg)
        if kind in ("reversed_throttle", "missing_marker") and index is None:
            raise UserError(f"--hil-fault {text!r}: no car {arg!r} (cars: {', '.join(c.name for c in cars)})")
        if kind == "swapped_radio_ids":  # the first two cars' radios swapped (in a two-car race: both)
            radio_ids[0], radio_ids[1] = radio_ids[1], radio_ids[0]
            if receivers:
                receivers[0], receivers[1] = (dataclasses.replace(receivers[0], modem_id=receivers[1].modem_id),
                                              dataclasses.replace(receivers[1], modem_id=receivers[0].modem_id))
        elif kind == "reversed_throttle":
            if not receivers:
                raise UserError("--hil-fault reversed_throttle needs --link-protocol buzzracer-fhss (the receivers' "
                                "pulse calibration)")
            r = receivers[index]
            receivers[index] = dataclasses.replace(r, throttle_forward_us=r.throttle_reverse_us,
                                                   throttle_reverse_us=r.throttle_forward_us)
        elif kind == "missing_marker":
            options["hidden_markers"] = options.get("hidden_markers", ()) + (cars[index].marker_id,)
        else:
            if int(arg) not in fixed_ids:
                raise UserError(f"--hil-fault {text}: {arg} is not a fixed marker of this track "
                                f"(fixed markers: {', '.join(map(str, sorted(fixed_ids))) or 'none'})")
            options["covered_fixed_markers"] = options.get("covered_fixed_markers", ()) + (int(arg),)
    options["radio_ids"] = tuple(radio_ids)
    if receivers:
        options["receivers"] = tuple(receivers)
    return options


def run(args) -> int:
    args.fault = []
    mode = _check_mode(args)
    if args.hil_fault and mode != "hil":
        raise UserError("--hil-fault needs --hil")
    if not 0 < args.throttle <= 0.5:
        raise UserError(f"--throttle: must be in (0, 0.5] (a short, low pulse), got {args.throttle}")
    if not args.fps > 0:
        raise UserError(f"--fps must be positive, got {args.fps}")
    if args.link_capture:
        check_output_path(args.link_capture)  # before the world or the serial port opens
    setup = make_setup(args, args.seed, "rear", args.rd3g_speed, args.opponent_speed)
    config = LoopConfig()
    link_plan = plan_link(args, mode, setup, config.link_hz)
    cars = link_plan.cars
    fixed_path = None if args.mocap else args.fixed_markers or FIXED_MARKERS.get(setup.track.name)
    try:
        marker_set = load_fixed_markers(fixed_path) if fixed_path else None
    except (CalibrationError, ValueError, OSError) as exc:
        raise UserError(f"--fixed-markers: {exc}") from None
    fixed_ids = set(marker_set.markers) if marker_set else set()
    world_options = _world_options(args, link_plan, cars, fixed_ids) if mode == "hil" else {}
    if args.mocap and "hidden_markers" in world_options:
        raise UserError("--hil-fault missing_marker: not with --mocap (a lost rigid body is the race's occlude fault)")
    if mode == "hil":
        parts = _open_hil(args, setup, cars, config, (), link_plan, **world_options)
    else:
        parts = _open_hardware(args, setup, cars, config)
    world, feed, tracker, _, port, note = parts
    print(f"check ({mode}): {setup.track.name}, cars {', '.join(f'{c.name} marker {c.marker_id} radio {c.radio_id}' for c in cars)}; "
          f"{link_plan.protocol}" + (f"; set-up faults: {', '.join(args.hil_fault)}" if args.hil_fault else ""))
    if note:
        print(f"  {note}")
    capture = open_capture(args)
    link = SerialCarLink(port, baudrate=args.baud, rate_hz=link_plan.rate_hz, car_ids=[c.radio_id for c in cars],
                         encoder=link_plan.encoder, capture=capture)
    bodies = {m.key: m.rigid_body_id for m in tracker.cars} if args.mocap else None
    check = PreRaceCheck(feed=feed, tracker=tracker, track=setup.track, cars=cars, link=link, marker_set=marker_set,
                         expected_fps=args.fps, timing=CheckTiming(throttle=args.throttle),
                         on_go=(lambda: world.go(time.monotonic())) if world is not None else None,
                         **({"sensor": "mocap", "car_target": lambda c: f"rigid body {bodies[c.marker_id]}"}
                            if args.mocap else {}))
    try:
        items = check.run()
    finally:
        link.stop()
        (world or feed).close()
        if world is not None and feed is not world:  # --mocap: the NatNet client beside the HIL world
            feed.close()
        if capture is not None:
            capture.close()
    failed = [i for i in items if not i.ok]
    print(f"check: {len(items) - len(failed)}/{len(items)} passed" + (f"; FAILED: {', '.join(i.name for i in failed)}"
                                                                       if failed else ""))
    sys.stdout.flush()
    return 1 if failed else 0
