"""``emdflowd --demo``: headless, a live table read back from the pty by pymavlink."""

from __future__ import annotations

import os
import sys
import math
import re

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import engine_backend, flight_frames, run_cli, start_cli, write_video  # noqa: E402


def test_demo_prints_live_telemetry_and_a_summary(tmp_path):
    config = tmp_path / "demo.toml"
    backend = engine_backend()
    size = "" if backend == "opencl" else "[source]\nwidth = 96\nheight = 72\n"  # numpy is slow
    config.write_text(f'[engine]\nbackend = "{backend}"\n{size}')
    result = run_cli(["--demo", "--frames", "250", "--config", config], timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr[-3000:]
    lines = result.stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.lstrip().startswith("t [s]"))
    assert "latency p50/p99 ms" in lines[header] and "quality" in lines[header]
    rows = [line for line in lines[header + 1:] if re.match(r"\s+\d+\.\d\s", line)]
    assert rows, result.stdout
    # a row: time, frames/s, msgs/s, heartbeats, latency p50 / p99, flow rate x,y, truth x,y, quality
    fields = re.findall(r"[-+]?\d+\.?\d*", rows[-1])
    assert int(fields[1]) > 0 and int(fields[2]) > 0
    # (the quality of the row's last message: 0 for the six after a frame the paced flight
    # skipped on a loaded machine, "uneven")
    assert any(int(re.findall(r"[-+]?\d+\.?\d*", row)[-1]) > 0 for row in rows), rows
    summary = lines[-1]
    match = re.search(r"summary: 250 frames .* received (\d+) OPTICAL_FLOW \+ (\d+) HEARTBEAT .*"
                      r"latency capture->serial p50 ([\d.]+) ms p99 ([\d.]+) ms", summary)
    assert match, summary
    flows, beats, p50, p99 = int(match[1]), int(match[2]), float(match[3]), float(match[4])
    # (ArduPilot's 17 reports a second by default: one per six frames of 250)
    assert flows >= 35 and beats >= 1 and 0 < p50 <= p99
    assert "Traceback" not in result.stderr


def test_demo_link_ignores_the_files_link_keys(tmp_path):
    """A flight's configuration for INAV (MSP) with a message log: the demo still speaks
    MAVLink into its own pseudo-terminal, and writes nothing into the flight's log."""
    from io import StringIO

    from firmware_py.demo import run_demo

    flight_log = tmp_path / "flight.csv"
    config = tmp_path / "inav.toml"
    config.write_text('[link]\nport = "/dev/ttyAMA0"\nbaud = 57600\nautopilot = "inav"\nprotocol = "msp"\n'
                      f'message_log = "{flight_log}"\n')
    out = StringIO()
    code = run_demo(frames=120, source="synthetic:circle=2,period=1", config_path=str(config), out=out,
                    backend=engine_backend(), size=(96, 72))
    summary = out.getvalue().splitlines()[-1]
    assert code == 0, out.getvalue()
    match = re.search(r"received (\d+) OPTICAL_FLOW", summary)
    assert match and int(match[1]) > 0, summary
    assert not flight_log.exists()


def test_demo_rejects_a_frame_count_below_one():
    for count in ("0", "-3"):
        result = run_cli(["--demo", "--frames", count], timeout=60)
        assert result.returncode == 2, result.stdout + result.stderr
        assert f"--frames {count}: must be >= 1" in result.stderr
        assert "summary:" not in result.stdout


def test_demo_stops_on_its_own_after_the_set_time():
    # no --frames: the default run time is 10 s; run_demo's own parameter keeps this test short
    from io import StringIO

    from firmware_py.demo import DEMO_SECONDS, run_demo

    assert DEMO_SECONDS == 10.0
    out = StringIO()
    code = run_demo(seconds=2.5, source="synthetic:circle=2,period=1", config_path=None, out=out,
                    backend=engine_backend(), size=(96, 72))
    text = out.getvalue()
    assert code == 0, text
    assert text.count("\n") >= 4 and "summary:" in text.splitlines()[-1]


def test_demo_without_a_usable_opencl_device_says_why_and_runs_on_numpy(monkeypatch):
    """Where no OpenCL device can run the kernels the demo still shows the appliance: it
    prints the reason and the fix, then flies on the numpy reference."""
    from io import StringIO

    from firmware_py.demo import run_demo

    monkeypatch.setenv("EMDFLOW_OPENCL_DEVICE", "no-such-device")
    out = StringIO()
    code = run_demo(frames=40, source="synthetic:circle=2,period=1", config_path=None, out=out, size=(96, 72))
    text = out.getvalue()
    assert code == 0, text
    assert "OpenCL is not usable here" in text and "no-such-device" in text
    assert "every k-th frame, evenly spaced" in text  # the slow engine gets a steady subset
    assert "-> numpy engine ->" in text and "summary: 40 frames" in text.splitlines()[-1]
    assert "ON THE NUMPY REFERENCE" in text.splitlines()[-1]  # the engine check must not pass quietly


