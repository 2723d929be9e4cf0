"""``emdflow frames INPUT``: one CSV line of global flow per frame — the simplest way to script.

Columns::

    frame,t,flow_x,flow_y[,rate_x,rate_y],quality

frame
    0-based frame index.
t
    Seconds from the first frame (``frame / fps``; fps from the video or ``--fps``; empty
    when neither is known, e.g. a folder of images without ``--fps``).
flow_x, flow_y
    Global image flow, px/frame, image axes (x right, y down) — not MAVLink axes.
rate_x, rate_y
    Only with ``--focal-length-px``: the same flow as angular rate, rad/s
    (``flow · fps / f``, small-angle), still in image axes. Needs a frame rate.
quality
    0 (nothing measured: history filling, blank or texture-less frame) … 255.

Every frame gives a line, also the first ``3·max(delays)`` frames whose history is not
full yet (flow 0, quality 0).
"""

from __future__ import annotations

import sys

__all__ = ["csv_header", "format_row", "flow_to_rate", "add_arguments", "run"]


def flow_to_rate(flow_px_per_frame: float, fps: float, focal_length_px: float) -> float:
    """Angular rate in rad/s of an image flow in px/frame (small-angle: ``flow · fps / f``)."""
    return flow_px_per_frame * fps / focal_length_px


def csv_header(with_rates: bool) -> str:
    """The header line (without newline)."""
    cols = ["frame", "t", "flow_x", "flow_y"] + (["rate_x", "rate_y"] if with_rates else []) + ["quality"]
    return ",".join(cols)


def format_row(frame: int, fps, flow_x: float, flow_y: float, quality: int, focal_length_px=None) -> str:
    """One CSV line (without newline) for a frame's summary.

    Parameters
    ----------
    frame : int
        0-based frame index.
    fps : float or None
        Frame rate; None leaves ``t`` empty.
    flow_x, flow_y : float
        px/frame.
    quality : int
        0..255.
    focal_length_px : float, optional
        Adds ``rate_x, rate_y`` in rad/s (requires ``fps``).
    """
    t = f"{frame / fps:.6f}" if fps else ""
    parts = [str(frame), t, f"{flow_x:.4f}", f"{flow_y:.4f}"]
    if focal_length_px is not None:
        parts += [f"{flow_to_rate(flow_x, fps, focal_length_px):.6f}",
                  f"{flow_to_rate(flow_y, fps, focal_length_px):.6f}"]
    parts.append(str(int(quality)))
    return ",".join(parts)


def add_arguments(p) -> None:
    """The options of ``emdflow frames``."""
    from emdflow.tools import add_engine_arguments

    p.add_argument("input", metavar="INPUT",
                   help="video file, folder of images, one image, or synthetic:KEY=VALUE,... (see 'emdflow flow -h')")
    p.add_argument("-o", "--output", metavar="CSV", help="write here instead of stdout ('-': stdout)")
    p.add_argument("--fps", type=float, help="frame rate (overrides the video's; needed for folders)")
    p.add_argument("--focal-length-px", type=float, metavar="F",
                   help="focal length in pixels at the processed size: adds rate_x, rate_y (rad/s)")
    p.add_argument("--size", metavar="WxH", help="resize frames before processing (area interpolation)")
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_engine_arguments(p)


def run(args) -> int:
    """Run ``emdflow frames`` with parsed arguments; returns the exit code."""
    from emdflow import summarize
    from emdflow.tools import (ToolError, check_positive, make_estimator, open_input, progress_bar,
                               writing)

    check_positive("--focal-length-px", args.focal_length_px, "px")
    if args.output == "-":  # the usual name of stdout, where the CSV goes without -o (it made a file "-")
        args.output = None
    source = open_input(args)
    if args.focal_length_px is not None and not source.fps:
        raise ToolError(f"{args.input}: no frame rate known; rates need --fps", 2)
    est = make_estimator(args, source.width, source.height)
    # (only the output's own calls inside writing(): an error reading the input is not its)
    named = ("-o", args.output) if args.output else ("", "standard output")
    with writing(*named):
        out = open(args.output, "w", newline="") if args.output else sys.stdout

    def emit(line: str) -> None:
        with writing(*named):
            out.write(line + "\n")

    try:
        emit(csv_header(args.focal_length_px is not None))
        with progress_bar(source.frame_count, "frames", disable=args.quiet or not args.output) as bar:
            for i, frame in enumerate(source):
                s = summarize(est.update(frame))
                emit(format_row(i, source.fps, s.flow_x, s.flow_y, s.quality, args.focal_length_px))
                bar.update(1)
    finally:
        source.close()
        with writing(*named):
            if out is not sys.stdout:
                out.close()
            else:
                out.flush()
    return 0
