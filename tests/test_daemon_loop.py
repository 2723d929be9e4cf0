"""The loop's building blocks: steady subset, one-slot mailbox, source recovery."""

from __future__ import annotations

import logging
import os
import sys
import threading
import time

import numpy as np
import pytest

from firmware_py.daemon import FrameMailbox, SourceKeeper, Stats, SteadySubset, choose_threading
from firmware_py.sources import Frame, make_source
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import flight_frames, write_video  # noqa: E402


def _frame(index, fps=100.0):
    return Frame(np.zeros((4, 4), np.uint8), int(index * 1e6 / fps), 0, index)


def _feed(subset, start, count, busy_s, fps=100.0):
    """Capture ``count`` frames; the 'engine' takes busy_s per accepted frame."""
    accepted = []
    for i in range(start, start + count):
        f = _frame(i, fps)
        subset.observe_capture(f)
        if subset.accept(f):
            accepted.append(i)
            subset.observe_busy(busy_s, now_s=i / fps)
    return accepted


def test_steady_subset_keeps_even_spacing_under_load():
    subset = SteadySubset(relax_s=0.5)
    assert _feed(subset, 0, 20, 0.004) == list(range(20))         # 4 ms < 10 ms: every frame
    accepted = _feed(subset, 20, 200, 0.025)                      # 25 ms per frame at 100 fps
    assert subset.k == 3                                          # ceil(25 * 1.15 / 10)
    tail = np.diff(accepted[-30:])
    assert set(tail) == {3}                                       # evenly spaced, not "whatever arrives"
    accepted = _feed(subset, 220, 300, 0.004)                     # load gone: k relaxes step by step
    assert subset.k == 1 and set(np.diff(accepted[-20:])) == {1}


def test_steady_subset_follows_an_engine_far_slower_than_the_camera():
    """A 0.28 s engine behind a 100 fps camera needs every 33rd frame; a k held at 16 left
    the mailbox replacing every other subset frame, so no two processed frames were evenly
    spaced and every report went out with quality 0."""
    subset = SteadySubset()
    accepted = _feed(subset, 0, 1500, 0.28)
    assert subset.k == 33                                         # ceil(0.28 * 1.15 / 0.01)
    assert set(np.diff(accepted[-10:])) == {33}
    # a second a frame for 30 s, then the load is gone: k comes back within a minute (one
    # step per 2 s took 356 s from k = 115, the frames more than 0.45 s apart meanwhile:
    # too far apart for a good report)
    _feed(subset, 1500, 3000, 1.0)
    assert subset.k == 115
    _feed(subset, 4500, 6000, 0.004)                              # 60 s of frames
    assert subset.k == 1


def test_steady_subset_ignores_single_slow_frames_but_not_drops():
    subset = SteadySubset()
    subset.busy_drop()
    assert subset.k == 1                          # nothing measured yet: a burst, not a load
    for i in range(40):
        subset.observe_capture(_frame(i))
        subset.observe_busy(2.0 if i == 0 else 0.004, now_s=i / 100)  # first frame: kernel build
    assert subset.k == 1                          # one slow frame does not decimate for long
    for i in range(40, 60):
        subset.observe_capture(_frame(i))
        subset.observe_busy(0.016 if i % 3 == 0 else 0.004, now_s=i / 100)
    assert subset.k == 1                          # the typical frame fits ...
    subset.busy_drop()
    assert subset.k == 2                          # ... but a drop makes room for the slow ones
    assert subset.accept(_frame(100)) and not subset.accept(_frame(101)) and subset.accept(_frame(102))
    assert subset.accept(_frame(0))               # index went back (source reopened): accepted


def test_mailbox_replaces_unread_frame_and_counts_it():
    box = FrameMailbox()
    assert box.put(_frame(1)) is False
    assert box.put(_frame(2)) is True            # frame 1 was never processed: a drop
    assert box.get(0.01).index == 2              # the newest, never a queue
    assert box.get(0.01) is None


def test_blocking_mailbox_applies_back_pressure():
    box = FrameMailbox(block=True)
    box.put(_frame(1))
    done = threading.Event()
    threading.Thread(target=lambda: (box.put(_frame(2)), done.set()), daemon=True).start()
    assert not done.wait(0.2)                    # the writer waits for the reader
    assert box.get(1.0).index == 1
    assert done.wait(2.0) and box.get(1.0).index == 2


def test_threading_choice():
    assert choose_threading("auto", live=True) == "capture-thread"
    assert choose_threading("auto", live=False) == "single"
    assert choose_threading("single", live=True) == "single"
    assert choose_threading("capture-thread", live=False) == "capture-thread"


