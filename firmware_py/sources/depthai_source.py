"""``depthai:CAM_B`` — a Luxonis OAK mono camera through depthai 3.x, and
``depthai-replay:PATH`` — the same host-side code fed by ``ReplayVideo`` from a file.

Both build a pipeline whose last output delivers GRAY8 ``ImgFrame`` messages at the
processing resolution into a host queue; :meth:`DepthAISource.read` is the same for both.

- camera: ``Camera.build(socket, sensorFps=fps).requestOutput((w, h), GRAY8, CROP, fps)``;
  the timestamp is the device's capture time (``getTimestampDevice``), the latency start is
  the same instant in host time (``getTimestamp``, which depthai syncs to the host's
  monotonic clock), so USB transfer is counted. ``CROP`` keeps the aspect ratio: the
  sensor's 1280×800 (OV9282) or 640×480 (OV7251) image loses its sides or top and bottom,
  and :attr:`crop_fraction` says how much, from the first frame's source size (``open``
  waits for it), so a field of view in the configuration gives the right focal length;
- replay (no device, ``Pipeline(False)``): ``ReplayVideo`` (GRAY8), then the ``video:``
  source's centre crop to the w:h aspect ratio and area resize to w×h on the host (x and
  y scaled alike); the timestamp is ``sequence_number / file fps``. The frames come through
  a queue callback into :class:`_ReplayFrames` (ReplayVideo stops the pipeline right after
  its last frame, which closed the output queue with the file's last frames still in it);
  the replay stopping is the file's end, and so is no frame for several frame periods
  (2 s at least; 10 s before the first): a file is not a device that can be lost.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from queue import Empty, Full, Queue

import numpy as np

from ..clock import host_us
from .base import Frame, FrameSource, SourceConfigError, SourceError, fit_to
from .video import probe_video, stopped_short

__all__ = ["DepthAISource", "MONO_SOCKETS"]

log = logging.getLogger("emdflowd.depthai")

MONO_SOCKETS = ("CAM_B", "CAM_C")
# Replay runs as fast as the host takes frames unless --realtime; ReplayVideo paces itself
# to its fps, so "as fast as possible" is a high fps plus a blocking queue (back-pressure).
_UNPACED_FPS = 10_000.0
_GET_TIMEOUT_S = 2.0
# a replay: the pipeline starts (and the file opens) before its first frame
_FIRST_FRAME_TIMEOUT_S = 10.0
# how often a replay's reader (and its thread, when the reader is behind) looks again
_POLL_S = 0.01


def _import_depthai():
    try:
        import depthai
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise SourceError(
            f"depthai is not installed ({exc}); install it with: pip install 'emdflow[depthai]'"
        ) from None
    return depthai


class _ReplayFrames:
    """A replay's frames, handed from DepthAI's replay thread to the reader.

    ReplayVideo stops the pipeline as soon as it has sent a file's last frame, and the stop
    closes the output queue with what is still in it: the last two frames of every file
    were lost. DepthAI calls a queue's callbacks in the sending thread before it queues the
    message, so the frames are taken there and kept here, where the stop cannot reach them.
    """

    def __init__(self, newest_only: bool):
        # as fast as read: two frames and back-pressure (the replay waits for the reader);
        # paced (--realtime): only the newest, like a camera
        self._frames: Queue = Queue(maxsize=1 if newest_only else 2)
        self._newest_only = newest_only
        self._stopping = threading.Event()

    def put(self, msg) -> None:
        """The queue callback (DepthAI's replay thread): never raises, returns once stopped."""
        while not self._stopping.is_set():
            try:
                if self._newest_only:
                    self._frames.put_nowait(msg)
                else:
                    self._frames.put(msg, timeout=_POLL_S)
                return
            except Full:
                if self._newest_only:
                    try:
                        self._frames.get_nowait()  # the reader missed it: a camera drops it
                    except Empty:
                        pass

    def get(self, timeout: float):
        """The oldest frame kept, waiting up to ``timeout`` s; None if none came."""
        try:
            return self._frames.get(timeout=timeout) if timeout > 0 else self._frames.get_nowait()
        except Empty:
            return None

    def stop(self) -> None:
        """Release a replay thread waiting in :meth:`put` (close must not wait for a reader)."""
        self._stopping.set()
        while self.get(0) is not None:
            pass


class DepthAISource(FrameSource):
    """An OAK mono camera (``replay_path=None``) or a DepthAI replay of a video file.

    Parameters
    ----------
    socket : str
        ``CAM_B`` or ``CAM_C`` (the OAK-D left/right mono cameras); ignored for replay.
    width, height : int or None
        Processing resolution, px (replay: None keeps the file's size).
    fps : float
        Camera frame rate, frames/s (replay: the file's own rate is used).
    exposure_us : float or None
        Manual exposure, µs; None keeps auto exposure (camera only).
    gain : float or None
        Manual sensitivity as ISO (100..1600) when ``exposure_us`` is set (camera only).
    replay_path : str or None
        Video file for ``depthai-replay:``.
    loop : bool
        Replay: rewind at the end (``ReplayVideo.setLoop``).
    realtime : bool
        Replay: release frames at the file's rate.
    """

    def __init__(self, socket: str = "CAM_B", *, width: int | None = 320, height: int | None = 240,
                 fps: float = 100.0, exposure_us: float | None = None, gain: float | None = None,
                 replay_path: str | None = None, loop: bool = False, realtime: bool = False):
        _import_depthai()  # a missing package is a configuration error, not a lost camera
        self.replay_path = replay_path
        self.live = replay_path is None
        self.loop, self.realtime = bool(loop), bool(realtime)
        self.waits_in_read = self.realtime and not self.live  # (ReplayVideo's own pacing)
        self.exposure_us, self.gain = exposure_us, gain
        #: a replayed file's declared frame count (None: a camera, or none declared)
        self.declared_frames = None
        if self.live:
            socket = socket.upper()
            if socket not in MONO_SOCKETS:
                raise SourceError(f"depthai:{socket}: expected one of {', '.join(MONO_SOCKETS)} (OAK mono cameras)")
            self.uri = f"depthai:{socket}"
            self.socket = socket
            self.width, self.height, self.fps = int(width or 320), int(height or 240), float(fps)
        else:
            self.uri = f"depthai-replay:{replay_path}"
            native_w, native_h, file_fps, self.declared_frames = probe_video(replay_path)
            if not (file_fps > 0 and math.isfinite(file_fps)):
                file_fps = float(fps)
            self.width, self.height, self.fps = int(width or native_w), int(height or native_h), float(file_fps)
            self.default_focal_length_px = float(self.width)
            self._note_crop(native_w, native_h, "file")
        self._pipeline = None
        self._queue = None
        self._first = None  # the live camera's first frame, read by open()
        self._playing = False  # a replay's pipeline started (at the first read)
        self._index = 0
        self._last_index = -1  # a replay's last frame index (its position in the file)
        self._period_us = 1e6 / self.fps

    def _note_crop(self, delivered_w: int, delivered_h: int, what: str) -> None:
        """Record the shares of a delivered image's width and height that the centre crop
        to the processing aspect ratio keeps (:attr:`crop_fraction`; logged when it cuts)."""
        _, _, crop_w, crop_h = self._record_crop(delivered_w, delivered_h)
        crop = self.crop_fraction
        if crop != (1.0, 1.0):
            # a sensor of another aspect ratio is the normal case for a camera; a file is not
            level = logging.INFO if what == "sensor" else logging.WARNING
            log.log(level, "%s: the %s image is %dx%d, [source] asks for %dx%d (another aspect ratio): "
                    "its centre %dx%d (%.1f %% of its width) is used; a field of view in [optics] is "
                    "that of the whole %dx%d image", self.uri, what, delivered_w, delivered_h,
                    self.width, self.height, crop_w, crop_h, 100.0 * crop[0], delivered_w, delivered_h)

    # -- pipeline construction: the only part that differs between camera and replay --
    def _build_camera(self, dai, pipeline):
        cam = pipeline.create(dai.node.Camera).build(getattr(dai.CameraBoardSocket, self.socket), sensorFps=self.fps)
        if self.exposure_us is not None:
            iso = int(self.gain) if self.gain is not None else 400
            cam.initialControl.setManualExposure(int(self.exposure_us), iso)
        # CROP (depthai's default, said here): the sensor image is centre-cropped to the
        # aspect ratio, never stretched; open() learns the crop from the first frame
        return cam.requestOutput((self.width, self.height), dai.ImgFrame.Type.GRAY8,
                                 resizeMode=dai.ImgResizeMode.CROP, fps=self.fps)

    def _build_replay(self, dai, pipeline):
        replay = pipeline.create(dai.node.ReplayVideo)
        replay.setReplayVideoFile(self.replay_path)
        replay.setOutFrameType(dai.ImgFrame.Type.GRAY8)
        replay.setLoop(self.loop)
        replay.setFps(self.fps if self.realtime else _UNPACED_FPS)
        # The file's own frames: the centre crop to the aspect ratio and the resize are the
        # video: source's, on the host (_to_frame). DepthAI's host ImageManip resampled by
        # nearest pixel (darkening the last row and column when enlarging): on a noisy
        # 1280x960 recording scaled to 320x240 the summary's quality halved.
        return replay.out

    def _start(self, dai):
        """Build the pipeline and start a live camera's; returns (pipeline, output queue):
        a replay's is a :class:`_ReplayFrames`, and it starts at the first read
        (:meth:`_play`)."""
        if self.live:
            pipeline = dai.Pipeline()  # connects to the first OAK found
            output = self._build_camera(dai, pipeline)
            # Live camera: keep only the newest frame, never queue into latency.
            queue = output.createOutputQueue(maxSize=1, blocking=False)
            pipeline.start()
        else:
            pipeline = dai.Pipeline(False)  # host only, no device
            output = self._build_replay(dai, pipeline)
            # A paced file is a camera, which drops the frames a slow reader misses (a
            # blocking queue slowed the whole replay below real time instead); a file as
            # fast as it is read has back-pressure instead of dropping.
            queue = _ReplayFrames(newest_only=self.realtime)
            # DepthAI's own queue only carries the callback: never blocking, never read
            output.createOutputQueue(maxSize=1, blocking=False).addCallback(queue.put)
        return pipeline, queue

    def _play(self) -> bool:
        """Start a replay's pipeline; False (logged) if it cannot start. ReplayVideo plays
        the file from ``start()``, and the daemon builds and warms up its engine between
        ``open()`` and the first read (seconds on PoCL): started in ``open()``, a paced
        replay had played those seconds' frames to a queue that keeps only the newest (a
        4 s recording gave 1 frame). A file whose replay cannot start has ended, as one
        that cannot be opened (the daemon then stops, exit 2 before any frame): a retry
        would fail the same way."""
        try:
            self._pipeline.start()
        except Exception as exc:
            log.error("%s: cannot start the DepthAI pipeline: %s", self.uri, exc)
            return False
        self._playing = True
        return True

    def open(self) -> None:
        self.close()
        dai = _import_depthai()
        try:
            self._pipeline, self._queue = self._start(dai)
        except SourceError:
            raise
        except Exception as exc:
            if self.live and "socket not found" in str(exc).lower():
                raise SourceConfigError(
                    f"{self.uri}: cannot start the DepthAI pipeline: {exc} (this OAK has no {self.socket} "
                    f"camera: emdflow uses the mono cameras {' or '.join(MONO_SOCKETS)}; an OAK-1 has only "
                    "the colour camera)") from None
            hint = " (is an OAK connected, and the udev rule for 03e7 installed?)" if self.live else ""
            raise SourceError(f"{self.uri}: cannot start the DepthAI pipeline: {exc}{hint}") from None
        self._index = 0
        self._last_index = -1
        self._playing = self.live
        if self.live:
            # the crop the camera applies is known from its frames: wait for the first
            try:
                self._first = self._next()
            except SourceError:
                self.close()
                raise
            self._note_delivered_crop(self._first)

    def _note_delivered_crop(self, msg) -> None:
        """Record the centre crop the camera applied, from a frame's source (sensor image)
        size; (1, 1) when the frame does not say."""
        self.crop_fraction = (1.0, 1.0)
        try:
            source_w, source_h = int(msg.getSourceWidth()), int(msg.getSourceHeight())
        except Exception as exc:  # noqa: BLE001 - metadata only: the frames are still good
            log.debug("%s: no source size on the frames (%s)", self.uri, exc)
            return
        if source_w <= 0 or source_h <= 0:
            log.warning("%s: the frames do not say their sensor image size: the crop is unknown, and a "
                        "field of view in [optics] is taken over the %dx%d frames themselves", self.uri,
                        self.width, self.height)
            return
        self._note_crop(source_w, source_h, "sensor")

    def read(self) -> Frame | None:
        if self._queue is None:
            raise SourceError(f"{self.uri}: not open")
        if not self._playing and not self._play():
            return None
        if self._first is not None:
            # the frame open() waited for, unless a newer one came meanwhile (the daemon
            # builds its engine between open and the first read: seconds on PoCL)
            msg, self._first = self._first, None
            newer = self._queue.tryGet()
            self.waited_us = 0
            return self._to_frame(msg if newer is None else newer)
        t0 = host_us()
        msg = self._next()
        if msg is None:
            return None
        self.waited_us = host_us() - t0  # queue wait (replay pacing), not capture work
        return self._to_frame(msg)

    def _next(self):
        """The next message from the queue; None at the end of a replay."""
        if not self.live:
            return self._next_replayed()
        try:
            msg = self._queue.get(timeout=_timedelta(_GET_TIMEOUT_S))
        except Exception as exc:
            # the queue closes when the device goes away
            raise SourceError(f"{self.uri}: {exc or 'pipeline stopped'}") from None
        if msg is None:
            raise SourceError(f"{self.uri}: no frame for {_GET_TIMEOUT_S:g} s")
        return msg

    def _next_replayed(self):
        """The replay's next frame; None at the end of the file."""
        # a file cannot be unplugged: no frame for several of its frame periods (or for
        # longer before its first, while the pipeline starts) is its end. A lost device
        # it is not: a file that decodes to nothing was reopened for ever, and a
        # time-lapse below 0.5 fps never got past its first frame.
        timeout = max(_GET_TIMEOUT_S, 3.0 / self.fps if self.realtime else 0.0,
                      _FIRST_FRAME_TIMEOUT_S if self._index == 0 else 0.0)
        deadline = time.monotonic() + timeout
        while True:
            # ReplayVideo stops the pipeline after handing over the file's last frame (or
            # when it cannot decode the file): stopped, asked before looking, and nothing
            # kept is the end, with no frame left behind
            ended = not self._pipeline.isRunning()
            msg = self._queue.get(0 if ended else _POLL_S)
            if msg is not None:
                return msg
            if ended:
                log.debug("%s: the replay stopped: the end of the file", self.uri)
                self._note_short_file()
                return None
            if time.monotonic() >= deadline:
                log.info("%s: no frame for %.1f s: the end of the file", self.uri, timeout)
                self._note_short_file()
                return None

    def _note_short_file(self) -> None:
        """Warn when a replay ended well before the frames its file declares: the replay
        stops at a cut-off or corrupt part as at the end (the video: source says the same).
        By the last frame's position in the file, so a paced replay's dropped frames do not
        count; a looped replay rewinds instead of ending."""
        if not self.loop and stopped_short(self._last_index + 1, self.declared_frames):
            log.warning("%s: the replay stopped after %d of the %d frames the file declares (cut off or "
                        "corrupt?)", self.uri, self._last_index + 1, self.declared_frames)

    def _to_frame(self, msg) -> Frame:
        received = host_us()
        image = msg.getFrame()
        if image.ndim == 3:
            image = image[:, :, 0]
        image = np.ascontiguousarray(image, dtype=np.uint8)
        index = int(msg.getSequenceNum())
        self._last_index = index
        if self.live:
            stamp = int(msg.getTimestampDevice().total_seconds() * 1e6)
        else:
            stamp = int(round(index * self._period_us))
            image = fit_to(image, self.width, self.height)
        if self.live or self.realtime:
            # host monotonic time (µs) the camera captured it, or the paced replay released
            # it (when it was due): latency then counts any wait in the queue
            captured = int(msg.getTimestamp().total_seconds() * 1e6)
            if not (0 <= received - captured < 2_000_000):
                captured = received
        else:
            captured = received
        self._index += 1
        return Frame(image, stamp, captured, index)

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                if isinstance(self._queue, _ReplayFrames):
                    self._queue.stop()
                if self._playing:  # (a replay not read from never started)
                    self._pipeline.stop()
                    if not self.live:
                        # the replay thread may be in our callback: let it leave (wait() lets
                        # go of the GIL) before the pipeline is dropped, whose destructor
                        # waits for that thread while holding the GIL the callback needs
                        self._pipeline.wait()
            except Exception as exc:  # closing must never raise
                log.debug("%s: pipeline stop: %s", self.uri, exc)
            self._pipeline = None
            self._queue = None
        self._first = None
        self._playing = False


def _timedelta(seconds: float):
    import datetime

    return datetime.timedelta(seconds=seconds)
