"""Hardware-in-the-loop world: the simulator and the synthetic camera in their own process, the virtual
transmitter box in another, running in real time.

* The box (``vehicles.virtual_box.VirtualCarBox``) sits behind a :class:`SerialRelay` pty that the
  race loop's ``SerialCarLink`` opens like a USB serial port; the relay forwards the bytes and can
  corrupt them or vanish (fault injection). Box and relay run in their own process (:func:`box_main`),
  like the real box is its own hardware: in the world process their threads waited for the GIL behind
  the physics and the renderer, read late, and frames queued up in the pty were stamped with one
  receive time - a neutral frame followed by a driving one then had no duration at all.
* The box process sends every change of its output (accepted frame or failsafe, with the box's
  receive time) to the world process, which keeps a :class:`~vehicles.virtual_box.CommandHistory`
  of it (:class:`BoxMirror`).
* The simulator advances in 1 ms steps to each camera capture time with the commands the box had
  in effect at that moment (``commands_at``), so the loop's real latencies act on the cars.
* With ``link_protocol="buzzracer-fhss"`` the box is the BuzzRacer firmware's emulation: its output is
  pulse widths per modem id, which each simulated car's receiver (``WorldSpec.receivers``) turns into
  wheel angle and throttle; its debug text goes back through the relay to the link.
* Frames are rendered by ``sim.camera.SyntheticCamera`` at the camera rate and written to a shared
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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from race.commands import physical_command
from race.config import FaultSpec, lower_realtime_priority
from race.referee import Referee
from race.roster import two_car_roster
from race.world import WorldPacket, WorldSummary
from sim import Simulator
from sim.camera import CarAppearance, CarPose, SyntheticCamera, TrackDrawing, overhead_camera
from sim.camera_profile import CameraProfile, DelayedDelivery
from sim.natnet_emulator import MotiveEmulator
from sim.race import OFF_TRACK_ALLOWANCE_CAR_LENGTHS
from tracking.calibration import aruco_dictionary_id, load_fixed_markers
from tracking.camera import Frame
from tracking.mocap import MocapTransform, mocap_body
from vehicles import fhss
from vehicles.protocol import CAR_RECORD_LEN, CRC_LEN, HEADER_LEN, CarCommand
from vehicles.virtual_box import CommandHistory, VirtualCarBox

_MARKER_DATA = Path(__file__).resolve().parents[1] / "tracking" / "data"
# Surveyed fixed markers per track (the BuzzRacer layouts: on the 0.2 m floor border round their tiles).
FIXED_MARKERS = {"oval": _MARKER_DATA / "oval_fixed_markers.json",
                 **{f"buzzracer:{name}": _MARKER_DATA / f"buzzracer_{name}_fixed_markers.json"
                    for name in ("full", "small", "big", "easy")}}


@dataclass(frozen=True)
class MocapSpec:
    """HIL on motion capture (``race --hil --mocap``): the world streams the simulator's poses through a
    loopback Motive server (sim.natnet_emulator) instead of rendering camera frames."""

    rigid_body_ids: tuple[int, ...]        # roster order
    transform: MocapTransform               # mocap ground plane -> track (the emulator applies its inverse)
    port: int = 0                           # command port on 127.0.0.1 (0: a free one, reported at start)
    version: tuple[int, int] = (4, 1)       # NatNet version streamed (Motive 3.x)
    position_noise_m: float = 0.0002        # per-axis Gaussian noise of a rigid body's position
    yaw_noise_rad: float = 0.001
    body_height_m: float = 0.05             # rigid-body pivot above the floor


@dataclass(frozen=True)
class WorldSpec:
    track: object
    car: object                       # CarParams of every car
    start_states: np.ndarray          # (n, 6), roster order
    marker_ids: tuple[int, ...]
    radio_ids: tuple[int, ...]
    laps: int
    seed: int
    # the roster's names (roster order; default: the two-car race's)
    names: tuple[str, ...] = tuple(c.name for c in two_car_roster("mpc", 1.0, 1.0))
    finish: str = "first"             # race.setup.FINISHES: the race is decided at the first or the last finish
    fps: float = 60.0
    image_size: tuple[int, int] = (1280, 800)
    faults: tuple[FaultSpec, ...] = ()
    failsafe_timeout_s: float = 0.1
    physics_dt_s: float = 0.001
    # Lap/collision/track-limit checks every 10 ms instead of the simulator's 5 ms: the checks cost as
    # much as the physics in real time; at racing closing speeds (< 1 m/s) a car moves 1 cm between checks.
    check_dt_s: float = 0.01
    off_track_allowance_car_lengths: float = OFF_TRACK_ALLOWANCE_CAR_LENGTHS  # race.setup.RaceSetup's
    corrupt_byte_rate: float = 0.5    # serial_corrupt: fraction of bytes with one flipped bit
    slots: int = 8
    link_protocol: str = "rd3g"       # what the virtual box decodes (vehicles.link_protocols.PROTOCOLS)
    # buzzracer-fhss: the simulated cars' receivers (vehicles.fhss.ServoCalibration, one per car): which
    # modem id each listens to and how it turns pulses into wheel angle and throttle. Set-up faults for
    # `check --hil` are receivers that differ from the host's calibration (swapped ids, reversed throttle).
    receivers: tuple | None = None
    hidden_markers: tuple[int, ...] = ()   # car markers not drawn (covered or missing)
    covered_fixed_markers: tuple[int, ...] = ()  # fixed track markers not drawn
    camera_profile: CameraProfile = CameraProfile()  # --camera-profile (sim.camera_profile), seeded by `seed`
    mocap: MocapSpec | None = None    # stream poses over NatNet instead of camera frames


class SerialRelay:
    """A pty pair between the link and the box: bytes written to ``path`` are forwarded to the box's
    pty, with bit errors while ``corrupt`` is set. ``close()`` makes the device vanish: the link's
    next write fails with EIO, and the box, whose only writer the relay is, sees the host hang up."""

    def __init__(self, downstream_path: str, seed: int = 0, byte_error_rate: float = 0.5,
                 frame_len: int = HEADER_LEN + 2 * CAR_RECORD_LEN + CRC_LEN) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        # Read-write: the box's debug text comes back this way (to the link, dropped if it does not read).
        self._out = os.open(downstream_path, os.O_RDWR | os.O_NOCTTY)
        os.set_blocking(self._master, False)
        self._rng = np.random.default_rng(seed)
        self.byte_error_rate = float(byte_error_rate)
        # One frame (default: a two-car rd3g frame); a longer read means frames queued up while this
        # thread was not running.
        self.frame_len = frame_len
        self.corrupt = False
        self.bytes_forwarded = 0
        self.bytes_corrupted = 0
        self.reads = 0
        self.coalesced_reads = 0  # reads that carried more than one frame's worth: this thread fell behind
        self._wake_r, self._wake_w = os.pipe()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="SerialRelay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            readable, _, _ = select.select([self._master, self._out, self._wake_r], [], [])
            if self._wake_r in readable:
                return
            if self._out in readable:  # the box's text, up to the link
                try:
                    os.write(self._master, os.read(self._out, 4096))
                except BlockingIOError:
                    pass
                except OSError:
                    return
            if self._master not in readable:
                continue
            try:
                data = bytearray(os.read(self._master, 4096))
            except OSError:
                return
            if not data:
                return
            self.reads += 1
            if len(data) > self.frame_len:
                self.coalesced_reads += 1
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


FAILSAFE_CAUSES = {"corrupt": "corrupt serial stream", "hangup": "serial device closed by the host",
                   "read_error": "serial read failed"}


def failsafe_text(event) -> str:
    """The `box_failsafe` event text, `REASON: cause (last valid frame X ms before) - box commands all
    cars neutral`, REASON a vehicles.virtual_box.FailsafeReason (timeout, corrupt, hangup, read_error)."""
    cause = event.detail if event.reason == "timeout" else FAILSAFE_CAUSES[event.reason]
    since = ("no valid frame before" if event.last_valid_t is None
             else f"last valid frame {1e3 * (event.t - event.last_valid_t):.1f} ms before")
    return f"{event.reason}: {cause} ({since}) - box commands all cars neutral"


def box_main(conn, failsafe_timeout_s: float, seed: int, byte_error_rate: float, max_cars: int,
             protocol: str = "rd3g") -> None:
    """Box-process entry point: VirtualCarBox (driving ``max_cars`` cars) behind a SerialRelay. Messages to the world:
    ("ready", relay path), ("commands", t, {radio id: (steering, throttle)}), ("failsafe", FailsafeEvent),
    ("line_errors", n), ("injected", kind, t), ("summary", info); from the world: ("corrupt", on),
    ("vanish",), ("stop",). Times are time.monotonic() (shared by the processes of one machine)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us
    lower_realtime_priority(3)  # --rt-priority: hardware, above the world (5 below the loop)
    send_lock = threading.Lock()  # the box's reader thread and this thread both send

    def send(msg) -> None:
        with send_lock:
            try:
                conn.send(msg)
            except (BrokenPipeError, EOFError, OSError):
                pass

    box = VirtualCarBox(
        failsafe_timeout=failsafe_timeout_s, max_cars=max_cars, protocol=protocol,
        on_commands=lambda commands, t: send(("commands", t, {c: (v.steering, v.throttle) for c, v in commands.items()})),
        on_failsafe=lambda event: send(("failsafe", event)))
    relay = SerialRelay(box.path, seed=seed, byte_error_rate=byte_error_rate,
                        **({"frame_len": fhss.FRAME_LEN} if protocol == "buzzracer-fhss" else {}))
    send(("ready", relay.path))
    line_errors = 0
    try:
        while True:
            if conn.poll(0.02):  # injections and the line-error count (for the loop's serial hold) are not urgent
                msg = conn.recv()
                if msg[0] == "corrupt":
                    # Stamped before the switch: the relay thread may damage a read, and the box engage
                    # its failsafe on it, before this thread runs again.
                    t = time.monotonic()
                    relay.corrupt = msg[1]
                    send(("injected", "corrupt_on" if msg[1] else "corrupt_off", t))
                elif msg[0] == "vanish":
                    t = time.monotonic()
                    relay.close()
                    send(("injected", "vanish", t))
                elif msg[0] == "stop":
                    break
            stats = box.stats
            if stats.line_errors != line_errors:
                line_errors = stats.line_errors
                send(("line_errors", line_errors))
    except (EOFError, OSError):
        pass
    finally:
        relay.close()
        box.close()
    stats = box.stats
    send(("summary", {"frames_received": stats.frames_received, "failsafe_events": stats.failsafe_by_reason,
                      "corrupt": stats.decoder.corrupt, "truncated": stats.decoder.truncated,
                      "line_errors": stats.line_errors, "coalesced_reads": stats.coalesced_reads,
                      "relay_reads": relay.reads, "relay_coalesced_reads": relay.coalesced_reads}))


