"""Writing output files without ever destroying what is at the path (docs/file-formats.md, "Writing").

One policy for every output of every command (:func:`output_target` decides, before the work starts):

* a regular file or a missing path: written atomically (a temporary file in the target's directory,
  fsync, rename), so a reader sees the old file or the new one, never a part; missing parent
  directories are created;
* a symbolic link to a regular file: its target is written the same way and the link stays a link;
* a character device, a FIFO (named pipe), or an open descriptor such as ``/dev/stdout``,
  ``/dev/fd/N``, ``/proc/self/fd/N`` (or a link to one of these): written straight through, opened
  for appending and never created, truncated or renamed over, when the output allows it
  (``stream=True``); refused otherwise;
* refused always: a directory, a block device, a socket, a symbolic link to a directory, to nothing or
  in a loop, a read-only regular file, a parent that is a file.

Every failure raises :class:`OutputFileError` with a one-line message naming the path and leaves no
partial or temporary file."""
from __future__ import annotations

import contextlib
import os
import re
import stat
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from .read import file_kind


class OutputFileError(OSError):
    """An output file could not be written; str() is one line naming the path."""

    def __str__(self) -> str:
        return self.args[0]


def _message(path: Path, exc: OSError) -> str:
    return f"cannot write {path}: {exc.strerror or exc}"


@dataclass(frozen=True)
class OutputTarget:
    """Where and how an output is written: ``path`` as given; ``file`` the regular file that is replaced
    atomically (``path`` itself, or the target of a link), None for a stream written straight through."""

    path: Path
    file: Path | None

    @property
    def stream(self) -> bool:
        return self.file is None


# Directories whose entries are a process's open descriptors: /dev/stdout -> /proc/self/fd/1 -> pipe:[...]
_DESCRIPTOR_DIR = re.compile(r"/proc/(self|thread-self|[0-9]+)(/task/[0-9]+)?/fd|/dev/fd")
_MAX_LINKS = 40  # as the kernel's ELOOP limit


def _names_descriptor(path: Path) -> bool:
    """True when ``path`` or a link on its way is an entry of an open-descriptor directory (/dev/stdout,
    /dev/fd/1): what it points to is the command's own descriptor (a terminal, a pipe, the file the
    shell redirected to), to be written through, never renamed over even when it is a regular file."""
    p = os.path.abspath(path)
    for _ in range(_MAX_LINKS):
        if _DESCRIPTOR_DIR.fullmatch(os.path.realpath(os.path.dirname(p))):
            return True
        if not os.path.islink(p):
            return False
        p = os.path.abspath(os.path.join(os.path.dirname(p), os.readlink(p)))
    return False


def _check_parent(path: Path, file: Path, create_parent: bool) -> None:
    """``file``'s directory exists (created if allowed) and is writable; messages name ``path``."""
    parent = file.parent if str(file.parent) else Path(".")
    blocker = next((p for p in (parent, *parent.parents) if p.exists() or p.is_symlink()), None)
    if blocker is not None and not blocker.is_dir():
        what = "a file" if blocker.exists() else "a symbolic link to nothing"
        raise OutputFileError(f"cannot write {path}: {blocker} is {what}, not a directory")
    if not parent.is_dir():
        if not create_parent:
            raise OutputFileError(f"cannot write {path}: directory {parent} does not exist")
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputFileError(f"cannot write {path}: cannot create directory {parent}: "
                                  f"{exc.strerror or exc}") from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputFileError(f"cannot write {path}: directory {parent} is not writable")


