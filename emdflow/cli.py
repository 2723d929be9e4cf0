"""The ``emdflow`` command (also ``python -m emdflow``).

Subcommands::

    emdflow flow INPUT -o OUTPUT.avi   # flow video: detections in Middlebury colours + summary arrow
    emdflow frames INPUT               # CSV: frame, t, flow_x, flow_y[, rate_x, rate_y], quality
    emdflow eval [--quick]             # camera flights with exact truth, engine vs OpenCV DIS
    emdflow bench ...                  # the benchmark (emdflow.bench)
    emdflow devices                    # which OpenCL devices run the engine, which one it takes
    emdflow render INPUT -o OUT.mkv    # the frames themselves as gray lossless video (e.g. a synthetic flight)

Errors are one line on stderr naming the offending file; exit code 2 for bad input or
usage, 1 when the engine cannot start (e.g. no OpenCL platform), 130 on Ctrl-C.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

__all__ = ["main", "build_parser", "run_flow", "run_render"]


def _max_upscale(width: int, height: int) -> int:
    """Largest enlargement (at least 1) keeping a flow video within
    :data:`~emdflow.tools.video_io.MAX_VIDEO_SIDE` px a side."""
    from emdflow.tools.video_io import MAX_VIDEO_SIDE

    return max(1, MAX_VIDEO_SIDE // max(1, width, height))


def _auto_upscale(width: int, height: int) -> int:
    """Integer enlargement that makes a flow video about 480 px wide (1..4), keeping an
    enlarged video within :data:`~emdflow.tools.video_io.MAX_VIDEO_SIDE`."""
    return min(max(1, min(4, int(round(480 / max(1, width))))), _max_upscale(width, height))


def _add_video_io_arguments(p: argparse.ArgumentParser, codec_help: str) -> None:
    """INPUT, the output video and the frame options that ``flow`` and ``render`` share."""
    p.add_argument("input", metavar="INPUT",
                   help="video file, folder of images, one image, or synthetic:KEY=VALUE,... "
                        "(keys texture,u,v,frames,size,noise,contrast,drift,zoom,fps,seed)")
    p.add_argument("-o", "--output", required=True, metavar="VIDEO",
                   help=".avi/.mkv (lossless FFV1 by default) or .mp4 (mp4v)")
    p.add_argument("--codec", choices=("ffv1", "mjpg", "mp4v"), help=codec_help)
    p.add_argument("--fps", type=float, help="frame rate (overrides the video's; default 30 for folders)")
    p.add_argument("--size", metavar="WxH", help="resize frames before processing (area interpolation)")
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


#: Slowest frame rate the output video takes (FFmpeg's writer refused 0.001 frames/s here).
MIN_VIDEO_FPS = 0.01


def _open_input(args):
    """``(frames, fps)`` of INPUT after the options ``flow`` and ``render`` share are checked
    (a bad ``--fps`` or ``--size``, an output that cannot be written or would overwrite the
    input: ToolError 2)."""
    from emdflow.tools import ToolError, open_input, output_problem

    if problem := output_problem(args.output):  # (a folder: OpenCV's writer only says it cannot write)
        raise ToolError(f"-o {args.output}: {problem}", 2)
    if args.fps is not None and args.fps < MIN_VIDEO_FPS:  # (then blamed on the output file)
        raise ToolError(f"--fps {args.fps:g}: at least {MIN_VIDEO_FPS:g} frames/s (the output video's rate; "
                        "FFmpeg's writer refuses slower ones)", 2)
    source = open_input(args)
    return source, source.fps or 30.0


def _write_npz(file, store: dict, k: int, fps: float, speeds) -> None:
    """``emdflow flow --npz``: the first ``k`` frames' dense fields and summaries."""
    import numpy as np

    np.savez_compressed(
        file,
        u=np.stack(store["u"][:k]),
        v=np.stack(store["v"][:k]),
        flow_x=np.asarray(store["flow_x"][:k], np.float32),
        flow_y=np.asarray(store["flow_y"][:k], np.float32),
        quality=np.asarray(store["quality"][:k], np.uint8),
        fps=np.float64(fps),
        speeds=np.asarray(speeds, np.float32),
    )


