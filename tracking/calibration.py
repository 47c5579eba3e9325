"""Camera-to-track calibration from fixed ArUco markers at surveyed track points.

File formats (documented in docs/tracking.md):

* fixed-marker file (JSON): ``{"dictionary": "DICT_4X4_50", "markers": {"40": {"x": .., "y": ..,
  "size": .., "heading_deg": .. (optional), "z": .. (optional)}, ...}}``;
* intrinsics file: JSON ``{"image_width", "image_height", "camera_matrix", "dist_coeffs"}`` or an
  OpenCV FileStorage YAML/XML as written by OpenCV's calibration sample (``camera_matrix``,
  ``distortion_coefficients``, ``image_width``, ``image_height``);
* calibration output (JSON) written by :func:`save_calibration`.
"""
from __future__ import annotations

import functools
import json
import math
import warnings
from dataclasses import dataclass, field
from typing import Callable
from pathlib import Path

import cv2
import numpy as np

import fileio
from fileio import unknown_key_message

from tracking.geometry import PinholeCamera
from vehicles.params import MARKER_DICTIONARY

CALIBRATION_FORMAT_VERSION = 1


MAX_FILE_BYTES = 4 * 2**20
# Fixed-marker coordinates and sizes (m) and distortion coefficients beyond these are typos, not arenas:
# a 2**64 m marker put the camera "below the track", a 1e308 coefficient made OpenCV's pose solver assert.
MAX_ARENA_M = 1000.0
MAX_MARKER_M = 10.0
MAX_DISTORTION = 1e4


class CalibrationError(fileio.InputFileError):
    """Calibration input is invalid or the frame does not allow a calibration."""


# --------------------------------------------------------------------------- fixed markers
@dataclass(frozen=True)
class FixedMarker:
    """A marker lying flat at a surveyed place. ``heading_rad`` is the direction of the marker's
    top edge (the edge from its first to second corner points to the right of it); None if not
    surveyed, in which case only the centre is used."""

    marker_id: int
    x: float
    y: float
    size: float
    heading_rad: float | None = None
    z: float = 0.0

    def corners(self) -> np.ndarray:
        """Track-frame corners (4,3) in ArUco order (top-left, top-right, bottom-right, bottom-left)."""
        if self.heading_rad is None:
            raise ValueError(f"marker {self.marker_id}: heading not surveyed, corners unknown")
        return marker_corners_track(self.x, self.y, self.heading_rad, self.size, self.z)


@dataclass
class FixedMarkerSet:
    dictionary: str
    markers: dict[int, FixedMarker]


def marker_corners_track(x, y, heading, size, z=0.0) -> np.ndarray:
    """Corners of a horizontal square marker whose top edge faces ``heading``.

    Marker-local axes: u along ``heading`` (towards the marker's top edge), v to its left.
    ArUco corner order top-left, top-right, bottom-right, bottom-left = (+u,+v), (+u,-v),
    (-u,-v), (-u,+v), i.e. clockwise when seen from above.
    """
    half = size / 2.0
    local = np.array([[half, half], [half, -half], [-half, -half], [-half, half]])
    c, s = math.cos(heading), math.sin(heading)
    xy = local @ np.array([[c, s], [-s, c]]) + np.array([x, y])
    return np.column_stack([xy, np.full(4, z)])


def aruco_dictionary_id(name: str, field_name: str = "dictionary") -> int:
    value = getattr(cv2.aruco, str(name), None)
    if not isinstance(name, str) or not name.startswith("DICT_") or not isinstance(value, int):
        raise CalibrationError(f"{field_name}: unknown ArUco dictionary {name!r} (an OpenCV name such as "
                               f"{MARKER_DICTIONARY!r} or 'DICT_6X6_250')")
    return value


