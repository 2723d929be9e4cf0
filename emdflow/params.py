"""Model parameters and the integer tables that both backends share.

Everything the detector compares is an exact integer, so the numpy reference and the
OpenCL kernels agree bit for bit:

* the prefilter is a separable Gaussian with integer weights summing to 256 per axis,
  each pass rounded to whole gray levels, so the prefiltered image ``P`` is 8-bit;
* receptor values are *box sums* of ``P`` over ``k × k`` blocks (never divided; below
  2**16 for ``k ≤ 15``);
* the threshold θ is held in fixed point, ``θq = round(256 θ)``, and the ternary
  threshold on a box-sum difference is ``(θq · k²) >> 8`` = ``floor(θ̂ · k²)`` with
  ``θ̂ = θq / 256`` (θ rounded to a multiple of 1/256 gray level: θ itself for the default
  5.0), compared with ``>``, which is exactly "mean change > θ̂ gray levels";
* the gradient orientation used by the summary is binned with integer cross products
  against a table of boundary directions.

Channels
--------
A *channel* is one (scale ``k``, delay ``D``) pair. Its detector compares receptor values
``D`` frames apart and matches at speed ``k / D`` px/frame. The paper's model is the seven
channels ``(k, 1)`` for ``k = 1, 3, …, 13``; temporal delays (``delays``) add slow channels
at the scales in ``delay_scales``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers

import numpy as np

__all__ = ["EngineParams", "gaussian_weights", "ORIENTATION_BINS", "EVIDENCE_AXIS_STEPS", "GRADIENT_CLASS_STEPS",
           "HISTOGRAM_BINS", "MODELS"]

#: Named detector models: the ``FlowEstimator`` keywords of each. ``"paper"`` is the
#: published model (seven one-frame channels, fixed threshold); ``"extended"`` adds the
#: delays 2 and 4 at scale 1 (1/2 and 1/4 px/frame: hovering drift), a scale-15 channel
#: (the top of the 1–13 px/frame range is then inside a channel's band, not at the end
#: of the fastest one: 13 px/frame reads within 15 % instead of 33 %, for 5–7 % more
#: engine time), the contrast-adaptive threshold, brightness compensation (exposure
#: drift) and the gradient-strength classes of the summary's evidence. The daemon, the
#: benchmark and the calibration tools all use this.
MODELS = {
    "paper": {},
    "extended": {"scales": (1, 3, 5, 7, 9, 11, 13, 15), "delays": (1, 2, 4),
                 "delay_scales": (1,), "threshold_mode": "adaptive",
                 "brightness_compensation": True, "gradient_classes": True},
}

#: Orientation bins over 180° used to summarise the gradient direction of detections.
ORIENTATION_BINS = 64
#: Detector step ``B − A`` per scale unit (x right, y down) of each axis of the summary's
#: detection histogram: horizontal, vertical and, with ``diagonal_evidence``, the two
#: diagonals (the engine's detectors, the summary's geometry and the calibration's).
EVIDENCE_AXIS_STEPS = ((1, 0), (0, 1), (1, 1), (1, -1))
#: Gradient-strength classes of a detection: its class counts the steps ``m`` with
#: ``|∇R_k|₁ ≥ (m / 2) · 2θk²``, i.e. ``512 (|gx| + |gy|) ≥ m · 2 θ_q k²`` (exact integers;
#: with brightness compensation ``2 · gain_q`` instead of 512, the channel's exposure gain
#: bringing the gradient of ``t − D`` to the brightness of ``t``, whose threshold it meets).
#: ``|∇R_k|₁ / 2θk²`` is about the inverse of the displacement (px) that changes the receptor
#: by θ k², so it says which delays and scales *can* fire at a given speed: the code mixture
#: of a class depends much less on the texture than the mixture of all detections.
GRADIENT_CLASS_STEPS = (1, 2, 4)
#: Bins per (axis, code) row of the detection histogram with gradient classes: class-major,
#: ``bin = class · ORIENTATION_BINS + orientation`` (without: ``ORIENTATION_BINS``; see
#: :attr:`EngineParams.histogram_bins`).
HISTOGRAM_BINS = (len(GRADIENT_CLASS_STEPS) + 1) * ORIENTATION_BINS
#: Fixed-point scale of the orientation boundary table (cos/sin × 2**14).
_ORIENT_ONE = 1 << 14
#: Widest prefilter window, px (sigma = 17 px, already beyond the widest receptor, 15 px;
#: the OpenCL kernel keeps one horizontal pass per tap of the window in registers, and a
#: window of 100 001 taps took 13 s per 40×30 frame).
MAX_PREFILTER_SIZE = 101
#: The paper's 11-tap Gaussian (sigma = 11/6) with integer weights summing to 256.
_GAUSS11 = (1, 5, 15, 31, 48, 56, 48, 31, 15, 5, 1)


def gaussian_weights(size: int, total: int = 256) -> tuple[int, ...]:
    """Integer 1-D Gaussian weights of ``size`` taps (sigma = size / 6) summing to ``total``.

    The sampled Gaussian is rounded with the largest-remainder method, once, on the host;
    both backends use the same table. ``size`` 0 or 1 means no prefilter: ``(total,)``.
    For ``size == 11`` this is the table ``[1 5 15 31 48 56 48 31 15 5 1]``.
    """
    if size in (0, 1):
        return (total,)
    if size < 0 or size % 2 == 0 or size > MAX_PREFILTER_SIZE:
        raise ValueError(f"prefilter_size={size}: must be 0 (off) or an odd number from 3 to "
                         f"{MAX_PREFILTER_SIZE}")
    if size == 11 and total == 256:
        return _GAUSS11
    sigma = size / 6.0
    half = size // 2
    x = np.arange(size) - half
    g = np.exp(-0.5 * (x / sigma) ** 2)
    exact = g / g.sum() * total
    w = np.floor(exact).astype(np.int64)
    # Largest remainders take the missing units, in mirror pairs so the table stays
    # symmetric; an odd unit left over goes to the centre tap.
    rest = int(total - w.sum())
    for i in sorted(range(half), key=lambda i: -(exact[i] - w[i])):
        if rest < 2:
            break
        w[i] += 1
        w[size - 1 - i] += 1
        rest -= 2
    w[half] += rest
    return tuple(int(v) for v in w)


#: Channels (scale, delay pairs) an engine can have: a channel's index + 1 is a 4-bit code.
MAX_CHANNELS = 15

#: ``EngineParams.threshold_mode`` values
THRESHOLD_MODES = ("fixed", "adaptive", "local")


def _is_real(value) -> bool:
    """A finite real number (numpy scalars too), not a bool or a string."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)) and math.isfinite(value)


