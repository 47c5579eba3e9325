"""Typed contents of a track file (format in docs/tracks.md) and field-level validation.

``parse_definition`` turns the decoded JSON object into a :class:`TrackDefinition`, raising
:class:`TrackFormatError` that names the offending field (e.g. ``segments[2].radius``).
Checks that need the geometry (closure, width vs. curvature, self-overlap, arena fit) are done
when the :class:`tracks.Track` is built.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from fileio import InputFileError, unknown_key_message


class TrackFormatError(InputFileError):
    """A track file or definition is invalid. ``field`` names the part at fault (e.g. ``width``)."""

    def __init__(self, field: str, message: str, source: str = "<track>"):
        self.field = field
        self.source = source
        super().__init__(f"{source}: {field}: {message}")


@dataclass(frozen=True)
class StraightSegment:
    """Straight piece of a segment track; ``length`` in m (> 0)."""

    length: float


@dataclass(frozen=True)
class ArcSegment:
    """Circular arc of a segment track: ``radius`` in m (> 0); ``angle_deg`` signed, positive = left turn."""

    radius: float
    angle_deg: float

    @property
    def length(self) -> float:
        """Arc length (m)."""
        return self.radius * math.radians(abs(self.angle_deg))

    @property
    def curvature(self) -> float:
        """Signed curvature (1/m), positive = left."""
        return math.copysign(1.0 / self.radius, self.angle_deg)


@dataclass(frozen=True)
class Lane:
    """A lane of the road: ``offset`` is the lateral position of its centre (m, ey, positive = left
    of the direction of travel) and ``width`` its width (m)."""

    name: str
    offset: float
    width: float


@dataclass(frozen=True)
class Arena:
    """Axis-aligned rectangle (m, world frame) the whole track surface must fit in."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float

    @property
    def size(self) -> tuple[float, float]:
        """(extent along x, extent along y) in m."""
        return (self.x_max - self.x_min, self.y_max - self.y_min)


@dataclass(frozen=True)
class TileLayout:
    """A BuzzRacer-style tile track: square tiles of ``tile_size`` m on a ``rows`` x ``cols`` grid, laid
    along ``path``, a string of moves ``u`` (+y), ``r`` (+x), ``d`` (-y), ``l`` (-x) from tile (0, 0),
    whose lower-left corner is the world origin. Tile (i, j) is column i (x), row j (y).
    ``start_tile`` is the straight tile whose centre is the start line (None: the first straight
    tile along the path)."""

    rows: int
    cols: int
    path: str
    tile_size: float
    start_tile: tuple[int, int] | None = None


TILE_MOVES = "urdl"


@dataclass(frozen=True)
class TrackDefinition:
    """A track as written in its file. Exactly one of ``centerline``, (``start``, ``segments``) and
    ``tiles`` is set.

    ``width`` is the full drivable width in m: one number, or one per centre-line point.
    """

    name: str
    closed: bool
    width: float | tuple[float, ...]
    centerline: tuple[tuple[float, float], ...] | None = None
    start: tuple[float, float, float] | None = None  # (x m, y m, heading rad)
    segments: tuple[StraightSegment | ArcSegment, ...] | None = None
    tiles: TileLayout | None = None     # tile tracks: the Track builds start and segments from it
    lanes: tuple[Lane, ...] = ()
    arena: Arena | None = None
    description: str = ""


_TOP_LEVEL_KEYS = {"name", "description", "closed", "width", "centerline", "start", "segments", "tiles", "lanes", "arena"}
_TILE_KEYS = {"grid", "path", "tile_size", "start_tile"}
# Tile grids larger than this many tiles a side (60 m of 0.6 m tiles) are not a lab's floor; the bound keeps
# the straight/arc chain (one segment per tile) small.
MAX_TILE_GRID = 100

# Every number in a track file (m or degrees) lies within +-MAX_ABS_NUMBER; widths, lengths and radii
# are at least MIN_LENGTH_M: beyond either the geometry overflows or divides by ~0.
MAX_ABS_NUMBER = 1e6
MIN_LENGTH_M = 1e-3
# Consecutive centre-line points closer than this are treated as duplicates (m).
_DUPLICATE_POINT_TOLERANCE = 1e-6
# Closed tracks: first and last point this close mean the loop was written out explicitly (m).
CLOSURE_TOLERANCE = 1e-3