class BoxMirror:
    """World-process view of the box process: its output history (``commands_at``), failsafe events
    and counters, from the messages of :func:`box_main`. ``pump()`` reads what has arrived."""

    def __init__(self, conn, failsafe_timeout_s: float) -> None:
        self.conn = conn
        self.history = CommandHistory(failsafe_timeout_s)
        self.line_errors = 0
        self.failsafe_log: list = []          # vehicles.virtual_box.FailsafeEvent
        self.injected: list[tuple[str, float]] = []  # (kind, box time) not yet taken
        self.path: str | None = None
        self.summary: dict | None = None

    def pump(self, timeout: float = 0.0) -> None:
        while self.conn.poll(timeout):
            timeout = 0.0
            msg = self.conn.recv()
            kind = msg[0]
            if kind == "commands":
                self.history.append(msg[1], {c: CarCommand(s, th) for c, (s, th) in msg[2].items()})
            elif kind == "failsafe":
                self.failsafe_log.append(msg[1])
            elif kind == "line_errors":
                self.line_errors = msg[1]
            elif kind == "injected":
                self.injected.append((msg[1], msg[2]))
            elif kind == "ready":
                self.path = msg[1]
            elif kind == "summary":
                self.summary = msg[1]

    def commands_at(self, t: float):
        return self.history.commands_at(t)

    def send(self, *msg) -> None:
        try:
            self.conn.send(msg)
        except (BrokenPipeError, EOFError, OSError):
            pass

    def stop(self, timeout: float = 5.0) -> dict | None:
        self.send("stop")
        deadline = time.monotonic() + timeout
        while self.summary is None and time.monotonic() < deadline:
            try:
                self.pump(min(0.1, max(0.0, deadline - time.monotonic())))
            except (EOFError, OSError):
                break
        return self.summary


