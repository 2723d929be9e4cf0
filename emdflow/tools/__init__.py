"""Offline tools of the ``emdflow`` command: flow videos, evaluation, per-frame CSV.

Modules
-------
flowviz
    Middlebury colour wheel and the drawing of one flow-video frame.
flo
    Middlebury ``.flo`` files.
video_io
    Frames from any video / image folder; FFV1, MJPG or mp4v video out.
evaluate
    ``emdflow eval``: camera flights with exact truth, the engine against OpenCV DIS.
frames
    ``emdflow frames``: one CSV line of summary per frame.
calibrate_summary
    ``python -m emdflow.tools.calibrate_summary``: the summary's likelihood tables (fit,
    evaluate).
zoom_eval
    ``python -m emdflow.tools.zoom_eval``: the expansion-rate cue on zoom flights (measure,
    calibrate).
rotation_eval
    ``python -m emdflow.tools.rotation_eval``: how much faster a turn reads than a
    translation on a wide lens, per field of view.
cross_motion
    ``python -m emdflow.tools.cross_motion``: what the per-axis detectors still see of a
    flow's minor component as its major one grows (fast oblique flight).
engine_ab
    ``python -m emdflow.tools.engine_ab CHECKOUT``: the OpenCL engine against another
    checkout's, alternating in one process (speed changes of a few percent).

This package module holds what the subcommands share: :class:`ToolError` (a one-line
message plus an exit code), the engine options, the checks of a flight's frame size and
of positive options, a progress bar, and the linear soft binning the calibration tools
measure their tables with.
"""

from __future__ import annotations

import ast
import contextlib

__all__ = ["DIS_MIN_LONG_SIDE", "ToolError", "add_engine_arguments", "check_positive", "engine_kwargs",
           "frame_size_problem", "frames_origin", "interp_weights", "keyword_options", "make_estimator",
           "matplotlib_missing", "missing_folder", "number_list", "output_problem", "plot_type_problem",
           "progress_bar", "refuse_same_outputs", "texture_names_problem", "writing"]

#: OpenCV DIS (preset ULTRAFAST, patches of 8 px) needs a frame whose longer side is at
#: least this many px (measured with OpenCV 5.0 for every size from 8x8 to 79x79: it
#: refuses exactly those whose sides are both below 12).
DIS_MIN_LONG_SIDE = 12


def matplotlib_missing() -> str | None:
    """Why plots cannot be drawn here, or None: matplotlib comes with the ``tools`` extra
    (``dev`` has it too), not with ``pocl`` alone."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return 'matplotlib is not installed (pip install "emdflow[tools]")'
    return None


def texture_names_problem(names, load) -> str | None:
    """Why one of the ``--textures`` ``names`` cannot be flown over (``load(name)`` raises a
    ValueError naming it), or None."""
    for name in names:
        try:
            load(name)
        except ValueError as exc:
            return str(exc)
    return None


class ToolError(Exception):
    """A failure reported as one line on stderr with an exit code (2: bad input/usage)."""

    def __init__(self, message: str, code: int = 2):
        super().__init__(message)
        self.code = code


@contextlib.contextmanager
def writing(option: str, path):
    """Report an ``OSError`` raised while writing ``path`` as a :class:`ToolError` naming
    the option (none: ``""``) and the file: a failed write carries no file name, and "No
    space left on device" alone did not say which output (a pipe closed by its reader,
    ``BrokenPipeError``, is left to the command's quiet handling)."""
    try:
        yield
    except BrokenPipeError:
        raise
    except OSError as e:
        raise ToolError(f"{option + ' ' if option else ''}{path}: {e.strerror or e}", 2) from None


def frames_origin(args) -> str | None:
    """Where a tool's frame size comes from, for its errors: ``--size WxH`` or the input
    (None for options with neither)."""
    if getattr(args, "size", None):
        return f"--size {args.size}"
    return str(args.input) if getattr(args, "input", None) is not None else None


