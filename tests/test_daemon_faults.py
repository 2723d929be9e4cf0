"""Faults: sources that end or fail, wrong frames, a serial port that vanishes, no OpenCL,
signals and systemd notifications — each handled with a clear log line and no crash."""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import shutil
import signal
import socket
import subprocess
import time
import warnings

import numpy as np
import pytest

import emdflow

from firmware_py.config import Config
from firmware_py.sources import make_source
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import (  # noqa: E402
    Drain, FaultySource, PtyPair, engine_backend, flight_frames, parse_mavlink, run_cli, run_daemon, start_cli,
    stop_cli, write_video,
)


def _config(tmp_path, text=""):
    path = tmp_path / "emdflow.toml"
    path.write_text(f'[engine]\nbackend = "{engine_backend()}"\n{text}')
    return path


def _flow_qualities(msgs):
    return [(m.get_type(), getattr(m, "quality", None)) for m in msgs if m.get_type() in ("OPTICAL_FLOW", "HEARTBEAT")]


@pytest.mark.parametrize("threading", ["single", "capture-thread"])
def test_a_video_file_that_ends_stops_the_daemon_after_its_last_frame(tmp_path, threading):
    """A recording is finished at its end (exit 0): every frame processed and its flow
    sent, no reopen and no blind phase; ``--frames`` beyond the file's length is a cap, not
    a loop (``[source] loop = true`` replays a file)."""
    clip = write_video(tmp_path / "short.avi", flight_frames(12, width=96, height=72), fps=50)
    # the paper's model: its 3-frame history fits a 12-frame clip (the extended model needs 12)
    # (a report every frame: ArduPilot's default is 17 a second)
    config = _config(tmp_path, f'model = "paper"\n[daemon]\nthreading = "{threading}"\n[link]\nmessage_rate_hz = 100.0\n')
    pty = PtyPair()
    drain = Drain(pty.master)
    try:
        result = run_cli(["--config", config, "--source", f"video:{clip}", "--serial", pty.path,
                          "--autopilot", "ardupilot", "--baud", "921600", "--frames", 30])
    finally:
        data = drain.stop()
        pty.close()
    assert result.returncode == 0, result.stderr[-3000:]
    err = result.stderr
    assert "short.avi: end of stream: stopping" in err
    assert "reopening" not in err and "camera blind" not in err and "Traceback" not in err
    assert "reopens 0 blind 0" in err                           # the final status line
    flows = [m for m in parse_mavlink(data) if m.get_type() == "OPTICAL_FLOW"]
    if threading == "single":                                   # one per frame of the file
        assert len(flows) == 12
        assert [m.quality > 0 for m in flows] == [False] * 3 + [True] * 9
    else:  # (a capture thread may pass a subset of an unpaced file on a loaded machine,
        # and a frame it passes over makes the next three uneven: sent with quality 0)
        assert 4 <= len(flows) <= 12
        assert flows[-1].quality > 0 or re.search(r"uneven [1-9]", err), [m.quality for m in flows]


def _run_on_a_pty(tmp_path, source, *, frames):
    """``emdflowd`` on ``source`` with the default configuration, its port a fresh pty;
    returns the finished process."""
    pty = PtyPair()
    try:
        return run_cli(["--config", _config(tmp_path), "--source", source, "--serial", pty.path, "--frames", frames])
    finally:
        pty.close()


def test_a_recording_of_a_size_the_engine_cannot_take_names_the_file(tmp_path):
    """A file's own frame size outside the engine's limits is the source's problem, and
    [source] width and height its fix: the message said "[engine]: frame size 2x2"."""
    clip = write_video(tmp_path / "dot.mkv", np.zeros((5, 2, 2), np.uint8), fps=50)
    result = _run_on_a_pty(tmp_path, f"video:{clip}", frames=5)
    assert result.returncode == 2, result.stderr[-3000:]
    assert (f"source video:{clip}: frame size 2x2: at least 3 px wide and 4 px high; set [source] width and "
            "height to a size the engine takes") in result.stderr, result.stderr[-3000:]
    assert "[engine]" not in result.stderr and "Traceback" not in result.stderr


def test_a_recording_without_one_readable_frame_is_an_error(tmp_path):
    """A file that opens but yields no frame (cut off after its header) ends at once: that
    is bad input, not a finished flight (exit 2, one line naming the source)."""
    clip = write_video(tmp_path / "whole.mkv", flight_frames(12, width=96, height=72), fps=50)
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(clip.read_bytes()[:700])
    result = _run_on_a_pty(tmp_path, f"video:{cut}", frames=50)
    assert result.returncode == 2, result.stderr[-3000:]
    assert "cut.mkv" in result.stderr and "Traceback" not in result.stderr
    assert "ended before its first frame" in result.stderr or "video file" in result.stderr


