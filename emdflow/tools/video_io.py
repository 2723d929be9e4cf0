"""Frames in and video out for the offline tools.

Input (:func:`open_frames`): any video file OpenCV reads (FFmpeg backend), or a folder of
image files (sorted in natural order: ``f2.png`` before ``f10.png``), or one image file, or
``synthetic:KEY=VALUE,...`` — a camera flight over a photograph (:func:`parse_synthetic`),
to try the tools without a video.
Frames come out as 2-D uint8 gray images, optionally resized (area interpolation).

Output (:class:`VideoWriter`): lossless FFV1 in ``.avi`` or ``.mkv`` (default), MJPG in
``.avi`` (lossy, plays everywhere), or MPEG-4 part 2 (``mp4v``) in ``.mp4``. H.264 cannot
be written with the OpenCV wheel. Closing the writer (also on Ctrl-C, through the context
manager) writes the container's index, so an interrupted run leaves a playable file.

Every error is an :class:`InputError` / :class:`OutputError` whose message starts with the
offending path.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import sys
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "IMAGE_EXTENSIONS",
    "CODECS",
    "MAX_VIDEO_SIDE",
    "InputError",
    "OutputError",
    "parse_size",
    "to_gray",
    "list_image_files",
    "FrameSource",
    "open_frames",
    "parse_synthetic",
    "quiet_ffmpeg_log",
    "SYNTHETIC_DEFAULTS",
    "VideoWriter",
    "codec_for",
]

#: File name endings read as still images when INPUT is a folder (or one image).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pnm", ".webp")

#: Codec names accepted by :class:`VideoWriter` → (FourCC, allowed file endings).
CODECS = {
    "ffv1": ("FFV1", (".avi", ".mkv")),
    "mjpg": ("MJPG", (".avi", ".mkv")),
    "mp4v": ("mp4v", (".mp4", ".avi", ".mkv")),
}

#: Longest side, px, every codec of :data:`CODECS` writes here: the bound of an enlarged
#: flow video (measured with OpenCV 5.0's FFmpeg: mp4v opens 8190 px but not 8192, sides
#: being stored even; FFV1 and MJPG open 8192x8192, neither 16384x16384).
MAX_VIDEO_SIDE = 8190


class InputError(ValueError):
    """An input file or folder cannot be read; the message names it."""


class OutputError(ValueError):
    """An output file cannot be written; the message names it."""


def parse_size(text: str) -> tuple[int, int]:
    """Parse ``"WxH"`` (e.g. ``"320x240"``) into ``(width, height)``.

    Raises
    ------
    ValueError
        If the text is not two positive integers separated by ``x``.
    """
    m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", str(text))
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise ValueError(f"size {text!r}: expected WIDTHxHEIGHT, e.g. 320x240")
    return int(m.group(1)), int(m.group(2))


def to_gray(image: np.ndarray) -> np.ndarray:
    """Convert an OpenCV image (gray, BGR, BGRA; 8 or 16 bit, or float) to 2-D uint8.

    16-bit images keep their top 8 bits; float images are taken as 0..1 if their maximum
    is at most 1, else as 0..255.
    """
    if image.ndim == 3:
        if image.shape[2] == 1:
            image = image[..., 0]
        else:
            code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            image = cv2.cvtColor(np.ascontiguousarray(image), code)
    if image.dtype == np.uint8:
        return np.ascontiguousarray(image)
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    image = image.astype(np.float64)
    if image.size and np.nanmax(image) <= 1.0:
        image = image * 255.0
    return np.clip(np.rint(np.nan_to_num(image)), 0, 255).astype(np.uint8)


def _natural_key(name: str):
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def list_image_files(folder) -> list[Path]:
    """Image files directly inside ``folder`` (by :data:`IMAGE_EXTENSIONS`), natural order."""
    folder = Path(folder)
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS]
    return sorted(files, key=lambda p: _natural_key(p.name))


def quiet_ffmpeg_log() -> None:
    """Keep FFmpeg's own log (``[ffv1 @ 0x…] Slice pointer chain broken`` for every damaged
    frame) off stderr, unless ``EMDFLOW_DEBUG`` or ``OPENCV_FFMPEG_LOGLEVEL`` is set.

    OpenCV reads ``OPENCV_FFMPEG_LOGLEVEL`` once, when its FFmpeg backend first opens a file,
    so this runs when the modules that read video are imported. Redirecting file descriptor 2
    around ``read()`` is not enough: FFV1 decodes in worker threads, which log after
    ``read()`` has returned.
    """
    if not os.environ.get("EMDFLOW_DEBUG"):
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


quiet_ffmpeg_log()


@contextlib.contextmanager
def _quiet_native_stderr():
    """Silence FFmpeg's own messages on file descriptor 2 (e.g. "moov atom not found")."""
    if os.environ.get("EMDFLOW_DEBUG"):
        yield
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


