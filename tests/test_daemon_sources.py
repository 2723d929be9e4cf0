"""Frame sources: exact frames, timestamps and sizes from real files, DepthAI replay,
synthetic flights, V4L2 raw-buffer conversion (the camera itself is the only mock)."""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import threading
import time

import cv2
import numpy as np
import pytest

from firmware_py.angular import focal_length_px_from_fov
from firmware_py.clock import host_us
from firmware_py.config import Config
from firmware_py.sources import Frame, FrameError, SourceConfigError, SourceError, make_source, open_source, parse_uri
from firmware_py.sources.v4l2 import V4L2Source, raw_to_gray
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import flight_frames, run_isolated_from_native_crashes, write_video  # noqa: E402


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    frames = flight_frames(24, flow=(2.0, -1.0), width=160, height=120)
    path = write_video(tmp_path_factory.mktemp("clip") / "flight.avi", frames, fps=50.0)
    return path, frames


def _read_all(source):
    out = []
    while (frame := source.read()) is not None:
        out.append(frame)
    return out


def _check_frame(frame: Frame, width: int, height: int):
    assert isinstance(frame.image, np.ndarray) and frame.image.dtype == np.uint8
    assert frame.image.shape == (height, width) and frame.image.flags.c_contiguous
    assert isinstance(frame.timestamp_us, int) and isinstance(frame.capture_host_us, int)


def test_video_source_exact_frames_and_file_clock(clip):
    path, frames = clip
    with open_source(f"video:{path}") as source:
        got = _read_all(source)
    assert len(got) == len(frames)
    for i, frame in enumerate(got):
        _check_frame(frame, 160, 120)
        assert np.array_equal(frame.image, frames[i])
        assert frame.index == i
        assert frame.timestamp_us == i * 20_000  # 50 fps file: index / fps, not the wall clock
    assert source.default_focal_length_px == 160.0
    assert got[-1].capture_host_us >= got[0].capture_host_us


def test_video_source_resizes_and_loops(clip):
    path, frames = clip
    with open_source(f"video:{path}", width=80, height=60, loop=True) as source:
        got = [source.read() for _ in range(len(frames) + 5)]
    _check_frame(got[0], 80, 60)
    expected = cv2.resize(frames[3], (80, 60), interpolation=cv2.INTER_AREA)
    assert np.array_equal(got[3].image, expected)
    # after the rewind the content starts again but the clock keeps going
    assert np.array_equal(got[len(frames)].image, got[0].image)
    stamps = [f.timestamp_us for f in got]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)


def test_video_source_says_when_a_file_stops_short(clip, tmp_path, caplog):
    """OpenCV reports a stream that stops decoding like its end: a file that yields far
    fewer frames than its container declares gets a warning naming it; a whole file (read
    to the end, also paced and looped) none."""
    path, frames = clip
    with open_source(f"video:{path}", loop=True) as source:
        for _ in range(2 * len(frames) + 3):
            source.read()
    with open_source(f"video:{path}", realtime=True) as source:
        _read_all(source)
    assert "decoding stopped" not in caplog.text
    cut = tmp_path / "cut.avi"
    data = path.read_bytes()
    cut.write_bytes(data[:len(data) * 6 // 10])
    with open_source(f"video:{cut}") as source:
        got = _read_all(source)
    assert 0 < len(got) < len(frames) - 2
    assert (f"cut.avi': decoding stopped after {len(got)} of the {len(frames)} frames it declares"
            in caplog.text)
    # looped, it says so once, not at every rewind (a line per pass, for ever)
    caplog.clear()
    with open_source(f"video:{cut}", loop=True) as source:
        looped = [source.read() for _ in range(4 * len(got))]
        assert source.short_passes >= 3
    assert all(f is not None for f in looped)
    assert caplog.text.count("decoding stopped") == 1 and "looping over what decodes" in caplog.text


class _TimedDecoder:
    """A real capture whose frames take ``decode_s`` to decode and whose seek costs 16
    decodes (OpenCV's FFmpeg seek decodes forward from about 16 frames before its target)."""

    def __init__(self, cap, decode_s):
        self.cap, self.decode_s, self.seeks = cap, decode_s, 0

    def read(self):
        time.sleep(self.decode_s)
        return self.cap.read()

    def set(self, prop, value):
        if prop == cv2.CAP_PROP_POS_FRAMES:
            self.seeks += 1
            time.sleep(16 * self.decode_s)
        return self.cap.set(prop, value)

    def __getattr__(self, name):
        return getattr(self.cap, name)


def _paced_reads(path, decode_s, work_s, count):
    """``count`` reads of a ``--realtime`` video source whose decoding takes ``decode_s``
    per frame, with ``work_s`` of the reader's own work per frame; (frames, seconds, seeks)."""
    with open_source(f"video:{path}", realtime=True) as source:
        source._cap = _TimedDecoder(source._cap, decode_s)
        start = time.monotonic()
        got = []
        for _ in range(count):
            got.append(source.read())
            time.sleep(work_s)
        return got, time.monotonic() - start, source._cap.seeks


def test_a_paced_file_skips_what_a_slow_reader_missed_at_a_bounded_cost(tmp_path):
    """``--realtime``: a reader slower than the file's rate gets the frames that are due,
    like a camera's. A few missed frames are decoded through (a seek costs ~16 decodes:
    seeking for every skip held a file that decodes in time at 6 fps); many are passed by
    a seek, so a file that decodes slower than real time (a 1280x800 120 fps recording on
    a small board) stays at a bounded rate instead of falling further behind with every
    frame it decoded (0.1 fps and seconds of latency within a minute)."""
    frames = flight_frames(2000, width=32, height=24)
    path = write_video(tmp_path / "fast.avi", frames, fps=100.0)
    # decodes in time (3 ms a frame at 100 fps), the reader busy 15 ms a frame: ~55 fps
    got, elapsed, seeks = _paced_reads(path, 0.003, 0.015, 30)
    assert seeks == 0 and elapsed < 1.2, (elapsed, [f.index for f in got])
    gaps = [b.index - a.index for a, b in zip(got, got[1:])]
    assert max(gaps) <= 3 and got[-1].index >= 40
    # decodes in 25 ms a frame at 100 fps: reads settle at a seek and one decode each
    got, elapsed, seeks = _paced_reads(path, 0.025, 0.0, 12)
    assert seeks >= 4 and elapsed < 8.0, (elapsed, [f.index for f in got])
    for f in got:                                     # the frames themselves, at their indices
        assert np.array_equal(f.image, frames[f.index])


def test_paced_sources_count_the_frames_a_slow_reader_missed(tmp_path):
    """The frames a paced file or flight moves past are counted (``missed_frames``; the
    daemon adds them to its dropped count, as the mailbox's drops of a camera's): a skip
    is seen in the indices, and in no counter before."""
    path = write_video(tmp_path / "clip.avi", flight_frames(200, width=32, height=24), fps=100.0)
    for uri in (f"video:{path}", "synthetic:u=1,v=0"):
        source = open_source(uri, width=32, height=24, fps=100.0, realtime=True)
        try:
            got = []
            for _ in range(20):
                got.append(source.read().index)
                time.sleep(0.025)  # 2.5 frame periods of work per frame
            missed = source.missed_frames
        finally:
            source.close()
        assert missed == sum(b - a - 1 for a, b in zip(got, got[1:])) + got[0] and missed >= 20, (uri, got)


def test_video_source_missing_file_named(tmp_path):
    with pytest.raises(SourceError, match="nothere.avi.*no such file"):
        open_source(f"video:{tmp_path}/nothere.avi")
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"not a video" * 100)
    with pytest.raises(SourceError, match="bad.avi"):
        open_source(f"video:{bad}")


def test_video_path_that_is_no_file_says_what_it_is(tmp_path):
    """A folder or a FIFO given as the recording was reported as "no such file" (it exists):
    each says what it is, for video: and depthai-replay: alike, and stays exit 2."""
    from daemon_util import PtyPair, run_cli

    folder = tmp_path / "flights"
    folder.mkdir()
    fifo = tmp_path / "pipe.mkv"
    os.mkfifo(fifo)
    schemes = ["video"]
    try:
        import depthai  # noqa: F401 - the replay probes the file the same way, before its pipeline

        schemes.append("depthai-replay")
    except ImportError:
        pass
    for scheme in schemes:
        with pytest.raises(SourceError, match=rf"'{re.escape(str(folder))}': is a directory$"):
            make_source(f"{scheme}:{folder}")
        with pytest.raises(SourceError, match=rf"'{re.escape(str(fifo))}': is not a regular file$"):
            make_source(f"{scheme}:{fifo}")
        with pytest.raises(SourceError, match="nothere.mkv': no such file$"):
            make_source(f"{scheme}:{tmp_path}/nothere.mkv")
    pty = PtyPair()
    try:
        result = run_cli(["--source", f"video:{folder}", "--serial", pty.path, "--frames", 3], timeout=60)
    finally:
        pty.close()
    assert result.returncode == 2, result.stderr[-2000:]
    assert f"video file '{folder}': is a directory" in result.stderr and "Traceback" not in result.stderr


def test_depthai_replay_same_frames_as_file(clip, request):
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=30.0):
        return
    path, frames = clip
    source = open_source(f"depthai-replay:{path}")
    try:
        got = _read_all(source)
    finally:
        source.close()
    # the DepthAI pipeline may discard what is still in flight when the file ends, and under
    # load (once in a full test run) it lost the first five frames of the file as it started
    assert len(frames) - 8 <= len(got) <= len(frames)
    for frame in got:
        _check_frame(frame, 160, 120)
        assert np.array_equal(frame.image, frames[frame.index])  # GRAY8, bit-exact
        assert frame.timestamp_us == frame.index * 20_000
    first = got[0].index
    assert first <= 5 and [f.index for f in got] == list(range(first, first + len(got)))  # no gaps


