"""The diagonal detectors of the summary's evidence (``EngineParams.diagonal_evidence``)."""

from __future__ import annotations

import numpy as np
import pytest

from emdflow import opencl_backend
from emdflow.params import MODELS, EngineParams
from emdflow.reference import ReferenceEngine

#: histogram axis and sign (1: negative) of an edge moving along the diagonal (sx, sy)
DIAGONALS = {(1, 1): (2, 0), (-1, -1): (2, 1), (1, -1): (3, 0), (-1, 1): (3, 1)}


def diagonal_edge_frames(width, height, k, sx, sy, bright_ahead, frames):
    """A straight edge whose normal is the diagonal ``(sx, sy)``, moving ``k`` diagonal
    steps ``(sx, sy)`` per frame: ``d = sx x + sy y`` of the edge grows by ``2k`` a frame."""
    y, x = np.mgrid[0:height, 0:width]
    d = sx * x + sy * y
    start = d.min() + 12
    out = []
    for t in range(frames):
        ahead = d > start + 2 * k * t
        out.append(np.where(ahead == bright_ahead, 200, 40).astype(np.uint8))
    return out


def test_the_axes_have_one_step_everywhere():
    """The reference's detectors of each histogram axis step by the axis's step, the one
    the summary's and the calibration's geometry read (``EVIDENCE_AXIS_STEPS``)."""
    from emdflow.reference import DIRECTIONS, EVIDENCE_AXES
    from emdflow.params import EVIDENCE_AXIS_STEPS

    for axis, (positive, negative) in enumerate(EVIDENCE_AXES):
        assert DIRECTIONS[positive] == EVIDENCE_AXIS_STEPS[axis]
        assert DIRECTIONS[negative] == tuple(-v for v in EVIDENCE_AXIS_STEPS[axis])
    assert {DIRECTIONS[p] for p, _ in EVIDENCE_AXES[2:]} == set(DIAGONALS) & {(1, 1), (1, -1)}


@pytest.mark.parametrize("direction", list(DIAGONALS), ids=lambda d: f"{d[0]:+d}{d[1]:+d}")
@pytest.mark.parametrize("k", [1, 3, 5])
def test_an_edge_moving_along_a_diagonal_fires_that_diagonal_at_its_speed(direction, k):
    """Each diagonal detector reports an edge moving along it in its own axis, with the
    right sign and at the channel of its speed (``k`` steps of ``(1, ±1)`` px a frame); the
    other diagonal, along which the edge only slides, stays nearly silent. The two
    backends bin the same detections."""
    width, height = 150, 130
    params = EngineParams(evidence_row_step=1)
    axis, negative = DIAGONALS[direction]
    engines = (ReferenceEngine(width, height, params), opencl_backend.OpenCLEngine(width, height, params))
    total = np.zeros((4, 2 * len(params.channels)), np.int64)
    for bright_ahead in (True, False):  # both polarities
        for engine in engines:
            engine.reset()
        for frame in diagonal_edge_frames(width, height, k, *direction, bright_ahead, 7):
            (_, _, _, hist, pos), (_, _, _, hist_cl, pos_cl) = (e.step(frame) for e in engines)
            assert np.array_equal(hist, hist_cl) and np.array_equal(pos, pos_cl)
            total += hist.sum(axis=-1)
    c = params.channels.index((k, 1))
    along, other = total[axis], total[5 - axis]
    assert along.sum() > 50
    assert along[negative::2].sum() > 0.95 * along.sum()  # the sign
    # the channel of k fires, none slower; as on an axis, the next faster ones share a
    # sharp edge (the prefiltered ramp lights each receptor for two frames or more)
    per_channel = along.reshape(-1, 2).sum(axis=1)
    assert per_channel[c] > 0.15 * along.sum()
    assert per_channel[:c].sum() < 0.05 * along.sum() and per_channel[c + 3:].sum() == 0
    assert other.sum() < 0.1 * along.sum()


def test_the_dense_field_does_not_depend_on_the_diagonals():
    """The diagonals feed the histogram only: the codes, the counters and the position
    histogram are those of an engine without them; the histogram's first two axes too."""
    from emdflow.synthetic import CameraFlight

    width, height = 97, 61
    flight = CameraFlight("gravel", width=width, height=height, flow=(2.3, 1.1), noise_sigma=2, seed=4)
    for model in ("paper", "extended"):
        on = EngineParams(**MODELS[model])
        off = EngineParams(**MODELS[model], diagonal_evidence=False)
        assert on.diagonal_evidence and on.evidence_axes == 4 and off.evidence_axes == 2
        engines = [opencl_backend.OpenCLEngine(width, height, p) for p in (on, off)]
        diagonal = 0
        for t in range(on.history_frames + 4):
            frame = flight.render(t)
            (u, v, stats, hist, pos), (u2, v2, stats2, hist2, pos2) = (e.step(frame) for e in engines)
            assert np.array_equal(u, u2) and np.array_equal(v, v2) and np.array_equal(stats, stats2)
            assert np.array_equal(pos, pos2) and np.array_equal(hist[:2], hist2)
            assert hist.shape[0] == 4 and hist2.shape[0] == 2
            diagonal += int(hist[2:].sum())
        assert diagonal > 0


def test_the_diagonals_see_the_minor_axis_of_a_fast_oblique_flight():
    """Flow (8, 4) px/frame over gravel and brick: the vertical detectors go blind under
    the fast sideways motion (``emdflow.tools.cross_motion``), the diagonal nearest the
    flow sees it with a third of that sideways motion, and the summary's direction error
    falls (paper's model, its tables with and without the diagonals; 320×240, 8 flights)."""
    import emdflow
    from emdflow.tools.cross_motion import evaluate

    errors = {}
    for diagonal in (False, True):
        est = emdflow.FlowEstimator(320, 240, diagonal_evidence=diagonal)
        rows = evaluate(model="paper", textures=("gravel", "brick"), majors=(8.0,), flights=8, estimator=est)
        errors[diagonal] = {r["texture"]: r["direction_error_deg"] for r in rows}
    for texture in ("gravel", "brick"):
        assert errors[False][texture] > 6.0  # the blind minor axis (paper's model: 9.7° and 13.5°)
        assert errors[True][texture] < 0.7 * errors[False][texture], (texture, errors)
