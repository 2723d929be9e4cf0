"""MSP v2 link (INAV): test vector, independent decoding, INAV's sign/scale chain, carry."""

import math
import os
import struct
import sys
import time

import pytest

sys.path.insert(0, os.path.dirname(__file__))
from ptyutil import FrameFeeder, PtyPeer, fly_and_close, host_us  # noqa: E402

from firmware_py.links import LinkConfig, open_link  # noqa: E402
from firmware_py.links.msp import MspLink, encode_optic_flow  # noqa: E402

SPEC_EXAMPLE = "24583c00021f0900c80c000000f9ffffffc1"  # quality 200, x 12, y -7
FPS = 100.0


def _crc_table():
    # Independent of the link's bitwise CRC: a table-driven CRC-8 with polynomial 0xD5.
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0xD5) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return table


CRC_TABLE = _crc_table()


def decode_msp_v2(stream: bytes):
    """Decode a byte stream into [(function, payload)], asserting every frame is intact."""
    frames, i = [], 0
    while i < len(stream):
        assert stream[i:i + 3] == b"$X<", f"bad header at {i}: {stream[i:i + 3]!r}"
        flags, function, size = struct.unpack_from("<BHH", stream, i + 3)
        body = stream[i + 3:i + 8 + size]
        crc = 0
        for b in body:
            crc = CRC_TABLE[crc ^ b]
        assert crc == stream[i + 8 + size], "CRC mismatch"
        assert flags == 0
        frames.append((function, stream[i + 8:i + 8 + size]))
        i += 9 + size
    return frames


def optic_flow(stream: bytes):
    out = []
    for function, payload in decode_msp_v2(stream):
        assert function == 0x1F02 and len(payload) == 9
        out.append(struct.unpack("<Bii", payload))
    return out


def test_spec_example_byte_exact_and_decodes():
    data = encode_optic_flow(quality=200, motion_x=12, motion_y=-7)
    assert data.hex() == SPEC_EXAMPLE
    assert optic_flow(bytes.fromhex(SPEC_EXAMPLE)) == [(200, 12, -7)]


def inav_velocity(quality, motion_x, motion_y, dt_us, *, opflow_scale=10.5, alt_m=1.0, gyro_dps=(0.0, 0.0)):
    """What INAV does with one message (opflow_msp.c → opflow.c → pos_estimator_flow.c).

    Returns the body-frame velocity (forward, left) in m/s. INAV's body frame is X forward,
    Y left, Z up; gyro X = roll right, gyro Y = pitch down.
    """
    assert quality * 100 // 255 >= 35, "INAV ignores flow under 35 % quality"
    rate_scale = (1e6 / dt_us) / opflow_scale
    # opflow_align default CW0_DEG_FLIP: x -> -x, y -> y (boardalignment.c)
    aligned_x, aligned_y = -motion_x, motion_y
    flow_x = math.radians(aligned_x * rate_scale)
    flow_y = math.radians(aligned_y * rate_scale)
    body_x, body_y = (math.radians(g) for g in gyro_dps)
    vel_forward = -(flow_y - body_y) * alt_m
    vel_left = (flow_x - body_x) * alt_m
    return vel_forward, vel_left


@pytest.fixture
def peer(tmp_path):
    p = PtyPeer(tmp_path / "ttyFC")
    yield p
    p.close()


def run_inav(peer, *, flow_x, flow_y, frames=200, focal_length_px=400.0, **kw):
    """(quality, motionX, motionY) after the start marker (quality 0 at the first frame)."""
    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot="inav", focal_length_px=focal_length_px,
                                **kw))
    assert isinstance(link, MspLink)
    messages = optic_flow(fly_and_close(link, peer, frames, fps=FPS, flow_x=flow_x, flow_y=flow_y))
    assert messages[0] == (0, 0, 0)
    return link, messages[1:]


def test_rate_default_50hz_from_capture_time(peer):
    link, messages = run_inav(peer, flow_x=0.0, flow_y=1.0, frames=300)
    assert link.message_rate_hz == 50
    assert len(messages) == pytest.approx(3.0 * 50, abs=2)  # 3 s of capture time
    assert 18 * len(messages) / 3.0 <= 0.6 * 115200 / 10


