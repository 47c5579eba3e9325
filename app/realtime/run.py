"""`python -m app race --hil` and `python -m app race --camera N --serial DEV --calibration FILE`:
build the real-time loop's parts from the command line and run one race (docs/race-stack.md)."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.cli import UserError
from app.live_view import announce, live_view
from app.realtime.hardware import CameraFeed
from app.realtime.operator_key import TerminalStopKey
from app.realtime.mocap import add_mocap_arguments, open_mocap_hardware, open_mocap_hil
from race.hil import HilWorld, WorldSpec
from fileio import OutputFileError, atomic_write_text, check_output_path
from race.config import FAULT_KINDS, LoopConfig, LoopConfigError, check_fault_cars, parse_fault
from race.loop import CarBinding, LoopError, RaceLoop, setup_document
from race.planning import RacePlanners
from race.recording import RaceRecorder
from race.setup import start_states
from tracking.calibration import (CalibrationError, CameraCalibration, Intrinsics, calibrate_image, load_calibration,
                                  load_fixed_markers)
from tracking.camera import CameraError, OpenCVCamera
from tracking.estimator import MultiCarEstimator
from tracking.markers import ArucoTracker
from vehicles.fhss import servo_calibration
from sim.camera_profile import PROFILE_NAMES, camera_profile
from vehicles.link_capture import LinkCapture
from vehicles.link_protocols import HARDWARE_DEFAULT, HIL_DEFAULT, PROTOCOLS, check_protocol, make_encoder
from vehicles.params import CarParamsError, load_car_params
from vehicles.protocol import ProtocolError
from vehicles.serial_link import SerialCarLink, SerialLinkError


def add_realtime_arguments(p) -> None:
    g = p.add_argument_group("real-time race loop (docs/race-stack.md)")
    g.add_argument("--hil", action="store_true",
                   help="hardware in the loop: synthetic camera frames of the simulator through the real detector, "
                        "commands through the serial protocol over a pseudo-terminal to virtual cars")
    g.add_argument("--camera", help="hardware: camera index or stream URL")
    g.add_argument("--serial", help="hardware: serial device of the transmitter box, e.g. /dev/ttyUSB0")
    g.add_argument("--calibration", help="hardware: camera calibration JSON (python -m app calibrate)")
    g.add_argument("--loop-hz", type=float, default=60.0, help="loop rate (default 60 Hz); planning runs at --control-hz")
    g.add_argument("--command-delay-ms", type=float, default=None, metavar="MS",
                   help="from a loop tick's start until the cars act on its command (loop stages, serial link, "
                        "radio); plans are made for that instant, plan_ticks ticks ahead (default: "
                        "LoopConfig.command_delay_s, 19 ms, measured in HIL; see command_lag_ms)")
    g.add_argument("--fps", type=float, default=60.0, help="HIL camera frame rate (default 60)")
    g.add_argument("--camera-profile", choices=PROFILE_NAMES, default="ideal",
                   help="HIL synthetic camera: ideal (pinhole, global shutter) or realistic (lens distortion, MJPEG, "
                        "rolling shutter, delivery latency, flicker; sim/camera_profile.py; default ideal); ideal+EFFECT adds "
                        "one of the realistic effects alone")
    g.add_argument("--fault", action="append", default=[], metavar="KIND@START[+DUR][:CAR]",
                   help=f"HIL fault injection (repeatable): {', '.join(FAULT_KINDS)}")
    g.add_argument("--marker-ids", default="0,1", help="ArUco ids of the RD3G car and the opponent (default 0,1)")
    g.add_argument("--radio-ids", default=None, help="serial-protocol ids of the two cars (default: the marker ids)")
    g.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    add_link_arguments(g)
    g.add_argument("--human-opponent", action="store_true",
                   help="the opponent is driven by a person: tracked and raced against, never commanded")
    g.add_argument("--rt-priority", type=int, default=None, metavar="PRIO",
                   help="run the loop under SCHED_FIFO at this priority (1-99, needs CAP_SYS_NICE); the HIL world "
                        "runs 5, the virtual box 3, the planner 4 and the telemetry thread 10 below it. 0: normal "
                        f"scheduling. Default: {AUTO_RT_PRIORITY} when the process may use SCHED_FIFO, else normal "
                        "scheduling (with a warning)")
    g.add_argument("--stop-after-hold", type=float, default=3.0, metavar="S",
                   help="stop the race (exit code 1) when the cars have been held neutral by a safety hold "
                        "(lost car, planner fault, ...) for S seconds without a break (default 3)")
    g.add_argument("--camera-latency-ms", type=float, default=0.0,
                   help="hardware: exposure-to-delivery delay of the camera, subtracted from frame times")
    add_mocap_arguments(g)


def add_link_arguments(g) -> None:
    """The transmitter link's flags (race and check)."""
    g.add_argument("--link-protocol", default=None, metavar="|".join(PROTOCOLS),
                   help=f"frame the transmitter box reads (docs/serial-protocol.md); default {HARDWARE_DEFAULT} on "
                        f"hardware, {HIL_DEFAULT} with --hil")
    g.add_argument("--link-capture", default=None, metavar="FILE",
                   help="write every byte to and from the transmitter box here, one line per write or read: "
                        "'<seconds since the race started> tx|rx <hex>' (decode: python -m app link-decode FILE)")
    g.add_argument("--car-files", default=None, metavar="RD3G,OPPONENT",
                   help="car parameter files of the two cars (rd3g car first) whose [radio] section (modem id, "
                        "pulse calibration) drives buzzracer-fhss frames (docs/vehicles.md); default: --car-params "
                        "for both, modem ids from --radio-ids")


