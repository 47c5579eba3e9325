"""Hardware-in-the-loop world: the simulator, the virtual transmitter box and the synthetic camera in
their own process, running in real time.

* The box (``vehicles.virtual_box.VirtualCarBox``) sits behind a :class:`SerialRelay` pty that the
  race loop's ``SerialCarLink`` opens like a USB serial port; the relay forwards the bytes and can
  corrupt them or vanish (fault injection).
* The simulator advances in 1 ms steps to each camera capture time with the commands the box had
  in effect at that moment (``commands_at``), so the loop's real latencies act on the cars.
* Frames are rendered by ``tracking.SyntheticCamera`` at the camera rate and written to a shared
  memory ring; a small message per frame carries its slot, capture time, the true states (for
  telemetry and tracking error only), simulator/box events and render time.

Rendering runs here, outside the loop process, so it is not part of the loop's budget (it is
reported). Frames that cannot be rendered in time are dropped (counted), like a camera would.
"""
from __future__ import annotations

import math
import os
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.realtime.config import FaultSpec

CAR_NAMES = ("rd3g", "opponent")
FIXED_MARKERS = {"oval": Path(__file__).resolve().parents[2] / "tracking" / "data" / "oval_fixed_markers.json"}


@dataclass(frozen=True)
class WorldSpec:
    track: object
    car: object                       # CarParams of both cars
    start_states: np.ndarray          # (2, 6)
    marker_ids: tuple[int, int]
    radio_ids: tuple[int, int]
    laps: int
    seed: int
    fps: float = 60.0
    image_size: tuple[int, int] = (1280, 800)
    faults: tuple[FaultSpec, ...] = ()
    failsafe_timeout_s: float = 0.1
    physics_dt_s: float = 0.001
    # Lap/collision/track-limit checks every 10 ms instead of the simulator's 5 ms: the checks cost as
    # much as the physics in real time; at racing closing speeds (< 1 m/s) a car moves 1 cm between checks.
    check_dt_s: float = 0.01
    corrupt_byte_rate: float = 0.5    # serial_corrupt: fraction of bytes with one flipped bit
    slots: int = 8


class SerialRelay:
    """A pty pair between the link and the box: bytes written to ``path`` are forwarded to the box's
    pty, with bit errors while ``corrupt`` is set. ``close()`` makes the device vanish (the link's
    next write fails with EIO)."""

    def __init__(self, downstream_path: str, seed: int = 0, byte_error_rate: float = 0.5) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._out = os.open(downstream_path, os.O_WRONLY | os.O_NOCTTY)
        self._rng = np.random.default_rng(seed)
        self.byte_error_rate = float(byte_error_rate)
        self.corrupt = False
        self.bytes_forwarded = 0
        self.bytes_corrupted = 0
        self._wake_r, self._wake_w = os.pipe()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="SerialRelay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            readable, _, _ = select.select([self._master, self._wake_r], [], [])
            if self._wake_r in readable:
                return
            try:
                data = bytearray(os.read(self._master, 4096))
            except OSError:
                return
            if not data:
                return
            if self.corrupt:
                hit = np.nonzero(self._rng.random(len(data)) < self.byte_error_rate)[0]
                bits = self._rng.integers(0, 8, len(hit))
                for i, b in zip(hit.tolist(), bits.tolist()):
                    data[i] ^= 1 << b
                self.bytes_corrupted += len(hit)
            try:
                os.write(self._out, bytes(data))
            except OSError:
                return
            self.bytes_forwarded += len(data)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave, self._out, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass


def make_camera(spec: WorldSpec):
    """The synthetic overhead camera of the track's arena (and its fixed markers, if the track has a
    fixed-marker file)."""
    from tracking.calibration import load_fixed_markers
    from tracking.camera import CarAppearance, RenderEffects, SyntheticCamera, TrackDrawing, overhead_camera

    track = spec.track
    arena = track.arena
    bounds = (arena.x_min, arena.y_min, arena.x_max, arena.y_max) if arena else (0.0, 0.0, 5.0, 3.0)
    camera = overhead_camera(bounds, image_size=spec.image_size)
    left, right = track.boundaries(0.01)
    fixed_path = FIXED_MARKERS.get(track.name)
    fixed = list(load_fixed_markers(fixed_path).markers.values()) if fixed_path else []
    appearance = CarAppearance(roof_height_m=spec.car.marker.height_m)
    synth = SyntheticCamera(camera, TrackDrawing(left, right, arena_bounds=bounds), fixed, car=appearance,
                            effects=RenderEffects(seed=spec.seed), fps=spec.fps)
    return synth, camera, fixed_path, appearance


