"""Bee-style navigation cues from the same detections: expansion, time to contact, balance.

Honeybees land by holding the image expansion rate constant and fly down corridors by
balancing the image speed seen on either side. Both cues come from the detection
*position* histogram the backends compute next to the summary evidence
(``FlowField.positions``: detections on the sampled rows, horizontal ones binned by ``x``
and vertical ones by ``y`` into 16 bins), so they cost the same at any frame size:

* **expansion rate** ``r`` (1/frame): the relative growth of the image scale per frame.
  The image flow is modelled as ``F(X, Y) = (U + r·X, V + r·Y)`` about the image centre
  (a zoom plus a translation). The detectors do not measure that flow linearly: their
  channel speeds are quantised, they report how fast an edge *crosses* their axis, they
  fire less often at low speeds, and across a position bin the flow along the other axis
  varies with the other coordinate (``V + r·Y`` for a bin of horizontal detections). A
  line fit of the mean channel speed against position therefore read 1.3–2× the true
  rate. The cue is instead a calibrated forward model fitted to the 2 × 16 bins:

  - two tables per detector model (channel set), over the local flow's component ``a``
    along the detector's axis and ``o`` across it: the **response** ``G(a, o)``, the mean
    score of a detection (its signed channel speed, clipped at ``SCORE_CLIP`` = 5
    px/frame so that a few aliased fast codes do not dominate), and the **rate**
    ``D(a, o)``, detections per textured pixel (relative). They are measured on zoom
    flights (approaching and receding, 40 % without translation) over photographs the
    evaluation never uses; ``python -m emdflow.tools.zoom_eval calibrate --write`` writes
    them to ``cues_calibration.npz`` next to this module. The orientation of the edges is not modelled: the
    tables average over the calibration photographs (modelling it per orientation bin,
    with the summary's or a dedicated table, measured no better);
  - a bin's predicted mean score is the ``D``-weighted mean of ``G`` over the flows in the
    bin (its centre along the axis, 4 samples across the image along the other);
  - ``(U, V, r)`` minimise the weighted squared difference between measured and predicted
    bin means (weight ``n ** 0.5 / variance`` for a bin of ``n`` detections: neighbouring
    detections are not independent). Start: the translation that best explains the bins
    with ``r = 0``, then the best of a grid of rates; then 4 Levenberg–Marquardt
    evaluations with a finite-difference Jacobian (the tables are piecewise linear and
    noisy at low speeds: more iterations measured no better). About 0.4 ms per call on
    the 2-core test host at 320×240 and 640×480 alike (``summarize``: 0.3 ms).

  Measured with ``python -m emdflow.tools.zoom_eval`` (320×240, noise σ = 2, six
  photographs × rates 0.002–0.02 per frame, 8 frames × 6 flights per cell; the README has
  the tables): median relative error 11.8 % for the extended model on pure zooms (the
  former line fit 34 %), 20.3 % (54.7 %) with a 2.2 px/frame translation; the paper's model
  39 % (96 %) and 27 % (50 %) — it sees nothing below ~0.5 px/frame, so a zoom of
  0.2 %/frame (0.3 px/frame at the frame's edge) gives no cue and 0.5 %/frame reads
  0.5–0.75×. Brick reads 0.4–0.75×, as do random grids whose long straight edges lie along
the detector axes, drawn as thin lines or as step edges (the same grids turned by 30°
read 0.89–1.11×; README, under "The summary"). A channel
  set without a table falls back to the line fit. The divergence of the flow is ``2r``;
* **time to contact** ``1/r`` frames (``1/(r·fps)`` seconds) when approaching (``r > 0``);
* **balance** left/right and top/bottom, ``(S_b − S_a) / (S_b + S_a)`` of the mean image
  speed ``S`` in each half: positive when the right (bottom) half moves faster, i.e. is
  nearer.

Thin evidence — no axis with ``min_detections`` detections in at least 4 of its 16
position bins, or a fit that fails or lands beyond 0.1/frame — gives the no-cue value:
rate 0, time to contact ``inf``, ``detections`` 0 (a static scene has no detections).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from .field import FlowField
from .params import _is_whole
from .reference import POSITION_BINS

__all__ = ["LoomingCues", "looming_cues"]


@dataclasses.dataclass(frozen=True)
class LoomingCues:
    """Expansion and balance cues of one frame.

    Attributes
    ----------
    expansion_rate : float
        Relative image-scale growth per frame (1/frame); > 0 approaching, < 0 receding.
    time_to_contact_frames : float
        ``1 / expansion_rate`` when approaching, ``inf`` otherwise.
    balance_lr, balance_tb : float
        Image-speed balance right vs left and bottom vs top, −1..1 (0 = balanced); NaN for
        an axis without enough detections of its own when the other axis has them.
    detections : int
        Detections the cues were computed from (0 = no cue: all values 0 / inf).
    """

    expansion_rate: float = 0.0
    time_to_contact_frames: float = math.inf
    balance_lr: float = 0.0
    balance_tb: float = 0.0
    detections: int = 0

    def time_to_contact_s(self, fps: float) -> float:
        """Time to contact in seconds at ``fps`` frames per second."""
        return self.time_to_contact_frames / fps if fps > 0 else math.inf


# ---------------------------------------------------------------------------------------
# Calibration: response and rate tables per channel set
# ---------------------------------------------------------------------------------------
#: Nodes of the tables: |flow component along the detector's axis| and |across it|, px/frame.
AXIAL_NODES = (0.0, 0.03, 0.06, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7, 0.85, 1.0,
               1.2, 1.4, 1.6, 1.8, 2.0, 2.25, 2.5, 2.75, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0, 7.0, 8.0)
CROSS_NODES = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
#: Detection score: the signed channel speed, clipped at this many px/frame.
SCORE_CLIP = 5.0


def _signed_speeds(params) -> np.ndarray:
    """Signed channel speed of every code (2c: +, 2c + 1: −)."""
    speeds = np.asarray(params.speeds, np.float64)
    return np.repeat(speeds, 2) * np.tile([1.0, -1.0], len(speeds))


def _centres(size: int, bins: int) -> np.ndarray:
    """Centres of ``bins`` equal bins over ``size`` px, relative to the middle."""
    return (np.arange(bins) + 0.5) * size / bins - size / 2.0


class _Table:
    """One channel set's tables, resampled (bilinearly) on a fine uniform grid for
    nearest-node lookups, with the score of every code."""

    #: Fine grid steps along |axial| and |cross| flow, px/frame.
    A_SCALE = 64.0
    O_SCALE = 16.0

    def __init__(self, entry: dict, params):
        g = np.asarray(entry["response"], np.float64)
        d = np.maximum(np.asarray(entry["rate"], np.float64), 1e-6)
        g[0, :] = 0.0  # the response is odd in the axial flow
        an, on = np.asarray(AXIAL_NODES), np.asarray(CROSS_NODES)
        a = np.arange(int(an[-1] * self.A_SCALE) + 1) / self.A_SCALE
        o = np.arange(int(on[-1] * self.O_SCALE) + 1) / self.O_SCALE
        self.n_a, self.n_o = a.size, o.size
        i = np.minimum(np.searchsorted(an, a, side="right") - 1, an.size - 2)
        j = np.minimum(np.searchsorted(on, o, side="right") - 1, on.size - 2)
        fa = ((a - an[i]) / (an[i + 1] - an[i]))[:, None]
        fo = ((o - on[j]) / (on[j + 1] - on[j]))[None, :]
        ii, jj = i[:, None], j[None, :]

        def resample(t):
            lo = t[ii, jj] + fo * (t[ii, jj + 1] - t[ii, jj])
            hi = t[ii + 1, jj] + fo * (t[ii + 1, jj + 1] - t[ii + 1, jj])
            return (lo + fa * (hi - lo)).ravel()

        dd = resample(d).reshape(self.n_a, self.n_o)
        hh = resample(g).reshape(self.n_a, self.n_o) * dd  # the numerator of the D-weighted mean
        # over signed axial flow (row n_a − 1 is 0): H is odd, D even in it
        self.h = np.concatenate([-hh[:0:-1], hh]).ravel()
        self.d = np.concatenate([dd[:0:-1], dd]).ravel()
        self.a_offset = self.n_a - 1 + 0.5
        self.a_top = 2 * self.n_a - 2
        self.score = np.clip(_signed_speeds(params), -SCORE_CLIP, SCORE_CLIP)
        self.score2 = self.score ** 2


#: The tables of every calibrated detector model, written by
#: ``python -m emdflow.tools.zoom_eval calibrate --write``.
CALIBRATION_FILE = Path(__file__).with_name("cues_calibration.npz")
#: What each model's entry holds (arrays ``<model>.<field>`` in the file).
CALIBRATION_FIELDS = ("channels", "threshold_mode", "flights", "seed", "response", "rate")


def load_calibration(path=None) -> dict:
    """``{model: {"channels", "threshold_mode", "flights", "seed", "response", "rate"}}``
    from ``path`` (default :data:`CALIBRATION_FILE`); ``response`` and ``rate`` are indexed
    ``[|axial| node, |cross| node]`` (:data:`AXIAL_NODES`, :data:`CROSS_NODES`)."""
    out: dict = {}
    with np.load(CALIBRATION_FILE if path is None else path) as z:
        for key in z.files:
            model, _, name = key.partition(".")
            value = z[key]
            if name == "channels":
                value = tuple(tuple(int(x) for x in row) for row in value)
            elif name == "threshold_mode":
                value = str(value)
            elif name in ("flights", "seed"):
                value = int(value)
            out.setdefault(model, {})[name] = value
    return out


_TABLES: dict = {}
_CALIBRATION: dict = {}


def _table_for(params):
    """The calibrated tables of ``params``' channel set, or None."""
    key = tuple(params.channels)
    if key not in _TABLES:
        if "models" not in _CALIBRATION:
            _CALIBRATION["models"] = load_calibration() if CALIBRATION_FILE.is_file() else {}
        entry = next((e for e in _CALIBRATION["models"].values() if e["channels"] == key), None)
        _TABLES[key] = None if entry is None else _Table(entry, params)
    return _TABLES[key]


