"""The ArUco dictionary is a setting (car file ``marker.dictionary``, fixed-marker and calibration files'
``dictionary``, calibrate-camera's ``--dictionary``) with one default, validated against OpenCV's list,
and the renderer, the detector and the tracker all follow it."""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from race.hil import WorldSpec, make_camera
from sim.camera import CarAppearance, CarPose, RenderEffects, SyntheticCamera, overhead_camera
from tracking.calibration import CameraCalibration
from tracking.camera import Frame
from tracking.markers import ArucoTracker, MarkerDetector
from tracks import load_track
from vehicles.params import (MARKER_DICTIONARY, CarParams, CarParamsError, MarkerParams, aruco_dictionary_size,
                             car_params_from_dict, dump_car_params, load_car_params)


def test_one_default_everywhere():
    assert MARKER_DICTIONARY == MarkerParams().dictionary == CameraCalibration(None).dictionary
    assert aruco_dictionary_size("DICT_4X4_50") == 50 and aruco_dictionary_size("DICT_6X6_250") == 250
    assert aruco_dictionary_size("DICT_9X9_1") is None and aruco_dictionary_size("DICT_4X4_50 ") is None


def test_car_file_dictionary_is_read_validated_and_written(tmp_path):
    car = car_params_from_dict({"name": "c", "marker": {"dictionary": "DICT_5X5_100", "aruco_id": 7}}, "car.toml")
    assert car.marker.dictionary == "DICT_5X5_100"
    path = tmp_path / "c.toml"
    path.write_text(dump_car_params(car))
    assert load_car_params(path) == car
    for bad, message in (("DICT_5X5", "must be an OpenCV ArUco dictionary name"), (5, "must be a string")):
        with pytest.raises(CarParamsError, match=f"car.toml: marker.dictionary: {message}"):
            car_params_from_dict({"name": "c", "marker": {"dictionary": bad}}, "car.toml")
    assert load_car_params("buzzracer").marker.dictionary == MARKER_DICTIONARY  # older files: the default


def test_renderer_and_tracker_follow_the_setting():
    camera = overhead_camera((1.5, 0.9, 2.5, 1.5), image_size=(640, 400))  # markers of ~30 px
    car = CarAppearance(roof_height_m=0.045)
    pose = CarPose(17, 2.0, 1.2, 0.3)
    frame = SyntheticCamera(camera, car=car, effects=RenderEffects(seed=1),
                            dictionary=cv2.aruco.DICT_6X6_250).render([pose], 0.0)
    # OpenCV's own detector (not ours) reads the rendered marker in the chosen dictionary only.
    for name, expected in (("DICT_6X6_250", [17]), ("DICT_4X4_50", [])):
        _, ids, _ = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))).detectMarkers(frame.image)
        assert ([] if ids is None else ids.ravel().tolist()) == expected
    tracker = ArucoTracker(CameraCalibration(camera, dictionary="DICT_6X6_250"), car.marker_size_m, car.roof_height_m,
                           car_ids=[17], car_dictionary="DICT_6X6_250")
    found = tracker.process(Frame(frame.image, 0.0, 0)).cars
    assert set(found) == {17} and math.hypot(found[17].x - pose.x, found[17].y - pose.y) < 0.005
    assert set(MarkerDetector().detect(frame.image)) == set()  # the default detector: 4x4, nothing here
    with pytest.raises(ValueError, match="car marker dictionary DICT_6X6_250 .* differs from the calibration's DICT_4X4_50"):
        ArucoTracker(CameraCalibration(camera), 0.055, 0.045, car_ids=[17], car_dictionary="DICT_6X6_250")


def test_hil_world_refuses_car_and_fixed_markers_from_different_dictionaries():
    car = CarParams()
    spec = WorldSpec(track=load_track("oval"), car=car, start_states=np.zeros((2, 6)), marker_ids=(0, 1),
                     radio_ids=(0, 1), laps=1, seed=0, image_size=(320, 200))
    synth, *_ = make_camera(spec)  # the oval's fixed markers are DICT_4X4_50, as the car's default
    other = dataclasses.replace(car, marker=dataclasses.replace(car.marker, dictionary="DICT_5X5_100"))
    with pytest.raises(ValueError, match="marker.dictionary DICT_5X5_100 differs from .*oval_fixed_markers.json's "
                                         "dictionary DICT_4X4_50"):
        make_camera(dataclasses.replace(spec, car=other))
