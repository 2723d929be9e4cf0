"""How steadily the daemon's MSP reports leave when the processing time varies.

Runs the daemon on a paced synthetic flight (INAV link on a pseudo-terminal, 50 Hz reports,
its message log in a temporary folder) with every engine update padded to a random time
between ``--engine-ms`` (and every 100th to ``--spike-ms``), then prints the intervals
between the reports' writes — what INAV divides each report's counts by — and, for reports
held for their send time (``[link] msp_report_delay_ms``), how late they were written::

    python -m firmware_py.pacing_check                       # automatic delay (the default)
    python -m firmware_py.pacing_check --delay-ms 0          # each report as processed
    python -m firmware_py.pacing_check --threading single    # the loop of files and flights
    python -m firmware_py.pacing_check --pad python          # padding that holds the GIL

No hardware: the numbers are this machine's scheduling. The padding is a sleep by default,
which lets go of Python's GIL as the engine's OpenCL waits do; ``--pad python`` spins in
Python instead, holding it as pure-Python processing would, which the report writer thread
must then wait for (at most the daemon's 0.5 ms switch interval at a time).
"""

from __future__ import annotations

import argparse
import csv
import os
import select
import tempfile
import threading
import time

import numpy as np

from .config import Config
from .daemon import Daemon
from .links.base import MAX_REPORT_DELAY_MS


class PaddedEngine:
    """The daemon's estimator with each update padded to a random time between ``low_s``
    and ``high_s`` (every 100th to ``spike_s``), s: a board whose processing time varies
    from frame to frame (also the daemon tests')."""

    def __init__(self, inner, low_s: float, high_s: float, spike_s: float, *, hold_gil: bool = False,
                 seed: int = 5):
        self.inner, self.low_s, self.high_s, self.spike_s = inner, low_s, high_s, spike_s
        self.hold_gil = hold_gil
        self.rng = np.random.default_rng(seed)
        self.calls = 0

    def update(self, image):
        self.calls += 1
        spike = self.calls % 100 == 50
        until = time.perf_counter() + (self.spike_s if spike else self.rng.uniform(self.low_s, self.high_s))
        field = self.inner.update(image)
        while time.perf_counter() < until:
            if not self.hold_gil:
                time.sleep(0.0002)
        return field

    def __getattr__(self, name):
        return getattr(self.inner, name)


def _drain(fd: int, stop: threading.Event) -> None:
    while not stop.is_set():
        if select.select([fd], [], [], 0.05)[0]:
            try:
                os.read(fd, 65536)
            except OSError:
                time.sleep(0.01)


