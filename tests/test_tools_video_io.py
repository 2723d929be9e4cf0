"""Frames in, video out (emdflow.tools.video_io)."""

import cv2
import numpy as np
import pytest

from emdflow.tools.video_io import (
    InputError,
    OutputError,
    VideoWriter,
    codec_for,
    open_frames,
    parse_size,
    to_gray,
)


def _frames(n=6, w=40, h=30):
    rng = np.random.default_rng(3)
    return [rng.integers(0, 256, (h, w), dtype=np.uint8) for _ in range(n)]


@pytest.mark.parametrize("name, codec", [("a.avi", None), ("a.mkv", None), ("m.avi", "mjpg"), ("p.mp4", None)])
def test_write_then_read(tmp_path, name, codec):
    frames = _frames()
    path = tmp_path / name
    with VideoWriter(path, fps=12.5, codec=codec) as w:
        for f in frames:
            w.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    src = open_frames(path)
    got = list(src)
    assert len(got) == len(frames)
    assert (src.width, src.height) == (40, 30) and src.fps == pytest.approx(12.5)
    assert all(g.shape == (30, 40) and g.dtype == np.uint8 for g in got)
    if codec_for(path, codec) == "ffv1":  # lossless
        for g, f in zip(got, frames):
            np.testing.assert_array_equal(g, f)


def test_folder_natural_order_resize_and_limit(tmp_path):
    frames = _frames(12)
    for i, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"img{i}.png"), f)
    (tmp_path / "notes.txt").write_text("not an image")
    src = open_frames(tmp_path, fps=10)
    got = list(src)
    assert len(got) == 12 and src.fps == 10
    np.testing.assert_array_equal(got[2], frames[2])  # img2 before img10
    np.testing.assert_array_equal(got[10], frames[10])
    small = list(open_frames(tmp_path, size=(20, 15), max_frames=5))
    assert len(small) == 5 and small[0].shape == (15, 20)


def test_errors_name_the_path(tmp_path):
    with pytest.raises(InputError, match="missing.avi: no such file"):
        open_frames(tmp_path / "missing.avi")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"this is not a video" * 50)
    with pytest.raises(InputError, match="junk.mp4: OpenCV cannot read"):
        open_frames(junk)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="empty: folder has no image files"):
        open_frames(empty)
    folder = tmp_path / "seq"
    folder.mkdir()
    cv2.imwrite(str(folder / "a1.png"), _frames(1)[0])
    (folder / "a2.png").write_bytes(b"broken")
    with pytest.raises(InputError, match="a2.png: OpenCV cannot read"):
        list(open_frames(folder))
    with pytest.raises(OutputError, match="out.xyz: unsupported video type"):
        VideoWriter(tmp_path / "out.xyz")
    with pytest.raises(OutputError, match="does not exist"):
        VideoWriter(tmp_path / "no" / "out.avi")


def test_small_helpers():
    assert parse_size("320x240") == (320, 240)
    with pytest.raises(ValueError, match="WIDTHxHEIGHT"):
        parse_size("320")
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 2] = 255
    assert to_gray(bgr).shape == (4, 5) and to_gray(bgr)[0, 0] == 76  # red → 0.299·255
    assert to_gray(np.full((2, 2), 65535, np.uint16))[0, 0] == 255
