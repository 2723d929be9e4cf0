"""Calibrate the likelihood tables of :func:`emdflow.summarize` from synthetic flights.

The summary (``emdflow/summary.py``) models every detection as drawn from
``P(code | c, ψ, β)``: the probability that the winning signed channel of an axis
detector is ``code`` when an edge crosses that axis at the signed speed ``c`` px/frame,
the edge normal makes the angle ``ψ`` with the axis and ``β = |sin|`` of the angle between
the flow and the edge normal (0: the edge moves along its normal, 1: the flow slides along
the edge and only texture details move across the axis). Categories are
``2 · scale index + (1 if the code's sign disagrees with sign(c))``. This script measures
that table on a grid (trilinear soft binning of every histogram bin).

Steps (all deterministic; the committed table is exactly what these commands write; the
extended model's table below matches in every array but the misfit baseline, which a
re-fit on another host reproduced to 4e-16). ``collect`` flies with the diagonal
detectors' evidence (``EngineParams.diagonal_evidence``, the default), and ``fit`` sees it
in the files and writes the ``…_diagonal.npz`` table, whose axis distributions (``prob``)
are those of the table without it, plus the diagonals' (``prob_diagonal``); the former
tables, ``summary_calibration[_extended][_lines].npz``, which ``diagonal_evidence=False``
reads, are what the same commands write with ``collect --no-diagonal-evidence``::

    # 1. fly the camera over the CALIBRATION textures and store the raw histograms
    #    (OpenCL backend, 320x240; ~1.5 and ~3 minutes on two cores)
    python -m emdflow.tools.calibrate_summary collect --flights 3000 --seed 20240601 \
        --out /tmp/emdflow_calib.npz
    python -m emdflow.tools.calibrate_summary collect --flights 6000 --seed 7 \
        --out /tmp/emdflow_calib2.npz
    # 2. measure the table and write emdflow/summary_calibration.npz; then, with the
    #    new table, the median deviance of 4000 of these frames per speed (the
    #    baseline of the summary's misfit term, stored in the same file; `misfit`
    #    instead of `fit` measures only that, for a table already written)
    python -m emdflow.tools.calibrate_summary fit /tmp/emdflow_calib.npz \
        /tmp/emdflow_calib2.npz --write
    # 3. evaluate summarize() on the EVALUATION textures (per-speed table, coverage,
    #    quality bands and how well quality ranks the frames by error, how much of the
    #    error a flight keeps in all its frames, time per call);
    #    1728 frames per set, ~20 s each
    python -m emdflow.tools.calibrate_summary evaluate --offset 0
    python -m emdflow.tools.calibrate_summary evaluate --offset 0.3
    python -m emdflow.tools.calibrate_summary evaluate --random

The extended model (``[engine] model = "extended"``: delays 1, 2, 4 at scale 1, a scale-15
channel, adaptive threshold, brightness compensation) has its own table, ``emdflow/summary_calibration_extended.npz``
(~3.5, 3.5, 3, 3.5 and four times 4 minutes of collection on a quiet machine)::

    python -m emdflow.tools.calibrate_summary collect --model extended --flights 2800 \
        --frames 8 --seed 20240606 --out /tmp/emdflow_calib_ext.npz
    python -m emdflow.tools.calibrate_summary collect --model extended --flights 2800 \
        --frames 8 --seed 7 --out /tmp/emdflow_calib_ext2.npz
    python -m emdflow.tools.calibrate_summary collect --model extended --flights 2000 \
        --frames 8 --seed 11 --contrast-range 0.7,1 --scale-range 1,2 \
        --out /tmp/emdflow_calib_ext3.npz
    # stochastic ground-like textures (the photographs above are smoother than gravel,
    # grass or soil): two 1/f^beta noise textures and a stained tissue section
    python -m emdflow.tools.calibrate_summary collect --model extended --flights 2800 \
        --frames 8 --seed 31 --textures fractal-1.0-1,fractal-1.4-2,immunohistochemistry \
        --out /tmp/emdflow_calib_ext4.npz
    # rough, high-contrast ground: a frame's mean gradient g of 10-20 gray levels, as over
    # gravel or grass at full contrast (the photographs above mostly give g = 1-8, and a
    # table fitted without these read 0.25 px/frame 20-25 % slow over gravel and grass);
    # fractal-<beta>-<seed>-<sigma>: 1/f noise with a standard deviation of sigma
    ROUGH="python -m emdflow.tools.calibrate_summary collect --model extended --flights 2400 \
        --frames 8 --scale-range 1,2"
    $ROUGH --seed 43 --contrast-range 0.7,1 --out /tmp/emdflow_calib_ext5.npz \
        --textures fractal-0.8-3-60,fractal-1.0-5-55,fractal-1.2-6-60,astronaut
    $ROUGH --seed 47 --contrast-range 0.7,1 --out /tmp/emdflow_calib_ext6.npz \
        --textures fractal-0.9-7-60,fractal-1.1-8-65,fractal-0.7-9-50,coffee
    $ROUGH --seed 61 --contrast-range 0.7,1 --out /tmp/emdflow_calib_ext7.npz \
        --textures fractal-0.85-10-58,fractal-1.05-11-62,fractal-1.3-12-65,immunohistochemistry
    # ... and the same kind of ground at a quarter to half of that contrast
    $ROUGH --seed 67 --contrast-range 0.2,0.45 --out /tmp/emdflow_calib_ext8.npz \
        --textures fractal-0.8-13-60,fractal-1.0-14-55,fractal-1.2-15-60,astronaut
    python -m emdflow.tools.calibrate_summary fit --model extended /tmp/emdflow_calib_ext.npz \
        /tmp/emdflow_calib_ext2.npz /tmp/emdflow_calib_ext3.npz /tmp/emdflow_calib_ext4.npz \
        /tmp/emdflow_calib_ext5.npz /tmp/emdflow_calib_ext6.npz /tmp/emdflow_calib_ext7.npz \
        /tmp/emdflow_calib_ext8.npz --write
    # 10 speeds 0.25..13 px/frame x 4 textures x 8 directions x 6 frames = 1920 frames
    python -m emdflow.tools.calibrate_summary evaluate --model extended --random
    python -m emdflow.tools.calibrate_summary evaluate --model extended --offset 0.3
    python -m emdflow.tools.calibrate_summary evaluate --model extended --random --contrast 0.25
    python -m emdflow.tools.calibrate_summary evaluate --model extended --random --drift 0.2
    python -m emdflow.tools.calibrate_summary evaluate --model extended --random --drift -0.2

The extended model with the **local threshold** (``threshold_mode='local'``, README
"Shadows: the local threshold") has an edge table of its own,
``emdflow/summary_calibration_extended_local_diagonal.npz``: the eight sets above flown
with ``--threshold-mode local`` (``collect`` records the mode in its files, and ``fit``
names the table after it; ~20 minutes of collection here), then fitted as above. The
summary prefers a table made with the engine's threshold mode; the local threshold has no
line-ground table of its own and reads the adaptive one's::

    L="python -m emdflow.tools.calibrate_summary collect --model extended --threshold-mode local"
    # the eight commands above with $L in place of "... collect --model extended", then
    python -m emdflow.tools.calibrate_summary fit --model extended /tmp/emdflow_local_ext[1-8].npz --write
    python -m emdflow.tools.calibrate_summary evaluate --model extended --random --threshold-mode local

The extended model also has a **line-ground table**,
``emdflow/summary_calibration_extended_lines.npz`` (``fit --ground lines``): the same
measurement over grids of thin bright lines (``lines-<seed>-<angle>``,
:func:`emdflow.synthetic.grid_texture`: 4 px lines, columns 15–50 px and rows 40–120 px
apart, turned to 16 angles so the table knows lines of every orientation; the ground
scale 0.7–2 makes them 2–6 px wide in the image), which the summary reads next to the edge
table (``SummaryOptions.ground``; ~3.5, 3.5 and 2.5 minutes of collection)::

    A=lines-11-0,lines-12-11,lines-13-23,lines-14-34,lines-15-45,lines-16-56,lines-17-68,lines-18-79
    B=lines-21-6,lines-22-17,lines-23-28,lines-24-40,lines-25-51,lines-26-62,lines-27-73,lines-28-84
    LINES="python -m emdflow.tools.calibrate_summary collect --model extended --frames 8 \
        --scale-range 0.7,2"
    $LINES --flights 2800 --seed 105 --textures $A --out /tmp/emdflow_lines_ext.npz
    $LINES --flights 2800 --seed 106 --textures $B --out /tmp/emdflow_lines_ext2.npz
    # the top scene-contrast class (g > 12): the same grids at 1.6-2.6x their contrast
    $LINES --flights 2000 --seed 107 --contrast-range 1.6,2.6 --textures $B \
        --out /tmp/emdflow_lines_ext3.npz
    python -m emdflow.tools.calibrate_summary fit --model extended --ground lines \
        /tmp/emdflow_lines_ext.npz /tmp/emdflow_lines_ext2.npz /tmp/emdflow_lines_ext3.npz --write
    # SummaryOptions.line_ground_margin against accuracy, on validation flights over grounds
    # that neither calibration nor the evaluation flew over (two rough 1/f textures, one
    # grid of step edges, two turned grids of lines)
    V=fractal-1.1-91-50,fractal-1.4-92-30,cells-93-40,lines-91-20,lines-92-65
    python -m emdflow.tools.calibrate_summary evaluate --model extended --random \
        --textures $V --save /tmp/emdflow_validation_ext.npz
    python -m emdflow.tools.calibrate_summary margin /tmp/emdflow_validation_ext.npz

The paper's model has no line-ground table: the same recipe without ``--model extended``
(``--flights 3000``, seeds 5 and 6, no third set) makes one, but without gradient-strength
classes its likelihood cannot tell lines from edges (README, "Thin lines read slow").

(extended flights: speeds log-uniform 0.15..18 px/frame, contrast log-uniform 0.2..1 unless
``--contrast-range``, 60 % with an exposure drift uniform in ±30 % across the flight, 12
frames of history before the ``--frames`` recorded ones.)

``--backend numpy`` gives the same histograms (the backends agree bit for bit), ~30x
slower. ``evaluate --save F.npz`` stores the rendered histograms and ``evaluate --data
F.npz`` scores them again without rendering (for tuning :class:`SummaryOptions`).
``evaluate --size WxH`` flies at another frame size and ``evaluate --noise SIGMA`` with
another sensor noise (σ gray levels; 2 unless told); ``collect --noise-range lo,hi`` draws
the calibration flights' σ from another range (1..3 unless told).

Calibration uses the photographs ``moon, coffee, astronaut, rocket`` with random
direction, speed (log-uniform 0.4..18 px/frame), start position, noise and contrast; every
flight stays inside its photograph (past the border the renderer mirrors the texture, and
the mirrored part moves the other way). The evaluation flights (``gravel, brick, grass,
camera``; ``collect`` refuses them) are never seen here.

The crossing speed of a histogram bin is computed from the true flow ``F`` and the centre
of the bin's orientation ``n = (cos φ, sin φ)``: ``c = (n · F) / n_a``; the orientation
error of the detector's gradient is therefore part of the table (it grows with ``ψ``,
which is one reason ``ψ`` is a dimension).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from emdflow.params import GRADIENT_CLASS_STEPS, ORIENTATION_BINS, THRESHOLD_MODES, EngineParams
from emdflow.params import MODELS as _MODELS
from emdflow.tools import ToolError, check_positive, frame_size_problem, interp_weights, output_problem, texture_names_problem

CALIBRATION_TEXTURES = ("moon", "coffee", "astronaut", "rocket")
#: Kinds of ground a table is measured over (``fit --ground``): the photographs' edges, or
#: grids of thin bright lines (``lines-<seed>-<angle>``, :func:`emdflow.synthetic.grid_texture`).
GROUNDS = ("edges", "lines")


def inside_start(rng, size, view, shift):
    """A start coordinate (texture px) for a flight whose view of ``view`` texture px moves
    by ``shift`` texture px in total and must stay inside ``size``: rendering past the
    texture's border mirrors it, and the mirrored part moves the other way."""
    lo = view / 2.0 + 2.0 - min(0.0, shift)
    hi = size - view / 2.0 - 2.0 - max(0.0, shift)
    if hi < lo:
        raise ValueError("flight does not fit in the texture")
    return float(rng.uniform(lo, hi))


