"""Drive logs from race-stack Rerun recordings (`python -m app race --out RUN.rrd`, also --hil / hardware).

The recording is read with the race stack's own reader (``race.recording.load_recording``, rerun's chunk
reader). Per car (``cars/{car}/command/*`` present) the rows are the car's pose measurements with the
commands in effect (docs/sysid.md, "Rerun recordings"):

* poses, first available of:
  1. camera detections: ``world/cars/{car}/detection`` (Points2D, x y at the frame's capture time) and
     ``cars/{car}/detection_heading_rad`` (Scalars, same times) - HIL and hardware races;
  2. the simulator's state: ``world/cars/{car}/position`` (Points2D, CG) and the heading of
     ``world/cars/{car}/footprint`` (LineStrips2D, corners front-left, front-right, rear-right,
     rear-left) - in the pure simulation this is what the planners measure; in a HIL recording without
     detection headings it is the simulator's truth (the source says so); never in hardware mode, where
     these entities hold the estimate predicted ahead for planning;
* ``speed`` from ``cars/{car}/speed_mps`` only with source 2 in a pure simulation (the true speed is the
  measured one there);
* ``throttle`` and ``steering`` from ``cars/{car}/command/throttle`` and ``cars/{car}/command/steering_rad``
  (what was sent, logged per control step): row k gets the command in effect for most of
  [t_k, t_{k+1}) (the last one sent at or before the interval's middle), rows before the first command
  are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from race.recording import RecordingError, load_recording
from sim.collision import rectangle_poses
from sysid.log import DriveLog, LogFormatError, check_values

# Car ids of a pure-simulation recording (no marker ids there): the race's car order, which is also the
# real-time stack's default --marker-ids 0,1.


@dataclass(frozen=True)
class CarRows:
    """One car's extracted rows (before concatenation) and where they came from."""

    name: str
    car_id: int
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    throttle: np.ndarray
    steering: np.ndarray
    speed: np.ndarray | None
    pose_source: str


def read_rrd(path: Path) -> DriveLog:
    try:
        data = load_recording(path)
    except RecordingError as exc:
        raise LogFormatError(str(exc)) from None
    return drive_log_from_recording(data)


def _car_ids(data, names: list[str]) -> dict[str, int]:
    """Marker (ArUco) ids from the recording's roster (race.recording.RecordingData.roster)."""
    ids = {c["name"]: int(c["marker_id"]) for c in data.roster() if isinstance(c.get("marker_id"), int)}
    out, used = {}, set(ids.values()) | {-1}
    for name in names:
        if name in ids:
            out[name] = ids[name]
        else:  # a car the roster does not name: next free id
            out[name] = max(used) + 1
            used.add(out[name])
    return out


def _require(data, entity: str, what: str) -> None:
    if not data.has(entity):
        raise LogFormatError(f"{data.path}: entity {entity!r} is missing ({what})")


def _same_times(data, a: str, ta: np.ndarray, b: str, tb: np.ndarray) -> None:
    if ta.shape != tb.shape or not np.array_equal(ta, tb):
        raise LogFormatError(f"{data.path}: entities {a!r} ({ta.size} rows) and {b!r} ({tb.size} rows) are not "
                             f"logged at the same times; they must be one row per sample")


def _one_point(data, entity: str, t: np.ndarray, pts: list[np.ndarray]) -> np.ndarray:
    sizes = np.array([len(p) for p in pts])
    bad = np.flatnonzero(sizes != 1)
    if bad.size:
        raise LogFormatError(f"{data.path}: entity {entity!r}: row at sim_time {t[bad[0]]:.4f} s has "
                             f"{sizes[bad[0]]} points, expected 1")
    return np.concatenate(pts).reshape(-1, 2)


