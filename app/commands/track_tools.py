"""`python -m app track-show TRACK` and `python -m app track-import CSV`: the operator's track tools
(docs/tracks.md). Both print the track's length, width range, tightest turn radius and the lap time
of its racing line at the car's limits."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from app.cli import UserError
from fileio import atomic_write_text, check_output_path
from planning.reference import planner_racing_line
from race.hil import FIXED_MARKERS
from race.setup import RaceSetup
from tracking.calibration import load_fixed_markers
from tracks import Arena, TrackFormatError, UnknownTrackError, load_track, track_from_dict
from tracks.importers import FORMATS, CarEnvelope, TrackImportError, import_track
from tracks.racing_line import RacingLineError, lap_time_s, speed_profile
from vehicles.params import CarParamsError, load_car_params


def register(sub) -> None:
    show = sub.add_parser("track-show", help="draw a track with its racing line to a PNG and print its numbers")
    show.add_argument("track", metavar="TRACK", help="track name (oval, buzzracer:full, ...) or track file")
    show.add_argument("--out", help="PNG to write (default runs/track_<name>.png)")
    _car_arguments(show)
    show.set_defaults(func=run_show)

    imp = sub.add_parser("track-import", help="write a track file from a TUM centre-line or f1tenth raceline CSV")
    imp.add_argument("csv", metavar="CSV", help="TUM racetrack-database centre line or f1tenth raceline file")
    imp.add_argument("--out", required=True, help="track file (JSON) to write")
    imp.add_argument("--format", default="auto", choices=("auto", *FORMATS), help="file format (default: from the header)")
    imp.add_argument("--name", help="track name (default: the file's stem)")
    imp.add_argument("--width", type=float, help="full drivable width (m, after scaling) for every point; "
                                                 "required for f1tenth racelines")
    imp.add_argument("--fit-arena", action="store_true", help="scale and centre the circuit into the arena")
    imp.add_argument("--arena", default="5x3", help="arena size X x Y in m for --fit-arena (default 5x3)")
    imp.add_argument("--wall-margin", type=float, default=0.1, help="room from the track edge to the arena walls "
                                                                    "(m, --fit-arena; default 0.1)")
    imp.add_argument("--reverse", action="store_true", help="drive the circuit the other way round")
    imp.add_argument("--png", help="also draw the imported track to this PNG")
    _car_arguments(imp)
    imp.set_defaults(func=run_import)


def _car_arguments(p) -> None:
    p.add_argument("--car-params", default="buzzracer", help="car file whose limits set the racing line (default buzzracer)")
    p.add_argument("--top-speed", type=float, default=RaceSetup.rd3g_top_speed_mps,
                   help=f"top speed of the racing line (m/s; default {RaceSetup.rd3g_top_speed_mps}, the RD3G car's)")


def _car(args):
    try:
        return load_car_params(args.car_params)
    except CarParamsError as exc:
        raise UserError(str(exc)) from None


def summary_lines(track, line) -> list[str]:
    """Length, width range, tightest turn radius and the racing line's lap time, one fact a line."""
    s = np.linspace(0.0, track.length, max(2000, int(track.length / 0.005)), endpoint=not track.closed)
    kappa = float(np.max(np.abs(track.curvature(s))))
    radius = f"{1.0 / kappa:.3f} m" if kappa > 0 else "none (straight)"
    out = [f"track {track.name}: {'closed' if track.closed else 'open'}, length {track.length:.3f} m",
           f"width {track.min_width:.3f} .. {track.max_width:.3f} m",
           f"tightest centre-line turn radius {radius}"]
    if line is None:
        out.append("racing line: none (open track)")
    else:
        lim = line.limits
        out.append(f"racing line: length {line.length_m:.3f} m, tightest radius {line.min_radius_m:.3f} m, "
                   f"speed {line.speed_mps.min():.2f} .. {line.speed_mps.max():.2f} m/s, "
                   f"lap time {line.lap_time_s:.3f} s (friction circle {lim.lateral_accel_mps2:.2f} m/s^2, "
                   f"drive {lim.accel_mps2:.2f} m/s^2 at rest, brake {lim.brake_mps2:.2f} m/s^2, "
                   f"top speed {lim.top_speed_mps:g} m/s)")
        # The same limits on the centre line, for comparison (the reference the planners follow today).
        centre_kappa = track.curvature(line.s)
        step = np.full(len(line.s), track.length / len(line.s))
        centre_lap = lap_time_s(step, speed_profile(step, centre_kappa, lim, closed=True))
        out.append(f"centre line at the same limits: lap time {centre_lap:.3f} s")
    return out


def _line_or_none(track, car, top_speed):
    if not track.closed:
        return None
    try:
        return planner_racing_line(track, car, top_speed)
    except RacingLineError as exc:
        raise UserError(str(exc)) from None


def draw(track, line, out: Path) -> Path:
    """PNG of the track: surface, edges, start line, centre line, racing line coloured by speed,
    the fixed markers (if the track has a surveyed set) and the arena."""
    import matplotlib  # the plotting backend only when a picture is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tracks.plotting import draw_racing_line, draw_track  # matplotlib-only module

    fig, ax = plt.subplots(figsize=(8, 6))
    draw_track(ax, track)
    if line is not None:
        draw_racing_line(ax, track, line)
    marker_path = FIXED_MARKERS.get(track.name)
    if marker_path:
        for marker in load_fixed_markers(marker_path).markers.values():
            half = 0.5 * marker.size
            ax.add_patch(plt.Rectangle((marker.x - half, marker.y - half), marker.size, marker.size, color="k", zorder=3))
            ax.annotate(str(marker.marker_id), (marker.x, marker.y + half), ha="center", va="bottom", fontsize=7)
    title = track.name + (f": racing line {line.lap_time_s:.2f} s" if line is not None else "")
    ax.set_title(title)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    fig.tight_layout()
    check_output_path(out)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def run_show(args) -> int:
    car = _car(args)
    try:
        track = load_track(args.track)
    except (UnknownTrackError, TrackFormatError) as exc:
        raise UserError(str(exc)) from None
    line = _line_or_none(track, car, args.top_speed)
    for text in summary_lines(track, line):
        print(text)
    safe = re.sub(r"[^A-Za-z0-9_-]+", "_", track.name)
    out = Path(args.out) if args.out else Path("runs") / f"track_{safe}.png"
    print(f"picture: {draw(track, line, out)}")
    return 0


def _arena(text: str) -> Arena:
    match = re.fullmatch(r"\s*([0-9.]+)\s*[xX]\s*([0-9.]+)\s*", text)
    if not match or float(match[1]) <= 0 or float(match[2]) <= 0:
        raise UserError(f"--arena: expected X x Y in metres, e.g. 5x3, got {text!r}")
    return Arena(0.0, float(match[1]), 0.0, float(match[2]))


def run_import(args) -> int:
    car = _car(args)
    check_output_path(args.out)
    try:
        data = import_track(args.csv, car=CarEnvelope.of(car), fmt=args.format, name=args.name, width_m=args.width,
                            fit_arena=args.fit_arena, arena=_arena(args.arena), wall_margin_m=args.wall_margin,
                            reverse=args.reverse)
    except TrackImportError as exc:
        raise UserError(str(exc)) from None
    track = track_from_dict(data, Path(args.out).name)
    atomic_write_text(args.out, json.dumps(data, indent=1) + "\n")
    print(f"track file: {args.out}")
    line = _line_or_none(track, car, args.top_speed)
    for text in summary_lines(track, line):
        print(text)
    if args.png:
        print(f"picture: {draw(track, line, Path(args.png))}")
    return 0
