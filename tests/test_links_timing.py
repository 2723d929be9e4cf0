"""Link timing as each autopilot sees it: blindness judged on host time, slow but steady
streams, where the autopilot's interval starts (integration restarts, keep-alives), and the
order of the extra values.

A simulated host clock drives ``submit(sample, now_host_us)`` and ``service(now)`` over a
real pty. The autopilot's end reads after every call, so each message is timed by the host
time at which it was written, and decodes it with pymavlink (ArduPilot, PX4) or an
independent MSP v2 decoder (INAV), then derives the flow rate the way that autopilot does:
ArduPilot from ``flow_rate_x/y``, PX4 from ``integrated_x/y / integration_time_us``, INAV from
``motion × 1e6 / Δt_us / opflow_scale`` with Δt the time since the *previous message*.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import parse_msp_v2  # noqa: E402
from ptyutil import PtyPeer, host_us  # noqa: E402

from firmware_py.links import FlowSample, LinkConfig, open_link  # noqa: E402
from firmware_py.links.mavlink import ARDUPILOT_MIN_REPORT_SPAN_US  # noqa: E402

F = 100.0            # focal length, px
STEP_US = 10_000     # the daemon services the link every 10 ms
OPFLOW_SCALE = 10.5  # INAV's default, the link's default msp_counts_per_degree
TIMEOUT_US = {"ardupilot": 500_000, "px4": 500_000, "inav": 200_000}


@pytest.fixture
def peer(tmp_path):
    p = PtyPeer(tmp_path / "ttyFC")
    yield p
    p.close()


class FlightController:
    """The autopilot's end of the pty: every flow message with its arrival time (µs), its
    quality, whether the autopilot uses it, and the rate it derives (rad/s, MAVLink axes)."""

    def __init__(self, peer: PtyPeer, autopilot: str):
        self.peer, self.autopilot = peer, autopilot
        self.parser = mavlink2.MAVLink(None)
        self.messages: list[dict] = []
        self.wire: list[tuple[int, object]] = []   # (arrival, message) of every MAVLink message
        self._last_arrival: int | None = None

    def poll(self, now_us: int) -> None:
        data = self.peer.read()
        if self.autopilot == "inav":
            for function, payload in parse_msp_v2(data):
                if function != 0x1F02:
                    continue
                quality = payload[0]
                motion = (int.from_bytes(payload[1:5], "little", signed=True),
                          int.from_bytes(payload[5:9], "little", signed=True))
                dt = None if self._last_arrival is None else now_us - self._last_arrival
                self._last_arrival = now_us
                # INAV: deg/s = motion × 1e6 / Δt / opflow_scale; motion = -scale × degrees(angle)
                rate = None if not dt else tuple(-math.radians(m * 1e6 / dt / OPFLOW_SCALE) for m in motion)
                self.messages.append({"at": now_us, "quality": quality, "rate": rate,
                                      "used": quality * 100 // 255 >= 35 and rate is not None})
            return
        for m in self.parser.parse_buffer(data) or []:
            self.wire.append((now_us, m))
            name = m.get_type()
            if name == "OPTICAL_FLOW" and self.autopilot == "ardupilot":
                self.messages.append({"at": now_us, "quality": m.quality, "used": m.quality > 0,
                                      "rate": (m.flow_rate_x, m.flow_rate_y), "time_usec": m.time_usec})
            elif name == "OPTICAL_FLOW_RAD" and self.autopilot == "px4":
                dt = m.integration_time_us / 1e6
                rate = (m.integrated_x / dt, m.integrated_y / dt) if dt > 0 else None
                self.messages.append({"at": now_us, "quality": m.quality,
                                      "used": m.quality > 0 and rate is not None, "rate": rate,
                                      "integration_time_us": m.integration_time_us, "time_usec": m.time_usec,
                                      "integrated": (m.integrated_x, m.integrated_y)})

    def ekf3_fused(self, task_hz: float = 200.0, phase_us: int = 1_234) -> list[dict]:
        """The good OPTICAL_FLOW messages ArduPilot's EKF3 stores: AP_OpticalFlow's task
        (``task_hz``, Copter's 200 Hz) hands a message over at its first run after the
        arrival, and ``NavEKF3_core::writeOptFlowMeas`` drops a sample less than 50 ms
        (``sensorIntervalMin_ms``, whole ms of IMU time) after the last one it took, a
        quality-0 one included (it counts before the quality is looked at)."""
        period = 1e6 / task_hz
        fused, last_ms = [], None
        for m in self.messages:
            run_ms = int((phase_us + math.ceil((m["at"] - phase_us) / period) * period) // 1000)
            if last_ms is not None and run_ms - last_ms < 50:
                continue
            last_ms = run_ms
            if m["quality"] > 0:
                fused.append(m)
        return fused

    def px4_published(self, sens_flow_rate_hz: float = 70.0) -> list[dict]:
        """What PX4's sensors module (``VehicleOpticalFlow``) makes of the OPTICAL_FLOW_RAD
        messages: it adds messages up until their integration time reaches
        1 / SENS_FLOW_RATE, publishes the sums with the *mean* quality, and starts afresh
        after a gap of 2 × a message's integration time, or when a good message follows
        only quality-0 ones (timestamps: the arrival times, as PX4's MAVLink receiver sets
        them). EKF2 fuses a published sample of quality ≥ EKF2_OF_QMIN (default 1)."""
        published, acc, last = [], None, None
        for m in self.messages:
            span = m["integration_time_us"]
            if acc is not None and (m["at"] >= last + 2 * span or (m["quality"] > 0 and acc["qsum"] == 0)):
                acc = None
            last = m["at"]
            if acc is None:
                acc = {"x": 0.0, "y": 0.0, "span": 0, "qsum": 0, "n": 0}
            acc["x"] += m["integrated"][0]
            acc["y"] += m["integrated"][1]
            acc["span"] += span
            acc["qsum"] += m["quality"]
            acc["n"] += 1
            if acc["span"] >= 1e6 / sens_flow_rate_hz:
                quality = acc["qsum"] // acc["n"]
                dt = acc["span"] / 1e6
                published.append({"at": m["at"], "quality": quality, "used": quality >= 1 and dt > 0,
                                  "rate": (acc["x"] / dt, acc["y"] / dt) if dt > 0 else None,
                                  "messages": acc["n"]})
                acc = None
        return published

    def used(self) -> list[dict]:
        return [m for m in self.messages if m["used"]]

    def largest_gap_us(self, after_us: int) -> int:
        times = [m["at"] for m in self.messages if m["at"] >= after_us]
        return max(b - a for a, b in zip(times, times[1:]))


def held_us(link, engine_us):
    """How long after its frame's submit a report reaches the autopilot when the frames take
    ``engine_us`` to process: 0, or for MSP, whose reports go out on the capture clock, what
    the pacer's delay after capture leaves (``firmware_py.links.pacing``)."""
    pacer = getattr(link, "pacer", None)
    return 0 if pacer is None else max(0, pacer.delay_us - engine_us)


def make_link(peer, autopilot, **kw):
    return open_link(LinkConfig(port=peer.path, baud=921600, autopilot=autopilot, focal_length_px=F, **kw))


def drive(link, fc, frames, *, start_us, end_us, stall=None):
    """Run the host clock from ``start_us`` to ``end_us`` in 10 ms steps (the frame loop's
    ``service()`` calls); each frame ``(submit_host_us, sample)`` is submitted at its host
    time (to the µs), and, as the daemon's report writer thread does, ``send_due()`` runs
    when a report held for its send time is due (:meth:`FlowLink.wake_in_s`), whatever the
    loop is doing. ``stall``: ``(from_us, to_us)`` host times strictly between which
    ``service()`` is not called (the frame loop is stuck in the engine)."""
    pending = sorted(frames, key=lambda item: item[0])
    t = start_us
    while t <= end_us:
        while pending and pending[0][0] <= t:
            at, sample = pending.pop(0)
            link.submit(sample, now_host_us=at)
            fc.poll(at)
        if (t - start_us) % STEP_US == 0 and (stall is None or not stall[0] < t < stall[1]):
            link.service(t)
        link.send_due(t)
        fc.poll(t)
        step = start_us + ((t - start_us) // STEP_US + 1) * STEP_US
        if pending:
            step = min(step, max(t + 1, pending[0][0]))
        wake = link.wake_in_s(t)
        if wake is not None:
            step = min(step, t + max(1, round(wake * 1e6)))
        t = step


def stream(start_us, intervals_us, *, engine_us, flow_px_per_s=(0.0, 0.0), quality=200):
    """Processed frames captured after the given intervals (the capture clock is the host
    clock here), each submitted ``engine_us`` after its capture: ``[(submit_host_us, sample)]``.
    The flow of a frame is the motion since the previous one."""
    frames, t = [], start_us
    for i, dt in enumerate([0, *intervals_us]):
        t += dt
        u, v = (c * dt / 1e6 for c in flow_px_per_s)
        frames.append((t + engine_us, FlowSample(timestamp_us=t, capture_host_us=t, flow_x=u, flow_y=v,
                                                 quality=quality if i else 0)))
    return frames


# The true flow of the tests: 12 px/s down the image = 0.12 rad/s about Y at f = 100 px.
FLOW = (0.0, 12.0)
TRUE_RATE = (0.0, 12.0 / F)


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4", "inav"])
@pytest.mark.parametrize("interval_us, engine_us", [
    (333_333, 300_000),   # 30 fps camera, every 10th frame processed, 0.3 s engine (numpy at 640x480)
    (400_000, 5_000),     # a 2.5 fps camera, fast engine
    (120_000, 5_000),     # an 8 fps camera: slower than blind_after_s for MSP, faster than INAV's timeout
])
def test_slow_but_steady_stream_gets_its_real_flow_through(peer, caplog, autopilot, interval_us, engine_us):
    """Frames further apart than blind_after_s (judged on host time since the last submit,
    not on their capture time) are reported with their real flow and quality; a keep-alive
    goes out only once the next frame is overdue, before the autopilot's timeout where the
    frame interval allows it; a frame interval beyond the timeout is logged once."""
    caplog.set_level(logging.WARNING)
    link = make_link(peer, autopilot)
    fc = FlightController(peer, autopilot)
    start = host_us()
    count = 15
    frames = stream(start, [interval_us] * (count - 1), engine_us=engine_us, flow_px_per_s=FLOW)
    last_submit = frames[-1][0]
    try:
        drive(link, fc, frames, start_us=start, end_us=last_submit + 1_000_000)
    finally:
        link.close()
    used = fc.used()
    # All but the first two: the start marker, and the first interval (the stream's spacing is
    # not known yet, so a keep-alive may come before its second frame).
    assert len(used) >= count - 2, [m["quality"] for m in fc.messages]
    quantum = math.radians(1 / OPFLOW_SCALE) * 1e6 / interval_us if autopilot == "inav" else 1e-6
    for m in used:
        assert m["rate"][0] == pytest.approx(TRUE_RATE[0], abs=quantum)
        assert m["rate"][1] == pytest.approx(TRUE_RATE[1], rel=0.01, abs=quantum)
        if autopilot == "px4":
            assert m["integration_time_us"] == interval_us
    assert link.stats["integration_restarts"] == 0
    # Once frames stop, the keep-alive starts before the autopilot times out, whenever the
    # frame interval itself leaves room for that.
    after_stop = [m for m in fc.messages if m["at"] > last_submit + held_us(link, engine_us)]
    assert after_stop and all(m["quality"] == 0 for m in after_stop)
    timeout = TIMEOUT_US[autopilot]
    warned = [r for r in caplog.records if "processed frames arrive every" in r.getMessage()]
    if interval_us < timeout:
        assert fc.largest_gap_us(after_us=frames[2][0]) < timeout
        assert not warned
    else:
        assert after_stop[0]["at"] - last_submit <= 1.25 * interval_us + STEP_US
        assert len(warned) == 1 and "0.20 s timeout" in warned[0].getMessage()


def test_blindness_counts_from_the_submit_not_from_the_capture(peer):
    """A 100 fps camera whose frames each reach the link 0.3 s after capture (engine
    latency) is not blind: no keep-alive, every report good."""
    link = make_link(peer, "px4", message_rate_hz=50)
    fc = FlightController(peer, "px4")
    start = host_us()
    frames = stream(start, [10_000] * 99, engine_us=300_000, flow_px_per_s=FLOW)
    try:
        drive(link, fc, frames, start_us=frames[0][0], end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    assert link.stats["blind_reports"] == 0
    assert len(fc.used()) == 49 and len(fc.messages) == 50  # 50 Hz after the start marker


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4", "inav"])
def test_restart_starts_the_autopilots_interval_at_once(peer, autopilot):
    """After a stall (integration restarts) and after a blind period (keep-alives), the
    first good report must not be divided by more time than its counts cover: a quality-0
    report goes out at the restart frame itself."""
    link = make_link(peer, autopilot, message_rate_hz=50)
    fc = FlightController(peer, autopilot)
    start = host_us()
    # 100 fps; a 120 ms stall (shorter than the keep-alive delay), then a 400 ms blind period.
    intervals = [10_000] * 30 + [120_000] + [10_000] * 30 + [400_000] + [10_000] * 30
    # 1 rad/s: 11.5 MSP counts per 20 ms message, so one count is < 10 % of a rate
    frames = stream(start, intervals, engine_us=3_000, flow_px_per_s=(0.0, 100.0))
    try:
        drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    used = fc.used()
    assert len(used) >= 40
    quantum = math.radians(1 / OPFLOW_SCALE) * 1e6 / 20_000 if autopilot == "inav" else 1e-6
    for m in used:  # every report the autopilot uses has the true rate, the first after a restart too
        assert m["rate"][1] == pytest.approx(1.0, rel=1e-4, abs=quantum)
    # The marker: quality 0, sent when the restart frame was submitted.
    restart_submits = [frames[31][0], frames[62][0]]
    for at in restart_submits:
        marker = [m for m in fc.messages if m["at"] == at + held_us(link, 3_000)]
        assert len(marker) == 1 and marker[0]["quality"] == 0
        if "time_usec" in marker[0]:
            assert marker[0]["time_usec"] == at - 3_000     # the restart frame's capture time
    if autopilot == "px4":
        after = [m for m in fc.messages if m["at"] > restart_submits[1]]
        assert after[0]["quality"] > 0 and after[0]["integration_time_us"] == 20_000
    assert link.stats["integration_restarts"] == 2 and link.stats["blind_reports"] >= 2


@pytest.mark.parametrize("autopilot", ["px4", "inav"])
def test_keepalive_before_a_late_frame_keeps_the_interval_but_not_its_quality(peer, autopilot):
    """A slow stream (0.3 s) whose frame comes late (0.42 s, past the keep-alive delay but
    not a gap): the keep-alive does not discard the pending interval, and the report that
    closes it goes out with quality 0 — the autopilot's interval began at the keep-alive."""
    link = make_link(peer, autopilot)
    fc = FlightController(peer, autopilot)
    start = host_us()
    intervals = [300_000] * 8 + [420_000] + [300_000] * 5
    frames = stream(start, intervals, engine_us=5_000, flow_px_per_s=FLOW)
    try:
        drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    late_submit, held = frames[9][0], held_us(link, 5_000)
    keepalives = [m for m in fc.messages if frames[8][0] + held < m["at"] < late_submit]
    assert len(keepalives) == 1 and keepalives[0]["quality"] == 0
    late = [m for m in fc.messages if m["at"] == late_submit + held]
    assert len(late) == 1 and late[0]["quality"] == 0 and not late[0]["used"]
    if autopilot == "px4":
        assert late[0]["integration_time_us"] == 420_000   # the frames' interval, not discarded
    assert link.stats["integration_restarts"] == 0
    after = [m for m in fc.messages if m["at"] > late_submit + held]
    assert len(after) == 5 and all(m["used"] for m in after)
    quantum = math.radians(1 / OPFLOW_SCALE) * 1e6 / 300_000 if autopilot == "inav" else 1e-6
    for m in fc.used():
        assert m["rate"][1] == pytest.approx(TRUE_RATE[1], rel=0.01, abs=quantum)


def _processed_in_turn(start_us, count, engine_us, *, interval_us=10_000, flow_px_per_s=(0.0, 0.0)):
    """Frames captured every ``interval_us`` and processed one after the other, frame i taking
    ``engine_us[i]`` (a frame waits while the one before is still processed): ``[(submit_host_us,
    sample)]`` as :func:`stream` gives them."""
    frames, done = [], start_us
    for i in range(count):
        t = start_us + i * interval_us
        done = max(done, t) + int(engine_us[i])
        u, v = (c * interval_us / 1e6 for c in flow_px_per_s)
        frames.append((done, FlowSample(timestamp_us=t, capture_host_us=t, flow_x=u if i else 0.0,
                                        flow_y=v if i else 0.0, quality=200 if i else 0)))
    return frames


@pytest.mark.parametrize("delay_ms", [0.0, None, 12.0], ids=["as-processed", "automatic", "fixed-12ms"])
def test_inav_reads_the_true_rate_however_long_each_frame_takes(peer, delay_ms):
    """INAV divides a report's counts by the time since the previous report *arrived*. Sent
    as soon as its frame is processed (``msp_report_delay_ms = 0``, all reports before), a
    report arrives as much later as its frame took longer: processing times of 2-8 ms (every
    100th frame 11 ms) moved the arrivals of 50 Hz reports by up to 6 ms, and INAV read rates
    off by up to 30 %. Paced on the capture clock (automatic delay, the default, or a fixed
    one) they arrive exactly as far apart as their frames were captured, and INAV reads the
    true rate in every report but the few of the automatic delay's start (which follows the
    slowest processing seen)."""
    import numpy as np

    rng = np.random.default_rng(5)
    engine_us = rng.uniform(2_000, 8_000, 1_000)
    engine_us[50::100] = 11_000
    link = make_link(peer, "inav", message_rate_hz=50, msp_report_delay_ms=delay_ms)
    fc = FlightController(peer, "inav")
    flow = (0.0, 500.0)  # 5 rad/s at f = 100 px: 60 counts a report, so one count is 1.7 %
    frames = _processed_in_turn(host_us(), len(engine_us), engine_us, flow_px_per_s=flow)
    try:
        drive(link, fc, frames, start_us=frames[0][0], end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    used = fc.used()
    assert len(used) >= 490
    gaps = [b["at"] - a["at"] for a, b in zip(fc.messages, fc.messages[1:])]
    exact = sum(gap == 20_000 for gap in gaps) / len(gaps)
    off = [abs(m["rate"][1] / 5.0 - 1) for m in used]
    if delay_ms == 0:
        assert exact < 0.1 and sum(e > 0.1 for e in off) > 0.3 * len(off)
        assert link.stats["report_delay_ms"] == 0 and link.stats["late_reports"] == 0
        return
    assert exact > (0.97 if delay_ms is None else 0.999), gaps[:40]
    assert sum(e <= inav_quantum(20_000) / 5.0 + 1e-9 for e in off) > (0.97 if delay_ms is None else 0.999) * len(off)
    if delay_ms is None:
        # (just above the slowest frames' processing, not at the ceiling)
        assert 11.0 < link.stats["report_delay_ms"] <= 13.0
        assert link.stats["late_reports"] <= 10
    else:
        assert link.stats["report_delay_ms"] == 12.0 and link.stats["late_reports"] == 0


def test_extra_values_follow_their_frames_flow_message(peer):
    """NAMED_VALUE_FLOATs are queued after the frame's OPTICAL_FLOW: at 115200 baud four of
    them would delay it by ~10 ms. (A report every frame, so that every extras round has
    its frame's flow message to follow: by default ArduPilot's are 17 a second.)"""
    link = make_link(peer, "ardupilot", extra_values=True, message_rate_hz=100.0)
    fc = FlightController(peer, "ardupilot")
    extras = (("expansion", 0.1), ("ttc_s", -1.0), ("balanceLR", 0.0), ("balanceTB", 0.0))
    start = host_us()
    frames = [(at, FlowSample(timestamp_us=s.timestamp_us, capture_host_us=s.capture_host_us, flow_x=s.flow_x,
                              flow_y=s.flow_y, quality=200, extras=extras))
              for at, s in stream(start, [10_000] * 60, engine_us=3_000, flow_px_per_s=FLOW)]
    try:
        drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    named = 0
    last_flow_ms = None
    for _, m in fc.wire:  # wire order
        if m.get_type() == "OPTICAL_FLOW":
            last_flow_ms = m.time_usec // 1000
        elif m.get_type() == "NAMED_VALUE_FLOAT":
            named += 1
            assert last_flow_ms == m.time_boot_ms, "a frame's extras went out before its flow message"
    assert named >= 4 * 2


def _px4_flight(peer, intervals, **kw):
    """Fly ``intervals`` (µs) at 1 rad/s to a PX4 link, then go blind for 1 s; PX4's view."""
    link = make_link(peer, "px4", **kw)
    fc = FlightController(peer, "px4")
    start = host_us()
    frames = stream(start, intervals, engine_us=3_000, flow_px_per_s=(0.0, 100.0))
    try:
        drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + 1_000_000)
    finally:
        link.close()
    return link, fc


PX4_FLIGHTS = {
    # 100 fps with a stall and a blind period; at 100 Hz the blind period's first keep-alive
    # met a pending good report (an odd count of reports before it) and PX4 fused 0.077 and
    # 0.032 rad/s at quality 100
    "100fps": [10_000] * 29 + [120_000] + [10_000] * 29 + [400_000] + [10_000] * 30,
    "75fps": [13_333] * 41,
    # 30 fps with one early frame (a report at 0.75 of a frame would span < 1/70 s) ...
    "30fps-early-frame": [33_333] * 20 + [12_500] + [33_333] * 3,
    # ... and a camera that speeds up from 30 to 80 fps
    "30-to-80fps": [33_333] * 20 + [12_500] * 7,
}


@pytest.mark.parametrize("flight", list(PX4_FLIGHTS))
@pytest.mark.parametrize("rate", [None, 100.0])
def test_px4_never_fuses_a_quality0_report_merged_with_a_good_one(peer, flight, rate):
    """PX4 merges OPTICAL_FLOW_RAD messages whose integration time is below
    1/SENS_FLOW_RATE (default 70 Hz) and publishes the mean of their qualities: a good
    report merged with a quality-0 one (a keep-alive, the report that closes a blind frame's
    interval) would be fused with an angle that misses motion. Every good report spans at
    least 1/70 s, at any frame rate and any message_rate_hz, so PX4 fuses only true rates."""
    kw = {} if rate is None else {"message_rate_hz": rate}
    link, fc = _px4_flight(peer, PX4_FLIGHTS[flight], **kw)
    assert link.message_rate_hz == (70 if rate is None else rate)
    assert all(m["integration_time_us"] >= 1e6 / 70 for m in fc.messages if m["quality"] > 0)
    published = fc.px4_published()
    fused = [m for m in published if m["used"]]
    assert len(fused) >= 8
    for m in fused:
        assert m["rate"][1] == pytest.approx(1.0, rel=1e-4), m
    assert published[-1]["quality"] == 0   # the blind second reached PX4 as such


def test_the_px4_model_catches_merged_quality0_reports(peer, monkeypatch):
    """The control: without the minimum span, 100 Hz reports are merged by PX4 and the
    model sees good reports fused with the blind period's first quality-0 one."""
    from firmware_py.links import mavlink

    monkeypatch.setattr(mavlink, "PX4_MIN_REPORT_SPAN_US", 0)
    _, fc = _px4_flight(peer, PX4_FLIGHTS["100fps"], message_rate_hz=100.0)
    wrong = [m for m in fc.px4_published() if m["used"] and m["rate"][1] != pytest.approx(1.0, rel=1e-4)]
    assert wrong and all(m["rate"][1] < 0.1 and m["messages"] == 2 for m in wrong)


def test_px4_rate_above_sens_flow_rate_is_warned(caplog):
    caplog.set_level(logging.WARNING, logger="firmware_py.links.mavlink")
    for autopilot, rate, warned in (("px4", 100, True), ("both", 100, True), ("px4", 70, False),
                                    ("ardupilot", 100, False)):
        caplog.clear()
        link = open_link(LinkConfig(port=None, baud=921600, autopilot=autopilot, focal_length_px=F,
                                    message_rate_hz=rate))
        link.close()
        assert link.message_rate_hz == rate
        assert any("SENS_FLOW_RATE" in r.getMessage() for r in caplog.records) == warned, autopilot


# -- the fewest reports: often enough for the autopilots, never a span they reject ---------

MAX_SPAN_US = 450_000   # the integrator's max_interval_us: ArduPilot needs a message every < 0.5 s
#: ArduPilot's EKF3 uses optical flow only while its newest sample is < 200 ms old, and INAV
#: drops an MSP flow sensor after 200 ms without one: reports go out at most 180 ms apart
#: (room for jitter) wherever the frames themselves are no further apart.
FRESH_US = 180_000
FLOW_MESSAGES = ("OPTICAL_FLOW", "OPTICAL_FLOW_RAD", "MSP2_SENSOR_OPTIC_FLOW")


def logged_spans(log_path) -> list[int]:
    """Every flow report's span (µs) in the link's own message log (the wire carries it only
    for PX4), in the order written."""
    logged = [json.loads(line) for line in log_path.read_text().splitlines()]
    return [r["integration_time_us"] for r in logged if r["message"] in FLOW_MESSAGES]


def inav_quantum(span_us: float) -> float:
    """One MSP motion count as a rate over ``span_us``, rad/s (INAV's rates are quantised)."""
    return math.radians(1 / OPFLOW_SCALE) * 1e6 / span_us


LOW_RATES = {
    # the extras' 600 bytes/s once left the flow 1 report/s: it keeps 10/s
    "9600-extras": ("ardupilot", {"baud": 9600, "extra_values": True}),
    # the slowest standard baud that carries OPTICAL_FLOW_RAD's up to 11 reports/s: its 60 %
    # budget gives 9/s (4800 baud, where the budget gave 4 and the 7/s floor applied, is refused)
    "px4-9600": ("px4", {"baud": 9600}),
    # the 7/s floor itself on that line
    "px4-7hz": ("px4", {"baud": 9600, "message_rate_hz": 7.0}),
    "ardupilot-7hz": ("ardupilot", {"baud": 9600, "message_rate_hz": 7.0}),
}


@pytest.mark.parametrize("interval_us", [10_000, 111_111], ids=["100fps", "9fps"])
@pytest.mark.parametrize("case", list(LOW_RATES))
def test_a_low_message_rate_reports_often_enough_within_the_span_cap(peer, case, interval_us):
    """A 100 fps and a 9 fps camera on a slow line: a report every <= 180 ms, each spanning
    <= 0.45 s, all with the true rate. (At 7/s a 9 fps camera's reports used to wait for the
    frame after 1/7 s: 222 ms apart.)"""
    autopilot, settings = LOW_RATES[case]
    link = open_link(LinkConfig(port=peer.path, autopilot=autopilot, focal_length_px=F, **settings))
    fc = FlightController(peer, autopilot)
    start = host_us()
    frames = stream(start, [interval_us] * int(3e6 / interval_us), engine_us=3_000, flow_px_per_s=FLOW)
    try:
        drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    assert link.message_rate_hz == settings.get("message_rate_hz", {"ardupilot": 10, "px4": 9}[autopilot])
    first = next(i for i, m in enumerate(fc.messages) if m["quality"] > 0)
    reports = fc.messages[first:]    # after the quality-0 start marker (and a keep-alive before it)
    assert fc.largest_gap_us(reports[0]["at"]) <= FRESH_US
    # one a frame, or the configured rate if that is less
    assert len(reports) >= 3e6 / max(interval_us, 1e6 / link.message_rate_hz) - 3
    if autopilot == "px4":
        spans = [m["integration_time_us"] for m in reports]
    else:                            # contiguous reports: each spans from the previous one's end
        spans = [b["time_usec"] - a["time_usec"] for a, b in zip(fc.messages[first - 1:], reports)]
    assert max(spans) <= MAX_SPAN_US, spans
    assert all(m["used"] for m in reports)                 # real flow, not keep-alives
    for m in reports:
        assert m["rate"][1] == pytest.approx(TRUE_RATE[1], rel=0.01)


#: Frames per report for steady frames at these fps, at the fewest reports a second the link
#: sends: 7 (the floor: message_rate_hz = 7) and the 60 % budgets of the slowest standard bauds
#: accepted, INAV at 2400 (8/s) and PX4 at 9600 (9/s). A report goes out on the frame at
#: which 1/rate (less a quarter frame) has passed, or earlier, on the last frame before the
#: next one would take it past 180 ms: with frames 90-180 ms apart, each frame is one.
FRAMES_PER_REPORT = {     # fps: {reports/s: frames}
    7.5: {7: 1, 8: 1, 9: 1},      # 133 ms
    8.8: {7: 1, 8: 1, 9: 1},      # 114 ms (2 frames at 7/s: 227 ms)
    9.0: {7: 1, 8: 1, 9: 1},      # 111 ms (2 at 7/s: 222 ms)
    10.0: {7: 1, 8: 1, 9: 1},     # 100 ms (2 at 7/s: 200 ms)
    11.0: {7: 1, 8: 1, 9: 1},     # 91 ms, 11 reports/s (2 at 7 and 8/s: 182 ms)
    12.0: {7: 2, 8: 2, 9: 2},     # 167 ms
    14.0: {7: 2, 8: 2, 9: 2},     # 143 ms
    100.0: {7: 15, 8: 13, 9: 11},  # 150, 130, 110 ms: the backstop adds no reports
}
FLOOR_LINKS = {
    "ardupilot-7hz": ("ardupilot", {"baud": 115200, "message_rate_hz": 7.0}, 7),
    "px4-7hz": ("px4", {"baud": 115200, "message_rate_hz": 7.0}, 7),
    "inav-7hz": ("inav", {"baud": 115200, "message_rate_hz": 7.0}, 7),
    "inav-2400": ("inav", {"baud": 2400}, 8),
    "px4-9600": ("px4", {"baud": 9600}, 9),
}


@pytest.mark.parametrize("fps", list(FRAMES_PER_REPORT))
@pytest.mark.parametrize("case", list(FLOOR_LINKS))
def test_reports_at_the_floor_are_at_most_180ms_apart(peer, tmp_path, case, fps):
    """At the fewest reports a second (the 7/s floor, the budget of a slow line), steady frames
    at 7.5-14 fps are reported at most 180 ms apart, as the autopilot receives them and as
    the message log records their spans: at 7/s, frames 90-114 ms apart used to wait for the
    frame after 1/7 s and go out 200-227 ms apart (ArduPilot's EKF3 and INAV want < 200 ms).
    A fast camera gets no more reports than the rate asks for (100 fps at 7/s: every 150 ms)."""
    autopilot, settings, rate = FLOOR_LINKS[case]
    log_path = tmp_path / "messages.jsonl"
    link = open_link(LinkConfig(port=peer.path, autopilot=autopilot, focal_length_px=F,
                                message_log=str(log_path), **settings))
    fc = FlightController(peer, autopilot)
    interval_us = round(1e6 / fps)
    start = host_us()
    frames = stream(start, [interval_us] * int(3e6 / interval_us), engine_us=3_000, flow_px_per_s=FLOW)
    try:
        drive(link, fc, frames, start_us=frames[0][0], end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    assert link.message_rate_hz == rate
    per_report_us = FRAMES_PER_REPORT[fps][rate] * interval_us
    assert fc.messages[0]["quality"] == 0                                          # the start marker
    assert fc.messages[0]["at"] == frames[0][0] + held_us(link, 3_000)
    arrivals = [m["at"] for m in fc.messages]
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
    assert max(gaps) <= FRESH_US, gaps
    assert set(gaps) == {per_report_us}, gaps
    reports = fc.messages[1:]
    assert len(reports) == (len(frames) - 1) // FRAMES_PER_REPORT[fps][rate]
    assert all(m["used"] for m in reports), [m["quality"] for m in reports]     # no keep-alive either
    spans = logged_spans(log_path)
    assert len(spans) == len(fc.messages) and set(spans[1:]) == {per_report_us}, spans
    if autopilot == "px4":
        assert [m["integration_time_us"] for m in reports] == spans[1:]
    quantum = inav_quantum(per_report_us) if autopilot == "inav" else 1e-6
    for m in reports:
        assert m["rate"][1] == pytest.approx(TRUE_RATE[1], rel=0.01, abs=quantum)


#: At the 7/s floor, jittery frames 90-140 ms apart (7-11 fps) are each a report, so nothing
#: is left pending for a late frame to close (the floor's period alone paired them up,
#: 220-240 ms apart) ...
JITTER_US = [100_000, 120_000, 90_000, 140_000, 110_000, 130_000, 95_000, 135_000, 105_000]
#: ... then a 30 fps camera: a report every 5 frames (167 ms); the late frame comes 3 frames
#: (100 ms) into the next one.
FAST_US = 33_333
FAST_BEFORE = 16
PENDING_FRAMES = 3
AFTER_US = [FAST_US] * 30


def _link_at_the_floor(peer, tmp_path, autopilot):
    """A link at the 7 Hz floor on a fast line, its message log, and the autopilot's ears:
    ``(log_path, link, flight_controller)``."""
    log_path = tmp_path / "messages.jsonl"
    link = make_link(peer, autopilot, message_rate_hz=7.0, message_log=str(log_path))
    return log_path, link, FlightController(peer, autopilot)


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot", "inav"])
@pytest.mark.parametrize("late_us", [370_000, 420_000], ids=["late-370ms", "late-420ms"])
def test_a_late_frame_closes_the_pending_report_within_the_span_cap(peer, tmp_path, autopilot, late_us):
    """No report spans more than 0.45 s, however the frames jitter: a frame that would take
    the pending report past it sends that report at once, ending at the frame before, with
    quality 0, and integration restarts at the late frame. Exactly one report goes out then:
    it stands for the restart marker (a marker as well would be a second report of 0 s), and
    the late frame's own flow, which began before it, is not sent (INAV would divide it by
    the ~0 s since that report). The camera stalls here, the daemon goes on: keep-alives go
    out during the wait (test_a_late_frame_after_an_engine_stall_... has none). At 30 fps
    either wait is past the gap threshold (5 frames) as well."""
    log_path, link, fc = _link_at_the_floor(peer, tmp_path, autopilot)
    start = host_us()
    intervals = JITTER_US + [FAST_US] * FAST_BEFORE + [late_us] + AFTER_US
    frames = stream(start, intervals, engine_us=3_000, flow_px_per_s=FLOW)
    try:
        drive(link, fc, frames, start_us=frames[0][0], end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    spans = logged_spans(log_path)
    assert len(spans) == len(fc.messages) and max(spans) <= MAX_SPAN_US, spans
    if autopilot == "px4":
        assert [m["integration_time_us"] for m in fc.messages] == spans
    # The jittery frames: one report each, as fresh as the frames themselves.
    held = held_us(link, 3_000)
    jitter_end = frames[len(JITTER_US)][0] + held
    jittery = [m["at"] for m in fc.messages if m["at"] <= jitter_end]
    assert jittery == [at + held for at, _ in frames[:len(JITTER_US) + 1]]
    late_index = len(JITTER_US) + FAST_BEFORE + 1
    late_submit = frames[late_index][0]
    # Up to the stall, 30 fps as well: at most 180 ms apart.
    before = [m["at"] for m in fc.messages if m["at"] <= frames[late_index - 1][0] + held]
    assert max(b - a for a, b in zip(before, before[1:])) <= FRESH_US
    at_late = [i for i, m in enumerate(fc.messages) if m["at"] == late_submit + held]
    assert len(at_late) == 1, [fc.messages[i] for i in at_late]
    # the pending 100 ms (not the gap's discard), with quality 0
    assert spans[at_late[0]] == PENDING_FRAMES * FAST_US
    assert sum(intervals[late_index - 1 - PENDING_FRAMES:late_index - 1]) == spans[at_late[0]]
    assert fc.messages[at_late[0]]["quality"] == 0 and not fc.messages[at_late[0]]["used"]
    keepalives = [m for m in fc.messages if frames[late_index - 1][0] + held < m["at"] < late_submit]
    assert keepalives and all(m["quality"] == 0 for m in keepalives)
    arrivals = [m["at"] for m in fc.messages]
    assert len(set(arrivals)) == len(arrivals), "two reports at once"
    assert link.stats["integration_restarts"] == 1
    # The frames after the late one report their true flow from the first on (5 frames each).
    after = [m for m in fc.messages if m["at"] > late_submit + held]
    assert len(after) == len(AFTER_US) // 5 and all(m["used"] for m in after)
    if autopilot == "px4":
        assert {m["integration_time_us"] for m in after} == {5 * FAST_US}
    quantum = inav_quantum(5 * FAST_US) if autopilot == "inav" else 1e-6
    for m in fc.used():
        assert m["rate"][1] == pytest.approx(TRUE_RATE[1], rel=0.01, abs=quantum)


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot", "inav"])
def test_a_late_frame_after_an_engine_stall_closes_the_pending_report_with_quality_0(peer, tmp_path, autopilot):
    """The engine stalls: 400 ms pass with neither a submit() nor a service() call (no
    keep-alive can go out), and the next frame is the first captured after the stall. It
    closes the pending report (2 frames, 67 ms) with quality 0: the autopilot's interval for
    it runs from the previous message, 467 ms before — INAV would divide its counts by that
    (a seventh of the true rate), PX4 match them with 467 ms of its gyro. The reports after it
    are good from the first on, their counts starting at the late frame."""
    flow = (0.0, 100.0)     # 1 rad/s: 1 count is < 1 % of an INAV rate over 167 ms
    log_path, link, fc = _link_at_the_floor(peer, tmp_path, autopilot)
    start = host_us()
    stall_us, stall_after = 400_000, 22      # frames 1-20: 4 reports; then 2 frames pending
    intervals = [FAST_US] * stall_after + [stall_us] + [FAST_US] * 30
    frames = stream(start, intervals, engine_us=3_000, flow_px_per_s=flow)
    late_submit = frames[stall_after + 1][0]
    try:
        drive(link, fc, frames, start_us=frames[0][0], end_us=frames[-1][0] + STEP_US,
              stall=(frames[stall_after][0], late_submit))
    finally:
        link.close()
    assert link.stats["blind_reports"] == 0     # nothing went out during the stall
    spans = logged_spans(log_path)
    assert len(spans) == len(fc.messages)
    held = held_us(link, 3_000)
    at_late = [i for i, m in enumerate(fc.messages) if m["at"] == late_submit + held]
    assert len(at_late) == 1
    closed = fc.messages[at_late[0]]
    previous = fc.messages[at_late[0] - 1]
    assert spans[at_late[0]] == 2 * FAST_US                                 # the pending frames' counts ...
    assert late_submit + held - previous["at"] == 2 * FAST_US + stall_us    # ... the autopilot's interval
    assert closed["quality"] == 0 and not closed["used"]
    if autopilot == "inav":
        assert closed["rate"][1] == pytest.approx(1.0 * 2 * FAST_US / (2 * FAST_US + stall_us), abs=0.01)
    if autopilot == "px4":
        assert closed["integration_time_us"] == 2 * FAST_US
        published = fc.px4_published()
        assert next(m for m in published if m["at"] == late_submit)["quality"] == 0
        fused = [m for m in published if m["used"]]
        assert fused and all(m["rate"][1] == pytest.approx(1.0, rel=1e-4) for m in fused)
    arrivals = [m["at"] for m in fc.messages]
    assert len(set(arrivals)) == len(arrivals), "two reports at once"
    assert link.stats["integration_restarts"] == 1
    after = [m for m in fc.messages if m["at"] > late_submit + held]
    assert len(after) == 30 // 5 and all(m["used"] for m in after)
    assert after[0]["at"] - (late_submit + held) == 5 * FAST_US     # counted from the late frame on
    if autopilot == "px4":
        assert {m["integration_time_us"] for m in after} == {5 * FAST_US}
    quantum = inav_quantum(5 * FAST_US) if autopilot == "inav" else 1e-6
    used = fc.used()
    assert len(used) == len(fc.messages) - 2       # all but the start marker and the closed report
    for m in used:
        assert m["rate"][1] == pytest.approx(1.0, rel=1e-4, abs=quantum)


EXTRAS = (("expansion", 0.1), ("ttc_s", -1.0), ("balanceLR", 0.0), ("balanceTB", 0.0))


def _with_extras(frames):
    return [(at, FlowSample(timestamp_us=s.timestamp_us, capture_host_us=s.capture_host_us, flow_x=s.flow_x,
                            flow_y=s.flow_y, quality=s.quality, extras=EXTRAS)) for at, s in frames]


def test_extra_values_that_do_not_fit_are_thinned_not_the_flow(peer, caplog):
    """At 9600 baud four NAMED_VALUE_FLOATs at 5 Hz (600 bytes/s) alone exceed the 576 bytes/s
    budget: the flow keeps 10 reports/s, the extras get what is left, with one warning."""
    caplog.set_level(logging.WARNING, logger="firmware_py.links")
    link = open_link(LinkConfig(port=peer.path, baud=9600, autopilot="ardupilot", focal_length_px=F,
                                extra_values=True))
    fc = FlightController(peer, "ardupilot")
    start = host_us()
    seconds = 20.0
    frames = _with_extras(stream(start, [10_000] * int(100 * seconds), engine_us=3_000, flow_px_per_s=FLOW))
    try:
        drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    warnings = [r.getMessage() for r in caplog.records if "extra_values" in r.getMessage()]
    assert len(warnings) == 1 and "at 9600 baud" in warnings[0] and "times per second instead of 5" in warnings[0]
    assert link.message_rate_hz >= 10
    named = [m for _, m in fc.wire if m.get_type() == "NAMED_VALUE_FLOAT"]
    assert 0 < len(named) <= 4 * (seconds * 1.0 + 1)          # thinned to below 1 round/s
    wire_bytes = sum(len(m.get_msgbuf()) for _, m in fc.wire)
    assert wire_bytes / seconds <= 0.6 * 9600 / 10           # the whole link within its budget
    assert len([m for m in fc.messages if m["used"]]) >= 10 * seconds - 2


def test_extra_values_go_on_after_the_capture_clock_restarts(peer):
    """A reopened OAK's device clock starts again near 0: the extras' schedule must start
    afresh, not wait for the old uptime (1 h here) to come round again."""
    link = make_link(peer, "ardupilot", extra_values=True)
    fc = FlightController(peer, "ardupilot")
    host = host_us()
    frames = []
    for phase, capture_start in enumerate((3_600_000_000, 100_000)):   # 1 h of uptime, then 0.1 s
        for i in range(100):                                           # 1 s at 100 fps each
            at = host + (phase * 100 + i) * 10_000
            frames.append((at + 3_000, FlowSample(timestamp_us=capture_start + i * 10_000, capture_host_us=at,
                                                  flow_x=0.0, flow_y=0.12, quality=200, extras=EXTRAS)))
    try:
        drive(link, fc, frames, start_us=host, end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    named = [m for _, m in fc.wire if m.get_type() == "NAMED_VALUE_FLOAT"]
    before = [m for m in named if m.time_boot_ms >= 3_600_000]
    after = [m for m in named if m.time_boot_ms < 3_600_000]
    assert len(before) >= 4 * 4
    assert len(after) >= 4 * 4                     # 5 rounds/s of 4 values over the second phase
    assert after[0].time_boot_ms == 100            # the first frame of the restarted clock


def _jittered_frames(start_us, interval_us, count, rng, doubtful_share=0.0, doubtful_as_blind=False):
    """``count`` frames ``interval_us`` apart with ±1 ms capture jitter, each submitted 2-6 ms
    after its capture, at the true ``FLOW``; a ``doubtful_share`` of them (at random) rated
    below the floor with a wrong-sign flow, sent as the daemon sends them (``doubtful``),
    or as it did before (quality 0) with ``doubtful_as_blind``."""
    frames, t = [], start_us
    for i in range(count):
        dt = interval_us + int(rng.integers(-1000, 1001)) if i else 0
        t += dt
        u, v = (c * dt / 1e6 for c in FLOW)
        quality, doubtful = (200 if i else 0), False
        if i and rng.uniform() < doubtful_share:
            u, v, quality, doubtful = -3 * u, -3 * v, 40, True
            if doubtful_as_blind:
                quality, doubtful = 0, False
        frames.append((t + int(rng.integers(2000, 6001)),
                       FlowSample(timestamp_us=t, capture_host_us=t, flow_x=u, flow_y=v, quality=quality,
                                  doubtful=doubtful)))
    return sorted(frames, key=lambda item: item[0])


@pytest.mark.parametrize("interval_us", [10_000, 8_333, 16_667, 18_500, 33_333, 50_000])
def test_ardupilot_ekf3_fuses_every_default_report(peer, interval_us):
    """ArduPilot's EKF3 stores a flow sample only 50 ms after the last one it took: of the
    former default's 100 reports a second (at 115200 baud and up) it fused one in five or
    six, each spanning one frame. By default the reports are now at most 17 a second, each
    of at least 57 ms of frames: on cameras of 120, 100, 60, 54, 30 and 20 fps with jittery
    capture and processing, EKF3 fuses every good report. (At 20 fps the frame alignment's
    quarter-frame tolerance alone let a single 50 ms frame be a report.)"""
    rng = np.random.default_rng(interval_us)
    seen = {}
    for rate in (None, 100.0):
        link = make_link(peer, "ardupilot", **({} if rate is None else {"message_rate_hz": rate}))
        fc = FlightController(peer, "ardupilot")
        start = host_us()
        frames = _jittered_frames(start, interval_us, int(3e6 / interval_us), rng)  # 3 s
        try:
            drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
        finally:
            link.close()
        good = [m for m in fc.messages if m["quality"] > 0]
        seen[rate] = (len(fc.ekf3_fused()), len(good),
                      [b["time_usec"] - a["time_usec"] for a, b in zip(good, good[1:])])
    fused, good, spans = seen[None]
    whole = math.ceil(ARDUPILOT_MIN_REPORT_SPAN_US / interval_us) * interval_us  # (whole frames)
    assert good >= 0.8 * 3e6 / whole and fused == good, (fused, good)
    assert min(spans) >= 50_000, min(spans)
    fused, good, _ = seen[100.0]
    if interval_us < 20_000:  # (a report every frame: the EKF3 takes one in five or six, three or four at 60 fps)
        assert fused <= 0.35 * good, (fused, good)


def test_ardupilot_ekf3_fuses_reports_around_doubtful_frames(peer):
    """A frame below the quality floor (ArduPilot's default 64 or 128) zeroed the whole
    report it fell in: with six frames a report, 10 % such frames cost EKF3 about a third of
    its reports. The report now leaves that frame out and reads its span at its other
    frames' rate: EKF3 fuses nearly every report, each at the true rate (the doubtful
    frames' wrong-sign flow never reaches it)."""
    fused = {}
    for as_blind in (False, True):
        link = make_link(peer, "ardupilot")
        fc = FlightController(peer, "ardupilot")
        start = host_us()
        frames = _jittered_frames(start, 10_000, 300, np.random.default_rng(7), doubtful_share=0.1,
                                  doubtful_as_blind=as_blind)
        try:
            drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
        finally:
            link.close()
        fused[as_blind] = fc.ekf3_fused()
    now, before = len(fused[False]), len(fused[True])
    assert now >= 45 and before <= 0.75 * now, (now, before)  # (50 reports in 3 s at 100 fps)
    for m in fused[False]:
        assert m["rate"][0] == pytest.approx(TRUE_RATE[0], abs=1e-3)
        assert m["rate"][1] == pytest.approx(TRUE_RATE[1], rel=0.02)


@pytest.mark.parametrize("interval_us", [10_000, 16_667, 55_556, 58_824])
def test_ardupilot_plane_fuses_every_report_at_15_a_second(peer, interval_us):
    """ArduPlane hands flow messages to EKF3 from a 50 Hz task: its 20 ms step can put a
    60 ms report 40 ms after the last one fused, and EKF3 drops it. The README's advice for
    Plane, ``message_rate_hz = 15`` (reports of seven frames at 100 fps), fuses every good
    report through that task at every phase of it tried — also on 18 and 17 fps cameras,
    whose single frames the alignment tolerance made 15 Hz reports of 55.6 and 58.8 ms
    before a set rate this low got the minimum span too."""
    for phase_us in range(0, 20_000, 2_500):
        link = make_link(peer, "ardupilot", message_rate_hz=15.0)
        fc = FlightController(peer, "ardupilot")
        start = host_us()
        frames = _jittered_frames(start, interval_us, int(2e6 / interval_us), np.random.default_rng(phase_us))
        try:
            drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
        finally:
            link.close()
        good = [m for m in fc.messages if m["quality"] > 0]
        whole = math.ceil(0.97e6 / 15 / interval_us) * interval_us
        assert len(good) >= 0.8 * 2e6 / whole, (len(good), phase_us)
        assert len(fc.ekf3_fused(task_hz=50.0, phase_us=phase_us)) == len(good), phase_us


def test_the_minimum_report_span_never_costs_a_slow_cameras_report(peer):
    """ArduPilot's 57 ms minimum span held a 40 ms interval of a ~2.3 fps camera; the next
    frame took it past the longest span a report may have (0.45 s) and out with quality 0,
    its flow lost. The minimum yields to that limit: every report good."""
    link = make_link(peer, "ardupilot")
    fc = FlightController(peer, "ardupilot")
    start = host_us()
    frames = stream(start, [430_000, 430_000, 430_000, 40_000, 430_000, 430_000, 430_000], engine_us=5_000,
                    flow_px_per_s=FLOW)
    try:
        drive(link, fc, frames, start_us=start, end_us=frames[-1][0] + STEP_US)
    finally:
        link.close()
    qualities = [m["quality"] for m in fc.messages if m["at"] > start + 500_000]
    assert qualities and all(q > 0 for q in qualities), qualities