def measure(*, delay_ms: float | None, threading_mode: str, frames: int, engine_ms: tuple[float, float],
            spike_ms: float, hold_gil: bool = False, fps: float = 100.0, rate_hz: float = 50.0) -> dict:
    """Run the daemon once; returns the written reports' intervals (ms), their write times
    after due (ms, held reports) and the link's chosen delay (ms) and late count."""
    with tempfile.TemporaryDirectory() as folder:
        log_path = os.path.join(folder, "sent.csv")
        master, slave = os.openpty()
        stop = threading.Event()
        drain = threading.Thread(target=_drain, args=(master, stop), daemon=True)
        drain.start()
        config = Config()
        for section, key, value in (
                ("source", "uri", "synthetic:u=2,v=1"), ("source", "width", 96), ("source", "height", 72),
                ("source", "fps", fps), ("source", "realtime", True), ("engine", "model", "paper"),
                ("link", "autopilot", "inav"), ("link", "port", os.ttyname(slave)), ("link", "baud", 921600),
                ("link", "message_rate_hz", rate_hz), ("link", "message_log", log_path),
                ("daemon", "threading", threading_mode), ("daemon", "log_level", "WARNING")):
            config.set(section, key, value)
        if delay_ms is not None:
            config.set("link", "msp_report_delay_ms", delay_ms)
        config.frames = frames

        def estimator(width, height):
            inner = Daemon(config)._default_estimator(width, height)
            return PaddedEngine(inner, engine_ms[0] / 1e3, engine_ms[1] / 1e3, spike_ms / 1e3, hold_gil=hold_gil)

        daemon = Daemon(config, estimator_factory=estimator)
        try:
            code = daemon.run()
        finally:
            stop.set()
            drain.join(2.0)
            os.close(master)
            os.close(slave)
        if code != 0:
            raise SystemExit(f"the daemon exited {code}")
        with open(log_path, newline="") as f:
            reports = [r for r in csv.DictReader(f) if r["message"] == "MSP2_SENSOR_OPTIC_FLOW"]
    reports = reports[len(reports) // 4:]  # (after the automatic delay's start)
    written = np.array([int(r["host_us"]) for r in reports], np.int64)
    late = [(int(r["latency_us"]) - int(r["paced_us"])) / 1e3 for r in reports if r["paced_us"] and r["latency_us"]]
    return {"gaps_ms": np.diff(written) / 1e3, "late_ms": np.array(late), "period_ms": 1e3 / rate_hz,
            "delay_ms": daemon.link.stats.get("report_delay_ms", 0.0),
            "late_reports": daemon.link.stats.get("late_reports", 0), "reports": len(reports)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m firmware_py.pacing_check", description=__doc__.split("\n\n")[0])
    ap.add_argument("--delay-ms", default="auto", help="[link] msp_report_delay_ms: auto (default), 0, or ms")
    ap.add_argument("--threading", default="capture-thread", choices=("capture-thread", "single"))
    ap.add_argument("--frames", type=int, default=600, help="frames processed (100 fps; default 600)")
    ap.add_argument("--engine-ms", default="2-8", help="range of an update's time, ms (default 2-8)")
    ap.add_argument("--spike-ms", type=float, default=11.0, help="every 100th update's time, ms (default 11)")
    ap.add_argument("--pad", default="sleep", choices=("sleep", "python"),
                    help="padding that lets go of the GIL (sleep, default) or holds it (python)")
    a = ap.parse_args(argv)
    try:
        low, high = (float(v) for v in a.engine_ms.split("-"))
    except ValueError:
        ap.error(f"--engine-ms {a.engine_ms!r}: expected a range of ms, e.g. 2-8")
    try:
        delay = None if a.delay_ms == "auto" else float(a.delay_ms)
    except ValueError:
        delay = -1.0
    if delay is not None and not 0 <= delay <= MAX_REPORT_DELAY_MS:
        ap.error(f"--delay-ms {a.delay_ms!r}: expected auto or 0..{MAX_REPORT_DELAY_MS:g} ms")
    if not 0 <= low <= high or a.spike_ms < 0 or a.frames < 100:
        ap.error("--engine-ms low-high with 0 <= low <= high, --spike-ms >= 0, --frames >= 100")
    r = measure(delay_ms=delay, threading_mode=a.threading, frames=a.frames, engine_ms=(low, high),
                spike_ms=a.spike_ms, hold_gil=a.pad == "python")
    gaps, period = r["gaps_ms"], r["period_ms"]
    if len(gaps) < 2:
        print(f"only {r['reports']} reports after the first quarter: too few to measure (more --frames)")
        return 1
    print(f"delay {a.delay_ms} ({r['delay_ms']:.1f} ms at the end), {a.threading}, update {a.engine_ms} ms "
          f"(every 100th {a.spike_ms:g} ms, padded by {a.pad}): {r['reports']} reports after the first "
          f"quarter, {r['late_reports']} late")
    p5, p50, p95 = np.percentile(gaps, [5, 50, 95])
    print(f"intervals between written reports: p5 {p5:.2f} p50 {p50:.2f} p95 {p95:.2f} ms; "
          f"{np.mean(np.abs(gaps - period) <= 0.5):.0%} within 0.5 ms of {period:g} ms")
    if len(r["late_ms"]):
        q50, q95 = np.percentile(r["late_ms"], [50, 95])
        print(f"held reports written after their due time: p50 {q50:.2f} p95 {q95:.2f} max {r['late_ms'].max():.2f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
