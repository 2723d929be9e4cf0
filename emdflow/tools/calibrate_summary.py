"""Calibrate the likelihood table of :func:`emdflow.summarize` from synthetic flights.

The summary (``emdflow/summary.py``) models every detection as drawn from
``P(code | c, ψ, β)``: the probability that the winning signed channel of an axis
detector is ``code`` when an edge crosses that axis at the signed speed ``c`` px/frame,
the edge normal makes the angle ``ψ`` with the axis and ``β = |sin|`` of the angle between
the flow and the edge normal (0: the edge moves along its normal, 1: the flow slides along
the edge and only texture details move across the axis). Categories are
``2 · scale index + (1 if the code's sign disagrees with sign(c))``. This script measures
that table on a grid (trilinear soft binning of every histogram bin).

Steps (all deterministic; the committed table is exactly what these commands write)::

    # 1. fly the camera over the CALIBRATION textures and store the raw histograms
    #    (OpenCL backend, 320x240; ~1.5 and ~3 minutes on two cores)
    python -m emdflow.tools.calibrate_summary collect --flights 3000 --seed 20240601 \
        --out /tmp/emdflow_calib.npz
    python -m emdflow.tools.calibrate_summary collect --flights 6000 --seed 7 \
        --out /tmp/emdflow_calib2.npz
    # 2. measure the table and write emdflow/summary_calibration.npz
    python -m emdflow.tools.calibrate_summary fit /tmp/emdflow_calib.npz \
        /tmp/emdflow_calib2.npz --write
    # 3. evaluate summarize() on the EVALUATION textures (per-speed table, coverage,
    #    quality bands, time per call); 1728 frames per set, ~20 s each
    python -m emdflow.tools.calibrate_summary evaluate --offset 0
    python -m emdflow.tools.calibrate_summary evaluate --offset 0.3
    python -m emdflow.tools.calibrate_summary evaluate --random

``--backend numpy`` gives the same histograms (the backends agree bit for bit), ~30x
slower. ``evaluate --save F.npz`` stores the rendered histograms and ``evaluate --data
F.npz`` scores them again without rendering (for tuning :class:`SummaryOptions`).

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
import math
import sys
import time
from pathlib import Path

import numpy as np

CALIBRATION_TEXTURES = ("moon", "coffee", "astronaut", "rocket")


def inside_start(rng, size, view, shift):
    """A start coordinate (texture px) for a flight whose view of ``view`` texture px moves
    by ``shift`` texture px in total and must stay inside ``size``: rendering past the
    texture's border mirrors it, and the mirrored part moves the other way."""
    lo = view / 2.0 + 2.0 - min(0.0, shift)
    hi = size - view / 2.0 - 2.0 - max(0.0, shift)
    if hi < lo:
        raise ValueError("flight does not fit in the texture")
    return float(rng.uniform(lo, hi))


