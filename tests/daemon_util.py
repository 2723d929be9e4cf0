"""Helpers shared by the daemon tests: real video files, real ptys, real parsers."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def flight_frames(count: int, *, flow=(2.0, 0.0), width=160, height=120, texture="gravel", seed=0):
    """Frames of a straight camera flight with known image flow (px/frame)."""
    from emdflow.synthetic import CameraFlight

    flight = CameraFlight(texture, width=width, height=height, flow=flow, noise_sigma=1.0,
                          supersample=2, seed=seed)
    return flight.render_many(count)


def write_video(path: Path, frames: np.ndarray, fps: float = 50.0) -> Path:
    """Write gray frames losslessly (FFV1); OpenCV reads them back bit-exact."""
    h, w = frames.shape[1:]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, (w, h), isColor=False)
    assert writer.isOpened(), f"cannot write {path}"
    for frame in frames:
        writer.write(frame)
    writer.release()
    return Path(path)


class PtyPair:
    """A pseudo-terminal: the daemon opens ``path``; the test reads ``master``."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo or line discipline on the bytes
        self.path = os.ttyname(self.slave)
        self.buffer = bytearray()

    def read_for(self, seconds: float) -> bytes:
        """Read everything that arrives within ``seconds``."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            ready, _, _ = select.select([self.master], [], [], min(left, 0.05))
            if ready:
                try:
                    self.buffer += os.read(self.master, 65536)
                except OSError:
                    time.sleep(0.01)
        return bytes(self.buffer)

    def close(self):
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class Drain:
    """Reads a pty master in a background thread so the writer never blocks."""

    def __init__(self, fd: int):
        import threading

        self.fd = fd
        self.data = bytearray()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            ready, _, _ = select.select([self.fd], [], [], 0.05)
            if ready:
                try:
                    self.data += os.read(self.fd, 65536)
                except OSError:
                    time.sleep(0.02)

    def stop(self) -> bytes:
        self._stop.set()
        self._thread.join(2.0)
        return bytes(self.data)


def run_daemon(config, *, frames=None, baud=921600, **factories):
    """Run a :class:`~firmware_py.daemon.Daemon` in this process until it stops, its link
    on a fresh pty (``baud``) drained in the background; ``frames`` sets ``config.frames``
    when given; ``factories``: the Daemon's ``source_factory`` / ``estimator_factory`` /
    ``link_factory``. Returns ``(exit_code, daemon, bytes_written)``."""
    from firmware_py.daemon import Daemon

    if frames is not None:
        config.frames = frames
    pty = PtyPair()
    config.set("link", "port", pty.path)
    config.set("link", "baud", baud)
    drain = Drain(pty.master)
    daemon = Daemon(config, **factories)
    try:
        code = daemon.run()
    finally:
        data = drain.stop()
        pty.close()
    return code, daemon, data


def parse_mavlink(data: bytes):
    """All MAVLink messages in ``data`` with valid CRC, parsed by pymavlink."""
    from pymavlink.dialects.v20 import common as mavlink

    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return [m for m in (parser.parse_buffer(data) or []) if m.get_type() != "BAD_DATA"]


def _crc8_dvb_s2(data: bytes) -> int:
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0xD5) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def parse_msp_v2(data: bytes):
    """(function, payload) of every MSP v2 frame with a valid CRC (an independent decoder)."""
    frames = []
    i = 0
    while True:
        i = data.find(b"$X", i)
        if i < 0 or i + 8 > len(data):
            return frames
        # header: '$', 'X', direction, flags (CRC'd, not needed here), function, size
        function = int.from_bytes(data[i + 4:i + 6], "little")
        size = int.from_bytes(data[i + 6:i + 8], "little")
        end = i + 8 + size
        if end >= len(data):
            return frames
        if _crc8_dvb_s2(data[i + 3:end]) == data[end]:
            frames.append((function, data[i + 8:end]))
            i = end + 1
        else:
            i += 2


def _env(extra):
    # Inherit PYTHONPATH: the tree when run from it, the installed package in CI.
    full_env = dict(os.environ)
    full_env.update(extra or {})
    return full_env


def run_cli(args, *, timeout=120, env=None) -> subprocess.CompletedProcess:
    """Run ``python -m firmware_py.cli ARGS`` (the emdflowd entry point) to completion.

    The working directory is neutral so that ``-m`` does not pick up a checkout in the
    current directory instead of the installed package (CI tests the installed one).
    """
    return subprocess.run([sys.executable, "-m", "firmware_py.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=_env(env),
                          cwd=tempfile.gettempdir())


def start_cli(args, *, env=None, stderr=subprocess.PIPE) -> subprocess.Popen:
    """Start ``python -m firmware_py.cli ARGS`` without waiting; ``stderr`` as for Popen
    (a file: the tests that need to know its device and inode, like journald's stream)."""
    return subprocess.Popen([sys.executable, "-m", "firmware_py.cli", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=stderr, text=True, env=_env(env),
                            cwd=tempfile.gettempdir())


def stop_cli(daemon, drain, pty) -> tuple[str, bytes]:
    """SIGTERM a daemon started with :func:`start_cli` (killed and reaped if it does not
    stop in 30 s), then its stderr (empty when it went to a file) and every byte it wrote
    to the pseudo-terminal ``pty`` that ``drain`` reads."""
    err = ""
    try:
        if daemon.poll() is None:
            daemon.send_signal(signal.SIGTERM)
        try:
            _, err = daemon.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            daemon.kill()
            _, err = daemon.communicate()
    finally:
        data = drain.stop()
        pty.close()
    return err or "", data


def opencl_available() -> bool:
    try:
        import emdflow

        return bool(emdflow.opencl_devices())
    except Exception:
        return False


def engine_backend() -> str:
    """Engine backend for process-level tests: OpenCL where a platform exists (CI installs
    PoCL), else the numpy reference; ``EMDFLOW_TEST_BACKEND`` overrides."""
    return os.environ.get("EMDFLOW_TEST_BACKEND") or ("opencl" if opencl_available() else "numpy")


class FaultySource:
    """A real source that fails the way a camera does: unplugged at read ``fail_at`` (a
    SourceError; the daemon then reopens a camera and stops a recording), or one frame of
    the wrong size at read ``bad_at``. ``live``: whether it stands for a camera (default:
    what the inner source is; a synthetic flight or a file is a recording)."""

    def __init__(self, inner, *, fail_at=None, bad_at=None, live=None):
        self.inner, self.fail_at, self.bad_at, self.reads = inner, fail_at, bad_at, 0
        self.live = inner.live if live is None else live

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def read(self):
        from firmware_py.sources import Frame, SourceError

        self.reads += 1
        if self.reads == self.fail_at:
            raise SourceError(f"{self.inner.uri}: read failed (USB camera unplugged)")
        frame = self.inner.read()
        if self.reads == self.bad_at:
            image = np.zeros((frame.image.shape[0] + 8, frame.image.shape[1]), np.uint8)
            return Frame(image, frame.timestamp_us, frame.capture_host_us, frame.index)
        return frame


#: Set in the child process that runs one isolated test (its pytest node id).
ISOLATED_ENV = "EMDFLOW_ISOLATED_TEST"


def run_isolated_from_native_crashes(request, *, timeout: float = 120.0, attempts: int = 3) -> bool:
    """Run the calling test's body in a child pytest; True in that child (run the body),
    False in the parent once the child passed (return at once).

    DepthAI 3.12's host-only pipeline (ReplayVideo + host ImageManip) corrupts the heap in
    about one of 4 000 start/stop cycles (measured here with a loop of open, read to the
    end, close: "corrupted double-linked list" in 13 of 170 runs of 300 cycles, with or
    without waiting for the pipeline to stop, keeping it alive or copying the frames).
    glibc then aborts, and DepthAI's crash handler deadlocks in malloc while the thread
    holds the GIL, so not even pytest-timeout can end the run: CI would hang. In a child
    process a crash or hang costs one retry (the child is killed after ``timeout`` s); a
    failing assertion fails at once, with the child's output.
    """
    if os.environ.get(ISOLATED_ENV) == request.node.nodeid:
        return True
    env = dict(os.environ, **{ISOLATED_ENV: request.node.nodeid})
    crashes = []
    for _ in range(attempts):
        try:
            # -P: the installed package (CI's), not a checkout in the working directory
            result = subprocess.run([sys.executable, "-P", "-m", "pytest", "-q", "-p", "no:cacheprovider",
                                     request.node.nodeid], cwd=str(request.config.rootpath), env=env,
                                    capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            crashes.append(f"hung for {timeout:g} s")
            continue
        if result.returncode == 0:
            return False
        if result.returncode < 0 or "corrupted" in result.stderr:
            crashes.append(f"killed by signal {-result.returncode}" if result.returncode < 0
                           else result.stderr.strip().splitlines()[-1])
            continue
        pytest.fail(f"the isolated run failed:\n{result.stdout[-4000:]}\n{result.stderr[-2000:]}")
    pytest.fail(f"DepthAI crashed or hung in all {attempts} isolated runs: {crashes}")
