"""Rendered frames with known geometry -> detection, pose and calibration checks.

References are independent of the code under test: poses and camera placed by the test,
the analytic parallax of a raised marker h*d/(H-h), and OpenCV's own projection.
"""
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from tracking.calibration import (CalibrationError, CameraCalibration, FixedMarkerSet, Intrinsics,
                                  calibrate_image, load_fixed_markers, parse_fixed_markers)
from tracking.camera import CameraError, EndOfStream, OpenCVCamera, VideoFileCamera
from sim.camera import CarAppearance, CarPose, RenderEffects, SyntheticCamera, TrackDrawing, overhead_camera
from tracking.markers import ArucoTracker, procrustes_pose
from tracks.geometry import wrap_angle

FIXED_FILE = Path(__file__).resolve().parents[1] / "tracking" / "data" / "oval_fixed_markers.json"
CAR = CarAppearance()


@pytest.fixture(scope="module")
def fixed():
    return load_fixed_markers(FIXED_FILE)


@pytest.fixture(scope="module")
def track_drawing():
    from tracks import load_track

    left, right = load_track("oval").boundaries()
    return TrackDrawing(left, right)


@pytest.fixture(scope="module")
def camera():
    return overhead_camera()


def car_poses_on_track(rng, n=6):
    """Poses on the oval's surface (straights at y = 0.5 / 2.5 and the turn areas)."""
    poses = []
    for i in range(n):
        x, y = rng.uniform(0.5, 4.5), rng.choice([rng.uniform(0.3, 0.7), rng.uniform(2.3, 2.7)])
        poses.append(CarPose(i, x, y, rng.uniform(-math.pi, math.pi)))
    return poses


@pytest.fixture(scope="module")
def scene(camera, fixed, track_drawing):
    rng = np.random.default_rng(7)
    synth = SyntheticCamera(camera, track_drawing, list(fixed.markers.values()), car=CAR,
                            effects=RenderEffects(seed=3))
    poses = car_poses_on_track(rng)
    return synth, poses, synth.render(poses, 1.25)


def pose_errors(detections, poses):
    out = []
    for p in poses:
        m = detections.cars[p.marker_id]
        out.append((math.hypot(m.x - p.x, m.y - p.y), abs(math.degrees(wrap_angle(m.heading - p.heading)))))
    return np.array(out)


def test_detected_car_poses_match_truth_with_height_correction(scene, camera, fixed):
    synth, poses, frame = scene
    tracker = ArucoTracker(CameraCalibration(camera), marker_size_m=CAR.marker_size_m,
                           marker_height_m=CAR.roof_height_m, fixed_ids=fixed.markers)
    det = tracker.process(frame)
    assert set(det.cars) == {p.marker_id for p in poses}
    assert det.t_capture_s == 1.25
    err = pose_errors(det, poses)
    assert err[:, 0].max() < 0.003  # metres
    assert err[:, 1].max() < 1.0  # degrees
    print(f"\npose error max {err[:, 0].max() * 1e3:.2f} mm, heading max {err[:, 1].max():.2f} deg")


def test_height_correction_matters_and_matches_parallax(scene, camera, fixed):
    synth, poses, frame = scene
    tracker = ArucoTracker(CameraCalibration(camera), marker_size_m=CAR.marker_size_m,
                           marker_height_m=CAR.roof_height_m, fixed_ids=fixed.markers, correct_height=False)
    det = tracker.process(frame)
    cam_x, cam_y, cam_h = camera.position
    h = CAR.roof_height_m
    parallaxes = []
    for p in poses:
        m = det.cars[p.marker_id]
        d = math.hypot(p.x - cam_x, p.y - cam_y)
        parallax = h * d / (cam_h - h)  # a raised point seen from the camera lands this far outward
        radial = np.array([p.x - cam_x, p.y - cam_y]) / d
        shift = np.array([m.x - p.x, m.y - p.y])
        assert abs(shift @ radial - parallax) < 0.002
        assert abs(shift @ np.array([-radial[1], radial[0]])) < 0.002  # no sideways shift
        parallaxes.append(parallax)
    # Without the correction a 4.5 cm high marker is off by centimetres away from the nadir.
    assert max(parallaxes) > 0.02


