"""The daemon's timing with real sources and the real engine: when the link's keep-alive
starts, slow engines and slow frame streams, the extra values' units. Messages are read on
a real pty (pymavlink, the MSP v2 decoder) and from the link's message log (host times)."""

from __future__ import annotations

import csv
import math
import os
import re
import statistics
import sys
import time

import numpy as np
import pytest

import emdflow
from emdflow.synthetic import CameraFlight
from firmware_py.config import Config
from firmware_py.sources import make_source
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import (  # noqa: E402
    FaultySource, engine_backend, flight_frames, parse_mavlink, run_daemon, write_video)


class _SlowerThanRequested:
    """A real source that says ``fps`` (what was requested) but delivers the file's rate,
    like a camera that cannot keep up with the requested frame rate."""

    def __init__(self, inner, fps):
        self.inner, self.fps = inner, fps

    def __getattr__(self, name):
        return getattr(self.inner, name)


class _SlowEngine:
    """The real estimator, taking ``extra_s`` longer per frame (numpy at 640x480, a slow board)."""

    def __init__(self, inner, extra_s):
        self.inner, self.extra_s = inner, extra_s

    def update(self, image):
        time.sleep(self.extra_s)
        return self.inner.update(image)

    def reset(self):
        self.inner.reset()


def _config(uri, *, autopilot="px4", model="paper", settings=None):
    """Single-thread daemon on ``uri``; ``settings``: {(section, key): value}."""
    config = Config()
    config.set("source", "uri", uri)
    config.set("engine", "backend", engine_backend())
    config.set("engine", "model", model)
    config.set("link", "autopilot", autopilot)
    config.set("daemon", "threading", "single")
    for (section, key), value in (settings or {}).items():
        config.set(section, key, value)
    return config


@pytest.mark.parametrize("autopilot, blind_after_s, link_blind_after_s, timeout_s", [
    ("inav", 0.25, 0.15, 0.2),       # the daemon's default must not delay INAV's keep-alive
    ("ardupilot", 1.0, 0.3, 0.5),    # nor a large setting ArduPilot's
])
def test_keepalive_starts_before_the_autopilot_times_out(tmp_path, autopilot, blind_after_s,
                                                         link_blind_after_s, timeout_s):
    made = []

    def factory():
        inner = make_source("synthetic:u=2,v=1", width=96, height=72, fps=100)
        made.append(FaultySource(inner, fail_at=20 if not made else None, live=True))  # a camera
        return made[-1]

    log_path = tmp_path / "sent.csv"
    config = _config("synthetic:u=2,v=1", autopilot=autopilot,
                     settings={("source", "width"): 96, ("source", "height"): 72,
                               ("link", "message_log"): str(log_path), ("daemon", "blind_after_s"): blind_after_s,
                               ("daemon", "reopen_backoff_s"): 1.0})
    code, daemon, _ = run_daemon(config, frames=40, source_factory=factory)
    assert code == 0
    with open(log_path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["message"] != "HEARTBEAT"]
    times = [int(r["host_us"]) for r in rows]
    gaps = [b - a for a, b in zip(times, times[1:])]
    # the camera was away for ~1 s; the flow messages never paused for the autopilot's timeout
    assert max(gaps) < timeout_s * 1e6, max(gaps)
    assert daemon.link.blind_after_s == link_blind_after_s
    assert daemon.stats.reopens == 1 and daemon.link.stats["blind_reports"] >= 5


