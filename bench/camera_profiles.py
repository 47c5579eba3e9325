"""What each imperfection of the realistic camera costs the tracker: ``python -m app bench camera-profiles``.

Two cars drive the oval's centre line at race speeds (2.0 and 1.6 m/s, turn rate from the curvature);
each camera profile (sim/camera_profile.py: ideal, every realistic effect alone, all of them) renders
their frames through the HIL world's camera; the tracker gets what the HIL race loop gets (the camera pose
calibrated from the first frame's fixed markers, with the profile's estimated lens) and its raw detections
are compared with the truth at the time the frame is stamped with (delivery time less the latency the loop
knows). The search is the race loop's (``--search loop``: race.perception.Perception's regions around the
estimator's predictions, a full-frame search every 6th frame while a car is lost) or a full-frame search of
every frame without predictions (``--search full``). Two rows print the car markers on labels with a 5 mm
white margin instead of 8 mm; a last row glues the marker 4 mm ahead, 2 mm left and 1.5 degrees off without
telling the tracker (the car file's marker.offset_forward_m/offset_left_m/yaw_rad left at 0). Deterministic
except the ms per frame (CPU time of detection and estimation, ``time.process_time``).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench.report import write_section
from race.config import LoopConfig
from race.perception import Perception
from race.world import WorldPacket
from sim.camera import CarAppearance, CarPose, SyntheticCamera, TrackDrawing, overhead_camera
from sim.camera_profile import SINGLE_EFFECTS, DeliveryClock, camera_profile
from tracking.calibration import load_fixed_markers
from tracking.estimator import MultiCarEstimator
from tracking.markers import ArucoTracker
from tracks import load_track
from tracks.geometry import wrap_angle

FIXED = Path(__file__).resolve().parents[1] / "tracking" / "data" / "oval_fixed_markers.json"
GLUED = dict(marker_offset_m=0.004, marker_offset_left_m=0.002, marker_yaw_rad=math.radians(1.5))
NARROW_MARGIN_M = 0.005  # white label margin of the narrow-label rows (CarAppearance's default: 8 mm)
SEARCHES = ("loop", "full")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `python -m app bench camera-profiles`."""
    parser.add_argument("--frames", type=int, default=300, help="frames per profile at 60 fps (default 300)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--search", choices=SEARCHES, default="loop",
                        help="loop: the race loop's search around the estimator's predictions (default); full: a "
                             "full-frame search of every frame")
    parser.add_argument("--no-docs", action="store_true", help="print only; do not update docs/tracking.md")


@dataclass(frozen=True)
class _Car:  # what Perception needs of a race car (race.loop.CarBinding)
    name: str
    marker_id: int


class _KeepLast:
    """The tracker, keeping its last frame's detections (every id it reported, ours or not)."""

    def __init__(self, tracker: ArucoTracker):
        self.tracker, self.last = tracker, None

    def process(self, frame, predictions=None):
        self.last = self.tracker.process(frame, predictions)
        return self.last


