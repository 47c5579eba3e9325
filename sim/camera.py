"""The synthetic overhead camera (a sensor simulation): it renders the simulator's world as a monochrome
overhead camera would see it: floor, track surface and boundary lines (polylines in track metres),
fixed ArUco markers at surveyed points, and each car as a box with an ArUco marker (on a white label)
on its roof, through a pinhole camera with optional lens distortion, plus motion blur (sub-exposure
samples along each car's motion), defocus blur, uneven lighting and sensor noise, all seeded. It is a
``tracking.camera.CameraSource``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import cv2
import numpy as np

from tracking.calibration import FixedMarker, marker_corners_track
from tracking.camera import CameraError, Frame
from tracking.geometry import PinholeCamera, rotation_look_at
from tracking.motion import ctrv_transition
from vehicles.params import MARKER_DICTIONARY, MarkerParams


# --------------------------------------------------------------------------- synthetic camera
@dataclass(frozen=True)
class CarPose:
    """Car reference point and heading in the track frame. ``speed`` and ``yaw_rate`` only drive
    the motion blur (the car moves along a constant-turn arc during the exposure)."""

    marker_id: int
    x: float
    y: float
    heading: float
    speed: float = 0.0
    yaw_rate: float = 0.0


@dataclass(frozen=True)
class CarAppearance:
    """Box body with a square marker on a white label on its roof (1/28 scale defaults)."""

    length_m: float = 0.16
    width_m: float = 0.075
    roof_height_m: float = MarkerParams.height_m  # height of the marker above the track surface
    marker_size_m: float = MarkerParams.size_m
    label_margin_m: float = 0.008  # white border around the marker (quiet zone)
    marker_offset_m: float = 0.0  # marker centre ahead of the car reference point
    body_gray: int = 40
    roof_gray: int = 70


@dataclass(frozen=True)
class RenderEffects:
    exposure_s: float = 0.003
    defocus_sigma_px: float = 0.5  # Gaussian point-spread, 0 = sharp
    noise_sigma: float = 2.0  # additive sensor noise, grey levels
    vignetting: float = 0.25  # relative brightness loss in the image corners
    light_variation: float = 0.2  # amplitude of a smooth illumination ramp/hotspot
    max_motion_samples: int = 8
    seed: int = 0


@dataclass
class TrackDrawing:
    """What the floor shows: boundary polylines in track metres (closed loops for a circuit)."""

    left: np.ndarray | None = None
    right: np.ndarray | None = None
    arena_bounds: tuple[float, float, float, float] = (0.0, 0.0, 5.0, 3.0)  # x_min, y_min, x_max, y_max
    line_width_m: float = 0.02
    floor_gray: int = 150
    surface_gray: int = 95
    line_gray: int = 235


def overhead_camera(arena_bounds=(0.0, 0.0, 5.0, 3.0), image_size=(1280, 800), height_m: float = 3.0,
                    offset_m=(0.0, -0.35), margin: float = 1.04, dist_coeffs=None) -> PinholeCamera:
    """A camera ``height_m`` above the arena, displaced by ``offset_m`` from the centre and aimed
    at the centre (so slightly tilted), with the focal length that just fits the arena (times
    ``margin``) in the image. The arena's long side runs along the image width."""
    x0, y0, x1, y1 = arena_bounds
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    position = centre + np.array([offset_m[0], offset_m[1], height_m])
    long_axis_x = (x1 - x0) >= (y1 - y0)
    up_hint = (0.0, 1.0, 0.0) if long_axis_x else (-1.0, 0.0, 0.0)
    rot = rotation_look_at(position, centre, up_hint)
    trans = -rot @ position
    w, h = image_size
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float) * 1.0
    corners = corners + (corners - centre) * (margin - 1.0)
    cam = corners @ rot.T + trans
    norm = cam[:, :2] / cam[:, 2:3]
    focal = min((w / 2) / np.max(np.abs(norm[:, 0])), (h / 2) / np.max(np.abs(norm[:, 1])))
    k = np.array([[focal, 0, (w - 1) / 2], [0, focal, (h - 1) / 2], [0, 0, 1]])
    return PinholeCamera(k, np.zeros(5) if dist_coeffs is None else dist_coeffs, rot, trans, (w, h))


