"""Synthetic camera flights over real photographs, with exact ground truth.

A downward-looking camera flies over a flat textured ground (one of the photographs that
scikit-image bundles, or any image file). Each frame is rendered at ``supersample`` times
the output resolution with bilinear interpolation and then area-averaged down, so sub-pixel
motion is rendered the way a real sensor integrates light over its pixel area. Sensor noise,
contrast reduction and exposure drift are optional.

The ground is tiled by reflection, so flights can be arbitrarily long.

Everything here is pure computation on arrays: the same renderer feeds the tests, the
evaluation tool, the benchmark and the daemon's ``synthetic:`` source.
"""

from __future__ import annotations

import dataclasses
import math
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

__all__ = ["TEXTURES", "MIN_SIDE", "load_texture", "CameraFlight", "FlightTruth", "RotatingCamera"]

#: Smallest frame side :class:`CameraFlight` renders, px.
MIN_SIDE = 8

# The renderer's ground coordinates stay small: OpenCV's warpAffine finds a sample far
# outside the texture by reflecting it back one texture length at a time (time grows with
# the distance; NaN or a saturated coordinate never comes back), and its fixed-point
# coordinates saturate beyond 2**21 px.
#: Beyond this many reflection periods from the texture the image centre is folded back
#: (the reflected ground repeats every period; nearer flights render bit for bit as before).
_FOLD_PERIODS = 16
#: A frame's view may be at most this many texture sizes across (a zoom flight receding
#: for long); beyond, render() raises ValueError.
_MAX_VIEW_TEXTURES = 256

#: Names of bundled photographs usable as ground textures (scikit-image's ``data`` module).
#: Besides these (and image files), ``"immunohistochemistry"`` (a stained tissue section:
#: a fine, irregular texture), synthetic ``"fractal-<beta>-<seed>[-<sigma>]"`` textures
#: (:func:`fractal_texture`), ``"grain-<period>-<seed>[-<sigma>]"`` (:func:`grain_texture`)
#: and the pair ``"lines-<seed>[-<angle>]"`` / ``"cells-<seed>[-<angle>]"``
#: (:func:`grid_texture`: thin lines, or step edges, on one layout) are known.
TEXTURES = ("gravel", "grass", "brick", "camera", "moon", "coffee", "astronaut", "rocket")
_EXTRA_PHOTOGRAPHS = ("immunohistochemistry",)


def fractal_texture(beta: float, seed: int, size: int = 1024, sigma: float = 40.0) -> np.ndarray:
    """A random texture with a ``1 / f**beta`` amplitude spectrum (uint8, mean 128, standard
    deviation ``sigma`` gray levels before clipping to 0..255).

    With ``beta`` below the bundled calibration photographs' (their amplitude spectra
    fall about as ``1 / f**1.2``–``1 / f**1.4``) it is rougher than they are, but it is
    not granular: gravel's and grass's photographs have a flat spectrum up to a grain size
    and a steep one beyond (:func:`grain_texture`). Deterministic for a seed.
    With ``sigma`` ≈ 60 the frame's mean gradient is that of gravel or grass (~17–19 gray
    levels), which the summary's calibration needs to see."""
    f = _frequencies(size)
    f[0, 0] = 1.0
    return _random_phase_texture(f ** -_finite("beta", beta), seed, size, sigma)


def _frequencies(size: int) -> np.ndarray:
    """|f| (cycles/px) of the rfft2 bins of a ``size`` × ``size`` image."""
    return np.hypot(np.fft.rfftfreq(size)[None, :], np.fft.fftfreq(size)[:, None])


def _random_phase_texture(amplitude: np.ndarray, seed: int, size: int, sigma: float) -> np.ndarray:
    """Gaussian noise of amplitude spectrum ``amplitude`` (rfft2 bins; the mean is left
    out), as uint8 of mean 128 and standard deviation ``sigma`` gray levels before clipping
    to 0..255; deterministic for a seed."""
    sigma = _finite("sigma", sigma)
    if sigma <= 0.0:
        raise ValueError(f"sigma={sigma!r}: must be > 0 gray levels")
    rng = np.random.default_rng(int(seed))
    spectrum = (rng.normal(size=amplitude.shape) + 1j * rng.normal(size=amplitude.shape)) * amplitude
    spectrum[0, 0] = 0.0
    image = np.fft.irfft2(spectrum, s=(size, size))
    image = (image - image.mean()) / image.std() * sigma + 128.0
    return np.clip(image, 0, 255).astype(np.uint8)


