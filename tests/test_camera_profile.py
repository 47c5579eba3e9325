"""The synthetic camera's profiles (sim/camera_profile.py) against independent references: OpenCV's
projectPoints for the distorted rendering, the hand-computed row-time shift of a car moving at a known
speed, the car file's marker offset and yaw removed by the tracker, JPEG at quality 75 keeping a marker
of known size detectable, and seeded frames that repeat."""
import dataclasses
import math

import cv2
import numpy as np
import pytest

from sim.camera import CarAppearance, CarPose, RenderEffects, SyntheticCamera, TrackDrawing, overhead_camera
from sim.camera_profile import CameraProfile, DelayedDelivery, DeliveryClock, camera_profile
from tracking.calibration import CameraCalibration, FixedMarker
from tracking.markers import ArucoTracker, MarkerDetector
from tracks.geometry import wrap_angle
from vehicles.params import MARKER_DICTIONARY, CarParamsError, car_params_from_dict

REALISTIC = camera_profile("realistic", seed=5)
QUIET = RenderEffects(noise_sigma=0.0, defocus_sigma_px=0.0, vignetting=0.0, light_variation=0.0)


def _tracker(camera, car=CarAppearance(), **kw):
    return ArucoTracker(CameraCalibration(camera), car.marker_size_m, car.roof_height_m, **kw)


def test_distorted_rendering_matches_opencv_projection():
    """Fixed markers rendered through the realistic lens: their detected corners are where cv2.projectPoints
    of the surveyed corners with the same lens puts them (the nearest-pixel rendering and the detector's
    sub-pixel refinement leave a few tenths of a pixel)."""
    camera = overhead_camera(dist_coeffs=np.array(REALISTIC.dist_coeffs))
    size = 0.12
    markers = [FixedMarker(40 + i, x, y, size, 0.0, h) for i, (x, y, h) in
               enumerate([(0.3, 0.3, 0.0), (4.7, 0.3, 0.5), (2.5, 1.5, 1.0), (0.3, 2.7, 0.0), (4.7, 2.7, 0.2)])]
    synth = SyntheticCamera(camera, fixed_markers=markers, effects=QUIET)
    image = synth.render([], 0.0).image
    found = MarkerDetector(getattr(cv2.aruco, MARKER_DICTIONARY)).detect(image)
    rvec, _ = cv2.Rodrigues(camera.rotation)
    shift_at_corner = 0.0
    for m in markers:
        c, s = math.cos(m.heading_rad), math.sin(m.heading_rad)
        half = size / 2
        local = np.array([[-half, half], [half, half], [half, -half], [-half, -half]])
        pts = np.column_stack([local @ np.array([[c, s], [-s, c]]) + [m.x, m.y], np.full(4, m.z)])
        ref, _ = cv2.projectPoints(pts, rvec, camera.translation, camera.camera_matrix, camera.dist_coeffs)
        ref = ref.reshape(4, 2)
        assert m.marker_id in found
        # each detected corner against the nearest projected one (no corner-order convention needed)
        err = np.linalg.norm(found[m.marker_id][:, None, :] - ref[None], axis=2).min(axis=1)
        assert err.max() < 0.5, (m.marker_id, err)
        pinhole, _ = cv2.projectPoints(pts, rvec, camera.translation, camera.camera_matrix, None)
        shift_at_corner = max(shift_at_corner, float(np.linalg.norm(pinhole.reshape(4, 2) - ref, axis=1).max()))
    assert shift_at_corner > 20  # the lens moves the arena's corners by tens of pixels: the check has teeth


def test_rolling_shutter_shifts_a_moving_car_by_its_row_time():
    """A car at 2 m/s along +x, its marker near the top rows: exposed readout * (row / (h - 1) - 0.5) before
    the frame's time, so it is seen that far behind (hand-computed from the projected row)."""
    camera = overhead_camera()
    readout = 0.010
    effects = dataclasses.replace(QUIET, readout_s=readout, exposure_s=0.0)
    synth = SyntheticCamera(camera, effects=effects)
    tracker = _tracker(camera)
    speed = 2.0
    for x, y in ((1.5, 2.6), (3.5, 0.4)):  # top rows (y large), then bottom rows
        row = camera.project(np.array([[x, y, CarAppearance().roof_height_m]]))[0, 1]
        dt = readout * (row / (camera.image_size[1] - 1) - 0.5)
        det = tracker.process(synth.render([CarPose(3, x, y, 0.0, speed, 0.0)], 1.0))
        m = det.cars[3]
        assert abs(dt) > 0.003  # a shift of at least 6 mm: far above the detection's 0.5 mm
        assert m.x - x == pytest.approx(speed * dt, abs=0.0008)
        assert abs(m.y - y) < 0.0008