def wants_realtime(args) -> bool:
    return bool(getattr(args, "hil", False) or getattr(args, "camera", None) is not None
                or getattr(args, "serial", None) is not None or getattr(args, "calibration", None) is not None
                or getattr(args, "mocap", None) is not None)


def _ids(text: str, flag: str) -> tuple[int, int]:
    try:
        ids = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise UserError(f"{flag}: expected two integers like 0,1, got {text!r}") from None
    if len(ids) != 2 or ids[0] == ids[1] or not all(0 <= i <= 255 for i in ids):
        raise UserError(f"{flag}: expected two different ids in 0..255, got {text!r}")
    return ids


def _check_mode(args) -> str:
    hw = {"--camera": args.camera, "--serial": args.serial, "--calibration": args.calibration}
    mocap = getattr(args, "mocap", None)
    if mocap is not None:  # the mocap system replaces the camera and its calibration
        if args.camera is not None or args.calibration is not None:
            raise UserError("--mocap replaces the camera: drop --camera and --calibration")
        hw = {"--serial": args.serial}
    elif getattr(args, "mocap_calibration", None) is not None:
        raise UserError("--mocap-calibration needs --mocap natnet://SERVER")
    given = [k for k, v in hw.items() if v is not None]
    if args.hil:
        if given:
            raise UserError(f"--hil simulates the camera and the serial link; drop {', '.join(given)}")
        return "hil"
    missing = [k for k, v in hw.items() if v is None]
    if missing:
        needs = "--mocap and --serial" if mocap is not None else "--camera, --serial and --calibration"
        raise UserError(f"hardware mode needs {needs}; missing {', '.join(missing)}")
    if args.fault:
        raise UserError("--fault is only available with --hil")
    return "hardware"


AUTO_RT_PRIORITY = 20


