"""Ground truth: camera flights over real photographs with exact, sub-pixel motion.

The flights are rendered at 4x the resolution and area-averaged down, with sensor noise
sigma = 2 (see emdflow.synthetic). The OpenCL backend is used for speed; it is tested
to equal the numpy reference exactly in test_engine_exact.py.
"""

import math

import numpy as np
import pytest

import emdflow
from emdflow.synthetic import CameraFlight

W, H = 320, 240
DIRS = {"E": (1, 0), "W": (-1, 0), "S": (0, 1), "N": (0, -1)}


def run_flight(flow, texture="gravel", frames=7, seed=0, **kw):
    est = emdflow.FlowEstimator(W, H)
    flight = CameraFlight(texture, width=W, height=H, flow=flow, noise_sigma=2.0, seed=seed, **kw)
    return [est.update(flight.render(t)) for t in range(frames)][3:]


@pytest.mark.parametrize("speed", [1, 3, 5, 7, 9, 11, 13])
@pytest.mark.parametrize("direction", list(DIRS))
def test_scale_k_wins_for_speed_k_with_the_right_sign(speed, direction):
    dx, dy = DIRS[direction]
    fields = run_flight((speed * dx, speed * dy), texture="gravel", seed=speed)
    axis_codes = np.concatenate([(f.u_code if dx else f.v_code).ravel() for f in fields])
    codes = axis_codes[axis_codes != 0].astype(int)
    assert codes.size > 500, "too few detections along the motion axis"
    sign = dx + dy
    assert np.mean(np.sign(codes) == sign) > 0.9, "sign of the detections"
    speeds = np.array(emdflow.EngineParams().speeds)
    winners, counts = np.unique(speeds[np.abs(codes) - 1], return_counts=True)
    assert winners[np.argmax(counts)] == speed, dict(zip(winners, counts))


def test_diagonal_motion_gives_both_components():
    fields = run_flight((2.5, 2.5), texture="gravel")
    u = np.concatenate([f.u[np.isfinite(f.u)] for f in fields])
    v = np.concatenate([f.v[np.isfinite(f.v)] for f in fields])
    assert u.size > 500 and v.size > 500
    assert np.mean(u > 0) > 0.9 and np.mean(v > 0) > 0.9


@pytest.mark.parametrize("texture", ["gravel", "grass", "camera"])
def test_static_textured_scene_is_a_valid_zero_measurement(texture):
    for field in run_flight((0.0, 0.0), texture=texture):
        assert field.u_detections == 0 and field.v_detections == 0
        s = emdflow.summarize(field)
        assert (s.flow_x, s.flow_y) == (0.0, 0.0)
        assert s.quality > 0 and s.static


def test_sub_threshold_noise_on_a_blank_scene_gives_nothing():
    est = emdflow.FlowEstimator(W, H)
    rng = np.random.default_rng(0)
    for t in range(8):
        frame = np.clip(128 + rng.normal(0, 2.0, (H, W)), 0, 255).astype(np.uint8)
        field = est.update(frame)
        assert field.u_detections == 0 and field.v_detections == 0
        s = emdflow.summarize(field)
        assert (s.flow_x, s.flow_y, s.quality) == (0.0, 0.0, 0)


@pytest.mark.parametrize("value", [0, 128, 255])
def test_blank_and_saturated_frames_have_quality_zero(value):
    est = emdflow.FlowEstimator(W, H)
    flight = CameraFlight("gravel", width=W, height=H, flow=(3, 0))
    for t in range(4):
        est.update(flight.render(t))
    for _ in range(4):
        s = emdflow.summarize(est.update(np.full((H, W), value, np.uint8)))
        assert s.quality == 0


