"""Numpy reference of the Elementary Velocity Detector — the executable specification.

This module implements ``docs/spec/template-model.md`` (a precise reading of Quelin, Bouzerdoum
& Phung, "Fast digital optical flow estimation based on EMD", EUVIP 2010) in plain,
vectorised numpy. The OpenCL backend must reproduce it exactly: same ternary states, same
template matches, same flow codes, same summary statistics. It favours readability over
speed, but has no per-pixel Python loops.

Pipeline for one frame (paper section in brackets):

1. :func:`prefilter` — integer Gaussian ``w × w`` window, ``sigma = w/6`` [§4];
2. :func:`receptor_change` — change of the ``k × k`` receptor box sums between frames
   ``D`` apart (high-pass = frame difference) [§2, §3.2];
3. :func:`ternary_states` — threshold into −1 / 0 / +1 [§2];
4. :func:`velocity_templates` — two motion templates linked in space and time
   (``A→B`` at ``t−D`` and ``B→C`` at ``t``) in the four directions [§3.1, Table 1];
5. :func:`fuse_channels` — highest velocity wins, opposite directions at the same speed
   are ambiguous [§3.2];
6. :func:`summary_statistics` — the per-frame evidence the summary is computed from
   (detections binned by axis, speed and gradient orientation; texture; saturation).

Borders: the prefilter clamps reads to the frame (replicated edge); a receptor exists only
where its whole ``k × k`` block lies inside the frame (elsewhere its state is 0), so a
detector fires only where ``A``, ``B`` and ``C`` all have full blocks inside the frame.
"""

from __future__ import annotations

import numpy as np

from .params import EVIDENCE_AXIS_STEPS, ORIENTATION_BINS, EngineParams

__all__ = [
    "DIRECTIONS",
    "prefilter",
    "box_sums",
    "receptor_change",
    "ternary_states",
    "velocity_templates",
    "fuse_channels",
    "summary_statistics",
    "ReferenceEngine",
    "STAT_U_DETECTIONS",
    "STAT_V_DETECTIONS",
    "STAT_TEXTURED",
    "STAT_SATURATED",
    "STAT_BRIGHTENING",
    "STAT_CONTRAST",
    "STAT_STEP_CHANGED",
    "STAT_FIRST_CHANGED",
    "POSITION_BINS",
]

#: Detector directions as unit steps (dx, dy) in image coordinates (y down).
DIRECTIONS = {"E": (1, 0), "W": (-1, 0), "S": (0, 1), "N": (0, -1),
              # the diagonals of the summary's evidence (EngineParams.diagonal_evidence)
              "SE": (1, 1), "NW": (-1, -1), "NE": (1, -1), "SW": (-1, 1)}
#: The evidence histogram's axes: (positive, negative) direction of each (x right, y down).
EVIDENCE_AXES = (("E", "W"), ("S", "N"), ("SE", "NW"), ("NE", "SW"))

# Layout of the per-frame statistics vector (int64) shared with the OpenCL backend.
STAT_U_DETECTIONS = 0  #: pixels with a horizontal detection
STAT_V_DETECTIONS = 1  #: pixels with a vertical detection
STAT_TEXTURED = 2  #: sampled pixels with gradient above the threshold (see summary_statistics)
STAT_SATURATED = 3  #: sampled pixels at 0..2 or 253..255
#: positive states of the finest one-frame channel, without brightness compensation
#: (the exposure-step test)
STAT_BRIGHTENING = 4
STAT_CONTRAST = 5  #: sum of |ΔxP| + |ΔyP| over the textured statistic's sample
#: nonzero states of the finest one-frame channel without brightness compensation (the
#: exposure-step test: a step's mean is taken out of the compensated states)
STAT_STEP_CHANGED = 6
STAT_FIRST_CHANGED = 7  #: then one count of nonzero states per channel
#: Detections are also counted by position: x (horizontal) or y (vertical) in this many bins.
POSITION_BINS = 16