#: Power-spectrum exponent of :func:`grain_texture` above its grain frequency (between
#: the steep falls of gravel's and grass's photographs).
GRAIN_EXPONENT = 3.5


def grain_texture(period: float, seed: int, size: int = 1024, sigma: float = 40.0) -> np.ndarray:
    """A random *granular* texture (uint8, mean 128, standard deviation ``sigma`` gray levels
    before clipping to 0..255), like a ground of pebbles, sand or grass blades about
    ``period`` px across. Its power spectrum is ``1 / (1 + (f · period)²)**(e / 2)`` with
    ``e = GRAIN_EXPONENT`` (``f`` in cycles/px): nearly flat well below the grain frequency
    ``1 / period`` (down to 0.30 at it), falling as ``f**-e`` well above it.
    Deterministic for a seed. ``period`` is at most ``size``.

    Gravel and grass are granular, not fractal: their photographs' spectra are nearly flat
    up to a grain size and steep beyond, where a 1/f texture keeps much of its power at
    low frequencies. Granular ground decorrelates under a sideways shift much sooner
    (README, "Fast oblique flight over rough ground")."""
    period = _finite("period", period)
    if not 0.0 < period <= size:
        raise ValueError(f"period={period!r}: must be > 0 and at most the texture's {size} px")
    amplitude = (1.0 + (_frequencies(size) * period) ** 2) ** (-GRAIN_EXPONENT / 4.0)
    return _random_phase_texture(amplitude, seed, size, sigma)


def grid_texture(kind: str, seed: int, size: int = 1024, line_width: int = 4,
                 angle_deg: float = 0.0) -> np.ndarray:
    """A rectangular grid ground, as thin lines or as step edges on the same layout (uint8).

    Columns are 15–50 px apart and rows 40–120 px (drawn from ``seed``), like a brick or
    tiled floor seen from above. ``kind="lines"`` draws the grid as ``line_width`` px bright
    lines (+60 gray levels on 100, like mortar joints); ``kind="cells"`` fills the same grid
    cells with uniform gray levels drawn from 70–160, so every line becomes a step edge.
    Both carry the same fine texture (σ = 3 gray levels). The pair isolates what thin lines
    do to the detector: on an axis flight a line fires the scale of its speed and nothing
    above, where an edge also fires the next larger scales (README, "Thin lines read slow").

    ``angle_deg`` turns the grid (counter-clockwise in the image, degrees): unless it is a
    multiple of 360°, the grid is drawn on a square ``√2`` times larger (so its layout
    differs from the unturned one of the same seed), turned with bilinear interpolation
    about its centre and cut to
    ``size``. The summary's line-ground table is calibrated on turned grids, so that it
    knows lines of every orientation, not only the axes'."""
    if kind not in ("lines", "cells"):
        raise ValueError(f"grid texture kind {kind!r}: expected 'lines' or 'cells'")
    angle_deg = _finite("angle_deg", angle_deg)
    if angle_deg % 360.0:
        drawn = int(math.ceil(size * math.sqrt(2.0))) + 2
        big = _grid(kind, seed, drawn, line_width).astype(np.float32)
        turn = cv2.getRotationMatrix2D(((drawn - 1) / 2.0, (drawn - 1) / 2.0), angle_deg, 1.0)
        turn[:, 2] -= (drawn - size) / 2.0  # the centre of the turned square to the output's
        turned = cv2.warpAffine(big, turn, (size, size), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_REFLECT)
        return np.clip(np.rint(turned), 0, 255).astype(np.uint8)
    return np.clip(np.rint(_grid(kind, seed, size, line_width)), 0, 255).astype(np.uint8)


