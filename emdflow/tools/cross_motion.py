"""Fast oblique flight: how the per-axis detectors see a flow's minor component.

The paper's detectors are one-dimensional: a vertical detector of scale ``k`` compares k×k
receptors ``k`` px apart along a column, frame after frame. A flow ``(U, V)`` with a large
``U`` moves the ground *across* that column while ``V`` moves it along: by the time the
pattern has moved ``k`` px down it has also moved sideways under the receptor. Long
straight edges look the same wherever along them the receptor sits, but granular ground
(gravel, grass) does not: the receptor sees new grains, the detections of the minor axis
thin out and scatter over all scales and both signs.

This tool measures it: flights with the minor component ``V`` (4 px/frame unless told)
on the vertical axis and a growing major component ``U`` on the horizontal one. Per
ground and ``U`` it prints

- the vertical axis's detections per frame (as the summary samples them: the evidence
  rows, ``EngineParams.evidence_row_step``, with a nonzero gradient), the share of them in
  the two channels that bracket ``V`` with its sign, and the share with the wrong sign;
- what the summary reads: ``U`` and ``V`` (medians over the frames), the median direction
  error and quality, and the share of frames with quality 0 (they read flow 0 and count
  as 180° off, as in ``calibrate_summary evaluate``);
- the ``V`` it reads from the horizontal axis's detections alone (the vertical and the
  diagonal axes' taken out of the histogram): how much of the reading the others carry. At
  ``U`` = 0 the horizontal axis is not the major one; its reading is still printed, as the
  baseline of what that axis says about ``V`` alone.

Each row flies ``flights`` flights at start positions spread over the room the photograph
leaves around their path, so every view stays inside it::

    python -m emdflow.tools.cross_motion                      # extended model, ~5 s on 2 cores (OpenCL)
    python -m emdflow.tools.cross_motion --model paper --minor 3 --majors 0,6,12 --flights 16

Everything but :func:`main` is a pure function of its arguments.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from emdflow.params import MODELS
from emdflow.tools import ToolError, check_positive, frame_size_problem, make_estimator, number_list

DEFAULT_TEXTURES = ("gravel", "grass", "brick", "camera")
DEFAULT_MAJORS = (0.0, 4.0, 8.0, 12.0)


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


def _starts(texture_shape, width: int, height: int, flow, first: int, last: int, flights: int):
    """Camera positions at frame 0 (ground px) of ``flights`` flights whose views from frame
    ``first`` to ``last`` stay inside the photograph: the path's midpoint at the centre,
    shifted along the diagonal of the room the photograph leaves. ValueError when the path
    does not fit."""
    th, tw = texture_shape
    span = last - first
    room = (tw - width - abs(flow[0]) * span - 2.0, th - height - abs(flow[1]) * span - 2.0)
    if min(room) < 0.0:
        raise ValueError(f"flow ({flow[0]:g}, {flow[1]:g}) px/frame: the {width}x{height} view moves past "
                         f"the {tw}x{th} px ground within the measured frames (fewer frames or a slower flow)")
    mid = (first + last) / 2.0
    # the ground moves by +flow in the image: the camera by -flow on the ground
    centre = (tw / 2.0 + flow[0] * mid, th / 2.0 + flow[1] * mid)
    shifts = np.linspace(-0.5, 0.5, flights) if flights > 1 else np.zeros(1)
    return [(centre[0] + room[0] * a, centre[1] + room[1] * a) for a in shifts]


def evaluate(*, model: str = "extended", textures=DEFAULT_TEXTURES, minor: float = 4.0,
             majors=DEFAULT_MAJORS, flights: int = 4, frames: int = 6, width: int = 320,
             height: int = 240, backend: str = "opencl", noise: float = 2.0, estimator=None) -> list[dict]:
    """One row per (ground, major component): flights of flow ``(major, minor)`` px/frame,
    ``flights`` of them per row (noise seeds 0, 1, …; start positions from
    :func:`_starts`), ``frames`` ready frames each, sensor noise σ = ``noise`` gray levels.

    A row holds the vertical (minor) axis's sampled detections per frame (``detections``),
    the share of them in the :func:`bracketing_channels` of ``minor`` with its sign
    (``right``) and with the other sign (``wrong_sign``; both NaN without detections), the
    summary's median ``U`` and ``V`` (``read_u``, ``read_v``; a quality-0 frame reads 0),
    median direction error (``direction_error_deg``; a quality-0 frame counts 180°),
    median quality, share of quality-0 frames (``blind``) and median ``V`` from the same
    frames with the vertical and diagonal axes' detections taken out (``major_only_v``).
    ``estimator``: a :class:`emdflow.FlowEstimator` of ``width`` × ``height`` to use
    instead of one made from ``model`` and ``backend``."""
    import emdflow
    from emdflow.field import FlowField
    from emdflow.tools.calibrate_summary import _frame_error
    from emdflow.synthetic import CameraFlight, load_texture

    if model not in MODELS:
        raise ValueError(f"model={model!r}: expected one of {', '.join(MODELS)}")
    if not (math.isfinite(minor) and minor > 0):
        raise ValueError(f"minor={minor!r}: must be a finite number > 0 (px/frame)")
    if not majors or any(not (math.isfinite(u) and u >= 0) for u in majors):
        raise ValueError(f"majors={tuple(majors)!r}: must be finite numbers >= 0 (px/frame)")
    if not textures:
        raise ValueError("textures: at least one ground is needed")
    if flights < 1 or frames < 1:
        raise ValueError(f"flights={flights!r}, frames={frames!r}: both must be at least 1")
    if estimator is None:
        estimator = emdflow.FlowEstimator(width, height, backend=backend, **MODELS[model])
    params = estimator.params
    warm = params.history_frames
    bracket = bracketing_channels(params.speeds, minor)
    no_codes = np.zeros((height, width), np.int8)  # the summary reads the histogram only
    rows = []
    for texture in textures:
        shape = load_texture(texture).shape
        for major in majors:
            flow = (float(major), float(minor))
            # the frames the one-frame templates see, as calibrate_summary's evaluation
            starts = _starts(shape, width, height, flow, max(0, warm - 3), warm + frames - 1, flights)
            counts = np.zeros(2 * len(params.channels))
            reads, errors, quality, major_only = [], [], [], []
            for seed, start in enumerate(starts):
                flight = CameraFlight(texture, width=width, height=height, flow=flow,
                                      noise_sigma=noise, seed=seed, start=start)
                estimator.reset()
                for t in range(warm + frames):
                    field = estimator.update(flight.render(t))
                    if not field.ready:
                        continue
                    counts += field.histogram[1].sum(axis=-1)  # vertical axis, per code
                    s = emdflow.summarize(field)
                    reads.append((s.flow_x, s.flow_y) if s.quality > 0 else (0.0, 0.0))
                    errors.append(_frame_error(s, *flow)[1])  # quality 0: 180°
                    quality.append(s.quality)
                    hist = field.histogram.copy()
                    hist[1:] = 0  # (and the diagonals, with diagonal evidence)
                    alone = emdflow.summarize(FlowField(
                        no_codes, no_codes, field.stats, hist, params, field.frame_index,
                        positions=field.positions, exposure_step=field.exposure_step))
                    major_only.append(alone.flow_y if alone.quality > 0 else 0.0)
            total = float(counts.sum())
            # codes are 2 · channel + sign (1: negative); the minor component is > 0
            right = sum(counts[2 * c] for c in bracket) / total if total else math.nan
            wrong = float(counts[1::2].sum()) / total if total else math.nan
            reads = np.asarray(reads)
            rows.append({"texture": texture, "major": flow[0], "minor": flow[1],
                         "detections": total / len(errors), "right": float(right), "wrong_sign": wrong,
                         "read_u": float(np.median(reads[:, 0])), "read_v": float(np.median(reads[:, 1])),
                         "direction_error_deg": float(np.median(errors)),
                         "quality": float(np.median(quality)),
                         "blind": float(np.mean(np.asarray(quality) == 0)),
                         "major_only_v": float(np.median(major_only))})
    return rows


def format_report(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    header = ("| ground | flow (U, V) px/frame | vertical-axis detections per frame | in the channels of V "
              "| wrong sign | summary reads U | summary reads V | direction error | quality | quality 0 "
              "| V from the horizontal axis alone |")
    lines = [header, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['texture']} | ({r['major']:g}, {r['minor']:g}) | {r['detections']:.0f} "
                     f"| {r['right'] * 100:.0f} % | {r['wrong_sign'] * 100:.0f} % | {r['read_u']:.2f} "
                     f"| {r['read_v']:.2f} | {r['direction_error_deg']:.1f}° | {r['quality']:.0f} "
                     f"| {r['blind'] * 100:.0f} % | {r['major_only_v']:.2f} |")
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
    ap.add_argument("--noise", type=float, default=2.0, help="sensor noise, standard deviation in gray levels")
    ap.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    a = ap.parse_args(argv)
    from emdflow.tools.video_io import parse_size

    t0 = time.time()
    try:
        textures = tuple(t for t in a.textures.split(",") if t)
        if not textures:
            raise ToolError(f"--textures {a.textures!r}: name at least one ground")
        check_positive("--minor", a.minor, "px/frame")
        if any(not (math.isfinite(u) and u >= 0) for u in a.majors):
            majors = ",".join(f"{u:g}" for u in a.majors)
            raise ToolError(f"--majors {majors}: must be finite numbers >= 0 (px/frame)")
        if a.flights < 1 or a.frames < 1:
            raise ToolError(f"--flights {a.flights} --frames {a.frames}: both must be at least 1")
        if not (math.isfinite(a.noise) and a.noise >= 0):
            raise ToolError(f"--noise {a.noise:g}: must be a finite number >= 0 (gray levels)")
        try:
            width, height = parse_size(a.size)
        except ValueError as exc:
            raise ToolError(f"--size: {exc}") from None
        problem = frame_size_problem(width, height, dis=False)
        if problem:
            raise ToolError(f"--size {a.size}: {problem}")
        estimator = make_estimator(argparse.Namespace(model=a.model, backend=a.backend), width, height)
        rows = evaluate(model=a.model, textures=textures, minor=a.minor, majors=a.majors,
                        flights=a.flights, frames=a.frames, width=width, height=height,
                        noise=a.noise, estimator=estimator)
    except ToolError as exc:
        print(f"cross_motion: {exc}", file=sys.stderr)
        return exc.code
    except ValueError as exc:
        print(f"cross_motion: {exc}", file=sys.stderr)
        return 2
    print(f"{a.model} model, {width}x{height}, noise sigma {a.noise:g} (gray levels), {a.flights} flights x "
          f"{a.frames} frames per row ({time.time() - t0:.0f} s)")
    print(format_report(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
