"""Reader for the F1/10 run folders of the FrictionMaps data set (../shared/data/real-drive-logs/frictionmaps-f110,
README there; docs/sysid.md, "F1/10 runs").

A run folder holds one CSV per ROS topic, each with its own time stamps (columns ``s``, ``ns``):
``pfPoseData.csv`` (particle-filter pose: ``x``, ``y``, quaternion ``q.z``, ``q.w``), ``commandData.csv``
(the Ackermann command: speed set-point ``V`` in m/s, steering angle ``delta`` in rad) and
``pfOdomData.csv`` (wheel speed ``vx``). One row per pose; the commands stay on their own time stamps
(``DriveLog.commands``) and are also given per row (the one in effect at the pose, for range checks);
the speed column is the wheel speed's magnitude at the pose time (linear interpolation). Poses before
the first command are dropped. The commands are declared as steering in rad and a speed set-point.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

import fileio
from sysid.log import MAX_FILE_BYTES, MAX_LINE, CommandStream, CommandUnits, DriveLog, LogFormatError, check_values

POSE_FILE, COMMAND_FILE, WHEEL_FILE = "pfPoseData.csv", "commandData.csv", "pfOdomData.csv"
UNITS = CommandUnits(steering="rad", throttle="speed")


def is_f110_run(path: Path) -> bool:
    return (path / POSE_FILE).is_file() and (path / COMMAND_FILE).is_file()


def _columns(path: Path, wanted: tuple[str, ...]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The wanted columns (floats) and each row's line number; errors name the file, row and column."""
    text = fileio.read_text(path, "F1/10 log file", max_bytes=MAX_FILE_BYTES, max_line=MAX_LINE, error=LogFormatError)
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        raise LogFormatError(f"{path}: empty file (no header row)")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in ("s", "ns", *wanted) if c not in header]
    if missing:
        raise LogFormatError(f"{path}: row 1: header is missing column(s) {missing}")
    if len(rows) < 2:
        raise LogFormatError(f"{path}: the file has a header but no data rows")
    index = {c: header.index(c) for c in ("s", "ns", *wanted)}
    out = {c: np.empty(len(rows) - 1) for c in index}
    for k, fields in enumerate(rows[1:]):
        if len(fields) != len(header):
            raise LogFormatError(f"{path}: row {k + 2}: expected {len(header)} fields, got {len(fields)}")
        for c, i in index.items():
            try:
                v = float(fields[i])
            except ValueError:
                raise LogFormatError(f"{path}: row {k + 2}, column {c}: not a number: {fields[i]!r}") from None
            if not math.isfinite(v):
                raise LogFormatError(f"{path}: row {k + 2}, column {c}: must be finite, got {fields[i]!r}")
            out[c][k] = v
    t = out.pop("s") + 1e-9 * out.pop("ns")
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        raise LogFormatError(f"{path}: row {back[0] + 3}, column s/ns: time goes backwards "
                             f"({t[back[0] + 1]!r} after {t[back[0]]!r})")
    out["t"] = t
    return out, np.arange(2, len(rows) + 1)


def read_f110_run(path: str | Path) -> DriveLog:
    path = Path(path)
    pose, rows = _columns(path / POSE_FILE, ("x", "y", "q.z", "q.w"))
    cmd, _ = _columns(path / COMMAND_FILE, ("V", "delta"))
    keep = pose["t"] >= cmd["t"][0]
    if keep.sum() < 3:
        raise LogFormatError(f"{path / POSE_FILE}: fewer than 3 poses after the first command "
                             f"({path / COMMAND_FILE} starts at {cmd['t'][0]:.3f} s)")
    t = pose["t"][keep]
    active = np.searchsorted(cmd["t"], t, side="right") - 1
    speed = None
    if (path / WHEEL_FILE).is_file():
        wheel, _ = _columns(path / WHEEL_FILE, ("vx",))
        speed = np.abs(np.interp(t, wheel["t"], wheel["vx"]))
    heading = np.angle(np.exp(2j * np.arctan2(pose["q.z"][keep], pose["q.w"][keep])))
    log = DriveLog(
        source=str(path), t=t, car=np.zeros(t.size, dtype=int), x=pose["x"][keep], y=pose["y"][keep],
        heading=heading, throttle=cmd["V"][active], steering=cmd["delta"][active], speed=speed, row=rows[keep],
        commands=CommandStream(cmd["t"], cmd["V"], cmd["delta"]), units=UNITS,
    )
    check_values(log, log.car.astype(float))
    return log
