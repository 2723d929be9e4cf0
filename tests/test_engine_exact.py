"""The OpenCL kernels reproduce the numpy reference exactly (run on PoCL).

Same ternary states, same raw detector matches, same flow codes, same statistics and
detection histogram, frame after frame, for odd frame sizes that are multiples of no
work-group or vector width, every scale, every direction, both polarities, and the
parameter variants (sharp templates, no prefilter, other prefilter widths, temporal
delays, with and without the diagonal detectors' evidence, whose detections the
histogram compares).
"""

import threading

import numpy as np
import pytest

from emdflow.params import MODELS, EngineParams
from emdflow.reference import STAT_CONTRAST, STAT_TEXTURED, ReferenceEngine, prefilter
from emdflow.synthetic import CameraFlight

opencl_backend = pytest.importorskip("emdflow.opencl_backend")


def _compare(width, height, frames, params=EngineParams(), each=None):
    """Step the reference and a debug OpenCL engine through ``frames`` and assert that
    every state, match, code, count and histogram agrees; ``each(t, ref, ocl)`` after every
    frame checks more. Returns the number of template matches that fired."""
    ref = ReferenceEngine(width, height, params)
    ocl = opencl_backend.OpenCLEngine(width, height, params, debug=True)
    fired = 0
    for t, frame in enumerate(frames):
        u_r, v_r, stats_r, hist_r, pos_r = ref.step(frame)
        u_o, v_o, stats_o, hist_o, pos_o = ocl.step(frame)
        for c, (s_r, s_o) in enumerate(zip(ref.states, ocl.debug_states())):
            assert np.array_equal(s_r, s_o), f"frame {t}: states of channel {params.channels[c]} differ"
        matches = ocl.debug_matches()
        for key, m_r in ref.matches.items():
            assert np.array_equal(m_r, matches[key]), f"frame {t}: matches {key} differ"
            fired += int(m_r.sum())
        assert np.array_equal(u_r, u_o), f"frame {t}: u codes differ"
        assert np.array_equal(v_r, v_o), f"frame {t}: v codes differ"
        assert np.array_equal(stats_r, stats_o), f"frame {t}: stats {stats_r} != {stats_o}"
        assert np.array_equal(hist_r, hist_o), f"frame {t}: histograms differ"
        assert np.array_equal(pos_r, pos_o), f"frame {t}: position histograms differ"
        if each is not None:
            each(t, ref, ocl)
    return fired


def moving_edges(width, height, speed, direction, polarity, count=7):
    """Bright/dark bars sliding ``speed`` px/frame in one of E/W/S/N."""
    dx, dy = {"E": (1, 0), "W": (-1, 0), "S": (0, 1), "N": (0, -1)}[direction]
    yy, xx = np.mgrid[0:height, 0:width]
    frames = []
    for t in range(count):
        coord = (xx * dx + yy * dy) - speed * t
        bars = (np.floor(coord / 23.0) % 2).astype(np.float64)
        base, amp = (60, 140) if polarity > 0 else (200, -140)
        frames.append(np.clip(base + amp * bars, 0, 255).astype(np.uint8))
    return frames


@pytest.mark.parametrize("size", [(97, 61), (131, 77), (64, 48)])
def test_random_and_flight_sequences(size):
    width, height = size
    rng = np.random.default_rng(width)
    noise = [rng.integers(0, 256, (height, width), dtype=np.uint8) for _ in range(5)]
    # a random walk of a textured frame: lots of states of both signs
    walk = CameraFlight("brick", width=width, height=height, flow=(3.4, -2.2), noise_sigma=3, seed=1)
    frames = noise + [walk.render(t) for t in range(6)]
    assert _compare(width, height, frames) > 0


@pytest.mark.parametrize("params", [EngineParams(), EngineParams(**MODELS["extended"])], ids=["paper", "extended"])
def test_portable_kernels_are_exact_too(monkeypatch, params):
    """The kernels without the PoCL/x86 builtins (what GPUs and ARM boards run: portable
    packs, saturating compares and atomics) give the same states, matches and output."""
    monkeypatch.setenv(opencl_backend.PORTABLE_ENV, "1")
    width, height = 101, 59
    flight = CameraFlight("gravel", width=width, height=height, flow=(1.7, -0.6), noise_sigma=2, seed=6)
    frames = [flight.render(t) for t in range(params.history_frames + 4)]
    assert _compare(width, height, frames, params) > 0


