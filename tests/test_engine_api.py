"""Public API of the engine: shapes, validation, laziness, ownership, reset, devices."""

import os

import numpy as np
import pytest

import emdflow
from emdflow.synthetic import CameraFlight

BACKENDS = ["numpy", "opencl"]


def _flight(w=96, h=72, flow=(3.0, 0.0), **kw):
    return CameraFlight("gravel", width=w, height=h, flow=flow, **kw)


@pytest.mark.parametrize("backend", BACKENDS)
def test_update_returns_field_every_frame_nan_until_history_full(backend):
    est = emdflow.FlowEstimator(96, 72, backend=backend)
    flight = _flight()
    for t in range(6):
        field = est.update(flight.render(t))
        assert isinstance(field, emdflow.FlowField)
        assert field.u.shape == (72, 96) and field.u.dtype == np.float32
        assert field.v.shape == (72, 96) and field.v.dtype == np.float32
        if t < 3:
            assert not field.ready
            assert np.isnan(field.u).all() and np.isnan(field.v).all()
            s = emdflow.summarize(field)
            assert (s.flow_x, s.flow_y, s.quality) == (0.0, 0.0, 0)
        else:
            assert field.ready
            finite = field.u[np.isfinite(field.u)]
            assert finite.size > 0
            assert set(np.unique(np.abs(finite))) <= set(map(float, est.params.speeds))


@pytest.mark.parametrize("backend", BACKENDS)
def test_arrays_belong_to_caller_and_are_lazy(backend):
    est = emdflow.FlowEstimator(96, 72, backend=backend)
    flight = _flight()
    fields = [est.update(flight.render(t)) for t in range(5)]
    first = fields[3]
    assert first._u is None and first._v is None, "u/v must not be materialised eagerly"
    u_before = first.u.copy()
    codes_before = first.u_code.copy()
    est.update(flight.render(9))
    est.update(np.zeros((72, 96), np.uint8))
    assert np.array_equal(first.u_code, codes_before)
    np.testing.assert_array_equal(first.u, u_before)
    assert first.u is first.u  # cached


@pytest.mark.parametrize("backend", BACKENDS)
def test_fields_pickle_and_copy(backend):
    """A field kept for later (a worker process, a recording) pickles and copies, read or
    not yet read, and the copy holds the same flow and summary after later updates."""
    import copy
    import pickle

    est = emdflow.FlowEstimator(96, 72, backend=backend)
    flight = _flight(flow=(2.0, -1.0))
    fields = [est.update(flight.render(t)) for t in range(6)]
    unread, read = fields[4], fields[5]
    read.u  # noqa: B018 - materialised before copying
    clones = [(f, c(f)) for f in (unread, read) for c in (copy.copy, copy.deepcopy,
                                                         lambda f: pickle.loads(pickle.dumps(f)))]
    for t in range(6, 10):
        est.update(flight.render(t))
    for original, clone in clones:
        np.testing.assert_array_equal(clone.u, original.u)
        np.testing.assert_array_equal(clone.v, original.v)
        assert emdflow.summarize(clone) == emdflow.summarize(original)


def test_opencl_codes_stay_packed_until_read_and_match_numpy():
    pytest.importorskip("pyopencl")
    ocl = emdflow.FlowEstimator(96, 72, backend="opencl")
    ref = emdflow.FlowEstimator(96, 72, backend="numpy")
    flight = _flight(flow=(2.2, -1.4), noise_sigma=2)
    pairs = [(ocl.update(f), ref.update(f)) for f in (flight.render(t) for t in range(7))]
    assert pairs[4][0]._u_code is None, "the OpenCL field must not unpack its codes eagerly"
    detections = 0
    for field_o, field_r in pairs:  # unpacked only now, after later updates
        np.testing.assert_array_equal(field_o.u_code, field_r.u_code)
        np.testing.assert_array_equal(field_o.v_code, field_r.v_code)
        np.testing.assert_array_equal(field_o.u, field_r.u)
        assert field_o.u_detections == np.count_nonzero(field_o.u_code)
        detections += field_o.u_detections + field_o.v_detections
    assert detections > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_reset_forgets_history(backend):
    est = emdflow.FlowEstimator(96, 72, backend=backend)
    flight = _flight()
    for t in range(5):
        est.update(flight.render(t))
    est.reset()
    assert est.frames_seen == 0
    for t in range(3):
        assert np.isnan(est.update(flight.render(10 + t)).u).all()
    assert np.isfinite(est.update(flight.render(13)).u).any()


