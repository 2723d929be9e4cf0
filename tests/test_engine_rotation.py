"""Turns of a pinhole camera: the renderer's geometry, and how much faster the summary reads
a turn than a translation of the same centre flow on a wide lens (README, "Wide lenses and
turns"). OpenCL on PoCL where the engine runs."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from emdflow.synthetic import RotatingCamera
from emdflow.tools import rotation_eval
from firmware_py.angular import turn_gain


def _dis_mean(a, b, rows, cols):
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(a, b, None)
    return flow[rows, cols].reshape(-1, 2).mean(axis=0)


@pytest.mark.parametrize("flow", [(3.0, 0.0), (0.0, -2.0), (2.0, 1.5)])
def test_rotating_camera_moves_the_centre_by_the_flow_and_the_edge_by_the_pinhole_law(flow):
    f = 200.0
    cam = RotatingCamera("gravel", focal_length_px=f, flow=flow, noise_sigma=0.0)
    a, b = cam.render(3), cam.render(4)
    centre = _dis_mean(a, b, slice(110, 130), slice(150, 170))
    assert np.allclose(centre, flow, atol=0.06), centre
    # 122 px right of the centre (X = 0.61, Y ~ 0): u = u0 (1 + X²); the turn about x adds u0-free XY terms
    edge = _dis_mean(a, b, slice(110, 130), slice(272, 292))
    X = 122.0 / f
    assert edge[0] == pytest.approx(flow[0] * (1 + X * X), abs=0.12 + 0.03 * abs(flow[0]))
    assert cam.truth(4).flow_x == flow[0] and cam.truth(4).flow_y == flow[1]


def test_rotating_camera_refuses_bad_parameters():
    with pytest.raises(ValueError, match="focal_length_px"):
        RotatingCamera(focal_length_px=0.0)
    with pytest.raises(ValueError, match="focal_length_px"):
        RotatingCamera(focal_length_px=float("nan"))
    with pytest.raises(ValueError, match="45 deg"):
        RotatingCamera(focal_length_px=10.0, flow=(20.0, 0.0))
    with pytest.raises(ValueError, match="frame size"):
        RotatingCamera(width=4)
    # 6 deg per frame: frame 10 looks 60 deg + the corner's 32 deg away from frame 0's axis
    cam = RotatingCamera(focal_length_px=200.0, flow=(21.0, 0.0), noise_sigma=0.0)
    cam.render(5)
    with pytest.raises(ValueError, match="frame 10: a corner looks"):
        cam.render(10)
    assert RotatingCamera(focal_length_px=200.0, flow=(21.0, 0.0), reference_frame=10).render(10).shape == (240, 320)


def test_turn_gain_is_the_even_spread_pinhole_mean():
    f = 320 / 2 / math.tan(math.radians(73) / 2)
    gx, gy = turn_gain(width=320, height=240, focal_length_px=f)
    assert gx == pytest.approx(1 + math.tan(math.radians(36.5)) ** 2 / 3)
    assert 1.0 < gy < gx
    assert turn_gain(width=320, height=240, focal_length_px=1e6) == pytest.approx((1.0, 1.0))
    with pytest.raises(ValueError, match="focal_length_px"):
        turn_gain(width=320, height=240, focal_length_px=0)


def test_summary_reads_turns_faster_on_a_wide_lens():
    rows = rotation_eval.evaluate(model="extended", fovs=(30.0, 90.0), textures=("gravel",), frames=4,
                                  backend="opencl")
    narrow, wide = rows
    # translations read alike at every field of view (the same flights)
    assert narrow["translation"] == wide["translation"] and 0.85 < narrow["translation"] < 1.1
    # a narrow lens: a turn reads as its centre flow, within 4 %
    assert narrow["ratio"] == pytest.approx(1.0, abs=0.04)
    # a wide one: ~1.15-1.2x, up to the even-spread prediction (1.26; with the diagonal
    # detectors' evidence the summary reads 1.16 over gravel, without it 1.235)
    assert 1.12 < wide["ratio"] < wide["pinhole"] + 0.03
    report = rotation_eval.format_report(rows)
    assert "| 90° | gravel |" in report and f"**{wide['ratio']:.3f}**" in report


def test_rotation_eval_command_refuses_bad_options(capsys):
    with pytest.raises(SystemExit):
        rotation_eval.main(["--fovs", "0,200"])
    assert "fields of view" in capsys.readouterr().err
    assert rotation_eval.main(["--speed", "-1", "--fovs", "40", "--textures", "gravel"]) == 2
    assert "speed=-1.0: must be > 0" in capsys.readouterr().err
