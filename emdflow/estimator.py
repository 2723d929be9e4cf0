"""`FlowEstimator`: the public entry point of the engine."""

from __future__ import annotations

import numpy as np

from .field import FlowField
from .params import EngineParams, _is_whole
from .reference import (STAT_BRIGHTENING, STAT_STEP_CHANGED, STAT_U_DETECTIONS, STAT_V_DETECTIONS,
                        ReferenceEngine, _Codes)

__all__ = ["FlowEstimator", "FrameSizeError", "BACKENDS"]

BACKENDS = ("opencl", "numpy")
#: Largest frame (pixels): the kernels' 32-bit sums (the frame's brightness for the
#: compensation, 255 per pixel; each counter copy's contrast sum) stay exact up to it.
MAX_PIXELS = 1 << 24
#: Widest frame (pixels): the OpenCL texture statistic's column arithmetic is 16-bit.
MAX_WIDTH = 1 << 15

#: A frame where at least this share of the finest receptors changed, and nearly all the
#: same way (brightening share above 1 - POLARITY or below POLARITY), is a global
#: brightness step (auto-exposure, lights), not motion. With brightness compensation the
#: test reads the states that channel would have without it.
STEP_CHANGED = 0.2
STEP_POLARITY = 0.1


def _empty_output(height: int, width: int, stats, hist, positions):
    """The output of a frame before the history is full: no codes, no detections counted
    or binned (the frame's other counters, texture and changed states, stay)."""
    stats = stats.copy()
    stats[STAT_U_DETECTIONS] = stats[STAT_V_DETECTIONS] = 0
    codes = np.zeros((height, width), np.int8)
    empty = None if hist is None else np.zeros_like(hist)
    return _Codes(codes, codes.copy()), stats, empty, None if positions is None else np.zeros_like(positions)


def _is_brightness_step(stats, pixels: int) -> bool:
    # the finest one-frame channel's states *without* brightness compensation (which
    # takes a step's mean out; what is left of a gain step has both polarities)
    changed = int(stats[STAT_STEP_CHANGED])
    if changed < STEP_CHANGED * pixels:
        return False
    bright = int(stats[STAT_BRIGHTENING]) / changed
    return bright > 1 - STEP_POLARITY or bright < STEP_POLARITY


class FrameSizeError(ValueError):
    """A frame size the engine cannot take (too small, too many pixels, too wide): a
    ``ValueError`` that callers can tell from a bad option (the daemon and the tools then
    name the source of the frames, not the engine's settings)."""