def _set_scheduling(rt_priority: int | None) -> str:
    """Switch the calling thread to SCHED_FIFO (before any thread or the world process exists:
    they inherit the policy and lower their own priority where they are helpers). ``None`` = auto:
    SCHED_FIFO at AUTO_RT_PRIORITY when permitted, else normal scheduling with a warning: a real-time
    loop is the default because time-sharing on this 2-core machine misses 25-45 % of the HIL
    loop's deadlines (docs/race-stack.md, "Scheduling"). Returns a description for the recording."""
    if rt_priority == 0:
        return "normal time-sharing (--rt-priority 0)"
    if rt_priority is not None and not 1 <= rt_priority <= 99:
        raise UserError(f"--rt-priority: must be in 1..99 (0 = normal scheduling), got {rt_priority}")
    prio = AUTO_RT_PRIORITY if rt_priority is None else rt_priority
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except (PermissionError, OSError, AttributeError) as exc:
        if rt_priority is not None:
            raise UserError(f"--rt-priority {rt_priority}: cannot switch to SCHED_FIFO ({exc}); "
                            f"run with --rt-priority 0 or grant CAP_SYS_NICE") from None
        print(f"warning: SCHED_FIFO not permitted ({exc}); the loop runs under normal scheduling and may "
              f"miss deadlines. Grant CAP_SYS_NICE (docs/race-stack.md, \"Scheduling\") or pass --rt-priority 0 "
              f"to silence this.", file=sys.stderr)
        return f"normal time-sharing (SCHED_FIFO not permitted: {exc})"
    return f"SCHED_FIFO priority {prio}" + (" (default)" if rt_priority is None else "")


def run_realtime(args) -> int:
    mode = _check_mode(args)
    policy = (os.sched_getscheduler(0), os.sched_getparam(0)) if hasattr(os, "sched_getscheduler") else None
    try:
        return _run_realtime(args, mode)
    finally:
        if policy is not None and args.rt_priority != 0:
            try:  # the calling thread goes back to its scheduling policy (matters when called in-process)
                os.sched_setscheduler(0, policy[0], policy[1])
            except OSError:
                pass