def test_slow_engine_gets_real_flow_through():
    """0.3 s per frame (more than blind_after_s): the link judges blindness from the last
    submit, so no keep-alive comes between frames and the reports keep their quality."""
    # the synthetic source stamps its frames 10 ms apart however slowly they are made: one
    # report per 10 ms frame is ArduPilot's message set at 100 a second (PX4's reports span
    # >= 1/70 s; ArduPilot's default 17 a second would span six frames)
    config = _config("synthetic:u=2,v=1", autopilot="ardupilot",
                     settings={("source", "width"): 96, ("source", "height"): 72,
                               ("link", "message_rate_hz"): 100.0})

    def slow(width, height):
        real = emdflow.FlowEstimator(width, height, backend=config.engine.backend,
                                     **config.engine.estimator_options())
        return _SlowEngine(real, 0.3)

    code, daemon, data = run_daemon(config, frames=12, estimator_factory=slow)
    assert code == 0
    flow = [m for m in parse_mavlink(data) if m.get_type() == "OPTICAL_FLOW"]
    good = [m for m in flow if m.quality > 0]
    assert len(good) >= 8, [m.quality for m in flow]      # the paper's model needs 3 frames
    assert daemon.link.stats["blind_reports"] <= 1        # before the stream's pace is known
    assert daemon.link.stats["integration_restarts"] == 0
    for m in good:  # 100 fps synthetic flight, v = 1 px/frame, f = 96 px: one frame per report
        assert m.flow_y == pytest.approx(10.0, abs=4)      # deci-pixels
        assert m.flow_rate_y == pytest.approx(100 / 96, rel=0.35)


def test_frames_further_apart_than_the_reset_gap_are_not_each_a_gap(tmp_path):
    """Processed frames 0.33 s apart (a 3 fps camera, or a large frame subset) with
    reset_after_gap_s = 0.25: the estimator is not reset at every frame, and the link
    reports their real flow over their real 0.33 s interval."""
    clip = write_video(tmp_path / "slow.mkv", flight_frames(16, flow=(2.0, -1.5), width=96, height=72), fps=3.0)
    config = _config(f"video:{clip}", settings={("engine", "reset_after_gap_s"): 0.25})
    code, daemon, data = run_daemon(config, frames=15)
    assert code == 0
    assert daemon.stats.resets <= 1                       # the first interval: its pace unknown yet
    rad = [m for m in parse_mavlink(data) if m.get_type() == "OPTICAL_FLOW_RAD"]
    good = [m for m in rad if m.quality > 0]
    assert len(good) >= 10, [m.quality for m in rad]
    assert all(m.integration_time_us == pytest.approx(333_333, abs=1) for m in good)
    seconds = sum(m.integration_time_us for m in good) / 1e6
    # 2 px/frame right, 1.5 px/frame up, 3 frames/s, f = 96 px
    assert sum(m.integrated_x for m in good) / seconds == pytest.approx(2.0 * 3 / 96, rel=0.35)
    assert sum(m.integrated_y for m in good) / seconds == pytest.approx(-1.5 * 3 / 96, rel=0.35)
    assert daemon.link.stats["integration_restarts"] == 0


def test_extra_values_use_the_real_frame_interval(tmp_path):
    """A camera asked for 100 fps that delivers 50: expansion (1/s) and time to contact (s)
    come from the processed frames' capture timestamps, not the nominal rate."""
    rate_per_frame = 0.01
    flight = CameraFlight("gravel", width=160, height=120, flow=(0.0, 0.0), expansion_rate=rate_per_frame,
                          noise_sigma=1.0, supersample=2, seed=0)
    clip = write_video(tmp_path / "zoom.mkv", flight.render_many(60), fps=50.0)
    config = _config(f"video:{clip}", autopilot="ardupilot", model="extended",
                     settings={("link", "extra_values"): True})

    def factory():
        return _SlowerThanRequested(make_source(f"video:{clip}"), fps=100.0)

    code, daemon, data = run_daemon(config, frames=60, source_factory=factory)
    assert code == 0
    assert daemon.fps == 100.0
    named = [m for m in parse_mavlink(data) if m.get_type() == "NAMED_VALUE_FLOAT"]
    # skip the extended model's 12 frames of history (extras go out at 5 Hz: every 10th frame)
    expansion = [m.value for m in named if m.name == "expansion" and m.time_boot_ms >= 300]
    ttc = [m.value for m in named if m.name == "ttc_s" and m.time_boot_ms >= 300]
    assert len(expansion) >= 3
    assert statistics.median(expansion) == pytest.approx(rate_per_frame * 50, rel=0.3)   # not × 100
    assert statistics.median(ttc) == pytest.approx(1 / (rate_per_frame * 50), rel=0.3)


