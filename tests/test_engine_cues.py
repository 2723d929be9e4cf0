"""Looming cues: expansion rate, time to contact, left/right and top/bottom balance."""

import math

import numpy as np

import emdflow
from emdflow.cues import looming_cues
from emdflow.synthetic import CameraFlight

W, H = 320, 240


def median_cues(frames):
    est = emdflow.FlowEstimator(W, H)
    cues = [looming_cues(est.update(f)) for f in frames]
    return cues[:3], cues[3:]


def test_no_cue_before_history_is_full():
    flight = CameraFlight("gravel", width=W, height=H, expansion_rate=0.02, flow=(0, 0), ground_scale=2.0)
    first, _ = median_cues([flight.render(t) for t in range(5)])
    assert all(c.detections == 0 and c.expansion_rate == 0.0 and math.isinf(c.time_to_contact_frames) for c in first)


def test_expansion_sign_and_monotonic_in_the_true_rate():
    rates = {}
    for r in (-0.02, 0.0, 0.01, 0.02, 0.04):
        flight = CameraFlight("brick", width=W, height=H, expansion_rate=r, flow=(0, 0), ground_scale=2.0, seed=2)
        _, cues = median_cues([flight.render(t) for t in range(10)])
        rates[r] = float(np.median([c.expansion_rate for c in cues]))
    assert rates[-0.02] < -0.005, rates
    assert abs(rates[0.0]) < 0.003, rates
    assert 0.005 < rates[0.01] < rates[0.02] < rates[0.04], rates
    # approaching: finite time to contact, receding: none
    flight = CameraFlight("brick", width=W, height=H, expansion_rate=0.02, flow=(0, 0), ground_scale=2.0)
    _, cues = median_cues([flight.render(t) for t in range(8)])
    ttc = float(np.median([c.time_to_contact_frames for c in cues]))
    assert 10 < ttc < 100  # truth 50 frames; the cue errs early (see emdflow.cues)


def test_translation_has_no_expansion():
    flight = CameraFlight("gravel", width=W, height=H, flow=(3.0, -2.0), seed=4)
    _, cues = median_cues([flight.render(t) for t in range(9)])
    # texture inhomogeneity alone gives |r| of a few 1e-3 (a time to contact of > 100 frames)
    assert abs(float(np.median([c.expansion_rate for c in cues]))) < 0.008


def test_balance_points_to_the_faster_half():
    """Left half of the image flows 4 px/frame, right half 1 px/frame: a near wall on the left."""
    fast = CameraFlight("gravel", width=W, height=H, flow=(4.0, 0.0), seed=1)
    slow = CameraFlight("grass", width=W, height=H, flow=(1.0, 0.0), seed=2)
    frames = []
    for t in range(9):
        frame = slow.render(t)
        frame[:, : W // 2] = fast.render(t)[:, : W // 2]
        frames.append(frame)
    _, cues = median_cues(frames)
    assert float(np.median([c.balance_lr for c in cues])) < -0.2
    # and the same scene mirrored: the right half is faster
    _, cues = median_cues([np.ascontiguousarray(f[:, ::-1]) for f in frames])
    assert float(np.median([c.balance_lr for c in cues])) > 0.2
