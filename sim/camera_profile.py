"""Camera profiles of the synthetic overhead camera (``--camera-profile ideal|realistic``): every
imperfection of a real USB camera as a typed, seeded parameter.

``ideal`` is the renderer as it was before profiles (pinhole lens, global shutter, no compression, no
delivery delay). ``realistic`` stands for a 1280x800 60 fps rolling-shutter USB camera (UVC, MJPEG)
with a wide M12 lens, 3 m above a 3 x 5 m arena. Its numbers are *typical* values (datasheets of such
cameras and published OpenCV calibrations of wide USB lenses), chosen by us, not measured on one camera:

==========================  ===============  ================================================================
parameter                   realistic        where the number comes from
==========================  ===============  ================================================================
dist_coeffs k1, k2, p1, p2  -0.12, 0.03,     moderate barrel distortion of a ~90 degree HFOV M12 lens;
                            5e-4, -3e-4      published calibrations of wide USB cameras report k1 from
                                             -0.05 to -0.4, k2 of the opposite sign and a few tenths of it,
                                             tangential terms below 1e-3 (lens decentring)
calibration_views           20               the lens the tracker uses is estimated, not told: calibrate-camera
                                             (tracking.charuco) on 20 rendered views of an A4 ChArUco board
                                             (7 x 5 squares of 37 mm, 28 mm markers, as make-board's A4
                                             page) held 0.45-0.7 m from the lens, tilted 15-40 degrees,
                                             anywhere in the image, through the true lens with the
                                             profile's defocus, noise and JPEG (sim.charuco_views); cached
                                             per profile and seed in runs/cache/camera_calibration/
effects.jpeg_quality        75               MJPEG quality of UVC cameras (libjpeg scale; webcams stream at
                                             about 70-85 to fit 1280x800 at 60 fps into USB 2.0)
effects.readout_s           0.010 s          rolling-shutter readout of a 800-row sensor at 60 fps (rows
                                             read over most of the 16.7 ms frame period; CMOS datasheets
                                             give 8-15 ms)
effects.exposure_s          0.004 s          indoor auto exposure under bright lab lighting
effects.flicker_amplitude   0.04             +-4 % brightness at twice the mains frequency (LED or
                            at 100 Hz        fluorescent lighting on 50 Hz mains)
latency_s                   0.030 s          UVC exposure-to-delivery delay (readout, MJPEG encoding, USB
                                             transfer, driver buffering: 20-50 ms is usual at 60 fps)
jitter_s                    0.003 s          standard deviation of that delay (USB scheduling)
survey_sigma_m              0.003 m          fixed markers surveyed with a tape over a 5 m arena: a few
                                             mm per coordinate (issue 33's independent renderer: 3 mm)
latency_known_s             0.030 s          the loop is told the nominal delay (measured once, e.g. by
                                             filming a millisecond clock; OpenCVCamera's latency_s)
==========================  ===============  ================================================================

The marker glued off the car's reference point is a property of each car, not of the camera: the car
file's ``marker.offset_forward_m``, ``marker.offset_left_m`` and ``marker.yaw_rad`` (vehicles/params.py).
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.camera import RenderEffects
from sim.charuco_views import BoardRenderer
from tracking.calibration import (CalibrationError, CameraCalibration, FixedMarkerSet, Intrinsics, calibrate_image,
                                  load_intrinsics, save_intrinsics)
from tracking.charuco import BoardDetector, CharucoBoardSpec, calibrate_intrinsics
from tracking.geometry import PinholeCamera

# One effect of the realistic profile alone on the ideal one ("ideal+jpeg"), to measure what each costs:
# the profile fields (``effects.X``: a RenderEffects field) it takes from the realistic profile.
SINGLE_EFFECTS = {
    "lens": ("dist_coeffs",),  # distortion rendered, and known exactly to the tracker
    "calibration": ("dist_coeffs", "calibration_views"),  # the lens estimated from rendered board views
    "jpeg": ("effects.jpeg_quality",),
    "rolling_shutter": ("effects.readout_s",),
    "latency": ("latency_s", "jitter_s", "latency_known_s"),
    "survey": ("survey_sigma_m",),
    "motion_blur": ("effects.exposure_s",),
    "flicker": ("effects.flicker_amplitude", "effects.flicker_hz"),
}
PROFILE_NAMES = ("ideal", "realistic", *(f"ideal+{name}" for name in SINGLE_EFFECTS))


@dataclass(frozen=True)
class CameraProfile:
    """What the synthetic camera does to its images and their timestamps, and what the tracker is told.

    ``dist_coeffs``: the lens's true OpenCV distortion (k1, k2, p1, p2, k3), rendered through.
    ``calibration_views``: 0, the tracker is told the true intrinsics; N, it uses those calibrate-camera estimates
    from N rendered ChArUco board views (:meth:`estimated`).
    ``latency_s``/``jitter_s``: a frame is delivered ``latency_s`` + N(0, ``jitter_s``) after its exposure
    (seeded, never before its exposure nor before the previous frame); ``latency_known_s`` is what the loop
    subtracts from the delivery time to stamp it (0: the loop knows only the delivery time).
    ``survey_sigma_m``: standard deviation of each surveyed coordinate of the fixed markers the camera pose
    is calibrated from (the renderer draws them at their true places).
    """

    name: str = "ideal"
    effects: RenderEffects = RenderEffects()
    dist_coeffs: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    calibration_views: int = 0
    latency_s: float = 0.0
    jitter_s: float = 0.0
    latency_known_s: float = 0.0
    survey_sigma_m: float = 0.0

    def __post_init__(self) -> None:
        for key in ("latency_s", "jitter_s", "latency_known_s", "survey_sigma_m"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"camera profile {self.name}: {key}: must be >= 0 (seconds), got {getattr(self, key)}")
        if len(self.dist_coeffs) != 5:
            raise ValueError(f"camera profile {self.name}: dist_coeffs: 5 OpenCV coefficients (k1, k2, p1, p2, k3)")
        if self.calibration_views != 0 and not 3 <= self.calibration_views <= 100:
            raise ValueError(f"camera profile {self.name}: calibration_views: 0 (true intrinsics) or 3..100 board "
                             f"views, got {self.calibration_views}")

    @property
    def seed(self) -> int:
        return self.effects.seed

    def with_seed(self, seed: int) -> "CameraProfile":
        return dataclasses.replace(self, effects=dataclasses.replace(self.effects, seed=int(seed)))

    def estimated(self, camera: PinholeCamera, cache_dir: str | os.PathLike | None = None) -> PinholeCamera:
        """``camera`` (the renderer's true one, with this profile's lens) with the intrinsics a lab would use:
        the true ones without ``calibration_views``, else :func:`board_calibration`'s estimate (computed once
        per profile, seed and camera, and cached as an intrinsics file in ``cache_dir``, default
        runs/cache/camera_calibration/ of this checkout)."""
        if self.calibration_views == 0:
            return PinholeCamera(camera.camera_matrix.copy(), np.asarray(camera.dist_coeffs, float).copy(),
                                 camera.rotation.copy(), camera.translation.copy(), camera.image_size)
        key = hashlib.sha256(repr((_BOARD_VERSION, camera.camera_matrix.round(9).tolist(), self.dist_coeffs,
                                   camera.image_size, self.calibration_views, self.effects.defocus_sigma_px,
                                   self.effects.noise_sigma, self.effects.jpeg_quality)).encode()).hexdigest()[:16]
        path = Path(cache_dir or DEFAULT_CACHE_DIR) / f"{self.name}-seed{self.seed}-{key}.json"
        intrinsics = None
        if path.is_file():
            try:
                intrinsics = load_intrinsics(path)
            except CalibrationError:
                pass  # a damaged cache entry is recomputed
        if intrinsics is None:
            intrinsics = board_calibration(self, camera)
            save_intrinsics(path, intrinsics)
        return PinholeCamera(intrinsics.camera_matrix, intrinsics.dist_coeffs, camera.rotation.copy(),
                             camera.translation.copy(), camera.image_size)

    def lab_calibration(self, camera: PinholeCamera, image: np.ndarray, marker_set: FixedMarkerSet) -> CameraCalibration:
        """The calibration a lab would make of ``camera`` (the renderer's true one): :meth:`estimated`'s
        intrinsics, and the camera pose from `calibrate` on ``image`` (a frame showing the fixed markers)
        with the markers as :meth:`surveyed`."""
        estimated = self.estimated(camera)
        return calibrate_image(image, self.surveyed(marker_set),
                               Intrinsics(estimated.camera_matrix, estimated.dist_coeffs, estimated.image_size))

    def surveyed(self, marker_set: FixedMarkerSet) -> FixedMarkerSet:
        """The fixed markers as a lab surveyed them: x, y, z each off by N(0, survey_sigma_m), seeded."""
        if self.survey_sigma_m == 0:
            return marker_set
        rng = np.random.default_rng(self.seed + 5)
        moved = {}
        for marker_id in sorted(marker_set.markers):
            m = marker_set.markers[marker_id]
            dx, dy, dz = rng.normal(0.0, self.survey_sigma_m, 3)
            moved[marker_id] = dataclasses.replace(m, x=m.x + dx, y=m.y + dy, z=m.z + dz)
        return dataclasses.replace(marker_set, markers=moved)


DEFAULT_CACHE_DIR = Path(__file__).resolve().parents[1] / "runs" / "cache" / "camera_calibration"
CALIBRATION_BOARD = CharucoBoardSpec(7, 5, 0.037, 0.028)  # make-board's A4 page (docstring)
_BOARD_VERSION = 1  # of the views below: a change invalidates the cache


def board_calibration(profile: CameraProfile, camera: PinholeCamera) -> Intrinsics:
    """calibrate-camera's intrinsics from ``profile.calibration_views`` ChArUco views rendered through the true
    lens (``camera``'s matrix, ``profile.dist_coeffs``) with the profile's defocus, noise and JPEG, seeded by
    the profile's seed (CalibrationError if too few views are usable)."""
    board = CALIBRATION_BOARD
    render = BoardRenderer((board.squares_x, board.squares_y), board.square_length_m, board.marker_length_m,
                           board.dictionary, camera.camera_matrix, np.asarray(profile.dist_coeffs, float),
                           camera.image_size, supersample=1)
    rng = np.random.default_rng(profile.seed + 6)
    detector = BoardDetector(board)
    fx = profile.effects
    views = [detector.detect(render(rvec, tvec, blur=fx.defocus_sigma_px, noise=fx.noise_sigma, rng=rng,
                                    jpeg_quality=fx.jpeg_quality), f"view {i}")
             for i, (rvec, tvec) in enumerate(render.random_poses(profile.calibration_views, rng, depth_m=(0.45, 0.7),
                                                                  centre_range=(0.15, 0.85)))]
    return calibrate_intrinsics(views, camera.image_size).intrinsics


def _realistic_effects(seed: int) -> RenderEffects:
    return RenderEffects(exposure_s=0.004, jpeg_quality=75, readout_s=0.010, flicker_amplitude=0.04,
                         flicker_hz=100.0, seed=seed)


def camera_profile(name: str, seed: int = 0) -> CameraProfile:
    """The named profile (``PROFILE_NAMES``) with its random effects seeded by ``seed``."""
    if name == "ideal":
        return CameraProfile("ideal", RenderEffects(seed=seed))
    if name == "realistic":
        return CameraProfile("realistic", _realistic_effects(seed), dist_coeffs=(-0.12, 0.03, 5e-4, -3e-4, 0.0),
                             calibration_views=20,
                             latency_s=0.030, jitter_s=0.003,
                             latency_known_s=0.030, survey_sigma_m=0.003)
    if name.startswith("ideal+") and name[6:] in SINGLE_EFFECTS:
        real, ideal = camera_profile("realistic", seed), camera_profile("ideal", seed)
        top = {k: getattr(real, k) for k in SINGLE_EFFECTS[name[6:]] if not k.startswith("effects.")}
        fx = {k[8:]: getattr(real.effects, k[8:]) for k in SINGLE_EFFECTS[name[6:]] if k.startswith("effects.")}
        return dataclasses.replace(ideal, name=name, effects=dataclasses.replace(ideal.effects, **fx), **top)
    raise ValueError(f"camera profile: {name!r} is not one of {', '.join(PROFILE_NAMES)}")


class DeliveryClock:
    """Delivery times of frames: exposure time + latency + seeded jitter, kept in order."""

    def __init__(self, profile: CameraProfile):
        self.profile = profile
        self._rng = np.random.default_rng(profile.seed + 4)
        self._last = -np.inf

    def delivery_time(self, t_exposure_s: float) -> float:
        p = self.profile
        t = t_exposure_s + p.latency_s + (p.jitter_s * float(self._rng.normal()) if p.jitter_s > 0 else 0.0)
        t = max(t, t_exposure_s, self._last)
        self._last = t
        return t

    def stamp(self, t_delivery_s: float) -> float:
        """The capture time the loop believes: delivery time minus the latency it was told."""
        return t_delivery_s - self.profile.latency_known_s


class DelayedDelivery:
    """Hands rendered frames on at their delivery time (``DeliveryClock``) from a thread of its own, so
    the renderer goes on with the next frame meanwhile. ``submit(t_exposure_s, item)`` queues an item;
    ``deliver(t_stamp_s, item)`` is called at ``clock.delivery_time(t_exposure_s)`` on the monotonic clock
    with the stamp the loop believes (``clock.stamp``). With no latency nor jitter it calls through."""

    def __init__(self, profile: CameraProfile, deliver, now=None, sleep=None):
        import queue
        import threading
        import time

        self.clock = DeliveryClock(profile)
        self._deliver = deliver
        self._now, self._sleep = now or time.monotonic, sleep or time.sleep
        self._direct = profile.latency_s == 0 and profile.jitter_s == 0 and profile.latency_known_s == 0
        self._queue: queue.Queue = queue.Queue()
        self._thread = None if self._direct else threading.Thread(target=self._run, name="frame-delivery", daemon=True)
        if self._thread is not None:
            self._thread.start()

    def submit(self, t_exposure_s: float, item) -> None:
        if self._direct:
            self._deliver(t_exposure_s, item)
            return
        self._queue.put((self.clock.delivery_time(t_exposure_s), item))

    def _run(self) -> None:
        while True:
            entry = self._queue.get()
            if entry is None:
                return
            t_delivery, item = entry
            wait = t_delivery - self._now()
            if wait > 0:
                self._sleep(wait)
            self._deliver(self.clock.stamp(t_delivery), item)

    def close(self) -> None:
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout=2.0)