def prefilter(frame: np.ndarray, weights: tuple[int, ...]) -> np.ndarray:
    """Integer Gaussian prefilter (paper §4), in gray levels.

    Separable: a horizontal then a vertical pass with integer weights summing to 256, reads
    clamped to the frame, each pass rounded to whole gray levels, ``(s + 128) >> 8``. The
    result is again an 8-bit image, so a ``k × k`` box sum stays below 2**16 for every
    scale up to 15 px and the OpenCL kernels can work on 16 pixels per 256-bit vector.

    Parameters
    ----------
    frame : ndarray of uint8, shape (H, W)
    weights : tuple of int
        Odd-length 1-D table summing to 256 (see :func:`emdflow.params.gaussian_weights`).

    Returns
    -------
    ndarray of int32, shape (H, W)
        Prefiltered image ``P`` (0..255).
    """
    w = np.asarray(weights, dtype=np.int32)
    r = len(w) // 2
    img = frame.astype(np.int32)
    if r == 0:
        return img  # weights (256,): each pass is the identity after rounding
    H, W = img.shape
    xs = np.clip(np.arange(W)[None, :] + np.arange(-r, r + 1)[:, None], 0, W - 1)
    horiz = np.zeros((H, W), np.int32)
    for i in range(len(w)):
        horiz += int(w[i]) * img[:, xs[i]]
    horiz = (horiz + 128) >> 8
    ys = np.clip(np.arange(H)[None, :] + np.arange(-r, r + 1)[:, None], 0, H - 1)
    vert = np.zeros((H, W), np.int32)
    for i in range(len(w)):
        vert += int(w[i]) * horiz[ys[i], :]
    return (vert + 128) >> 8


def box_sums(image: np.ndarray, k: int) -> np.ndarray:
    """Sum of ``image`` over the ``k × k`` block centred on each pixel (receptor value).

    Where the block does not lie wholly inside the frame the result is 0 (no receptor).
    Returns int64 of the same shape.
    """
    r = k // 2
    H, W = image.shape
    out = np.zeros((H, W), np.int64)
    if H < k or W < k:
        return out
    sat = np.zeros((H + 1, W + 1), np.int64)
    sat[1:, 1:] = image.astype(np.int64).cumsum(0).cumsum(1)
    out[r : H - r, r : W - r] = (
        sat[k:, k:] - sat[:-k, k:] - sat[k:, :-k] + sat[:-k, :-k]
    )
    return out


def receptor_change(p_now: np.ndarray, p_before: np.ndarray, k: int) -> np.ndarray:
    """Change of the scale-``k`` receptors, ``R_k(t) − R_k(t−D)`` as box sums (paper §2).

    The intensity-change detector is a frame difference; since a box sum is linear this is
    the box sum of the difference of the prefiltered frames.
    """
    return box_sums(p_now.astype(np.int64) - p_before, k)


def gain_compensated_change(p_now: np.ndarray, p_before: np.ndarray, k: int, ratio_q: int) -> np.ndarray:
    """``256 · R_k(t) − ratio_q · R_k(t−D)``: the receptor change with the exposure gain
    ``ratio_q / 256`` between the two frames taken out (brightness compensation), as box
    sums of ``256 · P(t) − ratio_q · P(t−D)`` (exact integers; 0 where there is no receptor).
    """
    return box_sums(p_now.astype(np.int64) * 256 - p_before.astype(np.int64) * int(ratio_q), k)


def ternary_states(change: np.ndarray, box_threshold) -> np.ndarray:
    """Ternary template-model states (paper §2): +1 if ``change > T``, −1 if ``< −T``, else 0.

    ``box_threshold`` (an int, or an array of the change's shape for the local threshold)
    is ``floor(θ̂ · k²)`` with ``θ̂`` the fixed-point θ (see
    :meth:`EngineParams.box_threshold`), so the test is exactly "mean receptor change > θ̂
    gray levels".
    """
    return ((change > box_threshold).astype(np.int8) - (change < -box_threshold).astype(np.int8))


