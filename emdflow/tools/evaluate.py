"""``emdflow eval``: accuracy of the engine (and of OpenCV DIS) on camera flights with exact truth.

A *flight* is a :class:`emdflow.synthetic.CameraFlight` over a real photograph: a fixed
image flow (speed, direction) plus a *variant* (noise, low contrast, exposure drift, zoom).
Every frame after the detector's history is full is measured, for the engine and for
OpenCV's DIS optical flow (preset ULTRAFAST) on the same frame pairs.

Per-pixel truth is exact: :func:`truth_field` maps every output pixel through the flight's
camera model (translation and zoom), at the current frame's pixel positions for the
engine's field and at the previous frame's positions for DIS (which reports the flow of
frame ``t−1``'s pixels).

Metrics, per (variant, method, speed), over all directions, textures and measured frames:

density
    Share of pixels with a detection on at least one axis (DIS: 1).
sign accuracy
    Share of detected components whose sign equals the truth's, over components whose true
    magnitude is at least 0.1 px/frame.
pixel error
    Median (and 90th percentile) of ``|estimate − truth|`` over detected components,
    px/frame. The detector measures how fast an edge *crosses* an axis, so off-axis motion
    has large per-component errors by design; the summary is what corrects that.
summary relative error
    ``|S − T| / |T|`` for the global flow ``S`` (:func:`emdflow.summarize`; DIS: the median
    of its dense field) against the flight's flow ``T`` at the image centre. A frame whose
    summary has quality 0 counts as 100 % (and 180°).
summary direction error
    Angle between ``S`` and ``T`` in degrees (180° when ``S`` is zero).
coverage
    Share of measured frames whose summary has quality > 0 (DIS: 1).
expansion error
    Zoom flights only: relative error of the expansion rate (image scale growth per frame,
    the value of :meth:`CameraFlight.truth`); DIS's is fitted to its dense field, the
    engine's is :func:`emdflow.cues.looming_cues`' ``expansion_rate``.

Everything but :func:`main` is a pure function of its arguments.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..cues import looming_cues

__all__ = [
    "Variant",
    "DEFAULT_VARIANTS",
    "VARIANTS",
    "DEFAULT_SPEEDS",
    "COMPASS_DIRECTIONS",
    "OFF_AXIS_DIRECTIONS",
    "DEFAULT_TEXTURES",
    "EvalConfig",
    "quick_config",
    "truth_field",
    "summary_errors",
    "dis_summary",
    "fit_expansion",
    "Accumulator",
    "run_evaluation",
    "format_table",
    "format_markdown",
    "write_csv",
    "read_csv",
    "plot_results",
    "CSV_COLUMNS",
    "add_arguments",
    "run",
    "main",
]


@dataclasses.dataclass(frozen=True)
class Variant:
    """Imaging conditions of a flight.

    Attributes
    ----------
    name : str
        Key used on the command line and in the CSV.
    description : str
        One line for the table header.
    noise_sigma : float
        Sensor noise, gray levels.
    contrast : float
        Scene contrast factor.
    shade : float
        Light on the right half of the view (a shadow; see :class:`CameraFlight`).
    exposure_drift : float
        Relative exposure change over the whole flight (linear ramp).
    expansion_rate : float
        Image scale growth per frame (zoom flight towards the ground).
    """

    name: str
    description: str
    noise_sigma: float = 2.0
    contrast: float = 1.0
    shade: float = 1.0
    exposure_drift: float = 0.0
    expansion_rate: float = 0.0


VARIANTS = {
    v.name: v
    for v in (
        Variant("base", "noise σ=2"),
        Variant("noisy", "noise σ=5", noise_sigma=5.0),
        Variant("contrast", "contrast ×0.25, noise σ=2", contrast=0.25),
        Variant("shade", "right half of the view in shade (light ×0.25), noise σ=2", shade=0.25),
        Variant("bright", "exposure +20 % over the flight, noise σ=2", exposure_drift=0.2),
        Variant("dark", "exposure −20 % over the flight, noise σ=2", exposure_drift=-0.2),
        Variant("zoom", "zoom 0.5 %/frame + translation, noise σ=2", expansion_rate=0.005),
    )
}

#: Variants flown by default (``shade`` on request: the README's tables predate it).
DEFAULT_VARIANTS = ("base", "noisy", "contrast", "bright", "dark", "zoom")

#: Speeds flown by default, px/frame (the paper's channels are the odd integers 1..13).
DEFAULT_SPEEDS = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0, 9.0, 11.0, 13.0)
#: The eight compass directions, degrees (0 = right, 90 = down).
COMPASS_DIRECTIONS = (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0)
#: Directions between the detector's axes and diagonals.
OFF_AXIS_DIRECTIONS = (22.5, 112.5, 202.5, 292.5)
#: Evaluation photographs (disjoint from the summary's calibration set).
DEFAULT_TEXTURES = ("gravel", "brick", "grass", "camera")

CSV_COLUMNS = (
    "variant",
    "method",
    "speed",
    "frames",
    "density",
    "sign_accuracy",
    "pixel_error_median",
    "pixel_error_p90",
    "summary_rel_error_median",
    "summary_dir_error_median_deg",
    "coverage",
    "expansion_rel_error_median",
)


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """What to fly.

    Each (variant, speed, direction) cell is flown ``repeats`` times, over textures taken
    round-robin from ``textures``, from random start positions (seeded).
    """

    textures: tuple = DEFAULT_TEXTURES
    speeds: tuple = DEFAULT_SPEEDS
    directions: tuple = COMPASS_DIRECTIONS + OFF_AXIS_DIRECTIONS
    variants: tuple = DEFAULT_VARIANTS
    width: int = 320
    height: int = 240
    measure_frames: int = 5
    repeats: int = 2
    seed: int = 1
    dis: bool = True

    def flights(self):
        """Yield ``(variant, speed, direction, texture, seed)`` for every flight."""
        i = 0
        for vname in self.variants:
            for speed in self.speeds:
                for direction in self.directions:
                    for _ in range(self.repeats):
                        yield VARIANTS[vname], speed, direction, self.textures[i % len(self.textures)], self.seed + i
                        i += 1

    @property
    def n_flights(self) -> int:
        return len(self.variants) * len(self.speeds) * len(self.directions) * self.repeats


def quick_config(**overrides) -> EvalConfig:
    """A small run (about 80 flights at 160×120) for a first look or a smoke test."""
    base = dict(
        textures=("gravel",),
        speeds=(0.5, 1.0, 2.0, 3.0, 5.0, 9.0, 13.0),
        directions=(0.0, 90.0, 225.0, 22.5),
        variants=("base", "contrast", "zoom"),
        width=160,
        height=120,
        measure_frames=4,
        repeats=1,
    )
    base.update(overrides)
    return EvalConfig(**base)


def truth_field(flight, t: int, *, at: str = "current") -> tuple[np.ndarray, np.ndarray]:
    """Exact image motion of every pixel between frames ``t−1`` and ``t`` of a flight.

    Parameters
    ----------
    flight : emdflow.synthetic.CameraFlight
    t : int
        Frame index, ``t >= 1``.
    at : {'current', 'previous'}
        Pixel positions the flow is given at: of frame ``t`` (where the detector reports
        motion) or of frame ``t−1`` (OpenCV's convention, ``prev(x) ≈ next(x + flow)``).

    Returns
    -------
    u, v : ndarray of float64, shape (height, width)
        px/frame, x right, y down.

    Notes
    -----
    The renderer maps output pixel ``i`` at frame ``t`` to the ground coordinate
    ``g = c_t + (i + ½ − W/2)·m_t − ½`` (``c_t`` the ground point under the image centre,
    ``m_t`` ground pixels per image pixel). A ground point's image position at frame ``t'``
    inverts that map; the flow is the difference of positions.
    """
    if t < 1:
        raise ValueError(f"t={t}: the flow of frame t needs frame t-1")
    cx1, cy1, m1 = flight._camera(int(t))
    cx0, cy0, m0 = flight._camera(int(t) - 1)
    X = np.arange(flight.width) + 0.5 - flight.width / 2.0
    Y = np.arange(flight.height) + 0.5 - flight.height / 2.0
    if at == "current":
        u = X - (cx1 - cx0 + X * m1) / m0
        v = Y - (cy1 - cy0 + Y * m1) / m0
    elif at == "previous":
        u = (cx0 - cx1 + X * m0) / m1 - X
        v = (cy0 - cy1 + Y * m0) / m1 - Y
    else:
        raise ValueError(f"at={at!r}: expected 'current' or 'previous'")
    shape = (flight.height, flight.width)
    return np.broadcast_to(u[None, :], shape), np.broadcast_to(v[:, None], shape)


def summary_errors(sx: float, sy: float, quality: float, tx: float, ty: float) -> tuple[float, float]:
    """Relative error and direction error (degrees) of a summary against the truth.

    A summary with quality 0 counts as relative error 1 (100 %) and 180°; so does a zero
    vector for its direction.
    """
    true_speed = math.hypot(tx, ty)
    if quality <= 0:
        return 1.0, 180.0
    rel = math.hypot(sx - tx, sy - ty) / max(true_speed, 1e-12)
    if math.hypot(sx, sy) < 1e-12 or true_speed < 1e-12:
        return rel, 180.0
    d = math.degrees(math.atan2(sy, sx) - math.atan2(ty, tx))
    d = abs((d + 180.0) % 360.0 - 180.0)
    return rel, d


def dis_summary(flow: np.ndarray) -> tuple[float, float]:
    """DIS's global flow: the per-component median of its dense field (px/frame)."""
    return float(np.median(flow[..., 0])), float(np.median(flow[..., 1]))


def fit_expansion(u: np.ndarray, v: np.ndarray) -> float:
    """Least-squares scale growth ``d`` of ``u = a + d·X``, ``v = b + d·Y`` (X, Y from the centre).

    Returns the image scale growth per frame (divergence / 2); NaN values are ignored.
    """
    h, w = u.shape
    X = np.broadcast_to(np.arange(w) - (w - 1) / 2.0, (h, w))
    Y = np.broadcast_to((np.arange(h) - (h - 1) / 2.0)[:, None], (h, w))
    num = den = 0.0
    for comp, coord in ((u, X), (v, Y)):
        ok = np.isfinite(comp)
        if ok.sum() < 2:
            continue
        c = coord[ok] - coord[ok].mean()
        num += float(np.dot(c, comp[ok]))
        den += float(np.dot(c, c))
    return num / den if den > 0 else float("nan")


_ERR_STEP = 0.005
_ERR_BINS = 10000  # 0 .. 50 px/frame, the last bin collects everything above


class Accumulator:
    """Running sums of the metrics of one (variant, method, speed) cell.

    Per-pixel errors are kept as a fine histogram (0.005 px/frame bins), so memory does not
    grow with the number of frames.
    """

    def __init__(self):
        self.frames = 0
        self.pixels = 0
        self.detected_pixels = 0
        self.sign_right = 0
        self.sign_total = 0
        self.err_hist = np.zeros(_ERR_BINS, np.int64)
        self.rel = []
        self.direction = []
        self.covered = 0
        self.expansion = []

    def add_field(self, u, v, tu, tv) -> None:
        """Add one frame's per-pixel estimate (NaN = undetected) against the truth."""
        du, dv = np.isfinite(u), np.isfinite(v)
        self.pixels += u.size
        self.detected_pixels += int(np.count_nonzero(du | dv))
        for est, truth, det in ((u, tu, du), (v, tv, dv)):
            e, t = est[det], truth[det]
            if e.size == 0:
                continue
            signed = np.abs(t) >= 0.1
            self.sign_total += int(np.count_nonzero(signed))
            self.sign_right += int(np.count_nonzero(np.sign(e[signed]) == np.sign(t[signed])))
            # (clipped before the cast: an error past 2^63 steps wrapped to a negative bin)
            idx = np.minimum(np.abs(e - t) / _ERR_STEP, _ERR_BINS - 1).astype(np.int64)
            self.err_hist += np.bincount(idx, minlength=_ERR_BINS)

    def add_summary(self, sx, sy, quality, tx, ty) -> None:
        """Add one frame's summary against the true global flow."""
        rel, d = summary_errors(sx, sy, quality, tx, ty)
        self.frames += 1
        self.rel.append(rel)
        self.direction.append(d)
        self.covered += int(quality > 0)

    def add_expansion(self, estimate, truth) -> None:
        """Add one frame's expansion-rate estimate (NaN/None = not available)."""
        if estimate is None or not np.isfinite(estimate) or truth == 0:
            return
        self.expansion.append(abs(estimate - truth) / abs(truth))

    def _err_quantile(self, q: float) -> float:
        total = int(self.err_hist.sum())
        if total == 0:
            return float("nan")
        k = int(np.searchsorted(np.cumsum(self.err_hist), q * total, side="left"))
        return (k + 0.5) * _ERR_STEP

    def merge(self, other: "Accumulator") -> "Accumulator":
        """A new accumulator holding both."""
        out = Accumulator()
        for name in ("frames", "pixels", "detected_pixels", "sign_right", "sign_total", "covered"):
            setattr(out, name, getattr(self, name) + getattr(other, name))
        out.err_hist = self.err_hist + other.err_hist
        out.rel = self.rel + other.rel
        out.direction = self.direction + other.direction
        out.expansion = self.expansion + other.expansion
        return out

    def row(self) -> dict:
        """The metrics as a dict with the keys of :data:`CSV_COLUMNS` (less the labels)."""
        nan = float("nan")
        return {
            "frames": self.frames,
            "density": self.detected_pixels / self.pixels if self.pixels else nan,
            "sign_accuracy": self.sign_right / self.sign_total if self.sign_total else nan,
            "pixel_error_median": self._err_quantile(0.5),
            "pixel_error_p90": self._err_quantile(0.9),
            "summary_rel_error_median": float(np.median(self.rel)) if self.rel else nan,
            "summary_dir_error_median_deg": float(np.median(self.direction)) if self.direction else nan,
            "coverage": self.covered / self.frames if self.frames else nan,
            "expansion_rel_error_median": float(np.median(self.expansion)) if self.expansion else nan,
        }


def run_evaluation(config: EvalConfig, make_estimator, *, progress=None, engine_label="emd") -> list[dict]:
    """Fly every flight of ``config`` and measure the engine and DIS.

    Parameters
    ----------
    config : EvalConfig
    make_estimator : callable
        ``make_estimator(width, height) -> FlowEstimator``; called once, the estimator is
        reset between flights.
    progress : callable, optional
        Called with the number of frames processed after every frame (e.g. a tqdm update).
    engine_label : str
        Method name of the engine in the results.

    Returns
    -------
    list of dict
        One row per (variant, method, speed) and per (variant, method, ``"all"``), with the
        keys of :data:`CSV_COLUMNS`.
    """
    import cv2

    from emdflow import summarize
    from emdflow.synthetic import CameraFlight, load_texture

    est = make_estimator(config.width, config.height)
    history = est.params.history_frames
    total = history + config.measure_frames
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST) if config.dis else None
    methods = (engine_label, "dis") if config.dis else (engine_label,)
    cells = {}
    rng = np.random.default_rng(config.seed)
    for variant, speed, direction, texture, seed in config.flights():
        th, tw = load_texture(texture).shape
        start = (float(rng.uniform(0, tw)), float(rng.uniform(0, th)))
        a = math.radians(direction)
        flow = (speed * math.cos(a), speed * math.sin(a))
        flight = CameraFlight(
            texture,
            width=config.width,
            height=config.height,
            flow=flow,
            noise_sigma=variant.noise_sigma,
            contrast=variant.contrast,
            shade=variant.shade,
            exposure_drift=variant.exposure_drift,
            drift_frames=total,
            expansion_rate=variant.expansion_rate,
            seed=seed,
            start=start,
        )
        emd_acc = cells.setdefault((variant.name, methods[0], speed), Accumulator())
        dis_acc = cells.setdefault((variant.name, "dis", speed), Accumulator()) if dis else None
        est.reset()
        prev = None
        for t in range(total):
            frame = flight.render(t)
            field = est.update(frame)
            if field.ready and t >= 1:
                truth = flight.truth(t)
                s = summarize(field)
                tu, tv = truth_field(flight, t, at="current")
                emd_acc.add_field(field.u, field.v, tu, tv)
                emd_acc.add_summary(s.flow_x, s.flow_y, s.quality, truth.flow_x, truth.flow_y)
                if variant.expansion_rate:
                    emd_acc.add_expansion(looming_cues(field).expansion_rate, truth.expansion_rate)
                if dis is not None:
                    f = dis.calc(prev, frame, None)
                    pu, pv = truth_field(flight, t, at="previous")
                    dis_acc.add_field(f[..., 0], f[..., 1], pu, pv)
                    dx, dy = dis_summary(f)
                    dis_acc.add_summary(dx, dy, 255, truth.flow_x, truth.flow_y)
                    if variant.expansion_rate:
                        dis_acc.add_expansion(fit_expansion(f[..., 0], f[..., 1]), truth.expansion_rate)
            prev = frame
            if progress is not None:
                progress(1)
    rows = []
    for vname in config.variants:
        for method in methods:
            merged = Accumulator()
            for speed in config.speeds:
                acc = cells.get((vname, method, speed), Accumulator())
                merged = merged.merge(acc)
                rows.append({"variant": vname, "method": method, "speed": speed, **acc.row()})
            rows.append({"variant": vname, "method": method, "speed": "all", **merged.row()})
    return rows


