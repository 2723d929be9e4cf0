"""Zoom flights: measure, and calibrate, the expansion-rate cue of :mod:`emdflow.cues`.

Measure (default): the camera flies towards (or away from) a textured plane with a known
expansion rate ``r`` (``CameraFlight(expansion_rate=r)``, 320×240, noise σ = 2,
supersample 2), without and with a translation of (2, −1) px/frame, over six photographs
the calibration never saw (gravel, brick, grass, camera, coffee, astronaut), at rates
0.002, 0.005, 0.01 and 0.02 per frame, for the paper's model and the extended one; 6
flights per cell, each from its own random start, and the 8 frames after the detector's
history is full are measured. Printed per model and translation: the median of measured /
true rate per texture × rate for :func:`emdflow.cues.looming_cues` and, in brackets, for
the former uncalibrated line fit (:func:`emdflow.cues.slope_expansion_rate`), then the
median relative error over all frames (a frame without a cue counts as 100 %) and the
time per ``looming_cues`` call::

    python -m emdflow.tools.zoom_eval                      # ~20 s on 2 cores (OpenCL)
    python -m emdflow.tools.zoom_eval --backend numpy      # the same numbers, much slower
    python -m emdflow.tools.zoom_eval --models extended --rates 0.005,-0.01 --textures gravel

Calibrate: zoom flights (approaching and receding, 40 % without translation) over other
photographs measure, per detector model, the mean detection score and the detection rate
as functions of the local flow along and across the detector's axis; ``--write`` stores
the tables in ``emdflow/cues_calibration.npz`` (the committed tables are its output,
rounded to 4 significant digits; ~5 minutes on 2 cores)::

    python -m emdflow.tools.zoom_eval calibrate --write

Everything but :func:`main` is a pure function of its arguments.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from emdflow.params import MODELS
from emdflow.tools import interp_weights, number_list, texture_names_problem

__all__ = [
    "CALIBRATION_TEXTURES",
    "DEFAULT_RATES",
    "DEFAULT_TRANSLATIONS",
    "EVALUATION_TEXTURES",
    "calibrate",
    "evaluate",
    "format_calibration",
    "format_report",
    "main",
    "texture_source",
    "write_calibration",
]

#: Photographs the measurement flies over (none of them is used by the calibration).
EVALUATION_TEXTURES = ("gravel", "brick", "grass", "camera", "coffee", "astronaut")
#: Photographs of the calibration: scikit-image's bundled ``moon``, ``rocket`` and the
#: files ``ihc.png``, ``motorcycle_left.png``, ``chelsea.png``, ``coins.png`` of its data
#: folder (the small last two seen at 0.6 texture px per image px).
CALIBRATION_TEXTURES = ("moon", "rocket", "ihc", "motorcycle_left", "chelsea", "coins")
_SMALL_TEXTURES = {"chelsea": 0.6, "coins": 0.6}
DEFAULT_RATES = (0.002, 0.005, 0.01, 0.02)
#: (u, v) px/frame: a pure zoom and a zoom while drifting.
DEFAULT_TRANSLATIONS = ((0.0, 0.0), (2.0, -1.0))


def texture_source(name: str) -> str:
    """A texture for :class:`~emdflow.synthetic.CameraFlight`: any name it knows (a bundled
    photograph, an image file, a synthetic ``fractal-…``, ``lines-…`` or ``cells-…``
    ground), else the file of that name in scikit-image's data folder (e.g. ``ihc`` →
    ``.../ihc.png``)."""
    from emdflow.synthetic import load_texture

    try:
        load_texture(name)
        return name
    except ValueError:
        pass
    import skimage

    folder = Path(skimage.__file__).parent / "data"
    for ext in (".png", ".jpg"):
        if (folder / (name + ext)).is_file():
            return str(folder / (name + ext))
    raise ValueError(f"texture {name!r}: not bundled and not in {folder}")


def _estimator(model: str, backend: str, width: int, height: int):
    from emdflow import FlowEstimator

    return FlowEstimator(width, height, backend=backend, **MODELS[model])


# ---------------------------------------------------------------------------------------
# Measurement
# ---------------------------------------------------------------------------------------
#: the flights' frame size and supersampling (px)
FLIGHT_WIDTH, FLIGHT_HEIGHT, FLIGHT_SUPERSAMPLE = 320, 240, 2


def evaluate(models=("paper", "extended"), textures=EVALUATION_TEXTURES, rates=DEFAULT_RATES,
             translations=DEFAULT_TRANSLATIONS, frames: int = 8, flights: int = 6,
             backend: str = "opencl", seed: int = 1, width: int = FLIGHT_WIDTH, height: int = FLIGHT_HEIGHT,
             progress=None) -> dict:
    """Fly every model × translation × texture × rate ``flights`` times (each from its own
    random start on the photograph) and measure ``frames`` ready frames per flight.

    Returns ``{(model, (u, v), texture, rate): {"new": [...], "old": [...]}}`` with the
    measured rates (NaN where the cue gave nothing) and ``"_times"``: the seconds per
    ``looming_cues`` call.
    """
    from emdflow.cues import looming_cues, slope_expansion_rate
    from emdflow.synthetic import CameraFlight, load_texture

    out: dict = {"_times": []}
    rng = np.random.default_rng(seed)
    for model in models:
        est = _estimator(model, backend, width, height)
        total = est.params.history_frames + frames
        for uv in translations:
            for texture in textures:
                th, tw = load_texture(texture_source(texture)).shape
                for rate in rates:
                    cell = out.setdefault((model, tuple(uv), texture, rate), {"new": [], "old": []})
                    for _ in range(flights):
                        start = (float(rng.uniform(0.4, 0.6)) * tw, float(rng.uniform(0.4, 0.6)) * th)
                        flight = CameraFlight(texture_source(texture), width=width, height=height,
                                              flow=tuple(uv), expansion_rate=rate, noise_sigma=2.0,
                                              supersample=FLIGHT_SUPERSAMPLE, seed=int(rng.integers(1 << 30)),
                                              start=start)
                        est.reset()
                        for t in range(total):
                            field = est.update(flight.render(t))
                            if not field.ready:
                                continue
                            t0 = time.perf_counter()
                            cues = looming_cues(field)
                            out["_times"].append(time.perf_counter() - t0)
                            cell["new"].append(cues.expansion_rate if cues.detections else math.nan)
                            old = slope_expansion_rate(field)
                            cell["old"].append(math.nan if old is None else old)
                    if progress:
                        progress(model, uv, texture, rate)
    return out


def _ratio(values, rate) -> float:
    """Median measured / true rate over the frames with a cue (NaN when none had one)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return float(np.median(v) / rate) if v.size else math.nan


