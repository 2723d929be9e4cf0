"""MAVLink 2 link over a real pty, checked with pymavlink's parser on the autopilot's end."""

import math
import os
import sys

import pytest
from pymavlink.dialects.v20 import common as mavlink2

sys.path.insert(0, os.path.dirname(__file__))
from ptyutil import FrameFeeder, PtyPeer, fly_and_close, host_us  # noqa: E402

from firmware_py.links import FlowSample, LinkConfig, open_link  # noqa: E402
from firmware_py.links.mavlink import MavlinkLink, encode_heartbeat, new_encoder, pack  # noqa: E402

SPEC_HEARTBEAT = "fd09000000019e000000000000001208000403fb1d"
SPEC_FLOW_RAD = ("fd2c000001019e6a000040420f0000000000204e00000ad7233c0ad7a3bc6f12833a6f1203bb6f12033a"
                 "000000000000c03fc40900c8b3fd")
F = 400.0
FPS = 100.0


def strict_parse(data: bytes):
    """pymavlink, non-robust: a bad CRC or a torn frame raises."""
    parser = mavlink2.MAVLink(None)
    messages = parser.parse_buffer(data) or []
    assert all(m.get_type() != "BAD_DATA" for m in messages)
    return messages


def of_type(messages, name):
    return [m for m in messages if m.get_type() == name]


@pytest.fixture
def peer(tmp_path):
    p = PtyPeer(tmp_path / "ttyFC")
    yield p
    p.close()


def make_link(peer, **kw):
    options = dict(port=peer.path, baud=115200, autopilot="ardupilot", focal_length_px=F)
    options.update(kw)
    return open_link(LinkConfig(**options))


def test_spec_test_vectors_byte_exact():
    enc = new_encoder(sysid=1, compid=158)
    assert encode_heartbeat(enc).hex() == SPEC_HEARTBEAT
    msg = enc.optical_flow_rad_encode(
        time_usec=1_000_000, sensor_id=0, integration_time_us=20_000, integrated_x=0.01, integrated_y=-0.02,
        integrated_xgyro=0.001, integrated_ygyro=-0.002, integrated_zgyro=0.0005, temperature=2500,
        quality=200, time_delta_distance_us=0, distance=1.5)
    assert pack(enc, msg).hex() == SPEC_FLOW_RAD


def test_first_bytes_on_the_wire_are_the_spec_heartbeat(peer):
    link = make_link(peer, autopilot="px4")
    try:
        assert isinstance(link, MavlinkLink)
        data = peer.read()
        assert data.hex() == SPEC_HEARTBEAT  # at start, before any frame
    finally:
        link.close()


@pytest.mark.parametrize("autopilot, expected, absent", [
    ("ardupilot", {"OPTICAL_FLOW"}, "OPTICAL_FLOW_RAD"),
    ("px4", {"OPTICAL_FLOW_RAD"}, "OPTICAL_FLOW"),
    ("both", {"OPTICAL_FLOW", "OPTICAL_FLOW_RAD"}, None),
])
@pytest.mark.parametrize("baud", [57600, 115200])
def test_message_set_rate_and_byte_budget(peer, autopilot, expected, absent, baud):
    link = make_link(peer, autopilot=autopilot, baud=baud)
    feeder = FrameFeeder(link, fps=FPS)
    sink = bytearray()
    frames = 300  # 3 s of capture time
    try:
        feeder.frames(frames, flow_y=1.0, peer=peer, sink=sink)
        messages = strict_parse(bytes(sink))
    finally:
        link.close()
    names = {m.get_type() for m in messages}
    assert expected <= names and "HEARTBEAT" in names
    if absent:
        assert absent not in names
    span_s = frames / FPS
    rate = link.message_rate_hz
    for name in expected:
        count = len(of_type(messages, name))
        # Frame-aligned emission: the highest rate ≤ the chosen one that divides 100 fps.
        frames_per_message = math.ceil(FPS / rate - 0.25)
        assert count == pytest.approx(span_s * FPS / frames_per_message, abs=2)
        assert count <= rate * span_s + 2
    # ≤ 60 % of the line (8N1 = baud/10 bytes/s) per second of capture time.
    assert len(sink) / span_s <= 0.6 * baud / 10
    assert link.stats["dropped_messages"] == 0
    assert link.stats["bytes_written"] == len(sink)