def test_depthai_replay_delivers_every_frame_of_a_file(request, tmp_path):
    """ReplayVideo stops the pipeline right after sending a file's last frame, and the stop
    closed the output queue with the frames still in it: a reader slower than the replay
    lost the last two frames of every file (the daemon said 'in 98' of a 100-frame file).
    Every frame comes, in order and once, for a slow reader and a fast one; the end is seen
    at once (not after the 2 s without a frame that also ends a file); a looped replay
    goes on into the file's second pass."""
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=60.0):
        return
    count = 100
    frames = flight_frames(count, width=160, height=120)
    path = write_video(tmp_path / "clip.mkv", frames)
    for work_s in (0.003, 0.0):
        source = open_source(f"depthai-replay:{path}")
        got = []
        try:
            while (frame := source.read()) is not None:
                got.append(frame)
                last = time.monotonic()
                time.sleep(work_s)
            ended_after = time.monotonic() - last
        finally:
            source.close()
        assert [f.index for f in got] == list(range(count)), f"work {work_s} s: {[f.index for f in got][-5:]}"
        assert all(np.array_equal(f.image, frames[f.index]) for f in got)
        assert ended_after < 1.0, ended_after
    source = open_source(f"depthai-replay:{path}", loop=True)
    try:
        got = [source.read() for _ in range(count + 10)]
    finally:
        source.close()
    assert [f.index for f in got] == list(range(count + 10))
    assert all(np.array_equal(f.image, frames[i % count]) for i, f in enumerate(got))


def test_depthai_replay_of_a_file_without_frames_ends(request, tmp_path):
    """A file cut off inside its header decodes to nothing: the replay ends (the daemon
    then stops with 'ended before its first frame', exit 2), where it raised 'no frame for
    2 s' as if an OAK were lost and the daemon reopened the file for ever."""
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=60.0):
        return
    full = write_video(tmp_path / "full.mkv", flight_frames(30, width=160, height=120))
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(full.read_bytes()[:3000])
    try:
        source = open_source(f"depthai-replay:{cut}")
    except SourceError:
        return  # (refused at open: as good)
    try:
        assert source.read() is None
    finally:
        source.close()


def test_depthai_replay_says_when_a_file_stops_short(request, tmp_path, caplog):
    """A recording cut off partway replays its first part and stops as at its end; the
    video: source warned about such a file, the depthai-replay: source said nothing (a
    flight log would show a short recording as a complete one). A whole file: no warning."""
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=90.0):
        return
    frames = flight_frames(40, width=96, height=72)
    full = write_video(tmp_path / "full.avi", frames)
    with caplog.at_level(logging.WARNING):
        source = open_source(f"depthai-replay:{full}")
        try:
            whole = _read_all(source)
        finally:
            source.close()
        assert len(whole) == len(frames) and "declares" not in caplog.text
        cut = tmp_path / "cut.avi"
        data = full.read_bytes()
        cut.write_bytes(data[:len(data) * 6 // 10])
        source = open_source(f"depthai-replay:{cut}")
        try:
            got = _read_all(source)
        finally:
            source.close()
    assert 0 < len(got) < len(frames) - 2
    assert (f"cut.avi: the replay stopped after {len(got)} of the {len(frames)} frames the file declares"
            in caplog.text), caplog.text


def test_a_paced_depthai_replay_drops_what_a_slow_reader_misses(request, tmp_path):
    """``--realtime`` replay behaves like a camera: a reader slower than the file's frame
    rate gets the newest frames (the ones it missed are skipped) and each frame's capture
    time is when the replay released it. A blocking queue slowed the whole replay to the
    reader's pace instead, with the latency shown near zero."""
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=60.0):
        return
    path = write_video(tmp_path / "clip.mkv", flight_frames(60, width=64, height=48), fps=50.0)
    source = open_source(f"depthai-replay:{path}", realtime=True)
    got, ages = [], []
    try:
        start = time.monotonic()
        while (frame := source.read()) is not None and len(got) < 25:
            got.append(frame)
            ages.append(host_us() - frame.capture_host_us)
            time.sleep(0.06)  # three frame periods of work per frame
        elapsed = time.monotonic() - start
    finally:
        source.close()
    indices = [f.index for f in got]
    assert indices == sorted(indices) and max(b - a for a, b in zip(indices, indices[1:])) >= 2, indices
    assert indices[-1] >= 1.5 * len(got)             # the file ran at its own rate, not the reader's
    assert elapsed < 2.5 and max(ages) < 500_000     # fresh frames, the queue never builds up


def test_a_paced_depthai_replay_starts_playing_at_its_first_read(request, tmp_path):
    """The daemon builds and warms up its engine between opening the source and reading
    from it (seconds on PoCL with a cold kernel cache). A paced replay started playing at
    open, into a queue that keeps only the newest frame: a recording shorter than the
    warm-up gave one frame. It plays from the first read, as a paced video: file does,
    and a replay closed before any read closes at once."""
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=60.0):
        return
    path = write_video(tmp_path / "clip.mkv", flight_frames(40, width=64, height=48), fps=50.0)
    source = open_source(f"depthai-replay:{path}", realtime=True)
    source.close()
    source = open_source(f"depthai-replay:{path}", realtime=True)
    try:
        time.sleep(1.0)  # the warm-up: longer than the 0.8 s recording
        got = []
        while (frame := source.read()) is not None:
            got.append(frame.index)
    finally:
        source.close()
    # (under load the pipeline has lost a few frames as it started: see
    # test_depthai_replay_same_frames_as_file)
    assert len(got) >= 32 and got == sorted(got), got


