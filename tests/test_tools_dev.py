"""The developer tools (``python -m emdflow.tools.zoom_eval``, ``calibrate_summary``,
``rotation_eval``) refuse bad options and unwritable outputs up front: one line naming the
option, exit code 2, no traceback, and no flight flown (the tools' long-running functions
are replaced by stand-ins that fail the test when reached)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest


def _never(*args, **kwargs):
    raise AssertionError("the run started although an option was bad")


def _refused(main, argv, capsys, option: str) -> str:
    """Run ``main(argv)``: it must stop with exit code 2 and a message naming ``option``."""
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, (argv, code, err)
    assert option in err, (argv, err)
    assert "Traceback" not in err
    return err


# ---- zoom_eval ----------------------------------------------------------------------------
ZOOM = ["--models", "paper", "--textures", "gravel", "--translations", "0,0", "--frames", "1",
        "--rates", "0.01", "--flights", "1"]


@pytest.mark.parametrize("extra, option", [
    (["--textures", "nope"], "--textures"),
    (["--textures", ","], "--textures"),
    (["--rates", "nan"], "--rates"),
    (["--rates", "0"], "--rates"),
    (["--seed", "-1"], "--seed"),
    (["--models", ","], "--models"),
    (["--flights", "0"], "--flights"),
    (["--flights", "-1"], "--flights"),
    (["--frames", "0"], "--frames"),
    # a receding flight whose last frame cannot be rendered (a traceback mid-run before)
    (["--rates=-0.5", "--frames", "8"], "--rates -0.5 over gravel (8 frames): frame 10:"),
])
def test_zoom_eval_refuses_bad_options(monkeypatch, capsys, extra, option):
    from emdflow.tools import zoom_eval

    monkeypatch.setattr(zoom_eval, "evaluate", _never)
    monkeypatch.setattr(zoom_eval, "calibrate", _never)
    _refused(zoom_eval.main, ZOOM + extra, capsys, option)


@pytest.mark.parametrize("extra, option", [(["--flights", "0"], "--flights"), (["--seed", "-1"], "--seed")])
def test_zoom_eval_calibrate_refuses_bad_options(monkeypatch, capsys, extra, option):
    from emdflow.tools import zoom_eval

    monkeypatch.setattr(zoom_eval, "calibrate", _never)
    _refused(zoom_eval.main, ["calibrate", "--models", "paper"] + extra, capsys, option)


def test_zoom_eval_passes_the_flights_given(monkeypatch, capsys):
    """``--flights`` is used as given (``a.flights or 6`` used to fly 6 for 0)."""
    from emdflow.tools import zoom_eval

    seen = {}

    def evaluate(**kwargs):
        seen.update(kwargs)
        return {"_times": []}

    monkeypatch.setattr(zoom_eval, "evaluate", evaluate)
    monkeypatch.setattr(zoom_eval, "format_report", lambda results: "")
    assert zoom_eval.main(ZOOM[:-1] + ["3"]) == 0
    assert seen["flights"] == 3
    assert zoom_eval.main(ZOOM[:-2]) == 0
    assert seen["flights"] == 6


def test_zoom_eval_bad_option_in_a_subprocess_has_no_traceback():
    run = subprocess.run([sys.executable, "-m", "emdflow.tools.zoom_eval", *ZOOM, "--textures", "nope"],
                         check=False, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    assert "--textures" in run.stderr and "Traceback" not in run.stderr


# ---- rotation_eval ------------------------------------------------------------------------
@pytest.mark.parametrize("textures", ["", ","])
def test_rotation_eval_refuses_no_ground(monkeypatch, capsys, textures):
    """``--textures ""`` used to print an empty table with exit code 0."""
    from emdflow.tools import rotation_eval

    monkeypatch.setattr(rotation_eval, "evaluate", _never)
    err = _refused(rotation_eval.main, ["--size", "96x72", "--frames", "1", "--fovs", "60",
                                        "--textures", textures], capsys, "--textures")
    assert "name at least one ground" in err


# ---- calibrate_summary --------------------------------------------------------------------
@pytest.fixture
def cs(monkeypatch):
    from emdflow.tools import calibrate_summary

    for name in ("collect", "fit_main", "write_misfit", "margin_sweep", "render_evaluation", "score"):
        monkeypatch.setattr(calibrate_summary, name, _never)
    return calibrate_summary


@pytest.mark.parametrize("argv, option", [
    (["collect", "--scale-range", "abc"], "--scale-range"),
    (["collect", "--scale-range", "0,1"], "--scale-range"),
    (["collect", "--contrast-range", "x"], "--contrast-range"),
    (["collect", "--seed", "-1"], "--seed"),
    (["collect", "--flights", "0"], "--flights"),
    (["collect", "--frames", "0"], "--frames"),
    (["collect", "--frames", "3"], "--frames"),  # the paper model's flights: no ready frame
    (["fit", "no-such-file.npz"], "no-such-file.npz"),
    (["misfit", "no-such-file.npz"], "no-such-file.npz"),
    (["margin", "no-such-file.npz"], "no-such-file.npz"),
    (["evaluate", "--data", "no-such-file.npz"], "--data"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--frames", "0"], "--frames"),
    (["evaluate", "--size", "4x4", "--textures", "gravel", "--frames", "1"], "--size"),
    # (tracebacks from EngineParams or the renderer before, or garbage flown)
    (["collect", "--evidence-row-step", "-1"], "--evidence-row-step -1"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--evidence-row-step", "5000"], "--evidence-row-step"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--offset", "nan"], "--offset nan"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--contrast", "-1"], "--contrast -1"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--contrast", "inf"], "--contrast inf"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--drift", "-5"], "--drift -5"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--engine-opt", "thresh=8"], "--engine-opt"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--engine-opt", "prefilter_size=4"],
     "prefilter_size=4"),
    (["evaluate", "--size", "96x72", "--textures", "gravel", "--engine-opt", "sharp_templates=maybe"],
     "'maybe' is not a value for sharp_templates"),
])
def test_calibrate_summary_refuses_bad_options(cs, tmp_path, capsys, argv, option):
    if argv[0] == "collect":
        argv = argv + ["--out", str(tmp_path / "c.npz")]
    _refused(cs.main, argv, capsys, option)
    assert not (tmp_path / "c.npz").exists()


@pytest.mark.parametrize("content, problem", [
    (b"", "not a NumPy .npz archive"),
    (b"hist,flow\n1,2\n", "not a NumPy .npz archive"),
    ("one array", "one NumPy array, not an .npz archive"),
    ("no flow", "no 'stats' or 'flow' array in it"),
    ("no frames", "no frames in it"),  # (an IndexError at the first frame before)
    ("0-d flow", "no frames in it"),
    # (an IndexError traceback, or a mismatch deep inside the fit, before)
    ("1-D hist", "its 'hist' array has shape (10,): expected one (2 or 4 axes"),
    ("hist short", "its 'hist' array has shape (2, 2, 2, 64): expected one (2 or 4 axes, signed channels, "
                   "bins) histogram per frame of its 'flow' (3 frames)"),
    ("3 axes", "its 'hist' array has shape (3, 3, 2, 64)"),
    ("stats short", "its 'stats' array has shape (2, 8): expected one row per frame of its 'flow' (3 frames)"),
    ("stats narrow", "its 'stats' rows hold 5 counts: the engine's 8 for the 1 channels of its 'hist'"),
])
@pytest.mark.parametrize("command", ["fit", "misfit", "margin", "evaluate"])
def test_calibrate_summary_names_a_file_that_holds_no_flights(cs, tmp_path, capsys, command, content, problem):
    """An empty, foreign or incomplete data file is one line naming it (it was a zipfile
    or EOFError traceback from deep inside the command)."""
    path = tmp_path / "flights.npz"
    if content == "one array":
        with open(path, "wb") as f:
            np.save(f, np.zeros(3))
    elif content == "no flow":
        np.savez(path, hist=np.zeros((1, 2, 2, 64)))
    elif content == "0-d flow":
        np.savez(path, hist=np.zeros((1, 2, 2, 64)), stats=np.zeros((1, 9)), flow=np.array(1.0),
                 shape=np.array([72, 96]), frame_index=np.array(20))
    elif content == "no frames":
        np.savez(path, hist=np.zeros((0, 2, 2, 64)), stats=np.zeros((0, 9)), flow=np.zeros((0, 2)),
                 shape=np.array([72, 96]), frame_index=np.array(20))
    elif content in ("1-D hist", "hist short", "3 axes", "stats short", "stats narrow"):
        hist = {"1-D hist": (10,), "hist short": (2, 2, 2, 64), "3 axes": (3, 3, 2, 64)}.get(content, (3, 2, 2, 64))
        stats = {"stats short": (2, 8), "stats narrow": (3, 5)}.get(content, (3, 8))
        np.savez(path, hist=np.zeros(hist), stats=np.zeros(stats), flow=np.ones((3, 2)), shape=np.array([72, 96]),
                 frame_index=np.arange(3))
    else:
        path.write_bytes(content)
    argv = [command, "--data", str(path)] if command == "evaluate" else [command, str(path)]
    _refused(cs.main, argv, capsys, f"{path}: {problem}")


@pytest.mark.parametrize("command", ["margin", "evaluate"])
def test_calibrate_summary_names_collected_flights_it_cannot_summarise_again(cs, tmp_path, capsys, command):
    """collect --out stores no frame size: evaluate --data and margin, which summarise the
    frames again, say so (a KeyError traceback before); fit takes such a file."""
    path = tmp_path / "collected.npz"
    np.savez(path, hist=np.zeros((3, 2, 2, 64)), stats=np.zeros((3, 8)), flow=np.ones((3, 2)))
    argv = [command, "--data", str(path)] if command == "evaluate" else [command, str(path)]
    err = _refused(cs.main, argv, capsys, f"{path}: no 'shape' or 'frame_index' array in it")
    assert "only evaluate --save stores what summarising again needs" in err


@pytest.mark.parametrize("command", ["fit", "misfit"])
def test_calibrate_summary_refuses_flights_of_another_model(cs, tmp_path, capsys, command):
    """fit and misfit --model extended on the paper model's flights: one line naming the
    file and both models, before any table is looked for or fitted."""
    path = tmp_path / "paper.npz"
    np.savez(path, hist=np.zeros((3, 4, 14, 64)), stats=np.zeros((3, 14)), flow=np.ones((3, 2)),
             model=np.array("paper"))
    _refused(cs.main, [command, "--model", "extended", str(path)], capsys,
             f"data {path}: flights of the paper model, not --model extended")


def test_calibrate_summary_misfit_needs_the_table_it_adds_to(cs, monkeypatch, tmp_path, capsys):
    """misfit adds a baseline to a table fit --write made: without one (the paper model's
    line-ground table, which nobody has fitted), one line naming it and the command that
    makes it (a FileNotFoundError traceback before)."""
    path = tmp_path / "paper.npz"
    np.savez(path, hist=np.zeros((3, 4, 14, 64)), stats=np.zeros((3, 14)), flow=np.ones((3, 2)),
             model=np.array("paper"))
    missing = tmp_path / "summary_calibration_lines_diagonal.npz"
    monkeypatch.setattr(cs, "calibration_path", lambda *args, **kwargs: missing)
    err = _refused(cs.main, ["misfit", "--ground", "lines", str(path)], capsys,
                   f"misfit --model paper --ground lines: no table {missing.name} to add the baseline to")
    assert "fit --write --model paper --ground lines makes it" in err


def test_calibrate_summary_fit_names_too_few_flights(monkeypatch, tmp_path):
    """Two flights leave most of the table's cells empty: the fit stops with a line that
    says so and how many frames it had (a RuntimeError traceback from deep inside it
    before), and writes nothing."""
    from emdflow.tools import calibrate_summary as cs

    table = tmp_path / "table.npz"  # (never the package's own table)
    monkeypatch.setattr(cs, "calibration_path", lambda *args, **kwargs: table)
    out = tmp_path / "few.npz"
    cs.collect(2, str(out), frames=4, width=64, height=48, textures=("moon",))
    with pytest.raises(SystemExit) as stop:
        cs.main(["fit", str(out), "--write"])
    assert not table.exists()
    message = str(stop.value.code)
    assert "contrast class 0: no calibration data at ψ node" in message
    assert "2 frames are too few to fit a table (the committed edge table's recipe collects 9 000 flights" in message


@pytest.mark.parametrize("argv, option", [
    (["collect", "--flights", "1", "--frames", "5", "--out"], "--out"),
    (["evaluate", "--size", "96x72", "--frames", "1", "--textures", "gravel", "--save"], "--save"),
])
def test_calibrate_summary_checks_outputs_before_the_run(cs, tmp_path, capsys, argv, option):
    for bad in (tmp_path / "missing" / "x.npz", tmp_path):  # no such folder; a folder
        _refused(cs.main, argv + [str(bad)], capsys, option)


def test_calibrate_summary_writes_exactly_the_path_given(monkeypatch, tmp_path, capsys):
    """An output without ``.npz`` is written under that name (numpy used to append .npz
    while the tool printed the name without it, so ``fit`` on that name failed)."""
    from emdflow.tools import calibrate_summary as cs

    out = tmp_path / "flights.dat"
    cs.collect(1, str(out), frames=4, width=64, height=48, textures=("moon",))
    assert out.is_file() and not (tmp_path / "flights.dat.npz").exists()
    assert str(out) in capsys.readouterr().err
    with np.load(out) as d:
        assert len(d["flow"]) == 1

    flights = {"flow": np.zeros((2, 2)), "hist": np.zeros((2, 1), np.int32)}
    monkeypatch.setattr(cs, "render_evaluation", lambda *args, **kwargs: flights)
    monkeypatch.setattr(cs, "score", lambda *args, **kwargs: None)
    saved = tmp_path / "evaluation.dat"
    cs.evaluate(0.3, save=str(saved), textures=("gravel",))
    assert saved.is_file() and not (tmp_path / "evaluation.dat.npz").exists()
    with np.load(saved) as d:
        assert d["flow"].shape == (2, 2)


@pytest.mark.parametrize("argv, option", [
    (["--frames", "0"], "--frames"),
    (["--shade", "0"], "--shade"),
    (["--shade", "2"], "--shade"),
    (["--speeds", "1,nan"], "--speeds"),
    (["--speeds", "-1"], "--speeds"),
    (["--textures", "nosuchground"], "--textures"),
    (["--textures", ","], "--textures"),
    (["--modes", "tiles"], "--modes"),
])
def test_shade_eval_refuses_bad_options(monkeypatch, capsys, argv, option):
    from emdflow.tools import shade_eval

    monkeypatch.setattr(shade_eval, "evaluate", _never)
    _refused(shade_eval.main, argv, capsys, option)


def test_shade_eval_measures_both_halves_and_the_balance():
    """The tool's rows: one per mode and speed, the local threshold seeing more of the
    shaded half than the frame's one threshold does, and a table line per row."""
    from emdflow.tools import shade_eval

    rows = shade_eval.evaluate(speeds=(1.0,), textures=("gravel",), frames=3)
    assert [(r["mode"], r["speed"]) for r in rows] == [("adaptive", 1.0), ("local", 1.0)]
    adaptive, local = rows
    for r in rows:
        assert 0 < r["density_shaded"] < r["density_lit"] < 1 and -1 <= r["balance_lr"] <= 1
    assert local["density_shaded"] / local["density_lit"] > 1.5 * adaptive["density_shaded"] / adaptive["density_lit"]
    report = shade_eval.format_report(rows)
    assert report.count("\n| adaptive | 1 |") == 1 and report.count("\n| local | 1 |") == 1