def test_summary_recovers_the_flight_velocity():
    """Median over flights at 1-13 px/frame in 8 directions (45 deg steps and off-axis)."""
    rel, ang, blind = [], [], 0
    for i, speed in enumerate([1, 2, 3, 5, 7, 9, 11]):
        for j in range(4):
            theta = j * math.pi / 2 + (0.3 if i % 2 else math.pi / 4)
            flow = (speed * math.cos(theta), speed * math.sin(theta))
            for field in run_flight(flow, texture=("gravel", "brick", "grass", "camera")[j], frames=6, seed=i):
                s = emdflow.summarize(field)
                if s.quality == 0:
                    blind += 1
                    rel.append(1.0)
                    ang.append(180.0)
                    continue
                rel.append(math.hypot(s.flow_x - flow[0], s.flow_y - flow[1]) / speed)
                diff = math.degrees(math.atan2(s.flow_y, s.flow_x) - theta)
                ang.append(abs((diff + 180) % 360 - 180))
    assert blind == 0
    assert np.median(rel) <= 0.12, f"median relative error {np.median(rel):.3f}"
    assert np.median(ang) <= 3.0, f"median direction error {np.median(ang):.2f} deg"


def _density(flow, frames=8, **kw):
    est = emdflow.FlowEstimator(W, H, **{k: v for k, v in kw.items() if k in ("threshold_mode", "delays")})
    flight = CameraFlight("gravel", width=W, height=H, flow=flow, noise_sigma=2.0,
                          **{k: v for k, v in kw.items() if k in ("contrast", "exposure_drift", "drift_frames")})
    fields = [est.update(flight.render(t)) for t in range(frames)][est.params.history_frames:]
    return np.mean([(f.u_detections + f.v_detections) / (W * H) for f in fields]), fields


@pytest.mark.filterwarnings("ignore::emdflow.summary.CalibrationWarning")  # (another setting on purpose)
def test_adaptive_threshold_keeps_density_when_contrast_drops_4x():
    full, _ = _density((3.0, 1.0))
    fixed_low, _ = _density((3.0, 1.0), contrast=0.25)
    adaptive_low, fields = _density((3.0, 1.0), contrast=0.25, threshold_mode="adaptive")
    assert fixed_low < 0.5 * full, "the paper's fixed threshold is a contrast gate"
    assert adaptive_low > 0.6 * full, (full, fixed_low, adaptive_low)
    s = emdflow.summarize(fields[-1])
    assert s.quality > 0 and math.hypot(s.flow_x - 3.0, s.flow_y - 1.0) < 0.6


def test_temporal_delays_see_slow_motion():
    """0.25 px/frame: nothing for the paper's model, detections with delays (1, 2, 4)."""
    paper, _ = _density((0.25, 0.0))
    slow, fields = _density((0.25, 0.0), frames=20, delays=(1, 2, 4))
    assert paper < 0.001
    assert slow > 0.002 and slow > 20 * paper
    u = np.concatenate([f.u[np.isfinite(f.u)] for f in fields])
    assert np.mean(u > 0) > 0.9
    assert set(np.unique(np.abs(u))) <= {0.25, 0.5, 1.0} and np.median(u) <= 0.5


@pytest.mark.parametrize("step", [+30, -40])
def test_a_global_brightness_step_is_discounted_not_taken_for_motion(step):
    est = emdflow.FlowEstimator(W, H)
    flight = CameraFlight("gravel", width=W, height=H, flow=(3.0, 1.0), noise_sigma=2.0)
    qualities = []
    for t in range(14):
        frame = flight.render(t).astype(int) + (step if t >= 8 else 0)
        field = est.update(np.clip(frame, 0, 255).astype(np.uint8))
        s = emdflow.summarize(field)
        qualities.append(s.quality)
        if t in (8, 9, 10):
            assert field.exposure_step and s.quality == 0 and (s.flow_x, s.flow_y) == (0.0, 0.0)
        elif t >= 3:
            assert not field.exposure_step and s.quality > 0
            assert math.hypot(s.flow_x - 3.0, s.flow_y - 1.0) < 0.6