def test_rate_chosen_from_baud():
    # OPTICAL_FLOW alone at most 17 Hz by default: ArduPilot's EKF3 takes a flow sample only
    # 50 ms after the one before (test_ardupilot_ekf3_fuses_every_default_report)
    assert make_link_no_port(autopilot="ardupilot", baud=57600).message_rate_hz == 17
    assert make_link_no_port(autopilot="ardupilot", baud=57600, message_rate_hz=74).message_rate_hz == 74
    assert make_link_no_port(autopilot="both", baud=57600).message_rate_hz == 33
    # OPTICAL_FLOW_RAD at most 70 Hz by default: PX4 merges what comes faster than its
    # SENS_FLOW_RATE (70 Hz) and averages the qualities (test_links_timing)
    assert make_link_no_port(autopilot="both", baud=115200).message_rate_hz == 67
    assert make_link_no_port(autopilot="px4", baud=921600).message_rate_hz == 70
    assert make_link_no_port(autopilot="ardupilot", baud=921600).message_rate_hz == 17
    assert make_link_no_port(autopilot="px4", baud=921600, message_rate_hz=25).message_rate_hz == 25


def make_link_no_port(**kw):
    link = open_link(LinkConfig(port=None, focal_length_px=F, **kw))
    link.close()
    return link


def test_a_slow_line_gets_the_fewest_reports_the_autopilots_accept(caplog):
    """The line must carry up to 11 reports/s (at least 7: ArduPilot's EKF3 and INAV stop
    using flow older than 200 ms; with a camera near 11 fps every frame is one, to keep them
    <= 180 ms apart) plus the heartbeats, or the link is refused, naming the baud rate whose
    60 % budget would hold them (the 7/s floor alone let 4800 baud through; test_links_timing
    flies these rates)."""
    # The slowest standard bauds still accepted, and the rates their 60 % budgets give:
    # (576 - 21 HEARTBEAT B/s) / 46 B OPTICAL_FLOW, / 56 B OPTICAL_FLOW_RAD; (1152 - 21) / 102 B
    assert make_link_no_port(autopilot="ardupilot", baud=9600).message_rate_hz == 12
    assert make_link_no_port(autopilot="px4", baud=9600).message_rate_hz == 9
    assert "only 9 flow messages/s fit in 9600 baud" in caplog.text
    assert "over the 60 % budget" not in caplog.text
    assert make_link_no_port(autopilot="both", baud=19200).message_rate_hz == 11
    # Below 7 a second the budget still gives way to the floor, and says so (only a
    # non-standard baud between need and budget gets there now): (336 - 21) / 46 = 6.8
    caplog.clear()
    assert make_link_no_port(autopilot="ardupilot", baud=5600).message_rate_hz == 7
    assert "61 % of the line, over the 60 % budget" in caplog.text       # (7 x 46 + 21) / 560
    # need = 1e6 / 90 ms x bytes + 21 B/s of HEARTBEAT
    for autopilot, baud, need, advice in (("ardupilot", 2400, 532, 9600), ("ardupilot", 4800, 532, 9600),
                                          ("px4", 4800, 643, 19200), ("both", 4800, 1154, 38400),
                                          ("both", 9600, 1154, 38400)):
        with pytest.raises(ValueError, match=rf"baud {baud} is too low: up to 11 .* reports per second \(at "
                                             r"least 7, and every frame of a camera near 11 fps; ") as info:
            open_link(LinkConfig(port=None, baud=baud, autopilot=autopilot, focal_length_px=F))
        text = str(info.value)
        assert f"need {need} bytes/s, and {baud} baud carries {baud // 10} bytes/s" in text
        assert f"use {advice} baud or more on both ends" in text and "< 200 ms old" in text
    with pytest.raises(ValueError, match=r"message_rate_hz must be None or >= 7 \(ArduPilot's EKF3 .* 200 ms"):
        LinkConfig(port=None, message_rate_hz=6.9)
    assert LinkConfig(port=None, message_rate_hz=7.0).message_rate_hz == 7