class FlowEstimator:
    """Insect-vision optical flow (Elementary Velocity Detector) over a stream of frames.

    Parameters
    ----------
    width, height : int
        Frame size in pixels, at least 3 wide and 4 high, at most 2^24 pixels and 32 768
        (``MAX_WIDTH``) wide (:class:`FrameSizeError` otherwise). Every frame given to
        :meth:`update` must have this size.
    backend : {'opencl', 'numpy'}
        ``'opencl'`` (default) runs the kernels in ``kernels/`` through pyopencl;
        ``'numpy'`` runs the reference implementation (exactly the same results, far
        slower).
    scales : tuple of int, optional
        Odd receptor sizes in pixels, paper default ``(1, 3, 5, 7, 9, 11, 13)`` (§3.2).
    threshold : float, optional
        Ternary threshold in gray levels of 8-bit input, paper default 5 (§4).
    prefilter_size : int, optional
        Gaussian prefilter width (odd, at most 101 px), ``sigma = size / 6``; paper default 11,
        0 = off (§4).
    sharp_templates : bool, optional
        Accept the sharp template ``[p 0 / 0 p]`` too (default False, spec §2).
    delays : tuple of int, optional
        Temporal delays in frames; ``(1,)`` (default) is the paper's model, ``(1, 2, 4)``
        adds slow channels (1/2 and 1/4 px/frame at scale 1).
    delay_scales : tuple of int, optional
        Scales at which delays > 1 apply (default ``(1,)``).
    threshold_mode : {'fixed', 'adaptive', 'local'}, optional
        ``'fixed'`` (default, the paper), ``'adaptive'``: θ follows the scene contrast
        frame by frame, or ``'local'``: the same per tile of the frame, so each part of the
        view follows its own contrast (see :class:`emdflow.EngineParams`).
    threshold_tile : int, optional
        Side of the tiles of ``threshold_mode='local'``, px (default 64; a multiple of 32).
    adaptive_gain, threshold_min, threshold_max : float, optional
        Gain and limits of the adaptive threshold, gray levels.
    brightness_compensation : bool, optional
        Luminance adaptation (default False, the paper): each channel compares its
        receptors with their values ``D`` frames back scaled by the exposure gain over
        those frames (the ratio of the frames' brightness), so an exposure drift does not
        favour one polarity of the states (see :class:`emdflow.EngineParams`).
    gradient_classes : bool, optional
        Bin the summary's evidence also by gradient strength (default False; the extended
        model's summary table needs it, see :class:`emdflow.EngineParams`).
    evidence_row_step : int, optional
        Every how many rows the detections feed the summary's evidence; 0 (default):
        automatic, about 60 rows per frame. Denser evidence gives a more accurate summary
        direction for more engine time (see :class:`emdflow.EngineParams`).
    summary_evidence : bool, optional
        Compute the evidence of :func:`emdflow.summarize` and of the looming cues
        (default True). False: the dense field and the counters only, 20–27 % less engine
        time at 640×480 and 42–44 % at 320×240 (the extended and the paper's model, threads
        pinned, the README's "Speed" table; more with PoCL's own scheduling); those
        functions then refuse the field (ValueError).
    diagonal_evidence : bool, optional
        Also bin the detections of velocity detectors along the two diagonals into the
        summary's evidence (default True; see :class:`emdflow.EngineParams`). The dense
        field does not change.
    device : str or int, optional
        OpenCL device: an index into :func:`emdflow.opencl_devices` or a substring of the
        platform/device name (OpenCL backend only). Default: the ``EMDFLOW_OPENCL_DEVICE``
        environment variable, else the first device found that builds the kernels
        (:attr:`device` then names it).

    Raises
    ------
    ValueError
        On a bad size or parameter, naming it.
    RuntimeError
        When ``backend='opencl'`` and no OpenCL platform is usable; the message says how
        to install one.

    Examples
    --------
    >>> est = FlowEstimator(320, 240, backend="numpy")
    >>> field = est.update(frame)          # doctest: +SKIP
    >>> s = summarize(field)               # doctest: +SKIP
    """

    def __init__(
        self,
        width: int,
        height: int,
        backend: str = "opencl",
        *,
        scales=(1, 3, 5, 7, 9, 11, 13),
        threshold: float = 5.0,
        prefilter_size: int = 11,
        sharp_templates: bool = False,
        delays=(1,),
        delay_scales=(1,),
        threshold_mode: str = "fixed",
        threshold_tile: int = 64,
        adaptive_gain: float = 0.4,
        threshold_min: float = 1.5,
        threshold_max: float = 10.0,
        brightness_compensation: bool = False,
        gradient_classes: bool = False,
        evidence_row_step: int = 0,
        summary_evidence: bool = True,
        diagonal_evidence: bool = True,
        device=None,
    ):
        for name, value in (("width", width), ("height", height)):
            if not _is_whole(value):
                raise ValueError(f"{name} must be an integer number of pixels, got {value!r}")
        # (Python ints from here: numpy integers would wrap in width * height)
        width, height = int(width), int(height)
        if width < 3 or height < 4:
            # the texture statistic samples the even interior rows: a 3-row frame has none,
            # and its summary would be blind for good
            raise FrameSizeError(f"frame size {width}x{height}: at least 3 px wide and 4 px high")
        if width * height > MAX_PIXELS:
            raise FrameSizeError(f"frame size {width}x{height}: at most {MAX_PIXELS} pixels (e.g. 4096x4096) "
                             "are supported")
        if width > MAX_WIDTH:
            # (wider, OpenCL's texture and contrast counters read 0: a blind summary)
            raise FrameSizeError(f"frame size {width}x{height}: at most {MAX_WIDTH} px wide")
        if backend not in BACKENDS:
            raise ValueError(f"backend={backend!r}: expected one of {', '.join(BACKENDS)}")
        self.width, self.height, self.backend = int(width), int(height), backend
        # (EngineParams checks every value's type and range: no silent conversion here)
        self.params = EngineParams(
            scales=scales,
            threshold=threshold,
            prefilter_size=prefilter_size,
            sharp_templates=sharp_templates,
            delays=delays,
            delay_scales=delay_scales,
            threshold_mode=threshold_mode,
            threshold_tile=threshold_tile,
            adaptive_gain=adaptive_gain,
            threshold_min=threshold_min,
            threshold_max=threshold_max,
            brightness_compensation=brightness_compensation,
            gradient_classes=gradient_classes,
            evidence_row_step=evidence_row_step,
            summary_evidence=summary_evidence,
            diagonal_evidence=diagonal_evidence,
        )
        if backend == "numpy":
            if device is not None:  # (a choice that would silently do nothing)
                raise ValueError(f"device={device!r}: only the OpenCL backend runs on a device, "
                                 "not backend='numpy'")
            self._engine = ReferenceEngine(self.width, self.height, self.params)
        else:
            from .opencl_backend import OpenCLEngine

            self._engine = OpenCLEngine(self.width, self.height, self.params, device=device)
        self._frames = 0
        self._last_step = None
        # Frames flagged from a brightness step on: a delay-D channel's templates read its
        # states of t - 2D, t - D and t, so the step sits in them for 3D frames. Without
        # brightness compensation all of it reads as motion (0.5 px/frame read 0.60-0.66 at
        # quality 116-236 four to eleven frames after a x1.3 step, delays 1, 2, 4): the
        # whole 3 max(D). With it the delayed channels' share is taken out (0.49 at quality
        # 238-241 over the same frames, one frame of 0.39 after a x0.7 step), and dropping
        # them for 12 frames would blind the extended model's hovering channels: 3.
        self._step_frames = 3 if self.params.brightness_compensation else 3 * self.params.max_delay

    def _check(self, frame) -> np.ndarray:
        expected = f"a 2-D uint8 array of shape ({self.height}, {self.width})"
        if not isinstance(frame, np.ndarray):
            raise ValueError(f"frame: expected {expected}, got {type(frame).__name__}")
        if isinstance(frame, np.ma.MaskedArray):
            # the OpenCL backend would read the data under the mask, the reference compute
            # with the mask: neither is what a mask means here
            raise ValueError(f"frame: expected {expected}, got a masked array (fill it first: "
                             "frame.filled(value))")
        if frame.ndim != 2:
            raise ValueError(f"frame: expected {expected}, got {frame.ndim}-D shape {frame.shape}")
        if frame.dtype != np.uint8:
            raise ValueError(f"frame: expected {expected}, got dtype {frame.dtype}")
        if frame.shape != (self.height, self.width):
            raise ValueError(
                f"frame: expected {expected}, got shape {frame.shape} "
                f"({frame.shape[1]}x{frame.shape[0]} instead of {self.width}x{self.height})"
            )
        return frame

    def update(self, frame: np.ndarray) -> FlowField:
        """Feed one frame; returns the flow field for it (all NaN until history is full).

        Parameters
        ----------
        frame : ndarray of uint8, shape (height, width)
            Gray image; frames are assumed evenly spaced in time.

        Returns
        -------
        FlowField
            ``u``, ``v`` in px/frame (NaN = undetected) plus the summary's evidence. The
            arrays belong to the caller.
        """
        frame = self._check(frame)
        # the codes stay behind decode() (bit-packed on OpenCL) until the dense field is read
        packed, stats, hist, positions = self._engine.step_packed(frame)
        self._frames += 1
        if self._frames <= self.params.history_frames:
            # The slowest channel's history is not full yet, and until it is the field is
            # all NaN (and its detection counts and histograms empty): with delays > 1 the
            # one-frame channels could fire from frame 4, but the summary's tables and the
            # field's contract are for the whole channel set.
            packed, stats, hist, positions = _empty_output(self.height, self.width, stats, hist, positions)
        if _is_brightness_step(stats, self.width * self.height):
            self._last_step = self._frames
        # the step's states sit in the templates of this frame and the next
        # _step_frames - 1 (2, or 3 max(delays) - 1 for uncompensated delays)
        in_templates = self._last_step is not None and self._frames - self._last_step < self._step_frames
        return FlowField(None, None, stats, hist, self.params, self._frames, positions=positions,
                         exposure_step=in_templates, packed=packed, shape=(self.height, self.width))

    def reset(self) -> None:
        """Forget the frame history (the next 3·max(delays) frames give no flow)."""
        self._engine.reset()
        self._frames = 0
        self._last_step = None

    @property
    def device(self) -> str | None:
        """The OpenCL device the engine runs on, ``"platform: device"`` as
        :func:`emdflow.opencl_devices` names it (the automatic choice may pass over devices
        that cannot build the kernels); None on the numpy backend."""
        dev = getattr(self._engine, "device", None)
        if dev is None:
            return None
        from .opencl_backend import device_label

        return device_label(dev)

    @property
    def frames_seen(self) -> int:
        """Frames processed since construction or the last reset."""
        return self._frames

    def __repr__(self) -> str:
        return f"FlowEstimator({self.width}, {self.height}, backend={self.backend!r}, {self.params})"