@pytest.mark.filterwarnings("ignore::emdflow.summary.CalibrationWarning")  # (another setting on purpose)
def test_brightness_compensation_keeps_a_drifting_static_scene_static():
    """A hovering camera over a static scene while the exposure drifts by 30 %: without
    compensation the slow channels see the drift as a change and fire; with it (the
    extended model's default) the states stay quiet and the summary reads a static
    scene with good quality."""
    from emdflow.params import MODELS
    from emdflow.reference import STAT_FIRST_CHANGED

    results = {}
    for compensate in (False, True):
        kw = dict(MODELS["extended"], brightness_compensation=compensate)
        est = emdflow.FlowEstimator(W, H, **kw)
        slowest = est.params.channels.index((1, 4))
        flight = CameraFlight("gravel", width=W, height=H, flow=(0.0, 0.0), noise_sigma=2.0, seed=3,
                              exposure_drift=-0.3, drift_frames=20)
        changed, detections, summaries = [], [], []
        for t in range(20):
            field = est.update(flight.render(t))
            if t >= 14:
                changed.append(int(field.stats[STAT_FIRST_CHANGED + slowest]))
                detections.append(int(np.count_nonzero(field.u_code) + np.count_nonzero(field.v_code)))
                summaries.append(emdflow.summarize(field))
        results[compensate] = (np.mean(changed), np.mean(detections), summaries)
    (changed_off, det_off, _), (changed_on, det_on, sums) = results[False], results[True]
    assert changed_off > 0.05 * W * H, "the drift should light up the uncompensated slow channel"
    assert changed_on < 0.1 * changed_off
    assert det_on <= 0.2 * det_off + 50
    for s in sums:
        assert s.quality > 0 and math.hypot(s.flow_x, s.flow_y) < 0.15


def test_gradient_classes_do_not_follow_the_exposure_drift():
    """A detection's gradient-strength class compares the gradient at t - D with the
    threshold at t; under an exposure drift the channel's gain between the two is taken
    out, so darkening and brightening flights give the same mix of classes (without it,
    darkening put the slowest channel's detections in stronger classes than brightening:
    mean class 2.39 against 2.31, and the summary read 0.25 px/frame slow)."""
    from emdflow.params import MODELS

    def mean_class(drift):
        est = emdflow.FlowEstimator(160, 120, **MODELS["extended"])
        flight = CameraFlight("gravel", width=160, height=120, flow=(0.2, 0.15), noise_sigma=2.0, seed=1,
                              exposure_drift=drift, drift_frames=30)
        counts = 0
        for t in range(30):
            field = est.update(flight.render(t))
            if field.ready:  # the slowest channel (0.25 px/frame: codes 0 and 1) by class
                counts = counts + field.histogram[:, :2].reshape(2, 2, -1, 64).sum(axis=(0, 1, 3))
        assert counts.sum() > 5000, "too few slow detections"
        return float(counts @ np.arange(counts.size)) / counts.sum()

    darker, brighter = mean_class(-0.2), mean_class(0.2)
    assert abs(darker - brighter) < 0.025, (darker, brighter)


def test_compensated_states_stay_near_the_steady_count_at_the_threshold_floor():
    """A static, noisy scene at a quarter of the contrast, where the adaptive threshold
    sits at its floor (θ = 1.5, T = 1 at scale 1), under a +20 % exposure drift: the
    compensated slow channels light 2.1-3.7x the states of a steady exposure (the
    compensated change is not a whole number, so its rounding noise is no longer the
    same in both frames), not the 18-21x of the former threshold 256 T. That one let
    through every compensated change between T and T + 1, which the plain test (> T on
    whole numbers, i.e. >= T + 1) drops; drifting calibration flights then taught the
    summary's table more fast codes at slow speeds than a steady camera shows."""
    from emdflow.params import MODELS
    from emdflow.reference import STAT_FIRST_CHANGED

    changed = {}
    for drift in (0.0, 0.2):
        est = emdflow.FlowEstimator(W, H, **MODELS["extended"])
        flight = CameraFlight("coffee", width=W, height=H, flow=(0.0, 0.0), noise_sigma=2.0, seed=1,
                              contrast=0.25, exposure_drift=drift, drift_frames=20)
        counts = []
        for t in range(20):
            field = est.update(flight.render(t))
            if t >= 14:
                assert est._engine.last_theta_q == est.params.threshold_q(est.params.threshold_min)
                counts.append(field.stats[STAT_FIRST_CHANGED:STAT_FIRST_CHANGED + 3])
        changed[drift] = np.mean(counts, axis=0)  # channels (1, 4), (1, 2), (1, 1)
    assert changed[0.0].min() > 0
    assert np.all(changed[0.2] < 5 * changed[0.0]), (changed[0.0], changed[0.2])