def _small_flight_config(uri: str):
    """A daemon configuration for a 64x48 synthetic flight on the numpy reference."""
    from firmware_py.config import Config

    config = Config()
    config.set("source", "uri", uri)
    config.set("source", "width", 64)
    config.set("source", "height", 48)
    config.set("engine", "backend", "numpy")
    return config


def test_a_paced_source_on_the_numpy_reference_gets_the_capture_thread():
    """``auto`` threading: a paced (``realtime``) flight on the numpy reference is read by a
    capture thread that passes an evenly spaced subset, as for a camera — one thread would
    skip whichever frames came due while the slow engine worked (gaps of 1–3 frames at
    random, which the velocity templates cannot follow); unpaced it stays one thread."""

    from daemon_util import run_daemon

    modes = {}
    for realtime in (True, False):
        config = _small_flight_config("synthetic:u=2,v=1")
        config.source.realtime = realtime
        code, daemon, _ = run_daemon(config, frames=6)
        assert code == 0
        modes[realtime] = daemon.mode
    assert modes == {True: "capture-thread", False: "single"}


def test_a_slow_paced_flight_in_one_thread_keeps_the_link_serviced(tmp_path):
    """A --realtime flight at 1.5 fps read by the single-threaded loop: between frames the
    loop services the link in short slices, so no flow message is further apart than a
    report may span (0.45 s) and heartbeats keep their rate. read() used to sleep the whole
    frame period, and nothing went out for 0.67 s at a time (a 0.08 fps recording held the
    systemd watchdog off for 12.5 s)."""
    import csv

    from firmware_py.config import Config

    from daemon_util import engine_backend, run_daemon

    log_path = tmp_path / "sent.csv"
    config = Config()
    for section, key, value in (("source", "uri", "synthetic:u=1,v=1"), ("source", "width", 64),
                                ("source", "height", 48), ("source", "fps", 1.5),
                                ("engine", "backend", engine_backend()), ("daemon", "threading", "single"),
                                ("link", "autopilot", "ardupilot"), ("link", "message_log", str(log_path))):
        config.set(section, key, value)
    config.source.realtime = True
    code, daemon, _ = run_daemon(config, frames=4)
    assert code == 0 and daemon.mode == "single" and daemon.stats.processed == 4
    rows = list(csv.DictReader(open(log_path, newline="")))
    flow = [int(r["host_us"]) for r in rows if r["message"] == "OPTICAL_FLOW"]
    beats = [int(r["host_us"]) for r in rows if r["message"] == "HEARTBEAT"]
    assert flow[-1] - flow[0] > 1.8e6                       # the run spans the slow frames
    assert max(b - a for a, b in zip(flow, flow[1:])) < 0.45e6
    assert len(beats) >= 2 and max(b - a for a, b in zip(beats, beats[1:])) < 1.1e6
    # the first waits of a slow flight are its frame period, not a blind camera (the gap
    # limit is the nominal period until two frames gave the typical one)
    assert daemon.stats.blind_periods == 0


def _live(source):
    """A file source that stands in for a live stream (a camera's stream that ends is lost)."""
    source.live = True
    return source


def test_source_keeper_reopens_with_backoff(tmp_path, caplog):
    path = write_video(tmp_path / "short.avi", flight_frames(5, width=32, height=24), fps=50)
    stats = Stats()
    keeper = SourceKeeper(lambda: _live(make_source(f"video:{path}")), backoff_s=0.05, backoff_max_s=0.2,
                          stats=stats)
    got = []
    deadline = time.monotonic() + 10
    nones = 0
    while len(got) < 12 and time.monotonic() < deadline:
        frame = keeper.read()
        if frame is None:
            nones += 1
            time.sleep(0.01)
        else:
            got.append(frame.index)
    assert got[:12] == [0, 1, 2, 3, 4, 0, 1, 2, 3, 4, 0, 1]   # end of stream -> reopened twice
    assert stats.reopens == 2 and nones >= 2
    assert "end of stream; reopening in 0.1 s" in caplog.text or "end of stream; reopening in 0.05" in caplog.text
    keeper.close()


def test_source_keeper_ends_with_a_recording(tmp_path, caplog):
    """A file (not live) is read once: at its end the keeper says so and never reopens it."""
    caplog.set_level(logging.INFO)
    path = write_video(tmp_path / "short.avi", flight_frames(5, width=32, height=24), fps=50)
    stats = Stats()
    keeper = SourceKeeper(lambda: make_source(f"video:{path}"), backoff_s=0.01, stats=stats)
    got = [keeper.read() for _ in range(6)]
    assert [f.index for f in got[:5]] == [0, 1, 2, 3, 4] and got[5] is None
    assert keeper.ended and keeper.source is None
    time.sleep(0.05)  # past any back-off: still nothing, and nothing reopened
    assert keeper.read() is None and stats.reopens == 0
    assert "short.avi: end of stream: stopping" in caplog.text