def test_a_depthai_replay_that_cannot_start_has_ended(request, tmp_path, caplog):
    """Started at the first read, a replay whose pipeline cannot start reads as the end
    of the file (the daemon stops: exit 2 before any frame), as a file that cannot be
    opened, not as a camera lost for a while (reopened for ever)."""
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=60.0):
        return

    class _NoStart:
        def __init__(self, pipeline):
            self.pipeline = pipeline

        def start(self):
            raise RuntimeError("cannot start")

        def __getattr__(self, name):
            return getattr(self.pipeline, name)

    path = write_video(tmp_path / "clip.mkv", flight_frames(10, width=64, height=48), fps=50.0)
    source = open_source(f"depthai-replay:{path}", realtime=True)
    try:
        source._pipeline = _NoStart(source._pipeline)
        with caplog.at_level(logging.ERROR):
            assert source.read() is None
    finally:
        source.close()
    assert "cannot start the DepthAI pipeline: cannot start" in caplog.text


@pytest.mark.parametrize("size", [(80, 60), (320, 240)], ids=["down", "up"])
def test_depthai_replay_resizes_like_a_video_file(clip, request, size):
    """The replay's frames are the video: source's, pixel for pixel, down and up: DepthAI's
    host ImageManip resampled by nearest pixel (and darkened the last row and column when
    enlarging), which halved the summary's quality on a noisy high-resolution file."""
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=30.0):
        return
    path, frames = clip
    width, height = size
    source = open_source(f"depthai-replay:{path}", width=width, height=height)
    try:
        frame = source.read()
    finally:
        source.close()
    _check_frame(frame, width, height)
    with open_source(f"video:{path}", width=width, height=height) as video:
        same = [f for f in (video.read() for _ in range(frame.index + 1))][-1]
    assert same.index == frame.index and np.array_equal(frame.image, same.image)


def test_depthai_replay_centre_crops_another_aspect_ratio_like_a_video_file(clip, request):
    """A 160x120 file asked for at 80x80: the replay cuts the sides as the video source
    does (not DepthAI's default STRETCH, which scales x and y differently), and the source
    says so in crop_fraction, from which the daemon derives the focal length."""
    pytest.importorskip("depthai")
    if not run_isolated_from_native_crashes(request, timeout=30.0):
        return
    path, frames = clip
    video = open_source(f"video:{path}", width=80, height=80)
    source = open_source(f"depthai-replay:{path}", width=80, height=80)
    try:
        frame = source.read()
    finally:
        source.close()
        video.close()
    _check_frame(frame, 80, 80)
    assert source.crop_fraction == video.crop_fraction == (0.75, 1.0)
    reference = cv2.resize(frames[frame.index][:, 20:140], (80, 80), interpolation=cv2.INTER_AREA)
    assert np.abs(frame.image.astype(int) - reference).mean() < 8
    stretched = cv2.resize(frames[frame.index], (80, 80), interpolation=cv2.INTER_AREA)
    assert np.abs(frame.image.astype(int) - stretched).mean() > np.abs(frame.image.astype(int) - reference).mean() + 4


class _FakeOakFrame:
    """What a live OAK's GRAY8 ImgFrame offers the source (no device exists here)."""

    def __init__(self, index, image, source_size):
        import datetime

        self.index, self.image, self.source_size = index, image, source_size
        now = datetime.timedelta(microseconds=host_us())
        self.device_time = datetime.timedelta(seconds=5, milliseconds=10 * index)
        self.host_time = now - datetime.timedelta(milliseconds=4)

    def getFrame(self):
        return self.image

    def getSequenceNum(self):
        return self.index

    def getTimestampDevice(self):
        return self.device_time

    def getTimestamp(self):
        return self.host_time

    def getSourceWidth(self):
        return self.source_size[0]

    def getSourceHeight(self):
        return self.source_size[1]


class _FakeOakQueue:
    def __init__(self, frames):
        self.frames = list(frames)

    def get(self, timeout=None):
        return self.frames.pop(0) if self.frames else None

    def tryGet(self):
        return self.frames.pop(0) if self.frames else None


class _FakePipeline:
    stopped = False

    def stop(self):
        self.stopped = True

    def isRunning(self):
        return not self.stopped


def _fake_oak(frames=(), error=None):
    from firmware_py.sources.depthai_source import DepthAISource

    pipeline = _FakePipeline()

    class FakeOak(DepthAISource):
        def _start(self, dai):  # the thin seam: everything but the device
            if error:
                raise error
            return pipeline, _FakeOakQueue(frames)

    return FakeOak("CAM_B", width=320, height=240, fps=100), pipeline


@pytest.mark.parametrize("sensor, crop", [((1280, 800), (0.833, 1.0)), ((1280, 720), (0.75, 1.0)),
                                          ((640, 480), (1.0, 1.0)), ((0, 0), (1.0, 1.0))])
def test_live_oak_reports_the_crop_of_its_sensor_image(sensor, crop):
    """depthai's requestOutput crops the sensor image to the asked aspect ratio: the
    OV9282's 1280x800 loses a sixth of its width at 320x240. open() waits for the first
    frame, whose source size tells the crop, and the daemon's focal length follows it."""
    pytest.importorskip("depthai")
    image = _luma(320, 240)
    source, pipeline = _fake_oak([_FakeOakFrame(0, image, sensor)])
    source.open()
    assert source.crop_fraction == pytest.approx(crop, abs=1e-3)
    got = [source.read()]                                        # the frame open() waited for
    source._queue.frames += [_FakeOakFrame(i, image, sensor) for i in (1, 2)]
    got += [source.read(), source.read()]
    assert [f.index for f in got] == [0, 1, 2]
    assert [f.timestamp_us for f in got] == [5_000_000, 5_010_000, 5_020_000]  # device clock
    assert np.array_equal(got[0].image, image)
    source.close()
    assert pipeline.stopped
    # ... unless a newer frame came while the daemon built its engine: the live queue
    # holds only the newest, and the stale one is not flown on
    source, pipeline = _fake_oak([_FakeOakFrame(0, image, sensor), _FakeOakFrame(7, image, sensor)])
    source.open()
    assert source.read().index == 7
    # a 71.9° lens over the whole sensor width: f at 320 px wide from the uncropped width
    config = Config()
    config.set("optics", "horizontal_fov_deg", 71.9)
    expected = focal_length_px_from_fov(fov_deg=71.9, size_px=320 / crop[0])
    assert config.focal_length_px(320 / source.crop_fraction[0], None) == pytest.approx(expected, rel=1e-3)
    source.close()
    assert pipeline.stopped


def test_live_oak_without_a_first_frame_or_camera_is_a_source_error():
    pytest.importorskip("depthai")
    source, pipeline = _fake_oak([])
    with pytest.raises(SourceError, match=r"depthai:CAM_B: no frame for 2 s"):
        source.open()
    assert pipeline.stopped                                    # not left running
    source, _ = _fake_oak(error=RuntimeError("Camera socket not found on the connected device"))
    with pytest.raises(SourceConfigError, match=r"this OAK has no CAM_B camera.*OAK-1 has only the colour camera"):
        source.open()


