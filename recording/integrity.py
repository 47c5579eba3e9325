"""Is a Rerun recording file whole? Read its chunks with Rerun's own decoder and say what is wrong.

A recording that ``RecordingStream.save`` finished ends with an RRD footer (the manifest of its
stores). Damage shows as one of:

* ``truncated``: no footer (a copy cut short, or a writer killed before it finished the file), or a
  message that runs past the end of the file;
* ``corrupt``: not an RRD file (wrong header bytes) or a message Rerun cannot decode (flipped bytes
  in a compressed or framed part).

What can be recovered is counted from the chunks Rerun decodes before the damage; a file cut short
is first passed through ``rerun rrd filter`` (the SDK's command-line tool), which copies every whole
message of it to a new, finished file. RRD files carry no checksums: a flipped bit inside a value
that still decodes is not detected (4 of 25 random single-bit flips in a 1.4 MB race recording
decoded without error, both here and with ``rerun rrd verify``).
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

TIMELINE = "sim_time"  # the race's time axis (s), used to say which part of a race was recovered


@dataclass(frozen=True)
class Readable:
    """What Rerun could decode of a (damaged) recording."""

    chunks: int
    entities: int
    t_first_s: float | None  # range of TIMELINE over the decoded chunks, None if none has it
    t_last_s: float | None

    def describe(self) -> str:
        if not self.chunks:
            return "nothing readable (no data chunk before the damage)"
        span = ("" if self.t_first_s is None
                else f", {TIMELINE} {self.t_first_s:.2f}-{self.t_last_s:.2f} s")
        return f"{self.chunks} data chunks of {self.entities} entities{span}"


class RecordingDamage(ValueError):
    """A damaged recording: ``kind`` ('truncated' or 'corrupt'), Rerun's diagnosis, what is readable."""

    def __init__(self, path: Path, kind: str, detail: str, readable: Readable | None):
        self.path, self.kind, self.detail, self.readable = Path(path), kind, detail, readable
        recovered = "could not be determined (rerun executable not found)" if readable is None else readable.describe()
        super().__init__(f"{self.path}: {kind} recording ({detail}); readable before the damage: {recovered}; "
                         f"no summary is given for a damaged file (`rerun rrd filter {self.path} > COPY.rrd` "
                         f"copies the readable part to a new file)")


def rerun_executable() -> str | None:
    """The ``rerun`` command-line tool of the installed rerun-sdk: its binary (package ``rerun_cli``;
    the ``rerun`` script beside Python runs it as a child process, which a signal to the script would
    leave running), else the script beside this Python or on PATH."""
    try:
        import rerun_cli
    except ImportError:
        rerun_cli = None
    if rerun_cli is not None and Path(rerun_cli.__file__).with_name("rerun").exists():
        return str(Path(rerun_cli.__file__).with_name("rerun"))
    beside = Path(sys.executable).with_name("rerun")
    if beside.exists():
        return str(beside)
    return shutil.which("rerun")


def _kind(message: str) -> str:
    text = message.lower()
    return "truncated" if ("exceeds file size" in text or "unexpected end" in text or "eof" in text) else "corrupt"


def _decode(path: Path):
    """(store, chunks decoded, footer present, error message or None) of the first recording store."""
    import rerun as rr

    chunks: list = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            reader = rr.chunk.RrdReader(path)
            stores = reader.recordings()
        except Exception as exc:  # Rerun's reader raises plain exceptions for undecodable files
            return None, chunks, False, str(exc)
    footer = not any("footer" in str(w.message).lower() for w in caught)
    if not stores:
        return None, chunks, footer, None
    try:
        for chunk in reader.stream(store=stores[0]):
            chunks.append(chunk)
    except Exception as exc:
        return stores[0], chunks, footer, str(exc)
    return stores[0], chunks, footer, None


def readable_part(chunks) -> Readable:
    entities, t_min, t_max = set(), None, None
    for chunk in chunks:
        if chunk.is_static:
            continue
        entities.add(chunk.entity_path)
        batch = chunk.to_record_batch()
        if TIMELINE in batch.schema.names and batch.num_rows:
            t = np.asarray(batch.column(TIMELINE).cast("int64").to_numpy(zero_copy_only=False), float) * 1e-9
            t_min = float(t.min()) if t_min is None else min(t_min, float(t.min()))
            t_max = float(t.max()) if t_max is None else max(t_max, float(t.max()))
    return Readable(sum(not c.is_static for c in chunks), len(entities), t_min, t_max)


def _readable_prefix(path: Path) -> Readable | None:
    """Chunks before the damage of a file Rerun cannot enumerate, via ``rerun rrd filter``."""
    exe = rerun_executable()
    if exe is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "readable.rrd"
        with copy.open("wb") as out:
            subprocess.run([exe, "rrd", "filter", str(path)], stdout=out, stderr=subprocess.DEVNULL, timeout=120)
        _, chunks, _, _ = _decode(copy)
        return readable_part(chunks)


def read_verified(path) -> tuple:
    """(store entry, chunks) of the first recording in ``path``; ``RecordingDamage`` if the file is
    truncated or corrupt, ``FileNotFoundError``/``ValueError`` if it is missing or holds no recording."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: recording not found")
    if not path.is_file():  # a FIFO is never opened (Rerun's reader would block on it)
        raise ValueError(f"{path}: recording is not a regular file")
    store, chunks, footer, error = _decode(path)
    if error is not None:
        kind = _kind(error)
        readable = readable_part(chunks) if store is not None else _readable_prefix(path)
        raise RecordingDamage(path, kind, f"Rerun: {error}", readable)
    if not footer:
        raise RecordingDamage(path, "truncated", "no RRD footer: the file was cut short or its writer never "
                              "finished it", readable_part(chunks))
    if store is None:
        raise ValueError(f"{path}: the file holds no rerun recording")
    return store, chunks