def world_main(spec: WorldSpec, conn, shm_name: str) -> None:
    """Child-process entry point. Messages to the parent: ("ready", info), ("frame", info),
    ("summary", info); from the parent: ("go", t_go), ("stop",)."""
    import signal
    from multiprocessing import shared_memory

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us; Ctrl-C goes to the parent
    from app.realtime.config import lower_realtime_priority

    lower_realtime_priority(5)  # --rt-priority: the world (camera, cars) just below the loop
    import sys

    sys.setswitchinterval(0.001)  # physics, renderer and box threads share the GIL at a fine grain
    try:
        _World(spec, conn, shared_memory.SharedMemory(name=shm_name)).run()
    except Exception as exc:  # report, so the parent can stop the race with a clear message
        import traceback

        conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))


class _World:
    def __init__(self, spec: WorldSpec, conn, shm) -> None:
        from app.race_runner import fault_of, footprint_gap
        from sim import Simulator
        from tracking.camera import CarPose
        from vehicles.virtual_box import VirtualCarBox

        self.spec, self.conn, self.shm = spec, conn, shm
        self.CarPose, self.fault_of, self.footprint_gap = CarPose, fault_of, footprint_gap
        w, h = spec.image_size
        self.frames = np.ndarray((spec.slots, h, w), dtype=np.uint8, buffer=shm.buf)
        self.sim = Simulator(spec.track, [spec.car, spec.car], seed=spec.seed, physics_dt=spec.physics_dt_s,
                             laps_to_win=spec.laps, check_dt=spec.check_dt_s)
        self.sim.reset(np.asarray(spec.start_states, dtype=float))
        self.box = VirtualCarBox(failsafe_timeout=spec.failsafe_timeout_s)
        self.relay = SerialRelay(self.box.path, seed=spec.seed, byte_error_rate=spec.corrupt_byte_rate)
        self.synth, self.camera, self.fixed_path, self.appearance = make_camera(spec)
        self.max_steer = spec.car.actuators.max_steering_rad
        self.events: list[tuple] = []      # (race time, kind, text) not yet sent
        self.collisions: list[dict] = []
        self.min_gap = math.inf
        self.neutral_at_box = True
        self.render_ms: list[float] = []
        self.dropped = 0
        self.rendered = 0
        self._fault_state: dict[int, bool] = {}
        self._last_corrupt = 0
        self._last_failsafe = 0
        # Under --rt-priority the box and relay threads (created above) emulate hardware and must
        # preempt the physics and the renderer, which therefore run 2 levels lower.
        from app.realtime.config import lower_realtime_priority

        lower_realtime_priority(2)
        # Rendering runs in its own thread: OpenCV releases the GIL, so it overlaps the physics.
        self._render_cv = threading.Condition()
        self._pending: dict | None = None
        self._stop_render = False
        self._render_thread = threading.Thread(target=self._render_loop, name="render", daemon=True)
        self._render_thread.start()

    # ---- helpers
    def _commands(self, t_abs: float) -> np.ndarray:
        cmds = self.box.commands_at(t_abs)
        out = np.zeros((2, 2))
        for i, rid in enumerate(self.spec.radio_ids):
            c = cmds.get(rid)
            if c is not None:
                out[i] = (c.throttle, c.steering * self.max_steer)
        return out

    def _poses(self, states: np.ndarray, t_race: float | None) -> list:
        poses = []
        for i, state in enumerate(states):
            hidden = t_race is not None and any(
                f.kind == "occlude" and f.active(t_race) and f.applies_to(CAR_NAMES[i]) for f in self.spec.faults)
            if hidden:  # the marker is covered: the car is not drawn at all
                continue
            speed = math.hypot(state[3], state[4])
            poses.append(self.CarPose(self.spec.marker_ids[i], float(state[0]), float(state[1]), float(state[2]),
                                      speed, float(state[5])))
        return poses

    def _snapshot(self, index: int, t_cap: float, t_race: float | None) -> None:
        """Hand the current world state to the render thread; an unrendered older one is dropped
        (its events move to this one)."""
        box = self.box.stats
        status = self.sim.race_status()
        snap = {"index": index, "slot": index % self.spec.slots, "t_capture": t_cap, "t_race": t_race,
                "truth": self.sim.states, "dropped": 0, "box_frames": box.frames_received,
                "box_corrupt": box.decoder.corrupt, "box_failsafe_events": box.failsafe_events,
                "winner": None if status.winner is None else CAR_NAMES[status.winner]}
        with self._render_cv:
            events, self.events = self.events, []
            if self._pending is not None:
                events = self._pending["events"] + events
                if t_race is not None:
                    self.dropped += 1
            snap["events"] = events
            snap["dropped"] = self.dropped
            self._pending = snap
            self._render_cv.notify_all()
            # Let the renderer take it before the physics runs on: a physics thread that is behind
            # would otherwise keep the GIL and every frame would be replaced before it is drawn.
            self._render_cv.wait_for(lambda: self._pending is not snap, timeout=1.0 / self.spec.fps)

    def _render_loop(self) -> None:
        while True:
            with self._render_cv:
                while self._pending is None and not self._stop_render:
                    self._render_cv.wait()
                if self._stop_render:
                    return
                snap, self._pending = self._pending, None
                self._render_cv.notify_all()
            t0 = time.perf_counter()
            frame = self.synth.render(self._poses(snap["truth"], snap["t_race"]), snap["t_capture"])
            self.frames[snap["slot"]] = frame.image
            snap["render_ms"] = 1e3 * (time.perf_counter() - t0)
            self.render_ms.append(snap["render_ms"])
            self.rendered += 1
            self.conn.send(("frame", snap))

    def _apply_faults(self, t_race: float) -> None:
        for n, f in enumerate(self.spec.faults):
            if f.kind == "serial_corrupt":
                on = f.active(t_race)
                if on != self._fault_state.get(n, False):
                    self.relay.corrupt = on
                    self.events.append((t_race, "fault_injected", f"serial_corrupt {'on' if on else 'off'}"))
                self._fault_state[n] = on
            elif f.kind == "serial_vanish" and t_race >= f.start_s and not self._fault_state.get(n):
                self._fault_state[n] = True
                self.relay.close()
                self.events.append((t_race, "fault_injected", "serial device vanished"))
            elif f.kind == "occlude":
                on = f.active(t_race)
                if on != self._fault_state.get(n, False):
                    self.events.append((t_race, "fault_injected", f"markers of {f.car or 'all cars'} "
                                                                  f"{'occluded' if on else 'visible again'}"))
                self._fault_state[n] = on

    def _box_events(self, t_race: float) -> None:
        box = self.box.stats
        if box.decoder.corrupt > self._last_corrupt:
            self.events.append((t_race, "serial_corrupt",
                                f"box rejected {box.decoder.corrupt - self._last_corrupt} corrupt frame(s)"))
            self._last_corrupt = box.decoder.corrupt
        if box.failsafe_events > self._last_failsafe:
            self.events.append((t_race, "box_failsafe", "no valid frame for 100 ms: box commands all cars neutral"))
            self._last_failsafe = box.failsafe_events

    def _advance(self, t_go: float, target: float) -> None:
        dt = self.spec.physics_dt_s
        sim = self.sim
        while sim.time < target - 1e-9:
            t_abs = t_go + sim.time
            cmds = self._commands(t_abs)
            neutral = not np.any(cmds)
            if neutral != self.neutral_at_box:
                self.events.append((sim.time, "cars_neutral" if neutral else "cars_driving",
                                    "every car neutral at the box" if neutral else "commands reach the cars"))
                self.neutral_at_box = neutral
            for ev in sim.step(cmds, dt):
                if ev.kind == "collision":
                    who = CAR_NAMES[self.fault_of(sim.states)]
                    self.collisions.append({"time_s": ev.time, "at_fault": who})
                    self.events.append((ev.time, "collision", f"{CAR_NAMES[ev.car]} (fault {who})"))
                elif ev.kind in ("lap", "finished", "off_track"):
                    extra = f" lap {ev.lap} in {ev.lap_time:.3f} s" if ev.kind == "lap" else ""
                    self.events.append((ev.time, ev.kind, f"{CAR_NAMES[ev.car]}{extra}"))

    # ---- main loop
    def run(self) -> None:
        spec = self.spec
        period = 1.0 / spec.fps
        self.conn.send(("ready", {"serial_path": self.relay.path, "camera": self.camera,
                                  "fixed_markers": str(self.fixed_path) if self.fixed_path else None,
                                  "marker_size_m": self.appearance.marker_size_m,
                                  "marker_height_m": self.appearance.roof_height_m}))
        index = 0
        t_go = None
        k = 0
        next_grid = time.monotonic()
        while True:
            while self.conn.poll():
                msg = self.conn.recv()
                if msg[0] == "go":
                    t_go = msg[1]
                elif msg[0] == "stop":
                    return self._finish()
            now = time.monotonic()
            if t_go is None or now < t_go - period:
                # Before the start: the grid, cars at rest, frames stamped with the wall clock.
                if now < next_grid:
                    time.sleep(min(next_grid - now, 0.005))
                    continue
                self._snapshot(index, now, None)
                index += 1
                next_grid = max(next_grid + period, time.monotonic())
                continue
            due = math.floor((now - t_go) / period)
            if due > k:  # could not keep up: skip the frames that are already past
                self.dropped += due - k
                k = due
            t_target = t_go + k * period
            if now < t_target:
                time.sleep(t_target - now)
            sim_target = round(k * period / spec.physics_dt_s) * spec.physics_dt_s
            self._apply_faults(sim_target)
            self._advance(t_go, sim_target)
            self._box_events(self.sim.time)
            self.min_gap = min(self.min_gap, self.footprint_gap(self.sim.states, spec.car))
            self._snapshot(index, t_go + self.sim.time, self.sim.time)
            index += 1
            k += 1

    def _finish(self) -> None:
        with self._render_cv:
            self._stop_render = True
            self._render_cv.notify()
        self._render_thread.join(timeout=2.0)
        status = self.sim.race_status()
        box = self.box.stats
        summary = {
            "winner": None if status.winner is None else CAR_NAMES[status.winner],
            "lap_times_s": {name: list(status.lap_times[i]) for i, name in enumerate(CAR_NAMES)},
            "min_gap_m": float(self.min_gap), "collisions": self.collisions, "race_time_s": self.sim.time,
            "off_track": {name: int(status.off_track_count[i]) for i, name in enumerate(CAR_NAMES)},
            "frames_rendered": self.rendered, "frames_dropped": self.dropped,
            "render_ms": np.array(self.render_ms, dtype=np.float32),
            "box": {"frames_received": box.frames_received, "failsafe_events": box.failsafe_events,
                    "corrupt": box.decoder.corrupt, "truncated": box.decoder.truncated},
            "events": (self._pending["events"] if self._pending else []) + self.events,
        }
        self.relay.close()
        self.box.close()
        self.conn.send(("summary", summary))
        self.shm.close()