def _run_inprocess(tmp_path, factory, frames, heartbeat_rate_hz=1.0, settings=()):
    """Run the daemon in this process on 96x72 frames of ``factory``; ``settings``:
    further ``(section, key, value)`` to set. Returns (exit code, daemon, MAVLink messages).
    A report every frame (ArduPilot's default is 17 a second), so each frame's fate shows."""
    config = Config()
    config.set("link", "heartbeat_rate_hz", heartbeat_rate_hz)
    config.set("link", "message_rate_hz", 100.0)
    config.set("source", "uri", "synthetic:u=2,v=1")
    config.set("source", "width", 96)
    config.set("source", "height", 72)
    config.set("engine", "backend", engine_backend())
    config.set("daemon", "reopen_backoff_s", 0.2)
    config.set("daemon", "blind_after_s", 0.05)
    config.set("daemon", "threading", "single")
    for section, key, value in settings:
        config.set(section, key, value)
    code, daemon, data = run_daemon(config, frames=frames, source_factory=factory)
    return code, daemon, parse_mavlink(data)


def test_source_that_raises_is_reopened_and_link_reports_blind(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="emdflowd")
    made = []

    def factory():
        inner = make_source("synthetic:u=2,v=1", width=96, height=72, fps=100)
        made.append(FaultySource(inner, fail_at=15 if not made else None, live=True))  # a camera
        return made[-1]

    code, daemon, msgs = _run_inprocess(tmp_path, factory, frames=40, heartbeat_rate_hz=20.0)
    assert code == 0
    assert daemon.stats.processed == 40 and daemon.stats.reopens == 1 and len(made) == 2
    assert "synthetic:u=2,v=1: read failed (USB camera unplugged); reopening in 0.2 s" in caplog.text
    assert "camera blind" in caplog.text
    if engine_backend() == "opencl":  # the start-up line names the device the engine chose
        assert "96x72 ready in" in caplog.text and f" on {daemon.estimator.device}\n" in caplog.text
    qualities = [m.quality for m in msgs if m.get_type() == "OPTICAL_FLOW"]
    first_blind = qualities.index(0, 5)                    # quality 0 while unplugged ...
    assert any(q > 0 for q in qualities[first_blind:])     # ... and good flow again after
    assert daemon.link.stats["blind_reports"] >= 1
    # heartbeats go on while the camera is away (between the first blind report and the
    # first good flow after it)
    seq = _flow_qualities(msgs)
    good = [i for i, (name, q) in enumerate(seq) if name == "OPTICAL_FLOW" and q > 0]
    blind = [i for i, (name, q) in enumerate(seq) if name == "OPTICAL_FLOW" and q == 0 and i > good[0]]
    assert blind, "no quality-0 flow message while the source was closed"
    gap = seq[blind[0]:next(i for i in good if i > blind[0])]
    assert ("HEARTBEAT", None) in gap


@pytest.mark.parametrize("threading", ["single", "capture-thread"])
def test_a_recording_whose_read_fails_stops_instead_of_replaying(tmp_path, caplog, threading):
    """A file that fails to read part-way (an I/O error) ends the run with exit 2 (bad
    input: systemd's unit does not restart it) and the error logged: reopened like a camera
    it started again at frame 0, flew the same frames again and, failing at the same place,
    looped until --frames stopped it."""
    caplog.set_level(logging.INFO, logger="emdflowd")
    clip = write_video(tmp_path / "part.mkv", flight_frames(30, width=96, height=72), fps=50)
    made = []

    def factory():
        made.append(FaultySource(make_source(f"video:{clip}"), fail_at=20))
        return made[-1]

    code, daemon, msgs = _run_inprocess(tmp_path, factory, frames=200,
                                        settings=[("source", "uri", f"video:{clip}"),
                                                  ("daemon", "threading", threading)])
    assert code == 2
    assert len(made) == 1 and daemon.stats.reopens == 0
    assert daemon.stats.processed <= 19  # the frames before the failure, once (a subset may skip some)
    assert "read failed (USB camera unplugged): a recording is not reopened" in caplog.text
    assert "reopening in" not in caplog.text


def test_an_evidence_row_step_that_starves_the_summary_is_named_at_start(tmp_path, caplog):
    """[engine] evidence_row_step beyond the processed height leaves the summary one
    sampled row: quality 0 on every frame, silently before. The start-up log names the key,
    the rows it samples and the largest step that works; a step that samples enough rows
    says nothing."""
    caplog.set_level(logging.INFO, logger="emdflowd")

    def factory():
        return make_source("synthetic:u=2,v=1", width=96, height=72, fps=100)

    code, _, msgs = _run_inprocess(tmp_path, factory, frames=30, settings=[("engine", "evidence_row_step", 120)])
    assert code == 0
    assert ("[engine] evidence_row_step = 120 samples 1 of the 72 processed rows: the summary sees too few "
            "detections and reports quality 0 on most frames; at most 5 here") in caplog.text
    assert not any(m.quality for m in msgs if m.get_type() == "OPTICAL_FLOW")  # (what it warns of)
    caplog.clear()
    code, _, msgs = _run_inprocess(tmp_path, factory, frames=30, settings=[("engine", "evidence_row_step", 4)])
    assert code == 0 and "evidence_row_step" not in caplog.text
    assert any(m.quality for m in msgs if m.get_type() == "OPTICAL_FLOW")


