"""Benchmark: the OpenCL engine against the numpy reference, OpenCV DIS and a Gaussian blur.

Run ``emdflow bench`` (or ``python -m emdflow.bench``). All methods run in one process on
the same pre-rendered frames of a camera flight, alternating method by method in blocks
(default 50 frames, long enough not to measure thread wake-ups; each block starts with
two untimed frames of the same method, because the first frame after another method's
block took 2-3x a steady one here: threads waking up, caches refilled); the table gives the
median ms/frame over the blocks and ratios measured in the same run (DIS / OpenCL twice:
the ratio of the medians, and the median over the rounds of each round's ratio, whose
blocks ran seconds apart under the same load):

* ``opencl``   — ``FlowEstimator.update`` on the OpenCL backend: frame upload, all kernels,
  result download to the host (the paper's 7-scale model; ``--model extended`` the
  daemon's default model);
* ``opencl-dense`` — the same engine made with ``summary_evidence=False``: the dense
  field (and the frame's counters) only, without the histograms the summary reads — the
  detector as the paper defines it, for a caller that never summarises;
* ``opencl+summary`` — ``opencl`` plus :func:`emdflow.summarize` (what the daemon pays);
* ``numpy``    — the vectorised reference (fewer, shorter blocks: it is slow);
* ``dis``      — OpenCV's DIS optical flow, ULTRAFAST preset, between consecutive frames;
* ``blur``     — one ``cv2.GaussianBlur`` 11×11 pass (a yardstick for memory speed).

``emdflow bench --stages`` prints instead where one frame's time goes: the device time of
each command (upload, the four kernels, download) from OpenCL profiling events (on a CPU
device the frame and result buffers are host memory: "upload" is then the host's copy of
the frame into it, and there is no download: the host reads the result where the kernels
wrote it), the gaps between them, the host's wall time per frame and the time of
``summarize`` after it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time

import numpy as np

from .params import MODELS, THRESHOLD_MODES

__all__ = ["main", "profile_stages", "run_benchmark"]

SIZES = ((320, 240), (640, 480))


#: The ground of the benchmark's flight (``--texture``).
DEFAULT_TEXTURE = "gravel"

#: The per-round DIS / engine ratios: result key and the engine's method.
_DIS_PAIRED = (("dis_per_opencl_paired", "opencl"), ("dis_per_dense_paired", "opencl-dense"))


def _frames(width: int, height: int, count: int, drift: float = 0.0,
            texture: str = DEFAULT_TEXTURE) -> list[np.ndarray]:
    """A camera flight over ``texture`` (gravel unless told; see
    :func:`emdflow.synthetic.load_texture`); with ``drift`` an exposure ramp of that relative
    size across the clip (every frame then has a gain for the brightness compensation)."""
    from .synthetic import CameraFlight

    flight = CameraFlight(texture, width=width, height=height, flow=(2.3, -1.6), supersample=2, seed=1,
                          exposure_drift=drift, drift_frames=count)
    return [flight.render(t) for t in range(count)]


def _methods(width: int, height: int, frames, *, backend_kwargs=None):
    import cv2

    from . import FlowEstimator, summarize

    kwargs = backend_kwargs or {}
    methods = {}
    est = FlowEstimator(width, height, backend="opencl", **kwargs)
    methods["opencl"] = lambda i: est.update(frames[i])
    est_d = FlowEstimator(width, height, backend="opencl", **{**kwargs, "summary_evidence": False})
    methods["opencl-dense"] = lambda i: est_d.update(frames[i])
    est_s = FlowEstimator(width, height, backend="opencl", **kwargs)
    methods["opencl+summary"] = lambda i: summarize(est_s.update(frames[i]))
    ref = FlowEstimator(width, height, backend="numpy", **kwargs)
    methods["numpy"] = lambda i: ref.update(frames[i])
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST)
    n = len(frames)
    methods["dis"] = lambda i: dis.calc(frames[i], frames[(i + 1) % n], None)
    methods["blur"] = lambda i: cv2.GaussianBlur(frames[i], (11, 11), 11 / 6)
    return methods


def alternating_blocks(methods: dict, n_frames: int, *, rounds: int, block: int, warmup: int,
                       counts: dict | None = None, swap: bool = False, progress=None) -> dict:
    """Time ``methods`` (``name -> fn(frame index)``) in alternating blocks; returns
    ``{name: [ms per frame of each round's block]}``.

    Round ``r`` runs every method on the frames ``r · block`` on (modulo ``n_frames``),
    ``counts[name]`` of them (default ``block``), after ``warmup`` untimed frames of the
    same method just before them (none for a method with its own count: a slow one);
    ``swap`` reverses the order of the methods every other round; ``progress(r)`` after
    each round."""
    counts = counts or {}
    samples = {name: [] for name in methods}
    for r in range(rounds):
        cursor = r * block
        order = list(methods.items())
        for name, fn in (order[::-1] if swap and r % 2 else order):
            count = counts.get(name, block)
            for j in range(0 if name in counts else warmup, 0, -1):
                fn((cursor - j) % n_frames)
            t0 = time.perf_counter()
            for j in range(count):
                fn((cursor + j) % n_frames)
            samples[name].append((time.perf_counter() - t0) * 1e3 / count)
        if progress:
            progress(r)
    return samples


def run_benchmark(*, sizes=SIZES, block: int = 50, rounds: int = 7, numpy_block: int = 3,
                  frames_per_size: int = 40, backend_kwargs=None, progress=None, warmup: int = 2,
                  texture: str = DEFAULT_TEXTURE) -> dict:
    """Time every method; returns ``{(w, h): {method: median ms/frame}}``, plus
    ``"dis_per_opencl_paired"`` (and ``"dis_per_dense_paired"``): the median over the
    rounds of each round's DIS / OpenCL (DIS / dense-only) time ratio (less sensitive than
    the ratio of the medians to load that comes and goes between rounds). Each block but
    the numpy reference's (100 ms frames) starts with ``warmup`` untimed frames (the frames
    just before the block's, so the engines' history runs on without a jump)."""
    results = {}
    for width, height in sizes:
        frames = _frames(width, height, frames_per_size, texture=texture)
        methods = _methods(width, height, frames, backend_kwargs=backend_kwargs)
        for fn in methods.values():  # warm up: kernel builds, caches, history
            for i in range(4):
                fn(i)
        report = (lambda r, size=f"{width}x{height}": progress(f"{size}: round {r + 1}/{rounds}")) if progress else None
        samples = alternating_blocks(methods, len(frames), rounds=rounds, block=block, warmup=warmup,
                                     counts={"numpy": numpy_block}, progress=report)
        results[(width, height)] = {name: statistics.median(v) for name, v in samples.items()}
        # DIS / engine within each round (blocks seconds apart share the host's load of
        # the moment), then the median over the rounds
        for key, engine in _DIS_PAIRED:
            results[(width, height)][key] = statistics.median(
                d / o for d, o in zip(samples["dis"], samples[engine]))
    return results


def format_table(results: dict) -> str:
    lines = [
        "| size | OpenCL engine | dense field only | + summary | numpy reference | DIS ultrafast "
        "| GaussianBlur 11x11 | DIS / OpenCL | per round | DIS / dense only | per round "
        "| OpenCL / blur | numpy / OpenCL |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (w, h), r in results.items():
        # DIS / engine: the ratio of the medians, then the per-round median (empty if absent)
        dis_cells = ""
        for key, engine in _DIS_PAIRED:
            paired = r.get(key)
            dis_cells += f"| {r['dis'] / r[engine]:.2f}x | {'' if paired is None else f'{paired:.2f}x'} "
        lines.append(
            f"| {w}x{h} | {r['opencl']:.3f} ms | {r['opencl-dense']:.3f} ms | {r['opencl+summary']:.3f} ms "
            f"| {r['numpy']:.1f} ms | {r['dis']:.3f} ms | {r['blur']:.3f} ms {dis_cells}"
            f"| {r['opencl'] / r['blur']:.1f}x | {r['numpy'] / r['opencl']:.0f}x |"
        )
    return "\n".join(lines)


def write_plot(results: dict, path: str) -> None:
    """Bar chart of ms/frame by method and resolution (matplotlib, headless)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = ["opencl", "opencl-dense", "opencl+summary", "dis", "blur", "numpy"]
    fig, ax = plt.subplots(figsize=(8.5, 3.6), dpi=100)
    width = 0.8 / len(results)
    for k, ((w, h), r) in enumerate(results.items()):
        xs = np.arange(len(methods)) + k * width
        bars = ax.bar(xs, [r[m] for m in methods], width, label=f"{w}x{h}")
        ax.bar_label(bars, [f"{r[m]:.2f}" for m in methods], fontsize=7)
    ax.set_xticks(np.arange(len(methods)) + width * (len(results) - 1) / 2, methods)
    ax.set_yscale("log")
    ax.set_ylabel("ms per frame (log)")
    ax.set_title("emdflow bench: time per frame (median of alternating blocks)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def profile_stages(width: int, height: int, *, frames: int = 200, backend_kwargs=None,
                   drift: float = 0.0, texture: str = DEFAULT_TEXTURE) -> dict:
    """Device time of each command of a frame (OpenCL profiling events), median ms.

    The engine runs on a profiling queue over a camera flight; ``"wall"`` is the host's
    time for the whole ``step`` (upload to downloaded result), ``"gaps"`` what the device
    timeline spends between the first command's start and the last one's end outside
    the commands (scheduling, thread wake-ups), ``"decode"`` the host's time to unpack
    the int8 codes (paid only when the dense field is read), ``"summary"`` the host's time
    for :func:`emdflow.summarize` right after each frame's update (absent for an engine made
    with ``summary_evidence=False``: ``emdflow bench --stages --dense-only``).
    """
    import pyopencl as cl

    from .opencl_backend import OpenCLEngine
    from .params import EngineParams

    clip = _frames(width, height, 40, drift, texture)
    engine = OpenCLEngine(width, height, EngineParams(**(backend_kwargs or {})))
    engine.queue = cl.CommandQueue(engine.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
    for i in range(10):
        engine.step_packed(clip[i % len(clip)])
    engine.trace = []
    walls, decodes = [], []
    per_stage = {name: [] for name in OpenCLEngine.STAGES}
    gaps = []
    kept = []
    for i in range(frames):
        if engine.frame_host is not None:
            # a CPU device reads the frame from host memory: the upload is the host's copy
            t0 = time.perf_counter()
            np.copyto(engine.frame_host, clip[i % len(clip)])
            per_stage["upload"].append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        codes = engine.step_packed(clip[i % len(clip)])[0]
        walls.append((time.perf_counter() - t0) * 1e3)
        if i % 10 == 0:  # decoded after the loop: ~1 ms of host work between frames
            kept.append(codes)  # would evict the engine's data from the caches
        # read the events at once: they keep the frame's host arrays alive, and fresh
        # pages for every frame's result would add page faults to the download
        events = engine.trace.pop()
        busy = 0.0
        for name, ev in zip(engine.stages, events):
            ms = (ev.profile.end - ev.profile.start) * 1e-6
            per_stage[name].append(ms)
            busy += ms
        gaps.append((events[-1].profile.end - events[0].profile.start) * 1e-6 - busy)
    for codes in kept:
        t0 = time.perf_counter()
        codes.decode()
        decodes.append((time.perf_counter() - t0) * 1e3)
    # (no download where the host reads the result buffer's memory itself)
    out = {name: statistics.median(v) for name, v in per_stage.items() if v}
    out["gaps"] = statistics.median(gaps)
    out["wall"] = statistics.median(walls)
    out["decode"] = statistics.median(decodes)
    if engine.params.summary_evidence:  # (a dense-only engine has nothing to summarise)
        out["summary"] = _summary_time(width, height, clip, backend_kwargs)
    return out


def _summary_time(width: int, height: int, clip, backend_kwargs, frames: int = 120) -> float:
    """Median ms of :func:`emdflow.summarize` called right after each ``update`` (as the
    daemon does: the engine has just evicted the summary's tables from the caches)."""
    from . import FlowEstimator, summarize

    est = FlowEstimator(width, height, backend="opencl", **(backend_kwargs or {}))
    times = []
    for i in range(frames):
        field = est.update(clip[i % len(clip)])
        if field.ready:
            t0 = time.perf_counter()
            summarize(field)
            times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times[5:])