def test_marker_offset_and_yaw_of_the_car_file_are_removed():
    car = car_params_from_dict({"name": "glued", "marker": {"offset_forward_m": 0.004, "offset_left_m": -0.003,
                                                             "yaw_rad": math.radians(1.5)}})
    mk = car.marker
    appearance = CarAppearance(marker_offset_m=mk.offset_forward_m, marker_offset_left_m=mk.offset_left_m,
                               marker_yaw_rad=mk.yaw_rad)
    camera = overhead_camera()
    synth = SyntheticCamera(camera, car=appearance, effects=RenderEffects(seed=2))
    poses = [CarPose(i, x, y, h) for i, (x, y, h) in enumerate([(1.0, 0.5, 0.3), (2.5, 1.5, 2.0), (4.0, 2.5, -2.5)])]
    frame = synth.render(poses, 0.0)
    told = _tracker(camera, marker_offset_m=mk.offset_forward_m, marker_offset_left_m=mk.offset_left_m,
                    marker_yaw_rad=mk.yaw_rad).process(frame)
    naive = _tracker(camera).process(frame)
    metres_per_px = camera.position[2] / camera.camera_matrix[0, 0]
    for p in poses:
        m, n = told.cars[p.marker_id], naive.cars[p.marker_id]
        assert math.hypot(m.x - p.x, m.y - p.y) < 0.25 * metres_per_px  # a quarter pixel (about 1 mm)
        assert abs(math.degrees(wrap_angle(m.heading - p.heading))) < 0.5
        assert math.hypot(n.x - p.x, n.y - p.y) == pytest.approx(0.005, abs=0.001)  # the 5 mm of the offset
        assert math.degrees(wrap_angle(n.heading - p.heading)) == pytest.approx(1.5, abs=0.5)
    with pytest.raises(CarParamsError, match="marker.offset_left_m"):
        car_params_from_dict({"name": "bad", "marker": {"offset_left_m": 0.5}}, "cars/bad.toml")


def test_jpeg_at_quality_75_keeps_a_marker_of_known_size():
    """A 55 mm marker (about 13 px at the arena's scale) through JPEG at quality 75: still found, in place."""
    camera = overhead_camera()
    effects = dataclasses.replace(RenderEffects(seed=4), jpeg_quality=75)
    synth = SyntheticCamera(camera, effects=effects)
    poses = [CarPose(i, 0.6 + 0.9 * i, 0.4 + 0.45 * i, 0.7 * i) for i in range(5)]
    frame = synth.render(poses, 0.0)
    plain = SyntheticCamera(camera, effects=RenderEffects(seed=4)).render(poses, 0.0)
    assert np.abs(frame.image.astype(int) - plain.image).mean() > 0.3  # the frame did go through JPEG
    det = _tracker(camera).process(frame)
    side_px = CarAppearance().marker_size_m * camera.camera_matrix[0, 0] / camera.position[2]
    assert 10 < side_px < 16
    for p in poses:
        m = det.cars[p.marker_id]
        assert math.hypot(m.x - p.x, m.y - p.y) < 0.003
        assert abs(math.degrees(wrap_angle(m.heading - p.heading))) < 2.0


def test_seeded_realistic_profile_repeats_and_seed_changes_it():
    camera = overhead_camera(dist_coeffs=np.array(REALISTIC.dist_coeffs))
    poses = [CarPose(1, 2.0, 0.5, 0.2, 1.5, 0.5), CarPose(2, 3.0, 2.5, 3.0, 1.0, -0.3)]

    def frames(profile):
        synth = SyntheticCamera(camera, effects=profile.effects)
        return [synth.render(poses, t).image for t in (0.0, 1 / 60)]

    a, b = frames(REALISTIC), frames(REALISTIC)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    c = frames(REALISTIC.with_seed(6))
    assert not np.array_equal(a[0], c[0])
    clock_a, clock_b = DeliveryClock(REALISTIC), DeliveryClock(REALISTIC)
    times = np.arange(200) / 60
    da = np.array([clock_a.delivery_time(t) for t in times])
    assert np.array_equal(da, [clock_b.delivery_time(t) for t in times])
    delay = da - times
    assert np.all(np.diff(da) >= 0) and np.all(delay >= 0)
    assert np.median(delay) == pytest.approx(REALISTIC.latency_s, abs=0.001)
    assert np.std(delay) == pytest.approx(REALISTIC.jitter_s, rel=0.3)
    assert clock_a.stamp(1.0) == pytest.approx(1.0 - REALISTIC.latency_known_s)


