"""``v4l2:/dev/videoN`` or ``v4l2:N`` — a UVC camera (or another plain V4L2 capture node)
through OpenCV's V4L2 backend. Not a Raspberry Pi CSI camera under libcamera (Raspberry Pi
OS Bookworm), whose nodes OpenCV cannot read as a capture device.

Latency choices: the driver keeps only ``buffer_count`` buffers (default 2) so a frame never
waits behind older ones; the raw buffer is taken without OpenCV's RGB conversion and turned
into gray in one step (GREY: a view, YUYV: the luma plane, MJPG: a luma-only JPEG decode);
the capture timestamp is the driver's buffer timestamp, which V4L2 takes from
``CLOCK_MONOTONIC`` — the host clock the latency is measured in.

A buffer that cannot be converted (a truncated JPEG or a short buffer: what USB bandwidth
glitches produce) is a bad *frame*, not a lost camera: it is skipped, counted in
:attr:`~firmware_py.sources.base.FrameSource.bad_frames` and logged at most once per 5 s;
only a run of them, or a failed driver read, raises :class:`SourceError` (and the daemon
reopens the camera). A camera that delivers another size than asked is centre-cropped to
the asked aspect ratio before resizing, so both axes get the same scale.
"""

from __future__ import annotations

import logging
import math
import os
import stat
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from ..clock import host_us
from .base import _BAD_FRAME_LOG_S, Frame, FrameError, FrameSource, SourceConfigError, SourceError, fit_to

__all__ = ["V4L2Source", "raw_to_gray", "PIXEL_FORMATS"]

log = logging.getLogger("emdflowd.v4l2")

PIXEL_FORMATS = ("GREY", "YUYV", "MJPG")
# What drivers also report and raw_to_gray reads: JPEG is MJPG's other name; planar 4:2:0
# formats start with the full luma plane, which is GREY's layout; BGR3 / RGB3 are a
# driver's own conversion to colour, read from their three channels.
_FORMAT_ALIASES = {"JPEG": "MJPG", "YU12": "GREY", "YV12": "GREY", "NV12": "GREY", "NV21": "GREY"}
_DRIVER_COLOUR = ("BGR3", "RGB3")
# V4L2 exposure_absolute is in units of 100 µs; V4L2_EXPOSURE_AUTO = 0, MANUAL = 1, APERTURE_PRIORITY = 3.
_EXPOSURE_UNIT_US = 100.0
_AUTO_EXPOSURE_FULL, _AUTO_EXPOSURE_MANUAL, _AUTO_EXPOSURE_AUTO = 0, 1, 3
# A buffer timestamp further than this from "now" is not CLOCK_MONOTONIC (some old drivers).
_PLAUSIBLE_TIMESTAMP_US = 2_000_000
# This many unconvertible buffers in a row mean the stream itself is broken (a wedged
# decoder, a format mix-up): the camera is reopened. 25 frames: 0.25 s at 100 frames/s,
# 0.8 s at 30 — isolated corrupt frames, as USB glitches produce them, are skipped.
BAD_FRAMES_BEFORE_REOPEN = 25


#: Formats raw_to_gray reads besides PIXEL_FORMATS: planar 4:2:0 (the luma plane first, then
#: half as many bytes of chroma) and a driver's own conversion to colour.
_PLANAR = ("YU12", "YV12", "NV12", "NV21")
_RAW_FORMATS = PIXEL_FORMATS + _PLANAR + _DRIVER_COLOUR
#: Most padding a driver adds to a row (its stride over width x bytes per pixel; the Pi's
#: unicam aligns rows to 16 or 32 bytes), bytes.
_MAX_ROW_PADDING = 256


def _image_rows(flat: np.ndarray, fmt: str, height: int, row_bytes: int) -> np.ndarray:
    """The ``height`` rows of ``row_bytes`` bytes of a flat buffer: packed, or with each
    row padded to a stride (as some drivers deliver them), for a planar 4:2:0 format its
    luma plane. A buffer of any other length is a FrameError: cut to the expected length it
    gave sheared images that passed as good ones."""
    size = flat.size
    planes = 1.5 if fmt in _PLANAR else 1.0  # (4:2:0: half a plane of chroma after the luma)
    stride = size / (planes * height)
    if stride == int(stride) and row_bytes <= stride < row_bytes + _MAX_ROW_PADDING:
        stride = int(stride)
        return flat[: height * stride].reshape(height, stride)[:, :row_bytes]
    expected = int(planes * height * row_bytes)
    raise FrameError(f"{fmt} frame of {size} bytes, expected {expected} ({row_bytes} bytes a row x {height} "
                     f"rows{', and 4:2:0 chroma' if planes > 1 else ''}, or its rows padded to a stride)")