def test_roi_search_finds_the_same_cars(scene, camera, fixed):
    synth, poses, frame = scene
    tracker = ArucoTracker(CameraCalibration(camera), marker_size_m=CAR.marker_size_m,
                           marker_height_m=CAR.roof_height_m, fixed_ids=fixed.markers, full_search_every=5)
    full = tracker.process(frame)
    predictions = {p.marker_id: (p.x + 0.03, p.y - 0.02) for p in poses}  # predictions a few cm off
    roi = tracker.process(frame, predictions)
    assert not roi.full_search and full.full_search
    assert set(roi.cars) == set(full.cars)
    assert not set(roi.markers) & set(fixed.markers)  # fixed markers lie outside the car ROIs
    for i in roi.cars:
        assert math.hypot(roi.cars[i].x - full.cars[i].x, roi.cars[i].y - full.cars[i].y) < 1e-4


def test_downscaled_detection_with_large_markers(camera):
    big = CarAppearance(length_m=0.3, width_m=0.16, marker_size_m=0.13, label_margin_m=0.012, roof_height_m=0.08)
    synth = SyntheticCamera(camera, car=big, effects=RenderEffects(seed=1))
    poses = [CarPose(3, 1.2, 0.9, 0.4), CarPose(9, 3.6, 2.1, -2.0)]
    frame = synth.render(poses, 0.0)
    tracker = ArucoTracker(CameraCalibration(camera), marker_size_m=big.marker_size_m,
                           marker_height_m=big.roof_height_m, downscale=0.5)
    err = pose_errors(tracker.process(frame), poses)
    assert err[:, 0].max() < 0.003 and err[:, 1].max() < 1.0


def test_motion_blurred_car_pose_is_mid_exposure(camera):
    synth = SyntheticCamera(camera, effects=RenderEffects(exposure_s=0.004, seed=2))
    poses = [CarPose(1, 2.0, 0.5, 0.0, speed=3.0), CarPose(2, 3.0, 2.5, math.pi, speed=2.5, yaw_rate=2.0)]
    frame = synth.render(poses, 0.0)
    tracker = ArucoTracker(CameraCalibration(camera), marker_size_m=CAR.marker_size_m,
                           marker_height_m=CAR.roof_height_m)
    err = pose_errors(tracker.process(frame), poses)
    assert err[:, 0].max() < 0.004 and err[:, 1].max() < 1.5


def test_procrustes_pose_of_known_square():
    heading, size = 2.1, 0.05
    c, s = math.cos(heading), math.sin(heading)
    half = size / 2
    local = np.array([[half, half], [half, -half], [-half, -half], [-half, half]])
    pts = local @ np.array([[c, s], [-s, c]]) + [1.0, 2.0]
    x, y, h, side = procrustes_pose(pts, size)
    assert (x, y) == pytest.approx((1.0, 2.0)) and h == pytest.approx(heading) and side == pytest.approx(size)


# ------------------------------------------------------------------ calibration
def assert_recovers_camera(cal, camera, pos_tol=0.005, deg_tol=0.05):
    assert np.linalg.norm(cal.camera.position - camera.position) < pos_tol
    rel = cal.camera.rotation @ camera.rotation.T
    angle = math.degrees(math.acos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
    assert angle < deg_tol
    # Homography of the track plane: map a grid of track points with both, compare in pixels.
    grid = np.stack(np.meshgrid(np.linspace(0.2, 4.8, 5), np.linspace(0.2, 2.8, 4)), -1).reshape(-1, 2)
    pts = np.column_stack([grid, np.ones(len(grid))])
    a = pts @ cal.track_to_image_homography().T
    b = pts @ camera.plane_homography(0.0).T
    assert np.abs(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:]).max() < 0.3