@pytest.mark.parametrize("k", [1, 3, 5])
def test_compensation_at_unit_gain_is_the_plain_test(k):
    """With ρ = 256 (no gain) the compensated test, 256 ΔR > 256 T + 128, gives exactly the
    plain states (ΔR > T): the two paths meet where the engine switches between them."""
    from emdflow.params import EngineParams
    from emdflow.reference import gain_compensated_change, receptor_change, ternary_states

    rng = np.random.default_rng(k)
    now = rng.integers(0, 256, (40, 50))
    then = np.clip(now + rng.integers(-4 * k, 4 * k + 1, now.shape), 0, 255)
    for T in (0, 1, 2, k * k, 3 * k * k):
        plain = ternary_states(receptor_change(now, then, k), T)
        compensated = ternary_states(gain_compensated_change(now, then, k, 256),
                                     EngineParams.compensated_threshold(T))
        assert np.array_equal(plain, compensated)
        assert np.count_nonzero(plain) > 0


@pytest.mark.parametrize("gain", [1.3, 0.7])
def test_a_gain_step_is_caught_with_brightness_compensation(gain):
    """With brightness compensation a gain step is taken out of the states: the step test
    counts the finest channel's states as they would be without compensation, and flags
    it (three frames, quality 0); the slow drift around it is not a step."""
    from emdflow.params import MODELS

    est = emdflow.FlowEstimator(W, H, **MODELS["extended"])
    flight = CameraFlight("gravel", width=W, height=H, flow=(2.0, -1.0), noise_sigma=2.0, seed=2,
                          exposure_drift=0.15, drift_frames=24)
    flagged = []
    for t in range(24):
        frame = flight.render(t).astype(np.float64) * (gain if t >= 16 else 1.0)
        field = est.update(np.clip(frame, 0, 255).astype(np.uint8))
        flagged.append(field.exposure_step)
        if field.exposure_step:
            assert emdflow.summarize(field).quality == 0
        if t == 16:
            # the share the step test read on the step's frame (later frames are flagged
            # while the step is still in the templates' history): nearly all of one
            # polarity, within 0..1 (it used to divide by the compensated channel's count)
            share = field.brightening_fraction
            assert (share > 0.9) if gain > 1 else (share < 0.1)
        assert 0.0 <= field.brightening_fraction <= 1.0
    assert [t for t, f in enumerate(flagged) if f] == [16, 17, 18]


@pytest.mark.filterwarnings("ignore::emdflow.summary.CalibrationWarning")  # (another setting on purpose)
@pytest.mark.parametrize("compensation", [False, True])
def test_a_step_is_flagged_while_it_sits_in_the_delayed_templates(compensation):
    """A delay-D channel's templates hold a brightness step for 3D frames. Without
    brightness compensation the flag covers all of them (the delay-4 channels read the
    step as motion: 0.5 px/frame read 0.60-0.66 at high quality); with it, which takes the
    step out of the delayed channels too, the three frames of the one-frame channels."""
    from emdflow.params import MODELS

    params = dict(MODELS["extended"], brightness_compensation=compensation)
    est = emdflow.FlowEstimator(160, 120, **params)
    flight = CameraFlight("gravel", width=160, height=120, flow=(0.5, 0.0), noise_sigma=2.0, seed=0)
    flagged = []
    for t in range(30):
        frame = flight.render(t).astype(np.float64) * (1.3 if t >= 16 else 1.0)
        field = est.update(np.clip(frame, 0, 255).astype(np.uint8))
        s = emdflow.summarize(field)
        if field.exposure_step:
            flagged.append(t)
            assert s.quality == 0
        elif t >= 16:
            # the frames after the flag read the flight, not the step
            assert s.quality > 0 and abs(s.flow_x - 0.5) < 0.1 * 0.5 + 0.06
    assert flagged == (list(range(16, 19)) if compensation else list(range(16, 28)))


