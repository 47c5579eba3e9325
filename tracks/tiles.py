"""Tile tracks: a path of moves over square tiles turned into the exact straight/arc chain.

Every tile holds one piece of centre line from the middle of the edge the path enters by to the
middle of the edge it leaves by: a straight of one tile length, or a quarter turn of radius half a
tile about the tile corner between the two edges (BuzzRacer's straight and turn tiles). The chain
starts at the centre of the start tile, heading along the path.
"""
from __future__ import annotations

import math

from .definition import ArcSegment, StraightSegment, TileLayout, TILE_MOVES, TrackFormatError

# Unit steps (column, row) and headings (deg) of the moves, in TILE_MOVES order (u, r, d, l).
_STEP = {"u": (0, 1), "r": (1, 0), "d": (0, -1), "l": (-1, 0)}
_HEADING_DEG = {"u": 90.0, "r": 0.0, "d": 270.0, "l": 180.0}


def tile_sequence(layout: TileLayout, source: str = "<track>") -> list[tuple[int, int]]:
    """The tiles the path visits, from (0, 0), one per move (the last move returns to (0, 0)).

    Raises :class:`TrackFormatError` with field ``tiles.path[i]`` naming the move at fault: a move
    off the grid, onto a tile already used (the track would cross or touch itself), back to the
    first tile before the last move, or a path that ends away from tile (0, 0).
    """
    assert set(layout.path) <= set(TILE_MOVES), "letters are checked when the file is parsed"
    tiles = [(0, 0)]
    seen = {(0, 0): -1}
    col, row = 0, 0
    last = len(layout.path) - 1
    for i, move in enumerate(layout.path):
        col, row = col + _STEP[move][0], row + _STEP[move][1]
        field = f"tiles.path[{i}]"
        if not (0 <= col < layout.cols and 0 <= row < layout.rows):
            raise TrackFormatError(field, f"move {i} {move!r} leaves the {layout.rows} x {layout.cols} grid "
                                          f"(to tile ({col}, {row}))", source)
        if (col, row) in seen:
            if (col, row) == (0, 0) and i == last:
                break
            by = "the start tile (0, 0)" if seen[(col, row)] < 0 else f"move {seen[(col, row)]}"
            what = "returns to" if (col, row) == (0, 0) else "enters"
            raise TrackFormatError(field, f"move {i} {move!r} {what} tile ({col}, {row}), already used by {by}: "
                                          "the track crosses itself", source)
        seen[(col, row)] = i
        tiles.append((col, row))
    else:
        raise TrackFormatError(f"tiles.path[{last}]", f"the path does not close: after the last move {last} "
                                                      f"{layout.path[last]!r} it is at tile ({col}, {row}), not (0, 0)",
                               source)
    return tiles


def tile_chain(layout: TileLayout, source: str = "<track>"):
    """``(start, segments)`` of the tile track: the start pose (x m, y m, heading rad) and the
    StraightSegment/ArcSegment chain around the loop (see :func:`tile_sequence` for the errors).

    The start is the centre of ``layout.start_tile`` (which must be a straight tile on the path) or,
    without one, of the first straight tile along the path; a loop of turns only starts at the edge
    tile (0, 0) is entered by.
    """
    tiles = tile_sequence(layout, source)
    n = len(layout.path)
    # Tile k is entered by move k-1 (tile 0 by the last move) and left by move k.
    entry = [layout.path[k - 1] for k in range(n)]
    exit_ = list(layout.path)
    straight = [entry[k] == exit_[k] for k in range(n)]
    if layout.start_tile is not None:
        if layout.start_tile not in tiles[:n]:
            raise TrackFormatError("tiles.start_tile", f"tile {list(layout.start_tile)} is not on the path", source)
        first = tiles.index(layout.start_tile)
        if not straight[first]:
            raise TrackFormatError("tiles.start_tile", f"tile {list(layout.start_tile)} is a turn; the start line "
                                                       "must be on a straight tile", source)
    else:
        first = next((k for k in range(n) if straight[k]), None)

    half = 0.5 * layout.tile_size
    segments: list[StraightSegment | ArcSegment] = []
    for k in range(n):
        turn = (_HEADING_DEG[exit_[k]] - _HEADING_DEG[entry[k]]) % 360.0
        if turn == 0.0:
            segments.append(StraightSegment(layout.tile_size))
        else:
            segments.append(ArcSegment(half, 90.0 if turn == 90.0 else -90.0))
    if first is None:  # turns only: start where the path enters tile (0, 0)
        heading = _HEADING_DEG[entry[0]]
        dx, dy = _STEP[entry[0]]
        start = ((0.5 - 0.5 * dx) * layout.tile_size, (0.5 - 0.5 * dy) * layout.tile_size, math.radians(heading))
        return start, tuple(segments)
    col, row = tiles[first]
    start = ((col + 0.5) * layout.tile_size, (row + 0.5) * layout.tile_size, math.radians(_HEADING_DEG[exit_[first]]))
    # The start tile's straight is split at the start line: its second half opens the chain, its first half closes it.
    chain = [StraightSegment(half)] + segments[first + 1:] + segments[:first] + [StraightSegment(half)]
    return start, tuple(chain)
