"""Wide lenses: how much faster a turn reads than a translation of the same centre flow.

An autopilot fuses the sensor's flow with its gyro on the assumption that a pure rotation
of the vehicle reads as the body rate: the angular flow *at the optical axis*. The summary
(:func:`emdflow.summarize`) fits one global flow to detections from the whole image. Over
flat ground a translation moves the whole image alike, but a turn moves a pinhole image
faster towards its edges (along the flow by ``1 + X²``, ``X`` the normalised distance from
the centre along the flow), so the global flow of a turn reads high, more so the wider the
lens: for detections spread evenly over a ``W`` px wide image the mean gain along x is
``1 + tan²(HFOV/2) / 3`` (1.02 at 30°, 1.11 at 60°, 1.18 at 73°, 1.33 at 90°). The
autopilot takes the excess for translation: at 1 rad/s of roll and a gain of 1.15, 0.15
rad/s of false flow, 0.3 m/s at 2 m.

This tool measures it: per horizontal field of view and ground texture it flies a
translation (:class:`emdflow.synthetic.CameraFlight`) and a pure turn of a distortion-free
pinhole camera (:class:`emdflow.synthetic.RotatingCamera`), both with the same flow at the
image centre, in four directions (right, down, and the two diagonals), and prints the
median speed the summary reads over the true centre speed for each, their ratio (the
lens's gain on turns as the summary sees it, over the four directions) and the even-spread
prediction averaged over the same directions, ``1 + ((g_x − 1) + (g_y − 1)) / 2``. The turn
is square-on to the texture in the middle of the measured frames
(``RotatingCamera(reference_frame=…)``), so its frames see the ground about as the
translation's do::

    python -m emdflow.tools.rotation_eval                 # extended model, ~7 s on 2 cores (OpenCL)
    python -m emdflow.tools.rotation_eval --model paper --fovs 40,73 --speed 5

A real lens with barrel distortion compresses its edges and reads turns less high than a
pinhole of the same field of view; fisheye lenses close to f·θ hardly at all.

Everything but :func:`main` is a pure function of its arguments.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from emdflow.params import MODELS
from emdflow.tools import number_list
from firmware_py.angular import focal_length_px_from_fov, turn_gain

DEFAULT_FOVS = (30.0, 45.0, 60.0, 73.0, 90.0)
DEFAULT_TEXTURES = ("gravel", "grass", "camera")
#: flow directions of the flights, degrees (x right, y down)
DIRECTIONS_DEG = (0.0, 90.0, 45.0, 135.0)


def even_spread_gain(fov_deg: float, width: int, height: int) -> float:
    """The even-spread pinhole gain of a turn (:func:`firmware_py.angular.turn_gain`: ``g_x``,
    ``g_y``) along a flow direction θ is ``1 + cos²θ (g_x − 1) + sin²θ (g_y − 1)``; its mean
    over :data:`DIRECTIONS_DEG`, for a frame of ``width`` × ``height`` px whose horizontal
    field of view is ``fov_deg``."""
    gx, gy = turn_gain(width=width, height=height,
                       focal_length_px=focal_length_px_from_fov(fov_deg=fov_deg, size_px=width))
    cos2 = [math.cos(math.radians(d)) ** 2 for d in DIRECTIONS_DEG]
    return 1.0 + float(np.mean([c * (gx - 1.0) + (1.0 - c) * (gy - 1.0) for c in cos2]))


def _read_speeds(frames, estimator, skip: int) -> list[float]:
    """Speeds (px/frame) the summary reads on the frames after ``skip``; quality 0 reads 0."""
    from emdflow import summarize

    estimator.reset()
    speeds = []
    for t, frame in enumerate(frames):
        field = estimator.update(frame)
        if t >= skip:
            s = summarize(field)
            speeds.append(s.speed if s.quality > 0 else 0.0)
    return speeds


def evaluate(*, model: str = "extended", fovs=DEFAULT_FOVS, textures=DEFAULT_TEXTURES,
             speed: float = 3.0, frames: int = 8, width: int = 320, height: int = 240,
             backend: str = "opencl", noise: float = 2.0, supersample: int = 2) -> list[dict]:
    """One row per (field of view, texture): the median speed read over the true centre
    speed for the translations and for the turns, over :data:`DIRECTIONS_DEG` and
    ``frames`` frames each after the detector's history, and the even-spread pinhole gain
    averaged over the directions."""
    import emdflow
    from emdflow.synthetic import CameraFlight, RotatingCamera

    if model not in MODELS:
        raise ValueError(f"model={model!r}: expected one of {', '.join(MODELS)}")
    if not speed > 0:
        raise ValueError(f"speed={speed!r}: must be > 0 px/frame")
    if frames < 1:
        raise ValueError(f"frames={frames!r}: must be at least 1")
    estimator = emdflow.FlowEstimator(width, height, backend=backend, **MODELS[model])
    skip = estimator.params.history_frames + 1
    flights = []  # (keywords of the flight) per direction, the same for every ground and lens
    for i, direction in enumerate(DIRECTIONS_DEG):
        flow = (speed * math.cos(math.radians(direction)), speed * math.sin(math.radians(direction)))
        flights.append({"width": width, "height": height, "flow": flow, "noise_sigma": noise,
                        "supersample": supersample, "seed": 1000 * i + 7})
    # translations read the same at every field of view: flown once per texture
    moved = {texture: [read for common in flights for read in
                       _read_speeds(CameraFlight(texture, **common).frames(skip + frames), estimator, skip)]
             for texture in textures}
    rows = []
    for fov in fovs:
        f = focal_length_px_from_fov(fov_deg=float(fov), size_px=width)
        pinhole = even_spread_gain(float(fov), width, height)
        for texture in textures:
            turned = []
            for common in flights:
                camera = RotatingCamera(texture, focal_length_px=f, reference_frame=skip + frames // 2, **common)
                turned += _read_speeds(camera.frames(skip + frames), estimator, skip)
            m, r = float(np.median(moved[texture])) / speed, float(np.median(turned)) / speed
            rows.append({"fov_deg": float(fov), "texture": texture, "translation": m, "rotation": r,
                         "ratio": r / m if m > 0 else math.nan, "pinhole": pinhole})
    return rows


def format_report(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    header = ("| HFOV | texture | translation read / true | turn read / true | turn / translation "
              "| even-spread pinhole gain, mean over the directions |")
    lines = [header, "|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['fov_deg']:g}° | {r['texture']} | {r['translation']:.3f} | {r['rotation']:.3f} "
                     f"| **{r['ratio']:.3f}** | {r['pinhole']:.3f} |")
    return "\n".join(lines)


def _fields_of_view(text: str) -> tuple[float, ...]:
    values = number_list(text, float)
    if not all(0.0 < v < 180.0 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: fields of view must be between 0 and 180 deg")
    return values


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m emdflow.tools.rotation_eval",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="extended", choices=tuple(MODELS))
    ap.add_argument("--fovs", type=_fields_of_view, default=DEFAULT_FOVS,
                    help="horizontal fields of view, degrees, comma-separated")
    ap.add_argument("--textures", default=",".join(DEFAULT_TEXTURES), help="comma-separated grounds")
    ap.add_argument("--speed", type=float, default=3.0, help="flow at the image centre, px/frame")
    ap.add_argument("--frames", type=int, default=8, help="measured frames per flight")
    ap.add_argument("--size", default="320x240", help="frame size WxH")
    ap.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    a = ap.parse_args(argv)
    from emdflow.tools.video_io import parse_size

    t0 = time.time()
    textures = tuple(t for t in a.textures.split(",") if t)
    if not textures:  # (an empty table with exit 0 otherwise)
        print(f"rotation_eval: --textures {a.textures!r}: name at least one ground", file=sys.stderr)
        return 2
    try:
        width, height = parse_size(a.size)
        rows = evaluate(model=a.model, fovs=a.fovs, textures=textures,
                        speed=a.speed, frames=a.frames, width=width, height=height, backend=a.backend)
    except ValueError as exc:
        print(f"rotation_eval: {exc}", file=sys.stderr)
        return 2
    print(f"{a.model} model, {width}x{height}, {a.speed:g} px/frame at the image centre, noise sigma 2 (gray levels), "
          f"directions {', '.join(f'{d:g}' for d in DIRECTIONS_DEG)} deg ({time.time() - t0:.0f} s)")
    print(format_report(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
