"""The marker detector on real photographs: no false ids, every marker plain OpenCV finds, corner accuracy.

Photos: OpenCV's ArUco tutorial photographs in ``../shared/data/opencv-aruco-photos/`` (beside the
repository; its README lists what each shows). The references do not come from the code under test:

* no 4x4 (or 5x5, 7x7, original ArUco, AprilTag) marker is in any of these photos (README), so every
  id reported with those dictionaries is false;
* the DICT_6X6_250 ids are the ones OpenCV's own ``ArucoDetector`` with default parameters finds,
  checked by hand against the photos: the ChArUco board (5 x 7 squares) carries ids 0-16, all visible
  in ``img_00``, ``img_02``, ``img_03`` and ``choriginal``; in ``chocclusion_original`` a hand covers
  ids 11, 13, 14 and 16; ``singlemarkersoriginal`` shows six markers on a sheet of paper;
* corner accuracy: OpenCV's ChArUco board object gives the marker corners on the board plane; the
  corners, undistorted with OpenCV's published intrinsics of that camera, must fit one plane
  homography.

Marker-free negatives: real photographs shipped by matplotlib (already a dependency) and, when
installed (the ``test`` extra), scikit-image; licences beside the file names below.
"""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from tracking.markers import MarkerDetector

# RD3G_SHARED_DIR overrides the ../shared location (a checkout that is not beside shared/).
SHARED = Path(os.environ.get("RD3G_SHARED_DIR") or Path(__file__).resolve().parents[2] / "shared")
PHOTOS = SHARED / "data" / "opencv-aruco-photos"
BOARD_PHOTOS = ("img_00.jpg", "img_02.jpg", "img_03.jpg", "choriginal.jpg", "chocclusion_original.jpg")
ALL_PHOTOS = BOARD_PHOTOS + ("singlemarkersoriginal.jpg", "gboriginal.png", "gbocclusion.png", "diamondsaxis.jpg")
BOARD_IDS = set(range(17))
IDS_6X6 = {name: BOARD_IDS for name in BOARD_PHOTOS[:4]}
IDS_6X6["chocclusion_original.jpg"] = BOARD_IDS - {11, 13, 14, 16}
IDS_6X6["singlemarkersoriginal.jpg"] = {23, 40, 62, 98, 124, 203}
# The tracker's dictionary and a few larger ones (the more ids, the easier a false match). Decoding with
# the 1000-id, original ArUco and AprilTag dictionaries takes ~0.1 s per photo each, so only
# RD3G_PHOTO_DICTIONARIES=all adds them (docs/tracking.md, "False detections").
NO_MARKER_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_250", "DICT_5X5_250", "DICT_7X7_250") + (
    ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11")
    if os.environ.get("RD3G_PHOTO_DICTIONARIES") == "all" else ())

needs_photos = pytest.mark.skipif(not PHOTOS.is_dir(), reason=f"real ArUco photos not found at {PHOTOS} "
                                  "(shared/ beside the repository, or set RD3G_SHARED_DIR)")


def photo(name: str) -> np.ndarray:
    image = cv2.imread(str(PHOTOS / name), cv2.IMREAD_GRAYSCALE)
    assert image is not None, f"cannot read {PHOTOS / name}"
    return image


def dictionary(name: str) -> int:
    return getattr(cv2.aruco, name)


@needs_photos
@pytest.mark.parametrize("name", ALL_PHOTOS)
def test_no_false_ids_in_real_photos(name):
    image = photo(name)
    false = {d: sorted(MarkerDetector(dictionary(d)).detect(image)) for d in NO_MARKER_DICTIONARIES}
    assert not any(false.values()), f"{name}: false ids {false}"
    found = set(MarkerDetector(cv2.aruco.DICT_6X6_250).detect(image))
    assert found <= IDS_6X6.get(name, set()), f"{name}: false DICT_6X6_250 ids {sorted(found - IDS_6X6.get(name, set()))}"


@needs_photos
@pytest.mark.parametrize("name", [n for n in ALL_PHOTOS if n in IDS_6X6])
def test_every_marker_plain_opencv_finds_is_found(name):
    image = photo(name)
    corners, ids, _ = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)).detectMarkers(image)
    plain = set() if ids is None else set(ids.ravel().tolist())
    assert plain == IDS_6X6[name]  # the hand-checked list above
    for refine in ("ecc", "aruco"):
        assert set(MarkerDetector(cv2.aruco.DICT_6X6_250, refine=refine).detect(image)) == plain


