"""Tile tracks (tracks/tiles.py): BuzzRacer layouts against hand-counted geometry, and the errors
that name the move at fault."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from app.cli import main
from tracks import TrackFormatError, available_tracks, load_track, track_from_dict


def tile_track(path: str, grid=(3, 3), **tiles) -> dict:
    return {"name": "t", "closed": True, "width": 0.563,
            "tiles": {"grid": list(grid), "path": path, "tile_size": 0.6, **tiles}}


def test_buzzracer_full_matches_hand_counted_tiles():
    track = load_track("buzzracer:full")
    # uuurrullurrrdddddluulddl: pairs (move i-1, move i) round the loop, counted by hand: 12 keep
    # the direction (straight tiles), 12 turn (quarter circles of radius 0.3 m).
    assert track.length == pytest.approx(12 * 0.6 + 12 * 0.5 * math.pi * 0.3, abs=1e-9)
    # Start at the centre of tile (3, 3) heading -y; half a tile on, the edge to tile (3, 2).
    x, y = track.position(0.0)
    assert (x, y, float(track.heading(0.0))) == pytest.approx((2.1, 2.1, -math.pi / 2), abs=1e-12)
    assert track.position(0.3) == pytest.approx([2.1, 1.8], abs=1e-12)
    arena = track.arena   # the grid with the 0.2 m floor border the file declares for the fixed markers
    assert (arena.x_min, arena.x_max, arena.y_min, arena.y_max) == pytest.approx((-0.2, 2.6, -0.2, 3.8))
    assert abs(track.curvature(np.linspace(0, track.length, 500))).max() == pytest.approx(1 / 0.3)
    left, right = track.boundaries(0.01)
    for edge in (left, right):   # the surface lies on the grid, within 18.5 mm of its walls at most
        assert edge.min() >= 0.0185 - 1e-9 and edge[:, 0].max() <= 2.4 - 0.0185 + 1e-9


def test_every_shipped_buzzracer_layout_loads_with_its_own_name():
    names = [n for n in available_tracks() if n.startswith("buzzracer:")]
    assert {"buzzracer:full", "buzzracer:small", "buzzracer:big", "buzzracer:easy"} <= set(names)
    for name in names:
        assert load_track(name).name == name


def test_four_turn_loop_is_a_circle():
    # "urdl" on a 2 x 2 grid: four quarter turns about the shared corner (0.6, 0.6), radius 0.3.
    track = track_from_dict(tile_track("urdl", grid=(2, 2)))
    s = np.linspace(0, track.length, 100, endpoint=False)
    p = track.position(s)
    assert track.length == pytest.approx(2 * math.pi * 0.3)
    arena = track.arena   # no arena in the file: the tile grid
    assert (arena.x_min, arena.x_max, arena.y_min, arena.y_max) == (0.0, 1.2, 0.0, 1.2)
    assert np.hypot(p[:, 0] - 0.6, p[:, 1] - 0.6) == pytest.approx(np.full(100, 0.3), abs=1e-12)


@pytest.mark.parametrize("path, grid, field, words", [
    ("uurx", (3, 3), "tiles.path[3]", "move 3 is 'x': unknown move letter"),
    ("uurr", (3, 3), "tiles.path[3]", "does not close"),
    ("ruuldrdl", (3, 3), "tiles.path[5]", "move 5 'r' enters tile (1, 1), already used by move 1: the track crosses itself"),
    ("rrulldrr", (3, 3), "tiles.path[5]", "move 5 'd' returns to tile (0, 0)"),
    ("uuuurddd", (3, 3), "tiles.path[2]", "move 2 'u' leaves the 3 x 3 grid"),
])
def test_bad_tile_paths_name_the_move(path, grid, field, words):
    with pytest.raises(TrackFormatError) as info:
        track_from_dict(tile_track(path, grid))
    assert info.value.field == field and words in str(info.value)


def test_start_tile_must_be_a_straight_on_the_path():
    with pytest.raises(TrackFormatError, match="tiles.start_tile: tile \\[1, 1\\] is a turn"):
        track_from_dict(tile_track("urdl", (2, 2), start_tile=[1, 1]))
    with pytest.raises(TrackFormatError, match="tiles.start_tile: tile \\[2, 2\\] is not on the path"):
        track_from_dict(tile_track("urdl", (3, 3), start_tile=[2, 2]))


def test_bad_tile_file_exits_2_naming_file_and_move(tmp_path, capsys):
    f = tmp_path / "lab.json"
    f.write_text(json.dumps(tile_track("uurrddlq", (3, 3))))
    code = main(["track-show", str(f), "--out", str(tmp_path / "x.png")])
    err = capsys.readouterr().err
    assert code == 2 and "lab.json: tiles.path[7]: move 7 is 'q'" in err
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("tiles, field", [
    ({"grid": [0, 3]}, "tiles.grid[0]"),
    ({"grid": [3, 101]}, "tiles.grid[1]"),
    ({"tile_size": -0.6}, "tiles.tile_size"),
    ({"start_tile": [1]}, "tiles.start_tile"),
    ({"tile_sise": 0.6}, "tiles.tile_sise"),
])
def test_bad_tile_fields_are_named(tiles, field):
    data = tile_track("urdl", (2, 2))
    data["tiles"].update(tiles)
    with pytest.raises(TrackFormatError) as info:
        track_from_dict(data)
    assert info.value.field == field
