"""End to end as a process: ``emdflowd --source FILE --serial PTY --frames N``; the pty's
other end is read with pymavlink (ArduPilot, PX4) or an independent MSP v2 decoder (INAV),
and the flow's signs and size must match the file's known motion."""

from __future__ import annotations

import os
import sys
import statistics

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import (  # noqa: E402
    Drain, PtyPair, engine_backend, flight_frames, parse_mavlink, parse_msp_v2, run_cli, write_video,
)

FPS = 50.0
WIDTH, HEIGHT = 160, 120
FLOW = (2.0, -1.5)          # px/frame: ground moves right and up in the image
FOCAL = WIDTH               # documented default focal length of video: sources
FRAMES = 30


@pytest.fixture(scope="module")
def flight_file(tmp_path_factory):
    frames = flight_frames(FRAMES + 12, flow=FLOW, width=WIDTH, height=HEIGHT)
    return write_video(tmp_path_factory.mktemp("e2e") / "flight.mkv", frames, fps=FPS)


@pytest.fixture
def config_file(tmp_path):
    path = tmp_path / "emdflow.toml"
    path.write_text(f'[engine]\nbackend = "{engine_backend()}"\n[daemon]\nlog_interval_s = 1.0\n')
    return path


def _run(source, autopilot, config_file, *extra):
    pty = PtyPair()
    drain = Drain(pty.master)
    choice = ["--autopilot", autopilot] if autopilot else []
    try:
        result = run_cli(["--config", config_file, "--source", source, "--serial", pty.path,
                          *choice, "--baud", "921600", "--frames", FRAMES, *extra])
    finally:
        data = drain.stop()
        pty.close()
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    return data, result


def _heartbeats_ok(msgs):
    beats = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert beats, "no HEARTBEAT"
    assert all(m.autopilot == 8 and m.get_srcSystem() == 1 and m.get_srcComponent() == 158 for m in beats)


def _good(msgs, name):
    return [m for m in msgs if m.get_type() == name and m.quality > 0]


@pytest.mark.parametrize("scheme", ["video", "depthai-replay"])
def test_ardupilot_optical_flow_matches_the_motion(flight_file, config_file, scheme):
    if scheme == "depthai-replay":
        pytest.importorskip("depthai")
    data, result = _run(f"{scheme}:{flight_file}", "ardupilot", config_file)
    msgs = parse_mavlink(data)
    _heartbeats_ok(msgs)
    assert not [m for m in msgs if m.get_type() == "OPTICAL_FLOW_RAD"]   # ArduPilot's set only
    good = _good(msgs, "OPTICAL_FLOW")
    assert len(good) >= FRAMES // 2, [m.get_type() for m in msgs]
    rate_x = statistics.median(m.flow_rate_x for m in good)
    rate_y = statistics.median(m.flow_rate_y for m in good)
    # spec: flow_rate_x = +u·fps/f, flow_rate_y = +v·fps/f
    assert rate_x == pytest.approx(FLOW[0] * FPS / FOCAL, rel=0.35)
    assert rate_y == pytest.approx(FLOW[1] * FPS / FOCAL, rel=0.35)
    assert statistics.median(m.flow_x for m in good) > 0 > statistics.median(m.flow_y for m in good)
    # the status line reports latency percentiles
    assert "latency capture->serial p50" in result.stderr


def test_px4_optical_flow_rad_matches_the_motion(flight_file, config_file):
    data, _ = _run(f"video:{flight_file}", "px4", config_file)
    msgs = parse_mavlink(data)
    _heartbeats_ok(msgs)
    assert not [m for m in msgs if m.get_type() == "OPTICAL_FLOW"]
    good = _good(msgs, "OPTICAL_FLOW_RAD")
    assert len(good) >= FRAMES // 2
    for m in good:  # integration time comes from the file's clock, not the wall clock
        assert m.integration_time_us % 20_000 == 0 and m.integration_time_us > 0
    per_s_x = sum(m.integrated_x for m in good) / sum(m.integration_time_us for m in good) * 1e6
    per_s_y = sum(m.integrated_y for m in good) / sum(m.integration_time_us for m in good) * 1e6
    assert per_s_x == pytest.approx(FLOW[0] * FPS / FOCAL, rel=0.35)      # +u/f per frame
    assert per_s_y == pytest.approx(FLOW[1] * FPS / FOCAL, rel=0.35)      # +v/f per frame


def test_inav_msp_counts_match_the_motion(flight_file, config_file):
    data, _ = _run(f"video:{flight_file}", "inav", config_file)
    frames = [(fn, payload) for fn, payload in parse_msp_v2(data) if fn == 0x1F02]
    assert len(frames) >= 5
    assert not parse_mavlink(data)                 # MSP only on this port
    good = [(int.from_bytes(p[1:5], "little", signed=True), int.from_bytes(p[5:9], "little", signed=True))
            for _, p in frames if p[0] > 0]
    motion_x = sum(x for x, _ in good)
    motion_y = sum(y for _, y in good)
    # firmware_py.links.msp: motion = -opflow_scale(10.5) * degrees(integrated angle)
    assert motion_x < 0 < motion_y
    assert abs(motion_y / motion_x) == pytest.approx(abs(FLOW[1] / FLOW[0]), rel=0.35)


def test_protocol_mavlink_alone_sends_both_flow_messages(flight_file, config_file):
    data, _ = _run(f"video:{flight_file}", None, config_file, "--protocol", "mavlink")
    names = [m.get_type() for m in parse_mavlink(data)]
    assert {"HEARTBEAT", "OPTICAL_FLOW", "OPTICAL_FLOW_RAD"} <= set(names)