def test_synthetic_straight_flight_has_known_motion():
    source = open_source("synthetic:u=3,v=-2,noise=0", width=96, height=72, fps=50)
    a, b = source.read(), source.read()
    _check_frame(a, 96, 72)
    assert (a.index, b.index) == (0, 1)
    assert (a.timestamp_us, b.timestamp_us) == (0, 20_000)
    assert source.truth(1) == (3.0, -2.0)
    # the rendered motion matches the truth: phase correlation of the two frames
    window = cv2.createHanningWindow((96, 72), cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(a.image.astype(np.float64), b.image.astype(np.float64), window)
    assert dx == pytest.approx(3.0, abs=0.25) and dy == pytest.approx(-2.0, abs=0.25)


def test_synthetic_circle_loops_seamlessly():
    source = open_source("synthetic:circle=2,period=0.2,noise=0", width=64, height=48, fps=100)
    frames = [source.read() for _ in range(41)]
    assert source.loop_frames == 20
    assert np.array_equal(frames[0].image, frames[20].image)   # one period later: same place
    assert frames[20].timestamp_us == 200_000                  # but the clock goes on
    speeds = [math.hypot(*source.truth(i)) for i in range(20)]
    assert speeds == pytest.approx([2.0] * 20)
    assert source.truth(5) == pytest.approx((0.0, 2.0), abs=1e-9)  # a quarter turn: moving down


def test_bad_uris_are_explained():
    for uri in ("usb:0", "v4l2:", "v4l2:camera", "depthai:RGB", "synthetic:u=fast", "video:"):
        with pytest.raises(ValueError):
            parse_uri(uri)
    # a stray space from a config file: a camera that never appears, retried for ever before
    with pytest.raises(ValueError, match="trailing whitespace"):
        parse_uri("v4l2:/dev/video0 ")
    with pytest.raises(SourceError, match="expected v4l2:/dev/videoN"):
        make_source("webcam")


# -- V4L2: conversion of the raw buffers a driver hands out ------------------------------

def _luma(width=32, height=24):
    return flight_frames(1, width=width, height=height)[0]


def test_raw_grey_is_a_view():
    y = _luma()
    gray = raw_to_gray(y.copy(), "GREY", 32, 24)
    assert np.array_equal(gray, y)
    flat = y.reshape(1, -1).copy()
    assert np.shares_memory(raw_to_gray(flat, "GREY", 32, 24), flat)


def test_raw_yuyv_gives_luma():
    y = _luma()
    packed = np.empty((24, 32, 2), np.uint8)
    packed[:, :, 0] = y
    packed[:, :, 1] = np.tile([90, 160], 16)  # U, V alternate
    assert np.array_equal(raw_to_gray(packed, "YUYV", 32, 24), y)
    assert np.array_equal(raw_to_gray(packed.reshape(1, -1), "YUYV", 32, 24), y)


def test_raw_mjpg_decodes_luma_only():
    y = _luma()
    ok, jpeg = cv2.imencode(".jpg", y, [cv2.IMWRITE_JPEG_QUALITY, 98])
    gray = raw_to_gray(jpeg.reshape(1, -1), "MJPG", 32, 24)
    assert gray.shape == (24, 32)
    assert np.abs(gray.astype(int) - y).mean() < 3
    with pytest.raises(SourceError, match="MJPG frame of 10 bytes"):
        raw_to_gray(np.zeros((1, 10), np.uint8), "MJPG", 32, 24)


def test_raw_short_buffer_is_an_error():
    with pytest.raises(SourceError, match="YUYV frame of 100 bytes, expected 1536"):
        raw_to_gray(np.zeros(100, np.uint8), "YUYV", 32, 24)


class _FakeV4L2Capture:
    """Stands in for cv2.VideoCapture on a /dev/video device (none exists here).

    By default a GREY camera delivering the same 64x48 picture ``frames`` times, whatever
    size was asked. ``buffers(i)`` gives the raw buffer of read ``i`` instead (None: the
    driver read fails), ``size`` and ``fourcc`` what the driver reports, ``interval_s`` the
    frame period (reads block like a camera's).
    """

    def __init__(self, device, api, *, opened=True, frames=3, buffers=None, size=None, fourcc=None,
                 interval_s=0.0):
        self.device, self.api, self.opened = device, api, opened
        self.props: dict[int, float] = {}
        self.frames = frames
        self.luma = _luma(64, 48)
        self.buffers, self.interval_s, self.reads = buffers, interval_s, 0
        self.size = size or (self.luma.shape[1], self.luma.shape[0])
        self.fourcc = fourcc
        self.released = False

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_POS_MSEC:  # V4L2 buffer time: CLOCK_MONOTONIC, in ms
            import time

            return time.monotonic() * 1000.0 - 3.0
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            return self.size[0 if prop == cv2.CAP_PROP_FRAME_WIDTH else 1]  # ignores requests
        if prop == cv2.CAP_PROP_FOURCC and self.fourcc:
            return cv2.VideoWriter_fourcc(*self.fourcc)
        return self.props.get(prop, 0.0)

    def read(self):
        if self.interval_s:
            import time

            time.sleep(self.interval_s)
        if self.buffers is not None:
            self.reads += 1
            raw = self.buffers(self.reads - 1)
            return (False, None) if raw is None else (True, raw)
        if self.frames == 0:
            return False, None
        self.frames -= 1
        return True, self.luma.reshape(1, -1).copy()  # GREY raw buffer

    def release(self):
        self.released = True


def test_v4l2_source_settings_timestamps_and_binning():
    caps = []

    def factory(device, api):
        caps.append(_FakeV4L2Capture(device, api))
        return caps[-1]

    source = V4L2Source("0", width=32, height=24, fps=90, buffer_count=2, exposure_us=2000,
                        capture_factory=factory)
    source.open()
    cap = caps[0]
    assert (cap.device, cap.api) == (0, cv2.CAP_V4L2)
    assert cap.props[cv2.CAP_PROP_BUFFERSIZE] == 2
    assert cap.props[cv2.CAP_PROP_CONVERT_RGB] == 0
    assert cap.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter_fourcc(*"GREY")
    assert cap.props[cv2.CAP_PROP_EXPOSURE] == 20  # 2000 µs in V4L2's 100 µs units
    assert cap.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1  # V4L2_EXPOSURE_MANUAL
    assert cap.props[cv2.CAP_PROP_FRAME_WIDTH] == 32 and cap.props[cv2.CAP_PROP_FPS] == 90
    # this driver delivers 64x48 whatever was asked: the source bins it to 32x24
    frame = source.read()
    _check_frame(frame, 32, 24)
    assert np.array_equal(frame.image, cv2.resize(cap.luma, (32, 24), interpolation=cv2.INTER_AREA))
    assert frame.timestamp_us == frame.capture_host_us  # the driver's monotonic buffer time
    assert 0 < host_us() - frame.capture_host_us < 1_000_000
    source.close()
    assert cap.released


def test_v4l2_device_index_out_of_range_is_a_clear_error():
    """Linux numbers video devices 0..255: a larger index is a configuration error naming
    it (it reached OpenCV, whose overflow error ended the daemon with a traceback, exit 1:
    systemd restarted it in a loop); an error OpenCV raises when opening the camera is a
    source error naming the camera."""
    assert V4L2Source("255").device == 255
    for index in ("256", "99999999999999999999"):
        with pytest.raises(SourceError, match=rf"v4l2 device index {index}: expected 0 to 255"):
            V4L2Source(index)

    def refusing(device, api):
        raise cv2.error("OpenCV(5.0.0) videoio: cannot handle this device")

    with pytest.raises(SourceError, match=r"v4l2:3: cannot open the camera: OpenCV.*cannot handle this device"):
        V4L2Source("3", capture_factory=refusing).open()


def test_v4l2_index_out_of_range_on_the_command_line_exits_2(tmp_path):
    from daemon_util import run_cli

    result = run_cli(["--source", "v4l2:99999999999999999999", "--serial", str(tmp_path / "ttyFC"),
                      "--focal-length-px", "300"], timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]
    assert "v4l2 device index 99999999999999999999: expected 0 to 255" in result.stderr
    assert "Traceback" not in result.stderr


def test_v4l2_without_exposure_asks_for_auto_exposure():
    """A UVC camera keeps an earlier run's manual exposure until it loses power: with no
    exposure_us the source asks for auto exposure (V4L2_EXPOSURE_APERTURE_PRIORITY)."""
    caps = []
    source = V4L2Source("0", capture_factory=lambda d, a: caps.append(_FakeV4L2Capture(d, a)) or caps[-1])
    source.open()
    cap = caps[0]
    assert cap.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 3
    assert cv2.CAP_PROP_EXPOSURE not in caps[0].props
    source.close()
    # V4L2 counts exposure in whole 100 µs units: 50 µs is the shortest, 1, not 0
    source = V4L2Source("0", exposure_us=50, capture_factory=lambda d, a: caps.append(_FakeV4L2Capture(d, a)) or caps[-1])
    source.open()
    assert caps[-1].props[cv2.CAP_PROP_EXPOSURE] == 1 and caps[-1].props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1
    source.close()


def test_v4l2_auto_exposure_falls_back_to_full_auto():
    """A driver whose exposure menu has no aperture priority (3) gets full auto (0)."""
    class NoAperturePriority(_FakeV4L2Capture):
        def set(self, prop, value):
            return False if (prop, value) == (cv2.CAP_PROP_AUTO_EXPOSURE, 3) else super().set(prop, value)

    caps = []
    source = V4L2Source("0", capture_factory=lambda d, a: caps.append(NoAperturePriority(d, a)) or caps[-1])
    source.open()
    assert caps[0].props[cv2.CAP_PROP_AUTO_EXPOSURE] == 0
    source.close()


@pytest.mark.parametrize("delivered, used", [("JPEG", "MJPG"), ("BGR3", "YUYV"), ("NV12", "GREY"),
                                             ("YU12", "GREY")])
def test_v4l2_pixel_format_aliases_are_read(delivered, used, caplog):
    """JPEG is MJPG's other name; planar 4:2:0 (NV12, YU12) starts with the luma plane, as
    GREY does; BGR3 is the driver's own conversion, read from its three channels: all still
    give frames."""
    luma = _luma(64, 48)
    if delivered == "JPEG":
        raw = _jpeg(luma)
    elif delivered == "BGR3":
        raw = cv2.cvtColor(luma, cv2.COLOR_GRAY2BGR)
    else:  # as OpenCV hands out a raw 4:2:0 buffer: (1.5 h, w), luma first, then chroma
        raw = np.concatenate([luma, np.full((24, 64), 128, np.uint8)])
    source = V4L2Source("0", width=64, height=48, pixel_format="YUYV",
                        capture_factory=lambda d, a: _FakeV4L2Capture(d, a, buffers=lambda i: raw, fourcc=delivered))
    source.open()
    assert source.pixel_format == used
    frame = source.read()
    _check_frame(frame, 64, 48)
    assert np.abs(frame.image.astype(int) - luma).mean() < 3
    source.close()


@pytest.mark.parametrize("fmt", ["BGR3", "RGB3"])
@pytest.mark.parametrize("layout", ["flat", "3-D"])
def test_v4l2_driver_colour_is_read_as_colour(fmt, layout):
    """A camera that refuses GREY falls back to the driver's BGR24 (the Pi's legacy CSI
    driver offers no GREY): recent OpenCV hands it out as a flat row with CONVERT_RGB off,
    which was read as GREY (each pixel three times), and RGB3 was weighted as BGR."""
    rng = np.random.default_rng(3)
    colour = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    expected = cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY if fmt == "RGB3" else cv2.COLOR_BGR2GRAY)
    raw = colour.reshape(1, -1) if layout == "flat" else colour
    source = V4L2Source("0", width=64, height=48, pixel_format="GREY",
                        capture_factory=lambda d, a: _FakeV4L2Capture(d, a, buffers=lambda i: raw.copy(),
                                                                      fourcc=fmt, size=(64, 48)))
    source.open()
    try:
        frame = source.read()
    finally:
        source.close()
    assert np.array_equal(frame.image, expected) and source.bad_frames == 0
    red = np.zeros((48, 64, 3), np.uint8)
    red[..., 0 if fmt == "RGB3" else 2] = 200   # pure red in the format's own channel order
    assert raw_to_gray(red.reshape(1, -1), fmt, 64, 48)[0, 0] == 60