def _pct(x, digits=0):
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.{digits}f}%"


def _num(x, fmt):
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def format_table(rows: list[dict], *, engine_label: str = "emd") -> str:
    """The results as a plain-text table, one block per variant (speeds as rows)."""
    out = []
    by = {(r["variant"], r["method"], str(r["speed"])): r for r in rows}
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    speeds = list(dict.fromkeys(str(r["speed"]) for r in rows))
    has_dis = any(r["method"] == "dis" for r in rows)
    has_exp = any(not math.isnan(r["expansion_rel_error_median"]) for r in rows if isinstance(r["expansion_rel_error_median"], float))
    name = engine_label.upper()
    head = f"{'speed':>6} | {name + ' dens':>9} {'sign':>5} {'px err':>6} {'rel err':>7} {'dir err':>7} {'cover':>5}"
    if has_dis:
        head += f" | {'DIS px err':>10} {'rel err':>7} {'dir err':>7}"
    for vname in variants:
        desc = VARIANTS[vname].description if vname in VARIANTS else vname
        out.append(f"variant {vname} ({desc})")
        out.append(head)
        out.append("-" * len(head))
        for sp in speeds:
            e = by.get((vname, engine_label, sp))
            if e is None:
                continue
            label = sp if sp == "all" else f"{float(sp):g}"
            line = (
                f"{label:>6} | {_pct(e['density'], 1):>9} {_pct(e['sign_accuracy']):>5} "
                f"{_num(e['pixel_error_median'], '.2f'):>6} {_pct(e['summary_rel_error_median'], 1):>7} "
                f"{_num(e['summary_dir_error_median_deg'], '.1f'):>6}° {_pct(e['coverage']):>5}"
            )
            d = by.get((vname, "dis", sp))
            if d is not None:
                line += (
                    f" | {_num(d['pixel_error_median'], '.2f'):>10} {_pct(d['summary_rel_error_median'], 1):>7} "
                    f"{_num(d['summary_dir_error_median_deg'], '.1f'):>6}°"
                )
            out.append(line)
        if vname == "zoom" and has_exp:
            e = by.get((vname, engine_label, "all"))
            d = by.get((vname, "dis", "all"))
            parts = []
            if e is not None:
                parts.append(f"{name} {_pct(e['expansion_rel_error_median'], 1)}")
            if d is not None:
                parts.append(f"DIS {_pct(d['expansion_rel_error_median'], 1)}")
            out.append("expansion rate, median relative error: " + ", ".join(parts))
        out.append("")
    out.append(
        "dens = pixels with a detection; sign = right sign of detected components; px err = median "
        "|error| of detected components (px/frame); rel/dir err = median error of the global summary "
        "(quality-0 frames count as 100 %/180°); cover = frames with quality > 0."
    )
    return "\n".join(out)