class FrameSource:
    """Gray frames from a video file or a list of image files (use :func:`open_frames`).

    Attributes
    ----------
    path : str
        The input as given.
    width, height : int
        Size of the frames yielded (after resizing).
    fps : float or None
        Frame rate: the video's own, the one given to :func:`open_frames`, or None.
    frame_count : int or None
        Number of frames that will be yielded if known (a video's count is the
        container's claim and may be off by a few frames).
    """

    def __init__(self, path, capture, files, first, fps, frame_count, size, max_frames):
        self.path = str(path)
        self._capture = capture
        self._files = files
        self._first = first
        self._size = size
        self.height, self.width = (first.shape[:2] if size is None else (size[1], size[0]))
        self.fps = fps
        #: the count the container declares (None if unknown), before --max-frames
        self.declared_frames = frame_count if capture is not None else None
        if max_frames is not None:
            frame_count = max_frames if frame_count is None else min(frame_count, max_frames)
        self.frame_count = frame_count
        self._max_frames = max_frames
        self.source_size = (first.shape[1], first.shape[0])

    def _prepare(self, image, name) -> np.ndarray:
        gray = to_gray(image)
        if gray.shape[:2] != self._first.shape[:2]:
            raise InputError(
                f"{name}: frame size {gray.shape[1]}x{gray.shape[0]} differs from the first "
                f"frame's {self._first.shape[1]}x{self._first.shape[0]}"
            )
        if self._size is not None and (gray.shape[1], gray.shape[0]) != self._size:
            gray = cv2.resize(gray, self._size, interpolation=cv2.INTER_AREA)
        return gray

    def __iter__(self):
        limit = self._max_frames if self._max_frames is not None else float("inf")
        n = 0
        if self._files is not None:
            for p in self._files:
                if n >= limit:
                    break
                if isinstance(p, np.ndarray):  # a rendered synthetic frame
                    image = p
                else:
                    image = cv2.imread(str(p), cv2.IMREAD_UNCHANGED) if n else self._first
                if image is None:
                    raise InputError(f"{p}: OpenCV cannot read this image file")
                yield self._prepare(image, p)
                n += 1
            return
        try:
            image = self._first
            while image is not None and n < limit:
                yield self._prepare(image, self.path)
                n += 1
                with _quiet_native_stderr():  # (a damaged stream: FFmpeg's own lines per frame)
                    ok, image = self._capture.read()
                if not ok:
                    image = None
        finally:
            with _quiet_native_stderr():
                self._capture.release()
        declared = self.declared_frames
        if image is None and declared and n + 2 < min(declared, limit):  # (a container's count may be off by a frame)
            print(f"emdflow: {self.path}: the video ended after {n} of the {declared} frames its container "
                  "declares (a cut-off or damaged file?)", file=sys.stderr)

    def close(self) -> None:
        """Release the video file (also done when iteration ends)."""
        if self._capture is not None:
            self._capture.release()


#: Keys of a ``synthetic:`` input and their defaults (see :func:`parse_synthetic`).
SYNTHETIC_DEFAULTS = {
    "texture": "gravel", "u": 2.0, "v": 1.0, "frames": 60, "size": "320x240", "noise": 2.0,
    "contrast": 1.0, "drift": 0.0, "zoom": 0.0, "fps": 30.0, "seed": 0,
}