def test_v4l2_buffers_with_padded_rows_or_a_wrong_length():
    """Drivers that pad each row to a stride (the Pi's unicam: 16 or 32 bytes) are read row
    by row; a buffer that fits neither the size nor a stride is a bad frame. Longer buffers
    were cut to the expected length: sheared images that passed as good ones."""
    luma = _luma(100, 24)
    padded = np.zeros((24, 112), np.uint8)
    padded[:, :100] = luma
    assert np.array_equal(raw_to_gray(padded.reshape(1, -1), "GREY", 100, 24), luma)
    yuyv = np.full((24, 256), 128, np.uint8)
    yuyv[:, 0:200:2] = luma
    assert np.array_equal(raw_to_gray(yuyv.reshape(1, -1), "YUYV", 100, 24), luma)
    nv12 = np.full((36, 128), 128, np.uint8)   # 24 luma rows and 12 chroma rows, stride 128
    nv12[:24, :100] = luma
    assert np.array_equal(raw_to_gray(nv12.reshape(1, -1), "NV12", 100, 24), luma)
    for bad in (np.zeros(100 * 24 + 7, np.uint8), np.zeros(100 * 24 * 4, np.uint8)):
        with pytest.raises(FrameError, match=rf"GREY frame of {bad.size} bytes, expected 2400"):
            raw_to_gray(bad, "GREY", 100, 24)
    with pytest.raises(FrameError, match="MJPG frame of 0 bytes"):   # (a cv2.error from imdecode)
        raw_to_gray(np.zeros((1, 0), np.uint8), "MJPG", 100, 24)


def test_v4l2_rate_and_size_the_driver_settles_on(caplog):
    """A camera that runs at another rate than the one asked says so, and source.fps is its
    rate (OpenCV's setter succeeds for a rate the camera rounds); a driver that reports no
    size gets it from an unpacked GREY buffer's shape (flat rows cannot tell)."""

    class Rounded(_FakeV4L2Capture):
        def get(self, prop):
            return 30.0 if prop == cv2.CAP_PROP_FPS else super().get(prop)

    big = _luma(96, 72)
    source = V4L2Source("0", width=64, height=48, fps=100.0, capture_factory=lambda d, a: Rounded(
        d, a, buffers=lambda i: big.copy(), size=(0, 0)))
    with caplog.at_level("WARNING", logger="emdflowd.v4l2"):
        source.open()
    try:
        frame = source.read()
    finally:
        source.close()
    assert source.fps == 30.0 and "asked for 100 fps, the camera runs at 30 fps" in caplog.text
    assert source.bad_frames == 0 and frame.image.shape == (48, 64)
    assert np.abs(frame.image.astype(int) - cv2.resize(big, (64, 48), interpolation=cv2.INTER_AREA)).max() <= 1


@pytest.mark.parametrize("delivered", ["Y16 ", "UYVY", "Y10 "])
def test_v4l2_pixel_format_the_source_cannot_decode_is_refused(delivered):
    """A driver that refuses the asked format falls back to its own; one raw_to_gray does
    not know would be decoded as the asked one (garbage frames that look valid)."""
    caps = []
    source = V4L2Source("0", pixel_format="YUYV",
                        capture_factory=lambda d, a: caps.append(_FakeV4L2Capture(d, a, fourcc=delivered)) or caps[-1])
    with pytest.raises(SourceError, match=f"v4l2:0: asked for pixel format YUYV, the driver delivers '{delivered}'"):
        source.open()
    assert caps[0].released


