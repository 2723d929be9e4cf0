"""Transport faults on real ptys: vanished port, stalled reader, missing port, message log."""

import csv
import json
import logging
import os
import sys
import threading

import pytest
from pymavlink.dialects.v20 import common as mavlink2

sys.path.insert(0, os.path.dirname(__file__))
from ptyutil import FrameFeeder, PtyPeer, host_us  # noqa: E402

from firmware_py.links import LinkConfig, open_link  # noqa: E402

FPS = 100.0


def strict_parse(data: bytes):
    messages = mavlink2.MAVLink(None).parse_buffer(data) or []
    assert all(m.get_type() != "BAD_DATA" for m in messages)
    return messages


def robust_parse(data: bytes):
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    return [m for m in parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]


def test_pty_closed_and_reopened_mid_stream(tmp_path, caplog):
    peer = PtyPeer(tmp_path / "ttyFC")
    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot="px4", focal_length_px=400.0))
    feeder = FrameFeeder(link, fps=FPS)
    sink = bytearray()
    try:
        feeder.frames(50, flow_y=1.0, peer=peer, sink=sink)
        first = strict_parse(bytes(sink))
        assert len([m for m in first if m.get_type() == "OPTICAL_FLOW_RAD"]) > 10

        caplog.set_level(logging.DEBUG, logger="firmware_py.links")
        peer.close()  # the device vanishes (USB adapter unplugged)
        feeder.frames(30, flow_y=1.0)  # no exception may escape submit/service
        assert link.stats["port_open"] is False
        assert link.stats["write_errors"] + link.stats["read_errors"] >= 1
        assert peer.path in link.stats["last_error"]
        assert any(peer.path in r.getMessage() for r in caplog.records)

        # Reopen attempts with the device still missing: back-off, no exception.
        now = host_us()
        for k in range(1, 30):
            link.service(now + k * 100_000)
        assert link.stats["open_failures"] >= 2
        assert link.stats["open_failures"] < 29  # backed off, not every call

        peer.open()  # plugged back in at the same path
        later = now + 30 * 100_000
        for k in range(1, 200):  # up to 20 s of simulated back-off
            link.service(later + k * 100_000)
            if link.stats["port_open"]:
                break
        assert link.stats["port_open"] is True and link.stats["reopen_count"] == 1
        sink = bytearray(peer.read())
        feeder.frames(50, flow_y=1.0, peer=peer, sink=sink)
        again = strict_parse(bytes(sink))
        assert again[0].get_type() == "HEARTBEAT"  # a heartbeat greets every (re)open
        rad = [m for m in again if m.get_type() == "OPTICAL_FLOW_RAD"]
        assert len(rad) > 10
        # The simulated seconds without frames were reported as blind (quality 0); the frames
        # after the reopen integrate normally (px4: reports span ≥ 1/70 s = every 2nd frame of 100 fps).
        fresh = [m for m in rad if m.quality == 200]
        assert len(fresh) >= 22 and all(m.integration_time_us == 20_000 for m in fresh)
        assert all(m.quality == 0 and m.integration_time_us < 500_000 for m in rad[:len(rad) - len(fresh)])
        assert link.stats["internal_errors"] == 0
    finally:
        link.close()
        peer.close()


def test_reader_that_stops_reading_drops_oldest_and_never_blocks(tmp_path):
    peer = PtyPeer(tmp_path / "ttyFC")
    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot="both", focal_length_px=400.0))
    feeder = FrameFeeder(link, fps=FPS)
    finished = threading.Event()
    errors = []

    def frame_loop():
        try:
            feeder.frames(3000, flow_y=1.0)  # nobody reads: the pty buffer fills up
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)
        finished.set()

    thread = threading.Thread(target=frame_loop, daemon=True)
    try:
        thread.start()
        # A blocking write would hang here forever; 60 s is far beyond the ~1 s it takes.
        assert finished.wait(60), "submit()/service() blocked on a stalled reader"
        assert not errors
        stats = link.stats
        assert stats["dropped_messages"] > 100
        assert stats["write_errors"] == 0 and stats["port_open"]
        assert link.transport.queued_messages <= link.transport.max_queue_messages + 1
        # The reader wakes up: the stream is intact (only whole messages were dropped) and
        # fresh messages follow.
        backlog = peer.read()
        sink = bytearray()
        feeder.frames(100, flow_y=1.0, peer=peer, sink=sink)
        messages = strict_parse(backlog + bytes(sink))
        assert len(messages) > 100
        newest = [m for m in messages if m.get_type() == "OPTICAL_FLOW_RAD"]
        assert feeder.t_us - newest[-1].time_usec <= 20_000  # caught up with real time
    finally:
        link.close()
        peer.close()


