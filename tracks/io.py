"""Loading track files: ``load_track("oval")`` or ``load_track("path/to/file.json")``."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping

from .definition import TrackFormatError, parse_definition
from .track import Track

DATA_DIR = Path(__file__).resolve().parent / "data"


class UnknownTrackError(ValueError):
    """A bare track name that is not one of the shipped tracks."""


def available_tracks() -> list[str]:
    """Names of the shipped tracks (files ``tracks/data/<name>.json``), sorted."""
    return sorted(p.stem for p in DATA_DIR.glob("*.json"))


def track_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> Track:
    """Build a :class:`Track` from an already decoded track-file object (same rules as the file)."""
    return Track(parse_definition(data, source), source)


def load_track(name_or_path: str | os.PathLike) -> Track:
    """Load and validate a track.

    A bare name without a directory or ``.json`` suffix (e.g. ``"oval"``) loads the shipped
    ``tracks/data/<name>.json``; anything else is a file path. Raises :class:`UnknownTrackError`
    for an unknown bare name, FileNotFoundError for a missing path and :class:`TrackFormatError`
    (a ValueError naming the field at fault) for invalid contents.
    """
    text = os.fspath(name_or_path)
    is_bare_name = not isinstance(name_or_path, Path) and os.sep not in text and "/" not in text and not text.endswith(".json")
    if is_bare_name:
        path = DATA_DIR / f"{text}.json"
        if not path.is_file():
            raise UnknownTrackError(f"unknown track {text!r}; shipped tracks: {', '.join(available_tracks())}")
    else:
        path = Path(text)
    source = path.name
    with open(path, encoding="utf-8") as f:
        try:
            data = json.load(f)
        except json.JSONDecodeError as exc:
            raise TrackFormatError("<json>", f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}", source) from exc
    return track_from_dict(data, source)