def raw_to_gray(raw: np.ndarray, pixel_format: str, width: int, height: int) -> np.ndarray:
    """Turn what ``VideoCapture.read`` returns with ``CONVERT_RGB`` off into 2-D gray.

    Parameters
    ----------
    raw : numpy.ndarray
        Raw buffer as OpenCV hands it out: (h, w) for GREY, (h, w, 2) or a flat byte row
        for YUYV, a flat byte row for MJPG, planar 4:2:0 and (recent OpenCV) BGR3/RGB3,
        (h, w, 3) for BGR3/RGB3 from older OpenCV. Rows padded to a stride are read.
    pixel_format : str
        The format the driver delivers: one of :data:`PIXEL_FORMATS`, a planar 4:2:0
        format (YU12, YV12, NV12, NV21: their luma plane) or BGR3/RGB3.
    width, height : int
        Size the driver delivers, px.

    Returns
    -------
    numpy.ndarray
        uint8 (height, width); a view of ``raw`` where the layout allows it.

    Raises
    ------
    FrameError
        This buffer cannot be converted (an empty or undecodable JPEG, a buffer whose
        length fits neither the size nor a padded stride).
    SourceError
        Unknown pixel format.
    """
    if pixel_format not in _RAW_FORMATS:
        raise SourceError(f"pixel format {pixel_format!r}: expected one of {', '.join(_RAW_FORMATS)}")
    if pixel_format in _DRIVER_COLOUR or (raw.ndim == 3 and raw.shape[2] == 3):
        # (older OpenCV hands a driver's colour out as (h, w, 3), newer as a flat row)
        colour = raw if raw.ndim == 3 else _image_rows(raw.reshape(-1), pixel_format, height, 3 * width).reshape(
            height, width, 3)
        code = cv2.COLOR_RGB2GRAY if pixel_format == "RGB3" else cv2.COLOR_BGR2GRAY
        return cv2.cvtColor(colour, code)
    if pixel_format == "MJPG":
        if raw.size == 0:  # (imdecode asserts on an empty buffer: a cv2.error, not a bad frame)
            raise FrameError("MJPG frame of 0 bytes: not a decodable JPEG")
        gray = cv2.imdecode(raw.reshape(-1), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise FrameError(f"MJPG frame of {raw.size} bytes: not a decodable JPEG")
        return gray
    if pixel_format == "YUYV":
        # Y0 U Y1 V: one cvtColor pass extracts the luma into a contiguous image.
        packed = _image_rows(raw.reshape(-1), "YUYV", height, 2 * width).reshape(height, width, 2)
        return cv2.cvtColor(packed, cv2.COLOR_YUV2GRAY_YUYV)
    if raw.ndim == 2 and raw.shape == (height, width):
        return raw  # GREY as OpenCV hands it out
    return _image_rows(raw.reshape(-1), pixel_format, height, width)


#: the Linux kernel's character-device major number of Video4Linux (/dev/video*)
V4L2_MAJOR = 81
#: V4L2 device indices: /dev/video0 .. /dev/video255 (the kernel's VIDEO_NUM_DEVICES)
MAX_DEVICE_INDEX = 255


class _NoDevice(Exception):
    """No device node for a camera given by its index."""


def _unplugged(uri: str, node) -> SourceError:
    """The error of a camera whose device node is missing (by path or by index)."""
    return SourceError(f"{uri}: {node} does not exist (camera unplugged?)")


def _open_capture(device, api):
    """OpenCV's capture of ``device``; a camera given by its index whose node is missing
    raises :class:`_NoDevice` first (OpenCV would fail too, with two warnings of its own on
    stderr at every retry, and the message would blame a busy camera or permissions)."""
    if isinstance(device, int) and not Path(f"/dev/video{device}").exists():
        raise _NoDevice(f"/dev/video{device}")
    return cv2.VideoCapture(device, api)


def parse_device(target: str) -> str | int:
    """``/dev/video0`` → that path; ``0`` → index 0; anything else is an error."""
    if target.isdecimal():
        if int(target) > MAX_DEVICE_INDEX:
            raise SourceError(f"v4l2 device index {target}: expected 0 to {MAX_DEVICE_INDEX} "
                              f"(/dev/video0 to /dev/video{MAX_DEVICE_INDEX})")
        return int(target)
    if target.startswith("/dev/"):
        return target
    raise SourceError(f"v4l2 device {target!r}: expected /dev/videoN, a /dev/ symlink or an index N")


def _not_a_camera(path: Path) -> str | None:
    """What an existing ``path`` is if it cannot be a V4L2 camera, else None. The major
    number is Linux's: elsewhere (FreeBSD's webcamd) any character device may be one."""
    info = path.stat()
    if stat.S_ISDIR(info.st_mode):
        return "a directory"
    if not stat.S_ISCHR(info.st_mode):
        return "not a device"
    major = os.major(info.st_rdev)
    if sys.platform.startswith("linux") and major != V4L2_MAJOR:
        return f"a character device of major {major}, not V4L2's {V4L2_MAJOR}"
    return None


class V4L2Source(FrameSource):
    """A V4L2 camera.

    Parameters
    ----------
    device : str
        ``/dev/videoN`` (or a udev symlink such as ``/dev/emdflow-camera``) or an index.
    width, height : int
        Processing resolution, px; the camera is asked for it and any other size it delivers
        is centre-cropped to this aspect ratio (WARNING in the log, :attr:`crop_fraction`)
        and area-resized to it.
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
    capture_factory : callable, optional
        ``(device, api) -> VideoCapture``; the seam the tests replace (no camera here).
        Default: OpenCV's, after checking that an index's ``/dev/videoN`` exists.
    bad_frames_before_reopen : int
        Unconvertible buffers in a row after which :meth:`read` gives up with
        :class:`SourceError` (fewer are skipped and counted in :attr:`bad_frames`).
    """

    live = True

    def __init__(self, device: str, *, width: int = 320, height: int = 240, fps: float = 100.0,
                 pixel_format: str = "GREY", buffer_count: int = 2,
                 exposure_us: float | None = None, gain: float | None = None,
                 capture_factory=None, bad_frames_before_reopen: int = BAD_FRAMES_BEFORE_REOPEN):
        self.uri = f"v4l2:{device}"
        self.device = parse_device(device)
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        pixel_format = pixel_format.upper()
        if pixel_format not in PIXEL_FORMATS:
            raise SourceError(f"{self.uri}: pixel format {pixel_format!r}: expected one of {', '.join(PIXEL_FORMATS)}")
        self.pixel_format = pixel_format
        self._raw_format = pixel_format   # what the driver delivers (raw_to_gray's format)
        self.buffer_count = int(buffer_count)
        self.exposure_us = exposure_us
        self.gain = gain
        self._factory = capture_factory or _open_capture
        self._cap = None
        self._size = (self.width, self.height)   # what the driver delivers, px
        self._size_reported = False
        self._index = 0
        self.bad_frames_before_reopen = max(1, int(bad_frames_before_reopen))
        self.bad_frames = 0
        self._bad_in_row = 0
        self._last_bad_log = -float("inf")

    def _set(self, prop: int, value: float, what: str) -> None:
        if not self._cap.set(prop, value):
            log.warning("%s: the driver refused %s = %g; continuing without it", self.uri, what, value)

    def open(self) -> None:
        self.close()
        if isinstance(self.device, str):
            path = Path(self.device)
            if not path.exists():
                raise _unplugged(self.uri, self.device)
            # a path that is there but no V4L2 device (a folder, a file, /dev/null) never
            # becomes a camera: a setting to fix, not a camera to wait for
            if what := _not_a_camera(path):
                raise SourceConfigError(f"{self.uri}: {self.device} is {what}: expected a camera, "
                                        "/dev/videoN or a /dev/ symlink to one")
        try:
            cap = self._factory(self.device, cv2.CAP_V4L2)
        except _NoDevice as exc:
            raise _unplugged(self.uri, exc) from None
        except cv2.error as exc:  # OpenCV refusing the device outright
            raise SourceError(f"{self.uri}: cannot open the camera: {str(exc).strip()}") from exc
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
            # whole 100 µs units, at least one (0 is not an exposure time)
            units = max(1, round(self.exposure_us / _EXPOSURE_UNIT_US))
            self._set(cv2.CAP_PROP_EXPOSURE, units, "exposure (100 µs units)")
        elif not (cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, _AUTO_EXPOSURE_AUTO)
                  or cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, _AUTO_EXPOSURE_FULL)):
            # a UVC camera keeps its controls until it loses power: an earlier run's manual
            # exposure would stay, so auto exposure is asked for whenever none is set
            # (aperture priority, UVC's auto mode, else full auto); a camera without the
            # control is not an error
            log.info("%s: the driver has no auto exposure control (or refused it)", self.uri)
        if self.gain is not None:
            self._set(cv2.CAP_PROP_GAIN, self.gain, "gain")
        got_w, got_h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        # A driver that does not report its size: assume the asked one until a frame tells.
        self._size_reported = got_w > 0 and got_h > 0
        got_w, got_h = (got_w, got_h) if self._size_reported else (self.width, self.height)
        got_fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
        got_fmt = got_fourcc.to_bytes(4, "little").decode("ascii", "replace") if got_fourcc > 0 else self.pixel_format
        # (a planar format or the driver's colour is read as such: as the asked format, its
        # buffers were garbage frames that looked valid)
        self._raw_format = got_fmt if got_fmt in _PLANAR + _DRIVER_COLOUR else _FORMAT_ALIASES.get(got_fmt, got_fmt)
        if got_fmt in _FORMAT_ALIASES:
            if _FORMAT_ALIASES[got_fmt] != self.pixel_format:
                log.warning("%s: asked for %s, the driver delivers %s: read as %s", self.uri,
                            self.pixel_format, got_fmt, _FORMAT_ALIASES[got_fmt])
            got_fmt = _FORMAT_ALIASES[got_fmt]
            self.pixel_format = got_fmt
        if got_fmt in _DRIVER_COLOUR:
            log.warning("%s: asked for %s, the driver converts to colour (%s): gray is computed from "
                        "its three channels", self.uri, self.pixel_format, got_fmt)
        elif got_fmt != self.pixel_format:
            if got_fmt not in PIXEL_FORMATS:
                # decoding its buffers as the asked format would give garbage frames that
                # look valid (a Y16 buffer read as GREY, UYVY as YUYV)
                self.close()
                raise SourceConfigError(
                    f"{self.uri}: asked for pixel format {self.pixel_format}, the driver delivers "
                    f"{got_fmt!r}, which emdflow cannot read (it reads {', '.join(PIXEL_FORMATS)}, JPEG, "
                    "planar 4:2:0 and the driver's own BGR/RGB); set [source] pixel_format to one the "
                    "camera offers (v4l2-ctl --list-formats-ext)")
            log.warning("%s: asked for %s, the driver delivers %s", self.uri, self.pixel_format, got_fmt)
            self.pixel_format = got_fmt
        self._size = (got_w, got_h)
        self._note_geometry(got_w, got_h)
        # the rate the driver settled on (OpenCV's setter succeeds for a rate the camera rounds)
        got_fps = float(cap.get(cv2.CAP_PROP_FPS))
        if got_fps > 0 and math.isfinite(got_fps) and abs(got_fps - self.fps) > 0.01 * self.fps:
            log.warning("%s: asked for %g fps, the camera runs at %g fps", self.uri, self.fps, got_fps)
            self.fps = got_fps
        self._index = 0
        self._bad_in_row = 0

    def _note_geometry(self, got_w: int, got_h: int) -> None:
        """Record how a delivered ``got_w × got_h`` image becomes a processed frame, and say
        so when it is not the asked size (a WARNING when the aspect ratio differs)."""
        x0, y0, crop_w, crop_h = self._record_crop(got_w, got_h)
        if (got_w, got_h) == (self.width, self.height):
            return
        scale = self.width / crop_w
        if (crop_w, crop_h) == (got_w, got_h):
            log.info("%s: camera delivers %dx%d, scaled by %.3f to %dx%d; [optics] focal_length_px refers to "
                     "the %dx%d frames", self.uri, got_w, got_h, scale, self.width, self.height,
                     self.width, self.height)
            return
        if crop_w < got_w:
            cut = f"{x0} columns cut on the left, {got_w - crop_w - x0} on the right"
        else:
            cut = f"{y0} rows cut at the top, {got_h - crop_h - y0} at the bottom"
        log.warning(
            "%s: asked for %dx%d, the camera delivers %dx%d (another aspect ratio): its centre %dx%d is "
            "used (%s) and scaled by %.3f on both axes to %dx%d. [optics] focal_length_px must be the "
            "focal length of these %dx%d frames (%.3f x the focal length in px of the delivered %dx%d "
            "image); they show %.1f %% of its width, so a horizontal field of view of the whole delivered "
            "width means f = %d / 2 / tan(fov / 2) / %.4f",
            self.uri, self.width, self.height, got_w, got_h, crop_w, crop_h, cut, scale, self.width,
            self.height, self.width, self.height, scale, got_w, got_h, 100.0 * self.crop_fraction[0],
            self.width, self.crop_fraction[0])

    def _skip(self, index: int, exc: FrameError) -> None:
        """Count and (rate-limited) log an unconvertible buffer; after
        ``bad_frames_before_reopen`` in a row, give up with :class:`SourceError`."""
        self.bad_frames += 1
        self._bad_in_row += 1
        if self._bad_in_row >= self.bad_frames_before_reopen:
            raise SourceError(f"{self.uri}: {self._bad_in_row} frames in a row could not be converted "
                              f"(last: {exc}); the camera stream is broken")
        now = time.monotonic()
        if now - self._last_bad_log >= _BAD_FRAME_LOG_S:
            self._last_bad_log = now
            log.warning("%s: frame %d: %s: frame skipped (%d bad frames so far; the camera is reopened "
                        "after %d in a row)", self.uri, index, exc, self.bad_frames, self.bad_frames_before_reopen)

    def read(self) -> Frame | None:
        """The next frame the camera delivers; an unconvertible buffer is skipped (see the
        module docstring). Raises :class:`SourceError` when the driver read fails or
        ``bad_frames_before_reopen`` buffers in a row could not be converted."""
        if self._cap is None:
            raise SourceError(f"{self.uri}: not open")
        while True:
            ok, raw = self._cap.read()
            now = host_us()
            if not ok or raw is None:
                raise SourceError(f"{self.uri}: read failed (camera unplugged or stalled)")
            index = self._index
            self._index += 1  # a skipped buffer keeps its place: the gap shows in the indices
            try:
                if (not self._size_reported and raw.ndim >= 2 and raw.shape[0] > 1 and raw.size
                        and self._raw_format not in _PLANAR):  # (a planar buffer's rows hold chroma too)
                    # a driver that did not say its size: an unpacked buffer's shape does
                    self._size_reported = True
                    if (raw.shape[1], raw.shape[0]) != self._size:
                        self._size = (raw.shape[1], raw.shape[0])
                        self._note_geometry(*self._size)
                gray = raw_to_gray(raw, self._raw_format, *self._size)
                got = (gray.shape[1], gray.shape[0])
                if got != self._size:  # only a JPEG can decode to another size
                    if self._size_reported:
                        raise FrameError(f"{self.pixel_format} frame decodes to {got[0]}x{got[1]}, the "
                                         f"driver announced {self._size[0]}x{self._size[1]}")
                    self._size = got
                    self._note_geometry(*got)
            except FrameError as exc:
                self._skip(index, exc)
                continue
            self._bad_in_row = 0
            stamp_us = int(self._cap.get(cv2.CAP_PROP_POS_MSEC) * 1000.0)
            if not (0 < now - stamp_us < _PLAUSIBLE_TIMESTAMP_US):
                stamp_us = now  # driver without monotonic buffer timestamps
            return Frame(fit_to(gray, self.width, self.height), stamp_us, stamp_us, index)