_ORIENTATION_TEST_KERNEL = """
__kernel void orientation_test(__global const int *g, __global int *bins)
{
    const int i = get_global_id(0);
    bins[i] = orientation_bin(g[2 * i], g[2 * i + 1]);
}
"""


def _orientation_test_gradients():
    """Every gradient up to 40 per component; each boundary direction at 1-3 times its
    table length (exactly on the boundary, where the bin's test is ">= 0", and one unit off
    each way), in both half-planes; the largest components (box sums below 2^16); and
    random ones."""
    g = np.mgrid[-40:41, -40:41].reshape(2, -1).T
    table = EngineParams.orientation_table()
    near = [m * table + d for m in (1, 2, 3) for d in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1))]
    big = np.array([[65535, 0], [-65535, 0], [0, 65535], [0, -65535], [65535, 65535], [-65535, 65535],
                    [65535, -1], [-65535, 1], [1, 65535], [-1, 65535], [65535, 1], [-65535, -1]])
    rng = np.random.default_rng(5)
    g = np.concatenate([g, *near, *(-n for n in near), big, rng.integers(-65535, 65536, (20000, 2))])
    return g[np.any(g != 0, axis=1)].astype(np.int32)  # (0, 0) is never binned


@pytest.mark.parametrize("portable", [False, True])
def test_orientation_lookup_is_the_reference_count(monkeypatch, portable):
    """The detector kernel's orientation bin (one division, a cell table and one exact
    boundary test: evidence.cl) is the reference's count of boundaries for every gradient
    the tables can give, on and next to every boundary; run as the engine builds it."""
    cl = pytest.importorskip("pyopencl")
    from emdflow.reference import orientation_bins

    if portable:
        monkeypatch.setenv(opencl_backend.PORTABLE_ENV, "1")
    eng = opencl_backend.OpenCLEngine(64, 48, EngineParams())
    source = opencl_backend.program_source(eng.device, eng.layout) + _ORIENTATION_TEST_KERNEL
    if "portable computing language" in eng.device.platform.name.lower():
        assert ("#define EMD_CLANG_BUILTINS" in source) != portable
    program = cl.Program(eng.ctx, source).build(options=["-cl-std=CL1.2"])
    g = _orientation_test_gradients()
    bins = np.empty(len(g), np.int32)
    mf = cl.mem_flags
    g_buf = cl.Buffer(eng.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(g))
    out = cl.Buffer(eng.ctx, mf.WRITE_ONLY, bins.nbytes)
    program.orientation_test(eng.queue, (len(g),), None, g_buf, out)
    cl.enqueue_copy(eng.queue, bins, out, is_blocking=True)
    expected = orientation_bins(g[:, 0], g[:, 1])
    wrong = np.flatnonzero(bins != expected)
    assert wrong.size == 0, f"{wrong.size} gradients binned differently, e.g. {g[wrong[:5]].tolist()}: " \
                            f"{bins[wrong[:5]].tolist()} != {expected[wrong[:5]].tolist()}"
    assert set(np.unique(expected)) == set(range(64))  # every bin was reached


def test_orientation_cells_refuse_boundaries_too_close_for_the_lookup(monkeypatch):
    """Two boundaries less than 2 cells apart could both lie in one cell's range, and the
    kernel tests only one: the table is refused instead of built wrong."""
    table = EngineParams.orientation_table().copy()
    table[1] = table[0] + [-1, 1]  # a direction a hair past boundary 0
    monkeypatch.setattr(EngineParams, "orientation_table", staticmethod(lambda: table))
    opencl_backend.orientation_cells.cache_clear()
    try:
        with pytest.raises(ValueError, match="closer than 2"):
            opencl_backend.orientation_cells()
    finally:
        monkeypatch.undo()
        opencl_backend.orientation_cells.cache_clear()


