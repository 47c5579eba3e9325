"""fileio: strict reading (file kinds from the OS, byte offsets and nesting counted by hand) and atomic
writing (failures injected with real directories and a monkeypatched disk-full write)."""
from __future__ import annotations

import dataclasses
import errno
import os

import pytest

import fileio
from fileio import (Array, FieldSpec, InputFileError, Number, OutputFileError, String, Table, atomic_write_text,
                    check_output_path, load_json, load_toml, read_bytes, read_text, validate)


def test_only_regular_files_are_read(tmp_path):
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)  # nobody writes to it: a blocking open would hang forever
    with pytest.raises(InputFileError, match=r"pipe.json: problem file is a FIFO \(named pipe\), not a regular file"):
        read_bytes(fifo, "problem file")
    with pytest.raises(InputFileError, match="is a directory, not a regular file"):
        read_bytes(tmp_path)
    with pytest.raises(InputFileError, match="is a character device"):
        read_bytes("/dev/zero")
    with pytest.raises(InputFileError, match="missing.json: file not found"):
        read_bytes(tmp_path / "missing.json")


def test_size_line_and_encoding_limits_name_the_place(tmp_path):
    big = tmp_path / "big.json"
    big.write_bytes(b" " * 101)
    with pytest.raises(InputFileError, match="big.json: file is 101 bytes, more than the limit of 100"):
        read_bytes(big, max_bytes=100)
    lines = tmp_path / "lines.csv"
    lines.write_text("a,b\n" + "1," * 30 + "\nc\n")
    with pytest.raises(InputFileError, match="lines.csv: line 2 is 60 characters long, more than the limit of 50"):
        read_text(lines, max_line=50)
    bad = tmp_path / "bad.json"
    bad.write_bytes('{"é": 1,\n "x": "'.encode() + b"\xff" + b'"}')  # 10 bytes on line 1 ("é" is two), 7 before 0xff on line 2
    with pytest.raises(InputFileError, match=r"bad.json: not UTF-8 text: byte 17 \(line 2, column 8\) is 0xff"):
        read_text(bad)


@pytest.mark.parametrize("depth, ok", [(32, True), (33, False), (100_000, False)])
def test_nesting_depth_is_bounded_before_parsing(tmp_path, depth, ok):
    j = tmp_path / "deep.json"
    j.write_text("[" * depth + "]" * depth)
    t = tmp_path / "deep.toml"
    t.write_text("a = " + "[" * depth + "]" * depth + "\n")
    if ok:
        assert load_json(j) == eval("[" * depth + "]" * depth)
        load_toml(t)
    else:
        with pytest.raises(InputFileError, match="column 33: nested more than 32 levels deep"):
            load_json(j)
        with pytest.raises(InputFileError, match="nested more than 32 levels deep"):
            load_toml(t)


def test_brackets_inside_strings_and_comments_do_not_count(tmp_path):
    j = tmp_path / "s.json"
    j.write_text('{"a": "' + "[" * 100 + '\\"[["}')
    assert load_json(j) == {"a": "[" * 100 + '"[['}
    t = tmp_path / "s.toml"
    t.write_text("# " + "[" * 100 + "\na = '" + "{" * 50 + "'\nb = \"\"\"\n" + "[" * 40 + "\"\"\"\n")
    assert load_toml(t)["a"] == "{" * 50


def test_duplicate_json_keys_and_invalid_json_name_the_place(tmp_path):
    d = tmp_path / "dup.json"
    d.write_text('{"dt": 0.1, "dt": 0.2}')
    with pytest.raises(InputFileError, match="dup.json: key 'dt' appears twice"):
        load_json(d)
    e = tmp_path / "e.json"
    e.write_text('{"a": 1,\n "b": tru}')
    with pytest.raises(InputFileError, match=r"e.json: not valid JSON: Expecting value at line 2, column 7 \(byte 15\)"):
        load_json(e)