def frame_size_problem(width: int, height: int, *, dis: bool, dis_role: str = "",
                       dis_hint: str = "") -> str | None:
    """Why a ``width`` x ``height`` camera flight cannot be measured, or None.

    Both sides must be at least :data:`emdflow.synthetic.MIN_SIDE` px (the renderer's
    smallest frame), the frame at most the engine's ``MAX_PIXELS`` and ``MAX_WIDTH``; with
    ``dis`` (OpenCV DIS runs on the frames) the longer side at least
    :data:`DIS_MIN_LONG_SIDE` px. The DIS
    message is ``"OpenCV DIS{dis_role} needs a side of at least {DIS_MIN_LONG_SIDE}
    px{dis_hint}"``; the caller puts the option in front.
    """
    from emdflow.estimator import MAX_PIXELS, MAX_WIDTH
    from emdflow.synthetic import MIN_SIDE

    if min(width, height) < MIN_SIDE:
        return f"both sides must be at least {MIN_SIDE} px (the flight renderer's smallest frame)"
    if width * height > MAX_PIXELS:
        # (known before minutes of rendering, not from the engine afterwards)
        return f"at most {MAX_PIXELS} pixels (the engine's limit, e.g. 4096x4096)"
    if width > MAX_WIDTH:
        return f"at most {MAX_WIDTH} px wide (the engine's limit)"
    if dis and max(width, height) < DIS_MIN_LONG_SIDE:
        return f"OpenCV DIS{dis_role} needs a side of at least {DIS_MIN_LONG_SIDE} px{dis_hint}"
    return None


def missing_folder(path) -> str | None:
    """``"folder F does not exist"`` when the folder an output file ``path`` would go in is
    missing (checked before a long run, not when it ends), else None; the caller puts the
    option or path in front."""
    from pathlib import Path

    parent = Path(path).resolve().parent
    return None if parent.is_dir() else f"folder {parent} does not exist"


def output_problem(path) -> str | None:
    """Why an output file cannot be written at ``path`` — its folder is missing or not
    writable, or the path is a folder — checked before a long run (not when it ends, with
    the run's results lost), else None; the caller puts the option or path in front."""
    import os
    from pathlib import Path

    if problem := missing_folder(path):
        return problem
    target = Path(path)
    if target.is_dir():
        return "is a folder"
    if not os.access(target.resolve().parent, os.W_OK):
        return f"folder {target.resolve().parent} is not writable"
    return None


def plot_type_problem(path) -> str | None:
    """Why matplotlib cannot draw ``path`` (not installed, or no image type for its file
    ending), or None."""
    from pathlib import Path

    missing = matplotlib_missing()
    if missing:
        return missing
    from matplotlib.backend_bases import FigureCanvasBase

    ext = Path(path).suffix.lower()
    if not ext:
        return "no file ending to choose the image type; use .png"
    if ext[1:] not in FigureCanvasBase.get_supported_filetypes():
        return f"matplotlib cannot write {ext} files; use .png"
    return None


def refuse_same_outputs(named) -> None:
    """Raise ToolError (code 2) when two outputs, ``(option, path)`` pairs (path None =
    not given), name the same file: the later one would overwrite the earlier."""
    from pathlib import Path

    seen = {}
    for option, path in named:
        if not path:
            continue
        key = Path(path).resolve()
        if key in seen:
            raise ToolError(f"{option} {path}: the same file as {seen[key]}", 2)
        seen[key] = f"{option} {path}"


def check_positive(option: str, value, unit: str) -> None:
    """Raise ToolError (code 2) naming ``option`` unless ``value`` is None or a finite
    number > 0 (argparse's ``float()`` takes "nan" and "inf", which pass a ``<= 0`` test)."""
    import math

    if value is not None and not (math.isfinite(value) and value > 0):
        raise ToolError(f"{option} {value:g}: must be a finite number > 0 ({unit})", 2)


def check_count(option: str, value) -> None:
    """Raise ToolError (code 2) naming ``option`` unless ``value`` is None or an int ≥ 1
    (``--max-frames -1`` used to run no frame and exit 0)."""
    if value is not None and value < 1:
        raise ToolError(f"{option} {value}: must be at least 1", 2)