def _lookup(table: _Table, a: np.ndarray, o: np.ndarray):
    """``H`` (odd in ``a``) and ``D`` at the fine-grid node nearest to ``a``, ``|o|``
    (clamped to the table)."""
    i = np.clip(a * table.A_SCALE + table.a_offset, 0.0, table.a_top).astype(np.intp)
    j = np.minimum(np.abs(o) * table.O_SCALE + 0.5, table.n_o - 1).astype(np.intp)
    k = i * table.n_o + j
    return table.h[k], table.d[k]


class _Geometry:
    """Bin centres along each used axis and samples of the other coordinate, relative to
    the image centre, shaped (axes, bins, 1) and (axes, 1, samples)."""

    SAMPLES = 4

    def __init__(self, width: int, height: int, bins: int, axes):
        m = self.SAMPLES
        along = (_centres(width, bins), _centres(height, bins))
        across = (_centres(height, m), _centres(width, m))
        self.x = np.stack([along[a] for a in axes])[:, :, None]
        self.y = np.stack([across[a] for a in axes])[:, None, :]
        # the parameter (U = 0, V = 1) that is the in-axis / cross translation of each axis
        self.inaxis = np.array([0 if a == 0 else 1 for a in axes])
        self.cross = 1 - self.inaxis


def _predict(table: _Table, geo: _Geometry, p: np.ndarray) -> np.ndarray:
    """Predicted mean score of every position bin for the parameter rows ``p``
    (candidates × [U, V, r]): shape (candidates, axes, bins)."""
    r = p[:, 2, None, None, None]
    fa = p[:, geo.inaxis, None, None] + r * geo.x  # (C, A, bins, 1)
    fo = p[:, geo.cross, None, None] + r * geo.y  # (C, A, 1, samples)
    h, d = _lookup(table, fa, fo)  # (C, A, bins, samples)
    return h.sum(axis=3) / d.sum(axis=3)


