"""Time rendering and detection on synthetic frames: ``python -m app bench tracking``.

Prints median and 90th-percentile milliseconds per frame for the synthetic render, full-frame
detection, ROI detection around predicted positions, and the EKF update of all cars. Pose
errors against the rendered truth are printed alongside so a speed-up that breaks accuracy
shows. Timings, not assertions: the machine is shared.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from sim.camera import CarAppearance, CarPose, RenderEffects, SyntheticCamera, TrackDrawing, overhead_camera
from tracking.calibration import CameraCalibration, load_fixed_markers
from tracking.estimator import MultiCarEstimator
from tracking.markers import ArucoTracker
from tracks import load_track
from tracks.geometry import wrap_angle


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `python -m app bench tracking`."""
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--cars", type=int, default=4)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=800)
    parser.add_argument("--refine", choices=("ecc", "aruco"), default="ecc")


def run(args) -> int:
    track = load_track("oval")
    left, right = track.boundaries()
    fixed = load_fixed_markers(Path(__file__).resolve().parents[1] / "tracking" / "data" / "oval_fixed_markers.json")
    camera = overhead_camera(image_size=(args.width, args.height))
    car = CarAppearance()
    speed = 2.0

    def world(t):  # cars spread along the centre line at 2 m/s
        poses = []
        for i in range(args.cars):
            s = (speed * t + i * track.length / args.cars) % track.length
            x, y = track.position(s)
            poses.append(CarPose(i, float(x), float(y), float(track.heading(s)), speed, speed * float(track.curvature(s))))
        return poses

    synth = SyntheticCamera(camera, TrackDrawing(left, right), list(fixed.markers.values()), car=car,
                            effects=RenderEffects(), world=world, fps=60.0)
    tracker = ArucoTracker(CameraCalibration(camera), car.marker_size_m, car.roof_height_m,
                           fixed_ids=fixed.markers, refine=args.refine, full_search_every=10 ** 9)
    estimator = MultiCarEstimator()
    timings = {"render": [], "detect full frame": [], "detect ROI": [], "EKF update": []}
    errors, missed = [], 0
    for _ in range(args.frames):
        start = time.perf_counter()
        frame = synth.read()
        timings["render"].append(time.perf_counter() - start)
        truth = world(frame.t_capture_s)
        tracker._frames_since_full = 0
        full = tracker.process(frame)
        timings["detect full frame"].append(full.detect_time_s)
        predictions = {i: (s.x, s.y) for i, s in estimator.states_at(frame.t_capture_s).items()}
        det = tracker.process(frame, predictions) if predictions else full
        if predictions:
            timings["detect ROI"].append(det.detect_time_s)
        start = time.perf_counter()
        estimator.update(frame.t_capture_s, det.cars.values())
        timings["EKF update"].append(time.perf_counter() - start)
        for p in truth:
            m = det.cars.get(p.marker_id)
            if m is None:
                missed += 1
            else:
                errors.append((math.hypot(m.x - p.x, m.y - p.y), abs(math.degrees(wrap_angle(m.heading - p.heading)))))
    print(f"{args.width}x{args.height}, {args.cars} cars at {speed} m/s, {args.frames} frames, refine={args.refine}")
    for name, values in timings.items():
        if values:
            ms = np.array(values) * 1e3
            print(f"  {name:18s} median {np.median(ms):6.2f} ms   p90 {np.percentile(ms, 90):6.2f} ms")
    err = np.array(errors)
    print(f"  pose error: median {np.median(err[:, 0]) * 1e3:.2f} mm, max {err[:, 0].max() * 1e3:.2f} mm; "
          f"heading median {np.median(err[:, 1]):.2f} deg, max {err[:, 1].max():.2f} deg; "
          f"missed {missed}/{args.frames * args.cars}")
    return 0


if __name__ == "__main__":
    raise SystemExit("moved: python -m app bench tracking")