def _number(value, where: str, positive: bool = False, bound: float = 1e300) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or abs(value) > 1e300 or not math.isfinite(value):
        raise CalibrationError(f"{where}: must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise CalibrationError(f"{where}: must be positive, got {value!r}")
    if abs(value) > bound:
        raise CalibrationError(f"{where}: must be within +-{bound:g}, got {value!r}")
    return float(value)


def parse_fixed_markers(data, source: str = "fixed markers") -> FixedMarkerSet:
    if not isinstance(data, dict):
        raise CalibrationError(f"{source}: top level must be a JSON object")
    for key in data:
        if key not in ("dictionary", "markers", "description"):
            raise CalibrationError(f"{source}: {key}: {unknown_key_message(key, ('dictionary', 'markers', 'description'))}")
    dictionary = data.get("dictionary", MARKER_DICTIONARY)
    dict_id = aruco_dictionary_id(dictionary, f"{source}: dictionary")
    n_ids = cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0]
    raw = data.get("markers")
    if not isinstance(raw, dict) or not raw:
        raise CalibrationError(f"{source}: markers: must be a non-empty object mapping marker id -> marker")
    markers: dict[int, FixedMarker] = {}
    for key, entry in raw.items():
        where = f"{source}: markers[{key!r}]"
        if not key.isdigit() or len(key) > 9:  # int() would also take " 4", "+4", "4_0" and "٤"
            raise CalibrationError(f"{where}: key must be an integer marker id")
        marker_id = int(key)
        if not 0 <= marker_id < n_ids:
            raise CalibrationError(f"{where}: id outside {dictionary} (0..{n_ids - 1})")
        if marker_id in markers:  # "40" and "040" are one marker: which survey would be used?
            twin = next(k for k in raw if k != key and int(k) == marker_id)
            raise CalibrationError(f"{where}: marker id {marker_id} appears twice (also as {twin!r})")
        if not isinstance(entry, dict):
            raise CalibrationError(f"{where}: must be an object with x, y, size")
        for key in entry:
            if key not in ("x", "y", "size", "heading_deg", "z"):
                raise CalibrationError(f"{where}.{key}: {unknown_key_message(key, ('x', 'y', 'size', 'heading_deg', 'z'))}")
        for name in ("x", "y", "size"):
            if name not in entry:
                raise CalibrationError(f"{where}.{name}: missing")
        heading = entry.get("heading_deg")
        if "heading_deg" in entry and heading is None:  # null is not "absent": a damaged value must not pass
            raise CalibrationError(f"{where}.heading_deg: must be a finite number (leave the key out when the "
                                   "heading is unknown), got null")
        markers[marker_id] = FixedMarker(
            marker_id=marker_id,
            x=_number(entry["x"], f"{where}.x", bound=MAX_ARENA_M),
            y=_number(entry["y"], f"{where}.y", bound=MAX_ARENA_M),
            size=_number(entry["size"], f"{where}.size", positive=True, bound=MAX_MARKER_M),
            heading_rad=None if heading is None else math.radians(_number(heading, f"{where}.heading_deg", bound=1e6)),
            z=_number(entry.get("z", 0.0), f"{where}.z", bound=MAX_ARENA_M),
        )
    return FixedMarkerSet(dictionary=dictionary, markers=markers)


def _load_json(path, what: str):
    return fileio.load_json(path, what, max_bytes=MAX_FILE_BYTES, error=CalibrationError)


def load_fixed_markers(path) -> FixedMarkerSet:
    return parse_fixed_markers(_load_json(path, "fixed-marker file"), str(path))


# --------------------------------------------------------------------------- intrinsics
@dataclass
class Intrinsics:
    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple[int, int]  # (width, height)


def _matrix(value, shape, where) -> np.ndarray:
    if not _numeric_nest(value):
        raise CalibrationError(f"{where}: must be numbers (nested lists of numbers), got {fileio.schema.show(value)}")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{where}: must be a rectangular array of numbers") from None
    if shape is not None and arr.shape != shape:
        raise CalibrationError(f"{where}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{where}: contains non-finite values")
    return arr


