"""Middlebury ``.flo`` optical-flow files (read and write).

Format (Baker et al., "A Database and Evaluation Methodology for Optical Flow", the
Middlebury flow-code ``flowIO``), little-endian:

========  ===========  ==========================================================
bytes     type         content
========  ===========  ==========================================================
0–3       char[4]      the magic ``PIEH`` (the float 202021.25 read as float32)
4–7       int32        width
8–11      int32        height
12–       float32      ``height × width × 2`` values, row by row, ``u`` and ``v``
                       interleaved per pixel
========  ===========  ==========================================================

Unknown flow is stored as ``1e10``; by the Middlebury convention a value with magnitude
above ``1e9`` is unknown. The detector of emdflow can see one axis of a pixel and not the
other, so this module stores and reads unknown per *component*: NaN in ``u`` or ``v``
becomes ``1e10`` in that component only, and any component above ``1e9`` reads back as NaN.
(Middlebury's own tools treat the whole pixel as unknown when either component is.)
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["FLO_MAGIC", "UNKNOWN_FLOW", "UNKNOWN_THRESHOLD", "write_flo", "read_flo", "FloError"]

#: The four magic bytes at the start of every ``.flo`` file.
FLO_MAGIC = b"PIEH"
#: Value written for unknown flow.
UNKNOWN_FLOW = 1e10
#: Values with a larger magnitude are unknown when reading.
UNKNOWN_THRESHOLD = 1e9
_MAX_SIDE = 1 << 16


class FloError(ValueError):
    """A ``.flo`` file cannot be read or written; the message names the file."""


def write_flo(path, u: np.ndarray, v: np.ndarray) -> None:
    """Write a flow field as a Middlebury ``.flo`` file.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (conventionally ending in ``.flo``); overwritten if it exists.
    u, v : ndarray, shape (H, W)
        Horizontal (right) and vertical (down) flow in px/frame. NaN or infinite values are
        written as :data:`UNKNOWN_FLOW`.

    Raises
    ------
    FloError
        If ``u`` and ``v`` are not 2-D arrays of the same shape.
    OSError
        If the file cannot be written.
    """
    u = np.asarray(u, dtype=np.float32)
    v = np.asarray(v, dtype=np.float32)
    if u.ndim != 2 or u.shape != v.shape:
        raise FloError(
            f"{os.fspath(path)}: u and v must be 2-D arrays of one shape, got {u.shape} and {v.shape}"
        )
    h, w = u.shape
    data = np.empty((h, w, 2), dtype="<f4")
    data[..., 0] = np.where(np.isfinite(u), u, UNKNOWN_FLOW)
    data[..., 1] = np.where(np.isfinite(v), v, UNKNOWN_FLOW)
    with open(path, "wb") as f:
        f.write(FLO_MAGIC)
        f.write(np.array([w, h], dtype="<i4").tobytes())
        f.write(data.tobytes())


def read_flo(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a Middlebury ``.flo`` file.

    Parameters
    ----------
    path : str or os.PathLike
        The file to read.

    Returns
    -------
    u, v : ndarray of float32, shape (H, W)
        Flow in px/frame, NaN where the stored component is unknown (``|value| > 1e9``).

    Raises
    ------
    FloError
        If the file is missing, has no ``PIEH`` magic, an implausible size, or is truncated;
        the message names the file.
    """
    name = os.fspath(path)
    p = Path(path)
    if not p.is_file():
        raise FloError(f"{name}: no such file")
    raw = p.read_bytes()
    if len(raw) < 12 or raw[:4] != FLO_MAGIC:
        raise FloError(f"{name}: not a Middlebury .flo file (no PIEH magic)")
    w, h = (int(x) for x in np.frombuffer(raw, dtype="<i4", count=2, offset=4))
    if not (0 < w < _MAX_SIDE and 0 < h < _MAX_SIDE):
        raise FloError(f"{name}: implausible size {w}x{h}")
    expected = 12 + 8 * w * h
    if len(raw) < expected:
        raise FloError(f"{name}: truncated ({len(raw)} bytes, {w}x{h} needs {expected})")
    data = np.frombuffer(raw, dtype="<f4", count=2 * w * h, offset=12).reshape(h, w, 2)
    u = data[..., 0].astype(np.float32)
    v = data[..., 1].astype(np.float32)
    u[~(np.abs(u) <= UNKNOWN_THRESHOLD)] = np.nan
    v[~(np.abs(v) <= UNKNOWN_THRESHOLD)] = np.nan
    return u, v