def test_source_keeper_backoff_grows_while_source_is_missing(tmp_path, caplog):
    path = tmp_path / "later.avi"
    keeper = SourceKeeper(lambda: make_source(f"video:{path}"), backoff_s=0.05, backoff_max_s=0.1)
    assert keeper.read() is None and keeper.blind
    assert "later.avi" in caplog.text and "no such file" in caplog.text
    assert 0.0 < keeper.retry_in_s() <= 0.05
    time.sleep(0.06)
    assert keeper.read() is None
    assert 0.05 < keeper.retry_in_s() <= 0.1                   # doubled
    write_video(path, flight_frames(3, width=32, height=24))   # the device comes back
    time.sleep(0.11)
    frame = keeper.read()
    assert frame is not None and frame.index == 0 and not keeper.blind
    keeper.close()


class _Clock:
    """The keeper's clock in 10 ms ticks, advanced by the test (no float drift)."""

    def __init__(self):
        self.ticks = 100_000

    def __call__(self) -> float:
        return self.ticks / 100


def _keep_reading(keeper, clock, seconds=None, *, until=None, limit_s=60.0):
    """The capture loop on the simulated clock, one read per 10 ms (a 100 fps camera), for
    ``seconds`` or until ``until()`` holds (within ``limit_s``)."""
    for _ in range(round((seconds if seconds is not None else limit_s) * 100)):
        clock.ticks += 1
        keeper.read()
        if until is not None and until():
            return
    assert until is None, "the condition never came true"


def _flaky_camera(clock, opened, fail_at):
    """A real synthetic flight that fails like an unplugged camera at read ``fail_at(n)`` of
    its n-th open; ``opened`` collects the open times."""
    from daemon_util import FaultySource

    def factory():
        opened.append(clock())
        return FaultySource(make_source("synthetic:u=2,v=1", width=32, height=24, fps=100),
                            fail_at=fail_at(len(opened)), live=True)
    return factory


def test_a_camera_that_fails_right_after_each_open_is_reopened_ever_more_slowly(caplog):
    """One frame and a failure is no recovery: such a camera was reopened every 0.5 s
    forever (and the estimator, which needs 12 frames, never gave flow). The back-off
    doubles to its cap; only 5 s of delivered frames start it again from 0.5 s."""
    clock, opened, steady_from = _Clock(), [], [99]
    # one frame, then a failure; from the `steady_from`-th open on 6 s of frames (600) first
    factory = _flaky_camera(clock, opened, lambda n: 2 if n < steady_from[0] else 601)
    keeper = SourceKeeper(factory, backoff_s=0.5, backoff_max_s=10.0, clock=clock)
    _keep_reading(keeper, clock, 60.0)
    gaps = [b - a for a, b in zip(opened, opened[1:])]
    assert gaps == pytest.approx([0.5, 1, 2, 4, 8, 10, 10, 10, 10], abs=0.025)
    assert "read failed (USB camera unplugged); reopening in 10.0 s" in caplog.text

    steady_from[0] = len(opened) + 1
    _keep_reading(keeper, clock, until=lambda: len(opened) == steady_from[0])
    _keep_reading(keeper, clock, until=lambda: keeper.source is None, limit_s=7.0)   # 6 s of frames
    failed_at = clock()
    _keep_reading(keeper, clock, until=lambda: len(opened) == steady_from[0] + 1, limit_s=11.0)
    assert opened[-1] - failed_at == pytest.approx(0.5, abs=0.015)   # not 10 s: it had recovered
    keeper.close()


def test_a_camera_that_fails_within_the_steady_time_keeps_the_longer_back_off():
    """3 s of frames (less than the 5 s that make a source steady) do not reset the back-off."""
    clock, opened = _Clock(), []
    keeper = SourceKeeper(_flaky_camera(clock, opened, lambda n: 2 if n < 3 else 301),
                          backoff_s=0.5, backoff_max_s=10.0, clock=clock)
    _keep_reading(keeper, clock, until=lambda: len(opened) == 3)         # two quick failures
    _keep_reading(keeper, clock, until=lambda: keeper.source is None, limit_s=4.0)  # 3 s of frames
    failed_at = clock()
    _keep_reading(keeper, clock, until=lambda: len(opened) == 4, limit_s=11.0)
    assert opened[-1] - failed_at == pytest.approx(2.0, abs=0.015)     # doubling went on: 0.5, 1, 2
    keeper.close()