def test_rate_limited_by_baud():
    link = open_link(LinkConfig(port=None, baud=9600, autopilot="inav", focal_length_px=400.0))
    link.close()
    assert link.message_rate_hz == 32  # 960 B/s * 0.6 / 18 B
    link = open_link(LinkConfig(port=None, baud=4800, autopilot="inav", focal_length_px=400.0))
    link.close()
    assert link.message_rate_hz == 16  # 288 B/s / 18 B
    # the slowest standard baud that carries the up to 11 reports/s INAV may get (at least 7:
    # it drops the sensor after 200 ms without one; every frame of a camera near 11 fps, to
    # keep them <= 180 ms apart): 11.1 x 18 B = 200 B/s of its 240; its budget gives 8/s
    link = open_link(LinkConfig(port=None, baud=2400, autopilot="inav", focal_length_px=400.0))
    link.close()
    assert link.message_rate_hz == 8   # 144 B/s / 18 B
    # 1200 baud (120 B/s) is refused, naming the baud whose 60 % budget holds 200 B/s
    with pytest.raises(ValueError, match=r"baud 1200 is too low: up to 11 MSP2_SENSOR_OPTIC_FLOW reports per "
                                         r"second \(at least 7, and every frame of a camera near 11 fps; 18 bytes "
                                         r"each; .*\) need 200 bytes/s, and 1200 baud carries 120 bytes/s \(8N1\); "
                                         r"use 4800 baud or more on both ends"):
        open_link(LinkConfig(port=None, baud=1200, autopilot="inav", focal_length_px=400.0))


def test_forward_flight_worked_example(peer):
    # README (INAV worked example): f = 400 px, 100 fps, ground moving down the image at 2 px/frame
    # (forward at 0.5 m/s, 1 m above ground). 50 Hz → 4 px per message = 0.01 rad = 0.573°
    # → motionY = -10.5 × 0.573 = -6.016 counts (remainder carried).
    _, messages = run_inav(peer, flow_x=0.0, flow_y=2.0)
    assert {m[1] for m in messages} == {0}
    assert set(m[2] for m in messages) <= {-6, -7}
    total = sum(m[2] for m in messages)
    expected = -10.5 * math.degrees(len(messages) * 4.0 / 400.0)
    assert total == pytest.approx(expected, abs=1)
    # One count is 1/10.5° per 20 ms = 0.083 rad/s: single messages are quantised, the carry
    # makes the mean exact.
    velocities = [inav_velocity(q, mx, my, 20_000) for q, mx, my in messages]
    assert all(0.5 - 0.09 < fwd < 0.5 + 0.09 and left == 0.0 for fwd, left in velocities)
    assert sum(v[0] for v in velocities) / len(velocities) == pytest.approx(0.5, rel=0.01)


def test_rightward_flight_inav_sees_rightward_velocity(peer):
    # Moving right at 0.25 m/s at 1 m: the ground moves left in the image, u = -1 px/frame.
    _, messages = run_inav(peer, flow_x=-1.0, flow_y=0.0)
    velocities = [inav_velocity(q, mx, my, 20_000) for q, mx, my in messages]
    mean_left = sum(v[1] for v in velocities) / len(velocities)
    assert mean_left == pytest.approx(-0.25, rel=0.02)  # -left = right
    assert all(mx > 0 for _, mx, _ in messages)


def test_pure_rotation_cancels_against_inav_gyro(peer):
    # Rolling right at 30 deg/s: the view tilts left, the ground moves right in the image,
    # u = +rate·f/fps. INAV subtracts its gyro (X = roll right): the velocity must be ~0.
    rate = math.radians(30.0)
    u = rate * 400.0 / FPS
    _, messages = run_inav(peer, flow_x=u, flow_y=0.0)
    lefts = [inav_velocity(q, mx, my, 20_000, gyro_dps=(30.0, 0.0))[1] for q, mx, my in messages[1:]]
    assert all(abs(v) < 0.09 for v in lefts)  # only count rounding left over ...
    assert abs(sum(lefts) / len(lefts)) < 0.005  # ... which the carry averages out
    # Pitching down at 30 deg/s (INAV gyro Y positive): the view tilts back, the ground moves
    # up the image (v < 0).
    _, messages = run_inav(peer, flow_x=0.0, flow_y=-u)
    forwards = [inav_velocity(q, mx, my, 20_000, gyro_dps=(0.0, 30.0))[0] for q, mx, my in messages[1:]]
    assert all(abs(v) < 0.09 for v in forwards)
    assert abs(sum(forwards) / len(forwards)) < 0.005


