"""The live view of a race (`race --viewer/--serve`, recording.live) and the operator stop key
(race.operator, app/realtime/operator_key.py).

There is no screen here: the viewer is Rerun's own headless gRPC server (`rerun --port P --save FILE`,
which writes what it receives), and the served stream is read by Rerun's own client (`rerun URL
--save FILE`). What a viewer got and what the file holds are compared entity by entity (rows of each
entity path) with Rerun's chunk reader; the file of a race with a viewer is compared with the file of
the same seed's race without one. The stop key is tested as a state machine with a scripted input,
in the loop on a simulated clock (the fake world of test_loop_safety), on a pseudo-terminal, and in a
HIL race on a pseudo-terminal."""
from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import pty
import select
import signal
import socket
import subprocess
import sys
import termios
import time
import warnings
from pathlib import Path

import pytest

from app.cli import main
from app.live_view import answers
from app.realtime.operator_key import TerminalStopKey
from race.config import LoopConfig
from race.loop import RaceLoop, SimulatedDeadlineMonitor
from race.operator import END_REASON, OperatorStop
from race.planning import SyncPlanRunner
from race.recording import RaceRecorder, load_recording
from race.review import summarize
from race.world import SimulatedClock
from recording.integrity import rerun_executable
from recording.live import DEFAULT_VIEWER_PORT, LiveView, viewer_address
from test_loop_safety import CARS, T0, Link, Planners, Tracker, World, driving
from test_loop_support import neutral_within
from test_recording_blueprint import SIMULATION_VIEWS, blueprint_views
from tracking.estimator import MultiCarEstimator

ROOT = Path(__file__).resolve().parents[1]
RERUN = rerun_executable()
needs_rerun = pytest.mark.skipif(RERUN is None, reason="the rerun executable of rerun-sdk is not installed")


# --------------------------------------------------------------------------- helpers
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(0.1)