def test_orientation_cells_are_exact_bounds():
    """The cell table the kernel's lookup reads: each cell's count of boundaries certainly
    below is monotone, starts at 0 and ends at all 63, and a numpy mirror of the kernel's
    lookup (the same integer arithmetic) agrees with the reference's count."""
    from emdflow.reference import orientation_bins

    cells = np.array(opencl_backend.orientation_cells())
    n = opencl_backend.ORIENT_CELLS
    assert len(cells) == 2 * n + 1 and cells[0] == 0 and cells[-1] == 63 and np.all(np.diff(cells) >= 0)
    g = _orientation_test_gradients().astype(np.int64)
    flip = (g[:, 1] < 0) | ((g[:, 1] == 0) & (g[:, 0] < 0))
    gx, gy = np.where(flip, -g[:, 0], g[:, 0]), np.where(flip, -g[:, 1], g[:, 1])
    q = gy * n // (np.abs(gx) + gy)
    lo = cells[np.where(gx < 0, 2 * n - q, q)]
    table = np.vstack([EngineParams.orientation_table(), [[0, 0]]])
    test = table[lo, 0] * gy - table[lo, 1] * gx >= 0
    assert np.array_equal(lo + ((lo < 63) & test), orientation_bins(g[:, 0], g[:, 1]))