def _environment(width: int, height: int, kwargs: dict) -> str:
    """Device, thread pinning, cores and Python of the run. The device is the one the
    OpenCL engine of the first size runs on (its program is the benchmark's own)."""
    import platform

    from . import FlowEstimator

    device = FlowEstimator(width, height, backend="opencl", **kwargs).device
    affinity = os.environ.get("POCL_AFFINITY", "unset (0)")
    return (
        f"device: {device}; POCL_AFFINITY={affinity}; cores: {os.cpu_count()}; "
        f"python {platform.python_version()}"
    )


def _size_list(text: str) -> tuple[tuple[int, int], ...]:
    """argparse type of ``--sizes``: comma-separated ``WxH`` → ``((w, h), ...)``, px."""
    from .tools.video_io import parse_size

    try:
        return tuple(parse_size(item) for item in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated WIDTHxHEIGHT, "
                                         "e.g. 320x240,640x480") from None


def _check_arguments(parser: argparse.ArgumentParser, args) -> dict:
    """Usage errors (parser.error, exit 2) before anything is rendered or timed; returns
    the engine's keyword arguments."""
    from .params import EngineParams
    from .synthetic import load_texture
    from .tools import frame_size_problem, output_problem, plot_type_problem

    try:
        load_texture(args.texture)
    except ValueError as exc:
        parser.error(f"--texture: {exc}")
    for option, value, low in (("--block", args.block, 1), ("--rounds", args.rounds, 1),
                               ("--warmup", args.warmup, 0)):
        if value < low:  # (0 blocks: no median; 0 frames per block: a division by zero)
            parser.error(f"{option} {value}: must be at least {low}")
    if not (math.isfinite(args.drift) and args.drift > -1.0):
        # (the exposure factor 1 + drift reaches 0 at -1: a black clip)
        parser.error(f"--drift {args.drift:g}: must be a finite number > -1 (relative exposure change)")
    if args.drift and not args.stages:  # (the timing table's flight has no exposure ramp)
        parser.error("--drift: only with --stages")
    for option, path in (("--plot", args.plot), ("--json", args.json)):
        if path and args.stages:  # (the per-command profile is one printed line per size)
            parser.error(f"{option}: not with --stages (its profile is printed, not plotted or saved)")
    for w, h in args.sizes:
        problem = frame_size_problem(w, h, dis=not args.stages, dis_role=" (one of the methods timed)")
        if problem:
            parser.error(f"--sizes {w}x{h}: {problem}")
    kwargs = dict(MODELS[args.model])
    given = []
    if args.delays is not None:
        kwargs["delays"] = args.delays
        given.append(f"--delays {','.join(map(str, args.delays))}")
    if args.evidence_row_step:
        kwargs["evidence_row_step"] = args.evidence_row_step
        given.append(f"--evidence-row-step {args.evidence_row_step}")
    if not args.diagonal_evidence:
        kwargs["diagonal_evidence"] = False
    if args.threshold_mode is not None:
        kwargs["threshold_mode"] = args.threshold_mode
        given.append(f"--threshold-mode {args.threshold_mode}")
    if args.dense_only:
        if not args.stages:  # (the timing table measures the dense-only engine in its own column)
            parser.error("--dense-only: only with --stages (the table has a dense-only column)")
        kwargs["summary_evidence"] = False
    try:  # the engine's own checks, before the flight is rendered
        EngineParams(**kwargs)
    except (TypeError, ValueError) as exc:
        parser.error(f"{' '.join(given) or f'--model {args.model}'}: {exc}")
    for option, path in (("--plot", args.plot), ("--json", args.json)):
        problem = path and (output_problem(path) or (option == "--plot" and plot_type_problem(path)))
        if problem:
            parser.error(f"{option} {path}: {problem}")
    return kwargs