def collect(flights: int, out: str, frames: int = 7, seed: int = 20240601, width=320, height=240,
            textures=CALIBRATION_TEXTURES, backend: str = "opencl", scale_range=(1.0, 1.0)):
    """Render ``flights`` random flights; store every ready frame's histogram and truth.

    Each flight draws a direction, a speed (log-uniform 0.4..18 px/frame), noise σ, a
    contrast, a ground scale (log-uniform in ``scale_range``: texture px per image px, so
    the photographs are seen finer or coarser) and a start that keeps the whole flight
    inside the photograph (no mirrored borders)."""
    from emdflow import FlowEstimator
    from emdflow.synthetic import CameraFlight, load_texture

    rng = np.random.default_rng(seed)
    est = FlowEstimator(width, height, backend=backend)
    hists, flows, stats, names = [], [], [], []
    t0 = time.time()
    for i in range(flights):
        texture = textures[i % len(textures)]
        th, tw = load_texture(texture).shape
        angle = rng.uniform(0, 2 * math.pi)
        speed = math.exp(rng.uniform(math.log(0.4), math.log(18.0)))
        flow = (speed * math.cos(angle), speed * math.sin(angle))
        scale = math.exp(rng.uniform(math.log(scale_range[0]), math.log(scale_range[1])))
        # the largest scale at which the flight fits in the photograph
        fit = min((tw - 6.0) / (width + abs(flow[0]) * (frames - 1)),
                  (th - 6.0) / (height + abs(flow[1]) * (frames - 1)))
        scale = min(scale, fit)
        start = (inside_start(rng, tw, width * scale, -flow[0] * scale * (frames - 1)),
                 inside_start(rng, th, height * scale, -flow[1] * scale * (frames - 1)))
        flight = CameraFlight(
            texture, width=width, height=height, flow=flow,
            noise_sigma=float(rng.uniform(1.0, 3.0)), contrast=float(rng.uniform(0.6, 1.0)),
            seed=int(rng.integers(1 << 30)), start=start, ground_scale=scale,
        )
        est.reset()
        for t in range(frames):
            field = est.update(flight.render(t))
            if field.ready:
                hists.append(field.histogram.astype(np.int32))
                flows.append(flow)
                names.append(texture)
                stats.append(field.stats.copy())
        if (i + 1) % 500 == 0:
            print(f"{i + 1}/{flights} flights, {time.time() - t0:.0f} s", file=sys.stderr)
    np.savez_compressed(out, hist=np.array(hists), flow=np.array(flows), stats=np.array(stats),
                        texture=np.array(names))
    print(f"wrote {len(hists)} frames to {out}", file=sys.stderr)


#: Grid of the table: angle ψ between edge normal and detector axis (degrees) ...
PSI_NODES_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 70.0, 80.0, 90.0)
#: ... β = |sin| of the angle between the flow and the edge normal (0: the edge moves along
#: its normal, 1: it slides along itself) ...
BETA_NODES = (0.0, 0.3, 0.6, 0.8, 1.0)
#: ... and |c| on ``u = log(|c| + U_OFFSET)``, ``U_COUNT`` nodes from |c| = 0 to ``C_MAX``.
U_OFFSET = 0.5
U_COUNT = 40
C_MAX = 60.0
#: A cell needs this much detection weight to stand on its own (else: nearest filled cell).
MIN_CELL_WEIGHT = 100.0


def _interp_weights(x, nodes):
    """Indices (i, i+1) and linear weights of ``x`` on increasing ``nodes`` (clamped)."""
    nodes = np.asarray(nodes, np.float64)
    x = np.clip(x, nodes[0], nodes[-1])
    i = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, len(nodes) - 2)
    f = (x - nodes[i]) / (nodes[i + 1] - nodes[i])
    return i, f


def crossing_geometry():
    """Per (axis, orientation bin): unit normal (2, 64, 2), signed n_a and ψ in degrees."""
    from emdflow.params import EngineParams

    phi = EngineParams.orientation_centres()
    n = np.stack([np.cos(phi), np.sin(phi)], axis=1)  # (64, 2)
    normals = np.stack([n, n])  # (axis, bin, 2)
    n_axis = np.stack([n[:, 0], n[:, 1]])  # (axis, bin), signed
    psi = np.degrees(np.arccos(np.clip(np.abs(n_axis), 0.0, 1.0)))
    return normals, n_axis, psi


def u_nodes():
    return np.linspace(math.log(U_OFFSET), math.log(C_MAX + U_OFFSET), U_COUNT)


