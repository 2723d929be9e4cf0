"""MSP v2 link: MSP2_SENSOR_OPTIC_FLOW (0x1F02) for INAV (opflow_hardware = MSP). Not
ArduPilot (see :data:`firmware_py.links.base.MSP_ARDUPILOT`), nor Betaflight (its MSP flow
reading needs an MT rangefinder on the link and scales the counts its own way).

Frame: ``$`` ``X`` ``<``, flags u8 (0), function u16 LE, payload size u16 LE, payload,
CRC8/DVB-S2 (poly 0xD5, init 0) over flags … payload. Payload (9 bytes): quality u8,
motionX i32 LE, motionY i32 LE — counts accumulated since the previous message.

Sign and scale (derived from INAV ``src/main/io/opflow_msp.c``, ``src/main/sensors/opflow.c``,
``src/main/sensors/boardalignment.c``, ``src/main/navigation/navigation_pos_estimator_flow.c``;
worked example in the README, INAV section)::

    motionX = -opflow_scale × degrees(integrated_x)
    motionY = -opflow_scale × degrees(integrated_y)

with ``integrated_x/y`` the MAVLink-convention angles of :mod:`firmware_py.angular` and
``opflow_scale`` = :attr:`LinkConfig.msp_counts_per_degree` (INAV default 10.5). INAV turns
counts into deg/s with ``motion × 1e6 / Δt_us / opflow_scale``, applies the default
``opflow_align = CW0_DEG_FLIP`` (x negated) and works in a body frame with X forward, Y left,
Z up; both signs come out negative. Counts are integers: the fractional remainder is carried from message
to message.
"""

from __future__ import annotations

import math
import struct

from ..angular import FlowInterval
from .base import FlowLink, LinkConfig, carry_round
from .pacing import ReportPacer

__all__ = ["MspLink", "MSP2_SENSOR_OPTIC_FLOW", "crc8_dvb_s2", "encode_msp_v2", "encode_optic_flow",
           "WIRE_BYTES"]

MSP2_SENSOR_OPTIC_FLOW = 0x1F02
#: Bytes of one MSP2_SENSOR_OPTIC_FLOW frame on the wire.
WIRE_BYTES = 8 + 9 + 1
_INT32_MAX = 2**31 - 1


def crc8_dvb_s2(data: bytes, crc: int = 0) -> int:
    """CRC-8/DVB-S2 (polynomial 0xD5, initial value ``crc``), as MSP v2 uses it."""
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0xD5) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def encode_msp_v2(function: int, payload: bytes, *, direction: bytes = b"<", flags: int = 0) -> bytes:
    """Frame an MSP v2 message.

    Parameters
    ----------
    function : int
        MSP v2 function id (u16).
    payload : bytes
        Message payload.
    direction : bytes
        ``b"<"`` to the flight controller (what sensors send), ``b">"`` a reply.
    flags : int
        Flags byte (0).
    """
    header = struct.pack("<BHH", flags, function, len(payload))
    body = header + bytes(payload)
    return b"$X" + direction + body + bytes([crc8_dvb_s2(body)])


def encode_optic_flow(*, quality: int, motion_x: int, motion_y: int) -> bytes:
    """MSP2_SENSOR_OPTIC_FLOW frame: quality 0..255, motion counts (i32)."""
    payload = struct.pack("<Bii", max(0, min(255, int(quality))), int(motion_x), int(motion_y))
    return encode_msp_v2(MSP2_SENSOR_OPTIC_FLOW, payload)


def _clamp_i32(value: int) -> int:
    return max(-_INT32_MAX, min(_INT32_MAX, int(value)))


class MspLink(FlowLink):
    """MSP v2 optical-flow sensor (see module docstring).

    Parameters
    ----------
    config : LinkConfig
        ``msp_counts_per_degree`` must match INAV's ``opflow_scale``.
    """

    protocol = "msp"
    #: INAV declares the sensor unhealthy after 0.2 s without a message.
    autopilot_timeout_s = 0.2
    blind_after_s = 0.15

    def __init__(self, config: LinkConfig):
        self._carry = [0.0, 0.0]
        self._counts_per_rad = config.msp_counts_per_degree * 180.0 / math.pi
        delay_ms = config.msp_report_delay_ms
        #: each report on the capture clock: INAV divides its counts by the time since the
        #: previous one arrived (module docstring of :mod:`firmware_py.links.pacing`)
        self.pacer = ReportPacer(None if delay_ms is None else int(round(delay_ms * 1000)))
        super().__init__(config)
        self.stats["report_delay_ms"] = 0.0
        self.stats["late_reports"] = 0

    @property
    def paces_reports(self) -> bool:
        return self.pacer.fixed_us != 0

    def _send_at(self, capture_host_us: int | None, capture_us: int, now: int) -> int | None:
        was_real_time = self.pacer.real_time
        due = self.pacer.send_at(capture_host_us, capture_us, now)
        if was_real_time and not self.pacer.real_time:
            self.transport.release_held()  # (no capture clock to keep to: what waits goes now)
        self.stats["report_delay_ms"] = self.pacer.delay_us / 1000.0 if self.pacer.real_time else 0.0
        self.stats["late_reports"] = self.pacer.late
        return due

    def _on_sent(self, message, host_us: int, latency_us: int | None) -> None:
        if message.written_after_due_us is not None:
            self.pacer.written(message.written_after_due_us)
            self.stats["late_reports"] = self.pacer.late
        super()._on_sent(message, host_us, latency_us)

    @classmethod
    def line_need(cls, config: LinkConfig) -> tuple[str, int, float, str]:
        return "MSP2_SENSOR_OPTIC_FLOW", WIRE_BYTES, 0.0, ""

    def _default_rate_cap(self) -> float:
        return 50.0

    def _reset_carry(self) -> None:
        self._carry = [0.0, 0.0]

    def motion_counts(self, interval: FlowInterval) -> tuple[int, int]:
        """Counts for one interval, remainder carried (also used by the message log)."""
        mx, self._carry[0] = carry_round(-self._counts_per_rad * interval.integrated_x, self._carry[0])
        my, self._carry[1] = carry_round(-self._counts_per_rad * interval.integrated_y, self._carry[1])
        return _clamp_i32(mx), _clamp_i32(my)

    def _encode_flow(self, interval: FlowInterval) -> list[tuple[str, bytes, dict]]:
        mx, my = self.motion_counts(interval)
        data = encode_optic_flow(quality=interval.quality, motion_x=mx, motion_y=my)
        fields = {"time_usec": int(interval.end_us), "integration_time_us": interval.integration_time_us,
                  "integrated_x": interval.integrated_x, "integrated_y": interval.integrated_y,
                  "motion_x": mx, "motion_y": my, "quality": int(interval.quality)}
        return [("MSP2_SENSOR_OPTIC_FLOW", data, fields)]

    def _handle_rx(self, data: bytes, now: int) -> None:
        # A flight controller does not answer sensor messages; whatever arrives is counted
        # (stats["rx_bytes"]) and dropped.
        return