_GEOMETRY: dict = {}


def _symmetric(values) -> np.ndarray:
    """0, then ± each value by growing size (so that ties go to the smaller one)."""
    values = np.asarray(values, np.float64)
    return np.concatenate([[0.0], np.column_stack([values, -values]).ravel()])


#: Translations (px/frame) and rates (1/frame) of the starting grids.
_START_SHIFTS = _symmetric(np.geomspace(0.1, 8.0, 9))
_START_RATES = _symmetric(np.geomspace(0.001, 0.04, 5))
#: Levenberg–Marquardt: model evaluations, the starting damping, and the finite
#: differences of the Jacobian (px/frame for U, V; relative for r, with a floor in
#: 1/frame). The model is piecewise linear and, at low speeds, noisy: beyond a few steps
#: from the grid's start the fit measured no better.
_EVALUATIONS = 4
_DAMPING = 1e-2
_DELTA_SHIFT = 0.05
_DELTA_RATE = (0.03, 2e-4)
#: A position bin of n detections weighs like n ** _WEIGHT_EXPONENT independent ones.
_WEIGHT_EXPONENT = 0.5
#: Fitted rates beyond this (1/frame: contact within 10 frames) are no cue.
_MAX_RATE = 0.1


def _solve3(A, g, lam: float):
    """``(A + lam·diag(A)) x = g`` for a 3 × 3 ``A`` (nested lists), by Cramer's rule;
    None when singular."""
    (a, b, c), (d, e, f), (h, i, j) = A
    a, e, j = a * (1.0 + lam) + 1e-12, e * (1.0 + lam) + 1e-12, j * (1.0 + lam) + 1e-12
    co0, co1, co2 = e * j - f * i, f * h - d * j, d * i - e * h
    det = a * co0 + b * co1 + c * co2
    if not det or not math.isfinite(det):
        return None
    x, y, z = g
    return np.array([
        (x * co0 + b * (f * z - y * j) + c * (y * i - e * z)) / det,
        (a * (y * j - f * z) + x * co1 + c * (d * z - y * h)) / det,
        (a * (e * z - y * i) + b * (y * h - d * z) + x * co2) / det,
    ])


