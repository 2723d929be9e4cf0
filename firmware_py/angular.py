"""Image flow (px/frame) to angular flow (rad/s, rad) in the flow-sensor axes of MAVLink.

The conversion follows ``docs/spec/autopilot-links.md``:

* angle per frame [rad] = pixel flow [px] / focal length [px] (small-angle; the focal length
  is the one *at the processed resolution*);
* rates use the **measured** frame intervals taken from the frames' capture timestamps, never
  the nominal fps or the host clock;
* the mounting setting (rotation in 90° steps, mirror) is applied to the image flow (u, v)
  first, then the default-mounting rule ``integrated_x = +u/f``, ``integrated_y = +v/f``.

Mounting convention
-------------------
Default mounting: camera looking down, top of the image towards the vehicle's front, image
right towards the vehicle's right. ``rotation_deg`` is how far the camera is turned
**clockwise, seen from above** (looking down through the camera), from that default:
with 90 the top of the image points to the vehicle's right. ``mirror`` means the picture is
left-right mirrored (a mirror/prism in the optical path, or a sensor flip setting); the mirror
is undone first, then the rotation.

==========  =======================  ====================================
rotation     image top points to      (u', v') from image flow (u, v)
==========  =======================  ====================================
0            front                    ( u,  v)
90           right                    (-v,  u)
180          back                     (-u, -v)
270          left                     ( v, -u)
==========  =======================  ====================================

(u', v') is the flow a default-mounted camera would have seen; mirror replaces u by -u
before the table.

Interval integration
--------------------
:class:`FlowIntegrator` sums frames until the link takes an interval. The flow reported
with a frame is the motion since the previous frame, so it belongs to the time between
the two capture timestamps. Rules:

* The nominal frame interval is the lower median of the last frame intervals (capture
  timestamps), so one stall or dropped frame does not move it, and a stream that slows down
  for good (a larger frame subset, a slower camera) is learned within a few frames.
* A frame arriving more than ``gap_threshold_us`` after the previous one (5 nominal frame
  intervals, but at most 0.25 s unless the frame rate is very low — then 2 intervals — and
  never more than ``max_interval_us``) restarts integration: its flow spans the gap and is discarded, as is
  the unsent partial interval. No spike, no huge integration time. A slow but steady stream
  (frames up to ``max_interval_us`` = 0.45 s apart: ArduPilot needs a message every < 0.5 s)
  is integrated normally.
* A timestamp that does not advance (clock reset, duplicate) also restarts integration.
* A quality-0 ("blind") frame still advances time so the autopilot keeps a continuous
  sequence (PX4 resets on gaps, ArduPilot needs a message every < 0.5 s); its flow is not
  added. A quality-0 frame after a long pause (a daemon's keep-alive sample while the camera
  is blind) extends the interval instead of restarting it, up to ``max_blind_interval_us``.
* Interval quality is the mean of the frames' qualities, but **0 if any frame in the interval
  was blind**: that interval's angle is missing the blind frames' motion, so it must not be
  fused as a good measurement (EKF3 and PX4 both reject quality 0).
* A *doubtful* frame (its summary rated below the link's quality floor: a flow that may be
  far off or of the wrong sign) is left out of the sums, not counted as blind: the interval's
  flow is its other frames' mean rate (their flow over their time) over the whole interval,
  and its quality their mean quality times the share of the span they cover — or 0 when
  they are fewer than half of its frames (a one-frame interval of a
  doubtful frame is quality 0, as when the floor zeroed each frame). Otherwise one doubtful
  frame in six cost ArduPilot the 60 ms report around it.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

__all__ = [
    "focal_length_px_from_fov",
    "fov_deg_from_focal_length_px",
    "turn_gain",
    "TURN_GAIN_WARNING",
    "apply_mounting",
    "FlowInterval",
    "FlowIntegrator",
    "RecentIntervals",
    "VALID_ROTATIONS_DEG",
]

VALID_ROTATIONS_DEG = (0, 90, 180, 270)

#: A gap this long always restarts integration (PX4 rejects > 1 s, ArduPilot > 0.5 s).
DEFAULT_MAX_GAP_US = 250_000
#: Quality-0 keep-alive frames may stretch an interval up to this (ArduPilot needs < 0.5 s).
DEFAULT_MAX_BLIND_INTERVAL_US = 450_000
#: Longest frame interval a report may contain, µs (ArduPilot: < 0.5 s between messages).
DEFAULT_MAX_INTERVAL_US = 450_000


class RecentIntervals:
    """Typical spacing of a stream: the lower median of its last few intervals.

    One stall or dropped frame does not move it; a lasting change (a slower camera, a larger
    frame subset) does within ``size // 2 + 1`` intervals.

    Parameters
    ----------
    size : int
        Number of intervals remembered.
    """

    def __init__(self, size: int = 9):
        self._values: deque[float] = deque(maxlen=size)
        self._typical: float | None = None

    def add(self, interval: float) -> None:
        """Remember one interval (any unit; values <= 0 are ignored)."""
        if interval > 0:
            self._values.append(float(interval))
            # Computed here, once: it is read several times per frame.
            ordered = sorted(self._values)
            self._typical = ordered[(len(ordered) - 1) // 2]

    def __len__(self) -> int:
        return len(self._values)

    @property
    def typical(self) -> float | None:
        """Lower median of the remembered intervals, None before the first one."""
        return self._typical


def focal_length_px_from_fov(*, fov_deg: float, size_px: float) -> float:
    """Focal length in pixels of a pinhole camera from its field of view.

    Parameters
    ----------
    fov_deg : float
        Full field of view in degrees along the same direction as ``size_px``
        (horizontal FOV with the image width, or diagonal FOV with the diagonal).
    size_px : float
        Image extent in pixels along that direction, **at the processed resolution**
        (after binning/resizing).

    Returns
    -------
    float
        Focal length in pixels: ``(size_px / 2) / tan(fov / 2)``.
    """
    if not 0.0 < fov_deg < 180.0:
        raise ValueError(f"field of view must be in (0, 180) degrees, got {fov_deg}")
    if size_px <= 0:
        raise ValueError(f"image size must be positive, got {size_px} px")
    return 0.5 * size_px / math.tan(math.radians(fov_deg) / 2.0)


def fov_deg_from_focal_length_px(*, focal_length_px: float, size_px: float) -> float:
    """Full field of view in degrees across ``size_px`` pixels at ``focal_length_px``: the
    inverse of :func:`focal_length_px_from_fov`."""
    if focal_length_px <= 0 or size_px <= 0:
        raise ValueError(f"focal length and image size must be positive, got {focal_length_px} and {size_px} px")
    return math.degrees(2.0 * math.atan(0.5 * size_px / focal_length_px))


#: Above this even-spread gain on turns (:func:`turn_gain`, the mean of x and y) the daemon
#: warns at start-up.
TURN_GAIN_WARNING = 1.10


def turn_gain(*, width: int, height: int, focal_length_px: float) -> tuple[float, float]:
    """How much faster a turn reads than the body rate, along x and along y, for a
    distortion-free lens whose image is ``width`` × ``height`` px at focal length
    ``focal_length_px`` (all at the processed resolution).

    The summary fits one flow to detections from the whole image. A translation over flat
    ground moves the image alike everywhere, a turn moves a pinhole image faster away from
    the centre (along the flow by ``1 + X²``, ``X = x / f``), and the autopilot expects
    the rate at the optical axis. For detections spread evenly over the frame the mean
    gain is ``1 + (W / 2f)² / 3`` along x and ``1 + (H / 2f)² / 3`` along y (``X`` measured
    along the flow). On rendered turns over evenly textured ground
    (``python -m emdflow.tools.rotation_eval``: gravel, grass) the summary's gain, averaged
    over four directions, is within 0.03 of the same average of these from 30° to 90° of
    horizontal field of view; a ground whose texture gathers at the centre (the camera
    photograph) reads less. Barrel distortion lowers it too.
    """
    if not (focal_length_px > 0 and width > 0 and height > 0):
        raise ValueError(f"turn_gain: width={width}, height={height}, focal_length_px={focal_length_px}: "
                         "all must be > 0")
    return (1.0 + (width / (2.0 * focal_length_px)) ** 2 / 3.0,
            1.0 + (height / (2.0 * focal_length_px)) ** 2 / 3.0)


def apply_mounting(u: float, v: float, *, rotation_deg: int = 0, mirror: bool = False) -> tuple[float, float]:
    """Turn image flow into the flow a default-mounted camera would have seen.

    Parameters
    ----------
    u, v : float
        Image flow, x right / y down, any unit (px/frame, px, ...).
    rotation_deg : {0, 90, 180, 270}
        Clockwise turn of the camera seen from above (see module docstring).
    mirror : bool
        The picture is left-right mirrored; undone before the rotation.

    Returns
    -------
    tuple of float
        ``(u', v')``: flow along the vehicle's right and rear directions.
    """
    if mirror:
        u = -u
    r = int(rotation_deg) % 360
    if r == 0:
        return u, v
    if r == 90:
        return -v, u
    if r == 180:
        return -u, -v
    if r == 270:
        return v, -u
    raise ValueError(f"mounting rotation must be one of {VALID_ROTATIONS_DEG} degrees, got {rotation_deg}")


@dataclass(frozen=True, slots=True)
class FlowInterval:
    """Flow integrated between two messages, in the sensor axes of the spec.

    Attributes
    ----------
    start_us, end_us : int
        Capture timestamps (µs, source clock) bounding the interval.
    integrated_x, integrated_y : float
        Accumulated angular flow, rad (RH rotation about sensor X / Y).
    sum_u_px, sum_v_px : float
        The same motion in pixels after mounting (``integrated * f``).
    quality : int
        0..255; 0 if any frame in the interval was blind.
    frame_count : int
        Frames whose motion is in the interval (blind frames included).
    """

    start_us: int
    end_us: int
    integrated_x: float
    integrated_y: float
    sum_u_px: float
    sum_v_px: float
    quality: int
    frame_count: int

    @property
    def integration_time_us(self) -> int:
        """Length of the interval, µs."""
        return self.end_us - self.start_us

    @property
    def rate_x(self) -> float:
        """Mean angular flow rate about sensor X, rad/s (0 for an empty interval)."""
        dt = self.integration_time_us
        return self.integrated_x * 1e6 / dt if dt > 0 else 0.0

    @property
    def rate_y(self) -> float:
        """Mean angular flow rate about sensor Y, rad/s (0 for an empty interval)."""
        dt = self.integration_time_us
        return self.integrated_y * 1e6 / dt if dt > 0 else 0.0


class FlowIntegrator:
    """Accumulate per-frame image flow into angular-flow intervals.

    Parameters
    ----------
    focal_length_px : float
        Focal length in pixels at the processed resolution.
    rotation_deg : {0, 90, 180, 270}
        Mounting rotation, see :func:`apply_mounting`.
    mirror : bool
        Mounting mirror, see :func:`apply_mounting`.
    gap_frames : float
        A frame interval longer than this many nominal intervals restarts integration.
    max_gap_us : int
        A frame interval longer than this always restarts integration (unless the nominal
        frame interval itself is longer, see :attr:`gap_threshold_us`), µs.
    max_blind_interval_us : int
        Longest interval a quality-0 keep-alive frame may close, µs.
    max_interval_us : int
        Longest frame interval that is integrated at all, µs; a longer one always restarts.
    """

    def __init__(self, *, focal_length_px: float, rotation_deg: int = 0, mirror: bool = False,
                 gap_frames: float = 5.0, max_gap_us: int = DEFAULT_MAX_GAP_US,
                 max_blind_interval_us: int = DEFAULT_MAX_BLIND_INTERVAL_US,
                 max_interval_us: int = DEFAULT_MAX_INTERVAL_US):
        if not focal_length_px > 0 or not math.isfinite(focal_length_px):
            raise ValueError(f"focal length must be a positive number of pixels, got {focal_length_px}")
        apply_mounting(0.0, 0.0, rotation_deg=rotation_deg)  # validates the rotation
        self.focal_length_px = float(focal_length_px)
        self.rotation_deg = int(rotation_deg) % 360
        self.mirror = bool(mirror)
        self.gap_frames = float(gap_frames)
        self.max_gap_us = int(max_gap_us)
        self.max_blind_interval_us = int(max_blind_interval_us)
        self.max_interval_us = int(max_interval_us)
        self._intervals = RecentIntervals()
        self.restart_count = 0
        self._last_us: int | None = None
        self._clear(None)

    # -- state -----------------------------------------------------------------------
    def _clear(self, start_us: int | None) -> None:
        self._start_us = start_us
        self._sum_u = 0.0
        self._sum_v = 0.0
        self._quality_sum = 0
        self._frames = 0
        self._doubtful = 0
        self._trusted_us = 0  # (the time the frames whose flow is summed span)
        self._blind = False

    @property
    def gap_threshold_us(self) -> float:
        """Frame interval above which integration restarts, µs."""
        if self.nominal_interval_us is None:
            return float(min(self.max_gap_us, self.max_interval_us))
        # 5 nominal intervals, but never less than 2 at very low frame rates, never above
        # max_gap_us unless the camera itself is that slow, and never above max_interval_us.
        return min(self.gap_frames * self.nominal_interval_us,
                   max(float(self.max_gap_us), 2.0 * self.nominal_interval_us),
                   float(self.max_interval_us))

    @property
    def elapsed_us(self) -> int:
        """Source time covered by the pending interval, µs."""
        if self._start_us is None or self._last_us is None:
            return 0
        return self._last_us - self._start_us

    @property
    def last_timestamp_us(self) -> int | None:
        """Capture timestamp of the latest frame, µs (None before the first frame)."""
        return self._last_us

    @property
    def nominal_interval_us(self) -> float | None:
        """Typical frame interval, µs (lower median of recent good frames), None at first."""
        return self._intervals.typical

    def restart(self, timestamp_us: int | None = None) -> None:
        """Forget the pending interval; the next frame (or ``timestamp_us``) starts a new one."""
        self._last_us = timestamp_us
        self._clear(timestamp_us)

    # -- input -----------------------------------------------------------------------
    def add_frame(self, *, timestamp_us: int, flow_x_px: float, flow_y_px: float, quality: int,
                  doubtful: bool = False) -> bool:
        """Add one processed frame.

        Parameters
        ----------
        timestamp_us : int
            Capture timestamp, µs, source clock.
        flow_x_px, flow_y_px : float
            Image flow since the previous frame, px/frame (x right, y down). Not finite,
            or a focal length or more: the frame counts as blind.
        quality : int
            0..255; 0 = blind (no usable flow).
        doubtful : bool
            The flow is not trusted (below the link's quality floor): time advances, the
            flow and quality are left out and the interval's rate is its other frames'.

        Returns
        -------
        bool
            False if the frame (re)started integration — the first frame, or one after a gap
            or a clock reset — and its flow was discarded.
        """
        ts = int(timestamp_us)
        q = max(0, min(255, int(quality))) if math.isfinite(quality) else 0
        # NaN, or a flow of a focal length or more (45° or more of view per frame): no
        # camera measures that, and sums of such values overflow the wire's fields (a
        # doubtful frame's flow is left out anyway: it stays doubtful, not blind)
        if not math.hypot(flow_x_px, flow_y_px) < self.focal_length_px and not doubtful:
            q = 0
        if self._last_us is None:
            self.restart(ts)
            return False
        dt = ts - self._last_us
        if q > 0 and 0 < dt <= self.max_interval_us:
            # Learn the interval from good frames before judging the gap: a stream that slows
            # down for good is not a gap at every frame (keep-alive samples teach nothing).
            self._intervals.add(dt)
        blind_keepalive = q == 0 and 0 < dt <= self.max_blind_interval_us and self.elapsed_us + dt <= self.max_blind_interval_us
        if dt <= 0 or (dt > self.gap_threshold_us and not blind_keepalive):
            self.restart_count += 1
            self.restart(ts)
            return False
        if self._start_us is None:
            self._start_us = self._last_us
        self._last_us = ts
        self._frames += 1
        if q == 0:
            self._blind = True
        elif doubtful:
            self._doubtful += 1
        else:
            self._trusted_us += dt
            u, v = apply_mounting(float(flow_x_px), float(flow_y_px), rotation_deg=self.rotation_deg, mirror=self.mirror)
            self._sum_u += u
            self._sum_v += v
            self._quality_sum += q
        return True

    def take(self) -> FlowInterval:
        """Return the pending interval and start the next one at the latest frame."""
        f = self.focal_length_px
        start = self._start_us if self._start_us is not None else (self._last_us or 0)
        end = self._last_us if self._last_us is not None else start
        trusted = self._frames - self._doubtful
        if self._blind or trusted <= 0 or 2 * trusted < self._frames:
            quality, scale = 0, 1.0
        else:
            # (the doubtful frames' time at the others' mean rate: the whole span's angle;
            # exactly 1 without doubtful frames)
            quality = round(self._quality_sum / trusted)
            scale = (end - start) / self._trusted_us if self._doubtful else 1.0
            # (a partly filled-in report is worth less: PX4 scales its flow noise by quality)
            quality = max(1, round(quality / scale))
        sum_u, sum_v = self._sum_u * scale, self._sum_v * scale
        interval = FlowInterval(start_us=start, end_us=end,
                                integrated_x=sum_u / f, integrated_y=sum_v / f,
                                sum_u_px=sum_u, sum_v_px=sum_v,
                                quality=int(quality), frame_count=self._frames)
        self._clear(self._last_us)
        return interval