def format_markdown(rows: list[dict], *, engine_label: str = "emd", full_variants=("base",)) -> str:
    """The results as Markdown: per speed for ``full_variants``, then one line per variant.

    Columns as in :func:`format_table`; the second table holds the ``all`` rows.
    """
    name = engine_label.upper()
    by = {(r["variant"], r["method"], str(r["speed"])): r for r in rows}
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    speeds = list(dict.fromkeys(str(r["speed"]) for r in rows))
    head = (f"| {{key}} | {name} density | {name} sign | {name} px err | {name} rel err | {name} dir err | "
            f"{name} coverage | DIS px err | DIS rel err | DIS dir err |\n|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")

    def line(key, e, d):
        cells = [key, _pct(e["density"], 1), _pct(e["sign_accuracy"]), _num(e["pixel_error_median"], ".2f"),
                 _pct(e["summary_rel_error_median"], 1), _num(e["summary_dir_error_median_deg"], ".1f") + "°",
                 _pct(e["coverage"])]
        if d is not None:
            cells += [_num(d["pixel_error_median"], ".2f"), _pct(d["summary_rel_error_median"], 1),
                      _num(d["summary_dir_error_median_deg"], ".1f") + "°"]
        else:
            cells += ["", "", ""]
        return "| " + " | ".join(cells) + " |"

    out = []
    for vname in full_variants:
        if not any(k[0] == vname for k in by):
            continue
        desc = VARIANTS[vname].description if vname in VARIANTS else vname
        out.append(f"Variant `{vname}` ({desc}), per speed (px/frame):\n")
        out.append(head.format(key="speed"))
        for sp in speeds:
            e = by.get((vname, engine_label, sp))
            if e is not None:
                out.append(line(sp if sp == "all" else f"{float(sp):g}", e, by.get((vname, "dis", sp))))
        out.append("")
    out.append("All speeds, per variant:\n")
    out.append(head.format(key="variant"))
    for vname in variants:
        e = by.get((vname, engine_label, "all"))
        if e is not None:
            out.append(line(vname, e, by.get((vname, "dis", "all"))))
    return "\n".join(out) + "\n"


