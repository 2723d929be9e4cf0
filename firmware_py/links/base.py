"""What every link shares: the sample and config types, rate choice, and the frame-driven
scheduling around :class:`~firmware_py.angular.FlowIntegrator` and
:class:`~firmware_py.links.serial_port.SerialTransport`.

Timing model
------------
* ``submit()`` adds a frame to the integrator; when the pending interval (capture-timestamp
  time, not wall clock) reaches the message period, the protocol encodes it and it is queued
  and written at once — messages go out as soon as the flow is known, at a steady rate
  (a frame's extra values are queued after its flow message).
* **At least** :data:`MIN_MESSAGE_RATE_HZ` **(7) reports a second**: ArduPilot's EKF3 uses
  optical flow only while its newest sample is < 200 ms old, and INAV drops an MSP flow
  sensor after 200 ms without an update. A baud rate that cannot carry that is refused
  (:func:`line_problem`: sized for :data:`FLOOR_REPORTS_HZ`, below), and the extra values
  get only what the flow leaves of the budget. Reports end on frame boundaries, but a
  report is also due once the next frame (at the lower median of recent intervals) would
  take it past :data:`FRESH_REPORT_US` (180 ms): at the floor alone, frames 90-114 ms apart
  had them 181-228 ms apart. From ~11 fps down every frame can then be a report (up to
  :data:`FLOOR_REPORTS_HZ` a second); frame jitter can still push one a little past 180 ms,
  and with frames more than 180 ms apart each frame is a report (too few for the EKF3 and
  INAV: the camera's own rate).
* **No report spans more than 0.45 s** (the integrator's ``max_interval_us``; ArduPilot marks
  the sensor unhealthy without a message for 0.5 s, PX4 drops integration times >= 1 s): a
  report goes out on the last frame before the next one would take it past that span, and a
  frame that would take it past anyway (a late one) closes the pending report at the previous
  frame, with quality 0 (its counts end there, the autopilot's interval at the late frame),
  and starts the next interval at itself.
* ``service(now_host_us)`` does everything that depends on host time: reopening the port,
  reading the autopilot's side, heartbeats, and the blind keep-alive.
* **Blind camera.** ArduPilot marks the flow sensor unhealthy when the last message is
  ≥ 0.5 s old, INAV after 0.2 s, and PX4 restarts its accumulation on gaps; all three drop
  quality-0 samples from the estimator but keep the sensor "present". So while no frames
  arrive the link keeps sending the flow message with zero flow and quality 0 at
  :data:`BLIND_RATE_HZ` (integration time = real host time since the previous message,
  below 0.5 s), next to the 1 Hz heartbeat. "No frames" is judged on the host time since
  the last ``submit()`` — a slow engine makes every frame's capture time old before it is
  submitted — and a slow but steady stream (frames further apart than ``blind_after_s``,
  up to the longest interval a report may span) gets :data:`SLOW_STREAM_WAIT` times its
  typical interval before the keep-alive starts (no later than :data:`TIMEOUT_MARGIN_S`
  before the autopilot's timeout unless the stream itself is that slow): it is slow, not
  blind. And whatever the stream, a keep-alive also goes out :data:`TIMEOUT_MARGIN_S`
  before the timeout counted from the last *message* once the next frame is overdue (by
  :data:`OVERDUE_US`, or a quarter of its interval): at a low message rate the last report
  can precede the last frame by a whole period.
* **Where the autopilot's interval starts.** INAV divides a
  message's counts by the time since the *previous message*, and PX4 integrates its own gyro
  from the previous message on; so any message starts the autopilot's next interval.
  Hence (1) when integration (re)starts — the first frame, a frame after a gap or a clock
  reset — the link sends a quality-0 report at once, so the next report's counts and the
  autopilot's interval start at the same frame (after a late frame, the report it closed
  is that report, and integration restarts at the late frame); (2) a keep-alive never
  discards the pending interval, but the report that closes an interval begun before a
  keep-alive goes out with quality 0 (its counts span more than the autopilot's interval).
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, replace

from ..angular import VALID_ROTATIONS_DEG, FlowIntegrator, FlowInterval, RecentIntervals
from ..clock import host_us
from .message_log import MessageLog
from .serial_port import OutgoingMessage, SerialTransport

__all__ = ["FlowSample", "LinkConfig", "FlowLink", "choose_message_rate", "AUTOPILOTS", "PROTOCOLS",
           "AUTOPILOT_PROTOCOLS", "MSP_ARDUPILOT", "protocol_refusal", "BLIND_RATE_HZ", "MIN_MESSAGE_RATE_HZ",
           "MIN_RATE_REASON", "FRESH_REPORT_US", "FLOOR_REPORTS_HZ", "resolve_protocol", "line_problem"]

log = logging.getLogger(__name__)

AUTOPILOTS = ("ardupilot", "px4", "inav", "both")
PROTOCOLS = ("mavlink", "msp")
#: The wire protocols over which each autopilot setting's flow message set can go, the
#: default first (docs/spec/autopilot-links.md): PX4 only MAVLink, INAV only MSP; "both" is
#: the two MAVLink messages. ArduPilot only MAVLink (FLOW_TYPE = 5): its MSP driver
#: (FLOW_TYPE = 7, ``AP_OpticalFlow_MSP.cpp``) takes the mean counts of the messages since its
#: last update *times* the time between them (the Matek 3901-L0X's convention), so no count
#: per degree gives a rate that does not change with the message interval (:data:`MSP_ARDUPILOT`).
AUTOPILOT_PROTOCOLS = {"ardupilot": ("mavlink",), "px4": ("mavlink",), "inav": ("msp",),
                       "both": ("mavlink",)}
#: Why ArduPilot is not sent MSP (the refusal's explanation).
MSP_ARDUPILOT = ("ArduPilot's MSP flow driver (FLOW_TYPE = 7) multiplies the mean counts by the time "
                 "between messages (the Matek 3901-L0X's scaling), so per-degree counts would read "
                 "wrong by a factor that changes with the message rate; use MAVLink (FLOW_TYPE = 5)")

#: Quality-0 keep-alive messages per second while no frames arrive.
BLIND_RATE_HZ = 10.0
#: A slow but steady stream is blind only after this many of its typical frame intervals.
SLOW_STREAM_WAIT = 1.25
#: Keep-alives start at least this long before the autopilot's timeout when they can, s
#: (serial latency, the daemon's 10 ms loop).
TIMEOUT_MARGIN_S = 0.05
#: How late past its typical interval a frame may reach the link before a keep-alive near
#: the autopilot's timeout takes it for a stall, µs (at least; a quarter of the interval
#: when that is more): the daemon hands a frame over after the engine and the summary, whose
#: time varies (garbage collection, a slow frame), and a keep-alive costs the pending report.
OVERDUE_US = 15_000
#: Fraction of the line's capacity the link may use (the rest absorbs jitter and bursts).
BUSY_FRACTION = 0.6
#: Fewest flow reports per second, whatever the baud rate or ``message_rate_hz``: ArduPilot's
#: EKF3 starts (and re-enters) flow aiding only while the newest flow sample is < 200 ms old
#: (``readyToUseOptFlow``), and INAV times an MSP flow sensor out after 200 ms
#: (``OPFLOW_UPDATE_TIMEOUT_US``); a period of 1/7 s (143 ms) leaves room for frame alignment
#: and jitter. (PX4's EKF2 has no such limit, but "both" feeds ArduPilot too, and one floor
#: keeps the baud rule simple.)
MIN_MESSAGE_RATE_HZ = 7.0
#: Longest ``msp_report_delay_ms``: INAV compensates rotation with its gyro over the arrival
#: interval, so a report held longer compares its flow with a gyro window that much later;
#: and a held report must stay well within the transport's 0.25 s before it is dropped as
#: stale.
MAX_REPORT_DELAY_MS = 50.0
#: Reports go out at most this far apart (host µs) where the frames allow it: the floor's
#: period alone, with reports ending on frames, let them drift to 200-227 ms apart at 9-10
#: fps (a report waits for the frame after the period); ArduPilot's EKF3 and INAV need
#: < 200 ms, less jitter.
FRESH_REPORT_US = 180_000
#: The most reports per second that freshness can ask for: with frames just over
#: FRESH_REPORT_US / 2 apart (~11 fps), every frame is one (what the line check sizes for).
FLOOR_REPORTS_HZ = 1e6 / (FRESH_REPORT_US / 2)
#: Why :data:`MIN_MESSAGE_RATE_HZ`, for the error messages that enforce it.
MIN_RATE_REASON = ("ArduPilot's EKF3 uses optical flow only while its newest sample is < 200 ms old, "
                   "and INAV drops an MSP flow sensor after 200 ms without an update")
#: Baud rates suggested when the line is too slow (the usual UART settings).
STANDARD_BAUDS = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)


@dataclass(frozen=True, slots=True)
class FlowSample:
    """One processed frame's flow summary, as the daemon hands it to the link.

    Attributes
    ----------
    timestamp_us : int
        Capture timestamp of the frame, µs, source clock (file sources: index / fps).
    capture_host_us : int
        Host monotonic time when the frame was captured/received, µs (for latency).
    flow_x, flow_y : float
        Image flow since the previous frame, px/frame, x right, y down.
    quality : int
        0 (no usable flow) … 255 (best).
    doubtful : bool
        The summary's quality is below the link's floor (``[link] min_quality``): the report
        leaves this frame's flow out and reads its span at its other frames' rate (quality 0
        when those are fewer than half; :meth:`FlowIntegrator.add_frame`).
    extras : tuple of (str, float)
        Named extra values (expansion rate, time to contact, balance ...) that a link may
        send as well when ``LinkConfig.extra_values`` is on (MAVLink: NAMED_VALUE_FLOAT,
        names of at most 10 characters).
    """

    timestamp_us: int
    capture_host_us: int
    flow_x: float
    flow_y: float
    quality: int
    extras: tuple = ()
    doubtful: bool = False


@dataclass(kw_only=True)
class LinkConfig:
    """Configuration of a link to a flight controller.

    Attributes
    ----------
    port : str or None
        Serial device (``/dev/ttyAMA0``, ``/dev/ttyUSB0``, a pty). None: no port, messages
        are only counted (and logged).
    baud : int
        Baud rate; also sets the message rate when ``message_rate_hz`` is None.
    autopilot : {"ardupilot", "px4", "inav", "both"}
        Which controller listens; selects protocol and message set.
    protocol : {None, "mavlink", "msp"}
        None derives it from ``autopilot`` (inav → msp, others → mavlink); given, it must be
        the autopilot's (:data:`AUTOPILOT_PROTOCOLS`: a pair that cannot work is refused).
        (Not Betaflight: its MSP flow reading needs an MT rangefinder on the same link and
        scales the counts its own way; README, "Notes on the spec".)
    focal_length_px : float
        Focal length in pixels at the processed resolution.
    mounting_rotation_deg : {0, 90, 180, 270}
        Camera turned clockwise seen from above, see :mod:`firmware_py.angular`.
    mounting_mirror : bool
        Picture mirrored left-right.
    sysid, compid : int
        MAVLink system and component id of the appliance.
    sensor_id : int
        ``sensor_id`` field of the flow messages.
    message_rate_hz : float or None
        Flow messages per second; None chooses the highest rate keeping the line ≤ 60 % busy,
        capped at 17 Hz (OPTICAL_FLOW alone: what ArduPilot's EKF3 fuses, see
        ``mavlink.ARDUPILOT_EKF3_RATE_HZ``), 70 Hz (with OPTICAL_FLOW_RAD, whose reports
        also span at least 1/70 s: PX4's SENS_FLOW_RATE) or 50 Hz (MSP). Never more than one
        message per frame, never fewer than :data:`MIN_MESSAGE_RATE_HZ` (ArduPilot's EKF3 and
        INAV need a flow sample every < 200 ms).
    heartbeat_rate_hz : float
        MAVLink HEARTBEAT rate, Hz (also while the camera is blind).
    ground_distance_m : float or None
        Fixed known distance to the ground, m; None (or a value <= 0) sends -1 (unknown).
    message_log : str or None
        ``*.csv`` or ``*.jsonl`` path of a log of every message written, or None.
    extra_values : bool
        Also send the samples' extra values (MAVLink: NAMED_VALUE_FLOAT at 5 Hz, queued after
        the frame's flow message, thinned or left out where the baud rate leaves them no
        room next to the flow messages; MSP: not sent).
    msp_counts_per_degree : float
        MSP motion counts per degree of angular flow; must equal INAV's ``opflow_scale``
        (default 10.5) so INAV's rates come out in the right scale.
    msp_report_delay_ms : float or None
        MSP only: each report goes on the wire this long after its newest frame's capture,
        ms, so that INAV (which divides a report's counts by the time since the previous one
        arrived) sees the capture intervals, not the processing time's jitter; None:
        automatic (just above the recent times from capture to report,
        :mod:`firmware_py.links.pacing`); 0: each report as soon as it is processed. The
        caller writes held reports when due (:attr:`FlowLink.paces_reports`).
    """

    port: str | None = None
    baud: int = 115200
    autopilot: str = "ardupilot"
    protocol: str | None = None
    focal_length_px: float = 400.0
    mounting_rotation_deg: int = 0
    mounting_mirror: bool = False
    sysid: int = 1
    compid: int = 158
    sensor_id: int = 0
    message_rate_hz: float | None = None
    heartbeat_rate_hz: float = 1.0
    ground_distance_m: float | None = None
    message_log: str | None = None
    extra_values: bool = False
    msp_counts_per_degree: float = 10.5
    msp_report_delay_ms: float | None = None

    def __post_init__(self):
        if self.autopilot not in AUTOPILOTS:
            raise ValueError(f"autopilot must be one of {AUTOPILOTS}, got {self.autopilot!r}")
        if self.protocol is not None and self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be None or one of {PROTOCOLS}, got {self.protocol!r}")
        if self.protocol is not None and self.protocol not in AUTOPILOT_PROTOCOLS[self.autopilot]:
            raise ValueError(f"autopilot {self.autopilot!r} with protocol {self.protocol!r}: "
                             + protocol_refusal(self.autopilot))
        if int(self.mounting_rotation_deg) % 360 not in VALID_ROTATIONS_DEG:
            raise ValueError(f"mounting_rotation_deg must be one of {VALID_ROTATIONS_DEG}, "
                             f"got {self.mounting_rotation_deg}")
        if not (self.focal_length_px and self.focal_length_px > 0 and math.isfinite(self.focal_length_px)):
            raise ValueError(f"focal_length_px must be positive, got {self.focal_length_px}")
        if int(self.baud) <= 0:
            raise ValueError(f"baud must be positive, got {self.baud}")
        if self.message_rate_hz is not None and not self.message_rate_hz >= MIN_MESSAGE_RATE_HZ:
            raise ValueError(f"message_rate_hz must be None or >= {MIN_MESSAGE_RATE_HZ:g} ({MIN_RATE_REASON}), "
                             f"got {self.message_rate_hz}")
        if not self.heartbeat_rate_hz > 0:
            raise ValueError(f"heartbeat_rate_hz must be positive, got {self.heartbeat_rate_hz}")
        if not 0 <= int(self.sensor_id) <= 255:
            raise ValueError(f"sensor_id must be 0..255, got {self.sensor_id}")
        for name in ("sysid", "compid"):
            if not 1 <= int(getattr(self, name)) <= 255:
                raise ValueError(f"{name} must be 1..255, got {getattr(self, name)}")
        if not self.msp_counts_per_degree > 0:
            raise ValueError(f"msp_counts_per_degree must be positive, got {self.msp_counts_per_degree}")
        if self.msp_report_delay_ms is not None and not 0 <= self.msp_report_delay_ms <= MAX_REPORT_DELAY_MS:
            raise ValueError(f"msp_report_delay_ms must be 0..{MAX_REPORT_DELAY_MS:g} ms (or unset: automatic), "
                             f"got {self.msp_report_delay_ms}")


def protocol_refusal(autopilot: str, name: str | None = None, advice: str = "") -> str:
    """Why ``autopilot`` (shown as ``name``) takes no other protocol than
    :data:`AUTOPILOT_PROTOCOLS` lists, ``advice`` after the rule."""
    speaks = AUTOPILOT_PROTOCOLS[autopilot]
    text = f"{name or autopilot} takes optical flow over {' or '.join(speaks)} only{advice}"
    return f"{text}: {MSP_ARDUPILOT}" if autopilot == "ardupilot" else text


def resolve_protocol(config: LinkConfig) -> str:
    """Wire protocol for a config: the explicit one, else the autopilot's default (msp for
    INAV, mavlink otherwise: :data:`AUTOPILOT_PROTOCOLS`)."""
    if config.protocol is not None:
        return config.protocol
    return AUTOPILOT_PROTOCOLS[config.autopilot][0]


def choose_message_rate(*, baud: int, bytes_per_message: int, cap_hz: float,
                        reserved_bytes_per_s: float = 0.0, busy_fraction: float = BUSY_FRACTION) -> float:
    """Highest whole message rate that keeps the line under ``busy_fraction``.

    Parameters
    ----------
    baud : int
        Line rate, bit/s; 8N1 framing makes that ``baud / 10`` bytes/s.
    bytes_per_message : int
        Bytes on the wire for one report (all messages of the set).
    cap_hz : float
        Upper limit, Hz.
    reserved_bytes_per_s : float
        Other traffic (heartbeats), bytes/s.
    busy_fraction : float
        Share of the line the link may occupy.

    Returns
    -------
    float
        Message rate, Hz, at least :data:`MIN_MESSAGE_RATE_HZ` even where the budget gives
        less (at a slower rate ArduPilot's EKF3 and INAV stop using the flow;
        :func:`line_problem` says when the line cannot carry even that).
    """
    budget = baud / 10.0 * busy_fraction - reserved_bytes_per_s
    return float(max(MIN_MESSAGE_RATE_HZ, min(int(cap_hz), math.floor(budget / bytes_per_message))))


def line_problem(*, baud: int, report: str, bytes_per_report: int, reserved_bytes_per_s: float,
                 reserved: str = "") -> str | None:
    """Why a line of ``baud`` cannot carry the fewest reports the autopilots use — at least
    :data:`MIN_MESSAGE_RATE_HZ` a second, and up to :data:`FLOOR_REPORTS_HZ` with a camera
    near 11 fps, each frame then one report to keep them < 200 ms apart (a text that
    continues "baud N is "), or None.

    Parameters
    ----------
    baud : int
        Line rate, bit/s (8N1: ``baud / 10`` bytes/s).
    report : str
        The report's message names, for the text.
    bytes_per_report : int
        Bytes on the wire of one report.
    reserved_bytes_per_s : float
        Traffic that is always sent (heartbeats), bytes/s; ``reserved`` names it.
    """
    need = FLOOR_REPORTS_HZ * bytes_per_report + reserved_bytes_per_s
    if need <= baud / 10.0:
        return None
    # Suggest a rate whose 60 % budget holds them, as the rate choice wants.
    fits = [b for b in STANDARD_BAUDS if b / 10.0 * BUSY_FRACTION >= need]
    advice = f"use {fits[0]} baud or more" if fits else "use a faster line"
    return (f"too low: up to {FLOOR_REPORTS_HZ:.0f} {report} reports per second (at least "
            f"{MIN_MESSAGE_RATE_HZ:g}, and every frame of a camera near 11 fps; {bytes_per_report} bytes "
            f"each; {MIN_RATE_REASON}){reserved} need {need:.0f} bytes/s, "
            f"and {baud} baud carries {baud / 10.0:.0f} bytes/s (8N1); {advice} on both ends")


class FlowLink:
    """Base class of the protocol links (see the module docstring for the timing model).

    Subclasses set :attr:`protocol`, implement :meth:`line_need` and :meth:`_encode_flow`
    and may override :meth:`_default_rate_cap`, :meth:`_reserved_bytes_per_s`,
    :meth:`_handle_rx`, :meth:`_periodic`, :meth:`_on_open`.
    """

    protocol = "?"
    #: Start the blind keep-alive after this long without a submitted frame, s (the daemon
    #: may lower it with ``[daemon] blind_after_s``, never raise it).
    blind_after_s = 0.3
    #: The autopilot declares the sensor lost after this long without a message, s
    #: (ArduPilot: 0.5 s).
    autopilot_timeout_s = 0.5
    #: Shortest capture span a good report may cover, µs (0: any; the MAVLink link sets it
    #: before this class's __init__: PX4's message sets, ArduPilot's at its default rate).
    min_report_span_us = 0.0
    #: Whether reports are held for a send time (:meth:`_send_at`): the caller then calls
    #: :meth:`send_due` when :meth:`wake_in_s` says (the daemon: from its report writer thread).
    paces_reports = False

    def __init__(self, config: LinkConfig):
        self.config = config
        #: every public method holds it: the daemon's report writer thread sends held reports
        #: (:meth:`send_due`) while the frame loop submits and services
        self._lock = threading.RLock()
        #: set when a report is queued to be held for its send time (:meth:`wake_in_s`)
        self.reports_held = threading.Event()
        self.stats: dict = {"protocol": self.protocol, "port": config.port, "messages_sent": {},
                            "flow_reports": 0, "blind_reports": 0, "integration_restarts": 0,
                            "internal_errors": 0, "frames": 0}
        self.integrator = FlowIntegrator(focal_length_px=config.focal_length_px,
                                         rotation_deg=config.mounting_rotation_deg,
                                         mirror=config.mounting_mirror)
        self.message_rate_hz = self._choose_rate()
        self.period_us = 1e6 / self.message_rate_hz
        self.stats["message_rate_hz"] = self.message_rate_hz
        self.message_log = None
        if config.message_log:
            try:
                self.message_log = MessageLog(config.message_log)
            except OSError as exc:
                log.warning("message log %s cannot be created: %s; not logging", config.message_log, exc)
        self._last_submit_host_us: int | None = None    # host time of the last submit()
        self._last_capture_host_us: int | None = None   # capture_host_us of that frame
        self._submit_intervals = RecentIntervals()      # host µs between submits
        self._slow_stream_logged = False
        self._last_flow_host_us: int | None = None
        self._last_report_end_us: int | None = None
        self._keepalive_in_interval = False  # a keep-alive went out since the pending interval began
        self._internal_error_logged = False
        if config.port is None:
            log.warning("no serial port configured: %s messages are counted but not sent", self.protocol)
        self.transport = SerialTransport(port=config.port, baud=config.baud, stats=self.stats,
                                         max_queue_messages=self._queue_capacity(),
                                         on_open=self._on_open, on_sent=self._on_sent,
                                         on_flow_gap=self._flow_gap)
        self.transport.try_open(host_us())
        self.transport.pump()

    # -- configuration hooks ---------------------------------------------------------
    @classmethod
    def line_need(cls, config: LinkConfig) -> tuple[str, int, float, str]:
        """What the line must carry for ``config`` whatever else is configured: the report's
        message names, its bytes on the wire, and the bytes/s of traffic always sent next to
        it with their description (see :func:`line_problem`)."""
        raise NotImplementedError

    @classmethod
    def line_problem(cls, config: LinkConfig) -> str | None:
        """Why ``config.baud`` cannot carry this link's reports at all, or None."""
        report, size, reserved, what = cls.line_need(config)
        return line_problem(baud=config.baud, report=report, bytes_per_report=size,
                            reserved_bytes_per_s=reserved, reserved=what)

    def _bytes_per_report(self) -> int:
        return self.line_need(self.config)[1]

    def _default_rate_cap(self) -> float:
        return 100.0

    def _reserved_bytes_per_s(self) -> float:
        """Bytes/s sent next to the reports: :meth:`line_need`'s always-sent traffic."""
        return self.line_need(self.config)[2]

    def _rate_ceiling_hz(self) -> float:
        """Most reports per second the minimum span lets out, whatever the configured rate."""
        return 1e6 / self.min_report_span_us if self.min_report_span_us > 0 else math.inf

    def _queue_capacity(self) -> int:
        # About 0.1 s of reports (plus room for a heartbeat) before the oldest goes.
        return max(4, int(math.ceil(self.message_rate_hz * 0.1)) * self._messages_per_report() + 2)

    def _messages_per_report(self) -> int:
        return 1

    def _choose_rate(self) -> float:
        cfg = self.config
        problem = self.line_problem(cfg)
        if problem:
            # Refused, not warned: reports the line cannot carry age out in the queue, and
            # the autopilot sees a sensor that keeps timing out (the daemon checks this at
            # start-up and exits 2, naming [link] baud).
            raise ValueError(f"{self.protocol} on {cfg.port}: baud {cfg.baud} is {problem}")
        budget_rate = choose_message_rate(baud=cfg.baud, bytes_per_message=self._bytes_per_report(),
                                          cap_hz=self._default_rate_cap(),
                                          reserved_bytes_per_s=self._reserved_bytes_per_s())
        rate = budget_rate if cfg.message_rate_hz is None else float(cfg.message_rate_hz)
        load = (rate * self._bytes_per_report() + self._reserved_bytes_per_s()) / (cfg.baud / 10.0)
        if cfg.message_rate_hz is None:
            if rate < 10:  # (a configured rate is a choice, not a shortfall)
                over = (f" ({100 * load:.0f} % of the line, over the {100 * BUSY_FRACTION:.0f} % budget: the "
                        f"fewest that keep ArduPilot's EKF3 and INAV using the flow, which need a sample "
                        f"every < 200 ms)" if load > BUSY_FRACTION else "")
                log.warning("%s on %s: only %.0f flow messages/s fit in %d baud%s; raise the baud rate",
                            self.protocol, cfg.port, rate, cfg.baud, over)
        elif load > BUSY_FRACTION:
            log.warning("%s on %s: %.0f Hz needs %.0f %% of %d baud (budget %.0f %%): expect drops; "
                        "%.0f Hz would fit", self.protocol, cfg.port, rate, 100 * load, cfg.baud,
                        100 * BUSY_FRACTION, budget_rate)
        log.info("%s on %s: up to %.0f flow messages/s (%d bytes each) at %d baud", self.protocol, cfg.port,
                 min(rate, self._rate_ceiling_hz()), self._bytes_per_report(), cfg.baud)
        return rate

    # -- public interface ------------------------------------------------------------
    def submit(self, sample: FlowSample, now_host_us: int | None = None) -> None:
        """Add one processed frame; sends a report when the interval is complete.

        ``now_host_us`` is the host monotonic time of the call, µs (default: now): the blind
        keep-alive counts from the last submit, not from the frame's capture. Never blocks,
        never raises.
        """
        with self._lock:
            try:
                self._submit(sample, host_us() if now_host_us is None else int(now_host_us))
            except Exception:  # noqa: BLE001 - the frame loop must survive any link bug
                self._internal_error("submit")

    def service(self, now_host_us: int) -> None:
        """Host-time housekeeping: reopen, read, heartbeats, blind keep-alive, flush.

        Call it every frame and while blind. Never waits for the port (only for another
        thread's call to finish), never raises.
        """
        with self._lock:
            try:
                now = int(now_host_us)
                self.transport.service(now)
                data = self.transport.read_available(now_us=now)
                if data:
                    self._handle_rx(data, now)
                self._periodic(now)
                self._blind_keepalive(now)
                self.transport.pump(now)
            except Exception:  # noqa: BLE001
                self._internal_error("service")

    def set_focal_length_px(self, focal_length_px: float) -> None:
        """Convert pixels to angles with this focal length (px) from the next report on:
        the daemon calls it when a camera opened after start-up delivers another image
        (aspect ratio, hence crop) than the one the link was made for."""
        with self._lock:
            self.config = replace(self.config, focal_length_px=focal_length_px)  # validates it
            self.integrator.focal_length_px = float(self.config.focal_length_px)

    def wake_in_s(self, now_host_us: int) -> float | None:
        """Seconds from ``now_host_us`` until a report held for its send time is due (0:
        due; call :meth:`send_due` then); None: none held that could be written then (see
        :meth:`SerialTransport.next_due_us`). Never raises."""
        with self._lock:
            try:
                due = self.transport.next_due_us()
            except Exception:  # noqa: BLE001
                self._internal_error("wake_in_s")
                return None
        return None if due is None else max(0.0, (due - int(now_host_us)) / 1e6)

    @property
    def queued_messages(self) -> int:
        """Messages waiting to be written (a partly written one included)."""
        with self._lock:
            return self.transport.queued_messages

    def send_due(self, now_host_us: int) -> None:
        """Write the reports held for their send time that are due at ``now_host_us`` (host
        µs), from any thread: the daemon's report writer calls it at :meth:`wake_in_s`,
        whatever the frame loop is doing. Never waits for the port, never raises."""
        with self._lock:
            try:
                self.transport.pump(int(now_host_us))
            except Exception:  # noqa: BLE001
                self._internal_error("send_due")

    def stats_snapshot(self) -> dict:
        """A copy of :attr:`stats` (its per-type counts too) taken while no other thread
        changes them, for a status line."""
        with self._lock:
            return {key: dict(value) if isinstance(value, dict) else value for key, value in self.stats.items()}

    def latencies_us(self) -> list[int]:
        """Capture-to-write latencies (µs) of flow messages written since the previous call.

        Each value is the host time the message's last byte was handed to the OS minus the
        ``capture_host_us`` of the newest frame in it. Draining: every value is returned once.
        """
        with self._lock:
            values = list(self.transport.latencies_us)
            self.transport.latencies_us.clear()
        return values

    def close(self) -> None:
        """Flush what is queued (best effort, ≤ 0.2 s; reports held for their send time go
        when due) and close the port and the log."""
        with self._lock:
            try:
                self.transport.close()
            except Exception:  # noqa: BLE001
                self._internal_error("close")
            if self.message_log is not None:
                self.message_log.close()

    def reopen_message_log(self) -> str | None:
        """Reopen the message log (SIGHUP after a log rotation), or create it if it could
        not be at start-up (a folder made since); returns its path, None without one
        configured. Never raises: a log that still cannot be written logs a warning."""
        with self._lock:
            if self.message_log is not None:
                self.message_log.reopen()
            elif self.config.message_log:
                try:
                    self.message_log = MessageLog(self.config.message_log)
                except OSError as exc:
                    log.warning("message log %s cannot be created: %s; not logging", self.config.message_log,
                                exc)
                    return None
            else:
                return None
            return self.message_log.path

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- internals -------------------------------------------------------------------
    def _internal_error(self, where: str) -> None:
        self.stats["internal_errors"] += 1
        if not self._internal_error_logged:
            self._internal_error_logged = True
            log.exception("%s link on %s: unexpected error in %s (continuing)", self.protocol,
                          self.config.port, where)

    def _send_extras(self, sample: FlowSample) -> None:
        """Protocol hook for ``sample.extras`` (only MAVLink has a field for them)."""

    def _submit(self, sample: FlowSample, now: int) -> None:
        self.stats["frames"] += 1
        self._note_submit(now)
        integ = self.integrator
        dt = int(sample.timestamp_us) - (integ.last_timestamp_us or 0)
        # A frame that would take the pending report past max_interval_us (jitter past the
        # nominal interval the schedule below plans with) closes it first, at the previous
        # frame. Judged here, not against gap_threshold_us: add_frame() learns dt before its
        # gap test, and a late frame can lift the threshold enough to pass as an ordinary one.
        late = integ.elapsed_us > 0 and dt > 0 and integ.elapsed_us + dt > integ.max_interval_us
        if late:
            # With quality 0: its counts end at the previous frame, but the autopilot's next
            # interval runs from the previous message to now (INAV would divide them by that
            # longer time, PX4 match them with the wrong gyro window).
            # (sent on this frame's clock: the autopilot's next interval starts at this frame)
            self._emit_pending(capture_host_us=self._last_capture_host_us, now=now, quality0=True,
                               paced_on=(int(sample.capture_host_us), int(sample.timestamp_us)))
        accepted = integ.add_frame(timestamp_us=sample.timestamp_us, flow_x_px=sample.flow_x,
                                   flow_y_px=sample.flow_y, quality=sample.quality, doubtful=sample.doubtful)
        if late or not accepted:
            self.stats["integration_restarts"] = integ.restart_count
        if late:
            # The report just sent starts the autopilot's next interval now, at this frame:
            # the frame's own flow began before it (sent too, INAV would divide it by ~0 s;
            # PX4 drops a sample older than the one before), so integration restarts here.
            # That report also stands for the restart marker below (no second report at
            # once, gap or not); only the carried remainders are left to forget.
            if accepted:
                integ.restart(int(sample.timestamp_us))
            self._reset_carry()
        elif not accepted:
            # The first frame or a restart (the only time restart_count changes). The
            # autopilot's next interval must begin at this frame as well; the quality-0
            # marker also forgets the protocol's carried remainders (_emit).
            self._keepalive_in_interval = False
            marker = self._quality0_interval(end_us=int(sample.timestamp_us),
                                             span_us=self._quality0_span_us(now))
            self._emit(marker, capture_host_us=int(sample.capture_host_us), now=now)
        else:
            # Emit on frame boundaries: a quarter-frame tolerance keeps e.g. 50 Hz at 100 fps
            # from slipping to every third frame on jitter.
            nominal = integ.nominal_interval_us or 0.0
            tolerance = 0.25 * nominal
            # ... and no later than the frame after which the next one would take the report
            # past FRESH_REPORT_US (at the floor, frames 90-140 ms apart would otherwise wait
            # for the frame after the period: 200-227 ms between reports) or max_interval_us.
            # The minimum span yields to both backstops too: held, a short interval of a slow
            # camera would go past max_interval_us with the next frame (out as quality 0), or
            # reports would drift past FRESH_REPORT_US apart.
            backstop = min(FRESH_REPORT_US - nominal, integ.max_interval_us - nominal)
            due = max(min(self.period_us - tolerance, backstop), min(self.min_report_span_us, backstop))
            if integ.elapsed_us > 0 and integ.elapsed_us >= due:
                self._emit_pending(capture_host_us=int(sample.capture_host_us), now=now)
        self._last_capture_host_us = int(sample.capture_host_us)
        # After the flow message: the extras must not delay it on the wire.
        if self.config.extra_values and sample.extras:
            self._send_extras(sample)
        self.transport.pump(now)

    def _emit_pending(self, *, capture_host_us: int | None, now: int, quality0: bool = False,
                      paced_on: tuple[int, int] | None = None) -> None:
        """Send the pending interval as a report (``quality0``: with quality 0; ``paced_on``
        as in :meth:`_emit`)."""
        interval = self.integrator.take()
        # (after a keep-alive the autopilot's interval began there, these counts earlier)
        if quality0 or self._keepalive_in_interval:
            interval = replace(interval, quality=0)
        self._keepalive_in_interval = False
        self._emit(interval, capture_host_us=capture_host_us, now=now, paced_on=paced_on)

    def _note_submit(self, now: int) -> None:
        """Track the host interval between submitted frames; warn once when it is longer
        than the autopilot tolerates between messages."""
        if self._last_submit_host_us is not None:
            self._submit_intervals.add(now - self._last_submit_host_us)
        self._last_submit_host_us = now
        if self._slow_stream_logged or len(self._submit_intervals) < 5:
            return  # judged on a median of 5 or more: one stall is not a slow stream
        typical = self._submit_intervals.typical
        max_interval_us = self.integrator.max_interval_us
        if typical <= min(self.autopilot_timeout_s * 1e6, max_interval_us):
            return
        self._slow_stream_logged = True
        if typical > max_interval_us:
            effect = (f"more than a report may span ({max_interval_us / 1e6:.2f} s): only quality-0 "
                      "messages can be sent")
        else:
            effect = (f"more than the autopilot's {self.autopilot_timeout_s:.2f} s timeout: it will see "
                      "the flow sensor time out between reports")
        log.warning("%s on %s: processed frames arrive every %.2f s, %s; use a faster engine "
                    "(OpenCL, smaller frames) or camera", self.protocol, self.config.port, typical / 1e6,
                    effect)

    def _keepalive_after_us(self) -> float:
        """Host time without a submitted frame after which the link is blind, µs.

        ``blind_after_s``; for a slow but steady stream that can be reported,
        :data:`SLOW_STREAM_WAIT` of its typical interval (a keep-alive before its next frame
        would cost that frame's report), but no later than :data:`TIMEOUT_MARGIN_S` before the
        autopilot's timeout — unless the stream itself is about that slow: then its reports
        come first (and :meth:`_note_submit` warns when it exceeds the timeout).
        """
        after = self.blind_after_s * 1e6
        typical = self._submit_intervals.typical
        if typical is None or typical > self.integrator.max_interval_us:
            return after  # fast, not known yet, or too slow to report anyway
        wait = min(SLOW_STREAM_WAIT * typical, (self.autopilot_timeout_s - TIMEOUT_MARGIN_S) * 1e6)
        if wait <= typical:
            wait = SLOW_STREAM_WAIT * typical
        return max(after, wait)

    def _quality0_span_us(self, now: int) -> int:
        """Span of a quality-0 report: the host time since the previous flow message (what
        PX4 integrates its own gyro over), below ArduPilot's 0.5 s, µs."""
        if self._last_flow_host_us is None:
            return int(1e6 / BLIND_RATE_HZ)
        return max(0, min(now - self._last_flow_host_us, self.integrator.max_blind_interval_us))

    @staticmethod
    def _quality0_interval(*, end_us: int, span_us: int) -> FlowInterval:
        """Zero flow, quality 0, ending at ``end_us`` (capture clock)."""
        return FlowInterval(start_us=end_us - span_us, end_us=end_us, integrated_x=0.0, integrated_y=0.0,
                            sum_u_px=0.0, sum_v_px=0.0, quality=0, frame_count=0)

    def _timeout_near(self, now: int, since_submit: int) -> bool:
        """Whether the autopilot's timeout is :data:`TIMEOUT_MARGIN_S` away with the next
        frame overdue (its typical interval plus :data:`OVERDUE_US`): the stream has stalled
        before it counts as blind, so a keep-alive goes out now. Blindness is judged from
        the last frame, the timeout from the last message: at a low message rate (7 Hz, the
        floor) the last message can precede the last frame by a whole period, and waiting
        for blindness then left INAV 270-290 ms without one (its timeout: 200 ms)."""
        if self._last_flow_host_us is None:
            return False
        if now - self._last_flow_host_us < (self.autopilot_timeout_s - TIMEOUT_MARGIN_S) * 1e6:
            return False
        typical = self._submit_intervals.typical
        return typical is not None and since_submit > max(SLOW_STREAM_WAIT * typical, typical + OVERDUE_US)

    def _blind_keepalive(self, now: int) -> None:
        if self._last_submit_host_us is not None:
            since_submit = now - self._last_submit_host_us
            # _keepalive_after_us() is never below blind_after_s: skip it while frames arrive.
            if ((since_submit < self.blind_after_s * 1e6 or since_submit < self._keepalive_after_us())
                    and not self._timeout_near(now, since_submit)):
                return
        if self._last_flow_host_us is not None and now - self._last_flow_host_us < 1e6 / BLIND_RATE_HZ:
            return
        span = self._quality0_span_us(now)
        if self._last_report_end_us is None:
            end = now  # nothing reported yet: the host clock is all there is
        else:
            # Continue the capture clock from the previous report by the host time since.
            end = self._last_report_end_us + span
        if self.integrator.last_timestamp_us is not None:
            # The pending interval stays (a late frame may still close it), but not as a good report.
            self._keepalive_in_interval = True
        self.stats["blind_reports"] += 1
        self._emit(self._quality0_interval(end_us=end, span_us=span), capture_host_us=None, now=now)

    def _emit(self, interval: FlowInterval, *, capture_host_us: int | None, now: int | None = None,
              paced_on: tuple[int, int] | None = None) -> None:
        """Queue the report of ``interval``, whose newest frame was captured at
        ``capture_host_us`` (host clock; None: a keep-alive). ``paced_on``: the frame whose
        capture times (host, capture clock) its send time follows where reports are paced
        (default: the newest frame's, ``capture_host_us`` and ``interval.end_us``)."""
        now = host_us() if now is None else now
        self._last_flow_host_us = now
        self._last_report_end_us = interval.end_us
        self.stats["flow_reports"] += 1
        if interval.quality == 0:
            self._reset_carry()
        messages = self._encode_flow(interval)
        if interval.quality == 0:
            # ... and its own rounding remainder: a quality-0 report with counts (closing an
            # interval after a keep-alive or a flow gap) would hand it to the next good one
            self._reset_carry()
        if paced_on is None:
            paced_on = (capture_host_us, interval.end_us)
        not_before = self._send_at(*paced_on, now)
        for name, data, fields in messages:
            fields.setdefault("frames", interval.frame_count)
            if not_before is not None:  # (held: its send time after the capture it is paced on)
                fields["paced_us"] = not_before - paced_on[0]
            self.transport.enqueue(OutgoingMessage(name=name, data=data, queued_host_us=now,
                                                   capture_host_us=capture_host_us, fields=fields,
                                                   flow=True, marker=interval.quality == 0,
                                                   not_before_host_us=not_before))
        if not_before is not None:
            self.reports_held.set()
        self.transport.pump(now)

    def _flow_gap(self) -> None:
        # The port (re)opened, or the transport dropped a report on a stalled line: it holds
        # good reports back until a quality-0 one goes out, and the pending interval's
        # report is that one (the one after it is good again).
        self._keepalive_in_interval = True

    def _enqueue_other(self, name: str, data: bytes, fields: dict, now: int, *, first: bool = False) -> None:
        self.transport.enqueue(OutgoingMessage(name=name, data=data, queued_host_us=now, fields=fields),
                               first=first)

    def _on_sent(self, message: OutgoingMessage, host_us: int, latency_us: int | None) -> None:
        if self.message_log is not None:
            self.message_log.write(host_us=host_us, message=message.name, size=len(message.data),
                                   latency_us=latency_us, fields=message.fields)

    # -- protocol hooks --------------------------------------------------------------
    def _encode_flow(self, interval: FlowInterval) -> list[tuple[str, bytes, dict]]:
        """Encode one report: ``[(message_name, frame_bytes, fields_for_log), ...]``."""
        raise NotImplementedError

    def _reset_carry(self) -> None:
        """Forget fractional remainders (after an integration restart or a blind interval)."""

    def _send_at(self, capture_host_us: int | None, capture_us: int, now: int) -> int | None:
        """Host time (µs) before which a report of a frame captured at ``capture_host_us``
        (None: a keep-alive; ``capture_us`` its capture time on the capture clock) is not
        written; None: at once (the default)."""
        return None

    def _handle_rx(self, data: bytes, now: int) -> None:
        """Bytes from the autopilot."""

    def _periodic(self, now: int) -> None:
        """Host-time periodic messages (heartbeats)."""

    def _on_open(self, now: int) -> None:
        """The port was (re)opened."""


def carry_round(value: float, remainder: float) -> tuple[int, float]:
    """Round ``value + remainder`` to an integer and return the new remainder.

    Integer wire units (MSP counts, MAVLink deci-pixels) would otherwise turn a slow, steady
    flow into a stream of zeros.
    """
    total = value + remainder
    whole = int(round(total))
    return whole, total - whole