def _grid(kind: str, seed: int, size: int, line_width: int) -> np.ndarray:
    """The unturned grid of :func:`grid_texture` as float64 gray levels (not yet rounded)."""
    rng = np.random.default_rng(int(seed))
    # the layout and the fine texture come first from the seed: both kinds share them
    columns = np.cumsum(rng.integers(15, 51, size // 15 + 1))
    rows = np.cumsum(rng.integers(40, 121, size // 40 + 1))
    columns, rows = columns[columns < size], rows[rows < size]
    image = rng.normal(0.0, 3.0, (size, size))
    if kind == "lines":
        image += 100.0
        for x in columns:
            image[:, x:x + line_width] += 60.0
        for y in rows:
            image[y:y + line_width, :] += 60.0
    else:
        levels = rng.uniform(70.0, 160.0, (len(rows) + 1, len(columns) + 1))
        cell_of_x = np.searchsorted(columns, np.arange(size), side="right")
        cell_of_y = np.searchsorted(rows, np.arange(size), side="right")
        image += levels[cell_of_y[:, None], cell_of_x[None, :]]
    return image


#: Random textures by name, ``<kind>-<parameter>-<seed>[-<sigma>]``: the function, what its
#: first parameter is, and examples for the error message.
_NOISE_TEXTURES = {
    "fractal": (fractal_texture, "beta", "fractal-1.0-1 or fractal-0.8-3-60"),
    "grain": (grain_texture, "period px", "grain-12-1 or grain-8-3-50"),
}


@lru_cache(maxsize=16)
def _load_texture_cached(name: str) -> np.ndarray:
    if name in TEXTURES or name in _EXTRA_PHOTOGRAPHS:
        import skimage.data

        image = getattr(skimage.data, name)()
    elif name.partition("-")[0] in _NOISE_TEXTURES and not Path(name).is_file():
        kind = name.partition("-")[0]
        make, parameter, examples = _NOISE_TEXTURES[kind]
        try:  # <kind>-<parameter>-<seed>[-<sigma>]
            _, value, seed, *sigma = name.split("-")
            if len(sigma) > 1:
                raise ValueError(name)
            image = make(float(value), int(seed), sigma=float(sigma[0]) if sigma else 40.0)
        except ValueError:
            raise ValueError(f"texture {name!r}: expected {kind}-<{parameter}>-<seed>[-<sigma>], "
                             f"e.g. {examples}") from None
    elif name.startswith(("lines-", "cells-")) and not Path(name).is_file():
        kind, _, rest = name.partition("-")
        fields = rest.split("-", 1)  # the angle may carry its own minus sign
        try:  # <kind>-<seed>[-<angle in degrees>]
            if not (1 <= len(fields) <= 2 and fields[0].isdecimal()):
                raise ValueError(name)
            angle = float(fields[1]) if len(fields) == 2 else 0.0
            if not math.isfinite(angle):
                raise ValueError(name)
        except ValueError:
            raise ValueError(f"texture {name!r}: expected {kind}-<seed>[-<angle in degrees>], "
                             f"e.g. {kind}-1 or {kind}-1-30") from None
        image = grid_texture(kind, int(fields[0]), angle_deg=angle)
    else:
        path = Path(name)
        if not path.is_file():
            raise ValueError(
                f"texture {name!r}: not a bundled texture ({', '.join(TEXTURES)}) "
                "and not an image file"
            )
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"texture {name!r}: OpenCV cannot read this image file")
    if image.ndim == 3:
        code = cv2.COLOR_RGBA2GRAY if image.shape[2] == 4 else cv2.COLOR_RGB2GRAY
        image = cv2.cvtColor(np.ascontiguousarray(image), code)
    if image.dtype != np.uint8:
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    texture = image.astype(np.float32)
    texture.setflags(write=False)
    return texture


def load_texture(name: str) -> np.ndarray:
    """Return a ground texture as a read-only float32 gray image (0..255).

    Parameters
    ----------
    name : str
        One of :data:`TEXTURES`, or the path of any image file OpenCV reads.
    """
    return _load_texture_cached(str(name))


@dataclasses.dataclass(frozen=True)
class FlightTruth:
    """Ground truth of one rendered frame.

    Attributes
    ----------
    flow_x, flow_y : float
        Image motion of the ground between the previous frame and this one at the image
        centre, px/frame (x right, y down).
    expansion_rate : float
        Relative growth of the image scale per frame, ``r`` (1/frame); 0 for a
        translation. At frame ``t−1``'s pixel positions the flow is ``u = flow_x + r·X``,
        ``v = flow_y + r·Y`` with ``(X, Y)`` measured from the image centre, so the
        divergence is ``2r`` and the time to contact ``1/r`` frames.
    """

    flow_x: float
    flow_y: float
    expansion_rate: float = 0.0


def _finite(name: str, value) -> float:
    """``value`` as a float; ValueError naming ``name`` unless it is a finite number."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r}: expected a number") from None
    if not math.isfinite(number):
        raise ValueError(f"{name}={value!r}: must be a finite number")
    return number


def _finite_pair(name: str, pair, unit: str) -> tuple[float, float]:
    """``(x, y)`` as floats; ValueError naming ``name`` unless both are finite numbers."""
    try:
        x, y = pair
    except (TypeError, ValueError):
        raise ValueError(f"{name}={pair!r}: expected two numbers (x, y), {unit}") from None
    return _finite(f"{name}[0]", x), _finite(f"{name}[1]", y)


def _check_raster(width: int, height: int, supersample: int) -> None:
    """ValueError for a frame too small to render or a supersampling factor below 1."""
    if width < MIN_SIDE or height < MIN_SIDE:
        raise ValueError(f"frame size {width}x{height}: both sides must be at least {MIN_SIDE} px")
    if supersample < 1:
        raise ValueError(f"supersample={supersample}: must be >= 1")


def _sensor_frame(image: np.ndarray, noise_sigma: float, seed: int) -> np.ndarray:
    """The 8-bit frame a sensor delivers from ``image`` (gray levels): Gaussian noise of
    ``noise_sigma`` (generator seeded with ``seed``, so a frame renders again on its own),
    rounded and clipped to 0..255."""
    if noise_sigma > 0:
        rng = np.random.default_rng(seed)
        image = image + rng.normal(0.0, noise_sigma, image.shape).astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


class _RenderedFrames:
    """What the renderers share: their raster, ground and noise, and frame sequences of
    their ``render(t)``."""

    def _init_raster(self, texture: str, width: int, height: int, supersample: int,
                     noise_sigma: float, seed: int) -> None:
        self.noise_sigma = _finite("noise_sigma", noise_sigma)
        self.texture_name = str(texture)
        self.texture = load_texture(texture)
        self.width, self.height = int(width), int(height)
        self.supersample = int(supersample)
        self.seed = int(seed)

    def frames(self, count: int, start: int = 0):
        """Yield ``count`` consecutive frames starting at index ``start``."""
        for t in range(start, start + count):
            yield self.render(t)

    def render_many(self, count: int, start: int = 0) -> np.ndarray:
        """Render ``count`` frames as an array of shape (count, height, width)."""
        return np.stack(list(self.frames(count, start)))


class CameraFlight(_RenderedFrames):
    """A camera flight over a textured ground plane with known image motion.

    Parameters
    ----------
    texture : str
        Ground texture: a name from :data:`TEXTURES` or an image file path.
    width, height : int
        Output frame size in pixels.
    flow : (float, float)
        Image flow of the ground, px/frame (x right, y down). The camera moves the
        opposite way.
    noise_sigma : float
        Standard deviation of additive Gaussian sensor noise, gray levels (8-bit).
    contrast : float
        Scene contrast factor around mid-gray (1 = the photograph's own contrast).
    shade : float
        Light on the right half of the view, relative to the left (1 = even light): a
        shadow fixed in the view, such as the vehicle's own or a wall's beside its path.
        The shaded pixels are multiplied by it, so their brightness and their contrast
        drop together; in (0, 1].
    exposure_drift : float
        Relative exposure change across ``drift_frames`` frames (e.g. 0.2 for +20 %),
        applied as a linear gain ramp; negative values darken.
    drift_frames : int
        Length of the exposure ramp in frames.
    expansion_rate : float
        Zoom flight: relative growth of image scale per frame (1/frame), as when the
        camera approaches the ground; the flow field is then radial about the centre.
        Must be > -1.
    ground_scale : float
        Ground texture pixels per output pixel at frame 0 (values < 1 magnify the
        photograph, > 1 shrink it); > 0.
    supersample : int
        Rendering oversampling factor per axis before area averaging.
    seed : int
        Seed of the noise generator; frame ``t`` uses ``seed + t`` so any frame can be
        rendered again on its own.
    start : (float, float), optional
        Ground position (texture px) under the image centre at frame 0; default the
        texture's centre.

    Raises
    ------
    ValueError
        If a side is below :data:`MIN_SIDE` px, a number is NaN or infinite, or
        ``expansion_rate``, ``ground_scale`` or ``supersample`` is out of range (naming
        the parameter).
    """

    def __init__(
        self,
        texture: str = "gravel",
        *,
        width: int = 320,
        height: int = 240,
        flow: tuple[float, float] = (1.0, 0.0),
        noise_sigma: float = 2.0,
        contrast: float = 1.0,
        shade: float = 1.0,
        exposure_drift: float = 0.0,
        drift_frames: int = 100,
        expansion_rate: float = 0.0,
        ground_scale: float = 1.0,
        supersample: int = 4,
        seed: int = 0,
        start: tuple[float, float] | None = None,
    ):
        _check_raster(width, height, supersample)
        # NaN or infinity would reach cv2.warpAffine, which then never returns
        self.flow = _finite_pair("flow", flow, "px/frame")
        self._init_raster(texture, width, height, supersample, noise_sigma, seed)
        self.contrast = _finite("contrast", contrast)
        self.shade = _finite("shade", shade)
        if not 0.0 < self.shade <= 1.0:
            raise ValueError(f"shade={shade!r}: must be in (0, 1] (the shaded half's share of the light)")
        self.exposure_drift = _finite("exposure_drift", exposure_drift)
        self.expansion_rate = _finite("expansion_rate", expansion_rate)
        if self.expansion_rate <= -1.0:  # the image scale (1 + r)**t would reach 0
            raise ValueError(f"expansion_rate={expansion_rate!r}: must be > -1 (scale growth per frame)")
        self.ground_scale = _finite("ground_scale", ground_scale)
        if self.ground_scale <= 0.0:
            raise ValueError(f"ground_scale={ground_scale!r}: must be > 0 (ground px per image px)")
        self.drift_frames = max(1, int(drift_frames))
        th, tw = self.texture.shape
        self.start = _finite_pair("start", start, "texture px") if start is not None else (tw / 2.0, th / 2.0)
        # BORDER_REFLECT_101 repeats the ground every 2 (n - 1) px
        self._periods = (2.0 * (tw - 1), 2.0 * (th - 1))
        # the largest ground px per image px render() accepts
        self._max_view = _MAX_VIEW_TEXTURES * max(tw, th)

    def truth(self, t: int) -> FlightTruth:
        """Ground truth of frame ``t`` (motion from frame ``t−1`` to ``t``)."""
        return FlightTruth(self.flow[0], self.flow[1], self.expansion_rate)

    def _camera(self, t: int) -> tuple[float, float, float]:
        """Ground position of the image centre and ground px per image px at frame t."""
        try:
            m = self.ground_scale * (1.0 + self.expansion_rate) ** (-t)
        except OverflowError:  # (a float power beyond 1e308 raises instead of giving inf)
            m = math.inf
        # Image flow +u means the ground moves right in the image: the camera moves left
        # over the ground. For a zoom flight the ground pixel under the centre stays put.
        if self.expansion_rate == 0.0:
            cx = self.start[0] - self.flow[0] * m * t
            cy = self.start[1] - self.flow[1] * m * t
        else:
            # integrate the centre's ground motion with the changing scale
            ks = np.arange(1, t + 1)
            ms = self.ground_scale * (1.0 + self.expansion_rate) ** (-ks.astype(np.float64))
            cx = self.start[0] - self.flow[0] * float(ms.sum())
            cy = self.start[1] - self.flow[1] * float(ms.sum())
        return cx, cy, m

    def view_problem(self, t: int) -> str | None:
        """Why frame ``t`` cannot be rendered (the message :meth:`render` raises), or None:
        its ground coordinates overflow, or its view is more than 256 texture sizes across.
        Cheap: nothing is drawn."""
        t = int(t)
        return self._view_problem(t, *self._camera(t))

    def _view_problem(self, t: int, cx: float, cy: float, m: float) -> str | None:
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(m)):
            return f"frame {t}: the camera's ground position ({cx:g}, {cy:g}) px or scale {m:g} overflows"
        if max(self.width, self.height) * m > self._max_view:
            th, tw = self.texture.shape
            return (f"frame {t}: {m:g} ground px per image px (expansion_rate={self.expansion_rate:g}): "
                    f"the view would be more than {_MAX_VIEW_TEXTURES} widths of the {tw}x{th} texture across")
        return None

    def render(self, t: int) -> np.ndarray:
        """Render frame ``t`` as a 2-D uint8 array of shape (height, width).

        Raises
        ------
        ValueError
            If the frame's ground coordinates overflow (a flight of astronomically many
            pixels) or its view is more than 256 texture sizes across (a zoom flight that
            has receded too far): OpenCV cannot render either in reasonable time.
        """
        t = int(t)
        cx, cy, m = self._camera(t)
        if problem := self._view_problem(t, cx, cy, m):
            raise ValueError(problem)
        period_x, period_y = self._periods
        # far flights: shift by whole periods (exact in floating point; same samples)
        if period_x > 0 and abs(cx) > _FOLD_PERIODS * period_x:
            cx = math.fmod(cx, period_x)
        if period_y > 0 and abs(cy) > _FOLD_PERIODS * period_y:
            cy = math.fmod(cy, period_y)
        s = self.supersample
        W, H = self.width * s, self.height * s
        # Affine map from supersampled output pixel centres to ground coordinates.
        step = m / s
        x0 = cx - (self.width / 2.0) * m + step / 2.0 - 0.5
        y0 = cy - (self.height / 2.0) * m + step / 2.0 - 0.5
        M = np.array([[step, 0.0, x0], [0.0, step, y0]], dtype=np.float64)
        fine = cv2.warpAffine(
            self.texture,
            M,
            (W, H),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REFLECT_101,
        )
        image = cv2.resize(fine, (self.width, self.height), interpolation=cv2.INTER_AREA)
        gain = 1.0 + self.exposure_drift * min(1.0, t / self.drift_frames)
        image = (image - 128.0) * self.contrast + 128.0
        if self.shade != 1.0:
            image[:, self.width // 2 :] *= self.shade
        return _sensor_frame(image * gain, self.noise_sigma, self.seed + t)


class RotatingCamera(_RenderedFrames):
    """A pinhole camera turning in place over a textured scene, with exact ground truth.

    The camera (focal length ``focal_length_px``, no lens distortion) turns about a fixed
    axis through its centre at a constant rate, chosen so that the image moves by ``flow``
    px/frame *at the image centre*. This is what an autopilot compares with its gyro: for
    a pure rotation the angular flow at the optical axis is the body rate. Away from the
    centre a pinhole image moves faster — along the flow by the factor ``1 + X²`` at
    normalised coordinate ``X = x / f`` — so a wide lens sees the same turn as faster
    motion at its edges. (A translation over flat ground, :class:`CameraFlight`, moves the
    whole image alike.) For a pure rotation the image transformation is the homography
    ``K R K⁻¹`` whatever the scene's depth; frame ``reference_frame`` shows the texture
    (reflected past its borders, as seen square-on) at one texture pixel per image pixel
    at the centre, and the camera is tilted by the turn's angle × ``t − reference_frame``
    from it at frame ``t``: put it in the middle of the frames you measure, so that they
    see the texture about as a translation flight does.

    Rendering, noise and ``seed`` are as in :class:`CameraFlight`: supersampled,
    area-averaged down, Gaussian noise of ``noise_sigma`` gray levels.

    Raises
    ------
    ValueError
        If a side is below :data:`MIN_SIDE` px, ``focal_length_px`` is not positive, a
        number is NaN or infinite, or the flow would turn the camera by 45° or more per
        frame (naming the parameter); :meth:`render` when a corner of the frame looks
        more than :attr:`MAX_RAY_TILT_DEG` away from the reference view's axis (towards
        its horizon, where the texture would be rendered mirrored).
    """

    #: Steepest ray (degrees from the reference view's axis) :meth:`render` accepts.
    MAX_RAY_TILT_DEG = 75.0

    def __init__(self, texture: str = "gravel", *, width: int = 320, height: int = 240,
                 focal_length_px: float = 320.0, flow: tuple[float, float] = (3.0, 0.0),
                 noise_sigma: float = 2.0, supersample: int = 4, seed: int = 0,
                 reference_frame: int = 0):
        _check_raster(width, height, supersample)
        self.focal_length_px = _finite("focal_length_px", focal_length_px)
        if self.focal_length_px <= 0.0:
            raise ValueError(f"focal_length_px={focal_length_px!r}: must be > 0")
        self.flow = _finite_pair("flow", flow, "px/frame")
        # the turn per frame that moves the centre by |flow|: f tan(angle) = |flow|
        self.angle_per_frame = math.atan(math.hypot(*self.flow) / self.focal_length_px)
        if self.angle_per_frame >= math.radians(45.0):
            raise ValueError(f"flow={flow}: turns the camera by 45 deg or more per frame at "
                             f"focal_length_px={focal_length_px:g}")
        self._init_raster(texture, width, height, supersample, noise_sigma, seed)
        self.reference_frame = int(reference_frame)
        # the centre's ray after one frame must point at the ray that showed the ground
        # now at the centre, i.e. towards (-u, -v, f): axis = z x (-u, -v, f)
        u, v = self.flow
        axis = np.array([v, -u, 0.0])
        norm = float(np.linalg.norm(axis))
        self._axis = axis / norm if norm > 0 else np.array([0.0, 1.0, 0.0])
        # the parts of the homography that do not turn: supersampled output pixel -> image
        # coordinates about the centre -> ray; turned ray -> the reference view's image ->
        # texture pixel (the texture's centre at the centre)
        s, f = self.supersample, self.focal_length_px
        th, tw = self.texture.shape
        to_image = np.array([[1.0 / s, 0.0, 0.5 / s - self.width / 2.0],
                             [0.0, 1.0 / s, 0.5 / s - self.height / 2.0], [0.0, 0.0, 1.0]])
        to_texture = np.array([[1.0, 0.0, tw / 2.0 - 0.5], [0.0, 1.0, th / 2.0 - 0.5], [0.0, 0.0, 1.0]])
        self._pixel_to_ray = np.diag([1.0 / f, 1.0 / f, 1.0]) @ to_image
        self._ray_to_texture = to_texture @ np.diag([f, f, 1.0])
        self._corner_rays = np.array([[x / f, y / f, 1.0] for x in (-self.width / 2.0, self.width / 2.0)
                                      for y in (-self.height / 2.0, self.height / 2.0)])

    def truth(self, t: int) -> FlightTruth:
        """Ground truth of frame ``t``: the image motion **at the centre** (px/frame); away
        from it a turn moves the image faster (see the class), unlike the translation
        flights' uniform ``flow_x, flow_y``."""
        return FlightTruth(self.flow[0], self.flow[1], 0.0)

    def render(self, t: int) -> np.ndarray:
        """Render frame ``t`` as a 2-D uint8 array of shape (height, width)."""
        R, _ = cv2.Rodrigues(self._axis * (self.angle_per_frame * (int(t) - self.reference_frame)))
        corners = self._corner_rays @ R.T
        tilt = np.degrees(np.arccos(corners[:, 2] / np.linalg.norm(corners, axis=1))).max()
        if tilt > self.MAX_RAY_TILT_DEG:
            raise ValueError(f"frame {t}: a corner looks {tilt:.0f} deg from the reference view's axis "
                             f"(more than {self.MAX_RAY_TILT_DEG:g}): the turn has gone too far from "
                             f"reference_frame={self.reference_frame}")
        M = self._ray_to_texture @ R @ self._pixel_to_ray
        size = (self.width * self.supersample, self.height * self.supersample)
        fine = cv2.warpPerspective(self.texture, M, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                   borderMode=cv2.BORDER_REFLECT_101)
        image = cv2.resize(fine, (self.width, self.height), interpolation=cv2.INTER_AREA)
        return _sensor_frame(image, self.noise_sigma, self.seed + int(t))