def parse_synthetic(uri: str) -> dict:
    """Parse ``synthetic:KEY=VALUE,...`` into a dict of :data:`SYNTHETIC_DEFAULTS` keys.

    Keys: ``texture`` (bundled name or image file), ``u``, ``v`` (px/frame), ``frames``,
    ``size`` (WxH), ``noise`` (σ ≥ 0, gray levels), ``contrast``, ``drift`` (relative exposure
    change over the clip), ``zoom`` (scale growth per frame, > -1), ``fps``, ``seed``.
    Numbers must be finite.

    Raises
    ------
    InputError
        On an unknown key or a bad value, naming the URI and the key.
    """
    opts = dict(SYNTHETIC_DEFAULTS)
    body = uri.split(":", 1)[1]
    for item in filter(None, (x.strip() for x in body.split(","))):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in opts:
            raise InputError(f"{uri}: unknown synthetic option {item!r}; keys: {', '.join(opts)}")
        try:
            if key in ("texture", "size"):
                opts[key] = value.strip()
            elif key in ("frames", "seed"):
                opts[key] = int(value)
            else:
                opts[key] = float(value)
        except ValueError:
            raise InputError(f"{uri}: bad value for {key}: {value!r}") from None
        # float() takes "nan" and "inf": the renderer would never return
        if isinstance(opts[key], float) and not math.isfinite(opts[key]):
            raise InputError(f"{uri}: bad value for {key}: {value.strip()!r} (must be a finite number)")
    try:
        opts["size"] = parse_size(opts["size"])
    except ValueError as e:
        raise InputError(f"{uri}: {e}") from None
    from emdflow.tools import frame_size_problem

    # (before the first frame is rendered: 100000x100000 was a traceback from OpenCV's
    # allocator)
    if problem := frame_size_problem(*opts["size"], dis=False):
        raise InputError(f"{uri}: size={opts['size'][0]}x{opts['size'][1]}: {problem}")
    if opts["frames"] < 1 or opts["fps"] <= 0:
        raise InputError(f"{uri}: frames and fps must be positive")
    if opts["frames"] > MAX_SYNTHETIC_FRAMES:  # (a clip of 10^20 frames overflowed an index)
        raise InputError(f"{uri}: frames={opts['frames']}: at most {MAX_SYNTHETIC_FRAMES}")
    if opts["zoom"] <= -1.0:  # the image scale (1 + zoom)**t would reach 0
        raise InputError(f"{uri}: zoom={opts['zoom']:g}: must be > -1 (scale growth per frame)")
    if opts["noise"] < 0:  # (the renderer took a negative σ as no noise, silently)
        raise InputError(f"{uri}: noise={opts['noise']:g}: must be 0 or more (σ, gray levels)")
    return opts


#: frames of a synthetic clip (rendered on demand: the bound only keeps counts sane, ~11.6
#: days at 1000 fps)
MAX_SYNTHETIC_FRAMES = 10**9


def _open_synthetic(uri, size, fps, max_frames) -> FrameSource:
    from emdflow.synthetic import CameraFlight

    o = parse_synthetic(uri)
    w, h = o["size"]
    try:
        flight = CameraFlight(o["texture"], width=w, height=h, flow=(o["u"], o["v"]), noise_sigma=o["noise"],
                              contrast=o["contrast"], exposure_drift=o["drift"], drift_frames=o["frames"],
                              expansion_rate=o["zoom"], seed=o["seed"])
    except ValueError as e:
        raise InputError(f"{uri}: {e}") from None
    files = _RenderedFrames(flight, o["frames"], uri)
    return FrameSource(uri, None, files, files[0], fps or o["fps"], len(files), size, max_frames)


class _RenderedFrames:
    """Frames of a flight rendered on demand (a sequence, so FrameSource treats it like files)."""

    def __init__(self, flight, count, uri):
        self.flight, self.count, self.uri = flight, count, uri

    def __len__(self):
        return self.count

    def __getitem__(self, t):
        try:
            return self.flight.render(t)
        except ValueError as e:  # e.g. a zoom flight receded too far to render
            raise InputError(f"{self.uri}: {e}") from None

    def __iter__(self):
        return (self[t] for t in range(self.count))


def open_frames(path, *, size=None, fps=None, max_frames=None) -> FrameSource:
    """Open a video file, a folder of images or one image as a source of gray frames.

    Parameters
    ----------
    path : str or os.PathLike
        Video file (anything OpenCV's FFmpeg backend reads), folder of image files, or
        one image file.
    size : (int, int), optional
        Resize every frame to ``(width, height)`` with area interpolation.
    fps : float, optional
        Frame rate to report; overrides the video's own (folders have none).
    max_frames : int, optional
        Stop after this many frames.

    Returns
    -------
    FrameSource
        Iterable of 2-D uint8 frames. The first frame has already been read, so a file
        that cannot be decoded fails here.

    Raises
    ------
    InputError
        If the path does not exist, is an empty folder, or cannot be decoded; the message
        starts with the path.
    """
    name = os.fspath(path)
    if size is not None:
        size = (int(size[0]), int(size[1]))
    if name.startswith("synthetic:"):
        return _open_synthetic(name, size, fps, max_frames)
    p = Path(name)
    if not p.exists():
        raise InputError(f"{name}: no such file or directory")
    if p.is_dir() or p.suffix.lower() in IMAGE_EXTENSIONS:
        files = list_image_files(p) if p.is_dir() else [p]
        if not files:
            raise InputError(
                f"{name}: folder has no image files ({', '.join(IMAGE_EXTENSIONS)})"
            )
        first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise InputError(f"{files[0]}: OpenCV cannot read this image file")
        return FrameSource(name, None, files, first, fps, len(files), size, max_frames)
    if not os.access(name, os.R_OK):
        raise InputError(f"{name}: permission denied")
    with _quiet_native_stderr():
        capture = cv2.VideoCapture(name, cv2.CAP_FFMPEG)
        ok, first = capture.read() if capture.isOpened() else (False, None)
    if not ok or first is None:
        capture.release()
        raise InputError(f"{name}: OpenCV cannot read this file as a video")
    own_fps = capture.get(cv2.CAP_PROP_FPS)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    if fps is None and own_fps and 0 < own_fps < 10000:
        fps = float(own_fps)
    return FrameSource(name, capture, None, first, fps, count if count > 0 else None, size, max_frames)


