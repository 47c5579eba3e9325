"""The HIL world's synthetic camera with two cars close together (race/hil.py renders with
tracking.camera.SyntheticCamera): a car beside another one must stay visible as long as the cars do
not touch, whatever order the world passes them in (HIL seed 16 of the loop bench lost the RD3G car
this way, 1-2 cm from the opponent, and then drove into it on a dead-reckoned state)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tracking.calibration import marker_corners_track
from sim.camera import CarAppearance, CarPose, RenderEffects, SyntheticCamera, overhead_camera
from tracking.markers import MarkerDetector

CAR = CarAppearance(roof_height_m=0.045)  # the buzzracer marker height, as the HIL world uses


@pytest.fixture(scope="module")
def scene():
    camera = overhead_camera((0.0, 0.0, 5.0, 3.0))  # the oval's arena: camera above (2.5, 1.15)
    synth = SyntheticCamera(camera, car=CAR, effects=RenderEffects(seed=3))
    return camera, synth, MarkerDetector(cv2.aruco.DICT_4X4_50)


@pytest.mark.parametrize("near_first", [True, False])
@pytest.mark.parametrize("gap_m", [0.005, 0.015])
def test_cars_side_by_side_both_markers_visible(scene, near_first, gap_m):
    camera, synth, detector = scene
    # Two cars side by side, driving +y near the arena's right edge (about 1.9 m from the camera's
    # ground point, where the projected side walls reach ~3 cm towards the image centre); bodies
    # gap_m apart. The roofs are level, so from above neither roof can hide the other's marker.
    x_near = 4.3
    x_far = x_near + CAR.width_m + gap_m
    near, far = CarPose(0, x_near, 1.9, math.pi / 2), CarPose(1, x_far, 1.9, math.pi / 2)
    assert math.hypot(near.x - camera.position[0], near.y - camera.position[1]) < \
        math.hypot(far.x - camera.position[0], far.y - camera.position[1])
    frame = synth.render([near, far] if near_first else [far, near], 0.0)
    found = detector.detect(frame.image, None, {0, 1})
    assert set(found) == {0, 1}
    for pose in (near, far):
        # independent reference: the pinhole projection of the marker's corners on the roof
        expected = camera.project(marker_corners_track(pose.x, pose.y, pose.heading, CAR.marker_size_m,
                                                       CAR.roof_height_m))
        assert np.max(np.linalg.norm(found[pose.marker_id] - expected, axis=1)) < 1.0  # px