def _poses(data, name: str, mode: str):
    """(t, x, y, heading, speed or None, source) of one car; see the module doc for the order."""
    det, det_heading = f"world/cars/{name}/detection", f"cars/{name}/detection_heading_rad"
    if data.has(det_heading):
        _require(data, det, "camera detections of the car")
        t, pts = data.points(det)
        th, heading = data.scalars(det_heading)
        _same_times(data, det, t, det_heading, th)
        xy = _one_point(data, det, t, pts)
        return t, xy[:, 0], xy[:, 1], heading, None, f"camera detections ({det}, {det_heading})"
    position, footprint = f"world/cars/{name}/position", f"world/cars/{name}/footprint"
    if mode == "hardware":
        raise LogFormatError(f"{data.path}: entity {det_heading!r} is missing (headings of the camera detections); "
                             f"a hardware recording has no other pose measurement ({position} is the estimate "
                             f"predicted ahead for planning)")
    _require(data, position, "positions of the car")
    _require(data, footprint, "footprints of the car, which give its heading")
    t, pts = data.points(position)
    tf, strips = data.strips(footprint)
    _same_times(data, position, t, footprint, tf)
    xy = _one_point(data, position, t, pts)
    short = [i for i, s in enumerate(strips) if not s or len(s[0]) < 4]
    if short:
        raise LogFormatError(f"{data.path}: entity {footprint!r}: row at sim_time {tf[short[0]]:.4f} s has fewer "
                             f"than 4 corners")
    _, heading, _ = rectangle_poses(np.array([s[0][:4] for s in strips]))
    speed = None
    source = f"simulator states ({position}, heading of {footprint})"
    if mode == "simulation":
        speed_entity = f"cars/{name}/speed_mps"
        ts, v = data.scalars(speed_entity)
        if ts.size:
            _same_times(data, position, t, speed_entity, ts)
            speed = v
            source = f"simulator states ({position}, heading of {footprint}, {speed_entity})"
    else:
        source = f"simulator truth, no camera detection headings in this recording ({position}, heading of {footprint})"
    return t, xy[:, 0], xy[:, 1], heading, speed, source


def _commands_for(t_rows: np.ndarray, t_cmd: np.ndarray) -> np.ndarray:
    """Index of the command in effect for most of each row's interval [t_k, t_{k+1}): the last one sent at
    or before the interval's middle (the row's own time for the last row); -1 before the first command."""
    mid = np.append(0.5 * (t_rows[:-1] + t_rows[1:]), t_rows[-1:]) if t_rows.size else t_rows
    return np.searchsorted(t_cmd, mid, side="right") - 1


def car_rows(data, name: str, car_id: int) -> CarRows:
    mode = str(data.setup().get("mode", "simulation"))
    thr_entity, steer_entity = f"cars/{name}/command/throttle", f"cars/{name}/command/steering_rad"
    _require(data, thr_entity, "throttle commands sent to the car")
    _require(data, steer_entity, "steering commands sent to the car")
    t_cmd, throttle = data.scalars(thr_entity)
    t_steer, steering = data.scalars(steer_entity)
    _same_times(data, thr_entity, t_cmd, steer_entity, t_steer)
    t, x, y, heading, speed, source = _poses(data, name, mode)
    if t_cmd.size == 0 or t.size == 0:
        raise LogFormatError(f"{data.path}: car {name}: no commands or no poses recorded")
    which = _commands_for(t, t_cmd)
    keep = which >= 0
    if not keep.any():
        raise LogFormatError(f"{data.path}: car {name}: every pose is older than the first command "
                             f"({thr_entity} starts at {t_cmd[0]:.3f} s)")
    which = which[keep]
    return CarRows(name=name, car_id=car_id, t=t[keep], x=x[keep], y=y[keep], heading=heading[keep],
                   throttle=throttle[which], steering=steering[which],
                   speed=None if speed is None else speed[keep], pose_source=source)


def recording_cars(data) -> list[str]:
    """Names of the cars that were sent commands (a human-driven opponent has none)."""
    names = sorted({e.split("/")[1] for e in data.entities
                    if e.startswith("cars/") and e.endswith("/command/throttle")})
    if not names:
        raise LogFormatError(f"{data.path}: no entity 'cars/<car>/command/throttle' (commands sent to a car); "
                             f"not a race-stack recording (docs/sysid.md)")
    order = {c["name"]: i for i, c in enumerate(data.roster())}
    return sorted(names, key=lambda n: (order.get(n, len(order)), n))


def drive_log_from_recording(data) -> DriveLog:
    """All commanded cars of a recording as one DriveLog (rows ordered by car, then time)."""
    names = recording_cars(data)
    ids = _car_ids(data, names)
    rows = [car_rows(data, name, ids[name]) for name in names]
    with_speed = all(r.speed is not None for r in rows)
    cat = lambda field: np.concatenate([getattr(r, field) for r in rows])  # noqa: E731
    n = sum(r.t.size for r in rows)
    car = np.concatenate([np.full(r.t.size, r.car_id, dtype=int) for r in rows])
    log = DriveLog(
        source=str(data.path), t=cat("t"), car=car, x=cat("x"), y=cat("y"), heading=cat("heading"),
        throttle=cat("throttle"), steering=cat("steering"), speed=cat("speed") if with_speed else None,
        row=np.arange(1, n + 1), car_labels={r.car_id: r.name for r in rows},
        pose_sources={r.car_id: r.pose_source for r in rows},
    )
    check_values(log, car.astype(float))
    return log
