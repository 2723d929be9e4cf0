"""Middlebury .flo read/write (emdflow.tools.flo)."""

import numpy as np
import pytest

from emdflow.tools.flo import FLO_MAGIC, UNKNOWN_FLOW, FloError, read_flo, write_flo


def test_round_trip_with_unknown_components(tmp_path):
    rng = np.random.default_rng(0)
    u = rng.normal(0, 3, (7, 11)).astype(np.float32)
    v = rng.normal(0, 3, (7, 11)).astype(np.float32)
    u[2, 3] = np.nan  # only u unknown
    v[4, 5] = np.nan  # only v unknown
    u[6, 10] = v[6, 10] = np.nan
    path = tmp_path / "f.flo"
    write_flo(path, u, v)
    raw = path.read_bytes()
    assert raw[:4] == FLO_MAGIC
    assert np.frombuffer(raw, "<i4", 2, 4).tolist() == [11, 7]  # width, height
    assert len(raw) == 12 + 7 * 11 * 2 * 4
    data = np.frombuffer(raw, "<f4", offset=12).reshape(7, 11, 2)
    assert data[2, 3, 0] == np.float32(UNKNOWN_FLOW) and data[2, 3, 1] == v[2, 3]  # interleaved u, v
    u2, v2 = read_flo(path)
    assert u2.dtype == np.float32 and u2.shape == (7, 11)
    np.testing.assert_array_equal(u2, u)  # NaN in the same places
    np.testing.assert_array_equal(v2, v)


def test_reads_middlebury_unknown_convention(tmp_path):
    path = tmp_path / "m.flo"
    data = np.zeros((2, 3, 2), "<f4")
    data[0, 0] = (1e10, 1e10)
    data[1, 2] = (2e9, -0.5)
    path.write_bytes(b"PIEH" + np.array([3, 2], "<i4").tobytes() + data.tobytes())
    u, v = read_flo(path)
    assert np.isnan(u[0, 0]) and np.isnan(v[0, 0]) and np.isnan(u[1, 2]) and v[1, 2] == -0.5


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "no PIEH magic"),
        (b"XXXX" + b"\0" * 20, "no PIEH magic"),
        (b"PIEH" + np.array([4, 4], "<i4").tobytes() + b"\0" * 16, "truncated"),
        (b"PIEH" + np.array([-1, 4], "<i4").tobytes(), "implausible size"),
    ],
)
def test_bad_files_name_the_file(tmp_path, content, message):
    path = tmp_path / "bad.flo"
    path.write_bytes(content)
    with pytest.raises(FloError, match=message) as e:
        read_flo(path)
    assert str(path) in str(e.value)


def test_missing_file_and_shape_mismatch(tmp_path):
    with pytest.raises(FloError, match="nope.flo: no such file"):
        read_flo(tmp_path / "nope.flo")
    with pytest.raises(FloError, match="x.flo"):
        write_flo(tmp_path / "x.flo", np.zeros((2, 3)), np.zeros((3, 2)))