class _RenderCanvas:
    """Undistorted render target. With lens distortion it is larger than the sensor image so
    the distorted image can be resampled from it."""

    def __init__(self, camera: PinholeCamera):
        w, h = camera.image_size
        self.remap = None
        pad_x = pad_y = 0
        if camera.has_distortion:
            grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)), -1)
            ideal = camera.undistort_pixels(grid.reshape(-1, 2)).reshape(h, w, 2).astype(np.float32)
            pad_x = int(np.clip(math.ceil(max(-ideal[..., 0].min(), ideal[..., 0].max() - (w - 1), 0)) + 2, 0, w))
            pad_y = int(np.clip(math.ceil(max(-ideal[..., 1].min(), ideal[..., 1].max() - (h - 1), 0)) + 2, 0, h))
            ideal[..., 0] += pad_x
            ideal[..., 1] += pad_y
            self.remap = cv2.convertMaps(ideal[..., 0], ideal[..., 1], cv2.CV_16SC2)
        k = camera.camera_matrix.copy()
        k[0, 2] += pad_x
        k[1, 2] += pad_y
        self.camera = PinholeCamera(k, np.zeros(5), camera.rotation, camera.translation,
                                    (w + 2 * pad_x, h + 2 * pad_y))
        self.size = self.camera.image_size

    def to_sensor(self, canvas: np.ndarray) -> np.ndarray:
        if self.remap is None:
            return canvas
        return cv2.remap(canvas, self.remap[0], self.remap[1], cv2.INTER_LINEAR, borderValue=0)


_SUPERSAMPLE = 4