def test_stochastic_calibration_textures():
    """The extended model's calibration also flies over 1/f^beta noise textures and a
    tissue section (ground is rougher than the bundled photographs): deterministic per
    seed, 8-bit, mean 128 and σ 40 (or as named); a malformed name says what is expected."""
    from emdflow.synthetic import fractal_texture, load_texture

    a = load_texture("fractal-1.0-1")
    assert a.shape == (1024, 1024) and np.array_equal(a, fractal_texture(1.0, 1).astype(np.float32))
    assert not np.array_equal(a, load_texture("fractal-1.0-2"))
    assert abs(a.mean() - 128) < 2 and abs(a.std() - 40) < 2
    # rougher for a smaller beta
    rough = np.abs(np.diff(a, axis=1)).mean()
    assert rough > 2 * np.abs(np.diff(load_texture("fractal-1.4-2"), axis=1)).mean()
    assert load_texture("immunohistochemistry").shape == (512, 512)
    # an optional fourth field sets the contrast (σ before clipping): gravel-like gradients
    b = load_texture("fractal-1.0-1-60")
    assert abs(b.std() - 60) < 3 and np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99
    for bad in ("fractal-x", "fractal-1.0-1-60-2", "fractal-1.0-1-bright"):
        with pytest.raises(ValueError, match=r"fractal-<beta>-<seed>\[-<sigma>\]"):
            load_texture(bad)


def test_granular_textures():
    """grain-<period>-<seed>[-<sigma>]: a spectrum flat below the grain frequency and steep
    above it (gravel and grass are granular, not 1/f), deterministic per seed, mean 128 and
    σ 40 (or as named); a malformed name or period says what is expected."""
    from emdflow.synthetic import GRAIN_EXPONENT, grain_texture, load_texture

    a = load_texture("grain-12-1")
    assert a.shape == (1024, 1024) and np.array_equal(a, grain_texture(12, 1).astype(np.float32))
    assert not np.array_equal(a, load_texture("grain-12-2"))
    assert abs(a.mean() - 128) < 2 and abs(a.std() - 40) < 2
    assert abs(load_texture("grain-12-1-55").std() - 55) < 3
    # radially averaged power: flat well below 1/period, falling as f**-GRAIN_EXPONENT above
    power = np.abs(np.fft.fft2(a - a.mean())) ** 2
    f = np.hypot(np.fft.fftfreq(1024)[:, None], np.fft.fftfreq(1024)[None, :])

    def band(lo, hi):
        return power[(f >= lo) & (f < hi)].mean()

    assert 0.6 < band(0.004, 0.008) / band(0.008, 0.016) < 1.6  # below the grain: flat
    fall = math.log(band(0.16, 0.2) / band(0.32, 0.4)) / math.log(2.0)
    assert fall == pytest.approx(GRAIN_EXPONENT, abs=0.4)
    # a finer grain is rougher
    roughness = [np.abs(np.diff(load_texture(f"grain-{p}-1"), axis=1)).mean() for p in (4, 12, 30)]
    assert roughness[0] > 1.4 * roughness[1] > 1.4 * 1.4 * roughness[2]
    for bad in ("grain-x-1", "grain-12-1-40-2", "grain-0-1", "grain-inf-1", "grain-1e300-1",
                "grain-12-1-nan", "grain-12-1-0"):
        with pytest.raises(ValueError, match=r"grain-<period px>-<seed>\[-<sigma>\]"):
            load_texture(bad)
    with pytest.raises(ValueError, match="period=0.0: must be > 0 and at most the texture's 1024 px"):
        grain_texture(0.0, 1)
    with pytest.raises(ValueError, match="sigma=-5.0: must be > 0 gray levels"):
        grain_texture(12, 1, sigma=-5.0)


