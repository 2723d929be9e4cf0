"""The `emdflow` command: flow, frames, eval, bench — each on a small generated clip."""

import csv
import importlib.machinery
import importlib.util
import os
import subprocess
import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from emdflow.cli import main
from emdflow.synthetic import CameraFlight
from emdflow.tools.flo import read_flo
# The CLI sets FFmpeg's log level before it opens its first file: importing video_io does
# (quiet_ffmpeg_log). OpenCV reads that level once, at the first file this process opens,
# and the fixtures below write their videos with cv2 directly, so it is imported here, before
# any of them runs: a test run that started with the fixtures printed FFmpeg's "[ffv1 ...]"
# lines where the CLI, run alone, prints none.
from emdflow.tools.video_io import quiet_ffmpeg_log  # noqa: F401

import emdflow

# Where the emdflow under test lives (the installed package in CI, the source tree otherwise):
# subprocesses import the same one.
PACKAGE_ROOT = Path(emdflow.__file__).resolve().parents[1]
W, H, N = 96, 72, 9
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(PACKAGE_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


@pytest.fixture(scope="session")
def backend():
    """The engine backend these tool tests run on: numpy unless EMDFLOW_TEST_BACKEND says otherwise.

    The tools only see FlowFields, and both backends give identical fields (the engine's own
    tests check that); the numpy reference is fast at 96×72 and needs no kernel build, which
    keeps this file well under its time budget. ``EMDFLOW_TEST_BACKEND=opencl`` runs them on
    OpenCL (skipped when the OpenCL backend is not installed).
    """
    forced = os.environ.get("EMDFLOW_TEST_BACKEND", "numpy")
    if forced == "opencl" and importlib.util.find_spec("emdflow.opencl_backend") is None:
        pytest.skip("EMDFLOW_TEST_BACKEND=opencl but emdflow.opencl_backend is not installed")
    return forced


def test_default_backend_is_opencl():
    from emdflow.cli import build_parser

    for cmd in (["flow", "x", "-o", "y.avi"], ["frames", "x"], ["eval"]):
        assert build_parser().parse_args(cmd).backend == "opencl"


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 96×72, 9-frame lossless video of a camera flight at (2, 1) px/frame, and the frames."""
    d = tmp_path_factory.mktemp("clip")
    flight = CameraFlight("gravel", width=W, height=H, flow=(2.0, 1.0), seed=4)
    frames = [flight.render(t) for t in range(N)]
    path = d / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (W, H), True)
    for f in frames:
        w.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    w.release()
    folder = d / "seq"
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"frame{i}.png"), f)
    return path, folder, frames


def _read_video(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    fps = cap.get(cv2.CAP_PROP_FPS)
    cap.release()
    return frames, fps


def _one_line_error(capsys, *names):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for name in names:
        assert str(name) in err, err
    return err


# ------------------------------------------------------------------------------------ flow


@pytest.mark.parametrize("name, codec", [("flow.avi", None), ("flow.mkv", None), ("flow_mjpg.avi", "mjpg")])
def test_flow_writes_a_readable_video(tmp_path, clip, backend, name, codec):
    video, _, _ = clip
    out = tmp_path / name
    argv = ["flow", str(video), "-o", str(out), "--backend", backend, "--upscale", "2", "-q"]
    if codec:
        argv += ["--codec", codec]
    assert main(argv) == 0
    frames, fps = _read_video(out)
    assert len(frames) == N
    assert frames[0].shape == (2 * H, 2 * W, 3)
    assert fps == pytest.approx(25.0)


def test_flow_exports_npz_and_flo(tmp_path, clip, backend):
    _, folder, _ = clip
    out, npz, flo_dir = tmp_path / "f.avi", tmp_path / "f.npz", tmp_path / "flo"
    assert main(["flow", str(folder), "-o", str(out), "--npz", str(npz), "--flo-dir", str(flo_dir),
                 "--backend", backend, "--fps", "10", "-q"]) == 0
    frames, fps = _read_video(out)
    assert len(frames) == N and fps == pytest.approx(10.0)
    assert frames[0].shape[:2] == (H * 4, W * 4)  # auto upscale to ~480 px wide, at most 4
    z = np.load(npz)
    assert z["u"].shape == (N, H, W) and z["u"].dtype == np.float16
    assert z["quality"].shape == (N,) and z["quality"][-1] > 0
    assert z["flow_x"][-1] > 1.0  # the flight moves right at 2 px/frame
    flos = sorted(flo_dir.glob("*.flo"))
    assert len(flos) == N
    u, v = read_flo(flos[-1])
    assert u.shape == (H, W)
    np.testing.assert_array_equal(np.isnan(u), np.isnan(z["u"][-1]))
    np.testing.assert_allclose(u[np.isfinite(u)], z["u"][-1][np.isfinite(u)].astype(np.float32))
    assert np.isfinite(u).any()
    assert np.isnan(read_flo(flos[0])[0]).all()  # history not full yet
    # the file is written where it was asked for (numpy appends ".npz" to a bare name)
    other = tmp_path / "fields.dat"
    assert main(["flow", str(folder), "-o", str(tmp_path / "g.avi"), "--npz", str(other),
                 "--backend", backend, "--fps", "10", "--max-frames", "3", "-q"]) == 0
    assert other.is_file() and not (tmp_path / "fields.dat.npz").exists()
    assert np.load(other)["u"].shape == (3, H, W)


def test_flow_ctrl_c_leaves_a_playable_file(tmp_path, clip, backend, monkeypatch):
    import emdflow.tools.flowviz as fv

    real = fv.render_flow_frame
    calls = {"n": 0}

    def interrupting(*a, **k):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(fv, "render_flow_frame", interrupting)
    out = tmp_path / "cut.avi"
    assert main(["flow", str(clip[0]), "-o", str(out), "--backend", backend, "-q"]) == 130
    frames, _ = _read_video(out)
    assert len(frames) == 4


def test_flow_on_a_synthetic_input_with_snapshot(tmp_path, backend):
    out, snap = tmp_path / "s.mkv", tmp_path / "s.png"
    src = "synthetic:texture=brick,u=-1,v=3,frames=6,size=64x48,fps=20"
    assert main(["flow", src, "-o", str(out), "--snapshot", str(snap), "--upscale", "1",
                 "--backend", backend, "-q"]) == 0
    frames, fps = _read_video(out)
    assert len(frames) == 6 and frames[0].shape == (48, 64, 3) and fps == pytest.approx(20.0)
    assert snap.read_bytes()[:8] == PNG_MAGIC
    np.testing.assert_array_equal(cv2.imread(str(snap)), frames[-1])  # FFV1 is lossless


def test_flow_refuses_a_flo_dir_of_an_earlier_run(tmp_path, capsys, backend):
    """A second run into the same --flo-dir left the longer first run's files behind,
    mixed with its own; an empty existing folder is still taken."""
    flo_dir = tmp_path / "flo"
    flo_dir.mkdir()

    def run(frames, video):
        return main(["flow", f"synthetic:frames={frames},size=32x24", "-o", str(tmp_path / video),
                     "--flo-dir", str(flo_dir), "--backend", backend, "-q"])

    assert run(5, "a.avi") == 0
    assert len(list(flo_dir.glob("frame_*.flo"))) == 5
    assert run(3, "b.avi") == 2
    _one_line_error(capsys, f"--flo-dir {flo_dir}: holds 5 .flo files of an earlier run", "empty or new folder")
    assert not (tmp_path / "b.avi").exists()


def test_flow_upscale_is_bounded_before_the_run(tmp_path, capsys, backend):
    """--upscale had no bound: OpenCV failed on the enlarged frame (an allocation
    traceback, or "cannot write a ... video here" after the first frame)."""
    out = tmp_path / "big.mp4"
    assert main(["flow", "synthetic:frames=3,size=16x16", "-o", str(out), "--upscale", "520",
                 "--backend", backend, "-q"]) == 2
    _one_line_error(capsys, "--upscale 520", "8320x8320", "at most 8190 px a side", "at most --upscale 511")
    assert not out.exists()


# ---------------------------------------------------------------------------------- frames


def test_frames_csv(tmp_path, clip, backend):
    video, folder, _ = clip
    out = tmp_path / "frames.csv"
    assert main(["frames", str(video), "-o", str(out), "--backend", backend,
                 "--focal-length-px", "100", "-q"]) == 0
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == ["frame", "t", "flow_x", "flow_y", "rate_x", "rate_y", "quality"]
    assert len(rows) == N
    assert float(rows[3]["t"]) == pytest.approx(3 / 25.0)
    assert rows[0]["quality"] == "0"  # history filling
    last = rows[-1]
    assert int(last["quality"]) > 0
    assert float(last["flow_x"]) > 1.0 and float(last["flow_y"]) > 0.2
    assert float(last["rate_x"]) == pytest.approx(float(last["flow_x"]) * 25.0 / 100.0, rel=1e-3)


def test_frames_on_a_folder_to_stdout_via_python_m(clip, backend):
    _, folder, _ = clip
    r = subprocess.run([sys.executable, "-m", "emdflow", "frames", str(folder), "--backend", backend],
                       env=_env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert lines[0] == "frame,t,flow_x,flow_y,quality"
    assert len(lines) == N + 1
    assert lines[1].split(",")[1] == ""  # no frame rate for a folder: t empty


def test_frames_output_dash_is_stdout(tmp_path, monkeypatch, capsys, backend):
    """``-o -`` wrote a file named "-"; it is stdout, where the CSV goes without -o."""
    monkeypatch.chdir(tmp_path)
    assert main(["frames", "synthetic:frames=3,size=32x24", "-o", "-", "--backend", backend]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "frame,t,flow_x,flow_y,quality" and len(lines) == 4
    assert not (tmp_path / "-").exists()


# ------------------------------------------------------------------------------------ eval


def test_eval_csv_table_and_plot(tmp_path, backend, capsys):
    texture = tmp_path / "ground.png"
    import skimage.data

    cv2.imwrite(str(texture), skimage.data.brick()[:200, :200])
    out_csv, out_png = tmp_path / "e.csv", tmp_path / "e.png"
    argv = ["eval", "--size", "96x72", "--speeds", "1,3", "--directions", "0,112.5",
            "--variants", "base,zoom", "--frames", "2", "--repeats", "1",
            "--textures", "gravel", str(texture), "--csv", str(out_csv), "--plot", str(out_png),
            "--backend", backend, "-q"]
    assert main(argv) == 0
    table = capsys.readouterr().out
    assert "variant base" in table and "variant zoom" in table and "DIS" in table
    rows = list(csv.DictReader(out_csv.open()))
    keys = [(r["variant"], r["method"], r["speed"]) for r in rows]
    assert keys == [(v, m, s) for v in ("base", "zoom") for m in ("emd", "dis") for s in ("1", "3", "all")]
    for r in rows:
        assert int(r["frames"]) == (4 if r["speed"] != "all" else 8)  # 2 directions × 2 frames
        assert 0.0 <= float(r["coverage"]) <= 1.0
    dis = {(r["variant"], r["speed"]): r for r in rows if r["method"] == "dis"}
    for key, r in dis.items():  # DIS on small, easy motion: its errors are small
        assert float(r["summary_rel_error_median"]) < 0.15, key
        assert float(r["summary_dir_error_median_deg"]) < 5.0, key
        assert float(r["pixel_error_median"]) < 0.3, key
        assert float(r["density"]) == 1.0 and float(r["sign_accuracy"]) > 0.9
    assert float(dis[("zoom", "all")]["expansion_rel_error_median"]) < 0.6
    emd = [r for r in rows if r["method"] == "emd" and r["variant"] == "base" and r["speed"] == "all"][0]
    assert float(emd["density"]) > 0.01 and float(emd["sign_accuracy"]) > 0.8
    png = out_png.read_bytes()
    assert png[:8] == PNG_MAGIC
    img = cv2.imread(str(out_png))
    assert img is not None and img.shape[0] > 100 and img.shape[1] > 100

    # re-plot and Markdown from the CSV without flying again
    md, png2 = tmp_path / "t.md", tmp_path / "again.png"
    assert main(["eval", "--from-csv", str(out_csv), "--plot", str(png2), "--markdown", str(md)]) == 0
    assert png2.read_bytes()[:8] == PNG_MAGIC
    # the image type follows the file ending (an .svg used to get PNG bytes)
    svg = tmp_path / "again.svg"
    assert main(["eval", "--from-csv", str(out_csv), "--plot", str(svg)]) == 0
    assert b"<svg" in svg.read_bytes()[:2000]
    text = md.read_text()
    assert "| speed | EMD density" in text and "| zoom |" in text
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    capsys.readouterr()
    assert main(["eval", "--from-csv", str(bad)]) == 2
    _one_line_error(capsys, bad)


def test_eval_from_csv_without_engine_rows_is_an_error(tmp_path, capsys):
    """A CSV with its header only, or with DIS rows only, printed an empty table, exit 0."""
    from emdflow.tools.evaluate import CSV_COLUMNS, write_csv

    empty = tmp_path / "empty.csv"
    write_csv([], empty)
    assert main(["eval", "--from-csv", str(empty), "--plot", ""]) == 2
    _one_line_error(capsys, f"{empty}: no rows")
    dis_only = tmp_path / "dis.csv"
    write_csv([{**dict.fromkeys(CSV_COLUMNS, 0.5), "variant": "base", "method": "dis", "speed": 1.0,
                "frames": 2}], dis_only)
    assert main(["eval", "--from-csv", str(dis_only), "--plot", ""]) == 2
    _one_line_error(capsys, f"{dis_only}: no engine rows (only DIS)")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device every write to fails)")
@pytest.mark.parametrize("command, option", [
    (["frames", "synthetic:frames=4", "--size", "96x72", "--backend", "numpy", "-q", "-o", "/dev/full"], "-o"),
    (["flow", "synthetic:frames=4", "--size", "96x72", "--backend", "numpy", "-q", "-o", "{tmp}/f.avi",
      "--npz", "/dev/full"], "--npz"),
    (["eval", "--size", "96x72", "--speeds", "1", "--directions", "0", "--variants", "base", "--frames", "1",
      "--repeats", "1", "--no-dis", "--backend", "numpy", "-q", "--plot", "", "--csv", "/dev/full"], "--csv"),
])
def test_a_failed_write_names_its_output(tmp_path, capsys, command, option):
    """A write that fails (a full disk; /dev/full fails every one) said only "No space
    left on device": a write error carries no file name. Now the option and the file."""
    assert main([c.replace("{tmp}", str(tmp_path)) for c in command]) == 2
    _one_line_error(capsys, f"{option} /dev/full: No space left on device")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device every write to fails)")
