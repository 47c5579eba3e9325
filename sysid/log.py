"""Drive logs for model identification: reading (CSV, race-stack Rerun .rrd) and writing CSV.

Format (docs/sysid.md): one row per pose measurement with columns
``t, car, x, y, heading, throttle, steering`` and optionally ``speed``. Commands are the values
sent at time ``t``. Readers are chosen by file suffix through ``LOG_READERS``; the .rrd reader
(``sysid.rrd``) extracts the same rows from a race recording.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

import fileio

REQUIRED_COLUMNS = ("t", "car", "x", "y", "heading", "throttle", "steering")
OPTIONAL_COLUMNS = ("speed",)
# Plausibility bounds: values outside are logging errors, not driving.
MAX_ABS_STEERING_RAD = 1.2
MAX_ABS_POSITION_M = 1000.0
MAX_SPEED_MPS = 50.0
MAX_CAR_ID = 2**31 - 1
CAR_ID_RULE = f"must be an integer id in 0..{MAX_CAR_ID}"
# A row of 8 numbers is under 200 characters; anything far longer is not a drive log.
MAX_LINE = 4096
MAX_FILE_BYTES = 1024 * 2**20


class LogFormatError(fileio.InputFileError):
    """The log is malformed; the message names the file, row (1-based line number) and column."""


# Command conventions (docs/sysid.md, "Command conventions"): what the steering and throttle columns hold.
STEERING_UNITS = ("rad", "normalized", "us")  # wheel angle command; fraction of max_steering_rad; pulse width
THROTTLE_UNITS = ("normalized", "us", "speed")  # throttle in [-1, 1]; pulse width; speed set-point in m/s
PULSE_RANGE_US = (1000.0, 2000.0)


@dataclass(frozen=True)
class CommandUnits:
    """The convention of a log's command columns, as declared (an option, or the reader's format)."""

    steering: str = "rad"
    throttle: str = "normalized"

    def __post_init__(self) -> None:
        if self.steering not in STEERING_UNITS:
            raise ValueError(f"steering units: one of {STEERING_UNITS}, got {self.steering!r}")
        if self.throttle not in THROTTLE_UNITS:
            raise ValueError(f"throttle units: one of {THROTTLE_UNITS}, got {self.throttle!r}")


@dataclass(frozen=True)
class CommandStream:
    """Commands logged on their own time stamps (a reader whose commands and poses come from different
    messages): each is held from its time until the next."""

    t: np.ndarray
    throttle: np.ndarray
    steering: np.ndarray


@dataclass(frozen=True)
class DriveLog:
    """All rows of a log, in file order. ``row`` holds each sample's line number in the file (for a
    recording: the number of the extracted row, ordered by car, then time). ``car_labels`` names the
    cars of a recording (id -> race name); ``pose_sources`` says where each car's poses came from."""

    source: str
    t: np.ndarray
    car: np.ndarray  # int
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    throttle: np.ndarray
    steering: np.ndarray
    speed: np.ndarray | None
    row: np.ndarray  # int, line number in the file (header = 1)
    car_labels: dict[int, str] = field(default_factory=dict)
    pose_sources: dict[int, str] = field(default_factory=dict)
    commands: CommandStream | None = None  # None: the commands of the rows (sent at the rows' times)
    units: CommandUnits = CommandUnits()

    @property
    def cars(self) -> list[int]:
        return sorted(set(self.car.tolist()))

    def describe_cars(self) -> str:
        """'[0, 1]' or, for a recording, '[0 (rd3g), 1 (opponent)]'."""
        return "[" + ", ".join(f"{c} ({self.car_labels[c]})" if c in self.car_labels else str(c) for c in self.cars) + "]"

    def select_car(self, car: int) -> "DriveLog":
        keep = self.car == car
        if not keep.any():
            raise LogFormatError(f"{self.source}: no rows for car {car}; the log has cars {self.describe_cars()}")
        return DriveLog(
            source=self.source,
            t=self.t[keep], car=self.car[keep], x=self.x[keep], y=self.y[keep], heading=self.heading[keep],
            throttle=self.throttle[keep], steering=self.steering[keep],
            speed=None if self.speed is None else self.speed[keep], row=self.row[keep],
            car_labels={c: n for c, n in self.car_labels.items() if c == car},
            pose_sources={c: n for c, n in self.pose_sources.items() if c == car}, commands=self.commands,
            units=self.units,
        )


_UNITS_COMMENT = re.compile(r"^\s*#\s*(steering|throttle)_units\s*[=:]\s*(\S+)\s*$")