def test_extra_values_are_budgeted_after_the_flow():
    """The extras (4 NAMED_VALUE_FLOATs at 5 Hz: 600 bytes/s) take what the flow leaves:
    all of it from 19200 baud on, less at 9600, nothing where even 0.5 rounds/s do not fit."""
    full = make_link_no_port(autopilot="ardupilot", baud=57600, extra_values=True)
    assert (full.extras_rate_hz, full.message_rate_hz) == (5.0, 17)        # (3456 - 21 - 600) / 46 = 61 > 17
    assert make_link_no_port(autopilot="ardupilot", baud=57600, extra_values=True,
                             message_rate_hz=61).extras_rate_hz == 5.0
    assert make_link_no_port(autopilot="ardupilot", baud=19200, extra_values=True).extras_rate_hz == 5.0
    thin = make_link_no_port(autopilot="ardupilot", baud=9600, extra_values=True)
    assert (thin.extras_rate_hz, thin.message_rate_hz) == (0.7, 10)        # was 5 Hz and 1 flow message/s
    none = make_link_no_port(autopilot="px4", baud=9600, extra_values=True)
    assert (none.extras_rate_hz, none.message_rate_hz) == (0.0, 9)
    assert make_link_no_port(autopilot="ardupilot", baud=9600).extras_rate_hz == 0.0


def fly(peer, *, flow_x, flow_y, frames=100, **kw):
    """Flow messages after the start marker (quality 0 at the first frame, checked here)."""
    link = make_link(peer, autopilot="both", **kw)
    messages = strict_parse(fly_and_close(link, peer, frames, fps=FPS, flow_x=flow_x, flow_y=flow_y))
    flow, rad = of_type(messages, "OPTICAL_FLOW"), of_type(messages, "OPTICAL_FLOW_RAD")
    assert flow[0].quality == 0 and flow[0].flow_x == flow[0].flow_y == 0 and rad[0].quality == 0
    return link, flow[1:], rad[1:]


def test_forward_flight_gives_positive_y(peer):
    # Flying forward, the ground moves down the image: +v. 1.2 px/frame at 100 fps, f = 400 px.
    _, flow, rad = fly(peer, flow_x=0.0, flow_y=1.2)
    expected_rate = 1.2 * FPS / F
    assert len(flow) > 10 and len(rad) > 10
    for m in flow:
        assert m.flow_rate_y == pytest.approx(expected_rate, rel=0.01)
        assert abs(m.flow_rate_x) < 1e-6
        assert m.flow_y > 0 and m.quality == 200 and m.ground_distance == -1.0
    for m in rad:
        assert m.integrated_y > 0
        assert m.integrated_y / (m.integration_time_us / 1e6) == pytest.approx(expected_rate, rel=0.01)
        assert all(math.isnan(g) for g in (m.integrated_xgyro, m.integrated_ygyro, m.integrated_zgyro))
        assert m.distance == -1.0
    # Deci-pixels, same axes, remainder carried: the sum matches 10 × Σv.
    total_v = 1.2 * sum(m.integration_time_us for m in rad) / 1e6 * FPS
    assert sum(m.flow_y for m in flow) == pytest.approx(10 * total_v, abs=1)


def test_focal_length_can_change_for_the_next_reports(peer):
    """``set_focal_length_px`` (the daemon's call when a camera opened late delivers a
    cropped image): the rates of the reports after it use the new focal length."""
    link = make_link(peer, autopilot="both")
    with pytest.raises(ValueError, match="focal_length_px"):
        link.set_focal_length_px(float("nan"))
    link.set_focal_length_px(2 * F)
    messages = strict_parse(fly_and_close(link, peer, 60, fps=FPS, flow_x=0.0, flow_y=1.2))
    flow = of_type(messages, "OPTICAL_FLOW")[1:]
    assert len(flow) > 10
    assert all(m.flow_rate_y == pytest.approx(1.2 * FPS / (2 * F), rel=0.01) for m in flow)


def test_rightward_flight_gives_negative_x(peer):
    # Moving right, the ground moves left in the image: -u.
    _, flow, rad = fly(peer, flow_x=-0.8, flow_y=0.0)
    for m in flow:
        assert m.flow_rate_x == pytest.approx(-0.8 * FPS / F, rel=0.01)
        assert m.flow_x < 0
    for m in rad:
        assert m.integrated_x < 0 and abs(m.integrated_y) < 1e-9
        assert m.integrated_x == pytest.approx(-0.8 / F * m.integration_time_us / 1e4, rel=0.01)


def test_90_degree_mounting_rotates_axes(peer):
    # Camera turned 90° clockwise (image top to the right): forward flight moves the ground
    # to the vehicle's rear, which is the image's right (+u). The link must report forward
    # flight (+y), exactly as a default-mounted camera would.
    _, flow, rad = fly(peer, flow_x=1.2, flow_y=0.0, mounting_rotation_deg=90)
    for m in rad:
        assert m.integrated_y > 0 and abs(m.integrated_x) < 1e-9
    for m in flow:
        assert m.flow_rate_y == pytest.approx(1.2 * FPS / F, rel=0.01)


