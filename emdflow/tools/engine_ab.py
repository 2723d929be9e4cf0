"""A/B of the OpenCL engine against another checkout's, in one process.

The machine's speed drifts by tens of percent from minute to minute, so two benchmark runs
a minute apart cannot show a change of a few percent. This tool loads the other checkout's
``emdflow`` package (and its ``kernels/``) next to this one, under another module name,
and times both engines' ``FlowEstimator.update`` on the same camera-flight frames in
alternating blocks (default 12 rounds of 50 frames, each block after two untimed frames,
the order swapped every round); it prints both medians and the median over the rounds of
each round's "other / this" ratio (> 1: this checkout is faster). Against an identical
checkout it spread 0.95-1.09 over several runs here (docs/speed-history.md): smaller differences
are noise::

    git worktree add /tmp/before HEAD~1
    python -m emdflow.tools.engine_ab /tmp/before                       # paper, 640x480
    python -m emdflow.tools.engine_ab /tmp/before --model extended --size 320x240

``--texture NAME`` flies over another ground (gravel unless told) and ``--drift X`` adds an
exposure ramp of that relative size across the clip: over a photograph with large bright
and dark regions (``--texture camera``) the motion alone changes the frame's brightness, so
the extended model's brightness compensation runs in most frames, as under a drift.

``--other-option KEY=VALUE`` passes an estimator keyword to the other engine only, so the
same checkout times the cost of an option::

    python -m emdflow.tools.engine_ab . --other-option evidence_row_step=1 --size 320x240

``--option KEY=VALUE`` passes a keyword to both engines, e.g. ``summary_evidence=False`` for
the dense field only::

    python -m emdflow.tools.engine_ab /tmp/before --option summary_evidence=False

``--summary`` times ``summarize`` instead of ``update``: each checkout's engine makes the
fields of the clip once, then the two summaries alternate over them in blocks (back to
back, so the summary's tables stay in the caches: the daemon, which calls it right after
an update, pays more for both)::

    python -m emdflow.tools.engine_ab /tmp/before --summary --model extended --size 320x240

The other checkout must have the source layout (``emdflow/`` and ``kernels/`` side by
side) and the same public API (``FlowEstimator``, ``emdflow.params.MODELS``).
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
from pathlib import Path

from emdflow.bench import DEFAULT_TEXTURE
from emdflow.params import MODELS
from emdflow.tools import ToolError

__all__ = ["load_checkout", "compare", "main"]


def load_checkout(root: Path, name: str = "emdflow_other"):
    """Import ``root/emdflow`` as the package ``name``, reading its kernels from
    ``root/kernels``."""
    package = root / "emdflow" / "__init__.py"
    if not package.is_file() or not (root / "kernels").is_dir():
        raise ToolError(f"{root}: not an emdflow checkout (needs emdflow/__init__.py and kernels/)")
    loaded = sys.modules.get(name)
    if loaded is not None:
        if Path(loaded.__file__).resolve() != package.resolve():
            raise ToolError(f"module name {name!r} already holds {loaded.__file__}, not {package}")
        return loaded
    spec = importlib.util.spec_from_file_location(name, package, submodule_search_locations=[str(package.parent)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    backend = importlib.import_module(f"{name}.opencl_backend")
    backend.kernel_source = lambda stage: (root / "kernels" / stage).read_text()
    return module


def compare(other, width: int, height: int, model: str = "paper", rounds: int = 12, block: int = 50,
            warmup: int = 2, other_options: dict | None = None, texture: str = DEFAULT_TEXTURE,
            drift: float = 0.0, summary: bool = False, options: dict | None = None) -> dict:
    """Alternating blocks of ``other.FlowEstimator`` (with ``options`` and then
    ``other_options`` on top of the model's) and this checkout's (with ``options``) on one camera flight (over ``texture``, with an exposure
    ramp of ``drift``); returns the per-round ms/frame of both and the median paired
    ratio. With ``summary``, of each checkout's ``summarize`` on its own engine's ready
    fields of the flight instead (ms per call)."""
    import emdflow
    from emdflow.bench import _frames, alternating_blocks

    frames = _frames(width, height, 40, drift, texture)
    both = {**MODELS[model], **(options or {})}
    engines = {"other": other.FlowEstimator(width, height, **{**both, **(other_options or {})}),
               "this": emdflow.FlowEstimator(width, height, **both)}
    for est in engines.values():
        for frame in frames[: max(10, est.params.history_frames)]:
            est.update(frame)
    if summary:
        # each checkout's fields of the whole clip (all ready: the history is full)
        fields = {name: [est.update(frame) for frame in frames] for name, est in engines.items()}
        methods = {name: (lambda i, f=fields[name], s=summarize: s(f[i]))
                   for name, summarize in (("other", other.summarize), ("this", emdflow.summarize))}
    else:
        methods = {name: (lambda i, est=est: est.update(frames[i])) for name, est in engines.items()}
    # (the order swaps every round: a block right after the other engine's pays for its caches)
    times = alternating_blocks(methods, len(frames), rounds=rounds, block=block, warmup=warmup, swap=True)
    return {**times, "ratio": statistics.median(o / t for o, t in zip(times["other"], times["this"]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m emdflow.tools.engine_ab", description=__doc__.splitlines()[0])
    ap.add_argument("checkout", type=Path, help="the other checkout (e.g. a git worktree)")
    ap.add_argument("--size", default="640x480", help="WxH (default: %(default)s)")
    ap.add_argument("--model", default="paper", choices=tuple(MODELS))
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--block", type=int, default=50)
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="estimator keyword for both engines (repeatable), e.g. summary_evidence=False "
                         "(the dense field only)")
    ap.add_argument("--other-option", action="append", default=[], metavar="KEY=VALUE",
                    help="estimator keyword for the other engine only (repeatable), e.g. "
                         "evidence_row_step=1")
    ap.add_argument("--texture", default=DEFAULT_TEXTURE, help="ground of the flight (default: %(default)s)")
    ap.add_argument("--drift", type=float, default=0.0,
                    help="exposure ramp of this relative size across the 40-frame clip")
    ap.add_argument("--summary", action="store_true",
                    help="time summarize() on each engine's fields instead of update()")
    a = ap.parse_args(argv)

    from emdflow.tools import ToolError, keyword_options

    try:
        options = keyword_options(a.other_option, "--other-option")
        shared = keyword_options(a.option, "--option")
    except ToolError as exc:
        ap.error(str(exc))
    from emdflow.tools.video_io import parse_size

    try:
        width, height = parse_size(a.size)
    except ValueError as exc:
        ap.error(f"--{exc}")
    try:
        other = load_checkout(a.checkout.resolve())
        r = compare(other, width, height, a.model, a.rounds, a.block, other_options=options,
                    texture=a.texture, drift=a.drift, summary=a.summary, options=shared)
    except (ToolError, TypeError, ValueError) as exc:
        print(f"engine_ab: {exc}", file=sys.stderr)
        return 2
    label = "".join(f" {k}={v!r}" for k, v in options.items())
    ground = a.texture + (f", drift {a.drift:+g}" if a.drift else "")
    ground += "".join(f", {k}={v!r}" for k, v in shared.items())
    what = "summarize() call" if a.summary else "frame"
    print(f"{a.model} {width}x{height} over {ground}: other{label} {statistics.median(r['other']):.3f} ms, "
          f"this {statistics.median(r['this']):.3f} ms per {what}; other / this per round "
          f"(median of {a.rounds}): {r['ratio']:.3f}")
    print("  rounds other:", " ".join(f"{x:.2f}" for x in r["other"]))
    print("  rounds this: ", " ".join(f"{x:.2f}" for x in r["this"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
