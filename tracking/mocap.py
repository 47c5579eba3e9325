"""Motion capture (OptiTrack Motive and the like) as a pose sensor: rigid-body poses in the mocap frame ->
car poses on the track (docs/tracking.md, "Motion capture").

* :class:`MocapFrame`: one frame of the mocap system, rigid bodies by id, on the loop's clock. It stands
  where a camera frame stands (``t_capture_s``, ``index``; no image).
* :func:`ground_pose`: a rigid body's position and quaternion -> (u, v, yaw) on the ground plane of the
  mocap frame, for Motive's Y-up (its default) or Z-up streaming. (u, v) is right-handed seen from above:
  Y-up (x, -z), Z-up (x, y); yaw is the body's +x axis counter-clockwise from +u.
* :class:`MocapTransform`: the 2-D similarity from that ground plane to the track frame (the mocap
  calibration file, docs/file-formats.md), :func:`fit_transform` estimates it from surveyed points.
* :class:`MocapTracker`: a frame -> ``tracking.markers.FrameDetections`` of the cars, keyed like the camera
  tracker's (the car's filter key), so the race loop's perception and estimator take mocap poses unchanged.
  A rigid body Motive reports untracked, or absent, is not measured (a lost marker).
"""
from __future__ import annotations

import csv
import math
import time
from dataclasses import dataclass, field

import numpy as np

import fileio
from fileio import Array, FieldSpec, Number, String, Table
from tracking.markers import CarMeasurement, FrameDetections
from tracks.geometry import wrap_angle

UP_AXES = ("y", "z")
CALIBRATION_FORMAT = "rd3g-mocap-calibration"


class MocapCalibrationError(fileio.InputFileError):
    """A mocap calibration file cannot be read or does not follow the format (names file and field)."""


@dataclass(frozen=True)
class RigidBodySample:
    position: tuple[float, float, float]      # metres, mocap frame
    rotation: tuple[float, float, float, float]  # quaternion (qx, qy, qz, qw), NatNet's order
    tracked: bool = True                       # Motive's "tracking valid" flag


@dataclass(frozen=True)
class MocapFrame:
    t_capture_s: float                  # on the loop's clock
    index: int                          # the mocap system's frame number
    bodies: dict[int, RigidBodySample]  # rigid-body id -> sample
    image: None = None                  # a pose sensor has no image


def ground_pose(position, rotation, up_axis: str = "y") -> tuple[float, float, float]:
    """(u, v, yaw) of a rigid body on the mocap frame's ground plane (module docstring)."""
    qx, qy, qz, qw = rotation
    # The body's +x axis in the mocap frame: first column of the rotation matrix.
    fx = 1.0 - 2.0 * (qy * qy + qz * qz)
    fy = 2.0 * (qx * qy + qw * qz)
    fz = 2.0 * (qx * qz - qw * qy)
    x, y, z = position
    if up_axis == "y":
        return float(x), float(-z), math.atan2(-fz, fx)
    if up_axis == "z":
        return float(x), float(y), math.atan2(fy, fx)
    raise ValueError(f"up_axis must be one of {UP_AXES}, got {up_axis!r}")


@dataclass(frozen=True)
class MocapTransform:
    """Track = scale * R(rotation_rad) @ (u, v) + translation_m; track heading = yaw + rotation_rad."""

    up_axis: str = "y"
    rotation_rad: float = 0.0
    translation_m: tuple[float, float] = (0.0, 0.0)
    scale: float = 1.0
    residual_rms_m: float | None = None   # of the fit that made it (None: set by hand)
    points: int | None = None             # surveyed points of that fit

    def __post_init__(self) -> None:
        if self.up_axis not in UP_AXES:
            raise ValueError(f"MocapTransform.up_axis: must be one of {UP_AXES}, got {self.up_axis!r}")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"MocapTransform.scale: must be a positive number, got {self.scale!r}")

    def to_track(self, u: float, v: float, yaw: float) -> tuple[float, float, float]:
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        k = self.scale
        return (k * (c * u - s * v) + self.translation_m[0], k * (s * u + c * v) + self.translation_m[1],
                wrap_angle(yaw + self.rotation_rad))

    def to_mocap(self, x: float, y: float, heading: float) -> tuple[float, float, float]:
        """The inverse of :meth:`to_track` (the loopback emulator puts track poses into the mocap frame)."""
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        dx, dy = (x - self.translation_m[0]) / self.scale, (y - self.translation_m[1]) / self.scale
        return c * dx + s * dy, -s * dx + c * dy, wrap_angle(heading - self.rotation_rad)