def test_ground_distance_and_ids(peer):
    _, flow, rad = fly(peer, flow_x=0.0, flow_y=1.0, frames=20, ground_distance_m=1.5, sysid=42, compid=159,
                       sensor_id=3)
    assert flow[0].ground_distance == pytest.approx(1.5) and rad[0].distance == pytest.approx(1.5)
    assert flow[0].sensor_id == 3 and rad[0].sensor_id == 3
    assert flow[0].get_srcSystem() == 42 and flow[0].get_srcComponent() == 159


def test_a_ground_distance_of_zero_goes_out_as_unknown(peer):
    # (the config refuses 0; a LinkConfig made in code gets -1, not a real 0 m range)
    _, flow, rad = fly(peer, flow_x=0.0, flow_y=1.0, frames=20, ground_distance_m=0.0)
    assert flow[0].ground_distance == -1.0 and rad[0].distance == -1.0


def test_integration_time_is_real_elapsed_time_and_drops_do_not_spike(peer):
    link = make_link(peer, autopilot="px4", message_rate_hz=50)
    # 100 fps with every 7th frame lost: the next frame carries two frames of motion.
    rad = of_type(strict_parse(fly_and_close(link, peer, 200, fps=FPS, flow_y=1.0, skip_every=7)),
                  "OPTICAL_FLOW_RAD")
    assert len(rad) > 50
    for prev, cur in zip(rad, rad[1:]):
        # time_usec is the capture time of the newest frame: consecutive differences are
        # exactly the integration times (continuous intervals, no overlap, no hole).
        assert cur.integration_time_us == cur.time_usec - prev.time_usec
        assert cur.integration_time_us in (20_000, 30_000)
        assert cur.integrated_y / cur.integration_time_us * 1e6 == pytest.approx(FPS / F, rel=1e-4)
    assert link.stats["integration_restarts"] == 0


def test_blind_camera_quality_zero_and_heartbeats_go_on(peer):
    link = make_link(peer, autopilot="both")
    sink = bytearray()
    try:
        FrameFeeder(link, fps=FPS).frames(50, flow_y=1.0, peer=peer, sink=sink)
        before = len(strict_parse(bytes(sink)))
        # Camera blind for 5 s of host time: only service() is called (simulated clock,
        # advanced in 10 ms steps; counts are checked against it, not against the wall clock).
        start = host_us()
        for step in range(1, 501):
            link.service(start + step * 10_000)
            sink.extend(peer.read())
    finally:
        link.close()
    messages = strict_parse(bytes(sink))[before:]
    heartbeats = of_type(messages, "HEARTBEAT")
    flow = of_type(messages, "OPTICAL_FLOW")
    rad = of_type(messages, "OPTICAL_FLOW_RAD")
    assert len(heartbeats) == pytest.approx(5, abs=1)  # 1 Hz
    assert len(flow) == pytest.approx(47, abs=4) and len(rad) == len(flow)  # 10 Hz after 0.3 s
    assert all(m.quality == 0 and m.flow_rate_x == 0 and m.flow_rate_y == 0 for m in flow)
    assert all(m.quality == 0 and 0 < m.integration_time_us < 500_000 for m in rad)
    # ArduPilot needs < 0.5 s between messages, PX4 needs continuity: time_usec advances by
    # the integration time.
    for prev, cur in zip(rad, rad[1:]):
        assert cur.time_usec - prev.time_usec == cur.integration_time_us


def test_blind_quality_zero_frames_from_the_daemon(peer):
    """The daemon's own quality-0 keep-alive samples (every 0.1 s) become quality-0 reports."""
    link = make_link(peer, autopilot="px4")
    sink = bytearray()
    try:
        feeder = FrameFeeder(link, fps=FPS)
        feeder.frames(21, flow_y=1.0, peer=peer, sink=sink)  # 10 reports of 2 frames (≥ 1/70 s)
        t = feeder.t_us + 250_000
        for _ in range(10):
            now = host_us()
            link.submit(FlowSample(timestamp_us=t, capture_host_us=now, flow_x=0.0, flow_y=0.0, quality=0))
            link.service(now)
            t += 100_000
        sink.extend(peer.read())
    finally:
        link.close()
    rad = of_type(strict_parse(bytes(sink)), "OPTICAL_FLOW_RAD")
    blind = [m for m in rad[1:] if m.quality == 0]  # rad[0]: the start marker of the first frame
    assert len(blind) == 10
    assert blind[0].integration_time_us == 250_000
    assert all(m.integration_time_us == 100_000 for m in blind[1:])