@contextlib.contextmanager
def viewer_server(save_to: Path):
    """A headless Rerun viewer server (what `rerun` listens with) saving what it receives; yields its URL."""
    port = free_port()
    proc = subprocess.Popen([RERUN, "--port", str(port), "--save", str(save_to)], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_until(lambda: answers("127.0.0.1", port, 0.2), 20, "the test's Rerun server")
        yield f"rerun+http://127.0.0.1:{port}/proxy"
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def served_copy(url: str, save_to: Path) -> subprocess.Popen:
    """Rerun's client connected to a served race, saving the stream as it comes (it exits when the
    race's process does)."""
    return subprocess.Popen([RERUN, url, "--save", str(save_to), "--port", str(free_port())], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def rows_by_entity(path: Path) -> dict[tuple[str, bool], int]:
    """{(entity path, static): rows} of the recording in an .rrd file (a copy saved by a viewer server
    may lack the footer: read what it has)."""
    import rerun as rr

    if not path.exists():
        return {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            reader = rr.chunk.RrdReader(path)
            stores = reader.recordings()
        except Exception:  # still being written
            return {}
    rows: dict[tuple[str, bool], int] = {}
    if not stores:
        return rows
    try:
        for chunk in reader.stream(store=stores[0]):
            key = (chunk.entity_path, chunk.is_static)
            rows[key] = rows.get(key, 0) + chunk.to_record_batch().num_rows
    except Exception:
        return {}
    return rows


# --------------------------------------------------------------------------- URLs and flags
def test_viewer_url_forms():
    assert viewer_address("rerun+http://127.0.0.1:9876/proxy") == ("127.0.0.1", 9876)
    assert viewer_address("rerun+https://lab-pc.local:443/proxy") == ("lab-pc.local", 443)
    for url, words in (("http://127.0.0.1:9876/proxy", "scheme"), ("rerun+http://127.0.0.1:9876/", "/proxy"),
                       ("rerun+http://127.0.0.1/proxy", "port"), ("rerun+http://127.0.0.1:99999/proxy", "port")):
        with pytest.raises(ValueError, match=words):
            viewer_address(url)
    with pytest.raises(ValueError, match="needs a viewer URL or a port"):
        LiveView()


def _race_error(capsys, argv: list[str]) -> str:
    assert main(["race", *argv]) == 2
    return capsys.readouterr().err


def test_live_view_flags_are_checked_before_the_race(tmp_path, capsys, monkeypatch):
    out = tmp_path / "r.rrd"
    base = ["--max-time", "1", "--out", str(out)]
    assert "--viewer" in _race_error(capsys, [*base, "--viewer", "http://127.0.0.1:9876/proxy"])
    nobody = free_port()
    err = _race_error(capsys, [*base, "--viewer", f"rerun+http://127.0.0.1:{nobody}/proxy"])
    assert "--viewer: no Rerun viewer answers" in err and str(nobody) in err
    with socket.socket() as busy:
        busy.bind(("0.0.0.0", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert f"--serve: port {port} is not free" in _race_error(capsys, [*base, "--serve", str(port)])
    port = free_port()
    assert "its own viewer" in _race_error(capsys, [*base, "--serve", str(port), "--viewer",
                                                    f"rerun+http://127.0.0.1:{port}/proxy"])
    assert "--serve: the port must be in 1..65535" in _race_error(capsys, [*base, "--serve", "70000"])
    if not answers("127.0.0.1", DEFAULT_VIEWER_PORT):  # a viewer of someone else's may listen there
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        err = _race_error(capsys, [*base, "--viewer"])
        assert "no display" in err and "--serve" in err
    # the HIL mode checks them too, before its processes start
    assert "--viewer: no Rerun viewer answers" in _race_error(
        capsys, ["--hil", *base, "--viewer", f"rerun+http://127.0.0.1:{nobody}/proxy"])
    assert not out.exists()


# --------------------------------------------------------------------------- the simulated race
@needs_rerun
def test_simulated_race_streams_to_a_viewer_and_records_the_same_file(tmp_path, capsys):
    alone, watched, got = tmp_path / "alone.rrd", tmp_path / "watched.rrd", tmp_path / "viewer.rrd"
    race = ["race", "--seed", "3", "--max-time", "2"]
    assert main([*race, "--out", str(alone), "--json", str(tmp_path / "alone.json")]) == 0
    with viewer_server(got) as url:
        assert main([*race, "--out", str(watched), "--json", str(tmp_path / "watched.json"), "--viewer", url]) == 0
        assert f"streaming to the Rerun viewer at {url}" in capsys.readouterr().out
        expected = rows_by_entity(watched)
        wait_until(lambda: rows_by_entity(got) == expected, 20, "the viewer to receive the whole race")
    # the file of the watched race holds what the race without a viewer holds (seeded: the same race)
    assert rows_by_entity(alone) == expected and len(expected) > 30
    assert ("/race/events", False) in expected and ("/world/track/left", True) in expected
    a, w = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("alone", "watched"))
    for key in ("winner", "lap_times_s", "min_gap_m", "collisions", "race_time_s"):
        assert a[key] == w[key]
    # the viewer opens on the race layout (the views of the file's blueprint); the file is finished
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the viewer's copy has no footer
        views = blueprint_views(got)
    assert views == blueprint_views(watched) == blueprint_views(alone) and set(views) == SIMULATION_VIEWS
    assert load_recording(watched).has("world/cars/rd3g/position")


@needs_rerun
def test_served_recording_reaches_a_viewer_that_connects_late(tmp_path):
    port = free_port()
    path, got = tmp_path / "served.rrd", tmp_path / "client.rrd"
    rec = RaceRecorder(path, "served", live=LiveView(serve_port=port), car_names=["a"])
    for k in range(120):  # before any viewer: the server keeps them
        rec.scalar("cars/a/speed_mps", k, k / 60, 0.01 * k)
    rec.event(1.0, "start", "race started")
    time.sleep(1.0)  # past the background flush
    client = served_copy(f"rerun+http://127.0.0.1:{port}/proxy", got)
    try:
        time.sleep(1.5)
        for k in range(120, 300):
            rec.points("world/cars/a/position", k, k / 60, [0.001 * k, 0.0])
        rec.close()  # closes the server (a client's stream ends when the race process exits)
        expected = rows_by_entity(path)
        wait_until(lambda: rows_by_entity(got) == expected, 20, "the client to receive the whole recording")
    finally:
        client.terminate()
        client.wait(timeout=10)
    assert expected[("/cars/a/speed_mps", False)] == 120 and expected[("/world/cars/a/position", False)] == 180


@needs_rerun
def test_file_is_whole_when_the_viewer_goes_away(tmp_path):
    path = tmp_path / "r.rrd"
    port = free_port()
    server = subprocess.Popen([RERUN, "--port", str(port), "--save", str(tmp_path / "v.rrd")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_until(lambda: answers("127.0.0.1", port, 0.2), 20, "the test's Rerun server")
        rec = RaceRecorder(path, "lost", live=LiveView(viewer_url=f"rerun+http://127.0.0.1:{port}/proxy"),
                           background=False, flush_every_s=0.05)
        for k in range(400):
            rec.scalar("cars/a/speed_mps", k, k / 30, 1.0)
            if k == 200:
                server.kill()
                server.wait(timeout=10)
            time.sleep(0.001)
        rec.close()
    finally:
        if server.poll() is None:
            server.kill()
    data = load_recording(path)  # footer present: a finished file
    assert len(data.scalars("cars/a/speed_mps")[0]) == 400


# --------------------------------------------------------------------------- the stop key's logic
class ScriptedInput:
    """A fake operator: poll() answers from a script, then False."""

    def __init__(self, answers_: list[bool]) -> None:
        self.answers, self.polls = list(answers_), 0

    def poll(self) -> bool:
        self.polls += 1
        return self.answers.pop(0) if self.answers else False


def test_operator_stop_state_machine():
    neutrals, events = [], []
    source = ScriptedInput([False, False, True, False])
    stop = OperatorStop(source, lambda: neutrals.append(len(events)),
                        lambda kind, text, t_race=None: events.append((t_race, kind, text)))
    assert stop.check(0.0) is None and stop.check(0.1) is None and not neutrals and not events
    assert stop.check(0.2) == END_REASON
    assert neutrals == [0] and events == [(0.2, "stop", "operator stop key - all cars neutral")]
    # once stopped it stays stopped, without sending or logging again
    assert stop.check(0.3) == END_REASON and stop.check(0.4) == END_REASON
    assert neutrals == [0] and len(events) == 1 and source.polls == 3 and stop.stopped_at == 0.2


class KeyAt:
    """The operator presses the key at absolute time ``t`` of the loop's (simulated) clock."""

    def __init__(self, clock: SimulatedClock, t: float) -> None:
        self.clock, self.t = clock, t

    def poll(self) -> bool:
        return self.clock.now() >= self.t


def test_loop_stops_on_the_operator_key(track, car):
    from race.setup import RaceSetup

    setup = RaceSetup(track=track, car=car, max_time_s=5.0)
    clock = SimulatedClock(T0)
    world = World(clock, setup.track)
    link = Link(world)
    key = KeyAt(clock, math.inf)
    loop = RaceLoop(setup=setup, config=LoopConfig(), feed=world, tracker=Tracker(world), estimator=MultiCarEstimator(),
                    link=link, planners=Planners(), cars=CARS, mode="hardware", clock=clock,
                    worker_factory=SyncPlanRunner, monitor_factory=SimulatedDeadlineMonitor, operator=key)
    original_cold_start = loop._cold_start

    def cold_start():
        original_cold_start()
        world.t_go = loop.t_go
        key.t = loop.t_go + 1.0  # pressed 1 s into the race, between two ticks

    loop._cold_start = cold_start
    o = loop.run()
    period = 1 / LoopConfig().rate_hz
    t_stop = math.ceil(1.0 / period - 1e-9) * period  # the first tick at or after the key
    # hardware race time is the last instant the referee judged: the states of the tick before, at its t_plan
    t_judged = t_stop - period + LoopConfig().plan_latency_s
    assert o.reason == "operator_stop" and o.race_time_s == pytest.approx(t_judged, abs=1e-9)
    (t_event, text), = [(t, text) for t, kind, text in o.events if kind == "stop"]
    assert t_event == pytest.approx(t_stop, abs=1e-9) and "operator stop key" in text
    # neutral at once at the stop tick (and again at shutdown); driving until the tick before, nothing after
    assert link.neutrals[0] == pytest.approx(t_stop, abs=1e-9)
    assert all(driving(c) for t, c in link.sent if 0.2 < t)
    assert max(t for t, _ in link.sent) == pytest.approx(t_stop - period, abs=1e-9)
    s = o.summary()
    assert s["end_reason"] == "operator_stop" and s["events"]["stop"] == 1 and s["ticks"] == o.ticks


# --------------------------------------------------------------------------- the terminal key
class Fd:
    def __init__(self, fd: int) -> None:
        self.fd = fd

    def fileno(self) -> int:
        return self.fd


def test_terminal_key_on_a_pseudo_terminal(monkeypatch):
    master, slave = pty.openpty()
    try:
        original = termios.tcgetattr(slave)
        os.write(master, b" ")  # typed before the race: not a stop
        sigterm_before = signal.getsignal(signal.SIGTERM)
        with TerminalStopKey(Fd(slave)) as key:
            assert key.active
            lflags = termios.tcgetattr(slave)[3]
            assert not lflags & termios.ICANON and not lflags & termios.ECHO and lflags & termios.ISIG
            assert not key.poll()
            os.write(master, b"x")
            time.sleep(0.05)
            assert not key.poll()  # other keys do nothing
            os.write(master, b" ")
            time.sleep(0.05)
            assert key.poll()
            os.write(master, b"\r")
            time.sleep(0.05)
            assert key.poll() and not key.poll()
            assert signal.getsignal(signal.SIGTERM) != sigterm_before
        assert termios.tcgetattr(slave) == original and not key.active
        assert signal.getsignal(signal.SIGTERM) == sigterm_before
        # a race started in the background leaves the terminal alone (changing it would stop the process)
        monkeypatch.setattr(os, "tcgetpgrp", lambda fd: os.getpgrp() + 1)
        with TerminalStopKey(Fd(slave)) as key:
            assert not key.active and termios.tcgetattr(slave) == original
            os.write(master, b" ")
            assert not key.poll()
    finally:
        os.close(master)
        os.close(slave)
    r, w = os.pipe()  # not a terminal: a no-op
    try:
        with TerminalStopKey(Fd(r)) as key:
            os.write(w, b" ")
            assert not key.active and not key.poll()
    finally:
        os.close(r)
        os.close(w)


def _own_terminal() -> None:
    """In the child: its stdin (a pseudo-terminal) becomes its controlling terminal, itself the foreground."""
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)


def test_terminal_mode_restored_on_sigterm():
    master, slave = pty.openpty()
    try:
        original = termios.tcgetattr(slave)
        code = ("import sys, time; sys.path.insert(0, %r)\n"
                "from app.realtime.operator_key import TerminalStopKey\n"
                "key = TerminalStopKey().arm(); print('armed', key.active, flush=True); time.sleep(60)\n" % str(ROOT))
        proc = subprocess.Popen([sys.executable, "-c", code], stdin=slave, stdout=subprocess.PIPE,
                                start_new_session=True, preexec_fn=_own_terminal)
        try:
            assert proc.stdout.readline().decode().strip() == "armed True"
            assert termios.tcgetattr(slave) != original
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(timeout=20) == -signal.SIGTERM  # still killed by the signal
        finally:
            if proc.poll() is None:
                proc.kill()
        assert termios.tcgetattr(slave) == original
    finally:
        os.close(master)
        os.close(slave)


# --------------------------------------------------------------------------- a HIL race, end to end
def _read_until(stream, text: str, timeout_s: float) -> str:
    seen, deadline = b"", time.monotonic() + timeout_s
    while text.encode() not in seen:
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([stream], [], [], left)[0]:
            raise AssertionError(f"no {text!r} within {timeout_s:g} s; output so far:\n{seen.decode()}")
        chunk = os.read(stream.fileno(), 4096)
        if not chunk:
            raise AssertionError(f"the race exited before {text!r}; output:\n{seen.decode()}")
        seen += chunk
    return seen.decode()


@needs_rerun
def test_hil_race_served_live_and_stopped_by_the_operator_key(tmp_path):
    port = free_port()
    out, js, got = tmp_path / "hil.rrd", tmp_path / "hil.json", tmp_path / "client.rrd"
    master, slave = pty.openpty()
    original = termios.tcgetattr(slave)
    race = subprocess.Popen([sys.executable, "-m", "app", "race", "--hil", "--seed", "1", "--max-time", "40",
                             "--serve", str(port), "--out", str(out), "--json", str(js)],
                            cwd=ROOT, stdin=slave, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, preexec_fn=_own_terminal)
    client = None
    try:
        printed = _read_until(race.stdout, "press space or Enter", 120)
        assert f"serving on port {port}" in printed
        client = served_copy(f"rerun+http://127.0.0.1:{port}/proxy", got)
        # the viewer sees the race while it runs: 2 s of loop ticks arrive before the operator stops it
        wait_until(lambda: rows_by_entity(got).get(("/loop/busy_ms", False), 0) >= 120, 90,
                   "the served viewer to receive 2 s of the race")
        os.write(master, b" ")
        assert race.wait(timeout=60) == 1, race.stderr.read().decode()  # stopped by the operator: not finished
        assert client.wait(timeout=30) == 0
    finally:
        for proc in (race, client):
            if proc is not None and proc.poll() is None:
                proc.kill()
        restored = termios.tcgetattr(slave) == original  # the race gave the terminal back as it was
        os.close(master)
        os.close(slave)
    assert restored
    s = json.loads(js.read_text())
    assert s["end_reason"] == "operator_stop" and s["events"]["stop"] == 1 and 2.0 < s["race_time_s"] < 40
    review = summarize(load_recording(out))  # a finished recording
    (stop,) = [e for e in review["events"] if e["kind"] == "stop"]
    assert "operator stop key" in stop["text"]
    # the cars were driving and the box put them neutral within a few milliseconds of the stop
    assert any(e["kind"] == "cars_driving" for e in review["events"])
    assert neutral_within(review["events"], stop["time_s"], stop["time_s"] + 0.05)
    # the served viewer got the whole recording
    assert rows_by_entity(got) == rows_by_entity(out)
