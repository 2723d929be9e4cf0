"""``synthetic:`` — a camera flight over a real photograph with known image motion.

URI options (comma separated ``key=value`` after ``synthetic:``; all optional):

``texture``  ground photograph: a name from :data:`emdflow.synthetic.TEXTURES` or an image
             file path (default ``gravel``);
``u``, ``v`` constant image flow of the ground, px/frame, x right / y down, each within
             ±100; giving either selects a straight flight;
``circle``   speed of a circular flight, px/frame, 0..100 (default 2.0; used when neither
             ``u`` nor ``v`` is given): the flow turns once per ``period``;
``period``   duration of one circle, s, above 0 and at most 3600 (default 4.0);
``noise``    sensor noise sigma, gray levels, 0..100 (default 2.0);
``seed``     noise seed, integer 0..2**31-1 (default 0);
``supersample`` rendering oversampling per axis, integer 1..16 (default 2).

Numbers must be finite and within these limits (``inf``, ``nan`` or ``period=1e7`` are
errors naming the option, which stop the daemon at start-up with exit code 2).

The frame rate and size come from the configuration (default 320×240 at 100 frames/s), the
timestamps are ``index / fps``, and the default focal length is the frame width in px.
A circular flight returns to its start after one period, so its frames are rendered once and
then replayed from a buffer: after the first circle the source costs nothing.
"""

from __future__ import annotations

import math

import numpy as np

from ..clock import host_us
from .base import Frame, FrameSource, Pacer, SourceError

__all__ = ["SyntheticSource", "SYNTHETIC_DEFAULTS"]

#: Defaults of the URI options (documented in the module docstring and the README).
SYNTHETIC_DEFAULTS = {
    "texture": "gravel",
    "u": None,
    "v": None,
    "circle": 2.0,
    "period": 4.0,
    "noise": 2.0,
    "seed": 0,
    "supersample": 2,
}
#: a circle's frames are kept only up to this many bytes in all (the 1000 frames of a
#: 10 s circle at 100 fps at 640×480, 4166 at 320×240); longer or larger circles are
#: rendered live (a frame count alone let a 4096×4096 circle keep up to 16.8 GB)
_MAX_CACHED_BYTES = 320_000_000
#: Accepted range of each numeric option: (minimum, maximum, minimum is exclusive). Beyond
#: these a flight is meaningless (flow far beyond what the engine resolves, noise beyond the
#: gray range), or a typo that must not become an hour-long loop or an unbounded render cost
#: (supersampling costs its square); inf and nan are refused.
OPTION_LIMITS = {
    "u": (-100, 100, False),
    "v": (-100, 100, False),
    "circle": (0, 100, False),
    "period": (0, 3600, True),
    "noise": (0, 100, False),
    "seed": (0, 2**31 - 1, False),
    "supersample": (1, 16, False),
}


def parse_options(text: str) -> dict:
    """Parse ``key=value,...`` into typed options; raise ValueError naming a bad key."""
    options = dict(SYNTHETIC_DEFAULTS)
    if not text:
        return options
    for item in text.split(","):
        if not item.strip():
            continue
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in SYNTHETIC_DEFAULTS:
            raise ValueError(
                f"synthetic option {item!r}: expected key=value with key one of "
                f"{', '.join(SYNTHETIC_DEFAULTS)}"
            )
        value = value.strip()
        if key == "texture":
            options[key] = value
            continue
        integer = key in ("seed", "supersample")
        try:
            number = int(value) if integer else float(value)
        except ValueError:
            kind = "an integer" if integer else "a number"
            raise ValueError(f"synthetic option {key}={value!r}: not {kind}") from None
        low, high, open_low = OPTION_LIMITS[key]
        if not math.isfinite(number):
            raise ValueError(f"synthetic option {key}={value}: must be a finite number in "
                             f"{'(' if open_low else '['}{low}, {high}]")
        if number < low or (open_low and number == low) or number > high:
            raise ValueError(f"synthetic option {key}={value}: must be {'>' if open_low else '>='} {low} "
                             f"and <= {high}")
        options[key] = number
    return options


