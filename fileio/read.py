"""Reading input files strictly: only regular files, bounded size, line length and nesting depth,
UTF-8 with the byte offset of the first bad byte, duplicate JSON keys rejected. Every error names
the file and raises the caller's error class (a subclass of :class:`InputFileError`)."""
from __future__ import annotations

import json
import os
import re
import stat
import tomllib
from pathlib import Path
from typing import Any

# Defaults, documented in docs/file-formats.md; a format may pass its own.
MAX_DEPTH = 32                  # nested arrays/objects; the deepest valid file in the repository has 5
MAX_BYTES = 64 * 2**20          # whole file
MAX_LINE = 64 * 2**20           # one line (JSON written by json.dump is a single line)


class InputFileError(ValueError):
    """An input file that cannot be used; the message names the file and the place at fault."""


def file_kind(mode: int) -> str:
    """What an ``st_mode`` is, for messages: "a directory", "a FIFO (named pipe)", ..."""
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISREG, "a regular file")):
        if test(mode):
            return name
    return "not a regular file"


def read_bytes(path: str | os.PathLike, what: str = "file", *, max_bytes: int = MAX_BYTES,
               error: type[InputFileError] = InputFileError) -> bytes:
    """The contents of a regular file. A FIFO, device or directory is an error, never a blocking read
    (the file is opened non-blocking and checked with fstat before anything is read)."""
    path = Path(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{path}: {what} is {file_kind(st.st_mode)}, not a regular file")
        if st.st_size > max_bytes:
            raise error(f"{path}: {what} is {st.st_size} bytes, more than the limit of {max_bytes}")
        chunks, total = [], 0
        while True:
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                break
            total += len(chunk)
            if total > max_bytes:  # grew while being read
                raise error(f"{path}: {what} is more than the limit of {max_bytes} bytes")
            chunks.append(chunk)
        return b"".join(chunks)
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def line_col(text: str, index: int) -> tuple[int, int]:
    """1-based (line, column) of a character index."""
    line = text.count("\n", 0, index) + 1
    return line, index - (text.rfind("\n", 0, index) + 1) + 1


def decode_utf8(data: bytes, source: str, error: type[InputFileError] = InputFileError) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        head = data[:exc.start].decode("utf-8")
        line, col = line_col(head, len(head))
        raise error(f"{source}: not UTF-8 text: byte {exc.start} (line {line}, column {col}) is "
                    f"0x{data[exc.start]:02x}") from None


def check_line_length(text: str, source: str, max_line: int, error: type[InputFileError] = InputFileError) -> None:
    start = 0
    n = 1
    while True:
        end = text.find("\n", start)
        stop = len(text) if end < 0 else end
        if stop - start > max_line:
            raise error(f"{source}: line {n} is {stop - start} characters long, more than the limit of {max_line}")
        if end < 0:
            return
        start, n = end + 1, n + 1


# Tokens that can hold brackets without nesting: strings (and TOML comments). Everything else that
# matters for depth is a bracket.
_JSON_TOKENS = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]', re.S)
_TOML_TOKENS = re.compile(r'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'|#[^\n]*|[\[\]{}]')


def check_depth(text: str, source: str, syntax: str, max_depth: int = MAX_DEPTH,
                error: type[InputFileError] = InputFileError) -> None:
    """Reject nesting deeper than max_depth before a recursive parser sees it (a RecursionError or a
    stack overflow otherwise)."""
    depth = 0
    for m in (_JSON_TOKENS if syntax == "json" else _TOML_TOKENS).finditer(text):
        c = m.group()
        if c in "[{":
            depth += 1
            if depth > max_depth:
                line, col = line_col(text, m.start())
                raise error(f"{source}: line {line}, column {col}: nested more than {max_depth} levels deep")
        elif c in "]}":
            depth -= 1


def _no_duplicate_keys(source: str, error: type[InputFileError]):
    def hook(pairs: list[tuple[str, Any]]) -> dict:
        out: dict = {}
        for key, value in pairs:
            if key in out:
                raise error(f"{source}: key {key!r} appears twice in one object")
            out[key] = value
        return out
    return hook


def read_text(path: str | os.PathLike, what: str = "file", *, max_bytes: int = MAX_BYTES,
              max_line: int = MAX_LINE, error: type[InputFileError] = InputFileError) -> str:
    """A regular UTF-8 text file within the size and line-length limits."""
    text = decode_utf8(read_bytes(path, what, max_bytes=max_bytes, error=error), str(path), error)
    check_line_length(text, str(path), max_line, error)
    return text


def parse_json(text: str, source: str, *, max_depth: int = MAX_DEPTH,
               error: type[InputFileError] = InputFileError) -> Any:
    """json.loads with a depth limit and duplicate keys rejected. NaN/Infinity are read as floats (the
    schema decides where they are allowed)."""
    check_depth(text, source, "json", max_depth, error)
    try:
        return json.loads(text, object_pairs_hook=_no_duplicate_keys(source, error))
    except json.JSONDecodeError as exc:
        raise error(f"{source}: not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno} "
                    f"(byte {len(text[:exc.pos].encode())})") from None
    except RecursionError:  # check_depth makes this unreachable; kept so no input can give a traceback
        raise error(f"{source}: nested too deeply") from None


def parse_toml(text: str, source: str, *, max_depth: int = MAX_DEPTH,
               error: type[InputFileError] = InputFileError) -> dict:
    check_depth(text, source, "toml", max_depth, error)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{source}: nested too deeply") from None


def load_json(path: str | os.PathLike, what: str = "file", *, max_bytes: int = MAX_BYTES, max_line: int = MAX_LINE,
              max_depth: int = MAX_DEPTH, error: type[InputFileError] = InputFileError) -> Any:
    text = read_text(path, what, max_bytes=max_bytes, max_line=max_line, error=error)
    return parse_json(text, str(path), max_depth=max_depth, error=error)


def load_toml(path: str | os.PathLike, what: str = "file", *, max_bytes: int = MAX_BYTES, max_line: int = MAX_LINE,
              max_depth: int = MAX_DEPTH, error: type[InputFileError] = InputFileError) -> dict:
    text = read_text(path, what, max_bytes=max_bytes, max_line=max_line, error=error)
    return parse_toml(text, str(path), max_depth=max_depth, error=error)