def test_profiles_by_name_and_bad_values():
    assert camera_profile("ideal").effects == RenderEffects()
    ideal_camera = overhead_camera()
    told = camera_profile("ideal").estimated(ideal_camera)  # no calibration views: the true intrinsics
    np.testing.assert_array_equal(told.camera_matrix, ideal_camera.camera_matrix)
    jpeg = camera_profile("ideal+jpeg")
    assert jpeg.effects == dataclasses.replace(RenderEffects(), jpeg_quality=75) and jpeg.dist_coeffs == (0,) * 5
    assert camera_profile("ideal+calibration").calibration_views == REALISTIC.calibration_views > 0
    with pytest.raises(ValueError, match="ideal, realistic"):
        camera_profile("fisheye")
    with pytest.raises(ValueError, match="latency_s"):
        CameraProfile("x", latency_s=-0.01)
    with pytest.raises(ValueError, match="jpeg_quality"):
        RenderEffects(jpeg_quality=0)


def test_estimated_intrinsics_come_from_board_views_and_are_cached(tmp_path):
    """The realistic profile's intrinsics are calibrate-camera's estimate from rendered ChArUco views: close to
    the true lens (focal length within 2 %, principal point within 10 px, k1 within 0.02: what a calibration
    leaves), not equal to it, the same again from the cache file, and another seed gives another estimate."""
    import time

    camera = overhead_camera(dist_coeffs=np.array(REALISTIC.dist_coeffs))
    estimated = REALISTIC.estimated(camera, cache_dir=tmp_path)
    true_k = camera.camera_matrix
    assert estimated.camera_matrix[0, 0] == pytest.approx(true_k[0, 0], rel=0.02)  # seed 5: +1.0 %
    assert estimated.camera_matrix[1, 1] == pytest.approx(true_k[1, 1], rel=0.02)
    assert np.abs(estimated.camera_matrix[:2, 2] - true_k[:2, 2]).max() < 10.0
    assert estimated.dist_coeffs[0] == pytest.approx(REALISTIC.dist_coeffs[0], abs=0.02)
    assert not np.array_equal(estimated.camera_matrix, true_k)
    np.testing.assert_array_equal(estimated.rotation, camera.rotation)
    (cached,) = tmp_path.glob("realistic-seed5-*.json")
    start = time.perf_counter()
    again = REALISTIC.estimated(camera, cache_dir=tmp_path)
    assert time.perf_counter() - start < 1.0  # read back, not recomputed (recomputing renders 20 views)
    np.testing.assert_allclose(again.camera_matrix, estimated.camera_matrix, rtol=1e-12)
    other = REALISTIC.with_seed(6).estimated(camera, cache_dir=tmp_path)
    assert not np.allclose(other.camera_matrix, estimated.camera_matrix)


def test_delayed_delivery_hands_frames_on_after_their_latency_in_order():
    import time

    profile = dataclasses.replace(camera_profile("ideal"), latency_s=0.02, jitter_s=0.002, latency_known_s=0.02)
    got = []
    delivery = DelayedDelivery(profile, lambda stamp, item: got.append((time.monotonic(), stamp, item)))
    t0 = time.monotonic()
    for i in range(5):
        delivery.submit(t0 + i * 0.005, i)
    deadline = time.monotonic() + 5.0
    while len(got) < 5 and time.monotonic() < deadline:
        time.sleep(0.01)
    delivery.close()
    assert [item for _, _, item in got] == list(range(5))
    for arrived, stamp, i in got:
        exposure = t0 + i * 0.005
        assert arrived >= exposure + 0.01  # not before its latency (less 5 jitter sigmas)
        assert abs(stamp - exposure) < 0.012  # the loop's stamp: delivery less the known latency


