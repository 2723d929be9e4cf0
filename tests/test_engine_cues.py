"""Looming cues: expansion rate, time to contact, left/right and top/bottom balance."""

import math

import numpy as np
import pytest

import emdflow
from emdflow import cues
from emdflow.cues import _table_for, looming_cues, slope_expansion_rate
from emdflow.params import MODELS
from emdflow.synthetic import CameraFlight

W, H = 320, 240
EXTENDED = MODELS["extended"]


def fly(flight, frames, **engine):
    """Cues of the ready frames (after the detector's history) of ``frames`` frames."""
    est = emdflow.FlowEstimator(W, H, **engine)
    fields = [est.update(flight.render(t)) for t in range(est.params.history_frames + frames)]
    return [looming_cues(f) for f in fields if f.ready], fields


def median_rate(cues):
    return float(np.median([c.expansion_rate for c in cues]))


def test_no_cue_before_history_is_full():
    flight = CameraFlight("gravel", width=W, height=H, expansion_rate=0.02, flow=(0, 0), ground_scale=2.0)
    est = emdflow.FlowEstimator(W, H)
    first = [looming_cues(est.update(flight.render(t))) for t in range(est.params.history_frames)]
    assert all(c.detections == 0 and c.expansion_rate == 0.0 and math.isinf(c.time_to_contact_frames) for c in first)


@pytest.mark.parametrize("texture", ["gravel", "grass"])
def test_zoom_rate_is_within_15_percent_of_truth(texture):
    """The issue's target, on two of the evaluation photographs (the calibration never saw
    them): the extended model at 1 %/frame, the paper's at 2 %/frame (its slowest channel
    is 1 px/frame: slower zooms barely reach it), where the former line fit read 1.5–1.9×
    the truth; and the extended model at 0.5 %/frame (the edges move 0.8 px/frame) within
    20 %."""
    for engine, rate, tolerance in ((EXTENDED, 0.01, 0.15), ({}, 0.02, 0.15), (EXTENDED, 0.005, 0.2)):
        flight = CameraFlight(texture, width=W, height=H, flow=(0, 0), expansion_rate=rate,
                              supersample=2, seed=11)
        cues, fields = fly(flight, 6, **engine)
        measured = median_rate(cues)
        assert abs(measured / rate - 1.0) < tolerance, (texture, engine, rate, measured)
        ttc = float(np.median([c.time_to_contact_frames for c in cues]))
        assert abs(ttc * rate - 1.0) < tolerance + 0.05, (texture, engine, rate, ttc)
        if tolerance == 0.15:
            old = float(np.median([slope_expansion_rate(f) for f in fields if f.ready]))
            assert old / rate > 1.3, (texture, engine, rate, old)  # the former cue, for the record


def test_receding_is_negative_and_has_no_time_to_contact():
    flight = CameraFlight("gravel", width=W, height=H, flow=(0, 0), expansion_rate=-0.01, supersample=2, seed=3)
    cues, _ = fly(flight, 6, **EXTENDED)
    assert -0.013 < median_rate(cues) < -0.007
    assert all(math.isinf(c.time_to_contact_frames) for c in cues)


def test_static_scene_gives_no_cue():
    flight = CameraFlight("grass", width=W, height=H, flow=(0, 0), seed=5)
    cues, _ = fly(flight, 4)
    assert all(c.detections == 0 and c.expansion_rate == 0.0 for c in cues)


def test_translation_has_no_expansion():
    flight = CameraFlight("gravel", width=W, height=H, flow=(3.0, -2.0), seed=4)
    cues, _ = fly(flight, 6)
    assert all(c.detections > 1000 for c in cues)
    # texture inhomogeneity alone gives |r| of a few 1e-3 (a time to contact of > 200 frames)
    assert abs(median_rate(cues)) < 0.005
    cues, _ = fly(CameraFlight("grass", width=W, height=H, flow=(0.5, 0.3), seed=4), 6, **EXTENDED)
    assert abs(median_rate(cues)) < 0.002


def test_uncalibrated_channels_fall_back_to_the_line_fit():
    flight = CameraFlight("gravel", width=W, height=H, flow=(0, 0), expansion_rate=0.02, supersample=2, seed=2)
    est = emdflow.FlowEstimator(W, H, scales=(1, 3, 5, 7))
    assert _table_for(est.params) is None
    for t in range(est.params.history_frames + 2):
        field = est.update(flight.render(t))
    cue = looming_cues(field)
    assert cue.detections > 0 and cue.expansion_rate == pytest.approx(slope_expansion_rate(field))
    assert cue.expansion_rate > 0.01