def test_v4l2_path_that_is_no_camera_is_a_setting_to_fix(tmp_path):
    """A folder, a regular file or (on Linux) a character device that is not V4L2's
    (/dev/null) never becomes a camera: a configuration error (exit 2 at start), not a
    camera retried as unplugged or in use for ever."""
    regular = tmp_path / "video0"
    regular.write_bytes(b"")
    cases = [("/dev/", "is a directory"), (str(regular), "is not a device")]
    if sys.platform.startswith("linux"):
        cases.append(("/dev/null", "is a character device of major 1, not V4L2's 81"))
    for path, what in cases:
        source = V4L2Source("/dev/video0")
        source.device = path  # (v4l2: URIs name /dev/ paths; the file is the test's own)
        with pytest.raises(SourceConfigError, match=re.escape(f"{path} {what}: expected a camera")):
            source.open()


def test_v4l2_errors_name_the_device(tmp_path):
    with pytest.raises(SourceError, match="/dev/video9 does not exist"):
        V4L2Source("/dev/video9").open()
    # by index too (OpenCV's failure was blamed on a busy camera or the group 'video'); the
    # last index Linux numbers, which no machine of these tests has
    assert not os.path.exists("/dev/video255")
    with pytest.raises(SourceError, match=re.escape("v4l2:255: /dev/video255 does not exist (camera unplugged?)")):
        V4L2Source("255").open()
    source = V4L2Source("3", capture_factory=lambda d, a: _FakeV4L2Capture(d, a, opened=False))
    with pytest.raises(SourceError, match="v4l2:3: cannot open the camera.*group 'video'"):
        source.open()
    source = V4L2Source("3", capture_factory=lambda d, a: _FakeV4L2Capture(d, a, frames=0))
    source.open()
    with pytest.raises(SourceError, match="v4l2:3: read failed"):
        source.read()


def test_video_source_color_file_gives_luma(tmp_path):
    gray = flight_frames(4, width=96, height=72)
    color = np.stack([cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) for g in gray])
    path = tmp_path / "color.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (96, 72))
    for frame in color:
        writer.write(frame)
    writer.release()
    with open_source(f"video:{path}") as source:
        frames = _read_all(source)
    assert len(frames) == 4
    for frame, expected in zip(frames, gray):
        _check_frame(frame, 96, 72)
        assert np.abs(frame.image.astype(int) - expected).mean() < 4  # lossy MJPG, same picture
    assert frames[1].timestamp_us == 40_000


# -- V4L2: a corrupt buffer is a bad frame, not a lost camera ------------------------------

def _jpeg(image):
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].reshape(1, -1)


