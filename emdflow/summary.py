"""Global flow summary: what the autopilot flies on.

The detector's output is sparse, quantised to the channels' speeds, and each axis measures
how fast an edge *crosses that axis*, not a flow component (``spec/template-model.md`` §6):
a per-axis mean is 40–100 % off. The summary works on the detection histogram
``hist[axis, code, orientation]`` that the backends compute next to the detector, so its
cost does not depend on the frame size.

Method
------
1. **Intersection of constraints (IoC), the initial guess** (spec §6). Each detection is
   a constraint on the global flow ``F = (U, V)`` along the gradient direction
   ``n = (cos φ, sin φ)`` of its orientation bin: a horizontal detection of channel speed
   ``r`` says ``n · F = r · cos φ``, a vertical one ``n · F = r · sin φ``. ``F`` is the
   Huber IRLS solution. The right-hand side is quantised to the channel speeds (scale
   ``k`` fires for crossing speeds of about ``k/2 … 1.5k`` and the fastest channel wins),
   so the quantisation errors only cancel for motion along the axes or diagonals; off
   those directions the fit snaps towards the axes (21 % / 11° median error at +0.3 rad).
2. **Calibrated maximum likelihood, the answer.** Each histogram row (axis ``a``,
   orientation bin) is treated as a sample of the *mixture of winning codes* the detector
   produces when an edge crosses axis ``a`` at the signed speed ``c = (n · F) / n_a``. The
   table ``P(code | c, ψ, β)`` — ``ψ`` the angle between the edge normal and the axis,
   ``β = |sin|`` of the angle between the flow and the edge normal — is measured on
   camera flights with known flow (``emdflow/tools/calibrate_summary.py``, stored in
   ``summary_calibration.npz`` next to this module) and mixed with a uniform outlier
   probability. ``F`` maximises ``Σ_rows Σ_codes count · log P(code | c(F), ψ, β(F))``,
   searched coarse-to-fine on a polar grid (log speed × direction) around the IoC
   guess (4 levels of 9×9, 5×5, 5×5, 5×5 candidates; the per-row likelihood curves are
   tabulated once per frame, so a candidate costs one interpolation per row). Rows whose
   normal is more than ``max_axis_angle`` (60°) from their axis are left out: their
   crossing speed ``c = n·F / n_a`` is huge and the detections there are dominated by
   texture details rather than edges. The table carries the band overlap and
   the highest-speed priority, the orientation error of the gradient, and the
   texture-detail ("point") responses that appear when the flow slides along an edge.
3. **Quality (0..255) tells the expected error.** It multiplies a texture factor (share
   of pixels with enough contrast), an evidence factor (detections), a geometry factor
   (gradient directions constraining both axes, the aperture problem) and an *accuracy*
   factor computed from the curvature of the log-likelihood around its maximum (the
   predicted relative error of ``F``, inflated by a calibrated over-dispersion because
   neighbouring detections are not independent), the disagreement between the IoC guess
   and the likelihood fit, and the top of the speed range (above ~11 px/frame only the
   13 px scale fires and speed is poorly resolved). See :class:`SummaryOptions`.

Blank, saturated or texture-less frames give flow 0 with quality 0. A *static* textured
scene — texture present, almost no receptor changes at scale 1, so the image moves less
than the detector's floor of about 0.5 px/frame — is a valid measurement: flow 0 with a
quality set by the texture.

The calibration exists for the paper's channel set (scales 1, 3, …, 13, delay 1). For any
other channel set (e.g. with temporal delays) the summary falls back to step 1 alone.

Measured accuracy
-----------------
Numpy backend, 320×240, noise σ = 2, 9 speeds (1–13 px/frame) × 8 directions × 4
evaluation textures (gravel, brick, grass, camera — the calibration never saw them) × 3
frames; quality-0 frames count as 100 % error
(``python -m emdflow.tools.calibrate_summary evaluate --offset 0`` / ``--offset 0.3``):

==========================  ===================  ==============
directions                  IoC only (previous)  this summary
==========================  ===================  ==============
multiples of 45°            7.9 %, 0.93°         9.1 %, 0.67°
multiples of 45° + 0.3 rad  21 %, 11°            8.9 %, 2.4°
==========================  ===================  ==============

Off-axis, 1–7 px/frame are within 5–10 % and 1–3°; 9–13 px/frame remain 13–30 % and
5–7° (above ~11 px/frame only the 13 px scale fires; the quality says so). Cost ≈ 1 ms
per call on the host (IoC alone: 0.15 ms).

References
----------
Quelin, Bouzerdoum & Phung, "Fast digital optical flow estimation based on EMD",
EUVIP 2010; ``spec/template-model.md`` §6 (facts the summary is built on).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from .field import FlowField
from .params import EngineParams

__all__ = ["FlowSummary", "summarize", "SummaryOptions"]

#: Calibration table written by ``python -m emdflow.tools.calibrate_summary fit``.
CALIBRATION_FILE = Path(__file__).with_name("summary_calibration.npz")


@dataclasses.dataclass(frozen=True)
class FlowSummary:
    """Global image flow of one frame.

    Attributes
    ----------
    flow_x, flow_y : float
        Global image flow, px/frame, image axes (x right, y down) — not MAVLink axes.
    quality : int
        0 (no information) … 255 (best). It falls as the expected error grows (see
        :class:`SummaryOptions` and the README's quality table).
    detections : int
        Detections that entered the fit.
    static : bool
        True when the scene is textured but does not move measurably (< ~0.5 px/frame);
        the flow is then 0 by definition.
    inlier_fraction : float
        Share of detection weight the robust IoC fit kept (1 = all agree).
    expected_error : float
        Predicted relative error of the flow (0.1 = 10 % of its magnitude); ``inf`` when
        nothing was estimated, 0 for a static scene.
    """

    flow_x: float = 0.0
    flow_y: float = 0.0
    quality: int = 0
    detections: int = 0
    static: bool = False
    inlier_fraction: float = 0.0
    expected_error: float = math.inf

    @property
    def speed(self) -> float:
        """Magnitude of the global flow, px/frame."""
        return math.hypot(self.flow_x, self.flow_y)


@dataclasses.dataclass(frozen=True)
class SummaryOptions:
    """Tuning of :func:`summarize` (defaults measured on texture flights, see README).

    Attributes
    ----------
    min_textured : float
        Textured share of pixels below which a frame is blank (quality 0).
    full_textured : float
        Textured share at which the texture factor of the quality reaches 1.
    max_saturated : float
        Saturated share of pixels above which a frame is unusable (quality 0).
    min_detections : int
        Fewer detections than this cannot make a moving estimate.
    full_detections : int
        Detections at which the evidence factor reaches 1.
    static_changed : float
        Share of scale-1 receptors with a nonzero state below which a textured scene with
        too few detections counts as static.
    huber_fraction, huber_floor : float
        Huber threshold of the IoC fit: ``max(floor, fraction · |F|)`` px/frame
        (the detector's speed bands are relative: scale ``k`` fires from ~k/2 to ~1.5k).
    iterations : int
        IRLS iterations of the IoC fit.
    likelihood : bool
        Refine the IoC guess by calibrated maximum likelihood (method step 2). Ignored
        (IoC only) when the channel set is not the calibrated one.
    max_axis_angle : float
        Degrees; histogram rows whose gradient normal is further than this from the
        detector's axis are left out of the likelihood.
    outlier_probability : float
        Probability mass spread uniformly over all codes in the likelihood (robustness to
        detections the table does not explain: other motion, flicker, noise).
    overdispersion : float
        Factor on the curvature-based standard error of the likelihood fit (detections of
        one edge are not independent); calibrated so that ``expected_error`` matches the
        median error on calibration flights.
    quality_error : float
        Expected relative error at which the accuracy factor of the quality is 1/2
        (the factor is ``1 / (1 + (expected_error / quality_error)²)``).
    top_speed : float
        Speed (px/frame) above which the fastest scale alone fires and the expected error
        grows; the expected error gains ``(|F| / top_speed − 1) · 0.5`` above it.
    """

    min_textured: float = 0.01
    full_textured: float = 0.10
    max_saturated: float = 0.5
    min_detections: int = 20
    full_detections: int = 400
    static_changed: float = 0.002
    huber_fraction: float = 0.15
    huber_floor: float = 0.3
    iterations: int = 12
    likelihood: bool = True
    max_axis_angle: float = 60.0
    outlier_probability: float = 0.01
    overdispersion: float = 1.0
    quality_error: float = 0.15
    top_speed: float = 11.0


_DEFAULT_OPTIONS = SummaryOptions()
_BLIND = FlowSummary()


# ---------------------------------------------------------------------------------------
# Step 1: intersection of constraints (initial guess, and the fallback)
# ---------------------------------------------------------------------------------------
def _constraint_tables(params: EngineParams):
    """Per histogram bin: normal (cos, sin) and right-hand side, cached per params."""
    key = (params.speeds,)
    hit = _TABLE_CACHE.get(key)
    if hit is not None:
        return hit
    phi = EngineParams.orientation_centres()
    cos, sin = np.cos(phi), np.sin(phi)
    speeds = np.asarray(params.speeds)
    n_codes = 2 * len(speeds)
    signed = np.repeat(speeds, 2) * np.tile([1.0, -1.0], len(speeds))  # code 2c / 2c+1
    nx = np.broadcast_to(cos, (2, n_codes, cos.size))
    ny = np.broadcast_to(sin, (2, n_codes, sin.size))
    axis_component = np.stack([np.broadcast_to(cos, (n_codes, cos.size)),
                               np.broadcast_to(sin, (n_codes, sin.size))])
    rhs = signed[None, :, None] * axis_component
    tables = (nx.ravel().copy(), ny.ravel().copy(), rhs.ravel().copy())
    _TABLE_CACHE[key] = tables
    return tables


_TABLE_CACHE: dict = {}


def _robust_fit(nx, ny, rhs, w0, opts: SummaryOptions):
    """Huber IRLS for ``F`` minimising Σ w ρ(n·F − rhs); returns (U, V, inlier share, cond)."""
    w = w0
    U = V = 0.0
    products = np.stack([nx * nx, nx * ny, ny * ny, nx * rhs, ny * rhs])
    for it in range(opts.iterations + 1):
        sxx, sxy, syy, bx, by = products @ w
        det = sxx * syy - sxy * sxy
        if det <= 1e-9 * max(1.0, (sxx + syy) ** 2):
            return None
        U_new = (syy * bx - sxy * by) / det
        V_new = (sxx * by - sxy * bx) / det
        converged = it > 0 and abs(U_new - U) + abs(V_new - V) < 1e-3
        U, V = U_new, V_new
        res = np.abs(nx * U + ny * V - rhs)
        c = max(opts.huber_floor, opts.huber_fraction * math.hypot(U, V))
        w = w0 * np.minimum(1.0, c / np.maximum(res, 1e-12))
        if converged:
            break
    inliers = float(np.dot(w0, res <= c)) / max(1e-12, float(w0.sum()))
    trace = sxx + syy
    geometry = 2.0 * math.sqrt(max(0.0, det)) / trace if trace > 0 else 0.0  # 1 = isotropic
    return U, V, inliers, geometry


# ---------------------------------------------------------------------------------------
# Step 2: calibrated maximum likelihood
# ---------------------------------------------------------------------------------------
class _LikelihoodModel:
    """The calibration table laid out per histogram row, for one (table, options) pair.

    Rows are ``axis · 64 + orientation bin``. ``logp[row, code, β node · 2U + j]`` is the
    log-probability of ``code`` for ``|c|`` at u-node ``j`` (``c > 0`` for ``j < U``,
    ``c < 0`` for ``j ≥ U``).
    """

    def __init__(self, table: dict, max_axis_angle: float, outlier: float):
        prob = np.asarray(table["prob"], np.float64)  # (ψ, β, u, category)
        psi_nodes = np.asarray(table["psi_nodes_deg"], np.float64)
        self.beta_nodes = np.asarray(table["beta_nodes"], np.float64)
        u_nodes = np.asarray(table["u_nodes"], np.float64)
        self.u_offset = float(table["u_offset"])
        self.u0 = float(u_nodes[0])
        self.du = float(u_nodes[1] - u_nodes[0])
        self.n_u = len(u_nodes)
        n_cat = prob.shape[-1]
        phi = EngineParams.orientation_centres()
        cos, sin = np.cos(phi), np.sin(phi)
        self.nx = np.concatenate([cos, cos])
        self.ny = np.concatenate([sin, sin])
        self.na = np.concatenate([cos, sin])  # signed axis component of the normal
        psi = np.degrees(np.arccos(np.clip(np.abs(self.na), 0.0, 1.0)))
        self.usable = psi < max_axis_angle
        i = np.clip(np.searchsorted(psi_nodes, psi, side="right") - 1, 0, len(psi_nodes) - 2)
        f = ((psi - psi_nodes[i]) / (psi_nodes[i + 1] - psi_nodes[i]))[:, None, None, None]
        p_row = (1.0 - f) * prob[i] + f * prob[i + 1]  # (row, β, u, category)
        p_row = (1.0 - outlier) * p_row + outlier / n_cat
        lp = np.log(p_row)
        # category = code for c > 0, code ^ 1 (sign flipped) for c < 0
        swap = np.arange(n_cat) ^ 1
        both = np.concatenate([lp, lp[..., swap]], axis=2)  # (row, β, 2U, code)
        n_rows, n_beta = both.shape[:2]
        self.n_beta = n_beta
        self.rows = np.nonzero(self.usable)[0]
        self.logp = np.ascontiguousarray(
            both[self.rows].transpose(0, 3, 1, 2).reshape(self.rows.size, n_cat, -1)
        ).astype(np.float32)
        r = self.rows
        # c = (n·F) / n_a = F · (nx, ny) / n_a
        self.gain = np.stack([self.nx[r] / self.na[r], self.ny[r] / self.na[r]])  # (2, R)
        self.nx_r, self.ny_r = self.nx[r], self.ny[r]
        self.base = np.arange(r.size) * (2 * self.n_u)
        self.flat_base = np.arange(r.size) * n_beta


_MODEL_CACHE: dict = {}
_CALIBRATION: dict = {}


def _load_calibration():
    if "table" not in _CALIBRATION:
        with np.load(CALIBRATION_FILE) as z:
            _CALIBRATION["table"] = {k: z[k] for k in z.files}
    return _CALIBRATION["table"]


def _model_for(params: EngineParams, opts: SummaryOptions):
    """The likelihood model for these channels, or None when they are not calibrated."""
    key = (params.speeds, opts.max_axis_angle, opts.outlier_probability)
    if key in _MODEL_CACHE:
        return _MODEL_CACHE[key]
    table = _load_calibration()
    model = None
    if tuple(params.speeds) == tuple(float(s) for s in table["speeds"]):
        model = _LikelihoodModel(table, opts.max_axis_angle, opts.outlier_probability)
    _MODEL_CACHE[key] = model
    return model


def _search_grid(dl: float, da: float, m: int):
    """Offsets of one search level: log-speed steps, exp of them, cos/sin of the turns."""
    ls = np.linspace(-dl, dl, m)
    aa = np.radians(np.linspace(-da, da, m))
    LS, AA = np.meshgrid(ls, aa, indexing="ij")
    return ls, aa, np.exp(LS.ravel()), np.cos(AA.ravel()), np.sin(AA.ravel())


#: Coarse-to-fine search: (± log-speed span, ± direction span in degrees, points per side).
_SEARCH_LEVELS = ((0.45, 24.0, 9), (0.1, 5.0, 5), (0.03, 1.5, 5), (0.008, 0.4, 5))
_SEARCH_GRIDS = [_search_grid(*lvl) for lvl in _SEARCH_LEVELS]
#: Level whose grid gives the curvature of the log-likelihood (expected error).
_CURVATURE_LEVEL = 1


class _RowCurves:
    """Per-row log-likelihood curves of one frame, as functions of (β, signed |c|)."""

    def __init__(self, model: _LikelihoodModel, hist: np.ndarray):
        h = hist.transpose(0, 2, 1).reshape(-1, hist.shape[1])[model.rows]  # (row, code)
        self.model = model
        self.count = float(h.sum())
        self.active = int(np.count_nonzero(h.sum(axis=1)))
        # (R, 1, codes) @ (R, codes, β·2U) -> (R, β·2U)
        self.curves = np.matmul(h.astype(np.float32)[:, None, :], model.logp)[:, 0, :]

    def at_direction(self, angle: float) -> np.ndarray:
        """Curves over signed |c| (R, 2U) with β interpolated for a flow at ``angle``."""
        m = self.model
        vn = m.nx_r * math.cos(angle) + m.ny_r * math.sin(angle)
        beta = np.sqrt(np.maximum(1.0 - vn * vn, 0.0))
        nodes = m.beta_nodes
        i = np.minimum(np.searchsorted(nodes, beta, side="right") - 1, len(nodes) - 2)
        f = ((beta - nodes[i]) / (nodes[i + 1] - nodes[i]))[:, None]
        c = self.curves.reshape(-1, 2 * m.n_u)  # (R·β, 2U)
        k = m.flat_base + i
        return (1.0 - f) * c[k] + f * c[k + 1]

    def loglik(self, curves: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """Log-likelihood of candidate flows (M,) given curves at their direction."""
        m = self.model
        c = np.stack([fx, fy], axis=1) @ m.gain  # (M, R) signed crossing speeds
        x = np.log(np.abs(c) + m.u_offset)
        x -= m.u0
        x *= 1.0 / m.du
        np.clip(x, 0.0, m.n_u - 1 - 1e-9, out=x)
        j = x.astype(np.intp)
        x -= j  # fraction
        j += np.where(c < 0, m.n_u, 0)
        j += m.base
        flat = curves.ravel()
        lo = flat[j]
        return (lo + x * (flat[j + 1] - lo)).sum(axis=1)


def _curvature_sigma(L: np.ndarray, step: float, axis: int) -> float:
    """Standard error along one axis of a grid of log-likelihoods: 1/sqrt(−L'') from a
    least-squares parabola through the grid's profile at its maximum."""
    bi = np.unravel_index(int(np.argmax(L)), L.shape)
    prof = L[:, bi[1]] if axis == 0 else L[bi[0], :]
    x = (np.arange(prof.size) - (prof.size - 1) / 2) * step
    a = np.polyfit(x, prof, 2)[0]
    # a flat or convex profile: the data do not pin the maximum within the grid's span
    return 1.0 / math.sqrt(-2.0 * a) if a < -0.5 / x[-1] ** 2 else 2.0 * x[-1]


def _likelihood_fit(curves: _RowCurves, U0: float, V0: float):
    """Coarse-to-fine polar search; returns (U, V, σ of log-speed, σ of direction)."""
    s = max(math.hypot(U0, V0), 0.5)
    a = math.atan2(V0, U0)
    sig_s = sig_a = math.inf
    for level, (ls, aa, es, ca, sa) in enumerate(_SEARCH_GRIDS):
        cur = curves.at_direction(a)
        sp = s * es
        cos_a, sin_a = math.cos(a), math.sin(a)
        fx = sp * (cos_a * ca - sin_a * sa)
        fy = sp * (sin_a * ca + cos_a * sa)
        L = curves.loglik(cur, fx, fy).reshape(ls.size, aa.size)
        bi, bj = np.unravel_index(int(np.argmax(L)), L.shape)
        if level == _CURVATURE_LEVEL:
            sig_s = _curvature_sigma(L, ls[1] - ls[0], 0)
            sig_a = _curvature_sigma(L, aa[1] - aa[0], 1)
        s = s * math.exp(ls[bi])
        a = a + aa[bj]
    return s * math.cos(a), s * math.sin(a), sig_s, sig_a


# ---------------------------------------------------------------------------------------
def summarize(field: FlowField, *, options: SummaryOptions | None = None) -> FlowSummary:
    """Global image flow of a :class:`FlowField` with a quality that says how far to trust it.

    Parameters
    ----------
    field : FlowField
        The detector's output for one frame (from :meth:`FlowEstimator.update`).
    options : SummaryOptions, optional
        Thresholds and fit tuning; the defaults are documented in :class:`SummaryOptions`.

    Returns
    -------
    FlowSummary
        ``flow_x, flow_y`` in px/frame (image axes: x right, y down), ``quality``
        0..255 and ``expected_error``. When nothing can be estimated (history filling,
        blank, saturated or texture-less frame, inconsistent evidence) the flow is 0.0
        with quality 0.

    Notes
    -----
    IoC guess refined by calibrated maximum likelihood over the detection histogram; see
    the module docstring and ``spec/template-model.md`` §6.
    """
    opts = options or _DEFAULT_OPTIONS
    if not isinstance(field, FlowField):
        raise TypeError(f"summarize() takes a FlowField, not {type(field).__name__}")
    if not field.ready:
        return _BLIND
    textured = field.textured_fraction
    if textured < opts.min_textured or field.saturated_fraction > opts.max_saturated:
        return _BLIND
    q_texture = min(1.0, textured / opts.full_textured)
    hist = field.histogram
    counts = hist.ravel().astype(np.float64)
    n = int(counts.sum())
    if n < opts.min_detections:
        # Few detections: either the scene is static (below the detector's floor) or the
        # motion is one the detector cannot follow (too fast, flicker): tell them apart by
        # how many scale-1 receptors changed at all.
        params = field.params
        c1 = params.channels.index((params.scales[0], 1))
        if field.changed_fraction[c1] <= opts.static_changed:
            return FlowSummary(0.0, 0.0, int(round(255 * q_texture * 0.75)), n, True, 1.0, 0.0)
        return FlowSummary(detections=n)
    nx, ny, rhs = _constraint_tables(field.params)
    used = counts > 0
    fit = _robust_fit(nx[used], ny[used], rhs[used], counts[used], opts)
    if fit is None:
        return FlowSummary(detections=n)
    U, V, inliers, geometry = fit
    q_evidence = min(1.0, n / opts.full_detections)
    q_geometry = min(1.0, 2.0 * geometry)

    model = _model_for(field.params, opts) if opts.likelihood else None
    curves = _RowCurves(model, hist) if model is not None else None
    if curves is not None and curves.active >= 2 and curves.count >= opts.min_detections:
        U1, V1, sig_s, sig_a = _likelihood_fit(curves, U, V)
        speed = math.hypot(U1, V1)
        disagreement = math.hypot(U1 - U, V1 - V) / max(speed, 0.5)
        expected = math.hypot(opts.overdispersion * math.hypot(sig_s, sig_a), 0.5 * disagreement)
        U, V = U1, V1
    else:
        speed = math.hypot(U, V)
        expected = 0.1 + (1.0 - inliers)  # IoC only: a rough figure
    if speed > opts.top_speed:
        expected += 0.5 * (speed / opts.top_speed - 1.0)
    q_accuracy = 0.0
    if math.isfinite(expected):
        q_accuracy = 1.0 / (1.0 + (expected / opts.quality_error) ** 2)
    quality = 255.0 * q_texture * q_evidence * q_geometry * q_accuracy
    # an estimate was made: quality 0 stays reserved for "no information, flow 0"
    quality = max(1, int(round(quality)))
    return FlowSummary(float(U), float(V), quality, n, False, inliers, float(expected))