def test_reads_autopilot_heartbeat_and_survives_garbage(peer):
    link = make_link(peer, autopilot="ardupilot")
    rng = __import__("random").Random(3)
    try:
        fc = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        fc_heartbeat = fc.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           0, 0, mavlink2.MAV_STATE_STANDBY).pack(fc)
        garbage = bytes(rng.getrandbits(8) for _ in range(10_000))
        feeder = FrameFeeder(link, fps=FPS)
        sink = bytearray()
        peer.write(garbage[:5000] + fc_heartbeat + garbage[5000:] + fc_heartbeat)
        for _ in range(20):
            feeder.frames(5, flow_y=1.0, peer=peer, sink=sink)
        assert link.stats["rx_heartbeat"] == {"sysid": 1, "compid": 1, "type": mavlink2.MAV_TYPE_QUADROTOR,
                                              "autopilot": mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              "system_status": mavlink2.MAV_STATE_STANDBY}
        assert link.stats["rx_bytes"] == len(garbage) + 2 * len(fc_heartbeat)
        assert link.stats["rx_messages"].get("HEARTBEAT", 0) >= 1
        assert link.stats["internal_errors"] == 0
        # ... and it still sends valid flow.
        assert len(of_type(strict_parse(bytes(sink)), "OPTICAL_FLOW")) > 10
    finally:
        link.close()


def test_latencies_are_reported_once(peer):
    link = make_link(peer)
    try:
        FrameFeeder(link, fps=FPS).frames(40, flow_y=1.0, peer=peer, sink=bytearray())
        lat = link.latencies_us()
        assert len(lat) == link.stats["messages_sent"]["OPTICAL_FLOW"]
        assert all(0 <= v < 1_000_000 for v in lat)
        assert link.latencies_us() == []
    finally:
        link.close()


def test_extra_values_go_out_as_named_value_float_only_when_enabled(tmp_path):
    """Issue #6 cues (expansion, time to contact, balance) ride on NAMED_VALUE_FLOAT, and
    the CSV message log has their name, value and sequence number (blank rows before)."""
    import csv
    import os

    from pymavlink.dialects.v20 import common as mavlink2

    from firmware_py.links import FlowSample, LinkConfig, open_link

    for enabled in (False, True):
        master, slave = os.openpty()
        os.set_blocking(master, False)
        log_path = tmp_path / f"sent_{enabled}.csv"
        link = open_link(LinkConfig(port=os.ttyname(slave), baud=921600, autopilot="ardupilot",
                                    focal_length_px=300.0, extra_values=enabled, message_log=str(log_path)))
        try:
            for i in range(50):  # 0.5 s of frames at 100 fps
                link.submit(FlowSample(timestamp_us=i * 10_000, capture_host_us=i * 10_000,
                                       flow_x=1.0, flow_y=0.0, quality=200,
                                       extras=(("expansion", 0.02), ("ttc_s", 0.5))))
                link.service(i * 10_000)
            import time

            time.sleep(0.05)
            data = b""
            while True:
                try:
                    chunk = os.read(master, 65536)
                except BlockingIOError:
                    break
                if not chunk:
                    break
                data += chunk
        finally:
            link.close()
            os.close(master)
            os.close(slave)
        parser = mavlink2.MAVLink(None)
        msgs = [m for m in parser.parse_buffer(data) or [] if m.get_type() == "NAMED_VALUE_FLOAT"]
        if not enabled:
            assert msgs == []
        else:
            names = {m.name for m in msgs}
            assert names == {"expansion", "ttc_s"}
            values = {m.name: m.value for m in msgs}
            assert abs(values["expansion"] - 0.02) < 1e-6 and abs(values["ttc_s"] - 0.5) < 1e-6
            # 5 Hz over 0.5 s of capture time, two names: 2-3 reports each
            assert 4 <= len(msgs) <= 6
            with open(log_path, newline="") as f:
                rows = [r for r in csv.DictReader(f) if r["message"] == "NAMED_VALUE_FLOAT"]
            assert [r["name"] for r in rows] == [m.name for m in msgs]
            assert [float(r["value"]) for r in rows] == pytest.approx([m.value for m in msgs], rel=1e-6)  # (float32)
            assert [int(r["seq"]) for r in rows] == [m.get_seq() for m in msgs]
