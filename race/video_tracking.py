"""Tracking a recorded video offline (`python -m app track`): its frames through the race loop's own
perception (race.perception.Perception: ArucoTracker with region-of-interest search, MultiCarEstimator)
or, ``raw``, the tracker's detections of full-frame searches without the filter; and the commands a
link capture (vehicles.link_capture) had in effect at each pose's time, so that video and capture
become a drive log that ``sysid`` reads (sysid.log).

A row is written for a car in a frame when the car was found there: with the filter, when the
estimator accepted the frame's measurement (the row holds the filtered pose at the frame's time);
raw, when the tracker detected it. Frames without an accepted measurement of a car are counted per
car (``missed``: not detected; ``gated``: detected but rejected by the filter's gate).
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

import fileio
from race.perception import Perception
from race.world import WorldPacket
from tracking.camera import CameraError, CameraSource, EndOfStream
from vehicles.link_capture import CaptureDecode

POSE_COLUMNS = ("t", "car", "x", "y", "heading")
COMMAND_COLUMNS = ("throttle", "steering")


class VideoTrackError(CameraError):
    """The video cannot be tracked as given (cut short, wrong image size); the message names the file and frame."""


@dataclass(frozen=True)
class TrackedCar:
    """A car to track: its marker id (the ``car`` column) and, for commands from a link capture, its
    radio id in the capture's frames and ``to_physical(steering, throttle) -> (throttle, steering rad)``
    for the values the capture holds (normalised for rd3g, pulse widths for buzzracer-fhss)."""

    marker_id: int
    radio_id: int | None = None
    to_physical: Callable[[float, float], tuple[float, float]] | None = None

    @property
    def name(self) -> str:  # race.perception.Perception's car binding
        return str(self.marker_id)


@dataclass
class TrackResult:
    rows: np.ndarray                      # (n, 5): t, car, x, y, heading
    frames: int
    image_size: tuple[int, int] | None    # (width, height) of the frames
    missed: dict[int, int]                # frames in which a car was not detected
    gated: dict[int, int]                 # frames in which its detection was rejected by the filter
    commands: np.ndarray | None = None    # (n, 2): throttle, steering rad per row (link capture)
    command_notes: list[str] = field(default_factory=list)


def check_image_size(frame, source: str, calibration, calibration_path: str) -> tuple[int, int]:
    """(width, height) of ``frame``; VideoTrackError unless it is the calibration's image size."""
    height, width = frame.image.shape[:2]
    expected = tuple(int(v) for v in calibration.camera.image_size)
    if (width, height) != expected:
        raise VideoTrackError(f"{source}: frame {frame.index} is {width}x{height} px but {calibration_path}: "
                              f"image_width/image_height is {expected[0]}x{expected[1]} px (a calibration of "
                              f"another camera or resolution)")
    return width, height


def track_video(source: CameraSource, tracker, cars: list[TrackedCar], estimator=None, *,
                lost_search_every: int = 1, calibration_path: str = "calibration",
                progress: Callable[[int], None] | None = None) -> TrackResult:
    """Every frame of ``source`` until its end. ``estimator`` None: raw detections (a full-frame search
    per frame); else the race loop's perception, which searches around the tracked cars and the full
    frame every ``lost_search_every`` frames while a car is lost (1: every frame; offline nothing is
    gained by skipping frames). ``source.frame_count`` (when known) must be reached: a video that ends earlier is cut
    short (VideoTrackError). ``progress(1)`` after each frame."""
    ids = [c.marker_id for c in cars]
    perception = None if estimator is None else Perception(tracker, estimator, cars, lost_search_every)
    rows: list[tuple[float, int, float, float, float]] = []
    missed = {m: 0 for m in ids}
    gated = {m: 0 for m in ids}
    frames = 0
    size = None
    name = getattr(source, "path", "video")
    while True:
        try:
            frame = source.read()
        except EndOfStream:
            break
        if size is None:
            size = check_image_size(frame, name, tracker.calibration, calibration_path)
        elif frame.image.shape[:2] != size[::-1]:
            raise VideoTrackError(f"{name}: frame {frame.index} is {frame.image.shape[1]}x{frame.image.shape[0]} px, "
                                  f"frame 0 was {size[0]}x{size[1]} px")
        frames += 1
        t = frame.t_capture_s
        if perception is None:
            found = tracker.process(frame, None).cars
            for m in ids:
                if m in found:
                    d = found[m]
                    rows.append((t, m, d.x, d.y, d.heading))
                else:
                    missed[m] += 1
        else:
            out = perception.perceive(WorldPacket(frame=frame), t, t)
            detected = set(out.observation.poses) if out.observation is not None else set()
            for c in cars:
                if c.name not in detected:
                    missed[c.marker_id] += 1
                elif c.name not in out.accepted or c.name not in out.states:
                    gated[c.marker_id] += 1
                else:
                    x, y, heading = out.states[c.name][:3]
                    rows.append((t, c.marker_id, float(x), float(y), float(heading)))
        if progress is not None:
            progress(1)
    count = getattr(source, "frame_count", None)
    if count is not None and frames < count:
        raise VideoTrackError(f"{name}: frame {frames}: cannot be read, but the file announces {count} frames "
                              f"(truncated or damaged video)")
    if frames == 0:
        raise VideoTrackError(f"{name}: no frames")
    array = np.array(rows, dtype=float).reshape(-1, 5)
    return TrackResult(array, frames, size, missed, gated)