def test_calibration_with_known_intrinsics_recovers_pose(scene, camera, fixed):
    _, _, frame = scene
    intr = Intrinsics(camera.camera_matrix, np.zeros(5), camera.image_size)
    cal = calibrate_image(frame.image, fixed, intr)
    assert cal.markers_used == sorted(fixed.markers) and not cal.markers_missing
    assert cal.reprojection_rms_px < 0.2
    assert_recovers_camera(cal, camera)


def test_calibration_without_intrinsics_estimates_focal_length(scene, camera, fixed):
    _, _, frame = scene
    cal = calibrate_image(frame.image, fixed)
    assert cal.intrinsics_source == "estimated"
    assert cal.camera.camera_matrix[0, 0] == pytest.approx(camera.camera_matrix[0, 0], rel=0.01)
    assert_recovers_camera(cal, camera, pos_tol=0.03, deg_tol=0.2)


def test_calibration_with_lens_distortion(fixed, track_drawing):
    dist = np.array([-0.12, 0.03, 0.0, 0.0, 0.0])
    camera = overhead_camera(dist_coeffs=dist)
    synth = SyntheticCamera(camera, track_drawing, list(fixed.markers.values()), effects=RenderEffects(seed=4))
    poses = [CarPose(0, 1.0, 0.5, 0.3), CarPose(1, 4.0, 2.5, -2.8)]  # towards the image corners
    frame = synth.render(poses, 0.0)
    cal = calibrate_image(frame.image, fixed, Intrinsics(camera.camera_matrix, dist, camera.image_size))
    assert cal.reprojection_rms_px < 0.2
    assert_recovers_camera(cal, camera)
    tracker = ArucoTracker(cal, marker_size_m=CAR.marker_size_m, marker_height_m=CAR.roof_height_m,
                           fixed_ids=fixed.markers)
    err = pose_errors(tracker.process(frame), poses)
    assert err[:, 0].max() < 0.003 and err[:, 1].max() < 1.0
    # Ignoring the distortion (same matrix, no coefficients) is visibly worse.
    naive = calibrate_image(frame.image, fixed, Intrinsics(camera.camera_matrix, np.zeros(5), camera.image_size))
    assert naive.reprojection_rms_px > 5 * cal.reprojection_rms_px


def test_calibration_from_marker_centres_only(scene, camera, fixed):
    _, _, frame = scene
    centres = FixedMarkerSet(fixed.dictionary, {
        i: type(m)(m.marker_id, m.x, m.y, m.size, None, m.z) for i, m in fixed.markers.items()})
    cal = calibrate_image(frame.image, centres, Intrinsics(camera.camera_matrix, np.zeros(5), camera.image_size))
    assert_recovers_camera(cal, camera, pos_tol=0.01, deg_tol=0.1)


def test_calibration_needs_four_points(scene, camera, fixed):
    _, _, frame = scene
    few = FixedMarkerSet(fixed.dictionary, {i: fixed.markers[i] for i in (40, 41, 42)})
    few = FixedMarkerSet(fixed.dictionary, {
        i: type(m)(m.marker_id, m.x, m.y, m.size, None) for i, m in few.markers.items()})
    with pytest.raises(CalibrationError, match=r"at least 4 .*found markers \[40, 41, 42\]"):
        calibrate_image(frame.image, few)


def test_intrinsics_size_mismatch_is_rejected(scene, camera, fixed):
    _, _, frame = scene
    with pytest.raises(CalibrationError, match="image_width/image_height"):
        calibrate_image(frame.image, fixed, Intrinsics(camera.camera_matrix, np.zeros(5), (640, 480)))