def test_hil_world_camera_uses_the_profile_and_the_car_files_marker_placement():
    from race.hil import WorldSpec, make_camera
    from tracks import load_track

    car = car_params_from_dict({"name": "glued", "marker": {"offset_forward_m": 0.004, "yaw_rad": 0.02}})
    spec = WorldSpec(track=load_track("oval"), car=car, start_states=np.zeros((2, 6)), marker_ids=(0, 1),
                     radio_ids=(0, 1), laps=1, seed=9, camera_profile=camera_profile("realistic"))
    synth, camera, _, appearance = make_camera(spec)
    assert tuple(camera.dist_coeffs) == REALISTIC.dist_coeffs
    assert synth.effects == camera_profile("realistic", seed=9).effects
    assert (appearance.marker_offset_m, appearance.marker_yaw_rad) == (0.004, 0.02)


def test_surveyed_fixed_markers_are_off_by_the_profiles_seeded_survey_error():
    from pathlib import Path

    from tracking.calibration import load_fixed_markers

    fixed = load_fixed_markers(Path(__file__).resolve().parents[1] / "tracking" / "data" / "oval_fixed_markers.json")
    a, b = REALISTIC.surveyed(fixed), REALISTIC.surveyed(fixed)
    assert a == b and camera_profile("ideal").surveyed(fixed) is fixed
    d = np.array([[a.markers[i].x - m.x, a.markers[i].y - m.y, a.markers[i].z - m.z] for i, m in fixed.markers.items()])
    assert np.all(d != 0) and np.abs(d).max() < 5 * REALISTIC.survey_sigma_m
    assert 0.3 * REALISTIC.survey_sigma_m < d.std() < 2 * REALISTIC.survey_sigma_m


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_regions_redone_through_the_lens_equal_the_whole_image_pipeline(sigma):
    """With lens distortion only the cars' regions are resampled per frame; the reference is the whole canvas
    through the lens map and the sensor effects. Cars overlapping, in a corner (strongest distortion) and
    half outside the image."""
    camera = overhead_camera(dist_coeffs=np.array(REALISTIC.dist_coeffs))
    synth = SyntheticCamera(camera, effects=RenderEffects(seed=5, defocus_sigma_px=sigma))
    cases = [[CarPose(1, 2.0, 1.0, 0.3), CarPose(2, 2.08, 1.04, 0.5)],
             [CarPose(1, 0.05, 0.05, 0.8), CarPose(2, 4.95, 2.95, 1.0)],
             [CarPose(1, -0.15, 1.5, 0.0), CarPose(2, 2.5, 3.1, 2.0)]]
    for poses in cases:
        canvas = synth._background.copy()
        boxes = [b for b in (synth._draw_objects(canvas, [synth._car_objects(p.marker_id, p.x, p.y, p.heading)])
                             for p in poses) if b is not None]
        assert boxes
        whole = synth._sensor_effects(synth._canvas.to_sensor(canvas))
        np.testing.assert_array_equal(synth._sensor_image(canvas, boxes), whole)
        assert not np.array_equal(whole, synth._background_sensor)  # the cars did change the image


def test_hil_race_with_the_realistic_camera_and_a_glued_marker(tmp_path, capsys):
    """`race --hil --camera-profile realistic` end to end, the car file saying where its marker is glued: the race
    runs to its time limit and the tracking error is that of a real camera (issue 33's goal: median below 10 mm),
    well above the ideal camera's 0.05 mm, so the profile did act."""
    import json

    from app.cli import main
    from vehicles.params import dump_car_params, load_car_params

    base = load_car_params("buzzracer")
    car = dataclasses.replace(base, marker=dataclasses.replace(base.marker, offset_forward_m=0.004, offset_left_m=0.002,
                                                               yaw_rad=math.radians(1.5)))
    car_file, js = tmp_path / "glued.toml", tmp_path / "race.json"
    car_file.write_text(dump_car_params(car))
    code = main(["race", "--hil", "--camera-profile", "realistic", "--car-params", str(car_file), "--max-time", "3",
                 "--out", str(tmp_path / "race.rrd"), "--json", str(js)])
    assert code == 0, capsys.readouterr()
    summary = json.loads(js.read_text())
    assert summary["end_reason"] == "time_limit"
    assert 1.0 < summary["tracking_error_mm_median"] < 10.0
    assert summary["tracking_error_mm_p95"] < 20.0
    # the car file's 1.5 degree marker yaw is subtracted: the heading error stays well below it
    assert summary["tracking_heading_error_deg_median"] < 0.75
    assert summary["tracking_heading_error_deg_p95"] >= summary["tracking_heading_error_deg_median"]
