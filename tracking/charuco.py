"""Camera intrinsics from views of a ChArUco board (OpenCV's ``CharucoBoard``/``CharucoDetector``,
``matchImagePoints`` and ``calibrateCameraExtended``); docs/tracking.md, "Camera intrinsics".

A view is used when the board is found with at least :data:`MIN_CORNERS` chessboard corners, not all
on one line, and its edges are sharp (:func:`edge_blur_px` at most ``max_blur_px``); calibration needs
at least :data:`MIN_VIEWS` such views. The result carries the per-view and overall reprojection error,
the standard deviations of fx, fy, cx, cy (OpenCV's, from the Jacobian at the solution scaled by the
residual) and warnings when the views leave image corners or board tilts uncovered.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

import fileio
from tracking.calibration import CalibrationError, Intrinsics, aruco_dictionary_id
from tracking.camera import CameraSource, EndOfStream
from vehicles.params import MARKER_DICTIONARY, aruco_dictionary_size

MIN_VIEWS = 3  # Zhang's method: 3 views of a plane fix fx, fy, cx, cy; 10-20 varied views are better
MIN_CORNERS = 6  # a homography needs 4 points; 6 keep one view from being decided by a single marker
MAX_BLUR_PX = 2.0  # edge blur (Gaussian sigma, px) above which a view is rejected as blurred
MIN_TILT_DEG = 20.0  # views should tilt the board at least this much about each image axis
CORNER_CELL = 1 / 3  # an image corner counts as covered when a board corner lies in this fraction of it
# Lowest corner count at which the blur estimate is taken (fewer neighbouring pairs: not measured).
_MIN_BLUR_PAIRS = 3


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board's geometry, as OpenCV defines it: ``squares_x`` columns and ``squares_y`` rows of
    squares of side ``square_length_m``, markers of side ``marker_length_m`` in the white squares;
    ``legacy_pattern`` for boards printed with OpenCV up to 4.5 (or bought ones made that way), whose
    chessboard starts with the other colour when ``squares_y`` is even."""

    squares_x: int
    squares_y: int
    square_length_m: float
    marker_length_m: float
    dictionary: str = MARKER_DICTIONARY
    legacy_pattern: bool = False

    def __post_init__(self):
        for name in ("squares_x", "squares_y"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 2 <= value <= 100:
                raise ValueError(f"{name}: must be an integer in [2, 100], got {value!r}")
        for name in ("square_length_m", "marker_length_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 10:
                raise ValueError(f"{name}: must be a length in metres in (0, 10), got {value!r}")
        if not self.marker_length_m < self.square_length_m:
            raise ValueError(f"marker_length_m: must be smaller than the square ({1000 * self.marker_length_m:.4g} mm "
                             f">= {1000 * self.square_length_m:.4g} mm)")
        size = aruco_dictionary_size(self.dictionary)
        if size is None:
            aruco_dictionary_id(self.dictionary)  # raises, naming the field
        if self.markers > size:
            raise ValueError(f"dictionary: {self.dictionary} has {size} markers, a {self.squares_x} x "
                             f"{self.squares_y} board needs {self.markers}")

    @property
    def markers(self) -> int:
        return self.squares_x * self.squares_y // 2

    def board(self) -> cv2.aruco.CharucoBoard:
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), float(self.square_length_m),
                                       float(self.marker_length_m),
                                       cv2.aruco.getPredefinedDictionary(aruco_dictionary_id(self.dictionary)))
        board.setLegacyPattern(bool(self.legacy_pattern))
        return board

    def describe(self) -> str:
        return (f"{self.squares_x} x {self.squares_y} squares of {1000 * self.square_length_m:g} mm, markers "
                f"{1000 * self.marker_length_m:g} mm, {self.dictionary}" + (", legacy pattern" if self.legacy_pattern else ""))


# --------------------------------------------------------------------------- board file
BOARD_FORMAT_VERSION = 1


@dataclass(frozen=True)
class PrintedBoard:
    """The side file `make-board` writes beside the board image: the geometry as printed (lengths are
    whole image pixels at ``dpi``, converted back to metres), so `calibrate-camera --board` uses exactly
    what is on the paper when it is printed at 100 %."""

    board: CharucoBoardSpec
    paper: str
    paper_width_mm: float
    paper_height_mm: float
    dpi: int
    image: str  # file name of the board image, beside the side file


def save_board_file(path, printed: PrintedBoard) -> None:
    data = {"format_version": BOARD_FORMAT_VERSION, **dataclasses.asdict(printed)}
    fileio.atomic_write_text(path, json.dumps(data, indent=2) + "\n")


