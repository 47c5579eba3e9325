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
calibration_focal_error     +0.3 %           focal length of the calibration against the lens's: within the
                                             0.5 % that calibrate-camera recovers on rendered boards
                                             (docs/tracking.md), issue 33: +0.5 % costs 1.5 mm
calibration_dist_error      +0.002 on k1,    what a good ChArUco calibration leaves (its k1 standard error
                            -0.001 on k2     is of order 1e-3); issue 33: k1 off by 0.01 costs 12 mm
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
from dataclasses import dataclass

import numpy as np

from sim.camera import RenderEffects
from tracking.calibration import FixedMarkerSet
from tracking.geometry import PinholeCamera

# One effect of the realistic profile alone on the ideal one ("ideal+jpeg"), to measure what each costs:
# the profile fields (``effects.X``: a RenderEffects field) it takes from the realistic profile.
SINGLE_EFFECTS = {
    "lens": ("dist_coeffs",),  # distortion rendered, and known exactly to the tracker
    "calibration": ("dist_coeffs", "calibration_dist_error", "calibration_focal_error"),  # lens estimated with errors
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
    ``calibration_dist_error``: added to it in the calibration the tracker uses (an estimated lens), whose
    focal length is off by ``calibration_focal_error`` (relative).
    ``latency_s``/``jitter_s``: a frame is delivered ``latency_s`` + N(0, ``jitter_s``) after its exposure
    (seeded, never before its exposure nor before the previous frame); ``latency_known_s`` is what the loop
    subtracts from the delivery time to stamp it (0: the loop knows only the delivery time).
    ``survey_sigma_m``: standard deviation of each surveyed coordinate of the fixed markers the camera pose
    is calibrated from (the renderer draws them at their true places).
    """

    name: str = "ideal"
    effects: RenderEffects = RenderEffects()
    dist_coeffs: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    calibration_dist_error: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    calibration_focal_error: float = 0.0  # relative: the calibration's fx, fy are (1 + this) times the lens's
    latency_s: float = 0.0
    jitter_s: float = 0.0
    latency_known_s: float = 0.0
    survey_sigma_m: float = 0.0

    def __post_init__(self) -> None:
        for key in ("latency_s", "jitter_s", "latency_known_s", "survey_sigma_m"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"camera profile {self.name}: {key}: must be >= 0 (seconds), got {getattr(self, key)}")
        for key in ("dist_coeffs", "calibration_dist_error"):
            if len(getattr(self, key)) != 5:
                raise ValueError(f"camera profile {self.name}: {key}: 5 OpenCV coefficients (k1, k2, p1, p2, k3)")

    @property
    def seed(self) -> int:
        return self.effects.seed

    def with_seed(self, seed: int) -> "CameraProfile":
        return dataclasses.replace(self, effects=dataclasses.replace(self.effects, seed=int(seed)))

    def estimated(self, camera: PinholeCamera) -> PinholeCamera:
        """``camera`` (the renderer's true one) with the distortion a calibration would estimate."""
        dist = np.asarray(camera.dist_coeffs, float).ravel()
        dist = np.pad(dist, (0, max(0, 5 - len(dist))))[:5] + np.asarray(self.calibration_dist_error)
        k = camera.camera_matrix.copy()
        k[0, 0] *= 1.0 + self.calibration_focal_error
        k[1, 1] *= 1.0 + self.calibration_focal_error
        return PinholeCamera(k, dist, camera.rotation.copy(), camera.translation.copy(),
                             camera.image_size)


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


def _realistic_effects(seed: int) -> RenderEffects:
    return RenderEffects(exposure_s=0.004, jpeg_quality=75, readout_s=0.010, flicker_amplitude=0.04,
                         flicker_hz=100.0, seed=seed)


def camera_profile(name: str, seed: int = 0) -> CameraProfile:
    """The named profile (``PROFILE_NAMES``) with its random effects seeded by ``seed``."""
    if name == "ideal":
        return CameraProfile("ideal", RenderEffects(seed=seed))
    if name == "realistic":
        return CameraProfile("realistic", _realistic_effects(seed), dist_coeffs=(-0.12, 0.03, 5e-4, -3e-4, 0.0),
                             calibration_dist_error=(0.002, -0.001, 0.0, 0.0, 0.0), calibration_focal_error=0.003,
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