def _errors(values, rate) -> np.ndarray:
    """Relative error per frame; a frame without a cue counts as 1 (100 %)."""
    v = np.asarray(values, np.float64)
    return np.where(np.isfinite(v), np.abs(v / rate - 1.0), 1.0)


def format_report(results: dict) -> str:
    """Tables of median measured / true rate (new, and the old line fit in brackets) per
    model and translation, texture × rate, and the median relative errors."""
    keys = [k for k in results if k != "_times"]
    models = list(dict.fromkeys(k[0] for k in keys))
    lines = []
    overall = {"new": [], "old": []}
    for model in models:
        per_model = {"new": [], "old": []}
        for uv in dict.fromkeys(k[1] for k in keys if k[0] == model):
            sub = [k for k in keys if k[0] == model and k[1] == uv]
            textures = list(dict.fromkeys(k[2] for k in sub))
            rates = list(dict.fromkeys(k[3] for k in sub))
            motion = "zoom only" if uv == (0.0, 0.0) else f"zoom + translation ({uv[0]:g}, {uv[1]:g}) px/frame"
            lines.append(f"{model} model, {motion}: median measured / true rate "
                         "(in brackets: the former line fit)")
            lines.append("| texture | " + " | ".join(f"r = {r:g}" for r in rates) + " |")
            lines.append("|---|" + "---:|" * len(rates))
            errs = {"new": [], "old": []}
            for texture in textures:
                cells = []
                for rate in rates:
                    c = results[(model, uv, texture, rate)]
                    cells.append(f"{_ratio(c['new'], rate):.2f} ({_ratio(c['old'], rate):.2f})")
                    for which in ("new", "old"):
                        errs[which].append(_errors(c[which], rate))
                lines.append(f"| {texture} | " + " | ".join(cells) + " |")
            e_new, e_old = (np.concatenate(errs[w]) for w in ("new", "old"))
            lines.append(f"median relative error: {100 * np.median(e_new):.1f} % "
                         f"(line fit {100 * np.median(e_old):.1f} %), frames within 15 %: "
                         f"{100 * np.mean(e_new <= 0.15):.0f} % ({100 * np.mean(e_old <= 0.15):.0f} %)")
            lines.append("")
            for w in ("new", "old"):
                per_model[w].append(e_new if w == "new" else e_old)
        pm_new, pm_old = (np.concatenate(per_model[w]) for w in ("new", "old"))
        overall["new"].append(pm_new)
        overall["old"].append(pm_old)
        lines.append(f"{model} model, all flights: median relative error {100 * np.median(pm_new):.1f} % "
                     f"(line fit {100 * np.median(pm_old):.1f} %)")
        lines.append("")
    o_new, o_old = (np.concatenate(overall[w]) for w in ("new", "old"))
    lines.append(f"overall median relative error: {100 * np.median(o_new):.1f} % "
                 f"(line fit {100 * np.median(o_old):.1f} %), {o_new.size} frames")
    times = results.get("_times") or [math.nan]
    lines.append(f"looming_cues: median {1e3 * np.median(times):.3f} ms, "
                 f"99th percentile {1e3 * np.percentile(times, 99):.3f} ms per call")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------