def accumulate(hist, flow):
    """Detection weight ``N[ψ, β, u, category]`` from histograms with known flow.

    ``category = 2·scale_index + (0 if the code's sign agrees with sign(c) else 1)``;
    every histogram bin is spread over the 8 surrounding grid nodes (trilinear weights).
    """
    hist = np.asarray(hist, np.float64)  # (frames, 2, 14, 64)
    flow = np.asarray(flow, np.float64)
    n_frames, _, n_codes, n_bins = hist.shape
    normals, n_axis, psi = crossing_geometry()
    vn = np.einsum("fj,abj->fab", flow, normals)  # normal speed
    speed = np.maximum(np.hypot(flow[:, 0], flow[:, 1]), 1e-9)[:, None, None]
    c = vn / n_axis
    beta = np.sqrt(np.clip(1.0 - (vn / speed) ** 2, 0.0, 1.0))
    shape = (len(PSI_NODES_DEG), len(BETA_NODES), U_COUNT, n_codes)
    ui, uf = _interp_weights(np.log(np.abs(c) + U_OFFSET), u_nodes())
    bi, bf = _interp_weights(beta, BETA_NODES)
    pi, pf = _interp_weights(psi, PSI_NODES_DEG)
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


def fit_main(data, write):
    hists, flows = [], []
    for path in data:
        d = np.load(path)
        hists.append(d["hist"])
        flows.append(d["flow"])
    N = accumulate(np.concatenate(hists), np.concatenate(flows))
    P, tot = table_from_counts(N)
    out = Path(__file__).resolve().parents[1] / "summary_calibration.npz"
    filled = (tot >= MIN_CELL_WEIGHT).mean(axis=(1, 2))
    print("filled share per ψ node:", " ".join(f"{x:.2f}" for x in filled))
    if write:
        np.savez_compressed(
            out, prob=P.astype(np.float32), psi_nodes_deg=np.asarray(PSI_NODES_DEG),
            beta_nodes=np.asarray(BETA_NODES), u_nodes=u_nodes(),
            u_offset=np.float64(U_OFFSET), weight=tot.astype(np.float32),
            speeds=np.array([1, 3, 5, 7, 9, 11, 13], np.float64),
        )
        print(f"wrote {out}")

EVALUATION_TEXTURES = ("gravel", "brick", "grass", "camera")
EVALUATION_SPEEDS = (1, 2, 3, 4, 5, 7, 9, 11, 13)
#: Seed of the random-direction evaluation set (``evaluate --random``).
RANDOM_DIRECTIONS_SEED = 4242


def _directions(offset, random_set):
    """The 8 flight directions (radians) of one (speed, texture) cell, as a function of
    the cell's index (the random set draws fresh directions per cell)."""
    if not random_set:
        return lambda cell: [a * math.pi / 4 + offset for a in range(8)]
    rng = np.random.default_rng(RANDOM_DIRECTIONS_SEED)
    table = rng.uniform(0.0, 2.0 * math.pi, (len(EVALUATION_SPEEDS) * len(EVALUATION_TEXTURES), 8))
    return lambda cell: list(table[cell])


def render_evaluation(offset: float = 0.0, random_set: bool = False, frames: int = 6,
                      backend: str = "opencl", width=320, height=240):
    """Flights over the evaluation textures: 9 speeds × 4 textures × 8 directions
    (multiples of 45° plus ``offset`` radians, or random directions), noise σ = 2,
    ``frames`` ready frames each. Returns the histograms, statistics and true flows."""
    from emdflow import FlowEstimator
    from emdflow.synthetic import CameraFlight, load_texture

    est = FlowEstimator(width, height, backend=backend)
    warm = est.params.history_frames
    directions = _directions(offset, random_set)
    hists, stats, flows = [], [], []
    cell = 0
    for sp in EVALUATION_SPEEDS:
        for texture in EVALUATION_TEXTURES:
            for a, th in enumerate(directions(cell)):
                fu, fv = sp * math.cos(th), sp * math.sin(th)
                # the view's path is centred on the photograph (never past its border)
                size = load_texture(texture).shape
                start = (size[1] / 2 + fu * (frames + warm - 1) / 2,
                         size[0] / 2 + fv * (frames + warm - 1) / 2)
                flight = CameraFlight(texture, width=width, height=height, flow=(fu, fv),
                                      noise_sigma=2.0, seed=a, start=start)
                est.reset()
                for t in range(frames + warm):
                    field = est.update(flight.render(t))
                    if field.ready:
                        hists.append(field.histogram.copy())
                        stats.append(field.stats.copy())
                        flows.append((fu, fv))
            cell += 1
    return dict(hist=np.array(hists), stats=np.array(stats), flow=np.array(flows),
                shape=np.array([height, width]), frame_index=warm + 1)