@pytest.mark.parametrize(
    "frame, message",
    [
        (np.zeros((72, 96, 3), np.uint8), "3-D"),
        (np.zeros((72, 96), np.float32), "dtype float32"),
        (np.zeros((96, 72), np.uint8), "(96, 72)"),
        (np.zeros((73, 96), np.uint8), "96x73"),
        ([[0] * 96] * 72, "list"),
        # the backends would disagree on it (OpenCL reads the data, numpy computes masked)
        (np.ma.masked_array(np.zeros((72, 96), np.uint8), mask=False), "masked array"),
    ],
)
def test_bad_frames_raise_value_error_naming_expected_and_received(frame, message):
    est = emdflow.FlowEstimator(96, 72, backend="numpy")
    with pytest.raises(ValueError) as err:
        est.update(frame)
    text = str(err.value)
    assert "(72, 96)" in text and "uint8" in text and message in text


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(scales=(1, 4)), "odd"),
        (dict(scales=(1, 17)), "15"),
        (dict(threshold=-1.0), "threshold"),
        (dict(prefilter_size=4), "prefilter_size"),
        (dict(prefilter_size=103), "from 3 to 101"),
        (dict(prefilter_size=1_000_000_001), "from 3 to 101"),  # (was a 7 GiB allocation)
        (dict(delays=(2,)), "delays"),
        (dict(delay_scales=(3,), scales=(1, 5), delays=(1, 2)), "delay_scales"),
        (dict(delay_scales=(), delays=(1, 2)), r"delay_scales=\(\)"),  # no channel, yet 6 frames late
        # types are checked, not converted: a string, a fraction or None is an error
        (dict(threshold="5"), "threshold"),
        (dict(threshold=True), "threshold"),
        (dict(threshold=None), "threshold"),
        (dict(threshold=float("nan")), "threshold"),
        (dict(scales=5), "scales"),
        (dict(scales=(1.5, 3)), "scales"),
        (dict(scales=None), "scales"),
        (dict(prefilter_size=11.7), "prefilter_size"),
        (dict(prefilter_size=None), "prefilter_size"),
        (dict(delays=(1, 2.5)), "delays"),
        (dict(delays=3), "delays"),
        (dict(delay_scales=None), "delay_scales"),
        (dict(sharp_templates="no"), "sharp_templates"),
        (dict(brightness_compensation="no"), "brightness_compensation"),
        (dict(gradient_classes=1), "gradient_classes"),
        (dict(adaptive_gain=True), "adaptive_gain"),
        (dict(threshold_min=None), "threshold_min"),
        # 16 channels: one more than a 4-bit code can name, in both backends
        (dict(scales=(1, 3, 5, 7, 9, 11, 13, 15), delays=tuple(range(1, 10)), backend="numpy"), "at most 15"),
        (dict(backend="cuda"), "backend"),
        (dict(evidence_row_step=-1), "evidence_row_step"),
        (dict(evidence_row_step=2.5), "evidence_row_step"),
        (dict(summary_evidence="no"), "summary_evidence"),
        (dict(threshold_mode="tiles"), "threshold_mode"),
        (dict(threshold_mode="local", threshold_tile=48), "threshold_tile"),
        (dict(threshold_mode="local", threshold_tile=0), "threshold_tile"),
        (dict(threshold_mode="local", threshold_tile=2048), "threshold_tile"),
        (dict(threshold_mode="local", threshold_tile=64.0), "threshold_tile"),
    ],
)
def test_bad_parameters_raise_value_error_naming_them(kwargs, message):
    with pytest.raises(ValueError, match=message):
        emdflow.FlowEstimator(96, 72, **kwargs)