class SyntheticSource(FrameSource):
    """Frames of a synthetic camera flight (see the module docstring for the options).

    Parameters
    ----------
    options : str
        The part of the URI after ``synthetic:``.
    width, height : int
        Frame size, px.
    fps : float
        Frame rate of the flight's clock, frames/s.
    realtime : bool
        Release frames at ``fps`` instead of as fast as they are rendered.
    """

    live = False

    def __init__(self, options: str = "", *, width: int = 320, height: int = 240,
                 fps: float = 100.0, realtime: bool = False):
        from emdflow.synthetic import CameraFlight, load_texture

        self.uri = f"synthetic:{options}"
        try:
            self.options = parse_options(options)
            load_texture(self.options["texture"])
        except ValueError as exc:
            raise SourceError(f"source {self.uri!r}: {exc}") from None
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.default_focal_length_px = float(self.width)
        self.realtime = bool(realtime)
        o = self.options
        self.straight = o["u"] is not None or o["v"] is not None
        common = dict(width=self.width, height=self.height, noise_sigma=o["noise"],
                      supersample=o["supersample"])
        if self.straight:
            self._flow = (o["u"] or 0.0, o["v"] or 0.0)
            self._flight = CameraFlight(o["texture"], flow=self._flow, seed=o["seed"], **common)
            self.loop_frames = 0
        else:
            self.loop_frames = max(3, int(round(o["period"] * self.fps)))
            self._flight_kwargs = dict(texture=o["texture"], flow=(0.0, 0.0), **common)
            th, tw = load_texture(o["texture"]).shape
            self._centre = (tw / 2.0, th / 2.0)
            cacheable = self.loop_frames * self.width * self.height <= _MAX_CACHED_BYTES
            self._cache: list[np.ndarray | None] | None = [None] * self.loop_frames if cacheable else None
        self._pacer = Pacer(self.fps) if realtime else None
        self._index = 0
        self._period_us = 1e6 / self.fps

    def truth(self, index: int) -> tuple[float, float]:
        """Image flow of the ground from frame ``index − 1`` to ``index``, px/frame (x, y)."""
        if self.straight:
            return self._flow
        speed = self.options["circle"]
        phase = 2.0 * math.pi * (index % self.loop_frames) / self.loop_frames
        return speed * math.cos(phase), speed * math.sin(phase)

    def _circle_position(self, k: int) -> tuple[float, float]:
        """Ground position (texture px) under the image centre at frame ``k`` of the loop.

        The camera moves against the image flow: the position is the start minus the flows
        of frames 0..k, summed in closed form (no per-frame table: a long period costs
        nothing). The flows of one period sum to zero, so the loop closes.
        """
        n, speed = self.loop_frames, self.options["circle"]
        half = math.pi / n  # half the turn per frame
        # sum_{j=0..k} (cos, sin)(2 pi j / n) = sin((k+1) half) / sin(half) * (cos, sin)(k half)
        amplitude = speed * math.sin((k + 1) * half) / math.sin(half)
        return (self._centre[0] - amplitude * math.cos(k * half),
                self._centre[1] - amplitude * math.sin(k * half))

    def _render(self, index: int) -> np.ndarray:
        from emdflow.synthetic import CameraFlight

        if self.straight:
            return self._flight.render(index)
        k = index % self.loop_frames
        if self._cache is not None and self._cache[k] is not None:
            return self._cache[k]
        cx, cy = self._circle_position(k)
        flight = CameraFlight(start=(float(cx), float(cy)), seed=self.options["seed"] + k,
                              **self._flight_kwargs)
        image = flight.render(0)
        image.setflags(write=False)  # shared by every loop
        if self._cache is not None:
            self._cache[k] = image
        return image

    def open(self) -> None:
        self._index = 0
        if self._pacer:
            self._pacer.restart()

    def pacing_wait_s(self) -> float:
        return self._pacer.wait_s(self._index) if self._pacer else 0.0

    def read(self) -> Frame | None:
        due_us = None
        if self._pacer:
            index, self.waited_us, due_us = self._pacer.next(self._index)
            self.missed_frames += index - self._index
            self._index = index
        image = self._render(self._index)
        # Paced: captured when due (like a camera); else when rendered.
        captured = due_us if due_us is not None else host_us()
        frame = Frame(image, int(round(self._index * self._period_us)), captured, self._index)
        self._index += 1
        return frame
