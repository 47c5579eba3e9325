"""Writing output files atomically: a temporary file in the target's directory, fsync, rename. A
failure (missing directory, a directory in the way, read-only, disk full) raises
:class:`OutputFileError` with a one-line message naming the path, and leaves no partial file."""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Callable, Iterator


class OutputFileError(OSError):
    """An output file could not be written; str() is one line naming the path."""

    def __str__(self) -> str:
        return self.args[0]


def _message(path: Path, exc: OSError) -> str:
    return f"cannot write {path}: {exc.strerror or exc}"


def check_output_path(path: str | os.PathLike, create_parent: bool = True) -> Path:
    """Fail early, before long work, if ``path`` cannot become a file: a directory in its place, a
    parent that is a file or cannot be created, or a read-only directory."""
    path = Path(path)
    if path.is_dir():
        raise OutputFileError(f"cannot write {path}: it is a directory")
    parent = path.parent if str(path.parent) else Path(".")
    blocker = next((p for p in (parent, *parent.parents) if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise OutputFileError(f"cannot write {path}: {blocker} is a file, not a directory")
    try:
        if create_parent:
            parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputFileError(f"cannot write {path}: cannot create directory {parent}: {exc.strerror or exc}") from None
    if not parent.is_dir():
        raise OutputFileError(f"cannot write {path}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputFileError(f"cannot write {path}: directory {parent} is not writable")
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, create_parent: bool = True) -> Iterator[Path]:
    """Yields a temporary path beside ``path``; on normal exit it replaces ``path``, on any error it is
    removed. For writers that want a file name (matplotlib's savefig, rerun)."""
    path = check_output_path(path, create_parent)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise OutputFileError(_message(path, exc)) from None
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give what open() would
        os.replace(tmp_path, path)
    except OSError as exc:
        tmp_path.unlink(missing_ok=True)
        raise OutputFileError(_message(path, exc)) from None
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()  # read once at import: os.umask can only be read by setting it, which races with threads


def atomic_write_bytes(path: str | os.PathLike, data: bytes, create_parent: bool = True) -> Path:
    with atomic_path(path, create_parent) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, create_parent: bool = True) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"), create_parent)


def atomic_write_with(path: str | os.PathLike, write: Callable[[Path], object], create_parent: bool = True) -> Path:
    """``write(tmp_path)`` fills a temporary file that then replaces ``path``."""
    with atomic_path(path, create_parent) as tmp:
        write(tmp)
    return Path(path)