def test_a_failed_write_to_standard_output_names_it(tmp_path):
    """emdflow frames without -o writes the CSV to standard output; a failed write there
    is named as such (there is no -o to name)."""
    import subprocess

    with open("/dev/full", "w") as full:
        result = subprocess.run([sys.executable, "-m", "emdflow", "frames", "synthetic:frames=4", "--size", "96x72",
                                 "--backend", "numpy", "-q"], stdout=full, stderr=subprocess.PIPE, text=True,
                                timeout=120, cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == "emdflow frames: error: standard output: No space left on device", result.stderr


def test_eval_from_csv_refuses_flight_options(tmp_path, capsys):
    """--from-csv flies nothing: a flight or engine option beside it (a different speed
    list, another model) used to be ignored without a word, and the table printed was the
    CSV's, not the one asked for."""
    from emdflow.tools.evaluate import CSV_COLUMNS, write_csv

    saved = tmp_path / "saved.csv"
    write_csv([{**dict.fromkeys(CSV_COLUMNS, 0.5), "variant": "base", "method": "emd", "speed": 1.0,
                "frames": 2}], saved)
    for extra in (["--speeds", "2,3"], ["--model", "extended", "--quick"], ["--seed", "4"],
                  ["--engine-opt", "threshold=3"], ["--label", "mine"], ["--csv", str(tmp_path / "other.csv")]):
        assert main(["eval", "--from-csv", str(saved), "--plot", "", *extra]) == 2
        _one_line_error(capsys, f"--from-csv {saved} flies nothing", *(e for e in extra if e.startswith("--")))
    assert main(["eval", "--from-csv", str(saved), "--plot", ""]) == 0


def test_plots_without_matplotlib(tmp_path, monkeypatch, capsys):
    """Installed with the ``pocl`` extra alone there is no matplotlib: ``emdflow eval``
    leaves its default plot out with a note, an explicit ``--plot`` is an error before
    anything is flown or timed (eval and bench), one line with the fix."""
    out_csv = tmp_path / "e.csv"
    assert main(["eval", "--size", "96x72", "--speeds", "1", "--directions", "0", "--variants", "base",
                 "--frames", "1", "--repeats", "1", "--no-dis", "--backend", "numpy", "-q",
                 "--csv", str(out_csv), "--plot", ""]) == 0
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now fails
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(["eval", "--from-csv", str(out_csv)]) == 0
    assert 'no plot: matplotlib is not installed (pip install "emdflow[tools]")' in capsys.readouterr().err
    assert not (tmp_path / "emdflow_eval.png").exists()
    assert main(["eval", "--from-csv", str(out_csv), "--plot", "p.png"]) == 2
    _one_line_error(capsys, "--plot p.png", 'pip install "emdflow[tools]"')
    with pytest.raises(SystemExit) as usage:  # (the benchmark's own parser: a usage error)
        main(["bench", "--sizes", "32x24", "--plot", "b.png"])
    assert usage.value.code == 2
    err = capsys.readouterr().err
    assert "--plot b.png" in err and "matplotlib is not installed" in err


def test_eval_accumulator_bins_any_error():
    """An absurd per-pixel error (a flight at 10^17 px/frame) goes to the last bin of the
    error histogram: its index overflowed int64 and bincount refused the negative value,
    after the whole run."""
    from emdflow.tools.evaluate import Accumulator

    acc = Accumulator()
    u = np.array([[1.0, np.nan]], np.float32)
    acc.add_field(u, u, np.full((1, 2), 1e17), np.full((1, 2), 1e17))
    assert acc.err_hist[-1] == 2 and acc.err_hist.sum() == 2


def test_eval_truth_field_matches_the_renderer():
    """The exact per-pixel truth warps frame t−1 onto frame t (zoom + translation)."""
    from emdflow.tools.evaluate import fit_expansion, truth_field

    f = CameraFlight("gravel", width=80, height=60, flow=(1.3, -0.7), noise_sigma=0, expansion_rate=0.02)
    prev, nxt = f.render(4).astype(np.float32), f.render(5).astype(np.float32)
    u, v = truth_field(f, 5, at="previous")
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float32)
    warped = cv2.remap(nxt, xx + u.astype(np.float32), yy + v.astype(np.float32), cv2.INTER_CUBIC)
    wrong = cv2.remap(nxt, xx + 1.3, yy - 0.7, cv2.INTER_CUBIC)  # translation only
    inner = np.s_[8:-8, 8:-8]
    assert np.abs(warped - prev)[inner].mean() < 0.3 * np.abs(wrong - prev)[inner].mean()
    assert fit_expansion(u, v) == pytest.approx(0.02, rel=1e-6)
    uc, vc = truth_field(f, 5, at="current")
    assert uc[0, 40] == pytest.approx((1.3 + (40.5 - 40) * 0.02) / 1.02, rel=1e-6)  # (F + r·X) / (1 + r)


