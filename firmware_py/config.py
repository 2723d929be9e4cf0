"""The daemon's configuration: a TOML file (stdlib ``tomllib``) plus command-line overrides.

Every key is documented in the commented example ``deploy/emdflow.toml``. An unknown
section or key, or a value of the wrong type or out of range, is a :class:`ConfigError`
whose message names the file and the ``[section] key``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from pathlib import Path

from emdflow.params import MODELS, THRESHOLD_MODES

from .links.base import (AUTOPILOT_PROTOCOLS, MAX_REPORT_DELAY_MS, MIN_MESSAGE_RATE_HZ, MIN_RATE_REASON,
                         protocol_refusal)

__all__ = ["Config", "SourceConfig", "OpticsConfig", "EngineConfig", "LinkConfigSection",
           "DaemonConfig", "ConfigError", "load_config", "SECTIONS", "ARDUPILOT_MIN_QUALITY"]

#: The default ``[link] min_quality`` for ArduPilot, per model: the lowest quality band in
#: which the summary's error is still that of the better bands (the extended model's 1-63
#: band reads 10 % median, 24 % 90th percentile, against 5-7 % and 11-14 % above it; the
#: paper model's 64-127 band 11.5 % and 57 %): README, "Thresholds".
ARDUPILOT_MIN_QUALITY = {"extended": 64, "paper": 128}


class ConfigError(ValueError):
    """A configuration problem; the message names the file and key."""


def _opt(default=None, *, choices=None, minimum=None, maximum=None, doc="", why=""):
    # why: the reason for the minimum, appended to a too-low error (not to a too-high one)
    return dataclasses.field(default=default, metadata=dict(choices=choices, minimum=minimum,
                                                            maximum=maximum, doc=doc, why=why))


@dataclasses.dataclass
class SourceConfig:
    """``[source]``: where frames come from and at which processing resolution."""

    uri: str = _opt("synthetic:", doc="frame source URI")
    width: int | None = _opt(None, minimum=16, maximum=4096, doc="processing width, px")
    height: int | None = _opt(None, minimum=16, maximum=4096, doc="processing height, px")
    fps: float | None = _opt(None, minimum=1.0, maximum=1000.0, doc="requested frame rate, frames/s")
    pixel_format: str = _opt("GREY", choices=("GREY", "YUYV", "MJPG"), doc="V4L2 pixel format")
    buffer_count: int = _opt(2, minimum=1, maximum=10, doc="V4L2 driver buffers")
    exposure_us: float | None = _opt(None, minimum=1.0, maximum=1_000_000.0, doc="manual exposure, µs")
    # V4L2 gains are driver units (0..255 up to a few thousand), DepthAI's an ISO of 100..1600;
    # anything near the bound is a typo (DepthAI raises on an ISO beyond 32 bits, every open)
    gain: float | None = _opt(None, minimum=0.0, maximum=1_000_000.0, doc="manual gain (V4L2 units, DepthAI ISO)")
    loop: bool = _opt(False, doc="rewind files at their end")
    realtime: bool = _opt(False, doc="pace file and synthetic sources to their fps")


@dataclasses.dataclass
class OpticsConfig:
    """``[optics]``: lens and mounting, at the processing resolution."""

    focal_length_px: float | None = _opt(None, minimum=1.0, maximum=100_000.0, doc="focal length, px")
    horizontal_fov_deg: float | None = _opt(None, minimum=1.0, maximum=179.0, doc="horizontal field of view, deg")
    mounting_rotation_deg: int = _opt(0, choices=(0, 90, 180, 270), doc="sensor rotation, deg")
    mounting_mirror: bool = _opt(False, doc="mirrored image")


@dataclasses.dataclass
class EngineConfig:
    """``[engine]``: the flow estimator."""

    backend: str = _opt("opencl", choices=("opencl", "numpy"), doc="estimator backend")
    reset_after_gap_s: float = _opt(0.5, minimum=0.01, maximum=60.0, doc="reset after this gap, s")
    # "extended" by default: a flying vehicle needs the slow drift (hover) and contrast
    # changes the paper's model is blind to; "paper" is the published model unchanged.
    model: str = _opt("extended", choices=tuple(MODELS), doc="detector model")
    threshold: float = _opt(5.0, minimum=0.5, maximum=100.0, doc="ternary threshold, gray levels")
    # the extended model's summary reads its evidence per gradient-strength class (more
    # accurate speed, direction and slow speeds; the summary costs ~2.2-2.4 ms instead of
    # ~1.3-1.5 ms per 320x240 frame in the demo on a 2-core x86): false trades that accuracy
    # for the time on slow boards
    gradient_classes: bool = _opt(True, doc="summary evidence per gradient-strength class")
    # 0: about 60 sampled rows per frame. 1 (every row) at 320x240 takes the summary's
    # direction error from ~1.9 to ~1.65 degrees for ~0.44 ms more engine time per frame
    evidence_row_step: int = _opt(0, minimum=0, maximum=1024,
                                  doc="rows between the rows feeding the summary (0: automatic)")
    # detectors along the two diagonals feed the summary (not the dense field): a fast
    # oblique flight over rough ground no longer blinds its minor axis (README, "Diagonal
    # evidence"); false saves ~9-16 % of the engine time at 640x480 for that accuracy
    diagonal_evidence: bool = _opt(True, doc="diagonal detectors in the summary's evidence")
    # unset: the model's own (extended: "adaptive", one threshold following the whole frame's
    # contrast; paper: "fixed"). "local": the threshold follows each tile's contrast, so a
    # part of the view in shade keeps its detections beside a lit one (README, "Shadows:
    # the local threshold"), for ~4 % more engine time
    threshold_mode: str | None = _opt(None, choices=THRESHOLD_MODES, doc="threshold mode (default: the model's)")
    threshold_tile: int = _opt(64, choices=(32, 64, 96, 128, 192, 256), doc="local threshold's tile side, px")

    def estimator_options(self) -> dict:
        """Keyword arguments of ``emdflow.FlowEstimator`` for this section."""
        # extended: temporal delays see 1/2 and 1/4 px/frame (hovering drift), a scale-15
        # channel resolves 11-15 px/frame, the threshold follows scene contrast and the
        # states discount the frame's brightness change (emdflow.params.MODELS)
        options = {"threshold": self.threshold, **MODELS[self.model]}
        if not self.gradient_classes and options.get("gradient_classes"):
            options["gradient_classes"] = False
        if self.evidence_row_step:
            options["evidence_row_step"] = self.evidence_row_step
        if not self.diagonal_evidence:
            options["diagonal_evidence"] = False
        if self.threshold_mode is not None:
            options["threshold_mode"] = self.threshold_mode
        if options.get("threshold_mode") == "local":
            options["threshold_tile"] = self.threshold_tile
        return options


@dataclasses.dataclass
class LinkConfigSection:
    """``[link]``: the serial link to the flight controller (see ``firmware_py.links``)."""

    port: str | None = _opt(None, doc="serial device")
    baud: int = _opt(115200, minimum=1200, maximum=4_000_000, doc="baud rate")
    autopilot: str | None = _opt(None, choices=("ardupilot", "px4", "inav", "both"), doc="autopilot")
    protocol: str | None = _opt(None, choices=("mavlink", "msp"), doc="wire protocol")
    sysid: int = _opt(1, minimum=1, maximum=255, doc="MAVLink system id")
    compid: int = _opt(158, minimum=1, maximum=255, doc="MAVLink component id")
    sensor_id: int = _opt(0, minimum=0, maximum=255, doc="flow sensor id")
    message_rate_hz: float | None = _opt(None, minimum=MIN_MESSAGE_RATE_HZ, maximum=1000.0, doc="flow message rate",
                                         why=MIN_RATE_REASON)
    heartbeat_rate_hz: float = _opt(1.0, minimum=0.1, maximum=50.0, doc="heartbeat rate")
    ground_distance_m: float | None = _opt(None, minimum=0.01, maximum=1000.0, doc="fixed ground distance, m",
                                           why="0 m would go out as a real reading; leave it unset for unknown")
    message_log: str | None = _opt(None, doc="CSV / JSON-lines log of sent messages")
    extra_values: bool = _opt(False, doc="send extra named values")
    # ArduPilot's EKF3 fuses every report of quality > 0 (it has no quality threshold):
    # below this the daemon sends quality 0. Empty: 64 (extended model) or 128 (paper's)
    # for ArduPilot and for both (whose OPTICAL_FLOW ArduPilot reads), 0 for PX4 and INAV,
    # which apply their own (EKF2_OF_QMIN, 35 %)
    min_quality: int | None = _opt(None, minimum=0, maximum=255, doc="lowest quality whose flow a report uses")
    # must equal INAV's opflow_scale, or INAV's rates come out scaled by the ratio
    msp_counts_per_degree: float = _opt(10.5, minimum=0.1, maximum=1000.0,
                                        doc="MSP motion counts per degree of angular flow")
    # INAV divides a report's counts by the time since the previous one arrived: each report
    # goes out this long after its frame's capture (empty: automatic, just above the recent
    # times from capture to report; 0: as soon as processed)
    msp_report_delay_ms: float | None = _opt(None, minimum=0.0, maximum=MAX_REPORT_DELAY_MS,
                                             doc="MSP report delay after capture, ms")


@dataclasses.dataclass
class DaemonConfig:
    """``[daemon]``: loop, logging and recovery."""

    log_level: str = _opt("INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"), doc="log level")
    log_interval_s: float = _opt(10.0, minimum=0.5, maximum=3600.0, doc="status line period, s")
    threading: str = _opt("auto", choices=("auto", "single", "capture-thread"), doc="loop structure")
    reopen_backoff_s: float = _opt(0.5, minimum=0.05, maximum=60.0, doc="first reopen delay, s")
    reopen_backoff_max_s: float = _opt(10.0, minimum=0.1, maximum=600.0, doc="longest reopen delay, s")
    # the link's keep-alive starts after the smaller of this and its own value (MAVLink 0.3 s,
    # MSP 0.15 s): a larger value cannot make the autopilot time out
    blind_after_s: float = _opt(0.25, minimum=0.02, maximum=10.0, doc="no frame for this long = blind, s")


_AUTOPILOT_NAMES = {"ardupilot": "ArduPilot", "px4": "PX4", "inav": "INAV",
                    "both": "'both' (OPTICAL_FLOW and OPTICAL_FLOW_RAD)"}

SECTIONS: dict[str, type] = {
    "source": SourceConfig,
    "optics": OpticsConfig,
    "engine": EngineConfig,
    "link": LinkConfigSection,
    "daemon": DaemonConfig,
}


@dataclasses.dataclass
class Config:
    """The whole configuration; ``path`` is the file it came from (None: defaults only)."""

    source: SourceConfig = dataclasses.field(default_factory=SourceConfig)
    optics: OpticsConfig = dataclasses.field(default_factory=OpticsConfig)
    engine: EngineConfig = dataclasses.field(default_factory=EngineConfig)
    link: LinkConfigSection = dataclasses.field(default_factory=LinkConfigSection)
    daemon: DaemonConfig = dataclasses.field(default_factory=DaemonConfig)
    path: str | None = None
    frames: int | None = None  # command line only: stop after this many processed frames

    def set(self, section: str, key: str, value, *, origin: str = "command line") -> None:
        """Validate and set one value (used for command-line overrides)."""
        obj = getattr(self, section)
        where = f"{origin}: [{section}] {key}"
        value = _check(type(obj), key, value, where)
        if (section, key) == ("source", "uri"):
            _check_uri(value, where)
        setattr(obj, key, value)

    def min_quality(self) -> int:
        """The lowest frame quality whose flow a report uses (below: left out, the report's
        rate its other frames'; FlowSample.doubtful): ``[link] min_quality``, else
        for ArduPilot (EKF3 fuses any quality > 0) the model's band floor where the
        summary's error grows (README, "Thresholds"), else 0."""
        if self.link.min_quality is not None:
            return self.link.min_quality
        if self.link_autopilot() in ("ardupilot", "both"):
            return ARDUPILOT_MIN_QUALITY.get(self.engine.model, 0)
        return 0

    def link_autopilot(self) -> str:
        """The autopilot whose message set to send: the configured one, else from the
        protocol (``mavlink`` alone: both flow messages; ``msp``: INAV), else ArduPilot."""
        if self.link.autopilot:
            return self.link.autopilot
        return {"mavlink": "both", "msp": "inav"}.get(self.link.protocol, "ardupilot")

    def validate(self) -> None:
        """Checks across keys (after the file, and again after command-line overrides)."""
        where = self.path or "configuration"
        if (self.source.width is None) != (self.source.height is None):
            raise ConfigError(f"{where}: [source] width and height must be given together")
        if self.daemon.reopen_backoff_max_s < self.daemon.reopen_backoff_s:
            raise ConfigError(f"{where}: [daemon] reopen_backoff_max_s must be >= reopen_backoff_s")
        autopilot, protocol = self.link.autopilot, self.link.protocol
        speaks = AUTOPILOT_PROTOCOLS.get(autopilot, ())
        if protocol is not None and speaks and protocol not in speaks:
            raise ConfigError(
                f"{where}: [link] autopilot = {autopilot!r} with protocol = {protocol!r} (--autopilot / "
                f"--protocol): " + protocol_refusal(autopilot, _AUTOPILOT_NAMES[autopilot],
                                                    f"; leave protocol out or set it to {speaks[0]!r}"))

    def cautions(self) -> list[str]:
        """Settings that are valid but risky for the configured autopilot (logged as
        warnings at start-up; the README's PX4 notes, from PX4's EKF2 source)."""
        where = self.path or "configuration"
        notes = []
        if self.link.ground_distance_m is not None and self.link_autopilot() in ("px4", "both"):
            notes.append(
                f"{where}: [link] ground_distance_m = {self.link.ground_distance_m:g} with PX4: EKF2 takes "
                "it as a rangefinder reading whenever no distance sensor has reported for 1 s, a false "
                "height for a vehicle whose height changes; leave it out unless the camera's height "
                "cannot change")
        if self.link.ground_distance_m is not None and self.link_autopilot() == "inav":
            notes.append(
                f"{where}: [link] ground_distance_m = {self.link.ground_distance_m:g} with INAV: MSP2_SENSOR_"
                "OPTIC_FLOW has no distance field and no rangefinder message is sent, so INAV never sees "
                "it; it needs its own rangefinder for flow position hold")
        return notes

    def focal_length_px(self, width: int, default: float | None) -> float:
        """Focal length at the processing width, px: explicit value, else from the field of
        view, else the source's documented default; ConfigError when none applies."""
        o = self.optics
        if o.focal_length_px is not None:
            return float(o.focal_length_px)
        if o.horizontal_fov_deg is not None:
            return width / 2.0 / math.tan(math.radians(o.horizontal_fov_deg) / 2.0)
        if default is not None:
            return float(default)
        raise ConfigError(
            f"{self.path or 'configuration'}: source {self.source.uri!r} is a camera: give "
            "--focal-length-px F or [optics] focal_length_px / horizontal_fov_deg "
            "(e.g. horizontal_fov_deg = 71.9 for an OAK-D mono camera)"
        )


def _base_type(tp):
    """``int | None`` → (int, True); ``str`` → (str, False)."""
    args = typing.get_args(tp)
    if args:
        inner = [a for a in args if a is not type(None)]
        return inner[0], type(None) in args
    return tp, False


def _check(cls: type, key: str, value, where: str):
    hints = typing.get_type_hints(cls)
    field = {f.name: f for f in dataclasses.fields(cls)}[key]
    base, optional = _base_type(hints[key])
    meta = field.metadata
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{where}: a value is required")
    if base is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} = {value!r}: expected true or false")
    elif base is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} = {value!r}: expected an integer")
    elif base is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where} = {value!r}: expected a number")
        value = float(value)
    elif base is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} = {value!r}: expected a string")
        if meta.get("choices") and key in ("pixel_format", "log_level"):
            value = value.upper()
        elif meta.get("choices"):
            value = value.lower()
    if meta.get("choices") and value not in meta["choices"]:
        raise ConfigError(f"{where} = {value!r}: expected one of {', '.join(map(str, meta['choices']))}")
    why = f" ({meta['why']})" if meta.get("why") else ""
    if meta.get("minimum") is not None and value < meta["minimum"]:
        raise ConfigError(f"{where} = {value!r}: must be >= {meta['minimum']}{why}")
    if meta.get("maximum") is not None and value > meta["maximum"]:
        raise ConfigError(f"{where} = {value!r}: must be <= {meta['maximum']}")
    return value


