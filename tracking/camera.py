"""Camera sources: real cameras and video files through OpenCV (the synthetic overhead camera, a
sensor simulation, is ``sim.camera.SyntheticCamera``).

Every source implements :class:`CameraSource`: ``read()`` returns the next :class:`Frame`
(grayscale or BGR ``uint8`` image, capture time in seconds, frame index) and raises
:class:`EndOfStream` when no more frames will come.
"""
from __future__ import annotations

import math
import os
import queue
import threading
import time
from dataclasses import dataclass
from typing import Literal, Protocol

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
    """Frames of a video file. ``clock="index"``: ``t_capture_s`` is frame index / frame rate (the
    container's position in milliseconds if it reports no frame rate); ``clock="container"``: the
    frame's own timestamp (``CAP_PROP_POS_MSEC`` after the read: its presentation time), which must
    increase from frame to frame (CameraError naming the frame otherwise). ``frame_count`` is what the
    container announces (None if it does not), so a reader can tell a cut file from its end.
    ``grey``: frames as one channel; an MJPEG video's JPEG frames are then decoded straight to grey
    (half the decoding time of OpenCV's colour frames), a frame that does not decode is a CameraError."""

    def __init__(self, path, clock: Literal["index", "container"] = "index", grey: bool = False):
        self.path = str(path)
        if clock not in ("index", "container"):
            raise ValueError(f"VideoFileCamera clock: 'index' or 'container', got {clock!r}")
        self.clock = clock
        if not os.path.exists(self.path):
            raise CameraError(f"{self.path}: video file not found")
        if not os.path.isfile(self.path):  # a FIFO or device would block OpenCV
            raise CameraError(f"{self.path}: not a regular file")
        self._cap = cv2.VideoCapture(self.path)
        if not self._cap.isOpened():
            raise CameraError(f"{self.path}: OpenCV cannot open this video (unsupported codec or container?)")
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and fps > 0 else None
        count = self._cap.get(cv2.CAP_PROP_FRAME_COUNT)
        self.frame_count = int(count) if count and count > 0 else None
        self.grey = bool(grey)
        fourcc = int(self._cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").upper()
        # Undecoded packets (CAP_PROP_FORMAT -1) of an MJPEG stream are JPEG images.
        self._jpeg = self.grey and fourcc == b"MJPG" and self._cap.set(cv2.CAP_PROP_FORMAT, -1)
        self._index = 0
        self._last_t: float | None = None

    def read(self) -> Frame:
        ok, image = self._cap.read()
        if not ok:
            raise EndOfStream(f"{self.path}: end of video after {self._index} frames")
        if self._jpeg:
            image = cv2.imdecode(image, cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise CameraError(f"{self.path}: frame {self._index}: the JPEG image does not decode (damaged or "
                                  f"truncated video)")
        elif self.grey and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self.clock == "container":
            t = self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            if self._last_t is not None and not t > self._last_t:
                raise CameraError(f"{self.path}: frame {self._index}: timestamp {t:.6f} s does not advance past "
                                  f"frame {self._index - 1}'s {self._last_t:.6f} s (timestamps go backwards)")
            self._last_t = t
        # Backends differ in what CAP_PROP_POS_MSEC means around a read; with a known frame
        # rate the frame index is the reliable clock (constant-frame-rate files).
        elif self.fps is not None:
            t = self._index / self.fps
        else:
            t = self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        frame = Frame(image, t, self._index)
        self._index += 1
        return frame

    def close(self) -> None:
        self._cap.release()


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


class ImageFolderCamera:
    """The image files of a folder (``IMAGE_SUFFIXES``), in file-name order (zero-padded numbers sort
    right), read as grey; ``t_capture_s`` is index / ``fps``. An unreadable file is a CameraError
    naming it and its frame index."""

    def __init__(self, folder, fps: float):
        self.path = str(folder)
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
            raise ValueError(f"ImageFolderCamera fps: must be a positive number, got {fps!r}")
        if not os.path.isdir(self.path):
            raise CameraError(f"{self.path}: not a folder")
        self.fps = float(fps)
        self.files = sorted(e.path for e in os.scandir(self.path)
                            if e.is_file() and os.path.splitext(e.name)[1].lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise CameraError(f"{self.path}: no image files ({', '.join(IMAGE_SUFFIXES)})")
        self.frame_count = len(self.files)
        self._index = 0

    def read(self) -> Frame:
        if self._index >= len(self.files):
            raise EndOfStream(f"{self.path}: end of the folder after {self._index} images")
        path = self.files[self._index]
        image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise CameraError(f"{path}: frame {self._index}: not a readable image")
        frame = Frame(image, self._index / self.fps, self._index)
        self._index += 1
        return frame

    def close(self) -> None:
        pass


class ReadAhead:
    """Reads ``source`` in a background thread up to ``depth`` frames ahead: OpenCV's decoders release
    the GIL, so decoding a video overlaps the caller's work on another core. Frames, the end of the
    stream and errors reach ``read()`` in order; other attributes are the source's (``path``,
    ``frame_count``)."""

    def __init__(self, source: CameraSource, depth: int = 4):
        self.source = source
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._ended: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="read-ahead", daemon=True)
        self._thread.start()

    def __getattr__(self, name):
        return getattr(self.source, name)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                item = self.source.read()
            except Exception as exc:  # handed to the reader, in order
                item = exc
            while not self._stop.is_set():
                try:
                    self._queue.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if isinstance(item, Exception):
                return

    def read(self) -> Frame:
        if self._ended is not None:
            raise self._ended
        item = self._queue.get()
        if isinstance(item, Exception):
            self._ended = item
            raise item
        return item

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.source.close()