def make_camera(spec: WorldSpec):
    """The synthetic overhead camera of the track's arena (and its fixed markers, if the track has a
    fixed-marker file)."""
    track = spec.track
    arena = track.arena
    bounds = (arena.x_min, arena.y_min, arena.x_max, arena.y_max) if arena else (0.0, 0.0, 5.0, 3.0)
    profile = spec.camera_profile.with_seed(spec.seed)
    camera = overhead_camera(bounds, image_size=spec.image_size, dist_coeffs=np.array(profile.dist_coeffs))
    left, right = track.boundaries(0.01)
    fixed_path = FIXED_MARKERS.get(track.name)
    marker_set = load_fixed_markers(fixed_path) if fixed_path else None
    dictionary = spec.car.marker.dictionary  # the car file's; the fixed markers must be printed from the same
    if marker_set is not None and marker_set.dictionary != dictionary:
        raise ValueError(f"car file marker.dictionary {dictionary} differs from {fixed_path}'s dictionary "
                         f"{marker_set.dictionary}: the tracker reads one dictionary")
    fixed = [m for m in (marker_set.markers.values() if marker_set else []) if m.marker_id not in spec.covered_fixed_markers]
    mk = spec.car.marker
    appearance = CarAppearance(roof_height_m=mk.height_m, marker_size_m=mk.size_m, marker_offset_m=mk.offset_forward_m,
                               marker_offset_left_m=mk.offset_left_m, marker_yaw_rad=mk.yaw_rad)
    synth = SyntheticCamera(camera, TrackDrawing(left, right, arena_bounds=bounds), fixed, car=appearance,
                            effects=profile.effects, dictionary=aruco_dictionary_id(dictionary),
                            fps=spec.fps)
    return synth, camera, fixed_path, appearance


