"""A frame grabber behind the :class:`calib.acquisition.protocol.Imager` protocol: OpenCV
``VideoCapture`` of the scanner's video output (a capture device), a stream URL, a video
file, or a still image the scanner keeps overwriting with its current frame.

Each grab returns a frame captured after the call: a device or stream is drained of
``flush_frames`` buffered frames first (they may show the probe before the robot
settled); a still image is read afresh. The B-mode region is cropped (``roi_px``) and
turned grey; its pixel spacing comes from the config (a capture carries none).
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.errors import FrameGrabberError
from calib.records import UsFrame

from .config import GrabberConfig

__all__ = ["FrameGrabber"]

_STILL_IMAGES = {".pgm", ".ppm", ".pnm", ".png", ".bmp", ".tif", ".tiff", ".jpg", ".jpeg"}


class FrameGrabber:
    """Frames of the scanner, as the pipeline consumes them (uint8, rows = depth)."""

    def __init__(self, cfg: GrabberConfig) -> None:
        self.cfg = cfg
        self.spacing = (cfg.pixel_spacing_mm[0] * 1e-3, cfg.pixel_spacing_mm[1] * 1e-3)
        src = cfg.source.strip()
        # A still image the scanner keeps overwriting is read afresh at each grab; a
        # device, a stream URL or a video file is a stream of frames.
        still = Path(src).suffix.lower() in _STILL_IMAGES and "://" not in src
        self._file = Path(src) if still else None
        self._capture: cv2.VideoCapture | None = None
        if self._file is None:
            self._capture = cv2.VideoCapture(int(src) if src.isdigit() else src)
            if not self._capture.isOpened():
                raise FrameGrabberError(f"frame grabber source {src!r} cannot be opened")

    def grab(self) -> UsFrame:
        """A fresh frame, cropped and grey."""
        deadline = time.monotonic() + self.cfg.timeout_s
        while True:
            frame = self._read()
            if frame is not None:
                return UsFrame(self._crop(frame), self.spacing)
            if time.monotonic() > deadline:
                raise FrameGrabberError(
                    f"frame grabber {self.cfg.source!r}: no frame for {self.cfg.timeout_s:g} s "
                    "(is the scanner's video output connected and live?)"
                )
            time.sleep(0.01)

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None

    def __enter__(self) -> FrameGrabber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _read(self) -> NDArray[np.uint8] | None:
        if self._file is not None:
            if not self._file.is_file():
                return None
            cap = cv2.VideoCapture(str(self._file))
            try:
                ok, frame = cap.read()
            finally:
                cap.release()
            return frame if ok else None
        cap = self._capture
        for _ in range(self.cfg.flush_frames):
            if not cap.grab():
                return None
        ok, frame = cap.read()
        return frame if ok else None

    def _crop(self, frame: NDArray[np.uint8]) -> NDArray[np.uint8]:
        grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        if self.cfg.roi_px is None:
            return np.ascontiguousarray(grey)
        x, y, w, h = self.cfg.roi_px
        H, W = grey.shape
        if x + w > W or y + h > H:
            raise FrameGrabberError(
                f"grabber.roi_px {list(self.cfg.roi_px)} reaches outside the captured "
                f"{W} × {H} frame"
            )
        return np.ascontiguousarray(grey[y : y + h, x : x + w])