#: Detector models the summary is calibrated for: keyword options of ``FlowEstimator``
#: (``extended`` is the daemon's ``[engine] model = "extended"``).
MODELS = _MODELS
#: Per model, what ``collect`` draws for a flight: speed range (log-uniform, px/frame),
#: contrast range (log-uniform), the share of flights with an exposure drift and its
#: largest size (uniform in ±drift across the whole flight), and the u grid offset of the
#: table (finer near 0 for the slow channels).
COLLECT_RANGES = {
    "paper": {"speed": (0.4, 18.0), "contrast": (0.6, 1.0), "drift_share": 0.0, "drift": 0.0},
    "extended": {"speed": (0.15, 18.0), "contrast": (0.2, 1.0), "drift_share": 0.6, "drift": 0.3},
}


def model_options(model: str, diagonal: bool = True, threshold_mode: str | None = None) -> dict:
    """The ``FlowEstimator`` keywords of ``model`` with ``diagonal_evidence=diagonal`` (the
    default, on: the flights and tables of the diagonal detectors' evidence; off: those of
    the horizontal and vertical detectors alone, the former tables) and ``threshold_mode``
    instead of the model's own (None: the model's; e.g. ``'local'``, whose tables
    :func:`calibration_path` names apart)."""
    options = dict(MODELS[model], diagonal_evidence=bool(diagonal))
    if threshold_mode is not None:
        options["threshold_mode"] = threshold_mode
    return options


def model_params(model: str, diagonal: bool = True, threshold_mode: str | None = None):
    from emdflow.params import EngineParams

    return EngineParams(**model_options(model, diagonal, threshold_mode))


def stored_threshold_mode(paths, model: str) -> str:
    """The threshold mode the stored flights of ``paths`` (``collect`` files of ``model``)
    were flown with; a file that does not record one (made before ``--threshold-mode``)
    flew the model's own. The files must agree."""
    own = MODELS[model].get("threshold_mode", "fixed")
    modes = set()
    for path in paths:
        with np.load(path) as z:
            modes.add(str(z["threshold_mode"]) if "threshold_mode" in z.files else own)
    if len(modes) > 1:
        raise SystemExit(f"the calibration files mix threshold modes: {sorted(modes)}")
    return modes.pop() if modes else own


def stored_engine_settings(paths, model: str) -> dict:
    """The engine settings (:meth:`EngineParams.calibration_settings`) the stored flights of
    ``paths`` were flown with; a file that does not record them (made before they were
    recorded) flew the defaults of ``model`` with its threshold mode. The files must
    agree: a table is measured with one set."""
    from emdflow.summary import table_settings

    found = {}
    for path in paths:
        with np.load(path) as z:  # (recorded, or the model's; fit checks each file's model is ``model``)
            settings = table_settings(z)
        found.setdefault(json.dumps(settings, sort_keys=True), []).append(str(path))
    if len(found) > 1:
        raise SystemExit("the calibration files were flown with different engine settings: "
                         + "; ".join(f"{', '.join(files)}: {settings}" for settings, files in found.items()))
    return json.loads(found.popitem()[0]) if found else model_params(model).calibration_settings()


def _stored_shape(path, name: str) -> tuple[int, ...]:
    """Shape of the array ``name`` in the ``.npz`` file ``path``, from its header alone (an
    extended calibration file's histograms are ~1 GB when decompressed)."""
    import zipfile

    with zipfile.ZipFile(path) as z, z.open(name + ".npy") as f:
        fmt = np.lib.format
        header = fmt.read_array_header_1_0 if fmt.read_magic(f) == (1, 0) else fmt.read_array_header_2_0
        return header(f)[0]


#: The arrays every file of stored flights holds (``collect --out``, ``evaluate --save``).
STORED_ARRAYS = ("hist", "stats", "flow")


#: What summarising stored flights needs besides STORED_ARRAYS (``evaluate --save`` writes
#: them; ``collect --out`` does not): the frame size and the frames' index.
SCORED_ARRAYS = ("shape", "frame_index")


def stored_flights_problem(path, scored: bool = False) -> str | None:
    """Why ``path`` is not a file of stored flights, or None (reads the archive's directory,
    its flows and the shapes of its histograms and counters). ``scored``: the flights are to be summarised again
    (``evaluate --data``, ``margin``), which needs :data:`SCORED_ARRAYS` too."""
    import zipfile
    import zlib

    if not Path(path).is_file():
        return "no such file"
    try:
        stored = np.load(path)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        return f"not a NumPy .npz archive ({exc})"
    if not isinstance(stored, np.lib.npyio.NpzFile):
        return "one NumPy array, not an .npz archive of stored flights"
    with stored:
        missing = [name for name in STORED_ARRAYS if name not in stored.files]
        if missing:
            return (f"no {' or '.join(repr(m) for m in missing)} array in it "
                    "(not written by collect --out or evaluate --save)")
        if scored and (missing := [name for name in SCORED_ARRAYS if name not in stored.files]):
            return (f"no {' or '.join(repr(m) for m in missing)} array in it (written by collect --out: "
                    "only evaluate --save stores what summarising again needs)")
        try:
            flow = stored["flow"]  # (each access reads the member again)
            if flow.ndim != 2 or len(flow) == 0:
                return "no frames in it (its 'flow' array holds no (u, v) rows)"
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:  # (a corrupt member)
            return f"its 'flow' array cannot be read ({exc})"
    from emdflow.reference import STAT_FIRST_CHANGED

    try:  # (from the headers: an extended file's histograms are ~1 GB decompressed)
        hist, stats = _stored_shape(path, "hist"), _stored_shape(path, "stats")
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        return f"its 'hist' or 'stats' array cannot be read ({exc})"
    if len(hist) != 4 or hist[1] not in (2, 4) or hist[0] != len(flow):
        return (f"its 'hist' array has shape {hist}: expected one (2 or 4 axes, signed channels, bins) "
                f"histogram per frame of its 'flow' ({len(flow)} frames)")
    if len(stats) != 2 or stats[0] != len(flow):
        return f"its 'stats' array has shape {stats}: expected one row per frame of its 'flow' ({len(flow)} frames)"
    channels = hist[2] // 2
    if stats[1] != STAT_FIRST_CHANGED + channels:  # (the summary's own check, up front)
        return (f"its 'stats' rows hold {stats[1]} counts: the engine's {STAT_FIRST_CHANGED + channels} for "
                f"the {channels} channels of its 'hist'")
    return None


def recorded_model(stored) -> str:
    """The model an opened file of stored flights was flown with (a file from before the
    extended model records none: the paper's)."""
    return str(stored["model"]) if "model" in stored else "paper"


def has_diagonal(data) -> bool:
    """Whether the stored flights ``data`` (paths) carry the diagonal detectors' histogram
    axes (all of them, or none: SystemExit on a mixture)."""
    kinds = set()
    for path in data:
        kinds.add(_stored_shape(path, "hist")[1] == 4)
    if len(kinds) > 1:
        raise SystemExit("the calibration files mix flights with and without diagonal evidence")
    return kinds == {True}