def _number(value: Any, field: str, source: str) -> float:
    # bool is an int subclass in Python, but `true` is never a valid length.
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TrackFormatError(field, f"expected a number, got {value!r}", source)
    if isinstance(value, int) and abs(value) > MAX_ABS_NUMBER:  # (float() of a huge int overflows)
        raise TrackFormatError(field, f"must be within +-{MAX_ABS_NUMBER:g}, got an integer of {len(str(abs(value)))} digits", source)
    value = float(value)
    if not math.isfinite(value):
        raise TrackFormatError(field, f"must be finite, got {value!r}", source)
    if abs(value) > MAX_ABS_NUMBER:  # the geometry would overflow to inf/NaN
        raise TrackFormatError(field, f"must be within +-{MAX_ABS_NUMBER:g} (m or degrees), got {value!r}", source)
    return value


def _positive(value: Any, field: str, source: str) -> float:
    value = _number(value, field, source)
    if value < MIN_LENGTH_M:  # 1e-320 is positive, but its curvature is infinite
        raise TrackFormatError(field, f"must be >= {MIN_LENGTH_M:g} m, got {value!r}", source)
    return value


def _require(data: Mapping[str, Any], key: str, source: str, prefix: str = "") -> Any:
    if key not in data:
        raise TrackFormatError(prefix + key, "missing", source)
    return data[key]


def _check_keys(data: Mapping[str, Any], allowed: set[str], prefix: str, source: str) -> None:
    for key in data:
        if key not in allowed:
            raise TrackFormatError(f"{prefix}{key}", unknown_key_message(key, allowed), source)


def parse_definition(data: Any, source: str = "<track>") -> TrackDefinition:
    """Validate a decoded track-file object field by field and return its typed definition."""
    if not isinstance(data, Mapping):
        raise TrackFormatError("<root>", f"expected a JSON object, got {type(data).__name__}", source)
    _check_keys(data, _TOP_LEVEL_KEYS, "", source)

    name = _require(data, "name", source)
    if not isinstance(name, str) or not name.strip():
        raise TrackFormatError("name", f"expected a non-empty string, got {name!r}", source)
    description = data.get("description", "")
    if not isinstance(description, str):
        raise TrackFormatError("description", f"expected a string, got {description!r}", source)
    closed = _require(data, "closed", source)
    if not isinstance(closed, bool):
        raise TrackFormatError("closed", f"expected true or false, got {closed!r}", source)

    has_points = "centerline" in data
    has_segments = "segments" in data or "start" in data
    has_tiles = "tiles" in data
    if has_points + has_segments + has_tiles > 1:
        raise TrackFormatError("centerline", "give one of 'centerline', 'start'+'segments' or 'tiles', not several", source)
    if not has_points and not has_segments and not has_tiles:
        raise TrackFormatError("centerline", "missing (give 'centerline' points, 'start'+'segments' or 'tiles')", source)

    raw_width = _require(data, "width", source)
    centerline = start = segments = tiles = None
    if has_tiles:
        if not closed:
            raise TrackFormatError("closed", "a tile track is a loop: must be true", source)
        if isinstance(raw_width, list):
            raise TrackFormatError("width", "a tile track takes one width; give one number", source)
        width = _positive(raw_width, "width", source)
        tiles = _parse_tiles(data["tiles"], source)
        if width >= tiles.tile_size:
            raise TrackFormatError("width", f"{width:g} m does not fit on tiles of {tiles.tile_size:g} m", source)
    elif has_points:
        centerline = _parse_centerline(data["centerline"], source)
        if isinstance(raw_width, list):
            if len(raw_width) != len(centerline):
                raise TrackFormatError(
                    "width", f"has {len(raw_width)} values but centerline has {len(centerline)} points", source
                )
            width: float | tuple[float, ...] = tuple(
                _positive(w, f"width[{i}]", source) for i, w in enumerate(raw_width)
            )
        else:
            width = _positive(raw_width, "width", source)
        if closed and math.dist(centerline[0], centerline[-1]) <= CLOSURE_TOLERANCE:
            # The loop was written with its first point repeated at the end: drop the repeat.
            centerline = centerline[:-1]
            if isinstance(width, tuple):
                width = width[:-1]
            if len(centerline) < 3:
                raise TrackFormatError("centerline", "a closed track needs at least 3 distinct points", source)
    else:
        if isinstance(raw_width, list):
            raise TrackFormatError("width", "per-point widths need a 'centerline' track; give one number", source)
        width = _positive(raw_width, "width", source)
        start = _parse_start(_require(data, "start", source), source)
        segments = _parse_segments(_require(data, "segments", source), source)

    lanes = _parse_lanes(data.get("lanes", []), width, source)
    arena = _parse_arena(data["arena"], source) if "arena" in data else None
    if arena is None and tiles is not None:  # the tile grid is the lab's floor
        arena = Arena(0.0, round(tiles.cols * tiles.tile_size, 9), 0.0, round(tiles.rows * tiles.tile_size, 9))
    return TrackDefinition(
        name=name,
        closed=closed,
        width=width,
        centerline=centerline,
        start=start,
        segments=segments,
        tiles=tiles,
        lanes=lanes,
        arena=arena,
        description=description,
    )


