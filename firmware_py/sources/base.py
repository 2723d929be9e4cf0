"""The one interface every frame source implements.

A source delivers gray frames at the *processing* resolution (it resizes or bins what the
camera or file gives), each with a capture timestamp in the source's own clock and the host
monotonic time at which it was captured or received (for latency measurement).
"""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np

__all__ = ["Frame", "FrameSource", "SourceError", "Pacer", "fit_to", "host_us"]


class SourceError(RuntimeError):
    """A source cannot be opened or has failed; the message names the device or file."""


def host_us() -> int:
    """Host monotonic clock in microseconds (``CLOCK_MONOTONIC``, as V4L2 and DepthAI use)."""
    return time.monotonic_ns() // 1000


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
    """

    uri: str = ""
    width: int = 0
    height: int = 0
    fps: float = 0.0
    live: bool = False
    default_focal_length_px: float | None = None
    #: Time the last :meth:`read` spent pacing (``--realtime``), µs: not capture work.
    waited_us: int = 0

    def open(self) -> None:
        """Open the device or file; raise :class:`SourceError` naming it on failure."""
        raise NotImplementedError

    def read(self) -> Frame | None:
        """Return the next frame (blocking until it is there), or None at end of stream."""
        raise NotImplementedError

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


def fit_to(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Return ``image`` at (height, width), area-averaged (binning for integer factors).

    The input is returned unchanged, without a copy, when it already has that size.
    """
    if image.shape[0] == height and image.shape[1] == width:
        return image if image.flags.c_contiguous else np.ascontiguousarray(image)
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

    def restart(self) -> None:
        """Forget the schedule (after a rewind)."""
        self._start = None