def _fit_rate(table: _Table, field: FlowField, pos: np.ndarray, counts: np.ndarray,
              axes) -> float | None:
    """Expansion rate fitted to the position bins of ``axes`` (see the module docstring)."""
    if len(axes) < 2:
        pos, counts = pos[list(axes)], counts[list(axes)]
    n = counts
    safe = np.maximum(n, 1.0)
    mean = (table.score @ pos) / safe
    var = np.maximum((table.score2 @ pos) / safe - mean * mean, 1e-2)
    pooled = (var * n).sum(axis=1, keepdims=True) / np.maximum(n.sum(axis=1, keepdims=True), 1.0)
    w = np.where(n >= _MIN_BIN, n ** _WEIGHT_EXPONENT, 0.0) / pooled
    h, wd = field.shape
    key = (wd, h, n.shape[1], tuple(axes))
    geo = _GEOMETRY.get(key)
    if geo is None:
        geo = _GEOMETRY[key] = _Geometry(wd, h, n.shape[1], axes)

    # start: the translation for r = 0 (every bin of an axis then sees the same flow: one
    # lookup per axis and candidate), then the best rate of a grid
    u = _START_SHIFTS[:, None]
    v = _START_SHIFTS[None, :]
    c = 0.0
    for row, a in enumerate(axes):
        fa, fo = (u, v) if a == 0 else (v, u)
        hs, ds = _lookup(table, fa, fo)
        flat = hs / ds  # (U, V) candidates
        wa = w[row]
        c = c + (wa @ mean[row] ** 2) - 2.0 * (wa @ mean[row]) * flat + wa.sum() * flat * flat
    iu, iv = np.unravel_index(int(np.argmin(c)), c.shape)
    grid = np.zeros((_START_RATES.size, 3))
    grid[:, 0] = _START_SHIFTS[iu]
    grid[:, 1] = _START_SHIFTS[iv]
    grid[:, 2] = _START_RATES
    c = (w * (mean - _predict(table, geo, grid)) ** 2).sum(axis=(1, 2))
    p = grid[int(np.argmin(c))]

    # Levenberg–Marquardt with a finite-difference Jacobian: each model evaluation is the
    # trial point and its three perturbations
    m = mean.ravel()
    wr = w.ravel()
    best = math.inf
    lam = _DAMPING
    trial = p
    A = g = None
    for it in range(_EVALUATIONS):
        dr = max(_DELTA_RATE[0] * abs(trial[2]), _DELTA_RATE[1])
        cand = np.repeat(trial[None], 4, axis=0)
        cand[1, 0] += _DELTA_SHIFT
        cand[2, 1] += _DELTA_SHIFT
        cand[3, 2] += dr
        pred = _predict(table, geo, cand).reshape(4, -1)
        res = m - pred[0]
        cost = float(wr @ (res * res))
        if cost <= best:
            p, best = trial, cost
            J = (pred[1:] - pred[0]) / np.array([[_DELTA_SHIFT], [_DELTA_SHIFT], [dr]])  # (3, n)
            Jw = J * wr
            A = (Jw @ J.T).tolist()
            g = (Jw @ res).tolist()
            lam = max(lam / 3.0, 1e-6)
        else:
            lam *= 5.0
        if A is None:
            return None  # not even the start could be evaluated
        if it == _EVALUATIONS - 1:
            break
        step = _solve3(A, g, lam)
        if step is None:
            break
        trial = p + step
    rate = float(p[2])
    return rate if math.isfinite(rate) and abs(rate) <= _MAX_RATE else None