def load_board_file(path) -> PrintedBoard:
    """Strict loader (unknown keys, wrong types and an impossible geometry name the file and field)."""
    data = fileio.load_json(path, "board file (written by `python -m app make-board`)", max_bytes=2**16,
                            error=CalibrationError)
    spec = fileio.table_from_dataclass(
        PrintedBoard, overrides={"dpi": fileio.Number(integer=True, gt=0, le=100_000),
                                 "paper_width_mm": fileio.Number(gt=0, le=10_000),
                                 "paper_height_mm": fileio.Number(gt=0, le=10_000)},
        extra={"format_version": fileio.FieldSpec(fileio.Number(integer=True, ge=BOARD_FORMAT_VERSION,
                                                                le=BOARD_FORMAT_VERSION))})
    values = fileio.validate(data, spec, str(path), error=CalibrationError)
    values.pop("format_version")
    try:
        board = CharucoBoardSpec(**values.pop("board"))
    except ValueError as exc:
        raise CalibrationError(f"{path}: board.{exc}") from None
    return PrintedBoard(board=board, **values)


# --------------------------------------------------------------------------- one view
@dataclass
class BoardView:
    """The board in one image: ChArUco corner ids, their pixels (N,2) and board points (N,3), or why the
    view is not used (``rejected``: "board not found", "too few corners", "corners on one line",
    "blurred")."""

    name: str
    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray
    blur_px: float = math.nan
    rejected: str | None = None
    # Filled in by the calibration for the views it used:
    rms_px: float = math.nan
    tilt_deg: tuple[float, float] = (math.nan, math.nan)  # about the image's x (rows) and y (columns) axes

    @property
    def corners(self) -> int:
        return len(self.ids)


class BoardDetector:
    """Finds a ChArUco board in images and decides whether a view is good enough to calibrate with."""

    def __init__(self, spec: CharucoBoardSpec, max_blur_px: float = MAX_BLUR_PX, min_corners: int = MIN_CORNERS):
        if not max_blur_px > 0:
            raise ValueError(f"max_blur_px: must be positive, got {max_blur_px}")
        self.spec = spec
        self.board = spec.board()
        self.detector = cv2.aruco.CharucoDetector(self.board)
        self.max_blur_px = float(max_blur_px)
        self.min_corners = max(int(min_corners), 4)
        self._grid = np.asarray(self.board.getChessboardCorners(), float).reshape(-1, 3)

    def detect(self, image: np.ndarray, name: str = "view") -> BoardView:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, marker_corners, marker_ids = self.detector.detectBoard(gray)
        empty = BoardView(name, np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 3)))
        if ids is None or len(ids) == 0:
            markers = 0 if marker_ids is None else len(marker_ids)
            empty.rejected = "board not found" + (f" ({markers} markers of {self.spec.dictionary}, no chessboard "
                                                  "corner between them)" if markers else "")
            return empty
        ids = ids.ravel().astype(int)
        pixels = corners.reshape(-1, 2).astype(float)
        view = BoardView(name, ids, pixels, self._grid[ids])
        if len(ids) < self.min_corners:
            view.rejected = f"too few corners ({len(ids)} < {self.min_corners})"
            return view
        centred = view.object_points[:, :2] - view.object_points[:, :2].mean(axis=0)
        if np.linalg.matrix_rank(centred, tol=1e-3 * self.spec.square_length_m) < 2:
            view.rejected = "corners on one line"
            return view
        view.blur_px = edge_blur_px(gray, view.image_points, view.object_points, self.spec.square_length_m,
                                    self.spec.marker_length_m)
        if view.blur_px > self.max_blur_px:
            view.rejected = f"blurred (edge blur {view.blur_px:.1f} px > {self.max_blur_px:g} px)"
        return view