def test_engine_settings_the_summary_table_was_not_measured_with_are_named_at_start(tmp_path, caplog):
    """[engine] threshold = 8 with the paper's model: the summary reads the table measured
    at 5, less accurately, which nothing said. The start-up log names the key, both values
    and the table, once (not again from summarize); the model's own settings say nothing."""
    caplog.set_level(logging.INFO, logger="emdflowd")
    emdflow.summary.warn_if_uncalibrated.cache_clear()

    def factory():
        return make_source("synthetic:u=2,v=1", width=96, height=72, fps=100)

    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        code, _, msgs = _run_inprocess(tmp_path, factory, frames=30,
                                       settings=[("engine", "model", "paper"), ("engine", "threshold", 8.0)])
    assert code == 0
    assert not [w for w in shown if issubclass(w.category, emdflow.summary.CalibrationWarning)]
    assert ("[engine] threshold = 8.0 (table: 5.0): the paper model's summary table "
            "summary_calibration_diagonal.npz was measured with other settings") in caplog.text
    assert caplog.text.count("measured with other settings") == 1
    assert any(m.quality for m in msgs if m.get_type() == "OPTICAL_FLOW")  # (it still flies)
    caplog.clear()
    code, _, _ = _run_inprocess(tmp_path, factory, frames=30, settings=[("engine", "model", "paper")])
    assert code == 0 and "measured with other settings" not in caplog.text


def test_extra_values_over_msp_are_named_and_not_computed(tmp_path, caplog, monkeypatch):
    """MSP has no message for the looming cues: [link] extra_values with INAV said nothing
    and computed them every frame (~0.4 ms) to drop them."""
    import firmware_py.daemon as daemon_module

    caplog.set_level(logging.INFO, logger="emdflowd")
    calls = []
    monkeypatch.setattr(daemon_module, "looming_cues", lambda field: calls.append(field))

    def factory():
        return make_source("synthetic:u=2,v=1", width=96, height=72, fps=100)

    config = Config()
    for section, key, value in (("source", "uri", "synthetic:u=2,v=1"), ("source", "width", 96),
                                ("source", "height", 72), ("engine", "backend", engine_backend()),
                                ("daemon", "threading", "single"), ("link", "autopilot", "inav"),
                                ("link", "extra_values", True), ("daemon", "log_interval_s", 60.0)):
        config.set(section, key, value)
    code, daemon, data = run_daemon(config, frames=20, source_factory=factory)
    assert code == 0 and daemon.stats.processed == 20
    assert "[link] extra_values = true: msp has no message for the looming cues; not computed or sent" in caplog.text
    assert len(calls) <= 1  # (the status line's, from the last field: not one per frame)


@pytest.mark.parametrize("call", ["read", "close", "open"])
def test_a_hung_driver_call_ends_the_daemon_for_systemd_to_restart(tmp_path, caplog, monkeypatch, call):
    """A camera whose read, or whose close after a failed read, or whose reopen never
    returns (a wedged USB device): the main loop notices the call has not returned for
    the set time and exits 1, so systemd restarts the process (only a new one recovers
    such a driver). Before, a hung open or close went unnoticed: blind for good, the
    watchdog fed."""
    import threading

    import firmware_py.daemon as daemon_module

    monkeypatch.setattr(daemon_module, "_STUCK_DRIVER_S", 1.0)
    caplog.set_level(logging.INFO, logger="emdflowd")
    release = threading.Event()  # (frees the capture thread at the end; 15 s at most)
    made = []

    class Wedged(FaultySource):
        def read(self):
            if call == "read" and self.reads == 14:
                self.reads += 1
                release.wait(15)
            return super().read()

        def close(self):
            if call == "close" and self is made[0]:
                release.wait(15)
            self.inner.close()

        def open(self):
            if call == "open" and len(made) == 2:
                release.wait(15)
            self.inner.open()

    def factory():  # the first camera fails at its 15th read (unplugged), the next ones work
        made.append(Wedged(make_source("synthetic:u=2,v=1", width=96, height=72, fps=100),
                           fail_at=15 if call != "read" and not made else None, live=True))
        return made[-1]

    started = time.monotonic()
    try:
        code, daemon, msgs = _run_inprocess(tmp_path, factory, frames=300,
                                            settings=[("daemon", "threading", "capture-thread")])
    finally:
        release.set()
    assert code == 1, caplog.text[-2000:]
    assert f"source synthetic:u=2,v=1: {call}() has not returned for 1 s (driver hung)" in caplog.text
    assert time.monotonic() - started < 12
    assert daemon.stats.processed < 300


