"""`python -m app calibrate-camera IMAGES_OR_FOLDER... | --camera N --out intrinsics.json`: camera
intrinsics (focal lengths, principal point, distortion) from views of a ChArUco board (docs/tracking.md,
"Camera intrinsics")."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from app.cli import UserError
from fileio import InputFileError, check_output_path, read_bytes
from tracking.calibration import CalibrationError, save_intrinsics
from tracking.camera import CameraError, OpenCVCamera
from tracking.charuco import (MAX_BLUR_PX, MIN_VIEWS, BoardDetector, BoardView, CharucoBoardSpec, IntrinsicsCalibration,
                              calibrate_intrinsics, capture_views, load_board_file)
from vehicles.params import MARKER_DICTIONARY

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
MAX_IMAGE_BYTES = 256 * 2**20


def register(sub):
    p = sub.add_parser(
        "calibrate-camera", help="camera intrinsics from photographs (or a live camera) of a ChArUco board",
        description="Find a ChArUco board in each image, calibrate focal lengths, principal point and "
                    "distortion with OpenCV, report per-view errors, rejected views and uncertainties, and "
                    "write the intrinsics file that `calibrate --intrinsics` reads. Board geometry from "
                    "--board (written by make-board) or the --squares-x/--squares-y/--square-length/"
                    f"--marker-length options. At least {MIN_VIEWS} good views are needed (10-20 varied ones "
                    "are better). docs/tracking.md, \"Camera intrinsics\".")
    p.add_argument("images", nargs="*", metavar="IMAGES_OR_FOLDER", help="image files or folders of images")
    p.add_argument("--camera", help="live camera index (integer) or stream URL instead of images")
    p.add_argument("--every", type=int, default=10, metavar="K", help="with --camera: check every K-th frame (default 10)")
    p.add_argument("--views", type=int, default=20, help="with --camera: views to collect (default 20)")
    p.add_argument("--min-motion", type=float, default=0.05,
                   help="with --camera: keep a view once the board moved this fraction of the image diagonal "
                        "(default 0.05)")
    p.add_argument("--max-frames", type=int, default=None, help="with --camera: stop after this many frames")
    p.add_argument("--board", help="board file written by make-board (instead of the geometry options)")
    p.add_argument("--squares-x", type=int, help="squares along the board's x axis (columns)")
    p.add_argument("--squares-y", type=int, help="squares along the board's y axis (rows)")
    p.add_argument("--square-length", type=float, help="chessboard square side (m)")
    p.add_argument("--marker-length", type=float, help="marker side (m)")
    p.add_argument("--dictionary", help=f"ArUco dictionary, OpenCV name (default {MARKER_DICTIONARY})")
    p.add_argument("--legacy-pattern", action="store_true",
                   help="board printed with OpenCV up to 4.5 (or bought): other chessboard colour when "
                        "--squares-y is even")
    p.add_argument("--max-blur", type=float, default=MAX_BLUR_PX,
                   help=f"reject views whose edge blur (Gaussian sigma) exceeds this many px (default {MAX_BLUR_PX:g})")
    p.add_argument("--min-views", type=int, default=MIN_VIEWS,
                   help=f"good views required (default and least {MIN_VIEWS})")
    p.add_argument("--out", required=True, help="intrinsics JSON to write (read by calibrate --intrinsics, "
                                                "race --calibration via calibrate)")
    p.set_defaults(func=run)


GEOMETRY_OPTIONS = ("squares_x", "squares_y", "square_length", "marker_length", "dictionary", "legacy_pattern")


def board_spec(args) -> CharucoBoardSpec:
    given = [name for name in GEOMETRY_OPTIONS if getattr(args, name) not in (None, False)]
    if args.board:
        if given:
            raise UserError(f"--board {args.board} gives the geometry; leave out --{given[0].replace('_', '-')}")
        try:
            return load_board_file(args.board).board
        except CalibrationError as exc:
            raise UserError(f"--board: {exc}") from None
    missing = [name for name in GEOMETRY_OPTIONS[:4] if getattr(args, name) is None]
    if missing:
        raise UserError(f"board geometry: give --board FILE or --{missing[0].replace('_', '-')} "
                        "(and the other --squares-x/--squares-y/--square-length/--marker-length)")
    try:
        return CharucoBoardSpec(args.squares_x, args.squares_y, args.square_length, args.marker_length,
                                args.dictionary or MARKER_DICTIONARY, args.legacy_pattern)
    except ValueError as exc:
        raise geometry_option_error(exc) from None


def geometry_option_error(exc: ValueError) -> UserError:
    """A board geometry error as the option that set the field: "square_length_m: ..." -> "--square-length: ..."."""
    name, _, problem = str(exc).partition(": ")
    return UserError(f"--{name.removesuffix('_m').replace('_', '-')}: {problem}")


def image_files(arguments: list[str]) -> list[Path]:
    files: list[Path] = []
    for argument in arguments:
        path = Path(argument)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
            if not found:
                raise UserError(f"{path}: no image files ({', '.join(IMAGE_SUFFIXES)}) in this folder")
            files += found
        else:
            files.append(path)
    return files


def read_image(path: Path) -> np.ndarray:
    import cv2

    try:  # through fileio: cv2.imread says nothing about why, blocks on a FIFO and reads devices
        data = read_bytes(path, "board image", max_bytes=MAX_IMAGE_BYTES)
    except InputFileError as exc:
        raise UserError(str(exc)) from None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE) if data else None
    if image is None:
        raise UserError(f"{path}: not an image OpenCV can decode (empty, truncated or another format)")
    return image


def views_from_files(paths: list[Path], detector: BoardDetector) -> tuple[list[BoardView], tuple[int, int]]:
    from tqdm import tqdm

    views, size = [], None
    for path in tqdm(paths, desc="board images", unit="image", disable=len(paths) < 10):
        image = read_image(path)
        height, width = image.shape
        if size is None:
            size = (width, height)
        elif size != (width, height):
            raise UserError(f"{path}: image size {width}x{height} differs from {paths[0]}'s {size[0]}x{size[1]} "
                            "(one camera at one resolution per calibration)")
        views.append(detector.detect(image, str(path)))
    return views, size


def views_from_camera(args, detector: BoardDetector) -> tuple[list[BoardView], tuple[int, int]]:
    from tqdm import tqdm

    source = int(args.camera) if args.camera.isdigit() else args.camera
    try:
        camera = OpenCVCamera(source)
    except CameraError as exc:
        raise UserError(f"--camera: {exc}") from None
    print(f"move the board through the view (corners, edges, tilted both ways); {args.views} views wanted")
    try:
        with tqdm(total=args.views, desc="board views", unit="view") as bar:
            capture = capture_views(camera, detector, args.views, args.every, args.min_motion, args.max_frames,
                                    progress=lambda n: bar.update(n - bar.n))
    except CameraError as exc:
        raise UserError(f"--camera: {exc}") from None
    finally:
        camera.close()
    if capture.rejected:
        print("frames not taken: " + ", ".join(f"{n} {reason}" for reason, n in capture.rejected.items()))
    if capture.image_size is None:
        raise UserError(f"--camera {args.camera}: no frame delivered")
    return capture.views, capture.image_size


def report(result: IntrinsicsCalibration) -> None:
    k = result.intrinsics.camera_matrix
    print(f"views: {len(result.used)} used, {len(result.rejected)} rejected")
    for view in result.views:
        if view.rejected:
            print(f"  {view.name}: rejected, {view.rejected}")
        else:
            print(f"  {view.name}: {view.corners} corners, reprojection rms {view.rms_px:.3f} px, edge blur "
                  f"{view.blur_px:.2f} px, tilt {view.tilt_deg[0]:.0f}/{view.tilt_deg[1]:.0f} deg")
    print(f"reprojection error: rms {result.rms_px:.3f} px over {sum(v.corners for v in result.used)} corners")
    s = result.std_px
    print(f"fx {k[0, 0]:.2f} +- {s['fx']:.2f} px, fy {k[1, 1]:.2f} +- {s['fy']:.2f} px, "
          f"cx {k[0, 2]:.2f} +- {s['cx']:.2f} px, cy {k[1, 2]:.2f} +- {s['cy']:.2f} px (one standard deviation; "
          "3 of them bound the error, docs/tracking.md)")
    print("distortion (k1, k2, p1, p2, k3): " + ", ".join(f"{d:.5g}" for d in result.intrinsics.dist_coeffs))
    for warning in result.warnings:
        print(f"warning: {warning}")
    if not math.isfinite(result.rms_px) or result.rms_px > 1.0:
        print(f"warning: reprojection error {result.rms_px:.2f} px is large (a good calibration stays below "
              "0.5 px): check the board geometry (--legacy-pattern?) and that the board is flat")


def run(args) -> int:
    spec = board_spec(args)
    if bool(args.images) == bool(args.camera):
        raise UserError("give board images (files or folders) or --camera N, not both or neither")
    if args.min_views < MIN_VIEWS:
        raise UserError(f"--min-views: at least {MIN_VIEWS}, got {args.min_views}")
    try:
        detector = BoardDetector(spec, max_blur_px=args.max_blur)
    except ValueError as exc:
        raise UserError(f"--max-blur: {exc}") from None
    check_output_path(args.out)  # before the images are read or a camera opened
    print(f"board: {spec.describe()}")
    if args.camera:
        views, size = views_from_camera(args, detector)
    else:
        views, size = views_from_files(image_files(args.images), detector)
    try:
        result = calibrate_intrinsics(views, size, args.min_views)
    except CalibrationError as exc:
        source = f" from --board {args.board}" if args.board else ""
        raise UserError(f"{exc} (board: {spec.describe()}{source})") from None
    report(result)
    save_intrinsics(args.out, result.intrinsics)
    print(f"wrote {args.out} ({size[0]}x{size[1]})")
    return 0