def test_parameters_accept_numpy_scalars_and_channel_sets_without_scale_1():
    """numpy numbers are numbers (a config read through numpy, a sweep with np.arange),
    and ``delay_scales`` only matters with a delay above 1: a channel set without scale 1
    needs no ``delay_scales`` of its own."""
    est = emdflow.FlowEstimator(96, 72, backend="numpy", scales=np.array([3, 5, 7]), threshold=np.float32(4.5),
                                prefilter_size=np.int64(7), threshold_mode="adaptive",
                                adaptive_gain=np.float64(0.4), sharp_templates=np.bool_(True))
    p = est.params
    assert p.scales == (3, 5, 7) and p.threshold == 4.5 and p.prefilter_size == 7 and p.sharp_templates is True
    assert all(type(k) is int for k in p.scales) and type(p.threshold) is float
    assert emdflow.FlowEstimator(96, 72, backend="numpy", scales=(15,)).params.channels == ((15, 1),)
    flight = _flight(flow=(5.0, 0.0))
    fields = [est.update(flight.render(t)) for t in range(5)]
    assert np.isfinite(fields[-1].u).any()


@pytest.mark.parametrize("size", [(2, 50), (50, 0), (50, 3), (50.5, 40), (4097, 4096), (1 << 17, 129),
                                  (np.uint16(4097), np.uint16(4096)), (np.int16(8000), np.int16(8000))])
def test_bad_sizes(size):
    from emdflow.estimator import FrameSizeError

    with pytest.raises(ValueError, match="frame size|integer") as caught:
        emdflow.FlowEstimator(*size, backend="numpy")
    # a size out of range is a FrameSizeError (the daemon and the tools name the frames'
    # source for it); a size that is no whole number is a plain bad parameter
    assert isinstance(caught.value, FrameSizeError) == str(caught.value).startswith("frame size")


@pytest.mark.parametrize("backend", BACKENDS)
def test_nothing_is_detected_until_the_slowest_channel_has_its_history(backend):
    """With delays up to 4 (the extended model) the one-frame channels could fire from
    frame 4, but the field is all NaN, with no detection counted or binned, until the
    whole channel set has its history (frame 13); the frame's other counters are kept."""
    from emdflow.params import MODELS

    est = emdflow.FlowEstimator(96, 72, backend=backend, **MODELS["extended"])
    assert est.params.history_frames == 12
    flight = _flight(flow=(3.0, -1.0), noise_sigma=2)
    for t in range(14):
        field = est.update(flight.render(t))
        assert field.ready == (t >= 12)
        if not field.ready:
            assert np.isnan(field.u).all() and np.isnan(field.v).all()
            assert field.u_detections == field.v_detections == 0
            assert not field.histogram.any() and not field.positions.any()
            assert field.textured_fraction > 0.5
        if t >= 4:
            assert field.changed_fraction.max() > 0  # the states are there all along
    assert np.isfinite(field.u).any() and field.u_detections == np.count_nonzero(field.u_code) > 0
    assert field.histogram.any()