def test_fast_oblique_flight_drowns_the_minor_axis_over_granular_ground():
    """README, "Fast oblique flight over rough ground": with 10 px/frame across it, the
    vertical detectors lose most of their detections over gravel (the ground slides
    sideways under their receptors) and a third or more of those left have the wrong
    sign, where long edges (the camera photograph) keep theirs, and the quality falls
    with them; moving along the axis, both read the 4 px/frame in the two channels that
    bracket it."""
    from emdflow.tools import cross_motion

    assert cross_motion.bracketing_channels((0.25, 0.5, 1, 3, 5, 7), 4) == (3, 4)
    assert cross_motion.bracketing_channels((0.25, 0.5, 1, 3, 5, 7), 3) == (3,)
    assert cross_motion.bracketing_channels((0.25, 0.5, 1, 3, 5, 7), 20) == (5,)
    rows = cross_motion.evaluate(model="extended", textures=("gravel", "camera"), majors=(0, 10),
                                 flights=2, frames=3)
    (gravel_along, gravel_across), (camera_along, camera_across) = rows[:2], rows[2:]
    for along in (gravel_along, camera_along):
        assert along["right"] > 0.8 and along["wrong_sign"] < 0.05
        assert along["read_v"] == pytest.approx(4.0, rel=0.1) and abs(along["read_u"]) < 0.4
    assert gravel_across["detections"] < 0.2 * gravel_along["detections"]
    assert camera_across["detections"] > 0.3 * camera_along["detections"]
    assert gravel_across["wrong_sign"] > 0.3 and camera_across["wrong_sign"] < gravel_across["wrong_sign"]
    # over the camera photograph the direction still holds, and the quality says which holds
    assert camera_across["direction_error_deg"] < 4.0
    assert gravel_across["quality"] < 0.6 * camera_across["quality"]
    assert gravel_across["quality"] < 0.6 * gravel_along["quality"]
    assert all(r["blind"] == 0.0 for r in rows)
    assert "| gravel | (10, 4) |" in cross_motion.format_report(rows)


def test_cross_motion_flights_stay_over_the_photograph():
    """Every measured view of every flight lies inside the photograph (no mirrored ground),
    the flights' midpoints spread over the room it leaves; a path too long says so; a
    frame without an answer counts as 180° off, as in calibrate_summary's evaluation."""
    from types import SimpleNamespace

    from emdflow.tools import cross_motion
    from emdflow.tools.calibrate_summary import _frame_error  # what cross_motion counts with

    flow, first, last = (12.0, 4.0), 9, 17
    starts = cross_motion._starts((512, 512), 320, 240, flow, first, last, 8)
    assert len(starts) == 8 and len(set(starts)) == 8
    for x0, y0 in starts:
        for t in range(first, last + 1):  # the camera moves by -flow on the ground
            cx, cy = x0 - flow[0] * t, y0 - flow[1] * t
            assert 160 <= cx <= 512 - 160 and 120 <= cy <= 512 - 120
    with pytest.raises(ValueError, match=r"flow \(30, 4\) px/frame: the 320x240 view moves past the 512x512"):
        cross_motion._starts((512, 512), 320, 240, (30.0, 4.0), first, last, 2)
    blind = SimpleNamespace(quality=0, flow_x=0.0, flow_y=0.0)
    assert _frame_error(blind, 12.0, 4.0)[1] == 180.0
    tilted = SimpleNamespace(quality=9, flow_x=1.0, flow_y=-1.0)
    assert _frame_error(tilted, 1.0, 1.0)[1] == pytest.approx(90.0)
    # a zero reading with quality (a flight read static) has no direction: 180 deg, as
    # emdflow eval counts it (it scored the true flow's polar angle: 0 deg for a flight
    # along +x, 90 deg along +y)
    static = SimpleNamespace(quality=191, flow_x=0.0, flow_y=0.0)
    assert _frame_error(static, 0.25, 0.0) == (1.0, 180.0) == _frame_error(static, 0.0, 0.25)