@pytest.mark.parametrize("autopilot", ["px4", "inav"])
def test_a_stalled_line_restarts_the_autopilots_interval_with_quality_0(tmp_path, autopilot):
    """A reader that stops (a stalled line): reports are dropped. The autopilot times each
    report's counts from the report before it (INAV divides them by that time, PX4
    integrates its gyro over it), so the first report it gets after a gap must have quality
    0, and the good ones follow one report period apart. The good reports behind a dropped
    one went out as they were."""
    peer = PtyPeer(tmp_path / "ttyFC")
    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot=autopilot, focal_length_px=400.0))
    feeder = FrameFeeder(link, fps=FPS)
    try:
        sink = bytearray()
        feeder.frames(20, flow_y=1.0, peer=peer, sink=sink)
        feeder.frames(3000, flow_y=1.0)         # nobody reads: the pty buffer fills, reports drop
        assert link.stats["dropped_messages"] > 0
        sink += peer.read()
        feeder.frames(60, flow_y=1.0, peer=peer, sink=sink)
    finally:
        link.close()
        peer.close()
    if autopilot == "px4":
        reports = [(m.time_usec, m.quality) for m in strict_parse(bytes(sink)) if m.get_type() == "OPTICAL_FLOW_RAD"]
    else:
        from daemon_util import parse_msp_v2

        # MSP2_SENSOR_OPTIC_FLOW (0x1F02) carries no time: the wire order and quality tell
        reports = [(None, payload[0]) for function, payload in parse_msp_v2(bytes(sink)) if function == 0x1F02]
    qualities = [q for _, q in reports]
    assert len(qualities) > 20
    # in wire order: a run of good reports, then (after the gap) a quality-0 one, then good again
    first_zero = qualities.index(0, 1)
    assert all(q > 0 for q in qualities[1:first_zero]) and all(q > 0 for q in qualities[first_zero + 1:]), qualities
    if autopilot == "px4":
        times = [t for t, _ in reports]
        steps = [b - a for a, b in zip(times, times[1:])]
        typical = sorted(steps)[len(steps) // 2]
        for (t0, _), (t1, q1) in zip(reports, reports[1:]):
            if t1 - t0 > 1.5 * typical:
                assert q1 == 0, (t0, t1, q1)    # the report after a gap restarts the interval


def _service_until_open(link):
    """Run the link's service (its reopen back-off) over ten simulated seconds, until its
    port is open."""
    now = host_us()
    for k in range(1, 100):
        link.service(now + k * 100_000)
        if link.stats["port_open"]:
            break
    assert link.stats["port_open"] is True


def test_missing_port_is_retried_not_raised(tmp_path):
    path = str(tmp_path / "ttyUSB-not-yet")
    link = open_link(LinkConfig(port=path, baud=57600, autopilot="ardupilot", focal_length_px=400.0))
    try:
        assert link.stats["port_open"] is False
        assert path in link.stats["last_error"]
        FrameFeeder(link, fps=FPS).frames(20, flow_y=1.0)  # runs without a port
        peer = PtyPeer(path)
        _service_until_open(link)
        messages = strict_parse(peer.read())
        assert messages and messages[0].get_type() == "HEARTBEAT"
        peer.close()
    finally:
        link.close()


def test_random_bytes_from_the_autopilot_side_msp(tmp_path):
    peer = PtyPeer(tmp_path / "ttyFC")
    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot="inav", focal_length_px=400.0))
    try:
        peer.write(os.urandom(10_000))
        FrameFeeder(link, fps=FPS).frames(50, flow_y=1.0)
        assert link.stats["rx_bytes"] == 10_000
        assert link.stats["internal_errors"] == 0
    finally:
        link.close()
        peer.close()


def _fly_logged(tmp_path, log_path, *, frames, autopilot):
    """Fly ``frames`` frames at 1 px/frame through a link logging to ``log_path``; the
    messages the autopilot's side received (parsed), including what was flushed on close."""
    peer = PtyPeer(tmp_path / "ttyFC")
    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot=autopilot, focal_length_px=400.0,
                                message_log=str(log_path)))
    sink = bytearray()
    try:
        FrameFeeder(link, fps=FPS).frames(frames, flow_y=1.0, peer=peer, sink=sink)
    finally:
        link.close()
        sink.extend(peer.read())
        peer.close()
    return robust_parse(bytes(sink))


