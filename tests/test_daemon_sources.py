"""Frame sources: exact frames, timestamps and sizes from real files, DepthAI replay,
synthetic flights, V4L2 raw-buffer conversion (the camera itself is the only mock)."""

from __future__ import annotations

import os
import sys
import math

import cv2
import numpy as np
import pytest

from firmware_py.sources import Frame, SourceError, host_us, make_source, open_source, parse_uri
from firmware_py.sources.v4l2 import V4L2Source, raw_to_gray
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import flight_frames, write_video  # noqa: E402


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


def test_video_source_missing_file_named(tmp_path):
    with pytest.raises(SourceError, match="nothere.avi.*no such file"):
        open_source(f"video:{tmp_path}/nothere.avi")
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"not a video" * 100)
    with pytest.raises(SourceError, match="bad.avi"):
        open_source(f"video:{bad}")


def test_depthai_replay_same_frames_as_file(clip):
    pytest.importorskip("depthai")
    path, frames = clip
    source = open_source(f"depthai-replay:{path}")
    try:
        got = _read_all(source)
    finally:
        source.close()
    # the DepthAI pipeline may discard what is still in flight when the file ends
    assert len(frames) - 3 <= len(got) <= len(frames)
    for frame in got:
        _check_frame(frame, 160, 120)
        assert np.array_equal(frame.image, frames[frame.index])  # GRAY8, bit-exact
        assert frame.timestamp_us == frame.index * 20_000
    assert [f.index for f in got] == list(range(len(got)))


def test_depthai_replay_host_imagemanip_resizes(clip):
    pytest.importorskip("depthai")
    path, frames = clip
    source = open_source(f"depthai-replay:{path}", width=80, height=60)
    try:
        frame = source.read()
    finally:
        source.close()
    _check_frame(frame, 80, 60)
    reference = cv2.resize(frames[frame.index], (80, 60), interpolation=cv2.INTER_AREA)
    assert np.abs(frame.image.astype(int) - reference).mean() < 8  # same picture, DepthAI's resampler


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
    """Stands in for cv2.VideoCapture on a /dev/video device (none exists here)."""

    def __init__(self, device, api, *, opened=True, frames=3):
        self.device, self.api, self.opened = device, api, opened
        self.props: dict[int, float] = {}
        self.frames = frames
        self.luma = _luma(64, 48)
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
            return self.luma.shape[1 if prop == cv2.CAP_PROP_FRAME_WIDTH else 0]  # ignores requests
        return self.props.get(prop, 0.0)

    def read(self):
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
    assert cap.props[cv2.CAP_PROP_FRAME_WIDTH] == 32 and cap.props[cv2.CAP_PROP_FPS] == 90
    # this driver delivers 64x48 whatever was asked: the source bins it to 32x24
    frame = source.read()
    _check_frame(frame, 32, 24)
    assert np.array_equal(frame.image, cv2.resize(cap.luma, (32, 24), interpolation=cv2.INTER_AREA))
    assert frame.timestamp_us == frame.capture_host_us  # the driver's monotonic buffer time
    assert 0 < host_us() - frame.capture_host_us < 1_000_000
    source.close()
    assert cap.released


def test_v4l2_errors_name_the_device(tmp_path):
    with pytest.raises(SourceError, match="/dev/video9 does not exist"):
        V4L2Source("/dev/video9").open()
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