def _run_realtime(args, mode: str) -> int:
    from app.commands.race import DEFAULT_OUT, make_setup  # here: app.commands.race imports this module

    if args.laps < 1:
        raise UserError(f"--laps must be at least 1, got {args.laps}")
    for name in ("rd3g_speed", "opponent_speed", "loop_hz", "fps", "stop_after_hold"):
        if not getattr(args, name) > 0:
            raise UserError(f"--{name.replace('_', '-')} must be positive")
    latency = {}
    if args.command_delay_ms is not None:
        if not (math.isfinite(args.command_delay_ms) and 0 < args.command_delay_ms <= 500):
            raise UserError(f"--command-delay-ms must be in (0, 500] ms, got {args.command_delay_ms}")
        latency["command_delay_s"] = args.command_delay_ms / 1e3
    try:
        # A mocap frame holds every body: no region-of-interest search to fall back from while a car is lost.
        config = LoopConfig(rate_hz=args.loop_hz, plan_hz=args.control_hz, stop_after_hold_s=args.stop_after_hold,
                            **latency, **({"lost_search_every": 1} if getattr(args, "mocap", None) else {}))
        faults = tuple(parse_fault(f) for f in args.fault)
    except LoopConfigError as exc:
        raise UserError(str(exc)) from None
    out = Path(args.out)
    if out.suffix != ".rrd":
        raise UserError(f"--out must be a .rrd file, got {args.out!r}")
    stamp = time.strftime("%Y%m%d-%H%M%S")
    if args.out == DEFAULT_OUT:  # one file per race
        out = out.parent / f"{mode}-seed{args.seed}-{stamp}.rrd"
    for path, stream in ((out, False), (args.json, True), (args.link_capture, False)):
        if path:
            check_output_path(path, stream=stream)  # before the HIL processes or the hardware open
    setup = make_setup(args, args.seed, args.start, args.rd3g_speed, args.opponent_speed, args.laps, args.max_time)
    live = live_view(args)  # before anything opens: a viewer that cannot be reached is a usage error
    roster = race_roster(args, setup)
    try:
        check_fault_cars(faults, setup.names)
    except LoopConfigError as exc:
        raise UserError(f"--fault: {exc}") from None
    opponent = "human" if args.human_opponent else args.opponent
    link_plan = plan_link(args, mode, setup, config.link_hz)  # everything about the link valid before it opens
    cars = link_plan.cars

    scheduling = _set_scheduling(args.rt_priority)
    if mode == "hardware":
        parts = _open_hardware(args, setup, cars, config)
    else:
        parts = _open_hil(args, setup, cars, config, faults, link_plan)
    world, feed, tracker, estimator, link_port, note = parts
    recorder = loop = capture = None
    stop_key = TerminalStopKey()
    try:
        planners = RacePlanners(setup, roster)
        recorder = RaceRecorder(out, recording_id=f"{mode}-seed{args.seed}-{stamp}", car_names=[c.name for c in cars],
                                live=live)
        announce(live)
        recorder.static_track(setup.track)
        if (line := setup.racing_line()) is not None:
            recorder.static_racing_line(setup.track, line)
        recorder.static_document("race/setup", setup_document(setup, config, mode, cars, opponent, faults,
                                                                  planners={c.name: c.planner for c in roster}))
        recorder.static_car_colors([c.name for c in cars])
        stop_key.arm()  # the terminal's mode is restored in the finally below (and on SIGTERM, at exit)
        loop = RaceLoop(setup=setup, config=config, feed=feed, tracker=tracker, estimator=estimator, link=None,
                        planners=planners, cars=cars, recorder=recorder, faults=faults, world=world, mode=mode,
                        operator=stop_key)
        commanded = [c.radio_id for c in cars if c.name in planners.commanded]
        capture = open_capture(args)
        link = SerialCarLink(link_port, baudrate=args.baud, rate_hz=link_plan.rate_hz, car_ids=commanded,
                             on_fault=loop._on_link_fault, encoder=link_plan.encoder, capture=capture)
        try:
            link.start()
        except SerialLinkError as exc:
            raise UserError(f"--serial: {exc}") from None
        loop.link = link
        loop._event("setup", f"scheduling: {scheduling}", t_race=0.0)
        loop._event("setup", f"link: {link_plan.protocol} at {link_plan.rate_hz:g} frames/s, {args.baud} baud"
                             + (f", capture {capture.path}" if capture else ""), t_race=0.0)
        if note:
            loop._event("setup", note, t_race=0.0)
        if stop_key.active:
            print("operator stop: press space or Enter to stop the race (every car neutral at once)", flush=True)
        try:
            outcome = loop.run()
        except LoopError as exc:
            raise UserError(str(exc)) from None
    finally:
        stop_key.close()
        if loop is None or loop.t_go is None:  # failed before the race: release what was opened
            if world is not None:
                world.close()
            elif feed is not None:
                feed.close()
        if recorder is not None:
            recorder.close()
        if capture is not None:
            capture.close()
    if recorder.live_error:
        print(f"warning: live view: the viewers did not get the whole race ({recorder.live_error}); "
              f"the recording {out} is complete", file=sys.stderr)
    _print(outcome, setup, args, mode, opponent)
    if args.json:
        atomic_write_text(args.json, json.dumps(outcome.summary(), indent=2) + "\n", stream=True)
    return 0 if outcome.reason in ("finished", "time_limit") else 1


def race_roster(args, setup):
    """The cars this real-time race drives: the set-up's roster; ``--human-opponent`` (the two-car race)
    makes the second car human-driven (tracked, never commanded)."""
    if not args.human_opponent:
        return setup.cars
    if setup.roster is not None:
        raise UserError("--human-opponent: a --cars/--roster race names its human-driven cars with planner human")
    return (setup.cars[0], dataclasses.replace(setup.cars[1], planner="human"))