@pytest.mark.parametrize("suffix", [".csv", ".jsonl"])
def test_message_log(tmp_path, suffix):
    log_path = tmp_path / ("sent" + suffix)
    sent = _fly_logged(tmp_path, log_path, frames=60, autopilot="both")
    if suffix == ".csv":
        with open(log_path, newline="") as f:
            rows = list(csv.DictReader(f))
    else:
        rows = [json.loads(line) for line in open(log_path)]
    assert [r["message"] for r in rows] == [m.get_type() for m in sent]
    rad_rows = [r for r in rows if r["message"] == "OPTICAL_FLOW_RAD"]
    rad_msgs = [m for m in sent if m.get_type() == "OPTICAL_FLOW_RAD"]
    for row, msg in zip(rad_rows, rad_msgs):
        assert int(row["time_usec"]) == msg.time_usec
        assert int(row["integration_time_us"]) == msg.integration_time_us
        assert float(row["integrated_y"]) == pytest.approx(msg.integrated_y, rel=1e-6)
        assert int(row["latency_us"]) >= 0


@pytest.mark.parametrize("suffix", [".csv", ".jsonl"])
def test_message_log_survives_a_daemon_restart(tmp_path, suffix):
    """systemd restarts the daemon after a watchdog kill or a hung camera: the restarted
    link appends to the flight's log (one CSV header), even after a row torn by a power loss."""
    log_path = tmp_path / ("sent" + suffix)
    sent = []
    for run in range(2):
        sent += [m.get_type() for m in _fly_logged(tmp_path, log_path, frames=30, autopilot="px4")]
        if run == 0:
            with open(log_path, "a") as f:
                f.write('1234,OPTICAL_FLOW_RAD,56,' if suffix == ".csv" else '{"host_us":1234,"mess')
    lines = log_path.read_text().splitlines()
    torn = [i for i, line in enumerate(lines) if line.startswith(("1234,", '{"host_us":1234'))]
    assert len(torn) == 1                          # the torn row stays on a line of its own
    del lines[torn[0]]
    if suffix == ".csv":
        assert sum(line.startswith("host_us,") for line in lines) == 1
        rows = list(csv.DictReader(lines))
    else:
        rows = [json.loads(line) for line in lines]
    assert [r["message"] for r in rows] == sent    # both runs, in order
    assert sent.count("HEARTBEAT") >= 2 and sent.count("OPTICAL_FLOW_RAD") >= 2 * 10


def test_a_csv_log_of_other_columns_is_set_aside(tmp_path, caplog):
    """A log written by a version with fewer columns (the extra values' name and value came
    later) is renamed to .old rather than appended to under a header its rows do not match;
    a log with this version's header is appended to."""
    from firmware_py.links.message_log import LOG_COLUMNS, MessageLog

    path = tmp_path / "sent.csv"
    old_text = ",".join(LOG_COLUMNS[:-2]) + "\n1,HEARTBEAT,21\n"
    path.write_text(old_text)
    with caplog.at_level(logging.WARNING):
        log = MessageLog(str(path))
    log.write(host_us=2, message="HEARTBEAT", size=21, latency_us=None, fields={})
    log.close()
    assert (tmp_path / "sent.csv.old").read_text() == old_text
    assert path.read_text().splitlines() == [",".join(LOG_COLUMNS), "2,HEARTBEAT,21" + "," * (len(LOG_COLUMNS) - 3)]
    assert "its columns are another version's; moved to" in caplog.text
    log = MessageLog(str(path))  # (this version's header: appended to, nothing moved)
    log.write(host_us=3, message="HEARTBEAT", size=21, latency_us=None, fields={})
    log.close()
    assert len(path.read_text().splitlines()) == 3 and (tmp_path / "sent.csv.old").read_text() == old_text


