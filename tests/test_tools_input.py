"""Bad input to the tools and to CameraFlight: one clear line and exit code 2 (a ValueError
for the library), never a traceback or a hang.

A case that used to hang runs in a subprocess with a timeout, so a regression fails the
test instead of stalling the suite.
"""

import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import emdflow
from emdflow.cli import main
from emdflow.synthetic import CameraFlight, load_texture

PACKAGE_ROOT = Path(emdflow.__file__).resolve().parents[1]
SMALL = "synthetic:frames=3,size=32x24"
HANG_TIMEOUT_S = 60  # a fixed case takes a few seconds (imports); a hang never ends


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(PACKAGE_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def _emdflow(*argv, timeout=HANG_TIMEOUT_S):
    """``python -m emdflow ARGV`` in a subprocess; fails the test if it does not end."""
    try:
        return subprocess.run([sys.executable, "-m", "emdflow", *argv], env=_env(), capture_output=True,
                              text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail(f"emdflow {' '.join(argv)}: still running after {timeout} s (hang)")


def _one_line(text, *names):
    lines = text.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in text, text
    for name in names:
        assert str(name) in lines[0], lines[0]
    return lines[0]


def _usage_error(capsys, call, *names):
    """``call()`` is an argparse usage error (SystemExit 2) whose error line names ``names``."""
    with pytest.raises(SystemExit) as exc:
        call()
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("emdflow bench: error: "), err
    for name in names:
        assert name in last, last
    return last


# ------------------------------------------------------------------------ bench (defect 6)

SMALL_BENCH = ["--sizes", "32x24", "--block", "2", "--rounds", "1"]


@pytest.mark.parametrize("extra, names", [
    (["--sizes", "320"], ["--sizes", "'320'"]),
    (["--sizes", "320x240,x"], ["--sizes", "320x240,x"]),
    (["--sizes", "2x2"], ["--sizes 2x2", "8 px"]),
    (["--sizes", "7x40", "--stages"], ["--sizes 7x40", "8 px"]),
    (["--sizes", "11x11"], ["--sizes 11x11", "DIS", "12 px"]),  # DIS refuses it
    (["--delays", "a"], ["--delays", "'a'"]),
    (["--delays", "2"], ["--delays 2", "delays=(2,)"]),
    (["--evidence-row-step", "-3"], ["--evidence-row-step -3"]),
    (["--block", "0"], ["--block 0"]),
    (["--rounds", "0"], ["--rounds 0"]),
    (["--warmup", "-1"], ["--warmup -1"]),
    (["--drift", "nan", "--stages"], ["--drift nan"]),
    (["--drift", "-2", "--stages"], ["--drift -2", "> -1"]),
    # the engine's pixel limit, before minutes of rendering (it used to end in a traceback
    # after the first size's run)
    (["--sizes", "16x16,4097x4096"], ["--sizes 4097x4096", "16777216 pixels"]),
    (["--json", "/nonexistent/x.json"], ["--json /nonexistent/x.json", "does not exist"]),
])
def test_bench_bad_arguments_are_usage_errors_before_the_run(capsys, monkeypatch, extra, names):
    """Each of these used to end in a traceback (some after the whole run)."""
    from emdflow import bench

    monkeypatch.setattr(bench, "_environment", lambda *args: "test")  # (no OpenCL probe needed)
    _usage_error(capsys, lambda: main(["bench", *SMALL_BENCH, *extra]), *names)


def test_bench_output_paths_are_checked_before_the_run(tmp_path, capsys, monkeypatch):
    from emdflow import bench

    def no_run(**kw):
        raise AssertionError("the benchmark ran before its output paths were checked")

    monkeypatch.setattr(bench, "run_benchmark", no_run)
    monkeypatch.setattr(bench, "_environment", lambda *args: "test")
    for option, path, why in (("--plot", tmp_path / "b.txt", "cannot write .txt"),
                              ("--plot", tmp_path / "b", "no file ending"),
                              ("--plot", tmp_path, "is a folder"),
                              ("--json", tmp_path / "no" / "b.json", "does not exist")):
        argv = [*SMALL_BENCH, option, str(path)]
        _usage_error(capsys, lambda argv=argv: bench.main(argv), f"{option} {path}", why)


def test_bench_runtime_errors_go_through_the_commands_handlers(monkeypatch, capsys):
    """``emdflow bench`` ends like the other subcommands: a failed write after the run is
    one line naming the file (exit 2), Ctrl-C exit 130."""
    from emdflow import bench

    fake = {(32, 24): {name: 1.0 for name in ("opencl", "opencl-dense", "opencl+summary", "numpy", "dis", "blur")}}
    monkeypatch.setattr(bench, "_environment", lambda *args: "test")
    monkeypatch.setattr(bench, "run_benchmark", lambda **kw: fake)
    if Path("/dev/full").exists():
        assert main(["bench", *SMALL_BENCH, "--json", "/dev/full"]) == 2
        _one_line(capsys.readouterr().err, "emdflow bench: error: /dev/full")

    def interrupted(**kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(bench, "run_benchmark", interrupted)
    try:
        code = main(["bench", *SMALL_BENCH])
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C in emdflow bench was not handled")
    assert code == 130
    assert capsys.readouterr().err.strip().endswith("emdflow bench: interrupted")


def test_bench_smallest_sizes_run(tmp_path, capsys):
    """The limits are the renderer's (8 px a side) and, for the timing table, DIS's (one
    side of 12 px): 12x8 and 8x12 are timed, 8x8 profiled."""
    pytest.importorskip("pyopencl")
    from emdflow import bench

    out = tmp_path / "b.json"
    assert bench.main(["--sizes", "12x8,8x12", "--block", "2", "--rounds", "1", "--json", str(out)]) == 0
    assert set(json.loads(out.read_text())) == {"12x8", "8x12"}
    assert bench.main(["--stages", "--sizes", "8x8"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("8x8")


# --------------------------------------------------------- CameraFlight, synthetic: (defect 7)

NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("kwargs, name", [
    (dict(flow=(NAN, 1.0)), "flow"),
    (dict(flow=(1.0, -INF)), "flow"),
    (dict(noise_sigma=NAN), "noise_sigma"),
    (dict(contrast=INF), "contrast"),
    (dict(exposure_drift=NAN), "exposure_drift"),
    (dict(expansion_rate=NAN), "expansion_rate"),
    (dict(expansion_rate=-1.0), "expansion_rate"),
    (dict(expansion_rate=-3.0), "expansion_rate"),
    (dict(ground_scale=0.0), "ground_scale"),
    (dict(ground_scale=INF), "ground_scale"),
    (dict(start=(NAN, 10.0)), "start"),
    (dict(shade=0.0), "shade"),
    (dict(shade=1.5), "shade"),
    (dict(shade=NAN), "shade"),
])
def test_camera_flight_rejects_what_it_cannot_render(kwargs, name):
    """NaN or infinity reached cv2.warpAffine, which never returned; expansion_rate -1
    divided by zero."""
    with pytest.raises(ValueError, match=name):
        CameraFlight("gravel", width=32, height=24, **kwargs)


def test_camera_flight_shades_the_right_half_of_the_view():
    """``shade`` multiplies the right half's light: its brightness and contrast drop by the
    same factor; the left half is the flight's own."""
    lit = CameraFlight("gravel", width=64, height=48, noise_sigma=0).render(3).astype(float)
    shaded = CameraFlight("gravel", width=64, height=48, noise_sigma=0, shade=0.25).render(3).astype(float)
    assert np.array_equal(lit[:, :32], shaded[:, :32])
    assert np.abs(shaded[:, 32:] - 0.25 * lit[:, 32:]).max() <= 0.5  # (rounded to gray levels)
    assert shaded[:, 32:].std() < 0.3 * lit[:, 32:].std()


_FAR_FLIGHTS = textwrap.dedent("""
    import json, sys
    import numpy as np
    from emdflow.synthetic import CameraFlight, load_texture

    th, tw = load_texture("gravel").shape
    period = 2 * (tw - 1)  # the reflected ground repeats every 2 (n - 1) px
    near = CameraFlight("gravel", width=48, height=32, flow=(0, 0), start=(100.3, 200.7), noise_sigma=0).render(0)
    out = {}
    for k in (3, 40, 10**6, 10**9):
        far = CameraFlight("gravel", width=48, height=32, flow=(0, 0), noise_sigma=0,
                           start=(100.3 + k * period, 200.7 - k * period)).render(0)
        out[k] = int(np.abs(far.astype(int) - near).max())
    CameraFlight("gravel", width=48, height=32, flow=(1e9, -1e12)).render(5)
    receding = CameraFlight("gravel", width=48, height=32, expansion_rate=-0.5)
    try:
        for t in range(40):
            receding.render(t)
        out["receding"] = "rendered"
    except ValueError as e:
        out["receding"] = str(e)
    print(json.dumps(out))
""")


def test_far_and_receding_flights_end():
    """Far from the texture, cv2.warpAffine took time in proportion to the distance (hours
    for a flow of 1e9 px/frame) and a receding zoom flight's view grew without bound: far
    flights now render the same ground as near ones at once (to rounding), a zoom flight
    whose view would be hundreds of textures wide is a ValueError naming the frame."""
    try:
        r = subprocess.run([sys.executable, "-c", _FAR_FLIGHTS], env=_env(), capture_output=True, text=True,
                           timeout=HANG_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail(f"rendering far or receding flights still running after {HANG_TIMEOUT_S} s (hang)")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert all(out[str(k)] <= 1 for k in (3, 40, 10**6, 10**9)), out
    assert out["receding"].startswith("frame ") and "ground px per image px" in out["receding"], out


@pytest.mark.parametrize("uri, names", [
    ("synthetic:u=nan,frames=5", ["u", "'nan'", "finite"]),
    ("synthetic:v=-inf,frames=5", ["v", "'-inf'", "finite"]),
    ("synthetic:zoom=nan,frames=5", ["zoom", "finite"]),
    ("synthetic:noise=inf,frames=5", ["noise", "finite"]),
    ("synthetic:fps=nan,frames=5", ["fps", "finite"]),
    ("synthetic:frames=5,zoom=-1", ["zoom=-1", "> -1"]),
    ("synthetic:frames=5,noise=-5", ["noise=-5", "0 or more"]),                  # taken as no noise
    ("synthetic:frames=100000000000000000000", ["frames=100000000000000000000", "at most"]),  # OverflowError
])
def test_synthetic_input_rejects_what_it_cannot_render(uri, names):
    from emdflow.tools.video_io import InputError, parse_synthetic

    with pytest.raises(InputError) as exc:
        parse_synthetic(uri)
    _one_line(str(exc.value), uri, *names)


@pytest.mark.parametrize("uri, names", [
    ("synthetic:u=nan,frames=5,size=32x24", ["u", "finite"]),                    # used to hang
    ("synthetic:frames=5,zoom=-1,size=32x24", ["zoom=-1"]),                      # ZeroDivisionError
    ("synthetic:frames=40,zoom=-0.5,size=64x48", ["frame ", "ground px"]),        # hung at frame ~20
])
def test_frames_on_a_bad_synthetic_input_is_one_line(uri, names):
    r = _emdflow("frames", uri, "--backend", "numpy")
    assert r.returncode == 2, r.stderr
    _one_line(r.stderr, "emdflow frames: error: ", uri, *names)


@pytest.mark.parametrize("option, value", [("--speeds", "nan"), ("--speeds", "1,inf"), ("--directions", "0,nan")])
def test_eval_rejects_non_finite_speeds_and_directions(tmp_path, option, value):
    """``float()`` takes nan and inf: the flights used to hang in cv2.warpAffine."""
    r = _emdflow("eval", option, value, "--quick", "--no-dis", "--frames", "1", "--repeats", "1",
                 "--backend", "numpy", "--csv", str(tmp_path / "e.csv"), "--plot", "", "-q")
    assert r.returncode == 2, r.stderr
    _one_line(r.stderr, "emdflow eval: error: ", option, "finite")
    assert not (tmp_path / "e.csv").exists()


# ----------------------------------------------------------------- eval --size (defect 8)

EVAL_SMALL = ["--quick", "--speeds", "1", "--directions", "0", "--variants", "base", "--frames", "1",
              "--repeats", "1", "--backend", "numpy", "--plot", "", "-q"]


@pytest.mark.parametrize("size, dis, names", [
    ("5x5", False, ["--size 5x5", "at least 8 px"]),
    ("7x300", False, ["--size 7x300", "at least 8 px"]),
    ("9x9", True, ["--size 9x9", "DIS", "12 px", "--no-dis"]),
    ("11x8", True, ["--size 11x8", "DIS"]),
])
def test_eval_size_below_the_renderers_or_dis_minimum(tmp_path, capsys, size, dis, names):
    argv = ["eval", "--size", size, *EVAL_SMALL, "--csv", str(tmp_path / "e.csv")] + ([] if dis else ["--no-dis"])
    assert main(argv) == 2
    _one_line(capsys.readouterr().err, "emdflow eval: error: ", *names)


def test_eval_smallest_sizes_run(tmp_path, capsys):
    """8x8 without DIS, 12x8 with it: the smallest sizes accepted do run."""
    for size, extra in (("8x8", ["--no-dis"]), ("12x8", [])):
        csv = tmp_path / f"{size}.csv"
        assert main(["eval", "--size", size, *EVAL_SMALL, "--csv", str(csv), *extra]) == 0, capsys.readouterr().err
        assert csv.exists()


# ------------------------------------------------------------ flow, frames (defects 9, 10)


@pytest.mark.parametrize("argv, names", [
    (["flow", SMALL, "-o", "{tmp}/o.avi", "--max-flow", "nan"], ["--max-flow nan"]),
    (["flow", SMALL, "-o", "{tmp}/o.avi", "--max-flow", "inf"], ["--max-flow inf"]),
    (["flow", SMALL, "-o", "{tmp}/o.avi", "--snapshot", "{tmp}/shot.txt"], ["--snapshot", "shot.txt", ".png"]),
    (["flow", SMALL, "-o", "{tmp}/o.avi", "--snapshot", "{tmp}/shot"], ["--snapshot", "shot", ".png"]),
    (["flow", SMALL, "-o", "{tmp}/o.avi", "--fps", "nan"], ["--fps nan"]),
    (["frames", SMALL, "--fps", "nan"], ["--fps nan"]),
    (["frames", SMALL, "--fps", "inf"], ["--fps inf"]),
    (["frames", SMALL, "--focal-length-px", "nan"], ["--focal-length-px nan"]),
    (["frames", SMALL, "--focal-length-px=-inf"], ["--focal-length-px -inf"]),
])
def test_flow_and_frames_reject_non_finite_options_up_front(tmp_path, capsys, argv, names):
    """NaN passed the "<= 0" checks (and crashed later or wrote NaN times); a snapshot
    OpenCV cannot write failed only after the whole video."""
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main([*argv, "--backend", "numpy", "-q"]) == 2
    _one_line(capsys.readouterr().err, f"emdflow {argv[0]}: error: ", *names)
    assert not (tmp_path / "o.avi").exists()  # nothing processed


def test_snapshot_in_another_image_type_still_works(tmp_path):
    shot = tmp_path / "shot.jpg"
    assert main(["flow", SMALL, "-o", str(tmp_path / "o.avi"), "--snapshot", str(shot), "--backend", "numpy",
                 "-q"]) == 0
    assert shot.read_bytes()[:2] == b"\xff\xd8"


def test_finite_inputs_still_render_as_before():
    """The checks leave ordinary flights alone: a near flight renders bit for bit as with
    the parameters given as ints, and a zoom flight's truth is unchanged."""
    a = CameraFlight("gravel", width=32, height=24, flow=(2, -1), expansion_rate=0.01, seed=3)
    b = CameraFlight("gravel", width=32, height=24, flow=(2.0, -1.0), expansion_rate=0.01, seed=3)
    assert (a.render(7) == b.render(7)).all()
    assert a.flow == (2.0, -1.0) and math.isclose(a.truth(3).expansion_rate, 0.01)
    th, tw = load_texture("gravel").shape
    assert a.start == (tw / 2.0, th / 2.0)
