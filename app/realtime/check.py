"""The pre-race hardware check (``python -m app check``, docs/race-stack.md "Pre-race check"): camera,
fixed markers and calibration, car markers, serial port, each car's radio (steering sweep, a short
throttle pulse), the box failsafe. Judgements are in tracking.checks; this module drives the hardware
(or the HIL world) and never leaves a car with a non-neutral command."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from tracking.checks import STILL_M, displacement, fixed_marker_fit, judge_throttle_pulse
from vehicles.protocol import NEUTRAL, CarCommand
from vehicles.serial_link import SerialLinkError

# Fixed-marker fit limits: a calibration that still fits reprojects within a couple of pixels
# (HIL: ~0.2 px) and maps corners back within a few mm; a bumped camera is off by far more.
MAX_REPROJECTION_PX = 2.0
MAX_REPROJECTION_MM = 5.0
MIN_RATE_FRACTION = 0.9      # camera: frames per second vs the expected rate


@dataclass(frozen=True)
class CheckItem:
    name: str
    ok: bool
    detail: str


@dataclass
class CheckTiming:
    """Durations (s) and levels of the active steps."""

    camera_s: float = 0.5
    sweep_step_s: float = 0.2        # each of full left, full right, straight
    throttle: float = 0.15           # the pulse's throttle (low: a few cm)
    pulse_s: float = 0.2
    settle_s: float = 0.5            # after neutral, before looking for the cars to stand still
    still_timeout_s: float = 3.0     # ... for at most this long (HIL: rolled out 0.65 s after the pulse)
    failsafe_window_s: float = 1.0   # sending stopped this long


class PreRaceCheck:
    """``feed.poll(timeout) -> WorldPacket`` (frames); ``tracker`` an ArucoTracker; ``cars``
    CarBindings; ``link`` a SerialCarLink not yet started (``start()`` is the serial check)."""

    def __init__(self, *, feed, tracker, track, cars, link, marker_set=None, expected_fps: float,
                 timing: CheckTiming | None = None, on_go=None, log=print, sensor: str = "camera",
                 car_target=None) -> None:
        self.feed, self.tracker, self.track, self.cars, self.link = feed, tracker, track, cars, link
        self.marker_set, self.expected_fps = marker_set, expected_fps
        self.timing = timing or CheckTiming()
        self.on_go = on_go          # HIL: start the world's physics before anything moves
        self.log = log
        # What finds the cars ("camera", or "mocap" for a motion-capture stream) and what it sees of each car.
        self.sensor = sensor
        self.car_target = car_target or (lambda c: f"marker {c.marker_id}")
        self.items: list[CheckItem] = []
        self._last_frame_index = -1

    def _add(self, name: str, ok: bool, detail: str) -> bool:
        item = CheckItem(name, ok, detail)
        self.items.append(item)
        self.log(f"[{'PASS' if ok else 'FAIL'}] {name}: {detail}")
        return ok

    # ------------------------------------------------------------------ frames
    def _next_frame(self, timeout: float = 2.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            packet = self.feed.poll(min(0.1, max(0.0, deadline - time.monotonic())))
            if packet.frame is not None and packet.frame.index != self._last_frame_index:
                self._last_frame_index = packet.frame.index
                return packet.frame
        return None

    def _poses(self, frames: int = 5) -> dict[str, tuple[float, float, float]]:
        """Median pose per car seen in ``frames`` new frames (cars never seen are absent)."""
        seen: dict[int, list[tuple[float, float, float]]] = {}
        for _ in range(frames):
            frame = self._next_frame()
            if frame is None:
                break
            for marker_id, m in self.tracker.process(frame).cars.items():
                seen.setdefault(marker_id, []).append((m.x, m.y, m.heading))
        poses = {}
        for c in self.cars:
            if c.marker_id in seen:
                a = np.array(seen[c.marker_id])
                heading = math.atan2(np.median(np.sin(a[:, 2])), np.median(np.cos(a[:, 2])))
                poses[c.name] = (float(np.median(a[:, 0])), float(np.median(a[:, 1])), heading)
        return poses

    def _still_poses(self) -> dict[str, tuple[float, float, float]]:
        """Poses once no visible car moves by more than a millimetre between two measurements (a car
        still rolling out after a pulse, or a slow host that held a pulse longer), or after
        ``still_timeout_s`` (the last poses then)."""
        end = time.monotonic() + self.timing.still_timeout_s
        previous = self._poses(3)
        while True:
            poses = self._poses(3)
            moving = [n for n in poses if n in previous and displacement(previous[n], poses[n]).distance_m > 0.001]
            if not moving or time.monotonic() > end:
                return poses
            previous = poses

    def _hold(self, commands: dict[int, CarCommand], seconds: float) -> None:
        """Send ``commands`` for ``seconds``, and for at least that many frames' worth: on a starved host
        the link's sender may not run for a while, and a pulse it never sent tests nothing. The sender
        skips missed ticks instead of bursting, so n frames span at least n - 1 periods at the box."""
        sent = self.link.stats.frames_sent
        self.link.set_commands(commands)
        start = time.monotonic()
        # +1: the first frame after set_commands may have been encoded before it
        frames = 0 if seconds <= 0 else sent + 1 + math.ceil(seconds * self.link.rate_hz)
        while True:
            now = time.monotonic()
            if now >= start + seconds and (self.link.stats.frames_sent >= frames or not self.link.running
                                           or now > start + seconds + 2.0):
                return
            self.feed.poll(0.005 if now >= start + seconds else min(0.05, start + seconds - now))  # drain frames

    # ------------------------------------------------------------------ steps
    def run(self) -> list[CheckItem]:
        try:
            self._camera()
            frame = self._next_frame()
            self._fixed_markers(frame)
            visible = self._car_markers()
            if self._serial():
                if self.on_go is not None:
                    self.on_go()
                movers = [c for c in self.cars if c.name in visible]
                passed = [c for c in movers if self._car_radio(c)]
                for c in self.cars:
                    if c.name not in visible:
                        self._add(f"radio {c.name}", False, f"not checked: its {self.car_target(c)} is not seen")
                self._failsafe(passed[0] if passed else None)
        except RuntimeError as exc:  # the feed's "the world failed" (a camera that stopped, a file that ended)
            self._add(self.sensor, False, f"{exc}; the remaining checks were not run")
        finally:
            self._all_neutral()
        return self.items

    def _camera(self) -> None:
        first = self._next_frame(5.0)
        if first is None:
            self._add(self.sensor, False, "no frame within 5 s")
            return
        end = time.monotonic() + self.timing.camera_s
        last = first
        while time.monotonic() < end:
            frame = self._next_frame(1.0)
            if frame is not None:
                last = frame
        span = last.t_capture_s - first.t_capture_s
        rate = (last.index - first.index) / span if span > 0 else 0.0
        self._add(self.sensor, rate >= MIN_RATE_FRACTION * self.expected_fps,
                  f"{rate:.1f} frames/s over {span:.2f} s (expected {self.expected_fps:g}, at least "
                  f"{MIN_RATE_FRACTION * self.expected_fps:.0f})")

    def _fixed_markers(self, frame) -> None:
        if self.sensor != "camera":
            self._add("fixed markers", True, f"not used by {self.sensor} (its transform is the mocap calibration file)")
            return
        if self.marker_set is None:
            self._add("fixed markers", True, "none surveyed for this track (calibration not re-checked)")
            return
        if frame is None:
            self._add("fixed markers", False, "no frame")
            return
        detected = self.tracker.detector.detect(frame.image)
        fit = fixed_marker_fit(self.tracker.calibration.camera, self.marker_set, detected)
        numbers = (f"{len(fit.seen)}/{len(self.marker_set.markers)} seen, reprojection rms {fit.rms_px:.2f} px, "
                   f"max {fit.max_px:.2f} px, max {fit.max_mm:.1f} mm")
        if fit.missing:
            self._add("fixed markers", False, f"{numbers}; fixed marker(s) {', '.join(map(str, fit.missing))} "
                                              f"not seen (covered, or the camera moved)")
        elif not (fit.max_px <= MAX_REPROJECTION_PX and fit.max_mm <= MAX_REPROJECTION_MM):
            self._add("fixed markers", False, f"{numbers}: the calibration no longer fits (limits "
                                              f"{MAX_REPROJECTION_PX} px, {MAX_REPROJECTION_MM} mm): recalibrate")
        else:
            self._add("fixed markers", True, numbers)

    def _car_markers(self) -> set[str]:
        poses = self._poses(10)
        visible = set()
        for c in self.cars:
            pose = poses.get(c.name)
            if pose is None:
                self._add(f"marker {c.name}", False, f"car {c.name}: {self.car_target(c)} not seen in 10 frames "
                                                     f"(covered, missing, or a wrong id)")
                continue
            s, ey = (float(v) for v in self.track.to_frenet(pose[0], pose[1])[:2])
            on = bool(self.track.is_inside(pose[0], pose[1]))
            self._add(f"marker {c.name}", on, f"car {c.name}: {self.car_target(c)} at ({pose[0]:.3f}, {pose[1]:.3f}) m, "
                                              f"heading {math.degrees(pose[2]):.0f} deg, s {s:.2f} m, ey {ey:+.3f} m"
                                              + ("" if on else ": off the track"))
            visible.add(c.name)
        return visible

    def _serial(self) -> bool:
        try:
            self.link.start()
        except SerialLinkError as exc:
            return self._add("serial", False, str(exc))
        return self._add("serial", True, f"{self.link.port} open, {self.link.encoder.name} at "
                                         f"{self.link.rate_hz:g} frames/s, {self.link.baudrate} baud")

    def _car_radio(self, car) -> bool:
        t = self.timing
        before = self._still_poses()
        for steering in (1.0, -1.0, 0.0):
            self._hold({car.radio_id: CarCommand(steering, 0.0)}, t.sweep_step_s)
        after = self._poses()
        if car.name not in before or car.name not in after:
            return self._add(f"radio {car.name}", False, f"car {car.name}: marker lost during the steering sweep")
        moved = {name: displacement(before[name], after[name]).distance_m for name in after if name in before}
        sweep_ok = all(d <= STILL_M for d in moved.values())
        self._add(f"steering {car.name}", sweep_ok,
                  f"sweep left/right/straight at zero throttle: " +
                  ", ".join(f"{name} moved {1e3 * d:.1f} mm" for name, d in moved.items())
                  + ("" if sweep_ok else f" (limit {1e3 * STILL_M:.0f} mm): a car rolled at zero throttle"))
        self._hold({car.radio_id: CarCommand(0.0, t.throttle)}, t.pulse_s)
        self._hold({car.radio_id: NEUTRAL}, t.settle_s)
        end = self._still_poses()
        if car.name not in end:
            return self._add(f"radio {car.name}", False, f"car {car.name}: marker lost after the throttle pulse")
        moves = {name: displacement(after[name], end[name]) for name in end if name in after}
        ok, text = judge_throttle_pulse(car.name, moves)
        return self._add(f"radio {car.name}", ok, f"throttle {t.throttle:g} for {1e3 * t.pulse_s:.0f} ms: {text}") \
            and sweep_ok

    def _failsafe(self, car) -> None:
        if car is None:
            self._add("failsafe", False, "not checked: no car passed its radio check")
            return
        t = self.timing
        before = self._still_poses()
        # A frame of a low throttle, then silence: the box must go neutral within its 100 ms. Two frames
        # counted after the command: the first may have been encoded before it.
        sent = self.link.stats.frames_sent
        self.link.set_commands({car.radio_id: CarCommand(0.0, t.throttle)})
        deadline = time.monotonic() + 1.0
        while self.link.stats.frames_sent < sent + 2 and time.monotonic() < deadline:
            time.sleep(0.001)
        self.link.pause_sending(True)
        t_stop = time.monotonic()
        try:
            self._hold({car.radio_id: NEUTRAL}, 0.0)  # what is sent when sending resumes
            while time.monotonic() < t_stop + t.failsafe_window_s:
                self.feed.poll(0.05)
            mid = self._poses()
            still_end = self._poses()
        finally:
            self.link.pause_sending(False)
            self.link.neutral()
        if car.name not in before or car.name not in mid or car.name not in still_end:
            self._add("failsafe", False, f"car {car.name}: marker lost during the failsafe test")
            return
        moved = displacement(before[car.name], mid[car.name]).distance_m
        rolling = displacement(mid[car.name], still_end[car.name]).distance_m
        # Without a failsafe the car keeps the throttle: in the 1 s window a BuzzRacer car at throttle 0.15
        # goes about 0.5 m and is still moving. With it, it drives for the failsafe's 100 ms (plus the
        # frames sent before the pause) and rolls out: 2-2.5 cm in HIL, 4 cm after 160 ms of throttle.
        limit = 0.10
        ok = STILL_M < moved <= limit and rolling <= STILL_M
        why = ("" if ok else ": the box kept driving it" if moved > limit or rolling > STILL_M
               else ": it never got the throttle frame, so the failsafe was not tested")
        self._add("failsafe", ok, f"sending stopped after a throttle {t.throttle:g} frame to {car.name}: it moved "
                                  f"{100 * moved:.1f} cm in {t.failsafe_window_s:g} s (expected {1e3 * STILL_M:.0f} mm "
                                  f"to {100 * limit:.0f} cm), then {1e3 * rolling:.1f} mm" + why)

    def _all_neutral(self) -> None:
        try:
            self.link.pause_sending(False)
            self.link.set_commands({c.radio_id: NEUTRAL for c in self.cars})
            self.link.neutral()
        except Exception:  # the link's stop() sends neutral again
            pass
