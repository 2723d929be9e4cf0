"""px/frame → rad, rad/s: conversion, mounting, measured intervals, gaps, quality."""

import math

import pytest

from firmware_py.angular import (
    FlowIntegrator,
    apply_mounting,
    focal_length_px_from_fov,
    fov_deg_from_focal_length_px,
)


def test_focal_length_from_fov():
    assert focal_length_px_from_fov(fov_deg=90.0, size_px=640) == pytest.approx(320.0)
    # Halving the processed resolution halves the focal length in pixels.
    full = focal_length_px_from_fov(fov_deg=62.2, size_px=640)
    half = focal_length_px_from_fov(fov_deg=62.2, size_px=320)
    assert half == pytest.approx(full / 2)
    # and back: the field of view of a focal length
    assert fov_deg_from_focal_length_px(focal_length_px=half, size_px=320) == pytest.approx(62.2)
    with pytest.raises(ValueError):
        fov_deg_from_focal_length_px(focal_length_px=0.0, size_px=320)
    with pytest.raises(ValueError):
        focal_length_px_from_fov(fov_deg=180.0, size_px=640)


@pytest.mark.parametrize("rotation, expected", [(0, (1.0, 2.0)), (90, (-2.0, 1.0)),
                                                (180, (-1.0, -2.0)), (270, (2.0, -1.0))])
def test_mounting_table(rotation, expected):
    assert apply_mounting(1.0, 2.0, rotation_deg=rotation) == expected


def test_mounting_physical_meaning():
    # Camera turned 90° clockwise (image top to the vehicle's right): flying forward moves
    # the ground towards the vehicle's rear = the image's right (+u). After mounting this must
    # be the default camera's forward-flight flow (+v').
    assert apply_mounting(2.0, 0.0, rotation_deg=90) == (0.0, 2.0)
    # Mirror is undone first: a mirrored default camera sees rightward motion as +u.
    assert apply_mounting(1.0, 0.0, mirror=True) == (-1.0, 0.0)
    assert apply_mounting(1.0, 0.0, rotation_deg=90, mirror=True) == (0.0, -1.0)
    with pytest.raises(ValueError):
        apply_mounting(1.0, 0.0, rotation_deg=45)


def feed(integ, stamps, flow=(0.0, 0.0), quality=200):
    for t in stamps:
        integ.add_frame(timestamp_us=t, flow_x_px=flow[0], flow_y_px=flow[1], quality=quality)


def test_conversion_px_per_frame_to_rad():
    f = 400.0
    integ = FlowIntegrator(focal_length_px=f)
    feed(integ, [0, 10_000, 20_000], flow=(-1.0, 2.0))
    iv = integ.take()
    assert iv.integration_time_us == 20_000
    assert iv.integrated_x == pytest.approx(-2.0 / f)
    assert iv.integrated_y == pytest.approx(4.0 / f)
    # rate = px/frame * fps / f
    assert iv.rate_y == pytest.approx(2.0 * 100 / f)
    assert iv.rate_x == pytest.approx(-1.0 * 100 / f)
    assert iv.quality == 200 and iv.frame_count == 2


def test_rates_use_measured_intervals_not_nominal_fps():
    integ = FlowIntegrator(focal_length_px=500.0)
    # A "100 fps" camera that really delivers 8, 12, 9, 11 ms frames with 0.5 px/ms motion.
    stamps = [0, 8_000, 20_000, 29_000, 40_000]
    integ.add_frame(timestamp_us=0, flow_x_px=0, flow_y_px=0, quality=200)
    for a, b in zip(stamps, stamps[1:]):
        integ.add_frame(timestamp_us=b, flow_x_px=0.0, flow_y_px=0.5 * (b - a) / 1000, quality=200)
    iv = integ.take()
    assert iv.integration_time_us == 40_000
    assert iv.rate_y == pytest.approx(0.5 * 1000 / 500.0)


def test_dropped_frame_gives_no_spike():
    f = 400.0
    integ = FlowIntegrator(focal_length_px=f)
    rates = []
    t = 0
    integ.add_frame(timestamp_us=t, flow_x_px=0, flow_y_px=0, quality=200)
    for i in range(30):
        step = 2 if i == 15 else 1  # one frame lost: the next reports two frames of motion
        t += step * 10_000
        integ.add_frame(timestamp_us=t, flow_x_px=0.0, flow_y_px=1.5 * step, quality=200)
        rates.append(integ.take())
    assert integ.restart_count == 0
    values = [iv.rate_y for iv in rates]
    assert max(values) == pytest.approx(min(values)) == pytest.approx(1.5 * 100 / f)
    assert rates[15].integration_time_us == 20_000