def test_schema_types_ranges_paths_and_suggestions():
    spec = Table({"dt": FieldSpec(Number(gt=0)), "n": FieldSpec(Number(integer=True, ge=1, le=10), required=False),
                  "x0": FieldSpec(Array(1, length=2)), "m": FieldSpec(Array(2), required=False),
                  "form": FieldSpec(String(choices=("distance", "squared")), required=False)})
    ok = {"dt": 1, "n": 3, "x0": [0, 1.5], "m": [[1, 2], [3, 4]], "form": "squared"}
    assert validate(ok, spec, "f") == {"dt": 1.0, "n": 3, "x0": [0.0, 1.5], "m": [[1.0, 2.0], [3.0, 4.0]], "form": "squared"}
    cases = [
        ({"dt": True, "x0": [0, 0]}, "f: dt: expected a finite number > 0, got true"),
        ({"dt": "2", "x0": [0, 0]}, "f: dt: expected a finite number > 0, got \"2\""),
        ({"dt": 10**400, "x0": [0, 0]}, "f: dt: expected a finite number > 0, got an integer too large for a float"),
        ({"dt": 1, "n": 1.0, "x0": [0, 0]}, "f: n: expected an integer >= 1 and <= 10, got 1.0"),
        ({"dt": 1, "x0": [0, float("nan")]}, "f: x0[1]: expected a finite number, got NaN"),
        ({"dt": 1, "x0": [0]}, "f: x0: expected 2 values, got 1"),
        ({"dt": 1, "x0": [0, 0], "m": [[1, 2], [3]]}, "f: m[1]: rows must all have 2 values"),
        ({"dt": 1, "x0": [0, 0], "dtt": 1}, "f: dtt: unknown key 'dtt'; did you mean 'dt'?"),
        ({"dt": 1, "x0": [0, 0], "form": "sqared"}, "f: form: expected one of 'distance', 'squared', got \"sqared\"; did you mean 'squared'?"),
        ({"x0": [0, 0]}, "f: dt: missing (expected a finite number > 0)"),
        ([], "f: <top level>: expected an object"),
    ]
    for doc, message in cases:
        with pytest.raises(InputFileError) as info:
            validate(doc, spec, "f")
        assert str(info.value).startswith(message), (str(info.value), message)


# --------------------------------------------------------------------------- writing
def test_atomic_write_replaces_whole_and_keeps_permissions(tmp_path):
    path = tmp_path / "sub" / "out.json"  # a missing directory is created
    atomic_write_text(path, "first")
    atomic_write_text(path, "second")
    assert path.read_text() == "second"
    assert os.listdir(path.parent) == ["out.json"]
    assert path.stat().st_mode & 0o777 == 0o666 & ~fileio.write._UMASK


def test_output_errors_are_one_line_and_leave_nothing(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("x")
    for target, why in ((tmp_path, "it is a directory"), (tmp_path / "file" / "out.json", "is a file, not a directory"),
                        (tmp_path / "file" / "a" / "out.json", "is a file, not a directory")):
        with pytest.raises(OutputFileError) as info:
            atomic_write_text(target, "x")
        assert why in str(info.value) and "\n" not in str(info.value) and str(target) in str(info.value)
    path = tmp_path / "full.json"
    path.write_text("old contents")

    real_open = open

    class DiskFull:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    monkeypatch.setattr(fileio.write, "open", lambda p, mode="r": DiskFull(real_open(p, mode)), raising=False)
    with pytest.raises(OutputFileError, match=f"cannot write {path}: No space left on device"):
        atomic_write_text(path, "new contents")
    assert path.read_text() == "old contents"  # the old file is untouched
    assert sorted(os.listdir(tmp_path)) == ["file", "full.json"]  # no temporary file left


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_read_only_directory(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    with pytest.raises(OutputFileError, match="is not writable"):
        check_output_path(ro / "x.json")


@dataclasses.dataclass
class _Inner:
    gain: float = 1.0


@dataclasses.dataclass
class _Outer:
    size: int
    weights: list[float]
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    label: str | None = None
    enabled: bool = True


def test_schema_follows_the_dataclass():
    """A field added to a dataclass is in the file format at once: required without a default,
    optional (null allowed) for `X | None`, typed by its annotation."""
    from fileio import table_from_dataclass

    spec = table_from_dataclass(_Outer)
    assert list(spec.fields) == ["size", "weights", "inner", "label", "enabled"]
    assert [f.required for f in spec.fields.values()] == [True, True, False, False, False]
    assert validate({"size": 3, "weights": [1, 2.5], "inner": {"gain": 2}, "label": None}, spec, "f") == \
        {"size": 3, "weights": [1.0, 2.5], "inner": {"gain": 2.0}}
    for doc, message in (({"size": 3}, "f: weights: missing"), ({"size": 3, "weights": [], "enabled": 1}, "f: enabled: expected true or false"),
                         ({"size": 3, "weights": [], "inner": {"gian": 1}}, "f: inner.gian: unknown key 'gian'; did you mean 'gain'?"),
                         ({"size": 2**31, "weights": []}, "f: size: expected an integer >= -2147483647 and <= 2147483647")):
        with pytest.raises(InputFileError) as info:
            validate(doc, spec, "f")
        assert str(info.value).startswith(message), str(info.value)