def world_main(spec: WorldSpec, conn, shm_name: str, box_conn) -> None:
    """Child-process entry point. Messages to the parent: ("ready", info), ("frame", info),
    ("summary", info); from the parent: ("go", t_go), ("stop",)."""
    import signal
    from multiprocessing import shared_memory

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us; Ctrl-C goes to the parent

    lower_realtime_priority(5)  # --rt-priority: the world (camera, cars) just below the loop
    import sys

    sys.setswitchinterval(0.001)  # physics, renderer and box threads share the GIL at a fine grain
    import cv2

    # One OpenCV thread: its parallel loops cut a frame's render time (5.0 vs 6.3 ms alone) but cost
    # 60 % more CPU (8.9 vs 5.5 ms per frame), which the loop and planners on the other core need.
    cv2.setNumThreads(1)
    try:
        _World(spec, conn, shared_memory.SharedMemory(name=shm_name), box_conn).run()
    except Exception as exc:  # report, so the parent can stop the race with a clear message
        import traceback

        conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))


class _World:
    def __init__(self, spec: WorldSpec, conn, shm, box_conn) -> None:
        self.spec, self.conn, self.shm = spec, conn, shm
        self.CarPose = CarPose
        n = len(spec.names)
        w, h = spec.image_size
        self.frames = np.ndarray((spec.slots, h, w), dtype=np.uint8, buffer=shm.buf)
        self.sim = Simulator(spec.track, [spec.car] * n, seed=spec.seed, physics_dt=spec.physics_dt_s,
                             laps_to_win=spec.laps, check_dt=spec.check_dt_s,
                             off_track_allowance_car_lengths=spec.off_track_allowance_car_lengths)
        self.sim.reset(np.asarray(spec.start_states, dtype=float))
        self.box = BoxMirror(box_conn, spec.failsafe_timeout_s)
        while self.box.path is None:
            if not box_conn.poll(30.0):
                raise RuntimeError("the virtual box process did not start")
            self.box.pump()
        self.synth, self.camera, self.fixed_path, self.appearance = make_camera(spec)
        self.emulator = (MotiveEmulator("127.0.0.1", spec.mocap.port, spec.mocap.version)
                         if spec.mocap is not None else None)
        self._mocap_rng = np.random.default_rng(spec.seed + 7)
        self._t_motive0 = time.monotonic()  # Motive's timestamps count from its start
        self.events: list[tuple] = []      # (race time, kind, text) not yet sent
        self.referee = Referee(spec.track, spec.car, spec.names)  # gap, collisions with fault, off-track
        self.neutral_at_box = True
        self.render_ms: list[float] = []
        # When the box's output for a car changed, as the simulated car got it: (t_abs, car, throttle,
        # steering rad); the loop matches these to its commands (command latency, RaceLoop.command_lag_ms).
        self.applied_changes: list[tuple[float, int, float, float]] = []
        self._last_applied = np.zeros((n, 2))
        self.dropped = 0
        self.rendered = 0
        self._fault_state: dict[int, bool] = {}
        self._last_corrupt = 0
        self._failsafe_seen = 0
        self.t_go: float | None = None
        # Rendering runs in its own thread: OpenCV releases the GIL, so it overlaps the physics.
        self._render_cv = threading.Condition()
        self._pending: dict | None = None
        self._stop_render = False
        self._send_lock = threading.Lock()  # the render thread and the main thread both send to the parent
        self._reported_corrupt = 0
        self._delivery = DelayedDelivery(spec.camera_profile, self._send_frame)  # the camera's delivery latency
        self._render_thread = threading.Thread(target=self._render_loop, name="render", daemon=True)
        self._render_thread.start()

    # ---- helpers
    def _commands(self, t_abs: float) -> np.ndarray:
        """(throttle, wheel angle rad) per car: the box's output through each car's receiver."""
        cmds = self.box.commands_at(t_abs)
        out = np.zeros((len(self.spec.names), 2))
        if self.spec.receivers is not None:  # FHSS: pulses, through the car's own calibration
            for i, cal in enumerate(self.spec.receivers):
                c = cmds.get(cal.modem_id)
                if c is not None:
                    out[i] = (cal.throttle(fhss.unit_to_pulse(c.throttle)),
                              cal.steering_rad(fhss.unit_to_pulse(c.steering)))
            return out
        for i, rid in enumerate(self.spec.radio_ids):
            c = cmds.get(rid)
            if c is not None:
                out[i] = physical_command(self.spec.car, c)
        return out

    def _poses(self, states: np.ndarray, t_race: float | None) -> list:
        poses = []
        for i, state in enumerate(states):
            hidden = self.spec.marker_ids[i] in self.spec.hidden_markers or t_race is not None and any(
                f.kind == "occlude" and f.active(t_race) and f.applies_to(self.spec.names[i]) for f in self.spec.faults)
            if hidden:  # the marker is covered: the car is not drawn at all
                continue
            speed = math.hypot(state[3], state[4])
            poses.append(self.CarPose(self.spec.marker_ids[i], float(state[0]), float(state[1]), float(state[2]),
                                      speed, float(state[5])))
        return poses

    def _snapshot(self, index: int, t_cap: float, t_race: float | None) -> None:
        """Hand the current world state to the render thread; an unrendered older one is dropped
        (its events move to this one)."""
        box = self.box
        status = self.sim.race_status()
        snap = {"index": index, "slot": index % self.spec.slots, "t_capture": t_cap, "t_race": t_race,
                "truth": self.sim.states, "dropped": 0,
                "box_corrupt": box.line_errors, "box_failsafe_events": len(box.failsafe_log),
                "winner": self._decided(status)}
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

    def _decided(self, status) -> str | None:
        """The winner once the race is decided (WorldSpec.finish: at the first finish or the last)."""
        if status.winner is None or (self.spec.finish == "all" and len(status.finish_order) < len(self.spec.names)):
            return None
        return self.spec.names[status.winner]

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
            if self.emulator is not None:
                self._stream_mocap(snap)
            else:
                frame = self.synth.render(self._poses(snap["truth"], snap["t_race"]), snap["t_capture"])
                self.frames[snap["slot"]] = frame.image
            snap["render_ms"] = 1e3 * (time.perf_counter() - t0)
            self.render_ms.append(snap["render_ms"])
            self.rendered += 1
            self._delivery.submit(snap["t_capture"], snap)

    def _stream_mocap(self, snap: dict) -> None:
        """The snapshot's true poses as a NatNet frame (frame number = snapshot index, timestamp = its
        capture time on Motive's clock); an occluded car's rigid body is sent untracked, as Motive does."""
        m = self.spec.mocap
        snap["slot"] = None  # no image
        bodies = []
        for i, state in enumerate(snap["truth"]):
            hidden = snap["t_race"] is not None and any(
                f.kind == "occlude" and f.active(snap["t_race"]) and f.applies_to(self.spec.names[i]) for f in self.spec.faults)
            u, v, yaw = m.transform.to_mocap(float(state[0]), float(state[1]), float(state[2]))
            du, dv = self._mocap_rng.normal(0.0, m.position_noise_m, 2)
            body = mocap_body(u + du, v + dv, yaw + self._mocap_rng.normal(0.0, m.yaw_noise_rad), m.body_height_m,
                              m.transform.up_axis)
            bodies.append((m.rigid_body_ids[i], body.position, body.rotation, not hidden, m.position_noise_m))
        self.emulator.send_frame(snap["index"], snap["t_capture"] - self._t_motive0, bodies)

    def _send_frame(self, t_stamp: float, snap: dict) -> None:
        """A frame as the loop receives it: stamped with its delivery time less the latency the loop knows
        (the true exposure time with the ideal camera)."""
        snap["t_capture"] = t_stamp
        with self._send_lock:
            self.conn.send(("frame", snap))

    def _apply_faults(self, t_race: float) -> None:
        """Faults due by race time ``t_race``. Serial faults are injected by the box process, which
        reports the moment (box clock, the time base of its failsafe events); see _box_events."""
        for n, f in enumerate(self.spec.faults):
            if f.kind == "serial_corrupt":
                on = f.active(t_race)
                if on != self._fault_state.get(n, False):
                    self.box.send("corrupt", on)
                self._fault_state[n] = on
            elif f.kind == "serial_vanish" and t_race >= f.start_s and not self._fault_state.get(n):
                self._fault_state[n] = True
                self.box.send("vanish")
            elif f.kind == "mocap_stall" and self.emulator is not None:
                on = f.active(t_race)
                if on != self._fault_state.get(n, False):
                    (self.emulator.stall if on else self.emulator.resume)()
                    self.events.append((t_race, "fault_injected", f"mocap stream {'stalled' if on else 'resumed'}"))
                self._fault_state[n] = on
            elif f.kind == "mocap_down" and self.emulator is not None and t_race >= f.start_s \
                    and not self._fault_state.get(n):
                self._fault_state[n] = True
                self.emulator.close()
                self.events.append((t_race, "fault_injected", "mocap server gone"))
            elif f.kind == "occlude":
                on = f.active(t_race)
                if on != self._fault_state.get(n, False):
                    self.events.append((t_race, "fault_injected", f"markers of {f.car or 'all cars'} "
                                                                  f"{'occluded' if on else 'visible again'}"))
                self._fault_state[n] = on

    def _box_events(self, t_race: float) -> None:
        box = self.box
        box.pump()
        for kind, t in box.injected:
            text = {"corrupt_on": "serial_corrupt on", "corrupt_off": "serial_corrupt off",
                    "vanish": "serial device vanished"}[kind]
            self.events.append((t - self.t_go, "fault_injected", text))
        box.injected.clear()
        if box.line_errors > self._last_corrupt:
            self.events.append((t_race, "serial_corrupt",
                                f"box rejected damaged bytes in {box.line_errors - self._last_corrupt} read(s)"))
            self._last_corrupt = box.line_errors
        for ev in box.failsafe_log[self._failsafe_seen:]:
            # At the box's own time: the failsafe acts between the simulator's frames.
            self.events.append((ev.t - self.t_go, "box_failsafe", failsafe_text(ev)))
        self._failsafe_seen = len(box.failsafe_log)

    def _advance(self, t_go: float, target: float) -> None:
        dt = self.spec.physics_dt_s
        sim = self.sim
        while sim.time < target - 1e-9:
            t_abs = t_go + sim.time
            cmds = self._commands(t_abs)
            changed = np.any(cmds != self._last_applied, axis=1)
            if changed.any():  # the box's output changed: record it; only then can "neutral" change
                for i in np.nonzero(changed)[0]:
                    self.applied_changes.append((t_abs, int(i), float(cmds[i, 0]), float(cmds[i, 1])))
                self._last_applied = cmds
                neutral = not np.any(cmds)
                if neutral != self.neutral_at_box:
                    self.events.append((sim.time, "cars_neutral" if neutral else "cars_driving",
                                        "every car neutral at the box" if neutral else "commands reach the cars"))
                    self.neutral_at_box = neutral
            for ev in sim.step(cmds, dt):
                entry = self.referee.sim_event(ev, sim.states)
                if entry is not None:
                    self.events.append((ev.time, *entry))

    # ---- main loop
    def run(self) -> None:
        spec = self.spec
        period = 1.0 / spec.fps
        self.conn.send(("ready", {"serial_path": self.box.path, "camera": self.camera,
                                  "fixed_markers": str(self.fixed_path) if self.fixed_path else None,
                                  "marker_size_m": self.appearance.marker_size_m,
                                  "marker_height_m": self.appearance.roof_height_m,
                                  "mocap_port": self.emulator.port if self.emulator is not None else None}))
        index = 0
        t_go = None
        k = 0
        next_grid = time.monotonic()
        while True:
            while self.conn.poll():
                msg = self.conn.recv()
                if msg[0] == "go":
                    t_go = self.t_go = msg[1]
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
            self.box.pump()  # everything the box did until now, before the physics catches up to now
            if self.box.line_errors > self._reported_corrupt:
                # Rejected bytes at the box reach the loop now, not with the next rendered frame (which
                # is up to a frame period plus a render later): the loop holds the cars on this report.
                self._reported_corrupt = self.box.line_errors
                with self._send_lock:
                    self.conn.send(("box", {"box_corrupt": self.box.line_errors}))
            self._advance(t_go, sim_target)
            self._box_events(self.sim.time)
            self.referee.observe(self.sim.time, self.sim.states)
            self._snapshot(index, t_go + self.sim.time, self.sim.time)
            index += 1
            k += 1

    def _finish(self) -> None:
        with self._render_cv:
            self._stop_render = True
            self._render_cv.notify()
        self._render_thread.join(timeout=2.0)
        self._delivery.close()
        if self.emulator is not None:
            self.emulator.close()
        status = self.sim.race_status()
        box_summary = self.box.stop()
        if self.t_go is not None:
            self._box_events(self.sim.time)  # failsafe events of the last moments (e.g. the final hang-up)
        names = self.spec.names
        order = [names[i] for i in status.finish_order]
        lap_times = {name: list(status.lap_times[i]) for i, name in enumerate(names)}
        summary = WorldSummary(
            winner=None if status.winner is None else names[status.winner],
            lap_times_s=lap_times, finish_order=order, results=self.referee.results(order, lap_times, self.spec.laps),
            min_gap_m=float(self.referee.min_gap_m), collisions=list(self.referee.collisions),
            race_time_s=self.sim.time,
            off_track={name: int(status.off_track_count[i]) for i, name in enumerate(names)},
            frames_rendered=self.rendered, frames_dropped=self.dropped,
            render_ms=np.array(self.render_ms, dtype=np.float32),
            applied_changes=self.applied_changes,
            box=box_summary,
            events=(self._pending["events"] if self._pending else []) + self.events,
        )
        self.conn.send(("summary", summary))
        self.shm.close()


