"""A rendered video of cars on known trajectories, tracked by `python -m app track`'s pipeline
(race.video_tracking): ``python -m app bench track-video [--frames 600] [--fps 60] [--out runs/track]
[--camera-profile ideal|realistic]``.

Renders the synthetic overhead camera (sim.camera, the HIL race's, through the camera profile's lens and
effects, sim.camera_profile) at 1280x800 over the oval with its surveyed fixed markers: car 3 at 2.0 m/s
and car 7 at 1.6 m/s along the centre line (car 7's marker hidden over ``HIDDEN_S``). It writes the frames
as MJPG .avi (cv2.VideoWriter), the true poses (CSV) and the calibration a lab would make of that camera:
the profile's intrinsics (true, or calibrate-camera's estimate from rendered board views) and the camera
pose from `calibrate` on the clip's first frame with the fixed markers as the profile surveys them. Then
it tracks the video and prints the tracking speed (frames/s, against real time) and the position and
heading errors against the truth. Timings are the machine's at the time: state its load.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from race.video_tracking import TrackedCar, track_video
from sim.camera import CarAppearance, CarPose, SyntheticCamera, TrackDrawing, overhead_camera
from sim.camera_profile import PROFILE_NAMES, CameraProfile, camera_profile
from tracking.calibration import CameraCalibration, load_fixed_markers, save_calibration
from tracking.camera import ReadAhead, VideoFileCamera
from tracking.estimator import MultiCarEstimator
from tracking.markers import ArucoTracker
from tracks import load_track
from tracks.geometry import wrap_angle

CARS = {3: (2.0, 0.0), 7: (1.6, 0.5)}  # marker id -> (speed m/s, start as a fraction of the lap)
HIDDEN_S = {7: (0.5, 0.7)}              # marker id -> [start, end) s in which its marker is not drawn
APPEARANCE = CarAppearance()           # the buzzracer car file's marker: 55 mm, 45 mm above the floor
FIXED = Path(__file__).resolve().parents[1] / "tracking" / "data" / "oval_fixed_markers.json"


@dataclass
class Clip:
    truth: dict[int, np.ndarray]   # marker id -> (frames, 4): t, x, y, heading (nan while hidden)
    calibration: Path
    camera: object                 # the rendering camera (true intrinsics, lens and pose)
    tracker_calibration: CameraCalibration  # what the tracker is told (written to ``calibration``)


def _poses(track, t: float) -> list[CarPose]:
    poses = []
    for marker, (speed, start) in CARS.items():
        s = (start * track.length + speed * t) % track.length
        x, y = track.position(s)
        poses.append(CarPose(marker, float(x), float(y), float(track.heading(s)), speed,
                             speed * float(track.curvature(s))))
    return poses


def render_clip(out: Path, frames: int, fps: float = 60.0, image_size=(1280, 800),
                profile: CameraProfile | None = None, folder: Path | None = None) -> Clip:
    """``out``: the .avi (MJPG) to write; ``folder``: also every frame as PNG there; ``profile``: the
    camera profile (default ideal, seed 0). The calibration a lab would make (module doc) is written
    beside ``out``."""
    profile = profile if profile is not None else camera_profile("ideal")
    track = load_track("oval")
    left, right = track.boundaries(0.01)
    fixed = load_fixed_markers(FIXED)
    camera = overhead_camera(image_size=image_size, dist_coeffs=np.array(profile.dist_coeffs))
    synth = SyntheticCamera(camera, TrackDrawing(left, right), list(fixed.markers.values()), car=APPEARANCE,
                            effects=profile.effects, fps=fps)
    calibration = profile.lab_calibration(camera, synth.render([], 0.0).image, fixed)
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"MJPG"), fps, image_size, isColor=False)
    if not writer.isOpened():
        raise RuntimeError(f"cv2.VideoWriter cannot write {out}")
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
    truth = {m: np.full((frames, 4), np.nan) for m in CARS}
    for k in range(frames):
        t = k / fps
        poses = []
        for p in _poses(track, t):
            truth[p.marker_id][k] = (t, p.x, p.y, p.heading)
            lo, hi = HIDDEN_S.get(p.marker_id, (math.inf, math.inf))
            if lo <= t < hi:
                truth[p.marker_id][k, 1:] = np.nan
            else:
                poses.append(p)
        image = synth.render(poses, t).image
        writer.write(image)
        if folder is not None:
            cv2.imwrite(str(folder / f"frame_{k:05d}.png"), image)
    writer.release()
    path = out.with_name(out.stem + "_calibration.json")
    save_calibration(path, calibration)
    return Clip(truth, path, camera, calibration)


def errors(rows: np.ndarray, truth: dict[int, np.ndarray], fps: float) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per car: position error (m) and absolute heading error (rad) of each row against the truth at
    the row's frame (rows at t = frame index / fps)."""
    out = {}
    for marker, tr in truth.items():
        mine = rows[rows[:, 1] == marker]
        k = np.rint(mine[:, 0] * fps).astype(int)
        ref = tr[k]
        out[marker] = (np.hypot(mine[:, 2] - ref[:, 1], mine[:, 3] - ref[:, 2]),
                       np.abs(wrap_angle(mine[:, 4] - ref[:, 3])))
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `python -m app bench track-video`."""
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--out", default="runs/track", help="folder for the clip, its calibration and truth.csv")
    parser.add_argument("--raw", action="store_true", help="detections without the estimator")
    parser.add_argument("--camera-profile", default="ideal", choices=PROFILE_NAMES,
                        help="the rendering camera's profile (sim/camera_profile.py; default ideal)")


def run(args) -> int:
    video = Path(args.out) / "clip.avi"
    clip = render_clip(video, args.frames, args.fps, profile=camera_profile(args.camera_profile))
    with open(Path(args.out) / "truth.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "car", "x", "y", "heading"])
        for marker, tr in clip.truth.items():
            for t, x, y, h in tr[np.isfinite(tr[:, 1])].tolist():
                w.writerow([f"{t:.6f}", marker, f"{x:.6f}", f"{y:.6f}", f"{h:.6f}"])
    tracker = ArucoTracker(clip.tracker_calibration, APPEARANCE.marker_size_m, APPEARANCE.roof_height_m,
                           car_ids=list(CARS), full_search_every=10 ** 9)
    source = ReadAhead(VideoFileCamera(video, clock="container", grey=True))  # as python -m app track
    load = os.getloadavg()[0]
    start, cpu = time.perf_counter(), time.process_time()
    result = track_video(source, tracker, [TrackedCar(m) for m in CARS], None if args.raw else MultiCarEstimator())
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    source.close()
    rate = result.frames / elapsed
    print(f"{video}: {result.frames} frames {result.image_size[0]}x{result.image_size[1]} at {args.fps:g} fps, "
          f"{args.camera_profile} camera, {'raw' if args.raw else 'filtered'}: {rate:.1f} frames/s = {rate / args.fps:.2f}x real time "
          f"(load average {load:.2f} on {os.cpu_count()} cores); CPU time {1e3 * cpu / result.frames:.2f} ms per frame")
    px_mm = 1e3 * 3.0 / clip.camera.camera_matrix[0, 0]  # floor metres per pixel under the camera
    for marker, (pos, head) in errors(result.rows, clip.truth, args.fps).items():
        print(f"  car {marker}: {len(pos)} rows, not found in {result.missed[marker]} frames; position error "
              f"median {1e3 * np.median(pos):.2f} mm, p95 {1e3 * np.percentile(pos, 95):.2f} mm "
              f"(a pixel is ~{px_mm:.1f} mm); heading median {math.degrees(np.median(head)):.2f} deg, "
              f"p95 {math.degrees(np.percentile(head, 95)):.2f} deg")
    return 0
