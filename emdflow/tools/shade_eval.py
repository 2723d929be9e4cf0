"""Shadows: what one threshold for the whole frame does to a shaded part of the view.

A shadow over part of the view (the vehicle's own, a wall's, a tree's) lowers both the
brightness and the contrast there. The adaptive threshold follows the mean contrast of the
whole frame (``EngineParams.threshold_mode='adaptive'``), which the lit part sets, so the
shaded part loses most of its detections; the local threshold (``'local'``) follows each
tile's contrast. This tool flies translations with the right half of the view in shade
(:class:`emdflow.synthetic.CameraFlight` ``shade``: its light times ``--shade``), 320×240,
noise σ = 2, over four photographs in eight directions (22.5° off the axes), for each
threshold mode, and prints per speed:

* the density (share of pixels with a detection) in the lit and the shaded half, and
  their ratio;
* the left/right balance cue (:func:`emdflow.cues.looming_cues` ``balance_lr``), whose
  truth on a translation is 0: a shaded side read slower makes it negative, which a
  corridor-centring controller would take for a farther wall and steer towards;
* the summary's median relative error (a quality-0 frame counts as 100 %)::

    python -m emdflow.tools.shade_eval                       # ~10 s on 2 cores (OpenCL)
    python -m emdflow.tools.shade_eval --shade 0.5 --speeds 1,4 --modes adaptive,local

Everything but :func:`main` is a pure function of its arguments.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from emdflow.params import MODELS, THRESHOLD_MODES
from emdflow.tools import number_list, texture_names_problem

DEFAULT_TEXTURES = ("gravel", "brick", "grass", "camera")
DEFAULT_SPEEDS = (0.5, 1.0, 3.0, 7.0)
DEFAULT_MODES = ("adaptive", "local")
#: flow directions of the flights, degrees (x right, y down): off the detector axes
DIRECTIONS_DEG = tuple(22.5 + 45.0 * i for i in range(8))


def evaluate(*, model: str = "extended", modes=DEFAULT_MODES, speeds=DEFAULT_SPEEDS, textures=DEFAULT_TEXTURES,
             shade: float = 0.25, frames: int = 8, width: int = 320, height: int = 240,
             backend: str = "opencl") -> list[dict]:
    """One row per (threshold mode, speed): ``density_lit``, ``density_shaded`` (shares of
    pixels), ``balance_lr`` (mean), ``summary_error`` (median relative error, quality 0
    counted as 1) over ``frames`` frames after the history of each flight."""
    import emdflow
    from emdflow.cues import looming_cues
    from emdflow.synthetic import CameraFlight

    rows = []
    for mode in modes:
        options = {**MODELS[model], "threshold_mode": mode}
        for speed in speeds:
            lit, shaded, balance, errors = [], [], [], []
            for i, direction in enumerate(DIRECTIONS_DEG):
                a = math.radians(direction)
                flow = (speed * math.cos(a), speed * math.sin(a))
                est = emdflow.FlowEstimator(width, height, backend, **options)
                flight = CameraFlight(textures[i % len(textures)], width=width, height=height, flow=flow,
                                      noise_sigma=2.0, seed=i, shade=shade)
                for t in range(est.params.history_frames + frames):
                    field = est.update(flight.render(t))
                    if not field.ready:
                        continue
                    seen = np.isfinite(field.u) | np.isfinite(field.v)
                    lit.append(seen[:, : width // 2].mean())
                    shaded.append(seen[:, width // 2 :].mean())
                    balance.append(looming_cues(field).balance_lr)  # (NaN: no horizontal evidence)
                    s = emdflow.summarize(field)
                    errors.append(math.hypot(s.flow_x - flow[0], s.flow_y - flow[1]) / speed if s.quality else 1.0)
            rows.append({"mode": mode, "speed": speed, "density_lit": float(np.mean(lit)),
                         "density_shaded": float(np.mean(shaded)), "balance_lr": float(np.nanmean(balance)),
                         "summary_error": float(np.median(errors))})
    return rows


def format_report(rows: list[dict]) -> str:
    lines = ["| threshold | px/frame | density lit | density shaded | shaded / lit | balance_lr (truth 0) "
             "| summary error |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        ratio = r["density_shaded"] / r["density_lit"] if r["density_lit"] > 0 else float("nan")
        lines.append(f"| {r['mode']} | {r['speed']:g} | {100 * r['density_lit']:.1f} % | "
                     f"{100 * r['density_shaded']:.1f} % | {ratio:.2f} | {r['balance_lr']:+.3f} | "
                     f"{100 * r['summary_error']:.1f} % |")
    return "\n".join(lines)


_EXPECTED = {"--frames": "at least 1", "--shade": "a share of the light in (0, 1]",
             "--speeds": "positive px/frame"}


def _modes(text: str) -> tuple[str, ...]:
    modes = tuple(m for m in text.split(",") if m)
    bad = [m for m in modes if m not in THRESHOLD_MODES]
    if bad or not modes:
        raise argparse.ArgumentTypeError(f"{text!r}: expected threshold modes from {', '.join(THRESHOLD_MODES)}")
    return modes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m emdflow.tools.shade_eval", description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="extended", choices=tuple(MODELS))
    ap.add_argument("--modes", type=_modes, default=DEFAULT_MODES,
                    help="threshold modes, comma-separated (default: adaptive,local)")
    ap.add_argument("--speeds", type=lambda text: number_list(text, float), default=DEFAULT_SPEEDS,
                    help="px/frame, comma-separated")
    ap.add_argument("--textures", default=",".join(DEFAULT_TEXTURES), help="comma-separated grounds")
    ap.add_argument("--shade", type=float, default=0.25, help="light in the shaded right half, in (0, 1]")
    ap.add_argument("--frames", type=int, default=8, help="measured frames per flight")
    ap.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    a = ap.parse_args(argv)
    from emdflow.synthetic import load_texture

    textures = tuple(t for t in a.textures.split(",") if t)
    problem = texture_names_problem(textures, load_texture)
    if problem or not textures:
        print(f"shade_eval: --textures {a.textures!r}: {problem or 'name at least one ground'}", file=sys.stderr)
        return 2
    for option, bad in (("--frames", a.frames < 1), ("--shade", not 0 < a.shade <= 1),
                        ("--speeds", not all(math.isfinite(s) and s > 0 for s in a.speeds))):
        if bad:
            print(f"shade_eval: {option}: expected {_EXPECTED[option]}", file=sys.stderr)
            return 2
    t0 = time.time()
    rows = evaluate(model=a.model, modes=a.modes, speeds=a.speeds, textures=textures, shade=a.shade,
                    frames=a.frames, backend=a.backend)
    print(f"{a.model} model, 320x240, right half in shade (light x{a.shade:g}), noise sigma 2, "
          f"{len(DIRECTIONS_DEG)} directions over {', '.join(textures)}, {a.frames} frames each "
          f"({time.time() - t0:.0f} s)")
    print(format_report(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