def _corrupt(pixel_format, luma):
    """What a USB bandwidth glitch leaves in a buffer of each format."""
    if pixel_format == "MJPG":
        jpeg = _jpeg(luma)
        return jpeg[:, : jpeg.size // 2].copy()                      # truncated JPEG
    return np.zeros((1, luma.size // 3), np.uint8)                 # short GREY / YUYV buffer


def _raw(pixel_format, luma):
    if pixel_format == "MJPG":
        return _jpeg(luma)
    if pixel_format == "YUYV":
        packed = np.full(luma.shape + (2,), 128, np.uint8)
        packed[:, :, 0] = luma
        return packed.reshape(1, -1)
    return luma.reshape(1, -1).copy()


@pytest.mark.parametrize("pixel_format", ["MJPG", "GREY", "YUYV"])
def test_v4l2_corrupt_buffer_is_skipped_counted_and_logged(pixel_format, caplog):
    luma = _luma(64, 48)
    bad = {2, 3, 6}  # reads whose buffer is damaged

    def buffers(i):
        return _corrupt(pixel_format, luma) if i in bad else _raw(pixel_format, luma)

    source = V4L2Source("0", width=64, height=48, pixel_format=pixel_format,
                        capture_factory=lambda d, a: _FakeV4L2Capture(d, a, buffers=buffers, fourcc=pixel_format))
    source.open()
    with caplog.at_level("WARNING", logger="emdflowd.v4l2"):
        frames = [source.read() for _ in range(5)]
    # the damaged buffers are gone, the good ones delivered; the indices show the gaps
    assert [f.index for f in frames] == [0, 1, 4, 5, 7]
    for frame in frames:
        _check_frame(frame, 64, 48)
        assert np.abs(frame.image.astype(int) - luma).mean() < 3
    assert source.bad_frames == 3
    skipped = [r for r in caplog.records if "frame skipped" in r.getMessage()]
    assert len(skipped) == 1                                           # rate-limited
    assert f"v4l2:0: frame 2: {pixel_format} frame of" in skipped[0].getMessage()
    assert skipped[0].levelname == "WARNING"


def test_v4l2_run_of_bad_buffers_or_failed_read_is_a_source_error():
    luma = _luma(64, 48)
    source = V4L2Source("0", width=64, height=48, pixel_format="MJPG", bad_frames_before_reopen=4,
                        capture_factory=lambda d, a: _FakeV4L2Capture(
                            d, a, buffers=lambda i: _jpeg(luma) if i == 0 else _corrupt("MJPG", luma)))
    source.open()
    assert source.read().index == 0
    with pytest.raises(SourceError, match=r"v4l2:0: 4 frames in a row could not be converted \(last: MJPG frame"):
        source.read()
    assert source.bad_frames == 4
    # a failed driver read is still the camera itself: no skipping
    source = V4L2Source("0", width=64, height=48, pixel_format="MJPG",
                        capture_factory=lambda d, a: _FakeV4L2Capture(d, a, buffers=lambda i: None))
    source.open()
    with pytest.raises(SourceError, match="v4l2:0: read failed"):
        source.read()
    assert source.bad_frames == 0


def test_daemon_flies_through_a_corrupt_v4l2_frame_without_reopening():
    """The reviewer's case end to end: one undecodable MJPG buffer in a 100 frames/s stream."""
    from firmware_py.config import Config
    from daemon_util import engine_backend, parse_mavlink, run_daemon

    size = (96, 72)
    flight = flight_frames(30, flow=(1.5, 1.0), width=size[0], height=size[1])
    opens = []

    def buffers(i):
        return _corrupt("MJPG", flight[0]) if i == 20 else _jpeg(flight[i % len(flight)])

    def factory():
        return V4L2Source("0", width=size[0], height=size[1], pixel_format="MJPG",
                          capture_factory=lambda d, a: opens.append(d) or _FakeV4L2Capture(
                              d, a, buffers=buffers, size=size, fourcc="MJPG", interval_s=0.01))

    config = Config()
    config.set("source", "uri", "v4l2:0")
    config.set("source", "pixel_format", "MJPG")
    config.set("optics", "focal_length_px", 100.0)
    config.set("engine", "backend", engine_backend())
    config.set("engine", "model", "paper")
    config.set("link", "message_rate_hz", 100.0)  # (a report every frame: the default is 17 a second)
    config.set("daemon", "blind_after_s", 1.0)   # a reopen (>= 0.5 s back-off) shows in reopens
    made = []
    code, daemon, data = run_daemon(config, frames=40, source_factory=lambda: made.append(factory()) or made[-1])
    assert code == 0
    assert len(opens) == 1 and daemon.stats.reopens == 0 and daemon.stats.blind_periods == 0
    assert daemon.stats.processed == 40
    assert sum(source.bad_frames for source in made) == 1
    assert daemon.stats.bad_frames == 1  # the status line's "bad" counts it
    flows = [m for m in parse_mavlink(data) if m.get_type() == "OPTICAL_FLOW"]
    assert flows and flows[-1].quality > 0


# -- aspect ratio: one scale for both axes ------------------------------------------------

def test_fit_to_centre_crops_to_the_asked_aspect_ratio():
    from firmware_py.sources import centre_crop, fit_to

    image = np.arange(400 * 640, dtype=np.uint32).astype(np.uint8).reshape(400, 640)
    assert centre_crop(640, 400, 320, 240) == (53, 0, 533, 400)        # 16:10 -> 4:3: sides cut
    assert centre_crop(640, 480, 320, 180) == (0, 60, 640, 360)        # 4:3 -> 16:9: rows cut
    assert centre_crop(640, 480, 320, 240) == (0, 0, 640, 480)         # same aspect: all of it
    out = fit_to(image, 320, 240)
    assert out.shape == (240, 320) and out.flags.c_contiguous
    expected = cv2.resize(np.ascontiguousarray(image[:, 53:586]), (320, 240), interpolation=cv2.INTER_AREA)
    assert np.array_equal(out, expected)
    assert np.array_equal(fit_to(image, 400, 400), image[:, 120:520])  # crop only, no resampling
    same = image[:240, :320].copy()
    assert fit_to(same, 320, 240) is same                             # the right size: untouched


def test_v4l2_other_aspect_ratio_is_cropped_not_stretched(caplog):
    """A camera that falls back to 640x400 when 320x240 was asked: equal motion on both axes
    of the sensor must stay equal in the processed frames (the link has one focal length)."""
    sensor = flight_frames(6, flow=(5.0, 5.0), width=640, height=400)  # 3 px/frame processed
    source = V4L2Source("0", width=320, height=240, capture_factory=lambda d, a: _FakeV4L2Capture(
        d, a, buffers=lambda i: sensor[i].reshape(1, -1).copy(), size=(640, 400)))
    with caplog.at_level("INFO", logger="emdflowd.v4l2"):
        source.open()
    frames = [source.read().image for _ in range(6)]
    window = cv2.createHanningWindow((320, 240), cv2.CV_64F)
    shifts = np.array([cv2.phaseCorrelate(a.astype(np.float64), b.astype(np.float64), window)[0]
                       for a, b in zip(frames, frames[1:])])
    dx, dy = np.median(shifts, axis=0)
    assert dx == pytest.approx(5.0 * 320 / 533, abs=0.1)    # both axes scaled by 0.6
    assert dy == pytest.approx(5.0 * 240 / 400, abs=0.1)
    assert dx / dy == pytest.approx(1.0, abs=0.03)          # stretched, it was 0.83
    warning = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warning) == 1
    text = warning[0].getMessage()
    for part in ("asked for 320x240, the camera delivers 640x400", "centre 533x400",
                 "53 columns cut on the left, 54 on the right", "scaled by 0.600 on both axes",
                 "focal_length_px must be the focal length of these 320x240 frames"):
        assert part in text, text
    # what the focal length refers to: 83.3 % of the delivered width is shown
    assert source.crop_fraction == (533 / 640, 1.0)
    fov = 70.0
    f_delivered = 640 / 2 / math.tan(math.radians(fov) / 2)            # px of the 640x400 image
    # (the daemon's rule: the lens sees 1 / crop_fraction[0] of the processed width)
    assert focal_length_px_from_fov(fov_deg=fov, size_px=source.width / source.crop_fraction[0]) == \
        pytest.approx(f_delivered * 320 / 533, rel=1e-9)


def test_v4l2_same_aspect_ratio_is_only_scaled(caplog):
    source = V4L2Source("0", width=32, height=24, capture_factory=_FakeV4L2Capture)  # delivers 64x48
    with caplog.at_level("INFO", logger="emdflowd.v4l2"):
        source.open()
    assert source.crop_fraction == (1.0, 1.0)
    assert focal_length_px_from_fov(fov_deg=90.0, size_px=source.width / source.crop_fraction[0]) == \
        pytest.approx(16.0)
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    assert "camera delivers 64x48, scaled by 0.500 to 32x24" in caplog.text


def _cropping_camera_daemon(*, frames, source_class=V4L2Source, links=None, **daemon_settings):
    """A daemon asking for 320x240 from a 70° camera that delivers 640x400 (cropped to its
    centre 533x400), on the numpy engine, with a link that records its focal lengths."""
    from firmware_py.config import Config
    from firmware_py.daemon import Daemon

    sensor = flight_frames(4, width=640, height=400)

    def factory():
        return source_class("0", width=320, height=240, capture_factory=lambda d, a: _FakeV4L2Capture(
            d, a, buffers=lambda i: sensor[i % 4].reshape(1, -1).copy(), size=(640, 400), interval_s=0.01))

    config = Config()
    config.set("source", "uri", "v4l2:0")
    config.set("optics", "horizontal_fov_deg", 70.0)
    config.set("engine", "backend", "numpy")
    for key, value in daemon_settings.items():
        config.set("daemon", key, value)
    config.frames = frames
    links = [] if links is None else links
    return Daemon(config, source_factory=factory, link_factory=lambda f: links.append(_NullLink(f)) or links[-1])


#: focal length of the 320x240 frames cut from the 640x400 image of a 70° lens, px
_F_CROP = 640 / 2 / math.tan(math.radians(70.0) / 2) * 320 / 533


def test_daemon_focal_length_from_fov_accounts_for_the_crop():
    daemon = _cropping_camera_daemon(frames=1)
    daemon.run()
    assert daemon.focal_length_px == pytest.approx(_F_CROP, rel=1e-6)


def test_camera_absent_at_start_gets_its_focal_length_when_it_opens():
    """A camera that is not there at start-up: the daemon starts with the focal length of
    the asked size; when the camera opens and delivers another aspect ratio (cropped), the
    link gets the focal length of the crop from then on."""
    from firmware_py.sources import SourceError

    attempts = []

    class Late(V4L2Source):
        def open(self):
            attempts.append(1)
            if len(attempts) == 1:
                raise SourceError("v4l2:0: no such device (unplugged)")
            super().open()

    links = []
    daemon = _cropping_camera_daemon(frames=2, source_class=Late, links=links, reopen_backoff_s=0.05)
    assert daemon.run() == 0
    f_asked = 320 / 2 / math.tan(math.radians(70.0) / 2)
    assert len(attempts) >= 2 and links[0].focal_lengths == [pytest.approx(f_asked), pytest.approx(_F_CROP)]
    assert daemon.focal_length_px == pytest.approx(_F_CROP)
    # (the camera opened in the capture thread, but the link is the loop's: it was told there)
    assert daemon.mode == "capture-thread" and links[0].threads == [threading.main_thread().name]


@pytest.mark.parametrize("threading_mode", ["single", "capture-thread"])
def test_a_crop_learnt_from_the_first_frame_changes_the_focal_length(threading_mode):
    """A driver that does not say its size (MJPG, width and height 0): the camera's 640x400
    shows only in the first decoded frame, and with it the crop. The link converts with
    the focal length of that crop from then on; it kept the asked size's (20 % off)."""
    from firmware_py.config import Config
    from firmware_py.daemon import Daemon

    jpeg = cv2.imencode(".jpg", flight_frames(1, width=640, height=400)[0])[1].reshape(1, -1)

    def factory():
        return V4L2Source("0", width=320, height=240, pixel_format="MJPG", capture_factory=lambda d, a: _FakeV4L2Capture(
            d, a, buffers=lambda i: jpeg.copy(), size=(0, 0), fourcc="MJPG", interval_s=0.01))

    config = Config()
    config.set("source", "uri", "v4l2:0")
    config.set("optics", "horizontal_fov_deg", 70.0)
    config.set("engine", "backend", "numpy")
    config.set("daemon", "threading", threading_mode)
    config.frames = 3
    links = []
    daemon = Daemon(config, source_factory=factory, link_factory=lambda f: links.append(_NullLink(f)) or links[-1])
    assert daemon.run() == 0
    f_asked = 320 / 2 / math.tan(math.radians(70.0) / 2)
    assert links[0].focal_lengths == [pytest.approx(f_asked), pytest.approx(_F_CROP)]
    assert daemon.focal_length_px == pytest.approx(_F_CROP)


class _NullLink:
    """A link that sends nothing and records its focal lengths (what those tests look at)."""

    def __init__(self, focal_length_px=None):
        self.stats = {}
        self.focal_lengths = [focal_length_px]
        self.threads = []  # (the threads that changed it)

    def set_focal_length_px(self, focal_length_px):
        self.focal_lengths.append(focal_length_px)
        self.threads.append(threading.current_thread().name)

    def submit(self, sample, now_host_us=None):
        pass

    def service(self, now_us):
        pass

    def latencies_us(self):
        return []

    def close(self):
        pass


# -- video: YUV files through OpenCV's conversion, gray files raw and exact ----------------

def test_video_yuv_file_reads_without_opencv_warnings(tmp_path, capfd):
    gray = flight_frames(12, width=96, height=72)
    path = tmp_path / "flight.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (96, 72), isColor=False)
    for frame in gray:
        writer.write(frame)
    writer.release()
    capfd.readouterr()
    with open_source(f"video:{path}") as source:
        frames = _read_all(source)
        assert not source.raw_gray
    err = capfd.readouterr().err
    assert "Unknown/unsupported picture format" not in err, err[:500]   # was one line per frame
    assert len(frames) == 12
    for frame, expected in zip(frames, gray):
        _check_frame(frame, 96, 72)
        assert np.abs(frame.image.astype(int) - expected).mean() < 4   # full-range gray, not raw luma


def test_video_gray_ffv1_stays_raw_and_exact(clip, capfd):
    path, frames = clip
    capfd.readouterr()
    with open_source(f"video:{path}") as source:
        assert source.raw_gray
        got = _read_all(source)
    assert all(np.array_equal(f.image, frames[i]) for i, f in enumerate(got)) and len(got) == len(frames)
    assert "Unknown/unsupported" not in capfd.readouterr().err


def test_video_other_aspect_ratio_is_cropped(clip, caplog):
    path, frames = clip  # 160x120
    with caplog.at_level("WARNING", logger="emdflowd.video"):
        source = open_source(f"video:{path}", width=160, height=90)
    with source:
        frame = source.read()
    assert np.array_equal(frame.image, frames[0][15:105])
    assert source.crop_fraction == (1.0, 0.75)
    assert "is 160x120, [source] asks for 160x90 (another aspect ratio): its centre 160x90" in caplog.text


# -- synthetic: every numeric option finite and within limits ------------------------------

@pytest.mark.parametrize("option, message", [
    ("period=inf", "period=inf: must be a finite number"),
    ("period=nan", "period=nan: must be a finite number"),
    ("period=1e7", "period=1e7: must be > 0 and <= 3600"),
    ("period=0", "period=0: must be > 0"),
    ("u=inf", "u=inf: must be a finite number"),
    ("v=-1e300", "v=-1e300: must be >= -100 and <= 100"),
    ("circle=-2", "circle=-2: must be >= 0"),
    ("noise=-1", "noise=-1: must be >= 0"),
    ("noise=nan", "noise=nan: must be a finite number"),
    ("seed=-1", "seed=-1: must be >= 0"),
    ("seed=1.5", "seed='1.5': not an integer"),
    ("supersample=0", "supersample=0: must be >= 1 and <= 16"),
    ("supersample=1000", "supersample=1000: must be >= 1 and <= 16"),
])
def test_synthetic_options_must_be_finite_and_sane(option, message):
    with pytest.raises(ValueError, match=re.escape(f"synthetic option {message}")):
        parse_uri(f"synthetic:{option}")
    with pytest.raises(SourceError, match=re.escape(message)):
        make_source(f"synthetic:{option}")


def test_synthetic_long_circle_costs_nothing_up_front():
    import time

    open_source("synthetic:", width=64, height=48).read()  # texture and imports loaded
    t0 = time.monotonic()
    source = open_source("synthetic:period=3600", width=64, height=48, fps=1000)  # 3.6 M frames a loop
    frame = source.read()
    assert time.monotonic() - t0 < 0.5   # was a per-frame table: 2 s and 300 MB here
    _check_frame(frame, 64, 48)
    assert source.loop_frames == 3_600_000


def test_synthetic_circle_cache_is_bounded_by_bytes_not_frames():
    """A circle's frames are kept while they fit 320 MB: a 100-frame circle of small frames
    is kept, the same circle at 4096×4096 (1.7 GB) is rendered live (a 1000-frame cap let
    it keep up to 16.8 GB)."""
    small = open_source("synthetic:period=1", width=64, height=48, fps=100)
    assert small.loop_frames == 100 and small._cache is not None
    large = make_source("synthetic:period=1", width=4096, height=4096, fps=100)
    assert large.loop_frames == 100 and large._cache is None


def test_synthetic_circle_frames_move_as_the_truth_says():
    source = open_source("synthetic:circle=3,period=0.4,noise=0", width=96, height=72, fps=100)
    frames = [source.read().image.astype(np.float64) for _ in range(41)]
    window = cv2.createHanningWindow((96, 72), cv2.CV_64F)
    for k in (1, 7, 13, 22, 31, 40):
        (dx, dy), _ = cv2.phaseCorrelate(frames[k - 1], frames[k], window)
        assert (dx, dy) == pytest.approx(source.truth(k), abs=0.3), k


def test_a_camera_that_cannot_work_as_configured_is_exit_2_at_start(caplog):
    """A camera that substitutes a pixel format emdflow cannot decode is a configuration
    fault, not a lost camera: retrying cannot help, so the daemon stops at start with exit
    code 2 and one line that names the format (the unit does not restart on 2)."""
    from firmware_py.cli import EXIT_CONFIG, run_daemon as run_cli_daemon
    from firmware_py.daemon import Daemon

    config = Config()
    config.set("source", "uri", "v4l2:0")
    config.set("source", "pixel_format", "YUYV")
    config.set("optics", "focal_length_px", 100.0)
    config.set("engine", "backend", "numpy")
    config.frames = 5

    def factory():
        return V4L2Source("0", width=64, height=48, pixel_format="YUYV",
                          capture_factory=lambda d, a: _FakeV4L2Capture(d, a, fourcc="Y16 "))

    import threading


    def make_daemon():
        links = []
        return Daemon(config, source_factory=factory, link_factory=lambda f: links.append(_NullLink(f)) or links[-1])

    # in a thread first: a daemon that retried instead would run for ever
    daemon, raised = make_daemon(), []

    def run():
        try:
            daemon.run()
        except Exception as exc:  # noqa: BLE001 - what the daemon lets out is the point
            raised.append(exc)

    runner = threading.Thread(target=run)
    runner.start()
    runner.join(20.0)
    if runner.is_alive():
        daemon.stop()
        runner.join(10.0)
    assert len(raised) == 1 and isinstance(raised[0], SourceConfigError), raised
    with caplog.at_level("ERROR", logger="emdflowd"):
        assert run_cli_daemon(config, daemon=make_daemon()) == EXIT_CONFIG
    assert any("driver delivers 'Y16 '" in r.getMessage() for r in caplog.records)
