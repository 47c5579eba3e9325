"""Camera sources: real cameras and video files through OpenCV (the synthetic overhead camera, a
sensor simulation, is ``sim.camera.SyntheticCamera``).

Every source implements :class:`CameraSource`: ``read()`` returns the next :class:`Frame`
(grayscale or BGR ``uint8`` image, capture time in seconds, frame index) and raises
:class:`EndOfStream` when no more frames will come.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np


@dataclass
class Frame:
    image: np.ndarray
    t_capture_s: float  # for the synthetic camera: middle of the exposure
    index: int


class CameraError(RuntimeError):
    """A camera or video could not be opened or stopped delivering frames."""


class EndOfStream(CameraError):
    """The source has no more frames (end of a video file)."""


class CameraSource(Protocol):
    def read(self) -> Frame: ...

    def close(self) -> None: ...


# --------------------------------------------------------------------------- OpenCV sources
class OpenCVCamera:
    """A live camera (device index) or stream URL through ``cv2.VideoCapture``.

    ``t_capture_s`` is ``time.monotonic()`` when the frame was grabbed minus ``latency_s``
    (the camera's own exposure-to-delivery delay, which OpenCV does not report; measure it
    once, e.g. by filming a millisecond clock, and pass it here).
    """

    def __init__(self, index_or_url: int | str, width: int | None = None, height: int | None = None,
                 fps: float | None = None, latency_s: float = 0.0):
        self.source = index_or_url
        self.latency_s = float(latency_s)
        self._cap = cv2.VideoCapture(index_or_url)
        if not self._cap.isOpened():
            self._cap.release()
            kind = "camera index" if isinstance(index_or_url, int) else "stream URL"
            raise CameraError(f"cannot open {kind} {index_or_url!r} (is it connected and not in use?)")
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, width), (cv2.CAP_PROP_FRAME_HEIGHT, height),
                            (cv2.CAP_PROP_FPS, fps)):
            if value is not None:
                self._cap.set(prop, value)
        self._index = 0

    def read(self) -> Frame:
        if not self._cap.grab():
            raise CameraError(f"camera {self.source!r} stopped delivering frames")
        t = time.monotonic() - self.latency_s
        ok, image = self._cap.retrieve()
        if not ok:
            raise CameraError(f"camera {self.source!r}: frame could not be decoded")
        frame = Frame(image, t, self._index)
        self._index += 1
        return frame

    def close(self) -> None:
        self._cap.release()


class VideoFileCamera:
    """Frames of a video file; ``t_capture_s`` is frame index / frame rate (the container's position
    in milliseconds if it reports no frame rate)."""

    def __init__(self, path):
        self.path = str(path)
        if not os.path.exists(self.path):
            raise CameraError(f"{self.path}: video file not found")
        self._cap = cv2.VideoCapture(self.path)
        if not self._cap.isOpened():
            raise CameraError(f"{self.path}: OpenCV cannot open this video (unsupported codec or container?)")
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and fps > 0 else None
        self._index = 0

    def read(self) -> Frame:
        ok, image = self._cap.read()
        if not ok:
            raise EndOfStream(f"{self.path}: end of video after {self._index} frames")
        # Backends differ in what CAP_PROP_POS_MSEC means around a read; with a known frame
        # rate the frame index is the reliable clock (constant-frame-rate files).
        if self.fps is not None:
            t = self._index / self.fps
        else:
            t = self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        frame = Frame(image, t, self._index)
        self._index += 1
        return frame

    def close(self) -> None:
        self._cap.release()
