"""Pinhole camera geometry shared by the renderer, the calibration and the marker tracker.

Frames: the *track frame* is right-handed with x, y on the track surface (metres) and z up.
The camera frame is OpenCV's (x right, y down, z along the optical axis). A camera pose is
the OpenCV extrinsic pair (R, t) with ``X_cam = R @ X_track + t``. Pixel coordinates follow
OpenCV: integer values are pixel centres.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


def rotation_look_at(position: np.ndarray, target: np.ndarray, up_hint=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-camera rotation for a camera at ``position`` whose optical axis points at ``target``.

    ``up_hint`` is a track-frame direction that should appear pointing *up* in the image
    (towards smaller pixel rows).
    """
    position = np.asarray(position, float)
    z_axis = np.asarray(target, float) - position
    z_axis /= np.linalg.norm(z_axis)
    down = -np.asarray(up_hint, float)
    x_axis = np.cross(down, z_axis)
    if np.linalg.norm(x_axis) < 1e-9:
        raise ValueError("up_hint: parallel to the viewing direction")
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    return np.stack([x_axis, y_axis, z_axis])


@dataclass
class PinholeCamera:
    """Intrinsics (camera matrix, OpenCV distortion coefficients) plus the track-to-camera pose."""

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    rotation: np.ndarray  # 3x3, track -> camera
    translation: np.ndarray  # (3,), track -> camera
    image_size: tuple[int, int]  # (width, height) in pixels
    _homography_cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        self.camera_matrix = np.asarray(self.camera_matrix, float).reshape(3, 3)
        self.dist_coeffs = np.asarray(self.dist_coeffs, float).ravel()
        self.rotation = np.asarray(self.rotation, float).reshape(3, 3)
        self.translation = np.asarray(self.translation, float).ravel()
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))

    @property
    def position(self) -> np.ndarray:
        """Camera centre in the track frame (metres)."""
        return -self.rotation.T @ self.translation

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist_coeffs != 0.0))

    def project(self, points_track: np.ndarray, distort: bool = True) -> np.ndarray:
        """Pixels (N,2) of track-frame points (N,3). ``distort=False`` gives ideal pinhole pixels."""
        pts = np.asarray(points_track, float).reshape(-1, 3)
        cam = pts @ self.rotation.T + self.translation
        if not distort or not self.has_distortion:
            uv = cam[:, :2] / cam[:, 2:3]
            return uv @ self.camera_matrix[:2, :2].T + self.camera_matrix[:2, 2]
        rvec, _ = cv2.Rodrigues(self.rotation)
        px, _ = cv2.projectPoints(pts, rvec, self.translation, self.camera_matrix, self.dist_coeffs)
        return px.reshape(-1, 2)

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Map measured (distorted) pixels to ideal pinhole pixels with the same camera matrix."""
        px = np.asarray(pixels, float).reshape(-1, 2)
        if not self.has_distortion or len(px) == 0:
            return px.copy()
        out = cv2.undistortPoints(px.reshape(-1, 1, 2), self.camera_matrix, self.dist_coeffs,
                                  P=self.camera_matrix)
        return out.reshape(-1, 2)

    def plane_homography(self, height_m: float = 0.0) -> np.ndarray:
        """3x3 homography from track (x, y) on the plane z = height_m to ideal pixels."""
        key = float(height_m)
        hom = self._homography_cache.get(key)
        if hom is None:
            r = self.rotation
            hom = self.camera_matrix @ np.column_stack([r[:, 0], r[:, 1], r[:, 2] * key + self.translation])
            hom = hom / hom[2, 2]
            self._homography_cache[key] = hom
        return hom

    def pixels_to_plane(self, pixels: np.ndarray, height_m: float = 0.0, undistort: bool = True) -> np.ndarray:
        """Intersect the viewing rays of ``pixels`` (N,2) with the horizontal plane z = height_m.

        This is the marker-height correction: a marker on a car roof is not on the track plane,
        so its pixels are mapped through the homography of its own plane, which depends on where
        the camera is (the ray from the camera centre through the pixel meets z = h closer to the
        camera's nadir than it meets z = 0).
        """
        px = self.undistort_pixels(pixels) if undistort else np.asarray(pixels, float).reshape(-1, 2)
        hinv = np.linalg.inv(self.plane_homography(height_m))
        homog = np.column_stack([px, np.ones(len(px))]) @ hinv.T
        return homog[:, :2] / homog[:, 2:3]
