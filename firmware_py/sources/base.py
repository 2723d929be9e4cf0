"""The one interface every frame source implements.

A source delivers gray frames at the *processing* resolution (it crops to the processing
aspect ratio and resizes or bins what the camera or file gives, one scale for both axes),
each with a capture timestamp in the source's own clock and the host monotonic time at which
it was captured or received (for latency measurement).
"""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np

__all__ = ["Frame", "FrameSource", "SourceError", "SourceConfigError", "FrameError", "Pacer", "fit_to",
           "centre_crop"]

#: At most one "frame skipped" log line per this many seconds (the sources' unconvertible
#: buffers, the daemon's frames of the wrong size).
_BAD_FRAME_LOG_S = 5.0


class SourceError(RuntimeError):
    """A source cannot be opened or has failed; the message names the device or file."""


class SourceConfigError(SourceError):
    """The camera is there but cannot work as configured (a pixel format it substitutes
    with one emdflow cannot decode, a socket the device does not have): retrying cannot
    help. At start the daemon exits with 2 on it; a camera that shows it after a reopen is
    retried like a lost one (another device may have been plugged in)."""


class FrameError(SourceError):
    """One frame cannot be converted (a corrupt or short camera buffer); the device is fine.

    Sources skip such a frame and count it (:attr:`FrameSource.bad_frames`) instead of
    treating it as a lost device; only a run of them ends in :class:`SourceError`.
    """


@dataclasses.dataclass(frozen=True, slots=True)
class Frame:
    """One gray frame at the processing resolution.

    Attributes
    ----------
    image : numpy.ndarray
        2-D uint8, C-contiguous, shape (height, width).
    timestamp_us : int
        Capture time in the source's clock, µs: the device's timestamp where there is one
        (V4L2 buffer time, DepthAI device time), ``index / fps`` for files and synthetic
        flights. Rates and integration times are computed from this, never the wall clock.
    capture_host_us : int
        Host monotonic time, µs, at which the frame was captured (V4L2, DepthAI) or
        decoded/rendered (files, synthetic): the start of the latency measurement.
    index : int
        Frame number since the source was opened (device sequence number where available).
    """

    image: np.ndarray
    timestamp_us: int
    capture_host_us: int
    index: int


class FrameSource:
    """Base class of all frame sources.

    Subclasses implement :meth:`open`, :meth:`read` and :meth:`close`. ``read`` returns the
    next :class:`Frame`, ``None`` at the end of a finite stream, and raises
    :class:`SourceError` when the device fails.

    Attributes
    ----------
    uri : str
        The URI the source was made from (for log lines).
    width, height : int
        Processing resolution of the frames it delivers, px.
    fps : float
        Nominal frame rate, frames/s (a file's own rate, a camera's requested rate).
    live : bool
        True for cameras (frames arrive on their own schedule and must not be queued).
    default_focal_length_px : float or None
        Focal length at the processing resolution to use when the configuration gives
        none; ``None`` for cameras, whose lens the configuration must describe.
    waited_us : int
        Time the last :meth:`read` slept for ``--realtime`` pacing, µs.
    bad_frames : int
        Frames skipped since construction because they could not be converted (a corrupt
        camera buffer); they never reach the caller.
    missed_frames : int
        Frames a paced (``--realtime``) file or flight moved past since construction
        because its reader was late for them, as a camera drops them.
    crop_fraction : (float, float)
        Fractions of the delivered image's width and height that the processed frames show
        (1.0, 1.0 unless the camera or file has another aspect ratio than the processing
        size and was centre-cropped to it); known after :meth:`open`.
    """

    uri: str = ""
    width: int = 0
    height: int = 0
    fps: float = 0.0
    live: bool = False
    default_focal_length_px: float | None = None
    #: Time the last :meth:`read` spent pacing (``--realtime``), µs: not capture work.
    waited_us: int = 0
    bad_frames: int = 0
    missed_frames: int = 0
    crop_fraction: tuple[float, float] = (1.0, 1.0)

    def open(self) -> None:
        """Open the device or file; raise :class:`SourceError` naming it on failure."""
        raise NotImplementedError

    def _record_crop(self, delivered_w: int, delivered_h: int) -> tuple[int, int, int, int]:
        """Set :attr:`crop_fraction` for a delivered ``delivered_w × delivered_h`` image
        and return its centre crop to the processing aspect ratio, ``(x0, y0, crop_width,
        crop_height)`` (:func:`centre_crop`); each source says in its own words what it cuts."""
        crop = centre_crop(delivered_w, delivered_h, self.width, self.height)
        self.crop_fraction = (crop[2] / delivered_w, crop[3] / delivered_h)
        return crop

    def read(self) -> Frame | None:
        """Return the next frame (blocking until it is there), or None at end of stream."""
        raise NotImplementedError

    #: read() waits on a clock it cannot report through :meth:`pacing_wait_s` (a paced
    #: DepthAI replay, which ReplayVideo paces inside the pipeline): the daemon reads such a
    #: source in a capture thread, as a camera, so the link is serviced while it waits.
    waits_in_read: bool = False

    def pacing_wait_s(self) -> float:
        """How long :meth:`read` would sleep before its next frame is due (``--realtime``
        files and synthetic flights), s; 0 for sources that are not paced here. The
        single-threaded daemon waits for a slow paced frame in short slices, servicing the
        link in between, instead of sleeping a whole frame period inside :meth:`read`."""
        return 0.0

    def close(self) -> None:
        """Release the device or file; safe to call twice."""
        cap = getattr(self, "_cap", None)  # OpenCV-backed sources keep a VideoCapture here
        if cap is not None:
            cap.release()
            self._cap = None

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.uri!r}, {self.width}x{self.height} @ {self.fps:g} fps)"