def mocap_body(u: float, v: float, yaw: float, height_m: float, up_axis: str = "y") -> RigidBodySample:
    """A level rigid body at ground-plane pose (u, v, yaw), ``height_m`` above the floor (inverse of
    :func:`ground_pose`)."""
    half = 0.5 * yaw
    if up_axis == "y":  # yaw about +y turns +x towards -z, i.e. towards +v
        return RigidBodySample((u, height_m, -v), (0.0, math.sin(half), 0.0, math.cos(half)))
    return RigidBodySample((u, v, height_m), (0.0, 0.0, math.sin(half), math.cos(half)))


@dataclass(frozen=True)
class TransformFit:
    transform: MocapTransform
    residuals_m: np.ndarray  # per point, distance between the mapped mocap point and the track point

    @property
    def rms_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_m ** 2)))


def fit_transform(mocap_uv, track_xy, up_axis: str = "y", with_scale: bool = False) -> TransformFit:
    """Least-squares 2-D rigid (or, ``with_scale``, similarity) transform taking ground-plane mocap points
    to surveyed track points (Umeyama's closed form, reflections excluded). At least 2 points (3 to
    have a residual that says anything)."""
    p = np.asarray(mocap_uv, dtype=float)
    q = np.asarray(track_xy, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape != q.shape:
        raise ValueError(f"fit_transform: expected two (n, 2) point arrays, got {p.shape} and {q.shape}")
    if len(p) < 2:
        raise ValueError(f"fit_transform: at least 2 points are needed, got {len(p)}")
    pm, qm = p.mean(axis=0), q.mean(axis=0)
    pc, qc = p - pm, q - qm
    spread = float(np.sum(pc ** 2))
    if spread < 1e-12:
        raise ValueError("fit_transform: the mocap points all coincide")
    # Rotation maximising sum q_i . R p_i: angle of sum (p x q, p . q).
    angle = math.atan2(float(np.sum(pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0])), float(np.sum(pc * qc)))
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    scale = float(np.sum(qc * (pc @ rot.T))) / spread if with_scale else 1.0
    t = qm - scale * rot @ pm
    residuals = np.linalg.norm(scale * p @ rot.T + t - q, axis=1)
    rms = float(np.sqrt(np.mean(residuals ** 2)))
    return TransformFit(MocapTransform(up_axis, angle, (float(t[0]), float(t[1])), scale, rms, len(p)), residuals)


_SCHEMA = Table({
    "format": FieldSpec(String(choices=(CALIBRATION_FORMAT,))),
    "up_axis": FieldSpec(String(choices=UP_AXES)),
    "rotation_rad": FieldSpec(Number(ge=-2 * math.pi, le=2 * math.pi)),
    "translation_m": FieldSpec(Array(1, Number(ge=-1e3, le=1e3), length=2)),
    "scale": FieldSpec(Number(gt=0.5, lt=2.0), required=False),
    "residual_rms_m": FieldSpec(Number(ge=0), required=False, nullable=True),
    "points": FieldSpec(Number(integer=True, ge=2), required=False, nullable=True),
}, "mocap calibration")


def load_mocap_calibration(path) -> MocapTransform:
    """A mocap calibration file (JSON, docs/file-formats.md); MocapCalibrationError naming file and field."""
    data = fileio.load_json(path, "mocap calibration file", error=MocapCalibrationError)
    d = fileio.validate(data, _SCHEMA, str(path), MocapCalibrationError)
    return MocapTransform(d["up_axis"], d["rotation_rad"], tuple(float(v) for v in d["translation_m"]),
                          d.get("scale", 1.0), d.get("residual_rms_m"), d.get("points"))


SURVEY_COLUMNS = ("mocap_x", "mocap_y", "mocap_z", "track_x", "track_y")
MAX_SURVEY_COORD_M = 100.0


@dataclass(frozen=True)
class SurveyPoints:
    """Surveyed points: where Motive sees a marker (its 3-D position, metres) and the track point it sits on."""

    names: list[str]
    mocap_xyz: np.ndarray   # (n, 3)
    track_xy: np.ndarray    # (n, 2)
    rows: list[int]         # file line of each point