def commands_at(decode: CaptureDecode, cars: list[TrackedCar], rows: np.ndarray, offset_s: float,
                failsafe_timeout_s: float, source: str = "capture") -> tuple[np.ndarray, list[str]]:
    """(throttle, steering rad) per row: the last frame of the capture sent at or before the row's time
    (capture time + ``offset_s`` is video time), neutral before the first frame and after
    ``failsafe_timeout_s`` without one (the box's silence failsafe). Notes count the rows outside the
    capture's span."""
    out = np.zeros((len(rows), 2))
    notes: list[str] = []
    if not decode.frames:
        raise ValueError(f"{source}: no good frame to take commands from")
    t_frames = np.array([f.t for f in decode.frames]) + offset_s
    if np.any(np.diff(t_frames) < 0):
        k = int(np.flatnonzero(np.diff(t_frames) < 0)[0]) + 1
        raise ValueError(f"{source}: frame {k} at {decode.frames[k].t} s is earlier than the frame before it")
    for car in cars:
        sel = np.flatnonzero(rows[:, 1] == car.marker_id)
        carried = [i for i, f in enumerate(decode.frames) if car.radio_id in f.cars]
        if not carried:
            ids = sorted({c for f in decode.frames for c in f.cars})
            raise ValueError(f"{source}: no frame carries radio id {car.radio_id} (car {car.marker_id}); "
                             f"the capture's ids: {ids}")
        values = np.array([car.to_physical(*decode.frames[i].cars[car.radio_id]) for i in carried])
        times = t_frames[carried]
        t = rows[sel, 0]
        k = np.searchsorted(times, t, side="right") - 1
        live = (k >= 0) & (t - times[np.maximum(k, 0)] < failsafe_timeout_s)
        out[sel[live]] = values[k[live]]
        before, after = int(np.sum(t < times[0])), int(np.sum(t >= times[-1] + failsafe_timeout_s))
        if before or after:
            notes.append(f"car {car.marker_id}: {before} row(s) before the capture's first frame and {after} after "
                         f"its last (neutral commands; check --link-offset)")
    return out, notes


def write_track_csv(path: str | Path, result: TrackResult) -> Path:
    """``t,car,x,y,heading`` (and ``throttle,steering`` with commands), the sysid drive-log format
    (docs/sysid.md), rows in time order."""
    columns = list(POSE_COLUMNS) + (list(COMMAND_COLUMNS) if result.commands is not None else [])

    def write(tmp: Path) -> None:
        with tmp.open("w", encoding="utf-8", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(columns)
            for k, (t, car, x, y, heading) in enumerate(result.rows.tolist()):
                row = [f"{t:.6f}", str(int(car)), f"{x:.6f}", f"{y:.6f}", f"{heading:.6f}"]
                if result.commands is not None:
                    row += [f"{v:.6f}" for v in result.commands[k]]
                w.writerow(row)
    return fileio.atomic_write_with(path, write)

