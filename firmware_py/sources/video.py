"""``video:PATH`` — any file OpenCV reads, timestamps from the file's frame rate."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from .base import Frame, FrameSource, Pacer, SourceError, fit_to, host_us

__all__ = ["VideoFileSource", "probe_video"]


def probe_video(path: str | Path) -> tuple[int, int, float]:
    """Return (width, height, fps) of a video file; raise :class:`SourceError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise SourceError(f"video file {str(path)!r}: no such file")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise SourceError(f"video file {str(path)!r}: OpenCV cannot open it")
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
    finally:
        cap.release()
    if width <= 0 or height <= 0:
        raise SourceError(f"video file {str(path)!r}: no video stream")
    return width, height, fps


def to_gray(image: np.ndarray) -> np.ndarray:
    """Convert an OpenCV-decoded frame (gray, BGR or BGRA) to 2-D uint8 gray."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(image, code)
    raise SourceError(f"unsupported decoded frame shape {image.shape}")


class VideoFileSource(FrameSource):
    """Frames of a video file, resized to the processing resolution.

    Parameters
    ----------
    path : str
        Any file OpenCV's FFmpeg backend reads (FFV1/MJPG ``.avi``/``.mkv`` are exact).
    width, height : int or None
        Processing resolution, px; None keeps the file's own size.
    fps : float or None
        Frame rate to assume when the file declares none, frames/s.
    loop : bool
        Rewind at the end instead of ending the stream; timestamps keep increasing.
    realtime : bool
        Release frames at the file's rate instead of as fast as they are read.
    """

    live = False

    def __init__(self, path: str, *, width: int | None = None, height: int | None = None,
                 fps: float | None = None, loop: bool = False, realtime: bool = False):
        self.uri = f"video:{path}"
        self.path = str(path)
        native_w, native_h, file_fps = probe_video(self.path)
        self.width = int(width or native_w)
        self.height = int(height or native_h)
        if not (file_fps > 0 and math.isfinite(file_fps)):
            if not fps:
                raise SourceError(f"video file {self.path!r}: declares no frame rate; set [source] fps")
            file_fps = float(fps)
        self.fps = float(file_fps)
        self.loop = bool(loop)
        self.realtime = bool(realtime)
        # Documented default: f = processed width (a 53° horizontal field of view).
        self.default_focal_length_px = float(self.width)
        self._cap: cv2.VideoCapture | None = None
        self._pacer = Pacer(self.fps) if realtime else None
        self._index = 0          # frames delivered since open (timestamps: index / fps)
        self._period_us = 1e6 / self.fps

    def open(self) -> None:
        self.close()
        cap = cv2.VideoCapture(self.path)
        if not cap.isOpened():
            raise SourceError(f"video file {self.path!r}: OpenCV cannot open it")
        # Gray files then decode straight to one channel (no BGR round trip).
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        self._cap = cap
        self._index = 0
        if self._pacer:
            self._pacer.restart()

    def _grab(self) -> np.ndarray | None:
        ok, image = self._cap.read()
        if ok:
            return image
        if not self.loop:
            return None
        self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        ok, image = self._cap.read()
        return image if ok else None

    def read(self) -> Frame | None:
        if self._cap is None:
            raise SourceError(f"video file {self.path!r}: not open")
        due_us = None
        if self._pacer:
            index, self.waited_us, due_us = self._pacer.next(self._index)
            for _ in range(index - self._index):  # frames a camera would have dropped
                if self._grab() is None:
                    return None
            self._index = index
        image = self._grab()
        if image is None:
            return None
        # Paced: captured when due (like a camera); else when decoded.
        captured = due_us if due_us is not None else host_us()
        gray = fit_to(to_gray(image), self.width, self.height)
        frame = Frame(gray, int(round(self._index * self._period_us)), captured, self._index)
        self._index += 1
        return frame