def _declared_units(source: str, lines: list[str], option: CommandUnits | None) -> CommandUnits:
    """The command convention of a CSV log: comment lines ``# steering_units = normalized`` /
    ``# throttle_units = us`` in the file, or the option; both given and different is an error."""
    found: dict[str, tuple[str, int]] = {}
    for i, line in enumerate(lines):
        hit = _UNITS_COMMENT.match(line)
        if hit:
            found[hit.group(1)] = (hit.group(2), i + 1)
    for channel, (value, row) in found.items():
        try:
            CommandUnits(**{channel: value})
        except ValueError as exc:
            raise LogFormatError(f"{source}: row {row}: {exc}") from None
    header = CommandUnits(**{k: v for k, (v, _) in found.items()})
    if option is None:
        return header
    for channel, (value, row) in found.items():
        if getattr(option, channel) != value:
            raise LogFormatError(f"{source}: row {row}: the file declares {channel}_units = {value}, the option "
                                 f"--{channel}-units {getattr(option, channel)}")
    return option


def _read_csv(path: Path, units: CommandUnits | None = None) -> DriveLog:
    source = str(path)
    text = fileio.read_text(path, "log file", max_bytes=MAX_FILE_BYTES, max_line=MAX_LINE, error=LogFormatError)
    lines = text.splitlines()
    units = _declared_units(source, lines, units)
    # Comment lines (#...) and blank lines are skipped but keep their line numbers.
    numbered = [(i + 1, ln) for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not numbered:
        raise LogFormatError(f"{source}: empty log (no header row)")
    reader = csv.reader([ln for _, ln in numbered])
    try:
        rows = list(reader)
    except csv.Error as exc:  # e.g. a NUL byte; lines are split before csv sees them, so line_num is the row
        raise LogFormatError(f"{source}: row {numbered[reader.line_num - 1][0]}: not CSV: {exc}") from None
    header_line, header = numbered[0][0], [h.strip() for h in rows[0]]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise LogFormatError(
            f"{source}: row {header_line}: header is missing column(s) {missing}; "
            f"required {list(REQUIRED_COLUMNS)}, optional {list(OPTIONAL_COLUMNS)}"
        )
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise LogFormatError(f"{source}: row {header_line}: duplicate column(s) {dup}")
    columns = list(REQUIRED_COLUMNS) + [c for c in OPTIONAL_COLUMNS if c in header]
    index = {c: header.index(c) for c in columns}
    if len(rows) < 2:
        raise LogFormatError(f"{source}: the log has a header but no data rows")

    n = len(rows) - 1
    values = {c: np.empty(n) for c in columns}
    line_numbers = np.array([ln for ln, _ in numbered[1:]], dtype=int)
    for k, fields in enumerate(rows[1:]):
        line = line_numbers[k]
        if len(fields) != len(header):
            raise LogFormatError(f"{source}: row {line}: expected {len(header)} fields, got {len(fields)}")
        for c in columns:
            raw = fields[index[c]].strip()
            try:
                v = float(raw)
            except ValueError:
                raise LogFormatError(f"{source}: row {line}, column {c}: not a number: {raw!r}") from None
            if not math.isfinite(v):
                raise LogFormatError(f"{source}: row {line}, column {c}: must be finite, got {raw!r}")
            values[c][k] = v
    car = values["car"]
    bad = _first_bad((car != np.round(car)) | (car < 0) | (car > MAX_CAR_ID))
    if bad is not None:  # before the cast to int, which would turn 1e300 into garbage
        raise LogFormatError(f"{source}: row {line_numbers[bad]}, column car: {CAR_ID_RULE}, got {float(car[bad])!r}")
    log = DriveLog(
        source=source,
        t=values["t"], car=car.astype(int), x=values["x"], y=values["y"], heading=values["heading"],
        throttle=values["throttle"], steering=values["steering"], speed=values.get("speed"), row=line_numbers,
        units=units,
    )
    check_values(log, values["car"])
    return log


def _first_bad(mask: np.ndarray) -> int | None:
    hits = np.flatnonzero(mask)
    return int(hits[0]) if hits.size else None


def check_values(log: DriveLog, car_raw: np.ndarray) -> None:
    """Range checks (vectorised); the first offending row and column are reported."""
    checks: list[tuple[str, np.ndarray, str]] = [
        ("car", (car_raw != np.round(car_raw)) | (car_raw < 0) | (car_raw > MAX_CAR_ID), CAR_ID_RULE),
        ("x", np.abs(log.x) > MAX_ABS_POSITION_M, f"|x| must be <= {MAX_ABS_POSITION_M} m"),
        ("y", np.abs(log.y) > MAX_ABS_POSITION_M, f"|y| must be <= {MAX_ABS_POSITION_M} m"),
        ("heading", np.abs(log.heading) > 100.0, "heading must be in radians (|heading| <= 100)"),
        _command_check("throttle", log.throttle, log.units.throttle),
        _command_check("steering", log.steering, log.units.steering),
    ]
    if log.speed is not None:
        checks.append(("speed", (log.speed < 0) | (log.speed > MAX_SPEED_MPS), f"speed must be in [0, {MAX_SPEED_MPS}] m/s"))
    for column, bad, why in checks:
        k = _first_bad(bad)
        if k is not None:
            value = float(getattr(log, column)[k] if column != "car" else car_raw[k])
            raise LogFormatError(f"{log.source}: row {log.row[k]}, column {column}: {why}, got {value!r}")
    # Time must not run backwards within a car (duplicates are allowed and merged later).
    for car in log.cars:
        idx = np.flatnonzero(log.car == car)
        back = _first_bad(np.diff(log.t[idx]) < 0)
        if back is not None:
            k = idx[back + 1]
            raise LogFormatError(
                f"{log.source}: row {log.row[k]}, column t: time goes backwards for car {car} "
                f"({log.t[k]!r} after {log.t[idx[back]]!r})"
            )


def _command_check(column: str, values: np.ndarray, unit: str) -> tuple[str, np.ndarray, str]:
    """Range of a command column in its declared convention."""
    if unit == "us":
        lo, hi = PULSE_RANGE_US
        return column, (values < lo) | (values > hi), f"declared as pulse widths (us): must be in [{lo:g}, {hi:g}]"
    if unit == "normalized":
        return column, np.abs(values) > 1.0, "declared normalised: must be in [-1, 1]"
    if unit == "speed":
        return column, np.abs(values) > MAX_SPEED_MPS, f"declared a speed set-point: must be within +-{MAX_SPEED_MPS} m/s"
    return (column, np.abs(values) > MAX_ABS_STEERING_RAD,
            f"steering must be a wheel angle in radians, |steering| <= {MAX_ABS_STEERING_RAD} (normalised commands "
            "or pulse widths: declare them, docs/sysid.md)")


def _read_rrd(path: Path) -> DriveLog:
    from sysid.rrd import read_rrd  # imports rerun; only when a recording is read

    return read_rrd(path)


# Suffix -> reader.
LOG_READERS: dict[str, Callable[[Path], DriveLog]] = {".csv": _read_csv, ".rrd": _read_rrd}


def _read_dir(path: Path) -> DriveLog:
    from sysid.f110 import is_f110_run, read_f110_run  # only for a run folder

    if not is_f110_run(path):
        raise LogFormatError(f"{path}: a folder that is not an F1/10 run (no commandData.csv and pfPoseData.csv)")
    return read_f110_run(path)


def read_log(path: str | Path, units: CommandUnits | None = None) -> DriveLog:
    """Read a log; ``units``: the declared convention of a CSV log's command columns (other formats
    declare their own and refuse a different one)."""
    path = Path(path)
    if path.is_dir():
        log = _read_dir(path)
    else:
        reader = LOG_READERS.get(path.suffix.lower())
        if reader is None:
            raise LogFormatError(f"{path}: unknown log format {path.suffix!r}; supported: {sorted(LOG_READERS)} "
                                 "and F1/10 run folders")
        if reader is _read_csv:
            return _read_csv(path, units)
        log = reader(path)
    if units is not None and units != log.units:
        raise LogFormatError(f"{path}: the format's commands are steering in {log.units.steering} and throttle in "
                             f"{log.units.throttle}; the declared units ({units.steering}, {units.throttle}) differ")
    return log


def write_log_csv(path: str | Path, log: DriveLog) -> Path:
    """Write ``log`` in the CSV format read by :func:`read_log`."""
    path = Path(path)
    columns = list(REQUIRED_COLUMNS) + (["speed"] if log.speed is not None else [])
    data = [log.t, log.car, log.x, log.y, log.heading, log.throttle, log.steering]
    if log.speed is not None:
        data.append(log.speed)
    def write(tmp: Path) -> None:
        with tmp.open("w", encoding="utf-8", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(columns)
            for row in zip(*(np.asarray(d).tolist() for d in data)):
                w.writerow([f"{v:.6f}" if isinstance(v, float) else str(v) for v in row])
    return fileio.atomic_write_with(path, write)