# Calibration
# ---------------------------------------------------------------------------------------
class _Accumulator:
    """Soft-binned sums on the (|axial|, |cross|) flow grid of :mod:`emdflow.cues`."""

    def __init__(self):
        from emdflow.cues import AXIAL_NODES, CROSS_NODES

        self.a_nodes = np.asarray(AXIAL_NODES)
        self.o_nodes = np.asarray(CROSS_NODES)
        shape = (self.a_nodes.size, self.o_nodes.size)
        self.count = np.zeros(shape)  # detections
        self.score = np.zeros(shape)  # their scores, sign taken relative to the axial flow
        self.pixels = np.zeros(shape)  # pixels × textured share of the frame

    def add(self, target, axial, cross, weight):
        i, fi = interp_weights(np.abs(axial), self.a_nodes)
        j, fj = interp_weights(np.abs(cross), self.o_nodes)
        for ii, wi in ((i, 1.0 - fi), (i + 1, fi)):
            for jj, wj in ((j, 1.0 - fj), (j + 1, fj)):
                np.add.at(target, (ii, jj), wi * wj * weight)


#: Cells of the tables with fewer (soft-binned) detections than this are filled in from
#: their measured neighbours.
MIN_CELL_COUNT = 50.0


def _fill(table: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``table`` with its invalid cells replaced, ring by ring, by the mean of their valid
    4-neighbours."""
    t = np.where(valid, table, 0.0)
    valid = valid.copy()
    while not valid.all():
        total = np.zeros_like(t)
        n = np.zeros_like(t)
        for axis in (0, 1):
            for shift in (1, -1):
                total += np.roll(np.where(valid, t, 0.0), shift, axis=axis) * _edge(t.shape, axis, shift)
                n += np.roll(valid, shift, axis=axis) * _edge(t.shape, axis, shift)
        grow = ~valid & (n > 0)
        if not grow.any():
            break
        t[grow] = total[grow] / n[grow]
        valid |= grow
    return t


def _edge(shape, axis: int, shift: int) -> np.ndarray:
    """1 where ``np.roll(.., shift, axis)`` brings a real neighbour (no wrap-around)."""
    m = np.ones(shape)
    index = [slice(None)] * 2
    index[axis] = 0 if shift == 1 else -1
    m[tuple(index)] = 0.0
    return m


def calibrate(model: str, flights: int = 2400, seed: int = 20240610, backend: str = "opencl",
              width: int = 320, height: int = 240, textures=CALIBRATION_TEXTURES,
              progress=None) -> dict:
    """Measure the response and rate tables of :mod:`emdflow.cues` for ``model``.

    Each flight draws a texture (in turn), an expansion rate log-uniform in 0.0015–0.03
    per frame (approaching 75 %, receding 25 %), a translation (none in 40 % of the
    flights, else log-uniform 0.2–5 px/frame in a random direction), a contrast (1 or
    0.6) and a start near the photograph's centre; 4 ready frames per flight. Every
    detection on every second row adds its score (the channel speed clipped at
    ``SCORE_CLIP``, signed relative to the local axial flow) and a count at its local flow
    ``(U + r·X, V + r·Y)``; every pixel of those rows adds the frame's textured share to
    the pixel count. Response = score / count, rate = count / pixels (scaled to a maximum
    of 1)."""
    from emdflow.cues import SCORE_CLIP
    from emdflow.synthetic import CameraFlight, load_texture

    rng = np.random.default_rng(seed)
    est = _estimator(model, backend, width, height)
    params = est.params
    speeds = np.minimum(np.asarray(params.speeds, np.float64), SCORE_CLIP)
    code_score = np.zeros(2 * len(speeds) + 1)  # indexed by the int8 code: ±(c + 1)
    for c, s in enumerate(speeds):
        code_score[c + 1] = s
        code_score[-(c + 1)] = -s
    acc = _Accumulator()
    ys, xs = np.mgrid[0:height:2, 0:width]
    X = xs - (width - 1) / 2.0
    Y = ys - (height - 1) / 2.0
    total = params.history_frames + 4
    for k in range(flights):
        texture = textures[k % len(textures)]
        source = texture_source(texture)
        th, tw = load_texture(source).shape
        r = math.exp(rng.uniform(math.log(0.0015), math.log(0.03)))
        r = r if rng.uniform() < 0.75 else -r
        if rng.uniform() < 0.4:
            u = v = 0.0
        else:
            s = math.exp(rng.uniform(math.log(0.2), math.log(5.0)))
            a = rng.uniform(0.0, 2.0 * math.pi)
            u, v = s * math.cos(a), s * math.sin(a)
        start = (float(rng.uniform(0.4, 0.6)) * tw, float(rng.uniform(0.4, 0.6)) * th)
        flight = CameraFlight(source, width=width, height=height, flow=(u, v), expansion_rate=r,
                              noise_sigma=2.0, supersample=2, seed=int(rng.integers(1 << 30)),
                              start=start, contrast=float(rng.choice([1.0, 1.0, 0.6])),
                              ground_scale=_SMALL_TEXTURES.get(texture, 1.0))
        est.reset()
        fx = u + r * X
        fy = v + r * Y
        textured = 0.0  # the frames' textured shares: the pixels' flows are the flight's
        for t in range(total):
            field = est.update(flight.render(t))
            if not field.ready:
                continue
            textured += field.textured_fraction
            for axial, cross, code in ((fx, fy, field.u_code), (fy, fx, field.v_code)):
                c = code[0::2].astype(np.int64)
                hit = c != 0
                a, o = axial[hit], cross[hit]
                score = code_score[c[hit]] * np.where(a < 0.0, -1.0, 1.0)
                acc.add(acc.count, a, o, 1.0)
                acc.add(acc.score, a, o, score)
        for axial, cross in ((fx, fy), (fy, fx)):
            acc.add(acc.pixels, axial.ravel(), cross.ravel(), textured)
        if progress and (k + 1) % 100 == 0:
            progress(k + 1, flights)
    response = acc.score / np.maximum(acc.count, 1e-9)
    rate = acc.count / np.maximum(acc.pixels, 1e-9)
    # flows the flights (almost) never had: the values of the nearest measured cells
    valid = (acc.count >= MIN_CELL_COUNT) & (acc.pixels > 0)
    response = _fill(response, valid)
    rate = _fill(rate, valid)
    response[0, :] = 0.0
    rate /= max(rate.max(), 1e-12)
    return {
        "channels": tuple(tuple(int(x) for x in ch) for ch in params.channels),
        "threshold_mode": params.threshold_mode,
        "flights": flights,
        "seed": seed,
        "response": response,
        "rate": rate,
    }


def format_calibration(tables: dict) -> str:
    """The tables ``{model: calibrate(model)}`` as text (what ``calibrate`` prints without
    ``--write``)."""
    out = []
    with np.printoptions(precision=4, suppress=True, linewidth=120):
        for model, t in tables.items():
            out.append(f"{model}: channels {t['channels']}, threshold {t['threshold_mode']}, "
                       f"{t['flights']} flights, seed {t['seed']}")
            for name in ("response", "rate"):
                out.append(f"  {name}[|axial| node, |cross| node]:")
                out.append(str(np.asarray(t[name])))
    return "\n".join(out)


def write_calibration(tables: dict, path: Path | None = None) -> Path:
    """Store ``{model: calibrate(model)}`` as the expansion cue's tables (default
    ``emdflow/cues_calibration.npz``, which :func:`emdflow.cues.load_calibration` reads)."""
    from emdflow.cues import CALIBRATION_FIELDS, CALIBRATION_FILE

    path = Path(path) if path else CALIBRATION_FILE
    arrays = {}
    for model, t in tables.items():
        for name in CALIBRATION_FIELDS:
            value = t[name]
            arrays[f"{model}.{name}"] = (np.asarray(value, np.int64) if name in ("channels", "flights", "seed")
                                         else np.asarray(value) if name == "threshold_mode"
                                         else np.asarray(value, np.float64))
    np.savez_compressed(path, **arrays)
    return path


# ---------------------------------------------------------------------------------------
def _translations(text: str) -> tuple:
    """argparse type: ``u,v`` px/frame pairs separated by ``;``."""
    pairs = tuple(number_list(item, float) for item in text.split(";") if item.strip())
    if not pairs or any(len(p) != 2 for p in pairs):
        raise argparse.ArgumentTypeError(f"{text!r}: expected u,v pairs separated by ';'")
    return pairs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m emdflow.tools.zoom_eval",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("command", nargs="?", default="evaluate", choices=("evaluate", "calibrate"),
                    help="evaluate (default): the measurement; calibrate: the tables of emdflow.cues")
    ap.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    ap.add_argument("--models", default="paper,extended", help="comma-separated (paper, extended)")
    ap.add_argument("--textures", default=",".join(EVALUATION_TEXTURES),
                    help="evaluate: comma-separated photographs (calibrate always flies "
                         "CALIBRATION_TEXTURES)")
    ap.add_argument("--rates", type=lambda text: number_list(text, float), default=DEFAULT_RATES,
                    help="expansion rates per frame, comma-separated (negative: receding)")
    ap.add_argument("--translations", type=_translations, default=DEFAULT_TRANSLATIONS,
                    help="u,v px/frame pairs separated by ';' (default '0,0;2,-1')")
    ap.add_argument("--frames", type=int, default=8, help="measured frames per flight")
    ap.add_argument("--flights", type=int, default=None,
                    help="flights per cell (evaluate, default 6) or per model (calibrate, default 2400)")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--write", action="store_true",
                    help="calibrate: write the tables to emdflow/cues_calibration.npz")
    a = ap.parse_args(argv)
    models = tuple(m for m in a.models.split(",") if m)
    if not models:
        ap.error(f"--models {a.models!r}: name at least one model; known: {', '.join(MODELS)}")
    bad = [m for m in models if m not in MODELS]
    if bad:
        ap.error(f"--models: unknown model(s) {', '.join(bad)}; known: {', '.join(MODELS)}")
    # every option checked before the flights (not as a traceback minutes into the run)
    if a.flights is not None and a.flights < 1:
        ap.error(f"--flights {a.flights}: must be at least 1")
    if a.frames < 1:
        ap.error(f"--frames {a.frames}: must be at least 1")
    if a.seed is not None and a.seed < 0:
        ap.error(f"--seed {a.seed}: must be >= 0")
    t0 = time.time()
    if a.command == "calibrate":
        tables = {}
        for model in models:
            tables[model] = calibrate(
                model, flights=2400 if a.flights is None else a.flights,
                seed=20240610 if a.seed is None else a.seed,
                backend=a.backend,
                progress=lambda k, n, m=model: print(f"{m}: {k}/{n} flights, {time.time() - t0:.0f} s",
                                                     file=sys.stderr, flush=True))
        if a.write:  # keep the committed tables of the models not recalibrated
            from emdflow.cues import load_calibration

            tables = {**load_calibration(), **tables}
            print(f"wrote {write_calibration(tables)}", file=sys.stderr)
        else:
            print(format_calibration(tables))
        return 0
    textures = tuple(t for t in a.textures.split(",") if t)
    if not textures:
        ap.error(f"--textures {a.textures!r}: name at least one photograph")
    if problem := texture_names_problem(textures, texture_source):
        ap.error(f"--textures: {problem}")
    bad_rates = [r for r in a.rates if not (math.isfinite(r) and r != 0.0 and r > -1.0)]
    if bad_rates:
        ap.error(f"--rates {','.join(f'{r:g}' for r in bad_rates)}: each must be a finite number "
                 "> -1 and not 0 (scale growth per frame)")
    if not all(math.isfinite(c) for uv in a.translations for c in uv):
        ap.error("--translations: u,v must be finite numbers (px/frame)")
    # a receding flight's last frame must still be renderable (a rate of -0.5 failed at frame
    # 9 of the default flights, a traceback mid-run): its view checked once per ground
    from emdflow.params import EngineParams
    from emdflow.synthetic import CameraFlight

    last = max(EngineParams(**MODELS[m]).history_frames for m in models) + a.frames - 1
    for texture in textures:
        for rate in sorted(set(a.rates)):
            flight = CameraFlight(texture_source(texture), width=FLIGHT_WIDTH, height=FLIGHT_HEIGHT,
                                  expansion_rate=rate, supersample=FLIGHT_SUPERSAMPLE)
            if problem := flight.view_problem(last):
                ap.error(f"--rates {rate:g} over {texture} ({a.frames} frames): {problem}")
    results = evaluate(models=models, textures=textures, rates=a.rates,
                       translations=a.translations, frames=a.frames,
                       flights=6 if a.flights is None else a.flights, backend=a.backend,
                       seed=1 if a.seed is None else a.seed)
    print(format_report(results))
    print(f"({time.time() - t0:.0f} s, backend {a.backend})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