def _same_file(a, b) -> bool:
    """Whether ``a`` and ``b`` are one file or folder on disk (also through a hard link, which
    ``Path.resolve`` does not see); False when either does not exist."""
    import os

    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def refuse_overwrite(input_path, output_path, option: str = "") -> None:
    """Raise ToolError (code 2) naming ``option`` and the output when the output file is the
    input itself, also through a symbolic or hard link (checked before the input is read:
    writing would destroy it), or an image file in the input folder of images (the next
    run over the folder would read it as a frame)."""
    from pathlib import Path

    from emdflow.tools.video_io import IMAGE_EXTENSIONS

    if not (input_path and output_path):
        return
    name = f"{option} {output_path}" if option else str(output_path)
    source, target = Path(input_path), Path(output_path)
    if _same_file(source, target):  # (through symbolic and hard links alike)
        raise ToolError(f"{name}: output would overwrite the input", 2)
    if (source.is_dir() and target.suffix.lower() in IMAGE_EXTENSIONS
            and _same_file(target.resolve().parent, source)):
        raise ToolError(f"{name}: an image in the input folder {input_path} would be read as a frame by "
                        "the next run; write it elsewhere", 2)


def open_input(args):
    """The frame source of ``args.input`` after the input options the tools share are
    checked (``--fps``, ``--max-frames``, ``--size``, and ``args.output`` neither the input
    itself nor an image in its folder, :func:`refuse_overwrite`: ToolError 2), opened with
    them (:func:`emdflow.tools.video_io.open_frames`)."""
    from emdflow.tools.video_io import open_frames, parse_size

    check_positive("--fps", args.fps, "frames/s")
    check_count("--max-frames", args.max_frames)
    try:
        size = parse_size(args.size) if args.size else None
    except ValueError as e:
        raise ToolError(f"--size: {e}", 2) from None
    refuse_overwrite(args.input, args.output, "-o")
    return open_frames(args.input, size=size, fps=args.fps, max_frames=args.max_frames)


def interp_weights(x, nodes):
    """Lower node index ``i`` and the weight of node ``i + 1`` of each ``x`` on the increasing
    ``nodes`` (linear soft binning, clamped to the nodes)."""
    import numpy as np

    nodes = np.asarray(nodes, np.float64)
    x = np.clip(x, nodes[0], nodes[-1])
    i = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, len(nodes) - 2)
    return i, (x - nodes[i]) / (nodes[i + 1] - nodes[i])


