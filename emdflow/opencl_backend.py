"""OpenCL backend: the kernels in ``kernels/`` driven through pyopencl.

Design (see ``kernels/*.cl``): all state lives on the device between frames — the
summed-area tables of the last ``max(delays) + 1`` prefiltered frames and, per channel, a
ring of ``2D + 1`` bit-packed ternary state planes. Per frame: one upload of the uint8
frame, four kernel launches on an in-order queue, one blocking download of one result
buffer (flow bit planes + statistics + detection histogram; the int8 codes are unpacked
on the host only when the dense field is read). On a CPU device the frame and result
buffers are host memory (``_shared_buffer``): the upload is a numpy copy, the download a
wait for the last kernel, and the frames take ``RESULT_SLOTS`` result buffers in turn, so
a frame's bit planes are read where the kernels wrote them (copied out only if their
field is still alive, not decoded, when the buffer comes round again). Sizes and tables are compile-time
constants; a program is built once per process and shape (PoCL also caches the binary on
disk, ``POCL_CACHE_DIR``).
"""

from __future__ import annotations

import logging
import math
import os
import struct
import threading
import weakref
from bisect import bisect_right
from fractions import Fraction
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from .params import ORIENTATION_BINS, EngineParams, _is_whole
from .reference import POSITION_BINS, STAT_CONTRAST, STAT_FIRST_CHANGED

__all__ = ["OpenCLEngine", "PackedCodes", "KernelBuildError", "list_devices", "kernel_source", "program_source",
           "orientation_cells"]

log = logging.getLogger(__name__)

_INSTALL_HINT = (
    "install an OpenCL runtime: `pip install \"emdflow[pocl]\"` (pyopencl with the PoCL CPU "
    "runtime on x86_64; needs binutils' `ld`, e.g. `apt-get install binutils`; on ARM PyPI has "
    "no PoCL: `apt-get install pocl-opencl-icd`), or your board vendor's "
    "OpenCL ICD (e.g. `apt-get install pocl-opencl-icd`, Mali/Jetson drivers) plus "
    "`pip install \"emdflow[opencl]\"`; or use backend=\"numpy\" (slow)"
)
#: PoCL hands the host CPU's name, as its own LLVM knows it, to the compiler; an LLVM older
#: than the processor names it "generic", which the compiler then rejects. (Seen with the
#: pip wheel's PoCL 3.0, LLVM 14, on AMD Zen 5; Debian 12's PoCL 3.1 falls back to a CPU
#: its LLVM knows.)
_UNKNOWN_CPU_HINT = (
    "this PoCL's compiler does not know this processor (its LLVM is older than the CPU): install "
    "a PoCL built with a newer LLVM, e.g. the distribution's (`apt-get install pocl-opencl-icd`; "
    "left to choose, emdflow uses the first device that builds its kernels), or choose another "
    "device with EMDFLOW_OPENCL_DEVICE (`emdflow devices` shows which ones work)"
)
_STAGES = ("common.cl", "prefilter.cl", "integral.cl", "states.cl", "evidence.cl", "evd.cl")
_PROGRAMS: dict = {}
_LOCK = threading.Lock()


def _import_cl():
    # PoCL's CPU device, left to itself, was measured here to run kernels at single-thread
    # speed on a 2-core machine; naming the thread count explicitly halves kernel times.
    # (Read once, when PoCL initialises; a value the user set wins.)
    os.environ.setdefault("POCL_MAX_PTHREAD_COUNT", str(len(os.sched_getaffinity(0))))
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise RuntimeError(f"the OpenCL backend needs pyopencl, which is not installed: {_INSTALL_HINT}") from exc
    return cl


def kernel_source(name: str) -> str:
    """Text of one kernel file, from the installed package or the source checkout."""
    try:
        return resources.files("emdflow.kernels").joinpath(name).read_text()
    except (ModuleNotFoundError, FileNotFoundError):
        path = Path(__file__).resolve().parent.parent / "kernels" / name
        if not path.is_file():
            raise RuntimeError(f"OpenCL kernel {name!r} not found (looked in package emdflow.kernels and {path})")
        return path.read_text()


def _all_devices():
    cl = _import_cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise RuntimeError(f"no OpenCL platform found ({exc}); {_INSTALL_HINT}") from exc
    devices = []
    for platform in platforms:
        try:
            devices.extend(platform.get_devices())
        except cl.Error:
            continue
    if not devices:
        raise RuntimeError(f"no OpenCL device found; {_INSTALL_HINT}")
    return devices


def list_devices() -> list[tuple[int, str]]:
    """The OpenCL devices as ``[(index, "platform: device"), ...]`` (whether or not they
    can build the kernels: see :func:`_first_buildable`)."""
    return [(i, device_label(d)) for i, d in enumerate(_all_devices())]


def device_label(device) -> str:
    """``"platform: device"``, the name :func:`list_devices` and :attr:`FlowEstimator.device`
    give a device (``emdflow devices`` matches the two)."""
    return f"{device.platform.name.strip()}: {device.name.strip()}"


def _device_choice(device) -> tuple:
    """``(choice, from_env)``: the caller's device choice, else EMDFLOW_OPENCL_DEVICE's
    (``from_env`` True); choice None: automatic. A choice is an index (an int, numpy's too,
    or a string of decimal digits) or a name (a str); anything else (True, 1.5, a list) is a
    ValueError (as every other bad parameter) rather than a guess. An empty or blank name is
    no choice (the variable then applies; " " matched any name with a space)."""
    if device is not None:
        if _is_whole(device):
            return int(device), False
        if not isinstance(device, str):
            raise ValueError(f"device={device!r}: expected an index (int) or part of a device name (str)")
        if device.strip():
            return device.strip(), False
    return os.environ.get("EMDFLOW_OPENCL_DEVICE", "").strip() or None, True