def _add_flow_arguments(p: argparse.ArgumentParser) -> None:
    from emdflow.tools import add_engine_arguments

    _add_video_io_arguments(p, "ffv1: lossless, large; mjpg: lossy .avi that plays everywhere; mp4v: .mp4")
    p.add_argument("--max-flow", type=float, default=6.0, metavar="PX",
                   help="flow drawn fully saturated by the colour wheel, px/frame (default %(default)s)")
    p.add_argument("--upscale", type=int, metavar="N",
                   help="enlarge the video N times (default: to about 480 px wide, at most 4); "
                        "an enlarged video is at most 8190 px a side")
    p.add_argument("--npz", metavar="PATH",
                   help="also save u, v (float16, NaN = undetected), flow_x, flow_y, quality per frame "
                        "(kept in memory until the end)")
    p.add_argument("--flo-dir", metavar="DIR",
                   help="also write every frame's field as DIR/frame_NNNNNN.flo (DIR new, or without "
                        ".flo files of an earlier run)")
    p.add_argument("--snapshot", metavar="PNG", help="also save the last frame of the video as a PNG")
    add_engine_arguments(p)


def run_flow(args) -> int:
    """``emdflow flow``: engine over a video, written as a flow video (+ optional exports)."""
    import numpy as np

    from emdflow import summarize
    from emdflow.tools import (ToolError, check_count, check_positive, make_estimator, output_problem,
                               progress_bar, refuse_overwrite, refuse_same_outputs, writing)
    from emdflow.tools.flo import write_flo
    from emdflow.tools.flowviz import render_flow_frame
    from emdflow.tools.video_io import MAX_VIDEO_SIDE, VideoWriter

    check_positive("--max-flow", args.max_flow, "px/frame")
    check_count("--upscale", args.upscale)
    for option, path in (("--npz", args.npz), ("--snapshot", args.snapshot)):
        if path and (problem := output_problem(path)):
            raise ToolError(f"{path}: {problem}", 2)
        refuse_overwrite(args.input, path, option)
    if args.flo_dir and Path(args.flo_dir).is_dir():
        # (a longer earlier run's frames would stay behind, mixed with this run's)
        old = sum(1 for _ in Path(args.flo_dir).glob("frame_*.flo"))
        if old:
            raise ToolError(f"--flo-dir {args.flo_dir}: holds {old} .flo files of an earlier run; "
                            "give an empty or new folder", 2)
    refuse_same_outputs((("-o", args.output), ("--npz", args.npz), ("--snapshot", args.snapshot),
                         ("--flo-dir", args.flo_dir)))
    if args.snapshot:
        import cv2

        # known before the whole video is processed, not after
        if not cv2.haveImageWriter(args.snapshot):
            ext = Path(args.snapshot).suffix
            why = f"OpenCV cannot write {ext} images" if ext else "no file ending to choose the image type"
            raise ToolError(f"--snapshot {args.snapshot}: {why}; use .png", 2)
    source, fps = _open_input(args)
    upscale = args.upscale or _auto_upscale(source.width, source.height)
    big = (source.width * upscale, source.height * upscale)
    if upscale > _max_upscale(source.width, source.height):
        # (OpenCV failed on it: an allocation traceback, or "cannot write a ffv1 video")
        source.close()
        raise ToolError(f"--upscale {upscale}: {source.width}x{source.height} frames would become "
                        f"{big[0]}x{big[1]}; a flow video is at most {MAX_VIDEO_SIDE} px a side (at most "
                        f"--upscale {_max_upscale(source.width, source.height)} here)", 2)
    writer = VideoWriter(args.output, fps, args.codec)
    flo_dir = None
    if args.flo_dir:
        flo_dir = Path(args.flo_dir)
        try:
            flo_dir.mkdir(exist_ok=True)
        except OSError as e:
            raise ToolError(f"{args.flo_dir}: cannot create folder ({e.strerror})", 2) from None
    est = make_estimator(args, source.width, source.height)
    store = {"u": [], "v": [], "flow_x": [], "flow_y": [], "quality": []} if args.npz else None
    n = 0
    interrupted = False
    try:
        with writer, progress_bar(source.frame_count, "flow", disable=args.quiet) as bar:
            try:
                for frame in source:
                    field = est.update(frame)
                    s = summarize(field)
                    label = f"{n / fps:6.2f}s" if source.fps else f"#{n}"
                    picture = render_flow_frame(frame, field.u, field.v, s.flow_x, s.flow_y, s.quality,
                                                max_flow=args.max_flow, upscale=upscale, label=label)
                    writer.write(picture)
                    if store is not None:
                        store["u"].append(field.u.astype(np.float16))
                        store["v"].append(field.v.astype(np.float16))
                        store["flow_x"].append(s.flow_x)
                        store["flow_y"].append(s.flow_y)
                        store["quality"].append(s.quality)
                    if flo_dir is not None:
                        write_flo(flo_dir / f"frame_{n:06d}.flo", field.u, field.v)
                    n += 1
                    bar.update(1)
            except KeyboardInterrupt:
                interrupted = True
    finally:
        source.close()
        k = min(len(x) for x in store.values()) if store is not None else 0
        if k:  # (an interrupt may land between the appends of one frame)
            # through a file object: given a name, numpy appends ".npz" to one without it
            with writing("--npz", args.npz), open(args.npz, "wb") as npz_file:
                _write_npz(npz_file, store, k, fps, est.params.speeds)
    if args.snapshot and n:
        import cv2

        png = Path(args.snapshot).suffix.lower() == ".png"
        if not cv2.imwrite(args.snapshot, picture, [cv2.IMWRITE_PNG_COMPRESSION, 9] if png else []):
            raise ToolError(f"{args.snapshot}: OpenCV cannot write this image", 2)
    if interrupted:
        # (the writer opens on the first frame: before it, there is no file to play)
        written = f"{args.output} is playable" if writer.frames_written else f"{args.output} was not written"
        print(f"emdflow flow: interrupted after {writer.frames_written} frames; {written}", file=sys.stderr)
        return 130
    if n == 0:
        raise ToolError(f"{args.input}: no frames", 2)
    if not args.quiet:
        print(f"wrote {args.output}: {n} frames {writer.size[0]}x{writer.size[1]} at {fps:g} fps ({writer.codec})",
              file=sys.stderr)
    return 0