def output_target(path: str | os.PathLike, create_parent: bool = True, *, stream: bool = False) -> OutputTarget:
    """How ``path`` is written, by the policy in the module doc; :class:`OutputFileError` if it must not be.
    ``stream``: this output may go to a character device, FIFO or open descriptor (a JSON summary to
    /dev/stdout); without it those are refused (a recording, a car file: files other commands read back).
    ``create_parent``: missing parent directories are created (the documented default) or refused."""
    path = Path(path)
    refuse = "written only as a regular file"
    if _names_descriptor(path):
        try:
            mode = os.stat(path).st_mode
        except OSError as exc:
            raise OutputFileError(_message(path, exc)) from None
        if not stream:
            raise OutputFileError(f"cannot write {path}: it is an open file descriptor; this output is {refuse}")
        if stat.S_ISDIR(mode) or stat.S_ISBLK(mode) or stat.S_ISSOCK(mode):
            raise OutputFileError(f"cannot write {path}: it is {file_kind(mode)}")
        return OutputTarget(path, None)
    try:
        link = stat.S_ISLNK(os.lstat(path).st_mode)
    except (FileNotFoundError, NotADirectoryError):  # nothing there, or a file where a directory should be
        _check_parent(path, path, create_parent)
        return OutputTarget(path, path)
    except OSError as exc:
        raise OutputFileError(_message(path, exc)) from None
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:  # a link to nothing, or links in a loop
        why = (f"a symbolic link to {os.readlink(path)}, which does not exist" if link and isinstance(exc, FileNotFoundError)
               else exc.strerror or str(exc))
        raise OutputFileError(f"cannot write {path}: {why}") from None
    what = f"a symbolic link to {file_kind(mode)}" if link else file_kind(mode)
    if stat.S_ISREG(mode):
        file = Path(os.path.realpath(path)) if link else path
        if not os.access(file, os.W_OK):
            raise OutputFileError(f"cannot write {path}: {'its target ' + str(file) if link else 'the file'} "
                                  f"is read-only")
        _check_parent(path, file, create_parent=False)
        return OutputTarget(path, file)
    if stat.S_ISCHR(mode) or stat.S_ISFIFO(mode):
        if not stream:
            raise OutputFileError(f"cannot write {path}: it is {what}; this output is {refuse}")
        return OutputTarget(path, None)
    raise OutputFileError(f"cannot write {path}: it is {what}")


def check_output_path(path: str | os.PathLike, create_parent: bool = True, *, stream: bool = False) -> Path:
    """Fail early, before long work, if ``path`` must not be written (:func:`output_target`); pass the
    same ``stream`` as the write that follows."""
    output_target(path, create_parent, stream=stream)
    return Path(path)


def check_output_dir(path: str | os.PathLike) -> Path:
    """A folder the outputs are written into (``--plots``, ``--figures``): an existing directory or a link
    to one, else created (with its parents); anything else at ``path`` is :class:`OutputFileError`. Each
    file in it is then written by the policy above."""
    path = Path(path)
    if path.is_dir():
        return path
    if path.is_symlink() or path.exists():
        try:
            what = file_kind(os.stat(path).st_mode)
        except OSError:
            what = f"a symbolic link to {os.readlink(path)}, which does not exist"
        raise OutputFileError(f"cannot write into {path}: it is {what}, not a directory")
    _check_parent(path, path / "_", create_parent=True)
    return path


def _write_through(target: OutputTarget, data: bytes) -> None:
    """Appends ``data`` to a device, FIFO or open descriptor: never created, truncated or replaced. A FIFO
    waits for its reader, as a shell's ``>`` does."""
    sys.stdout.flush()  # what the command printed comes first when the target is its own stdout
    sys.stderr.flush()
    flags = os.O_WRONLY | os.O_APPEND | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(target.path, flags)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
        finally:
            os.close(fd)
    except OSError as exc:
        raise OutputFileError(_message(target.path, exc)) from None


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, create_parent: bool = True, *, stream: bool = False) -> Iterator[Path]:
    """Yields a temporary path; on normal exit its contents become ``path`` (renamed over a regular file,
    written through to a stream), on any error it is removed. For writers that want a file name
    (matplotlib's savefig)."""
    target = output_target(path, create_parent, stream=stream)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.path.name}.", suffix=".tmp" + target.path.suffix,
                                   dir=None if target.stream else target.file.parent)
        os.close(fd)
    except OSError as exc:
        raise OutputFileError(_message(target.path, exc)) from None
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if target.stream:
            _write_through(target, tmp_path.read_bytes())
            return
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give what open() would
        os.replace(tmp_path, target.file)
    except OutputFileError:
        raise
    except OSError as exc:
        raise OutputFileError(_message(target.path, exc)) from None
    finally:
        tmp_path.unlink(missing_ok=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()  # read once at import: os.umask can only be read by setting it, which races with threads


def atomic_write_bytes(path: str | os.PathLike, data: bytes, create_parent: bool = True, *,
                       stream: bool = False) -> Path:
    with atomic_path(path, create_parent, stream=stream) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, create_parent: bool = True, *,
                      stream: bool = False) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"), create_parent, stream=stream)


def atomic_write_with(path: str | os.PathLike, write: Callable[[Path], object], create_parent: bool = True, *,
                      stream: bool = False) -> Path:
    """``write(tmp_path)`` fills a temporary file that then replaces ``path`` (or is written through)."""
    with atomic_path(path, create_parent, stream=stream) as tmp:
        write(tmp)
    return Path(path)
