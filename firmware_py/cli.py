"""``emdflowd`` — the optical-flow appliance daemon (console script and ``python -m``).

Exit codes: 0 clean stop (signal, ``--frames`` reached, a recording's end, demo finished);
1 runtime failure (no usable OpenCL device, a crash); 2 configuration or usage error (the
message names the file and key, the source or the port). The systemd unit does not
restart on 2.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys

from .config import ConfigError, load_config

__all__ = ["main", "build_parser", "setup_logging", "stderr_is_journal"]

EXIT_OK, EXIT_FAILURE, EXIT_CONFIG = 0, 1, 2

# syslog priorities for journald's "<N>" prefix on stderr lines
_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}


class _JournalFormatter(logging.Formatter):
    """``<6>emdflowd: message`` — journald reads the priority and adds the timestamp."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        prefix = f"<{_PRIORITY.get(record.levelno, 6)}>"
        return "\n".join(prefix + line for line in text.splitlines())


def stderr_is_journal() -> bool:
    """True if file descriptor 2 is the journal stream systemd connected us to.

    ``$JOURNAL_STREAM`` (``DEVICE:INODE``) is inherited by child processes, whose stderr may
    well be a pipe or a terminal: as systemd.exec(5) says, it only applies when it matches
    stderr's own ``st_dev:st_ino``.
    """
    device, sep, inode = os.environ.get("JOURNAL_STREAM", "").partition(":")
    try:
        expected = (int(device), int(inode)) if sep else None
        st = os.fstat(2)
    except (ValueError, OSError):  # malformed variable, or no stderr at all
        return False
    return expected == (st.st_dev, st.st_ino)


def setup_logging(level: str = "INFO") -> None:
    """Log to stderr: journald format (``<6>`` priority prefixes, no timestamp) when stderr is
    the journal stream (:func:`stderr_is_journal`), else timestamped lines."""
    handler = logging.StreamHandler(sys.stderr)
    if stderr_is_journal():
        handler.setFormatter(_JournalFormatter("%(name)s: %(message)s"))
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s.%(msecs)03d %(levelname)-7s %(name)s: %(message)s",
                                               "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="emdflowd",
        description="Insect-vision optical flow from a camera to a flight controller's serial port.",
        epilog="Run 'emdflowd --demo' first: a synthetic flight, no hardware. "
               "Every option can also be set in the --config file (see deploy/emdflow.toml).",
    )
    from emdflow import __version__

    p.add_argument("--version", action="version", version=f"emdflowd {__version__}")
    p.add_argument("--config", metavar="FILE", help="TOML configuration file (flags override it)")
    p.add_argument("--log-level", metavar="LEVEL", type=str.upper,
                   choices=("DEBUG", "INFO", "WARNING", "ERROR"), help="DEBUG, INFO, WARNING or ERROR")
    p.add_argument("--source", metavar="URI",
                   help="v4l2:/dev/videoN | v4l2:N | depthai:CAM_B | depthai-replay:PATH | "
                        "video:PATH | synthetic:[texture=NAME,u=PX,v=PX,...]")
    p.add_argument("--serial", metavar="PORT", help="serial port to the flight controller")
    p.add_argument("--baud", metavar="N", type=int, help="baud rate (default 115200)")
    p.add_argument("--autopilot", choices=("ardupilot", "px4", "inav", "both"),
                   help="ardupilot: OPTICAL_FLOW, px4: OPTICAL_FLOW_RAD, inav: MSP, both: both MAVLink messages")
    p.add_argument("--protocol", choices=("mavlink", "msp"),
                   help="force the wire protocol (mavlink sends both flow messages)")
    p.add_argument("--focal-length-px", metavar="F", type=float,
                   help="focal length at the processed resolution, px (cameras need it or a field of view)")
    p.add_argument("--frames", metavar="N", type=int, help="stop after N processed frames, exit 0")
    p.add_argument("--realtime", action="store_true", help="pace file and synthetic sources to their fps")
    p.add_argument("--demo", action="store_true",
                   help="synthetic flight -> engine -> MAVLink into a pseudo-terminal, read back and shown live")
    return p