def test_gap_restarts_integration():
    integ = FlowIntegrator(focal_length_px=400.0)
    feed(integ, range(0, 100_000, 10_000), flow=(0.0, 1.0))
    # A 2 s stall: the frame after it carries motion from across the gap.
    integ.add_frame(timestamp_us=2_090_000, flow_x_px=0.0, flow_y_px=200.0, quality=200)
    assert integ.restart_count == 1
    feed(integ, [2_100_000, 2_110_000], flow=(0.0, 1.0))
    iv = integ.take()
    assert iv.integration_time_us == 20_000  # no huge integration time
    assert iv.rate_y == pytest.approx(100 / 400.0)  # no spike
    # 5 nominal intervals is the threshold at 100 fps.
    assert integ.gap_threshold_us == pytest.approx(50_000, rel=0.05)


def test_clock_going_backwards_restarts():
    integ = FlowIntegrator(focal_length_px=400.0)
    feed(integ, [0, 10_000, 20_000])
    integ.add_frame(timestamp_us=5_000, flow_x_px=3.0, flow_y_px=3.0, quality=200)
    assert integ.restart_count == 1
    assert integ.take().integration_time_us == 0


def test_quality_mean_and_blind_frames():
    integ = FlowIntegrator(focal_length_px=400.0)
    integ.add_frame(timestamp_us=0, flow_x_px=0, flow_y_px=0, quality=100)
    integ.add_frame(timestamp_us=10_000, flow_x_px=0, flow_y_px=1, quality=100)
    integ.add_frame(timestamp_us=20_000, flow_x_px=0, flow_y_px=1, quality=200)
    assert integ.take().quality == 150
    # One blind frame: time still advances, the interval is reported as quality 0.
    integ.add_frame(timestamp_us=30_000, flow_x_px=0, flow_y_px=1, quality=200)
    integ.add_frame(timestamp_us=40_000, flow_x_px=9, flow_y_px=9, quality=0)
    iv = integ.take()
    assert iv.quality == 0 and iv.integration_time_us == 20_000
    assert iv.integrated_y == pytest.approx(1 / 400.0)  # the blind frame's garbage is not added
    # NaN flow counts as blind.
    integ.add_frame(timestamp_us=50_000, flow_x_px=math.nan, flow_y_px=0, quality=200)
    assert integ.take().quality == 0
    # So does a flow no camera measures (a focal length or more per frame): two such
    # frames summed would overflow to inf, which no link could encode
    for t, flow in ((60_000, 1e300), (70_000, 1.5e308), (80_000, 400.0)):
        integ.add_frame(timestamp_us=t, flow_x_px=flow, flow_y_px=-flow, quality=200)
        iv = integ.take()
        assert iv.quality == 0 and iv.integrated_x == iv.integrated_y == 0.0
    integ.add_frame(timestamp_us=90_000, flow_x_px=399.0, flow_y_px=0.0, quality=200)
    assert integ.take().quality == 200


