"""``v4l2:/dev/videoN`` or ``v4l2:N`` — a UVC or CSI camera through OpenCV's V4L2 backend.

Latency choices: the driver keeps only ``buffer_count`` buffers (default 2) so a frame never
waits behind older ones; the raw buffer is taken without OpenCV's RGB conversion and turned
into gray in one step (GREY: a view, YUYV: the luma plane, MJPG: a luma-only JPEG decode);
the capture timestamp is the driver's buffer timestamp, which V4L2 takes from
``CLOCK_MONOTONIC`` — the host clock the latency is measured in.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from .base import Frame, FrameSource, SourceError, fit_to, host_us

__all__ = ["V4L2Source", "raw_to_gray", "PIXEL_FORMATS"]

log = logging.getLogger("emdflowd.v4l2")

PIXEL_FORMATS = ("GREY", "YUYV", "MJPG")
# V4L2 exposure_absolute is in units of 100 µs; V4L2_EXPOSURE_MANUAL = 1, APERTURE_PRIORITY = 3.
_EXPOSURE_UNIT_US = 100.0
_AUTO_EXPOSURE_MANUAL, _AUTO_EXPOSURE_AUTO = 1, 3
# A buffer timestamp further than this from "now" is not CLOCK_MONOTONIC (some old drivers).
_PLAUSIBLE_TIMESTAMP_US = 2_000_000


def raw_to_gray(raw: np.ndarray, pixel_format: str, width: int, height: int) -> np.ndarray:
    """Turn what ``VideoCapture.read`` returns with ``CONVERT_RGB`` off into 2-D gray.

    Parameters
    ----------
    raw : numpy.ndarray
        Raw buffer as OpenCV hands it out: (h, w) for GREY, (h, w, 2) or a flat byte row
        for YUYV, a flat byte row for MJPG; (h, w, 3) BGR when the driver forced conversion.
    pixel_format : str
        One of :data:`PIXEL_FORMATS`.
    width, height : int
        Size the driver delivers, px.

    Returns
    -------
    numpy.ndarray
        uint8 (height, width); a view of ``raw`` where the layout allows it.
    """
    if raw.ndim == 3 and raw.shape[2] == 3:
        return cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
    if pixel_format == "MJPG":
        gray = cv2.imdecode(raw.reshape(-1), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise SourceError(f"MJPG frame of {raw.size} bytes: not a decodable JPEG")
        return gray
    flat = raw.reshape(-1)
    if pixel_format == "GREY":
        if flat.size < width * height:
            raise SourceError(f"GREY frame of {flat.size} bytes, expected {width * height}")
        return flat[: width * height].reshape(height, width)
    if pixel_format == "YUYV":
        if flat.size < width * height * 2:
            raise SourceError(f"YUYV frame of {flat.size} bytes, expected {width * height * 2}")
        # Y0 U Y1 V: one cvtColor pass extracts the luma into a contiguous image.
        packed = flat[: width * height * 2].reshape(height, width, 2)
        return cv2.cvtColor(packed, cv2.COLOR_YUV2GRAY_YUYV)
    raise SourceError(f"pixel format {pixel_format!r}: expected one of {', '.join(PIXEL_FORMATS)}")


def parse_device(target: str) -> str | int:
    """``/dev/video0`` → that path; ``0`` → index 0; anything else is an error."""
    if target.isdigit():
        return int(target)
    if target.startswith("/dev/"):
        return target
    raise SourceError(f"v4l2 device {target!r}: expected /dev/videoN, a /dev/ symlink or an index N")


class V4L2Source(FrameSource):
    """A V4L2 camera.

    Parameters
    ----------
    device : str
        ``/dev/videoN`` (or a udev symlink such as ``/dev/emdflow-camera``) or an index.
    width, height : int
        Processing resolution, px; the camera is asked for it and any other size it delivers
        is area-resized to it.
    fps : float
        Requested frame rate, frames/s.
    pixel_format : str
        ``GREY``, ``YUYV`` or ``MJPG``.
    buffer_count : int
        Driver buffers (1..10); 2 keeps latency at one frame at most.
    exposure_us : float or None
        Manual exposure time, µs; None leaves auto exposure on.
    gain : float or None
        Manual gain in the driver's units; None leaves it alone.
    capture_factory : callable
        ``(device, api) -> VideoCapture``; the seam the tests replace (no camera here).
    """

    live = True

    def __init__(self, device: str, *, width: int = 320, height: int = 240, fps: float = 100.0,
                 pixel_format: str = "GREY", buffer_count: int = 2,
                 exposure_us: float | None = None, gain: float | None = None,
                 capture_factory=cv2.VideoCapture):
        self.uri = f"v4l2:{device}"
        self.device = parse_device(device)
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        pixel_format = pixel_format.upper()
        if pixel_format not in PIXEL_FORMATS:
            raise SourceError(f"{self.uri}: pixel format {pixel_format!r}: expected one of {', '.join(PIXEL_FORMATS)}")
        self.pixel_format = pixel_format
        self.buffer_count = int(buffer_count)
        self.exposure_us = exposure_us
        self.gain = gain
        self._factory = capture_factory
        self._cap = None
        self._size = (self.width, self.height)
        self._index = 0

    def _set(self, prop: int, value: float, what: str) -> None:
        if not self._cap.set(prop, value):
            log.warning("%s: the driver refused %s = %g; continuing without it", self.uri, what, value)

    def open(self) -> None:
        self.close()
        if isinstance(self.device, str) and not Path(self.device).exists():
            raise SourceError(f"{self.uri}: {self.device} does not exist (camera unplugged?)")
        cap = self._factory(self.device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise SourceError(
                f"{self.uri}: cannot open the camera (is it in use, or is the user not in "
                "group 'video'?)"
            )
        self._cap = cap
        self._set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*self.pixel_format), f"pixel format {self.pixel_format}")
        self._set(cv2.CAP_PROP_FRAME_WIDTH, self.width, "width")
        self._set(cv2.CAP_PROP_FRAME_HEIGHT, self.height, "height")
        self._set(cv2.CAP_PROP_FPS, self.fps, "fps")
        self._set(cv2.CAP_PROP_BUFFERSIZE, self.buffer_count, "buffer count")
        # Raw buffers: gray is extracted by raw_to_gray without an RGB round trip.
        self._set(cv2.CAP_PROP_CONVERT_RGB, 0, "raw mode (CONVERT_RGB=0)")
        if self.exposure_us is not None:
            self._set(cv2.CAP_PROP_AUTO_EXPOSURE, _AUTO_EXPOSURE_MANUAL, "manual exposure")
            self._set(cv2.CAP_PROP_EXPOSURE, self.exposure_us / _EXPOSURE_UNIT_US, "exposure (100 µs units)")
        if self.gain is not None:
            self._set(cv2.CAP_PROP_GAIN, self.gain, "gain")
        got_w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) or self.width
        got_h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) or self.height
        got_fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
        got_fmt = got_fourcc.to_bytes(4, "little").decode("ascii", "replace") if got_fourcc > 0 else self.pixel_format
        if got_fmt in PIXEL_FORMATS and got_fmt != self.pixel_format:
            log.warning("%s: asked for %s, the driver delivers %s", self.uri, self.pixel_format, got_fmt)
            self.pixel_format = got_fmt
        self._size = (got_w, got_h)
        if self._size != (self.width, self.height):
            log.info("%s: camera delivers %dx%d, resized to %dx%d", self.uri, got_w, got_h, self.width, self.height)
        self._index = 0

    def read(self) -> Frame | None:
        if self._cap is None:
            raise SourceError(f"{self.uri}: not open")
        ok, raw = self._cap.read()
        now = host_us()
        if not ok or raw is None:
            raise SourceError(f"{self.uri}: read failed (camera unplugged or stalled)")
        stamp_us = int(self._cap.get(cv2.CAP_PROP_POS_MSEC) * 1000.0)
        if not (0 < now - stamp_us < _PLAUSIBLE_TIMESTAMP_US):
            stamp_us = now  # driver without monotonic buffer timestamps
        gray = raw_to_gray(raw, self.pixel_format, *self._size)
        frame = Frame(fit_to(gray, self.width, self.height), stamp_us, stamp_us, self._index)
        self._index += 1
        return frame