def write_csv(rows: list[dict], path) -> None:
    """Write the rows with the header :data:`CSV_COLUMNS` (floats with 6 significant digits)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for r in rows:
            w.writerow([f"{r[c]:.6g}" if isinstance(r[c], float) else r[c] for c in CSV_COLUMNS])


_FLOOR = 0.05  # plotted floor of the log axes (% and degrees)
#: The CSV ``emdflow eval`` writes unless told otherwise.
DEFAULT_CSV = "emdflow_eval.csv"
#: The plot ``emdflow eval`` draws unless told otherwise (where matplotlib is installed).
DEFAULT_PLOT = "emdflow_eval.png"


def read_csv(path) -> list[dict]:
    """Read rows written by :func:`write_csv` back (numbers as float, ``speed`` as float or "all").

    Raises
    ------
    ValueError
        If the file is not an ``emdflow eval`` CSV (naming it).
    """
    name = os.fspath(path)
    try:
        with open(name, newline="") as f:
            reader = csv.DictReader(f)
            if tuple(reader.fieldnames or ()) != CSV_COLUMNS:
                raise ValueError(f"{name}: not an emdflow eval CSV (header differs)")
            rows = []
            for r in reader:
                for key in CSV_COLUMNS[2:]:
                    if key == "speed" and r[key] == "all":
                        continue
                    r[key] = int(r[key]) if key == "frames" else float(r[key])
                rows.append(r)
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{name}: cannot read ({getattr(e, 'strerror', None) or e})") from None
    except (KeyError, TypeError, ValueError) as e:
        if str(e).startswith(name):
            raise
        raise ValueError(f"{name}: not an emdflow eval CSV ({e})") from None
    return rows


def plot_results(rows: list[dict], path, *, title: str | None = None, engine_label: str = "emd") -> None:
    """Plot summary relative and direction error against speed for each method and variant.

    Writes a PNG with matplotlib's Agg backend (no display needed). Solid lines: the
    engine; dashed: DIS.
    """
    from emdflow.tools import writing

    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    variants = list(dict.fromkeys(r["variant"] for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6), dpi=80)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, vname in enumerate(variants):
        for method, style in ((engine_label, "-"), ("dis", "--")):
            sel = [r for r in rows if r["variant"] == vname and r["method"] == method and r["speed"] != "all"]
            if not sel:
                continue
            sp = [float(r["speed"]) for r in sel]
            label = f"{'DIS' if method == 'dis' else method.upper()} {vname}"
            kw = dict(color=colors[i % len(colors)], linestyle=style, marker="o" if style == "-" else ".", ms=3,
                      label=label)
            axes[0].plot(sp, [max(_FLOOR, 100 * r["summary_rel_error_median"]) for r in sel], **kw)
            axes[1].plot(sp, [max(_FLOOR, r["summary_dir_error_median_deg"]) for r in sel], **kw)
    for ax, ylabel, top in zip(axes, ("summary relative error, median (%)", "summary direction error, median (°)"),
                               (400.0, 200.0)):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(_FLOOR, top)
        ax.get_yaxis().set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.set_xlabel("speed (px/frame)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xticks([0.25, 0.5, 1, 2, 3, 5, 7, 9, 13])
        ax.get_xaxis().set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    axes[0].axhline(10, color="gray", lw=0.8, ls=":")
    axes[1].axhline(2, color="gray", lw=0.8, ls=":")
    handles, labels = axes[0].get_legend_handles_labels()
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.legend(handles, labels, loc="lower center", ncol=min(6, max(1, len(labels) // 2)), fontsize=7,
               frameon=False)
    with writing("--plot", path):
        fig.savefig(path)  # (the image type from the file ending plot_type_problem checked)
    plt.close(fig)


# ---------------------------------------------------------------------------- command line


def _floats(text: str) -> tuple[float, ...]:
    from . import number_list

    return number_list(text, float)


def _directions(text: str) -> tuple[float, ...]:
    out = []
    for part in text.split(","):
        part = part.strip().lower()
        if part == "compass":
            out += COMPASS_DIRECTIONS
        elif part in ("offaxis", "off-axis"):
            out += OFF_AXIS_DIRECTIONS
        elif part:
            out += _floats(part)
    if not out:
        raise argparse.ArgumentTypeError(f"{text!r}: expected directions")
    return tuple(out)


def _variants(text: str) -> tuple[str, ...]:
    names = tuple(x.strip() for x in text.split(",") if x.strip())
    bad = [n for n in names if n not in VARIANTS]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"unknown variant {', '.join(bad) or text!r}; choose from {', '.join(VARIANTS)}")
    return names


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``emdflow eval``."""
    from emdflow.tools import add_engine_arguments

    p.add_argument("--textures", nargs="+", metavar="IMAGE",
                   help="ground textures: bundled names or any image files "
                        f"(default: {' '.join(DEFAULT_TEXTURES)})")
    p.add_argument("--speeds", type=_floats, metavar="LIST", help="px/frame, comma-separated "
                   f"(default: {','.join(f'{s:g}' for s in DEFAULT_SPEEDS)})")
    p.add_argument("--directions", type=_directions, metavar="LIST",
                   help="degrees (0 = right, 90 = down) and/or 'compass', 'offaxis' (default: compass,offaxis)")
    p.add_argument("--variants", type=_variants, metavar="LIST",
                   help=f"comma-separated from {', '.join(VARIANTS)} (default: {','.join(DEFAULT_VARIANTS)})")
    p.add_argument("--size", metavar="WxH", help="frame size (default 320x240; --quick 160x120)")
    p.add_argument("--frames", type=int, metavar="N", help="measured frames per flight after the history (default 5)")
    p.add_argument("--repeats", type=int, metavar="N", help="flights per (variant, speed, direction) (default 2)")
    p.add_argument("--seed", type=int, default=1, help="seed of start positions and noise (default 1)")
    p.add_argument("--quick", action="store_true",
                   help="small run: gravel, 160x120, 7 speeds, 4 directions, variants base,contrast,zoom")
    p.add_argument("--no-dis", action="store_true", help="skip OpenCV DIS")
    p.add_argument("--csv", metavar="PATH", help=f"CSV output (default {DEFAULT_CSV})")
    p.add_argument("--plot", default=None, metavar="PATH",
                   help=f"PNG plot (default {DEFAULT_PLOT} where matplotlib is installed, the "
                        "'tools' extra; '' to skip)")
    p.add_argument("--from-csv", metavar="CSV",
                   help="fly nothing: print the table and draw the plot of an earlier run's CSV")
    p.add_argument("--title", help="title of the plot")
    p.add_argument("--markdown", metavar="PATH", help="also write the tables as Markdown (for the README)")
    p.add_argument("--label", default="emd", help="method name of the engine in the outputs (default emd)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_engine_arguments(p)


def config_from_args(args) -> EvalConfig:
    """Build the :class:`EvalConfig` of parsed ``emdflow eval`` arguments.

    Raises
    ------
    ValueError
        On a bad size, count, speed, direction or texture (naming it).
    """
    from emdflow.synthetic import load_texture
    from emdflow.tools import frame_size_problem
    from emdflow.tools.video_io import parse_size

    over = {}
    if args.textures:
        for name in args.textures:
            load_texture(name)  # raises ValueError naming the file
        over["textures"] = tuple(args.textures)
    for key, attr in (("speeds", "speeds"), ("directions", "directions"), ("variants", "variants")):
        if getattr(args, attr):
            # each once (results are kept per speed and variant: "3,3.0" counted frames twice)
            over[key] = tuple(dict.fromkeys(getattr(args, attr)))
    if args.size:
        w, h = over["width"], over["height"] = parse_size(args.size)
        problem = frame_size_problem(w, h, dis=not args.no_dis, dis_hint=" (or skip it with --no-dis)")
        if problem:
            raise ValueError(f"--size {args.size}: {problem}")
    if args.frames is not None:
        if args.frames < 1:
            raise ValueError(f"--frames {args.frames}: must be at least 1")
        over["measure_frames"] = args.frames
    if args.repeats is not None:
        if args.repeats < 1:
            raise ValueError(f"--repeats {args.repeats}: must be at least 1")
        over["repeats"] = args.repeats
    # (float() takes "nan" and "inf": the flight's renderer would never return)
    bad = [s for s in over.get("speeds", ()) if not (math.isfinite(s) and s > 0)]
    if bad:
        raise ValueError(f"--speeds {bad[0]:g}: every speed must be a finite number > 0 (px/frame)")
    bad = [d for d in over.get("directions", ()) if not math.isfinite(d)]
    if bad:
        raise ValueError(f"--directions {bad[0]:g}: every direction must be a finite number (degrees)")
    if args.seed < 0:  # (numpy's generators take no negative seed)
        raise ValueError(f"--seed {args.seed}: must be 0 or more")
    over["seed"] = args.seed
    over["dis"] = not args.no_dis
    return quick_config(**over) if args.quick else EvalConfig(**over)


def _plot_path(args) -> str:
    """The plot to draw ('' for none): an explicit ``--plot`` needs matplotlib (an error
    before anything is flown); the default plot is left out, with a note, without it."""
    from emdflow.tools import ToolError, matplotlib_missing

    missing = matplotlib_missing()
    if args.plot is None:
        if missing:
            print(f"emdflow eval: no plot: {missing}", file=sys.stderr)
            return ""
        return DEFAULT_PLOT
    if args.plot and missing:
        raise ToolError(f"--plot {args.plot}: {missing}", 2)
    return args.plot


#: the options ``--from-csv`` still reads (its outputs and their look); every other one
#: shapes a flight or its engine, and set beside it is refused rather than silently ignored
_FROM_CSV_OPTIONS = frozenset({"from_csv", "plot", "markdown", "title", "quiet", "help"})


def _flight_options_given(args) -> list[str]:
    """The options of ``args`` set away from their defaults that ``--from-csv`` would
    ignore, as their long names (the defaults read from :func:`add_arguments` itself)."""
    parser = argparse.ArgumentParser(add_help=False)
    add_arguments(parser)
    return [max(a.option_strings, key=len) for a in parser._actions
            if a.dest not in _FROM_CSV_OPTIONS and getattr(args, a.dest, a.default) != a.default]


def run(args) -> int:
    """Run ``emdflow eval`` with parsed arguments; returns the exit code."""
    from emdflow.tools import (ToolError, make_estimator, output_problem, plot_type_problem, progress_bar,
                               refuse_same_outputs, writing)

    if args.from_csv:
        given = _flight_options_given(args)
        if given:
            raise ToolError(f"--from-csv {args.from_csv} flies nothing: {', '.join(given)} would have no effect "
                            "(leave them out, or fly again without --from-csv)", 2)
    if not args.from_csv and args.csv is None:
        args.csv = DEFAULT_CSV
    label = args.label.strip()
    if not label or label.lower() == "dis":  # (results are kept per method name)
        raise ToolError(f"--label {args.label!r}: must name the engine, not be empty or 'dis' (OpenCV DIS's "
                        "rows are named dis)", 2)
    args.label = label
    args.plot = _plot_path(args)
    outputs = (("--csv", None if args.from_csv else args.csv), ("--plot", args.plot), ("--markdown", args.markdown))
    for option, path in outputs:
        if path and (problem := output_problem(path) or (option == "--plot" and plot_type_problem(path))):
            raise ToolError(f"{option} {path}: {problem}", 2)
    refuse_same_outputs((("--from-csv", args.from_csv), *outputs))

    if args.from_csv:
        try:
            rows = read_csv(args.from_csv)
        except ValueError as e:
            raise ToolError(str(e), 2) from None
        # (an empty table and exit 0 read as a run that measured nothing wrong)
        if not rows:
            raise ToolError(f"{args.from_csv}: no rows", 2)
        label = next((r["method"] for r in rows if r["method"] != "dis"), None)
        if label is None:
            raise ToolError(f"{args.from_csv}: no engine rows (only DIS)", 2)
        print(format_table(rows, engine_label=label))
        if args.markdown:
            with writing("--markdown", args.markdown):
                Path(args.markdown).write_text(format_markdown(rows, engine_label=label))
            print(f"wrote {args.markdown}")
        if args.plot:
            title = args.title or f"{label.upper()} vs OpenCV DIS ULTRAFAST ({Path(args.from_csv).name})"
            plot_results(rows, args.plot, title=title, engine_label=label)
            print(f"wrote {args.plot}")
        return 0
    try:
        config = config_from_args(args)
    except ValueError as e:
        raise ToolError(str(e), 2) from None

    def factory(w, h):
        return make_estimator(args, w, h)

    est_probe = factory(config.width, config.height)
    history = est_probe.params.history_frames
    total = config.n_flights * (history + config.measure_frames)
    t0 = time.perf_counter()
    with progress_bar(total, "eval", unit="frame", disable=args.quiet) as bar:
        rows = run_evaluation(config, lambda w, h: est_probe, progress=bar.update, engine_label=args.label)
    elapsed = time.perf_counter() - t0
    header = (
        f"emdflow eval: {config.n_flights} flights of {config.measure_frames} measured frames at "
        f"{config.width}x{config.height}, textures {', '.join(os.path.basename(t) for t in config.textures)}, "
        f"{len(config.directions)} directions, {elapsed:.0f} s\n"
        f"engine: {est_probe!r}"
    )
    print(header)
    print()
    print(format_table(rows, engine_label=args.label))
    if args.csv:
        with writing("--csv", args.csv):
            write_csv(rows, args.csv)
        print(f"wrote {args.csv}")
    if args.markdown:
        with writing("--markdown", args.markdown):
            Path(args.markdown).write_text(format_markdown(rows, engine_label=args.label))
        print(f"wrote {args.markdown}")
    if args.plot:
        title = (f"{args.label.upper()} ({est_probe.backend}) vs OpenCV DIS ULTRAFAST, {config.width}x{config.height}, "
                 f"{config.n_flights} flights")
        plot_results(rows, args.plot, title=args.title or title, engine_label=args.label)
        print(f"wrote {args.plot}")
    return 0


def main(argv=None) -> int:
    """``python -m emdflow.tools.evaluate`` (same as ``emdflow eval``)."""
    from emdflow.cli import main as cli_main

    return cli_main(["eval", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