def _parse_centerline(raw: Any, source: str) -> tuple[tuple[float, float], ...]:
    if not isinstance(raw, list):
        raise TrackFormatError("centerline", "expected a list of [x, y] points", source)
    if len(raw) < 3:
        raise TrackFormatError("centerline", f"needs at least 3 points, got {len(raw)}", source)
    points = []
    for i, point in enumerate(raw):
        if not isinstance(point, list) or len(point) != 2:
            raise TrackFormatError(f"centerline[{i}]", f"expected [x, y], got {point!r}", source)
        p = (_number(point[0], f"centerline[{i}][0]", source), _number(point[1], f"centerline[{i}][1]", source))
        if points and math.dist(points[-1], p) <= _DUPLICATE_POINT_TOLERANCE:
            raise TrackFormatError(f"centerline[{i}]", f"repeats the previous point {list(p)}", source)
        points.append(p)
    return tuple(points)


def _parse_start(raw: Any, source: str) -> tuple[float, float, float]:
    if not isinstance(raw, list) or len(raw) != 3:
        raise TrackFormatError("start", f"expected [x, y, heading_rad], got {raw!r}", source)
    return tuple(_number(v, f"start[{i}]", source) for i, v in enumerate(raw))  # type: ignore[return-value]


def _parse_segments(raw: Any, source: str) -> tuple[StraightSegment | ArcSegment, ...]:
    if not isinstance(raw, list) or not raw:
        raise TrackFormatError("segments", "expected a non-empty list of segments", source)
    segments: list[StraightSegment | ArcSegment] = []
    for i, seg in enumerate(raw):
        prefix = f"segments[{i}]."
        if not isinstance(seg, Mapping):
            raise TrackFormatError(f"segments[{i}]", f"expected an object, got {seg!r}", source)
        kind = _require(seg, "type", source, prefix)
        if kind == "straight":
            _check_keys(seg, {"type", "length"}, prefix, source)
            segments.append(StraightSegment(_positive(_require(seg, "length", source, prefix), prefix + "length", source)))
        elif kind == "arc":
            _check_keys(seg, {"type", "radius", "angle_deg"}, prefix, source)
            radius = _positive(_require(seg, "radius", source, prefix), prefix + "radius", source)
            angle = _number(_require(seg, "angle_deg", source, prefix), prefix + "angle_deg", source)
            if angle == 0.0:
                raise TrackFormatError(prefix + "angle_deg", "must be non-zero (positive = left turn)", source)
            segments.append(ArcSegment(radius, angle))
        else:
            raise TrackFormatError(prefix + "type", f"expected 'straight' or 'arc', got {kind!r}", source)
    return tuple(segments)


