"""Pictures of optical flow, with the conventions of the optical-flow field.

* :func:`flow_to_color` — the Middlebury colour wheel (Baker et al. 2011, the
  ``flowToColor`` / ``computeColor`` code of the Middlebury benchmark): hue is the
  direction, saturation the magnitude relative to ``max_flow``; zero flow is white, flow
  beyond ``max_flow`` is drawn fully saturated and darkened to 75 %.
* :func:`render_flow_frame` — one frame of a flow video: the camera frame (dimmed gray),
  every detection coloured by the wheel, the global summary vector as an arrow from the
  centre whose colour goes from red (quality 0) to green (255), a text line with the
  numbers, a quality bar and a small colour-wheel legend.

Pure functions on arrays (numpy + OpenCV drawing); nothing here runs the engine.
Images are OpenCV BGR unless the name says RGB.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = [
    "make_colorwheel",
    "flow_to_color",
    "color_wheel_image",
    "quality_color",
    "render_flow_frame",
]

# Middlebury colour-wheel segment lengths (hues between the primaries).
_RY, _YG, _GC, _CB, _BM, _MR = 15, 6, 4, 11, 13, 6


def make_colorwheel() -> np.ndarray:
    """The Middlebury colour wheel.

    Returns
    -------
    ndarray of float64, shape (55, 3)
        RGB colours 0..255 around the wheel, starting at red, through yellow, green,
        cyan, blue and magenta.
    """
    # Each segment holds one channel at 255 and ramps another up (+1) or down (-1).
    segments = (  # (length, full channel, ramped channel, direction)
        (_RY, 0, 1, +1), (_YG, 1, 0, -1), (_GC, 1, 2, +1),
        (_CB, 2, 1, -1), (_BM, 2, 0, +1), (_MR, 0, 2, -1),
    )
    wheel = np.zeros((sum(seg[0] for seg in segments), 3))
    col = 0
    for n, full, ramped, direction in segments:
        ramp = np.floor(255 * np.arange(n) / n)
        wheel[col:col + n, full] = 255
        wheel[col:col + n, ramped] = ramp if direction > 0 else 255 - ramp
        col += n
    return wheel


_WHEEL = make_colorwheel()


def flow_to_color(u, v, max_flow: float | None = None, *, unknown_rgb=(0, 0, 0)) -> np.ndarray:
    """Colour-code a flow field with the Middlebury colour wheel.

    Parameters
    ----------
    u, v : array_like, shape (H, W)
        Flow in px/frame (x right, y down). A pixel where *both* components are NaN is
        unknown; a single NaN component is taken as 0 (the detector saw the other axis).
    max_flow : float, optional
        Magnitude drawn fully saturated. Default: the largest magnitude in the field
        (Middlebury's normalisation), at least 1e-6.
    unknown_rgb : tuple of int
        Colour of unknown pixels.

    Returns
    -------
    ndarray of uint8, shape (H, W, 3)
        RGB image.
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    unknown = np.isnan(u) & np.isnan(v)
    u = np.nan_to_num(u, nan=0.0, posinf=0.0, neginf=0.0)
    v = np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0)
    rad = np.hypot(u, v)
    if max_flow is None:
        max_flow = float(rad[~unknown].max()) if np.any(~unknown) else 1.0
    max_flow = max(float(max_flow), 1e-6)
    u, v, rad = u / max_flow, v / max_flow, rad / max_flow
    ncols = _WHEEL.shape[0]
    a = np.arctan2(-v, -u) / np.pi
    fk = (a + 1.0) / 2.0 * (ncols - 1)
    k0 = np.floor(fk).astype(np.int64)
    k1 = k0 + 1
    k1[k1 == ncols] = 0
    f = (fk - k0)[..., None]
    col = ((1 - f) * _WHEEL[k0] + f * _WHEEL[k1]) / 255.0
    inside = (rad <= 1)[..., None]
    col = np.where(inside, 1 - rad[..., None] * (1 - col), col * 0.75)
    rgb = np.floor(255 * col).astype(np.uint8)
    rgb[unknown] = unknown_rgb
    return rgb


