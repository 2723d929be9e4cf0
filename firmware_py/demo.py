"""``emdflowd --demo``: the whole appliance with no hardware.

A synthetic camera flight (a slow circle over a photograph, 320×240 at 100 frames/s, paced
in real time) goes through the OpenCL engine and the MAVLink link into a pseudo-terminal;
the demo reads the other end with pymavlink, as a flight controller would, and prints one
line per second: frame rate, message rate, latency (capture → serial write), the flow rate
received on the wire next to the flight's true rate, and the quality. It stops after 10 s
(or ``--frames N``) with a summary line; exit 0 when flow messages arrived with valid CRCs,
2 when the source delivered no frame at all (as for a source that cannot be opened).
"""

from __future__ import annotations

import logging
import math
import os
import select
import signal
import sys
import threading
import time

from .config import ConfigError, LinkConfigSection, load_config

__all__ = ["run_demo", "DEMO_SOURCE", "DEMO_SECONDS"]

DEMO_SOURCE = "synthetic:"
DEMO_SECONDS = 10.0
DEMO_BAUD = 921600  # the pty ignores it; high enough for a message per frame
_HEADER = (f"{'t [s]':>5} {'frames/s':>8} {'msgs/s':>6} {'HB':>3} {'latency p50/p99 ms':>18}  "
           f"{'flow rate x,y rad/s':>19}  {'truth x,y rad/s':>15}  {'quality':>7}")

log = logging.getLogger("emdflowd.demo")


class _WireReader:
    """Parses what the link wrote into the pty, with pymavlink, and counts it."""

    def __init__(self, fd: int):
        from pymavlink.dialects.v20 import common as mavlink

        self.fd = fd
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.counts: dict[str, int] = {}
        self.last_flow = None
        self.previous_flow = None  # (the message before: where the last one's span began)
        self.bytes = 0

    def poll(self, timeout: float) -> None:
        ready, _, _ = select.select([self.fd], [], [], timeout)
        if not ready:
            return
        try:
            data = os.read(self.fd, 65536)
        except OSError:  # the link closed its end (EIO on Linux)
            time.sleep(timeout)
            return
        self.bytes += len(data)
        for msg in self.parser.parse_buffer(data) or []:
            name = msg.get_type()
            if name == "BAD_DATA":
                continue
            self.counts[name] = self.counts.get(name, 0) + 1
            if name == "OPTICAL_FLOW":
                self.previous_flow, self.last_flow = self.last_flow, msg


def _fmt(x: float, width: int = 6) -> str:
    return f"{x:+{width}.3f}" if math.isfinite(x) else f"{'-':>{width}}"


def run_demo(*, frames: int | None = None, config_path: str | None = None, source: str | None = None,
             seconds: float = DEMO_SECONDS, backend: str | None = None,
             size: tuple[int, int] | None = None, focal_length_px: float | None = None, out=None) -> int:
    """Run the demo; returns the exit code (0: telemetry received and shown, or stdout
    closed by its reader, e.g. ``| head``).

    Parameters
    ----------
    frames : int, optional
        Stop after this many processed frames instead of after ``seconds``.
    config_path : str, optional
        Configuration whose engine/source keys to use (the link is always the demo's pty).
    source : str, optional
        Source URI instead of the default circular synthetic flight.
    seconds : float
        Run time when ``frames`` is not given, s.
    backend : str, optional
        Engine backend instead of the configuration's (default ``opencl``).
    size : (int, int), optional
        Processing width and height, px, instead of the configuration's (default 320×240).
    focal_length_px : float, optional
        Focal length at the processed size, px, instead of the configuration's
        (``--focal-length-px``).
    out : file, optional
        Where the table goes (default stdout).
    """
    out = out or sys.stdout
    try:
        return _run_demo(frames=frames, config_path=config_path, source=source, seconds=seconds,
                         backend=backend, size=size, focal_length_px=focal_length_px, out=out)
    except BrokenPipeError:
        # the reader went away (`emdflowd --demo | head -1`): a stop like Ctrl-C, not a crash;
        # _run_demo has stopped the daemon. Python's flush of stdout at exit would fail again.
        if out is sys.stdout:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        return 0