def _check_uri(uri: str, where: str) -> None:
    from .sources import parse_uri

    try:
        parse_uri(uri)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def config_from_dict(data: dict, *, origin: str = "configuration") -> Config:
    """Build a validated :class:`Config` from parsed TOML; errors name ``origin`` and key."""
    config = Config(path=origin)
    for section, values in data.items():
        if section not in SECTIONS and not isinstance(values, dict):  # a key above every [section]
            homes = [f"[{name}] {section}" for name, cls in SECTIONS.items()
                     if section in {f.name for f in dataclasses.fields(cls)}]
            raise ConfigError(f"{origin}: key {section} is outside every section; keys belong under a "
                              f"[section] header" + (f" (e.g. {homes[0]})" if homes else
                                                     f" (sections: {', '.join(SECTIONS)})"))
        if section not in SECTIONS:
            raise ConfigError(f"{origin}: unknown section [{section}] (known: {', '.join(SECTIONS)})")
        if not isinstance(values, dict):
            raise ConfigError(f"{origin}: {section} must be a [{section}] table")
        cls = SECTIONS[section]
        known = {f.name for f in dataclasses.fields(cls)}
        for key, value in values.items():
            if key not in known:
                raise ConfigError(
                    f"{origin}: unknown key [{section}] {key} (known: {', '.join(sorted(known))})"
                )
            config.set(section, key, value, origin=origin)
    optics = data.get("optics", {})
    if "focal_length_px" in optics and "horizontal_fov_deg" in optics:  # (a flag may override one)
        raise ConfigError(f"{origin}: [optics] focal_length_px and horizontal_fov_deg both given: "
                          "they say the same thing, keep one")
    config.validate()
    return config


def load_config(path: str | Path | None) -> Config:
    """Read and validate a TOML configuration file (None: all defaults)."""
    if path is None:
        return Config()
    path = Path(path)
    try:
        raw = path.read_bytes()
        # Windows editors (Notepad) start UTF-8 files with a byte order mark, which tomllib
        # reports as an invalid statement at line 1: the text after it is what was meant.
        data = tomllib.loads(raw.removeprefix(b"\xef\xbb\xbf").decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: configuration file not found") from None
    except PermissionError:
        raise ConfigError(f"{path}: permission denied") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a configuration file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        # tomllib decodes UTF-8 and lets this through (e.g. a "°" saved as Latin-1)
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset "
                          f"{exc.start}); save the file as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return config_from_dict(data, origin=str(path))
