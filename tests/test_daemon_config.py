"""Configuration: the example file, errors that name key and file, flag overrides."""

from __future__ import annotations

import csv
import os
import sys
import dataclasses
import math
import re

import pytest

from firmware_py.cli import _apply_flags, build_parser
from firmware_py.config import SECTIONS, Config, ConfigError, load_config
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # shared helpers
from daemon_util import REPO, Drain, PtyPair, engine_backend, parse_msp_v2, run_cli  # noqa: E402

EXAMPLE = REPO / "deploy" / "emdflow.toml"


def test_example_config_loads_and_lists_every_key():
    config = load_config(EXAMPLE)
    assert config.source.uri == "v4l2:/dev/video0"
    assert config.link.port == "/dev/serial0"
    # its camera has no lens given: one must be set (it shipped a 60° lens's 277 px active,
    # which switched that check off for whoever only edited the uri and the port)
    with pytest.raises(ConfigError, match="is a camera: give"):
        config.focal_length_px(320, None)
    text = EXAMPLE.read_text()
    for section, cls in SECTIONS.items():
        assert re.search(rf"^\[{section}\]", text, re.M), section
        body = text.split(f"[{section}]", 1)[1].split("\n[", 1)[0]
        for field in dataclasses.fields(cls):
            # present as a key, or as a commented-out example of one
            assert re.search(rf"^#?\s*{field.name}\s*=", body, re.M), f"[{section}] {field.name} undocumented"


def _write(tmp_path, text):
    path = tmp_path / "emdflow.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, needle", [
    ("[link]\nbaudrate = 9600\n", "unknown key [link] baudrate"),
    ("[camera]\nuri = 'x'\n", "unknown section [camera]"),
    ("[link]\nbaud = 'fast'\n", "[link] baud = 'fast': expected an integer"),
    ("[link]\nbaud = 300\n", "[link] baud = 300: must be >= 1200"),
    # (PX4 reads a distance of 0 as a real 0 m range)
    ("[link]\nground_distance_m = 0\n", "[link] ground_distance_m = 0.0: must be >= 0.01 (0 m would go out"),
    # (3 Hz was the floor: ArduPilot's EKF3 and INAV stop using flow older than 200 ms)
    ("[link]\nmessage_rate_hz = 6\n", ("[link] message_rate_hz = 6.0: must be >= 7.0 (ArduPilot's EKF3 uses "
                                      "optical flow only while its newest sample is < 200 ms old, and INAV "
                                      "drops an MSP flow sensor after 200 ms without an update)")),
    # (DepthAI raised TypeError on such an ISO at every open, and the camera was retried forever)
    ("[source]\ngain = 1e12\n", "[source] gain = 1000000000000.0: must be <= 1000000.0"),
    ("[link]\nautopilot = 'betaflight'\n", "[link] autopilot = 'betaflight': expected one of"),
    ("[engine]\nbackend = 'cuda'\n", "[engine] backend = 'cuda'"),
    ("[optics]\nmounting_rotation_deg = 45\n", "[optics] mounting_rotation_deg = 45"),
    ("[source]\nloop = 1\n", "[source] loop = 1: expected true or false"),
    ("[source]\nuri = 'usb:/dev/video0'\n", "[source] uri"),
    ("[source]\nuri = 'synthetic:speed=3'\n", "synthetic option 'speed=3'"),
    ("[source]\nwidth = 320\n", "width and height must be given together"),
    ("[daemon]\nreopen_backoff_s = 5.0\nreopen_backoff_max_s = 1.0\n", "reopen_backoff_max_s"),
    ("[link\nport = 1\n", "not valid TOML"),
    ("port = '/dev/ttyS0'\n", "key port is outside every section; keys belong under a [section] header "
                              "(e.g. [link] port)"),
    ("speed = 3\n", "key speed is outside every section"),
    ("[optics]\nfocal_length_px = 300.0\nhorizontal_fov_deg = 60.0\n",
     "focal_length_px and horizontal_fov_deg both given"),
    ("[link]\nautopilot = 'px4'\nprotocol = 'msp'\n", "PX4 takes optical flow over mavlink only"),
    ("[link]\nautopilot = 'inav'\nprotocol = 'mavlink'\n", "INAV takes optical flow over msp only"),
    ("[link]\nautopilot = 'both'\nprotocol = 'msp'\n", "over mavlink only"),
])
def test_bad_config_names_file_and_key(tmp_path, text, needle):
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)
    assert needle in str(info.value)