def main(argv=None) -> int:
    """``emdflow bench``; returns the exit code (usage errors: SystemExit 2, one line naming
    the option)."""
    from .synthetic import MIN_SIDE
    from .tools import DIS_MIN_LONG_SIDE, number_list

    parser = argparse.ArgumentParser(prog="emdflow bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=_size_list, default="320x240,640x480",
                        help=f"comma-separated WxH, sides >= {MIN_SIDE} px; for DIS in the timing table one "
                             f"side >= {DIS_MIN_LONG_SIDE} px (default: %(default)s)")
    parser.add_argument("--block", type=int, default=50, help="frames per timed block (default: %(default)s)")
    parser.add_argument("--rounds", type=int, default=7, help="alternating rounds (default: %(default)s)")
    parser.add_argument("--warmup", type=int, default=2,
                        help="untimed frames at the start of each block (default: %(default)s)")
    parser.add_argument("--plot", metavar="PNG", help="also write a bar chart to this PNG file")
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    parser.add_argument("--model", default="paper", choices=tuple(MODELS),
                        help="detector model (default: %(default)s; extended = the daemon's default: "
                             "delays 1, 2, 4 at scale 1, scale 15 and the adaptive threshold)")
    parser.add_argument("--delays", type=number_list, default=None,
                        help="temporal delays of the engine instead, e.g. 1,2,4 (fixed threshold)")
    parser.add_argument("--evidence-row-step", type=int, default=0,
                        help="rows between the rows that feed the summary's evidence (default: 0, "
                             "automatic: about 60 rows; 1 = every row, see EngineParams)")
    parser.add_argument("--diagonal-evidence", action=argparse.BooleanOptionalAction, default=True,
                        help="with (default) or without the diagonal detectors' evidence for the "
                             "summary (EngineParams.diagonal_evidence)")
    parser.add_argument("--threshold-mode", choices=THRESHOLD_MODES, default=None,
                        help="the engine's threshold instead of the model's (EngineParams.threshold_mode; "
                             "local: per 64-px tile)")
    parser.add_argument("--stages", action="store_true",
                        help="instead: device time per command of a frame (OpenCL profiling events)")
    parser.add_argument("--dense-only", action="store_true",
                        help="with --stages: the engine without the summary's evidence "
                             "(summary_evidence=False: the dense field only; no summary time)")
    parser.add_argument("--drift", type=float, default=0.0,
                        help="with --stages: an exposure drift of this relative size across the "
                             "40-frame clip (the brightness compensation's slower path)")
    parser.add_argument("--texture", default=DEFAULT_TEXTURE,
                        help="ground of the flight: a bundled photograph (emdflow.synthetic.TEXTURES), "
                             "fractal-<beta>-<seed> or an image file (default: %(default)s; over "
                             "large bright and dark regions the motion alone changes the frame's "
                             "brightness, which the extended model's compensation then takes out)")
    args = parser.parse_args(argv)
    kwargs = _check_arguments(parser, args)
    sizes = args.sizes
    try:  # no usable OpenCL device (or a device choice that names none): one line, exit 1
        environment = _environment(*sizes[0], kwargs)
    except (RuntimeError, ValueError) as exc:
        from .opencl_backend import exception_summary

        print(f"emdflow bench: error: OpenCL engine: {exception_summary(exc)}", file=sys.stderr)
        return 1
    print(f"# emdflow bench — {environment}; model: {args.model}"
          + (f", delays {kwargs['delays']}" if args.delays is not None else "")
          + (f", evidence every {args.evidence_row_step} row(s)" if args.evidence_row_step else "")
          + ("" if args.diagonal_evidence else ", without diagonal evidence")
          + (f", {args.threshold_mode} threshold" if args.threshold_mode else "")
          + (", dense field only" if args.dense_only else "")
          + f"; flight over {args.texture}",
          flush=True)
    if args.stages:
        for width, height in sizes:
            stages = profile_stages(width, height, backend_kwargs=kwargs, drift=args.drift,
                                    texture=args.texture)
            cells = " | ".join(f"{name} {ms:.3f}" for name, ms in stages.items())
            print(f"{width}x{height} (median ms per frame): {cells}")
        return 0
    results = run_benchmark(sizes=sizes, block=args.block, rounds=args.rounds, warmup=args.warmup,
                            backend_kwargs=kwargs, texture=args.texture,
                            progress=lambda m: print(f"  {m}", file=sys.stderr, flush=True))
    print(format_table(results))
    path = None
    try:  # (the paths were checked before the run; a full disk shows only now)
        if args.plot:
            path = args.plot
            write_plot(results, path)
            print(f"plot written to {path}")
        if args.json:
            path = args.json
            with open(path, "w") as fh:
                json.dump({f"{w}x{h}": r for (w, h), r in results.items()}, fh, indent=2)
    except OSError as exc:
        print(f"emdflow bench: error: {path}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