def test_remainder_carry_small_flow(peer):
    # f = 10.5 × 180/π px makes one count per pixel: 0.2 px/frame at 100 fps is 0.4 counts per
    # 50 Hz message. Rounding each message would send zeros forever.
    f = 10.5 * 180.0 / math.pi
    _, messages = run_inav(peer, flow_x=0.0, flow_y=0.2, frames=500, focal_length_px=f)
    counts = [m[2] for m in messages]
    assert set(counts) == {0, -1}
    assert sum(counts) == pytest.approx(-0.4 * len(messages), abs=1)


def test_a_quality0_report_leaves_no_remainder_to_the_next_good_one(peer):
    # 0.4 counts per 50 Hz report (one count per pixel, 0.2 px/frame at 100 fps). An engine
    # stall makes the link send a keep-alive; the report that then closes the interval
    # still carries its frames' counts, with quality 0. The first good report after it must
    # start from a clean carry (0.4 rounds to 0), as after a fresh start: one count left
    # over from the quality-0 report is motion INAV would take from before its interval.
    from firmware_py.links import FlowSample

    f = 10.5 * 180.0 / math.pi
    link = open_link(LinkConfig(port=peer.path, autopilot="inav", focal_length_px=f))
    start, sink = host_us(), bytearray()

    def frame(i, host_offset_us):
        now = start + host_offset_us
        link.submit(FlowSample(timestamp_us=1_000_000 + i * 10_000, capture_host_us=now, flow_x=0.0,
                               flow_y=0.2, quality=200), now)
        link.service(now)
        sink.extend(peer.read())

    try:
        for i in range(11):
            frame(i, i * 10_000)
        link.service(start + 260_000)  # no frame for 0.16 s: a keep-alive
        sink.extend(peer.read())
        for i in range(11, 21):
            frame(i, 260_000 + (i - 10) * 10_000)
    finally:
        link.close()
        sink.extend(peer.read())
    reports = optic_flow(bytes(sink))
    qualities = [q for q, _, _ in reports]
    last_zero = max(i for i, q in enumerate(qualities) if q == 0)
    assert last_zero > 1 and qualities[1] == 200  # keep-alive and closing report after good ones
    assert qualities[last_zero - 1] == 0
    first_good = reports[last_zero + 1]
    assert first_good[0] == 200
    assert first_good[2] == 0, reports


def test_counts_per_degree_setting(peer):
    _, messages = run_inav(peer, flow_x=0.0, flow_y=2.0, msp_counts_per_degree=21.0)
    assert sum(m[2] for m in messages) == pytest.approx(-21.0 * math.degrees(len(messages) * 0.01), abs=1)


def test_blind_keeps_inav_alive_with_quality_zero(peer):
    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot="inav", focal_length_px=400.0))
    sink = bytearray()
    try:
        FrameFeeder(link, fps=FPS).frames(20, flow_y=1.0, peer=peer, sink=sink)
        before = len(optic_flow(bytes(sink)))
        start = host_us()
        for step in range(1, 201):  # 2 s of simulated host time, no frames
            link.service(start + step * 10_000)
            sink.extend(peer.read())
    finally:
        link.close()
    blind = optic_flow(bytes(sink))[before:]
    # INAV times out after 0.2 s: 10 Hz keep-alive after 0.15 s.
    assert len(blind) == pytest.approx(19, abs=2)
    assert all(q == 0 and mx == 0 and my == 0 for q, mx, my in blind)


def _arrivals(peer, link, frame_times_us, end_us, *, late_us=0, seed=0, tick_us=10_000):
    """Feed frames captured at ``frame_times_us``, each handed to the link up to ``late_us``
    later (random: the daemon submits a frame after its engine and summary, whose time
    varies), and service the link every ``tick_us`` of host time (the daemon's loop: 10 ms)
    until ``end_us``; returns (host time read, quality) of every MSP flow report, as the
    autopilot's end of the pty saw them."""
    import random

    from firmware_py.links import FlowSample

    rng = random.Random(seed)
    frames = sorted((at + rng.randint(0, late_us), at) for at in frame_times_us)
    out, t = [], frame_times_us[0]

    def read(at):
        out.extend((at, q) for q, _, _ in optic_flow(peer.read()))

    while t <= end_us:
        while frames and frames[0][0] <= t:
            submitted, captured = frames.pop(0)
            link.submit(FlowSample(timestamp_us=captured, capture_host_us=captured, flow_x=0.0, flow_y=0.5,
                                   quality=200), submitted)
            read(submitted)
        link.service(t)
        read(t)
        t += tick_us
    return out