@dataclass(frozen=True)
class LinkPlan:
    """The transmitter link as configured from the command line, validated before anything opens."""

    protocol: str
    cars: list                 # race.loop.CarBinding, radio_id = modem id for buzzracer-fhss
    calibrations: tuple        # vehicles.fhss.ServoCalibration per car (buzzracer-fhss), else ()
    encoder: object            # vehicles.link_protocols.FrameEncoder
    rate_hz: float             # frames per second (the loop's link rate, capped by the receiver)


def plan_link(args, mode: str, setup, link_hz: float) -> LinkPlan:
    """Protocol, car bindings and encoder from --link-protocol, --marker-ids, --radio-ids, --car-files
    (UserError naming the flag or the car file's field on any fault)."""
    protocol = args.link_protocol or (HARDWARE_DEFAULT if mode == "hardware" else HIL_DEFAULT)
    try:
        check_protocol(protocol)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if setup.roster is not None:
        return _fleet_link(args, protocol, setup, link_hz)
    markers = _ids(args.marker_ids, "--marker-ids")
    files = [setup.car, setup.car]
    if args.car_files:
        paths = [p.strip() for p in args.car_files.split(",")]
        if len(paths) != 2 or not all(paths):
            raise UserError(f"--car-files: expected two files RD3G,OPPONENT, got {args.car_files!r}")
        try:
            files = [load_car_params(p) for p in paths]
        except CarParamsError as exc:
            raise UserError(f"--car-files: {exc}") from None
    if args.radio_ids:
        radios = _ids(args.radio_ids, "--radio-ids")
    elif args.car_files and protocol == "buzzracer-fhss":
        radios = tuple(car.radio.modem_id for car in files)
        for name, path, radio in zip(setup.names, paths, radios):
            if radio is None:
                raise UserError(f"--car-files: {path}: radio.modem_id is not set (car {name}: the FHSS box "
                                f"slot that drives it)")
        if radios[0] == radios[1]:
            raise UserError(f"--car-files: both cars have radio.modem_id {radios[0]}; each car needs its own")
    else:
        radios = markers
    cars = [CarBinding(name, marker, radio) for name, marker, radio in zip(setup.names, markers, radios)]
    calibrations = ()
    try:
        if protocol == "buzzracer-fhss":
            calibrations = tuple(servo_calibration(car, c.radio_id, setup.car.actuators.max_steering_rad)
                                 for car, c in zip(files, cars))
        encoder = make_encoder(protocol, calibrations)
    except ProtocolError as exc:
        raise UserError(f"--link-protocol {protocol}: {exc}") from None
    rate = min(link_hz, encoder.max_rate_hz or link_hz)
    return LinkPlan(protocol, cars, calibrations, encoder, rate)


def _fleet_link(args, protocol: str, setup, link_hz: float) -> LinkPlan:
    """The link of a --cars/--roster race: each car's marker and radio id from the roster (the FHSS box
    drives at most 6 cars), each car's receiver calibration from its car file."""
    for flag in ("marker_ids", "radio_ids", "car_files"):
        if getattr(args, flag, None) and getattr(args, flag) != "0,1":
            raise UserError(f"--{flag.replace('_', '-')}: a --cars/--roster race takes the ids and car files from the roster")
    cars = [CarBinding(c.name, c.marker_id, c.radio_id) for c in setup.cars]
    calibrations = ()
    try:
        if protocol == "buzzracer-fhss":
            for c in setup.cars:
                if not 0 <= c.radio_id < 6:
                    raise UserError(f"--cars/--roster: car {c.name}: radio_id: the FHSS box has modem ids 0-5, "
                                    f"got {c.radio_id}")
            calibrations = tuple(servo_calibration(setup.car_file(i), c.radio_id, setup.car.actuators.max_steering_rad)
                                 for i, c in enumerate(cars))
        encoder = make_encoder(protocol, calibrations)
    except ProtocolError as exc:
        raise UserError(f"--link-protocol {protocol}: {exc}") from None
    rate = min(link_hz, encoder.max_rate_hz or link_hz)
    return LinkPlan(protocol, cars, calibrations, encoder, rate)


