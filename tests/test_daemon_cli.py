"""End to end as a process: ``emdflowd --source FILE --serial PTY --frames N``; the pty's
other end is read with pymavlink (ArduPilot, PX4) or an independent MSP v2 decoder (INAV),
and the flow's signs and size must match the file's known motion."""

from __future__ import annotations

import math
import os
import re
import statistics
import subprocess
import sys
import time

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import (  # noqa: E402
    Drain, PtyPair, engine_backend, flight_frames, parse_mavlink, parse_msp_v2, run_cli, start_cli, stop_cli,
    write_video,
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
    # DepthAI's host pipeline corrupts the heap about once in 4 000 starts and then hangs
    # in its crash handler (daemon_util.run_isolated_from_native_crashes): a daemon on a
    # depthai-replay source that hangs or dies by a signal is run again, twice at most
    attempts = 3 if source.startswith("depthai") else 1
    for attempt in range(attempts):
        pty = PtyPair()
        drain = Drain(pty.master)
        choice = ["--autopilot", autopilot] if autopilot else []
        try:
            result = run_cli(["--config", config_file, "--source", source, "--serial", pty.path,
                              *choice, "--baud", "921600", "--frames", FRAMES, *extra], timeout=60)
        except subprocess.TimeoutExpired:
            if attempt + 1 == attempts:
                raise
            continue
        finally:
            data = drain.stop()
            pty.close()
        if result.returncode >= 0 or attempt + 1 == attempts:
            break
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
    # 17 reports a second by default (ArduPilot's EKF3 takes one 50 ms after the last): each
    # spans three of the 50 fps flight's frames, at least 50 ms of capture time
    assert len(good) >= FRAMES // 8, [m.get_type() for m in msgs]
    assert all(b.time_usec - a.time_usec >= 50_000 for a, b in zip(good, good[1:])), [m.time_usec for m in good]
    rate_x = statistics.median(m.flow_rate_x for m in good)
    rate_y = statistics.median(m.flow_rate_y for m in good)
    # spec: flow_rate_x = +u·fps/f, flow_rate_y = +v·fps/f
    assert rate_x == pytest.approx(FLOW[0] * FPS / FOCAL, rel=0.35)
    assert rate_y == pytest.approx(FLOW[1] * FPS / FOCAL, rel=0.35)
    assert statistics.median(m.flow_x for m in good) > 0 > statistics.median(m.flow_y for m in good)
    # the status line reports latency percentiles
    assert "latency capture->serial p50" in result.stderr


def test_px4_optical_flow_rad_matches_the_motion(flight_file, config_file):
    # a fixed ground distance is sent, with a warning: PX4's EKF2 takes it as a rangefinder
    config_file.write_text(config_file.read_text() + "[link]\nground_distance_m = 0.5\n")
    data, result = _run(f"video:{flight_file}", "px4", config_file)
    assert "ground_distance_m = 0.5 with PX4" in result.stderr
    msgs = parse_mavlink(data)
    _heartbeats_ok(msgs)
    assert not [m for m in msgs if m.get_type() == "OPTICAL_FLOW"]
    assert {m.distance for m in msgs if m.get_type() == "OPTICAL_FLOW_RAD"} == {0.5}
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


# -- configuration errors at start-up: exit 2 with the option named ------------------------

@pytest.mark.parametrize("where", ["flag", "file"])
def test_bad_synthetic_option_is_a_configuration_error(tmp_path, where):
    if where == "flag":
        args = ["--source", "synthetic:period=inf", "--serial", "/dev/null"]
        origin = "command line"
    else:
        path = tmp_path / "emdflow.toml"
        path.write_text('[source]\nuri = "synthetic:period=inf"\n')
        args = ["--config", path, "--serial", "/dev/null"]
        origin = str(path)
    result = run_cli(args, timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]      # was an OverflowError traceback, 1
    assert f"{origin}: [source] uri: synthetic option period=inf: must be a finite number" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("kind", ["directory", "regular file"])
def test_a_port_that_can_never_be_a_serial_port_is_a_configuration_error(tmp_path, kind):
    """A path that exists but is no character device (a typo that hits a folder or a file)
    is refused at start (exit 2); a path that does not exist yet is retried instead (see
    test_daemon_faults: a USB adapter plugged in later)."""
    port = tmp_path / "ttyFC"
    port.mkdir() if kind == "directory" else port.write_text("")
    result = run_cli(["--source", "synthetic:", "--serial", port, "--frames", 3], timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]
    assert f"[link] port (--serial) {port}: is a {kind}, not a serial device" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.skipif(not os.path.islink("/sys/dev/char/1:3/subsystem"),
                    reason="no sysfs entry for /dev/null's subsystem (not Linux, or /sys not mounted)")
@pytest.mark.parametrize("where", ["flag", "file"])
def test_a_character_device_that_is_no_tty_is_a_configuration_error(tmp_path, where):
    """/dev/null is a character device, but sysfs files it under 'mem', not 'tty': every
    termios call on it fails, so the port was accepted, warned about once and retried for
    ever, the daemon sending nothing (exit 0 at SIGTERM). Now refused at start (exit 2),
    found without opening the device (an open raises DTR, which resets some boards)."""
    if where == "flag":
        args, origin = ["--serial", "/dev/null"], "configuration"
    else:
        path = tmp_path / "emdflow.toml"
        path.write_text("[link]\nport = '/dev/null'\n")
        args, origin = ["--config", path], str(path)
    result = run_cli(["--source", "synthetic:", *args, "--frames", 3], timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]
    assert (f"{origin}: [link] port (--serial) /dev/null: is a character device of the 'mem' subsystem "
            "(1:3), not a serial port (tty)") in result.stderr, result.stderr[-2000:]
    assert "Traceback" not in result.stderr and "Could not configure port" not in result.stderr


@pytest.mark.parametrize("port, advice", [
    ("tty", "did you mean /dev/tty?"),                                   # /dev/tty is always there
    ("./tty", "did you mean /dev/tty?"),
    ("dev/tty", "did you mean /dev/tty?"),
    ("ttyEMDFLOW9", "give the device's absolute path (there is no /dev/ttyEMDFLOW9 now)"),
    ("null", "give the serial device's absolute path"),                  # /dev/null is no serial port
])
def test_a_relative_port_path_is_a_configuration_error(port, advice):
    """'--serial ttyUSB0' meant /dev/ttyUSB0: resolved against the working directory ('/'
    under systemd) it never appears, and was retried for ever with one warning. Refused at
    start (exit 2), with the /dev path when one exists there."""
    if port in ("null",) and not os.path.islink("/sys/dev/char/1:3/subsystem"):
        pytest.skip("no sysfs entry for /dev/null's subsystem")
    result = run_cli(["--source", "synthetic:", "--serial", port, "--frames", 3], timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]
    assert f"[link] port (--serial) {port}: is a relative path; {advice}" in result.stderr, result.stderr[-2000:]
    assert "Traceback" not in result.stderr


def test_a_relative_port_that_exists_here_is_named_absolutely(tmp_path, monkeypatch):
    """A socat link made in the current folder: the advice is its absolute path (the
    working directory is / under systemd), not a /dev path that does not exist."""
    from firmware_py.links.serial_port import port_problem

    pty = PtyPair()
    try:
        monkeypatch.chdir(tmp_path)
        os.symlink(pty.path, "ttyV0")
        assert port_problem("ttyV0") == ("is a relative path (to the working directory, / under systemd); "
                                         f"give it as {tmp_path / 'ttyV0'}")
        assert port_problem(str(tmp_path / "ttyV0")) is None
        # a stray space from a config file: never appears, was retried for ever
        assert port_problem(str(tmp_path / "ttyV0") + " ") == "has leading or trailing whitespace; a device path has none"
    finally:
        pty.close()


@pytest.mark.parametrize("how", ["device", "symlink"])
def test_a_pseudo_terminal_port_is_accepted(tmp_path, config_file, how):
    """A pty slave (/dev/pts/N; sysfs has no entry for it, which must read as "cannot tell",
    not as "no tty"), by its own path or a symlink to it as socat makes, still carries the link."""
    pty = PtyPair()
    drain = Drain(pty.master)
    port = pty.path
    if how == "symlink":
        port = tmp_path / "ttyFC"
        os.symlink(pty.path, port)
    try:
        result = run_cli(["--config", config_file, "--source", "synthetic:u=1,v=1", "--serial", port,
                          "--baud", "921600", "--frames", 5], timeout=120)
    finally:
        data = drain.stop()
        pty.close()
    assert result.returncode == 0, result.stderr[-3000:]
    assert "HEARTBEAT" in {m.get_type() for m in parse_mavlink(data)}, result.stderr[-3000:]
    assert "Traceback" not in result.stderr


def test_a_missing_absolute_port_is_retried_until_it_appears(tmp_path, config_file):
    """A port that does not exist yet (a USB adapter plugged in later, a udev link) is no
    configuration error: the daemon starts, warns, keeps retrying, and sends once it is there."""
    port = tmp_path / "ttyFC"
    log = tmp_path / "stderr.log"
    with open(log, "w") as stderr:
        daemon = start_cli(["--config", config_file, "--source", "synthetic:u=1,v=1", "--realtime",
                            "--serial", port, "--baud", "921600"], stderr=stderr)
    pty = PtyPair()
    drain = Drain(pty.master)
    try:
        deadline = time.monotonic() + 60                # the engine builds first (kernel cache)
        while f"cannot open serial port {port}" not in log.read_text() and time.monotonic() < deadline:
            assert daemon.poll() is None, log.read_text()[-3000:]
            time.sleep(0.05)
        assert f"cannot open serial port {port}" in log.read_text()
        os.symlink(pty.path, port)                      # ... plugged in
        deadline = time.monotonic() + 30
        while "HEARTBEAT" not in {m.get_type() for m in parse_mavlink(bytes(drain.data))} \
                and time.monotonic() < deadline:
            assert daemon.poll() is None, log.read_text()[-3000:]
            time.sleep(0.1)
    finally:
        _, data = stop_cli(daemon, drain, pty)
    err = log.read_text()
    assert daemon.returncode == 0, err[-3000:]
    assert "HEARTBEAT" in {m.get_type() for m in parse_mavlink(data)}, err[-3000:]
    assert f"serial port {port} open at 921600 baud" in err and "Traceback" not in err


def test_a_pyserial_url_port_is_a_configuration_error():
    """socket:// and other pyserial URLs open through serial_for_url, which the link does
    not use: refused at start instead of failing to open and being retried for ever."""
    result = run_cli(["--source", "synthetic:", "--serial", "socket://127.0.0.1:5760", "--frames", 3], timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]
    assert "[link] port (--serial) socket://127.0.0.1:5760: is a URL" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("autopilot, baud, advice", [("ardupilot", 4800, 9600), ("px4", 4800, 19200),
                                                     ("both", 9600, 38400), ("inav", 1200, 4800)])
def test_a_baud_rate_too_low_for_the_flow_messages_is_a_configuration_error(tmp_path, autopilot, baud, advice):
    """Not even the up to 11 reports per second the link may send fit (at least 7: ArduPilot's
    EKF3 and INAV stop using flow older than 200 ms; every frame of a camera near 11 fps, to
    keep them <= 180 ms apart): refused at start (exit 2) with the baud rate that would do,
    not run into timeouts. (The 4800 and 9600 baud here carried the 7/s floor alone.)"""
    port = tmp_path / "ttyFC"  # (not there: no port error; /dev/null is one, no tty)
    result = run_cli(["--source", "synthetic:", "--serial", port, "--baud", baud, "--autopilot",
                      autopilot, "--frames", 3], timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]
    assert (f"configuration: [link] baud = {baud} (--baud) is too low: up to 11 " in result.stderr
            and "(at least 7, and every frame of a camera near 11 fps; " in result.stderr), result.stderr[-2000:]
    assert "< 200 ms old" in result.stderr
    assert f"use {advice} baud or more on both ends" in result.stderr and "Traceback" not in result.stderr


def test_demo_with_a_missing_video_exits_2(tmp_path):
    """A source that cannot be opened is a usage error for the demo as for emdflowd (was 1)."""
    missing = tmp_path / "missing.mkv"
    result = run_cli(["--demo", "--source", f"video:{missing}", "--frames", 5], timeout=120)
    assert result.returncode == 2, result.stdout[-2000:] + result.stderr[-2000:]
    assert f"video file '{missing}': no such file" in result.stdout


def test_demo_with_a_bad_synthetic_option_exits_2():
    result = run_cli(["--demo", "--source", "synthetic:noise=-1"], timeout=60)
    assert result.returncode == 2
    assert "synthetic option noise=-1: must be >= 0" in result.stderr


def test_demo_takes_the_focal_length_and_refuses_link_options(tmp_path):
    """--focal-length-px was dropped by the demo (the file's [optics] value was used):
    now both give the same truth, 2 px/frame × 100 frames/s / 160 px = 1.25 rad/s. The
    demo's link is its own: a port, baud rate, autopilot or protocol for it is refused
    (exit 2, naming them), not ignored; --realtime is what the demo does anyway."""
    backend = engine_backend()
    engine = f'[engine]\nbackend = "{backend}"\n'
    if backend != "opencl":  # numpy is slow
        engine += "[source]\nwidth = 96\nheight = 72\n"
    plain, focal = tmp_path / "plain.toml", tmp_path / "focal.toml"
    plain.write_text(engine)
    # (the second also flies the local threshold, which the start line names)
    focal.write_text(engine.replace("[engine]\n", '[engine]\nthreshold_mode = "local"\n')
                     + "[optics]\nfocal_length_px = 160\n")
    for args, threshold in ((["--config", plain, "--focal-length-px", "160", "--realtime", "--log-level", "INFO"],
                             "adaptive"), (["--config", focal, "--log-level", "INFO"], "local threshold (64 px tiles")):
        result = run_cli(["--demo", "--frames", "130", *args], timeout=120)
        assert result.returncode == 0, result.stdout + result.stderr[-3000:]
        assert "focal length 160.0 px" in result.stderr, result.stderr[-3000:]  # the daemon's INFO start line
        assert f"extended model, {threshold}" in result.stderr, result.stderr[-3000:]
        rows = [line for line in result.stdout.splitlines() if re.match(r"\s+\d+\.\d\s", line)]
        assert rows, result.stdout
        truth = [float(x) for x in re.findall(r"[-+]\d+\.\d+", rows[-1])[-2:]]
        assert abs(math.hypot(*truth) - 1.25) < 0.01, (args, rows[-1])
    given = [["--serial", "/dev/ttyUSB0"], ["--baud", "57600"], ["--autopilot", "px4"], ["--protocol", "msp"]]
    for extra in [*given, [word for flag in given for word in flag]]:
        result = run_cli(["--demo", "--frames", "5", *extra], timeout=60)
        assert result.returncode == 2, (extra, result.stdout, result.stderr)
        names = ", ".join(extra[::2])
        assert f"command line: {names}: not with --demo, which makes its own link" in result.stderr, result.stderr
        assert "emdflowd demo:" not in result.stdout


# -- logging: journald's format only on systemd's own stream -------------------------------

def test_version_is_the_packages():
    """What a field report quotes: the daemon's version is the installed package's."""
    from emdflow import __version__

    r = run_cli(["--version"])
    assert r.returncode == 0 and r.stdout.strip() == f"emdflowd {__version__}", r.stderr


def test_stderr_is_journal_compares_device_and_inode(monkeypatch):
    from firmware_py.cli import stderr_is_journal

    st = os.fstat(2)
    monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
    assert stderr_is_journal()
    for inherited in (f"{st.st_dev}:{st.st_ino + 1}", "8:1234", "garbage", ""):
        monkeypatch.setenv("JOURNAL_STREAM", inherited)
        assert not stderr_is_journal(), inherited
    monkeypatch.delenv("JOURNAL_STREAM")
    assert not stderr_is_journal()


def test_inherited_journal_stream_keeps_timestamped_lines(tmp_path):
    """A child of a service inherits JOURNAL_STREAM with its stderr a pipe: plain lines."""
    args = ["--source", "synthetic:"]  # no serial port: one ERROR line, exit 2
    inherited = run_cli(args, timeout=60, env={"JOURNAL_STREAM": "8:1234"})
    assert inherited.returncode == 2
    line = inherited.stderr.strip().splitlines()[-1]
    assert re.match(r"\d\d:\d\d:\d\d\.\d{3} ERROR +emdflowd: configuration: no serial port", line), line
    # stderr really is the stream JOURNAL_STREAM names: priority prefix, no timestamp
    with open(tmp_path / "journal.log", "w+") as stream:
        st = os.fstat(stream.fileno())
        code = subprocess.run([sys.executable, "-m", "firmware_py.cli", *args], stderr=stream, timeout=60,
                              env={**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"},
                              cwd=tmp_path).returncode
        stream.seek(0)
        text = stream.read()
    assert code == 2
    assert text.strip().splitlines()[-1].startswith("<3>emdflowd: configuration: no serial port"), text