def calibration_path(model: str, ground: str = "edges", diagonal: bool = True,
                     threshold_mode: str | None = None) -> Path:
    """Where ``fit --write`` stores the table of ``model`` for ``ground`` (summary.py finds
    it there): ``summary_calibration[_<model>][_<threshold mode>][_lines][_diagonal].npz``,
    the threshold mode named only when it is not the model's own (``_local``)."""
    name = "summary_calibration" + ("" if model == "paper" else f"_{model}")
    if threshold_mode is not None and threshold_mode != MODELS[model].get("threshold_mode", "fixed"):
        name += f"_{threshold_mode}"
    name += "" if ground == "edges" else f"_{ground}"
    name += "_diagonal" if diagonal else ""
    return Path(__file__).resolve().parents[1] / (name + ".npz")


def _checked_noise(lo, hi, name: str) -> tuple[float, float]:
    """``(lo, hi)`` as floats when ``0 <= lo <= hi < inf`` (gray levels), else a ValueError
    that starts with ``name``."""
    lo, hi = float(lo), float(hi)
    if not (math.isfinite(hi) and 0.0 <= lo <= hi):
        raise ValueError(f"{name}: the sensor noise must be a standard deviation >= 0 (gray levels)")
    return lo, hi


def collect(flights: int, out: str, frames: int = 7, seed: int = 20240601, width=320, height=240,
            textures=CALIBRATION_TEXTURES, backend: str = "opencl", scale_range=(1.0, 1.0),
            model: str = "paper", contrast_range=None, evidence_row_step: int = 0,
            noise_range=(1.0, 3.0), diagonal: bool = True, threshold_mode: str | None = None):
    """Render ``flights`` random flights; store every ready frame's histogram and truth
    (and the threshold mode flown: ``threshold_mode``, or the model's own).

    Each flight draws a direction, a speed (log-uniform over the model's range, 0.4..18
    px/frame for the paper's model), a sensor noise σ (uniform in ``noise_range``, gray
    levels; 1..3 for the committed tables), a contrast, a ground scale (log-uniform in
    ``scale_range``: texture px per image px, so the photographs are seen finer or
    coarser) and a start that keeps the whole flight inside the photograph (no mirrored
    borders). For the extended model the contrast is log-uniform 0.2..1 and 60 % of the
    flights carry an exposure drift (uniform in ±30 % across the flight);
    ``evidence_row_step`` samples the histograms as in :class:`emdflow.EngineParams`
    (0: automatic, as the committed tables were made). ``frames``
    counts the *ready* frames per flight (the model's history comes on top: 3 frames for
    the paper's model, whose flights therefore have ``frames`` frames in all as before,
    12 for the extended one)."""
    lo_noise, hi_noise = _checked_noise(*noise_range, f"noise_range={tuple(noise_range)!r} (needs lo <= hi)")
    from emdflow import FlowEstimator
    from emdflow.synthetic import CameraFlight, load_texture

    rng = np.random.default_rng(seed)
    est = FlowEstimator(width, height, backend=backend, **model_options(model, diagonal, threshold_mode),
                        evidence_row_step=evidence_row_step)
    ranges = dict(COLLECT_RANGES[model])
    if contrast_range is not None:
        ranges["contrast"] = tuple(contrast_range)
    # the paper's flights are ``frames`` long in all (as the committed table was made)
    total = frames if model == "paper" else frames + est.params.history_frames
    hists, flows, stats, names = [], [], [], []
    t0 = time.time()
    for i in range(flights):
        texture = textures[i % len(textures)]
        th, tw = load_texture(texture).shape
        angle = rng.uniform(0, 2 * math.pi)
        lo, hi = ranges["speed"]
        speed = math.exp(rng.uniform(math.log(lo), math.log(hi)))
        flow = (speed * math.cos(angle), speed * math.sin(angle))
        scale = math.exp(rng.uniform(math.log(scale_range[0]), math.log(scale_range[1])))
        # the largest scale at which the flight fits in the photograph
        fit = min((tw - 6.0) / (width + abs(flow[0]) * (total - 1)),
                  (th - 6.0) / (height + abs(flow[1]) * (total - 1)))
        scale = min(scale, fit)
        start = (inside_start(rng, tw, width * scale, -flow[0] * scale * (total - 1)),
                 inside_start(rng, th, height * scale, -flow[1] * scale * (total - 1)))
        noise = float(rng.uniform(lo_noise, hi_noise))
        if model == "paper":  # the committed table's random stream, unchanged
            contrast = float(rng.uniform(*ranges["contrast"]))
            drift = 0.0
        else:
            clo, chi = ranges["contrast"]
            contrast = math.exp(rng.uniform(math.log(clo), math.log(chi)))
            drift = (float(rng.uniform(-ranges["drift"], ranges["drift"]))
                     if rng.uniform() < ranges["drift_share"] else 0.0)
        flight = CameraFlight(
            texture, width=width, height=height, flow=flow, noise_sigma=noise,
            contrast=contrast, exposure_drift=drift, drift_frames=total,
            seed=int(rng.integers(1 << 30)), start=start, ground_scale=scale,
        )
        est.reset()
        for t in range(total):
            field = est.update(flight.render(t))
            if field.ready:
                hists.append(field.histogram.astype(np.int32))
                flows.append(flow)
                names.append(texture)
                stats.append(field.stats.copy())
        if (i + 1) % 250 == 0:
            print(f"{i + 1}/{flights} flights, {time.time() - t0:.0f} s", file=sys.stderr,
                  flush=True)
    with open(out, "wb") as fh:  # exactly ``out`` (a path without .npz would get one appended)
        np.savez_compressed(fh, hist=np.array(hists), flow=np.array(flows), stats=np.array(stats),
                            texture=np.array(names), model=np.array(model),
                            threshold_mode=np.array(est.params.threshold_mode),
                            engine_settings=np.array(json.dumps(est.params.calibration_settings())))
    print(f"wrote {len(hists)} frames to {out}", file=sys.stderr)


#: Grid of the table: angle ψ between edge normal and detector axis (degrees) ...
PSI_NODES_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 70.0, 80.0, 90.0)
#: ... β = |sin| of the angle between the flow and the edge normal (0: the edge moves along
#: its normal, 1: it slides along itself) ...
BETA_NODES = (0.0, 0.3, 0.6, 0.8, 1.0)
#: ... and |c| on ``u = log(|c| + U_OFFSET)``, ``U_COUNT`` nodes from |c| = 0 to ``C_MAX``
#: (per model: the extended model's slow channels need nodes closer to 0).
U_OFFSET = 0.5
U_COUNT = 40
C_MAX = 60.0
U_GRID = {"paper": (U_OFFSET, U_COUNT), "extended": (0.2, 48)}
#: Per model, the scene-contrast classes of the table: edges on the frame's contrast
#: statistic ``g`` (mean |ΔxP| + |ΔyP| of the prefiltered frame, gray levels; the adaptive
#: threshold is ``clip(0.4 g, 1.5, 10)``). With the adaptive threshold the code mixture
#: still depends on ``g``: below g = 3.75 θ sits at its floor and noise weighs more; above
#: g = 12 (gravel, grass, rough ground at full contrast) the sensor noise is small against
#: θ and the slow channels fire more cleanly. A third class without calibration flights
#: over such ground was 6–7 points worse at 0.25 px/frame; with them (the ``fractal-…-60``
#: sets) it read 0.25 px/frame within 7.6–11.6 % instead of 14–19 % (with the former offset
#: brightness compensation; with the gain compensation 5.4–15.8 %, and since its threshold
#: is 256 T + 128, 6.2–10.7 %, see ``emdflow.summary``).
#: The paper's model has a single class (its layout is unchanged).
CONTRAST_EDGES = {"paper": (), "extended": (3.75, 12.0)}
#: Per model, whether the table has one distribution per gradient-strength class of the
#: detections (``emdflow.params.GRADIENT_CLASS_STEPS``). For the extended model they take
#: much of the texture out of its slow channels' code mixture (random directions, both
#: tables fitted on the same flights: 8.8 % / 2.10° → 7.0 % / 1.81°, 0.25 px/frame 9.8 % →
#: 6.5 %; with the compensation's former threshold 8.3 % / 2.06° → 7.1 % / 1.91°, 10 % →
#: 9.6 %; with the former offset brightness compensation 8.3 % / 2.14° → 7.1 % / 1.94°,
#: 10 % → 8 %; before the rough-ground flights and the third contrast class 8.9 % / 2.21° →
#: 8.2 % / 1.95°, 24 % → 16 %); for the paper's model they gained little (8.9 % / 2.37° →
#: 8.6 % / 2.26°) at twice
#: the summary's cost and a worse 1 px/frame, so its table has none and the summary sums
#: the classes.
GRADIENT_CLASS_TABLES = {"paper": False, "extended": True}
#: A cell needs this much detection weight to stand on its own (else: nearest filled cell).
MIN_CELL_WEIGHT = 100.0
#: Calibration flights the committed edge tables were fitted on, per model (the recipe in
#: this module's docstring; named when a fit has too few).
COMMITTED_FLIGHTS = {"paper": "9 000", "extended": "20 000"}


#: The axes that share a table: the horizontal and vertical detectors', and the diagonals'.
AXIS_GROUPS = ((0, 1), (2, 3))


def crossing_geometry(axes=(0, 1)):
    """Per (axis, orientation bin) of ``axes``: unit normal (axes, 64, 2), the normal's
    signed component along the detector's step ``n_a`` (``c = n·F / n_a`` is then the
    crossing speed in steps per frame: px along an axis, (1, ±1) steps along a diagonal)
    and ψ, the angle between the normal and the step, in degrees
    (:meth:`EngineParams.crossing_geometry`, which the summary reads too)."""
    from emdflow.params import EngineParams

    phi = EngineParams.orientation_centres()
    n = np.stack([np.cos(phi), np.sin(phi)], axis=1)  # (64, 2)
    n_axis, psi = EngineParams.crossing_geometry(axes)
    return np.stack([n] * len(axes)), n_axis, psi


