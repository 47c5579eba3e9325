"""`measure-marker`: the marker's offset and yaw from slow circles (tracking.marker_offset).

Reference: a car whose marker is glued 4 mm ahead, 2 mm right and turned 1.5 degrees, driven (rendered) on the
kinematic circles of two steering angles, placed by the test from the rear axle's circle (the rear axle of a car
rolling without slip circles at L / tan(delta) about a centre on its axis); tracked by the ArUco tracker told no
offset."""
import csv
import math
import re

import numpy as np
import pytest

from sim.camera import CarAppearance, CarPose, RenderEffects, SyntheticCamera, overhead_camera
from tracking.calibration import CameraCalibration
from tracking.marker_offset import MarkerOffsetError, circles_from_poses, fit_circle, marker_offset
from tracking.markers import ArucoTracker
from vehicles.params import load_car_params

GLUED = dict(forward=0.004, left=-0.002, yaw=math.radians(1.5))
GEOMETRY = load_car_params("buzzracer").geometry


def rear_axle_circle(steering, centre, n=48):
    """Poses of the reference point (lr ahead of the rear axle) while the rear axle circles about ``centre``."""
    lr, wheelbase = GEOMETRY.lr_m, GEOMETRY.wheelbase_m
    rear_radius = wheelbase / math.tan(steering)  # signed: positive turns left
    out = []
    for k in range(n):
        heading = 2 * math.pi * k / n
        rear = np.array(centre) + rear_radius * np.array([math.sin(heading), -math.cos(heading)])
        ref = rear + lr * np.array([math.cos(heading), math.sin(heading)])
        out.append((float(ref[0]), float(ref[1]), heading))
    return out


@pytest.fixture(scope="module")
def tracked_circles():
    """Rows (t, car, x, y, heading, throttle, steering) of the tracked marker, two circles of 0.3 m/s."""
    camera = overhead_camera()
    car = CarAppearance(marker_offset_m=GLUED["forward"], marker_offset_left_m=GLUED["left"], marker_yaw_rad=GLUED["yaw"])
    synth = SyntheticCamera(camera, car=car, effects=RenderEffects(seed=4))
    tracker = ArucoTracker(CameraCalibration(camera), car.marker_size_m, car.roof_height_m, car_ids=[5])
    rows, t = [], 0.0
    for steering in (0.3, -0.3):
        for x, y, heading in rear_axle_circle(steering, (2.5, 1.5)):
            radius = GEOMETRY.wheelbase_m / math.tan(steering)
            frame = synth.render([CarPose(5, x, y, heading, 0.3, 0.3 / radius)], t)
            m = tracker.process(frame).cars[5]
            rows.append((t, 5, m.x, m.y, m.heading, 0.1, steering))
            t += 1 / 30
    return rows


def test_fit_circle_is_exact_on_a_circle():
    a = np.linspace(0, 4, 30)
    centre, radius, rms = fit_circle(1.0 + 0.7 * np.cos(a), -2.0 + 0.7 * np.sin(a))
    assert np.allclose(centre, [1.0, -2.0]) and radius == pytest.approx(0.7) and rms < 1e-12


def test_offset_and_yaw_recovered_from_rendered_circles(tracked_circles):
    t, _, x, y, heading, _, steering = (np.array(c) for c in zip(*tracked_circles))
    result = marker_offset(circles_from_poses(t, x, y, heading, steering, GEOMETRY.lf_m, GEOMETRY.lr_m))
    assert result.offset_forward_m == pytest.approx(GLUED["forward"], abs=0.0005)
    assert result.offset_left_m == pytest.approx(GLUED["left"], abs=0.0005)
    assert math.degrees(result.yaw_rad) == pytest.approx(math.degrees(GLUED["yaw"]), abs=0.15)
    assert len(result.circles) == 2


def test_one_circle_is_refused(tracked_circles):
    rows = [r for r in tracked_circles if r[6] > 0]
    t, _, x, y, heading, _, steering = (np.array(c) for c in zip(*rows))
    with pytest.raises(MarkerOffsetError, match="two are needed"):
        circles_from_poses(t, x, y, heading, steering, GEOMETRY.lf_m, GEOMETRY.lr_m)


def _write_log(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "car", "x", "y", "heading", "throttle", "steering"])
        w.writerows(rows)


def test_cli_writes_the_car_file_with_the_measured_marker(tracked_circles, tmp_path, capsys):
    from app.cli import main

    log, out = tmp_path / "circles.csv", tmp_path / "car.toml"
    _write_log(log, tracked_circles)
    assert main(["measure-marker", str(log), "--car", "5", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert re.search(r"offset_forward_m = 0\.00[34]", text)
    car = load_car_params(out)
    assert car.marker.offset_forward_m == pytest.approx(0.004, abs=0.0005)
    assert math.degrees(car.marker.yaw_rad) == pytest.approx(1.5, abs=0.15)


def test_cli_bad_input_exits_2(tracked_circles, tmp_path, capsys):
    from app.cli import main

    log = tmp_path / "one.csv"
    _write_log(log, [r for r in tracked_circles if r[6] > 0])
    assert main(["measure-marker", str(log), "--car", "5"]) == 2
    assert "two are needed" in capsys.readouterr().err
    assert main(["measure-marker", str(log), "--car", "9"]) == 2
    assert "car 9" in capsys.readouterr().err
