"""Hardware frame feed: a capture thread reads the camera continuously and keeps the newest frame,
so the loop never waits on the camera and never processes a stale backlog."""
from __future__ import annotations

import threading

from race.world import WorldPacket


class CameraFeed:
    def __init__(self, camera) -> None:
        self.camera = camera
        self._cv = threading.Condition()
        self._frame = None
        self._error: Exception | None = None
        self._stop = False
        self.frames_read = 0
        self._thread = threading.Thread(target=self._run, name="CameraFeed", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            with self._cv:
                if self._stop:
                    return
            try:
                frame = self.camera.read()
            except Exception as exc:  # CameraError / EndOfStream: reported to the loop
                with self._cv:
                    self._error = exc
                    self._cv.notify_all()
                return
            with self._cv:
                self._frame = frame
                self.frames_read += 1
                self._cv.notify_all()

    def poll(self, timeout: float = 0.0) -> WorldPacket:
        packet = WorldPacket()
        with self._cv:
            if self._frame is None and self._error is None and timeout > 0:
                self._cv.wait(timeout)
            if self._error is not None and self._frame is None:
                raise RuntimeError(f"camera failed: {self._error}")
            packet.frame, self._frame = self._frame, None
        return packet

    def close(self) -> None:
        with self._cv:
            self._stop = True
        self._thread.join(timeout=2.0)
        self.camera.close()