def u_nodes(u_offset=U_OFFSET, u_count=U_COUNT):
    return np.linspace(math.log(u_offset), math.log(C_MAX + u_offset), u_count)


def accumulate_classes(hist, flow, u_offset=U_OFFSET, u_count=U_COUNT, axes=(0, 1)):
    """Detection weight ``N[gradient class, ψ, β, u, category]`` (see :func:`accumulate`)."""
    hist = np.asarray(hist)
    bins = ORIENTATION_BINS
    return np.stack([accumulate(hist[..., c * bins:(c + 1) * bins], flow, u_offset, u_count, axes)
                     for c in range(hist.shape[-1] // bins)])


def class_tables(Nc):
    """Conditional probabilities ``P[gradient class, ψ, β, u, category]`` and their weights,
    plus the all-classes table ``P_all[ψ, β, u, category]``: a cell of a class with less
    than ``MIN_CELL_WEIGHT`` of data takes the all-classes table's cell."""
    P_all, _ = table_from_counts(Nc.sum(axis=0))
    tot = Nc.sum(axis=-1)
    ok = (tot >= MIN_CELL_WEIGHT)[..., None]
    P = np.where(ok, Nc / np.maximum(tot, 1e-12)[..., None], P_all[None])
    return P, tot, P_all


def accumulate(hist, flow, u_offset=U_OFFSET, u_count=U_COUNT, axes=(0, 1)):
    """Detection weight ``N[ψ, β, u, category]`` from histograms with known flow (the
    gradient-strength classes summed), summed over the histogram ``axes`` (one group of
    :data:`AXIS_GROUPS`; ``hist`` holds those axes' rows only).

    ``category = 2·scale_index + (0 if the code's sign agrees with sign(c) else 1)``;
    every histogram bin is spread over the 8 surrounding grid nodes (trilinear weights).
    """
    hist = np.asarray(hist, np.float64)  # (frames, axes of the group, codes, classes · 64)
    hist = hist.reshape(*hist.shape[:3], -1, ORIENTATION_BINS).sum(axis=3)  # the classes summed
    flow = np.asarray(flow, np.float64)
    n_frames, _, n_codes, n_bins = hist.shape
    normals, n_axis, psi = crossing_geometry(axes)
    vn = np.einsum("fj,abj->fab", flow, normals)  # normal speed
    speed = np.maximum(np.hypot(flow[:, 0], flow[:, 1]), 1e-9)[:, None, None]
    c = vn / n_axis
    beta = np.sqrt(np.clip(1.0 - (vn / speed) ** 2, 0.0, 1.0))
    shape = (len(PSI_NODES_DEG), len(BETA_NODES), u_count, n_codes)
    ui, uf = interp_weights(np.log(np.abs(c) + u_offset), u_nodes(u_offset, u_count))
    bi, bf = interp_weights(beta, BETA_NODES)
    pi, pf = interp_weights(psi, PSI_NODES_DEG)
    pi = np.broadcast_to(pi, c.shape)
    pf = np.broadcast_to(pf, c.shape)
    codes = np.arange(n_codes)
    cat = np.where((c < 0)[..., None], codes ^ 1, codes)  # (f, a, b, code)
    h = np.moveaxis(hist, 2, 3)  # (f, a, b, code)
    N = np.zeros(int(np.prod(shape)))
    for dp, wp in ((0, 1 - pf), (1, pf)):
        for db, wb in ((0, 1 - bf), (1, bf)):
            for du, wu in ((0, 1 - uf), (1, uf)):
                w = (wp * wb * wu)[..., None] * h
                cell = ((pi + dp) * shape[1] + (bi + db)) * shape[2] + (ui + du)
                idx = cell[..., None] * n_codes + cat
                N += np.bincount(idx.ravel(), weights=w.ravel(), minlength=N.size)
    return N.reshape(shape)


def table_from_counts(N):
    """Conditional probabilities ``P[ψ, β, u, category]``.

    A cell with less than ``MIN_CELL_WEIGHT`` of data takes the distribution of the nearest
    filled cell of the same ψ (distance in grid steps of β and u).
    """
    tot = N.sum(-1)
    P = np.zeros_like(N)
    nb, nu = N.shape[1:3]
    bb, uu = np.meshgrid(np.arange(nb), np.arange(nu), indexing="ij")
    for p in range(N.shape[0]):
        ok = tot[p] >= MIN_CELL_WEIGHT
        if not ok.any():
            raise RuntimeError(f"no calibration data at ψ node {p}")
        ob, ou = bb[ok], uu[ok]
        for b in range(nb):
            for u in range(nu):
                if ok[b, u]:
                    src = (b, u)
                else:
                    j = np.argmin(2.0 * np.abs(ob - b) + np.abs(ou - u))
                    src = (ob[j], ou[j])
                P[p, b, u] = N[p][src] / tot[p][src]
    return P, tot


#: Frames ``fit`` accumulates at a time: the extended model's calibration is ~170 000
#: frames of 10 240 histogram bins (7 GB as int32, several times that as the float64
#: weights of one pass). The paper's 36 000 frames are a single chunk, so its table is
#: the same to the last bit as when everything was accumulated at once.
FIT_CHUNK_FRAMES = 40_000


def _frame_chunks(data, model: str, params, samples: int, chunk: int = FIT_CHUNK_FRAMES):
    """The frames of all files ``data``, in order, as ``(hist, flow, g)`` arrays of at most
    ``chunk`` frames (``g`` the frame's contrast statistic, gray levels)."""
    from emdflow.reference import STAT_CONTRAST

    parts, count = [], 0
    for path in data:
        with np.load(path) as d:
            recorded = recorded_model(d)
            if recorded != model:
                raise SystemExit(f"{path}: flights of the {recorded!r} model, not {model!r}")
            if d["hist"].shape[2] != 2 * len(params.channels):
                raise SystemExit(f"{path}: histograms do not match the {model!r} channels")
            hist, flow = d["hist"], d["flow"]
            g = d["stats"][:, STAT_CONTRAST] / samples
        start = 0
        while start < len(hist):
            take = min(chunk - count, len(hist) - start)
            parts.append((hist[start:start + take], flow[start:start + take], g[start:start + take]))
            count += take
            start += take
            if count == chunk:
                yield tuple(np.concatenate(a) for a in zip(*parts))
                parts, count = [], 0
        del hist, flow, g
    if parts:
        yield tuple(np.concatenate(a) for a in zip(*parts))


def fit_main(data, write, model="paper", ground="edges"):
    diagonal = has_diagonal(data)
    mode = stored_threshold_mode(data, model)  # (a table for the mode its flights were flown with)
    settings = stored_engine_settings(data, model)  # (and the other settings it depends on)
    params = model_params(model, diagonal, mode)
    samples = params.contrast_samples(320, 240)  # collect renders 320x240
    u_offset, u_count = U_GRID[model]
    edges = CONTRAST_EDGES[model]
    groups = AXIS_GROUPS if diagonal else AXIS_GROUPS[:1]
    # detection weight per axis group and contrast class
    counts = [[None] * (len(edges) + 1) for _ in groups]
    frames = [0] * (len(edges) + 1)
    for hist, flow, g in _frame_chunks(data, model, params, samples):
        cls = np.searchsorted(np.asarray(edges, np.float64), g, side="right")
        for c in range(len(edges) + 1):
            m = cls == c
            if not m.any():
                continue
            for j, axes in enumerate(groups):
                # (a group's axes are neighbours: one copy of the class's frames, its axes only)
                group_hist = hist[m, axes[0]:axes[-1] + 1]
                Nc = accumulate_classes(group_hist, flow[m], u_offset, u_count, axes)
                counts[j][c] = Nc if counts[j][c] is None else counts[j][c] + Nc
            frames[c] += int(m.sum())
        del hist, flow, g
    arrays = {}
    for j, (axes, group_counts) in enumerate(zip(groups, counts)):
        suffix = "" if j == 0 else "_diagonal"
        Ps, tots, P_all = [], [], []
        filled_classes = [c for c, Nc in enumerate(group_counts) if Nc is not None]
        for c, Nc in enumerate(group_counts):
            print(f"axes {axes}, contrast class {c}: {frames[c]} frames")
            if Nc is None and ground != "edges" and filled_classes:
                # a ground table may lack a contrast class (no thin-line ground as rough as
                # gravel): the nearest class with flights stands in for it
                near = min(filled_classes, key=lambda k: abs(k - c))
                print(f"  no frames: contrast class {near}'s distributions stand in")
                Nc = group_counts[near]
            if Nc is None:
                raise SystemExit(f"no calibration frames in contrast class {c} (edges {edges})")
            try:
                P, tot, P_all_c = class_tables(Nc)
            except RuntimeError as exc:  # (table_from_counts: a ψ node without a filled cell)
                raise SystemExit(f"axes {axes}, contrast class {c}: {exc}: {frames[c]} frames are too few "
                                 f"to fit a table (the committed edge table's recipe collects "
                                 f"{COMMITTED_FLIGHTS[model]} flights of 4-8 ready frames: collect "
                                 "more)") from None
            P_all.append(P_all_c)
            filled = (tot >= MIN_CELL_WEIGHT).mean(axis=(2, 3))
            for k, row in enumerate(filled):
                print(f"  gradient class {k}: filled share per ψ node:", " ".join(f"{x:.2f}" for x in row))
            Ps.append(P)
            tots.append(tot)
        P, tot = (Ps[0], tots[0]) if not edges else (np.stack(Ps), np.stack(tots))
        prob_all = P_all[0] if not edges else np.stack(P_all)
        if GRADIENT_CLASS_TABLES[model]:
            arrays["prob_all" + suffix] = prob_all.astype(np.float32)
        else:  # one distribution for all classes (the summary sums the histogram's classes)
            P, tot = prob_all, tot.sum(axis=-4)
        arrays["prob" + suffix] = P.astype(np.float32)
        arrays["weight" + suffix] = tot.astype(np.float32)
    out = calibration_path(model, ground, diagonal, mode)
    if write:
        extra = {}
        if GRADIENT_CLASS_TABLES[model]:
            extra["gradient_class_steps"] = np.asarray(GRADIENT_CLASS_STEPS, np.int64)
        # (the paper's table too: the summary prefers a table of the engine's threshold mode)
        extra.update(threshold_mode=np.array(params.threshold_mode))
        # the settings besides the channels that the table depends on (summary.calibration_mismatch)
        extra.update(engine_settings=np.array(json.dumps(settings)))
        if model != "paper":
            extra.update(channels=np.array(params.channels, np.int64), model=np.array(model))
        if edges:
            extra.update(contrast_edges=np.asarray(edges, np.float64))
        if ground != "edges":
            extra.update(ground=np.array(ground))
        np.savez_compressed(
            out, **arrays, psi_nodes_deg=np.asarray(PSI_NODES_DEG),
            beta_nodes=np.asarray(BETA_NODES), u_nodes=u_nodes(u_offset, u_count),
            u_offset=np.float64(u_offset), speeds=np.array(params.speeds, np.float64), **extra,
        )
        print(f"wrote {out}")
        write_misfit(data, model, out, ground=ground)

#: Speeds (px/frame) at which a table stores the calibration flights' median
#: :attr:`FlowSummary.deviance` (the baseline of the summary's misfit term), from this
#: many frames drawn (seeded) from the calibration files.
MISFIT_SPEEDS = (0.2, 0.35, 0.6, 1.0, 1.7, 3.0, 5.0, 8.0, 13.0, 20.0)
MISFIT_FRAMES = 4000
MISFIT_SEED = 20241122


def misfit_baseline(data, model: str, frames: int = MISFIT_FRAMES, seed: int = MISFIT_SEED,
                    min_frames: int = 30, ground: str = "edges"):
    """Median :attr:`FlowSummary.deviance` of calibration frames per node of
    :data:`MISFIT_SPEEDS`, by the summary's own speed (frames whose estimate falls between
    the midpoints, in log speed, around the node; a node with fewer than ``min_frames``
    frames is interpolated from its neighbours), the summary reading ``ground``'s table
    alone (which must already be written). Returns ``(median per node, frames per node)``."""
    from emdflow import summarize
    from emdflow.field import FlowField
    from emdflow.reference import STAT_FIRST_CHANGED
    from emdflow.summary import SummaryOptions, calibration_for

    params = model_params(model, has_diagonal(data), stored_threshold_mode(data, model))
    if calibration_for(params, ground) is None:
        # summarize() would read another table and the baseline would be that table's
        raise SystemExit(f"misfit baseline: the {model!r} model has no {ground} table to measure")
    options = SummaryOptions(ground=ground)
    sizes = []
    for path in data:
        with np.load(path) as d:
            sizes.append(len(d["flow"]))
    pick = np.sort(np.random.default_rng(seed).choice(sum(sizes), min(frames, sum(sizes)), replace=False))
    codes = np.zeros((240, 320), np.int8)  # collect renders 320x240
    deviance, speed = [], []
    start = 0
    for path, size in zip(data, sizes):
        rows = pick[(pick >= start) & (pick < start + size)] - start
        start += size
        with np.load(path) as d:
            hist, stats = d["hist"][rows], d["stats"][rows]
        if stats.shape[1] != STAT_FIRST_CHANGED + len(params.channels):
            raise SystemExit(f"{path}: {stats.shape[1]} statistics per frame, the engine now makes "
                             f"{STAT_FIRST_CHANGED + len(params.channels)}: collect it again")
        for hi, st in zip(hist, stats):
            s = summarize(FlowField(codes, codes, st, hi, params, params.history_frames + 1),
                          options=options)
            if s.quality > 0 and not s.static:
                deviance.append(s.deviance)
                speed.append(s.speed)
    nodes = np.log(np.asarray(MISFIT_SPEEDS))
    edges = np.concatenate([[-np.inf], (nodes[1:] + nodes[:-1]) / 2, [np.inf]])
    which = np.searchsorted(edges, np.log(np.maximum(speed, 1e-3)), side="right") - 1
    deviance = np.asarray(deviance)
    counts = np.bincount(which, minlength=nodes.size)
    median = np.array([np.median(deviance[which == i]) if counts[i] >= min_frames else np.nan
                       for i in range(nodes.size)])
    filled = np.isfinite(median)
    if not filled.any():
        raise SystemExit("misfit baseline: no calibration frame gave a likelihood fit")
    return np.interp(nodes, nodes[filled], median[filled]), counts


def write_misfit(data, model: str, path: Path | None = None, ground: str = "edges",
                 **baseline_options) -> Path:
    """Add the misfit baseline (:func:`misfit_baseline` of ``data``) to ``model``'s table
    for ``ground`` (``path``: another copy of it)."""
    import emdflow.summary as summary

    if path is None:
        path = calibration_path(model, ground, has_diagonal(data), stored_threshold_mode(data, model))
    path = Path(path)
    with np.load(path) as z:
        table = {k: z[k] for k in z.files if k not in ("misfit_speeds", "misfit_baseline")}
    # the summary reads the tables as they are on disk now (the deviance does not depend
    # on an old baseline: it is measured at the answer, which the misfit term leaves alone)
    summary._CALIBRATION.clear()
    summary._MODEL_CACHE.clear()
    baseline, counts = misfit_baseline(data, model, ground=ground, **baseline_options)
    print("misfit baseline (median deviance per detection) at", " ".join(
        f"{v:g}: {b:.3f} ({n})" for v, b, n in zip(MISFIT_SPEEDS, baseline, counts)))
    np.savez_compressed(path, **table, misfit_speeds=np.asarray(MISFIT_SPEEDS, np.float64),
                        misfit_baseline=baseline.astype(np.float64))
    summary._CALIBRATION.clear()
    summary._MODEL_CACHE.clear()
    print(f"wrote the misfit baseline into {path}")
    return path


EVALUATION_TEXTURES = ("gravel", "brick", "grass", "camera")
EVALUATION_SPEEDS = (1, 2, 3, 4, 5, 7, 9, 11, 13)
#: Per model: the speeds of the evaluation flights (the extended model's slow channels
#: are for 0.25–0.5 px/frame).
MODEL_EVALUATION_SPEEDS = {"paper": EVALUATION_SPEEDS,
                           "extended": (0.25, 0.5, 1, 2, 3, 5, 7, 9, 11, 13)}
#: Seed of the random-direction evaluation set (``evaluate --random``).
RANDOM_DIRECTIONS_SEED = 4242


def _directions(offset, random_set, speeds=EVALUATION_SPEEDS, textures=EVALUATION_TEXTURES):
    """The 8 flight directions (radians) of one (speed, texture) cell, as a function of
    the cell's index (the random set draws fresh directions per cell)."""
    if not random_set:
        return lambda cell: [a * math.pi / 4 + offset for a in range(8)]
    rng = np.random.default_rng(RANDOM_DIRECTIONS_SEED)
    table = rng.uniform(0.0, 2.0 * math.pi, (len(speeds) * len(textures), 8))
    return lambda cell: list(table[cell])


def render_evaluation(offset: float = 0.0, random_set: bool = False, frames: int = 6,
                      backend: str = "opencl", width=320, height=240, model: str = "paper",
                      contrast: float = 1.0, drift: float = 0.0, evidence_row_step: int = 0,
                      noise: float = 2.0, textures=EVALUATION_TEXTURES, diagonal: bool = True,
                      threshold_mode: str | None = None, engine_options=None):
    """Flights over the evaluation textures: the model's speeds (9 for the paper's model,
    10 from 0.25 px/frame for the extended one) × 4 textures × 8 directions (multiples of
    45° plus ``offset`` radians, or random directions), sensor noise σ = ``noise`` gray
    levels (2 unless told; the calibration flights draw it from 1–3), scene ``contrast``
    and an exposure ramp of ``drift`` (relative) across each whole flight, ``frames``
    ready frames each; ``evidence_row_step`` as in :class:`emdflow.EngineParams` (0:
    automatic); ``textures`` the grounds flown over (the evaluation set unless told: the
    calibration set measures how well a table fits its own ground); ``engine_options``
    other engine settings than the model's (:func:`engine_option_values`: what the summary
    reads with a table measured with the model's). Returns the histograms, statistics and
    true flows."""
    _checked_noise(noise, noise, f"noise={noise!r}")
    from emdflow import FlowEstimator
    from emdflow.synthetic import CameraFlight, load_texture

    est = FlowEstimator(width, height, backend=backend,
                        **dict(model_options(model, diagonal, threshold_mode), **(engine_options or {})),
                        evidence_row_step=evidence_row_step)
    warm = est.params.history_frames
    speeds = MODEL_EVALUATION_SPEEDS[model]
    directions = _directions(offset, random_set, speeds, textures)
    hists, stats, flows, names = [], [], [], []
    cell = 0
    for sp in speeds:
        for texture in textures:
            for a, th in enumerate(directions(cell)):
                fu, fv = sp * math.cos(th), sp * math.sin(th)
                # the path of the frames the one-frame templates see (from frame warm − 3;
                # all of them for the paper's model) is centred on the photograph, so it
                # never runs past its border (the slow channels' older frames may, at
                # speeds they cannot see anyway)
                size = load_texture(texture).shape
                mid = (warm - 3 + frames + warm - 1) / 2
                start = (size[1] / 2 + fu * mid, size[0] / 2 + fv * mid)
                flight = CameraFlight(texture, width=width, height=height, flow=(fu, fv),
                                      noise_sigma=noise, seed=a, start=start, contrast=contrast,
                                      exposure_drift=drift, drift_frames=frames + warm)
                est.reset()
                for t in range(frames + warm):
                    field = est.update(flight.render(t))
                    if field.ready:
                        hists.append(field.histogram.copy())
                        stats.append(field.stats.copy())
                        flows.append((fu, fv))
                        names.append(texture)
            cell += 1
    return dict(hist=np.array(hists), stats=np.array(stats), flow=np.array(flows),
                shape=np.array([height, width]), frame_index=warm + 1, model=np.array(model),
                flight_frames=np.array(frames), texture=np.array(names),
                threshold_mode=np.array(est.params.threshold_mode),
                engine_settings=np.array(json.dumps(est.params.calibration_settings())))


def score(data, options=None, out=print):
    """summarize() every stored frame; prints median relative / direction error per speed
    (quality-0 frames count as 100 % / 180°), coverage (share of frames with quality > 0),
    a quality-band table, how much of the error each flight keeps in all its frames (when
    the data store ``flight_frames``), each texture's median speed reading and direction
    error per speed (when they store ``texture``) and the mean time per :func:`summarize`
    call. Returns
    ``(errors (n, 2), quality (n,))``."""
    from emdflow import summarize

    fields, flows = _stored_fields(data)
    summarize(fields[0], options=options)  # builds the cached tables
    t0 = time.perf_counter()
    sums = [summarize(f, options=options) for f in fields]
    spent = (time.perf_counter() - t0) / max(1, len(fields))
    speed = np.hypot(flows[:, 0], flows[:, 1])
    err = np.empty((len(sums), 2))
    qual = np.array([s.quality for s in sums])
    for i, (s, (fu, fv)) in enumerate(zip(sums, flows)):
        err[i] = _frame_error(s, fu, fv)
    out("  speed | frames | median rel error | median direction error | coverage")
    for sp in np.unique(np.round(speed, 6)):
        m = np.isclose(speed, sp)
        out(f"  {sp:5.4g} | {int(m.sum()):6d} | {np.median(err[m, 0]) * 100:5.1f} % "
            f"| {np.median(err[m, 1]):5.2f} deg | {np.mean(qual[m] > 0) * 100:5.1f} %")
    out(f"    all | {len(err):6d} | {np.median(err[:, 0]) * 100:5.1f} % "
        f"| {np.median(err[:, 1]):5.2f} deg | {np.mean(qual > 0) * 100:5.1f} %"
        f"   ({spent * 1e3:.3f} ms per summarize call)")
    out("  quality band | frames | median rel error | 90th pct rel error")
    for lo, hi in ((0, 1), (1, 64), (64, 128), (128, 192), (192, 256)):
        m = (qual >= lo) & (qual < hi)
        if m.any():
            out(f"    {lo:3d}-{hi - 1:3d}   | {int(m.sum()):6d} | {np.median(err[m, 0]) * 100:5.1f} % "
                f"| {np.percentile(err[m, 0], 90) * 100:5.1f} %")
    rated = qual > 0
    expected = np.array([s.expected_error for s in sums])
    # (a static frame's expected error is 0 by definition: not an estimate of its error)
    usable = rated & np.isfinite(expected) & ~np.array([s.static for s in sums], bool)
    if usable.any():  # how the summary's own error estimate compares with the error
        out(f"  expected error: median {np.median(expected[usable]) * 100:.1f} % against a median error of "
            f"{np.median(err[usable, 0]) * 100:.1f} % (frames with quality > 0, not static)")
    if "flight_frames" in data:
        _print_flight_bias(sums, flows, int(data["flight_frames"]), out)
    if "texture" in data:
        _print_texture_speed(sums, flows, np.asarray(data["texture"]), out)
        _print_texture_direction(err, flows, np.asarray(data["texture"]), out)
        _print_line_share(sums, flows, np.asarray(data["texture"]), out)
    _print_search_check(fields, sums, flows, err, options, out)
    if rated.sum() > 2:
        from scipy.stats import spearmanr

        # how well quality ranks the frames by error: 1 = perfectly, 0 = not at all
        out(f"  rank correlation of quality with -error (Spearman, quality > 0): "
            f"{spearmanr(qual[rated], -err[rated, 0])[0]:.2f}")
    return err, qual


def _stored_fields(data):
    """The frames of stored flights (``evaluate --save``: histograms, statistics, their
    model and frame size) as :class:`FlowField` objects for :func:`summarize`, and their
    true flows (n, 2)."""
    from emdflow.field import FlowField
    from emdflow.params import EngineParams

    h, w = (int(x) for x in data["shape"])
    codes = np.zeros((h, w), np.int8)
    options = model_options(recorded_model(data), np.asarray(data["hist"]).shape[1] == 4,
                            str(data["threshold_mode"]) if "threshold_mode" in data else None)
    if "engine_settings" in data:  # (flown with other settings: the summary says if its table was not)
        options.update(json.loads(str(data["engine_settings"])))
    params = EngineParams(**options)
    fields = [FlowField(codes, codes, st, hi, params, int(data["frame_index"]))
              for hi, st in zip(data["hist"], data["stats"])]
    return fields, np.asarray(data["flow"], np.float64)


def _print_by_texture_and_speed(title, values, reduce, cell_format, flows, textures, out=print):
    """A table of ``reduce(values)`` over the frames of each speed (rows) and texture
    (columns), nan where a texture has no frame at a speed."""
    flows = np.asarray(flows, np.float64)
    speed = np.hypot(flows[:, 0], flows[:, 1])
    names = list(dict.fromkeys(str(t) for t in textures))
    out(f"  {title}: speed | " + " | ".join(f"{n:>7s}" for n in names))
    for sp in np.unique(np.round(speed, 6)):
        at = np.isclose(speed, sp)
        cells = []
        for n in names:
            m = at & (textures == n)
            cells.append(reduce(values[m]) if m.any() else math.nan)
        out(f"    {sp:5.4g} | " + " | ".join(cell_format.format(c) for c in cells))


def _print_texture_speed(sums, flows, textures, out=print):
    """Per speed and texture, the median of the speed the summary reads over the true speed
    (a quality-0 frame reads 0): whether a texture reads fast or slow, which the error
    medians do not say."""
    speed = np.hypot(*np.asarray(flows, np.float64).T)
    read = np.array([s.speed if s.quality > 0 else 0.0 for s in sums]) / np.maximum(speed, 1e-12)
    _print_by_texture_and_speed("median speed read / true, by texture", read, np.median, "{:7.3f}",
                                flows, textures, out)


def _print_texture_direction(err, flows, textures, out=print):
    """Per speed and texture, the median direction error (degrees; a quality-0 frame
    counts as 180°): which grounds the direction error of a speed comes from."""
    _print_by_texture_and_speed("median direction error (deg), by texture", np.asarray(err)[:, 1],
                                np.median, "{:7.2f}", flows, textures, out)


def _print_line_share(sums, flows, textures, out=print):
    """Per speed and texture, the share of frames whose answer is the line-ground table's
    (:attr:`FlowSummary.line_ground`); nothing when no frame's is."""
    on_lines = np.array([s.line_ground for s in sums])
    if on_lines.any():
        _print_by_texture_and_speed("share of frames read with the line-ground table",
                                    on_lines * 100.0, np.mean, "{:5.0f} %", flows, textures, out)


def margin_sweep(paths, margins, out=print):
    """:attr:`SummaryOptions.line_ground_margin` against accuracy: for each stored set of
    flights (``evaluate --save``) and each margin, the median relative and direction error
    of all frames and each texture's median relative error and share of frames read with
    the line-ground table (``ground="edges"``: the edge table alone, for reference)."""
    from emdflow import summarize
    from emdflow.summary import SummaryOptions

    for path in paths:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
        if "texture" not in data:
            raise SystemExit(f"{path}: no texture names (an older evaluate --save): render it again")
        model = recorded_model(data)
        fields, flows = _stored_fields(data)
        textures = np.asarray(data["texture"])
        names = list(dict.fromkeys(str(t) for t in textures))
        out(f"{path}: {len(fields)} frames, {model} model; per texture: relative error "
            "(share read with the line table)")
        out("  margin | all speeds | " + " | ".join(names))
        for margin in [None, *margins]:
            options = (SummaryOptions(ground="edges") if margin is None
                       else SummaryOptions(line_ground_margin=margin))
            sums = [summarize(f, options=options) for f in fields]
            err = np.array([_frame_error(s, fu, fv) for s, (fu, fv) in zip(sums, flows)])
            on_lines = np.array([s.line_ground for s in sums])
            cells = [f"{np.median(err[textures == n, 0]) * 100:4.1f} % "
                     f"({np.mean(on_lines[textures == n]) * 100:3.0f} %)" for n in names]
            label = "edges" if margin is None else f"{margin:g}"
            out(f"  {label:>6s} | {np.median(err[:, 0]) * 100:4.1f} % / {np.median(err[:, 1]):4.2f} deg | "
                + " | ".join(cells))


def _frame_error(s, fu: float, fv: float) -> tuple[float, float]:
    """(relative error, direction error in degrees) of summary ``s`` against the true flow,
    as ``emdflow eval`` counts it (:func:`emdflow.tools.evaluate.summary_errors`): a
    quality-0 frame is (1, 180), and so is the direction of a zero reading (a static
    reading of a moving flight scored the true flow's polar angle)."""
    from emdflow.tools.evaluate import summary_errors

    return summary_errors(s.flow_x, s.flow_y, s.quality, fu, fv)


def _print_search_check(fields, sums, flows, err, options=None, out=print, limit_deg: float = 3.0):
    """Of the frames whose direction is more than ``limit_deg`` off, how many the search
    failed (the true flow explains the detections better than the answer: a search
    problem) and how many the model failed (the table prefers the wrong answer: what a
    better search cannot fix)."""
    from emdflow.summary import _log_likelihood_at

    wrong = missed = 0
    for field, s, (fu, fv), e in zip(fields, sums, flows, err):
        if s.quality == 0 or s.static or e[1] <= limit_deg:
            continue
        values = _log_likelihood_at(field, [(fu, fv), (s.flow_x, s.flow_y)], options,
                                    "lines" if s.line_ground else "edges")
        if values is None:
            continue
        wrong += 1
        missed += values[0] > values[1]
    if wrong:
        out(f"  frames more than {limit_deg:g} deg off: {wrong}; the true flow is more likely than the "
            f"answer in {missed} ({missed / wrong * 100:.0f} %: the search missed it), less likely in "
            f"{wrong - missed} (the table prefers the wrong answer)")


def _print_flight_bias(sums, flows, per_flight: int, out=print):
    """How much of the error is the flight's (the scene's and direction's: the same in all
    of its frames) and how much the frame's: the median over flights of the absolute mean
    signed error, and of the spread (standard deviation) of the signed error within each
    flight, for the direction (degrees) and the speed (log of measured / true speed, as
    %). Flights with a quality-0 frame are left out."""
    n = len(sums) // per_flight
    if per_flight < 2 or n == 0 or n * per_flight != len(sums):
        return
    quality = np.array([s.quality for s in sums]).reshape(n, per_flight)
    est = np.array([(s.flow_x, s.flow_y) for s in sums])
    direction = np.degrees(np.arctan2(est[:, 1], est[:, 0]) - np.arctan2(flows[:, 1], flows[:, 0]))
    direction = ((direction + 180.0) % 360.0 - 180.0).reshape(n, per_flight)
    speed = np.log(np.maximum(np.hypot(est[:, 0], est[:, 1]), 1e-9)
                   / np.hypot(flows[:, 0], flows[:, 1])).reshape(n, per_flight)
    ok = (quality > 0).all(axis=1)
    if not ok.any():
        return
    out(f"  per flight ({int(ok.sum())} flights of {per_flight} frames): median |flight mean| "
        f"/ median spread within a flight: direction "
        f"{np.median(np.abs(direction[ok].mean(axis=1))):.2f} / {np.median(direction[ok].std(axis=1)):.2f} deg, "
        f"speed {np.median(np.abs(speed[ok].mean(axis=1))) * 100:.1f} / "
        f"{np.median(speed[ok].std(axis=1)) * 100:.1f} %")


def _keyword_values(items, defaults: dict) -> dict:
    """``KEY=VALUE`` items as keywords of ``defaults`` (name: default value), each value
    converted to its default's type (ValueError naming what is wrong): true/false or 1/0,
    an int, a string, else a number (or "none")."""
    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or key not in defaults:
            raise ValueError(f"{item!r}: expected KEY=VALUE with KEY one of {', '.join(defaults)}")
        default = defaults[key]
        try:
            if isinstance(default, bool):
                if text.lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                value = text.lower() in ("true", "1")
            elif isinstance(default, int):
                value = int(text)
            elif isinstance(default, str):
                value = text
            else:  # floats, and top_speed (None or a number)
                value = None if text.lower() == "none" else float(text)
        except ValueError:
            raise ValueError(f"{item!r}: {text!r} is not a value for {key}") from None
        out[key] = value
    return out


def summary_option_values(items) -> dict:
    """``--summary-opt KEY=VALUE`` items as SummaryOptions keywords, each value converted to
    its field's type (ValueError naming what is wrong)."""
    from emdflow.summary import SummaryOptions

    return _keyword_values(items, {f.name: f.default for f in dataclasses.fields(SummaryOptions)})


#: ``--engine-opt`` keys of ``evaluate``: the settings a table depends on besides the
#: channels (``EngineParams.calibration_settings``; the threshold mode has its own option)
ENGINE_OPTIONS = ("threshold", "prefilter_size", "sharp_templates", "brightness_compensation", "adaptive_gain",
                  "threshold_min", "threshold_max", "threshold_tile")


def engine_option_values(items) -> dict:
    """``--engine-opt KEY=VALUE`` items as ``FlowEstimator`` keywords of
    :data:`ENGINE_OPTIONS`, each value converted to its type (ValueError naming what is
    wrong; the value's range is EngineParams' to check)."""
    defaults = {f.name: f.default for f in dataclasses.fields(EngineParams)}
    return _keyword_values(items, {name: defaults[name] for name in ENGINE_OPTIONS})


def evaluate(offset: float, random_set: bool = False, frames: int = 6, backend: str = "opencl",
             save: str | None = None, data: str | None = None, model: str = "paper",
             contrast: float = 1.0, drift: float = 0.0, options=None, evidence_row_step: int = 0,
             width: int = 320, height: int = 240, noise: float = 2.0,
             textures=EVALUATION_TEXTURES, diagonal: bool = True, threshold_mode: str | None = None,
             engine_options=None):
    """Render (or load with ``data``) the evaluation flights (``width`` × ``height`` frames,
    over ``textures``; ``diagonal``: with the diagonal detectors' evidence, the default;
    ``engine_options``: other engine settings, :func:`engine_option_values`) and
    :func:`score` them.

    Raises
    ------
    ToolError
        Code 2 when the file ``data`` does not exist or holds no stored flights.
    """
    if data:
        if problem := stored_flights_problem(data, scored=True):
            raise ToolError(f"--data {data}: {problem}", 2)
        with np.load(data) as z:
            flights = {k: z[k] for k in z.files}
        stored = str(flights["threshold_mode"]) if "threshold_mode" in flights else None
        if threshold_mode is not None and threshold_mode != stored:
            raise ToolError(f"--threshold-mode {threshold_mode}: the flights of --data {data} were flown with "
                            f"{stored or 'the model' + chr(39) + 's own'} threshold", 2)
        label = data
    else:
        flights = render_evaluation(offset, random_set, frames, backend, width, height, model=model,
                                    contrast=contrast, drift=drift,
                                    evidence_row_step=evidence_row_step, noise=noise,
                                    textures=textures, diagonal=diagonal, threshold_mode=threshold_mode,
                                    engine_options=engine_options)
        label = "random directions" if random_set else f"offset {offset} rad"
        if (width, height) != (320, 240):
            label += f", {width}x{height}"
        label += f", {model} model"
        if contrast != 1.0:
            label += f", contrast x{contrast:g}"
        if drift:
            label += f", exposure drift {drift:+g}"
        if noise != 2.0:
            label += f", noise sigma {noise:g}"
        if evidence_row_step:
            label += f", evidence every {evidence_row_step} row(s)"
        if not diagonal:
            label += ", without diagonal evidence"
        if threshold_mode is not None:
            label += f", {threshold_mode} threshold"
        for key, value in (engine_options or {}).items():
            label += f", {key}={value}"
        if tuple(textures) != EVALUATION_TEXTURES:
            label += f", over {','.join(textures)}"
        if save:
            with open(save, "wb") as fh:  # exactly ``save`` (numpy would append .npz to a path)
                np.savez_compressed(fh, **flights)
    print(f"{label}: {len(flights['flow'])} frames")
    return score(flights, options)


def _positive_range(ap, option: str, text: str, unit: str) -> tuple[float, float]:
    """``lo,hi`` of ``option`` as floats with ``0 < lo <= hi < inf``, else ``ap.error``
    (exit 2) naming the option."""
    try:
        lo, hi = (float(x) for x in text.split(","))  # ValueError unless two numbers
    except ValueError:
        lo = hi = math.nan
    if not (math.isfinite(hi) and 0.0 < lo <= hi):
        ap.error(f"{option} {text!r}: expected lo,hi with 0 < lo <= hi ({unit})")
    return lo, hi


def _check_textures(ap, textures, text: str) -> None:
    """``ap.error`` (exit 2) unless every name of ``--textures`` is a ground the flights know."""
    from emdflow.synthetic import load_texture

    if not all(textures):
        ap.error(f"--textures {text!r}: expected comma-separated texture names")
    if problem := texture_names_problem(textures, load_texture):
        ap.error(f"--textures: {problem}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--flights", type=int, default=480)
    c.add_argument("--frames", type=int, default=7)
    c.add_argument("--seed", type=int, default=20240601)
    c.add_argument("--out", default="/tmp/emdflow_calib.npz")
    c.add_argument("--textures", default=",".join(CALIBRATION_TEXTURES),
                   help="comma-separated texture names (default: the calibration set)")
    c.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    c.add_argument("--scale-range", default="1,1",
                   help="ground scale range lo,hi (texture px per image px, log-uniform)")
    c.add_argument("--model", default="paper", choices=tuple(MODELS),
                   help="detector model (channel set and threshold mode) to calibrate")
    c.add_argument("--contrast-range", default=None,
                   help="scene contrast range lo,hi (default: the model's, see COLLECT_RANGES)")
    c.add_argument("--evidence-row-step", type=int, default=0,
                   help="rows between the rows that feed the histograms (EngineParams; default "
                        "0: automatic)")
    c.add_argument("--diagonal-evidence", action=argparse.BooleanOptionalAction, default=True,
                   help="with (default) or without the diagonal detectors' evidence (EngineParams."
                        "diagonal_evidence; without: the horizontal and vertical detectors' tables)")
    c.add_argument("--threshold-mode", choices=THRESHOLD_MODES, default=None,
                   help="fly this threshold mode instead of the model's (EngineParams.threshold_mode; "
                        "fit then writes the table under its own name, e.g. _extended_local_)")
    c.add_argument("--noise-range", default="1,3",
                   help="sensor noise range lo,hi of the flights, gray levels (uniform; default "
                        "1,3, as the committed tables were made)")
    f = sub.add_parser("fit")
    f.add_argument("data", nargs="+")
    f.add_argument("--write", action="store_true",
                   help="write emdflow/summary_calibration.npz (paper) or "
                        "emdflow/summary_calibration_<model>.npz (with --ground lines: "
                        "..._lines.npz)")
    f.add_argument("--model", default="paper", choices=tuple(MODELS))
    f.add_argument("--ground", default="edges", choices=GROUNDS,
                   help="the kind of ground the flights flew over: edges (the main table) or "
                        "lines (the line-ground table, summary_calibration[_<model>]_lines.npz)")
    m = sub.add_parser("misfit", help="(re)measure only the misfit baseline of a written table")
    m.add_argument("data", nargs="+")
    m.add_argument("--model", default="paper", choices=tuple(MODELS))
    m.add_argument("--ground", default="edges", choices=GROUNDS)
    g = sub.add_parser("margin", help="accuracy against SummaryOptions.line_ground_margin on "
                                      "flights stored by evaluate --save")
    g.add_argument("data", nargs="+")
    g.add_argument("--margins", default="0,5,10,15,20,30",
                   help="comma-separated margins to try, nats (default 0,5,10,15,20,30)")
    e = sub.add_parser("evaluate")
    e.add_argument("--threshold-mode", choices=THRESHOLD_MODES, default=None,
                   help="fly this threshold mode instead of the model's (its own table when one was fitted)")
    e.add_argument("--offset", type=float, default=0.3, help="direction offset, radians")
    e.add_argument("--random", action="store_true",
                   help="random directions (seeded) instead of multiples of 45° + offset")
    e.add_argument("--frames", type=int, default=6, help="ready frames per flight")
    e.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    e.add_argument("--save", help="also store the rendered histograms here (.npz)")
    e.add_argument("--data", help="score histograms stored by --save instead of rendering")
    e.add_argument("--model", default="paper", choices=tuple(MODELS))
    e.add_argument("--contrast", type=float, default=1.0, help="scene contrast factor")
    e.add_argument("--drift", type=float, default=0.0,
                   help="exposure drift across each flight (e.g. 0.2 for +20 %%)")
    e.add_argument("--ioc", action="store_true",
                   help="score the IoC fit alone (SummaryOptions(likelihood=False))")
    e.add_argument("--ground", default="auto", choices=("auto",) + GROUNDS,
                   help="the tables the summary reads (SummaryOptions.ground; default auto: the "
                        "edge table and, where it explains a frame better, the line-ground one)")
    e.add_argument("--evidence-row-step", type=int, default=0,
                   help="rows between the rows that feed the summary's evidence (EngineParams; "
                        "default 0: automatic, every 4th row at 240 px)")
    e.add_argument("--diagonal-evidence", action=argparse.BooleanOptionalAction, default=True,
                   help="with (default) or without the diagonal detectors' evidence (EngineParams."
                        "diagonal_evidence; without: the horizontal and vertical detectors' tables)")
    e.add_argument("--size", default="320x240",
                   help="frame size WxH of the flights (default 320x240, the size the tables "
                        "were calibrated at)")
    e.add_argument("--noise", type=float, default=2.0,
                   help="sensor noise of the flights, standard deviation in gray levels (default "
                        "2; the calibration flights draw it from 1-3)")
    e.add_argument("--summary-opt", action="append", default=[], metavar="KEY=VALUE",
                   help="a SummaryOptions field for the summary (repeatable), e.g. the former "
                        "quality weights: --summary-opt overdispersion=0.7 --summary-opt "
                        "disagreement_weight=0.5")
    e.add_argument("--engine-opt", action="append", default=[], metavar="KEY=VALUE",
                   help="fly other engine settings than the model's (repeatable; "
                        f"{', '.join(ENGINE_OPTIONS)}): the summary still reads the table measured "
                        "with the model's, e.g. --engine-opt threshold=10")
    e.add_argument("--textures", default=",".join(EVALUATION_TEXTURES),
                   help="comma-separated grounds of the flights (default: the evaluation set, "
                        "which the calibration never saw; the calibration set "
                        f"{','.join(CALIBRATION_TEXTURES)} measures how well a table fits "
                        "its own ground)")
    a = ap.parse_args(argv)
    # every option and file is checked here, before the flights (not as a traceback, or
    # an error after all of them)
    if a.cmd in ("fit", "misfit", "margin"):
        for path in a.data:
            if problem := stored_flights_problem(path, scored=a.cmd == "margin"):
                ap.error(f"data {path}: {problem}")
            if a.cmd != "margin":  # (margin reads each file's own model)
                with np.load(path) as stored:
                    flown = recorded_model(stored)
                if flown != a.model:
                    ap.error(f"data {path}: flights of the {flown} model, not --model {a.model}")
    if a.cmd in ("collect", "evaluate"):
        try:  # (EngineParams' own range, named by the option: a ValueError traceback before)
            EngineParams(evidence_row_step=a.evidence_row_step)
        except ValueError as exc:
            ap.error(f"--evidence-row-step {a.evidence_row_step}: {exc}")
    if a.cmd == "collect":
        textures = tuple(a.textures.split(","))
        bad = set(textures) & set(EVALUATION_TEXTURES)
        if bad:
            ap.error(f"--textures: {', '.join(sorted(bad))} belong to the evaluation set")
        _check_textures(ap, textures, a.textures)
        if a.flights < 1:
            ap.error(f"--flights {a.flights}: must be at least 1")
        history = model_params(a.model, a.diagonal_evidence).history_frames
        if a.frames < 1 or (a.model == "paper" and a.frames <= history):
            # (the paper's flights are --frames long in all, the first ones fill the history)
            least = history + 1 if a.model == "paper" else 1
            ap.error(f"--frames {a.frames}: must be at least {least} for the {a.model} model")
        if a.seed < 0:
            ap.error(f"--seed {a.seed}: must be >= 0")
        try:
            lo, hi = a.noise_range.split(",")  # ValueError unless two fields
            noise_range = _checked_noise(lo, hi, "--noise-range")
        except ValueError:
            ap.error(f"--noise-range {a.noise_range!r}: expected lo,hi with 0 <= lo <= hi (gray levels)")
        scale_range = _positive_range(ap, "--scale-range", a.scale_range, "texture px per image px")
        contrast_range = (_positive_range(ap, "--contrast-range", a.contrast_range, "contrast factor")
                          if a.contrast_range else None)
        if problem := output_problem(a.out):
            ap.error(f"--out {a.out}: {problem}")
        collect(a.flights, a.out, a.frames, a.seed, textures=textures,
                backend=a.backend, scale_range=scale_range, model=a.model,
                contrast_range=contrast_range,
                evidence_row_step=a.evidence_row_step, noise_range=noise_range,
                diagonal=a.diagonal_evidence, threshold_mode=a.threshold_mode)
    elif a.cmd == "fit":
        fit_main(a.data, a.write, a.model, a.ground)
    elif a.cmd == "misfit":
        table = calibration_path(a.model, a.ground, has_diagonal(a.data), stored_threshold_mode(a.data, a.model))
        if not table.is_file():
            ap.error(f"misfit --model {a.model} --ground {a.ground}: no table {table.name} to add the "
                     f"baseline to (fit --write --model {a.model} --ground {a.ground} makes it)")
        write_misfit(a.data, a.model, path=table, ground=a.ground)
    elif a.cmd == "margin":
        try:
            margins = [float(x) for x in a.margins.split(",")]
        except ValueError:
            ap.error(f"--margins {a.margins!r}: expected comma-separated numbers")
        if not all(map(math.isfinite, margins)):
            ap.error(f"--margins {a.margins!r}: expected finite numbers")
        margin_sweep(a.data, margins)
    else:
        from emdflow.summary import SummaryOptions

        try:  # (--summary-opt likelihood=... and ground=... override --ioc and --ground)
            options = SummaryOptions(**{"likelihood": not a.ioc, "ground": a.ground,
                                        **summary_option_values(a.summary_opt)})
        except (TypeError, ValueError) as exc:
            ap.error(f"--summary-opt: {exc}")
        from emdflow.tools.video_io import parse_size

        try:
            width, height = parse_size(a.size)
        except ValueError as exc:
            ap.error(f"--{exc}")  # "--size '...': expected WIDTHxHEIGHT, ..."
        if not a.data:  # (--data: the stored flights; evaluate() checks the file)
            if problem := frame_size_problem(width, height, dis=False):
                ap.error(f"--size {a.size}: {problem}")
            if a.save and (problem := output_problem(a.save)):
                ap.error(f"--save {a.save}: {problem}")
        if a.frames < 1:
            ap.error(f"--frames {a.frames}: must be at least 1")
        # (nan or inf flew a traceback; a negative contrast or a drift to -500 % garbage)
        if not math.isfinite(a.offset):
            ap.error(f"--offset {a.offset:g}: must be a finite number (radians)")
        try:
            check_positive("--contrast", a.contrast, "contrast factor")
        except ToolError as exc:
            ap.error(str(exc))
        if not (math.isfinite(a.drift) and a.drift > -1.0):
            ap.error(f"--drift {a.drift:g}: must be a finite number > -1 (relative exposure change)")
        try:
            _checked_noise(a.noise, a.noise, f"--noise {a.noise:g}")
        except ValueError as exc:
            ap.error(str(exc))
        textures = tuple(a.textures.split(","))
        _check_textures(ap, textures, a.textures)
        try:
            engine_options = engine_option_values(a.engine_opt)
            # (the range of each value, as the flights would meet it)
            EngineParams(**dict(model_options(a.model, a.diagonal_evidence, a.threshold_mode), **engine_options))
        except ValueError as exc:
            ap.error(f"--engine-opt: {exc}")
        if engine_options and a.data:
            ap.error("--engine-opt: --data scores stored flights, flown with the settings they were stored with")
        try:
            evaluate(a.offset, a.random, a.frames, a.backend, a.save, a.data, a.model, a.contrast,
                     a.drift, options, a.evidence_row_step, width, height, a.noise, textures,
                     a.diagonal_evidence, a.threshold_mode, engine_options)
        except ToolError as exc:
            ap.error(str(exc))


if __name__ == "__main__":
    main()
