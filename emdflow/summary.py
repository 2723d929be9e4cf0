"""Global flow summary: what the autopilot flies on.

The detector's output is sparse, quantised to the channels' speeds, and each axis measures
how fast an edge *crosses that axis*, not a flow component (``spec/template-model.md`` §6):
a per-axis mean is 40–100 % off. The summary therefore treats every detection as a
constraint on the global image flow ``F = (U, V)`` along the local gradient direction
``n = (cos φ, sin φ)`` of the receptor image (intersection of constraints):

* horizontal detection of speed ``r``: the edge crosses a row at ``r`` px/frame, so
  ``n · F = r · cos φ``;
* vertical detection of speed ``r``: ``n · F = r · sin φ``.

The residual ``n · F − r·n_axis`` is the error along the gradient in px/frame. ``F`` is the
robust (Huber) iteratively reweighted least-squares solution over all detections. The
detections arrive already binned by (axis, signed channel, gradient orientation) — the
histogram the backends compute next to the detector — so the solve costs the same for any
frame size.

Quality (0..255) multiplies four factors in 0..1, each saying why the number may be wrong:
texture (share of pixels with enough contrast), evidence (number of detections),
consistency (share of detection weight the robust fit keeps) and geometry (how well the
gradient directions constrain both axes — the aperture problem). Blank, saturated or
texture-less frames give 0. A *static* textured scene — texture present, almost no
receptor changes at scale 1, so the image moves less than the detector's floor of about
0.5 px/frame — is a valid measurement: flow 0 with a quality set by the texture.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .field import FlowField
from .params import EngineParams

__all__ = ["FlowSummary", "summarize", "SummaryOptions"]


@dataclasses.dataclass(frozen=True)
class FlowSummary:
    """Global image flow of one frame.

    Attributes
    ----------
    flow_x, flow_y : float
        Global image flow, px/frame, image axes (x right, y down) — not MAVLink axes.
    quality : int
        0 (no information) … 255 (best).
    detections : int
        Detections that entered the fit.
    static : bool
        True when the scene is textured but does not move measurably (< ~0.5 px/frame);
        the flow is then 0 by definition.
    inlier_fraction : float
        Share of detection weight the robust fit kept (1 = all agree).
    """

    flow_x: float = 0.0
    flow_y: float = 0.0
    quality: int = 0
    detections: int = 0
    static: bool = False
    inlier_fraction: float = 0.0

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
        Huber threshold of the robust fit: ``max(floor, fraction · |F|)`` px/frame
        (the detector's speed bands are relative: scale ``k`` fires from ~k/2 to ~1.5k).
    iterations : int
        IRLS iterations.
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


_DEFAULT_OPTIONS = SummaryOptions()
_BLIND = FlowSummary()


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
    for it in range(opts.iterations + 1):
        sxx = np.dot(w, nx * nx)
        sxy = np.dot(w, nx * ny)
        syy = np.dot(w, ny * ny)
        bx = np.dot(w, nx * rhs)
        by = np.dot(w, ny * rhs)
        det = sxx * syy - sxy * sxy
        if det <= 1e-9 * max(1.0, (sxx + syy) ** 2):
            return None
        U_new = (syy * bx - sxy * by) / det
        V_new = (sxx * by - sxy * bx) / det
        converged = it > 0 and abs(U_new - U) + abs(V_new - V) < 1e-4
        U, V = U_new, V_new
        res = np.abs(nx * U + ny * V - rhs)
        c = max(opts.huber_floor, opts.huber_fraction * math.hypot(U, V))
        huber = np.minimum(1.0, c / np.maximum(res, 1e-12))
        w = w0 * huber
        if converged:
            break
    inliers = float(np.dot(w0, res <= c)) / max(1e-12, float(w0.sum()))
    trace = sxx + syy
    geometry = 2.0 * math.sqrt(max(0.0, det)) / trace if trace > 0 else 0.0  # 1 = isotropic
    return U, V, inliers, geometry


def summarize(field: FlowField, *, options: SummaryOptions | None = None) -> FlowSummary:
    """Global image flow of a :class:`FlowField` with a quality that says how far to trust it.

    Parameters
    ----------
    field : FlowField
        The detector's output for one frame (from :meth:`FlowEstimator.update`).
    options : SummaryOptions, optional
        Thresholds and robust-fit tuning; the defaults are documented in
        :class:`SummaryOptions`.

    Returns
    -------
    FlowSummary
        ``flow_x, flow_y`` in px/frame (image axes: x right, y down) and ``quality``
        0..255. When nothing can be estimated (history filling, blank, saturated or
        texture-less frame, inconsistent evidence) the flow is 0.0 with quality 0.

    Notes
    -----
    Intersection of constraints with a Huber IRLS over the detection histogram; see the
    module docstring and ``spec/template-model.md`` §6.
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
    counts = field.histogram.ravel().astype(np.float64)
    n = int(counts.sum())
    if n < opts.min_detections:
        # Few detections: either the scene is static (below the detector's floor) or the
        # motion is one the detector cannot follow (too fast, flicker): tell them apart by
        # how many scale-1 receptors changed at all.
        params = field.params
        c1 = params.channels.index((params.scales[0], 1))
        if field.changed_fraction[c1] <= opts.static_changed:
            return FlowSummary(0.0, 0.0, int(round(255 * q_texture * 0.75)), n, True, 1.0)
        return FlowSummary(detections=n)
    nx, ny, rhs = _constraint_tables(field.params)
    used = counts > 0
    fit = _robust_fit(nx[used], ny[used], rhs[used], counts[used], opts)
    if fit is None:
        return FlowSummary(detections=n)
    U, V, inliers, geometry = fit
    q_evidence = min(1.0, n / opts.full_detections)
    quality = 255.0 * q_texture * q_evidence * inliers * min(1.0, 2.0 * geometry)
    return FlowSummary(float(U), float(V), int(round(quality)), n, False, inliers)
