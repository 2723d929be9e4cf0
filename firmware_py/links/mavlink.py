"""MAVLink 2 link for ArduPilot (OPTICAL_FLOW, id 100) and PX4 (OPTICAL_FLOW_RAD, id 106).

Encoding and parsing use pymavlink's generated MAVLink 2 ``common`` dialect.

Per report (one integrated interval, see :mod:`firmware_py.angular`):

OPTICAL_FLOW (ArduPilot, FLOW_TYPE=5)
    ``flow_rate_x/y`` = integrated angle / integration time, rad/s (firmware with PR #30663);
    ``flow_x/y`` = 10 × Σu' / Σv' deci-pixels since the previous message, in the *same* axes
    (older ArduPilot reads only these, see the README), with the fractional remainder carried;
    ``flow_comp_m_x/y`` = 0 (ArduPilot ignores them); ``ground_distance`` = configured range
    or -1; ``time_usec`` = capture timestamp of the newest frame; ``quality``; ``sensor_id``.
OPTICAL_FLOW_RAD (PX4)
    ``integration_time_us`` = capture-timestamp span of the interval; ``integrated_x/y`` rad;
    gyro fields NaN (no IMU: PX4 integrates its own gyro over an interval of the same length,
    ending at the message's arrival);
    ``distance`` = configured range or -1; ``temperature`` 0; ``time_delta_distance_us`` 0.
HEARTBEAT
    ``MAV_TYPE_ONBOARD_CONTROLLER``, ``MAV_AUTOPILOT_INVALID``, ``MAV_STATE_ACTIVE``, once on
    every (re)open, then at ``heartbeat_rate_hz``, also while the camera is blind.

Incoming bytes are parsed without blocking (robust mode: garbage and bad CRCs are counted,
never raised); the first HEARTBEAT of each other system is logged with its type and id.
"""

from __future__ import annotations

import logging
import math

from pymavlink.dialects.v20 import common as mavlink2

from ..angular import FlowInterval
from ..clock import host_us
from .base import BUSY_FRACTION, FlowLink, LinkConfig, carry_round, choose_message_rate

__all__ = ["MavlinkLink", "new_encoder", "pack", "MESSAGE_SETS", "WIRE_BYTES",
           "HEARTBEAT_TYPE", "encode_heartbeat", "message_set_for"]

log = logging.getLogger(__name__)

#: Bytes on the wire with every field non-zero: 10 header + payload + 2 CRC (unsigned).
WIRE_BYTES = {"HEARTBEAT": 21, "OPTICAL_FLOW": 46, "OPTICAL_FLOW_RAD": 56, "NAMED_VALUE_FLOAT": 30}
#: Extra values budgeted when ``extra_values`` is on (expansion, time to contact, 2 balances).
EXTRA_VALUES_BUDGETED = 4
#: The extra values never take the flow below this many reports per second (nor below what
#: the budget gives the flow alone): the flow flies the vehicle, the extras are for watching.
EXTRAS_KEEP_FLOW_HZ = 10.0
#: Extra values thinned below this many rounds per second are left out altogether.
EXTRAS_MIN_RATE_HZ = 0.5

#: Flow messages per autopilot.
MESSAGE_SETS = {
    "ardupilot": ("OPTICAL_FLOW",),
    "px4": ("OPTICAL_FLOW_RAD",),
    "both": ("OPTICAL_FLOW", "OPTICAL_FLOW_RAD"),
}

#: PX4's sensors module (``VehicleOpticalFlow``, before its 2026 accumulator) adds up
#: OPTICAL_FLOW_RAD messages until their integration time reaches 1 / SENS_FLOW_RATE
#: (default 70 Hz) and publishes the *mean* quality: a good report merged with a quality-0
#: one would be fused with an angle that misses motion. So every report of these message
#: sets spans at least 1/70 s (frames are added until it does), and the default rate is
#: capped at 70 Hz: PX4 publishes each report on its own.
PX4_SENS_FLOW_RATE_HZ = 70.0
PX4_MIN_REPORT_SPAN_US = math.ceil(1e6 / PX4_SENS_FLOW_RATE_HZ)

