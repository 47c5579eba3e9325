"""Track geometry: track files, arc-length centre line, Frenet coordinates, drivable area, laps.

    from tracks import load_track
    track = load_track("oval")            # shipped tracks: available_tracks()
    s, ey, epsi = track.to_frenet(x, y, heading)

Format and conventions: docs/tracks.md. Units: m, rad, s.
"""
from .definition import Arena, ArcSegment, Lane, StraightSegment, TrackDefinition, TrackFormatError
from .geometry import wrap_angle
from .io import UnknownTrackError, available_tracks, load_track, track_from_dict
from .track import Track


def draw_track(ax, track, **kwargs):
    """Draw a track on a matplotlib Axes (see tracks.plotting.draw_track; imports matplotlib on first use)."""
    from .plotting import draw_track as _draw_track  # matplotlib only when something is drawn

    return _draw_track(ax, track, **kwargs)


__all__ = [
    "Arena",
    "ArcSegment",
    "Lane",
    "StraightSegment",
    "Track",
    "TrackDefinition",
    "TrackFormatError",
    "UnknownTrackError",
    "available_tracks",
    "draw_track",
    "load_track",
    "track_from_dict",
    "wrap_angle",
]