def _numeric_nest(value) -> bool:
    """Numbers or nested lists of numbers; not booleans or strings (which numpy would convert)."""
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "fiu"
    if isinstance(value, list):
        return all(_numeric_nest(v) for v in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _validate_intrinsics(k: np.ndarray, dist: np.ndarray, size, source: str) -> Intrinsics:
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise CalibrationError(f"{source}: camera_matrix: focal lengths must be positive")
    if k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1 or k[1, 0] != 0:
        raise CalibrationError(f"{source}: camera_matrix: last row must be [0, 0, 1] and [1][0] zero")
    dist = dist.ravel()
    if dist.size not in (0, 4, 5, 8, 12, 14):
        raise CalibrationError(f"{source}: dist_coeffs: OpenCV needs 4, 5, 8, 12 or 14 values, got {dist.size}")
    if np.any(np.abs(dist) > MAX_DISTORTION):  # larger ones make OpenCV's pose solvers assert (cv2.error)
        raise CalibrationError(f"{source}: dist_coeffs: each must be within +-{MAX_DISTORTION:g}, got {dist.tolist()}")
    width, height = size
    for name, value in (("image_width", width), ("image_height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 2**31 or int(value) != value:
            raise CalibrationError(f"{source}: {name}: must be a positive integer, got {value!r}")
    for axis, c, name, n in (("x", k[0, 2], "image_width", width), ("y", k[1, 2], "image_height", height)):
        if not 0 <= c <= n:  # each valid alone, together a camera whose optical axis misses its own image
            raise CalibrationError(f"{source}: camera_matrix: principal point {axis} ({c:g} px) must lie inside the "
                                   f"image (0..{name} = {int(n)})")
    return Intrinsics(k, dist if dist.size else np.zeros(5), (int(width), int(height)))


def load_intrinsics(path) -> Intrinsics:
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml", ".xml"):
        text = fileio.read_text(path, "intrinsics file", max_bytes=MAX_FILE_BYTES, error=CalibrationError)
        try:
            storage = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        except cv2.error:
            raise CalibrationError(f"{path}: OpenCV could not parse this FileStorage file") from None
        if not storage.isOpened():
            raise CalibrationError(f"{path}: OpenCV could not read this FileStorage file")
        try:
            fields = {}
            for name in ("camera_matrix", "distortion_coefficients", "image_width", "image_height"):
                node = storage.getNode(name)
                if node.empty():
                    raise CalibrationError(f"{path}: {name}: missing")
                fields[name] = node.mat() if name.endswith(("matrix", "coefficients")) else node.real()
        finally:
            storage.release()
        k = _matrix(fields["camera_matrix"], (3, 3), f"{path}: camera_matrix")
        dist = _matrix(fields["distortion_coefficients"], None, f"{path}: distortion_coefficients")
        return _validate_intrinsics(k, dist, (fields["image_width"], fields["image_height"]), str(path))
    data = _load_json(path, "intrinsics file")
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: top level must be a JSON object")
    extra = [k for k in data if k not in INTRINSICS_KEYS]
    if extra:  # intrinsics often come from other tools, which add their own keys: named, not fatal
        warnings.warn(f"{path}: ignoring {', '.join(unknown_key_message(k, INTRINSICS_KEYS) for k in extra)}",
                      stacklevel=2)
    for name in ("camera_matrix", "dist_coeffs", "image_width", "image_height"):
        if name not in data:
            raise CalibrationError(f"{path}: {name}: missing")
    k = _matrix(data["camera_matrix"], (3, 3), f"{path}: camera_matrix")
    dist = _matrix(data["dist_coeffs"], None, f"{path}: dist_coeffs")
    return _validate_intrinsics(k, dist, (data["image_width"], data["image_height"]), str(path))


INTRINSICS_KEYS = ("image_width", "image_height", "camera_matrix", "dist_coeffs")


def _check_keys(data: dict, allowed, source: str) -> None:
    for key in data:
        if key not in allowed:
            raise CalibrationError(f"{source}: {key}: {unknown_key_message(key, allowed)}")


def save_intrinsics(path, intrinsics: Intrinsics) -> None:
    fileio.atomic_write_text(path, json.dumps({
        "image_width": intrinsics.image_size[0],
        "image_height": intrinsics.image_size[1],
        "camera_matrix": intrinsics.camera_matrix.tolist(),
        "dist_coeffs": intrinsics.dist_coeffs.tolist(),
    }, indent=2))


# --------------------------------------------------------------------------- calibration
@dataclass
class CameraCalibration:
    """Camera-to-track mapping. ``camera`` holds intrinsics, distortion and pose; pixels map to
    the track plane (or to the plane of a raised marker) with ``camera.pixels_to_plane``."""

    camera: PinholeCamera
    dictionary: str = MARKER_DICTIONARY
    intrinsics_source: str = "file"  # "file" or "estimated" (single-view, see docs/tracking.md)
    focal_std_px: float | None = None  # estimated focal length: standard deviation, both sources below combined
    focal_std_markers_px: float | None = None  # spread over marker bootstrap resamples (noise, lens misfit)
    focal_std_principal_point_px: float | None = None  # from the principal point's prior (PRINCIPAL_POINT_STD)
    reprojection_rms_px: float = float("nan")
    reprojection_max_px: float = float("nan")
    marker_errors_px: dict[int, float] = field(default_factory=dict)
    markers_missing: list[int] = field(default_factory=list)

    @property
    def markers_used(self) -> list[int]:
        return sorted(self.marker_errors_px)

    def track_to_image_homography(self) -> np.ndarray:
        """Track plane (z = 0) to ideal (undistorted) pixels."""
        return self.camera.plane_homography(0.0)


def _diagonal_intersection(quad: np.ndarray) -> np.ndarray:
    """Image of a square's centre: the intersection of the quad's diagonals (exact under perspective)."""
    p0, p1, p2, p3 = (np.append(q, 1.0) for q in quad)
    x = np.cross(np.cross(p0, p2), np.cross(p1, p3))
    return x[:2] / x[2]


def correspondences(detected: dict[int, np.ndarray], marker_set: FixedMarkerSet,
                    undistort: Callable | None = None):
    """Track points (N,3), ideal pixels (N,2) and the marker id of each row."""
    obj, img, ids = [], [], []
    for marker_id, marker in sorted(marker_set.markers.items()):
        if marker_id not in detected:
            continue
        quad = np.asarray(detected[marker_id], float).reshape(4, 2)
        if undistort is not None:
            quad = undistort(quad)
        if marker.heading_rad is not None:
            obj.append(marker.corners())
            img.append(quad)
            ids += [marker_id] * 4
        else:
            obj.append([[marker.x, marker.y, marker.z]])
            img.append(_diagonal_intersection(quad)[None])
            ids.append(marker_id)
    if not obj:
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, int)
    return np.vstack(obj), np.vstack(img), np.asarray(ids)


# Single-view focal length (docs/tracking.md, "Method"). One view of a plane gives two constraints on
# the intrinsics, so the principal point is fixed at the image centre; real lenses put it elsewhere
# (OpenCV's calibration of its tutorial camera: 38 px = 8 % of the height off), and the focal length
# follows it (about 2 px per px there). Its uncertainty therefore adds the spread over bootstrap
# resamples of the markers to the effect of a principal point PRINCIPAL_POINT_STD of the image
# diagonal off-centre (1 sigma, each axis).
PRINCIPAL_POINT_STD = 0.05
FOCAL_BOOTSTRAP_SAMPLES = 100
MAX_FOCAL_MARKER_STD = 0.10  # relative: beyond it the markers do not determine the focal length (3 deg tilt: 17 %)


@dataclass(frozen=True)
class FocalEstimate:
    camera_matrix: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    std_markers_px: float
    std_principal_point_px: float

    @property
    def std_px(self) -> float:
        return math.hypot(self.std_markers_px, self.std_principal_point_px)


def _fit_focal(obj, img, image_size, principal_point):
    width, height = image_size
    k0 = np.array([[max(width, height), 0, principal_point[0]], [0, max(width, height), principal_point[1]], [0, 0, 1]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    _, k, _, rvecs, tvecs = cv2.calibrateCamera([obj.astype(np.float32)], [img.astype(np.float32)],
                                                (width, height), k0, np.zeros(5), flags=flags)
    return k, rvecs[0], tvecs[0]


def estimate_focal_length(obj: np.ndarray, img: np.ndarray, groups: np.ndarray, image_size: tuple[int, int],
                          seed: int = 0) -> FocalEstimate:
    """One focal length (square pixels, principal point at the image centre, no distortion) and the
    pose from track points ``obj`` (N,3) seen at pixels ``img`` (N,2); ``groups`` names the marker of
    each point (the bootstrap resamples whole markers). CalibrationError when the markers do not
    determine the focal length (e.g. a view straight down on a flat scene, where focal length and
    height trade off): bootstrap spread above MAX_FOCAL_MARKER_STD or a failed fit."""
    width, height = image_size
    centre = np.array([(width - 1) / 2, (height - 1) / 2])
    try:
        k, rvec, tvec = _fit_focal(obj, img, image_size, centre)
    except cv2.error as exc:
        raise CalibrationError(f"focal-length estimation failed ({exc.err}); supply --intrinsics") from None
    focal = float(k[0, 0])
    rng = np.random.default_rng(seed)
    names = np.unique(groups)
    rows = {g: np.flatnonzero(groups == g) for g in names}
    samples = []
    for _ in range(FOCAL_BOOTSTRAP_SAMPLES):
        pick = np.concatenate([rows[g] for g in rng.choice(names, len(names))])
        try:
            samples.append(float(_fit_focal(obj[pick], img[pick], image_size, centre)[0][0, 0]))
        except cv2.error:
            samples.append(math.nan)  # a degenerate resample (e.g. all points on a line) says as much
    samples = np.asarray(samples)
    spread = float(np.std(samples[np.isfinite(samples)])) if np.isfinite(samples).sum() > 1 else math.inf
    if not (np.isfinite(samples).mean() > 0.9 and spread <= MAX_FOCAL_MARKER_STD * focal and 0 < focal < math.inf):
        raise CalibrationError(
            f"the view does not determine the focal length (estimate {focal:.0f} px, spread over marker resamples "
            f"{spread:.0f} px = {100 * spread / focal:.0f} %, limit {100 * MAX_FOCAL_MARKER_STD:.0f} %): a camera "
            "looking straight down at a flat scene cannot tell focal length from height; supply --intrinsics")
    step = PRINCIPAL_POINT_STD * math.hypot(width, height)
    slopes = []
    for axis in (0, 1):
        shifted = [centre + sign * step * np.eye(2)[axis] for sign in (-1, 1)]
        f_minus, f_plus = (float(_fit_focal(obj, img, image_size, pp)[0][0, 0]) for pp in shifted)
        slopes.append((f_plus - f_minus) / 2)  # focal-length change for a 1-sigma principal-point offset
    return FocalEstimate(k, rvec, tvec, spread, float(np.hypot(*slopes)))


def calibrate_from_detections(detected: dict[int, np.ndarray], marker_set: FixedMarkerSet,
                              image_size: tuple[int, int], intrinsics: Intrinsics | None = None
                              ) -> CameraCalibration:
    """Camera pose (and, without ``intrinsics``, the focal length) from detected fixed markers.

    ``detected`` maps marker id -> its 4 image corners in ArUco order (raw pixels).
    With intrinsics: corners are undistorted, then ``cv2.solvePnP`` (SQPnP + Levenberg-Marquardt
    refinement). Without: :func:`estimate_focal_length` (one focal length and its uncertainty, or
    CalibrationError if the view does not determine it).
    """
    width, height = int(image_size[0]), int(image_size[1])
    if intrinsics is not None and tuple(intrinsics.image_size) != (width, height):
        raise CalibrationError(
            f"intrinsics image_width/image_height {intrinsics.image_size} differ from the frame size {(width, height)}")
    missing = sorted(set(marker_set.markers) - set(detected))
    if intrinsics is not None:
        probe = PinholeCamera(intrinsics.camera_matrix, intrinsics.dist_coeffs, np.eye(3), np.zeros(3), (width, height))
        obj, img, ids = correspondences(detected, marker_set, probe.undistort_pixels)
    else:
        obj, img, ids = correspondences(detected, marker_set)
    found = sorted(set(ids.tolist()))
    if len(obj) < 4:
        raise CalibrationError(
            f"need at least 4 surveyed points (marker corners with heading_deg, or marker centres); found "
            f"markers {found}, missing {missing}")
    centred = obj - obj.mean(axis=0)
    if np.linalg.matrix_rank(centred, tol=1e-3) < 2:
        raise CalibrationError(f"fixed markers {found} are collinear; spread them over the arena")

    focal: FocalEstimate | None = None
    if intrinsics is not None:
        k = intrinsics.camera_matrix
        ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise CalibrationError("solvePnP failed on the fixed markers")
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec, tvec)
        dist = intrinsics.dist_coeffs
        source = "file"
    else:
        estimate = estimate_focal_length(obj, img, ids, (width, height))
        k, rvec, tvec = estimate.camera_matrix, estimate.rvec, estimate.tvec
        dist = np.zeros(5)
        focal = estimate
        source = "estimated"
    rot, _ = cv2.Rodrigues(rvec)
    camera = PinholeCamera(k, dist, rot, tvec.ravel(), (width, height))
    if camera.position[2] <= 0:
        raise CalibrationError("calibration places the camera below the track; check the marker coordinates")
    # Reprojection error in raw (distorted) pixels, per marker and overall.
    raw_obj, raw_img, raw_ids = correspondences(detected, marker_set)
    residual = np.linalg.norm(camera.project(raw_obj) - raw_img, axis=1)
    per_marker = {int(m): float(np.sqrt(np.mean(residual[raw_ids == m] ** 2))) for m in found}
    return CameraCalibration(
        camera=camera, dictionary=marker_set.dictionary, intrinsics_source=source,
        focal_std_px=None if focal is None else focal.std_px,
        focal_std_markers_px=None if focal is None else focal.std_markers_px,
        focal_std_principal_point_px=None if focal is None else focal.std_principal_point_px,
        reprojection_rms_px=float(np.sqrt(np.mean(residual ** 2))), reprojection_max_px=float(residual.max()),
        marker_errors_px=per_marker, markers_missing=missing)


def calibrate_image(image: np.ndarray, marker_set: FixedMarkerSet, intrinsics: Intrinsics | None = None
                    ) -> CameraCalibration:
    """Detect the fixed markers in one frame and calibrate (see :func:`calibrate_from_detections`)."""
    from tracking.markers import MarkerDetector  # here: tracking.markers imports this module

    detector = MarkerDetector(aruco_dictionary_id(marker_set.dictionary))
    detected = detector.detect(image)
    detected = {i: c for i, c in detected.items() if i in marker_set.markers}
    return calibrate_from_detections(detected, marker_set, (image.shape[1], image.shape[0]), intrinsics)


def save_calibration(path, calibration: CameraCalibration) -> None:
    fileio.atomic_write_text(path, json.dumps(calibration_to_json(calibration), indent=2))


def calibration_to_json(calibration: CameraCalibration) -> dict:
    """The calibration file's contents; its keys are the format's key list (the loader derives it)."""
    cam = calibration.camera
    rvec, _ = cv2.Rodrigues(cam.rotation)
    data = {
        "format_version": CALIBRATION_FORMAT_VERSION,
        "dictionary": calibration.dictionary,
        "image_width": cam.image_size[0],
        "image_height": cam.image_size[1],
        "camera_matrix": cam.camera_matrix.tolist(),
        "dist_coeffs": cam.dist_coeffs.tolist(),
        "intrinsics_source": calibration.intrinsics_source,
        "focal_std_px": calibration.focal_std_px,
        "focal_std_markers_px": calibration.focal_std_markers_px,
        "focal_std_principal_point_px": calibration.focal_std_principal_point_px,
        "rvec": rvec.ravel().tolist(),
        "tvec": cam.translation.tolist(),
        "camera_position_m": cam.position.tolist(),
        "homography_track_to_image": calibration.track_to_image_homography().tolist(),
        "reprojection_rms_px": calibration.reprojection_rms_px,
        "reprojection_max_px": calibration.reprojection_max_px,
        "marker_errors_px": {str(k): v for k, v in calibration.marker_errors_px.items()},
        "markers_missing": calibration.markers_missing,
    }
    return data


@functools.cache
def _calibration_keys() -> tuple[str, ...]:
    probe = CameraCalibration(PinholeCamera(np.eye(3), np.zeros(5), np.eye(3), np.array([0.0, 0.0, 1.0]), (1, 1)))
    return tuple(calibration_to_json(probe))


def load_calibration(path) -> CameraCalibration:
    path = Path(path)
    data = _load_json(path, "calibration file (run `python -m app calibrate`)")
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: top level must be a JSON object")
    _check_keys(data, _calibration_keys(), str(path))
    version = data.get("format_version")
    if isinstance(version, bool) or version != CALIBRATION_FORMAT_VERSION:  # (True == 1 in Python)
        raise CalibrationError(f"{path}: format_version: expected {CALIBRATION_FORMAT_VERSION}, got {version!r}")
    for name in ("camera_matrix", "dist_coeffs", "rvec", "tvec", "image_width", "image_height"):
        if name not in data:
            raise CalibrationError(f"{path}: {name}: missing")
    k = _matrix(data["camera_matrix"], (3, 3), f"{path}: camera_matrix")
    dist = _matrix(data["dist_coeffs"], None, f"{path}: dist_coeffs")
    intr = _validate_intrinsics(k, dist, (data["image_width"], data["image_height"]), str(path))
    rvec = _matrix(data["rvec"], (3,), f"{path}: rvec")
    tvec = _matrix(data["tvec"], (3,), f"{path}: tvec")
    rot, _ = cv2.Rodrigues(rvec)
    src = str(path)
    position = -rot.T @ tvec
    if not (np.all(np.isfinite(position)) and position[2] > 0):  # calibrate refuses these too
        raise CalibrationError(f"{src}: rvec/tvec: place the camera at {position.tolist()} m, not above the track "
                               "plane (z > 0)")
    # Derived from rvec/tvec and recomputed, not read; still numbers of the written shape, so that a damaged
    # or hand-mangled value is not silently passed over.
    for name, shape in (("camera_position_m", (3,)), ("homography_track_to_image", (3, 3))):
        if name in data:
            _matrix(data[name], shape, f"{src}: {name}")
    dictionary = data.get("dictionary", MARKER_DICTIONARY)
    aruco_dictionary_id(dictionary, f"{src}: dictionary")
    source = data.get("intrinsics_source", "file")
    if source not in ("file", "estimated"):
        raise CalibrationError(f"{src}: intrinsics_source: expected 'file' or 'estimated', got {fileio.schema.show(source)}")
    focal_std = data.get("focal_std_px")
    errors = data.get("marker_errors_px", {})
    if not isinstance(errors, dict) or not all(k.isdigit() for k in errors):
        raise CalibrationError(f"{src}: marker_errors_px: expected an object mapping marker id -> pixels")
    if len({int(k) for k in errors}) < len(errors):
        twins = sorted(k for k in errors if sum(int(j) == int(k) for j in errors) > 1)
        raise CalibrationError(f"{src}: marker_errors_px: marker id {int(twins[0])} appears twice ({', '.join(map(repr, twins))})")
    missing = data.get("markers_missing", [])
    if not isinstance(missing, list) or not all(isinstance(m, int) and not isinstance(m, bool) for m in missing):
        raise CalibrationError(f"{src}: markers_missing: expected a list of marker ids")
    used_and_missing = sorted(set(missing) & {int(k) for k in errors})
    if used_and_missing:  # calibrate lists a marker in one or the other
        raise CalibrationError(f"{src}: markers_missing: marker id {used_and_missing[0]} is also in marker_errors_px "
                               f"(a marker the calibration used)")

    def number(value, where):  # the stored quality figures may be NaN (no estimate)
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return float("nan")
        return _number(value, f"{src}: {where}")

    for key, v in errors.items():  # written by calibrate for every marker it used: never null
        _number(v, f"{src}: marker_errors_px[{key!r}]")

    return CameraCalibration(
        camera=PinholeCamera(intr.camera_matrix, intr.dist_coeffs, rot, tvec, intr.image_size),
        dictionary=dictionary,
        intrinsics_source=source,
        focal_std_px=None if focal_std is None else number(focal_std, "focal_std_px"),
        focal_std_markers_px=(None if data.get("focal_std_markers_px") is None
                              else number(data["focal_std_markers_px"], "focal_std_markers_px")),
        focal_std_principal_point_px=(None if data.get("focal_std_principal_point_px") is None
                                      else number(data["focal_std_principal_point_px"], "focal_std_principal_point_px")),
        reprojection_rms_px=number(data.get("reprojection_rms_px"), "reprojection_rms_px"),
        reprojection_max_px=number(data.get("reprojection_max_px"), "reprojection_max_px"),
        marker_errors_px={int(key): number(v, f"marker_errors_px[{key!r}]") for key, v in errors.items()},
        markers_missing=missing,
    )
