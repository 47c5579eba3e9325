"""Track files from the community's circuit formats: TUM racetrack-database centre lines and
f1tenth racelines, optionally scaled into the arena, checked for what a small car can drive.

* TUM centre line: ``# x_m,y_m,w_tr_right_m,w_tr_left_m`` (commas; widths to the right and
  left of the point; a closed circuit, first point not repeated).
* f1tenth raceline: ``# s_m; x_m; y_m; psi_rad; kappa_radpm; vx_mps; ax_mps2`` (semicolons); it
  has no widths, so the importer needs one (``width``).

Errors are :class:`TrackImportError` naming the file and the line (and column) at fault.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import fileio

from .definition import Arena, TrackFormatError
from .geometry import SplineCenterline
from .io import track_from_dict

FORMATS = {
    "tum": (",", ("x_m", "y_m", "w_tr_right_m", "w_tr_left_m")),
    "f1tenth": (";", ("s_m", "x_m", "y_m", "psi_rad", "kappa_radpm", "vx_mps", "ax_mps2")),
}
MIN_POINTS = 4
MAX_FILE_BYTES = 16 * 2**20
DEFAULT_ARENA = Arena(0.0, 5.0, 0.0, 3.0)   # the BuzzRacer arena (docs/tracks.md)


class TrackImportError(ValueError):
    """A circuit file cannot be read, or its track is not drivable; the message names the file and line."""


@dataclass(frozen=True)
class ImportedCircuit:
    """Points of a circuit file: centre line (m) with per-point full width (m, None without widths) and
    the file line each point came from (1-based)."""

    source: str
    format: str
    points: np.ndarray           # (n, 2)
    widths: np.ndarray | None    # (n,)
    lines: np.ndarray            # (n,) line numbers


@dataclass(frozen=True)
class CarEnvelope:
    """What the drivability checks need of the car: footprint width and tightest turn radius (m)."""

    footprint_width_m: float
    min_turn_radius_m: float

    @classmethod
    def of(cls, car) -> "CarEnvelope":
        """From a car file (vehicles.params.CarParams): rear-axle radius wheelbase / tan(max steering)."""
        g = car.geometry
        return cls(g.footprint_width_m, (g.lf_m + g.lr_m) / math.tan(car.actuators.max_steering_rad))


def read_circuit(path: str | os.PathLike, fmt: str = "auto") -> ImportedCircuit:
    """Read a TUM centre-line or f1tenth raceline CSV (``fmt`` "tum", "f1tenth" or "auto": from the header)."""
    source = os.fspath(path)
    try:
        text = fileio.read_text(path, "circuit file", max_bytes=MAX_FILE_BYTES)
    except fileio.InputFileError as exc:
        raise TrackImportError(str(exc)) from None
    lines = text.splitlines()
    header_line, header = 0, None
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if stripped.startswith("#"):
            if "x_m" in stripped:
                header_line, header = number, stripped.lstrip("#").strip()
            continue
        if stripped:
            break
    if fmt == "auto":
        if header is None:
            raise TrackImportError(f"{source}: no header line naming the columns (e.g. '# x_m,y_m,w_tr_right_m,w_tr_left_m'); "
                                   "give the format with --format tum|f1tenth")
        fmt = "f1tenth" if "psi_rad" in header or ";" in header else "tum"
    if fmt not in FORMATS:
        raise TrackImportError(f"{source}: unknown format {fmt!r} (formats: {', '.join(FORMATS)})")
    separator, columns = FORMATS[fmt]
    if header is not None:
        other = ";" if separator == "," else ","
        if separator not in header and other in header:
            raise TrackImportError(f"{source}: line {header_line}: columns separated by {other!r}; "
                                   f"the {fmt} format separates them by {separator!r}")
        names = [name.strip() for name in header.split(separator)]
        missing = [c for c in columns if c not in names]
        if missing:
            raise TrackImportError(f"{source}: line {header_line}: missing column(s) {', '.join(missing)} "
                                   f"(the {fmt} format has {separator.join(columns)})")
        index = [names.index(c) for c in columns]
    else:
        names, index = list(columns), list(range(len(columns)))
    wanted = ("x_m", "y_m", "w_tr_right_m", "w_tr_left_m") if fmt == "tum" else ("x_m", "y_m")
    rows, numbers = [], []
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        cells = [cell.strip() for cell in stripped.split(separator)]
        if len(cells) != len(names):
            hint = (f"; separated by {';' if separator == ',' else ','!r}?" if len(cells) == 1 and
                    (";" if separator == "," else ",") in stripped else "")
            raise TrackImportError(f"{source}: line {number}: {len(cells)} column(s), expected {len(names)} "
                                   f"({separator.join(names)}){hint}")
        row = []
        for column in wanted:
            cell = cells[index[columns.index(column)]]
            try:
                value = float(cell)
            except ValueError:
                raise TrackImportError(f"{source}: line {number}: {column}: {cell!r} is not a number") from None
            if not math.isfinite(value) or abs(value) > 1e6:
                raise TrackImportError(f"{source}: line {number}: {column}: {cell!r} must be finite, within +-1e6")
            if column.startswith("w_") and value <= 0.0:
                raise TrackImportError(f"{source}: line {number}: {column}: {value:g} m; widths must be positive")
            row.append(value)
        rows.append(row)
        numbers.append(number)
    if len(rows) < MIN_POINTS:
        raise TrackImportError(f"{source}: {len(rows)} point(s); a circuit needs at least {MIN_POINTS}")
    data = np.asarray(rows)
    numbers = np.asarray(numbers)
    points = data[:, :2]
    # A closed loop written with its first point repeated at the end: drop the repeat.
    if np.hypot(*(points[-1] - points[0])) < 1e-9:
        data, points, numbers = data[:-1], points[:-1], numbers[:-1]
    same = np.flatnonzero(np.hypot(*np.diff(points, axis=0).T) < 1e-9)
    if len(same):
        raise TrackImportError(f"{source}: line {numbers[same[0] + 1]}: repeats the point of line {numbers[same[0]]}")
    widths = None
    if fmt == "tum":
        # Asymmetric widths: our centre line is the middle of the surface.
        right, left = data[:, 2], data[:, 3]
        points = points + (0.5 * (left - right))[:, None] * _left_normals(points)
        widths = left + right
    return ImportedCircuit(source, fmt, points, widths, numbers)


def _left_normals(points: np.ndarray) -> np.ndarray:
    """Unit left normals of a closed polyline (central differences)."""
    tangent = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return np.column_stack([-tangent[:, 1], tangent[:, 0]])


def fit_into_arena(points: np.ndarray, half_width: float, arena: Arena, wall_margin_m: float, width_scales: bool = False):
    """``(points, scale)``: the circuit scaled about its centre, turned 90 deg if that allows a larger
    scale, and centred in ``arena`` with ``half_width + wall_margin_m`` (m) to every wall.
    ``half_width`` is in the file's units and scales with the circuit when ``width_scales``, else it
    is the final (m) half-width. Raises TrackImportError if even that room does not fit."""
    fixed = 0.0 if width_scales else 2.0 * half_width
    grown = 2.0 * half_width if width_scales else 0.0
    room_x = arena.x_max - arena.x_min - 2.0 * wall_margin_m - fixed
    room_y = arena.y_max - arena.y_min - 2.0 * wall_margin_m - fixed
    if room_x <= 0 or room_y <= 0:
        raise TrackImportError(f"a track {2 * half_width:g} m wide with {wall_margin_m:g} m to the walls does not fit "
                               f"the arena {arena.x_max - arena.x_min:g} x {arena.y_max - arena.y_min:g} m")
    best = None
    for turned in (False, True):
        p = points[:, ::-1] * np.array([-1.0, 1.0]) if turned else points
        extent = np.ptp(p, axis=0) + grown
        scale = min(room_x / extent[0], room_y / extent[1])
        if best is None or scale > best[1] * (1 + 1e-9):
            best = (p, scale)
    p, scale = best
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    arena_centre = np.array([0.5 * (arena.x_min + arena.x_max), 0.5 * (arena.y_min + arena.y_max)])
    return (p - centre) * scale + arena_centre, scale


def check_drivable(circuit: ImportedCircuit, points: np.ndarray, widths: np.ndarray, car: CarEnvelope) -> None:
    """The checks a small car needs after scaling, naming the file line at fault: width at least the
    car's footprint, turn radius above half the width and above the car's tightest radius, no
    crossing of the centre line."""
    src, lines = circuit.source, circuit.lines
    narrow = np.flatnonzero(widths < car.footprint_width_m)
    if len(narrow):
        i = narrow[np.argmin(widths[narrow])]
        raise TrackImportError(f"{src}: line {lines[i]}: the track is {widths[i]:.3f} m wide there, less than the car's "
                               f"footprint width {car.footprint_width_m:.3f} m (give a larger --width)")
    spline = SplineCenterline(points, True, widths)
    u = spline.u_knots[:-1]
    d1, d2 = spline.d1(u), spline.d2(u)
    kappa = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / np.hypot(d1[:, 0], d1[:, 1]) ** 3
    radius = 1.0 / np.maximum(kappa, 1e-12)
    for limit, what in ((0.5 * widths, "half the track width (the inner edge folds over)"),
                        (np.full(len(widths), car.min_turn_radius_m), "the car's tightest turn radius")):
        bad = np.flatnonzero(radius <= limit)
        if len(bad):
            i = bad[np.argmin(radius[bad] - limit[bad])]
            raise TrackImportError(f"{src}: line {lines[i]}: turn radius {radius[i]:.3f} m is below {what}, "
                                   f"{limit[i]:.3f} m")
    crossing = _first_crossing(points)
    if crossing is not None:
        i, j = crossing
        raise TrackImportError(f"{src}: line {lines[i]}: the centre line from here crosses the one from line {lines[j]}")


def _first_crossing(points: np.ndarray):
    """Indices (i, j) of the first pair of non-adjacent edges of the closed polyline that cross, or None."""
    a, b = points, np.roll(points, -1, axis=0)
    n = len(points)
    for i in range(n):
        j = np.arange(i + 2, n if i > 0 else n - 1)
        if len(j) == 0:
            continue
        p, r = a[i], b[i] - a[i]
        q, s = a[j], b[j] - a[j]
        denominator = r[0] * s[:, 1] - r[1] * s[:, 0]
        qp = q - p
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (qp[:, 0] * s[:, 1] - qp[:, 1] * s[:, 0]) / denominator
            w = (qp[:, 0] * r[1] - qp[:, 1] * r[0]) / denominator
        hit = (denominator != 0) & (t >= 0) & (t <= 1) & (w >= 0) & (w <= 1)
        if np.any(hit):
            return i, int(j[np.argmax(hit)])
    return None


def import_track(path: str | os.PathLike, *, car: CarEnvelope, fmt: str = "auto", name: str | None = None,
                 width_m: float | None = None, fit_arena: bool = False, arena: Arena = DEFAULT_ARENA,
                 wall_margin_m: float = 0.1, reverse: bool = False) -> dict:
    """A track-file object (docs/tracks.md) from a circuit CSV, checked by building the Track.

    ``width_m`` replaces the file's widths (after scaling; required for f1tenth files); with
    ``fit_arena`` the circuit is scaled into ``arena`` leaving ``wall_margin_m`` to the walls, else
    it keeps its coordinates (and the arena is not declared). ``reverse`` drives it the other way.
    """
    circuit = read_circuit(path, fmt)
    if width_m is not None and not (math.isfinite(width_m) and width_m > 0):
        raise TrackImportError(f"--width must be a positive number of metres, got {width_m!r}")
    if circuit.widths is None and width_m is None:
        raise TrackImportError(f"{circuit.source}: an {circuit.format} raceline has no track widths: give --width")
    points, widths = circuit.points, circuit.widths
    if reverse:
        circuit = ImportedCircuit(circuit.source, circuit.format, points[::-1], None if widths is None else widths[::-1],
                                  circuit.lines[::-1])
        points, widths = circuit.points, circuit.widths
    scale = 1.0
    if fit_arena:
        half = 0.5 * (width_m if width_m is not None else float(np.max(widths)))
        points, scale = fit_into_arena(points, half, arena, wall_margin_m, width_scales=width_m is None)
        if width_m is None:  # the circuit's own widths, scaled down with it
            widths = widths * scale
    widths = np.full(len(points), width_m) if width_m is not None else widths
    check_drivable(circuit, points, widths, car)
    stem = Path(circuit.source).stem
    uniform = bool(np.all(widths == widths[0]))
    data = {
        "name": name or stem,
        "description": (f"imported from {Path(circuit.source).name} ({circuit.format} format"
                        + (f", scaled 1:{1 / scale:.1f} into the arena" if fit_arena else "")
                        + (f", width set to {width_m:g} m" if width_m is not None else "") + ")"),
        "closed": True,
        "width": float(widths[0]) if uniform else [round(float(w), 6) for w in widths],
        "centerline": [[round(float(x), 6), round(float(y), 6)] for x, y in points],
    }
    if fit_arena:
        data["arena"] = {"x_min": arena.x_min, "x_max": arena.x_max, "y_min": arena.y_min, "y_max": arena.y_max}
    try:
        track_from_dict(data, Path(circuit.source).name)
    except TrackFormatError as exc:
        raise TrackImportError(f"{circuit.source}: not a drivable track after import: {exc}") from None
    return data