# --------------------------------------------------------------------------- parent side
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
        box_world_end, box_end = ctx.Pipe()  # the world talks to the box directly
        self.box_process = ctx.Process(target=box_main, name="hil-box", daemon=True,
                                       args=(box_end, spec.failsafe_timeout_s, spec.seed, spec.corrupt_byte_rate,
                                             len(spec.radio_ids), spec.link_protocol))
        self.box_process.start()
        self.process = ctx.Process(target=world_main, args=(spec, child, self.shm.name, box_world_end),
                                   name="hil-world", daemon=True)
        self.process.start()
        for end in (child, box_world_end, box_end):
            end.close()
        self.summary: WorldSummary | None = None
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
        packet = WorldPacket()
        newest = None
        while self.conn.poll(timeout):
            timeout = 0.0
            kind, info = self.conn.recv()
            if kind == "error":
                raise RuntimeError(f"HIL world process failed: {info}")
            if kind == "box":  # the box's report, ahead of the frame that will carry it too
                packet.box_corrupt = max(packet.box_corrupt, info["box_corrupt"])
                continue
            if kind != "frame":
                continue
            packet.events.extend(info["events"])
            packet.render_ms.append(info["render_ms"])
            packet.winner = info["winner"] or packet.winner
            packet.box_corrupt = max(packet.box_corrupt, info["box_corrupt"])
            packet.box_failsafe_events = info["box_failsafe_events"]
            packet.dropped = info["dropped"]
            packet.truths.append((info["index"], info["truth"], info["t_race"]))
            newest = info
        if newest is not None:
            if newest["slot"] is not None:  # None: HIL on mocap, the poses went out over NatNet
                image = self.frames[newest["slot"]].copy()  # the slot is rewritten 'slots' frames later
                packet.frame = Frame(image, newest["t_capture"], newest["index"])
            packet.truth = newest["truth"]
            packet.t_race = newest["t_race"]
            packet.t_truth = newest["t_capture"]
        return packet

    def observe(self, t_race: float, states: dict) -> WorldPacket:
        """Nothing to add: the world process judges the race on its true states (race.world.World)."""
        return WorldPacket()

    def close(self) -> WorldSummary | None:
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
        for process in (self.process, self.box_process):
            process.join(timeout=5.0)
            if process.is_alive():
                process.terminate()
                process.join(timeout=2.0)
        self.conn.close()
        self.shm.close()
        self.shm.unlink()
        return self.summary