def test_cross_motion_command_refuses_bad_options(capsys):
    from emdflow.tools import cross_motion

    assert cross_motion.main(["--minor", "-1", "--textures", "gravel"]) == 2
    assert "--minor -1: must be a finite number > 0 (px/frame)" in capsys.readouterr().err
    assert cross_motion.main(["--majors", "-3", "--textures", "gravel"]) == 2
    assert "--majors -3: must be finite numbers >= 0" in capsys.readouterr().err
    assert cross_motion.main(["--minor", "inf", "--textures", "gravel"]) == 2
    assert "--minor inf: must be a finite number > 0 (px/frame)" in capsys.readouterr().err
    assert cross_motion.main(["--size", "6x6", "--textures", "gravel"]) == 2
    assert "--size 6x6: both sides must be at least" in capsys.readouterr().err
    assert cross_motion.main(["--textures", ","]) == 2
    assert "name at least one ground" in capsys.readouterr().err


@pytest.mark.parametrize("speed", [1, 3, 5])
def test_thin_lines_need_the_prefilter(speed):
    """The spec's motion templates come from edges (§2): a line thinner than a receptor
    crosses it within one frame and leaves mixed-polarity patterns (``[p 0 / −p p]``) that
    no template accepts, sharp ones included. The default prefilter spreads a 1 px line over
    several pixels, and it is seen at its speed; without the prefilter it is not seen at all
    (README, "Notes on the spec and the paper")."""
    w, h = 120, 30

    def line(t):
        frame = np.full((h, w), 60, np.uint8)
        frame[:, 20 + speed * t] = 200
        return frame

    for prefilter_size, sharp, seen in ((11, False, True), (0, False, False), (0, True, False)):
        est = emdflow.FlowEstimator(w, h, backend="numpy", prefilter_size=prefilter_size,
                                    sharp_templates=sharp)
        u = np.concatenate([est.update(line(t)).u.ravel() for t in range(8)])
        u = u[np.isfinite(u)]
        if seen:
            assert u.size > 100 and np.all(u == speed), np.unique(u)
        else:
            assert u.size == 0, np.unique(u)


def test_grid_textures_share_their_layout():
    """``lines-<seed>`` and ``cells-<seed>`` draw one grid as thin bright lines or as step
    edges: the lines' columns are where the cells' gray level jumps; deterministic per
    seed; a malformed name says what is expected."""
    from emdflow.synthetic import grid_texture, load_texture

    lines, cells = load_texture("lines-3"), load_texture("cells-3")
    assert lines.shape == cells.shape == (1024, 1024)
    assert np.array_equal(lines, grid_texture("lines", 3).astype(np.float32))
    assert not np.array_equal(lines, load_texture("lines-4"))
    line_columns = np.flatnonzero(lines.mean(axis=0) > 140)      # full-height bright lines
    starts = line_columns[np.diff(line_columns, prepend=-10) > 1]
    # a cell border changes the level in most rows (levels 70-160), noise (σ 3) does not
    jumps = np.flatnonzero(np.percentile(np.abs(np.diff(cells, axis=1)), 90, axis=0) > 15) + 1
    assert len(starts) >= 20 and np.array_equal(starts, jumps)
    for bad in ("lines-x", "cells-", "cells-1-x", "lines-1-2-3", "lines-1-nan"):
        with pytest.raises(ValueError, match=r"(lines|cells)-<seed>\[-<angle in degrees>\]"):
            load_texture(bad)
    with pytest.raises(ValueError, match="expected 'lines' or 'cells'"):
        grid_texture("dots", 1)