class SyntheticCamera:
    """Renders car poses into monochrome frames of a simulated overhead camera.

    Use :meth:`render` with explicit poses, or pass ``world(t) -> [CarPose | (id, x, y, heading)]``
    and call :meth:`read` for frames at ``fps`` starting at ``t0_s``.
    """

    def __init__(self, camera: PinholeCamera, track: TrackDrawing | None = None,
                 fixed_markers: Sequence[FixedMarker] = (), car: CarAppearance = CarAppearance(),
                 effects: RenderEffects = RenderEffects(), dictionary: int = getattr(cv2.aruco, MARKER_DICTIONARY),
                 world: Callable[[float], Sequence] | None = None, fps: float = 60.0, t0_s: float = 0.0):
        for marker in fixed_markers:
            if marker.heading_rad is None:
                raise ValueError(f"fixed_markers: marker {marker.marker_id} needs a heading to be rendered")
        self.camera = camera
        self.track = track or TrackDrawing()
        self.car = car
        self.effects = effects
        self.world = world
        self.fps = float(fps)
        self.t0_s = float(t0_s)
        self._dictionary = cv2.aruco.getPredefinedDictionary(dictionary)
        self._index = 0
        self._canvas = _RenderCanvas(camera)
        self._marker_textures: dict[tuple[int, int], np.ndarray] = {}
        self._rng = np.random.default_rng(effects.seed)
        self._background = self._render_background(fixed_markers)
        self._gain = self._lighting_gain()
        self._noise = self._noise_bank()
        # The static scene as the sensor sees it (lighting, defocus), computed once: per frame only
        # the regions the cars changed go through the lighting and the blur again (render()).
        self._background_sensor = self._sensor_effects(self._canvas.to_sensor(self._background))

    # ---- static parts
    def _render_background(self, fixed_markers) -> np.ndarray:
        tr = self.track
        x0, y0, x1, y1 = tr.arena_bounds
        res = 0.0025  # floor texture resolution, metres per texel
        margin = 1.0  # floor extends beyond the arena
        tw, th = int((x1 - x0 + 2 * margin) / res), int((y1 - y0 + 2 * margin) / res)
        tex_rng = np.random.default_rng(self.effects.seed + 1)
        # Low-frequency floor mottling: coarse noise upsampled.
        coarse = tex_rng.normal(0.0, 6.0, (th // 40 + 2, tw // 40 + 2)).astype(np.float32)
        texture = tr.floor_gray + cv2.resize(coarse, (tw, th), interpolation=cv2.INTER_CUBIC)
        texture = np.clip(texture, 0, 255).astype(np.uint8)

        def to_texel(points):
            pts = np.asarray(points, float)[:, :2]
            return np.column_stack([(pts[:, 0] - (x0 - margin)) / res - 0.5,
                                    ((y1 + margin) - pts[:, 1]) / res - 0.5])

        def poly(points):  # cv2 fixed-point polygon (4 fractional bits)
            return np.round(to_texel(points) * 16).astype(np.int32)

        if tr.left is not None and tr.right is not None:
            left, right = np.asarray(tr.left, float), np.asarray(tr.right, float)
            closed = np.linalg.norm(left[0] - left[-1]) < 0.05 and np.linalg.norm(right[0] - right[-1]) < 0.05
            if closed:
                area = lambda p: abs(np.dot(p[:, 0], np.roll(p[:, 1], 1)) - np.dot(p[:, 1], np.roll(p[:, 0], 1)))
                outer, inner = (left, right) if area(left) > area(right) else (right, left)
                cv2.fillPoly(texture, [poly(outer)], tr.surface_gray, cv2.LINE_AA, 4)
                cv2.fillPoly(texture, [poly(inner)], tr.floor_gray, cv2.LINE_AA, 4)
            else:
                cv2.fillPoly(texture, [poly(np.vstack([left, right[::-1]]))], tr.surface_gray, cv2.LINE_AA, 4)
            thickness = max(1, int(round(tr.line_width_m / res)))
            for line in (left, right):
                cv2.polylines(texture, [poly(line)], closed, tr.line_gray, thickness, cv2.LINE_AA, 4)
        # Texel -> track -> canvas homography; the texture is only a little finer than the image.
        tex_to_track = np.array([[res, 0, x0 - margin + 0.5 * res], [0, -res, y1 + margin - 0.5 * res], [0, 0, 1]])
        hom = self._canvas.camera.plane_homography(0.0) @ tex_to_track
        texture = cv2.GaussianBlur(texture, (0, 0), 0.6)
        background = cv2.warpPerspective(texture, hom, self._canvas.size, flags=cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_CONSTANT, borderValue=tr.floor_gray)
        for marker in fixed_markers:
            label = marker.size * (1 + 2 / 6)  # one-cell white quiet zone around the marker
            self._draw_objects(background, [[
                ("poly", marker_corners_track(marker.x, marker.y, marker.heading_rad, label, marker.z), 255),
                ("marker", marker.marker_id, marker.x, marker.y, marker.heading_rad, marker.size, marker.z),
            ]])
        return background

    def _lighting_gain(self) -> np.ndarray:
        """Vignetting times a smooth illumination field, as uint8 gain with 1.0 == 128."""
        w, h = self.camera.image_size
        fx = self.camera.camera_matrix[0, 0]
        u = (np.arange(w) - (w - 1) / 2) / fx
        v = (np.arange(h) - (h - 1) / 2) / fx
        r2 = u[None, :] ** 2 + v[:, None] ** 2
        vignette = 1.0 - self.effects.vignetting * r2 / r2.max()
        rng = np.random.default_rng(self.effects.seed + 2)
        cx, cy = rng.uniform(-0.5, 0.5, 2) * np.array([u.max(), v.max()])
        hotspot = np.exp(-((u[None, :] - cx) ** 2 + (v[:, None] - cy) ** 2) / (0.5 * u.max() ** 2))
        ramp_dir = rng.normal(size=2)
        ramp = (u[None, :] * ramp_dir[0] + v[:, None] * ramp_dir[1]) / (np.linalg.norm(ramp_dir) * u.max())
        light = 1.0 + self.effects.light_variation * (hotspot - 0.5 + 0.5 * ramp)
        return np.clip(np.round(128 * vignette * light), 0, 255).astype(np.uint8)

    def _noise_bank(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Pre-drawn Gaussian noise; each frame uses a randomly offset window of it. Kept as its
        positive and negative parts in uint8 (at most one is non-zero per pixel), so adding it is two
        saturating uint8 operations: the same result as a signed addition, at a fraction of the cost."""
        if self.effects.noise_sigma <= 0:
            return None
        w, h = self.camera.image_size
        rng = np.random.default_rng(self.effects.seed + 3)
        noise = np.clip(np.round(rng.normal(0.0, self.effects.noise_sigma, (h + 64, w + 64))), -255, 255)
        return np.clip(noise, 0, 255).astype(np.uint8), np.clip(-noise, 0, 255).astype(np.uint8)

    def _sensor_effects(self, image: np.ndarray, gain: np.ndarray | None = None) -> np.ndarray:
        """Lighting (vignetting, illumination) and defocus of a sensor image, or of a region of it
        with the matching region of the gain."""
        image = cv2.multiply(image, self._gain if gain is None else gain, scale=1.0 / 128.0)
        if self.effects.defocus_sigma_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), self.effects.defocus_sigma_px)
        return image

    def _marker_texture(self, marker_id: int, px: int) -> np.ndarray:
        key = (marker_id, px)
        if key not in self._marker_textures:
            cells = self._dictionary.markerSize + 2
            side = cells * max(4, int(math.ceil(px / cells)))
            self._marker_textures[key] = cv2.aruco.generateImageMarker(self._dictionary, marker_id, side, borderBits=1)
        return self._marker_textures[key]

    # ---- drawing
    def _draw_objects(self, canvas: np.ndarray, samples: list[list[tuple]]) -> tuple[int, int, int, int] | None:
        """Draw the objects of each motion sample (supersampled, area-averaged) and average the
        samples. Objects: ("poly", points (N,3), gray) filled convex polygons in order, and
        ("marker", id, x, y, heading, size, z) flat markers. Returns the canvas box it may have
        changed (u0, v0, u1, v1), None if it is outside the canvas."""
        cam = self._canvas.camera
        ss = _SUPERSAMPLE
        # Every object's points, projected once (one call for all of them).
        points = [obj[1] if obj[0] == "poly" else marker_corners_track(*obj[2:5], obj[5], obj[6])
                  for objs in samples for obj in objs]
        pts = cam.project(np.vstack(points), distort=False)
        projected = np.split(pts, np.cumsum([len(p) for p in points])[:-1])
        cw, ch = self._canvas.size
        u0, v0 = np.floor(pts.min(axis=0)).astype(int) - 2
        u1, v1 = np.ceil(pts.max(axis=0)).astype(int) + 3
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, cw), min(v1, ch)
        if u1 <= u0 or v1 <= v0:
            return None
        base = canvas[v0:v1, u0:u1]
        hi_base = cv2.resize(base, None, fx=ss, fy=ss, interpolation=cv2.INTER_NEAREST)
        # canvas pixel coords -> supersampled patch pixel coords (pixel centres at integers)
        to_hi = np.array([[ss, 0, ss * (0.5 - u0) - 0.5], [0, ss, ss * (0.5 - v0) - 0.5], [0, 0, 1]])
        acc = np.zeros(base.shape, np.float32)
        next_projected = iter(projected)
        for objs in samples:
            hi = hi_base.copy()
            for obj in objs:
                if obj[0] == "poly":
                    p = next(next_projected)
                    p = p @ to_hi[:2, :2].T + to_hi[:2, 2]
                    hull = cv2.convexHull(np.round(p * 16).astype(np.int32))
                    cv2.fillConvexPoly(hi, hull, int(obj[2]), cv2.LINE_AA, 4)
                else:
                    marker_id = obj[1]
                    corners_px = next(next_projected)
                    side_px = ss * np.max(np.linalg.norm(np.diff(corners_px, axis=0, append=corners_px[:1]), axis=1))
                    tex = self._marker_texture(marker_id, int(side_px))
                    s = tex.shape[0]
                    tex_corners = np.array([[-0.5, -0.5], [s - 0.5, -0.5], [s - 0.5, s - 0.5], [-0.5, s - 0.5]])
                    hom = to_hi @ cv2.getPerspectiveTransform(tex_corners.astype(np.float32),
                                                              corners_px.astype(np.float32)).astype(float)
                    cv2.warpPerspective(tex, hom, (hi.shape[1], hi.shape[0]), dst=hi, flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_TRANSPARENT)
            acc += cv2.resize(hi, (base.shape[1], base.shape[0]), interpolation=cv2.INTER_AREA)
        canvas[v0:v1, u0:u1] = np.clip(np.round(acc / len(samples)), 0, 255).astype(np.uint8)
        return int(u0), int(v0), int(u1), int(v1)

    def _car_objects(self, marker_id: int, x: float, y: float, heading: float) -> list[tuple]:
        car = self.car
        c, s = math.cos(heading), math.sin(heading)
        hl, hw = car.length_m / 2, car.width_m / 2
        local = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
        xy = local @ np.array([[c, s], [-s, c]]) + np.array([x, y])
        clearance = 0.005
        box = np.vstack([np.column_stack([xy, np.full(4, clearance)]), np.column_stack([xy, np.full(4, car.roof_height_m)])])
        mx, my = x + car.marker_offset_m * c, y + car.marker_offset_m * s
        label = marker_corners_track(mx, my, heading, car.marker_size_m + 2 * car.label_margin_m, car.roof_height_m)
        return [
            ("poly", box, car.body_gray),
            ("poly", box[4:], car.roof_gray),
            ("poly", label, 255),
            ("marker", marker_id, mx, my, heading, car.marker_size_m, car.roof_height_m),
        ]

    def _motion_samples(self, pose: CarPose) -> list[tuple[float, float, float]]:
        exposure = self.effects.exposure_s
        travel_m = abs(pose.speed) * exposure + abs(pose.yaw_rate) * exposure * self.car.length_m / 2
        metres_per_px = self.camera.position[2] / self.camera.camera_matrix[0, 0]
        n = int(np.clip(math.ceil(travel_m / metres_per_px * 2), 1, self.effects.max_motion_samples))
        if n == 1:
            return [(pose.x, pose.y, pose.heading)]
        state = np.array([pose.x, pose.y, pose.heading, pose.speed, pose.yaw_rate])
        offsets = (np.arange(n) + 0.5) / n * exposure - exposure / 2  # centred on the capture time
        return [tuple(ctrv_transition(state, dt)[:3]) for dt in offsets]

    def render(self, car_poses: Sequence, t_s: float) -> Frame:
        """Frame showing the cars at time ``t_s`` (the middle of the exposure)."""
        canvas = self._background.copy()
        poses = [raw if isinstance(raw, CarPose) else CarPose(int(raw[0]), *map(float, raw[1:])) for raw in car_poses]
        # Painter's order: farthest from the camera's ground point first. The projected box of a car
        # includes its side walls, which reach towards the image centre; drawn after a nearer car
        # beside it, they covered that car's roof marker although the roof hides those walls (HIL
        # seed 16: the RD3G marker vanished 1-2 cm from the other car and the car was lost).
        cam_x, cam_y = self.camera.position[:2]
        poses.sort(key=lambda p: -math.hypot(p.x - cam_x, p.y - cam_y))
        boxes = []
        for pose in poses:
            samples = [self._car_objects(pose.marker_id, *xyh) for xyh in self._motion_samples(pose)]
            box = self._draw_objects(canvas, samples)
            if box is not None:
                boxes.append(box)
        image = self._sensor_image(canvas, boxes)
        if self._noise is not None:
            h, w = image.shape
            oy, ox = self._rng.integers(0, 64, 2)
            positive, negative = self._noise
            image = cv2.subtract(cv2.add(image, positive[oy:oy + h, ox:ox + w]), negative[oy:oy + h, ox:ox + w])
        frame = Frame(image, float(t_s), self._index)
        self._index += 1
        return frame

    def _sensor_image(self, canvas: np.ndarray, boxes: list[tuple[int, int, int, int]]) -> np.ndarray:
        """The sensor image of ``canvas``, which differs from the static background only inside
        ``boxes``: the static sensor image with those boxes (grown by the blur's radius) redone from
        regions another radius larger. Pixel for pixel the same as _sensor_effects on the whole
        canvas (at the image border a region ends there too, so the blur's border rule is the same). With lens distortion the whole image is
        resampled (the remap mixes pixels from anywhere), so it is done in full."""
        if self._canvas.remap is not None:
            return self._sensor_effects(self._canvas.to_sensor(canvas))
        image = self._background_sensor.copy()
        h, w = image.shape
        r = self._blur_radius()
        for u0, v0, u1, v1 in boxes:
            # The blur spreads the box's changes r pixels out, and needs r more pixels to compute those.
            u0, v0, u1, v1 = max(u0 - r, 0), max(v0 - r, 0), min(u1 + r, w), min(v1 + r, h)
            a0, b0, a1, b1 = max(u0 - r, 0), max(v0 - r, 0), min(u1 + r, w), min(v1 + r, h)
            region = self._sensor_effects(canvas[b0:b1, a0:a1], self._gain[b0:b1, a0:a1])
            image[v0:v1, u0:u1] = region[v0 - b0:v1 - b0, u0 - a0:u1 - a0]
        return image

    def _blur_radius(self) -> int:
        """Pixels the defocus blur reaches: OpenCV's kernel for 8-bit images has radius 3 sigma; one
        more for rounding."""
        return int(math.ceil(3 * self.effects.defocus_sigma_px)) + 1 if self.effects.defocus_sigma_px > 0 else 0

    def read(self) -> Frame:
        if self.world is None:
            raise CameraError("SyntheticCamera.read() needs a world(t) callback; use render(poses, t) instead")
        t = self.t0_s + self._index / self.fps
        return self.render(self.world(t), t)

    def close(self) -> None:
        pass