class _FailingEstimator:
    """The daemon's own estimator, whose update raises ``error`` on the calls in ``fail_on``
    (1-based) and on every call from ``fail_from`` on: an OpenCL runtime error, a driver fault."""

    def __init__(self, inner, fail_on=(), fail_from=None,
                 error=RuntimeError("clEnqueueNDRangeKernel failed: OUT_OF_RESOURCES"), reset_fail_on=()):
        self.inner, self.fail_on, self.fail_from, self.error = inner, set(fail_on), fail_from, error
        self.reset_fail_on = set(reset_fail_on)  # (1-based reset calls that raise ``error``)
        self.calls = self.resets = 0

    def update(self, frame):
        self.calls += 1
        if self.calls in self.fail_on or (self.fail_from is not None and self.calls >= self.fail_from):
            raise self.error
        return self.inner.update(frame)

    def reset(self):
        self.resets += 1
        if self.resets in self.reset_fail_on:
            raise self.error
        self.inner.reset()

    def __getattr__(self, name):  # params, device, ...
        return getattr(self.inner, name)


def _failing_factory(made, **failing):
    from firmware_py.daemon import Daemon

    def factory(width, height):
        made.append(_FailingEstimator(Daemon(Config())._default_estimator(width, height), **failing))
        return made[-1]
    return factory


def _engine_config(*settings):
    config = Config()
    for section, key, value in (("source", "uri", "synthetic:u=2,v=1"), ("source", "width", 96),
                                ("source", "height", 72), ("engine", "backend", engine_backend()),
                                ("daemon", "threading", "single"), *settings):
        config.set(section, key, value)
    return config


@pytest.mark.parametrize("stage", ["engine", "summary"])
def test_an_engine_error_skips_the_frame_and_the_flow_comes_back(tmp_path, caplog, monkeypatch, stage):
    """An exception from the engine (a transient OpenCL error) or the summary ended the
    daemon (exit 1: no heartbeat or flow until systemd restarted it, ~2 s and the model's
    history). Now that frame is skipped with one line (the traceback with it), the estimator
    is reset, the link reports quality 0 meanwhile, and good flow comes back."""
    import firmware_py.daemon as daemon_module

    caplog.set_level(logging.INFO, logger="emdflowd")
    made = []
    # (two errors, the flow back between them: the second is counted, not logged again
    # within 5 s)
    factory = _failing_factory(made, fail_on=(30, 60) if stage == "engine" else ())
    if stage == "summary":
        calls = []

        def summarize_twice_failing(field):
            calls.append(field)
            if len(calls) in (30, 60):
                raise FloatingPointError("overflow in the likelihood search")
            return daemon_module.emdflow.summarize(field)
        monkeypatch.setattr(daemon_module, "_summarize", summarize_twice_failing)
    code, daemon, data = run_daemon(_engine_config(("link", "heartbeat_rate_hz", 20.0)), frames=90,
                                    estimator_factory=factory)
    assert code == 0 and daemon.stats.processed == 90
    assert daemon.stats.engine_errors == 2 and made[0].resets >= 2
    error = ("RuntimeError: clEnqueueNDRangeKernel failed: OUT_OF_RESOURCES" if stage == "engine"
             else "FloatingPointError: overflow in the likelihood search")
    assert re.search(rf"{stage} failed on frame \d+ \({re.escape(error)}\): frame skipped, estimator reset "
                     r"before the next one \(1 engine errors so far\)", caplog.text)
    assert sum(r.exc_info is not None for r in caplog.records) == 1  # (the traceback, once)
    assert caplog.text.count("frame skipped, estimator reset") == 1
    assert "engine errors 2 |" in caplog.text  # (the total: line, which names the link's
    assert "internal errors 0 |" in caplog.text  # own errors too: they were counted, never shown)
    qualities = [m.quality for m in parse_mavlink(data) if m.get_type() == "OPTICAL_FLOW"]
    good = [i for i, q in enumerate(qualities) if q > 0]
    assert good and any(q == 0 for q in qualities[good[0]:])  # quality 0 after the error ...
    assert qualities[-1] > 0                                   # ... then good flow again


class _GapSource:
    """A real source whose timestamps jump ``gap_us`` forward from frame ``at`` on (a camera
    that stalled): the daemon resets the estimator there."""

    def __init__(self, inner, *, at, gap_us):
        self.inner, self.at, self.gap_us = inner, at, gap_us

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def read(self):
        from firmware_py.sources import Frame

        frame = self.inner.read()
        if frame is None or frame.index < self.at:
            return frame
        return Frame(frame.image, frame.timestamp_us + self.gap_us, frame.capture_host_us, frame.index)