def open_capture(args):
    """The --link-capture file (None without the flag); its time origin is now, the race's start."""
    if not getattr(args, "link_capture", None):
        return None
    path = Path(args.link_capture)
    try:
        return LinkCapture(path)
    except OutputFileError as exc:
        raise UserError(f"--link-capture: {exc}") from None
    except OSError as exc:
        raise UserError(f"--link-capture: cannot write {path}: {exc}") from None


def _open_hil(args, setup, cars, config, faults, link_plan, **world_options):

    fields = dict(track=setup.track, car=setup.car, start_states=start_states(setup),
                  marker_ids=tuple(c.marker_id for c in cars), radio_ids=tuple(c.radio_id for c in cars),
                  names=tuple(c.name for c in cars), finish=setup.finish,
                  laps=setup.laps, off_track_allowance_car_lengths=setup.off_track_allowance_car_lengths,
                  seed=setup.seed, fps=args.fps, faults=faults, link_protocol=link_plan.protocol,
                  receivers=link_plan.calibrations if link_plan.protocol == "buzzracer-fhss" else None,
                  camera_profile=camera_profile(getattr(args, "camera_profile", "ideal")))
    fields.update(world_options)  # `check --hil --hil-fault`: a world that differs from the host's set-up
    if getattr(args, "mocap", None) is not None:
        return open_mocap_hil(args, fields, setup, cars)
    spec = WorldSpec(**fields)
    world = HilWorld(spec)
    try:
        info = world.info
        # The lens as calibrate-camera estimates it from rendered board views (realistic profile; cached), not
        # the renderer's truth.
        camera = spec.camera_profile.with_seed(spec.seed).estimated(world.camera)
        fixed_ids = ()
        note = "calibration: true synthetic camera (no fixed markers for this track)"
        calibration = CameraCalibration(camera, dictionary=setup.car.marker.dictionary)
        if info["fixed_markers"]:
            # Calibrate like on the real track: camera pose from the fixed markers in a grid frame,
            # with known intrinsics.
            marker_set = spec.camera_profile.with_seed(spec.seed).surveyed(load_fixed_markers(info["fixed_markers"]))
            packet = world.poll(5.0)
            while packet.frame is None:
                packet = world.poll(5.0)
            calibration = calibrate_image(packet.frame.image, marker_set,
                                          Intrinsics(camera.camera_matrix, camera.dist_coeffs, camera.image_size))
            fixed_ids = marker_set.markers  # surveyed: fixed ids are accepted only near their projections
            err = 1e3 * float(np.linalg.norm(calibration.camera.position - camera.position))
            note = (f"calibration from {len(calibration.markers_used)} fixed markers: reprojection rms "
                    f"{calibration.reprojection_rms_px:.3f} px, camera position error {err:.1f} mm")
            if spec.camera_profile.calibration_views:
                note += f"; intrinsics from {spec.camera_profile.calibration_views} rendered ChArUco views"
        mk = setup.car.marker
        tracker = ArucoTracker(calibration, info["marker_size_m"], info["marker_height_m"],
                               car_ids=[c.marker_id for c in cars], fixed_ids=fixed_ids, full_search_every=10 ** 9,
                               car_dictionary=mk.dictionary, marker_offset_m=mk.offset_forward_m,
                               marker_offset_left_m=mk.offset_left_m, marker_yaw_rad=mk.yaw_rad)
    except Exception:
        world.close()
        raise
    return world, world, tracker, MultiCarEstimator(), world.serial_path, note