def edge_blur_px(gray: np.ndarray, pixels: np.ndarray, board_points: np.ndarray, square: float,
                 marker: float, step_px: float = 0.25) -> float:
    """Median blur (Gaussian sigma, px) of the chessboard edges between neighbouring corners.

    Across the edge halfway between two neighbouring corners the image steps from the black square to
    the white margin around the next square's marker; for a step blurred by a Gaussian of sigma s the
    steepest slope is (white - black) / (sqrt(2 pi) s). White is the brightest sample in the margin, black
    the median of the black square's inner half. NaN when fewer than 3 neighbouring pairs are found.
    """
    d = np.linalg.norm(board_points[:, None, :2] - board_points[None, :, :2], axis=2)
    first, second = np.nonzero(np.triu(np.abs(d - square) < 1e-6 * square))
    if len(first) < _MIN_BLUR_PAIRS:
        return math.nan
    p, q = pixels[first], pixels[second]
    length = np.linalg.norm(q - p, axis=1)
    normal = np.column_stack([-(q - p)[:, 1], (q - p)[:, 0]]) / length[:, None]
    reach = 0.45 * length.max()
    t = np.arange(-reach, reach + step_px / 2, step_px)
    points = (0.5 * (p + q))[:, None, :] + t[None, :, None] * normal[:, None, :]
    profile = cv2.remap(gray.astype(np.float32), points[..., 0].astype(np.float32), points[..., 1].astype(np.float32),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(float)
    margin = 0.5 * (square - marker) / square * length  # px from the edge to the marker, white side
    inside = np.abs(t)[None, :] <= 0.45 * length[:, None]
    near = (np.abs(t)[None, :] <= np.maximum(margin, 1.0)[:, None]) & inside
    pos, neg = t[None, :] > 0, t[None, :] < 0
    white_is_pos = np.nanmean(np.where(near & pos, profile, np.nan), axis=1) > \
        np.nanmean(np.where(near & neg, profile, np.nan), axis=1)
    white_side = np.where(white_is_pos[:, None], pos, neg)
    black_side = np.where(white_is_pos[:, None], neg, pos)
    white = np.nanmax(np.where(near & white_side, profile, np.nan), axis=1)
    black_core = black_side & (np.abs(t)[None, :] >= 0.2 * length[:, None]) & inside
    black = np.nanmedian(np.where(black_core, profile, np.nan), axis=1)
    slope = np.abs(np.gradient(profile, step_px, axis=1))
    steepest = np.nanmax(np.where(near, slope, np.nan), axis=1)
    sigma = (white - black) / (math.sqrt(2 * math.pi) * np.maximum(steepest, 1e-9))
    good = np.isfinite(sigma) & (white - black > 10)  # a pair whose contrast is lost (glare) says nothing
    return float(np.median(sigma[good])) if good.sum() >= _MIN_BLUR_PAIRS else math.nan


# --------------------------------------------------------------------------- calibration
@dataclass
class IntrinsicsCalibration:
    intrinsics: Intrinsics
    std_px: dict[str, float]  # fx, fy, cx, cy: one standard deviation
    rms_px: float  # over all corners of the views used
    views: list[BoardView]  # every view given, used or rejected
    warnings: list[str] = field(default_factory=list)

    @property
    def used(self) -> list[BoardView]:
        return [v for v in self.views if v.rejected is None]

    @property
    def rejected(self) -> list[BoardView]:
        return [v for v in self.views if v.rejected is not None]


def calibrate_intrinsics(views: list[BoardView], image_size: tuple[int, int], min_views: int = MIN_VIEWS
                         ) -> IntrinsicsCalibration:
    """fx, fy, cx, cy and OpenCV's 5 distortion coefficients (k1, k2, p1, p2, k3) from the good views.

    Raises CalibrationError naming every view and why it was rejected when fewer than ``min_views``
    (at least :data:`MIN_VIEWS`) good ones remain.
    """
    min_views = max(int(min_views), MIN_VIEWS)
    good = [v for v in views if v.rejected is None]
    if len(good) < min_views:
        reasons = "; ".join(f"{v.name}: {v.rejected}" for v in views if v.rejected) or "none rejected"
        raise CalibrationError(f"{len(good)} good board view(s) of {len(views)}, at least {min_views} needed "
                               f"(rejected: {reasons})")
    width, height = int(image_size[0]), int(image_size[1])
    objects = [v.object_points.astype(np.float32).reshape(-1, 1, 3) for v in good]
    pixels = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in good]
    try:
        rms, k, dist, rvecs, _tvecs, std_intrinsics, _std_extrinsics, per_view = cv2.calibrateCameraExtended(
            objects, pixels, (width, height), None, None)
    except cv2.error as exc:
        raise CalibrationError(f"cv2.calibrateCamera failed on {len(good)} views: "
                               f"{str(exc).strip().splitlines()[-1]}") from None
    if not (np.all(np.isfinite(k)) and np.all(np.isfinite(dist)) and k[0, 0] > 0 and k[1, 1] > 0):
        raise CalibrationError(f"cv2.calibrateCamera gave no usable camera matrix from {len(good)} views")
    std = std_intrinsics.ravel()
    for view, error, rvec in zip(good, per_view.ravel(), rvecs):
        view.rms_px = float(error)
        normal = cv2.Rodrigues(rvec)[0][:, 2]  # the board's normal in the camera frame
        view.tilt_deg = (math.degrees(math.atan2(abs(normal[1]), abs(normal[2]))),
                         math.degrees(math.atan2(abs(normal[0]), abs(normal[2]))))
    result = IntrinsicsCalibration(
        intrinsics=Intrinsics(k, dist.ravel(), (width, height)),
        std_px={name: float(s) for name, s in zip(("fx", "fy", "cx", "cy"), std[:4])},
        rms_px=float(rms), views=list(views))
    result.warnings = coverage_warnings(good, (width, height))
    return result