def color_wheel_image(size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """A round legend of the colour wheel (RGB) and its mask; the rim is ``max_flow``."""
    r = (size - 1) / 2.0
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    u, v = (x - r) / r, (y - r) / r
    mask = np.hypot(u, v) <= 1.0
    return flow_to_color(u, v, 1.0), mask


def quality_color(quality: float) -> tuple[int, int, int]:
    """BGR colour of a quality 0..255: red at 0, yellow at 128, green at 255."""
    q = min(1.0, max(0.0, float(quality) / 255.0))
    red = 255 if q < 0.5 else int(round(255 * (1 - q) * 2))
    green = int(round(255 * q * 2)) if q < 0.5 else 255
    return (0, green, red)


def _text(img, text, org, scale, color, thickness=1):
    """Text with a dark outline so it reads on any background: the same text in black one
    pixel around it (a thicker black stroke is wider: Hershey glyphs advance by their
    stroke, so its digits drifted out from under the white ones)."""
    x, y = org
    for dx, dy in ((-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)):
        cv2.putText(img, text, (x + dx, y + dy), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thickness,
                    cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, color, thickness, cv2.LINE_AA)


def render_flow_frame(
    gray: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    flow_x: float,
    flow_y: float,
    quality: float,
    *,
    max_flow: float = 6.0,
    upscale: int = 1,
    arrow_gain: float | None = None,
    background: float = 0.55,
    label: str | None = None,
    legend: bool = True,
) -> np.ndarray:
    """Draw one frame of a flow video.

    Parameters
    ----------
    gray : ndarray of uint8, shape (H, W)
        The camera frame.
    u, v : ndarray, shape (H, W)
        Detections in px/frame, NaN where undetected (a pixel is drawn when either
        component is known).
    flow_x, flow_y : float
        Global summary flow, px/frame (image axes).
    quality : float
        Summary quality 0..255 (arrow colour, quality bar).
    max_flow : float
        Flow magnitude drawn fully saturated by the colour wheel (the legend's rim).
    upscale : int
        Integer enlargement of the output (nearest neighbour, so detections stay crisp).
    arrow_gain : float, optional
        Output pixels of arrow per px/frame of flow; default: ``max_flow`` spans 40 % of
        the shorter side.
    background : float
        Brightness factor of the gray frame under the detections (0..1).
    label : str, optional
        Text put before the numbers (e.g. the time stamp).
    legend : bool
        Draw the colour-wheel legend in the top-right corner.

    Returns
    -------
    ndarray of uint8, shape (H·upscale, W·upscale, 3)
        BGR image.
    """
    gray = np.asarray(gray)
    if gray.ndim != 2:
        raise ValueError(f"gray: expected a 2-D image, got shape {gray.shape}")
    h, w = gray.shape
    if np.shape(u) != (h, w) or np.shape(v) != (h, w):
        raise ValueError(f"u, v: expected shape {(h, w)}, got {np.shape(u)} and {np.shape(v)}")
    upscale = max(1, int(upscale))
    base = (gray.astype(np.float32) * float(background)).astype(np.uint8)
    img = cv2.cvtColor(base, cv2.COLOR_GRAY2BGR)
    detected = np.isfinite(u) | np.isfinite(v)
    if detected.any():
        rgb = flow_to_color(u, v, max_flow)
        img[detected] = rgb[detected][:, ::-1]
    if upscale > 1:
        img = cv2.resize(img, (w * upscale, h * upscale), interpolation=cv2.INTER_NEAREST)
    H, W = img.shape[:2]
    short = min(H, W)
    if arrow_gain is None:
        arrow_gain = 0.4 * short / max(max_flow, 1e-6)
    color = quality_color(quality)
    centre = (W / 2.0, H / 2.0)
    tip = (centre[0] + flow_x * arrow_gain, centre[1] + flow_y * arrow_gain)
    thick = max(1, int(round(short / 160)))
    c0 = (int(round(centre[0])), int(round(centre[1])))
    c1 = (int(round(tip[0])), int(round(tip[1])))
    length = math.hypot(c1[0] - c0[0], c1[1] - c0[1])
    cv2.circle(img, c0, thick + 2, (0, 0, 0), -1, cv2.LINE_AA)
    if length >= 2:
        tip_len = min(0.35, 12.0 * thick / length)
        cv2.arrowedLine(img, c0, c1, (0, 0, 0), thick + 2, cv2.LINE_AA, tipLength=tip_len)
        cv2.arrowedLine(img, c0, c1, color, thick, cv2.LINE_AA, tipLength=tip_len)
    cv2.circle(img, c0, thick + 1, color, -1, cv2.LINE_AA)
    # Text and quality bar.
    scale = max(0.35, short / 600.0)
    text = f"flow {flow_x:+.2f},{flow_y:+.2f} px/f  q {int(round(quality)):3d}"
    if label:
        text = f"{label}  {text}"
    _text(img, text, (int(6 * scale / 0.5), int(20 * scale / 0.5)), scale, (255, 255, 255), 1)
    bar_h = max(3, int(round(short / 60)))
    bar_w = int(round((W - 2 * bar_h) * min(1.0, max(0.0, quality / 255.0))))
    cv2.rectangle(img, (bar_h, H - 2 * bar_h), (W - bar_h, H - bar_h), (40, 40, 40), -1)
    if bar_w > 0:
        cv2.rectangle(img, (bar_h, H - 2 * bar_h), (bar_h + bar_w, H - bar_h), color, -1)
    if legend and short >= 96:
        size = max(24, short // 6)
        wheel, mask = color_wheel_image(size)
        x0, y0 = W - size - 4, 4
        roi = img[y0:y0 + size, x0:x0 + size]
        roi[mask] = wheel[mask][:, ::-1]
        rim = f"rim {max_flow:g} px/f"
        (tw, th), _ = cv2.getTextSize(rim, cv2.FONT_HERSHEY_SIMPLEX, scale * 0.7, 1)
        _text(img, rim, (W - tw - 4, y0 + size + th + 4), scale * 0.7, (255, 255, 255), 1)
    return img