def test_a_too_high_message_rate_is_not_given_the_minimums_reason(tmp_path):
    """The reason for message_rate_hz's minimum (the autopilots' 200 ms) was appended to the
    too-high error as well, where it explains nothing."""
    with pytest.raises(ConfigError) as info:
        load_config(_write(tmp_path, "[link]\nmessage_rate_hz = 5000\n"))
    assert str(info.value).endswith("[link] message_rate_hz = 5000.0: must be <= 1000.0")


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="nope.toml: configuration file not found"):
        load_config(tmp_path / "nope.toml")


def test_a_byte_order_mark_is_not_part_of_the_configuration(tmp_path):
    """Notepad saves UTF-8 with a byte order mark; tomllib called it an invalid statement at
    line 1. The file means what follows it."""
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf[link]\nbaud = 57600\n")
    assert load_config(path).link.baud == 57600


def test_unreadable_files_are_config_errors_that_name_the_file(tmp_path):
    latin1 = tmp_path / "latin1.toml"  # a "°" saved by a Latin-1 editor
    latin1.write_bytes(b"# horizontal field of view 71.9\xb0\n[source]\nuri = 'synthetic:'\n")
    with pytest.raises(ConfigError, match=r"latin1.toml: not UTF-8 text \(byte 0xb0 at offset 31\)"):
        load_config(latin1)
    folder = tmp_path / "conf.toml"
    folder.mkdir()
    with pytest.raises(ConfigError, match="conf.toml: is a directory"):
        load_config(folder)
    # ... and the daemon exits 2 with that line (systemd does not restart it), no traceback
    for path, needle in ((latin1, "not UTF-8 text"), (folder, "is a directory")):
        result = run_cli(["--config", path, "--serial", "/dev/null"], timeout=60)
        assert result.returncode == 2, result.stderr[-2000:]
        assert f"{path}: {needle}" in result.stderr and "Traceback" not in result.stderr


def test_msp_counts_per_degree_is_a_link_key(tmp_path):
    config = load_config(_write(tmp_path, "[link]\nautopilot = 'inav'\nmsp_counts_per_degree = 21\n"))
    assert config.link.msp_counts_per_degree == 21.0
    assert Config().link.msp_counts_per_degree == 10.5          # INAV's default opflow_scale
    with pytest.raises(ConfigError, match=r"\[link\] msp_counts_per_degree = 0.0: must be >= 0.1"):
        load_config(_write(tmp_path, "[link]\nmsp_counts_per_degree = 0\n"))


def test_msp_report_delay_ms_is_a_link_key(tmp_path):
    """How long after its frame's capture an MSP report goes out: unset (automatic) by
    default, a fixed delay or 0 (as soon as processed) when set, at most 50 ms."""
    from firmware_py.daemon import link_config
    from firmware_py.links import open_link

    assert Config().link.msp_report_delay_ms is None
    for text, fixed_us in (("8", 8000), ("0", 0), ("2.5", 2500)):
        config = load_config(_write(tmp_path, f"[link]\nautopilot = 'inav'\nmsp_report_delay_ms = {text}\n"))
        link = open_link(link_config(config, 400.0))
        try:
            assert link.pacer.fixed_us == fixed_us
        finally:
            link.close()
    with pytest.raises(ConfigError, match=r"\[link\] msp_report_delay_ms = 60.0: must be <= 50"):
        load_config(_write(tmp_path, "[link]\nmsp_report_delay_ms = 60\n"))
    with pytest.raises(ConfigError, match=r"\[link\] msp_report_delay_ms = -1.0: must be >= 0"):
        load_config(_write(tmp_path, "[link]\nmsp_report_delay_ms = -1\n"))


