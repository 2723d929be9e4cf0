"""Bee-style navigation cues from the same detections: expansion, time to contact, balance.

Honeybees land by holding the image expansion rate constant and fly down corridors by
balancing the image speed seen on either side. Both cues come from the detection
*position* histogram the backends compute next to the summary evidence
(``FlowField.positions``: detections on the sampled rows, horizontal ones binned by ``x``
and vertical ones by ``y`` into 16 bins):

* **expansion rate** ``r`` (1/frame): the relative growth of the image scale per frame,
  from a weighted line fit of the mean signed horizontal speed against ``x`` and of the
  vertical speed against ``y`` (for a radial flow ``u = r·X``, ``v = r·Y`` about the image
  centre, the slopes are both ``r``; edge orientations average out of the crossing speeds
  because they are symmetric about the axes). The divergence of the flow is ``2r``;
* **time to contact** ``1/r`` frames (``1/(r·fps)`` seconds) when approaching (``r > 0``);
  Measured on zoom flights (README): the slope reads 1.3–2× the true rate on fine
  textures (the detector's speed bands are biased upwards below ~3 px/frame, spec §6),
  monotonic in the truth — a relative cue, and a time to contact that errs early;
* **balance** left/right and top/bottom, ``(S_b − S_a) / (S_b + S_a)`` of the mean image
  speed ``S`` in each half: positive when the right (bottom) half moves faster, i.e. is
  nearer.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .field import FlowField

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
        Image-speed balance right vs left and bottom vs top, −1..1 (0 = balanced).
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


def _axis_fit(counts: np.ndarray, signed_speed: np.ndarray, size: int):
    """Weighted line fit of the mean signed speed against position for one axis."""
    bins = counts.shape[1]
    centres = (np.arange(bins) + 0.5) * size / bins - size / 2.0
    n = counts.sum(axis=0).astype(np.float64)
    total = n.sum()
    if total < 2 or np.count_nonzero(n) < 3:
        return None
    speed_sum = (signed_speed[:, None] * counts).sum(axis=0)
    mean_x = float((n * centres).sum() / total)
    dx = centres - mean_x
    sxx = float((n * dx * dx).sum())
    if sxx <= 0:
        return None
    slope = float((dx * speed_sum).sum() / sxx)
    # mean absolute speed per half, for the balance cue
    abs_sum = (np.abs(signed_speed)[:, None] * counts).sum(axis=0)
    half = bins // 2
    a_n, b_n = n[:half].sum(), n[half:].sum()
    s_a = abs_sum[:half].sum() / a_n if a_n else 0.0
    s_b = abs_sum[half:].sum() / b_n if b_n else 0.0
    balance = (s_b - s_a) / (s_b + s_a) if s_a + s_b > 0 else 0.0
    return slope, balance, int(total)


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
        All zero / inf when the history is not full or evidence is too thin.
    """
    if not field.ready or field.positions is None:
        return LoomingCues()
    speeds = np.asarray(field.params.speeds)
    signed = np.repeat(speeds, 2) * np.tile([1.0, -1.0], len(speeds))  # code 2c / 2c + 1
    h, w = field.shape
    fits = [_axis_fit(field.positions[0], signed, w), _axis_fit(field.positions[1], signed, h)]
    fits = [f if f is not None and f[2] >= min_detections else None for f in fits]
    if fits[0] is None and fits[1] is None:
        return LoomingCues()
    slopes = [f[0] for f in fits if f is not None]
    weights = [f[2] for f in fits if f is not None]
    rate = float(np.average(slopes, weights=weights))
    ttc = 1.0 / rate if rate > 1e-6 else math.inf
    return LoomingCues(
        expansion_rate=rate,
        time_to_contact_frames=ttc,
        balance_lr=fits[0][1] if fits[0] is not None else 0.0,
        balance_tb=fits[1][1] if fits[1] is not None else 0.0,
        detections=int(sum(weights)),
    )