def _shift(states: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """Value at ``x + (dx, dy)`` for every pixel ``x`` (0 outside the frame)."""
    H, W = states.shape
    out = np.zeros_like(states)
    if abs(dx) >= W or abs(dy) >= H:
        return out
    ys = slice(max(0, -dy), H - max(0, dy))
    xs = slice(max(0, -dx), W - max(0, dx))
    ys_src = slice(max(0, dy), H + min(0, dy))
    xs_src = slice(max(0, dx), W + min(0, dx))
    out[ys, xs] = states[ys_src, xs_src]
    return out


def _rows_at(states: np.ndarray, rows: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """Value at ``(x + dx, y + dy)`` for every pixel ``x`` of the rows ``rows`` (0 outside
    the frame): :func:`_shift` on those rows only."""
    H, W = states.shape
    out = np.zeros((rows.size, W), states.dtype)
    ys = rows + dy
    inside = (ys >= 0) & (ys < H)
    if abs(dx) < W:
        xs = slice(max(0, -dx), W - max(0, dx))
        xs_src = slice(max(0, dx), W + min(0, dx))
        out[inside, xs] = states[ys[inside], xs_src]
    return out


def _motion_templates(a_prev, b_prev, a_now, b_now, sharp: bool):
    """The directional 2×2 templates for ``a → b`` (spec §2), per polarity and type.

    Returns a list of boolean arrays, one per (polarity, type) in a fixed order, so the
    velocity template can require the *same* (polarity, type) at both links.
    """
    out = []
    for p in (1, -1):
        ap, bp, an, bn = a_prev == p, b_prev == p, a_now == p, b_now == p
        a0n, b0p = a_now == 0, b_prev == 0
        out.append(ap & b0p & an & bn)  # start: [p 0 / p p]
        out.append(ap & bp & a0n & bn)  # end:   [p p / 0 p]
        if sharp:
            out.append(ap & b0p & a0n & bn)  # sharp: [p 0 / 0 p]
    return out


def velocity_templates(
    s_old: np.ndarray, s_mid: np.ndarray, s_new: np.ndarray, k: int, direction: str,
    *, sharp: bool = False, rows: np.ndarray | None = None,
) -> np.ndarray:
    """Elementary Velocity Detector output for one scale and direction (paper §3.1).

    With ``A = x``, ``B = x + k·δ``, ``C = x + 2k·δ``: the motion template ``A→B`` on
    states (``s_old``, ``s_mid``) and the same template ``B→C`` on (``s_mid``, ``s_new``).

    Parameters
    ----------
    s_old, s_mid, s_new : ndarray of int8
        Ternary states at ``t−2D``, ``t−D`` and ``t``.
    k : int
        Receptor spacing in pixels (the scale).
    direction : {'E', 'W', 'S', 'N', 'SE', 'NW', 'NE', 'SW'}
        ``B − A`` is ``k`` times the direction's step (x right, y down); the diagonals
        feed only the summary's evidence (``EngineParams.diagonal_evidence``).
    sharp : bool
        Also accept the sharp template.
    rows : ndarray of int, optional
        Only these rows of ``A`` (the result then has one row per entry); default all.

    Returns
    -------
    ndarray of bool
        True where the detector linked to ``A`` fires.
    """
    dx, dy = DIRECTIONS[direction]
    if rows is None:
        b_old, b_mid, b_new = (_shift(s, k * dx, k * dy) for s in (s_old, s_mid, s_new))
        c_mid, c_new = (_shift(s, 2 * k * dx, 2 * k * dy) for s in (s_mid, s_new))
    else:
        b_old, b_mid, b_new = (_rows_at(s, rows, k * dx, k * dy) for s in (s_old, s_mid, s_new))
        c_mid, c_new = (_rows_at(s, rows, 2 * k * dx, 2 * k * dy) for s in (s_mid, s_new))
        s_old, s_mid = s_old[rows], s_mid[rows]
    first = _motion_templates(s_old, b_old, s_mid, b_mid, sharp)  # A→B at t−D
    second = _motion_templates(b_mid, c_mid, b_new, c_new, sharp)  # B→C at t
    fired = np.zeros(s_old.shape, bool)
    for m1, m2 in zip(first, second):
        fired |= m1 & m2
    return fired


def fuse_channels(pos: list[np.ndarray], neg: list[np.ndarray]) -> np.ndarray:
    """Fuse one axis over channels: the fastest channel that fires wins (paper §3.2).

    Parameters
    ----------
    pos, neg : list of bool arrays
        Per channel (in increasing speed), detections in the positive (E or S) and the
        negative (W or N) direction.

    Returns
    -------
    ndarray of int8
        Flow code: ``+(c+1)`` / ``−(c+1)`` for channel ``c`` in the positive / negative
        direction, 0 where nothing fired or both directions fired at the winning channel
        (ambiguous).
    """
    code = np.zeros(pos[0].shape, np.int8)
    decided = np.zeros(pos[0].shape, bool)
    for c in range(len(pos) - 1, -1, -1):
        p = pos[c] & ~decided
        n = neg[c] & ~decided
        code[p & ~n] = c + 1
        code[n & ~p] = -(c + 1)
        decided |= pos[c] | neg[c]
    return code


def orientation_bins(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Orientation bin (0..ORIENTATION_BINS−1, over 180°) of integer gradients.

    The gradient is folded into the upper half-plane (the constraint of a detection does
    not depend on the gradient's sign), then counted against the integer boundary table
    of :meth:`EngineParams.orientation_table` — exact, so both backends agree.
    """
    gx = gx.astype(np.int64)
    gy = gy.astype(np.int64)
    flip = (gy < 0) | ((gy == 0) & (gx < 0))
    gx = np.where(flip, -gx, gx)
    gy = np.where(flip, -gy, gy)
    table = EngineParams.orientation_table()
    cross = table[None, :, 0] * gy[:, None] - table[None, :, 1] * gx[:, None]
    return (cross >= 0).sum(axis=1)


def summary_statistics(
    params: EngineParams,
    frame: np.ndarray,
    p_now: np.ndarray,
    u_code: np.ndarray,
    v_code: np.ndarray,
    receptors_mid: dict[int, np.ndarray],
    states_now: list[np.ndarray],
    theta_q: "int | np.ndarray | None" = None,
    step_states: np.ndarray | None = None,
    gains_q: dict | None = None,
    diagonal_codes: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple:
    """Per-frame evidence for the summary (identical in both backends).

    * counts of horizontal / vertical detections;
    * textured pixels: on even rows, interior pixels where
      ``|P(x+1)−P(x−1)| + |P(y+1)−P(y−1)| > floor(2θ)`` — a 1 px/frame motion there
      would change a scale-1 receptor by more than θ; and the sum of that quantity over
      the same pixels (the contrast statistic of the adaptive threshold);
    * saturated pixels: on even rows, raw value ≤ 2 or ≥ 253;
    * nonzero and positive states of the finest one-frame channel, without brightness
      compensation (``step_states``; a global brightness step turns most of them on at
      once, one way: the exposure-step test);
    * nonzero states per channel;
    * the detection histogram ``hist[axis, code, class · ORIENTATION_BINS + orientation]``
      (``class`` the gradient-strength class, see ``GRADIENT_CLASS_STEPS``): detections on every
      ``params.evidence_row_step_for(H)``-th row and
      ``EngineParams.evidence_column_step(W)``-th column,
      ``axis`` 0 = horizontal / 1 = vertical (2 = down-right and 3 = up-right diagonal
      with ``params.diagonal_evidence``, from ``diagonal_codes``), ``code = 2c + (1 if
      negative)``,
      ``orientation`` the bin of the gradient of the receptor image ``R_k`` at the middle
      receptor ``B`` at ``t−D`` (spec §6), reads clamped to the valid receptor range; the
      class compares that gradient, brought to the brightness of ``t`` by the channel's
      exposure gain ``gains_q[(k, D)] / 256`` (brightness compensation; 256 without), with
      the threshold of ``t``: ``2 · gain_q · |g|₁ >= m · 2θ_q k²``;
    * the position histogram ``positions[axis, code, bin]`` of the horizontal and vertical
      detections: ``bin``
      is ``x · POSITION_BINS // W`` for horizontal and ``y · POSITION_BINS // H`` for
      vertical detections (expansion and balance cues).

    Returns
    -------
    stats : ndarray of int64, shape (STAT_FIRST_CHANGED + n_channels,)
    hist : ndarray of int64, shape (params.evidence_axes, 2·n_channels, params.histogram_bins)
    positions : ndarray of int64, shape (2, 2·n_channels, POSITION_BINS)
        Both None without ``params.summary_evidence``.
    tile_contrast : ndarray of int64, shape ``params.threshold_tiles(W, H)``
        The contrast statistic's sum per tile of the local threshold (zero unless
        ``threshold_mode='local'``).

    ``theta_q`` is the threshold of the frame (an int) or, for ``'local'``, of each tile
    (an array): every use above takes the threshold at its pixel.
    """
    channels = params.channels
    H, W = frame.shape
    stats = np.zeros(STAT_FIRST_CHANGED + len(channels), np.int64)
    stats[STAT_U_DETECTIONS] = np.count_nonzero(u_code)
    stats[STAT_V_DETECTIONS] = np.count_nonzero(v_code)
    q = params.threshold_q(params.threshold) if theta_q is None else theta_q
    q = params.theta_map(q, W, H)  # (an int, or each pixel's tile's for 'local')
    ny, nx = params.threshold_tiles(W, H)
    tile_contrast = np.zeros((ny, nx), np.int64)
    if H >= 3 and W >= 3:
        p = p_now.astype(np.int64)
        gx = np.abs(p[1:-1, 2:] - p[1:-1, :-2])
        gy = np.abs(p[2:, 1:-1] - p[:-2, 1:-1])
        grad = (gx + gy)[1::2]  # rows 2, 4, …
        tex = params.texture_threshold_for(q)
        if np.ndim(tex):
            tex = tex[2:-1:2, 1:-1]
        stats[STAT_TEXTURED] = np.count_nonzero(grad > tex)
        stats[STAT_CONTRAST] = int(grad.sum())
        if params.threshold_mode == "local":
            t = params.threshold_tile
            rows = np.arange(2, H - 1, 2) // t
            cols = np.arange(1, W - 1) // t
            np.add.at(tile_contrast, (rows[:, None], cols[None, :]), grad)
    even = frame[0::2]
    stats[STAT_SATURATED] = np.count_nonzero((even <= 2) | (even >= 253))
    for c, s in enumerate(states_now):
        stats[STAT_FIRST_CHANGED + c] = np.count_nonzero(s)
    finest = channels.index((params.scales[0], 1))
    step = states_now[finest] if step_states is None else step_states
    stats[STAT_STEP_CHANGED] = np.count_nonzero(step)
    stats[STAT_BRIGHTENING] = np.count_nonzero(step > 0)
    if not params.summary_evidence:
        return stats, None, None, tile_contrast
    positions = np.zeros((2, 2 * len(channels), POSITION_BINS), np.int64)

    hist = np.zeros((params.evidence_axes, 2 * len(channels), params.histogram_bins), np.int64)
    channel_gain = np.array([(gains_q or {}).get(ch, 256) for ch in channels], np.int64)
    axis_codes = [u_code, v_code]
    if params.diagonal_evidence:
        axis_codes += list(diagonal_codes)
    for axis, code in enumerate(axis_codes):
        step = params.evidence_row_step_for(H)
        xstep = params.evidence_column_step(W)
        ys, xs = np.nonzero(code[0::step, 0::xstep])
        ys = ys * step
        xs = xs * xstep
        if ys.size == 0:
            continue
        cval = code[ys, xs].astype(np.int64)
        chan = np.abs(cval) - 1
        negative = cval < 0
        if axis < 2:
            where = xs * POSITION_BINS // W if axis == 0 else ys * POSITION_BINS // H
            np.add.at(positions[axis], (2 * chan + negative, where), 1)
        ks = np.array([channels[c][0] for c in range(len(channels))])[chan]
        ds = np.array([channels[c][1] for c in range(len(channels))])[chan]
        step = np.where(negative, -ks, ks)
        ex, ey = EVIDENCE_AXIS_STEPS[axis]  # B = A ± k (ex, ey)
        bx = xs + ex * step
        by = ys + ey * step
        gxs = np.zeros(ys.size, np.int64)
        gys = np.zeros(ys.size, np.int64)
        for key in np.unique(np.stack([ks, ds], 1), axis=0):
            k, d = int(key[0]), int(key[1])
            sel = (ks == k) & (ds == d)
            r = k // 2
            R = receptors_mid[(k, d)]
            x0, x1 = r, W - 1 - r
            y0, y1 = r, H - 1 - r
            cx, cy = bx[sel], by[sel]
            gxs[sel] = R[cy, np.clip(cx + 1, x0, x1)] - R[cy, np.clip(cx - 1, x0, x1)]
            gys[sel] = R[np.clip(cy + 1, y0, y1), cx] - R[np.clip(cy - 1, y0, y1), cx]
        keep = (gxs != 0) | (gys != 0)
        bins = orientation_bins(gxs[keep], gys[keep])
        # gradient-strength class: 2 gain_q |g|_1 >= m * 2 theta_q k^2 for each step m; the
        # gradient is of t - D and the threshold of t, so under an exposure drift the gain
        # between them is taken out (as the states do), or the classes would drift with it
        strength = 2 * channel_gain[chan[keep]] * (np.abs(gxs) + np.abs(gys))[keep]
        unit = 2 * (q[ys[keep], xs[keep]] if np.ndim(q) else q) * ks[keep] ** 2
        cls = np.zeros(strength.size, np.int64)
        for m in params.class_steps:
            cls += strength >= m * unit
        codes = 2 * chan[keep] + negative[keep]
        np.add.at(hist[axis], (codes, cls * ORIENTATION_BINS + bins), 1)
    return stats, hist, positions, tile_contrast


class ReferenceEngine:
    """Frame-by-frame numpy implementation of the detector (the executable specification).

    Keeps the prefiltered frames of the last ``max(delays)`` steps and the ternary states
    of the last ``2·D`` steps of each channel.

    Attributes after :meth:`step` (for tests and inspection)
    ---------------------------------------------------------
    states : list of int8 arrays, one per channel — states at ``t``
    matches : dict ``(channel, direction) -> bool array`` — raw detector outputs (E, W, S, N)
    """

    def __init__(self, width: int, height: int, params: EngineParams):
        self.width, self.height, self.params = int(width), int(height), params
        # pixels the contrast statistic samples, in the frame and per tile (made once)
        self._contrast_samples = params.contrast_samples(self.width, self.height)
        self._tile_samples = params.tile_contrast_samples(self.width, self.height)
        self.reset()

    def reset(self) -> None:
        self.theta_q = self.params.first_threshold_q(self.width, self.height)  # threshold of the next frame
        self._p_history: list[np.ndarray] = []  # newest last, up to max_delay + 1
        self._brightness: list[int] = []  # their pixel sums (brightness compensation)
        self._state_history = {ch: [] for ch in self.params.channels}  # newest last
        self.frame_count = 0
        self.states: list[np.ndarray] = []
        self.matches: dict = {}

    def step(self, frame: np.ndarray):
        """Process one frame; returns ``(u_code, v_code, stats, hist, positions)``."""
        prm = self.params
        p_now = prefilter(frame, prm.weights)
        self._p_history.append(p_now)
        del self._p_history[: -(prm.max_delay + 1)]
        # the prefiltered frame's pixel sum: the brightness the compensation follows
        self._brightness.append(int(p_now.sum(dtype=np.int64)) if prm.brightness_compensation else 0)
        del self._brightness[: -(prm.max_delay + 1)]
        zeros = np.zeros(frame.shape, np.int8)
        step_states = None  # the finest channel's uncompensated states (None: its own)
        n_axes = prm.evidence_axes if prm.summary_evidence else 2
        evidence_rows = np.arange(0, frame.shape[0], prm.evidence_row_step_for(frame.shape[0]))
        pos = {a: [] for a in range(n_axes)}
        neg = {a: [] for a in range(n_axes)}
        self.states = []
        self.matches = {}
        receptors_mid = {}
        gains_q = {}  # each channel's exposure gain over its delay, x256
        theta_map = prm.theta_map(self.theta_q, self.width, self.height)
        for c, (k, d) in enumerate(prm.channels):
            if len(self._p_history) > d:
                p_then = self._p_history[-1 - d]
                T = prm.box_threshold(k, theta_map)
                ratio_q = gains_q[(k, d)] = prm.brightness_ratio_q(self._brightness[-1],
                                                                    self._brightness[-1 - d])
                if ratio_q == 256:
                    s_now = ternary_states(receptor_change(p_now, p_then, k), T)
                else:  # exposure gain: 256 R(t) against ratio_q R(t - D), threshold 256 T + 128
                    s_now = ternary_states(gain_compensated_change(p_now, p_then, k, ratio_q),
                                           prm.compensated_threshold(T))
                    if (k, d) == (prm.scales[0], 1):  # the exposure-step test's states
                        step_states = ternary_states(receptor_change(p_now, p_then, k), T)
            else:
                s_now = zeros  # no frame D steps back yet: no change is known
            hist = self._state_history[(k, d)]
            hist.append(s_now)
            del hist[: -(2 * d + 1)]
            self.states.append(s_now)
            s_old = hist[-1 - 2 * d] if len(hist) > 2 * d else zeros
            s_mid = hist[-1 - d] if len(hist) > d else zeros
            for axis, (dpos, dneg) in enumerate(EVIDENCE_AXES[:n_axes]):
                # the diagonals feed the evidence only: their detectors run on its rows
                rows = evidence_rows if axis >= 2 else None
                mp = velocity_templates(s_old, s_mid, s_now, k, dpos, sharp=prm.sharp_templates, rows=rows)
                mn = velocity_templates(s_old, s_mid, s_now, k, dneg, sharp=prm.sharp_templates, rows=rows)
                if axis < 2:  # (the diagonals' matches show in the histogram only)
                    self.matches[(c, dpos)] = mp
                    self.matches[(c, dneg)] = mn
                pos[axis].append(mp)
                neg[axis].append(mn)
            if prm.summary_evidence:  # the evidence's gradients
                p_mid = self._p_history[-1 - d] if len(self._p_history) > d else p_now
                receptors_mid[(k, d)] = box_sums(p_mid, k)
        u_code = fuse_channels(pos[0], neg[0])
        v_code = fuse_channels(pos[1], neg[1])
        diagonal = None
        if n_axes > 2:  # the diagonals' codes on the evidence rows (0 elsewhere)
            diagonal = tuple(np.zeros_like(u_code) for _ in range(2, n_axes))
            for a, code in zip(range(2, n_axes), diagonal):
                code[evidence_rows] = fuse_channels(pos[a], neg[a])
        stats, hist, positions, tile_contrast = summary_statistics(
            prm, frame, p_now, u_code, v_code, receptors_mid, self.states, self.theta_q, step_states,
            gains_q, diagonal,
        )
        self.last_theta_q = self.theta_q
        #: each tile's contrast sum of this frame ('local'; None otherwise, as in OpenCL)
        self.tile_contrast = tile_contrast if prm.threshold_mode == "local" else None
        self.theta_q = prm.next_threshold_q(int(stats[STAT_CONTRAST]), self._contrast_samples,
                                            tile_contrast, self._tile_samples)
        self.frame_count += 1
        return u_code, v_code, stats, hist, positions

    def step_packed(self, frame: np.ndarray):
        """Like :meth:`step`, with the codes behind ``decode()`` as the OpenCL backend
        returns them (here already unpacked): ``(codes, stats, hist, positions)``."""
        u_code, v_code, stats, hist, positions = self.step(frame)
        return _Codes(u_code, v_code), stats, hist, positions


class _Codes:
    """Unpacked flow codes behind the ``decode()`` of the OpenCL backend's ``PackedCodes``."""

    __slots__ = ("u_code", "v_code")

    def __init__(self, u_code: np.ndarray, v_code: np.ndarray):
        self.u_code, self.v_code = u_code, v_code

    def decode(self) -> tuple[np.ndarray, np.ndarray]:
        return self.u_code, self.v_code