def centre_crop(in_width: int, in_height: int, width: int, height: int) -> tuple[int, int, int, int]:
    """The largest centred region of an ``in_width × in_height`` image with the aspect ratio
    ``width : height``, as ``(x0, y0, crop_width, crop_height)`` in px of the input.

    The whole image when the aspect ratios agree (to the pixel): a wider input loses columns
    on both sides, a taller one rows at the top and bottom. Resizing the crop to
    ``width × height`` then applies one scale to both axes, which the link's single focal
    length assumes.
    """
    if in_width * height > in_height * width:      # wider than asked: cut the sides
        crop_w, crop_h = min(in_width, max(1, round(in_height * width / height))), in_height
    else:                                          # taller (or equal): cut top and bottom
        crop_w, crop_h = in_width, min(in_height, max(1, round(in_width * height / width)))
    return (in_width - crop_w) // 2, (in_height - crop_h) // 2, crop_w, crop_h


def fit_to(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Return ``image`` at (height, width): centre-cropped to the aspect ratio
    ``width : height`` (:func:`centre_crop`), then area-averaged (binning for integer
    factors), so x and y are scaled alike.

    The input is returned unchanged, without a copy, when it already has that size.
    """
    in_h, in_w = image.shape[:2]
    if in_h == height and in_w == width:
        return image if image.flags.c_contiguous else np.ascontiguousarray(image)
    x0, y0, crop_w, crop_h = centre_crop(in_w, in_h, width, height)
    if (crop_w, crop_h) != (in_w, in_h):
        image = image[y0:y0 + crop_h, x0:x0 + crop_w]   # a view; resize reads it in place
        if (crop_w, crop_h) == (width, height):
            return np.ascontiguousarray(image)
    # INTER_AREA is exact pixel binning for integer factors and the right low-pass otherwise.
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


class Pacer:
    """Releases frame ``i`` at ``start + i / fps`` (``--realtime``), the way a camera would.

    A camera does not wait for a slow reader: when the reader is a whole frame period or
    more behind, the frames it missed are skipped, and a frame's capture instant is the time
    it was due — so latency measured from it includes any lateness.

    Parameters
    ----------
    fps : float
        Release rate, frames/s.
    """

    def __init__(self, fps: float):
        self.period_s = 1.0 / float(fps)
        self._start: float | None = None

    def next(self, index: int) -> tuple[int, int, int]:
        """Wait for the frame to deliver next.

        Parameters
        ----------
        index : int
            The next frame in sequence.

        Returns
        -------
        (int, int, int)
            The index to deliver (``index`` or later when frames were missed), the time
            slept in µs (not capture work), and the host monotonic time it was due, µs.
        """
        now = time.monotonic()
        if self._start is None:
            self._start = now - index * self.period_s
        due = self._start + index * self.period_s
        if now - due >= self.period_s:
            index = int((now - self._start) / self.period_s)
            due = self._start + index * self.period_s
        slept = 0
        if due > now:
            time.sleep(due - now)
            slept = int((due - now) * 1e6)
        return index, slept, int(due * 1e6)

    def wait_s(self, index: int) -> float:
        """Time until frame ``index`` is due, s: what :meth:`next` would sleep (0 when the
        schedule has not started, or the frame is due or late)."""
        if self._start is None:
            return 0.0
        return max(0.0, self._start + index * self.period_s - time.monotonic())

    def restart(self) -> None:
        """Forget the schedule (after a rewind)."""
        self._start = None