def score(data, options=None, out=print):
    """summarize() every stored frame; prints median relative / direction error per speed
    (quality-0 frames count as 100 % / 180°), coverage (share of frames with quality > 0),
    a quality-band table and the mean time per :func:`summarize` call. Returns
    ``(errors (n, 2), quality (n,))``."""
    from emdflow import summarize
    from emdflow.field import FlowField
    from emdflow.params import EngineParams

    h, w = (int(x) for x in data["shape"])
    codes = np.zeros((h, w), np.int8)
    params = EngineParams()
    flows = np.asarray(data["flow"], np.float64)
    fields = [FlowField(codes, codes, st, hi, params, int(data["frame_index"]))
              for hi, st in zip(data["hist"], data["stats"])]
    summarize(fields[0], options=options)  # builds the cached tables
    t0 = time.perf_counter()
    sums = [summarize(f, options=options) for f in fields]
    spent = (time.perf_counter() - t0) / max(1, len(fields))
    speed = np.hypot(flows[:, 0], flows[:, 1])
    err = np.empty((len(sums), 2))
    qual = np.array([s.quality for s in sums])
    for i, (s, (fu, fv), sp) in enumerate(zip(sums, flows, speed)):
        if s.quality == 0:
            err[i] = 1.0, 180.0
        else:
            d = math.degrees(math.atan2(s.flow_y, s.flow_x) - math.atan2(fv, fu))
            err[i] = math.hypot(s.flow_x - fu, s.flow_y - fv) / sp, abs((d + 180) % 360 - 180)
    out("  speed | frames | median rel error | median direction error | coverage")
    for sp in np.unique(np.round(speed, 6)):
        m = np.isclose(speed, sp)
        out(f"  {sp:5.0f} | {int(m.sum()):6d} | {np.median(err[m, 0]) * 100:5.1f} % "
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
    return err, qual


def evaluate(offset: float, random_set: bool = False, frames: int = 6, backend: str = "opencl",
             save: str | None = None, data: str | None = None):
    """Render (or load with ``data``) the evaluation flights and :func:`score` them."""
    if data:
        with np.load(data) as z:
            flights = {k: z[k] for k in z.files}
        label = data
    else:
        flights = render_evaluation(offset, random_set, frames, backend)
        label = "random directions" if random_set else f"offset {offset} rad"
        if save:
            np.savez_compressed(save, **flights)
    print(f"{label}: {len(flights['flow'])} frames")
    return score(flights)


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
    f = sub.add_parser("fit")
    f.add_argument("data", nargs="+")
    f.add_argument("--write", action="store_true",
                   help="write emdflow/summary_calibration.npz")
    e = sub.add_parser("evaluate")
    e.add_argument("--offset", type=float, default=0.3, help="direction offset, radians")
    e.add_argument("--random", action="store_true",
                   help="random directions (seeded) instead of multiples of 45° + offset")
    e.add_argument("--frames", type=int, default=6, help="ready frames per flight")
    e.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    e.add_argument("--save", help="also store the rendered histograms here (.npz)")
    e.add_argument("--data", help="score histograms stored by --save instead of rendering")
    a = ap.parse_args(argv)
    if a.cmd == "collect":
        bad = set(a.textures.split(",")) & set(EVALUATION_TEXTURES)
        if bad:
            ap.error(f"--textures: {', '.join(sorted(bad))} belong to the evaluation set")
        collect(a.flights, a.out, a.frames, a.seed, textures=tuple(a.textures.split(",")),
                backend=a.backend,
                scale_range=tuple(float(x) for x in a.scale_range.split(",")))
    elif a.cmd == "fit":
        fit_main(a.data, a.write)
    else:
        evaluate(a.offset, a.random, a.frames, a.backend, a.save, a.data)


if __name__ == "__main__":
    main()