# ---------------------------------------------------------------------------------------
# Uncalibrated channel sets: line fit of the mean signed channel speed; and the balance
# ---------------------------------------------------------------------------------------
def _slope_rate(pos: np.ndarray, counts: np.ndarray, signed: np.ndarray, shape, axes) -> float:
    """Detection-weighted mean over ``axes`` of the weighted line fits of the mean signed
    channel speed against position (the uncalibrated expansion rate)."""
    h, w = shape
    slopes, weights = [], []
    for a in axes:
        x = _centres(w if a == 0 else h, counts.shape[1])
        n = counts[a]
        dx = x - (n @ x) / n.sum()
        slopes.append(float((dx @ (signed @ pos[a])) / max(n @ (dx * dx), 1e-12)))
        weights.append(n.sum())
    return float(np.average(slopes, weights=weights))


def _balance(pos: np.ndarray, counts: np.ndarray, signed: np.ndarray) -> np.ndarray:
    """Per axis ``(S_b − S_a) / (S_b + S_a)`` of the mean |channel speed| in the first (a)
    and second (b) half of the bins."""
    speed = np.abs(signed) @ pos  # (axis, bin)
    half = counts.shape[1] // 2
    n = np.stack([counts[:, :half].sum(axis=1), counts[:, half:].sum(axis=1)], axis=1)
    s = np.stack([speed[:, :half].sum(axis=1), speed[:, half:].sum(axis=1)], axis=1)
    s = np.where(n > 0, s / np.maximum(n, 1.0), 0.0)
    total = s.sum(axis=1)
    return np.where(total > 0, (s[:, 1] - s[:, 0]) / np.maximum(total, 1e-12), 0.0)


#: Position bins with at least this many detections count as evidence ...
_MIN_BIN = 5
#: ... and an axis needs this many such bins.
_MIN_BINS = 4