def measure(profile_name: str, frames: int, seed: int, glued: bool = False, search: str = "loop",
            label_margin_m: float | None = None) -> dict:
    """Raw detection errors of one profile: position (mm) and heading (deg) median/p95, detection rate,
    wrong ids and CPU ms per frame."""
    track = load_track("oval")
    left, right = track.boundaries(0.01)
    fixed = load_fixed_markers(FIXED)
    profile = camera_profile(profile_name, seed)
    camera = overhead_camera(image_size=(1280, 800), dist_coeffs=np.array(profile.dist_coeffs))
    car = CarAppearance(**(GLUED if glued else {}),
                        **({} if label_margin_m is None else {"label_margin_m": label_margin_m}))
    speeds = (2.0, 1.6)

    def world(t):
        poses = []
        for i, v in enumerate(speeds):
            s = (v * t + i * track.length / 2) % track.length
            x, y = track.position(s)
            poses.append(CarPose(i, float(x), float(y), float(track.heading(s)), v, v * float(track.curvature(s))))
        return poses

    synth = SyntheticCamera(camera, TrackDrawing(left, right), list(fixed.markers.values()), car=car,
                            effects=profile.effects, world=world, fps=60.0)
    calibration = profile.lab_calibration(camera, synth.render([], -1.0).image, fixed)
    ids = list(range(len(speeds)))
    tracker = ArucoTracker(calibration, car.marker_size_m, car.roof_height_m, car_ids=ids, fixed_ids=fixed.markers,
                           full_search_every=1 if search == "full" else 10 ** 9)
    kept = _KeepLast(tracker)
    perception = Perception(kept, MultiCarEstimator(), [_Car(f"car{i}", i) for i in ids], LoopConfig().lost_search_every)
    for k in range(-3, 0):  # acquisition before the measured frames, as the race loop's before its start
        perception.acquire(WorldPacket(synth.render(world(k / 60.0), k / 60.0)))
    clock = DeliveryClock(profile)
    pos, head, missed, wrong, cpu = [], [], 0, 0, 0.0
    for _ in range(frames):
        frame = synth.read()
        stamp = clock.stamp(clock.delivery_time(frame.t_capture_s))
        frame = dataclasses.replace(frame, t_capture_s=stamp)
        start = time.process_time()
        if search == "full":
            cars = tracker.process(frame).cars
        else:
            kept.last = None
            perception.perceive(WorldPacket(frame), stamp, stamp)
            cars = {} if kept.last is None else kept.last.cars  # None: every car lost, no full search due
        cpu += time.process_time() - start
        wrong += sum(1 for i in cars if i not in ids)
        for p in world(stamp):
            m = cars.get(p.marker_id)
            if m is None:
                missed += 1
                continue
            pos.append(1e3 * math.hypot(m.x - p.x, m.y - p.y))
            head.append(abs(math.degrees(wrap_angle(m.heading - p.heading))))
    pos, head = np.array(pos), np.array(head)
    name = profile_name + ("" if label_margin_m is None else f", {1e3 * label_margin_m:g} mm label margin")
    return {"profile": name + (" + marker glued off, car file not told" if glued else ""),
            "pos_median_mm": float(np.median(pos)), "pos_p95_mm": float(np.percentile(pos, 95)),
            "heading_median_deg": float(np.median(head)), "heading_p95_deg": float(np.percentile(head, 95)),
            "detected": 1.0 - missed / (frames * len(speeds)), "wrong_ids": wrong, "ms_per_frame": 1e3 * cpu / frames}


def run(args) -> int:
    """Measures every profile; ValueError names a bad option."""
    if args.frames < 1:
        raise ValueError(f"--frames: need at least 1, got {args.frames}")
    cases = [(n, {}) for n in ["ideal", *(f"ideal+{e}" for e in SINGLE_EFFECTS), "realistic"]]
    cases += [("ideal", {"label_margin_m": NARROW_MARGIN_M}), ("realistic", {"label_margin_m": NARROW_MARGIN_M}),
              ("realistic", {"glued": True})]
    rows = [measure(n, args.frames, args.seed, search=args.search, **kw) for n, kw in tqdm(cases, desc="camera profiles")]
    search = ("the race loop's search around the estimator's predictions" if args.search == "loop"
              else "a full-frame search of every frame")
    lines = [f"Command: `python -m app bench camera-profiles --frames {args.frames} --seed {args.seed} --search "
             f"{args.search}` (two cars on the oval's centre line at 2.0 and 1.6 m/s, 1280x800 at 60 fps; {search}; raw "
             "detections against the truth at each frame's stamp; deterministic except ms per frame, the CPU time of "
             "detection and estimation for both cars).", "",
             "| camera profile | position median / p95 mm | heading median / p95 deg | detected | wrong ids | ms per frame |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['profile']} | {r['pos_median_mm']:.2f} / {r['pos_p95_mm']:.2f} | "
                     f"{r['heading_median_deg']:.2f} / {r['heading_p95_deg']:.2f} | {100 * r['detected']:.1f} % | "
                     f"{r['wrong_ids']} | {r['ms_per_frame']:.1f} |")
    body = "\n".join(lines)
    print(body)
    if not args.no_docs:
        write_section(f"camera-profiles-{args.search}", body, Path("docs/tracking.md"))
    return 0