@pytest.mark.parametrize("model", ["paper", "extended"])
def test_portable_kernels_are_standard_opencl_c_1_2(monkeypatch, tmp_path, model):
    """What a GPU or ARM board's own OpenCL compiler gets is OpenCL C 1.2 without compiler
    extensions (no clang builtins beyond the standard as_type, no variadic macros): clang
    in strict 1.2 mode for the SPIR target, pedantic, warns about nothing. Skipped where no
    clang is installed (Debian's PoCL brings one)."""
    import shutil
    import subprocess

    clang = next((c for c in ("clang", "clang-15", "clang-16", "clang-17", "clang-14") if shutil.which(c)), None)
    if clang is None:
        pytest.skip("no clang to check the portable kernels with")
    monkeypatch.setenv(opencl_backend.PORTABLE_ENV, "1")
    sources = []
    real_build = opencl_backend._build

    def capture(cl, ctx, device, source):
        sources.append(source)
        return real_build(cl, ctx, device, source)

    monkeypatch.setattr(opencl_backend, "_build", capture)
    monkeypatch.setattr(opencl_backend, "_PROGRAMS", {})  # build here, not from this process's cache
    opencl_backend.OpenCLEngine(97, 61, EngineParams(**MODELS[model]))
    assert sources and "#define EMD_CLANG_BUILTINS" not in sources[0]
    path = tmp_path / "portable.cl"
    path.write_text(sources[0])
    result = subprocess.run([clang, "-x", "cl", "-cl-std=CL1.2", "-target", "spir", "-Xclang",
                             "-finclude-default-header", "-fsyntax-only", "-Wall", "-pedantic", str(path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "warning" not in result.stderr, result.stderr[-2000:]


@pytest.mark.parametrize("prefilter_size", [11, 3, 41, 51])
@pytest.mark.parametrize("width", [3, 13, 26, 47, 70])
def test_prefilter_at_the_frame_edges(width, prefilter_size):
    """The prefiltered image equals the reference's (clamped reads at the frame edges),
    also where one 16-column strip holds both edges and where the radius (20 px at 41
    taps, 25 px at 51) spans more than one strip."""
    height = 9
    params = EngineParams(prefilter_size=prefilter_size)
    engine = opencl_backend.OpenCLEngine(width, height, params)
    rng = np.random.default_rng(width + prefilter_size)
    for _ in range(2):
        # extreme values at the edge columns: a lane that read past the frame shows
        frame = rng.integers(0, 256, (height, width), dtype=np.uint8)
        frame[:, 0], frame[:, -1] = 255, 0
        engine.step(frame)
        assert np.array_equal(engine.debug_prefiltered(), prefilter(frame, params.weights))


@pytest.mark.parametrize("size", [(661, 37), (1283, 21)])
def test_wide_frames(size):
    # from 640 px the summary's evidence samples every 2nd (from 1280 every 4th) column
    width, height = size
    assert EngineParams.evidence_column_step(width) > 1
    flight = CameraFlight("grass", width=width, height=height, flow=(2.6, 1.2), noise_sigma=2, seed=4)
    assert _compare(width, height, [flight.render(t) for t in range(6)]) > 0


@pytest.mark.parametrize("direction", ["E", "W", "S", "N"])
@pytest.mark.parametrize("polarity", [1, -1])
def test_structured_edges_every_direction_and_polarity(direction, polarity):
    width, height = 113, 71
    fired = 0
    for k in (1, 5, 13):
        fired += _compare(width, height, moving_edges(width, height, k, direction, polarity))
    assert fired > 0


@pytest.mark.parametrize("scales", [(1, 13), (3, 7, 15)])
def test_large_changes_at_the_widest_scales(scales):
    """At k = 13 and 15 a one-frame change is read from the difference table, wrapped to 16
    bits and exact only within 65535 - 255 k^2 (a box change of more than 132 gray levels
    per pixel at k = 13, 36 at k = 15 is not): squares that switch between black and white
    over noise put words on both sides of that limit, and every word must give the states of
    the reference."""
    width, height = 101, 67
    yy, xx = np.mgrid[0:height, 0:width]
    rng = np.random.default_rng(11)
    frames = []
    for t in range(8):
        frame = rng.normal(128, 25, (height, width))
        square = (np.abs(xx - 25 - 3 * t) < 18) & (np.abs(yy - 30) < 18)
        frame[square] = 255 if t % 2 else 0
        frame[:, 70:] = 255 * ((t // 2) % 2)  # a whole strip steps as well
        frames.append(np.clip(frame, 0, 255).astype(np.uint8))
    _compare(width, height, frames, EngineParams(scales=scales, threshold=2.0))
    # the whole frame switching between black and white: every box changes by exactly
    # 255 k^2, the largest change, in every lane of every word (a limit one too loose fails)
    flat = [np.full((41, 160), 255 * (t % 2), np.uint8) for t in range(6)]
    _compare(160, 41, flat, EngineParams(scales=scales, threshold=2.0))


@pytest.mark.parametrize(
    "params",
    [
        EngineParams(sharp_templates=True),
        EngineParams(prefilter_size=0, threshold=12.0),
        EngineParams(prefilter_size=7, threshold=3.0, scales=(1, 3, 7, 15)),
        EngineParams(delays=(1, 2, 4)),
        EngineParams(delays=(1, 3), delay_scales=(1, 3)),
        EngineParams(threshold_mode="adaptive"),
        EngineParams(threshold_mode="adaptive", delays=(1, 2, 4), threshold=7.3),
        EngineParams(**MODELS["extended"]),
        EngineParams(evidence_row_step=1),
        EngineParams(**MODELS["extended"], evidence_row_step=3),
        EngineParams(diagonal_evidence=False),
        EngineParams(**MODELS["extended"], diagonal_evidence=False),
    ],
    ids=["sharp", "no-prefilter", "w7-scales", "delays124", "delays13", "adaptive", "adaptive-delays",
         "extended", "evidence-every-row", "extended-evidence-step3", "no-diagonals", "extended-no-diagonals"],
)
def test_parameter_variants(params):
    width, height = 89, 67
    flight = CameraFlight("gravel", width=width, height=height, flow=(0.6, 1.3), noise_sigma=2, seed=3)
    frames = [flight.render(t) for t in range(14)]
    assert _compare(width, height, frames, params) > 0


@pytest.mark.parametrize("model", ["paper", "extended"])
def test_dense_only_engine_gives_the_same_field_and_counters(model):
    """``summary_evidence=False`` drops the histograms and nothing else: both backends
    give the codes and counters of the full engine (and of each other), and no
    histograms."""
    width, height = 97, 61
    full = EngineParams(**MODELS[model])
    dense = EngineParams(**MODELS[model], summary_evidence=False)
    flight = CameraFlight("grass", width=width, height=height, flow=(1.3, -2.1), noise_sigma=2, seed=8)
    engines = (ReferenceEngine(width, height, full), ReferenceEngine(width, height, dense),
               opencl_backend.OpenCLEngine(width, height, dense), opencl_backend.OpenCLEngine(width, height, full))
    detections = 0
    for t in range(full.history_frames + 5):
        frame = flight.render(t)
        (u, v, stats, hist, pos), *others = (engine.step(frame) for engine in engines)
        for kind, (u_o, v_o, stats_o, hist_o, pos_o) in zip(("numpy dense", "opencl dense", "opencl"), others):
            assert np.array_equal(u, u_o) and np.array_equal(v, v_o), f"frame {t}: {kind} codes differ"
            assert np.array_equal(stats, stats_o), f"frame {t}: {kind} counters differ"
            if kind == "opencl":
                assert np.array_equal(hist, hist_o) and np.array_equal(pos, pos_o)
            else:
                assert hist_o is None and pos_o is None
        detections += int(np.count_nonzero(u) + np.count_nonzero(v))
    assert detections > 0 and hist.sum() > 0


@pytest.mark.parametrize("portable", [False, True], ids=["x86", "portable"])
@pytest.mark.parametrize("size,model", [((89, 67), "extended"), ((75, 301), "extended"),
                                        ((89, 67), "finest-scale-3")])
def test_brightness_compensation_is_exact(monkeypatch, size, model, portable):
    """An exposure drift, a small step, a large one and a gain of 0.45, every channel with
    and without an exposure gain to compensate: the same states and output. The kernel
    tests gains within ±50 % in 16-bit lanes (up to k = 11) and larger ones in 32-bit
    lanes; both occur. 301 rows: the prefilter's strip sums cross its 256-row flush of the
    wrapping column sums. ``finest-scale-3``: the exposure-step test's uncompensated
    states then come from box sums."""
    if portable:
        monkeypatch.setenv(opencl_backend.PORTABLE_ENV, "1")
    width, height = size
    params = EngineParams(**MODELS["extended"]) if model == "extended" else EngineParams(
        scales=(3, 5, 7), delays=(1, 2), delay_scales=(3,), brightness_compensation=True)
    assert params.brightness_compensation
    flight = CameraFlight("gravel", width=width, height=height, flow=(0.4, -0.3), noise_sigma=2, seed=8)
    frames = []
    for t in range(22):  # steady exposure, a 2.5 %/frame drift, two steps, a gain of 0.45
        gain = 1.0 - 0.025 * max(0, t - 8)
        frame = flight.render(t) * gain + (4 if t >= 15 else 0) + (40 if t >= 18 else 0)
        frame *= 0.45 if t >= 20 else 1.0
        frames.append(np.clip(np.rint(frame), 0, 255).astype(np.uint8))
    # the gains the channels see: within ±0.2 % of 1 (no compensation), within ±50 % and
    # beyond (the kernel's 16-bit and 32-bit paths)
    sums = [int(prefilter(f, params.weights).sum()) for f in frames]
    ratios = [params.brightness_ratio_q(sums[t], sums[t - d]) for t in range(4, 22) for d in params.delays]
    need = 10 if model == "extended" else 5  # (two delays instead of three)
    assert ratios.count(256) > need and len({q for q in ratios if 128 < q < 384} - {256}) > need
    assert sum(not 128 < q < 384 for q in ratios) >= 2
    assert _compare(width, height, frames, params) > 0


def test_contrast_counter_past_two_to_the_31():
    """The contrast statistic of a large high-contrast frame passes 2^31 (each of the
    kernel's counter copies holds an eighth of it): the OpenCL engine adds the copies in
    64 bits and gives the reference's sum, and so the same adaptive threshold after it."""
    width, height = 4096, 2304
    params = EngineParams(prefilter_size=0, threshold_mode="adaptive")
    # stripes of period 4 in both axes: every central difference is ±255
    ramp = ((np.arange(4096) // 2) % 2) * 255
    frame = np.bitwise_xor.outer(ramp[:height], ramp[:width]).astype(np.uint8)
    p = frame.astype(np.int64)
    grad = np.abs(p[1:-1, 2:] - p[1:-1, :-2]) + np.abs(p[2:, 1:-1] - p[:-2, 1:-1])
    expected = int(grad[1::2].sum())  # the reference's statistic (summary_statistics)
    assert expected > 2 ** 31
    engine = opencl_backend.OpenCLEngine(width, height, params)
    stats = engine.step_packed(frame)[1]
    assert int(stats[STAT_CONTRAST]) == expected
    assert engine.theta_q == params.next_threshold_q(expected, params.contrast_samples(width, height))


def test_very_wide_frames_sample_the_same_columns():
    """From 20 480 px wide the column step would be 64, more than a 32-pixel word's mask
    can hold: it stops at 32, and both backends sample the same columns."""
    assert EngineParams.evidence_column_step(20480) == EngineParams.evidence_column_step(10240) == 32
    assert EngineParams.evidence_column_step(640) == 2
    width, height = 20480, 16
    params = EngineParams(scales=(1, 3))
    flight = CameraFlight("brick", width=width, height=height, flow=(1.0, 0.0), noise_sigma=2, seed=2)
    frames = [flight.render(t) for t in range(5)]
    assert _compare(width, height, frames, params) > 0


def test_the_widest_frame_counts_texture_as_the_reference_does():
    """The texture statistic's column arithmetic is 16-bit in the kernel: at 32 768 px
    wide (the limit) both backends count the same textured pixels and contrast sum (from
    32 770 OpenCL counted none, and its summary was blind); one pixel wider is refused."""
    import emdflow

    width, height = emdflow.estimator.MAX_WIDTH, 8
    params = EngineParams(scales=(1, 3), threshold_mode="adaptive")
    rng = np.random.default_rng(0)
    ground = rng.integers(0, 256, (height, width // 4 + 8), dtype=np.uint8).repeat(4, axis=1)
    frames = [np.ascontiguousarray(ground[:, 2 * t:2 * t + width]) for t in range(4)]
    ref = ReferenceEngine(width, height, params)
    ocl = opencl_backend.OpenCLEngine(width, height, params)
    for frame in frames:
        stats_r, stats_o = ref.step(frame)[2], ocl.step(frame)[2]
        assert np.array_equal(stats_r, stats_o), f"{stats_r} != {stats_o}"
    assert stats_r[STAT_TEXTURED] > 0.5 * width * (height - 4) // 2
    for backend in ("numpy", "opencl"):
        with pytest.raises(ValueError, match=f"at most {width} px wide"):
            emdflow.FlowEstimator(width + 1, height, backend=backend)


def test_full_size_flight_and_reset():
    width, height = 320, 240
    flight = CameraFlight("grass", width=width, height=height, flow=(-4.5, 2.0), noise_sigma=2, seed=5)
    frames = [flight.render(t) for t in range(6)]
    params = EngineParams()
    ref = ReferenceEngine(width, height, params)
    ocl = opencl_backend.OpenCLEngine(width, height, params)
    for f in frames:
        ref.step(f), ocl.step(f)
    ref.reset()
    ocl.reset()
    for t, f in enumerate(frames):
        a, b = ref.step(f), ocl.step(f)
        for x, y in zip(a, b):
            assert np.array_equal(x, y), f"after reset, frame {t} differs"
        if t < 3:
            assert not a[0].any() and not a[1].any(), "history must be empty after reset"


def test_long_run_past_the_device_time_period():
    """The kernels get t modulo a period of all ring lengths (so t never overflows int32):
    past that period (90 frames for delays 1, 2, 4: two tables, five prefiltered frames,
    rings of 3, 5 and 9) the OpenCL engine still equals the reference."""
    width, height = 40, 33
    params = EngineParams(delays=(1, 2, 4))
    period = opencl_backend.OpenCLEngine(width, height, params).layout.t_period
    assert period == 90
    flight = CameraFlight("brick", width=width, height=height, flow=(0.7, -0.4), noise_sigma=2, seed=9)
    ref = ReferenceEngine(width, height, params)
    ocl = opencl_backend.OpenCLEngine(width, height, params)
    fired = 0
    for t in range(period + 12):
        a, b = ref.step(flight.render(t)), ocl.step(flight.render(t))
        for x, y in zip(a, b):
            assert np.array_equal(x, y), f"frame {t} differs"
        fired += int(np.count_nonzero(a[0]))
    assert fired > 0


@pytest.mark.parametrize("shared", [True, False], ids=["host memory", "enqueued copies"])
def test_both_transfer_paths_are_exact(monkeypatch, shared):
    """On a CPU device the kernels read the frame from host memory the engine copies it
    into and write the result where the host reads it (no write or read command); other
    devices get enqueued copies. Both see every frame, and the caller's codes stay valid
    after the next frame."""
    if not shared:
        monkeypatch.setattr(opencl_backend, "_shared_buffer", lambda *args, **kwargs: None)
    width, height = 83, 45
    probe = opencl_backend.OpenCLEngine(width, height, EngineParams())
    if shared and probe.frame_host is None:
        pytest.skip("the OpenCL device does not share host memory")
    assert (probe.frame_host is not None) == (probe.result_host is not None) == shared
    assert ("upload" in probe.stages) == ("download" in probe.stages) != shared
    flight = CameraFlight("grass", width=width, height=height, flow=(-2.6, 1.3), noise_sigma=2, seed=4)
    frames = [flight.render(t) for t in range(8)]
    kept = [probe.step_packed(f)[0] for f in frames[:7]]
    before = [k.decode() for k in kept]
    probe.step_packed(frames[7])
    assert any(a[0].any() for a in before)
    assert all(np.array_equal(a[0], k.decode()[0]) for a, k in zip(before, kept))
    assert _compare(width, height, frames) > 0


def test_result_buffers_are_read_in_place_and_held_codes_copied_out(monkeypatch):
    """On a CPU device the frames take the result buffers in turn: a frame's bit planes
    are read where the kernels wrote them, not copied; codes still held when their buffer
    comes round again are copied out first (only those), and decode to the reference's
    codes however long they are kept. A decode in progress in another thread holds the
    next frame back until it is done."""
    width, height = 83, 45
    probe = opencl_backend.OpenCLEngine(width, height, EngineParams())
    if probe.result_host is None:
        pytest.skip("the OpenCL device does not share host memory")
    slots = opencl_backend.OpenCLEngine.RESULT_SLOTS
    hosts = [host for _, host in probe._results]
    detached = []
    detach = opencl_backend.PackedCodes.detach
    monkeypatch.setattr(opencl_backend.PackedCodes, "detach", lambda self: (detached.append(self), detach(self)))
    ref = ReferenceEngine(width, height, EngineParams())
    flight = CameraFlight("gravel", width=width, height=height, flow=(1.7, -2.2), noise_sigma=2, seed=9)
    frames = [flight.render(t) for t in range(12)]
    for frame in frames[:6]:  # codes dropped at once: nothing to copy out
        assert np.shares_memory(probe.step_packed(frame)[0].words, probe.result_host)
        ref.step(frame)
    assert detached == []
    kept, expected = [], []
    for frame in frames[6:]:
        codes = probe.step_packed(frame)[0]
        assert np.shares_memory(codes.words, probe.result_host)
        kept.append(codes)
        expected.append(ref.step(frame)[:2])
    assert detached == kept[:-slots]
    assert not any(np.shares_memory(codes.words, host) for codes in kept[:-slots] for host in hosts)
    assert any(u.any() for u, _ in expected)
    for codes, (u_r, v_r) in zip(kept, expected):
        u_o, v_o = codes.decode()
        assert np.array_equal(u_o, u_r) and np.array_equal(v_o, v_r)

    # fields pickle and copy (each copy with words of its own), before and after detaching
    import copy
    import pickle

    for codes, (u_r, v_r) in ((kept[-1], expected[-1]), (kept[0], expected[0])):
        for clone in (pickle.loads(pickle.dumps(codes)), copy.deepcopy(codes), copy.copy(codes)):
            assert not any(np.shares_memory(clone.words, host) for host in hosts)
            assert all(np.array_equal(a, b) for a, b in zip(clone.decode(), (u_r, v_r)))

    # with one result buffer the planes are copied out at once (no turn to wait for)
    with monkeypatch.context() as patch:
        patch.setattr(opencl_backend.OpenCLEngine, "RESULT_SLOTS", 1)
        single = opencl_backend.OpenCLEngine(width, height, EngineParams())
    held_single = [single.step_packed(frame)[0] for frame in frames[:8]]
    reference = ReferenceEngine(width, height, EngineParams())
    for codes, frame in zip(held_single, frames[:8]):
        assert all(np.array_equal(a, b) for a, b in zip(codes.decode(), reference.step(frame)[:2]))

    # a decode in progress (holding the codes' lock) on the buffer the next frame takes
    held = kept[-slots]
    finished = threading.Event()
    with held._lock:
        worker = threading.Thread(target=lambda: (probe.step_packed(frames[0]), finished.set()))
        worker.start()
        assert not finished.wait(0.5)
    worker.join(30)
    assert finished.is_set() and held in detached
    assert all(np.array_equal(a, b) for a, b in zip(held.decode(), expected[-slots]))


def test_int_arguments_fall_back_to_the_public_setter():
    """The per-frame int arguments go through pyopencl's raw-bytes setter; a pyopencl
    without it, or where it refuses bytes, gets the public ``set_arg`` instead."""
    seen = []

    class Public:
        def set_arg(self, index, value):
            seen.append((index, int(value), type(value).__name__))

    class Refusing(Public):
        def _set_arg_buf(self, index, data):
            raise TypeError("no bytes here")

    class Raw(Public):
        def _set_arg_buf(self, index, data):
            seen.append((index, int.from_bytes(data, "little", signed=True), "raw"))

    for kernel in (Public(), Refusing()):
        opencl_backend._int_arg_setter(kernel, 3)(3, -7)
    opencl_backend._int_arg_setter(Raw(), 1)(1, 12345)
    assert seen == [(3, -7, "int32"), (3, -7, "int32"), (1, 0, "raw"), (1, 12345, "raw")]


def _shaded_flight(width, height, count, flow=(1.4, -0.7), seed=5):
    """A flight whose right half is in shade (light x 0.2): its tiles get lower thresholds."""
    flight = CameraFlight("gravel", width=width, height=height, flow=flow, noise_sigma=2, seed=seed, shade=0.2)
    return [flight.render(t) for t in range(count)]


@pytest.mark.parametrize("portable", [False, True], ids=["x86", "portable"])
@pytest.mark.parametrize("size,tile,model", [((97, 61), 32, "extended"), ((131, 77), 64, "extended"),
                                             ((200, 131), 96, "paper"), ((64, 64), 64, "paper"),
                                             ((33, 35), 32, "extended")])
def test_local_threshold_is_exact(monkeypatch, size, tile, model, portable):
    """``threshold_mode='local'``: each tile's contrast sum, the thresholds made from them,
    and every use of a tile's threshold (states, texture count, gradient classes) agree;
    sizes cut the last row and column of tiles (and 33 x 35 leaves a one-column tile
    without samples, which takes the frame's threshold). The thresholds must differ
    between tiles, or a kernel that read one tile's for all would pass."""
    if portable:
        monkeypatch.setenv(opencl_backend.PORTABLE_ENV, "1")
    width, height = size
    params = EngineParams(**{**MODELS[model], "threshold_mode": "local", "threshold_tile": tile,
                             "gradient_classes": True})
    spread = 0

    def same_tiles(t, ref, ocl):
        nonlocal spread
        assert np.array_equal(ref.tile_contrast, ocl.tile_contrast), f"frame {t}: tile contrast sums differ"
        assert np.array_equal(ref.theta_q, ocl.theta_q), f"frame {t}: tile thresholds differ"
        assert ref.theta_q.shape == params.threshold_tiles(width, height)
        spread = max(spread, int(ref.theta_q.max() - ref.theta_q.min()))

    # (one pass: the debug engine checks states and matches too)
    assert _compare(width, height, _shaded_flight(width, height, 12), params, each=same_tiles) > 0
    if width > tile:
        assert spread >= 256, "the shaded tiles should have thresholds at least 1 gray level lower"


@pytest.mark.parametrize("shared", [True, False], ids=["host memory", "enqueued copies"])
def test_local_threshold_reaches_the_kernels_on_both_transfer_paths(monkeypatch, shared):
    """The tiles' thresholds are written into host memory the kernels read, or enqueued
    as a copy on other devices; both give the reference's field."""
    if not shared:
        monkeypatch.setattr(opencl_backend, "_shared_buffer", lambda *args, **kwargs: None)
    width, height = 131, 67
    params = EngineParams(**{**MODELS["extended"], "threshold_mode": "local", "threshold_tile": 32})
    assert _compare(width, height, _shaded_flight(width, height, 14), params) > 0
