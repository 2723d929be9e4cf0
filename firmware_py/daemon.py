"""The frame loop: source → FlowEstimator → summary → serial link, with recovery.

Structure (``[daemon] threading``, see :func:`choose_threading` for the measurement):

- ``capture-thread`` (default for cameras): a capture thread drains the
  source as fast as frames arrive and hands the newest accepted frame to the processing
  loop through a one-slot mailbox — frames are never queued into latency. When the engine
  cannot keep up, the capture thread passes a *steady subset* (every k-th frame) so the
  detector still sees evenly spaced frames; the link converts with the real interval taken
  from the capture timestamps.
- ``single`` (default for files and synthetic flights, paced or not): one thread reads and
  processes. Unpaced, nothing is dropped; paced (``--realtime``), the source skips the
  frames a camera would have dropped while the engine was busy.

The processing loop also services the link every iteration (heartbeats and quality-0 flow
messages go on while the camera is blind), pings the systemd watchdog, resets the estimator
only after a long gap, and logs one status line every ``log_interval_s``. "Long" is relative
to the typical interval between processed frames (capture timestamps): a slow camera or a
large frame subset is not a gap at every frame.
"""

from __future__ import annotations

import contextlib
import logging
import math
import statistics
import sys
import threading
import time
import warnings
from collections import deque
from typing import Callable

import numpy as np

import emdflow
from emdflow.cues import looming_cues
from emdflow.estimator import FrameSizeError

from .angular import TURN_GAIN_WARNING, RecentIntervals, apply_mounting, fov_deg_from_focal_length_px, turn_gain
from .clock import host_us
from .config import Config, ConfigError
from .links import FlowSample
from .sdnotify import Notifier
from .sources import Frame, FrameSource, SourceConfigError, SourceError, make_source
from .sources.base import _BAD_FRAME_LOG_S

__all__ = ["Daemon", "SourceKeeper", "FrameMailbox", "SteadySubset", "Stats", "choose_threading"]

log = logging.getLogger("emdflowd")

_POLL_S = 0.01            # longest wait for a frame before servicing the link again
#: The interpreter's switch interval while the report writer runs, s (see _ReportWriter).
_WRITER_SWITCH_S = 0.0005
# A driver call (open, read, close) that has not returned for this long is hung (OpenCV's
# V4L2 read gives up after 10 s): only a new process recovers it, so the daemon exits 1 and
# systemd restarts it.
_STUCK_DRIVER_S = 20.0
#: Fewest rows of a frame that should feed the summary (:meth:`Daemon._warn_of_sparse_evidence`).
_MIN_EVIDENCE_ROWS = 15
# Frames further apart than this many typical processed intervals are a gap (and no frame
# for that long is blindness), when that is longer than the configured time.
_GAP_INTERVALS = 3.0
# A reopened source that has delivered frames for this long is working again: only then does
# its reopen back-off start again from the first delay (one frame and a failure is no
# recovery; the extended model needs 12 frames before its first flow).
_STEADY_S = 5.0
# Frames after an uneven step sent with quality 0, at most (see Daemon._process): the span
# of the delay-1 and delay-2 channels, where audits measured the error. The extended
# model's delay-4 channels span 12 and, at 0.5 px/frame, stay off a few frames longer
# (12-16 % after a drop, ~25 % on two frames after a 0.2 s stall), but 12 blank frames are
# 200 ms at 60 fps: EKF3 and INAV stop using flow after that.
_UNEVEN_FRAMES_MAX = 6
# An error of the engine or the summary on a frame (an OpenCL runtime error, a driver
# fault) skips that frame and resets the estimator: the link sends quality 0 while blind,
# as for a bad frame. Errors that keep the flow from coming back (no ready field between
# them) for this long, at least _ENGINE_FAILURE_EXIT_ERRORS of them, are not transient:
# the daemon exits 1 and systemd restarts it, which builds the engine afresh.
_ENGINE_FAILURE_EXIT_S = 3.0
_ENGINE_FAILURE_EXIT_ERRORS = 10


def choose_threading(setting: str, *, live: bool) -> str:
    """Resolve ``auto``: a capture thread for cameras (``live``; the daemon also passes a
    paced source on the numpy reference, which cannot keep up), one thread otherwise.

    Measured with ``emdflowd --demo`` (320×240 at 100 frames/s, PoCL, 2 cores): one thread
    gives the lower latency when the engine keeps up (p50 3.5–4.7 ms, p99 8–10 ms against
    5.0–5.9 ms and 11–23 ms with a capture thread: the hand-over and the second Python
    thread cost more than they overlap). Cameras still get the capture thread: a driver
    read can block for seconds (OpenCV's V4L2 read gives up after 10 s), which must not stop
    heartbeats and the watchdog, and only the capture side can pass an evenly spaced subset
    of a camera's frames when the engine falls behind.
    """
    if setting != "auto":
        return setting
    return "capture-thread" if live else "single"


class Stats:
    """Counters and per-stage timings, cheap enough to update every frame.

    Counters only grow; :meth:`interval` returns the differences since the previous call.
    Stage times are sums and maxima in µs per log interval. The capture thread counts too:
    a counter either thread changes goes through :meth:`add` (``+=`` on an attribute is a
    read and a write, and a thread switch between them loses the other thread's count).
    """

    COUNTERS = ("frames_in", "processed", "skipped", "dropped", "bad_frames", "resets",
                "reopens", "blind_periods", "uneven", "engine_errors")
    STAGES = ("capture", "wait", "engine", "summary", "link")

    def __init__(self):
        for name in self.COUNTERS:
            setattr(self, name, 0)
        self._last = {name: 0 for name in self.COUNTERS}
        self.stage_sum = dict.fromkeys(self.STAGES, 0)
        self.stage_max = dict.fromkeys(self.STAGES, 0)
        self.stage_n = dict.fromkeys(self.STAGES, 0)
        self.last_summary = None
        self.last_field = None
        self.started_host_us = host_us()
        self._lock = threading.Lock()

    def add(self, name: str, count: int = 1) -> None:
        """Add ``count`` to the counter ``name`` (from any thread)."""
        with self._lock:
            setattr(self, name, getattr(self, name) + count)

    def stage(self, name: str, us: int) -> None:
        with self._lock:  # (the capture thread times "capture" while the loop resets the sums)
            self.stage_sum[name] += us
            self.stage_n[name] += 1
            if us > self.stage_max[name]:
                self.stage_max[name] = us

    def interval(self) -> dict:
        """Counter increments and mean/max stage times since the previous call."""
        out = {}
        with self._lock:
            for name in self.COUNTERS:
                value = getattr(self, name)
                out[name] = value - self._last[name]
                self._last[name] = value
            for name in self.STAGES:
                n = self.stage_n[name]
                out[f"{name}_ms"] = self.stage_sum[name] / n / 1000.0 if n else 0.0
                out[f"{name}_max_ms"] = self.stage_max[name] / 1000.0
                self.stage_sum[name] = self.stage_max[name] = self.stage_n[name] = 0
        return out

    def totals(self) -> dict:
        return {name: getattr(self, name) for name in self.COUNTERS}