def _grid_int(value: Any, field: str, source: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= MAX_TILE_GRID:
        raise TrackFormatError(field, f"expected an integer in [{low}, {MAX_TILE_GRID}], got {value!r}", source)
    return value


def _parse_tiles(raw: Any, source: str) -> TileLayout:
    if not isinstance(raw, Mapping):
        raise TrackFormatError("tiles", "expected an object with grid, path, tile_size (and start_tile)", source)
    _check_keys(raw, _TILE_KEYS, "tiles.", source)
    grid = _require(raw, "grid", source, "tiles.")
    if not isinstance(grid, list) or len(grid) != 2:
        raise TrackFormatError("tiles.grid", f"expected [rows, cols], got {grid!r}", source)
    rows, cols = (_grid_int(v, f"tiles.grid[{i}]", source, 1) for i, v in enumerate(grid))
    path = _require(raw, "path", source, "tiles.")
    if not isinstance(path, str) or len(path) < 4:
        raise TrackFormatError("tiles.path", f"expected a string of at least 4 moves u/r/d/l, got {path!r}", source)
    for i, move in enumerate(path):
        if move not in TILE_MOVES:
            raise TrackFormatError(f"tiles.path[{i}]", f"move {i} is {move!r}: unknown move letter (moves: u, r, d, l)", source)
    tile_size = _positive(_require(raw, "tile_size", source, "tiles."), "tiles.tile_size", source)
    start_tile = None
    if "start_tile" in raw:
        value = raw["start_tile"]
        if not isinstance(value, list) or len(value) != 2:
            raise TrackFormatError("tiles.start_tile", f"expected [column, row], got {value!r}", source)
        start_tile = (_grid_int(value[0], "tiles.start_tile[0]", source, 0), _grid_int(value[1], "tiles.start_tile[1]", source, 0))
    return TileLayout(rows, cols, path, tile_size, start_tile)


def _parse_lanes(raw: Any, width: float | tuple[float, ...], source: str) -> tuple[Lane, ...]:
    if not isinstance(raw, list):
        raise TrackFormatError("lanes", "expected a list of lanes", source)
    half_width = 0.5 * (min(width) if isinstance(width, tuple) else width)
    lanes = []
    for i, lane in enumerate(raw):
        prefix = f"lanes[{i}]."
        if not isinstance(lane, Mapping):
            raise TrackFormatError(f"lanes[{i}]", f"expected an object, got {lane!r}", source)
        _check_keys(lane, {"name", "offset", "width"}, prefix, source)
        name = _require(lane, "name", source, prefix)
        if not isinstance(name, str) or not name:
            raise TrackFormatError(prefix + "name", f"expected a non-empty string, got {name!r}", source)
        if any(other.name == name for other in lanes):
            raise TrackFormatError(prefix + "name", f"duplicate lane name {name!r}", source)
        offset = _number(_require(lane, "offset", source, prefix), prefix + "offset", source)
        lane_width = _positive(_require(lane, "width", source, prefix), prefix + "width", source)
        if abs(offset) + 0.5 * lane_width > half_width + 1e-9:
            raise TrackFormatError(
                prefix + "offset",
                f"lane spans ey in [{offset - lane_width / 2:g}, {offset + lane_width / 2:g}] m, "
                f"outside the track's +-{half_width:g} m",
                source,
            )
        lanes.append(Lane(name, offset, lane_width))
    return tuple(lanes)


def _parse_arena(raw: Any, source: str) -> Arena:
    if not isinstance(raw, Mapping):
        raise TrackFormatError("arena", "expected an object with x_min, x_max, y_min, y_max", source)
    keys = ("x_min", "x_max", "y_min", "y_max")
    _check_keys(raw, set(keys), "arena.", source)
    values = {k: _number(_require(raw, k, source, "arena."), f"arena.{k}", source) for k in keys}
    for axis in ("x", "y"):
        if values[f"{axis}_max"] <= values[f"{axis}_min"]:
            raise TrackFormatError(f"arena.{axis}_max", f"must be greater than arena.{axis}_min", source)
    return Arena(**values)
