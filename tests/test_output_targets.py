"""Outputs never destroy what is at the path (fileio/write.py, docs/file-formats.md "Writing"): a regular
file is replaced atomically, a device, FIFO or open descriptor is written straight through or refused,
and a directory, socket or bad link is refused; the thing at the path is the same kind of thing after."""
from __future__ import annotations

import json
import os
import socket
import stat
import threading

import pytest

import fileio
from app.cli import main
from fileio import OutputFileError, atomic_write_text, atomic_write_with, check_output_dir, check_output_path


class FifoReader:
    """Reads a FIFO to its end in a thread (the writer's open waits for a reader)."""

    def __init__(self, path):
        self.data = b""
        self._thread = threading.Thread(target=self._read, args=(path,), daemon=True)
        self._thread.start()

    def _read(self, path):
        with open(path, "rb") as f:
            self.data = f.read()

    def result(self) -> bytes:
        self._thread.join(timeout=30)
        assert not self._thread.is_alive(), "the writer never closed the FIFO"
        return self.data


def _mode(path) -> int:
    return os.lstat(path).st_mode


def test_regular_file_is_replaced_and_a_link_to_one_writes_its_target(tmp_path):
    target = tmp_path / "real.json"
    target.write_text("old")
    inode = target.stat().st_ino
    atomic_write_text(target, "new")
    assert target.read_text() == "new" and target.stat().st_ino != inode  # renamed over, not rewritten in place
    link = tmp_path / "link.json"
    link.symlink_to("real.json")  # relative, resolved from the link's directory
    atomic_write_text(link, "through the link")
    assert link.is_symlink() and os.readlink(link) == "real.json"
    assert target.read_text() == "through the link"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "real.json"]  # no temporary left