def _run_demo(*, frames, config_path, source, seconds, backend, size, focal_length_px, out) -> int:
    from .daemon import Daemon
    from .sources import SourceError
    from .sources.synthetic import SyntheticSource

    ptys: list[int] = []  # the pseudo-terminal's two ends, closed however the demo ends
    try:
        try:
            config = load_config(config_path)
            config.set("source", "uri", source or (config.source.uri if config_path else DEMO_SOURCE))
            config.source.realtime = True
            config.frames = frames
            if backend:
                config.set("engine", "backend", backend)
            if size:
                config.set("source", "width", int(size[0]))
                config.set("source", "height", int(size[1]))
            if focal_length_px is not None:
                config.set("optics", "focal_length_px", focal_length_px, origin="command line")
            if frames is not None and frames < 1:
                raise ConfigError(f"command line: --frames {frames}: must be >= 1")
            master, slave = os.openpty()
            ptys += [master, slave]
            # the demo's link is its own: MAVLink for ArduPilot into its pseudo-terminal, none
            # of the file's [link] keys (an MSP protocol, a flight's message log) apply
            config.link = LinkConfigSection()
            config.set("link", "port", os.ttyname(slave))
            config.set("link", "baud", DEMO_BAUD)
            config.set("link", "autopilot", "ardupilot")
            config.validate()
            truth_source = None
            if config.source.uri.startswith("synthetic:"):
                # (a texture that does not exist fails here first: exit 2 like emdflowd's, no traceback)
                truth_source = SyntheticSource(config.source.uri.partition(":")[2],
                                               width=config.source.width or 320,
                                               height=config.source.height or 240, fps=config.source.fps or 100.0)
        except (ConfigError, SourceError) as exc:
            log.error("%s", exc)
            return 2
        fell_back = not backend and config.engine.backend == "opencl" and _fall_back_without_opencl(config, out)
        daemon = Daemon(config)
        result: dict = {}

        def _run():
            try:
                result["code"] = daemon.run()
            except Exception as exc:  # reported below; the reader must not hang
                result["error"] = exc
            finally:
                daemon.running.set()

        thread = threading.Thread(target=_run, name="emdflowd-demo", daemon=True)
        stop = threading.Event()
        previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
        reader = _WireReader(master)
        thread.start()
        try:  # (a print may raise BrokenPipeError: the daemon is stopped below all the same)
            daemon.running.wait(120.0)  # the first OpenCL build may take a while
            start = time.monotonic()
            if daemon.width and "error" not in result:
                # after the source is made: its size is the one processed (a video's own, unless
                # [source] width and height are set), not the flight's default
                print(f"emdflowd demo: {config.source.uri} {daemon.width}x{daemon.height} "
                      f"-> {config.engine.backend} engine -> MAVLink OPTICAL_FLOW on {config.link.port} "
                      f"-> pymavlink; {'%d frames' % frames if frames else '%g s' % seconds}", file=out, flush=True)
            if thread.is_alive():
                print(_HEADER, file=out, flush=True)
            next_row = start + 1.0
            last_processed, last_msgs, last_latency = 0, 0, 0
            while not stop.is_set() and thread.is_alive():
                reader.poll(0.02)
                now = time.monotonic()
                # (with --frames the daemon ends the run; a source that has delivered nothing by
                # the demo's time never will in the demo: a camera that is absent or will not open)
                if now - start >= seconds and (frames is None or daemon.stats.frames_in == 0):
                    break
                if now >= next_row:
                    processed = daemon.stats.processed
                    msgs = reader.counts.get("OPTICAL_FLOW", 0)
                    latencies = daemon.latency_snapshot(last_latency)
                    print(_row(now - start, processed - last_processed, msgs - last_msgs, reader, daemon,
                               truth_source, latencies), file=out, flush=True)
                    last_processed, last_msgs = processed, msgs
                    last_latency += len(latencies)
                    next_row += 1.0
        finally:
            daemon.stop()
            thread.join(timeout=10.0)
            end = time.monotonic()
            reader.poll(0.05)
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if "error" in result:
            error = result["error"]
            print(f"demo failed: {error}", file=out, flush=True)
            # as emdflowd's: a source or setting that cannot work is a usage error (2), not a failure
            return 2 if isinstance(error, (ConfigError, SourceError)) else 1
        return _summary(end - start, reader, daemon, truth_source, out, result.get("code", 1), fell_back,
                        config.source.uri)
    finally:
        for fd in ptys:
            os.close(fd)