def _pick_device(choice, *, from_env: bool = False):
    """The device a non-automatic choice names: an index of ``list_devices()`` or a
    case-insensitive part of its name as listed ("platform: device") or of "platform
    device"; ``from_env``: the choice is EMDFLOW_OPENCL_DEVICE's (its errors say so: the
    variable is not in the call)."""
    devices = _all_devices()
    origin = " (EMDFLOW_OPENCL_DEVICE)" if from_env else ""
    if isinstance(choice, int) or choice.strip().isdecimal():
        index = int(choice)
        if not 0 <= index < len(devices):
            raise ValueError(f"OpenCL device index {index}{origin} out of range: {len(devices)} device(s) found")
        return devices[index]
    for d in devices:
        # (a part of the name as listed, "platform: device", or with a space between)
        if any(choice.lower() in name.lower() for name in (device_label(d), f"{d.platform.name} {d.name}")):
            return d
    names = ", ".join(device_label(d) for d in devices)
    raise ValueError(f"OpenCL device {choice!r}{origin} not found among: {names}")


def _int_arg_setter(kernel, probe_index: int):
    """``set(index, value)`` for a kernel's per-frame int arguments.

    pyopencl's ``Kernel.set_arg`` dispatches on the argument's type in Python (~8 us per
    call here, five calls a frame); its raw-bytes setter takes ~0.2 us. A pyopencl build
    without it (or where it refuses bytes: probed on the int argument ``probe_index``)
    falls back to ``set_arg``."""
    def slow(index, value):
        kernel.set_arg(index, np.int32(value))

    raw = getattr(kernel, "_set_arg_buf", None)
    if raw is None:
        return slow
    pack = struct.Struct("<i").pack
    try:
        raw(probe_index, pack(0))
    except Exception:  # noqa: BLE001 - a private API: any failure means "use the public one"
        return slow
    return lambda index, value: raw(index, pack(value))


def _fold_copies(copies: np.ndarray) -> np.ndarray:
    """Sum of the histogram copies (rows of ``copies``) as int64. Pairwise halving on
    contiguous halves: numpy's ``sum(axis=0)`` of 8 × 10 240 int32 took ~45 us here,
    this ~14 us (the extended model's histogram, every frame)."""
    while copies.shape[0] > 1 and copies.shape[0] % 2 == 0:
        half = copies.shape[0] // 2
        copies = copies[:half] + copies[half:]
    return copies[0].astype(np.int64) if copies.shape[0] == 1 else copies.sum(axis=0, dtype=np.int64)


def _shared_buffer(cl, ctx, queue, device, size: int, host_writes: bool):
    """``(buffer, host_array)`` of a buffer whose memory the host accesses directly, or
    None. On a CPU device a ``USE_HOST_PTR`` buffer is the host's memory itself (PoCL uses
    an aligned host pointer as is): the frame then reaches the kernels by one numpy copy
    into it instead of an enqueued write, and the result is read where the kernels wrote
    it, without a download command (each command's hand-over to PoCL's threads and back
    cost more than the copy itself: together ~0.05-0.1 ms per 640x480 frame here). The
    host touches the memory only between frames, when every command of the previous
    frame has finished. Whether the two sides really share it is checked here
    (``host_writes``: the device sees the host's writes, else the host sees the
    device's), twice, so a runtime that copies the memory once fails; any other device
    uses enqueued copies."""
    if not device.type & cl.device_type.CPU:
        return None
    raw = np.empty(size + 4096, np.uint8)
    host = raw[(-raw.ctypes.data) % 4096 :][:size]  # page-aligned
    flags = cl.mem_flags.READ_ONLY if host_writes else cl.mem_flags.READ_WRITE
    try:
        buf = cl.Buffer(ctx, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=host)
        seen = np.empty(size, np.uint8)
        for value in (0x5A, 0xA5):
            if host_writes:
                host[:] = np.arange(size) % 251 ^ value
                cl.enqueue_copy(queue, seen, buf, is_blocking=True)
                shared = np.array_equal(seen, host)
            else:
                cl.enqueue_fill_buffer(queue, buf, np.uint8(value), 0, size)
                queue.finish()
                shared = bool(np.all(host == value))
            if not shared:
                return None
    except cl.Error:  # pragma: no cover - depends on the runtime
        return None
    return buf, host


#: cells of the orientation lookup per quarter turn (evidence.cl: orientation_bin)
ORIENT_CELLS = 1024


@lru_cache(maxsize=None)
def orientation_cells() -> tuple[int, ...]:
    """The detector kernel's orientation lookup (``evidence.cl``, ``orientation_bin``).

    A gradient folded into the upper half-plane has the pseudo-angle
    ``p = gy / (|gx| + gy)`` for ``gx >= 0`` and ``2 - gy / (|gx| + gy)`` for ``gx < 0``,
    which grows with its angle over [0°, 180°). The kernel's cell is
    ``floor(ORIENT_CELLS · gy / (|gx| + gy))`` (``2 · ORIENT_CELLS`` minus that for
    ``gx < 0``), so ``ORIENT_CELLS · p`` lies strictly between ``j - 1`` and ``j + 1`` for the
    cell index ``j``.
    Entry ``j`` is the number of boundaries of :meth:`EngineParams.orientation_table`
    (exact fractions) at or below ``j - 1``: the gradient lies beyond all of them and
    before every boundary at or above ``j + 1``; at most one lies between (checked here:
    neighbouring boundaries are at least 2 cells apart), and that one, the entry's own
    index, the kernel tests exactly. So the bin is exactly the reference's count
    (:func:`emdflow.reference.orientation_bins`) with one division and one test.
    """
    scaled = []
    for c, s in EngineParams.orientation_table().tolist():
        if s <= 0:
            raise ValueError(f"orientation boundary ({c}, {s}) is not in the upper half-plane")
        p = Fraction(s, c + s) if c >= 0 else 2 - Fraction(s, s - c)
        scaled.append(ORIENT_CELLS * p)
    if any(b - a < 2 for a, b in zip(scaled, scaled[1:])):
        raise ValueError(f"orientation boundaries closer than 2 of {ORIENT_CELLS} cells: the lookup needs more")
    return tuple(bisect_right(scaled, j - 1) for j in range(2 * ORIENT_CELLS + 1))