def test_opencl_devices_and_device_choice(monkeypatch):
    devices = emdflow.opencl_devices()
    assert devices and devices[0][0] == 0 and ":" in devices[0][1]
    est = emdflow.FlowEstimator(64, 48, device=0)
    assert est.device == devices[0][1]  # the device it runs on, named as the list names it
    assert emdflow.FlowEstimator(64, 48, backend="numpy").device is None
    with pytest.raises(ValueError, match="only the OpenCL backend"):
        emdflow.FlowEstimator(64, 48, backend="numpy", device=0)
    # numpy's integers are indices too (np.int64(0) used to be looked up as the name "0")
    assert emdflow.FlowEstimator(64, 48, device=np.int64(0)).device == devices[0][1]
    # the name as listed chooses the device, from the call and from the environment (the
    # "platform: device" label used to be matched against "platform device" only)
    assert emdflow.FlowEstimator(64, 48, device=devices[0][1]).device == devices[0][1]
    monkeypatch.setenv("EMDFLOW_OPENCL_DEVICE", devices[0][1])
    assert emdflow.FlowEstimator(64, 48).device == devices[0][1]
    for bad in (True, 1.5, [0]):  # (a ValueError, as every bad parameter: it was a TypeError)
        with pytest.raises(ValueError, match="expected an index"):
            emdflow.FlowEstimator(64, 48, device=bad)
    # a superscript two is a digit to str.isdigit() but no number to int(): a name
    with pytest.raises(ValueError, match="OpenCL device '²' not found among"):
        emdflow.FlowEstimator(64, 48, device="²")
    monkeypatch.setenv("EMDFLOW_OPENCL_DEVICE", "no-such-device")
    # (an empty or blank name is no choice: the variable applies; "" skipped it and " "
    # matched any name with a space)
    for no_choice in (None, "", " "):
        with pytest.raises(ValueError, match=r"no-such-device.*\(EMDFLOW_OPENCL_DEVICE\)"):
            emdflow.FlowEstimator(64, 48, device=no_choice)
    monkeypatch.setenv("EMDFLOW_OPENCL_DEVICE", "7")
    with pytest.raises(ValueError, match=r"7 \(EMDFLOW_OPENCL_DEVICE\) out of range"):
        emdflow.FlowEstimator(64, 48)
    # the caller's choice wins over the environment's, and is not named after it, even when
    # the two are the same text
    with pytest.raises(ValueError, match=r"index 9 out of range"):
        emdflow.FlowEstimator(64, 48, device=9)
    with pytest.raises(ValueError, match=r"device '7' not found|index 7 out of range") as info:
        emdflow.FlowEstimator(64, 48, device="7")
    assert "EMDFLOW_OPENCL_DEVICE" not in str(info.value)


def test_missing_opencl_platform_says_how_to_install(monkeypatch):
    import pyopencl as cl

    from emdflow import opencl_backend

    def no_platform():
        raise cl.LogicError("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")

    monkeypatch.setattr(cl, "get_platforms", no_platform)
    with pytest.raises(RuntimeError) as err:
        opencl_backend.list_devices()
    assert 'pip install "emdflow[pocl]"' in str(err.value)
    assert "ICD" in str(err.value)


def test_kernels_are_installed_with_the_package():
    """In CI the package is pip-installed (non-editable): the kernels must come from it."""
    from emdflow import opencl_backend

    text = opencl_backend.kernel_source("evd.cl")
    assert "velocity_detectors" in text
    if os.environ.get("EMDFLOW_EXPECT_INSTALLED"):
        import importlib.resources

        assert "site-packages" in emdflow.__file__, emdflow.__file__
        assert importlib.resources.files("emdflow.kernels").joinpath("evd.cl").is_file()


def test_a_hand_made_field_without_a_histogram_is_a_clear_error():
    """FlowField is public: one made by hand without the evidence summarize() reads says
    so (it was an AttributeError from inside summarize)."""
    from emdflow.params import EngineParams
    from emdflow.reference import STAT_FIRST_CHANGED

    params = EngineParams()
    z = np.zeros((48, 64), np.int8)
    field = emdflow.FlowField(z, z, np.zeros(STAT_FIRST_CHANGED + len(params.channels), np.int64), None,
                              params, 5)
    with pytest.raises(ValueError, match=r"summarize\(\): this field has no summary evidence \(its histogram"):
        emdflow.summarize(field)


@pytest.mark.parametrize("backend", ["opencl", "numpy"])
def test_dense_only_fields_cannot_be_summarised(backend):
    """A field of ``summary_evidence=False`` has the flow but no histograms: summarize and
    the looming cues refuse it with a message naming the option, even before the history
    is full; the dense field is there."""
    from emdflow.cues import looming_cues, slope_expansion_rate

    est = emdflow.FlowEstimator(80, 60, backend, summary_evidence=False)
    flight = _flight(80, 60, seed=2)
    fields = [est.update(flight.render(t)) for t in range(5)]
    assert fields[-1].ready and fields[0].histogram is None and fields[-1].positions is None
    assert np.isfinite(fields[-1].u).any()
    for field in (fields[0], fields[-1]):
        for fn, name in ((emdflow.summarize, "summarize"), (looming_cues, "looming_cues"),
                         (slope_expansion_rate, "slope_expansion_rate")):
            with pytest.raises(ValueError, match=rf"{name}\(\).*summary_evidence=False"):
                fn(field)