@pytest.mark.parametrize("data, field", [
    ({"markers": {"40": {"x": 1, "y": 2}}}, r"markers\['40'\]\.size: missing"),
    ({"markers": {"40": {"x": 1, "y": 2, "size": -0.1}}}, r"markers\['40'\]\.size: must be positive"),
    ({"markers": {"x40": {"x": 1, "y": 2, "size": 0.1}}}, r"markers\['x40'\]: key must be an integer"),
    ({"markers": {"99": {"x": 1, "y": 2, "size": 0.1}}}, r"markers\['99'\]: id outside DICT_4X4_50"),
    ({"markers": {"4": {"x": "a", "y": 2, "size": 0.1}}}, r"markers\['4'\]\.x: must be a finite number"),
    ({"markers": {"4": {"x": 1, "y": 2, "size": 0.1, "yaw": 3}}}, r"markers\['4'\]: unknown field"),
    ({"dictionary": "DICT_9X9", "markers": {"4": {"x": 1, "y": 2, "size": 0.1}}}, "unknown ArUco dictionary"),
    ({"markers": {}}, "markers: must be a non-empty object"),
])
def test_fixed_marker_validation_names_field(data, field):
    with pytest.raises(CalibrationError, match=field):
        parse_fixed_markers(data, "f.json")


# ------------------------------------------------------------------ sources
def test_video_file_camera_reads_frames_and_ends(tmp_path, camera):
    synth = SyntheticCamera(camera, world=lambda t: [CarPose(0, 1.0 + t, 1.0, 0.0)], fps=30.0,
                            effects=RenderEffects(noise_sigma=0))
    frames = [synth.read() for _ in range(3)]
    assert [f.t_capture_s for f in frames] == pytest.approx([0.0, 1 / 30, 2 / 30])
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, camera.image_size, isColor=False)
    assert writer.isOpened()
    for f in frames:
        writer.write(f.image)
    writer.release()
    video = VideoFileCamera(path)
    got = [video.read() for _ in range(3)]
    assert [f.index for f in got] == [0, 1, 2]
    assert [f.t_capture_s for f in got] == pytest.approx([0.0, 1 / 30, 2 / 30], abs=1e-3)
    with pytest.raises(EndOfStream):
        video.read()
    video.close()


def test_missing_sources_raise_clear_errors(tmp_path):
    with pytest.raises(CameraError, match="not found"):
        VideoFileCamera(tmp_path / "nope.mp4")
    with pytest.raises(CameraError, match="cannot open"):
        OpenCVCamera(str(tmp_path / "no_such_stream.mjpg"))


@pytest.mark.parametrize("sigma", [0.5, 1.7])
def test_regions_redone_per_frame_equal_the_whole_image_pipeline(camera, track_drawing, sigma):
    # render() redoes lighting and blur only around the cars; the reference is the same effects applied
    # to the whole canvas. Cars overlapping, at the image border and half outside it.
    synth = SyntheticCamera(camera, track_drawing, effects=RenderEffects(seed=5, defocus_sigma_px=sigma))
    corner = camera.pixels_to_plane(np.array([[2.0, 3.0]]), CAR.roof_height_m)[0]
    cases = [[CarPose(1, 2.0, 1.0, 0.3, 2.0, 1.0), CarPose(2, 2.08, 1.04, 0.5, 1.0)],
             [CarPose(1, *corner, 0.0), CarPose(2, 4.9, 2.9, 1.0)],
             [CarPose(1, -0.1, 1.5, 0.0), CarPose(2, 0.6, 0.4, 2.0)]]
    at_border = []
    for poses in cases:
        canvas = synth._background.copy()
        boxes = [b for b in (synth._draw_objects(canvas, [synth._car_objects(p.marker_id, p.x, p.y, p.heading)])
                             for p in poses) if b is not None]
        assert boxes
        at_border.append(any(b[0] == 0 or b[1] == 0 for b in boxes))
        np.testing.assert_array_equal(synth._sensor_image(canvas, boxes), synth._sensor_effects(canvas))
    assert at_border[1]  # the corner case did reach the image border