def test_message_log_reopens_after_a_rotation_and_after_being_disabled(tmp_path):
    """SIGHUP's reopen(): rows after it go to a new file at the path (with its own header),
    and a log a write error closed starts again."""
    from firmware_py.links.message_log import MessageLog

    path = tmp_path / "sent.csv"
    log = MessageLog(path)
    row = dict(message="HEARTBEAT", size=21, latency_us=None, fields={"seq": 1})
    log.write(host_us=1, **row)
    path.rename(tmp_path / "sent.csv.1")
    log.reopen()
    log.write(host_us=2, **row)
    log.close()                      # what a write error does: the log is disabled ...
    log.write(host_us=3, **row)
    log.reopen()                     # ... until the next SIGHUP
    log.write(host_us=4, **row)
    log.close()
    old = list(csv.DictReader(open(tmp_path / "sent.csv.1", newline="")))
    new = list(csv.DictReader(open(path, newline="")))
    assert [r["host_us"] for r in old] == ["1"] and [r["host_us"] for r in new] == ["2", "4"]
    assert log.rows == 3


def test_sighup_creates_a_message_log_that_could_not_be_made_at_start(tmp_path):
    """A message log whose folder could not be made at start-up (a file in its way) is made
    by the next reopen (SIGHUP) once the way is clear; a link without one says so (None)."""
    blocker = tmp_path / "logs"
    blocker.write_text("not a folder")
    path = blocker / "sent.csv"
    link = open_link(LinkConfig(port=None, baud=115200, autopilot="ardupilot", focal_length_px=400.0,
                                message_log=str(path)))
    try:
        assert link.message_log is None
        assert link.reopen_message_log() is None          # still in the way: a warning, None
        blocker.unlink()
        assert link.reopen_message_log() == str(path) and link.message_log is not None
        link.message_log.write(host_us=1, message="HEARTBEAT", size=21, latency_us=None, fields={})
    finally:
        link.close()
    assert path.read_text().splitlines()[0].startswith("host_us,message,")
    plain = open_link(LinkConfig(port=None, baud=115200, autopilot="ardupilot", focal_length_px=400.0))
    assert plain.reopen_message_log() is None
    plain.close()


class HangUpAfterOpen:
    """A serial port that opens but fails at once (a dying adapter, a line that hangs up):
    each time the transport opens the pty's slave, the master is closed under it and a new
    pair is put at the same path for the next open. ``hang_up = False`` lets the next open
    stay up."""

    def __init__(self, peer: PtyPeer):
        self.peer, self.hang_up, self.opened_at = peer, True, []

    def __call__(self, now_us: int) -> None:   # SerialTransport's on_open
        self.opened_at.append(now_us)
        if self.hang_up:
            self.peer.close()
            self.peer.open()


def _run_port(transport, start_us: int, seconds: float, step_us: int = 10_000) -> int:
    """The link's loop on a simulated clock: reopen, write a heartbeat-sized message, read."""
    from firmware_py.links.serial_port import OutgoingMessage

    now = start_us
    for _ in range(int(seconds * 1e6 / step_us)):
        now += step_us
        transport.service(now)
        transport.enqueue(OutgoingMessage(name="HEARTBEAT", data=b"\xfd" + bytes(20)))
        transport.pump(now)
        transport.read_available(now_us=now)
    return now


def test_a_port_another_link_holds_is_not_shared(tmp_path, caplog):
    """Two daemons on one port (the service, and one started by hand): the second does not
    interleave its messages with the first's; it says the port is in use, keeps retrying,
    and takes the port over once the first lets go."""
    caplog.set_level(logging.WARNING, logger="firmware_py.links")
    peer = PtyPeer(tmp_path / "ttyFC")
    config = LinkConfig(port=peer.path, baud=115200, autopilot="ardupilot", focal_length_px=400.0)
    first = open_link(config)
    second = open_link(config)
    try:
        assert first.stats["port_open"] is True and second.stats["port_open"] is False
        assert f"cannot open serial port {peer.path} at 115200 baud: in use: locked by another process" in (
            second.stats["last_error"])
        assert second.stats["last_error"] in caplog.text
        FrameFeeder(second, fps=FPS).frames(20, flow_y=1.0)  # runs without the port
        assert second.stats["bytes_written"] == 0
        first.close()
        _service_until_open(second)
        assert strict_parse(peer.read())[0].get_type() == "HEARTBEAT"
    finally:
        first.close()
        second.close()
        peer.close()