def _fall_back_without_opencl(config, out) -> bool:
    """The demo shows the whole appliance even where no OpenCL device can run the kernels:
    it says why and what fixes it, and runs the numpy reference (~20 ms per 320×240 frame
    here) instead; returns True then. The daemon itself does not fall back: a flight needs
    the speed, so there an unusable backend stops the start (exit 1) with this same error.
    The demo's summary line says so again, since the demo is also the engine check after
    an install."""
    import emdflow

    width, height = config.source.width or 320, config.source.height or 240
    try:  # builds the kernels once; for the demo's flight the daemon's engine reuses them
        emdflow.FlowEstimator(width, height, backend="opencl", **config.engine.estimator_options())
    except Exception as exc:  # noqa: BLE001 - whatever stops the OpenCL engine: say it, fly on numpy
        print(f"OpenCL is not usable here: {exc}\nThe demo runs on the numpy reference instead "
              "(slow: a capture thread passes every k-th frame, evenly spaced, as for a camera; "
              "outside the demo emdflowd stops with this error, unless [engine] backend = "
              "\"numpy\" is set).", file=out, flush=True)
        from emdflow.opencl_backend import exception_summary

        log.error("OpenCL is not usable here (%s): the demo runs on the numpy reference",
                  exception_summary(exc))
        # (the daemon then reads the paced flight with a capture thread: see Daemon.run)
        config.set("engine", "backend", "numpy")
        return True
    return False


def _truth_rate(daemon, truth_source, reader) -> tuple[float, float]:
    """The flight's true rate over the frames the last flow message spans (a synthetic
    frame's capture time is ``index / fps``: its ``time_usec`` names its newest frame, the
    message before it where it began): a report of several frames averages a turning
    flight's flow over them, and its newest frame is older than the daemon's."""
    flow = reader.last_flow
    if truth_source is None or flow is None or not daemon.fps:
        return math.nan, math.nan
    newest = round(flow.time_usec * daemon.fps / 1e6)
    before = reader.previous_flow
    oldest = round(before.time_usec * daemon.fps / 1e6) + 1 if before is not None else newest
    frames = range(max(1, min(oldest, newest)), max(1, newest) + 1)
    us, vs = zip(*(truth_source.truth(i) for i in frames))
    u, v = sum(us) / len(frames), sum(vs) / len(frames)
    scale = daemon.fps / daemon.focal_length_px
    return u * scale, v * scale


def _row(t, processed, msgs, reader, daemon, truth_source, latencies) -> str:
    from .daemon import _percentiles

    p50, p99 = _percentiles(latencies)
    hb = reader.counts.get("HEARTBEAT", 0)
    flow = reader.last_flow
    fx = flow.flow_rate_x if flow is not None else math.nan
    fy = flow.flow_rate_y if flow is not None else math.nan
    q = flow.quality if flow is not None else 0
    tx, ty = _truth_rate(daemon, truth_source, reader)
    return (f"{t:5.1f} {processed:8d} {msgs:6d} {hb:3d} {p50 / 1000:8.2f} / {p99 / 1000:7.2f}  "
            f"{_fmt(fx, 9)},{_fmt(fy, 9)}  {_fmt(tx, 7)},{_fmt(ty, 7)}  {q:7d}")


def _summary(elapsed, reader, daemon, truth_source, out, code, fell_back=False, uri="") -> int:
    from .daemon import _percentiles

    p50, p99 = _percentiles(daemon.latency_snapshot())
    flows = reader.counts.get("OPTICAL_FLOW", 0)
    hbs = reader.counts.get("HEARTBEAT", 0)
    processed = daemon.stats.processed
    print(f"summary: {processed} frames in {elapsed:.1f} s ({processed / max(elapsed, 1e-9):.1f} fps), "
          f"received {flows} OPTICAL_FLOW + {hbs} HEARTBEAT ({reader.bytes} bytes, valid CRC), "
          f"latency capture->serial p50 {p50 / 1000:.2f} ms p99 {p99 / 1000:.2f} ms"
          + ("; ON THE NUMPY REFERENCE: OpenCL is not usable here (see above)" if fell_back else ""),
          file=out, flush=True)
    if code != 0:
        return code
    if daemon.stats.frames_in == 0:
        # a camera that is absent or will not open: the daemon retried all along (the warnings
        # above say why); for the demo, a check, that is a source that cannot be opened
        print(f"demo failed: source {uri} delivered no frame in {elapsed:.1f} s (it could not be "
              "opened or read: see the warnings above)", file=out, flush=True)
        return 2
    return 0 if flows > 0 and hbs > 0 else 1