def test_the_status_line_says_when_the_ground_reads_as_thin_lines():
    """The extended model over a grid of thin lines (paving, tiles): the summary reads it
    with its line-ground table, and the status line says so; over gravel it does not."""
    from firmware_py.config import Config

    from daemon_util import run_daemon

    said = {}
    for texture in ("lines-5-30", "gravel"):
        config = Config()
        config.set("source", "uri", f"synthetic:texture={texture},u=-6.6,v=-2.4")
        config.set("engine", "model", "extended")
        code, daemon, _ = run_daemon(config, frames=24)
        assert code == 0 and daemon.stats.last_summary.quality > 0
        said[texture] = "(line ground)" in daemon.status_text(daemon.stats.interval(), 1.0)
    assert said == {"lines-5-30": True, "gravel": False}


def test_status_lines_carry_the_link_counters_the_readme_lists():
    """The status line adds each of the link's trouble counters once it is not 0, and the
    final line all of them with the bytes and the autopilot's heartbeat (they were kept in
    link.stats only, though the README listed them as logged)."""
    from firmware_py.daemon import _link_stats

    stats = {"messages_sent": {"OPTICAL_FLOW": 5, "HEARTBEAT": 1}, "dropped_messages": 1, "blind_reports": 0,
             "port_open": True, "reopen_count": 2, "stale_messages": 3, "open_failures": 0, "write_errors": 0,
             "read_errors": 4, "integration_restarts": 0, "bytes_written": 999, "rx_bytes": 120,
             "rx_garbage_bytes": 7, "rx_heartbeat": {"sysid": 1, "compid": 1, "type": 2, "autopilot": 3}}
    status, final = _link_stats(stats), _link_stats(stats, final=True)
    assert status.startswith("sent HEARTBEAT 1,OPTICAL_FLOW 5; dropped 1 blind 0 port open reopens 2")
    assert "stale 3" in status and "read errors 4" in status and "garbage in 7" in status
    assert "write errors" not in status and "bytes out" not in status and "autopilot" not in status
    for part in ("stale 3", "open failures 0", "write errors 0", "read errors 4", "restarts 0", "bytes out 999",
                 "bytes in 120", "garbage in 7", "autopilot sysid 1 type 2"):
        assert part in final, (part, final)


def test_a_source_that_waits_inside_read_gets_the_capture_thread(tmp_path):
    """A paced DepthAI replay waits for its frames inside the pipeline, where the loop cannot
    see for how long: ``auto`` threading reads it in a capture thread, so the link is served
    meanwhile (one thread would block up to a frame period, 2 s and more, in read())."""
    from firmware_py.sources.synthetic import SyntheticSource

    from daemon_util import run_daemon

    class WaitsInRead(SyntheticSource):
        waits_in_read = True

    modes = {}
    for waits in (True, False):
        config = _small_flight_config("synthetic:u=1,v=1")
        cls = WaitsInRead if waits else SyntheticSource
        code, daemon, _ = run_daemon(config, frames=4, source_factory=lambda: cls("u=1,v=1", width=64, height=48))
        assert code == 0
        modes[waits] = daemon.mode
    assert modes == {True: "capture-thread", False: "single"}
    pytest.importorskip("depthai")
    from firmware_py.sources.depthai_source import DepthAISource

    path = write_video(tmp_path / "clip.mkv", flight_frames(4, width=64, height=48), fps=25)
    assert DepthAISource(replay_path=str(path), realtime=True).waits_in_read
    assert not DepthAISource(replay_path=str(path)).waits_in_read


class _SlowCountingCamera:
    """A camera that finds every frame bad and says so slowly (its count a property that
    gives up the GIL): the capture thread's count of its bad frames is then read while the
    loop counts bad frames of its own."""

    uri, live, missed_frames = "slow-counting", True, 0

    def __init__(self):
        self._bad = 0

    @property
    def bad_frames(self):
        time.sleep(0.0005)
        return self._bad

    def read(self):
        self._bad += 1
        return Frame(np.zeros((4, 4), np.uint8), 0, time.monotonic_ns() // 1000, self._bad)

    def close(self):
        pass


def test_bad_frames_counted_by_both_threads_are_all_counted():
    """The capture thread (the source's skipped buffers, through the keeper) and the loop
    (frames of the wrong size) both count bad frames. ``stats.bad_frames += n`` reads the
    counter, then the source's count, then writes: a loop count in between was lost."""
    from firmware_py.config import Config
    from firmware_py.daemon import Daemon

    daemon = Daemon(Config())
    keeper = SourceKeeper(_SlowCountingCamera, stats=daemon.stats)
    keeper.adopt(_SlowCountingCamera())
    reads = 200

    def capture():
        for _ in range(reads):
            keeper.read()

    thread = threading.Thread(target=capture)
    thread.start()
    loop_counts = 0
    while thread.is_alive():
        daemon._bad_frame("frame of the wrong size")
        loop_counts += 1
        time.sleep(0.0001)
    thread.join()
    assert loop_counts > 50
    assert daemon.stats.bad_frames == reads + loop_counts