# ----------------------------------------------------------------------------------- bench


def test_bench_forwards_its_arguments(monkeypatch):
    seen = {}
    fake = types.ModuleType("emdflow.bench")
    fake.__spec__ = importlib.machinery.ModuleSpec("emdflow.bench", None)
    fake.main = lambda argv: seen.setdefault("argv", argv) and 0
    monkeypatch.setitem(sys.modules, "emdflow.bench", fake)
    assert main(["bench", "--sizes", "320x240", "--png", "b.png"]) == 0
    assert seen["argv"] == ["--sizes", "320x240", "--png", "b.png"]


def test_bench_stages_times_every_command_of_a_frame(capsys):
    pytest.importorskip("pyopencl")
    from emdflow import bench
    from emdflow.opencl_backend import OpenCLEngine

    from emdflow.params import EngineParams

    stages = bench.profile_stages(96, 72, frames=30)
    # a device that shares the result buffers' memory with the host has no download: the
    # host reads the result where the kernels wrote it (the upload is the host's copy)
    commands = [name for name in OpenCLEngine.STAGES
                if name != "download" or OpenCLEngine(96, 72, EngineParams()).result_host is None]
    assert list(stages) == [*commands, "gaps", "wall", "decode", "summary"]
    kernels = [stages[name] for name in OpenCLEngine.STAGES[1:-1]]
    assert all(ms > 0 for ms in kernels), stages
    assert stages["summary"] > 0
    assert stages["gaps"] >= 0
    # device time of the commands is part of the host's wall time for the frame
    assert sum(stages[name] for name in commands) < stages["wall"]
    assert bench.main(["--stages", "--sizes", "64x48"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("64x48") and all(name in line for name in (*commands, "summary"))
    # the dense field only: the same commands (the detector kernel without the binning),
    # nothing to summarise
    assert bench.main(["--stages", "--dense-only", "--sizes", "64x48"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert "dense field only" in out[0]
    assert all(name in out[-1] for name in commands) and "summary" not in out[-1]
    with pytest.raises(SystemExit):  # the timing table has its own dense-only column
        bench.main(["--dense-only", "--sizes", "64x48"])


def test_bench_names_the_device_its_engine_runs_on(monkeypatch, capsys):
    """The header names the device the engine chose (the first one that builds, not simply
    the first one listed); a device choice that names none is one error line, exit 1."""
    pytest.importorskip("pyopencl")
    from emdflow import FlowEstimator, bench

    assert bench.main(["--stages", "--sizes", "48x40"]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert f"device: {FlowEstimator(48, 40).device};" in header
    monkeypatch.setenv("EMDFLOW_OPENCL_DEVICE", "no-such-device")
    assert bench.main(["--stages", "--sizes", "48x40"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("emdflow bench: error: OpenCL engine:") and "no-such-device" in err
    assert len(err.splitlines()) == 1
    # a compiler's multi-line log: still one line, with the compiler's error line in it
    from emdflow import opencl_backend

    monkeypatch.delenv("EMDFLOW_OPENCL_DEVICE")
    real, token = opencl_backend.kernel_source, os.urandom(4).hex()
    monkeypatch.setattr(opencl_backend, "kernel_source",
                        lambda name: real(name) + (f"\n#error broken on purpose {token}\n" if name == "evd.cl" else ""))
    assert bench.main(["--stages", "--sizes", "48x40"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"broken on purpose {token}" in err


def test_bench_ratios_of_medians_and_per_round(monkeypatch):
    """The table's DIS / OpenCL ratios: of the medians, and the median of each round's
    own ratio. A clock where DIS takes 3x the engine's time (4x the dense-only engine's),
    and from the middle of the third round (after its engine blocks) everything takes
    twice as long: the ratio of the medians compares a fast engine with a slow DIS (6x,
    8x dense only), each round's ratio is 3x (4x) but one."""
    from emdflow import bench

    state = {"t": 0.0, "round": 0}
    order = ["opencl", "opencl-dense", "opencl+summary", "numpy", "dis", "blur"]
    cost = {"dis": 3.0, "opencl-dense": 0.75}

    def methods(width, height, frames, backend_kwargs=None):
        def make(name):
            def run(i):
                loaded = state["round"] >= (2 if name == "dis" else 3)
                state["t"] += cost.get(name, 1.0) * (2.0 if loaded else 1.0) * 1e-3
            return run
        return {name: make(name) for name in order}

    monkeypatch.setattr(bench, "_methods", methods)
    monkeypatch.setattr(bench, "_frames", lambda w, h, n, **kw: [None] * n)
    monkeypatch.setattr(bench.time, "perf_counter", lambda: state["t"])
    results = bench.run_benchmark(sizes=((64, 48),), block=4, rounds=5,
                                  progress=lambda m: state.update(round=state["round"] + 1))
    r = results[(64, 48)]
    assert r["dis"] / r["opencl"] == pytest.approx(6.0)  # engine 1, 1, 1, 2, 2; DIS 3, 3, 6, 6, 6
    assert r["dis_per_opencl_paired"] == pytest.approx(3.0)  # 3, 3, 6, 3, 3
    assert r["dis"] / r["opencl-dense"] == pytest.approx(8.0)
    assert r["dis_per_dense_paired"] == pytest.approx(4.0)
    table = bench.format_table(results)
    assert "| per round |" in table and "| 6.00x | 3.00x | 8.00x | 4.00x |" in table


def test_bench_blocks_start_with_untimed_frames(monkeypatch):
    """The first frame after another method's block is slow (threads wake up, caches
    refill): each block starts with ``warmup`` untimed frames of its own method, the
    frames just before the block's (numpy, 100 ms a frame, gets none)."""
    from emdflow import bench

    state = {"t": 0.0, "last": None}
    calls = {}

    def methods(width, height, frames, backend_kwargs=None):
        def make(name):
            def run(i):
                state["t"] += (10.0 if state["last"] != name else 1.0) * 1e-3
                state["last"] = name
                calls.setdefault(name, []).append(i)
            return run
        return {name: make(name) for name in ["opencl", "opencl-dense", "opencl+summary", "numpy", "dis", "blur"]}

    monkeypatch.setattr(bench, "_methods", methods)
    monkeypatch.setattr(bench, "_frames", lambda w, h, n, **kw: [None] * n)
    monkeypatch.setattr(bench.time, "perf_counter", lambda: state["t"])
    steady = bench.run_benchmark(sizes=((64, 48),), block=4, rounds=3)[(64, 48)]
    assert steady["opencl"] == pytest.approx(1.0) and steady["dis"] == pytest.approx(1.0)
    assert steady["numpy"] == pytest.approx((10 + 1 + 1) / 3)
    # warm-up (4 frames 0..3), then per round 2 untimed frames before the block's 4
    assert calls["opencl"][4:12] == [38, 39, 0, 1, 2, 3, 2, 3]
    cold = bench.run_benchmark(sizes=((64, 48),), block=4, rounds=3, warmup=0)[(64, 48)]
    assert cold["opencl"] == pytest.approx((10 + 3) / 4)


def test_bench_stages_drift_gives_every_frame_a_gain_to_compensate():
    """``--stages --drift 0.3`` profiles the brightness compensation's slower path: over
    the slowest channel's 4 frames every frame of its clip has an exposure gain the
    extended model compensates; without drift hardly any."""
    from emdflow import bench
    from emdflow.params import MODELS, EngineParams
    from emdflow.reference import prefilter

    params = EngineParams(**MODELS["extended"])
    d = max(params.delays)
    for drift in (0.0, 0.3):
        # (the bench's own size: in a small frame the motion alone changes the brightness)
        sums = [int(prefilter(f, params.weights).sum()) for f in bench._frames(640, 480, 40, drift)]
        gains = [params.brightness_ratio_q(sums[t], sums[t - d]) for t in range(d, 40)]
        compensated = sum(g != 256 for g in gains)
        assert compensated == len(gains) if drift else compensated < len(gains) // 4, (drift, gains)


def test_bench_texture_option_flies_over_other_ground(monkeypatch, capsys):
    """``--texture NAME`` flies the benchmark over another ground (a bundled photograph,
    a fractal texture or an image file); an unknown name is a usage error naming it. Over
    the camera photograph, whose large bright and dark regions enter and leave the view,
    the motion alone changes the frame's brightness: the extended model's compensation
    sees a gain in most frames even at the one-frame delay, where gravel shows none."""
    from emdflow import bench
    from emdflow.params import MODELS, EngineParams
    from emdflow.reference import prefilter

    params = EngineParams(**MODELS["extended"])
    shares = {}
    for texture in ("gravel", "camera"):
        sums = [int(prefilter(f, params.weights).sum()) for f in bench._frames(640, 480, 40, texture=texture)]
        shares[texture] = np.mean([params.brightness_ratio_q(sums[t], sums[t - 1]) != 256 for t in range(1, 40)])
    assert shares["gravel"] < 0.1 and shares["camera"] > 0.9, shares
    seen = []
    real = bench.profile_stages
    monkeypatch.setattr(bench, "profile_stages",
                        lambda w, h, **kw: seen.append(kw["texture"]) or real(w, h, frames=5, **kw))
    pytest.importorskip("pyopencl")
    assert bench.main(["--stages", "--sizes", "48x40", "--texture", "camera"]) == 0
    assert seen == ["camera"] and "flight over camera" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        bench.main(["--stages", "--texture", "no-such-ground"])
    assert "--texture" in capsys.readouterr().err


def test_engine_ab_times_another_checkout_in_the_same_process(capsys):
    """``python -m emdflow.tools.engine_ab CHECKOUT`` loads another checkout's package and
    kernels under another module name and alternates both engines' blocks (here: this
    checkout against itself); a path that is no checkout is a one-line error."""
    from pathlib import Path

    from emdflow.tools import ToolError, engine_ab

    pytest.importorskip("pyopencl")
    root = Path(__file__).resolve().parents[1]
    other = engine_ab.load_checkout(root, name="emdflow_ab_test")
    assert other.FlowEstimator is not __import__("emdflow").FlowEstimator
    r = engine_ab.compare(other, 64, 48, rounds=3, block=4)
    assert len(r["other"]) == len(r["this"]) == 3 and all(x > 0 for x in r["other"] + r["this"])
    assert 0.2 < r["ratio"] < 5
    with pytest.raises(ToolError, match="not an emdflow checkout"):
        engine_ab.load_checkout(root / "tests")
    assert engine_ab.main([str(root / "tests")]) == 2
    assert "not an emdflow checkout" in capsys.readouterr().err


def test_engine_ab_other_option_times_an_option_against_the_default(capsys):
    """``--other-option KEY=VALUE`` gives the other engine one estimator keyword: the same
    checkout then times what an option costs; a malformed or invalid option is an error."""
    from pathlib import Path

    from emdflow.tools import engine_ab

    pytest.importorskip("pyopencl")
    root = str(Path(__file__).resolve().parents[1])
    assert engine_ab.main([root, "--size", "64x48", "--rounds", "2", "--block", "3",
                           "--other-option", "evidence_row_step=1"]) == 0
    out = capsys.readouterr().out
    assert "other evidence_row_step=1" in out and "per round" in out
    with pytest.raises(SystemExit):
        engine_ab.main([root, "--other-option", "evidence_row_step"])
    assert engine_ab.main([root, "--size", "64x48", "--other-option", "evidence_row_step=-3"]) == 2
    assert "evidence_row_step" in capsys.readouterr().err
    # over another ground, with an exposure ramp
    assert engine_ab.main([root, "--size", "64x48", "--rounds", "2", "--block", "3", "--model", "extended",
                           "--texture", "camera", "--drift", "0.3"]) == 0
    assert "over camera, drift +0.3" in capsys.readouterr().out
    assert engine_ab.main([root, "--size", "64x48", "--texture", "no-such-ground"]) == 2
    assert "no-such-ground" in capsys.readouterr().err


def test_engine_ab_option_applies_to_both_engines(monkeypatch, capsys):
    """``--option KEY=VALUE`` gives both engines the keyword (e.g. the dense field only,
    ``summary_evidence=False``), and ``--other-option`` the other one on top of it."""
    from pathlib import Path

    from emdflow.tools import engine_ab

    pytest.importorskip("pyopencl")
    root = str(Path(__file__).resolve().parents[1])
    other = engine_ab.load_checkout(Path(root), name="emdflow_ab_option")
    seen = {}
    for name, module in (("other", other), ("this", __import__("emdflow"))):
        real = module.FlowEstimator

        def capture(*a, name=name, real=real, **kw):
            seen[name] = kw
            return real(*a, **kw)

        monkeypatch.setattr(module, "FlowEstimator", capture)
    r = engine_ab.compare(other, 64, 48, rounds=1, block=2, options={"summary_evidence": False},
                          other_options={"evidence_row_step": 1})
    assert r["other"] and r["this"]
    assert seen["this"]["summary_evidence"] is False and "evidence_row_step" not in seen["this"]
    assert seen["other"]["summary_evidence"] is False and seen["other"]["evidence_row_step"] == 1
    monkeypatch.undo()
    assert engine_ab.main([root, "--size", "64x48", "--rounds", "2", "--block", "3",
                           "--option", "summary_evidence=False"]) == 0
    assert "over gravel, summary_evidence=False" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        engine_ab.main([root, "--option", "summary_evidence"])


def test_engine_ab_summary_times_summarize_on_each_engines_fields(capsys, monkeypatch):
    """``--summary`` alternates the two checkouts' ``summarize`` over each one's own fields
    (every call gets a ready field with evidence) instead of their updates."""
    from pathlib import Path

    import emdflow
    from emdflow.tools import engine_ab

    pytest.importorskip("pyopencl")
    seen = []
    real = emdflow.summarize
    monkeypatch.setattr(emdflow, "summarize", lambda field: seen.append(field.ready) or real(field))
    root = str(Path(__file__).resolve().parents[1])
    for model in ("paper", "extended"):  # (the extended model's history is 12 frames)
        seen.clear()
        assert engine_ab.main([root, "--size", "64x48", "--rounds", "2", "--block", "3", "--summary",
                               "--model", model]) == 0
        assert "per summarize() call" in capsys.readouterr().out
        assert len(seen) == 2 * (3 + 2) and all(seen)  # two rounds of 3 calls, each after 2 untimed
    # a field without the summary's evidence cannot be summarised: one-line error
    assert engine_ab.main([root, "--size", "64x48", "--rounds", "1", "--block", "2", "--summary",
                           "--other-option", "summary_evidence=False"]) == 2
    assert "summary_evidence=False" in capsys.readouterr().err


def test_bench_model_option_runs_the_daemons_model(monkeypatch, capsys):
    """``--model extended`` benchmarks the daemon's default model (delays and adaptive
    threshold from ``emdflow.params.MODELS``); ``--delays`` overrides the delays alone."""
    from emdflow import bench
    from emdflow.params import MODELS

    seen = []
    real = bench.profile_stages
    monkeypatch.setattr(bench, "profile_stages",
                        lambda w, h, backend_kwargs=None, **kw: seen.append(backend_kwargs) or real(
                            w, h, frames=5, backend_kwargs=backend_kwargs, **kw))
    pytest.importorskip("pyopencl")
    assert bench.main(["--stages", "--sizes", "48x40", "--model", "extended"]) == 0
    assert "model: extended" in capsys.readouterr().out
    assert seen[-1] == MODELS["extended"] and seen[-1]["threshold_mode"] == "adaptive"
    assert bench.main(["--stages", "--sizes", "48x40", "--delays", "1,3"]) == 0
    assert seen[-1] == {"delays": (1, 3)}
    assert bench.main(["--stages", "--sizes", "48x40", "--evidence-row-step", "1"]) == 0
    assert seen[-1] == {"evidence_row_step": 1} and "evidence every 1 row" in capsys.readouterr().out
    assert bench.main(["--stages", "--sizes", "48x40", "--model", "extended", "--threshold-mode", "local"]) == 0
    assert seen[-1] == {**MODELS["extended"], "threshold_mode": "local"}
    assert "extended, local threshold" in capsys.readouterr().out


def test_model_option_of_the_tools_selects_a_named_model(backend):
    """``--model extended`` (flow, frames, eval) gives the daemon's model; a single option
    such as ``--delays`` then overrides that keyword alone."""
    import argparse

    from emdflow.params import MODELS
    from emdflow.tools import ToolError, add_engine_arguments, engine_kwargs, make_estimator

    parser = argparse.ArgumentParser()
    add_engine_arguments(parser)
    assert engine_kwargs(parser.parse_args([])) == {}
    args = parser.parse_args(["--model", "extended", "--backend", backend])
    assert engine_kwargs(args) == MODELS["extended"]
    est = make_estimator(args, 64, 48)
    assert 15 in est.params.scales and 0.25 in est.params.speeds and est.params.threshold_mode == "adaptive"
    args = parser.parse_args(["--model", "extended", "--delays", "1,2"])
    assert engine_kwargs(args) == dict(MODELS["extended"], delays=(1, 2))
    with pytest.raises(SystemExit):
        parser.parse_args(["--model", "fast"])
    # the tools summarise every frame: a dense-only engine is refused up front
    with pytest.raises(ToolError, match="summary_evidence=False"):
        make_estimator(parser.parse_args(["--engine-opt", "summary_evidence=False"]), 64, 48)


# ---------------------------------------------------------------------------------- errors


def test_bad_inputs_give_one_line_naming_the_file(tmp_path, capsys, clip):
    missing = tmp_path / "missing.avi"
    assert main(["flow", str(missing), "-o", str(tmp_path / "o.avi"), "--backend", "numpy"]) == 2
    _one_line_error(capsys, missing)

    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\0garbage" * 100)
    assert main(["frames", str(junk), "--backend", "numpy"]) == 2
    _one_line_error(capsys, junk)

    assert main(["flow", str(clip[0]), "-o", str(tmp_path / "nodir" / "o.avi"), "--backend", "numpy"]) == 2
    _one_line_error(capsys, tmp_path / "nodir" / "o.avi")

    assert main(["flow", str(clip[0]), "-o", str(tmp_path / "o.gif"), "--backend", "numpy"]) == 2
    _one_line_error(capsys, tmp_path / "o.gif")

    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["frames", str(empty), "--backend", "numpy"]) == 2
    _one_line_error(capsys, empty)

    seq = tmp_path / "seq"
    seq.mkdir()
    cv2.imwrite(str(seq / "a1.png"), clip[2][0])
    (seq / "a2.png").write_bytes(b"not a png")
    assert main(["frames", str(seq), "--backend", "numpy", "-o", str(tmp_path / "x.csv")]) == 2
    _one_line_error(capsys, seq / "a2.png")

    assert main(["frames", str(clip[1]), "--focal-length-px", "300", "--backend", "numpy"]) == 2
    _one_line_error(capsys, clip[1], "--fps")

    # every output path before the run (--markdown used to fail only after it)
    for option in ("--markdown", "--csv"):
        target = tmp_path / "nodir" / "e.out"
        assert main(["eval", "--quick", option, str(target)]) == 2
        _one_line_error(capsys, target, "does not exist")

    bad_texture = tmp_path / "tex.png"
    bad_texture.write_text("nope")
    for tex in (bad_texture, tmp_path / "absent.jpg"):
        assert main(["eval", "--quick", "--textures", str(tex), "--csv", str(tmp_path / "e.csv")]) == 2
        _one_line_error(capsys, tex)


def test_bad_sizes_and_rates_name_their_origin(tmp_path, capsys, clip):
    """A frame size the engine cannot take is the input's fault, said with its name (it
    was blamed on "engine options"); a synthetic size beyond the engine's limits is refused
    before a frame is rendered (100000x100000 was a traceback from OpenCV's allocator); an
    output video's rate too slow for FFmpeg is --fps's fault (it was blamed on the output
    file, after the first frame)."""
    tiny = tmp_path / "tiny.avi"
    w = cv2.VideoWriter(str(tiny), cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (2, 2), True)
    for _ in range(3):
        w.write(np.zeros((2, 2, 3), np.uint8))
    w.release()
    assert main(["frames", str(tiny), "--backend", "numpy"]) == 2
    err = _one_line_error(capsys, tiny, "frame size 2x2")
    assert "engine options" not in err
    assert main(["frames", str(clip[0]), "--size", "2x2", "--backend", "numpy"]) == 2
    _one_line_error(capsys, "--size 2x2: frame size 2x2")
    for size, why in (("100000x100000", "at most 16777216 pixels"), ("40000x8", "at most 32768 px wide"),
                      ("40000x4", "both sides must be at least 8 px")):
        assert main(["frames", f"synthetic:size={size},frames=3", "--backend", "numpy"]) == 2
        _one_line_error(capsys, f"size={size}: {why}")
    assert main(["flow", str(clip[0]), "-o", str(tmp_path / "slow.avi"), "--fps", "1e-300", "--backend", "numpy"]) == 2
    _one_line_error(capsys, "--fps 1e-300: at least 0.01 frames/s")
    assert not (tmp_path / "slow.avi").exists()


def test_flow_ctrl_c_before_the_first_frame_says_nothing_was_written(tmp_path, clip, backend, monkeypatch,
                                                                      capsys):
    """The writer opens on the first frame: interrupted before it, there is no video, and
    the message said it was playable."""
    import emdflow.tools.flowviz as fv

    def interrupting(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(fv, "render_flow_frame", interrupting)
    out = tmp_path / "none.avi"
    assert main(["flow", str(clip[0]), "-o", str(out), "--backend", backend, "-q"]) == 130
    assert not out.exists()
    err = capsys.readouterr().err
    assert f"interrupted after 0 frames; {out} was not written" in err, err


def test_exit_code_as_a_process(tmp_path):
    missing = tmp_path / "nothing.mkv"
    r = subprocess.run([sys.executable, "-m", "emdflow", "flow", str(missing), "-o", str(tmp_path / "o.avi")],
                       env=_env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [f"emdflow flow: error: {missing}: no such file or directory"]


# ---------------------------------------------------------------------------------- render


def test_render_writes_the_frames_the_daemon_reads_back_exactly(tmp_path, capsys):
    """``emdflow render synthetic:...`` stores the flight as gray lossless FFV1: the
    daemon's ``video:`` source decodes it to the very frames the renderer made, at the
    flight's frame rate; a lossy codec stores colour channels, a gray one refuses them."""
    from emdflow.tools.video_io import open_frames
    from firmware_py.sources import make_source
    from firmware_py.sources.video import is_gray_stream

    uri = "synthetic:texture=grass,u=1.5,v=-0.5,frames=12,size=96x72,fps=50"
    out = tmp_path / "flight.mkv"
    assert main(["render", uri, "-o", str(out)]) == 0
    assert "12 frames 96x72 at 50 fps (gray ffv1)" in capsys.readouterr().err
    expected = list(open_frames(uri))
    cap = cv2.VideoCapture(str(out))
    assert is_gray_stream(cap)
    cap.release()
    source = make_source(f"video:{out}")
    source.open()
    try:
        got = [source.read() for _ in range(13)]
    finally:
        source.close()
    assert got[12] is None and source.fps == 50
    for frame, truth in zip(got[:12], expected):
        np.testing.assert_array_equal(frame.image, truth)
    assert main(["render", uri, "-o", str(tmp_path / "lossy.avi"), "--codec", "mjpg", "-q"]) == 0
    assert cv2.VideoCapture(str(tmp_path / "lossy.avi")).read()[1].ndim == 3
    assert main(["render", uri, "-o", str(tmp_path / "lossy.mp4"), "-q"]) == 0  # mp4v, colour channels
    assert cv2.VideoCapture(str(tmp_path / "lossy.mp4")).read()[1].ndim == 3
    assert main(["render", uri, "-o", str(out), "--size", "64x48", "--max-frames", "3", "-q"]) == 0
    assert main(["render", str(out), "-o", str(out)]) == 2
    _one_line_error(capsys, "would overwrite the input")
    # frames too (its CSV used to replace the video it was reading, exit 0)
    before = out.read_bytes()
    assert main(["frames", str(out), "-o", str(out), "--backend", "numpy"]) == 2
    _one_line_error(capsys, "would overwrite the input")
    assert out.read_bytes() == before
    for extra in (["--npz", str(out)], ["--snapshot", str(out)]):  # nor any other output of flow
        assert main(["flow", str(out), "-o", str(tmp_path / "o.avi"), *extra, "--backend", "numpy"]) == 2
        _one_line_error(capsys, "would overwrite the input")
    assert out.read_bytes() == before
    for argv, option in ((["frames", str(out), "--max-frames", "0"], "--max-frames 0"),
                         (["flow", str(out), "-o", str(tmp_path / "o.avi"), "--max-frames", "-1"], "--max-frames -1"),
                         (["flow", str(out), "-o", str(tmp_path / "o.avi"), "--upscale", "0"], "--upscale 0")):
        assert main([*argv, "--backend", "numpy"]) == 2
        _one_line_error(capsys, option, "at least 1")


def test_a_hard_link_to_the_input_is_the_input(tmp_path, capsys):
    """A hard link is the input under another name (Path.resolve does not see it): render
    read 6 of 40 frames and wrote over its own input."""
    src, link = tmp_path / "src.mkv", tmp_path / "hl.mkv"
    assert main(["render", "synthetic:frames=40,size=32x24", "-o", str(src), "-q"]) == 0
    try:
        os.link(src, link)
    except OSError as e:
        pytest.skip(f"no hard links here: {e}")
    before = src.read_bytes()
    for argv in (["render", str(src), "-o", str(link)],
                 ["frames", str(src), "-o", str(link), "--backend", "numpy"],
                 ["flow", str(src), "-o", str(tmp_path / "o.avi"), "--snapshot", str(link), "--backend", "numpy"],
                 ["flow", str(src), "-o", str(tmp_path / "o.avi"), "--npz", str(link), "--backend", "numpy"]):
        assert main(argv) == 2
        _one_line_error(capsys, str(link), "would overwrite the input")
    assert src.read_bytes() == before


def test_no_image_output_into_the_input_folder(tmp_path, capsys, clip, backend):
    """A snapshot (or any image-named output) in the folder of images being read became a
    frame of the next run over it, or stopped it with a frame of another size."""
    _, folder, _ = clip
    listed = sorted(folder.iterdir())
    alias = tmp_path / "alias"
    alias.symlink_to(folder, target_is_directory=True)
    video = str(tmp_path / "o.avi")
    for argv, name in (
            (["flow", str(folder), "-o", video, "--snapshot", str(folder / "snap.png")], "--snapshot"),
            (["flow", str(alias), "-o", video, "--snapshot", str(folder / "snap.JPG")], "--snapshot"),
            (["frames", str(folder), "-o", str(folder / "rows.tif")], "-o")):
        assert main([*argv, "--backend", backend, "-q"]) == 2
        _one_line_error(capsys, name, "an image in the input folder", "read as a frame")
    assert sorted(folder.iterdir()) == listed and not Path(video).exists()
    # beside the folder, and other files in it, are still fine
    assert main(["flow", str(folder), "-o", video, "--snapshot", str(tmp_path / "snap.png"), "--max-frames", "2",
                 "--backend", backend, "-q"]) == 0


# --------------------------------------------------------------------------------- devices


def test_devices_lists_what_runs_the_engine_and_marks_the_choice(capsys):
    """``emdflow devices`` tries every listed device for real and marks the one the engine
    takes when left to choose (exit 0)."""
    pytest.importorskip("pyopencl")
    listed = emdflow.opencl_devices()
    assert main(["devices"]) == 0
    out = capsys.readouterr().out.splitlines()
    rows = out[:len(listed)]
    for (index, name), row in zip(listed, rows):
        assert row[2:].startswith(f"{index}  {name}  ") and (row.endswith("works") or "fails: " in row)
    chosen = emdflow.FlowEstimator(64, 48).device
    marked = [row for row in rows if row.startswith("*")]
    assert len(marked) == 1 and f"  {chosen}  works" in marked[0]
    assert out[len(listed)].startswith(f"the engine runs on {chosen} ")


def test_devices_a_driver_failing_at_run_time_is_one_failed_row(monkeypatch, capsys):
    """A device whose kernels build but whose driver fails when the frame runs (pyopencl's
    errors are not RuntimeErrors; such a GPU driver cannot be had here, so the run is made
    to fail) is one failed row, not the end of the command."""
    cl = pytest.importorskip("pyopencl")
    from emdflow.tools import devices

    real = devices._run_once

    def flaky_driver(options, device):
        if device == 0:
            raise cl.MemoryError("clEnqueueNDRangeKernel failed: OUT_OF_RESOURCES")
        return real(options, device)

    monkeypatch.setattr(devices, "_run_once", flaky_driver)
    checks, _chosen = devices.check_devices()
    assert checks[0].error == "clEnqueueNDRangeKernel failed: OUT_OF_RESOURCES" and not checks[0].works
    assert main(["devices"]) in (0, 1)  # (0 where another device works)
    assert "0  " in capsys.readouterr().out


def test_devices_says_why_no_device_runs_the_engine(monkeypatch, capsys):
    """Where every device's compiler rejects the kernels (here: a kernel file broken on
    purpose, compiled for real), each line carries the compiler's error line and the
    command fails with exit 1 and one error line."""
    pytest.importorskip("pyopencl")
    from emdflow import opencl_backend

    real = opencl_backend.kernel_source
    token = os.urandom(4).hex()  # a program of its own (failures are remembered per source)
    monkeypatch.setattr(opencl_backend, "kernel_source",
                        lambda name: real(name) + (f"\n#error broken on purpose {token}\n" if name == "evd.cl" else ""))
    assert main(["devices", "--model", "extended"]) == 1
    captured = capsys.readouterr()
    rows = captured.out.splitlines()
    assert len(rows) == len(emdflow.opencl_devices()) and not any(row.startswith("*") for row in rows)
    assert all("fails: " in row and "error:" in row for row in rows)
    assert any(f"broken on purpose {token}" in row for row in rows)
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("emdflow devices: error: the engine cannot run (")


def test_output_mistakes_are_found_before_the_run(tmp_path, capsys, clip, backend):
    """Outputs that cannot be written, or two outputs on one file, stop a tool before its
    run (they were found after it, its results lost, or the later output overwrote the
    earlier), and so do option combinations a tool would ignore."""
    from emdflow import bench

    folder = tmp_path / "folder"
    folder.mkdir()
    video = str(tmp_path / "o.avi")
    assert main(["flow", str(clip[0]), "-o", video, "--npz", str(folder), "--backend", backend]) == 2
    _one_line_error(capsys, folder, "is a folder")
    videos = tmp_path / "d.mkv"
    videos.mkdir()
    for argv in (["flow", str(clip[0]), "-o", str(videos), "--backend", backend],
                 ["render", str(clip[0]), "-o", str(videos)]):
        assert main(argv) == 2  # (it said "OpenCV cannot write a ffv1 video here")
        _one_line_error(capsys, f"-o {videos}: is a folder")
    assert main(["flow", str(clip[0]), "-o", video, "--npz", video, "--backend", backend]) == 2
    _one_line_error(capsys, f"--npz {video}: the same file as -o {video}")
    assert not Path(video).exists()
    assert main(["eval", "--quick", "--csv", str(folder)]) == 2
    _one_line_error(capsys, folder, "is a folder")
    for label in ("dis", " "):
        assert main(["eval", "--quick", "--label", label, "--csv", str(tmp_path / "e.csv")]) == 2
        _one_line_error(capsys, "--label", "not be empty or 'dis'")
    assert main(["eval", "--quick", "--seed", "-1", "--csv", str(tmp_path / "e.csv")]) == 2  # (a traceback)
    _one_line_error(capsys, "--seed -1", "0 or more")
    if os.geteuid() != 0:  # (root writes anywhere)
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        assert main(["eval", "--quick", "--markdown", str(locked / "e.md")]) == 2
        _one_line_error(capsys, "--markdown", "is not writable")
    with pytest.raises(SystemExit):
        bench.main(["--stages", "--sizes", "64x48", "--json", str(tmp_path / "s.json")])
    assert "--json: not with --stages" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bench.main(["--sizes", "64x48", "--drift", "0.5"])
    assert "--drift: only with --stages" in capsys.readouterr().err


def test_eval_plot_needs_an_image_file_ending_and_speeds_count_once(tmp_path, capsys):
    from emdflow.cli import build_parser
    from emdflow.tools.evaluate import config_from_args

    args = build_parser().parse_args(["eval", "--speeds", "3,3.0,5", "--variants", "base,base",
                                      "--directions", "0,90,0"])
    config = config_from_args(args)
    assert config.speeds == (3.0, 5.0) and config.variants == ("base",) and config.directions == (0.0, 90.0)
    pytest.importorskip("matplotlib")
    csv_path = tmp_path / "e.csv"
    csv_path.write_text("variant,method,speed,frames\nbase,emd,3,2\n")
    assert main(["eval", "--from-csv", str(csv_path), "--plot", str(tmp_path / "p.txt")]) == 2
    _one_line_error(capsys, "--plot", "cannot write .txt files; use .png")


def test_flow_of_odd_size_keeps_every_pixel_and_snapshots_in_any_format(tmp_path, capfd, backend):
    """OpenCV's writer stores even sides only: an odd flow video is padded (it cut the last
    row and column, and said the size it was asked for); a JPEG snapshot gets no PNG
    option (OpenCV warned about it on stderr). A recording of odd size is refused: it could
    not be read back as rendered."""
    out, snap = tmp_path / "odd.avi", tmp_path / "s.jpg"
    assert main(["flow", "synthetic:frames=4,size=33x25", "-o", str(out), "--upscale", "3",
                 "--snapshot", str(snap), "--backend", backend]) == 0
    err = capfd.readouterr().err
    assert "wrote" in err and "100x76" in err and "WARN" not in err
    frames, _ = _read_video(out)
    assert len(frames) == 4 and frames[0].shape == (76, 100, 3)
    assert np.array_equal(frames[0][:, 99], frames[0][:, 98]) and cv2.imread(str(snap)).shape == (75, 99, 3)
    assert main(["render", "synthetic:frames=3,size=33x25", "-o", str(tmp_path / "r.mkv")]) == 2
    assert "33x25: a video stores even sides only" in capfd.readouterr().err
    assert not (tmp_path / "r.mkv").exists()


def test_a_cut_off_video_is_read_to_its_end_with_one_warning(tmp_path, capfd, backend):
    full = tmp_path / "full.avi"
    assert main(["render", "synthetic:frames=30,size=96x72", "-o", str(full)]) == 0
    cut = tmp_path / "cut.avi"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    capfd.readouterr()
    assert main(["frames", str(cut), "--fps", "30", "--backend", backend, "-o", str(tmp_path / "f.csv")]) == 0
    err = capfd.readouterr().err
    rows = (tmp_path / "f.csv").read_text().splitlines()[1:]
    assert 1 <= len(rows) < 28
    assert f"{cut}: the video ended after {len(rows)} of the 30 frames its container declares" in err
    assert "[ffv1" not in err


@pytest.mark.parametrize("module", ["emdflow.tools.video_io", "firmware_py.sources.video"])
def test_ffmpeg_log_is_quiet_unless_asked_for(module):
    """FFV1 decodes in worker threads that log after read() returned, past the stderr
    redirect, so FFmpeg's level is set before OpenCV's backend reads it (once, at its first
    file); a level the user set, or EMDFLOW_DEBUG, keeps FFmpeg's messages."""
    probe = f"import os, {module}; print(os.environ.get('OPENCV_FFMPEG_LOGLEVEL'))"

    def level_seen(**env):
        base = {k: v for k, v in _env().items() if k not in ("OPENCV_FFMPEG_LOGLEVEL", "EMDFLOW_DEBUG")}
        r = subprocess.run([sys.executable, "-c", probe], env={**base, **env}, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return r.stdout.strip()

    assert level_seen() == "-8"
    assert level_seen(OPENCV_FFMPEG_LOGLEVEL="24") == "24"
    assert level_seen(EMDFLOW_DEBUG="1") == "None"