def run_render(args) -> int:
    """``emdflow render``: the input's gray frames, as the engine sees them, into a video
    (gray lossless FFV1 by default: a recording for the daemon's ``video:`` and
    ``depthai-replay:`` sources)."""
    from emdflow.tools import ToolError, progress_bar
    from emdflow.tools.video_io import VideoWriter, codec_for

    source, fps = _open_input(args)
    codec = codec_for(args.output, args.codec)  # (.mp4: mp4v, colour channels)
    if source.width % 2 or source.height % 2:
        # (OpenCV's writer cuts a side to even: the recording would lose the last row or
        # column, and the daemon would read another size than the engine saw here)
        source.close()
        raise ToolError(f"{args.input}: {source.width}x{source.height}: a video stores even sides only; "
                        f"choose an even size (e.g. --size {source.width // 2 * 2}x{source.height // 2 * 2})", 2)
    writer = VideoWriter(args.output, fps, codec, gray=codec == "ffv1")
    try:
        with writer, progress_bar(source.frame_count, "render", disable=args.quiet) as bar:
            for frame in source:
                writer.write(frame)
                bar.update(1)
    except KeyboardInterrupt:
        print(f"emdflow render: interrupted after {writer.frames_written} frames", file=sys.stderr)
        return 130
    finally:
        source.close()
    if writer.frames_written == 0:
        raise ToolError(f"{args.input}: no frames", 2)
    if not args.quiet:
        kind = "gray " if writer.gray else ""
        print(f"wrote {args.output}: {writer.frames_written} frames {writer.size[0]}x{writer.size[1]} at "
              f"{fps:g} fps ({kind}{writer.codec})", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser of the ``emdflow`` command."""
    from emdflow import __version__
    from emdflow.tools import devices, evaluate, frames

    parser = argparse.ArgumentParser(
        prog="emdflow",
        description="Insect-vision optical flow (EMD template model): offline tools.",
        epilog="Run 'emdflow COMMAND -h' for the options of a command.",
    )
    parser.add_argument("--version", action="version", version=f"emdflow {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    p = sub.add_parser("flow", help="write a flow video (detections, summary arrow, quality)",
                       description="Run the engine over a video or image folder and write a flow video: "
                                   "the frame, detections coloured by the Middlebury colour wheel, the "
                                   "summary vector and its quality.")
    _add_flow_arguments(p)
    p.set_defaults(run=run_flow)
    p = sub.add_parser("frames", help="per-frame summary as CSV",
                       description="Print one CSV line per frame: frame,t,flow_x,flow_y[,rate_x,rate_y],quality "
                                   "(flow in px/frame, image axes x right / y down; rates in rad/s).")
    frames.add_arguments(p)
    p.set_defaults(run=frames.run)
    p = sub.add_parser("eval", help="accuracy on camera flights with exact truth, vs OpenCV DIS",
                       description="Fly a camera over photographs with exact ground truth (speeds, "
                                   "directions, noise, contrast, exposure, zoom); measure the engine and "
                                   "OpenCV DIS ULTRAFAST on the same frames; print a table, write a CSV "
                                   "and a PNG plot.")
    evaluate.add_arguments(p)
    p.set_defaults(run=evaluate.run)
    sub.add_parser("bench", help="benchmark (see 'emdflow bench -h')", add_help=False)
    p = sub.add_parser("render", help="write the input's gray frames as a video (gray lossless FFV1)",
                       description="Write the frames of INPUT (a synthetic flight, a video, images) as the "
                                   "engine sees them — gray, resized — into a video: gray lossless FFV1 "
                                   "in .mkv/.avi by default, a recording the daemon's video: and "
                                   "depthai-replay: sources read back exactly.")
    _add_video_io_arguments(p, "ffv1 (default for .mkv/.avi): gray, lossless; mjpg, mp4v: lossy, colour channels")
    p.set_defaults(run=run_render)
    p = sub.add_parser("devices", help="which OpenCL devices run the engine, and which one it takes",
                       description="Build the kernels and run one frame on every OpenCL device; say "
                                   "which work (or why not) and which one the engine takes when left "
                                   "to choose. Exit 0 when the engine can run, 1 when it cannot.")
    devices.add_arguments(p)
    p.set_defaults(run=devices.run)
    return parser


def _run_bench(argv) -> int:
    import importlib.util  # (binds importlib too: import_module below)

    if importlib.util.find_spec("emdflow.bench") is None:
        print("emdflow bench: error: the benchmark module emdflow.bench is not part of this installation",
              file=sys.stderr)
        return 2
    # (through sys.modules, not the package attribute: a test may stand in for the module)
    bench = importlib.import_module("emdflow.bench")
    return bench.main(list(argv))


def main(argv=None) -> int:
    """Entry point of the ``emdflow`` console script; returns the exit code."""
    from emdflow.tools import ToolError
    from emdflow.tools.flo import FloError
    from emdflow.tools.video_io import InputError, OutputError

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "bench":
        # (its own parser, but the same error handling as the other subcommands)
        prog = "emdflow bench"

        def run():
            return _run_bench(argv[1:])
    else:
        parser = build_parser()
        args = parser.parse_args(argv)
        if not getattr(args, "command", None):
            parser.print_help(sys.stderr)
            return 2
        prog = f"emdflow {args.command}"

        def run():
            return args.run(args)
    try:
        return int(run() or 0)
    except ToolError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return e.code
    except (InputError, OutputError, FloError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if isinstance(e, BrokenPipeError):
            # Output piped into e.g. `head`: stop quietly (and keep Python from complaining).
            try:
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
            except (OSError, ValueError):
                pass
            return 0
        name = e.filename if e.filename is not None else ""
        print(f"{prog}: error: {name}{': ' if name else ''}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