def test_an_error_in_the_estimators_reset_after_a_frame_gap_is_an_engine_error(tmp_path, caplog):
    """The reset after a frame gap ran outside the engine-error guard: an exception there
    (the OpenCL queue failing as the history buffers are cleared) ended the daemon with exit
    1. Now it is an engine error like one in update: that frame is skipped, the estimator
    reset again, and the flow comes back."""
    caplog.set_level(logging.INFO, logger="emdflowd")
    made = []
    # (reset 1 is the warm-up's, reset 2 the gap's)
    factory = _failing_factory(made, reset_fail_on=(2,),
                               error=RuntimeError("clEnqueueFillBuffer failed: OUT_OF_HOST_MEMORY"))

    def source():
        return _GapSource(make_source("synthetic:u=2,v=1", width=96, height=72, fps=100), at=30, gap_us=2_000_000)

    code, daemon, data = run_daemon(_engine_config(), frames=60, estimator_factory=factory, source_factory=source)
    assert code == 0 and daemon.stats.engine_errors == 1, caplog.text[-2000:]
    assert made[0].resets >= 3  # (the failed one, then the error's own)
    assert re.search(r"reset failed on frame 30 \(RuntimeError: clEnqueueFillBuffer failed: OUT_OF_HOST_MEMORY\): "
                     r"frame skipped, estimator reset", caplog.text)
    qualities = [m.quality for m in parse_mavlink(data) if m.get_type() == "OPTICAL_FLOW"]
    assert qualities[-1] > 0  # (the flow came back after the gap)


def test_a_reset_that_keeps_failing_ends_the_daemon_for_systemd_to_restart(monkeypatch, caplog):
    """A reset that fails is tried again before the next frame, each failure an engine
    error: the flow never comes back, so the daemon exits as for an engine that keeps
    failing (before, the second failure was a debug line and the frames after it ran on
    the uncleared history, their flow sent at full quality)."""
    import firmware_py.daemon as daemon_module

    monkeypatch.setattr(daemon_module, "_ENGINE_FAILURE_EXIT_S", 0.3)
    caplog.set_level(logging.INFO, logger="emdflowd")
    made = []
    factory = _failing_factory(made, reset_fail_on=range(2, 100_000),
                               error=RuntimeError("clEnqueueFillBuffer failed: OUT_OF_HOST_MEMORY"))

    def source():
        return _GapSource(make_source("synthetic:u=2,v=1", width=96, height=72, fps=100), at=30, gap_us=2_000_000)

    with pytest.raises(RuntimeError, match=r"engine errors in \d+\.\d s without a flow between them, the last in "
                                           r"the reset on frame \d+: RuntimeError: clEnqueueFillBuffer"):
        run_daemon(_engine_config(("source", "realtime", True)), frames=1000, estimator_factory=factory,
                   source_factory=source)
    assert made[0].resets >= 10 and made[0].calls < 40  # (no update on the uncleared history)


@pytest.mark.parametrize("failing", [{"fail_from": 20}, {"fail_on": range(20, 1000, 8)}],
                         ids=["every-frame", "every-8th-frame"])
def test_an_engine_that_keeps_failing_ends_the_daemon_for_systemd_to_restart(tmp_path, caplog, monkeypatch,
                                                                             failing):
    """Errors that keep the flow from coming back are not transient: an error on every
    frame, or on every 8th (the extended model's history of 12 frames never refills, and
    each frame between them "succeeded"): after _ENGINE_FAILURE_EXIT_S the daemon stops with
    an error naming it (emdflowd exits 1: systemd restarts the service, which builds the
    engine afresh). Logged at most once per 5 s meanwhile."""
    import firmware_py.daemon as daemon_module

    monkeypatch.setattr(daemon_module, "_ENGINE_FAILURE_EXIT_S", 0.3)
    caplog.set_level(logging.INFO, logger="emdflowd")
    made = []
    started = time.monotonic()
    with pytest.raises(RuntimeError, match=r"\d+ engine errors in 0\.[3-9] s without a flow between them, the last "
                                           r"in the engine on frame \d+: RuntimeError: clEnqueueNDRangeKernel"):
        run_daemon(_engine_config(("source", "fps", 100.0), ("source", "realtime", True)), frames=1000,
                   estimator_factory=_failing_factory(made, **failing))
    assert time.monotonic() - started < 5.0
    assert made[0].calls > 20 and made[0].resets >= 10
    assert caplog.text.count("frame skipped, estimator reset") == 1