def codec_for(path, codec: str | None = None) -> str:
    """The codec key of :data:`CODECS` for an output path.

    ``.avi`` / ``.mkv`` default to lossless FFV1, ``.mp4`` to ``mp4v``.

    Raises
    ------
    OutputError
        If the ending or the codec is not supported.
    """
    name = os.fspath(path)
    ext = Path(name).suffix.lower()
    if codec is None:
        codec = {".avi": "ffv1", ".mkv": "ffv1", ".mp4": "mp4v"}.get(ext)
        if codec is None:
            raise OutputError(f"{name}: unsupported video type {ext or '(none)'}; use .avi, .mkv or .mp4")
    codec = codec.lower()
    if codec not in CODECS:
        raise OutputError(f"{name}: unknown codec {codec!r}; choose from {', '.join(CODECS)}")
    if ext not in CODECS[codec][1]:
        raise OutputError(f"{name}: codec {codec} needs one of {', '.join(CODECS[codec][1])}")
    return codec


class VideoWriter:
    """Write BGR frames to a video file; a context manager that always finalises the file.

    Parameters
    ----------
    path : str or os.PathLike
        Output file: ``.avi``/``.mkv`` (FFV1 lossless by default, or MJPG) or ``.mp4``.
    fps : float
        Frame rate stored in the container.
    codec : {'ffv1', 'mjpg', 'mp4v'}, optional
        Default from the file ending (see :func:`codec_for`).
    gray : bool
        Store gray frames as one 8-bit channel (FFV1 only; the daemon's ``video:`` source
        reads such a stream back bit-exact). Otherwise gray frames are stored as BGR.

    The file is opened at the first :meth:`write`, when the frame size is known.
    """

    def __init__(self, path, fps: float = 30.0, codec: str | None = None, *, gray: bool = False):
        self.path = os.fspath(path)
        self.codec = codec_for(self.path, codec)
        if gray and self.codec != "ffv1":
            raise OutputError(f"{self.path}: gray frames are stored with the ffv1 codec only, not {self.codec}")
        self.gray = gray
        self.fps = float(fps) if fps and fps > 0 else 30.0
        parent = Path(self.path).resolve().parent
        if not parent.is_dir():
            raise OutputError(f"{self.path}: folder {parent} does not exist")
        self._writer = None
        self.size = None
        self.frames_written = 0

    def write(self, image: np.ndarray) -> None:
        """Append one frame (BGR uint8 or gray uint8, all frames the same size; gray
        only with ``gray=True``). An odd side is padded by its last row or column (the
        writer stores even sides only)."""
        if self.gray:
            if image.ndim != 2:
                raise OutputError(f"{self.path}: a gray video takes 2-D frames, not shape {image.shape}")
        elif image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if image.shape[0] % 2 or image.shape[1] % 2:
            # OpenCV's writer cuts odd sides to even: pad with the edge instead, so nothing
            # of the picture is lost (``size`` is what is stored)
            pad = ((0, image.shape[0] % 2), (0, image.shape[1] % 2)) + ((0, 0),) * (image.ndim - 2)
            image = np.pad(image, pad, mode="edge")
        h, w = image.shape[:2]
        if self._writer is None:
            fourcc = cv2.VideoWriter_fourcc(*CODECS[self.codec][0])
            with _quiet_native_stderr():
                writer = cv2.VideoWriter(self.path, cv2.CAP_FFMPEG, fourcc, self.fps, (w, h), not self.gray)
            if not writer.isOpened():
                raise OutputError(f"{self.path}: OpenCV cannot write a {self.codec} video here")
            self._writer, self.size = writer, (w, h)
        elif (w, h) != self.size:
            raise OutputError(f"{self.path}: frame size {w}x{h} differs from {self.size[0]}x{self.size[1]}")
        self._writer.write(np.ascontiguousarray(image))
        self.frames_written += 1

    def close(self) -> None:
        """Finalise the file (writes the index; safe to call twice)."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