@pytest.mark.parametrize("setting", [{"message_rate_hz": 7.0}, {"baud": 2400}])
def test_a_camera_that_stops_between_reports_keeps_inav_fed(peer, setting):
    """At the lowest message rates (7-8 Hz) the last report can precede the camera's last
    frame by almost a period: the keep-alive must go out before INAV's 200 ms timeout
    counted from that report, not 0.15 s after the last frame (270-290 ms without a
    message before). Whatever the phase of the stop, the gap stays below 200 ms."""
    worst = 0
    for n in range(100, 116):  # the camera stops at every phase of the report period
        link = open_link(LinkConfig(port=peer.path, autopilot="inav", focal_length_px=400.0, **setting))
        try:
            start = host_us()
            frames = [start + i * 10_000 for i in range(n)]
            reports = _arrivals(peer, link, frames, frames[-1] + 600_000)
        finally:
            link.close()
            peer.read()
        assert link.message_rate_hz <= 8.0
        times = [at for at, _ in reports]
        worst = max(worst, max(b - a for a, b in zip(times, times[1:])))
        assert [q for _, q in reports][-3:] == [0, 0, 0]  # blind: quality-0 keep-alives
    assert worst < 200_000, worst


@pytest.mark.parametrize("fps", [30.0, 15.0])
def test_frames_handed_over_late_at_the_lowest_rate_send_no_keepalive(peer, fps):
    """The keep-alive before the timeout waits for a frame overdue by more than the engine's
    and the summary's varying time can make it (up to 15 ms past its interval): a steady
    stream reported at 7 Hz (a report can wait a frame past 150 ms), its frames handed to
    the link up to 14 ms late and the link serviced every millisecond, keeps every report
    after the start marker good. (A frame 1.25 intervals overdue was a stall before: at 30
    fps one 8.4 ms later than the frame before it cost a report.)"""
    link = open_link(LinkConfig(port=peer.path, autopilot="inav", focal_length_px=400.0, message_rate_hz=7.0))
    try:
        start = host_us()
        frames = [start + round(i * 1e6 / fps) for i in range(int(10 * fps))]
        reports = _arrivals(peer, link, frames, frames[-1], late_us=14_000, seed=2, tick_us=1_000)
    finally:
        link.close()
    qualities = [q for _, q in reports]
    # (a keep-alive while the first frame is still on its way, then the start marker)
    first_good = qualities.index(200)
    assert first_good <= 2 and len(qualities) > first_good + 15
    assert all(q > 0 for q in qualities[first_good:]), qualities


@pytest.mark.parametrize("autopilot,protocol", [("ardupilot", "msp"), ("px4", "msp"), ("inav", "mavlink"),
                                                ("both", "msp")])
def test_a_link_config_refuses_a_protocol_its_autopilot_cannot_read(autopilot, protocol):
    """The library refuses what the daemon's configuration refuses: PX4 reads MAVLink only,
    INAV MSP only, and ArduPilot's MSP driver would scale per-degree counts by the message
    interval (its error says so and names the way out)."""
    with pytest.raises(ValueError, match=f"autopilot {autopilot!r} with protocol {protocol!r}: {autopilot} takes "
                                         "optical flow over (mavlink|msp) only") as caught:
        LinkConfig(port=None, autopilot=autopilot, protocol=protocol)
    assert ("FLOW_TYPE = 5" in str(caught.value)) == (autopilot == "ardupilot")
    for autopilot, protocol in (("ardupilot", "mavlink"), ("px4", "mavlink"), ("both", "mavlink"), ("inav", "msp")):
        LinkConfig(port=None, autopilot=autopilot, protocol=protocol)