def test_extra_values_are_unknown_without_a_cue_and_in_the_mounted_axes(tmp_path):
    """Before the history is full there is no cue: the extras say NaN ("unknown", as the
    gyro fields do), not a measured expansion 0 and ttc -1 (which also means receding).
    The balances are turned to a default-mounted camera's axes as the flow is: the same
    flight seen through a mirror, with mounting_mirror, gives the same balance (it flipped)."""
    flight = CameraFlight("gravel", width=160, height=120, flow=(1.5, 0.0), expansion_rate=0.01,
                          noise_sigma=1.0, supersample=2, seed=0)
    frames = flight.render_many(60)
    balances = {}
    for mirror in (False, True):
        clip = write_video(tmp_path / f"zoom{int(mirror)}.mkv",
                           np.ascontiguousarray(frames[:, :, ::-1]) if mirror else frames, fps=50.0)
        config = _config(f"video:{clip}", autopilot="ardupilot", model="extended",
                         settings={("link", "extra_values"): True, ("optics", "mounting_mirror"): mirror})
        code, daemon, data = run_daemon(config, frames=60)
        assert code == 0
        named = [m for m in parse_mavlink(data) if m.get_type() == "NAMED_VALUE_FLOAT"]
        early = [m for m in named if m.time_boot_ms < 100]      # the extended model's history fills
        assert {m.name for m in early} == {"expansion", "ttc_s", "balanceLR", "balanceTB"}
        assert all(math.isnan(m.value) for m in early), [(m.name, m.value) for m in early]
        balances[mirror] = statistics.median(m.value for m in named if m.name == "balanceLR" and m.time_boot_ms >= 300)
    assert abs(balances[False]) > 0.05
    assert balances[True] == pytest.approx(balances[False], abs=0.05)


class _DroppingSource:
    """A real source that loses frames the way a camera under load does: every frame in
    ``drop`` is read and thrown away (the next one comes two periods after the one before).
    ``renumber``: the indices count the frames that came (as OpenCV's V4L2 reads do), so the
    drop shows only in the timestamps. ``jitter_us``: timestamps alternately that much late
    and on time (a driver without buffer times, stamped at the host's read). ``every``:
    deliver every n-th of those frames only (a subset, as the capture thread's)."""

    def __init__(self, inner, *, drop=(), renumber=False, every=1, jitter_us=0):
        self.inner, self.drop, self.renumber, self.every, self.jitter_us = inner, set(drop), renumber, every, jitter_us
        self.came = 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def _next(self):
        from firmware_py.sources import Frame

        frame = self.inner.read()
        while frame is not None and frame.index in self.drop:
            frame = self.inner.read()
        if frame is None:
            return None
        self.came += 1
        index = self.came - 1 if self.renumber else frame.index
        return Frame(frame.image, frame.timestamp_us + self.jitter_us * (self.came % 2), frame.capture_host_us,
                     index)

    def read(self):
        for _ in range(self.every - 1):
            self._next()
        return self._next()


@pytest.mark.parametrize("drop, renumber, every, jitter_us, model, uneven", [
    ((30,), False, 1, 0, "paper", 3),       # a dropped frame: the indices jump
    ((30,), True, 1, 0, "paper", 3),        # ... or only the timestamps (indices that count reads)
    ((91,), True, 3, 0, "paper", 3),        # ... also in a subset of every 3rd frame (40 ms after 30)
    (range(30, 50), True, 1, 0, "paper", 3),  # a 0.2 s stall only in the timestamps (no reset)
    ((30,), False, 1, 0, "extended", 6),    # delays up to 4, but at most 6 frames
    ((), False, 2, 0, "paper", 0),          # a steady subset (every other frame) is even
    ((), True, 1, 3000, "paper", 0),        # 13 and 7 ms steps at 100 fps: jitter, not a drop
    ((), False, 1, 0, "paper", 0),
], ids=["dropped", "dropped-renumbered", "dropped-renumbered-every-3rd", "stall-renumbered", "dropped-extended",
        "every-other", "jitter", "none"])