#: ArduPilot's EKF3 stores an optical flow sample only 50 ms or more after the previous one
#: it took (``NavEKF3_core::writeOptFlowMeas``, ``sensorIntervalMin_ms``; a quality-0 one
#: counts), checked when its flow task (200 Hz on Copter and Rover) hands the message over:
#: of 100 reports a second it fuses one in five or six, each spanning 10 ms of frames. By
#: default (no ``message_rate_hz``) ``autopilot = "ardupilot"`` sends at most 17 a second,
#: each at least :data:`ARDUPILOT_MIN_REPORT_SPAN_US` of frames (whatever the frame rate:
#: the quarter frame's alignment tolerance alone let one frame of a 20 fps camera, 50 ms,
#: be a report; a set rate of 17 or less gets that minimum too, and 97 % of its period),
#: so that it comes 50 ms after the one before even when the task's 5 ms
#: step and some jitter fall against it: the EKF fuses each, averaging the frames of its
#: span (a little fewer a second than the ~19 it picked out of 100), and dates it closer to
#: its middle (it takes each to be 50 ms + EK3_FLOW_DELAY + half its time step old, the
#: middle of a PX4Flow's 100 ms).
ARDUPILOT_EKF3_RATE_HZ = 17.0
ARDUPILOT_MIN_REPORT_SPAN_US = 57_000

HEARTBEAT_TYPE = mavlink2.MAV_TYPE_ONBOARD_CONTROLLER  # 18: no MAV_TYPE for a flow sensor

_INT16_MAX = 32767


def message_set_for(config: LinkConfig) -> tuple[str, ...]:
    """The flow messages a config sends: its autopilot's set (a MAVLink config's autopilot
    is "ardupilot", "px4" or "both": :class:`LinkConfig` refuses "inav" with MAVLink)."""
    return MESSAGE_SETS[config.autopilot]


def new_encoder(*, sysid: int, compid: int) -> mavlink2.MAVLink:
    """A pymavlink MAVLink 2 encoder with its own sequence counter (no file attached)."""
    return mavlink2.MAVLink(None, srcSystem=int(sysid), srcComponent=int(compid))


def pack(encoder: mavlink2.MAVLink, message) -> bytes:
    """Frame ``message`` with the encoder's ids and sequence number, then advance it."""
    data = bytes(message.pack(encoder))
    encoder.seq = (encoder.seq + 1) % 256
    return data


def sequence_number(data: bytes) -> int:
    """The sequence number of a framed MAVLink 2 message (its header's fifth byte)."""
    return data[4]


#: NAMED_VALUE_FLOAT reports per second when ``extra_values`` is on.
EXTRAS_RATE_HZ = 5.0


def encode_heartbeat(encoder: mavlink2.MAVLink) -> bytes:
    """HEARTBEAT of a peripheral (``MAV_AUTOPILOT_INVALID``, state ACTIVE)."""
    return pack(encoder, encoder.heartbeat_encode(
        type=HEARTBEAT_TYPE, autopilot=mavlink2.MAV_AUTOPILOT_INVALID, base_mode=0, custom_mode=0,
        system_status=mavlink2.MAV_STATE_ACTIVE))


def _clamp_i16(value: int) -> int:
    return max(-_INT16_MAX, min(_INT16_MAX, int(value)))