# --------------------------------------------------------------------------- parent side
@dataclass
class WorldPacket:
    """What the loop gets per poll: the newest frame (copied out of shared memory) and everything
    the world reported since the last poll."""

    frame: object | None = None              # tracking.camera.Frame
    truth: np.ndarray | None = None          # (2, 6) true states at the frame's capture time
    t_race: float | None = None
    render_ms: list[float] = field(default_factory=list)
    events: list[tuple] = field(default_factory=list)
    winner: str | None = None
    box_corrupt: int = 0
    box_failsafe_events: int = 0
    dropped: int = 0


class HilWorld:
    """Starts the world process and reads its frames (parent side)."""

    def __init__(self, spec: WorldSpec, start_timeout_s: float = 60.0) -> None:
        import multiprocessing as mp
        from multiprocessing import shared_memory

        self.spec = spec
        w, h = spec.image_size
        self.shm = shared_memory.SharedMemory(create=True, size=spec.slots * w * h)
        self.frames = np.ndarray((spec.slots, h, w), dtype=np.uint8, buffer=self.shm.buf)
        ctx = mp.get_context("spawn")  # no fork of a process with threads (rerun, serial link)
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=world_main, args=(spec, child, self.shm.name), name="hil-world", daemon=True)
        self.process.start()
        child.close()
        self.summary: dict | None = None
        self._closed = False
        try:
            if not self.conn.poll(start_timeout_s):
                raise EOFError
            kind, info = self.conn.recv()
        except (EOFError, OSError):
            self.close()
            raise RuntimeError(f"HIL world process did not start (exit code {self.process.exitcode})") from None
        if kind != "ready":
            self.close()
            raise RuntimeError(f"HIL world process failed: {info}")
        self.info = info
        self.serial_path = info["serial_path"]
        self.camera = info["camera"]

    def go(self, t_go: float) -> None:
        self.conn.send(("go", t_go))

    def poll(self, timeout: float = 0.0) -> WorldPacket:
        from tracking.camera import Frame

        packet = WorldPacket()
        newest = None
        while self.conn.poll(timeout):
            timeout = 0.0
            kind, info = self.conn.recv()
            if kind == "error":
                raise RuntimeError(f"HIL world process failed: {info}")
            if kind != "frame":
                continue
            packet.events.extend(info["events"])
            packet.render_ms.append(info["render_ms"])
            packet.winner = info["winner"] or packet.winner
            packet.box_corrupt = info["box_corrupt"]
            packet.box_failsafe_events = info["box_failsafe_events"]
            packet.dropped = info["dropped"]
            newest = info
        if newest is not None:
            image = self.frames[newest["slot"]].copy()  # the slot is rewritten 'slots' frames later
            packet.frame = Frame(image, newest["t_capture"], newest["index"])
            packet.truth = newest["truth"]
            packet.t_race = newest["t_race"]
        return packet

    def close(self) -> dict | None:
        """Stop the world; returns its race summary (None if it could not be collected)."""
        if self._closed:
            return self.summary
        self._closed = True
        try:
            self.conn.send(("stop",))
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline and self.conn.poll(max(0.0, deadline - time.monotonic())):
                kind, info = self.conn.recv()
                if kind == "summary":
                    self.summary = info
                    break
                if kind == "error":
                    break
        except (BrokenPipeError, EOFError, OSError):
            pass
        self.process.join(timeout=5.0)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout=2.0)
        self.conn.close()
        self.shm.close()
        self.shm.unlink()
        return self.summary
