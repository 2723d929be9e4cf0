"""The per-frame result of the detector: a sparse flow field plus the summary's evidence."""

from __future__ import annotations

import functools

import numpy as np

from .params import EngineParams
from .reference import (
    STAT_BRIGHTENING,
    STAT_FIRST_CHANGED,
    STAT_SATURATED,
    STAT_STEP_CHANGED,
    STAT_TEXTURED,
    STAT_U_DETECTIONS,
    STAT_V_DETECTIONS,
)

__all__ = ["FlowField"]


@functools.lru_cache(maxsize=8)
def _code_table(speeds: tuple) -> np.ndarray:
    """float32 speed of every int8 code (indexed as uint8), NaN for 0 = undetected."""
    lut = np.full(256, np.nan, np.float32)
    for c, s in enumerate(speeds):
        lut[c + 1] = s
        lut[(-(c + 1)) & 0xFF] = -s
    lut.setflags(write=False)
    return lut


class FlowField:
    """Sparse optical flow of one frame, as the Elementary Velocity Detector sees it.

    The detector outputs a flow *code* per pixel and axis (int8: ``±(c+1)`` for channel
    ``c`` in the positive/negative direction, 0 for nothing). ``u`` and ``v`` are
    materialised from the codes on first access (float32, px/frame, NaN where undetected)
    and cached, so a caller that only needs :func:`emdflow.summarize` never pays for them.

    Attributes
    ----------
    u_code, v_code : ndarray of int8, shape (H, W)
        Raw flow codes (owned by this field; they stay valid after the next update). The
        OpenCL backend downloads them as bit planes and unpacks them on first access.
    speeds : tuple of float
        Speed of each channel, px/frame (``u = sign(code) · speeds[|code| − 1]``).
    stats : ndarray of int64
        Per-frame counters (detections, textured and saturated pixels, changed states).
    histogram : ndarray of int64, shape (params.evidence_axes, 2·channels, params.histogram_bins), or None
        Detections binned by axis (horizontal, vertical, and with ``diagonal_evidence`` the
        two diagonals), signed channel, gradient-strength class and gradient
        orientation (``class · ORIENTATION_BINS + orientation``; the summary's input; see
        :func:`emdflow.reference.summary_statistics`). None when the estimator was made
        with ``summary_evidence=False``.
    positions : ndarray of int64, shape (2, 2·channels, position bins) or None
        The same detections binned by x (horizontal) or y (vertical) position, for the
        expansion and balance cues (None like ``histogram``).
    frame_index : int
        Frames seen since the last reset, counting this one (1 for the first frame).
    exposure_step : bool
        A global brightness step (auto-exposure, lights) happened in this frame or one of
        the two before (with delays above 1 and no brightness compensation: the
        3 max(delays) - 1 before) — it is inside the velocity templates, so the detections
        are not to be trusted (the summary reports quality 0).
    ready : bool
        True once the detector's history is full (before that, everything is NaN).
    """

    __slots__ = (
        "speeds", "stats", "histogram", "frame_index", "ready",
        "params", "positions", "exposure_step", "_u", "_v", "_u_code", "_v_code", "_packed", "_shape",
    )

    def __init__(self, u_code, v_code, stats, histogram, params: EngineParams, frame_index: int,
                 *, positions=None, exposure_step: bool = False, packed=None, shape=None):
        # either the int8 codes, or `packed` (an object whose decode() gives them, e.g. the
        # OpenCL backend's bit planes) and the shape: decoded on first access
        self._u_code = u_code
        self._v_code = v_code
        self._packed = packed
        self._shape = tuple(shape) if shape is not None else u_code.shape
        self.stats = stats
        self.histogram = histogram
        self.positions = positions
        self.exposure_step = bool(exposure_step)
        self.params = params
        self.speeds = params.speeds
        self.frame_index = int(frame_index)
        self.ready = self.frame_index > params.history_frames
        self._u = None
        self._v = None

    @property
    def shape(self) -> tuple[int, int]:
        return self._shape

    def require_evidence(self, caller: str) -> None:
        """Raise ValueError (naming ``caller``) if the field carries no summary evidence."""
        if not self.params.summary_evidence:
            raise ValueError(f"{caller}: this field has no summary evidence (its FlowEstimator was "
                             "made with summary_evidence=False, which computes the dense field only)")
        if self.histogram is None:
            raise ValueError(f"{caller}: this field has no summary evidence (its histogram is None: a "
                             "FlowField made by hand needs one, as FlowEstimator.update gives it)")

    def _decode(self) -> None:
        self._u_code, self._v_code = self._packed.decode()
        self._packed = None

    @property
    def u_code(self) -> np.ndarray:
        """Raw horizontal flow codes, int8 (0 none, ±(c+1) = channel c, sign = direction)."""
        if self._u_code is None:
            self._decode()
        return self._u_code

    @property
    def v_code(self) -> np.ndarray:
        """Raw vertical flow codes, int8, like ``u_code``."""
        if self._v_code is None:
            self._decode()
        return self._v_code

    def _lookup(self) -> np.ndarray:
        return _code_table(self.speeds)

    @property
    def u(self) -> np.ndarray:
        """Horizontal flow, float32 px/frame (right positive), NaN where undetected."""
        if self._u is None:
            self._u = self._lookup()[self.u_code.view(np.uint8)]
        return self._u

    @property
    def v(self) -> np.ndarray:
        """Vertical flow, float32 px/frame (down positive), NaN where undetected."""
        if self._v is None:
            self._v = self._lookup()[self.v_code.view(np.uint8)]
        return self._v

    @property
    def u_detections(self) -> int:
        return int(self.stats[STAT_U_DETECTIONS])

    @property
    def v_detections(self) -> int:
        return int(self.stats[STAT_V_DETECTIONS])

    @property
    def textured_fraction(self) -> float:
        """Share of sampled pixels with enough contrast for the detector (0..1)."""
        h, w = self.shape
        sampled = max(1, ((h - 2) // 2) * max(0, w - 2))  # even interior rows
        return float(self.stats[STAT_TEXTURED]) / sampled

    @property
    def saturated_fraction(self) -> float:
        """Share of sampled pixels at the ends of the 8-bit range (0..1)."""
        h, w = self.shape
        return float(self.stats[STAT_SATURATED]) / max(1, ((h + 1) // 2) * w)

    @property
    def brightening_fraction(self) -> float:
        """Share of the finest one-frame channel's nonzero states that are positive (0..1;
        0.5 if none): its states *before* brightness compensation, the ones the
        exposure-step test reads (with compensation on, the channel's own states have a
        gain step taken out and are counted apart, in :attr:`changed_fraction`)."""
        changed = int(self.stats[STAT_STEP_CHANGED])
        return float(self.stats[STAT_BRIGHTENING]) / changed if changed else 0.5

    @property
    def changed_fraction(self) -> np.ndarray:
        """Per channel, share of pixels whose ternary state is nonzero."""
        h, w = self.shape
        return self.stats[STAT_FIRST_CHANGED:].astype(np.float64) / (h * w)

    def __repr__(self) -> str:
        h, w = self.shape
        return (
            f"FlowField({w}x{h}, frame {self.frame_index}, "
            f"{self.u_detections} u / {self.v_detections} v detections)"
        )
