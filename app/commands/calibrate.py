"""`python -m app calibrate --image FILE | --camera INDEX --fixed-markers FILE.json
[--intrinsics FILE] --out calibration.json`: camera-to-track calibration from one frame."""
from __future__ import annotations

import math

from app.cli import UserError
from fileio import InputFileError, check_output_path, read_bytes
from tracking.calibration import CalibrationError, calibrate_image, load_fixed_markers, load_intrinsics, save_calibration
from tracking.camera import CameraError, OpenCVCamera


def register(sub):
    p = sub.add_parser(
        "calibrate", help="camera-to-track calibration from fixed ArUco markers at surveyed points",
        description="Detect the fixed markers in one frame, compute the camera pose (and, without "
                    "--intrinsics, the focal length), report the reprojection error and save the "
                    "calibration. File formats: docs/tracking.md.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--image", help="image file of the arena")
    src.add_argument("--camera", help="camera index (integer) or stream URL to grab one frame from")
    p.add_argument("--fixed-markers", required=True, help="JSON: marker id -> track x, y, size (see docs)")
    p.add_argument("--intrinsics", help="camera matrix + distortion (JSON, or OpenCV YAML/XML)")
    p.add_argument("--out", required=True, help="calibration JSON to write")
    p.add_argument("--warmup-frames", type=int, default=10,
                   help="with --camera: frames to discard while exposure settles (default 10)")
    p.set_defaults(func=run)


def _grab(camera_arg: str, warmup: int):
    source = int(camera_arg) if camera_arg.isdigit() else camera_arg
    try:
        cam = OpenCVCamera(source)
        try:
            for _ in range(max(warmup, 0)):
                cam.read()
            return cam.read().image
        finally:
            cam.close()
    except CameraError as exc:
        raise UserError(f"--camera: {exc}") from None


def run(args) -> int:
    import cv2

    check_output_path(args.out)  # before a camera is opened
    marker_set = load_fixed_markers(args.fixed_markers)
    intrinsics = load_intrinsics(args.intrinsics) if args.intrinsics else None
    if args.image:
        import numpy as np

        try:  # read through fileio: cv2.imread blocks on a FIFO and reads devices
            data = read_bytes(args.image, "image", max_bytes=256 * 2**20)
        except InputFileError as exc:
            raise UserError(f"--image: {exc}") from None
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE) if data else None
        if image is None:
            raise UserError(f"--image: cannot read {args.image!r} (not an image OpenCV can decode)")
    else:
        image = _grab(args.camera, args.warmup_frames)
    inputs = f"--fixed-markers {args.fixed_markers}" + (f", --intrinsics {args.intrinsics}" if args.intrinsics else "")
    try:
        cal = calibrate_image(image, marker_set, intrinsics)
    except cv2.error as exc:  # OpenCV's assertions on degenerate input (a file's values it cannot use)
        raise UserError(f"calibration failed in OpenCV ({inputs}): {str(exc).strip().splitlines()[-1]}") from None
    except CalibrationError as exc:  # the files loaded, but their values do not fit this image: name them
        raise UserError(f"{exc} ({inputs})") from None
    save_calibration(args.out, cal)
    cam = cal.camera
    print(f"markers used: {cal.markers_used}" + (f"; not found: {cal.markers_missing}" if cal.markers_missing else ""))
    for marker_id, err in cal.marker_errors_px.items():
        print(f"  marker {marker_id}: reprojection rms {err:.3f} px")
    print(f"reprojection error: rms {cal.reprojection_rms_px:.3f} px, max {cal.reprojection_max_px:.3f} px")
    fx = cam.camera_matrix[0, 0]
    focal = f"focal length {fx:.1f} px ({cal.intrinsics_source}"
    if cal.focal_std_px is not None:
        focal += (f", std {cal.focal_std_px:.1f} px: {cal.focal_std_markers_px:.1f} over marker resamples, "
                  f"{cal.focal_std_principal_point_px:.1f} from the unknown principal point")
    print(focal + ")")
    x, y, z = cam.position
    tilt = math.degrees(math.acos(min(1.0, abs(cam.rotation[2] @ [0.0, 0.0, -1.0]))))
    print(f"camera at x={x:.3f} y={y:.3f} z={z:.3f} m, optical axis {tilt:.1f} deg from vertical")
    if cal.intrinsics_source == "estimated" and cal.focal_std_px is not None and cal.focal_std_px > 0.02 * fx:
        print("warning: the focal length is poorly determined from this view (a single view cannot place the "
              "principal point; the more the camera looks straight down, the more the focal length depends on "
              "it); marker-height correction will be inaccurate: pass --intrinsics")
    print(f"wrote {args.out}")
    return 0