def number_list(text: str, kind=int) -> tuple:
    """argparse type: comma-separated numbers of ``kind`` (int or float), at least one."""
    import argparse

    noun = "integers" if kind is int else "numbers"
    try:
        values = tuple(kind(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated {noun}") from None
    if not values:
        raise argparse.ArgumentTypeError(f"{text!r}: expected at least one of the {noun}")
    return values


def _int_list(text: str) -> tuple[int, ...]:
    return number_list(text, int)


def add_engine_arguments(parser) -> None:
    """Add the engine options (backend, device, detector parameters) to an argparse parser.

    Unset options keep :class:`emdflow.FlowEstimator`'s defaults (the paper's model), or
    those of ``--model``; the other options override single keywords of the model.
    """
    from emdflow.params import MODELS

    g = parser.add_argument_group("engine")
    g.add_argument("--backend", choices=("opencl", "numpy"), default="opencl",
                   help="opencl (default, fast) or numpy (the reference, slow)")
    g.add_argument("--model", choices=tuple(MODELS),
                   help="named detector model (emdflow.params.MODELS; default: the paper's; "
                        "extended = the daemon's default)")
    g.add_argument("--device", help="OpenCL device index or name substring (default: EMDFLOW_OPENCL_DEVICE or the first)")
    g.add_argument("--scales", type=_int_list, metavar="LIST", help="odd receptor sizes (default 1,3,5,7,9,11,13)")
    g.add_argument("--threshold", type=float, help="ternary threshold, gray levels (default 5)")
    g.add_argument("--prefilter-size", type=int, metavar="N", help="Gaussian prefilter width, 0 = off (default 11)")
    g.add_argument("--delays", type=_int_list, metavar="LIST", help="temporal delays in frames (default 1)")
    g.add_argument("--delay-scales", type=_int_list, metavar="LIST", help="scales with delays > 1 (default 1)")
    g.add_argument("--engine-opt", action="append", default=[], metavar="KEY=VALUE",
                   help="any other FlowEstimator keyword (VALUE as a Python literal); repeatable")


def engine_kwargs(args) -> dict:
    """FlowEstimator keyword arguments from parsed engine options (only the ones given).

    Raises
    ------
    ToolError
        On a malformed ``--engine-opt``.
    """
    from emdflow.params import MODELS

    model = getattr(args, "model", None)
    kw = dict(MODELS[model]) if model else {}
    for key in ("scales", "threshold", "prefilter_size", "delays", "delay_scales"):
        value = getattr(args, key, None)
        if value is not None:
            kw[key] = value
    device = getattr(args, "device", None)
    if device is not None:
        kw["device"] = int(device) if device.isdecimal() else device
    kw.update(keyword_options(getattr(args, "engine_opt", []) or [], "--engine-opt"))
    return kw


def keyword_options(items, option: str) -> dict:
    """``KEY=VALUE`` items of ``option`` as keywords: each value a Python literal where it
    reads as one (``False``, ``3``, ``(1, 2)``), else the text; a dash in a key is an
    underscore. Raises ToolError (code 2) naming the option for an item without ``=``."""
    kw = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key.isidentifier():
            raise ToolError(f"{option} {item!r}: expected KEY=VALUE", 2)
        try:
            kw[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            kw[key] = text
    return kw


def make_estimator(args, width: int, height: int):
    """A :class:`emdflow.FlowEstimator` for parsed command-line options; an error about
    the frame size names where it came from (:func:`frames_origin`).

    Raises
    ------
    ToolError
        Code 2 for bad parameters, code 1 when the OpenCL backend cannot start (the
        message suggests ``--backend numpy``).
    """
    from emdflow import FlowEstimator
    from emdflow.estimator import FrameSizeError

    kw = engine_kwargs(args)
    if kw.get("summary_evidence") is False:  # (other values: FlowEstimator's own error)
        raise ToolError("engine options: summary_evidence=False: these tools summarise every "
                        "frame and need the summary's evidence", 2)
    backend = getattr(args, "backend", "opencl")
    try:
        return FlowEstimator(int(width), int(height), backend=backend, **kw)
    except TypeError as e:
        raise ToolError(f"engine options: {e}", 2) from None
    except FrameSizeError as e:  # the input's fault, not an option's
        origin = frames_origin(args)
        raise ToolError(f"{origin}: {e}" if origin else str(e), 2) from None
    except ValueError as e:
        raise ToolError(f"engine options: {e}", 2) from None
    except (RuntimeError, ImportError) as e:
        from emdflow.opencl_backend import exception_summary

        raise ToolError(f"backend {backend}: {exception_summary(e)} (try --backend numpy)", 1) from None


class _NoBar:
    def update(self, n=1):
        pass

    def set_postfix_str(self, s):
        pass


@contextlib.contextmanager
def progress_bar(total, desc: str, unit: str = "frame", disable: bool = False):
    """A tqdm progress bar on stderr (rate and ETA), or a silent stand-in.

    ``disable=False`` still hides the bar when stderr is not a terminal; without tqdm
    installed there is no bar.
    """
    if disable:
        yield _NoBar()
        return
    try:
        from tqdm import tqdm
    except ImportError:
        yield _NoBar()
        return
    bar = tqdm(total=total, desc=desc, unit=unit, disable=None, dynamic_ncols=True, smoothing=0.1)
    try:
        yield bar
    finally:
        bar.close()