def _is_whole(value) -> bool:
    """A whole number (int or numpy integer), not a bool, a float or a string."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _flag(name: str, value) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}={value!r}: expected True or False")
    return bool(value)


def _whole_numbers(name: str, values, what: str) -> tuple[int, ...]:
    """``values`` as a tuple of ints, or a ValueError naming ``name``."""
    if isinstance(values, (str, bytes)) or not hasattr(values, "__iter__"):
        raise ValueError(f"{name}={values!r}: expected a sequence of {what}")
    values = tuple(values)
    for v in values:
        if not _is_whole(v):
            raise ValueError(f"{name}={values!r}: {v!r} is not a whole number (expected {what})")
    return tuple(int(v) for v in values)


@dataclasses.dataclass(frozen=True)
class EngineParams:
    """Parameters of the Elementary Velocity Detector (see ``docs/spec/template-model.md``).

    Parameters
    ----------
    scales : tuple of int
        Odd receptor sizes ``k`` in pixels (paper §3.2: 1, 3, …, 13). A match at scale
        ``k`` with delay 1 means ``k`` px/frame.
    threshold : float
        Ternary threshold ``θ`` on the mean receptor change, in gray levels of the 8-bit
        input (paper §4: 5).
    prefilter_size : int
        Width ``w`` of the Gaussian prefilter window (``sigma = w / 6``; paper §4: 11), odd,
        at most :data:`MAX_PREFILTER_SIZE` (101); 0 disables it.
    sharp_templates : bool
        Also accept the "sharp" template ``[p 0 / 0 p]`` (spec §2); off in the paper's model.
    delays : tuple of int
        Temporal delays ``D`` (frames). ``(1,)`` is the paper's model; e.g. ``(1, 2, 4)``
        adds channels comparing receptors 2 and 4 frames apart, which see 1/2 and 1/4
        px/frame at scale 1.
    delay_scales : tuple of int
        Scales at which the delays > 1 are applied.
    threshold_mode : {'fixed', 'adaptive', 'local'}
        ``'fixed'`` (the paper): θ = ``threshold`` always. ``'adaptive'``: contrast
        adaptation (the paper's §5 future work) — θ for frame ``t`` is
        ``clip(adaptive_gain · g(t−1), threshold_min, threshold_max)`` with ``g`` the mean
        ``|ΔxP| + |ΔyP|`` (central differences, gray levels) of the previous frame, so the
        detector keeps its density when scene contrast or exposure changes. ``'local'``:
        the same rule per square tile of ``threshold_tile`` px (:meth:`next_threshold_q`),
        so a shaded or low-contrast part of the view keeps its own density beside a
        bright, contrasty one (one global θ set by the contrasty part leaves it blind).
        Every use of θ at a pixel — its states' threshold, its texture test, the gradient
        class of a detection there — takes its tile's θ.
    threshold_tile : int
        Side of the local threshold's tiles, px (a multiple of 32 from 32 to 1024; tile
        ``(y // threshold_tile, x // threshold_tile)``; the last row and column of tiles
        may be cut by the frame's edge). Used by ``threshold_mode='local'`` only.
    adaptive_gain, threshold_min, threshold_max : float
        Gain and limits of the adaptive threshold (gray levels). The defaults give θ ≈ 4–8
        on the bundled photographs at full contrast (θ = 5 is the paper's) and follow a
        contrast drop down to 1.5 (≈ 3σ of the prefiltered frame-difference noise for
        sensor noise σ = 2).
    brightness_compensation : bool
        Luminance adaptation (off in the paper's model): an exposure change is a gain, so
        before thresholding each channel compares ``256 · R(t)`` with ``ρ · R(t−D)``, ``ρ``
        the ratio of the whole prefiltered frames' brightness over the same ``D`` frames
        ×256 (:meth:`brightness_ratio_q`; threshold :meth:`compensated_threshold`
        ``256 · T + 128``; exact integers). An
        exposure drift then no longer lowers the threshold of one polarity and raises the
        other's, bright parts of the scene no more than dark ones: at a drift of 20 % over
        a flight, the slow channels' changes of 1–2 px of motion and the drift are of the
        same size. A gain step is compensated the same way; the exposure-step test counts
        the uncompensated states and catches it.
    gradient_classes : bool
        Also bin the summary's evidence by the gradient strength of each detection
        against the threshold (``GRADIENT_CLASS_STEPS``; the histogram then has
        ``HISTOGRAM_BINS`` bins per row instead of ``ORIENTATION_BINS``). Off in the paper's
        model, whose summary table has no classes; on in the extended one.
    evidence_row_step : int
        Rows between the rows whose detections feed the summary's evidence (the histogram
        of codes by gradient orientation, and the position histogram). 0 (default):
        automatic, about 60 rows per frame (:meth:`evidence_row_step_for`). The summary's
        direction error falls with the number of sampled detections and the engine's
        time grows with it: at 320×240, every row (1) instead of every 4th takes the paper
        model's median direction error on random flights from 2.37° to 2.06° and the
        extended model's from 1.80° to 1.65° with its edge table alone (1.92° to 1.73°
        with its line-ground table too), for ~0.44 ms more per frame (README, "Evidence
        density"). The detections themselves (``u``, ``v``) do not change, nor do the
        calibration tables, which do not depend on the sampling.
    summary_evidence : bool
        Compute the summary's evidence next to the detector (default True): the
        orientation and position histograms that :func:`emdflow.summarize` and
        :func:`emdflow.cues.looming_cues` read. False gives the dense field (``u``, ``v``)
        and the frame's counters only, in 20–27 % less time at 640×480 (threads pinned;
        README, "Speed"), for a caller that never summarises (a researcher's dense flow);
        those two functions then refuse the field, and so do the command-line tools, which
        summarise every frame.
        The detections do not change.
    diagonal_evidence : bool
        Also run velocity detectors along the two diagonals on the evidence rows and bin
        their detections as histogram axes 2 (down-right, ``B = A + k·(1, 1)``) and 3
        (up-right, ``B = A + k·(1, −1)``); on by default. The dense field (``u``, ``v``)
        and the position histogram stay the horizontal and vertical detectors' own (the
        paper's four directions): the diagonals only feed :func:`emdflow.summarize`,
        whose calibration tables then carry a second set of distributions for them. A
        detector is one-dimensional, and a flow with a large component across its axis
        slides the ground sideways under its receptors: over granular ground the minor
        axis of a fast oblique flow goes blind, while the diagonal nearest the flow sees
        it with little sideways motion. The paper's model on random flights at 320×240:
        6.3 % / 1.96° median error instead of 8.9 % / 2.37° (both with the summary's former
        search, ``SummaryOptions(search_climbs=0)``), for 9–16 % more engine time
        at 640×480 (README, "Diagonal evidence"; docs/speed-history.md). False
        gives the former evidence and tables.
    """

    scales: tuple[int, ...] = (1, 3, 5, 7, 9, 11, 13)
    threshold: float = 5.0
    prefilter_size: int = 11
    sharp_templates: bool = False
    delays: tuple[int, ...] = (1,)
    delay_scales: tuple[int, ...] = (1,)
    threshold_mode: str = "fixed"
    threshold_tile: int = 64
    adaptive_gain: float = 0.4
    threshold_min: float = 1.5
    threshold_max: float = 10.0
    brightness_compensation: bool = False
    gradient_classes: bool = False
    evidence_row_step: int = 0
    summary_evidence: bool = True
    diagonal_evidence: bool = True

    def __post_init__(self):
        # every field is checked for its type as well as its range: a string, a fraction
        # or None must not become a different model by silent conversion
        for name in ("sharp_templates", "brightness_compensation", "gradient_classes", "summary_evidence",
                     "diagonal_evidence"):
            object.__setattr__(self, name, _flag(name, getattr(self, name)))
        step = self.evidence_row_step
        if not _is_whole(step) or not 0 <= step <= 1024:
            raise ValueError(f"evidence_row_step={step!r}: expected a whole number of rows from 1 "
                             "to 1024, or 0 for automatic")
        object.__setattr__(self, "evidence_row_step", int(step))
        if self.threshold_mode not in THRESHOLD_MODES:
            raise ValueError(f"threshold_mode={self.threshold_mode!r}: expected 'fixed', 'adaptive' or 'local'")
        tile = self.threshold_tile
        if not _is_whole(tile) or not 32 <= tile <= 1024 or tile % 32:
            raise ValueError(f"threshold_tile={tile!r}: expected a multiple of 32 px from 32 to 1024 "
                             "(tiles hold whole 32-pixel words of the state planes)")
        object.__setattr__(self, "threshold_tile", int(tile))
        for name in ("adaptive_gain", "threshold_min", "threshold_max"):
            value = getattr(self, name)
            if not (_is_real(value) and 0 < value <= 255):
                raise ValueError(f"{name}={value!r}: must be a number in (0, 255]")
            object.__setattr__(self, name, float(value))
        if self.threshold_min > self.threshold_max:
            raise ValueError(f"threshold_min={self.threshold_min} is above threshold_max={self.threshold_max}")
        scales = _whole_numbers("scales", self.scales, "odd receptor sizes, e.g. (1, 3, 5)")
        if not scales:
            raise ValueError("scales: at least one scale is needed")
        for k in scales:
            if k < 1 or k % 2 == 0 or k > 15:
                raise ValueError(f"scales: {k} is not an odd receptor size between 1 and 15 px")
        if len(set(scales)) != len(scales):
            raise ValueError(f"scales: {scales} has duplicates")
        object.__setattr__(self, "scales", tuple(sorted(scales)))
        if not (_is_real(self.threshold) and 0 <= self.threshold <= 255):
            raise ValueError(f"threshold={self.threshold!r}: must be a number of gray levels in 0..255")
        object.__setattr__(self, "threshold", float(self.threshold))
        if not _is_whole(self.prefilter_size):
            raise ValueError(f"prefilter_size={self.prefilter_size!r}: expected a whole number of pixels "
                             "(an odd window width, or 0 for none)")
        object.__setattr__(self, "prefilter_size", int(self.prefilter_size))
        gaussian_weights(self.prefilter_size)  # validates
        delays = tuple(sorted(set(_whole_numbers("delays", self.delays, "frame delays, e.g. (1, 2, 4)"))))
        if not delays or delays[0] != 1 or delays[-1] > 16:
            raise ValueError(f"delays={self.delays}: must include 1, each between 1 and 16 frames")
        object.__setattr__(self, "delays", delays)
        dscales = tuple(sorted(set(_whole_numbers("delay_scales", self.delay_scales, "scales, e.g. (1,)"))))
        if delays[-1] > 1:  # (without delays above 1 they make no channel)
            if not dscales:
                # (they would make no channel, yet hold back the first field by their length)
                raise ValueError(f"delays={delays} with delay_scales=(): the delays above 1 need a "
                                 "scale to run at, e.g. delay_scales=(1,)")
            for k in dscales:
                if k not in scales:
                    raise ValueError(f"delay_scales: {k} is not one of the scales {scales}")
        object.__setattr__(self, "delay_scales", dscales)
        # a channel's index + 1 is a 4-bit code in both backends' output
        if len(self.channels) > MAX_CHANNELS:
            raise ValueError(f"{len(self.channels)} channels (scales x delays): at most {MAX_CHANNELS} "
                             "are supported")

    # ---- derived tables (computed once, on the host, shared by both backends) ----
    @property
    def class_steps(self) -> tuple[int, ...]:
        """Steps of the gradient-strength classes (empty without ``gradient_classes``)."""
        return GRADIENT_CLASS_STEPS if self.gradient_classes else ()

    @property
    def evidence_axes(self) -> int:
        """Detector axes in the detection histogram: horizontal and vertical, and with
        ``diagonal_evidence`` the two diagonals."""
        return 4 if self.diagonal_evidence else 2

    @property
    def histogram_bins(self) -> int:
        """Bins per (axis, code) row of the detection histogram."""
        return (len(self.class_steps) + 1) * ORIENTATION_BINS

    @property
    def weights(self) -> tuple[int, ...]:
        """Integer prefilter weights (sum 256)."""
        return gaussian_weights(int(self.prefilter_size))

    # channels and speeds are read every frame (FlowField, summary): computed once
    @functools.cached_property
    def channels(self) -> tuple[tuple[int, int], ...]:
        """(scale, delay) pairs, sorted by increasing speed ``k / D``."""
        chans = [(k, 1) for k in self.scales]
        chans += [(k, d) for d in self.delays if d > 1 for k in self.delay_scales]
        return tuple(sorted(chans, key=lambda c: (c[0] / c[1], c[0])))

    @functools.cached_property
    def speeds(self) -> tuple[float, ...]:
        """Speed of each channel in px/frame, in channel order."""
        return tuple(k / d for k, d in self.channels)

    @property
    def max_delay(self) -> int:
        return max(self.delays)

    @staticmethod
    def threshold_q(theta: float) -> int:
        """Fixed-point threshold ``round(256 θ)`` (what both backends compute with)."""
        return int(round(float(theta) * 256))

    def box_threshold(self, k: int, theta_q=None):
        """Integer threshold on a k×k box-sum difference: ``(θq · k²) >> 8`` = ``floor(θ̂ · k²)``,
        ``θ̂ = θq / 256``, θ rounded to a multiple of 1/256: ``floor(θ · k²)`` itself for the
        default 5.0, otherwise possibly one box-sum unit away (θ = 0.1, k = 13: 17, not 16).
        ``theta_q`` may be an integer array (a per-pixel map, :meth:`theta_map`): the
        thresholds are then an array of the same shape."""
        if theta_q is None:
            theta_q = self.threshold_q(self.threshold)
        if np.ndim(theta_q):
            return (np.asarray(theta_q, np.int64) * (k * k)) >> 8
        return (int(theta_q) * k * k) >> 8

    @staticmethod
    def compensated_threshold(box_threshold: int) -> int:
        """Threshold on the gain-compensated change ``256 · R(t) − ρ · R(t−D)`` (units of
        1/256 gray level × k²) for the box threshold ``T``: ``256 · T + 128``.

        The plain change is a whole number, so its test ``> T`` means ``≥ T + 1``; the
        compensated change is not, and the same test on it, ``> 256 · T``, let through
        every change between ``T`` and ``T + 1`` the plain path drops: under an exposure
        drift the threshold's floor (θ = 1.5, ``T = 1`` at scale 1) then sat at the
        rounding noise of the prefiltered frames, and a static noisy scene at a quarter
        of the contrast lit 18–21× the slow channels' states of a steady exposure (now
        2–4×: the rounding noise of a compensated change is no longer the same in both
        frames). ``256 · T + 128`` is the plain test on the compensated change rounded to
        whole units (halves down), and with ρ = 256 exactly the plain test. An array of
        thresholds (``'local'``) gives an array.
        """
        if np.ndim(box_threshold):
            return 256 * np.asarray(box_threshold, np.int64) + 128
        return 256 * int(box_threshold) + 128

    #: Largest brightness ratio of :meth:`brightness_ratio_q` (×256): 16× brighter. Keeps
    #: ``ratio · R`` of the largest box sums (15 × 15 × 255) within 32-bit integers.
    BRIGHTNESS_RATIO_MAX_Q = 4096

    def brightness_ratio_q(self, brightness_now: int, brightness_then: int) -> int:
        """Gain of the exposure between two frames, ×256, rounded: ``round(256 · B_now /
        B_then)`` for the prefiltered frames' pixel sums ``B`` (0 … ``BRIGHTNESS_RATIO_MAX_Q``;
        256 when ``B_then`` is 0 or ``brightness_compensation`` is off). 256 means no
        compensation: a ratio within ±0.2 % of 1 (motion alone changes a frame's mean by
        less, mostly) leaves the states exactly as without it.
        """
        now, then = int(brightness_now), int(brightness_then)
        if not self.brightness_compensation or then <= 0:
            return 256
        return min((512 * now + then) // (2 * then), self.BRIGHTNESS_RATIO_MAX_Q)

    def texture_threshold_for(self, theta_q):
        """Threshold on ``|ΔxP| + |ΔyP|`` for a textured pixel: ``floor(2θ)`` (an array for
        an array of thresholds)."""
        if np.ndim(theta_q):
            return (2 * np.asarray(theta_q, np.int64)) >> 8
        return (2 * int(theta_q)) >> 8

    @property
    def texture_threshold(self) -> int:
        """:meth:`texture_threshold_for` the fixed threshold."""
        return self.texture_threshold_for(self.threshold_q(self.threshold))

    def next_threshold_q(self, contrast_sum: int, sampled: int, tile_sums=None, tile_samples=None):
        """Threshold (fixed point) for the next frame from this frame's contrast statistic.

        ``'fixed'`` and ``'adaptive'``: one int. ``'local'``: an int64 array of the tiles'
        thresholds, shape :meth:`threshold_tiles`, each from its tile's contrast sum
        (``tile_sums``) over its sampled pixels (``tile_samples``, see
        :meth:`tile_contrast_samples`); a tile without samples (a sliver at the frame's
        edge) takes the whole frame's. Both backends call this one function, so their
        thresholds agree exactly once their contrast sums do.
        """
        if self.threshold_mode == "fixed" or (sampled <= 0 and self.threshold_mode == "adaptive"):
            return self.threshold_q(self.threshold)
        # (gain times the mean, in that order: the adaptive threshold as it always was)
        whole = self.adaptive_gain * (contrast_sum / sampled) if sampled > 0 else self.threshold
        if self.threshold_mode == "adaptive":
            return self.threshold_q(min(self.threshold_max, max(self.threshold_min, whole)))
        sums = np.asarray(tile_sums, np.float64)
        samples = np.asarray(tile_samples, np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            theta = np.where(samples > 0, self.adaptive_gain * (sums / samples), whole)
        theta = np.clip(theta, self.threshold_min, self.threshold_max)
        return np.rint(theta * 256).astype(np.int64)  # (half to even, as threshold_q's round)

    def threshold_tiles(self, width: int, height: int) -> tuple[int, int]:
        """``(rows, columns)`` of the local threshold's tiles for a frame (1, 1 unless
        ``threshold_mode='local'``)."""
        if self.threshold_mode != "local":
            return 1, 1
        t = self.threshold_tile
        return -(-int(height) // t), -(-int(width) // t)

    def tile_contrast_samples(self, width: int, height: int) -> np.ndarray:
        """Pixels each tile's contrast statistic samples (the sampled pixels of
        :meth:`contrast_samples` that fall in it), int64, shape :meth:`threshold_tiles`."""
        rows = np.arange(2, int(height) - 1, 2)  # even interior rows
        cols = np.arange(1, int(width) - 1)
        t = self.threshold_tile if self.threshold_mode == "local" else max(int(width), int(height))
        ny, nx = self.threshold_tiles(width, height)
        per_row = np.bincount(rows // t, minlength=ny)[:ny]
        per_col = np.bincount(cols // t, minlength=nx)[:nx]
        return np.outer(per_row, per_col).astype(np.int64)

    def first_threshold_q(self, width: int, height: int):
        """The threshold of the first frame (and after a reset): ``threshold`` as
        :meth:`threshold_q`, for ``'local'`` in every tile (an int64 array, shape
        :meth:`threshold_tiles`)."""
        q = self.threshold_q(self.threshold)
        if self.threshold_mode == "local":
            return np.full(self.threshold_tiles(width, height), q, np.int64)
        return q

    def theta_map(self, theta_q, width: int, height: int):
        """The fixed-point threshold at each pixel: ``theta_q`` itself (an int) unless it is
        a tile array (``'local'``), which is spread over its tiles' pixels, (height, width)."""
        if np.ndim(theta_q) == 0:
            return int(theta_q)
        t = self.threshold_tile
        return np.repeat(np.repeat(np.asarray(theta_q, np.int64), t, axis=0), t, axis=1)[: int(height), : int(width)]

    @staticmethod
    def contrast_samples(width: int, height: int) -> int:
        """Pixels the textured and contrast statistics sample (even interior rows)."""
        return ((height - 2) // 2) * max(0, width - 2)

    @property
    def history_frames(self) -> int:
        """Frames needed before the slowest channel can fire (3 for the paper's model)."""
        return 3 * self.max_delay

    def calibration_settings(self) -> dict:
        """The settings besides the channels that shape which scales fire at a given speed,
        and so the summary's calibration tables: the prefilter, the templates, brightness
        compensation, the threshold mode and that mode's own settings (the fixed
        ``threshold``; the adaptive one's gain and bounds; the local one's also its tile).
        A table measured with other values still reads the detections, less accurately:
        :func:`emdflow.summary.calibration_mismatch` names the ones that differ. Plain
        Python values, keyed by field name."""
        settings = {"prefilter_size": self.prefilter_size, "sharp_templates": self.sharp_templates,
                    "brightness_compensation": self.brightness_compensation,
                    "threshold_mode": self.threshold_mode}
        if self.threshold_mode == "fixed":
            settings["threshold"] = self.threshold
        else:  # (the fixed threshold serves only a first frame without contrast samples)
            settings.update(adaptive_gain=self.adaptive_gain, threshold_min=self.threshold_min,
                            threshold_max=self.threshold_max)
        if self.threshold_mode == "local":
            settings["threshold_tile"] = self.threshold_tile
        return settings

    def evidence_row_step_for(self, height: int) -> int:
        """Rows between the rows whose detections feed the summary histogram.

        ``evidence_row_step`` when set; automatic (0): about 60 sampled rows whatever the
        frame height (every 4th row at 240 px, every 8th at 480 px, every 2nd below
        180 px) — a few thousand detections per frame, whose binning (a gradient and its
        orientation per detection) already takes about a quarter of the engine's time at
        320×240 and a sixth at 640×480.
        """
        if self.evidence_row_step:
            return self.evidence_row_step
        return max(2, int(height) // 60)

    @staticmethod
    def evidence_column_step(width: int) -> int:
        """Columns between the columns whose detections feed the summary histogram.

        1 up to 639 px wide, 2 from 640, 4 from 1280, …: at most ~320–640 sampled columns
        of ~60 sampled rows, so the summary sees about as many detections at 640×480 as at
        320×240 (where its likelihood was calibrated) and the evidence costs the same. At
        most 32 (from 10 240 px wide): the OpenCL kernel samples the columns of each 32-pixel
        word by a mask.
        """
        return min(32, 1 << max(0, (int(width) // 320).bit_length() - 1))

    @staticmethod
    def orientation_table() -> np.ndarray:
        """Boundary directions of the orientation bins as int64 ``(cos, sin)`` × 2**14.

        Row ``b`` is the direction ``(b + 1) · 180° / ORIENTATION_BINS``; a gradient folded
        into the upper half-plane lies in bin ``#{b : cos_b·gy − sin_b·gx >= 0}``.
        """
        b = np.arange(1, ORIENTATION_BINS)
        ang = b * math.pi / ORIENTATION_BINS
        return np.stack(
            [np.rint(np.cos(ang) * _ORIENT_ONE), np.rint(np.sin(ang) * _ORIENT_ONE)], axis=1
        ).astype(np.int64)

    @staticmethod
    def orientation_centres() -> np.ndarray:
        """Centre angle of each orientation bin, radians in [0, π)."""
        return (np.arange(ORIENTATION_BINS) + 0.5) * math.pi / ORIENTATION_BINS

    @staticmethod
    def crossing_geometry(axes) -> tuple[np.ndarray, np.ndarray]:
        """Per (histogram axis of ``axes``, orientation bin): the bin-centre normal's signed
        component ``n_a`` along the axis's detector step (:data:`EVIDENCE_AXIS_STEPS`;
        ``c = n·F / n_a`` is then the crossing speed in steps per frame: px along an axis,
        (1, ±1) steps along a diagonal) and ψ, the angle between the normal and the step,
        in degrees. Shapes (len(axes), ORIENTATION_BINS)."""
        phi = EngineParams.orientation_centres()
        steps = np.asarray([EVIDENCE_AXIS_STEPS[a] for a in axes], np.float64)
        n_axis = steps[:, :1] * np.cos(phi) + steps[:, 1:] * np.sin(phi)
        length = np.hypot(steps[:, 0], steps[:, 1])[:, None]
        return n_axis, np.degrees(np.arccos(np.clip(np.abs(n_axis) / length, 0.0, 1.0)))
