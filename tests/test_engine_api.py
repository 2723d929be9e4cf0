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
        (dict(delays=(2,)), "delays"),
        (dict(delay_scales=(3,), scales=(1, 5)), "delay_scales"),
        (dict(backend="cuda"), "backend"),
        (dict(evidence_row_step=-1), "evidence_row_step"),
        (dict(evidence_row_step=2.5), "evidence_row_step"),
        (dict(summary_evidence="no"), "summary_evidence"),
    ],
)
def test_bad_parameters_raise_value_error_naming_them(kwargs, message):
    with pytest.raises(ValueError, match=message):
        emdflow.FlowEstimator(96, 72, **kwargs)


@pytest.mark.parametrize("size", [(2, 50), (50, 0), (50.5, 40)])
def test_bad_sizes(size):
    with pytest.raises(ValueError):
        emdflow.FlowEstimator(*size, backend="numpy")


def test_opencl_devices_and_device_choice(monkeypatch):
    devices = emdflow.opencl_devices()
    assert devices and devices[0][0] == 0 and ":" in devices[0][1]
    est = emdflow.FlowEstimator(64, 48, device=0)
    assert est._engine.device is not None
    monkeypatch.setenv("EMDFLOW_OPENCL_DEVICE", "no-such-device")
    with pytest.raises(ValueError, match="no-such-device"):
        emdflow.FlowEstimator(64, 48)
    monkeypatch.setenv("EMDFLOW_OPENCL_DEVICE", "7")
    with pytest.raises(ValueError, match="out of range"):
        emdflow.FlowEstimator(64, 48)


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