def test_a_dropped_frame_sends_the_frames_it_unevens_with_quality_0(tmp_path, drop, renumber, every, jitter_us,
                                                                    model, uneven):
    """The paper model's output at frame t spans the frames t-3..t (templates over the
    states at t-2, t-1 and t, each a change from the frame before). After a frame the
    camera dropped, three frames span a longer step among the others, and the detector's
    output then is not the flow, at the usual quality: those three go out with quality 0
    and are counted as uneven (the extended model's six: its span, at most 6). A steady
    subset's equal steps are not uneven, nor a timestamp jitter of a third of a period."""
    log_path = tmp_path / "sent.csv"
    config = _config("synthetic:u=2,v=1", autopilot="ardupilot", model=model,
                     settings={("source", "width"): 96, ("source", "height"): 72,
                               ("link", "message_rate_hz"): 100.0, ("link", "message_log"): str(log_path),
                               ("link", "min_quality"): 0})

    def factory():
        return _DroppingSource(make_source("synthetic:u=2,v=1", width=96, height=72, fps=100),
                               drop=drop, renumber=renumber, every=every, jitter_us=jitter_us)

    code, daemon, _ = run_daemon(config, frames=60, source_factory=factory)
    assert code == 0
    assert daemon.stats.uneven == uneven and daemon.stats.resets == 0
    with open(log_path, newline="") as f:
        quality = [int(r["quality"]) for r in csv.DictReader(f) if r["message"] == "OPTICAL_FLOW"]
    # one report per processed frame (jittered, a 7 ms step is shorter than the period:
    # two frames to a report)
    assert len(quality) == (60 if not jitter_us else 30), quality
    history = 3 if model == "paper" else 12  # frames before the first flow
    history = -(-history // 2) if jitter_us else history  # (reports before it)
    zeros = [i for i, q in enumerate(quality) if q == 0 and i >= history]
    assert zeros == list(range(30, 30 + uneven)), quality  # the frames whose templates span the drop


def test_the_extra_values_of_uneven_frames_are_unknown(monkeypatch):
    """The frames whose templates span a dropped frame go out with quality 0: what the
    detector reports then is not the motion. Their cues (expansion, time to contact,
    balances) came from the same detections and went out as measured values; now as NaN,
    "unknown", like the flow's quality."""
    import firmware_py.daemon as daemon_module

    sent = []
    real = daemon_module.FlowSample

    def recorded(**fields):
        sent.append(real(**fields))
        return sent[-1]

    monkeypatch.setattr(daemon_module, "FlowSample", recorded)
    config = _config("synthetic:u=2,v=1", autopilot="ardupilot", model="paper",
                     settings={("source", "width"): 96, ("source", "height"): 72,
                               ("link", "extra_values"): True, ("link", "min_quality"): 0})
    code, daemon, _ = run_daemon(config, frames=60, source_factory=lambda: _DroppingSource(
        make_source("synthetic:u=2,v=1", width=96, height=72, fps=100), drop=(30,), renumber=False, every=1,
        jitter_us=0))
    assert code == 0 and daemon.stats.uneven == 3
    ready = sent[5:]  # (after the paper model's history)
    uneven = [s for s in ready if s.quality == 0]
    assert len(uneven) == 3
    assert all(math.isnan(value) for s in uneven for _, value in s.extras), [s.extras for s in uneven]
    measured = [s for s in ready if s.quality > 0]
    assert measured and all(math.isfinite(dict(s.extras)["expansion"]) for s in measured)


@pytest.mark.parametrize("autopilot, model, setting, floor", [
    ("ardupilot", "paper", None, 128),    # the paper model's default for ArduPilot
    ("both", "extended", None, 64),       # the extended model's (both: ArduPilot reads OPTICAL_FLOW)
    ("px4", "paper", None, 0),            # PX4 has EKF2_OF_QMIN
    ("ardupilot", "paper", 30, 30),
])
def test_ardupilot_gets_quality_0_below_the_models_floor(tmp_path, monkeypatch, autopilot, model, setting, floor):
    """ArduPilot's EKF3 fuses every report of quality > 0. A summary the engine itself
    rates low (too fast for the scales, noise only: 10-50 % off, or the wrong sign) went
    out to it as a measurement; below the model's floor it is sent with quality 0."""
    import firmware_py.daemon as daemon_module
    from emdflow.summary import FlowSummary

    # summaries of qualities 20, 100, 200, four frames each in turn
    real = daemon_module._summarize
    qualities = iter(([20] * 4 + [100] * 4 + [200] * 4) * 10)

    def rated(field):
        summary = real(field)
        return FlowSummary(flow_x=summary.flow_x, flow_y=summary.flow_y, quality=next(qualities))

    monkeypatch.setattr(daemon_module, "_summarize", rated)
    log_path = tmp_path / "sent.csv"
    settings = {("source", "width"): 96, ("source", "height"): 72, ("link", "message_rate_hz"): 100.0,
                ("link", "message_log"): str(log_path)}
    if setting is not None:
        settings[("link", "min_quality")] = setting
    config = _config("synthetic:u=2,v=1", autopilot=autopilot, model=model, settings=settings)
    code, daemon, _ = run_daemon(config, frames=40, source_factory=lambda: make_source(
        "synthetic:u=2,v=1", width=96, height=72, fps=100))
    assert code == 0 and daemon.min_quality == floor
    message = "OPTICAL_FLOW_RAD" if autopilot == "px4" else "OPTICAL_FLOW"
    with open(log_path, newline="") as f:
        sent = [int(r["quality"]) for r in csv.DictReader(f) if r["message"] == message]
    # (the first frames, history filling, are the link's restart marker and reports the
    # summary rated before it was ready: skipped; the warm-up took 2 of the qualities)
    late = sent[16:]
    if autopilot == "ardupilot":  # one report per frame
        assert set(late) == {0} | {q for q in (20, 100, 200) if q >= floor}, sent
    else:  # (PX4's reports span two frames: their mean quality, 0 if one of them was 0; a
        # frame below the floor left out, the other's quality times the half it covers)
        assert all(q == 0 or q >= floor or q in (50, 100) and floor > 20 for q in late) and max(late) == 200, sent
        assert (min(late) == 0) == (floor > 20), sent


def test_frames_a_paced_flight_moves_past_count_as_dropped():
    """A --realtime flight read by a loop slower than its frame rate moves past the frames
    it is late for, as a camera drops them: the daemon counts them as dropped (and the
    frames whose detector output spans the skip as uneven)."""
    config = _config("synthetic:u=2,v=1", settings={("source", "width"): 96, ("source", "height"): 72,
                                                    ("source", "realtime"): True})

    def slow(width, height):
        real = emdflow.FlowEstimator(width, height, backend=config.engine.backend,
                                     **config.engine.estimator_options())
        return _SlowEngine(real, 0.025)  # 2.5 periods of the 100 fps flight

    code, daemon, _ = run_daemon(config, frames=12, estimator_factory=slow)
    assert code == 0
    assert daemon.stats.dropped >= 12 and daemon.stats.skipped == 0


@pytest.mark.parametrize("threading_mode", ["capture-thread", "single"])
def test_inav_reports_leave_a_fixed_time_after_their_frames_capture(tmp_path, caplog, threading_mode):
    """INAV divides a report's counts by the time since the previous report arrived, so the
    daemon sends each MSP report a fixed delay after its newest frame's capture (automatic:
    just above the recent ready times) instead of as soon as it is processed. With 2-8 ms
    of processing (11 ms spikes) at 100 fps the automatic delay is longer than the frame
    period: a report falls due while the loop is in the engine with the next frame, and
    its writer thread sends it then. The 50 Hz reports then leave 20 ms apart (sent as
    processed, 10 % of them were within 0.5 ms of that; written by the frame loop when it
    got to it, 11 %)."""
    import logging

    from firmware_py.daemon import Daemon
    from firmware_py.pacing_check import PaddedEngine

    caplog.set_level(logging.INFO, logger="emdflowd")
    log_path = tmp_path / "sent.csv"
    config = _config("synthetic:u=2,v=1", autopilot="inav",
                     settings={("source", "width"): 96, ("source", "height"): 72, ("source", "fps"): 100.0,
                               ("source", "realtime"): True, ("daemon", "threading"): threading_mode,
                               ("link", "message_rate_hz"): 50, ("link", "message_log"): str(log_path),
                               ("daemon", "log_interval_s"): 1.0})

    def estimator(width, height):
        # (2-8 ms an update, every 100th 11 ms)
        return PaddedEngine(Daemon(config)._default_estimator(width, height), 0.002, 0.008, 0.011)

    code, daemon, _ = run_daemon(config, frames=400, estimator_factory=estimator)
    assert code == 0
    with open(log_path, newline="") as f:
        reports = [r for r in csv.DictReader(f) if r["message"] == "MSP2_SENSOR_OPTIC_FLOW" and r["latency_us"]]
    assert len(reports) >= 190
    # (each held report's delay after capture, as the pacer chose it then)
    held = [r for r in reports if r["paced_us"]]
    assert len(held) >= 0.8 * len(reports)  # (the rest were ready after their due time)
    assert all(1.0 <= int(r["paced_us"]) / 1e3 <= 25.0 for r in held)
    assert max(int(r["paced_us"]) for r in held[50:]) > 10_000  # (longer than a frame period)
    late_ms = [(int(r["latency_us"]) - int(r["paced_us"])) / 1e3 for r in held]
    assert min(late_ms) >= -0.01 and statistics.median(late_ms) < 2.0, late_ms
    # After the automatic delay's start (a loaded test machine's scheduler writes some late:
    # 0.41 with two other processes busy on 2 cores, 0.84-0.99 on an idle one).
    written = [int(r["host_us"]) for r in reports[50:]]
    steady = sum(abs(b - a - 20_000) <= 500 for a, b in zip(written, written[1:])) / (len(written) - 1)
    assert steady >= 0.3, steady
    delay_ms = daemon.link.stats["report_delay_ms"]
    assert f"paced {delay_ms:.1f} ms after capture" in caplog.text


def test_the_pacing_check_prints_the_intervals_inav_divides_by(capsys):
    """``python -m firmware_py.pacing_check`` (the README's INAV numbers): one run, its
    report intervals and how late the held reports were written."""
    from firmware_py.pacing_check import main

    for delay in ("auto", "0"):
        assert main(["--frames", "160", "--threading", "single", "--delay-ms", delay]) == 0
        out = capsys.readouterr().out
        match = re.search(r"intervals between written reports: p5 ([\d.]+) p50 ([\d.]+) p95 ([\d.]+) ms; "
                          r"(\d+)% within 0.5 ms of 20 ms", out)
        assert match, out
        # (50 Hz reports, however they jitter; unpaced, their intervals spread 15-25 ms and the
        # median of ~80 of them strays ~0.4 ms: 19.43 ms failed a 0.5 ms bound in one CI run)
        assert float(match[2]) == pytest.approx(20.0, abs=0.5 if delay == "auto" else 1.5)
        # (held, paced, only with a delay)
        assert ("held reports written after their due time: p50" in out) == (delay == "auto"), out
    for bad in (["--engine-ms", "fast"], ["--delay-ms", "60"], ["--delay-ms", "soon"], ["--frames", "10"]):
        with pytest.raises(SystemExit):
            main(bad)
        assert "error:" in capsys.readouterr().err