def test_turned_grids_turn_the_lines():
    """``lines-<seed>-<angle>`` turns the grid (the line-ground table is calibrated over
    lines of every orientation): the bright lines' direction follows the angle, the
    unturned name is angle 0, and both kinds still share one layout."""
    from emdflow.synthetic import load_texture

    assert np.array_equal(load_texture("lines-3-0"), load_texture("lines-3"))
    assert np.array_equal(load_texture("lines-3-360"), load_texture("lines-3"))
    assert np.array_equal(load_texture("lines-3--30"), load_texture("lines-3-330"))

    def line_angles(image):
        """Orientations (degrees mod 180) of the strongest straight bright lines."""
        centre = image[256:768, 256:768]
        bright = np.argwhere(centre > 140)
        best = []
        for a in np.arange(0.0, 180.0, 1.0):
            t = math.radians(a)
            # project onto the line normal: a straight line piles up in one bin
            offsets = bright[:, 1] * math.cos(t) + bright[:, 0] * math.sin(t)
            best.append(np.bincount(np.round(offsets - offsets.min()).astype(int)).max())
        best = np.array(best)
        return {int(a) for a in np.flatnonzero(best > 0.8 * best.max())}

    assert line_angles(load_texture("lines-3")) <= {0, 1, 89, 90, 91, 179}
    turned = line_angles(load_texture("lines-3-30"))
    # a normal at 0° turns to -30° = 150° (the image's y axis points down)
    assert turned and all(min(abs(a - 150), abs(a - 60)) <= 2 for a in turned), turned
    lines, cells = load_texture("lines-5-30"), load_texture("cells-5-30")
    bright = lines > 140
    jump = np.abs(np.diff(cells, axis=1)) > 15  # where the cells' levels change
    assert bright.mean() > 0.05 and jump[:, :-1][bright[:, 1:-1]].mean() > 4 * jump.mean()


@pytest.mark.parametrize("flow", [(7.0, 0.0), (0.0, -5.0)])
def test_thin_lines_fire_only_the_scale_of_their_speed(flow):
    """Why ground of thin lines (mortar joints, brick) reads slow through the summary: on an
    axis flight an edge also fires the larger scales (its changed receptors span the
    displacement plus the receptor), a line only the scale of its speed (a receptor larger
    than the displacement sees the line at both times, and the change cancels). The
    summary's table, measured over edges, reads a pure code-k mixture as slower than k
    (README, "Thin lines read slow")."""
    speed = abs(flow[0] or flow[1])
    share_at_speed = {}
    for texture in ("lines-1", "cells-1"):
        fields = run_flight(flow, texture=texture, seed=1, start=(512.0, 512.0))
        values = np.concatenate([(f.u if flow[0] else f.v).ravel() for f in fields])
        values = np.abs(values[np.isfinite(values)])
        assert values.size > 3000, texture
        share_at_speed[texture] = np.mean(values == speed)
        if texture == "cells-1":
            assert np.mean(values > speed) > 0.3, "edges fire the larger scales too"
    assert share_at_speed["lines-1"] > 0.97 and share_at_speed["cells-1"] < 0.7, share_at_speed


def test_local_threshold_sees_the_shaded_half_of_the_view():
    """A shadow over the right half of the view (light x 0.25): one threshold for the
    whole frame, set by the lit half's contrast, leaves the shaded half nearly blind, and
    the left/right balance then reads the shaded side slower (a corridor-centring robot
    would steer towards it). The local threshold follows each tile's contrast: the shaded
    half keeps most of its density and the balance stays near 0 (the truth: a pure
    translation)."""
    from emdflow.cues import looming_cues
    from emdflow.params import MODELS

    result = {}
    for mode in ("adaptive", "local"):
        lit = shaded = 0.0
        balance = []
        for texture, direction in (("gravel", 20.0), ("grass", 200.0), ("brick", 110.0)):
            a = math.radians(direction)
            est = emdflow.FlowEstimator(W, H, **{**MODELS["extended"], "threshold_mode": mode})
            flight = CameraFlight(texture, width=W, height=H, flow=(math.cos(a), math.sin(a)), noise_sigma=2.0,
                                  seed=3, shade=0.25)
            for t in range(20):
                field = est.update(flight.render(t))
                if field.ready:
                    seen = np.isfinite(field.u) | np.isfinite(field.v)
                    lit += seen[:, : W // 2].mean()
                    shaded += seen[:, W // 2 :].mean()
                    balance.append(looming_cues(field).balance_lr)
        result[mode] = shaded / lit, float(np.nanmean(balance))  # (NaN: a frame without the axis's evidence)
    (global_share, global_balance), (local_share, local_balance) = result["adaptive"], result["local"]
    # premises: the frame's one threshold shows the problem
    assert global_share < 0.35 and global_balance < -0.15, result
    assert local_share > 0.5 and local_share > 2 * global_share, result
    assert abs(local_balance) < 0.12 and abs(local_balance) < 0.4 * abs(global_balance), result
