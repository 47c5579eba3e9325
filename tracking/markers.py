"""ArUco detection and car poses in track coordinates.

Pose method (docs/tracking.md, "Marker height correction"): the four detected corners of a
car marker are undistorted and intersected, as viewing rays from the calibrated camera centre,
with the horizontal plane at the marker's height ``h`` (homography
``K [r1 r2 h*r3 + t]`` of that plane). A 2-D Procrustes fit of the marker's known square to
those four points gives the centre (mean of the corners) and heading (least-squares
rotation). Mapping the corners through the track-plane homography instead (``h = 0``) shifts a
raised marker away from the camera's nadir by ``h * d / (H - h)`` (``d`` = horizontal distance
from the nadir, ``H`` = camera height).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from tracking.calibration import CameraCalibration, FixedMarker, marker_corners_track
from tracking.camera import Frame
from vehicles.params import MARKER_DICTIONARY, MarkerParams


def default_detector_parameters() -> cv2.aruco.DetectorParameters:
    """Parameters for small markers (10-20 px, ~2 px per bit) seen from overhead.

    Recall (rendered frames, random poses, motion blur up to 3 m/s): OpenCV's defaults find ~75 % of
    12 px markers; bits sampled at 8 px per cell after perspective removal, adaptive-threshold windows
    3/13/23, a looser polygon fit and correcting every bit error the dictionary allows
    (``errorCorrectionRate`` 1.0) find nearly all. OpenCV's default rate 0.6 (no corrected bit in
    DICT_4X4_50) loses 11 % of the faster car's detections along HIL race trajectories, so the false
    ids that bit correction lets through (ChArUco squares and grid boards read as ids 9, 24, 43, 44 in
    real photographs) are rejected after decoding instead, by :class:`MarkerDetector`'s pattern check.
    ``minOtsuStdDev`` 20 grey levels (OpenCV: 5) rejects low-contrast candidates: a dark printed icon
    on a cardboard box decodes as id 17 with no bit error and matches its pattern (docs/tracking.md,
    "False detections").
    """
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.minMarkerPerimeterRate = 0.02
    params.adaptiveThreshWinSizeMin = 3
    params.adaptiveThreshWinSizeMax = 23
    params.adaptiveThreshWinSizeStep = 10
    params.perspectiveRemovePixelPerCell = 8
    params.polygonalApproxAccuracyRate = 0.05
    params.errorCorrectionRate = 1.0
    params.minOtsuStdDev = 20.0
    return params


_ECC_PX_PER_CELL = 6  # template resolution; 4 loses accuracy on ~12 px markers, 8 only costs time
_ECC_MARGIN_CELLS = 0.5  # white quiet zone included in the template (labels must be at least this wide)
_ECC_MAX_SHIFT = 0.15  # a refinement moving a corner further than this (in marker sides, at least
# 2 px) is treated as diverged
MIN_PATTERN_CORRELATION = 0.87  # at the ECC alignment: rendered car markers >= 0.91, false ids in real photos <= 0.81
# Pattern identification of undecoded squares (MarkerDetector.identify_by_pattern): a quad is ECC-refined
# as an id only when its correlation at ArUco's corners reaches this (ECC then decides); squares smaller
# than _MIN_IDENTIFY_SIDE_PX (6 bits of 1.3 px) are not tried.
_PRESCREEN_CORRELATION = 0.5
_MIN_IDENTIFY_SIDE_PX = 8.0


class MarkerDetector:
    """``cv2.aruco.ArucoDetector`` on a whole image, a downscaled image or regions of interest.

    Returns ``{marker_id: corners (4,2) float64}`` in full-resolution pixel coordinates, ArUco
    corner order. An id seen more than once in a frame is ambiguous and is dropped (counted in
    ``duplicates_dropped``).

    ``refine="ecc"`` (default) re-fits each marker's corners by aligning the known marker
    pattern to the image with ``cv2.findTransformECC`` (homography, intensity-affine invariant,
    so uneven lighting does not bias it). On markers of 10-15 px this brings corner errors from
    ~0.5 px (ArUco's own sub-pixel step, which has too few pixels per edge) to ~0.05 px; see
    docs/tracking.md. ``refine="aruco"`` keeps the detector's corners (ECC still runs for the pattern check). Refinements that fail
    or move a corner more than 15 % of the marker side (at least 2 px) keep the detector's corners and are counted in
    ``refine_failures``.

    Every detection is then checked against its id's pattern: the image inside the final corners
    (with half a cell of white margin) must correlate with the marker's template, blurred to the
    marker's scale, by at least ``min_pattern_correlation``; ids decoded from something that only
    resembles a marker at the bit level (board squares, printed patterns) fail and are counted in
    ``pattern_mismatches``.
    """

    def __init__(self, dictionary: int = getattr(cv2.aruco, MARKER_DICTIONARY),
                 parameters: cv2.aruco.DetectorParameters | None = None, downscale: float = 1.0,
                 refine: str = "ecc", min_pattern_correlation: float = MIN_PATTERN_CORRELATION):
        if not 0 < downscale <= 1:
            raise ValueError(f"downscale: must be in (0, 1], got {downscale}")
        if refine not in ("ecc", "aruco"):
            raise ValueError(f"refine: must be 'ecc' or 'aruco', got {refine!r}")
        if not -1.0 <= min_pattern_correlation < 1.0:
            raise ValueError(f"min_pattern_correlation: must be in [-1, 1), got {min_pattern_correlation}")
        self.downscale = float(downscale)
        self.refine = refine
        self.min_pattern_correlation = float(min_pattern_correlation)
        self._dictionary = cv2.aruco.getPredefinedDictionary(dictionary)
        self._detector = cv2.aruco.ArucoDetector(self._dictionary, parameters or default_detector_parameters())
        self._templates: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.duplicates_dropped = 0
        self.refine_failures = 0
        self.pattern_mismatches = 0
        self.identified_by_pattern = 0
        self.found_from_prediction = 0

    def _template(self, marker_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Marker pattern with a white margin (float32) and its outer corners in template pixels."""
        if marker_id not in self._templates:
            cells = self._dictionary.markerSize + 2
            side = cells * _ECC_PX_PER_CELL
            m = int(round(_ECC_MARGIN_CELLS * _ECC_PX_PER_CELL))
            image = np.full((side + 2 * m, side + 2 * m), 255, np.uint8)
            image[m:m + side, m:m + side] = cv2.aruco.generateImageMarker(self._dictionary, marker_id, side, borderBits=1)
            lo, hi = m - 0.5, m + side - 0.5
            corners = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])
            self._templates[marker_id] = (image.astype(np.float32), corners)
        return self._templates[marker_id]

    def _blurred_template(self, marker_id: int, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """The template blurred to roughly the image's sharpness at this marker's size (pixel area + a
        little optics), its corners and the marker's mean side in image pixels."""
        template, t_corners = self._template(marker_id)
        side_px = float(np.mean(np.linalg.norm(np.diff(corners, axis=0, append=corners[:1]), axis=1)))
        scale = (t_corners[1, 0] - t_corners[0, 0]) / max(side_px, 1.0)
        return cv2.GaussianBlur(template, (0, 0), 0.5 * scale), t_corners, side_px

    def _refine_ecc(self, gray: np.ndarray, marker_id: int, corners: np.ndarray) -> tuple[np.ndarray, float]:
        """ECC-refined corners and the pattern correlation at them; when ECC fails or diverges, the
        given corners and the correlation there (counted in ``refine_failures``)."""
        smooth, t_corners, side_px = self._blurred_template(marker_id, corners)
        h, w = gray.shape
        x0, y0 = np.maximum(np.floor(corners.min(0)).astype(int) - 4, 0)
        x1, y1 = np.minimum(np.ceil(corners.max(0)).astype(int) + 5, (w, h))
        patch = gray[y0:y1, x0:x1].astype(np.float32)
        offset = np.array([x0, y0], float)
        warp = cv2.getPerspectiveTransform(t_corners.astype(np.float32), (corners - offset).astype(np.float32))
        try:
            rho, warp = cv2.findTransformECC(smooth, patch, warp.astype(np.float32), cv2.MOTION_HOMOGRAPHY,
                                             (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3), None, 1)
        except cv2.error:
            self.refine_failures += 1
            return corners, self.pattern_correlation(gray, marker_id, corners)
        refined = cv2.perspectiveTransform(t_corners.reshape(-1, 1, 2).astype(np.float32), warp).reshape(4, 2) + offset
        if not np.all(np.isfinite(refined)) or np.max(np.linalg.norm(refined - corners, axis=1)) > max(2.0, _ECC_MAX_SHIFT * side_px):
            self.refine_failures += 1
            return corners, self.pattern_correlation(gray, marker_id, corners)
        return refined.astype(float), float(rho)

    def pattern_correlation(self, gray: np.ndarray, marker_id: int, corners: np.ndarray) -> float:
        """Correlation coefficient between the image resampled inside ``corners`` (plus the white
        margin) and ``marker_id``'s blurred template: 1 for a perfect match, ~0 for unrelated texture."""
        smooth, t_corners, _ = self._blurred_template(marker_id, corners)
        to_image = cv2.getPerspectiveTransform(t_corners.astype(np.float32), np.asarray(corners, np.float32))
        sampled = cv2.warpPerspective(gray, to_image, smooth.shape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                      borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
        a, b = smooth.ravel() - smooth.mean(), sampled.ravel() - sampled.mean()
        denominator = math.sqrt(float(a @ a) * float(b @ b))
        return float(a @ b) / denominator if denominator > 0 else 0.0

    @staticmethod
    def _gray(image: np.ndarray) -> np.ndarray:
        if image.ndim == 2:
            return image
        if image.ndim == 3 and image.shape[2] == 3:
            return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        raise ValueError(f"image: expected HxW or HxWx3 uint8, got shape {image.shape}")

    def _detect_raw(self, gray: np.ndarray, offset=(0, 0)) -> tuple[list[tuple[int, np.ndarray]], list[np.ndarray]]:
        """ArUco's decoded markers [(id, corners)] and the quads it found but could not decode."""
        if self.downscale < 1.0:
            small = cv2.resize(gray, None, fx=self.downscale, fy=self.downscale, interpolation=cv2.INTER_AREA)
            corners, ids, rejected = self._detector.detectMarkers(small)
            # small-image pixel centres -> full-image pixel centres; the ECC step (or, without
            # it, cornerSubPix) then refines at full resolution
            rejected = [(np.asarray(q, float).reshape(4, 2) + 0.5) / self.downscale - 0.5 for q in rejected]
            if ids is None:
                corners = []
            else:
                pts = (np.vstack([c.reshape(4, 2) for c in corners]) + 0.5) / self.downscale - 0.5
                if self.refine != "ecc":
                    pts = cv2.cornerSubPix(gray, pts.astype(np.float32).reshape(-1, 1, 2), (3, 3), (-1, -1),
                                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01))
                corners = list(np.asarray(pts, float).reshape(-1, 4, 2))
        else:
            corners, ids, rejected = self._detector.detectMarkers(gray)
        off = np.asarray(offset, float)
        quads = [np.asarray(q, float).reshape(4, 2) + off for q in rejected]
        if ids is None:
            return [], quads
        return [(int(i), np.asarray(c, float).reshape(4, 2) + off) for i, c in zip(ids.ravel(), corners)], quads

    def _refine_and_verify(self, gray, found, refine_ids, unverified=None) -> list[tuple[int, np.ndarray]]:
        """Refine (``refine="ecc"``, ids in ``refine_ids``) and keep the detections whose pattern
        correlation, measured at the ECC alignment (which removes the ~0.5 px corner error of small
        markers that would otherwise lower it), reaches ``min_pattern_correlation``. The corners of those
        that fail are appended to ``unverified`` (a list) when given."""
        kept = []
        for marker_id, corners in found:
            refined, rho = self._refine_ecc(gray, marker_id, corners)
            if rho < self.min_pattern_correlation:
                self.pattern_mismatches += 1
                if unverified is not None:
                    unverified.append(corners)
                continue
            use_refined = self.refine == "ecc" and (refine_ids is None or marker_id in refine_ids)
            kept.append((marker_id, refined if use_refined else corners))
        return kept

    def identify_by_pattern(self, gray: np.ndarray, quads: list[np.ndarray], ids) -> list[tuple[int, np.ndarray]]:
        """Markers among ``quads`` (image corners of squares ArUco found but did not decode, or decoded to an
        id whose pattern did not match) identified by their pattern alone: each quad, in each of its four
        corner orders, is compared with each id of ``ids``; the best match is ECC-refined and kept when its
        pattern correlation reaches ``min_pattern_correlation`` (the same check every decoded marker
        passes). Each id and each quad is used at most once, best matches first. Why: at 2 px per bit, the
        lens, MJPEG or a narrow white label leave cells grey and ArUco's bit decoding fails or returns
        another id, although the square is found and the whole pattern still matches (docs/tracking.md,
        "Detection rate"). Counted in ``identified_by_pattern``."""
        ids = sorted(set(int(i) for i in ids))
        if not ids or not quads:
            return []
        scored = []
        for q, quad in enumerate(quads):
            for marker_id in ids:
                rho, order = max((self.pattern_correlation(gray, marker_id, np.roll(quad, -k, axis=0)), k)
                                 for k in range(4))
                if rho >= _PRESCREEN_CORRELATION:
                    scored.append((rho, q, marker_id, order))
        kept, used_quads, used_ids = [], set(), set()
        for _, q, marker_id, order in sorted(scored, reverse=True):
            if q in used_quads or marker_id in used_ids:
                continue
            corners = np.roll(quads[q], -order, axis=0)
            refined, rho = self._refine_ecc(gray, marker_id, corners)
            if rho < self.min_pattern_correlation or refined is corners:  # not matched, or ECC failed
                continue
            used_quads.add(q)
            used_ids.add(marker_id)
            kept.append((marker_id, refined if self.refine == "ecc" else corners))
        self.identified_by_pattern += len(kept)
        return kept

    def find_from_seed(self, gray: np.ndarray, marker_id: int, seed: np.ndarray, quads: list[np.ndarray]
                       ) -> np.ndarray | None:
        """``marker_id`` near ``seed`` (its predicted image corners, ArUco order): the seed, and the seed moved
        onto the centre of each square ArUco found within half a side of it (the white label around a
        marker whose own border was not found shares its centre), ECC-refined; the first alignment whose
        pattern correlation reaches ``min_pattern_correlation`` (None if none). Counted in
        ``found_from_prediction``."""
        side = _mean_side(seed)
        centre = seed.mean(axis=0)
        starts = [seed] + [seed + (q.mean(axis=0) - centre) for q in quads
                           if np.linalg.norm(q.mean(axis=0) - centre) < 0.5 * side]
        for start in starts:
            refined, rho = self._refine_ecc(gray, marker_id, start)
            if refined is not start and rho >= self.min_pattern_correlation:
                self.found_from_prediction += 1
                return refined if self.refine == "ecc" else start
        return None

    def detect(self, image: np.ndarray, rois: list[tuple[int, int, int, int]] | None = None,
               refine_ids=None, identify_ids=(), seeds: dict[int, np.ndarray] | None = None) -> dict[int, np.ndarray]:
        """Markers in ``image``; with ``rois`` (x0, y0, x1, y1 pixel boxes) only inside those.
        ``refine_ids``: ids to refine (None = all). ``identify_ids``: ids (the cars expected in the image)
        that, when not decoded, are looked for among the squares ArUco could not decode
        (:meth:`identify_by_pattern`); ``seeds`` ({id: predicted image corners}): ids still not found are
        then aligned from their prediction (:meth:`find_from_seed`)."""
        gray = self._gray(image)
        found: list[tuple[int, np.ndarray]] = []
        quads: list[np.ndarray] = []
        if rois is None:
            found, quads = self._detect_raw(gray)
        else:
            h, w = gray.shape
            for x0, y0, x1, y1 in rois:
                x0, y0, x1, y1 = max(int(x0), 0), max(int(y0), 0), min(int(x1), w), min(int(y1), h)
                if x1 - x0 > 8 and y1 - y0 > 8:
                    more, more_quads = self._detect_raw(gray[y0:y1, x0:x1], (x0, y0))
                    found += more
                    quads += more_quads
        unverified: list[np.ndarray] = []
        found = self._refine_and_verify(gray, found, refine_ids, unverified)
        missing = set(int(i) for i in identify_ids) - {i for i, _ in found}
        if missing:
            taken = [c.mean(axis=0) for _, c in found]
            quads = [q for q in unverified + quads if _MIN_IDENTIFY_SIDE_PX <= _mean_side(q)
                     and all(np.linalg.norm(q.mean(axis=0) - t) > 2.0 for t in taken)]
            found += self.identify_by_pattern(gray, _distinct(quads), missing)
            for marker_id in sorted(missing - {i for i, _ in found}):
                if seeds is not None and marker_id in seeds:
                    corners = self.find_from_seed(gray, marker_id, np.asarray(seeds[marker_id], float), quads)
                    if corners is not None:
                        found.append((marker_id, corners))
        result: dict[int, np.ndarray] = {}
        seen_twice: set[int] = set()
        for marker_id, corners in found:
            if marker_id in result and np.linalg.norm(result[marker_id].mean(0) - corners.mean(0)) > 2.0:
                seen_twice.add(marker_id)  # overlapping ROIs find the same marker twice: not a duplicate
            result[marker_id] = corners
        for marker_id in seen_twice:
            del result[marker_id]
        self.duplicates_dropped += len(seen_twice)
        return result


def _mean_side(quad: np.ndarray) -> float:
    return float(np.mean(np.linalg.norm(np.diff(quad, axis=0, append=quad[:1]), axis=1)))


def _distinct(quads: list[np.ndarray]) -> list[np.ndarray]:
    """One of each group of quads whose centres lie within 2 px (overlapping ROIs, several threshold
    windows: ArUco reports the same square more than once)."""
    out: list[np.ndarray] = []
    for q in quads:
        if all(np.linalg.norm(q.mean(axis=0) - o.mean(axis=0)) > 2.0 for o in out):
            out.append(q)
    return out


@dataclass
class CarMeasurement:
    marker_id: int
    x: float
    y: float
    heading: float
    t_capture_s: float
    side_error_m: float  # measured minus nominal marker side: large values flag a bad detection


@dataclass
class FrameDetections:
    t_capture_s: float
    index: int
    cars: dict[int, CarMeasurement]
    markers: dict[int, np.ndarray]  # every detected marker that passed the checks: id -> image corners
    full_search: bool
    detect_time_s: float
    rejected: dict[int, str] = field(default_factory=dict)  # id -> why it was implausible (ArucoTracker.process)


def procrustes_pose(points_xy: np.ndarray, size: float) -> tuple[float, float, float, float]:
    """Centre, heading and mean side length of a square from its 4 corners (ArUco order) on a plane.

    The heading is the least-squares rotation between the nominal square (top edge facing
    +x) and the measured corners.
    """
    half = size / 2.0
    model = np.array([[half, half], [half, -half], [-half, -half], [-half, half]])
    centre = points_xy.mean(axis=0)
    q = points_xy - centre
    cross = np.sum(model[:, 0] * q[:, 1] - model[:, 1] * q[:, 0])
    dot = np.sum(model * q)
    heading = math.atan2(cross, dot)
    side = float(np.mean(np.linalg.norm(np.diff(points_xy, axis=0, append=points_xy[:1]), axis=1)))
    return float(centre[0]), float(centre[1]), heading, side


class _AllExcept:
    def __init__(self, excluded):
        self.excluded = excluded

    def __contains__(self, item):
        return item not in self.excluded


class ArucoTracker:
    """Finds car markers in frames and converts them to car poses in track coordinates.

    ``car_ids``: ids worn by cars (None = every id that is not a fixed marker).
    ``fixed_ids``: ids of the fixed markers, or ``{id: FixedMarker}`` (e.g. ``FixedMarkerSet.markers``);
    with surveyed markers, a fixed id is kept only near the projection of its surveyed centre.
    The dictionary is the calibration's (``dictionary`` overrides it); ``car_dictionary``, the car file's
    ``marker.dictionary``, must be the same (ValueError otherwise).
    ``marker_offset_m``, ``marker_offset_left_m``, ``marker_yaw_rad``: where the marker sits on the car (the
    car file's marker.offset_forward_m, offset_left_m, yaw_rad), subtracted to give the reference point.
    ``marker_height_m``: marker height above the track; ``correct_height=False`` maps the
    corners on the track plane instead (only for comparison, it is biased).
    ROI mode: :meth:`process` with ``predictions`` ({id: (x, y)} or {id: (x, y, heading)}) searches only squares of
    ``roi_radius_m`` around them, with a full-frame search every ``full_search_every`` frames
    to pick up new cars.

    Plausibility (every detection, reasons in ``FrameDetections.rejected`` and counted in
    ``rejected_counts``): ``"size"``, a car marker whose measured side (at the marker's height,
    i.e. its size in pixels against the size the calibration and the marker geometry predict there)
    differs from ``marker_size_m`` by more than ``max_side_error`` (fraction); ``"jump"``, a car
    detected farther than ``roi_radius_m`` from its predicted position (the ROI search would not have
    looked there; cars without a prediction, e.g. lost ones, are not checked, so a car put down
    elsewhere is picked up again); ``"fixed_position"``, a surveyed fixed marker whose image centre is
    more than half its projected side from where the calibration projects it.
    """

    def __init__(self, calibration: CameraCalibration, marker_size_m: float,
                 marker_height_m: float = MarkerParams.height_m, marker_offset_m: float = 0.0, car_ids=None,
                 marker_offset_left_m: float = 0.0, marker_yaw_rad: float = 0.0,
                 fixed_ids=(), correct_height: bool = True, dictionary: int | None = None,
                 car_dictionary: str | None = None, downscale: float = 1.0, refine: str = "ecc",
                 roi_radius_m: float = 0.2, full_search_every: int = 30,
                 parameters: cv2.aruco.DetectorParameters | None = None, max_side_error: float = 0.2):
        if marker_size_m <= 0:
            raise ValueError(f"marker_size_m: must be positive, got {marker_size_m}")
        cam_height = calibration.camera.position[2]
        if not 0 <= marker_height_m < cam_height:
            raise ValueError(f"marker_height_m: must be in [0, camera height {cam_height:.2f} m), got {marker_height_m}")
        if full_search_every < 1:
            raise ValueError(f"full_search_every: must be >= 1, got {full_search_every}")
        if not max_side_error > 0:
            raise ValueError(f"max_side_error: must be positive, got {max_side_error}")
        if car_dictionary is not None and car_dictionary != calibration.dictionary:
            raise ValueError(f"car marker dictionary {car_dictionary} (car file marker.dictionary) differs from the "
                             f"calibration's {calibration.dictionary} (its fixed-marker file's): one detector reads one "
                             "dictionary, so print the car markers and the fixed markers from the same one")
        if dictionary is None:
            dictionary = getattr(cv2.aruco, calibration.dictionary)
        n_ids = cv2.aruco.getPredefinedDictionary(dictionary).bytesList.shape[0]
        for what, ids in (("car_ids", car_ids or ()), ("fixed_ids", fixed_ids)):
            bad = [i for i in ids if not 0 <= int(i) < n_ids]
            if bad:  # an id the dictionary does not have is never seen: the car would be "lost" forever
                raise ValueError(f"{what}: marker id {bad[0]} is not in the ArUco dictionary "
                                 f"in use (ids 0..{n_ids - 1})")
        shared = sorted(set(int(i) for i in car_ids or ()) & set(int(i) for i in fixed_ids))
        if shared:  # a car wearing a fixed marker's id would be taken for the fixed marker, or move it
            raise ValueError(f"car_ids: marker id {shared[0]} is also a fixed marker of the track "
                             f"(fixed ids {', '.join(map(str, sorted(int(i) for i in fixed_ids)))})")
        self.calibration = calibration
        self.marker_size_m = float(marker_size_m)
        self.marker_height_m = float(marker_height_m)
        self.marker_offset_m = float(marker_offset_m)
        self.marker_offset_left_m = float(marker_offset_left_m)
        self.marker_yaw_rad = float(marker_yaw_rad)
        self.car_ids = None if car_ids is None else set(int(i) for i in car_ids)
        self.fixed_ids = set(int(i) for i in fixed_ids)
        surveyed = fixed_ids.values() if isinstance(fixed_ids, dict) else ()
        self._fixed_expected = {m.marker_id: self._expected_image(m) for m in surveyed if isinstance(m, FixedMarker)}
        self.correct_height = bool(correct_height)
        self.roi_radius_m = float(roi_radius_m)
        self.full_search_every = int(full_search_every)
        self.max_side_error = float(max_side_error)
        self.detector = MarkerDetector(dictionary, parameters, downscale, refine)
        self.rejected_counts = {"size": 0, "jump": 0, "fixed_position": 0}
        self._frames_since_full = full_search_every  # first frame is a full search

    def _expected_image(self, marker: FixedMarker) -> tuple[np.ndarray, float]:
        """Projected centre (px) of a surveyed marker and the tolerance for its detected centre (half
        its projected side; the heading does not change the side, so 0 stands in when not surveyed)."""
        corners = marker_corners_track(marker.x, marker.y, marker.heading_rad or 0.0, marker.size, marker.z)
        px = self.calibration.camera.project(corners)
        side = float(np.mean(np.linalg.norm(np.diff(px, axis=0, append=px[:1]), axis=1)))
        centre = self.calibration.camera.project(np.array([[marker.x, marker.y, marker.z]]))[0]
        return centre, 0.5 * side

    def is_car(self, marker_id: int) -> bool:
        if marker_id in self.fixed_ids:
            return False
        return self.car_ids is None or marker_id in self.car_ids

    def car_pose(self, corners_px: np.ndarray) -> tuple[float, float, float, float]:
        """(x, y, heading, side_error_m) of the car reference point from one marker's image corners."""
        height = self.marker_height_m if self.correct_height else 0.0
        on_plane = self.calibration.camera.pixels_to_plane(corners_px, height)
        x, y, heading, side = procrustes_pose(on_plane, self.marker_size_m)
        heading = math.atan2(math.sin(heading - self.marker_yaw_rad), math.cos(heading - self.marker_yaw_rad))
        c, s = math.cos(heading), math.sin(heading)
        fwd, left = self.marker_offset_m, self.marker_offset_left_m
        return x - fwd * c + left * s, y - fwd * s - left * c, heading, side - self.marker_size_m

    def marker_image_corners(self, x: float, y: float, heading: float) -> np.ndarray:
        """Image corners (4,2, ArUco order) of the marker of a car whose reference point is at (x, y, heading):
        the inverse of :meth:`car_pose` (marker offset and yaw, marker height, lens)."""
        c, s = math.cos(heading), math.sin(heading)
        fwd, left = self.marker_offset_m, self.marker_offset_left_m
        corners = marker_corners_track(x + fwd * c - left * s, y + fwd * s + left * c, heading + self.marker_yaw_rad,
                                       self.marker_size_m, self.marker_height_m if self.correct_height else 0.0)
        return self.calibration.camera.project(corners)

    def _rois(self, predictions: dict) -> list[tuple[int, int, int, int]]:
        cam = self.calibration.camera
        boxes = []
        r = self.roi_radius_m
        for x, y, *_ in predictions.values():
            square = np.array([[x - r, y - r], [x + r, y - r], [x + r, y + r], [x - r, y + r]])
            px = cam.project(np.column_stack([square, np.full(4, self.marker_height_m)]))
            (x0, y0), (x1, y1) = np.floor(px.min(0)), np.ceil(px.max(0))
            boxes.append((int(x0), int(y0), int(x1) + 1, int(y1) + 1))
        return boxes

    def process(self, frame: Frame, predictions: dict[int, tuple[float, ...]] | None = None) -> FrameDetections:
        """Car poses in ``frame``. ``predictions``: {id: (x, y)} or {id: (x, y, heading)} of the cars (the
        estimator's, at the frame's time): the search is limited to squares around them, and a car whose
        marker ArUco cannot decode is aligned from its predicted corners when the heading is given."""
        start = time.perf_counter()
        full = predictions is None or self._frames_since_full + 1 >= self.full_search_every
        car_ids = self.car_ids if self.car_ids is not None else _AllExcept(self.fixed_ids)
        # Cars expected in the frame: those predicted, or in a full search every car id we were given.
        expected = [i for i in (predictions or ()) if self.is_car(i)] if predictions else sorted(self.car_ids or ())
        seeds = {i: self.marker_image_corners(*predictions[i]) for i in expected
                 if predictions and i in predictions and len(predictions[i]) >= 3}
        markers = self.detector.detect(frame.image, None if full else self._rois(predictions), car_ids, expected,
                                       seeds)
        self._frames_since_full = 0 if full else self._frames_since_full + 1
        cars, rejected = {}, {}
        for marker_id, corners in markers.items():
            if self.is_car(marker_id):
                x, y, heading, side_err = self.car_pose(corners)
                reason = self._implausible_car(marker_id, x, y, side_err, predictions)
                if reason is None:
                    cars[marker_id] = CarMeasurement(marker_id, x, y, heading, frame.t_capture_s, side_err)
                else:
                    rejected[marker_id] = reason
            elif marker_id in self._fixed_expected:
                centre, tolerance = self._fixed_expected[marker_id]
                if np.linalg.norm(corners.mean(axis=0) - centre) > tolerance:
                    rejected[marker_id] = "fixed_position"
        for reason in rejected.values():
            self.rejected_counts[reason] += 1
        markers = {i: c for i, c in markers.items() if i not in rejected}
        return FrameDetections(frame.t_capture_s, frame.index, cars, markers, full, time.perf_counter() - start, rejected)

    def _implausible_car(self, marker_id: int, x: float, y: float, side_err: float, predictions) -> str | None:
        if abs(side_err) > self.max_side_error * self.marker_size_m:
            return "size"
        predicted = (predictions or {}).get(marker_id)
        if predicted is not None and math.hypot(x - predicted[0], y - predicted[1]) > self.roi_radius_m:
            return "jump"
        return None