class FrameMailbox:
    """One slot between capture and processing: a new frame replaces an unread one.

    Parameters
    ----------
    block : bool
        True for files read as fast as possible: ``put`` waits for the slot instead of
        replacing (back-pressure, nothing dropped).
    """

    def __init__(self, *, block: bool = False):
        self._frame: Frame | None = None
        self._cond = threading.Condition()
        self.block = block
        self.closed = False

    def put(self, frame: Frame) -> bool:
        """Deliver ``frame``; True if it replaced an unprocessed frame (a drop)."""
        with self._cond:
            if self.block:
                while self._frame is not None and not self.closed:
                    self._cond.wait(0.1)
            dropped = self._frame is not None
            self._frame = frame
            self._cond.notify_all()
            return dropped

    def get(self, timeout: float) -> Frame | None:
        """Take the frame, waiting at most ``timeout`` s; None if there is none."""
        with self._cond:
            if self._frame is None:
                self._cond.wait(timeout)
            frame, self._frame = self._frame, None
            if frame is not None:
                self._cond.notify_all()
            return frame

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


class SteadySubset:
    """Chooses k so that every k-th frame can be processed in time.

    The detector assumes evenly spaced frames and needs three in a row after a reset, so
    "process whatever arrives while idle" can starve it under load. Instead the capture
    side passes frames whose index is k apart. k follows robust statistics of the last
    ``window`` processing times: it rises as soon as the *median* needs more than k frame
    intervals, and falls only after the *90th percentile* has fitted into fewer intervals for
    ``relax_s``, to what that percentile needs but at most by half — a single slow frame
    (garbage collection, a kernel build) changes nothing, a lasting load changes k at once.

    Parameters
    ----------
    margin : float
        Headroom factor on the processing time.
    relax_s : float
        Time the load must stay low before k decreases, s.
    max_k : int
        Largest decimation: only a bound against a nonsense interval. A k too small for the
        engine leaves every processed frame unevenly spaced (the mailbox replaces every
        other one), and those are sent with quality 0: at 16, a 100 fps camera with a
        0.28 s engine (the numpy reference at 800×600) never sent good flow. Frames too far
        apart to report are the link's to say (it warns once).
    window : int
        Number of recent processing times considered.
    """

    def __init__(self, *, margin: float = 1.15, relax_s: float = 2.0, max_k: int = 1000, window: int = 32):
        self.k = 1
        self.margin, self.relax_s, self.max_k = margin, relax_s, max_k
        self._busy: deque[float] = deque(maxlen=window)
        self._interval_ema_s: float | None = None
        self._last_ts: int | None = None
        self._last_accepted: int | None = None
        self._low_since: float | None = None
        self.changes = 0

    def observe_capture(self, frame: Frame) -> None:
        """Track the source's real frame interval from capture timestamps."""
        if self._last_ts is not None:
            dt = (frame.timestamp_us - self._last_ts) / 1e6
            if 0 < dt < 1.0:
                self._interval_ema_s = dt if self._interval_ema_s is None else 0.9 * self._interval_ema_s + 0.1 * dt
        self._last_ts = frame.timestamp_us

    def accept(self, frame: Frame) -> bool:
        """True if ``frame`` belongs to the subset (index at least k after the last one)."""
        last = self._last_accepted
        if last is None or frame.index < last or frame.index - last >= self.k:
            self._last_accepted = frame.index
            return True
        return False

    def _need(self, busy_s: float) -> int:
        return min(self.max_k, max(1, math.ceil(busy_s * self.margin / self._interval_ema_s)))

    def _quantile(self, q: float) -> float:
        ordered = sorted(self._busy)
        return ordered[int(q * (len(ordered) - 1))]

    def observe_busy(self, busy_s: float, now_s: float) -> None:
        """Feed the processing time (s) of one frame; may change k."""
        self._busy.append(busy_s)
        if not self._interval_ema_s or len(self._busy) < 3:
            return
        typical = self._need(self._quantile(0.5))
        if typical > self.k:
            self._set(typical)
            self._low_since = None
        elif (need90 := self._need(self._quantile(0.9))) < self.k:
            self._low_since = self._low_since if self._low_since is not None else now_s
            if now_s - self._low_since >= self.relax_s:
                # at most halving, at once to what the 90th percentile needs when that is
                # more: one step per relax_s took 6 min to come back from k = 115
                self._set(max(need90, self.k // 2))
                self._low_since = None
        else:
            self._low_since = None

    def busy_drop(self) -> None:
        """A subset frame arrived while the previous one was still being processed: make
        room for the recent slow frames (not for one burst of arrivals)."""
        if self._interval_ema_s and len(self._busy) >= 3:
            self._set(max(self.k, self._need(self._quantile(0.9))))

    def _set(self, k: int) -> None:
        if k != self.k:
            nth = "every frame" if k == 1 else f"every {k}{'nd' if k == 2 else 'rd' if k == 3 else 'th'} frame"
            log.info("engine %s: processing %s", "behind" if k > self.k else "caught up", nth)
            self.k = k
            self.changes += 1


class SourceKeeper:
    """Owns a frame source: opens it, reads it, and after a failure, or the end of a live
    stream, closes it and reopens it with exponential back-off; a recording (a source that
    is not live) ends instead (:attr:`ended`), also when a read fails (:attr:`failed`): reopened
    it would start again at its first frame. :meth:`read` never raises.

    Parameters
    ----------
    factory : callable
        Returns a new, unopened :class:`FrameSource`.
    backoff_s, backoff_max_s : float
        First and longest delay between reopen attempts, s.
    stats : Stats
        Receives ``reopens`` and ``capture`` timings.
    steady_s : float
        The back-off starts again from ``backoff_s`` only after a source has delivered
        frames for this long, s; a source that fails sooner is reopened ever more slowly.
    clock : callable
        Monotonic time in s for the back-off and the hung-read check (tests drive it).
    """

    def __init__(self, factory: Callable[[], FrameSource], *, backoff_s: float = 0.5,
                 backoff_max_s: float = 10.0, stats: Stats | None = None, steady_s: float = _STEADY_S,
                 clock: Callable[[], float] = time.monotonic):
        self.factory = factory
        self.backoff_s, self.backoff_max_s = backoff_s, backoff_max_s
        self.steady_s = steady_s
        self._clock = clock
        self.stats = stats or Stats()
        self.source: FrameSource | None = None
        self._delay = backoff_s
        self._next_try = 0.0
        self._opened_once = False
        self._first_frame_at: float | None = None  # clock() at the current source's first frame (while backed off)
        self._lock = threading.Lock()
        #: called with each source the keeper opens itself (a camera absent at start-up,
        #: a reopen): the daemon checks what the camera delivers
        self.on_open: Callable[[FrameSource], None] | None = None
        #: the source's bad_frames and missed_frames already added to the daemon's counts
        self._bad_seen = self._missed_seen = 0
        #: clock() (time.monotonic() in the daemon) when the current driver call started
        #: (the source's open, read or close; also the factory making it), None outside one
        self.busy_since: float | None = None
        #: that call's name ("open", "read", "close")
        self.busy_with = ""
        #: a recording (file, replay) reached its end: nothing more to read, nothing to reopen
        self.ended = False
        #: ... because a read failed (the daemon then exits 2: bad input, which
        #: deploy/emdflowd.service does not restart into a replay from the first frame)
        self.failed = False

    def adopt(self, source: FrameSource) -> None:
        """Use an already opened source (opened at start-up to learn its size)."""
        self.source, self._opened_once = source, True
        self._count_source_skips(source, counted=False)

    def retry_after(self, delay_s: float) -> None:
        """Schedule the next open attempt ``delay_s`` from now."""
        self._next_try = self._clock() + delay_s

    def retry_in_s(self) -> float:
        return max(0.0, self._next_try - self._clock())

    def pacing_wait_s(self) -> float:
        """The open source's :meth:`~FrameSource.pacing_wait_s` (0 without one)."""
        source = self.source
        if source is None:
            return 0.0
        try:
            return float(source.pacing_wait_s())
        except Exception:  # noqa: BLE001 - read() reports a broken source; never stall on it
            return 0.0

    @property
    def blind(self) -> bool:
        return self.source is None

    def _fail(self, what: str) -> None:
        self.close()
        self._next_try = self._clock() + self._delay
        log.warning("%s; reopening in %.1f s (heartbeats continue, quality 0)", what, self._delay)
        self._delay = min(self.backoff_max_s, self._delay * 2.0)

    @contextlib.contextmanager
    def _driver_call(self, what: str):
        """Mark a call into the camera's driver, which may hang (see ``busy_since``)."""
        self.busy_with, self.busy_since = what, self._clock()
        try:
            yield
        finally:
            self.busy_since = None

    def _open(self) -> bool:
        try:
            with self._driver_call("open"):
                source = self.factory()
                source.open()
        except Exception as exc:  # SourceError, or a driver raising something else
            self._fail(f"source: cannot open: {exc}")
            return False
        self.source, self._first_frame_at = source, None
        self._count_source_skips(source, counted=False)
        if self._opened_once:
            self.stats.add("reopens")
            log.info("source %s reopened", source.uri)
        self._opened_once = True
        if self.on_open is not None:
            self.on_open(source)
        return True

    def _count_source_skips(self, source: FrameSource, *, counted: bool = True) -> None:
        """Add the frames the source itself skipped since the last call to the daemon's
        counts: a buffer it could not convert (bad), a frame a paced file or flight moved
        past (dropped, as the mailbox drops a camera's). ``counted=False``: only take the
        source's counts as the starting point (a source just opened or adopted)."""
        bad, missed = source.bad_frames, source.missed_frames
        if counted:
            self.stats.add("bad_frames", bad - self._bad_seen)
            self.stats.add("dropped", missed - self._missed_seen)
        self._bad_seen, self._missed_seen = bad, missed

    def read(self) -> Frame | None:
        """Next frame, or None while the source is unavailable (back-off running)."""
        with self._lock:
            if self.ended:
                return None
            if self.source is None:
                if self._clock() < self._next_try or not self._open():
                    return None
            source = self.source
            t0 = host_us()
            try:
                with self._driver_call("read"):
                    frame = source.read()
            except Exception as exc:
                error = str(exc) or type(exc).__name__
            else:
                error = None
            finally:
                self._count_source_skips(source)
            if error is not None:
                what = error if source.uri in error else f"source {source.uri}: {error}"
                if not source.live:
                    # a recording reopened starts at its first frame again: it would replay
                    # what was flown (and, failing at the same place, forever)
                    log.error("%s: a recording is not reopened (it would start again at its first "
                              "frame): stopping", what)
                    self._end_recording(failed=True)
                    return None
                self._fail(what)
                return None
            if frame is None:
                if not source.live:  # a recording ends; a camera's stream ending is a loss
                    log.info("source %s: end of stream: stopping (a file replays with [source] loop "
                             "= true)", source.uri)
                    self._end_recording(failed=False)
                    return None
                self._fail(f"source {source.uri}: end of stream")
                return None
            done = host_us()
            # Work, not waiting: a camera's frame age at delivery (transfer + conversion), a
            # file's read time minus the --realtime pacing sleep.
            if source.live:
                self.stats.stage("capture", max(0, done - frame.capture_host_us))
            else:
                self.stats.stage("capture", max(0, done - t0 - getattr(source, "waited_us", 0)))
            if self._delay != self.backoff_s:  # (a back-off raised by failures: is it over?)
                now = self._clock()
                if self._first_frame_at is None:
                    self._first_frame_at = now
                elif now - self._first_frame_at >= self.steady_s:
                    self._delay = self.backoff_s  # delivering steadily: a new failure starts afresh
            return frame

    def _end_recording(self, *, failed: bool) -> None:
        """Nothing more to read from a recording (:attr:`ended`, :attr:`failed`): it is not
        reopened."""
        self.ended, self.failed = True, failed
        self.close()

    def close(self) -> None:
        if self.source is not None:
            try:
                with self._driver_call("close"):
                    self.source.close()
            except Exception as exc:
                log.debug("closing source: %s", exc)
            self.source = None


class _CaptureThread(threading.Thread):
    """Reads the source continuously; passes the steady subset to the mailbox."""

    def __init__(self, keeper: SourceKeeper, mailbox: FrameMailbox, subset: SteadySubset,
                 stats: Stats, stop: threading.Event):
        super().__init__(name="emdflowd-capture", daemon=True)
        self.keeper, self.mailbox, self.subset, self.stats, self.stop = keeper, mailbox, subset, stats, stop

    def run(self) -> None:
        while not self.stop.is_set():
            frame = self.keeper.read()
            if frame is None:
                if self.keeper.ended:  # every frame is in the mailbox: the loop stops after them
                    break
                self.stop.wait(min(max(self.keeper.retry_in_s(), 0.005), 0.05))
                continue
            self.stats.add("frames_in")
            self.subset.observe_capture(frame)
            if not self.subset.accept(frame):
                self.stats.add("skipped")
                continue
            if self.mailbox.put(frame):
                self.stats.add("dropped")
                self.subset.busy_drop()
        self.keeper.close()


class _ReportWriter(threading.Thread):
    """Writes the link's reports held for their send time (MSP's, on the capture clock,
    :mod:`firmware_py.links.pacing`) when they are due: the frame loop is in the engine for
    most of a frame period, and a report due then would go out when it came back, as late as
    that frame took long — the jitter the pacing is there to take out.

    While it runs, the interpreter's switch interval is at most :data:`_WRITER_SWITCH_S`:
    a due report waits for the frame loop's thread to let go of the GIL (the OpenCL waits
    do, numpy's small steps in the summary only every switch interval, 5 ms by default).
    If it fails, the frame loop's ``service()`` still writes the due reports, later."""

    def __init__(self, link):
        super().__init__(name="emdflowd-reports", daemon=True)
        self.link = link
        self._stopping = threading.Event()
        self._switch_s = sys.getswitchinterval()

    def start(self) -> None:
        sys.setswitchinterval(min(self._switch_s, _WRITER_SWITCH_S))
        super().start()

    def stop(self) -> None:
        self._stopping.set()
        self.link.reports_held.set()  # (wakes it)
        self.join(timeout=1.0)
        sys.setswitchinterval(self._switch_s)

    def run(self) -> None:
        try:
            self._run()
        except Exception:  # noqa: BLE001 - the loop's service() still writes them
            log.exception("the report writer failed; held reports now go out when the frame loop "
                          "services the link (later than due)")

    def _run(self) -> None:
        held = self.link.reports_held
        while not self._stopping.is_set():
            held.clear()  # (before asking: a report queued after the answer sets it again)
            wait_s = self.link.wake_in_s(host_us())
            if wait_s is None:
                # nothing held: sleep until one is (polling while the port is still taking
                # something queued, which may hold one back)
                held.wait(_POLL_S if self.link.queued_messages else None)
            elif wait_s <= 0 or not self._stopping.wait(wait_s):
                # (due now, or once the wait is over: pump() sends nothing not yet due)
                self.link.send_due(host_us())


def _percentiles(values) -> tuple[float, float]:
    if len(values) == 0:
        return math.nan, math.nan
    p50, p99 = np.percentile(np.asarray(values, dtype=np.float64), [50, 99])
    return float(p50), float(p99)


def link_config(config, focal_length_px: float | None = None):
    """The :class:`~firmware_py.links.LinkConfig` of a daemon configuration, its settings
    checked: what LinkConfig refuses, and a baud rate too low for the fewest reports the
    autopilots use (:func:`~firmware_py.links.line_problem`), is a ConfigError naming
    ``[link]`` (exit 2, no restart). ``focal_length_px`` None: LinkConfig's default (the
    settings check before the camera says its own)."""
    from .links import LinkConfig, line_problem

    c = config.link
    where = f"{config.path or 'configuration'}: [link]"
    optional = {} if focal_length_px is None else {"focal_length_px": focal_length_px}
    try:
        settings = LinkConfig(
            port=c.port, baud=c.baud, autopilot=config.link_autopilot(), protocol=c.protocol,
            mounting_rotation_deg=config.optics.mounting_rotation_deg,
            mounting_mirror=config.optics.mounting_mirror,
            sysid=c.sysid, compid=c.compid, sensor_id=c.sensor_id,
            message_rate_hz=c.message_rate_hz, heartbeat_rate_hz=c.heartbeat_rate_hz,
            ground_distance_m=c.ground_distance_m, message_log=c.message_log,
            extra_values=c.extra_values, msp_counts_per_degree=c.msp_counts_per_degree,
            msp_report_delay_ms=c.msp_report_delay_ms, **optional)
    except ValueError as exc:
        raise ConfigError(f"{where} {exc}") from None
    problem = line_problem(settings)
    if problem:
        raise ConfigError(f"{where} baud = {c.baud} (--baud) is {problem}")
    return settings


class Daemon:
    """The running appliance.

    Parameters
    ----------
    config : Config
        Validated configuration (after command-line overrides).
    notifier : Notifier, optional
        systemd notification channel (default: from ``$NOTIFY_SOCKET``).
    source_factory : callable, optional
        Returns a new unopened source; default builds it from ``config.source``. Tests use
        it to inject faults around real sources.
    estimator_factory : callable, optional
        ``(width, height) -> estimator`` with ``update``/``reset``; default
        ``emdflow.FlowEstimator(width, height, backend=config.engine.backend)``.
    link_factory : callable, optional
        ``(focal_length_px) -> link``; default :func:`firmware_py.links.open_link` from
        ``config.link``.
    """

    def __init__(self, config: Config, *, notifier: Notifier | None = None,
                 source_factory: Callable[[], FrameSource] | None = None,
                 estimator_factory=None, link_factory=None):
        self.config = config
        self.notifier = notifier or Notifier()
        self._source_factory = source_factory or self._default_source
        self._estimator_factory = estimator_factory or self._default_estimator
        self._link_factory = link_factory or self._default_link
        self.stats = Stats()
        self.stop_event = threading.Event()
        self.subset = SteadySubset()
        self.link = None
        self._reopen_logs = False
        self._waits_in_read = False
        self._geometry_crop = (1.0, 1.0)  # the source's crop_fraction the focal length is for
        self._opened_unchecked = False  # the keeper opened a source whose geometry is not checked yet
        self._reset_pending = False     # an engine error left the estimator to reset before the next frame
        self.estimator = None
        self.width = self.height = 0
        self.fps = 0.0
        self.focal_length_px = math.nan
        self.mode = ""
        self.latencies_us: deque[int] = deque(maxlen=100_000)  # whole run, for the final line
        self._interval_latencies: list[int] = []             # since the last status line
        self._latency_lock = threading.Lock()
        self.exit_code = 0
        #: compute the looming cues per frame, for the link's extra values (set with the link)
        self._send_cues = False
        self.running = threading.Event()
        self._prev: Frame | None = None
        #: the steps between the processed frames the detector's output spans now (index
        #: step, capture-time step in source frame periods); its length is set by run()
        self._steps: deque[tuple[int, int]] = deque(maxlen=3)
        #: recent capture µs per source frame (step over index step): their median is the period
        self._periods_us: deque[float] = deque(maxlen=8)
        #: frame quality below which a frame is doubtful to the link (Config.min_quality; set by run())
        self.min_quality = 0
        self._processed_intervals = RecentIntervals()  # capture µs between processed frames
        self._last_frame_host_s = time.monotonic()
        self._blind_logged = False
        self._last_bad_log = -math.inf
        #: monotonic time of the first engine error since the last ready field, or None,
        #: and the errors since then
        self._failing_since: float | None = None
        self._failures = 0
        self._last_engine_log = -math.inf
        self._last_status_s = time.monotonic()

    # -- defaults ---------------------------------------------------------------------
    def _default_source(self) -> FrameSource:
        s = self.config.source
        return make_source(s.uri, width=s.width, height=s.height, fps=s.fps,
                           pixel_format=s.pixel_format, buffer_count=s.buffer_count,
                           exposure_us=s.exposure_us, gain=s.gain, loop=s.loop, realtime=s.realtime)

    def _default_estimator(self, width: int, height: int):
        backend = self.config.engine.backend
        if backend == "numpy":
            log.warning("engine backend 'numpy' (reference implementation): 10-100x slower than "
                        "OpenCL; expect a low frame rate. Install an OpenCL driver for flight use.")
        try:
            return emdflow.FlowEstimator(width, height, backend=backend, **self.config.engine.estimator_options())
        except FrameSizeError as exc:  # the source's size, not an [engine] setting: exit 2
            s = self.config.source
            if s.width is None:
                raise ConfigError(f"source {s.uri}: {exc}; set [source] width and height to a size "
                                  "the engine takes") from None
            raise ConfigError(f"[source] width and height: {exc}") from None
        except ValueError as exc:  # a setting, not a failure: exit 2 (systemd does not restart)
            # (the engine's own message names EMDFLOW_OPENCL_DEVICE when that made the choice)
            raise ConfigError(str(exc) if "(EMDFLOW_OPENCL_DEVICE)" in str(exc) else f"[engine]: {exc}") from None

    def _default_link(self, focal_length_px: float):
        from .links import open_link

        # (anything open_link raises is a failure, not a setting: those were checked)
        return open_link(link_config(self.config, focal_length_px))

    # -- start-up ---------------------------------------------------------------------
    def _start_source(self) -> SourceKeeper:
        """Create the source; files must open now (a missing file is a configuration
        error), cameras may be absent at start (the keeper keeps retrying)."""
        d = self.config.daemon
        keeper = SourceKeeper(self._source_factory, backoff_s=d.reopen_backoff_s,
                              backoff_max_s=d.reopen_backoff_max_s, stats=self.stats)
        source = self._source_factory()  # raises SourceError for a bad URI or missing file
        self.width, self.height, self.fps = source.width, source.height, source.fps
        self.live = source.live
        self._waits_in_read = bool(getattr(source, "waits_in_read", False))
        # Before opening: a camera without a focal length is a configuration error.
        self.focal_length_px = self.config.focal_length_px(self.width, source.default_focal_length_px)
        keeper.on_open = self._note_opened
        try:
            source.open()
            keeper.adopt(source)
        except SourceError as exc:
            if not source.live or isinstance(exc, SourceConfigError):
                raise  # a file that will not open, a camera that cannot work as configured
            log.warning("%s; retrying in %.1f s (heartbeats continue, quality 0)", exc, d.reopen_backoff_s)
            keeper.retry_after(d.reopen_backoff_s)
        else:
            self.focal_length_px = self._focal_length_of(source)
            self._geometry_crop = source.crop_fraction
            self.fps = source.fps  # (a camera may run at another rate than the one asked)
        return keeper

    def _focal_length_of(self, source: FrameSource) -> float:
        """The focal length at the processing size for an opened source: a field of view
        is the lens's over the image the camera delivers, and a camera that delivers
        another aspect ratio is centre-cropped (FrameSource.crop_fraction): the lens sees
        ``1 / crop_fraction[0]`` times the processed width. Crop (1, 1) (not opened) gives
        the start-up value."""
        return self.config.focal_length_px(self.width / source.crop_fraction[0],
                                           source.default_focal_length_px)

    def _warn_of_a_wide_lens(self) -> None:
        """A wide lens reads turns faster than the body rate (angular.turn_gain): say by how
        much where the mean over directions exceeds TURN_GAIN_WARNING, for the image the
        engine processes (at start, and again when a reopened camera changes it)."""
        gx, gy = turn_gain(width=self.width, height=self.height, focal_length_px=self.focal_length_px)
        if (gx + gy) / 2.0 > TURN_GAIN_WARNING:
            fov = fov_deg_from_focal_length_px(focal_length_px=self.focal_length_px, size_px=self.width)
            log.warning("focal length %.1f px at %dx%d (the processed image's horizontal field of view "
                        "%.0f deg): a turn of the vehicle reads about %.2fx (x) and %.2fx (y) its body rate "
                        "for a distortion-free lens, and the autopilot takes the excess for motion; a "
                        "narrower lens or a centre crop lowers it, and a flow scaler calibrated from turns "
                        "would scale translations down (README, \"Wide lenses and turns\")",
                        self.focal_length_px, self.width, self.height, fov, gx, gy)

    def _note_opened(self, source: FrameSource) -> None:
        """The keeper opened a source (a camera absent at start, a reopen), maybe in the
        capture thread: the loop checks its geometry before its next frame (the link and the
        focal length belong to the loop's thread)."""
        self._opened_unchecked = True

    def _check_geometry(self, source: FrameSource) -> None:
        """A source the keeper opened later (absent at start, or reopened), or one that
        learnt what its camera delivers only from a frame (a driver that does not say its
        size): if it delivers another image than the focal length was computed for, the
        link converts with the new one from its next report."""
        self._geometry_crop = source.crop_fraction
        focal = self._focal_length_of(source)
        if not math.isclose(focal, self.focal_length_px, rel_tol=1e-6):
            log.warning("source %s: crop %.3f x %.3f of the delivered image: focal length %.1f px "
                        "(was %.1f px)", source.uri, *source.crop_fraction, focal, self.focal_length_px)
            self.focal_length_px = focal
            if self.link is not None:
                self.link.set_focal_length_px(focal)
            self._warn_of_a_wide_lens()

    def _warm_up(self, t0: float) -> None:
        """Run the engine on blank frames once and load the summary's tables: kernels are
        built, buffers allocated and tables laid out before READY=1, not on the first
        camera frames (seconds on PoCL; the tables ~1 s)."""
        blank = np.zeros((self.height, self.width), np.uint8)
        for _ in range(2):
            _summarize(self.estimator.update(blank))
        self.estimator.reset()
        # (a blank frame never reaches the likelihood fit, so this does not happen above;
        # an engine stand-in without parameters, in tests, has no tables either)
        params = getattr(self.estimator, "params", None)
        if params is not None:
            emdflow.summary.prepare(params)
        log.info("engine %s %dx%d ready in %.2f s%s", self.config.engine.backend, self.width, self.height,
                 time.monotonic() - t0, _on_device(self.estimator))
        self._warn_of_sparse_evidence()
        if params is not None:
            self._warn_of_uncalibrated_settings(params)

    def _warn_of_uncalibrated_settings(self, params) -> None:
        """``[engine]`` settings the summary's calibration table was not measured with
        (``threshold`` with the paper's model, ``threshold_mode``, ``threshold_tile``): the
        summary still runs, less accurately and with a quality calibrated for the table's
        settings, so this is said once here, in the daemon's log, and not again by
        :func:`emdflow.summarize` on the first frame."""
        # (told here: the parameter set counts as warned, so summarize() stays quiet, without
        # a filter on the whole process's warnings)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", emdflow.summary.CalibrationWarning)
            mismatch = emdflow.summary.warn_if_uncalibrated(params)
        if mismatch:
            log.warning("[engine] %s: the %s model's summary table %s was measured with other settings; "
                        "the summary's error is larger and unmeasured with these (README, \"Calibration "
                        "settings\")", emdflow.summary.mismatch_text(mismatch, " = "), self.config.engine.model,
                        emdflow.summary.calibration_for(params).name)

    def _warn_of_sparse_evidence(self) -> None:
        """An ``[engine] evidence_row_step`` that samples too few rows of the processed frame
        leaves the summary too few detections: quality 0 on nearly every frame (120 at 240
        px high: 0 good reports of 40; 16: 28 of 40), which the config cannot know before
        the source's size is."""
        step = self.config.engine.evidence_row_step
        rows = -(-self.height // step) if step else None
        if rows is not None and rows < _MIN_EVIDENCE_ROWS:
            log.warning("[engine] evidence_row_step = %d samples %d of the %d processed rows: the summary "
                        "sees too few detections and reports quality 0 on most frames; at most %d here "
                        "(0, automatic, samples about 60)", step, rows, self.height,
                        max(1, (self.height - 1) // (_MIN_EVIDENCE_ROWS - 1)))

    # -- the loop ---------------------------------------------------------------------
    def stop(self) -> None:
        """Ask the loop to finish (signal handlers call this)."""
        self.stop_event.set()

    def reopen_logs(self) -> None:
        """Ask the loop to reopen the message log (SIGHUP, after a log rotation): it is done
        between frames, not inside the signal handler, which may interrupt a row's write."""
        self._reopen_logs = True

    def run(self) -> int:
        """Run until :meth:`stop`, ``config.frames`` processed frames, or a fatal error.

        Returns
        -------
        int
            Process exit code: 0 on a clean stop.
        """
        keeper = mailbox = capture = writer = None
        try:
            keeper = self._start_source()
            t0 = time.monotonic()
            self.estimator = self._estimator_factory(self.width, self.height)
            # the frames an uneven step spoils: 3 x the longest delay (an engine stand-in
            # without parameters, in tests, is the paper's model), at most _UNEVEN_FRAMES_MAX
            params = getattr(self.estimator, "params", None)
            self._steps = deque(maxlen=min(getattr(params, "history_frames", 3), _UNEVEN_FRAMES_MAX))
            self._warm_up(t0)
            self.link = self._link_factory(self.focal_length_px)
            if hasattr(self.link, "blind_after_s"):
                # The link's keep-alive starts then, but never later than the link's own value
                # (MSP: 0.15 s, INAV times out after 0.2 s).
                self.link.blind_after_s = min(self.link.blind_after_s, self.config.daemon.blind_after_s)
            if getattr(self.link, "paces_reports", False) is True:
                writer = _ReportWriter(self.link)
                writer.start()
            self._send_cues = self.config.link.extra_values
            if self._send_cues and getattr(self.link, "protocol", "mavlink") != "mavlink":
                # (MSP has no message for them: computed every frame, ~0.4 ms, and dropped)
                log.warning("[link] extra_values = true: %s has no message for the looming cues; not "
                            "computed or sent (MAVLink sends them as NAMED_VALUE_FLOAT)", self.link.protocol)
                self._send_cues = False
            # a paced recording or flight fed to the numpy reference is a camera the engine
            # cannot keep up with: it needs the capture side's evenly spaced subset too
            paced_slow = self.config.source.realtime and self.config.engine.backend == "numpy"
            # (and a source that waits for its frames where the loop cannot see how long)
            self.mode = choose_threading(self.config.daemon.threading,
                                         live=self.live or paced_slow or self._waits_in_read)
            engine = f"{self.config.engine.backend}, {self.config.engine.model} model"
            if params is not None:  # (the threshold the model or [engine] threshold_mode chose)
                engine += f", {params.threshold_mode} threshold"
                if params.threshold_mode == "local":
                    engine += f" ({params.threshold_tile} px tiles)"
            log.info("source %s: %dx%d @ %g fps, focal length %.1f px; engine %s; link %s %s @ %d baud; %s",
                     self.config.source.uri, self.width, self.height, self.fps, self.focal_length_px,
                     engine, self.config.link_autopilot(), self.config.link.port,
                     self.config.link.baud, self.mode)
            self.min_quality = self.config.min_quality()
            if self.min_quality:
                why = ("" if self.config.link.min_quality is not None else
                       f": the default for {self.config.link_autopilot()} with the {self.config.engine.model} model")
                log.info("frames of quality below %d are left out of their reports ([link] min_quality%s)",
                         self.min_quality, why)
            self._warn_of_a_wide_lens()
            if self.mode == "capture-thread":
                # Files read as fast as possible get back-pressure instead of drops.
                mailbox = FrameMailbox(block=not self.live and not self.config.source.realtime)
                capture = _CaptureThread(keeper, mailbox, self.subset, self.stats, self.stop_event)
                capture.start()
            self.notifier.ready(f"running {self.config.source.uri}")
            self.running.set()
            self._loop(keeper, mailbox)
        finally:
            self.stop_event.set()
            if mailbox is not None:
                mailbox.close()
            if capture is not None:
                capture.join(timeout=5.0)
            if writer is not None:
                writer.stop()  # (the link's close writes what it still holds, when due)
            if self.link is not None:  # (before the camera's close, which a driver can hang in)
                try:
                    self.link.close()
                except Exception as exc:
                    log.warning("closing the link: %s", exc)
            # Never release a device another thread is still reading (hung driver).
            if keeper is not None and not (capture is not None and capture.is_alive()):
                keeper.close()
            if self.running.is_set():
                self.notifier.stopping()
                self._log_status(final=True)  # (after the link's close: its last reports counted)
        return self.exit_code

    def _loop(self, keeper: SourceKeeper, mailbox: FrameMailbox | None) -> None:
        d = self.config.daemon
        self._last_frame_host_s = time.monotonic()  # start-up (kernel build) is not blindness
        self._last_status_s = time.monotonic()
        next_log = time.monotonic() + d.log_interval_s
        wd_interval = self.notifier.watchdog_interval_s
        next_wd = time.monotonic()
        limit = self.config.frames
        while not self.stop_event.is_set():
            if mailbox is not None:
                # (read before get: the capture thread puts a recording's last frame before it
                # marks the end, so after the end an empty mailbox stays empty)
                ended = keeper.ended
                frame = mailbox.get(_POLL_S)
            elif keeper.pacing_wait_s() > _POLL_S:
                # A paced recording's next frame is more than a poll away (a slow --realtime
                # file or flight): wait a slice, then service the link (heartbeats, the blind
                # keep-alive, the watchdog); read() would sleep the whole frame period.
                self.stop_event.wait(_POLL_S)
                frame, ended = None, keeper.ended
            else:
                frame = keeper.read()
                ended = keeper.ended
                if frame is not None:
                    self.stats.add("frames_in")
                elif not ended:
                    self.stop_event.wait(min(max(keeper.retry_in_s(), 0.001), _POLL_S))
            now_s = time.monotonic()
            if frame is not None:
                # (the flag before the source: a reopen in between sets it again)
                opened, self._opened_unchecked = self._opened_unchecked, False
                source = keeper.source
                if source is not None and (opened or source.crop_fraction != self._geometry_crop):
                    self._check_geometry(source)
                self._process(frame, now_s)
            elif ended:  # a recording's last frame is processed: send what is queued, stop
                self.link.service(host_us())
                if keeper.failed:  # (logged where it failed; 2: the unit does not restart it)
                    self.exit_code = 2
                elif self.stats.frames_in == 0:  # not one frame: nothing was flown, say so
                    log.error("source %s ended before its first frame (a truncated file, or a codec "
                              "this OpenCV cannot decode)", self.config.source.uri)
                    self.exit_code = 2
                break
            elif now_s - self._last_frame_host_s > self._gap_s(d.blind_after_s):
                self._blind(now_s)
            self.link.service(host_us())
            self._collect_latencies()
            if self._reopen_logs:
                self._reopen_logs = False
                reopen = getattr(self.link, "reopen_message_log", None)
                path = reopen() if reopen is not None else None
                if path is not None:
                    log.info("SIGHUP: message log %s reopened", path)
                else:
                    log.info("SIGHUP: no message log to reopen; running on")
            if wd_interval is not None and now_s >= next_wd:
                self.notifier.watchdog()
                next_wd = now_s + wd_interval
            if now_s >= next_log:
                self._log_status()
                next_log = now_s + d.log_interval_s
            since = keeper.busy_since
            if since is not None and now_s - since > _STUCK_DRIVER_S:
                log.error("source %s: %s() has not returned for %.0f s (driver hung): exiting so "
                          "that systemd restarts the daemon", self.config.source.uri, keeper.busy_with,
                          now_s - since)
                self.exit_code = 1
                break
            if limit is not None and self.stats.processed >= limit:
                log.info("processed %d frames (--frames): stopping", self.stats.processed)
                break

    def _bad_frame(self, what: str) -> None:
        self.stats.add("bad_frames")
        now = time.monotonic()
        if now - self._last_bad_log >= _BAD_FRAME_LOG_S:
            self._last_bad_log = now
            log.error("%s: frame skipped (%d bad frames so far)", what, self.stats.bad_frames)

    def _engine_error(self, frame: Frame, stage: str, exc: Exception, now_s: float) -> None:
        """``stage`` (engine, summary, or the estimator's reset) failed on ``frame``: skip it
        and reset the estimator before the next frame (its state may be half-written; a
        reset that fails is tried again at the frame after), so the link reports quality 0
        while blind and the flow comes back once the history has refilled. Errors that keep it from coming back
        (no ready field between them) for :data:`_ENGINE_FAILURE_EXIT_S`, at least
        :data:`_ENGINE_FAILURE_EXIT_ERRORS` of them, raise (the daemon exits 1 for systemd
        to restart it): an error on every few frames keeps the history from refilling."""
        self.stats.engine_errors += 1
        if self._failing_since is None:
            self._failing_since, self._failures = now_s, 0
        self._failures += 1
        failing_s = now_s - self._failing_since
        if failing_s > _ENGINE_FAILURE_EXIT_S and self._failures >= _ENGINE_FAILURE_EXIT_ERRORS:
            raise RuntimeError(f"{self._failures} engine errors in {failing_s:.1f} s without a flow between "
                               f"them, the last in the {stage} on frame {frame.index}: {type(exc).__name__}: "
                               f"{exc}; exiting for a restart") from exc
        self._log_engine_error(f"{stage} failed on frame {frame.index}",
                               "frame skipped, estimator reset before the next one", exc)
        self._reset_pending = True
        self._prev = None  # (the next frame starts the history again)
        self._last_frame_host_s = now_s  # (frames arrive: the camera is not blind)

    def _cues(self, field, frame: Frame):
        """The frame's looming cues, or None when computing them failed: the flow goes out
        as computed, its extra values as unknown (NaN), logged as an engine error (at most
        one line per 5 s; the estimator is not reset, the field is good)."""
        try:
            return looming_cues(field)
        except Exception as exc:  # noqa: BLE001 - the extras are optional, the flow is not
            self.stats.engine_errors += 1
            self._log_engine_error(f"looming cues failed on frame {frame.index}",
                                   "its extra values go out unknown", exc)
            return None

    def _log_engine_error(self, what: str, done: str, exc: Exception) -> None:
        """One error line with its traceback (it says where), at most one per
        :data:`_BAD_FRAME_LOG_S` (the first one always)."""
        now = time.monotonic()
        if now - self._last_engine_log >= _BAD_FRAME_LOG_S:
            self._last_engine_log = now
            log.error("%s (%s: %s): %s (%d engine errors so far)", what, type(exc).__name__, exc, done,
                      self.stats.engine_errors, exc_info=exc)

    def _process(self, frame: Frame, now_s: float) -> None:
        t0 = host_us()
        self.stats.stage("wait", max(0, t0 - frame.capture_host_us))
        image = frame.image
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.shape != (self.height, self.width):
            shape = getattr(image, "shape", None)
            dtype = getattr(image, "dtype", type(image).__name__)
            self._bad_frame(f"source frame {frame.index} is {shape} {dtype}, expected "
                            f"({self.height}, {self.width}) uint8 ({self.width}x{self.height})")
            return
        prev = self._prev
        gap_us = self._gap_s(self.config.engine.reset_after_gap_s) * 1e6
        gap = prev is not None and (frame.timestamp_us <= prev.timestamp_us or frame.index <= prev.index
                                    or frame.timestamp_us - prev.timestamp_us > gap_us)
        reset = gap or self._reset_pending
        if reset:
            try:
                self.estimator.reset()
            except Exception as exc:  # noqa: BLE001 - as an error in update: skip, retry the reset
                self._engine_error(frame, "reset", exc, now_s)
                return
            self._reset_pending = False
            self.stats.resets += 1
        if gap:
            if frame.index <= prev.index or frame.timestamp_us <= prev.timestamp_us:
                log.info("source restarted (frame %d after %d): estimator reset", frame.index, prev.index)
            else:
                log.info("frame gap %.3f s (frame %d after %d): estimator reset",
                         (frame.timestamp_us - prev.timestamp_us) / 1e6, frame.index, prev.index)
        if prev is not None:  # after the gap test: a stall must not widen its own threshold
            self._processed_intervals.add(frame.timestamp_us - prev.timestamp_us)
        uneven = self._uneven(frame, None if reset else prev)
        if self._blind_logged:
            log.info("source delivering again")
            self._blind_logged = False
        stage = "engine"
        try:
            try:
                field = self.estimator.update(image)
            except ValueError as exc:
                self._bad_frame(f"engine rejected frame {frame.index}: {exc}")
                return
            t1 = host_us()
            stage = "summary"
            summary = _summarize(field)
        except Exception as exc:  # noqa: BLE001 - the vehicle keeps its link (see _engine_error)
            self._engine_error(frame, stage, exc, now_s)
            return
        if field.ready:  # (the flow is back: a run of errors has ended)
            self._failing_since = None
        # the looming cues go out per frame only as extra values; the status line
        # computes them from the last field when it is due
        cues = self._cues(field, frame) if self._send_cues else None
        t2 = host_us()
        extras = ()
        if self._send_cues and (cues is None or not cues.detections or uneven):
            # no cue (history filling, a brightness step, thin evidence; or the detector's
            # output spans uneven steps, which is not the motion, as for the flow below):
            # "unknown", as the gyro fields say it, not a measured 0 (no expansion) and -1
            # (not approaching)
            extras = tuple((name, math.nan) for name in ("expansion", "ttc_s", "balanceLR", "balanceTB"))
        elif cues is not None:
            frame_s = self._frame_interval_s()
            ttc_s = cues.time_to_contact_frames * frame_s
            extras = (("expansion", cues.expansion_rate / frame_s),  # 1/s
                      ("ttc_s", ttc_s if math.isfinite(ttc_s) else -1.0),
                      *zip(("balanceLR", "balanceTB"), self._mounted_balance(cues)))
        if uneven and field.ready:  # (before, the history filling sends quality 0 anyway)
            self.stats.uneven += 1
        quality = 0 if uneven else summary.quality
        # (below the floor: ArduPilot's EKF3 would fuse what the summary itself doubts; the
        # report leaves the frame out, and is quality 0 when it has too few others)
        doubtful = 0 < quality < self.min_quality
        self.link.submit(FlowSample(timestamp_us=frame.timestamp_us, capture_host_us=frame.capture_host_us,
                                    flow_x=summary.flow_x, flow_y=summary.flow_y, quality=quality,
                                    extras=extras, doubtful=doubtful), now_host_us=t2)
        t3 = host_us()
        self.stats.stage("engine", t1 - t0)
        self.stats.stage("summary", t2 - t1)
        self.stats.stage("link", t3 - t2)
        self.stats.processed += 1
        self.stats.last_summary = summary
        self.stats.last_field = field
        self._prev = frame
        self._last_frame_host_s = now_s
        self.subset.observe_busy((t3 - t0) / 1e6, now_s)

    def _uneven(self, frame: Frame, prev: Frame | None) -> bool:
        """Does the detector's output at ``frame`` span steps of different lengths between
        processed frames (``prev``: the processed frame before it, None after a reset)?

        A channel of delay D compares the changes R(t-D) - R(t-2D) and R(t) - R(t-D) with
        those a frame-step earlier (its templates read the states at t-2D, t-D and t): its
        output spans the frames t-3D..t, and assumes them evenly spaced. After a frame the
        camera or a paced file dropped, or a change of the steady subset, what the detector
        reports is not the flow (too little, then too much) at its usual quality: the
        frames whose span holds unequal steps (3 of the paper's model, up to
        :data:`_UNEVEN_FRAMES_MAX` of the extended one's) are sent with quality 0, and the
        state is kept (a reset blinds as long, and longer). Steps are counted in source
        frames: index steps, and capture-time steps in source periods (a V4L2 camera's
        indices count reads: its drops show only in the timestamps), the period measured
        from the recent steps (not the nominal fps, which a camera may not keep); rounding
        absorbs jitter.
        """
        if prev is None:
            self._steps.clear()  # (no step to compare across a reset: the history refills)
        else:
            index_step, dt = frame.index - prev.index, frame.timestamp_us - prev.timestamp_us
            self._periods_us.append(dt / index_step)
            # (a median of an even count: jitter that alternates averages out, and one stall
            # does not move it)
            self._steps.append((index_step, round(dt / statistics.median(self._periods_us))))
        return len(set(self._steps)) > 1

    def _mounted_balance(self, cues) -> tuple[float, float]:
        """The left/right and top/bottom balance in the axes of a default-mounted camera,
        as the flow is sent: a balance is a vector in image axes (a mirror swaps left and
        right, a quarter turn left/right with top/bottom)."""
        optics = self.config.optics
        return apply_mounting(cues.balance_lr, cues.balance_tb, rotation_deg=optics.mounting_rotation_deg,
                              mirror=optics.mounting_mirror)

    def _gap_s(self, configured_s: float) -> float:
        """``configured_s``, or :data:`_GAP_INTERVALS` typical processed intervals when the
        frames are that far apart anyway (slow camera, large frame subset), s."""
        typical_us = self._processed_intervals.typical
        if typical_us is None:
            # (before two frames: the nominal period, so that the first wait of a slow
            # recording or flight is no blind camera)
            return max(configured_s, _GAP_INTERVALS / self.fps) if self.fps > 0 else configured_s
        return max(configured_s, _GAP_INTERVALS * typical_us / 1e6)

    def _frame_interval_s(self) -> float:
        """Typical interval between processed frames from their capture timestamps, s (the
        nominal 1/fps until two frames were processed): cues per frame become per second."""
        typical_us = self._processed_intervals.typical
        if typical_us is not None:
            return typical_us / 1e6
        return 1.0 / self.fps if self.fps > 0 else 1.0

    def _blind(self, now_s: float) -> None:
        """No frames: say so once. The link keeps the autopilot informed on its own
        (heartbeats plus quality-0 flow messages at a low rate, with real host intervals)."""
        if not self._blind_logged:
            log.warning("no frames for %.2f s: camera blind, the link sends quality 0",
                        now_s - self._last_frame_host_s)
            self._blind_logged = True
            self.stats.blind_periods += 1

    def _collect_latencies(self) -> None:
        values = self.link.latencies_us()
        if values:
            with self._latency_lock:
                self.latencies_us.extend(values)
            self._interval_latencies.extend(values)

    def latency_snapshot(self, start: int = 0) -> list[int]:
        """Capture→serial latencies (µs) of this run from position ``start`` on; safe to
        call from another thread (the demo's table)."""
        with self._latency_lock:
            return list(self.latencies_us)[start:]

    # -- status -----------------------------------------------------------------------
    def status_text(self, iv: dict | None = None, period_s: float | None = None) -> str:
        """One line: rates, counters, stage times, latency, flow."""
        # (a copy: the report writer thread counts what it sends)
        snapshot = getattr(self.link, "stats_snapshot", None)
        st = snapshot() if snapshot is not None else getattr(self.link, "stats", None)
        lat50, lat99 = _percentiles(self.latencies_us if iv is None else self._interval_latencies)
        s = self.stats.last_summary
        flow = f"flow {s.flow_x:+.2f},{s.flow_y:+.2f} px/frame q {s.quality}" if s else "flow -"
        if s and s.line_ground:  # read with the summary's line-ground table (paving, tiles)
            flow += " (line ground)"
        try:  # (a cue that failed on that frame was logged by _cues; the status line goes on)
            c = looming_cues(self.stats.last_field) if self.stats.last_field is not None else None
        except Exception:  # noqa: BLE001
            c = None
        if c is not None and c.detections:
            frame_s = self._frame_interval_s()
            ttc = c.time_to_contact_frames * frame_s
            lr, tb = (f"{b:+.2f}" if math.isfinite(b) else "-" for b in (c.balance_lr, c.balance_tb))
            flow += (f" | expansion {c.expansion_rate / frame_s:+.3f}/s ttc "
                     f"{'-' if not math.isfinite(ttc) else f'{ttc:.1f} s'} balance L/R {lr} T/B {tb}")
        if iv is None:
            t = self.stats.totals()
            return (f"total: in {t['frames_in']} processed {t['processed']} skipped {t['skipped']} "
                    f"dropped {t['dropped']} bad {t['bad_frames']} resets {t['resets']} "
                    f"reopens {t['reopens']} blind {t['blind_periods']} uneven {t['uneven']} "
                    f"engine errors {t['engine_errors']} | "
                    f"link {_link_stats(st, final=True)} | "
                    f"latency capture->serial p50 {lat50 / 1000:.2f} ms p99 {lat99 / 1000:.2f} ms "
                    f"(n={len(self.latencies_us)})")
        rate = iv["processed"] / period_s if period_s else 0.0
        return (f"{rate:.1f} fps processed (in {iv['frames_in']} proc {iv['processed']} "
                f"skip {iv['skipped']} drop {iv['dropped']} bad {iv['bad_frames']}"
                f"{f' uneven {u}' if (u := iv['uneven']) else ''}"
                f"{f' engine errors {e}' if (e := iv['engine_errors']) else ''} k={self.subset.k}) | "
                f"ms capture {iv['capture_ms']:.2f} wait {iv['wait_ms']:.2f} engine {iv['engine_ms']:.2f} "
                f"(max {iv['engine_max_ms']:.1f}) summary {iv['summary_ms']:.2f} link {iv['link_ms']:.2f} | "
                f"link {_link_stats(st)} | latency p50 {lat50 / 1000:.2f} ms p99 {lat99 / 1000:.2f} ms | {flow}")

    def _log_status(self, final: bool = False) -> None:
        now = time.monotonic()
        if final:
            log.info("%s", self.status_text())
            return
        period = now - self._last_status_s
        self._last_status_s = now
        text = self.status_text(self.stats.interval(), period)
        self._interval_latencies = []
        log.info("%s", text)
        self.notifier.status(text[:200])


#: The link's other counters, (stats key, label): in the final line always, in the status
#: line when not 0 (each says something went wrong on the wire, or what the autopilot sent).
_LINK_COUNTERS = (("stale_messages", "stale"), ("open_failures", "open failures"),
                  ("write_errors", "write errors"), ("read_errors", "read errors"),
                  ("integration_restarts", "restarts"), ("bytes_written", "bytes out"),
                  ("rx_bytes", "bytes in"), ("rx_garbage_bytes", "garbage in"),
                  ("internal_errors", "internal errors"), ("late_reports", "late reports"))


def _link_stats(st, *, final: bool = False) -> str:
    """Messages written (by type), drops and port state from the link's stats mapping, then
    the other counters (all of them in the ``final`` line, else those not 0) and the
    autopilot's heartbeat once one was seen."""
    if not isinstance(st, dict):
        return "-" if st is None else str(st)
    sent = st.get("messages_sent") or {}
    by_type = ",".join(f"{name} {count}" for name, count in sorted(sent.items())) or "none"
    text = (f"sent {by_type}; dropped {st.get('dropped_messages', 0)} blind {st.get('blind_reports', 0)} "
            f"port {'open' if st.get('port_open') else 'CLOSED'} reopens {st.get('reopen_count', 0)}")
    delay = st.get("report_delay_ms")
    if isinstance(delay, float) and delay > 0:  # (MSP: reports paced on the capture clock)
        text += f" paced {delay:.1f} ms after capture"
    for key, label in _LINK_COUNTERS:
        value = st.get(key)
        # (bytes out and in grow with every frame: only the final line carries them)
        if isinstance(value, int) and (final or (value and key not in ("bytes_written", "rx_bytes"))):
            text += f" {label} {value}"
    heartbeat = st.get("rx_heartbeat")
    if final and isinstance(heartbeat, dict):
        text += f" autopilot sysid {heartbeat.get('sysid')} type {heartbeat.get('type')}"
    return text


def _on_device(estimator) -> str:
    """" on <OpenCL device>" for the start-up log (estimators from a factory may not say)."""
    device = getattr(estimator, "device", None)
    return f" on {device}" if device else ""


def _summarize(field):
    return emdflow.summarize(field)
