"""Loading track files: ``load_track("oval")`` or ``load_track("path/to/file.json")``."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import fileio

from .definition import TrackFormatError, parse_definition
from .track import Track

DATA_DIR = Path(__file__).resolve().parent / "data"
MAX_FILE_BYTES = 16 * 2**20


class UnknownTrackError(ValueError):
    """A bare track name that is not one of the shipped tracks."""


def available_tracks() -> list[str]:
    """Names of the shipped tracks, sorted: ``<name>`` for ``tracks/data/<name>.json`` and
    ``<family>:<name>`` for ``tracks/data/<family>/<name>.json`` (e.g. ``buzzracer:full``)."""
    names = [p.stem for p in DATA_DIR.glob("*.json")]
    names += [f"{p.parent.name}:{p.stem}" for p in DATA_DIR.glob("*/*.json")]
    return sorted(names)


def shipped_track_path(name: str) -> Path:
    """The file of a shipped track name (``oval``, ``buzzracer:full``); UnknownTrackError if there is none."""
    family, _, stem = name.rpartition(":")
    path = DATA_DIR / family / f"{stem}.json" if family else DATA_DIR / f"{stem}.json"
    if not (stem and path.is_file()):
        raise UnknownTrackError(f"unknown track {name!r}; shipped tracks: {', '.join(available_tracks())}")
    return path


def track_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> Track:
    """Build a :class:`Track` from an already decoded track-file object (same rules as the file)."""
    return Track(parse_definition(data, source), source)


def load_track(name_or_path: str | os.PathLike) -> Track:
    """Load and validate a track.

    A bare name without a directory or ``.json`` suffix loads the shipped file: ``"oval"`` is
    ``tracks/data/oval.json``, ``"buzzracer:full"`` is ``tracks/data/buzzracer/full.json``; anything
    else is a file path. Raises :class:`UnknownTrackError`
    for an unknown bare name and :class:`TrackFormatError` (a ValueError naming the field at fault)
    for anything else: field ``<file>`` for a path that is missing, unreadable, not a regular file,
    too large or not UTF-8, ``<json>`` for invalid or too deeply nested JSON.
    """
    text = os.fspath(name_or_path)
    is_bare_name = not isinstance(name_or_path, Path) and os.sep not in text and "/" not in text and not text.endswith(".json")
    if is_bare_name:
        path = shipped_track_path(text)
    else:
        path = Path(text)
    source = path.name
    try:
        text = fileio.read_text(path, "track file", max_bytes=MAX_FILE_BYTES)
    except fileio.InputFileError as exc:
        raise TrackFormatError("<file>", str(exc).removeprefix(f"{path}: "), source) from None
    try:
        data = fileio.parse_json(text, str(path))
    except fileio.InputFileError as exc:
        raise TrackFormatError("<json>", str(exc).removeprefix(f"{path}: "), source) from None
    return track_from_dict(data, source)