def test_a_failing_cue_sends_its_extras_unknown_and_keeps_the_flow(tmp_path, caplog, monkeypatch):
    """The looming cues are extras: one that raises leaves the frame's flow as computed (no
    reset, no skipped frame) and sends its extra values as NaN, counted as an engine error."""
    import firmware_py.daemon as daemon_module

    caplog.set_level(logging.INFO, logger="emdflowd")
    sent, calls = [], []
    real_sample, real_cues = daemon_module.FlowSample, daemon_module.looming_cues

    def recorded(**fields):
        sent.append(real_sample(**fields))
        return sent[-1]

    def cues_once_failing(field):
        calls.append(field)
        if len(calls) == 30:
            raise ZeroDivisionError("float division by zero")
        return real_cues(field)

    monkeypatch.setattr(daemon_module, "FlowSample", recorded)
    monkeypatch.setattr(daemon_module, "looming_cues", cues_once_failing)
    made = []
    code, daemon, _ = run_daemon(_engine_config(("link", "extra_values", True)), frames=40,
                                 estimator_factory=_failing_factory(made))
    assert code == 0 and daemon.stats.processed == 40 and daemon.stats.engine_errors == 1
    assert daemon.stats.resets == 0 and len(sent) == 40
    failed = sent[-11]  # (the frame of the 30th call: the warm-up made none)
    assert failed.quality > 0 and all(math.isnan(v) for _, v in failed.extras), failed
    assert all(math.isfinite(dict(s.extras)["expansion"]) for s in sent[-10:])
    assert "looming cues failed on frame" in caplog.text and "its extra values go out unknown" in caplog.text


def test_cues_that_always_fail_leave_the_status_line_and_the_flow(tmp_path, caplog, monkeypatch):
    """The status line computes the last field's cues again: one that raises there, too,
    must not end the daemon (its frames' extras went out as NaN, logged once per 5 s)."""
    import firmware_py.daemon as daemon_module

    def failing(field):
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setattr(daemon_module, "looming_cues", failing)
    caplog.set_level(logging.INFO, logger="emdflowd")
    code, daemon, data = run_daemon(_engine_config(("link", "extra_values", True), ("source", "fps", 100.0),
                                                   ("source", "realtime", True), ("daemon", "log_interval_s", 0.5)),
                                    frames=80, estimator_factory=_failing_factory([]))
    assert code == 0 and daemon.stats.processed == 80 and daemon.stats.engine_errors == 80
    assert "fps processed" in caplog.text  # (a status line during the run)
    assert caplog.text.count("looming cues failed") == 1
    assert any(m.get_type() == "OPTICAL_FLOW" and m.quality > 0 for m in parse_mavlink(data))


def test_frame_of_wrong_size_is_skipped_with_a_clear_line(tmp_path, caplog):
    def factory():
        return FaultySource(make_source("synthetic:u=2,v=1", width=96, height=72, fps=100), bad_at=10)

    code, daemon, msgs = _run_inprocess(tmp_path, factory, frames=20)
    assert code == 0
    assert daemon.stats.bad_frames == 1 and daemon.stats.processed == 20
    assert "source frame 9 is (80, 96) uint8, expected (72, 96) uint8 (96x72): frame skipped" in caplog.text
    assert sum(m.get_type() == "OPTICAL_FLOW" for m in msgs) >= 15


def test_no_opencl_platform_is_a_clear_error(tmp_path):
    pty = PtyPair()
    try:
        # the ICD loader then finds no OpenCL driver at all, as on a board without one
        result = run_cli(["--source", "synthetic:", "--serial", pty.path, "--frames", 5],
                         env={"OCL_ICD_VENDORS": str(tmp_path / "no-such-vendors-dir")}, timeout=120)
    finally:
        pty.close()
    assert result.returncode == 1
    assert "no OpenCL platform" in result.stderr and 'backend="numpy"' in result.stderr
    assert "Traceback" not in result.stderr


def test_an_opencl_device_choice_that_names_none_is_a_configuration_error(tmp_path):
    """EMDFLOW_OPENCL_DEVICE naming no device is a setting to fix, not a crash: one line
    that names the variable and the devices there are, exit 2 (systemd does not restart)."""
    pytest.importorskip("pyopencl")
    pty = PtyPair()
    try:
        result = run_cli(["--source", "synthetic:", "--serial", pty.path, "--frames", 5],
                         env={"EMDFLOW_OPENCL_DEVICE": "no-such-device"}, timeout=120)
    finally:
        pty.close()
    assert result.returncode == 2, result.stderr
    assert "OpenCL device 'no-such-device' (EMDFLOW_OPENCL_DEVICE) not found among" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.skipif(shutil.which("socat") is None, reason="socat not installed (apt-get install socat)")