def test_doubtful_frames_are_left_out_and_the_rest_read_over_the_span():
    """A frame below the link's quality floor (doubtful: its flow may be far off) is left
    out of the sums, not taken as blind: the interval's angle is its other frames' mean rate
    over the whole span, its quality their mean; fewer trusted frames than half, or a
    one-frame interval of a doubtful frame: quality 0 (as the floor's zeroing did)."""
    integ = FlowIntegrator(focal_length_px=400.0)
    integ.add_frame(timestamp_us=0, flow_x_px=0, flow_y_px=0, quality=200)
    for i, (flow, quality, doubtful) in enumerate([(1.0, 200, False), (-7.0, 30, True), (1.0, 220, False),
                                                   (1.0, 240, False), (5.0, 40, True), (1.0, 200, False)]):
        integ.add_frame(timestamp_us=(i + 1) * 10_000, flow_x_px=0.0, flow_y_px=flow, quality=quality,
                        doubtful=doubtful)
    iv = integ.take()
    assert iv.integration_time_us == 60_000 and iv.frame_count == 6
    # (200 + 220 + 240 + 200) / 4 = 215, times the 40 of 60 ms those four frames cover
    assert iv.quality == 143
    assert iv.integrated_y == pytest.approx(6 * 1.0 / 400.0)   # 1 px/frame over all six frames
    assert iv.sum_v_px == pytest.approx(6.0) and iv.integrated_x == 0.0
    # half of them trusted is enough (the quality then half the trusted one's); fewer is 0
    for flags, quality in (([True, False], 100), ([True, True, False], 0), ([True], 0)):
        for j, doubtful in enumerate(flags):
            integ.add_frame(timestamp_us=integ.last_timestamp_us + 10_000, flow_x_px=0.0, flow_y_px=1.0,
                            quality=50 if doubtful else 200, doubtful=doubtful)
        assert integ.take().quality == quality, flags
    # a doubtful frame's flow is never summed: not even a NaN or absurd one blanks the report
    for bad in (math.nan, 1e300):
        for flow, doubtful in ((1.0, False), (bad, True), (1.0, False), (1.0, False)):
            integ.add_frame(timestamp_us=integ.last_timestamp_us + 10_000, flow_x_px=0.0, flow_y_px=flow,
                            quality=50 if doubtful else 200, doubtful=doubtful)
        iv = integ.take()
        assert iv.quality == 150 and iv.integrated_y == pytest.approx(4 / 400.0), bad
    # a blind frame still makes the interval quality 0
    integ.add_frame(timestamp_us=integ.last_timestamp_us + 10_000, flow_x_px=0.0, flow_y_px=1.0, quality=200)
    integ.add_frame(timestamp_us=integ.last_timestamp_us + 10_000, flow_x_px=0.0, flow_y_px=1.0, quality=50,
                    doubtful=True)
    integ.add_frame(timestamp_us=integ.last_timestamp_us + 10_000, flow_x_px=0.0, flow_y_px=1.0, quality=0)
    assert integ.take().quality == 0


def test_blind_keepalive_sample_extends_instead_of_restarting():
    integ = FlowIntegrator(focal_length_px=400.0)
    feed(integ, range(0, 200_000, 10_000), flow=(0.0, 1.0))
    integ.take()
    # The daemon's quality-0 sample 0.3 s later keeps the interval sequence continuous.
    integ.add_frame(timestamp_us=490_000, flow_x_px=0, flow_y_px=0, quality=0)
    assert integ.restart_count == 0
    iv = integ.take()
    assert iv.quality == 0 and iv.integration_time_us == 300_000
    # ... but not beyond what ArduPilot accepts (< 0.5 s).
    integ.add_frame(timestamp_us=1_490_000, flow_x_px=0, flow_y_px=0, quality=0)
    assert integ.restart_count == 1


def test_slow_steady_stream_is_integrated_not_a_gap_at_every_frame():
    # A 2.5-4 fps camera or a slow engine: frames 0.3 s apart are a steady stream, not gaps.
    integ = FlowIntegrator(focal_length_px=400.0)
    feed(integ, range(0, 3_000_000, 300_000), flow=(0.0, 4.0))
    assert integ.restart_count == 0
    iv = integ.take()
    assert iv.integration_time_us == 2_700_000 and iv.rate_y == pytest.approx(4.0 / 0.3 / 400.0)
    # ... but never beyond 0.45 s between frames (ArduPilot needs a message every < 0.5 s).
    integ.add_frame(timestamp_us=3_200_000, flow_x_px=0.0, flow_y_px=4.0, quality=200)
    assert integ.restart_count == 1 and integ.gap_threshold_us == 450_000


def test_frame_subset_growing_is_learned_within_a_few_frames():
    # A 30 fps camera whose engine falls behind: every 11th frame (0.367 s) from then on.
    integ = FlowIntegrator(focal_length_px=400.0)
    feed(integ, [i * 33_333 for i in range(30)])
    t = 29 * 33_333
    for _ in range(20):
        t += 11 * 33_333
        integ.add_frame(timestamp_us=t, flow_x_px=0.0, flow_y_px=11.0, quality=200)
    assert integ.restart_count == 4          # until the new spacing is the median of the last 9
    assert integ.nominal_interval_us == pytest.approx(366_663, abs=1)
    assert integ.elapsed_us == 16 * 366_663  # from the 4th such frame on: one continuous interval