def _ceil(a: int, b: int) -> int:
    return -(-a // b)


class _Layout:
    """Buffer geometry and compile-time constants for one frame size and parameter set."""

    SPAD = 16  # left padding of SAT rows (>= max radius + 1: 16-lane loads stay in bounds)
    PHEAD = 8  # zero words before the first state plane (a run's left neighbour word)
    PPAD = 16  # left padding of P rows
    #: histogram memory the detector kernel spreads its evidence atomics over, in
    #: orientation histograms: 8 copies of a histogram without gradient-strength classes,
    #: 2 of one with the four classes (so the copies zeroed, downloaded and summed per
    #: frame stay ~330 KB at 10 channels: 8 copies of the 4x larger one measured 0.02-0.05
    #: ms slower per 640x480 frame; with 2 threads even 1 copy measured no contention)
    HIST_BUDGET = 8
    #: copies of the frame's counters and of the detection position histogram (the
    #: same idea; see common.cl), and the counters' spacing in ints (two cache lines)
    COUNTER_COPIES, POS_COPIES, SLOT_INTS = 8, 8, 32

    def __init__(self, width: int, height: int, params: EngineParams):
        self.W, self.H = width, height
        self.NW = _ceil(width, 32)
        self.NSTRIPS = _ceil(width, 16)  # 16-column strips of the prefilter
        # plane rows of NW words, one zero word between rows: the detector kernel reads the
        # planes as one flat run of words, 8 at a time across row ends (at 640 px 21 words
        # a row instead of 24 when each row was padded to whole 8-word vectors)
        self.NWP = self.NW + 1
        self.PADR = 2 * max(params.scales)
        self.PSTRIDE = self.PPAD + self.NW * 32 + 32
        self.SSTRIDE = self.SPAD + self.NW * 32 + 32
        # Scale-1 receptors are the prefiltered pixels: their states (and the evidence's
        # gradients) come from a ring of prefiltered frames P, so the larger summed-area
        # tables are kept only as far back as the delays of the larger scales (two tables
        # for the extended model instead of five)
        self.P_SLOTS = params.max_delay + 1
        self.P_SIZE = self.PSTRIDE * height  # one slot of the prefiltered image
        self.SAT_SLOTS = 1 + max((d for k, d in params.channels if k > 1), default=0)
        # difference table S_t - S_(t-1) for the delay-1 channels at scales 3 and up
        self.DSAT = int(any(d == 1 and 1 < k for k, d in params.channels))
        chans = params.channels  # (at most 15: EngineParams checks it)
        self.channels = chans
        self.rings = [2 * d + 1 for _, d in chans]
        self.bases = [int(b) for b in np.cumsum([0] + self.rings[:-1])]
        self.plane_slots = int(sum(self.rings))
        self.t_period = math.lcm(self.SAT_SLOTS, self.P_SLOTS, *self.rings)
        self.plane_words = (height + 2 * self.PADR) * self.NWP
        # the detector kernel's 8-word runs: the flat words of rows 0..H-1 (each row's
        # leading zero word included), padded to whole runs and groups of runs
        self.n_runs = _ceil(height * self.NWP, 8)
        self.OUT_PLANE = self.n_runs * 8
        self.sat_elems = (height + 1) * self.SSTRIDE
        self.hist_size = params.evidence_axes * 2 * len(chans) * params.histogram_bins
        self.HIST_COPIES = max(1, self.HIST_BUDGET * ORIENTATION_BINS // params.histogram_bins)
        self.pos_size = 2 * 2 * len(chans) * POSITION_BINS
        self.n_fixed = STAT_FIRST_CHANGED + len(chans)  # at most 7 + 15 < SLOT_INTS
        # int32 statistics: the copies of the counters, of the positions, of the histogram
        self.pos_offset = self.COUNTER_COPIES * self.SLOT_INTS
        self.hist_offset = self.pos_offset + self.POS_COPIES * self.pos_size
        # (without the summary's evidence only the counters are zeroed and read)
        self.n_stats = (self.hist_offset + self.HIST_COPIES * self.hist_size if params.summary_evidence
                        else self.pos_offset)
        # output: per axis five bit planes (winning channel index, 4 bits, and sign) laid
        # out as the state planes' rows (OUT_PLANE words each: H rows of NWP words, padded)
        self.out_words = 2 * 5 * self.OUT_PLANE
        self.stats_offset = _ceil(4 * self.out_words, 64) * 64
        # the local threshold's contrast sums: per even row and tile, rows padded to whole
        # tiles (the padding, never written, stays zero) so the host sums them by a reshape
        self.LOCAL = int(params.threshold_mode == "local")
        self.NTY, self.NTX = params.threshold_tiles(width, height)
        self.TILE = params.threshold_tile
        self.tile_offset = self.n_stats
        self.tile_rows = self.NTY * self.TILE // 2 if self.LOCAL else 0
        self.result_bytes = self.stats_offset + 4 * (self.n_stats + self.tile_rows * self.NTX)
        table = EngineParams.orientation_table()
        w = params.weights
        if list(w) != list(w)[::-1]:  # prefilter.cl adds mirror taps before multiplying
            raise ValueError(f"prefilter taps {list(w)} are not symmetric; the OpenCL prefilter needs them to be")
        join = lambda v: ", ".join(str(int(x)) for x in v)  # noqa: E731
        self.defines = {
            "W": width, "H": height, "NW": self.NW, "NWP": self.NWP, "PADR": self.PADR,
            "PHEAD": self.PHEAD, "OUT_PLANE": self.OUT_PLANE, "PSTRIDE": self.PSTRIDE, "PPAD": self.PPAD,
            "P_SIZE": self.P_SIZE, "P_SLOTS": self.P_SLOTS,
            "SSTRIDE": self.SSTRIDE, "SPAD": self.SPAD, "SAT_SLOTS": self.SAT_SLOTS, "DSAT": self.DSAT,
            "NCH": len(chans),
            "COMPENSATE": int(params.brightness_compensation), "NSTRIPS": self.NSTRIPS,
            "BRIGHTNESS_RATIO_MAX_Q": EngineParams.BRIGHTNESS_RATIO_MAX_Q,
            "CH_K": join(k for k, _ in chans), "CH_D": join(d for _, d in chans),
            "CH_RING": join(self.rings), "CH_BASE": join(self.bases),
            "RADIUS": len(w) // 2, "WEIGHTS": join(w),
            "SHARP": int(params.sharp_templates),
            "STATS_OFFSET": self.stats_offset, "N_STATS": self.n_stats,
            "EVIDENCE": int(params.summary_evidence),
            "DIAGONAL": int(params.summary_evidence and params.diagonal_evidence),
            "EVIDENCE_ROW_STEP": params.evidence_row_step_for(height),
            # bits of a 32-pixel word in the sampled columns (the step is a power of two)
            "EVIDENCE_COLUMNS": "0x%08Xu" % sum(1 << j for j in range(0, 32, params.evidence_column_step(width))),
            "HIST_COPIES": self.HIST_COPIES, "POS_COPIES": self.POS_COPIES,
            "COUNTER_COPIES": self.COUNTER_COPIES, "SLOT_INTS": self.SLOT_INTS,
            "POS_BINS": POSITION_BINS,
            "FINEST_CHANNEL": chans.index((params.scales[0], 1)),
            "NBINS": ORIENTATION_BINS,
            "NCLASS": len(params.class_steps) + 1,
            "CLASS_STEPS": join(params.class_steps) or "0",
            "ORIENT_C": join(table[:, 0]),
            "ORIENT_S": join(table[:, 1]),
            "ORIENT_CELLS": ORIENT_CELLS, "ORIENT_CELL_TABLE": join(orientation_cells()),
            "LOCAL_THRESHOLD": self.LOCAL, "TILE": self.TILE, "NTX": self.NTX, "TILE_OFFSET": self.tile_offset,
        }

    def plane_rows(self, flat: np.ndarray) -> np.ndarray:
        """(..., OUT_PLANE) words as laid out by the detector kernel -> (..., H, NW) (a view)."""
        rows = flat[..., : self.H * self.NWP].reshape(*flat.shape[:-1], self.H, self.NWP)
        return rows[..., 1:]

    def header(self) -> str:
        return "".join(f"#define {k} {v}\n" for k, v in self.defines.items())


#: Set to 1 to build the kernels without the PoCL/clang/x86 compiler builtins (inline
#: atomics, clang's bit counts and constant shuffles, AVX2 pack and saturating intrinsics):
#: the standard OpenCL C 1.2 that GPUs and non-x86 boards run. The tests use it to check
#: that code path for exactness on PoCL.
PORTABLE_ENV = "EMDFLOW_OPENCL_PORTABLE"


class KernelBuildError(RuntimeError):
    """A device cannot run the emdflow kernels: its OpenCL compiler rejected them (the
    message carries the compiler's log), or no context could be made on it."""


#: devices the automatic choice has warned about (once per device and process)
_SKIPPED: set = set()


def _first_buildable(devices, build):
    """``(device, build(device))`` for the first device whose ``build`` does not raise
    :class:`KernelBuildError`; the failures are logged and, if every device fails,
    raised together. Two PoCL installations side by side (the pip wheel's and the
    distribution's) are common, and only one of them may know the processor."""
    failures = []
    for n, device in enumerate(devices):
        try:
            return device, build(device)
        except KernelBuildError as exc:
            failures.append(exc)
        if n + 1 < len(devices):  # a next one to try: say why this one is passed over
            key = getattr(device, "int_ptr", None) or device.name
            with _LOCK:
                new = key not in _SKIPPED
                _SKIPPED.add(key)
            if new:
                log.warning("OpenCL device %s cannot build the emdflow kernels; trying the next one (%s)",
                            device.name.strip(), first_error_line(str(failures[-1])))
    if len(failures) == 1:
        raise failures[0]
    raise KernelBuildError(f"none of the {len(failures)} OpenCL devices could build the emdflow kernels:\n"
                           + "\n".join(f"- {exc}" for exc in failures))


def error_summary(text: str) -> str:
    """One line for an OpenCL failure's message (a compiler log runs to many lines): its
    first line, the compiler's first ``error:`` line where that is another, and the fix
    where the message carries :data:`_UNKNOWN_CPU_HINT`."""
    line = next((x.strip() for x in text.splitlines() if x.strip()), "")
    error = first_error_line(text)
    if error not in line:
        line = f"{line} ... {error}"
    if _UNKNOWN_CPU_HINT in text and _UNKNOWN_CPU_HINT not in line:
        line = f"{line}; {_UNKNOWN_CPU_HINT}"
    return line


def exception_summary(exc: BaseException) -> str:
    """One line for an exception from the OpenCL engine: :func:`error_summary` of its
    message, or the exception's type name when it has none."""
    return error_summary(str(exc)) or type(exc).__name__


def first_error_line(text: str) -> str:
    """The line of an OpenCL failure's message that says why: the compiler's first
    ``error:`` line, else the first line ("" for none)."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return next((line for line in lines if "error:" in line), lines[0] if lines else "")


def _device_with_program(device, layout: _Layout, debug: bool):
    """``(device, context, queue, program)``: the device chosen by the caller or
    EMDFLOW_OPENCL_DEVICE, else the first one (in ``list_devices()`` order) that builds the
    kernels."""
    cl = _import_cl()
    choice, from_env = _device_choice(device)

    def build(dev):
        try:
            ctx, queue = _context(dev)
        except cl.Error as exc:  # a device without a usable context: as unusable as a failed build
            raise KernelBuildError(f"no OpenCL context on {dev.name.strip()}: {exc}") from exc
        return ctx, queue, _program(ctx, dev, layout, debug)

    chosen, (ctx, queue, program) = _first_buildable(
        [_pick_device(choice, from_env=from_env)] if choice is not None else _all_devices(), build)
    return chosen, ctx, queue, program


def program_source(device, layout: _Layout, debug: bool = False) -> str:
    """The OpenCL C the engine builds on ``device`` for ``layout``: its constants, the
    compiler's extras where the device is PoCL's (unless EMDFLOW_OPENCL_PORTABLE is set)
    and the kernels of every stage."""
    source = layout.header() + ("#define DEBUG_MATCHES 1\n" if debug else "")
    portable = os.environ.get(PORTABLE_ENV, "").strip() not in ("", "0")
    if not portable and "portable computing language" in device.platform.name.lower():
        # PoCL compiles for the host CPU with clang: compiler builtins beat its out-of-line
        # library (atomics) and its scalarised vector shuffles
        source += "#define EMD_INLINE_ATOMICS 1\n#define EMD_CLANG_BUILTINS 1\n"
        if device.type & _import_cl().device_type.CPU:
            source += "#define EMD_X86_BUILTINS 1\n"
    return source + "\n".join(kernel_source(name) for name in _STAGES)


def _program(ctx, device, layout: _Layout, debug: bool):
    cl = _import_cl()
    source = program_source(device, layout, debug)
    key = (device.int_ptr, source)
    with _LOCK:
        prog = _PROGRAMS.get(key)
        if prog is None:
            try:
                prog = _build(cl, ctx, device, source)
            except KernelBuildError as exc:
                # the same source fails the same way on the same compiler: later engines of
                # this process get its message (a str in place of the program) without
                # building again
                prog = str(exc)
            _PROGRAMS[key] = prog
    if isinstance(prog, str):
        raise KernelBuildError(prog)  # a fresh error each time (its own traceback)
    return prog


_KERNELS = ("prefilter_columns", "integral_rows", "ternary_states", "velocity_detectors")


def _build(cl, ctx, device, source: str):
    try:
        prog = cl.Program(ctx, source).build(options=["-cl-std=CL1.2"])
        if set(_KERNELS) <= set(prog.kernel_names.split(";")):
            return prog
        # A PoCL process killed while compiling can leave a cache entry without kernels
        # (seen with PoCL 3.0): build again under another cache key instead of failing.
        prog = cl.Program(ctx, source).build(options=["-cl-std=CL1.2", "-D", "EMD_REBUILD=1"])
        if set(_KERNELS) <= set(prog.kernel_names.split(";")):
            return prog
        raise RuntimeError(
            f"the emdflow OpenCL program on {device.name} lacks kernels ({prog.kernel_names!r}); "
            "clear the kernel cache (POCL_CACHE_DIR, default ~/.cache/pocl) and retry"
        )
    except cl.Error as exc:
        raise _build_failure(device.name, str(exc)) from exc


def _build_failure(device_name: str, log_text: str) -> KernelBuildError:
    """The error of a failed build: the device, the compiler's log and, where the log
    shows a known cause, what fixes it."""
    hint = f"; {_UNKNOWN_CPU_HINT}" if "unknown target CPU" in log_text else ""
    return KernelBuildError(f"building the emdflow OpenCL kernels failed on {device_name.strip()}: "
                            f"{log_text}{hint}")


_CONTEXTS: dict = {}


def _context(device):
    cl = _import_cl()
    with _LOCK:
        hit = _CONTEXTS.get(device.int_ptr)
        if hit is None:
            ctx = cl.Context([device])
            hit = (ctx, cl.CommandQueue(ctx))
            _CONTEXTS[device.int_ptr] = hit
    return hit


class PackedCodes:
    """The detector's output as downloaded: per axis, bit planes of the winning channel
    index ``c + 1`` (4 bits) and of the sign, 32 pixels per word (bit j of word i =
    pixel ``32 i + j``). :meth:`decode` gives the int8 codes ``±(c + 1)`` (0 = none)."""

    __slots__ = ("words", "width", "_lock", "__weakref__")

    def __init__(self, words: np.ndarray, width: int):
        self.words = words  # (2 axes, 5 planes, H, NW) uint32 (rows may be strided)
        self.width = width
        # decode() and detach() exclude each other: a decode in another thread must not
        # read memory the engine is about to overwrite
        self._lock = threading.Lock()

    def __reduce__(self):
        # (a lock does not pickle: a copy gets its own, and its own words)
        with self._lock:
            return PackedCodes, (self.words.copy(), self.width)

    def detach(self) -> None:
        """Copy the words out of the memory they share with the engine (its result buffer,
        which a later frame overwrites)."""
        with self._lock:
            self.words = self.words.copy()

    def decode(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            return self._decode()

    def _decode(self) -> tuple[np.ndarray, np.ndarray]:
        # 8 pixels at a time: a byte of each plane indexes a table of 8 code bytes (bit b
        # of the index at each set pixel), and the sign byte a table of 0xFF masks
        planes = self.words.astype("<u4", copy=False).view(np.uint8)  # (2, 5, H, 4 NW)
        spread = _SPREAD_TABLE
        code = spread[planes[:, 0]] | (spread[planes[:, 1]] << 1) | (spread[planes[:, 2]] << 2) \
            | (spread[planes[:, 3]] << 3)
        minus = spread[planes[:, 4]] * np.uint64(0xFF)
        # negate bytewise where the sign is set: (c ^ 0xFF) + 1, no carries (1 <= c <= 15)
        code = (code ^ minus) + (minus & np.uint64(0x0101010101010101))
        codes = code.view(np.int8)  # (2, H, 32 NW)
        if codes.shape[-1] != self.width:
            codes = np.ascontiguousarray(codes[..., : self.width])
        return codes[0], codes[1]


# byte p of entry v is bit p of v: 8 pixels of a bit plane -> 8 bytes of 0/1
_SPREAD_TABLE = (
    np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1, bitorder="little")
    .astype("<u1").copy().view("<u8").ravel()
)


class OpenCLEngine:
    """Device-resident detector; same interface and results as ``ReferenceEngine``."""

    def __init__(self, width: int, height: int, params: EngineParams, *, device=None, debug: bool = False):
        cl = _import_cl()
        self._cl = cl
        self.params = params
        self.layout = lay = _Layout(width, height, params)
        self.device, self.ctx, self.queue, self.program = _device_with_program(device, lay, debug)
        self.debug = debug
        mf = cl.mem_flags
        ctx = self.ctx
        tail = 64  # vector loads of the last row may run past its end
        shared = _shared_buffer(cl, ctx, self.queue, self.device, width * height + tail, host_writes=True)
        if shared is not None:
            self.frame_buf, host = shared
            #: the frame buffer's memory as a host array (a CPU device), or None
            self.frame_host = host[: width * height].reshape(height, width)
        else:
            self.frame_buf, self.frame_host = cl.Buffer(ctx, mf.READ_ONLY, width * height + tail), None
        self.p_buf = cl.Buffer(ctx, mf.READ_WRITE, lay.P_SIZE * lay.P_SLOTS + tail)
        self.sat_buf = cl.Buffer(ctx, mf.READ_WRITE, 2 * lay.sat_elems * lay.SAT_SLOTS + tail)
        self.dsat_buf = cl.Buffer(ctx, mf.READ_WRITE, (2 * lay.sat_elems if lay.DSAT else 0) + tail)
        # (the last plane's last run may read a row and 16 words past its end)
        plane_tail = lay.NWP + 16
        self.planes = cl.Buffer(ctx, mf.READ_WRITE, 4 * (lay.PHEAD + 2 * lay.plane_slots * lay.plane_words + plane_tail))
        shared = [_shared_buffer(cl, ctx, self.queue, self.device, lay.result_bytes, host_writes=False)
                  for _ in range(self.RESULT_SLOTS)]
        if all(slot is not None for slot in shared):
            # frames take the result buffers in turn, and a frame's bit planes stay where
            # the kernels wrote them (no copy per frame) until its buffer comes round
            # again; only codes still alive and not decoded by then are copied out
            self._results = shared
        else:
            self._results = [(cl.Buffer(ctx, mf.READ_WRITE, lay.result_bytes), None)]
        #: the codes of the frame each result buffer holds (weak references), or None
        self._result_codes = [None] * len(self._results)
        #: the latest frame's result buffer and its memory as a host array (a CPU device), or None
        self.result, self.result_host = self._results[0]
        # views of each result buffer's host memory, made once (a frame's host work after
        # the kernels runs on caches they have just emptied: ~3x slower than warm)
        self._result_views = [self._views(host) if host is not None else None for _, host in self._results]
        #: pixels the contrast statistic samples (the adaptive threshold's divisor)
        self._contrast_samples = params.contrast_samples(width, height)
        #: names of the commands of one frame, in the order of ``trace`` entries (no
        #: upload / download command where the host shares the buffer's memory)
        skipped = {"upload"} if self.frame_host is not None else set()
        skipped |= {"download"} if self.result_host is not None else set()
        self.stages = tuple(name for name in self.STAGES if name not in skipped)
        # brightness compensation: per slot of P the frame's pixel sum, then the
        # prefilter's per-strip sums, then each channel's gain (see common.cl, integral.cl)
        self.bright_buf = cl.Buffer(ctx, mf.READ_WRITE, 4 * (lay.P_SLOTS * (1 + lay.NSTRIPS) + len(params.channels)))
        # the local threshold's tiles (theta_q per tile, written by the host before each
        # frame; one unused int otherwise)
        n_tiles = lay.NTY * lay.NTX if lay.LOCAL else 1
        shared = _shared_buffer(cl, ctx, self.queue, self.device, 4 * n_tiles, host_writes=True)
        if shared is not None:
            self.theta_buf, host = shared
            self._theta_host = host.view(np.int32).reshape(-1)
        else:
            self.theta_buf = cl.Buffer(ctx, mf.READ_ONLY, 4 * n_tiles)
            self._theta_host = None
        self._theta_staging = np.zeros(n_tiles, np.int32)  # (the enqueued copy's source)
        #: pixels each tile's contrast statistic samples ('local')
        self._tile_samples = params.tile_contrast_samples(width, height)
        debug_words = 4 * len(params.channels) * lay.OUT_PLANE if debug else 1
        self.debug_buf = cl.Buffer(ctx, mf.READ_WRITE, 4 * debug_words)
        # (the result buffers too: the padding rows of the tiles' contrast sums are never
        # written and must read zero)
        for buf in (self.frame_buf, self.p_buf, self.sat_buf, self.dsat_buf, *(b for b, _ in self._results)):
            cl.enqueue_fill_buffer(self.queue, buf, np.uint8(0), 0, buf.size)
        # kernel objects of our own (the program is shared per process and shape; kernel
        # arguments are per object, so engines in different threads never collide)
        prg = self.program
        self._k_prefilter = cl.Kernel(prg, "prefilter_columns")
        self._k_integral = cl.Kernel(prg, "integral_rows")
        self._k_states = cl.Kernel(prg, "ternary_states")
        self._k_evd = cl.Kernel(prg, "velocity_detectors")
        # Explicit work-group sizes: PoCL's own choice sometimes puts a whole frame in one
        # or two groups and then runs it on one thread. Global sizes are padded to whole
        # groups; the kernels return early past the frame.
        strips = _ceil(width, 16)
        self._l_strips, self._l_rows, self._l_words = (2,), (4,), (8,)
        self._g_strips = (_ceil(strips, 2) * 2,)
        self._g_rows = (_ceil(height, 4) * 4,)
        self._g_words = (_ceil(lay.n_runs, 8) * 8,)
        # buffer arguments are set once; per frame only the scalars change (pyopencl's
        # Kernel.__call__ would set every argument again: ~10 us per launch)
        zero = np.int32(0)
        self._k_prefilter.set_args(self.frame_buf, self.p_buf, self.sat_buf, self.result, zero, zero,
                                   self.bright_buf)
        self._k_integral.set_args(self.sat_buf, self.dsat_buf, zero, self.bright_buf, zero)
        self._k_states.set_args(self.sat_buf, self.dsat_buf, self.planes, self.p_buf, self.frame_buf, self.result,
                                zero, zero, self.bright_buf, self.theta_buf)
        self._k_evd.set_args(self.planes, self.result, self.debug_buf, self.sat_buf, self.p_buf, zero, zero,
                             self.bright_buf, self.theta_buf)
        self._set_prefilter, self._set_integral, self._set_states, self._set_evd = (
            _int_arg_setter(k, i) for k, i in ((self._k_prefilter, 4), (self._k_integral, 2),
                                               (self._k_states, 6), (self._k_evd, 5)))
        #: set to a list to collect each frame's command events (needs a profiling queue)
        self.trace = None
        self.reset()

    def _views(self, host: np.ndarray) -> tuple:
        """``(planes, counters, positions, histograms, tiles)`` views of a result buffer's
        host memory: the bit planes as (2 axes, 5 planes, H, NW) words, the counter copies
        (COUNTER_COPIES, counters), the position and histogram copies (int32; None without
        the summary's evidence) and the local threshold's contrast sums as (tile rows,
        even rows of a tile, tile columns) (None without it)."""
        lay = self.layout
        planes = lay.plane_rows(host[: 4 * lay.out_words].view(np.uint32).reshape(2, 5, lay.OUT_PLANE))
        ints = host[lay.stats_offset :].view(np.int32)
        counters = ints[: lay.pos_offset].reshape(lay.COUNTER_COPIES, lay.SLOT_INTS)[:, : lay.n_fixed]
        tiles = None
        if lay.LOCAL:
            tiles = ints[lay.tile_offset : lay.tile_offset + lay.tile_rows * lay.NTX].reshape(
                lay.NTY, lay.TILE // 2, lay.NTX)
        if not self.params.summary_evidence:
            return planes, counters, None, None, tiles
        positions = ints[lay.pos_offset : lay.hist_offset].reshape(lay.POS_COPIES, lay.pos_size)
        hist = ints[lay.hist_offset : lay.hist_offset + lay.HIST_COPIES * lay.hist_size].reshape(
            lay.HIST_COPIES, lay.hist_size)
        return planes, counters, positions, hist, tiles

    def reset(self) -> None:
        """Forget the history: zero every state plane (and their padding)."""
        self._cl.enqueue_fill_buffer(self.queue, self.planes, np.uint8(0), 0, self.planes.size)
        self.queue.finish()
        self.t = 0
        self.theta_q = self.params.first_threshold_q(self.layout.W, self.layout.H)  # threshold of the next frame

    #: result buffers the frames take in turn where the host shares their memory
    RESULT_SLOTS = 2

    #: names of all the commands a frame may have (see ``stages``)
    STAGES = ("upload", "prefilter_columns", "integral_rows", "ternary_states", "velocity_detectors", "download")

    def step_packed(self, frame: np.ndarray):
        """Process one frame; returns ``(codes, stats, hist, positions)``.

        ``codes`` is a :class:`PackedCodes` (the detector's bit planes: 10 bits per pixel
        instead of two int8 codes, and no per-pixel work on the host);
        ``codes.decode()`` gives ``(u_code, v_code)`` like the reference.
        """
        cl, q, lay = self._cl, self.queue, self.layout
        # the kernels use t modulo the ring lengths and the SAT slots, and t < D: a device
        # t that wraps with period P (a multiple of them all, > every D) never overflows
        P = lay.t_period
        t = self.t if self.t < P else P + self.t % P
        slot = self.t % lay.SAT_SLOTS
        p_slot = self.t % lay.P_SLOTS
        launch = cl.enqueue_nd_range_kernel
        self._set_prefilter(4, slot)
        self._set_prefilter(5, p_slot)
        self._set_integral(2, slot)
        self._set_integral(4, p_slot)
        self._set_states(6, t)
        # (the local threshold's tiles are in theta_buf; the kernels then take the largest
        # as the frame's, which only chooses the states' arithmetic: see states.cl)
        theta_q = int(self.theta_q.max()) if lay.LOCAL else int(self.theta_q)
        self._set_states(7, theta_q)
        self._set_evd(5, t)
        self._set_evd(6, theta_q)
        # (one result buffer, or one the host cannot read in place: no turns to take)
        rotating = len(self._results) > 1
        slot_index = self.t % len(self._results)
        if rotating:
            self.result, self.result_host = self._results[slot_index]
            held = self._result_codes[slot_index]
            held = held() if held is not None else None
            if held is not None:  # a caller still holds that frame's field, not decoded
                held.detach()
            self._k_prefilter.set_arg(3, self.result)
            self._k_states.set_arg(5, self.result)
            self._k_evd.set_arg(1, self.result)
        if self.frame_host is not None:
            np.copyto(self.frame_host, frame)
            upload = ()
        else:
            upload = (cl.enqueue_copy(q, self.frame_buf, np.ascontiguousarray(frame), is_blocking=False),)
        if lay.LOCAL:  # the tiles' thresholds
            if self._theta_host is not None:
                self._theta_host[:] = self.theta_q.ravel()
            else:
                self._theta_staging[:] = self.theta_q.ravel()
                # (not among the frame's traced commands: a few bytes)
                cl.enqueue_copy(q, self.theta_buf, self._theta_staging, is_blocking=False)
        events = (
            *upload,
            launch(q, self._k_prefilter, self._g_strips, self._l_strips),
            launch(q, self._k_integral, self._g_rows, self._l_rows),
            launch(q, self._k_states, self._g_rows, self._l_rows),
            launch(q, self._k_evd, self._g_words, self._l_words),
        )
        if self.result_host is not None:
            views = self._result_views[slot_index]
            events[-1].wait()
            # the bit planes stay in the result buffer (detached before it is reused; with
            # one buffer there is no turn to wait for: copied); the statistics below are
            # summed into new arrays anyway
            planes = views[0] if rotating else views[0].copy()
        else:
            host = np.empty(lay.result_bytes, np.uint8)
            events += (cl.enqueue_copy(q, host, self.result, is_blocking=True),)
            views = self._views(host)
            planes = views[0]
        if self.trace is not None:  # profiling (emdflow bench --stages)
            self.trace.append(events)
        self.t += 1
        codes = PackedCodes(planes, lay.W)
        if rotating:
            self._result_codes[slot_index] = weakref.ref(codes)
        _, counters, position_copies, hist_copies, tiles = views
        # (the counters in int64 before they are added up: the contrast sum of a large
        # frame passes 2^31, each copy's share of it does not)
        stats = counters.sum(axis=0, dtype=np.int64)
        self.last_theta_q = self.theta_q
        #: each tile's contrast sum of this frame ('local'; None otherwise)
        self.tile_contrast = tiles.sum(axis=1, dtype=np.int64) if tiles is not None else None
        self.theta_q = self.params.next_threshold_q(int(stats[STAT_CONTRAST]), self._contrast_samples,
                                                    self.tile_contrast, self._tile_samples)
        if not self.params.summary_evidence:
            return codes, stats, None, None
        n_ch = len(lay.channels)
        positions = _fold_copies(position_copies)
        hist = _fold_copies(hist_copies).reshape(self.params.evidence_axes, 2 * n_ch, self.params.histogram_bins)
        return codes, stats, hist, positions.reshape(2, 2 * n_ch, POSITION_BINS)

    def step(self, frame: np.ndarray):
        """Process one frame; returns ``(u_code, v_code, stats, hist, positions)`` like the reference."""
        codes, stats, hist, positions = self.step_packed(frame)
        u_code, v_code = codes.decode()
        return u_code, v_code, stats, hist, positions

    # ---- inspection (tests): unpack device state into the reference's representation ----
    def _unpack(self, words: np.ndarray) -> np.ndarray:
        """(H, NW) uint32 words -> (H, W) bool, bit j of word i = pixel 32 i + j."""
        bits = np.unpackbits(words.astype("<u4").view(np.uint8), axis=1, bitorder="little")
        return bits[:, : self.layout.W].astype(bool)

    def debug_prefiltered(self) -> np.ndarray:
        """The last frame's prefiltered image P as (H, W) uint8 (like ``reference.prefilter``)."""
        lay = self.layout
        p = np.empty(self.p_buf.size, np.uint8)
        self._cl.enqueue_copy(self.queue, p, self.p_buf)
        slot = (self.t - 1) % lay.P_SLOTS
        rows = p[slot * lay.P_SIZE : (slot + 1) * lay.P_SIZE].reshape(lay.H, lay.PSTRIDE)
        return rows[:, lay.PPAD : lay.PPAD + lay.W].copy()

    def debug_states(self) -> list:
        """Ternary states of the last frame per channel, as int8 arrays (like the reference)."""
        lay = self.layout
        planes = np.empty(self.planes.size // 4, np.uint32)
        self._cl.enqueue_copy(self.queue, planes, self.planes)
        planes = planes[lay.PHEAD : lay.PHEAD + 2 * lay.plane_slots * lay.plane_words]
        planes = planes.reshape(lay.plane_slots, 2, lay.H + 2 * lay.PADR, lay.NWP)
        out = []
        for c, _ in enumerate(lay.channels):
            slot = lay.bases[c] + (self.t - 1) % lay.rings[c]
            rows = slice(lay.PADR, lay.PADR + lay.H)
            pos = self._unpack(planes[slot, 0, rows, 1 : 1 + lay.NW])
            neg = self._unpack(planes[slot, 1, rows, 1 : 1 + lay.NW])
            out.append(pos.astype(np.int8) - neg.astype(np.int8))
        return out

    def debug_matches(self) -> dict:
        """Raw detector outputs of the last frame, ``{(channel, 'E'|'W'|'S'|'N'): bool array}``.

        Needs ``debug=True`` at construction (the kernels then also write the matches).
        """
        if not self.debug:
            raise RuntimeError("debug_matches() needs OpenCLEngine(..., debug=True)")
        lay = self.layout
        words = np.empty(4 * len(lay.channels) * lay.OUT_PLANE, np.uint32)
        self._cl.enqueue_copy(self.queue, words, self.debug_buf)
        words = lay.plane_rows(words.reshape(len(lay.channels), 4, lay.OUT_PLANE))
        return {
            (c, d): self._unpack(words[c, j])
            for c in range(len(lay.channels))
            for j, d in enumerate("EWSN")
        }
