"""Camera images of a ChArUco board with known intrinsics and lens distortion, rendered with OpenCV alone
(independent of tracking.charuco, which they test): OpenCV's ``CharucoBoard.generateImage`` picture of the
board, warped by the board plane's homography ``K [r1 r2 t]`` into ideal pixels, the lens applied by
``cv2.undistortPoints`` on every (3x3 supersampled) output pixel, then Gaussian blur and sensor noise.

    render = BoardRenderer(board_spec_values..., camera_matrix, dist_coeffs, (width, height))
    image = render(rvec, tvec, blur=0.6, noise=2.0, rng=rng)
"""
from __future__ import annotations

import math

import cv2
import numpy as np

PX_PER_M = 12000  # board picture resolution: about 4 board pixels per camera pixel at the nearest views
# A 800x600 camera of a typical wide-angle USB lens (barrel distortion), for the tests and the coverage bench.
SIZE = (800, 600)
CAMERA_MATRIX = np.array([[700.0, 0.0, 412.0], [0.0, 706.0, 291.0], [0.0, 0.0, 1.0]])
DIST_COEFFS = np.array([-0.28, 0.11, 0.0008, -0.0005, -0.02])


class BoardRenderer:
    """Images of the board at a pose (rvec, tvec of the board frame in the camera frame)."""

    def __init__(self, squares: tuple[int, int], square_m: float, marker_m: float, dictionary: str,
                 camera_matrix=CAMERA_MATRIX, dist_coeffs=DIST_COEFFS, size=SIZE, supersample: int = 3,
                 legacy_pattern: bool = False):
        board = cv2.aruco.CharucoBoard(squares, square_m, marker_m,
                                       cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)))
        board.setLegacyPattern(legacy_pattern)  # OpenCV <= 4.5's colouring when squares[1] is even
        picture = board.generateImage((round(squares[0] * square_m * PX_PER_M), round(squares[1] * square_m * PX_PER_M)))
        self.pad = int(0.015 * PX_PER_M)  # white paper around the board
        self.paper = cv2.copyMakeBorder(picture, *[self.pad] * 4, cv2.BORDER_CONSTANT, value=255)
        w, h = size
        u = (np.arange(w * supersample) + 0.5) / supersample - 0.5  # sub-pixel centres, OpenCV pixel convention
        v = (np.arange(h * supersample) + 0.5) / supersample - 0.5
        grid = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        k = np.asarray(camera_matrix, float)
        self.ideal = cv2.undistortPoints(grid, k, np.asarray(dist_coeffs, float), None, None, k, criteria).reshape(-1, 2).T
        self.k, self.size, self.supersample = k, (int(w), int(h)), supersample
        self.board_size_m = (squares[0] * square_m, squares[1] * square_m)

    def __call__(self, rvec, tvec, blur: float = 0.6, noise: float = 2.0, rng=None,
                 jpeg_quality: int | None = None) -> np.ndarray:
        w, h = self.size
        s = self.supersample
        rot = cv2.Rodrigues(np.asarray(rvec, float))[0]
        to_board = np.linalg.inv(self.k @ np.column_stack([rot[:, 0], rot[:, 1], np.ravel(tvec)]))
        q = to_board @ np.vstack([self.ideal, np.ones(self.ideal.shape[1])])
        map_x = (q[0] / q[2] * PX_PER_M - 0.5 + self.pad).reshape(h * s, w * s).astype(np.float32)
        map_y = (q[1] / q[2] * PX_PER_M - 0.5 + self.pad).reshape(h * s, w * s).astype(np.float32)
        fine = cv2.remap(self.paper, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=90)
        image = cv2.resize(fine.astype(np.float32), self.size, interpolation=cv2.INTER_AREA)
        if blur > 0:
            image = cv2.GaussianBlur(image, (0, 0), blur)
        image = 30 + image * (200 / 255)  # paper and ink are not 0 and 255
        if noise > 0:
            image = image + (rng or np.random.default_rng(0)).normal(0, noise, image.shape)
        image = np.clip(np.round(image), 0, 255).astype(np.uint8)
        if jpeg_quality is not None:  # an MJPEG camera's compression
            image = cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])[1],
                                 cv2.IMREAD_GRAYSCALE)
        return image

    def random_poses(self, n: int, rng, tilt_deg=(15.0, 40.0), depth_m=(0.30, 0.42), centre_range=(0.3, 0.7)
                     ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Board poses tilted about random axes, the board's centre on random points of the image between the
        fractions ``centre`` of its width and height (default: its middle)."""
        centre_board = np.array([self.board_size_m[0] / 2, self.board_size_m[1] / 2, 0.0])
        out = []
        for _ in range(n):
            axis = rng.uniform(0, 2 * math.pi)
            tilt = math.radians(rng.uniform(*tilt_deg)) * np.array([math.cos(axis), math.sin(axis), 0.0])
            rot = cv2.Rodrigues(tilt)[0] @ cv2.Rodrigues(np.array([0.0, 0.0, rng.uniform(-0.3, 0.3)]))[0]
            pixel = np.array([rng.uniform(*centre_range) * self.size[0], rng.uniform(*centre_range) * self.size[1], 1.0])
            ray = np.linalg.solve(self.k, pixel)
            centre = ray * rng.uniform(*depth_m) / ray[2]
            out.append((cv2.Rodrigues(rot)[0].ravel(), centre - rot @ centre_board))
        return out