def test_demo_with_a_texture_that_does_not_exist_exits_2_without_a_traceback(tmp_path):
    """The demo made its flight's truth outside its checks: a traceback and exit 1, where
    emdflowd says what is wrong in one line and exits 2 (the URI's syntax is fine)."""
    config = tmp_path / "badtex.toml"
    config.write_text('[source]\nuri = "synthetic:texture=nosuch"\n')
    for args in (["--source", "synthetic:texture=nosuch"], ["--config", config]):
        result = run_cli(["--demo", "--frames", "5", *args], timeout=60)
        assert result.returncode == 2, result.stdout + result.stderr
        errors = [line for line in result.stderr.splitlines() if " ERROR " in line]
        assert len(errors) == 1 and "source 'synthetic:texture=nosuch': texture 'nosuch': not a bundled " \
            "texture" in errors[0], result.stderr
        assert "Traceback" not in result.stderr and "summary:" not in result.stdout


def test_demo_with_a_camera_that_never_delivers_a_frame_exits_2(tmp_path):
    """A camera that is not there: the demo runs its time on heartbeats and quality 0 as
    the daemon would, then says the source delivered nothing and exits 2 (was 0)."""
    from io import StringIO

    from firmware_py.demo import run_demo

    config = tmp_path / "camera.toml"
    config.write_text("[optics]\nfocal_length_px = 300\n")
    uri = "v4l2:/dev/emdflow-test-absent-camera"
    for frames in (None, 5):  # with --frames too: the daemon would wait for them for ever
        out = StringIO()
        code = run_demo(seconds=1.5, frames=frames, source=uri, config_path=str(config), out=out,
                        backend=engine_backend(), size=(96, 72))
        lines = out.getvalue().splitlines()
        assert code == 2, out.getvalue()
        assert lines[-2].startswith("summary: 0 frames") and "HEARTBEAT" in lines[-2]  # the run itself is kept
        assert lines[-1].startswith(f"demo failed: source {uri} delivered no frame in 1.")


def test_demo_banner_shows_the_size_processed(tmp_path):
    """A 160x120 recording is processed at 160x120 (no [source] size): the banner said 320x240."""
    from io import StringIO

    from firmware_py.demo import run_demo

    path = write_video(tmp_path / "small.mkv", flight_frames(24, width=160, height=120), fps=50.0)
    out = StringIO()
    code = run_demo(frames=10, source=f"video:{path}", config_path=None, out=out, backend=engine_backend())
    assert code == 0, out.getvalue()
    banner = out.getvalue().splitlines()[0]
    assert banner.startswith(f"emdflowd demo: video:{path} 160x120 -> "), banner


def test_demo_stops_quietly_when_its_reader_closes_stdout(tmp_path):
    """`emdflowd --demo | head -1`: the next row met a closed pipe, a BrokenPipeError
    traceback and exit 1. Now the demo stops like on Ctrl-C: exit 0, nothing on stderr."""
    config = tmp_path / "demo.toml"
    backend = engine_backend()
    size = "" if backend == "opencl" else "[source]\nwidth = 96\nheight = 72\n"
    config.write_text(f'[engine]\nbackend = "{backend}"\n{size}')
    proc = start_cli(["--demo", "--frames", "300", "--config", config])
    try:
        first = proc.stdout.readline()
        proc.stdout.close()  # as head does after its line; the demo's next row (at 1 s) meets it
        stderr = proc.stderr.read()
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert first.startswith("emdflowd demo: "), first
    assert code == 0, stderr
    assert "Traceback" not in stderr and "BrokenPipe" not in stderr and "Exception ignored" not in stderr, stderr


def test_demo_truth_is_the_true_rate_over_the_reports_frames():
    """The demo's truth column was the flight's rate at the daemon's newest frame: next to a
    report of six frames of a circling flight (ArduPilot's 17 a second) that read 0.06-0.09
    rad/s off on the turning axis. It is now the mean over the frames the message spans,
    from the message before it to its own newest frame (``time_usec`` = index / fps)."""
    from types import SimpleNamespace

    from firmware_py.demo import _truth_rate
    from firmware_py.sources.synthetic import SyntheticSource

    flight = SyntheticSource("", width=320, height=240, fps=100.0)
    daemon = SimpleNamespace(fps=100.0, focal_length_px=320.0)
    message = lambda index: SimpleNamespace(time_usec=index * 10_000)  # noqa: E731
    reader = SimpleNamespace(last_flow=message(106), previous_flow=message(100))
    tx, ty = _truth_rate(daemon, flight, reader)
    mean = [sum(flight.truth(i)[axis] for i in range(101, 107)) / 6 * 100.0 / 320.0 for axis in (0, 1)]
    assert (tx, ty) == pytest.approx(mean, abs=1e-12)
    newest = [c * 100.0 / 320.0 for c in flight.truth(106)]
    assert abs(tx - newest[0]) + abs(ty - newest[1]) > 1e-3  # (the circle turns within a report)
    # the first message: its newest frame alone; no message yet: no truth
    assert _truth_rate(daemon, flight, SimpleNamespace(last_flow=message(106), previous_flow=None)) == \
        pytest.approx(newest)
    assert all(math.isnan(x) for x in _truth_rate(daemon, flight, SimpleNamespace(last_flow=None,
                                                                                   previous_flow=None)))