def test_msp_counts_per_degree_reaches_the_wire(tmp_path):
    """The daemon's link sends -21 counts per degree when told (it must equal INAV's opflow_scale)."""
    log_path = tmp_path / "sent.csv"
    path = _write(tmp_path, f'[source]\nuri = "synthetic:u=2,v=1"\nwidth = 96\nheight = 72\n'
                            f'[engine]\nbackend = "{engine_backend()}"\nmodel = "paper"\n'
                            f'[link]\nautopilot = "inav"\nbaud = 921600\nmsp_counts_per_degree = 21.0\n'
                            f'message_log = "{log_path}"\n')
    pty = PtyPair()
    drain = Drain(pty.master)
    try:
        result = run_cli(["--config", path, "--serial", pty.path, "--frames", 40])
    finally:
        data = drain.stop()
        pty.close()
    assert result.returncode == 0, result.stderr[-3000:]
    with open(log_path, newline="") as f:
        rows = [r for r in csv.DictReader(f)
                if r["message"] == "MSP2_SENSOR_OPTIC_FLOW" and int(r["quality"]) > 0]
    assert len(rows) >= 10
    for axis in ("x", "y"):  # remainder carried from message to message: the sums agree within 1
        counts = sum(int(r[f"motion_{axis}"]) for r in rows)
        degrees = sum(math.degrees(float(r[f"integrated_{axis}"])) for r in rows)
        assert abs(degrees) > 1.0 and counts == pytest.approx(-21.0 * degrees, abs=1.0)
    on_wire = [p for fn, p in parse_msp_v2(data) if fn == 0x1F02 and p[0] > 0]
    assert ([int.from_bytes(p[5:9], "little", signed=True) for p in on_wire]
            == [int(r["motion_y"]) for r in rows])


def test_values_are_normalised_and_typed(tmp_path):
    path = _write(tmp_path, "[source]\npixel_format = 'yuyv'\nfps = 30\n[link]\nautopilot = 'PX4'\n")
    config = load_config(path)
    assert config.source.pixel_format == "YUYV"
    assert config.source.fps == 30.0 and isinstance(config.source.fps, float)
    assert config.link.autopilot == "px4"


def test_flags_override_file_and_are_validated(tmp_path):
    path = _write(tmp_path, "[source]\nuri = 'synthetic:'\n[link]\nport = '/dev/ttyS0'\nbaud = 57600\n")
    parser = build_parser()
    config = load_config(path)
    args = parser.parse_args(["--serial", "/dev/ttyUSB1", "--baud", "921600", "--autopilot", "px4",
                              "--focal-length-px", "300", "--frames", "5", "--realtime",
                              "--source", "video:/tmp/x.avi"])
    _apply_flags(config, args)
    assert (config.link.port, config.link.baud, config.link.autopilot) == ("/dev/ttyUSB1", 921600, "px4")
    assert config.optics.focal_length_px == 300.0
    assert config.frames == 5 and config.source.realtime
    assert config.source.uri == "video:/tmp/x.avi"
    with pytest.raises(ConfigError, match=r"command line: \[link\] baud = 10"):
        _apply_flags(load_config(path), parser.parse_args(["--baud", "10"]))
    with pytest.raises(ConfigError, match="command line: \\[source\\] uri"):
        _apply_flags(load_config(path), parser.parse_args(["--source", "webcam"]))


def test_focal_length_resolution():
    config = Config()
    assert config.focal_length_px(320, 320.0) == 320.0            # source default
    config.optics.horizontal_fov_deg = 90.0
    assert math.isclose(config.focal_length_px(320, 320.0), 160.0)  # from the field of view
    config.optics.focal_length_px = 277.0
    assert config.focal_length_px(320, None) == 277.0             # explicit wins
    camera = Config()
    camera.source.uri = "v4l2:/dev/video0"
    with pytest.raises(ConfigError, match="is a camera: give --focal-length-px"):
        camera.focal_length_px(320, None)