def test_the_first_device_that_builds_the_kernels_is_used(caplog):
    """Two PoCLs side by side (the pip wheel's and the distribution's) are common, and a
    PoCL whose LLVM is older than the processor cannot compile for it: the automatic
    choice moves on to the next device, says so once, and fails only if none builds."""
    from emdflow import opencl_backend

    class Device:
        def __init__(self, name):
            self.name = name

    old, new, other = Device("pthread-old-llvm"), Device("pthread-new-llvm"), Device("pthread-third")
    attempts = []

    def build(device):
        attempts.append(device.name)
        if device is old:
            raise opencl_backend._build_failure(device.name, "error: unknown target CPU 'generic'")
        return "program"

    caplog.set_level("WARNING", logger="emdflow.opencl_backend")
    opencl_backend._SKIPPED.discard(old.name)
    for _ in range(2):
        assert opencl_backend._first_buildable([old, new, other], build) == (new, "program")
    assert attempts == ["pthread-old-llvm", "pthread-new-llvm"] * 2  # never the third
    warnings = [r.getMessage() for r in caplog.records if "cannot build" in r.getMessage()]
    assert len(warnings) == 1 and "pthread-old-llvm" in warnings[0] and "unknown target CPU" in warnings[0]

    with pytest.raises(opencl_backend.KernelBuildError) as err:
        opencl_backend._first_buildable([old], build)
    assert "pthread-old-llvm" in str(err.value) and "apt-get install pocl-opencl-icd" in str(err.value)
    opencl_backend._SKIPPED.discard(old.name)
    caplog.clear()
    with pytest.raises(opencl_backend.KernelBuildError):  # a single (chosen) device: no "next one"
        opencl_backend._first_buildable([old], build)
    assert not [r for r in caplog.records if "trying the next one" in r.getMessage()]

    def nothing_builds(device):
        raise opencl_backend._build_failure(device.name, f"error: {device.name} says no")

    with pytest.raises(opencl_backend.KernelBuildError, match="none of the 2 OpenCL devices") as err:
        opencl_backend._first_buildable([new, other], nothing_builds)
    assert "pthread-new-llvm says no" in str(err.value) and "pthread-third says no" in str(err.value)
    assert "apt-get" not in str(err.value)  # the hint only where the log shows its cause


def test_a_kernel_build_failure_names_the_device_and_is_not_retried():
    """On the real PoCL device: a program the compiler rejects gives a KernelBuildError that
    carries the compiler's message, and the failure is remembered per (device, source)."""
    import pyopencl as cl

    from emdflow import opencl_backend

    device = emdflow.FlowEstimator(64, 48)._engine.device  # one whose compiler works here
    ctx, _ = opencl_backend._context(device)
    with pytest.raises(opencl_backend.KernelBuildError) as err:
        opencl_backend._build(cl, ctx, device, "__kernel void broken(__global int *a) { a[0] = ; }")
    assert device.name.strip() in str(err.value) and "error" in str(err.value)

    token = os.urandom(4).hex()  # a source of its own, whatever ran before in this process

    class Layout:  # the program's compile-time header, made invalid
        def header(self):
            return f"#error deliberately broken header {token}\n"

    before = len(opencl_backend._PROGRAMS)
    with pytest.raises(opencl_backend.KernelBuildError) as first:
        opencl_backend._program(ctx, device, Layout(), False)
    with pytest.raises(opencl_backend.KernelBuildError) as second:
        opencl_backend._program(ctx, device, Layout(), False)
    assert f"deliberately broken header {token}" in str(first.value)
    assert str(second.value) == str(first.value) and second.value is not first.value
    assert len(opencl_backend._PROGRAMS) == before + 1  # built (and failed) once