def test_the_automatic_report_delay_follows_the_processing_time():
    """The automatic delay after capture: just above the slowest 1 % of recent processing
    times, raised at once when frames take longer, lowered only after a whole window of
    faster frames (each change moves one report's arrival), never above 25 ms; reports
    processed past their due time go out at once and are counted late; frames that do not
    come in real time are not held."""
    from firmware_py.links.pacing import AUTO_MAX_US, AUTO_WINDOW, ReportPacer

    pacer = ReportPacer(None)
    t = 1_000_000

    def report(ready_us, period_us=20_000):
        nonlocal t
        t += period_us
        return pacer.send_at(t, t, t + ready_us)

    assert report(3_000) == t + 4_000                  # (its own time plus the 1 ms margin)
    for _ in range(AUTO_WINDOW):
        report(3_000)
    assert pacer.delay_us == 4_000 and pacer.late == 0
    assert report(9_000) is None and pacer.late == 1   # one slow frame: late (the slowest 1 % are)
    assert [report(9_000) for _ in range(3)][-1] == t + 10_000   # a slow spell: followed at once
    assert pacer.delay_us == 10_000 and pacer.late == 3
    for _ in range(AUTO_WINDOW - 4):
        report(3_000)
    assert pacer.delay_us == 10_000                    # (not lowered while they are in the window ...)
    delays = []
    for _ in range(20):
        report(3_000)
        delays.append(pacer.delay_us)
    # (... then by 0.5 ms a report, one report's interval 0.5 ms short, not one 5 ms short,
    # down to within the margin of what it would now choose, 4 ms)
    assert delays == list(range(9_500, 4_500, -500)) + [5_000] * 10
    for _ in range(5):
        assert report(60_000) is None
    assert pacer.delay_us == AUTO_MAX_US and pacer.late == 8
    pacer.written(after_due_us=1_500)
    pacer.written(after_due_us=2_500)  # (a stalled writer: late as well)
    assert pacer.late == 9
    # A recording read faster than it was captured: no capture clock to keep to.
    assert report(1_000, period_us=20_000) is not None
    t_host = t
    assert pacer.send_at(t_host + 10, t + 20_000, t_host + 20) is None and not pacer.real_time
    # Fixed and off.
    assert ReportPacer(7_000).send_at(100, 100, 3_000) == 7_100
    assert ReportPacer(0).send_at(100, 100, 3_000) is None
    with pytest.raises(ValueError, match="report delay must be >= 0"):
        ReportPacer(-1)


@pytest.mark.parametrize("with_port", [True, False], ids=["port", "no-port"])
def test_the_writer_is_woken_for_a_held_report_only_when_it_can_be_written(tmp_path, with_port):
    """A report held for its send time tells the daemon's report writer when to wake
    (``wake_in_s``); with no port to write it to (or a full kernel buffer) it does not, or
    the writer would spin on a due report it cannot send."""
    from firmware_py.links import FlowSample

    peer = PtyPeer(tmp_path / "ttyFC") if with_port else None
    link = open_link(LinkConfig(port=peer.path if peer else None, baud=115200, autopilot="inav",
                                msp_report_delay_ms=30.0))
    try:
        t = host_us()
        for i in range(2):  # (the start marker, then a report: both held 30 ms after capture)
            link.submit(FlowSample(timestamp_us=t + i * 20_000, capture_host_us=t + i * 20_000, flow_x=1.0,
                                   flow_y=0.0, quality=200), now_host_us=t + i * 20_000 + 3_000)
        now = t + 3_000
        if with_port:
            assert link.wake_in_s(now) == pytest.approx(0.027)
            assert link.wake_in_s(t + 60_000) == 0.0
            link.service(t + 30_000)
            assert peer.read() and link.wake_in_s(t + 30_000) == pytest.approx(0.02)
        else:
            assert link.wake_in_s(now) is None
    finally:
        link.close()
        if peer is not None:
            peer.close()


def test_a_held_report_behind_one_that_is_not_still_wakes_the_writer(peer):
    """A message queued at once while the kernel's buffer was full (a late report, a
    keep-alive) sits at the head with held reports behind it: once the port takes data
    again it is due now, or the writer slept while the reports behind it fell overdue."""
    from firmware_py.links.serial_port import OutgoingMessage

    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot="inav"))
    try:
        now = host_us()
        # (queued without a pump: as if the kernel's buffer had been full then)
        link.transport.enqueue(OutgoingMessage(name="late", data=b"x"))
        link.transport.enqueue(OutgoingMessage(name="held", data=b"y", not_before_host_us=now - 5_000))
        assert link.wake_in_s(now) == 0.0
        link.send_due(now)
        got, deadline = b"", time.monotonic() + 2.0
        while len(got) < 2 and time.monotonic() < deadline:
            got += peer.read()
            time.sleep(0.01)
        assert link.queued_messages == 0 and got == b"xy"
        assert link.wake_in_s(now) is None
    finally:
        link.close()