def test_a_port_that_fails_right_after_each_open_is_retried_ever_more_slowly(tmp_path, caplog):
    """Reopened every 0.5 s forever with two warnings each time, such a port filled the log
    (239 warnings a minute). The back-off doubles up to 8 s; only a port that stayed open for
    5 s starts it again at 0.5 s. One warning for the loss, one saying it keeps failing, then a
    summary per minute."""
    from firmware_py.links.serial_port import SerialTransport

    caplog.set_level(logging.DEBUG, logger="firmware_py.links")
    peer = PtyPeer(tmp_path / "ttyFC")
    port = HangUpAfterOpen(peer)
    stats: dict = {}
    transport = SerialTransport(port=peer.path, baud=115200, stats=stats, on_open=port)
    start = host_us()
    try:
        now = _run_port(transport, start, 70.0)
        gaps_s = [(b - a) / 1e6 for a, b in zip(port.opened_at, port.opened_at[1:])]
        assert gaps_s[:6] == pytest.approx([0.51, 1.01, 2.01, 4.01, 8.01, 8.01], abs=0.011)
        assert len(port.opened_at) == 12 and stats["open_failures"] == 0
        assert peer.path in stats["last_error"]
        warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(warnings) == 4, warnings
        assert "closing, will reopen" in warnings[0] and "reopened" in warnings[1]
        assert "again, 0.0 s after reopening: the port fails soon after each open" in warnings[2]
        assert "still fails soon after each open: 10 failure(s) in the last 63 s" in warnings[3]
        assert sum(peer.path in r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG) >= 10

        # The port recovers: open for 5 s, it is healthy; its next loss warns again and is
        # retried after 0.5 s, not 8 s.
        port.hang_up = False
        now = _run_port(transport, now, 8.0)
        assert transport.is_open and len(port.opened_at) == 13
        assert "has stayed open for 5 s after 12 failure(s) in a row: healthy again" in caplog.text
        caplog.clear()
        peer.close()                                  # unplugged ...
        peer.open()                                   # ... and back at once
        reopened = len(port.opened_at)
        _run_port(transport, now, 1.0)
        assert len(port.opened_at) == reopened + 1
        assert (port.opened_at[-1] - now) / 1e6 == pytest.approx(0.51, abs=0.011)
        warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(warnings) == 2 and "closing, will reopen" in warnings[0] and "again" not in warnings[0]
    finally:
        transport.close()
        peer.close()


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_a_reopened_port_gets_nothing_from_while_it_was_away(tmp_path, autopilot):
    """The reports queued while the port was gone are dropped at the reopen, and the first
    report on the new connection has quality 0: its counts began before the autopilot's new
    interval. They were sent as one burst of good reports up to 0.25 s old (INAV reads such
    a burst 1.6 ms apart as ~13x the motion), behind a heartbeat numbered after them. Frames
    keep coming through the outage in real time (no blind keep-alive may stand in for the
    quality-0 report)."""
    import time

    peer = PtyPeer(tmp_path / "ttyFC")
    link = open_link(LinkConfig(port=peer.path, baud=115200, autopilot=autopilot, focal_length_px=400.0))
    feeder = FrameFeeder(link, fps=FPS)
    try:
        feeder.frames(30, flow_x=1.0, peer=peer, sink=bytearray())
        blind_before = link.stats["blind_reports"]
        peer.close()
        lost_at = time.monotonic()
        while link.stats["reopen_count"] == 0 and time.monotonic() - lost_at < 10.0:
            if time.monotonic() - lost_at > 0.1 and peer.master is None and not link.stats["port_open"]:
                peer.open()  # plugged back in; the link reopens it after its back-off
            feeder.frames(1, flow_x=1.0)  # frames every ~10 ms of real time, as a camera's
            time.sleep(0.01)
        assert link.stats["reopen_count"] == 1
        reopened_at_us = feeder.t_us   # the last frame before the reopen
        sink = bytearray(peer.read())
        feeder.frames(60, flow_x=1.0, peer=peer, sink=sink)  # (ArduPilot's reports: 17 a second)
        assert link.stats["blind_reports"] == blind_before
        after = strict_parse(bytes(sink))
        assert after[0].get_type() == "HEARTBEAT"
        seqs = [m.get_seq() for m in after]
        assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:])), seqs
        name = "OPTICAL_FLOW" if autopilot == "ardupilot" else "OPTICAL_FLOW_RAD"
        flow = [m for m in after if m.get_type() == name]
        assert len(flow) > 5 and all(m.time_usec >= reopened_at_us for m in flow), \
            ([m.time_usec for m in flow][:3], reopened_at_us)
        qualities = [m.quality for m in flow]
        assert qualities[0] == 0 and all(q == 200 for q in qualities[1:]), qualities
    finally:
        link.close()
        peer.close()