def test_fifo_is_streamed_when_allowed_and_stays_a_fifo(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    reader = FifoReader(fifo)
    atomic_write_text(fifo, '{"a": 1}\n', stream=True)
    assert reader.result() == b'{"a": 1}\n'
    reader = FifoReader(fifo)
    atomic_write_with(fifo, lambda tmp: tmp.write_bytes(b"\x89PNG..."), stream=True)  # a writer that wants a name
    assert reader.result() == b"\x89PNG..."
    assert stat.S_ISFIFO(_mode(fifo))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe"]


def test_fifo_is_refused_where_the_output_must_be_a_regular_file(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    link = tmp_path / "to_pipe.json"
    link.symlink_to(fifo)
    for path in (fifo, link):
        with pytest.raises(OutputFileError, match="FIFO.*written only as a regular file"):
            atomic_write_text(path, "x")  # no reader: a write attempt would hang, a refusal returns at once
        with pytest.raises(OutputFileError, match="FIFO"):
            check_output_path(path)
    assert stat.S_ISFIFO(_mode(fifo)) and link.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe", "to_pipe.json"]


def _as_device(monkeypatch, path, kind=stat.S_IFCHR):
    """os.stat/os.lstat report ``path`` (a regular file) as a device: the writer must open it for appending
    (so its old contents stay and its inode is the same), never rename over it."""
    real_stat, real_lstat = os.stat, os.lstat

    def fake(real):
        def call(p, *a, **k):
            st = real(p, *a, **k)
            if os.fspath(p) == os.fspath(path):
                return os.stat_result((kind | 0o666, *tuple(st)[1:]))
            return st
        return call

    monkeypatch.setattr(fileio.write.os, "stat", fake(real_stat))
    monkeypatch.setattr(fileio.write.os, "lstat", fake(real_lstat))


def test_a_device_is_written_through_never_renamed_over(tmp_path, monkeypatch):
    dev = tmp_path / "device"
    dev.write_text("before|")
    inode = dev.stat().st_ino
    _as_device(monkeypatch, dev)
    with pytest.raises(OutputFileError, match="character device; this output is written only as a regular file"):
        atomic_write_text(dev, "x")
    atomic_write_text(dev, "after", stream=True)
    monkeypatch.undo()
    assert dev.read_text() == "before|after" and dev.stat().st_ino == inode
    assert sorted(p.name for p in tmp_path.iterdir()) == ["device"]


def test_a_block_device_is_never_written(tmp_path, monkeypatch):
    dev = tmp_path / "disk"
    dev.write_text("sectors")
    _as_device(monkeypatch, dev, stat.S_IFBLK)
    with pytest.raises(OutputFileError, match="it is a block device$"):
        atomic_write_text(dev, "x", stream=True)
    monkeypatch.undo()
    assert dev.read_text() == "sectors"


def _mknod_char(path, major, minor):
    if os.geteuid() != 0:
        pytest.skip("making a device node needs root")
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(major, minor))
    except OSError as exc:  # a container without CAP_MKNOD, or a nodev mount
        pytest.skip(f"cannot make a device node here: {exc}")


def test_real_character_devices_stay_devices(tmp_path):
    """As root (as in many robot containers): nodes like /dev/null (1, 3) and /dev/full (1, 7), made in the
    temporary directory so the system's own are never at stake."""
    null, full = tmp_path / "null", tmp_path / "full"
    _mknod_char(null, 1, 3)
    _mknod_char(full, 1, 7)
    atomic_write_text(null, "discarded", stream=True)
    with pytest.raises(OutputFileError) as info:
        atomic_write_text(full, "x", stream=True)
    assert str(info.value) == f"cannot write {full}: No space left on device"
    for path in (null, full):
        with pytest.raises(OutputFileError, match="character device"):
            atomic_write_text(path, "x")
        assert stat.S_ISCHR(_mode(path))
    assert os.major(null.stat().st_rdev) == 1 and os.minor(full.stat().st_rdev) == 7
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full", "null"]


def test_open_descriptors_are_appended_to_even_when_they_are_files(tmp_path):
    """/dev/stdout-style paths name the command's own descriptor: a pipe gets the bytes, and a regular
    file the shell redirected to is appended to, never replaced (what was printed before stays)."""
    r, w = os.pipe()
    try:
        atomic_write_text(f"/proc/self/fd/{w}", "to the pipe", stream=True)
        assert os.read(r, 100) == b"to the pipe"
        with pytest.raises(OutputFileError, match="open file descriptor"):
            atomic_write_text(f"/dev/fd/{w}", "x")
    finally:
        os.close(r)
        os.close(w)
    redirected = tmp_path / "stdout.txt"
    with open(redirected, "w") as f:
        f.write("printed first\n")
        f.flush()
        inode = redirected.stat().st_ino
        alias = tmp_path / "alias.json"
        alias.symlink_to(f"/dev/fd/{f.fileno()}")  # a link to a descriptor counts as the descriptor
        atomic_write_text(alias, "then the JSON\n", stream=True)
    assert redirected.read_text() == "printed first\nthen the JSON\n" and redirected.stat().st_ino == inode
    assert alias.is_symlink()


def test_directories_sockets_and_bad_links_are_refused(tmp_path, monkeypatch):
    folder = tmp_path / "folder"
    folder.mkdir()
    (tmp_path / "to_folder").symlink_to(folder)
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere" / "x.json")
    (tmp_path / "loop_a").symlink_to(tmp_path / "loop_b")
    (tmp_path / "loop_b").symlink_to(tmp_path / "loop_a")
    sock = socket.socket(socket.AF_UNIX)
    monkeypatch.chdir(tmp_path)  # a relative name: socket paths are limited to 107 bytes
    sock.bind("sock")
    cases = {"folder": "it is a directory", "to_folder": "a symbolic link to a directory",
             "dangling": "a symbolic link to .*nowhere/x.json, which does not exist",
             "loop_a": "symbolic links", "sock": "it is a socket"}
    try:
        for name, why in cases.items():
            for stream in (False, True):
                with pytest.raises(OutputFileError, match=why):
                    atomic_write_text(tmp_path / name, "x", stream=stream)
    finally:
        sock.close()
    assert not (tmp_path / "nowhere").exists()  # the link's missing target was not created
    assert stat.S_ISSOCK(_mode(tmp_path / "sock")) and stat.S_ISDIR(_mode(folder))
    assert list(folder.iterdir()) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write read-only files")
def test_a_read_only_file_is_not_replaced(tmp_path):
    path = tmp_path / "kept.toml"
    path.write_text("mine")
    path.chmod(0o444)
    with pytest.raises(OutputFileError, match="is read-only"):
        atomic_write_text(path, "x")
    assert path.read_text() == "mine"


def test_missing_parents_are_created_only_where_allowed(tmp_path):
    with pytest.raises(OutputFileError, match="does not exist"):
        check_output_path(tmp_path / "a" / "b.json", create_parent=False)
    assert not (tmp_path / "a").exists()
    atomic_write_text(tmp_path / "a" / "b.json", "x")
    assert (tmp_path / "a" / "b.json").read_text() == "x"


def test_output_folders(tmp_path):
    assert check_output_dir(tmp_path / "new" / "plots").is_dir()
    (tmp_path / "file").write_text("x")
    os.mkfifo(tmp_path / "pipe")
    (tmp_path / "link").symlink_to(tmp_path / "new")
    assert check_output_dir(tmp_path / "link") == tmp_path / "link"
    for name, why in (("file", "a regular file"), ("pipe", "a FIFO")):
        with pytest.raises(OutputFileError, match=f"cannot write into .*{name}: it is {why}.*not a directory"):
            check_output_dir(tmp_path / name)
    assert stat.S_ISFIFO(_mode(tmp_path / "pipe")) and (tmp_path / "file").read_text() == "x"


# --------------------------------------------------------------------------- through the command line
@pytest.fixture
def problem(tmp_path):
    path = tmp_path / "p.json"
    assert main(["scenario", "merge", "--cars", "2", "--seed", "0", "--out", str(path)]) == 0
    return path


def test_solve_streams_its_result_to_a_fifo(tmp_path, problem, capsys):
    fifo = tmp_path / "result"
    os.mkfifo(fifo)
    reader = FifoReader(fifo)
    code = main(["solve", str(problem), "--out", str(fifo)])
    result = json.loads(reader.result())
    assert code in (0, 1) and result["status"] and len(result["x"]) == 2  # the whole result, one per car
    assert stat.S_ISFIFO(_mode(fifo))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.json", "result"]


def test_outputs_read_back_refuse_a_fifo_before_the_work(tmp_path, capsys):
    """Problem files, recordings, link captures and drive logs are refused (exit 2, no wait for a reader),
    before the race, the HIL world or the generator starts."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    runs = [["scenario", "merge", "--out", str(fifo)],
            ["race", "--out", str(tmp_path / "r.rrd"), "--link-capture", str(fifo)],
            ["check", "--hil", "--link-capture", str(fifo)],
            ["sysid-generate", "--minutes", "0.1", "--out", str(fifo)]]
    rrd_fifo = tmp_path / "pipe.rrd"
    os.mkfifo(rrd_fifo)
    runs += [["race", "--out", str(rrd_fifo)], ["race", "--hil", "--out", str(rrd_fifo)]]
    for argv in runs:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "FIFO" in err and "written only as a regular file" in err and "Traceback" not in err
    assert stat.S_ISFIFO(_mode(fifo)) and stat.S_ISFIFO(_mode(rrd_fifo))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe", "pipe.rrd"]  # the race never started


@pytest.mark.parametrize("make, why", [
    (lambda p: p.mkdir(), "it is a directory"),
    (lambda p: p.symlink_to(p.parent / "missing" / "s.json"), "which does not exist"),
])
def test_race_json_is_checked_before_the_race(tmp_path, capsys, make, why):
    target = tmp_path / "summary.json"
    make(target)
    assert main(["race", "--out", str(tmp_path / "r.rrd"), "--json", str(target)]) == 2
    assert why in capsys.readouterr().err
    assert not (tmp_path / "r.rrd").exists() and not (tmp_path / "missing").exists()


def test_review_streams_its_json_and_refuses_a_folder(tmp_path, capsys):
    from test_review import _synthetic_recording
    from race.review import SUMMARY_KEYS
    from tracks import load_track

    path = tmp_path / "ok.rrd"
    _synthetic_recording(path, load_track("oval"), 2.0, n_ticks=30)
    fifo = tmp_path / "summary"
    os.mkfifo(fifo)
    reader = FifoReader(fifo)
    assert main(["review", str(path), "--no-plots", "--json", str(fifo)]) == 0
    assert tuple(json.loads(reader.result())) == SUMMARY_KEYS
    assert stat.S_ISFIFO(_mode(fifo))
    assert main(["review", str(path), "--json", str(tmp_path)]) == 2
    assert "it is a directory" in capsys.readouterr().err
    assert not (tmp_path / "ok_review").exists()  # refused before the plots
