"""Frame sources of the daemon, chosen by URI.

=========================  ==========================================================
URI                        Source
=========================  ==========================================================
``v4l2:/dev/videoN``       V4L2 camera by path (or udev symlink); ``v4l2:N`` by index
``depthai:CAM_B``          Luxonis OAK mono camera (``CAM_B`` or ``CAM_C``), depthai 3.x
``depthai-replay:PATH``    the DepthAI code path fed by ``ReplayVideo`` from a file
``video:PATH``             any video file OpenCV reads
``synthetic:``             camera flight over a photograph, options
                           ``texture=NAME,u=PX,v=PX,circle=PX,period=S,noise=S,seed=N,
                           supersample=N`` (see :mod:`firmware_py.sources.synthetic`)
=========================  ==========================================================
"""

from __future__ import annotations

import dataclasses

from .base import Frame, FrameError, FrameSource, Pacer, SourceConfigError, SourceError, centre_crop, fit_to

__all__ = ["Frame", "FrameSource", "SourceError", "SourceConfigError", "FrameError", "SourceSpec", "parse_uri", "open_source",
           "make_source", "SCHEMES", "Pacer", "fit_to", "centre_crop"]

SCHEMES = ("v4l2", "depthai", "depthai-replay", "video", "synthetic")
#: Schemes whose frames come from a camera (focal length must be configured).
CAMERA_SCHEMES = ("v4l2", "depthai")


@dataclasses.dataclass(frozen=True)
class SourceSpec:
    """A parsed source URI: ``scheme`` and the ``target`` after the colon."""

    scheme: str
    target: str

    @property
    def is_camera(self) -> bool:
        return self.scheme in CAMERA_SCHEMES

    @property
    def is_file(self) -> bool:
        return self.scheme in ("video", "depthai-replay")

    def __str__(self) -> str:
        return f"{self.scheme}:{self.target}"


def parse_uri(uri: str) -> SourceSpec:
    """Split and check a source URI; raise ValueError saying what is accepted."""
    scheme, sep, target = str(uri).partition(":")
    if not sep or scheme not in SCHEMES:
        raise ValueError(
            f"source {uri!r}: expected v4l2:/dev/videoN, v4l2:N, depthai:CAM_B, "
            "depthai-replay:PATH, video:PATH or synthetic:[options]"
        )
    if scheme in ("v4l2", "depthai", "video", "depthai-replay") and not target:
        raise ValueError(f"source {uri!r}: {scheme}: needs a device or path after the colon")
    if scheme == "v4l2" and not (target.isdecimal() or target.startswith("/dev/")):
        raise ValueError(f"source {uri!r}: expected v4l2:/dev/videoN or v4l2:N")
    if scheme == "v4l2" and target != target.strip():
        # ("/dev/video0 " is never plugged in: it was retried for ever as an absent camera)
        raise ValueError(f"source {uri!r}: the device has trailing whitespace; a device path has none")
    if scheme == "depthai" and target.upper() not in ("CAM_B", "CAM_C"):
        raise ValueError(f"source {uri!r}: expected depthai:CAM_B or depthai:CAM_C (OAK mono cameras)")
    if scheme == "synthetic":
        from .synthetic import parse_options

        parse_options(target)
    return SourceSpec(scheme, target)


def make_source(uri: str, *, width: int | None = None, height: int | None = None,
                fps: float | None = None, pixel_format: str = "GREY", buffer_count: int = 2,
                exposure_us: float | None = None, gain: float | None = None,
                loop: bool = False, realtime: bool = False) -> FrameSource:
    """Construct (not open) the source for ``uri``; see :func:`open_source`."""
    try:
        spec = parse_uri(uri)
    except ValueError as exc:
        raise SourceError(str(exc)) from None
    # Cameras and flights default to 320×240 at 100 frames/s; files keep their own size.
    cam_w, cam_h, cam_fps = width or 320, height or 240, fps or 100.0
    if spec.scheme == "v4l2":
        from .v4l2 import V4L2Source

        return V4L2Source(spec.target, width=cam_w, height=cam_h, fps=cam_fps,
                          pixel_format=pixel_format, buffer_count=buffer_count,
                          exposure_us=exposure_us, gain=gain)
    if spec.scheme == "depthai":
        from .depthai_source import DepthAISource

        return DepthAISource(spec.target, width=cam_w, height=cam_h, fps=cam_fps,
                             exposure_us=exposure_us, gain=gain)
    if spec.scheme == "depthai-replay":
        from .depthai_source import DepthAISource

        return DepthAISource(width=width, height=height, fps=cam_fps, replay_path=spec.target,
                             loop=loop, realtime=realtime)
    if spec.scheme == "video":
        from .video import VideoFileSource

        return VideoFileSource(spec.target, width=width, height=height, fps=fps, loop=loop,
                               realtime=realtime)
    from .synthetic import SyntheticSource

    return SyntheticSource(spec.target, width=cam_w, height=cam_h, fps=cam_fps, realtime=realtime)


def open_source(uri: str, *, width: int | None = None, height: int | None = None,
                fps: float | None = None, **options) -> FrameSource:
    """Construct and open the frame source named by ``uri``.

    Parameters
    ----------
    uri : str
        See the module docstring.
    width, height : int or None
        Processing resolution, px. None: 320×240 for cameras and synthetic flights, the
        file's own size for ``video:`` and ``depthai-replay:``.
    fps : float or None
        Requested camera / synthetic frame rate, frames/s (default 100); files use their own.
    **options
        ``pixel_format``, ``buffer_count`` (V4L2), ``exposure_us``, ``gain`` (cameras),
        ``loop``, ``realtime`` (files, synthetic).

    Raises
    ------
    SourceError
        Unknown URI, missing file or device, driver failure — the message names it.
    """
    source = make_source(uri, width=width, height=height, fps=fps, **options)
    source.open()
    return source
