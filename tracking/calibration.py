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

import json
import math
from dataclasses import dataclass, field
from typing import Callable
from pathlib import Path

import cv2
import numpy as np

from tracking.geometry import PinholeCamera

CALIBRATION_FORMAT_VERSION = 1


class CalibrationError(ValueError):
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
        raise CalibrationError(f"{field_name}: unknown ArUco dictionary {name!r} (e.g. 'DICT_4X4_50')")
    return value


def _number(value, where: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CalibrationError(f"{where}: must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise CalibrationError(f"{where}: must be positive, got {value!r}")
    return float(value)


def parse_fixed_markers(data, source: str = "fixed markers") -> FixedMarkerSet:
    if not isinstance(data, dict):
        raise CalibrationError(f"{source}: top level must be a JSON object")
    unknown = set(data) - {"dictionary", "markers", "description"}
    if unknown:
        raise CalibrationError(f"{source}: unknown field(s) {sorted(unknown)}")
    dictionary = data.get("dictionary", "DICT_4X4_50")
    dict_id = aruco_dictionary_id(dictionary, f"{source}: dictionary")
    n_ids = cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0]
    raw = data.get("markers")
    if not isinstance(raw, dict) or not raw:
        raise CalibrationError(f"{source}: markers: must be a non-empty object mapping marker id -> marker")
    markers: dict[int, FixedMarker] = {}
    for key, entry in raw.items():
        where = f"{source}: markers[{key!r}]"
        try:
            marker_id = int(key)
        except ValueError:
            raise CalibrationError(f"{where}: key must be an integer marker id") from None
        if not 0 <= marker_id < n_ids:
            raise CalibrationError(f"{where}: id outside {dictionary} (0..{n_ids - 1})")
        if not isinstance(entry, dict):
            raise CalibrationError(f"{where}: must be an object with x, y, size")
        extra = set(entry) - {"x", "y", "size", "heading_deg", "z"}
        if extra:
            raise CalibrationError(f"{where}: unknown field(s) {sorted(extra)}")
        for name in ("x", "y", "size"):
            if name not in entry:
                raise CalibrationError(f"{where}.{name}: missing")
        heading = entry.get("heading_deg")
        markers[marker_id] = FixedMarker(
            marker_id=marker_id,
            x=_number(entry["x"], f"{where}.x"),
            y=_number(entry["y"], f"{where}.y"),
            size=_number(entry["size"], f"{where}.size", positive=True),
            heading_rad=None if heading is None else math.radians(_number(heading, f"{where}.heading_deg")),
            z=_number(entry.get("z", 0.0), f"{where}.z"),
        )
    return FixedMarkerSet(dictionary=dictionary, markers=markers)


def load_fixed_markers(path) -> FixedMarkerSet:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: fixed-marker file not found") from None
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    return parse_fixed_markers(data, str(path))


# --------------------------------------------------------------------------- intrinsics
@dataclass
class Intrinsics:
    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple[int, int]  # (width, height)


def _matrix(value, shape, where) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: must be numeric") from None
    if shape is not None and arr.shape != shape:
        raise CalibrationError(f"{where}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{where}: contains non-finite values")
    return arr


def _validate_intrinsics(k: np.ndarray, dist: np.ndarray, size, source: str) -> Intrinsics:
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise CalibrationError(f"{source}: camera_matrix: focal lengths must be positive")
    if k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1 or k[1, 0] != 0:
        raise CalibrationError(f"{source}: camera_matrix: last row must be [0, 0, 1] and [1][0] zero")
    dist = dist.ravel()
    if dist.size not in (0, 4, 5, 8, 12, 14):
        raise CalibrationError(f"{source}: dist_coeffs: OpenCV needs 4, 5, 8, 12 or 14 values, got {dist.size}")
    width, height = size
    for name, value in (("image_width", width), ("image_height", height)):
        if int(value) != value or value <= 0:
            raise CalibrationError(f"{source}: {name}: must be a positive integer, got {value!r}")
    return Intrinsics(k, dist if dist.size else np.zeros(5), (int(width), int(height)))


def load_intrinsics(path) -> Intrinsics:
    path = Path(path)
    if not path.exists():
        raise CalibrationError(f"{path}: intrinsics file not found")
    if path.suffix.lower() in (".yaml", ".yml", ".xml"):
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
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
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: top level must be a JSON object")
    for name in ("camera_matrix", "dist_coeffs", "image_width", "image_height"):
        if name not in data:
            raise CalibrationError(f"{path}: {name}: missing")
    k = _matrix(data["camera_matrix"], (3, 3), f"{path}: camera_matrix")
    dist = _matrix(data["dist_coeffs"], None, f"{path}: dist_coeffs")
    return _validate_intrinsics(k, dist, (data["image_width"], data["image_height"]), str(path))


def save_intrinsics(path, intrinsics: Intrinsics) -> None:
    Path(path).write_text(json.dumps({
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
    dictionary: str = "DICT_4X4_50"
    intrinsics_source: str = "file"  # "file" or "estimated" (single-view, see docs/tracking.md)
    focal_std_px: float | None = None
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


def calibrate_from_detections(detected: dict[int, np.ndarray], marker_set: FixedMarkerSet,
                              image_size: tuple[int, int], intrinsics: Intrinsics | None = None
                              ) -> CameraCalibration:
    """Camera pose (and, without ``intrinsics``, the focal length) from detected fixed markers.

    ``detected`` maps marker id -> its 4 image corners in ArUco order (raw pixels).
    With intrinsics: corners are undistorted, then ``cv2.solvePnP`` (SQPnP + Levenberg-Marquardt
    refinement). Without: a single-view ``cv2.calibrateCamera`` that estimates one focal length
    with the principal point fixed at the image centre, square pixels and no distortion.
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

    focal_std = None
    if intrinsics is not None:
        k = intrinsics.camera_matrix
        ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise CalibrationError("solvePnP failed on the fixed markers")
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec, tvec)
        dist = intrinsics.dist_coeffs
        source = "file"
    else:
        k0 = np.array([[max(width, height), 0, (width - 1) / 2], [0, max(width, height), (height - 1) / 2], [0, 0, 1]])
        flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
                 | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
        try:
            result = cv2.calibrateCameraExtended(
                [obj.astype(np.float32)], [img.astype(np.float32)], (width, height), k0, np.zeros(5), flags=flags)
        except cv2.error as exc:
            raise CalibrationError(f"focal-length estimation failed ({exc.err}); supply --intrinsics") from None
        _, k, _, rvecs, tvecs, std_intr, _, _ = result
        rvec, tvec = rvecs[0], tvecs[0]
        dist = np.zeros(5)
        focal_std = float(np.max(std_intr.ravel()[:2]))  # fx is tied to fy by the fixed aspect ratio
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
        camera=camera, dictionary=marker_set.dictionary, intrinsics_source=source, focal_std_px=focal_std,
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
        "rvec": rvec.ravel().tolist(),
        "tvec": cam.translation.tolist(),
        "camera_position_m": cam.position.tolist(),
        "homography_track_to_image": calibration.track_to_image_homography().tolist(),
        "reprojection_rms_px": calibration.reprojection_rms_px,
        "reprojection_max_px": calibration.reprojection_max_px,
        "marker_errors_px": {str(k): v for k, v in calibration.marker_errors_px.items()},
        "markers_missing": calibration.markers_missing,
    }
    Path(path).write_text(json.dumps(data, indent=2))


def load_calibration(path) -> CameraCalibration:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: calibration file not found (run `python -m app calibrate`)") from None
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: top level must be a JSON object")
    version = data.get("format_version")
    if version != CALIBRATION_FORMAT_VERSION:
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
    errors = data.get("marker_errors_px", {})
    return CameraCalibration(
        camera=PinholeCamera(intr.camera_matrix, intr.dist_coeffs, rot, tvec, intr.image_size),
        dictionary=str(data.get("dictionary", "DICT_4X4_50")),
        intrinsics_source=str(data.get("intrinsics_source", "file")),
        focal_std_px=data.get("focal_std_px"),
        reprojection_rms_px=float(data.get("reprojection_rms_px", float("nan"))),
        reprojection_max_px=float(data.get("reprojection_max_px", float("nan"))),
        marker_errors_px={int(key): float(v) for key, v in errors.items()},
        markers_missing=[int(m) for m in data.get("markers_missing", [])],
    )
