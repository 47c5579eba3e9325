"""Matplotlib drawing of a track (imported lazily so the real-time stack never loads matplotlib)."""
from __future__ import annotations

import numpy as np
from matplotlib.patches import PathPatch
from matplotlib.path import Path as MplPath

from .track import Track


def draw_track(
    ax,
    track: Track,
    *,
    surface_color: str = "0.85",
    edge_color: str = "0.2",
    start_line_color: str = "tab:red",
    show_centerline: bool = True,
    show_lanes: bool = True,
    show_arena: bool = True,
    ds: float | None = None,
    zorder: float = 0.0,
) -> dict:
    """Draw ``track`` on a matplotlib Axes: surface, edges, start line, and (optionally) centre line,
    lane dividers and arena outline. Sets an equal aspect ratio.

    ``ds`` is the sampling step along the centre line (m; default length/2000). Returns a dict of
    the created artists (``surface``, ``left``, ``right``, ``start_line``, ...) for restyling.
    """
    ds = track.length / 2000.0 if ds is None else ds
    left, right = track.boundaries(ds)
    artists: dict = {}
    if track.closed:
        # One compound path: the left ring forward and the right ring backward make a hole
        # (the infield) under the non-zero winding rule whichever way the track turns.
        ring_l = np.vstack([left, left[:1]])
        ring_r = np.vstack([right, right[:1]])[::-1]
        verts = np.vstack([ring_l, ring_r])
        codes = np.full(len(verts), MplPath.LINETO)
        codes[0] = codes[len(ring_l)] = MplPath.MOVETO
        codes[len(ring_l) - 1] = codes[-1] = MplPath.CLOSEPOLY
    else:
        verts = np.vstack([left, right[::-1], left[:1]])
        codes = np.full(len(verts), MplPath.LINETO)
        codes[0] = MplPath.MOVETO
        codes[-1] = MplPath.CLOSEPOLY
    artists["surface"] = ax.add_patch(
        PathPatch(MplPath(verts, codes), facecolor=surface_color, edgecolor="none", zorder=zorder)
    )
    close = (lambda a: np.vstack([a, a[:1]])) if track.closed else (lambda a: a)
    (artists["left"],) = ax.plot(*close(left).T, color=edge_color, lw=1.5, zorder=zorder + 0.1)
    (artists["right"],) = ax.plot(*close(right).T, color=edge_color, lw=1.5, zorder=zorder + 0.1)
    s = np.linspace(0.0, track.length, len(left) + 1)
    if show_centerline:
        c = track.position(s)
        (artists["centerline"],) = ax.plot(*c.T, color=edge_color, lw=0.6, ls=":", zorder=zorder + 0.1)
    if show_lanes and len(track.lanes) > 1:
        # Dividers between adjacent lanes (ordered right to left).
        lanes = sorted(track.lanes, key=lambda lane: lane.offset)
        artists["lane_dividers"] = []
        for a, b in zip(lanes[:-1], lanes[1:]):
            ey = 0.5 * ((a.offset + a.width / 2) + (b.offset - b.width / 2))
            x, y = track.to_cartesian(s, np.full_like(s, ey))
            (line,) = ax.plot(x, y, color="white", lw=1.2, ls="--", zorder=zorder + 0.1)
            artists["lane_dividers"].append(line)
    half = 0.5 * float(track.width(0.0))
    x0, y0 = track.to_cartesian(np.array([0.0, 0.0]), np.array([-half, half]))
    (artists["start_line"],) = ax.plot(x0, y0, color=start_line_color, lw=2.5, zorder=zorder + 0.2)
    if show_arena and track.arena is not None:
        a = track.arena
        (artists["arena"],) = ax.plot(
            [a.x_min, a.x_max, a.x_max, a.x_min, a.x_min],
            [a.y_min, a.y_min, a.y_max, a.y_max, a.y_min],
            color="0.5",
            lw=1.0,
            zorder=zorder,
        )
    ax.set_aspect("equal")
    ax.autoscale_view()
    return artists


def draw_racing_line(ax, track: Track, line, *, cmap: str = "viridis", lw: float = 2.0, zorder: float = 0.5,
                     colorbar: bool = True):
    """Draw a racing line (tracks.racing_line.RacingLine) on ``track``, coloured by its speed (m/s).

    Returns the LineCollection (and adds a colour bar labelled in m/s unless ``colorbar`` is False).
    """
    from matplotlib.collections import LineCollection

    x, y = track.to_cartesian(line.s, line.ey)
    points = np.column_stack([x, y])
    segments = np.stack([points, np.roll(points, -1, axis=0)], axis=1)
    speed = line.speed_mps
    collection = LineCollection(segments, cmap=cmap, linewidths=lw, zorder=zorder)
    collection.set_array(0.5 * (speed + np.roll(speed, -1)))
    collection.set_clim(float(speed.min()), float(speed.max()) if speed.max() > speed.min() else float(speed.min()) + 1e-3)
    ax.add_collection(collection)
    if colorbar:
        ax.figure.colorbar(collection, ax=ax, label="racing-line speed (m/s)", shrink=0.8)
    return collection