def _open_hardware(args, setup, cars, config):
    if getattr(args, "mocap", None) is not None:
        feed, tracker, estimator, note = open_mocap_hardware(args, setup, cars)
        if not Path(args.serial).exists() and "://" not in args.serial:
            feed.close()
            raise UserError(f"--serial: {args.serial}: no such device (is the transmitter box plugged in?)")
        return None, feed, tracker, estimator, args.serial, note

    try:
        calibration = load_calibration(args.calibration)
    except FileNotFoundError:
        raise UserError(f"--calibration: {args.calibration}: file not found (create it with python -m app calibrate)") from None
    except (CalibrationError, ValueError, OSError) as exc:
        raise UserError(f"--calibration: {exc}") from None
    if not Path(args.serial).exists() and "://" not in args.serial:
        raise UserError(f"--serial: {args.serial}: no such device (is the transmitter box plugged in?)")
    source = int(args.camera) if args.camera.isdigit() else args.camera
    try:
        camera = OpenCVCamera(source, latency_s=args.camera_latency_ms / 1e3)
    except CameraError as exc:
        raise UserError(f"--camera: {exc}") from None
    mk = setup.car.marker
    tracker = ArucoTracker(calibration, mk.size_m, mk.height_m, car_ids=[c.marker_id for c in cars],
                           full_search_every=10 ** 9, car_dictionary=mk.dictionary, marker_offset_m=mk.offset_forward_m,
                           marker_offset_left_m=mk.offset_left_m, marker_yaw_rad=mk.yaw_rad)
    return None, CameraFeed(camera), tracker, MultiCarEstimator(), args.serial, None


def _print(o, setup, args, mode, opponent) -> None:
    s = o.summary()
    print(f"race ({mode}): {setup.track.name}, {args.laps} lap(s), seed {args.seed}, RD3G starts {args.start} "
          f"({args.rd3g_speed} m/s) vs {opponent} ({args.opponent_speed} m/s); ended: {o.reason}")
    print(f"winner: {s['winner'] or 'none'}")
    for name, laps in (s["lap_times_s"] or {}).items():
        print(f"  {name:9s} lap times: {', '.join(f'{t:.3f} s' for t in laps) or '-'}")
    if s["min_gap_m"] is not None:
        print(f"minimum gap between footprints: {s['min_gap_m']:.3f} m; collisions: {s['collisions']}")
    f = lambda v, spec=".1f": "-" if v is None else format(v, spec)  # noqa: E731
    print(f"loop: {s['ticks']} ticks, median {f(s['loop_hz_median'])} Hz, period p99 {f(s['loop_period_p99_ms'], '.2f')} ms, "
          f"deadline misses {s['deadline_misses']} ({f(100 * (s['deadline_miss_rate'] or 0), '.2f')} %)")
    print("stages p50/p99 ms: " + ", ".join(f"{k} {f(s['stage_ms_p50'][k], '.2f')}/{f(s['stage_ms_p99'][k], '.2f')}"
                                            for k in s["stage_ms_p50"]))
    print(f"planning: {s['plans']} plans, RD3G solve p50 {f(s['solve_ms_p50'])} ms, p99 {f(s['solve_ms_p99'])} ms; "
          f"failures {s['plan_failures']}; applied {f(s['plan_lag_ms_p50'])} ms (p50), {f(s['plan_lag_ms_p99'])} ms (p99) "
          f"after the instant they were planned for; the cars got them {f(s['command_lag_ms_p50'])} ms (p50), "
          f"{f(s['command_lag_ms_p99'])} ms (p99) after it")
    print(f"camera: {s['frames']} frames processed, {s['frames_dropped']} dropped by the renderer, "
          f"render p50 {f(s['render_ms_p50'])} ms (not in the loop budget)")
    if s["tracking_error_mm_median"] is not None:
        print(f"tracking error vs simulator truth: median {s['tracking_error_mm_median']:.2f} mm, "
              f"p95 {s['tracking_error_mm_p95']:.2f} mm; heading median {s['tracking_heading_error_deg_median']:.2f} "
              f"deg, p95 {s['tracking_heading_error_deg_p95']:.2f} deg")
    print(f"events: {s['events']}; load average {', '.join(f'{v:.2f}' for v in s['load_average'] or [])}")
    print(f"telemetry: {o.recording}")