def test_cli_reports_bad_key_and_exits_2(tmp_path):
    path = _write(tmp_path, "[link]\nport = '/dev/null'\nbuad = 115200\n")
    result = run_cli(["--config", path], timeout=60)
    assert result.returncode == 2
    assert f"{path}: unknown key [link] buad" in result.stderr
    assert "Traceback" not in result.stderr


def test_cli_needs_a_serial_port():
    result = run_cli(["--source", "synthetic:"], timeout=60)
    assert result.returncode == 2
    assert "no serial port" in result.stderr


def test_cli_help_lists_exactly_the_documented_flags():
    result = run_cli(["--help"], timeout=60)
    assert result.returncode == 0
    flags = set(re.findall(r"(--[a-z][a-z-]+)", result.stdout))
    assert flags == {"--help", "--config", "--log-level", "--source", "--serial", "--baud", "--autopilot",
                     "--protocol", "--focal-length-px", "--frames", "--realtime", "--demo", "--version"}


def test_engine_threshold_mode_overrides_the_models(tmp_path):
    """``[engine] threshold_mode = "local"`` gives either model the local threshold, with
    its tile side; unset keeps the model's own; a mode or tile it does not know is a
    configuration error naming the key."""
    import emdflow

    local = load_config(_write(tmp_path, '[engine]\nthreshold_mode = "local"\nthreshold_tile = 128\n')).engine
    options = local.estimator_options()
    assert options["threshold_mode"] == "local" and options["threshold_tile"] == 128
    assert options["delays"] == (1, 2, 4)  # still the extended model
    est = emdflow.FlowEstimator(320, 240, backend="numpy", **options)
    assert est.params.threshold_tiles(320, 240) == (2, 3)
    paper = load_config(_write(tmp_path, '[engine]\nmodel = "paper"\nthreshold_mode = "local"\n')).engine
    assert paper.estimator_options() == {"threshold": 5.0, "threshold_mode": "local", "threshold_tile": 64}
    own = load_config(_write(tmp_path, '[engine]\nthreshold_tile = 128\n')).engine.estimator_options()
    assert own["threshold_mode"] == "adaptive" and "threshold_tile" not in own
    for text, key in (('threshold_mode = "tiles"', "threshold_mode"), ("threshold_tile = 100", "threshold_tile")):
        with pytest.raises(ConfigError, match=key):
            load_config(_write(tmp_path, f"[engine]\n{text}\n"))


