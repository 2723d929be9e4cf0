"""``video:PATH`` — any file OpenCV reads, timestamps from the file's frame rate.

Files whose stream FFmpeg decodes to 8-bit gray (gray FFV1, as ``emdflow`` and the tests
write it) are decoded straight to one channel, bit-exact and without a BGR round trip;
every other stream (YUV: mp4v, H.264, MJPG, XVID, HuffYUV as OpenCV writes it; colour
FFV1) goes through OpenCV's normal conversion and then to gray. Raw decoding of a YUV stream would hand out
its limited-range luma plane with one OpenCV warning per frame on stderr — the journal
under systemd, which then rate-limits the service and drops the daemon's own lines.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import cv2
import numpy as np
from emdflow.tools.video_io import quiet_ffmpeg_log

from ..clock import host_us
from .base import Frame, FrameSource, Pacer, SourceError, fit_to

__all__ = ["VideoFileSource", "probe_video", "is_gray_stream"]

log = logging.getLogger("emdflowd.video")
quiet_ffmpeg_log()  # a damaged file: FFmpeg's lines per frame would flood the journal

#: Frames a container's declared count may be off by without meaning a cut-off file.
_DECLARED_SLACK = 2
#: Missed frames decoded through; more are passed by a seek (what one costs in decodes).
_SEEK_FRAMES = 24
# Codec pixel formats (FFmpeg's raw tags, as CAP_PROP_CODEC_PIXEL_FORMAT reports them) that
# OpenCV hands out as one 8-bit channel with CONVERT_RGB off: FFmpeg's GRAY8.
_GRAY8_TAGS = {cv2.VideoWriter_fourcc(*tag) for tag in ("Y800", "GREY", "Y8  ")}


def is_gray_stream(cap: cv2.VideoCapture) -> bool:
    """True if an opened capture's video stream is 8-bit gray (decoded bit-exact to 2-D
    with ``CAP_PROP_CONVERT_RGB`` off); False for YUV and colour streams."""
    tag = int(cap.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT))
    return tag in _GRAY8_TAGS


def probe_video(path: str | Path) -> tuple[int, int, float, int | None]:
    """Return (width, height, fps, declared frame count or None) of a video file; raise
    :class:`SourceError` naming it."""
    path = Path(path)
    if not path.is_file():
        # (an existing path that is no file is a wrong path, not a missing recording)
        what = ("is a directory" if path.is_dir() else
                "is not a regular file" if path.exists() else "no such file")
        raise SourceError(f"video file {str(path)!r}: {what}")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise SourceError(f"video file {str(path)!r}: OpenCV cannot open it")
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        declared = declared_frame_count(cap)
    finally:
        cap.release()
    if width <= 0 or height <= 0:
        raise SourceError(f"video file {str(path)!r}: no video stream")
    return width, height, fps, declared


def declared_frame_count(cap) -> int | None:
    """The frame count an opened ``cv2.VideoCapture``'s container declares (approximate: a
    few frames either way, see ``_DECLARED_SLACK``), or None where it declares none."""
    declared = cap.get(cv2.CAP_PROP_FRAME_COUNT)
    return int(declared) if declared > 0 and math.isfinite(declared) else None


def stopped_short(delivered: int, declared: int | None) -> bool:
    """Whether a pass over a file that delivered ``delivered`` frames stopped well short of
    the ``declared`` count (cut off or corrupt partway), beyond the containers' slack."""
    return declared is not None and delivered < declared - _DECLARED_SLACK


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
        Any file OpenCV's FFmpeg backend reads (gray FFV1 ``.avi``/``.mkv`` are exact).
    width, height : int or None
        Processing resolution, px; None keeps the file's own size. Another aspect ratio
        than the file's is centre-cropped first (one scale for both axes).
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
        # (the declared frame count: approximate, a few frames either way; it tells a file cut
        # off or corrupt partway from one read to its end)
        native_w, native_h, file_fps, self.declared_frames = probe_video(self.path)
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
        self._note_geometry(native_w, native_h)
        #: True while the stream is decoded raw (8-bit gray file), False when converted.
        self.raw_gray = False
        self._cap: cv2.VideoCapture | None = None
        self._pacer = Pacer(self.fps) if realtime else None
        self._index = 0          # frames delivered since open (timestamps: index / fps)
        self._period_us = 1e6 / self.fps

    def open(self) -> None:
        self.close()
        cap = cv2.VideoCapture(self.path)
        if not cap.isOpened():
            raise SourceError(f"video file {self.path!r}: OpenCV cannot open it")
        # Gray files decode straight to one channel (exact, no BGR round trip). Only those:
        # raw YUV comes out as limited-range luma with an OpenCV warning for every frame.
        self.raw_gray = is_gray_stream(cap)
        if self.raw_gray:
            cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        self._cap = cap
        self._index = 0
        self._decoded = 0  # frames decoded since the start of the file
        #: passes over the file that stopped decoding short of its declared frames (warned once)
        self.short_passes = 0
        if self._pacer:
            self._pacer.restart()

    def _note_geometry(self, native_w: int, native_h: int) -> None:
        """Record (and warn about) a centre crop when [source] width × height has another
        aspect ratio than the file: x and y must be scaled alike for the link (the file's
        size is known before it is opened; the daemon makes a new source to reopen)."""
        _, _, crop_w, crop_h = self._record_crop(native_w, native_h)
        if (crop_w, crop_h) != (native_w, native_h):
            log.warning("video file %r is %dx%d, [source] asks for %dx%d (another aspect ratio): its centre "
                        "%dx%d is used and scaled by %.3f on both axes; the focal length refers to the "
                        "%dx%d frames", self.path, native_w, native_h, self.width, self.height, crop_w, crop_h,
                        self.width / crop_w, self.width, self.height)

    def _grab(self) -> np.ndarray | None:
        ok, image = self._cap.read()
        if ok:
            self._decoded += 1
            return image
        if stopped_short(self._decoded, self.declared_frames):
            # OpenCV reports a stream that stops decoding like its end: say which it looks
            # like (once: a looped file would say it at every rewind)
            self.short_passes += 1
            if self.short_passes == 1:
                log.warning("video file %r: decoding stopped after %d of the %d frames it declares "
                            "(cut off or corrupt?)%s", self.path, self._decoded, self.declared_frames,
                            "; looping over what decodes" if self.loop else "")
        if not self.loop:
            return None
        self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._decoded = 0
        ok, image = self._cap.read()
        self._decoded += bool(ok)
        return image if ok else None

    def _skip(self, count: int) -> bool:
        """Move ``count`` frames ahead (frames a camera would have dropped); False at the
        end of a file that does not loop. A few are decoded through; more are passed by a
        seek, which costs about as much as ``_SEEK_FRAMES`` decodes (OpenCV's FFmpeg seek
        decodes forward from a frame about 16 before the target): a file that decodes
        slower than real time then stays at a bounded rate, where decoding every frame it
        missed put it further behind with every read (0.1 fps, seconds of latency)."""
        if count <= _SEEK_FRAMES:
            for _ in range(count):
                if self._grab() is None:
                    return False
            return True
        target = self._decoded + count
        if self.declared_frames and target >= self.declared_frames:
            if not self.loop:
                return False
            target %= self.declared_frames
        self._cap.set(cv2.CAP_PROP_POS_FRAMES, target)
        self._decoded = target
        return True

    def pacing_wait_s(self) -> float:
        return self._pacer.wait_s(self._index) if self._pacer and self._cap is not None else 0.0

    def read(self) -> Frame | None:
        if self._cap is None:
            raise SourceError(f"video file {self.path!r}: not open")
        due_us = None
        if self._pacer:
            index, self.waited_us, due_us = self._pacer.next(self._index)
            if index > self._index:
                if not self._skip(index - self._index):
                    return None
                self.missed_frames += index - self._index
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