def load_survey_points(path) -> SurveyPoints:
    """The points CSV of ``mocap-calibrate``: a header with mocap_x, mocap_y, mocap_z, track_x, track_y and an
    optional name column, one point per row (# comments and blank lines skipped). MocapCalibrationError
    naming the file, row and column."""
    source = str(path)
    text = fileio.read_text(path, "survey points file", error=MocapCalibrationError)
    numbered = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not numbered:
        raise MocapCalibrationError(f"{source}: empty file (expected a header {','.join(SURVEY_COLUMNS)})")
    try:
        rows = list(csv.reader(ln for _, ln in numbered))
    except csv.Error as exc:
        raise MocapCalibrationError(f"{source}: not CSV: {exc}") from None
    header = [h.strip() for h in rows[0]]
    unknown = [h for h in header if h not in (*SURVEY_COLUMNS, "name")]
    missing = [c for c in SURVEY_COLUMNS if c not in header]
    if unknown or missing or len(set(header)) != len(header):
        raise MocapCalibrationError(f"{source}: row {numbered[0][0]}: the header must have the columns "
                                    f"{', '.join(SURVEY_COLUMNS)} (and optionally name), once each; got {header}")
    names, values, lines = [], [], []
    for (line, _), fields in zip(numbered[1:], rows[1:]):
        if len(fields) != len(header):
            raise MocapCalibrationError(f"{source}: row {line}: expected {len(header)} fields, got {len(fields)}")
        row = dict(zip(header, (f.strip() for f in fields)))
        point = []
        for c in SURVEY_COLUMNS:
            try:
                v = float(row[c])
            except ValueError:
                raise MocapCalibrationError(f"{source}: row {line}, column {c}: not a number: {row[c]!r}") from None
            if not (math.isfinite(v) and abs(v) <= MAX_SURVEY_COORD_M):
                raise MocapCalibrationError(f"{source}: row {line}, column {c}: must be a finite number of metres "
                                            f"within +-{MAX_SURVEY_COORD_M:g}, got {row[c]!r}")
            point.append(v)
        names.append(row.get("name") or f"row {line}")
        values.append(point)
        lines.append(line)
    if len(values) < 3:
        raise MocapCalibrationError(f"{source}: {len(values)} point(s); at least 3 surveyed points are needed "
                                    f"(2 fix the transform, the third checks it)")
    a = np.array(values)
    return SurveyPoints(names, a[:, :3], a[:, 3:], lines)


def mocap_calibration_json(t: MocapTransform) -> dict:
    return {"format": CALIBRATION_FORMAT, "up_axis": t.up_axis, "rotation_rad": t.rotation_rad,
            "translation_m": list(t.translation_m), "scale": t.scale, "residual_rms_m": t.residual_rms_m,
            "points": t.points}


@dataclass(frozen=True)
class MocapCar:
    """One car as the mocap system sees it: its rigid body and where that body's pivot sits on the car
    (vehicles.params.MocapParams)."""

    key: int                        # the car's filter key in the race loop (race.loop.CarBinding.marker_id)
    rigid_body_id: int
    offset_forward_m: float = 0.0   # rigid-body pivot ahead of the car's reference point
    offset_left_m: float = 0.0
    yaw_rad: float = 0.0            # the body's +x axis turned counter-clockwise against the car's heading


@dataclass
class MocapTracker:
    """Mocap frames -> car poses in the track frame (``process`` is the camera tracker's call)."""

    transform: MocapTransform
    cars: list[MocapCar]
    counts: dict = field(default_factory=lambda: {"untracked": 0, "absent": 0})

    def __post_init__(self) -> None:
        self.by_body = {c.rigid_body_id: c for c in self.cars}

    def process(self, frame: MocapFrame, predictions=None) -> FrameDetections:
        """``predictions`` is ignored: the mocap system reports every body in every frame."""
        t0 = time.perf_counter()
        cars, rejected = {}, {}
        for car in self.cars:
            body = frame.bodies.get(car.rigid_body_id)
            if body is None or not body.tracked:
                reason = "absent" if body is None else "untracked"
                self.counts[reason] += 1
                rejected[car.key] = reason
                continue
            x, y, yaw = self.transform.to_track(*ground_pose(body.position, body.rotation, self.transform.up_axis))
            heading = wrap_angle(yaw - car.yaw_rad)
            c, s = math.cos(heading), math.sin(heading)
            x -= c * car.offset_forward_m - s * car.offset_left_m
            y -= s * car.offset_forward_m + c * car.offset_left_m
            cars[car.key] = CarMeasurement(car.key, x, y, heading, frame.t_capture_s, 0.0)
        return FrameDetections(frame.t_capture_s, frame.index, cars, {}, True, time.perf_counter() - t0, rejected)
