"""`python -m app track VIDEO_OR_FOLDER --calibration CAL.json --markers 3,7 | --car-params FILE... --out
POSES.csv [--fps F] [--raw] [--link-capture CAP.txt [--link-offset S] [--link-protocol P]]`: the car
poses of a recorded video (docs/tracking.md, "Tracking a recorded video")."""
from __future__ import annotations

import os
import time
from functools import partial

from app.cli import UserError
from fileio import check_output_path
from race.commands import physical_command
from race.video_tracking import TrackedCar, VideoTrackError, commands_at, track_video, write_track_csv
from tracking.calibration import CalibrationError, load_calibration
from tracking.camera import CameraError, ImageFolderCamera, ReadAhead, VideoFileCamera
from tracking.estimator import MultiCarEstimator
from tracking.markers import ArucoTracker
from vehicles.fhss import servo_calibration
from vehicles.link_capture import CaptureError, decode_capture, read_capture
from vehicles.link_protocols import HARDWARE_DEFAULT, PROTOCOLS, check_protocol
from vehicles.params import CarParamsError, load_car_params
from vehicles.protocol import CarCommand, ProtocolError

DEFAULT_CAR = "buzzracer"  # the race's default car file: marker geometry and actuators with --markers


def register(sub) -> None:
    p = sub.add_parser("track", help="track the cars of a recorded video (or image folder) into a CSV of poses",
                       description="Runs the race loop's marker tracker and estimator over every frame of a video "
                                   "and writes t,car,x,y,heading per car and frame in which it was found; with "
                                   "--link-capture also the throttle and steering in effect (a sysid drive log).")
    p.add_argument("video", metavar="VIDEO_OR_FOLDER", help="video file (any OpenCV can read) or folder of images")
    p.add_argument("--calibration", required=True, help="calibration JSON of the camera (python -m app calibrate)")
    cars = p.add_mutually_exclusive_group(required=True)
    cars.add_argument("--markers", help="car marker ids, comma-separated (marker geometry from "
                                        f"vehicles/{DEFAULT_CAR}.toml)")
    cars.add_argument("--car-params", nargs="+", metavar="FILE", help="car files: their marker ids and geometry")
    p.add_argument("--out", required=True, help="CSV to write")
    p.add_argument("--fps", type=float, default=None,
                   help="frame rate of an image folder (t = index / fps); a video uses its own timestamps")
    p.add_argument("--raw", action="store_true", help="the tracker's detections, without the estimator")
    p.add_argument("--link-capture", metavar="CAP.txt", help="the race's --link-capture file: adds throttle and "
                                                             "steering columns (the command in effect at each row)")
    p.add_argument("--link-offset", type=float, default=0.0, metavar="S",
                   help="seconds added to the capture's times to put them on the video's clock (default 0: "
                        "capture and video started together)")
    p.add_argument("--link-protocol", default=HARDWARE_DEFAULT, metavar="|".join(PROTOCOLS),
                   help=f"frame format of the capture (default {HARDWARE_DEFAULT})")
    p.add_argument("--link-failsafe", type=float, default=0.1, metavar="S",
                   help="the box's silence failsafe: a command older than S is neutral (default 0.1, the virtual "
                        "box's and the HIL race's)")
    p.add_argument("--radio-ids", help="radio ids of the cars in the capture, in --markers/--car-params order "
                                       "(default: rd3g the marker ids, buzzracer-fhss the car files' radio.modem_id)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _ids(text: str, flag: str) -> list[int]:
    try:
        ids = [int(v) for v in text.split(",")]
    except ValueError:
        raise UserError(f"{flag}: expected comma-separated integer ids, got {text!r}") from None
    if len(set(ids)) != len(ids) or any(i < 0 for i in ids):
        raise UserError(f"{flag}: ids must be distinct and >= 0, got {text!r}")
    return ids


def _car_files(args) -> tuple[list[int], list]:
    """(marker ids, car file per car)."""
    try:
        if args.markers is not None:
            car = load_car_params(DEFAULT_CAR)
            ids = _ids(args.markers, "--markers")
            return ids, [car] * len(ids)
        files = [load_car_params(f) for f in args.car_params]
    except CarParamsError as exc:
        raise UserError(f"--car-params: {exc}") from None
    ids = [c.marker.aruco_id for c in files]
    if len(set(ids)) != len(ids):
        raise UserError(f"--car-params: two car files have the same marker.aruco_id ({ids}); each car needs its own")
    for attr in ("size_m", "height_m", "dictionary"):
        values = {getattr(c.marker, attr) for c in files}
        if len(values) > 1:
            raise UserError(f"--car-params: marker.{attr} differs between the car files ({sorted(values)}); "
                            "the tracker reads one marker geometry")
    return ids, files


def _from_pulses(calibration, steering_us: float, throttle_us: float) -> tuple[float, float]:
    """FHSS pulse widths -> (throttle, wheel angle rad), as the car's receiver turns them."""
    return calibration.throttle(throttle_us), calibration.steering_rad(steering_us)


def _from_normalised(car, steering: float, throttle: float) -> tuple[float, float]:
    """rd3g normalised values -> (throttle, wheel angle rad)."""
    return physical_command(car, CarCommand(steering, throttle))


def _link_cars(args, ids, files) -> list[TrackedCar]:
    protocol = args.link_protocol
    if args.radio_ids:
        radios = _ids(args.radio_ids, "--radio-ids")
        if len(radios) != len(ids):
            raise UserError(f"--radio-ids: {len(radios)} ids for {len(ids)} cars")
    elif protocol == "buzzracer-fhss":
        radios = [c.radio.modem_id for c in files]
        if args.markers is not None or None in radios:
            raise UserError("--link-protocol buzzracer-fhss: give --radio-ids (modem ids) or car files with "
                            "radio.modem_id")
    else:
        radios = ids
    cars = []
    for marker, radio, car in zip(ids, radios, files):
        if protocol == "buzzracer-fhss":
            try:
                convert = partial(_from_pulses, servo_calibration(car, radio))
            except ProtocolError as exc:
                raise UserError(f"--radio-ids: {exc}") from None
        else:
            convert = partial(_from_normalised, car)
        cars.append(TrackedCar(marker, radio, convert))
    return cars


def _source(args):
    if os.path.isdir(args.video):
        if args.fps is None:
            raise UserError(f"{args.video}: a folder of images needs --fps (the camera's frame rate)")
        return ReadAhead(ImageFolderCamera(args.video, args.fps))
    if args.fps is not None:
        raise UserError("--fps: only for an image folder; a video's own timestamps are used")
    return ReadAhead(VideoFileCamera(args.video, clock="container", grey=True))  # decoding overlaps tracking


def run(args) -> int:
    check_output_path(args.out)
    if not args.link_failsafe > 0:
        raise UserError(f"--link-failsafe: must be positive, got {args.link_failsafe}")
    ids, files = _car_files(args)
    try:
        calibration = load_calibration(args.calibration)
    except CalibrationError as exc:
        raise UserError(f"--calibration: {exc}") from None
    decode = None
    if args.link_capture:
        try:
            check_protocol(args.link_protocol, "--link-protocol")
            decode = decode_capture(read_capture(args.link_capture), args.link_protocol)
        except CaptureError as exc:
            raise UserError(f"--link-capture: {exc}") from None
        cars = _link_cars(args, ids, files)
    else:
        cars = [TrackedCar(m) for m in ids]
    marker = files[0].marker
    try:
        tracker = ArucoTracker(calibration, marker.size_m, marker.height_m, car_ids=ids, full_search_every=10 ** 9,
                               car_dictionary=marker.dictionary)
    except ValueError as exc:
        raise UserError(f"--calibration {args.calibration} / car markers: {exc}") from None
    try:
        source = _source(args)
    except CameraError as exc:
        raise UserError(str(exc)) from None
    from tqdm import tqdm  # only the CLI shows progress

    bar = tqdm(total=getattr(source, "frame_count", None), unit="frame", desc="track",
               disable=args.no_progress or None, mininterval=1.0)
    start = time.perf_counter()
    try:
        result = track_video(source, tracker, cars, None if args.raw else MultiCarEstimator(),
                             calibration_path=args.calibration,
                             progress=bar.update)
    except (VideoTrackError, CameraError) as exc:
        raise UserError(str(exc)) from None
    finally:
        bar.close()
        source.close()
    elapsed = time.perf_counter() - start
    if decode is not None:
        try:
            result.commands, result.command_notes = commands_at(decode, cars, result.rows, args.link_offset,
                                                                args.link_failsafe, source=args.link_capture)
        except ValueError as exc:
            raise UserError(f"--link-capture: {exc}") from None
    write_track_csv(args.out, result)
    w, h = result.image_size
    print(f"{args.video}: {result.frames} frames {w}x{h} px tracked in {elapsed:.1f} s "
          f"({result.frames / max(elapsed, 1e-9):.1f} frames/s), {'raw detections' if args.raw else 'filtered'}")
    for m in ids:
        found = int((result.rows[:, 1] == m).sum())
        print(f"  car {m}: {found} rows; not found in {result.missed[m]} frames"
              + ("" if args.raw else f", detection rejected by the filter in {result.gated[m]}"))
    if decode is not None:
        print(f"  commands from {args.link_capture} ({args.link_protocol}, {len(decode.frames)} good frames, "
              f"{decode.bad_frames} bad, offset {args.link_offset:+.3f} s)")
        for note in result.command_notes:
            print(f"  {note}")
    print(f"wrote {args.out} ({len(result.rows)} rows)")
    return 0