def _apply_flags(config, args) -> None:
    """Command-line flags override the file; each is validated like the file's key."""
    overrides = [
        ("source", "uri", args.source), ("link", "port", args.serial), ("link", "baud", args.baud),
        ("link", "autopilot", args.autopilot), ("link", "protocol", args.protocol),
        ("optics", "focal_length_px", args.focal_length_px), ("daemon", "log_level", args.log_level),
    ]
    for section, key, value in overrides:
        if value is not None:
            config.set(section, key, value, origin="command line")
    if args.realtime:
        config.source.realtime = True
    if args.frames is not None:
        if args.frames < 1:
            raise ConfigError(f"command line: --frames {args.frames}: must be >= 1")
        config.frames = args.frames
    config.validate()


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``emdflowd``; returns the exit code."""
    # A SIGHUP (logrotate's, a closing terminal) before run_daemon installs its handler
    # would kill the process silently, which systemd counts as a clean stop (no restart):
    # until then there is no log to reopen, so it is ignored.
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    args = build_parser().parse_args(argv)
    # The demo's table is the output: only warnings and errors interleave unless asked.
    setup_logging(args.log_level or ("WARNING" if args.demo else "INFO"))
    log = logging.getLogger("emdflowd")
    if args.demo:
        from .demo import run_demo

        signal.signal(signal.SIGHUP, signal.SIG_DFL)  # (a terminal's demo ends with the terminal)

        # The demo's link is its own (MAVLink for ArduPilot into a pseudo-terminal it reads
        # back with pymavlink): a port, baud rate, autopilot or protocol given for it would be
        # ignored, so they are refused rather than dropped. (--realtime is what the demo does
        # anyway; --log-level applies above; --focal-length-px is the flight's, passed on.)
        given = [flag for flag, value in (("--serial", args.serial), ("--baud", args.baud),
                                          ("--autopilot", args.autopilot), ("--protocol", args.protocol))
                 if value is not None]
        if given:
            log.error("command line: %s: not with --demo, which makes its own link (MAVLink for ArduPilot "
                      "into a pseudo-terminal); leave %s out, or run emdflowd without --demo",
                      ", ".join(given), "it" if len(given) == 1 else "them")
            return EXIT_CONFIG
        return run_demo(frames=args.frames, config_path=args.config, source=args.source,
                        focal_length_px=args.focal_length_px)
    try:
        config = load_config(args.config)
        _apply_flags(config, args)
        if not config.link.port:
            raise ConfigError(f"{config.path or 'configuration'}: no serial port: give --serial PORT "
                              "or [link] port (or try 'emdflowd --demo')")
        from .links.serial_port import port_problem

        problem = port_problem(config.link.port)
        if problem:  # (a port that does not exist yet is retried: USB adapters come and go)
            raise ConfigError(f"{config.path or 'configuration'}: [link] port (--serial) "
                              f"{config.link.port}: {problem}")
        from .daemon import link_config

        link_config(config)  # before the camera opens and the kernels build
    except ConfigError as exc:
        log.error("%s", exc)
        return EXIT_CONFIG
    setup_logging(config.daemon.log_level)
    for note in config.cautions():
        log.warning("%s", note)
    return run_daemon(config)


def run_daemon(config, *, daemon=None) -> int:
    """Run :class:`~firmware_py.daemon.Daemon` with signal handling; returns the exit code."""
    from .daemon import Daemon
    from .sources import SourceError

    log = logging.getLogger("emdflowd")
    daemon = daemon or Daemon(config)

    def _stop(signum, _frame):
        log.info("%s: stopping", signal.Signals(signum).name)
        daemon.stop()

    def _reopen(_signum, _frame):
        daemon.reopen_logs()

    previous = {sig: signal.signal(sig, _stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    # SIGHUP (a log rotation's signal, or the terminal closing) must not end the flight:
    # by default it kills the process without a flush, and systemd counts that as a clean
    # stop, so Restart=on-failure would not bring the flow sensor back.
    previous[signal.SIGHUP] = signal.signal(signal.SIGHUP, _reopen)
    try:
        return daemon.run()
    except (ConfigError, SourceError) as exc:
        log.error("%s", exc)
        return EXIT_CONFIG
    except RuntimeError as exc:  # e.g. no OpenCL platform: the message says how to install one
        log.error("%s", exc)
        return EXIT_FAILURE
    except Exception:  # a bug: the traceback goes to the journal, systemd restarts us
        log.exception("unexpected error; exiting")
        return EXIT_FAILURE
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":
    sys.exit(main())