class MavlinkLink(FlowLink):
    """MAVLink 2 flow sensor (see module docstring).

    Parameters
    ----------
    config : LinkConfig
        ``autopilot`` selects the message set.
    """

    protocol = "mavlink"

    def __init__(self, config: LinkConfig):
        self.message_set = message_set_for(config)
        self._for_px4 = "OPTICAL_FLOW_RAD" in self.message_set  # (PX4's span and rate rules)
        # PX4 merges shorter OPTICAL_FLOW_RAD reports (see PX4_SENS_FLOW_RATE_HZ); ArduPilot's
        # EKF3 drops a report less than 50 ms after the last (ARDUPILOT_EKF3_RATE_HZ): at the
        # default rate, or a set one as low, each report spans at least 57 ms and nearly its
        # period (the quarter-frame alignment tolerance let one 55.6 ms frame of an 18 fps
        # camera be a 15 Hz report, 40 ms after the last on Plane's 20 ms task step); a faster
        # set rate (older firmware's FLOW_FXSCALER range) spans what it gives
        rate = config.message_rate_hz
        if self._for_px4:
            self.min_report_span_us = PX4_MIN_REPORT_SPAN_US
        elif rate is None or rate <= ARDUPILOT_EKF3_RATE_HZ:
            self.min_report_span_us = max(float(ARDUPILOT_MIN_REPORT_SPAN_US), 0.97e6 / rate if rate else 0.0)
        else:
            self.min_report_span_us = 0.0
        self.encoder = new_encoder(sysid=config.sysid, compid=config.compid)
        self._rx = self._new_parser()
        self._dpix_carry = [0.0, 0.0]
        self._next_heartbeat_us: int | None = None
        self._heartbeat_period_us = int(1e6 / config.heartbeat_rate_hz)
        self._seen_systems: set[tuple[int, int]] = set()
        self._last_extras_us: int | None = None  # capture time of the last extra values sent
        self.extras_rate_hz = 0.0                  # chosen with the flow rate (_choose_rate)
        self._distance = (float(config.ground_distance_m)
                          if config.ground_distance_m is not None and config.ground_distance_m > 0 else -1.0)
        super().__init__(config)
        self.stats.update({"message_set": "+".join(self.message_set), "rx_messages": {},
                           "rx_garbage_bytes": 0, "rx_heartbeat": None})

    @staticmethod
    def _new_parser() -> mavlink2.MAVLink:
        parser = mavlink2.MAVLink(None)
        parser.robust_parsing = True  # bad CRCs / garbage come back as MAVLink_bad_data
        return parser

    # -- rate ------------------------------------------------------------------------
    @classmethod
    def line_need(cls, config: LinkConfig) -> tuple[str, int, float, str]:
        names = message_set_for(config)
        hz = config.heartbeat_rate_hz
        return ("+".join(names), sum(WIRE_BYTES[name] for name in names), WIRE_BYTES["HEARTBEAT"] * hz,
                f" and {hz:g} HEARTBEAT per second ({WIRE_BYTES['HEARTBEAT']} bytes; heartbeat_rate_hz)")

    def _reserved_bytes_per_s(self) -> float:
        extras = WIRE_BYTES["NAMED_VALUE_FLOAT"] * EXTRA_VALUES_BUDGETED * self.extras_rate_hz
        return super()._reserved_bytes_per_s() + extras

    def _default_rate_cap(self) -> float:
        return PX4_SENS_FLOW_RATE_HZ if self._for_px4 else ARDUPILOT_EKF3_RATE_HZ

    def _choose_extras_rate(self) -> float:
        """Extra-value rounds per second: :data:`EXTRAS_RATE_HZ` where the budget has room
        for them next to the flow, fewer (or none) where it has not.

        The flow keeps the configured ``message_rate_hz``, or without one the smaller of
        :data:`EXTRAS_KEEP_FLOW_HZ` and what the budget gives the flow alone; the extras get
        what is left of the 60 % budget. (Reserved first, at 9600 baud their 600 bytes/s
        would leave the flow nothing but the 7 Hz minimum, over the budget.)
        """
        cfg = self.config
        if not cfg.extra_values:
            return 0.0
        heartbeat = super()._reserved_bytes_per_s()
        size = self._bytes_per_report()
        if cfg.message_rate_hz is not None:
            flow_hz = min(float(cfg.message_rate_hz), self._rate_ceiling_hz())
        else:
            flow_hz = min(EXTRAS_KEEP_FLOW_HZ, choose_message_rate(
                baud=cfg.baud, bytes_per_message=size, cap_hz=self._default_rate_cap(),
                reserved_bytes_per_s=heartbeat))
        per_round = WIRE_BYTES["NAMED_VALUE_FLOAT"] * EXTRA_VALUES_BUDGETED
        left = cfg.baud / 10.0 * BUSY_FRACTION - heartbeat - flow_hz * size
        rate = min(EXTRAS_RATE_HZ, math.floor(10 * max(0.0, left) / per_round) / 10)  # 0.1 Hz steps
        if rate < EXTRAS_RATE_HZ:
            done = (f"sending them {rate:g} times per second instead of {EXTRAS_RATE_HZ:g}"
                    if rate >= EXTRAS_MIN_RATE_HZ else "not sending them")
            log.warning("%s on %s: extra_values: at %d baud the NAMED_VALUE_FLOATs (%d x %d bytes, %g per "
                        "second: %.0f bytes/s) do not fit next to %.0f flow messages/s in the %.0f bytes/s "
                        "budget; %s (the flow comes first); raise the baud rate or set extra_values = false",
                        self.protocol, cfg.port, cfg.baud, EXTRA_VALUES_BUDGETED,
                        WIRE_BYTES["NAMED_VALUE_FLOAT"], EXTRAS_RATE_HZ, per_round * EXTRAS_RATE_HZ, flow_hz,
                        cfg.baud / 10.0 * BUSY_FRACTION, done)
        return rate if rate >= EXTRAS_MIN_RATE_HZ else 0.0

    def _choose_rate(self) -> float:
        self.extras_rate_hz = self._choose_extras_rate()
        rate = super()._choose_rate()
        if self._for_px4 and rate > PX4_SENS_FLOW_RATE_HZ:
            log.warning("%s on %s: message_rate_hz %.0f: OPTICAL_FLOW_RAD reports span at least %.1f ms "
                        "(PX4 merges shorter ones up to 1/SENS_FLOW_RATE, default %.0f Hz, and averages "
                        "their qualities), so at most %.0f go out per second", self.protocol,
                        self.config.port, rate, PX4_MIN_REPORT_SPAN_US / 1e3, PX4_SENS_FLOW_RATE_HZ,
                        self._rate_ceiling_hz())
        return rate

    def _messages_per_report(self) -> int:
        return len(self.message_set)

    # -- output ----------------------------------------------------------------------
    def _reset_carry(self) -> None:
        self._dpix_carry = [0.0, 0.0]

    def _encode_flow(self, interval: FlowInterval) -> list[tuple[str, bytes, dict]]:
        cfg = self.config
        out = []
        time_usec = max(0, int(interval.end_us))
        quality = int(interval.quality)
        for name in self.message_set:
            if name == "OPTICAL_FLOW":
                flow_x, self._dpix_carry[0] = carry_round(10.0 * interval.sum_u_px, self._dpix_carry[0])
                flow_y, self._dpix_carry[1] = carry_round(10.0 * interval.sum_v_px, self._dpix_carry[1])
                flow_x, flow_y = _clamp_i16(flow_x), _clamp_i16(flow_y)
                msg = self.encoder.optical_flow_encode(
                    time_usec=time_usec, sensor_id=cfg.sensor_id, flow_x=flow_x, flow_y=flow_y,
                    flow_comp_m_x=0.0, flow_comp_m_y=0.0, quality=quality,
                    ground_distance=self._distance, flow_rate_x=interval.rate_x, flow_rate_y=interval.rate_y)
                log_fields = {"time_usec": time_usec, "flow_x": flow_x, "flow_y": flow_y,
                              "flow_rate_x": interval.rate_x, "flow_rate_y": interval.rate_y,
                              "quality": quality, "distance": self._distance, "sensor_id": cfg.sensor_id,
                              "integration_time_us": interval.integration_time_us}
            else:
                msg = self.encoder.optical_flow_rad_encode(
                    time_usec=time_usec, sensor_id=cfg.sensor_id,
                    integration_time_us=max(0, int(interval.integration_time_us)),
                    integrated_x=interval.integrated_x, integrated_y=interval.integrated_y,
                    integrated_xgyro=math.nan, integrated_ygyro=math.nan, integrated_zgyro=math.nan,
                    temperature=0, quality=quality, time_delta_distance_us=0, distance=self._distance)
                log_fields = {"time_usec": time_usec, "integration_time_us": interval.integration_time_us,
                              "integrated_x": interval.integrated_x, "integrated_y": interval.integrated_y,
                              "quality": quality, "distance": self._distance, "sensor_id": cfg.sensor_id}
            data = pack(self.encoder, msg)
            log_fields["seq"] = sequence_number(data)
            out.append((name, data, log_fields))
        return out

    def _send_extras(self, sample) -> None:
        """NAMED_VALUE_FLOAT per extra value at EXTRAS_RATE_HZ (capture clock), off by default;
        called after the frame's flow message was queued, so they never delay it.

        No standard MAVLink field carries expansion or time to contact; NAMED_VALUE_FLOAT
        shows up in MAVProxy, QGroundControl's inspector and the autopilot's log (ArduPilot
        logs it as NVF; Lua scripts can read it).
        """
        if not self.extras_rate_hz:
            return  # no room for them at this baud rate (warned in _choose_extras_rate)
        ts = int(sample.timestamp_us)
        last = self._last_extras_us
        # A capture clock that went back (a reopened OAK restarts near 0) starts the schedule
        # afresh; measured from the old time, the next round would wait for the old uptime.
        if last is not None and last <= ts < last + 1e6 / self.extras_rate_hz:
            return
        self._last_extras_us = ts
        now = host_us()
        for name, value in sample.extras:
            label, value = str(name)[:10], float(value)  # (the field holds 10 characters)
            data = pack(self.encoder, self.encoder.named_value_float_encode(
                time_boot_ms=(ts // 1000) & 0xFFFFFFFF, name=label.encode(), value=value))
            # (name and value have their own log columns: the rows were blank before)
            self._enqueue_other("NAMED_VALUE_FLOAT", data,
                                {"seq": sequence_number(data), "name": label, "value": value}, now)

    def _send_heartbeat(self, now: int, *, first: bool = False) -> None:
        data = encode_heartbeat(self.encoder)
        self._enqueue_other("HEARTBEAT", data, {"seq": sequence_number(data)}, now, first=first)

    def _on_open(self, now: int) -> None:
        # A fresh parser: bytes from the previous connection must not glue onto new ones.
        self._rx = self._new_parser()
        self._send_heartbeat(now, first=True)  # before any flow queued while the port was away
        self._next_heartbeat_us = now + self._heartbeat_period_us

    def _periodic(self, now: int) -> None:
        if not self.transport.is_open:
            return
        if self._next_heartbeat_us is None:
            self._next_heartbeat_us = now
        if now >= self._next_heartbeat_us:
            self._send_heartbeat(now)
            self._next_heartbeat_us += self._heartbeat_period_us
            if self._next_heartbeat_us <= now:  # after a stall: no burst of catch-up heartbeats
                self._next_heartbeat_us = now + self._heartbeat_period_us

    # -- input -----------------------------------------------------------------------
    def _handle_rx(self, data: bytes, now: int) -> None:
        try:
            messages = self._rx.parse_buffer(data) or []
        except Exception as exc:  # noqa: BLE001 - pymavlink raises on some malformed input
            self.stats["rx_garbage_bytes"] += len(data)
            log.debug("MAVLink from %s: parser error %s; parser reset", self.config.port, exc)
            self._rx = self._new_parser()
            return
        rx = self.stats["rx_messages"]
        for msg in messages:
            name = msg.get_type()
            if name == "BAD_DATA":
                self.stats["rx_garbage_bytes"] += len(msg.get_msgbuf() or b"")
                continue
            rx[name] = rx.get(name, 0) + 1
            if name == "HEARTBEAT":
                self._note_heartbeat(msg)

    def _note_heartbeat(self, msg) -> None:
        key = (msg.get_srcSystem(), msg.get_srcComponent())
        if key == (self.config.sysid, self.config.compid):
            return  # our own heartbeat looped back
        info = {"sysid": key[0], "compid": key[1], "type": int(msg.type), "autopilot": int(msg.autopilot),
                "system_status": int(msg.system_status)}
        if msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID or self.stats["rx_heartbeat"] is None:
            self.stats["rx_heartbeat"] = info
        if key not in self._seen_systems:
            self._seen_systems.add(key)
            type_name = mavlink2.enums["MAV_TYPE"].get(int(msg.type))
            ap_name = mavlink2.enums["MAV_AUTOPILOT"].get(int(msg.autopilot))
            log.info("MAVLink on %s: HEARTBEAT from system %d component %d: %s, %s", self.config.port,
                     key[0], key[1], type_name.name if type_name else msg.type,
                     ap_name.name if ap_name else msg.autopilot)