def coverage_warnings(views: list[BoardView], image_size: tuple[int, int]) -> list[str]:
    """What the views leave uncovered: image corners no board corner reached (lens distortion is largest
    there and is extrapolated otherwise) and board tilts (without them focal length and principal point
    are poorly separated from the board's distance)."""
    width, height = image_size
    pixels = np.vstack([v.image_points for v in views])
    out = []
    missing = []
    for name, (right, bottom) in (("top-left", (0, 0)), ("top-right", (1, 0)), ("bottom-left", (0, 1)),
                                  ("bottom-right", (1, 1))):
        in_x = pixels[:, 0] >= (1 - CORNER_CELL) * width if right else pixels[:, 0] < CORNER_CELL * width
        in_y = pixels[:, 1] >= (1 - CORNER_CELL) * height if bottom else pixels[:, 1] < CORNER_CELL * height
        if not np.any(in_x & in_y):
            missing.append(name)
    if missing:
        out.append(f"no board corner in the image's {', '.join(missing)} corner{'s' if len(missing) > 1 else ''} "
                   f"(outer {100 * CORNER_CELL:.0f} % of width and height): distortion there is extrapolated; add "
                   "views with the board there")
    tilts = np.array([v.tilt_deg for v in views])
    for axis, (name, how) in enumerate((("horizontal", "top edge towards or away from the camera"),
                                        ("vertical", "left or right edge towards the camera"))):
        if np.nanmax(tilts[:, axis]) < MIN_TILT_DEG:
            out.append(f"no view tilts the board more than {MIN_TILT_DEG:g} deg about the {name} image axis "
                       f"(largest {np.nanmax(tilts[:, axis]):.0f} deg): add views with its {how}; focal length "
                       "and principal point are poorly determined without")
    return out


# --------------------------------------------------------------------------- live capture
@dataclass
class LiveCapture:
    views: list[BoardView]
    image_size: tuple[int, int] | None
    frames: int  # frames read
    rejected: dict[str, int]  # checked frames not taken, by reason


def board_moved(view: BoardView, previous: BoardView, min_motion_px: float) -> bool:
    """Whether the board moved enough since ``previous``: its common corners moved by ``min_motion_px``
    on average, or fewer than half of them are common (the board left part of the view)."""
    common, a, b = np.intersect1d(view.ids, previous.ids, return_indices=True)
    if len(common) < 0.5 * max(len(view.ids), len(previous.ids)):
        return True
    shift = np.linalg.norm(view.image_points[a] - previous.image_points[b], axis=1)
    return float(np.mean(shift)) >= min_motion_px


def capture_views(source: CameraSource, detector: BoardDetector, views: int, every: int = 10,
                  min_motion: float = 0.05, max_frames: int | None = None,
                  progress: Callable[[int], None] | None = None) -> LiveCapture:
    """Checks every ``every``-th frame of ``source`` and keeps a good view once the board has moved by
    ``min_motion`` of the image diagonal since the last view kept; stops after ``views`` views, at the
    end of the stream or after ``max_frames`` frames. ``progress(n)`` is called with the views so far."""
    if views < 1 or every < 1 or not min_motion >= 0:
        raise ValueError(f"views, every: must be >= 1 and min_motion >= 0, got {views}, {every}, {min_motion}")
    kept: list[BoardView] = []
    rejected: dict[str, int] = {}
    size = None
    frames = 0
    while len(kept) < views and (max_frames is None or frames < max_frames):
        try:
            frame = source.read()
        except EndOfStream:
            break
        frames += 1
        if (frames - 1) % every:
            continue
        height, width = frame.image.shape[:2]
        if size is None:
            size = (width, height)
        elif size != (width, height):
            raise CalibrationError(f"frame {frame.index}: size {width}x{height} differs from the first frame's "
                                   f"{size[0]}x{size[1]}")
        view = detector.detect(frame.image, f"frame {frame.index}")
        reason = view.rejected or ("board did not move" if kept and not board_moved(
            view, kept[-1], min_motion * math.hypot(width, height)) else None)
        if reason is not None:
            key = reason.split(" (")[0]
            rejected[key] = rejected.get(key, 0) + 1
            continue
        kept.append(view)
        if progress is not None:
            progress(len(kept))
    return LiveCapture(kept, size, frames, rejected)