def test_uncalibrated_line_fit_beyond_the_rate_limit_is_no_cue():
    """The line fit of an uncalibrated channel set is held to the same 0.1/frame limit as
    the calibrated fit: two halves moving apart at 6 px/frame (64 px wide) read rates of
    0.24-0.35/frame, contact 'in 3 frames', as a cue."""
    w, h = 64, 48
    left = CameraFlight("gravel", width=w, height=h, flow=(-6.0, 0.0), seed=1)
    right = CameraFlight("gravel", width=w, height=h, flow=(6.0, 0.0), seed=2)
    est = emdflow.FlowEstimator(w, h, scales=(1, 3, 5, 7))
    assert _table_for(est.params) is None
    fits = 0
    for t in range(8):
        frame = right.render(t)
        frame[:, : w // 2] = left.render(t)[:, : w // 2]
        field = est.update(frame)
        cue = looming_cues(field)
        fitted = slope_expansion_rate(field)
        if field.ready and cue.detections == 0 and fitted is not None and abs(fitted) > 0.1:
            fits += 1  # the fit went past the limit: no cue
        assert abs(cue.expansion_rate) <= 0.1
    assert fits > 0


def test_no_cue_while_a_brightness_step_is_in_the_templates():
    """The frames whose templates hold a global brightness step give no cue, as they give
    quality 0 in the summary (their detections are the step's, not motion)."""
    flight = CameraFlight("gravel", width=W, height=H, flow=(0, 0), expansion_rate=0.02, supersample=2, seed=2)
    est = emdflow.FlowEstimator(W, H)
    flagged = 0
    for t in range(14):
        frame = flight.render(t).astype(np.float64) * (1.4 if t >= 9 else 1.0)
        field = est.update(np.clip(frame, 0, 255).astype(np.uint8))
        cue = looming_cues(field)
        if field.exposure_step:
            flagged += 1
            assert cue.detections == 0 and cue.expansion_rate == 0.0
        elif field.ready and t >= 12:
            assert cue.detections > 0  # (the cue comes back after the step)
    assert flagged == 3


def test_cue_of_something_that_is_no_field_is_a_type_error():
    from emdflow.cues import slope_expansion_rate

    for thing in (None, np.zeros((4, 4)), "x"):
        with pytest.raises(TypeError, match=r"looming_cues\(\) takes a FlowField, not "):
            looming_cues(thing)
        # (its uncalibrated fallback too: an AttributeError from inside before)
        with pytest.raises(TypeError, match=r"slope_expansion_rate\(\) takes a FlowField, not "):
            slope_expansion_rate(thing)


def test_cue_reads_the_histograms_only():
    """The cue works on the 2 × 16 position bins, never on the dense field, so its cost
    does not grow with the frame size (the README gives the measured cost): a field whose
    dense codes cannot be decoded gives the same cue."""
    from emdflow.field import FlowField

    flight = CameraFlight("gravel", width=640, height=480, flow=(1.0, 0.5), expansion_rate=0.01, seed=1)
    est = emdflow.FlowEstimator(640, 480, **EXTENDED)
    fields = [est.update(flight.render(t)) for t in range(est.params.history_frames + 3)]
    field = fields[-1]

    class NoDenseField:
        def decode(self):
            raise AssertionError("looming_cues decoded the dense field")

    sparse = FlowField(None, None, field.stats, field.histogram, field.params, field.frame_index,
                       positions=field.positions, packed=NoDenseField(), shape=field.shape)
    cue = looming_cues(field)
    assert cue.detections > 0 and looming_cues(sparse) == cue


def test_balance_points_to_the_faster_half():
    """Left half of the image flows 4 px/frame, right half 1 px/frame: a near wall on the left."""
    fast = CameraFlight("gravel", width=W, height=H, flow=(4.0, 0.0), seed=1)
    slow = CameraFlight("grass", width=W, height=H, flow=(1.0, 0.0), seed=2)
    frames = []
    for t in range(9):
        frame = slow.render(t)
        frame[:, : W // 2] = fast.render(t)[:, : W // 2]
        frames.append(frame)
    est = emdflow.FlowEstimator(W, H)
    cues = [looming_cues(est.update(f)) for f in frames][3:]
    assert float(np.median([c.balance_lr for c in cues])) < -0.2
    # and the same scene mirrored: the right half is faster
    est = emdflow.FlowEstimator(W, H)
    cues = [looming_cues(est.update(np.ascontiguousarray(f[:, ::-1]))) for f in frames][3:]
    assert float(np.median([c.balance_lr for c in cues])) > 0.2


def test_an_axis_without_evidence_has_no_balance():
    """Vertical stripes sliding sideways give the horizontal detectors all the evidence and
    the vertical ones none: the top/bottom balance is unknown (NaN), not 0.0, which reads
    "balanced" (and went out as such over MAVLink)."""
    rng = np.random.default_rng(3)
    columns = (rng.random(W + 40) * 255).astype(np.uint8)
    frames = [np.ascontiguousarray(np.tile(columns[2 * t:2 * t + W], (H, 1))) for t in range(10)]
    est = emdflow.FlowEstimator(W, H)
    found = [c for c in (looming_cues(est.update(f)) for f in frames) if c.detections]
    assert found
    assert all(math.isnan(c.balance_tb) and math.isfinite(c.balance_lr) for c in found), found


def test_zoom_eval_tool_reports_every_cell(tmp_path):
    from emdflow.tools import zoom_eval

    results = zoom_eval.evaluate(models=("paper",), textures=("gravel",), rates=(0.02,),
                                 translations=((0.0, 0.0),), frames=2, flights=1, backend="numpy",
                                 width=96, height=72)
    cell = results[("paper", (0.0, 0.0), "gravel", 0.02)]
    assert len(cell["new"]) == len(cell["old"]) == 2
    report = zoom_eval.format_report(results)
    assert "| gravel |" in report and "median relative error" in report
    # the tables round-trip through the file the cue reads
    table = {"channels": ((1, 1),), "threshold_mode": "fixed", "flights": 1, "seed": 0,
             "response": np.arange(300.0).reshape(30, 10) / 7, "rate": np.ones((30, 10))}
    path = zoom_eval.write_calibration({"x": table}, tmp_path / "t.npz")
    back = cues.load_calibration(path)["x"]
    assert back["channels"] == ((1, 1),) and back["threshold_mode"] == "fixed" and back["flights"] == 1
    assert np.array_equal(back["response"], table["response"]) and "x: channels" in zoom_eval.format_calibration(
        {"x": table})


def test_zoom_eval_flies_over_any_known_ground(tmp_path):
    """``zoom_eval --textures`` takes every ground the renderer knows (synthetic grids and
    fractals, image files) besides scikit-image's data files, and names an unknown one."""
    import cv2

    from emdflow.tools import zoom_eval

    image = tmp_path / "ground.png"
    cv2.imwrite(str(image), (np.random.default_rng(1).random((64, 64)) * 255).astype(np.uint8))
    for name in ("lines-5-30", "cells-1", "fractal-1.0-1", "gravel", str(image)):
        assert zoom_eval.texture_source(name) == name
    assert zoom_eval.texture_source("ihc").endswith("ihc.png")
    with pytest.raises(ValueError, match="no-such-ground"):
        zoom_eval.texture_source("no-such-ground")


def test_hand_made_positions_and_min_detections_are_checked():
    """A position histogram of another shape gave a cue from the wrong bins, and a
    min_detections of '50' a numpy type error, NaN no cue, -1 was taken: all now say what
    was expected."""
    from emdflow.field import FlowField
    from emdflow.params import EngineParams

    params = EngineParams()
    codes = np.zeros((48, 64), np.int8)
    stats = np.zeros(20, np.int64)
    hist = np.zeros((params.evidence_axes, 14, 64), np.int64)
    good = np.full((2, 14, 16), 40, np.int64)
    for call in (looming_cues, slope_expansion_rate):
        field = FlowField(codes, codes, stats, hist, params, 9, positions=good[:, :, :8])
        with pytest.raises(ValueError, match=r"position histogram has shape \(2, 14, 8\).*need \(2, 14, 16\)"):
            call(field)
        field = FlowField(codes, codes, stats, hist, params, 9, positions=good)
        for bad in ("50", math.nan, -1, 2.5):
            with pytest.raises(ValueError, match="min_detections=.*expected a whole number >= 0"):
                call(field, min_detections=bad)
        call(field, min_detections=0)