def _check_call(field, min_detections, caller: str) -> None:
    """The argument checks :func:`looming_cues` and :func:`slope_expansion_rate` share: a
    hand-made field's position histogram must have the engine's shape (one of another
    shape gave a cue from the wrong bins), and ``min_detections`` a whole number ≥ 0; anything
    but a :class:`FlowField` is a TypeError (as for summarize(): not an AttributeError from
    inside)."""
    if not isinstance(field, FlowField):
        raise TypeError(f"{caller} takes a FlowField, not {type(field).__name__}")
    if not _is_whole(min_detections) or min_detections < 0:
        raise ValueError(f"{caller}: min_detections={min_detections!r}: expected a whole number >= 0")
    field.require_evidence(caller)
    if field.positions is not None:
        expected = (2, 2 * len(field.params.channels), POSITION_BINS)
        if np.shape(field.positions) != expected:
            raise ValueError(f"{caller}: the field's position histogram has shape {np.shape(field.positions)}, "
                             f"its parameters' channels need {expected} (axis, code, position bin)")


def looming_cues(field: FlowField, *, min_detections: int = 50) -> LoomingCues:
    """Expansion rate, time to contact and balance of a :class:`FlowField`.

    Parameters
    ----------
    field : FlowField
        Detector output with its position histogram (both backends provide it).
    min_detections : int
        Fewer detections on an axis than this give no cue for that axis.

    Returns
    -------
    LoomingCues
        All zero / inf when the history is not full, a brightness step is in the templates
        (:attr:`FlowField.exposure_step`) or evidence is too thin (no axis with
        ``min_detections`` detections in at least 4 of the 16 position bins).

    Raises
    ------
    ValueError
        If the field has no summary evidence (``FlowEstimator(..., summary_evidence=False)``),
        its position histogram is not the engine's shape, or ``min_detections`` is not a
        whole number ≥ 0.
    TypeError
        If ``field`` is not a :class:`FlowField`.
    """
    _check_call(field, min_detections, "looming_cues()")
    # (a brightness step in the templates: their detections are not motion, as for summarize())
    if not field.ready or field.exposure_step or field.positions is None:
        return LoomingCues()
    pos = field.positions.astype(np.float64)  # (axis, code, bin)
    counts = pos.sum(axis=1)  # (axis, bin)
    totals = counts.sum(axis=1)
    usable = (totals >= min_detections) & ((counts >= _MIN_BIN).sum(axis=1) >= _MIN_BINS)
    if not usable.any():
        return LoomingCues()
    axes = tuple(int(a) for a in np.flatnonzero(usable))
    table = _table_for(field.params)
    signed = _signed_speeds(field.params)
    if table is not None:
        rate = _fit_rate(table, field, pos, counts, axes)
        if rate is None:
            return LoomingCues()
    else:
        rate = _slope_rate(pos, counts, signed, field.shape, axes)
        if not (math.isfinite(rate) and abs(rate) <= _MAX_RATE):
            return LoomingCues()  # (the calibrated fit's limit holds for the line fit too)
    # (an axis without enough detections has no balance: NaN, not 0, which reads "balanced")
    balance = np.where(usable, _balance(pos, counts, signed), math.nan)
    return LoomingCues(
        expansion_rate=rate,
        time_to_contact_frames=1.0 / rate if rate > 1e-6 else math.inf,
        balance_lr=float(balance[0]),
        balance_tb=float(balance[1]),
        detections=int(totals[list(axes)].sum()),
    )


def slope_expansion_rate(field: FlowField, *, min_detections: int = 50) -> float | None:
    """The uncalibrated expansion rate: the line fit of the mean signed channel speed
    against position (what :func:`looming_cues` falls back to for a channel set without a
    table; kept for comparison, e.g. by ``emdflow.tools.zoom_eval``). None when no axis
    has ``min_detections`` detections in at least 3 position bins; ValueError for a field
    without summary evidence, TypeError for anything but a :class:`FlowField`."""
    _check_call(field, min_detections, "slope_expansion_rate()")
    if not field.ready or field.positions is None:
        return None
    pos = field.positions.astype(np.float64)
    counts = pos.sum(axis=1)
    usable = (counts.sum(axis=1) >= min_detections) & (np.count_nonzero(counts, axis=1) >= 3)
    if not usable.any():
        return None
    return _slope_rate(pos, counts, _signed_speeds(field.params), field.shape,
                       tuple(int(a) for a in np.flatnonzero(usable)))