def test_serial_port_that_disappears_and_comes_back(tmp_path):
    daemon_end, reader_end = tmp_path / "ttyFC", tmp_path / "ttyReader"

    def start_socat():
        proc = subprocess.Popen(["socat", f"PTY,link={daemon_end},raw,echo=0",
                                 f"PTY,link={reader_end},raw,echo=0"], stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 5
        while not (daemon_end.exists() and reader_end.exists()) and time.monotonic() < deadline:
            time.sleep(0.02)
        return proc

    def read_messages(seconds):
        """What arrives for ``seconds`` after the first bytes (the daemon opens the port
        only once its engine is built: seconds with an empty kernel cache), 60 s at most."""
        fd = os.open(reader_end, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        drain = Drain(fd)
        deadline = time.monotonic() + 60
        while not drain.data and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(seconds)
        data = drain.stop()
        os.close(fd)
        return parse_mavlink(data)

    socat = start_socat()
    config = _config(tmp_path, "[source]\nwidth = 96\nheight = 72\nfps = 50.0\n[link]\nheartbeat_rate_hz = 5.0\n"
                               "[daemon]\nlog_interval_s = 1.0\n")
    daemon = start_cli(["--config", config, "--source", "synthetic:u=2,v=1", "--realtime",
                        "--serial", daemon_end, "--baud", "921600"])
    try:
        before = read_messages(2.0)
        socat.terminate()
        socat.wait(5)                                  # the port is gone (like a USB adapter pulled)
        assert not daemon_end.exists()
        time.sleep(1.0)
        assert daemon.poll() is None                   # the daemon is still running
        socat = start_socat()                          # ... and plugged back in
        after = read_messages(3.0)
    finally:
        daemon.send_signal(signal.SIGTERM)
        out, err = daemon.communicate(timeout=30)
        socat.terminate()
        socat.wait(5)
    assert daemon.returncode == 0, err[-3000:]
    assert {"HEARTBEAT", "OPTICAL_FLOW"} <= {m.get_type() for m in before}, err[-3000:]
    assert {"HEARTBEAT", "OPTICAL_FLOW"} <= {m.get_type() for m in after}
    assert "reopened" in err and "Traceback" not in err


def test_sigterm_stops_cleanly_with_systemd_notifications(tmp_path):
    sock_path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(sock_path)
    server.settimeout(60)
    config = _config(tmp_path, "[source]\nwidth = 96\nheight = 72\n")
    pty = PtyPair()
    drain = Drain(pty.master)
    # systemd's stream: JOURNAL_STREAM names the device and inode of the daemon's stderr
    stderr = open(tmp_path / "journal.log", "w+")
    st = os.fstat(stderr.fileno())
    daemon = start_cli(["--config", config, "--source", "synthetic:u=1,v=1", "--realtime", "--serial", pty.path],
                       env={"NOTIFY_SOCKET": sock_path, "WATCHDOG_USEC": "400000",
                            "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}, stderr=stderr)
    try:
        messages = [server.recv(4096).decode()]
        while not any(m.startswith("WATCHDOG=1") for m in messages):
            messages.append(server.recv(4096).decode())
        daemon.send_signal(signal.SIGTERM)
        daemon.communicate(timeout=30)
        stderr.seek(0)
        err = stderr.read()
        server.settimeout(1)
        try:
            while True:
                messages.append(server.recv(4096).decode())
        except socket.timeout:
            pass
    finally:
        if daemon.poll() is None:
            daemon.kill()
        data = drain.stop()
        pty.close()
        server.close()
        stderr.close()
    assert daemon.returncode == 0, err[-3000:]
    assert messages[0].startswith("READY=1")
    assert "STOPPING=1" in messages
    assert "<6>emdflowd: SIGTERM: stopping" in err            # journald priority prefix
    assert "<6>emdflowd: total:" in err                      # final counters on the way out
    assert parse_mavlink(data)


def test_sighup_while_starting_up_does_not_end_the_daemon(tmp_path):
    """A SIGHUP (logrotate's) that arrives while the daemon still loads its configuration,
    before the loop's handlers exist, killed it silently (exit by signal: a clean stop to
    systemd, no restart): main() ignores it from its first line. The signal is sent from
    inside the configuration loading, so the moment is exact, not a race the test wins."""
    config = _config(tmp_path, "[source]\nwidth = 96\nheight = 72\n")
    pty = PtyPair()
    drain = Drain(pty.master)
    script = ("import os, signal, sys\n"
              "import firmware_py.cli as cli\n"
              "load = cli.load_config\n"
              "def loading(path):\n"
              "    os.kill(os.getpid(), signal.SIGHUP)\n"
              "    return load(path)\n"
              "cli.load_config = loading\n"
              "sys.exit(cli.main(sys.argv[1:]))\n")
    try:
        result = subprocess.run([sys.executable, "-c", script, "--config", str(config), "--source", "synthetic:u=1,v=1",
                                 "--serial", pty.path, "--frames", "20"],
                                capture_output=True, text=True, timeout=120, env=dict(os.environ))
    finally:
        drain.stop()
        pty.close()
    assert result.returncode == 0, (result.returncode, result.stderr[-3000:])
    assert "processed 20 frames (--frames): stopping" in result.stderr


def test_sighup_reopens_the_message_log_and_keeps_flying(tmp_path):
    """logrotate moves the log and sends SIGHUP: the daemon goes on, and its rows go to a new
    file with its own header. SIGHUP used to kill it without a flush (exit by signal, which
    systemd's Restart=on-failure does not restart)."""
    log_path, rotated = tmp_path / "sent.csv", tmp_path / "sent.csv.1"
    config = _config(tmp_path, f'[source]\nwidth = 96\nheight = 72\n[link]\nmessage_log = "{log_path}"\n')
    pty = PtyPair()
    drain = Drain(pty.master)
    daemon = start_cli(["--config", config, "--source", "synthetic:u=1,v=1", "--realtime", "--serial", pty.path,
                        "--autopilot", "ardupilot"])
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and daemon.poll() is None and not (
                log_path.exists() and len(log_path.read_text().splitlines()) > 20):
            time.sleep(0.1)
        log_path.rename(rotated)
        daemon.send_signal(signal.SIGHUP)
        while time.monotonic() < deadline and daemon.poll() is None and not (
                log_path.exists() and len(log_path.read_text().splitlines()) > 20):
            time.sleep(0.1)
        assert daemon.poll() is None
    finally:
        err, data = stop_cli(daemon, drain, pty)
    assert daemon.returncode == 0, err[-3000:]
    assert f"SIGHUP: message log {log_path} reopened" in err and "Traceback" not in err
    old, new = rotated.read_text().splitlines(), log_path.read_text().splitlines()
    assert old[0] == new[0] and new[0].startswith("host_us,message,")   # each file its header
    assert len(old) > 20 and len(new) > 20
    assert all("OPTICAL_FLOW" in row or "HEARTBEAT" in row for row in old[1:] + new[1:])
    # every message on the wire is in one log or the other (the rows' seq: no gap at the swap)
    sent = [m.get_seq() for m in parse_mavlink(data)]
    logged = [int(row.split(",")[4]) for row in old[1:] + new[1:]]
    assert logged == sent[:len(logged)] and len(logged) >= len(sent) - 2


def test_camera_missing_at_start_keeps_heartbeating_blind(tmp_path):
    config = _config(tmp_path, "[daemon]\nreopen_backoff_s = 0.2\nreopen_backoff_max_s = 0.4\n")
    pty = PtyPair()
    drain = Drain(pty.master)
    daemon = start_cli(["--config", config, "--source", "v4l2:/dev/video7", "--focal-length-px", "300",
                        "--serial", pty.path, "--autopilot", "ardupilot"])
    try:
        deadline = time.monotonic() + 60
        while (time.monotonic() < deadline and daemon.poll() is None
               and sum(m.get_type() == "OPTICAL_FLOW" for m in parse_mavlink(bytes(drain.data))) < 5):
            time.sleep(0.1)
    finally:
        err, data = stop_cli(daemon, drain, pty)
    assert daemon.returncode == 0, err[-3000:]
    assert "v4l2:/dev/video7: /dev/video7 does not exist (camera unplugged?)" in err
    assert err.count("does not exist") >= 2                                # retried
    msgs = parse_mavlink(data)
    flows = [m for m in msgs if m.get_type() == "OPTICAL_FLOW"]
    assert any(m.get_type() == "HEARTBEAT" for m in msgs)
    assert len(flows) >= 5 and all(m.quality == 0 and m.flow_rate_x == 0 for m in flows)


def test_camera_without_focal_length_is_a_config_error(tmp_path):
    # (a port that is not there yet passes the port check; /dev/null is refused before this)
    result = run_cli(["--source", "v4l2:/dev/video7", "--serial", tmp_path / "ttyFC"], timeout=60)
    assert result.returncode == 2
    assert "is a camera: give --focal-length-px F or [optics] focal_length_px" in result.stderr


def test_a_wide_lens_is_named_at_start_up_with_its_gain_on_turns(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="emdflowd")

    def factory():
        return make_source("synthetic:u=2,v=1", width=96, height=72, fps=100)

    def run(fov_deg):
        return _run_inprocess(tmp_path, factory, frames=5, settings=[("optics", "horizontal_fov_deg", fov_deg)])

    code, _, _ = run(73.0)
    assert code == 0
    assert "(the processed image's horizontal field of view 73 deg): a turn of the vehicle reads about " \
        "1.18x (x) and 1.10x (y)" in caplog.text
    caplog.clear()
    code, _, _ = run(45.0)  # gains 1.06 / 1.03: no warning
    assert code == 0 and "a turn of the vehicle reads" not in caplog.text
    code, daemon, _ = run(None)  # the synthetic source's f = width: 53 deg
    assert code == 0 and daemon.focal_length_px == 96 and "a turn of the vehicle reads" not in caplog.text