def test_engine_model_selects_the_estimator_options(tmp_path):
    import emdflow

    default = load_config(_write(tmp_path, '[engine]\nbackend = "opencl"\n')).engine
    assert default.model == "extended", "the daemon flies the extended model unless told otherwise"
    paper = load_config(_write(tmp_path, '[engine]\nmodel = "paper"\n')).engine
    assert paper.estimator_options() == {"threshold": 5.0}
    extended = load_config(_write(tmp_path, '[engine]\nmodel = "extended"\nthreshold = 6.0\n')).engine
    options = extended.estimator_options()
    assert options["delays"] == (1, 2, 4) and options["threshold_mode"] == "adaptive"
    est = emdflow.FlowEstimator(64, 48, backend="numpy", **options)
    assert 0.25 in est.params.speeds and 15 in est.params.scales and est.params.threshold == 6.0
    with pytest.raises(ConfigError, match="model"):
        load_config(_write(tmp_path, '[engine]\nmodel = "fancy"\n'))
    # the summary's gradient classes can be turned off (slow boards); the paper has none
    assert options.get("gradient_classes") is True
    cheap = load_config(_write(tmp_path, '[engine]\ngradient_classes = false\n')).engine.estimator_options()
    assert cheap["gradient_classes"] is False and cheap["brightness_compensation"] is True
    est = emdflow.FlowEstimator(64, 48, backend="numpy", **cheap)
    assert est.params.histogram_bins == 64
    paper_cheap = load_config(_write(tmp_path, '[engine]\nmodel = "paper"\ngradient_classes = false\n'))
    assert paper_cheap.engine.estimator_options() == {"threshold": 5.0}
    # denser summary evidence: every row feeds it (0 = automatic, the default)
    assert "evidence_row_step" not in options
    dense = load_config(_write(tmp_path, '[engine]\nevidence_row_step = 1\n')).engine.estimator_options()
    assert emdflow.FlowEstimator(64, 48, backend="numpy", **dense).params.evidence_row_step_for(48) == 1
    with pytest.raises(ConfigError, match="evidence_row_step"):
        load_config(_write(tmp_path, '[engine]\nevidence_row_step = -2\n'))
    # the diagonal detectors' evidence: on unless turned off, for either model
    assert "diagonal_evidence" not in options
    assert emdflow.FlowEstimator(64, 48, backend="numpy", **options).params.evidence_axes == 4
    for model in ("extended", "paper"):
        off = load_config(_write(tmp_path, f'[engine]\nmodel = "{model}"\ndiagonal_evidence = false\n'))
        est = emdflow.FlowEstimator(64, 48, backend="numpy", **off.engine.estimator_options())
        assert est.params.evidence_axes == 2 and not est.params.diagonal_evidence
    with pytest.raises(ConfigError, match="diagonal_evidence"):
        load_config(_write(tmp_path, '[engine]\ndiagonal_evidence = "no"\n'))


def test_autopilot_and_protocol_that_fit_together(tmp_path):
    """Each autopilot takes its own protocol: ArduPilot's MSP driver (FLOW_TYPE = 7) scales
    counts by the message interval (the Matek 3901-L0X's convention), so ArduPilot with MSP
    is refused with the reason and the way out; a contradictory pair made by a flag over
    the file is refused like one in the file."""
    with pytest.raises(ConfigError, match=r"ArduPilot takes optical flow over mavlink only; leave protocol "
                                          r"out .*multiplies the mean counts by the time between messages.*"
                                          r"FLOW_TYPE = 5"):
        load_config(_write(tmp_path, "[link]\nautopilot = 'ardupilot'\nprotocol = 'msp'\n"))
    config = load_config(_write(tmp_path, "[link]\nautopilot = 'inav'\nprotocol = 'msp'\n"))
    assert (config.link.autopilot, config.link.protocol) == ("inav", "msp")
    config.set("link", "autopilot", "px4")
    with pytest.raises(ConfigError, match="--autopilot / --protocol"):
        config.validate()
    # a flag's focal length over a file's field of view is an override, not a contradiction
    config = load_config(_write(tmp_path, "[optics]\nhorizontal_fov_deg = 60.0\n"))
    config.set("optics", "focal_length_px", 300.0)
    config.validate()
    assert config.focal_length_px(320, None) == 300.0


def test_ground_distance_with_px4_is_a_caution(tmp_path):
    """PX4's EKF2 takes the flow message's distance as a rangefinder reading when no
    distance sensor reports: a fixed ground distance is valid but worth a warning there.
    INAV never sees it (MSP's flow message has no distance; it was accepted in silence):
    a warning too. ArduPilot shows it only (the message's ground_distance)."""
    for autopilot, warned in (("px4", "EKF2 takes"), ("both", "EKF2 takes"), ("ardupilot", None),
                              ("inav", "INAV never sees it")):
        config = load_config(_write(tmp_path, f"[link]\nautopilot = '{autopilot}'\nground_distance_m = 0.3\n"))
        notes = config.cautions()
        assert bool(notes) == bool(warned), autopilot
        if warned:
            assert "ground_distance_m = 0.3" in notes[0] and "rangefinder" in notes[0] and warned in notes[0]
    assert load_config(_write(tmp_path, "[link]\nautopilot = 'px4'\n")).cautions() == []