def board_fit_rms(image, refine: str, camera_matrix, dist_coeffs) -> float:
    """RMS distance (px) of the detected, undistorted corners from the best homography of the board plane."""
    d6 = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    board = cv2.aruco.CharucoBoard((5, 7), 0.04, 0.02, d6)
    on_board = {int(i): np.asarray(p, float).reshape(4, 3)[:, :2] for i, p in zip(board.getIds().ravel(), board.getObjPoints())}
    found = MarkerDetector(cv2.aruco.DICT_6X6_250, refine=refine).detect(image)
    ids = sorted(found)
    src = np.vstack([on_board[i] for i in ids])
    pixels = cv2.undistortPoints(np.vstack([found[i] for i in ids]).reshape(-1, 1, 2), camera_matrix, dist_coeffs,
                                 P=camera_matrix).reshape(-1, 2)
    h, _ = cv2.findHomography(src, pixels, 0)
    fitted = cv2.perspectiveTransform(src.reshape(-1, 1, 2), h).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum((fitted - pixels) ** 2, axis=1))))


@needs_photos
def test_ecc_corners_fit_the_board_geometry_better_than_opencv_subpixel():
    storage = cv2.FileStorage(str(PHOTOS / "tutorial_camera_charuco.yml"), cv2.FILE_STORAGE_READ)
    k, dist = storage.getNode("camera_matrix").mat(), storage.getNode("distortion_coefficients").mat()
    storage.release()
    rows = []
    for name in BOARD_PHOTOS:
        ecc, subpix = (board_fit_rms(photo(name), refine, k, dist) for refine in ("ecc", "aruco"))
        rows.append((name, ecc, subpix))
        assert ecc < 0.45, f"{name}: ECC corners {ecc:.3f} px RMS off the board plane"
        assert subpix > 1.5 * ecc, f"{name}: ECC {ecc:.3f} px vs OpenCV sub-pixel {subpix:.3f} px"
    print("\n" + "\n".join(f"{n}: ECC {e:.3f} px, OpenCV sub-pixel {s:.3f} px RMS" for n, e, s in rows))


# ----------------------------------------------------------------------------- marker-free photographs
def _package_file(package: str, *parts: str) -> Path | None:
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]).joinpath(*parts)
    return path if path.is_file() else None


# (package, path inside it, licence as the package documents it)
NEGATIVES = [
    ("matplotlib", ("mpl-data", "sample_data", "grace_hopper.jpg"), "US Navy photograph, public domain"),
    ("skimage", ("data", "astronaut.png"), "NASA, public domain"),
    ("skimage", ("data", "brick.png"), "CC0"),
    ("skimage", ("data", "camera.png"), "CC0"),
    ("skimage", ("data", "chelsea.png"), "CC0"),
    ("skimage", ("data", "coffee.png"), "CC0"),
    ("skimage", ("data", "grass.png"), "CC0"),
    ("skimage", ("data", "gravel.png"), "CC0"),
    ("skimage", ("data", "rocket.jpg"), "SpaceX, public domain"),
]


@pytest.mark.parametrize("package, parts, licence", NEGATIVES, ids=[n[1][-1] for n in NEGATIVES])
def test_no_ids_in_marker_free_photographs(package, parts, licence):
    path = _package_file(package, *parts)
    if path is None:
        pytest.skip(f"{package} with {'/'.join(parts)} is not installed (pip install .[test])")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert image is not None
    for name in ("DICT_4X4_50", "DICT_6X6_250"):
        assert not MarkerDetector(dictionary(name)).detect(image), f"{path.name}: false id with {name}"


@needs_photos
def test_focal_length_uncertainty_covers_the_error_on_real_photos():
    """Single-view focal length from each board photo against OpenCV's published multi-view
    calibration of that camera (fx 452.5 px, principal point 38 px below the image centre)."""
    from tracking.calibration import estimate_focal_length

    storage = cv2.FileStorage(str(PHOTOS / "tutorial_camera_charuco.yml"), cv2.FILE_STORAGE_READ)
    fx_truth = storage.getNode("camera_matrix").mat()[0, 0]
    storage.release()
    d6 = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    board = cv2.aruco.CharucoBoard((5, 7), 0.04, 0.02, d6)
    # board frame (y down, z into the board) turned 180 deg about x: z up, camera above, as on a track
    on_board = {int(i): np.asarray(p, float).reshape(4, 3) * [1, -1, 1] for i, p in zip(board.getIds().ravel(), board.getObjPoints())}
    rows = []
    for name in BOARD_PHOTOS:
        found = MarkerDetector(cv2.aruco.DICT_6X6_250).detect(photo(name))
        ids = sorted(found)
        est = estimate_focal_length(np.vstack([on_board[i] for i in ids]), np.vstack([found[i] for i in ids]),
                                    np.repeat(ids, 4), (640, 480))
        error = est.camera_matrix[0, 0] - fx_truth
        rows.append(f"{name}: {est.camera_matrix[0, 0]:.1f} px ({100 * error / fx_truth:+.1f} %), std {est.std_px:.1f} px "
                    f"(markers {est.std_markers_px:.1f}, principal point {est.std_principal_point_px:.1f})")
        assert abs(error) <= 1.5 * est.std_px, rows[-1]
        assert abs(error) > 3 * est.std_markers_px  # the marker spread alone (or a Jacobian std) would not cover it
    print("\n" + "\n".join(rows))
