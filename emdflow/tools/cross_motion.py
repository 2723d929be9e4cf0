"""Fast oblique flight: how the per-axis detectors see a flow's minor component.

The paper's detectors are one-dimensional: a vertical detector of scale ``k`` compares k×k
receptors ``k`` px apart along a column, frame after frame. A flow ``(U, V)`` with a large
``U`` moves the ground *across* that column while ``V`` moves it along: by the time the
pattern has moved ``k`` px down it has also moved sideways under the receptor. Over long
straight edges this does no harm (an edge looks the same wherever along it the receptor
sits), but over rough ground (gravel, grass) the receptor sees new texture, the
detections of the minor axis thin out and scatter over all scales and both signs, and the
summary reads the minor component low: the direction is pulled towards the major axis.

This tool measures it: flights with the minor component ``V`` (4 px/frame unless told) on
the vertical axis and a growing major component ``U`` on the horizontal one, over rough
and edge-like grounds. Per ground and ``U`` it prints the vertical axis's detections per
frame, the share of them in the two channels that bracket ``V`` with its sign, the share
with the wrong sign, what the summary reads (``U`` and ``V``, median over the frames) with
its median direction error and quality, and the ``V`` it reads from the horizontal (major) axis's
detections alone: how much of the reading the minor axis still carries::

    python -m emdflow.tools.cross_motion                      # extended model, ~30 s on 2 cores (OpenCL)
    python -m emdflow.tools.cross_motion --model paper --minor 3 --majors 0,6,12

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

DEFAULT_TEXTURES = ("gravel", "grass", "brick", "camera")
DEFAULT_MAJORS = (0.0, 4.0, 8.0, 12.0)
#: the flights' start positions: this far apart on the ground (px), one per flight
FLIGHT_SPACING_PX = 20.0


def bracketing_channels(speeds, minor: float) -> tuple[int, ...]:
    """Indices of the channels whose speeds bracket ``minor`` px/frame: the fastest one at
    or below it and the slowest one at or above it (one index when a channel has exactly
    that speed or ``minor`` lies outside the channels' range)."""
    speeds = [float(s) for s in speeds]
    below = [i for i, s in enumerate(speeds) if s <= minor]
    above = [i for i, s in enumerate(speeds) if s >= minor]
    picked = set()
    if below:
        picked.add(max(below, key=lambda i: speeds[i]))
    if above:
        picked.add(min(above, key=lambda i: speeds[i]))
    return tuple(sorted(picked))


def evaluate(*, model: str = "extended", textures=DEFAULT_TEXTURES, minor: float = 4.0,
             majors=DEFAULT_MAJORS, flights: int = 4, frames: int = 6, width: int = 320,
             height: int = 240, backend: str = "opencl", noise: float = 2.0) -> list[dict]:
    """One row per (ground, major component): flights of flow ``(major, minor)`` px/frame,
    ``flights`` of them per row (start positions :data:`FLIGHT_SPACING_PX` apart, the
    path centred on the photograph), ``frames`` ready frames each, sensor noise σ =
    ``noise`` gray levels. A row holds the vertical (minor) axis's detections per frame,
    the share of them in the :func:`bracketing_channels` of ``minor`` with its sign
    (``right``) and with the other sign (``wrong_sign``), the summary's median ``U``, ``V``
    and direction error (degrees; a quality-0 frame reads flow 0), its median quality
    (``quality``) and its median ``V``
    from the same frames with the vertical axis's detections taken out (``major_only_v``)."""
    import emdflow
    from emdflow.field import FlowField
    from emdflow.synthetic import CameraFlight, load_texture

    if model not in MODELS:
        raise ValueError(f"model={model!r}: expected one of {', '.join(MODELS)}")
    if not minor > 0:
        raise ValueError(f"minor={minor!r}: must be > 0 px/frame")
    if any(not (math.isfinite(u) and u >= 0) for u in majors):
        raise ValueError(f"majors={tuple(majors)!r}: must be >= 0 px/frame")
    if flights < 1 or frames < 1:
        raise ValueError(f"flights={flights!r}, frames={frames!r}: both must be at least 1")
    estimator = emdflow.FlowEstimator(width, height, backend=backend, **MODELS[model])
    params = estimator.params
    warm = params.history_frames
    n_codes = 2 * len(params.channels)
    bracket = bracketing_channels(params.speeds, minor)
    mid = (warm + frames - 1) / 2.0
    no_codes = np.zeros((height, width), np.int8)  # the summary reads the histogram only
    rows = []
    for texture in textures:
        th, tw = load_texture(texture).shape
        for major in majors:
            counts = np.zeros(n_codes)
            reads, errors, major_only, quality = [], [], [], []
            for i in range(flights):
                # the camera is over the photograph's centre (shifted per flight) mid-flight
                shift = FLIGHT_SPACING_PX * (i - (flights - 1) / 2.0)
                start = (tw / 2.0 + major * mid + shift, th / 2.0 + minor * mid - shift)
                flight = CameraFlight(texture, width=width, height=height, flow=(major, minor),
                                      noise_sigma=noise, seed=i, start=start)
                estimator.reset()
                for t in range(warm + frames):
                    field = estimator.update(flight.render(t))
                    if not field.ready:
                        continue
                    counts += field.histogram[1].sum(axis=-1)  # vertical axis, per code
                    s = emdflow.summarize(field)
                    u, v = (s.flow_x, s.flow_y) if s.quality > 0 else (0.0, 0.0)
                    reads.append((u, v))
                    quality.append(s.quality)
                    hist = field.histogram.copy()
                    hist[1] = 0
                    alone = emdflow.summarize(FlowField(no_codes, no_codes, field.stats, hist, params,
                                                        field.frame_index))
                    major_only.append(alone.flow_y if alone.quality > 0 else 0.0)
                    d = math.degrees(math.atan2(v, u) - math.atan2(minor, major))
                    errors.append(abs((d + 180.0) % 360.0 - 180.0))
            total = max(float(counts.sum()), 1.0)
            # codes are 2 · channel + sign (1: negative); the flights' minor component is > 0
            right = sum(counts[2 * c] for c in bracket)
            reads = np.asarray(reads)
            rows.append({"texture": texture, "major": float(major), "minor": float(minor),
                         "detections": float(counts.sum()) / len(errors),
                         "right": float(right) / total, "wrong_sign": float(counts[1::2].sum()) / total,
                         "read_u": float(np.median(reads[:, 0])), "read_v": float(np.median(reads[:, 1])),
                         "direction_error_deg": float(np.median(errors)), "quality": float(np.median(quality)),
                         "major_only_v": float(np.median(major_only))})
    return rows


def format_report(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    header = ("| ground | flow (U, V) px/frame | minor-axis detections per frame | in the channels of V "
              "| wrong sign | summary reads U | summary reads V | direction error | quality "
              "| V from the major axis alone |")
    lines = [header, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['texture']} | ({r['major']:g}, {r['minor']:g}) | {r['detections']:.0f} "
                     f"| {r['right'] * 100:.0f} % | {r['wrong_sign'] * 100:.0f} % | {r['read_u']:.2f} "
                     f"| {r['read_v']:.2f} | {r['direction_error_deg']:.1f}° | {r['quality']:.0f} "
                     f"| {r['major_only_v']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m emdflow.tools.cross_motion",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="extended", choices=tuple(MODELS))
    ap.add_argument("--textures", default=",".join(DEFAULT_TEXTURES), help="comma-separated grounds")
    ap.add_argument("--minor", type=float, default=4.0, help="the flow's vertical component, px/frame")
    ap.add_argument("--majors", type=lambda t: number_list(t, float), default=DEFAULT_MAJORS,
                    help="horizontal components, px/frame, comma-separated")
    ap.add_argument("--flights", type=int, default=4, help="flights per ground and component")
    ap.add_argument("--frames", type=int, default=6, help="measured frames per flight")
    ap.add_argument("--size", default="320x240", help="frame size WxH")
    ap.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    a = ap.parse_args(argv)
    from emdflow.tools.video_io import parse_size

    t0 = time.time()
    try:
        width, height = parse_size(a.size)
        rows = evaluate(model=a.model, textures=tuple(t for t in a.textures.split(",") if t),
                        minor=a.minor, majors=a.majors, flights=a.flights, frames=a.frames,
                        width=width, height=height, backend=a.backend)
    except ValueError as exc:
        print(f"cross_motion: {exc}", file=sys.stderr)
        return 2
    print(f"{a.model} model, {width}x{height}, noise sigma 2 (gray levels), {a.flights} flights x "
          f"{a.frames} frames per row ({time.time() - t0:.0f} s)")
    print(format_report(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