def test_a_device_without_a_context_is_passed_over(monkeypatch, caplog):
    """A device on which no OpenCL context can be made (a driver that lists a GPU it cannot
    open) is skipped by the automatic choice like one whose compiler fails. The failure
    itself cannot be made to happen here, so the first context request is made to fail."""
    import pyopencl as cl

    from emdflow import opencl_backend

    device = emdflow.FlowEstimator(64, 48)._engine.device
    calls = []
    real_context = opencl_backend._context

    def first_fails(dev):
        calls.append(dev)
        if len(calls) == 1:
            raise cl.LogicError("clCreateContext failed: DEVICE_NOT_AVAILABLE")
        return real_context(dev)

    monkeypatch.setattr(opencl_backend, "_all_devices", lambda: [device, device])
    monkeypatch.setattr(opencl_backend, "_context", first_fails)
    monkeypatch.delenv("EMDFLOW_OPENCL_DEVICE", raising=False)
    opencl_backend._SKIPPED.discard(device.int_ptr)
    caplog.set_level("WARNING", logger="emdflow.opencl_backend")
    est = emdflow.FlowEstimator(64, 48)
    assert est._engine.device == device and len(calls) == 2
    assert any("DEVICE_NOT_AVAILABLE" in r.getMessage() for r in caplog.records)
    monkeypatch.setattr(opencl_backend, "_all_devices", lambda: [device])
    calls.clear()
    with pytest.raises(opencl_backend.KernelBuildError, match="no OpenCL context on .*DEVICE_NOT_AVAILABLE"):
        emdflow.FlowEstimator(64, 48)


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_readme_usage_example_prints_what_its_comments_say(backend, capsys):
    """The README's first example runs as written and prints the values its comments
    quote (its quality went stale once, unnoticed)."""
    import re
    from pathlib import Path

    readme = Path(__file__).resolve().parents[1] / "README.md"
    if not readme.is_file():
        pytest.skip("no README.md beside the tests")
    text = readme.read_text()
    block = re.search(r"## The engine: `emdflow`\n\n```python\n(.*?)```", text, re.S)[1]
    exec(compile(block.replace('backend="opencl"', f'backend="{backend}"'), "README.md", "exec"), {})
    printed = capsys.readouterr().out.splitlines()
    said = [line.split("#", 1)[1].strip() for line in block.splitlines() if line.startswith("print(")]
    flow_x, flow_y, quality = printed[0].split()
    assert said[0].startswith(f"{float(flow_x):.2f} {float(flow_y):.2f} {quality} ")
    assert said[1].startswith(printed[1] + ":")


@pytest.mark.parametrize("size", [(96, 72), (97, 61), (33, 35), (320, 240), (65, 131)])
@pytest.mark.parametrize("tile", [32, 64, 96])
def test_local_threshold_tiles_share_the_frames_samples(size, tile):
    """The tiles' sample counts are the frame's contrast samples split by tile (each
    sampled pixel counted once), in a grid of ceil(size / tile) tiles; and a tile without
    samples takes the frame's threshold, the others their own."""
    from emdflow.params import EngineParams

    width, height = size
    params = EngineParams(threshold_mode="local", threshold_tile=tile)
    samples = params.tile_contrast_samples(width, height)
    assert samples.shape == params.threshold_tiles(width, height) == (-(-height // tile), -(-width // tile))
    assert samples.sum() == params.contrast_samples(width, height)
    sums = samples * 20  # a mean contrast of 20 gray levels everywhere ...
    sums[0, 0] = samples[0, 0] * 5  # ... but 5 in the first tile
    whole = int(sums.sum())
    theta = params.next_threshold_q(whole, int(samples.sum()), sums, samples)
    frame_theta = params.threshold_q(min(params.threshold_max, params.adaptive_gain * whole / samples.sum()))
    assert theta[0, 0] == params.threshold_q(max(params.threshold_min, params.adaptive_gain * 5))
    assert np.all(theta[samples == 0] == frame_theta)
    if samples.size > 1:
        assert np.all(theta[(samples > 0)][1:] == params.threshold_q(params.adaptive_gain * 20))
