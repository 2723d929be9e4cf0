"""Real pseudo-terminal pairs for the link tests (no serial mocks).

The link opens the pty's slave end through a symlink, so a test can close the pair (the
device vanishes, like an unplugged USB adapter) and later point the same path at a new pair.
The test reads and writes the master end, standing in for the autopilot.
"""

from __future__ import annotations

import errno
import os
import time

from firmware_py.clock import host_us  # noqa: F401 - the clock the link tests stamp with


class PtyPeer:
    """The autopilot's end of a pty pair whose slave is reachable at ``path``.

    Parameters
    ----------
    path : str
        Symlink path the link is configured with.
    """

    def __init__(self, path: str):
        self.path = str(path)
        self.master: int | None = None
        self.open()

    def open(self) -> None:
        """Create a new pty pair and point ``path`` at its slave."""
        master, slave = os.openpty()
        name = os.ttyname(slave)
        os.close(slave)  # the link opens the slave itself
        os.set_blocking(master, False)
        tmp = self.path + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(name, tmp)
        os.replace(tmp, self.path)
        self.master = master

    def close(self) -> None:
        """Close the master: the slave device disappears, the link's writes fail with EIO."""
        if self.master is not None:
            os.close(self.master)
            self.master = None

    def read(self) -> bytes:
        """Everything the link has written so far (never waits)."""
        if self.master is None:
            return b""
        chunks = []
        while True:
            try:
                chunk = os.read(self.master, 65536)
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno == errno.EIO:  # no slave open at the moment
                    break
                raise
            if not chunk:
                break
            chunks.append(chunk)
        return b"".join(chunks)

    def write(self, data: bytes) -> int:
        """Send bytes to the link (as the autopilot)."""
        written = 0
        while written < len(data):
            try:
                written += os.write(self.master, data[written:])
            except BlockingIOError:
                time.sleep(0.001)
        return written


class FrameFeeder:
    """Submit synthetic summaries at a fixed frame rate (capture timestamps, not wall clock).

    Parameters
    ----------
    link : FlowLink
        Link under test.
    fps : float
        Nominal frame rate of the synthetic camera.
    start_us : int
        Capture timestamp of the first frame.
    """

    def __init__(self, link, *, fps: float = 100.0, start_us: int = 1_000_000):
        from firmware_py.links import FlowSample

        self._sample = FlowSample
        self.link = link
        self.interval_us = int(round(1e6 / fps))
        self.t_us = start_us

    def frames(self, count: int, *, flow_x: float = 0.0, flow_y: float = 0.0, quality: int = 200,
               skip_every: int = 0, peer: PtyPeer | None = None, sink: bytearray | None = None) -> None:
        """Submit ``count`` frames; with ``skip_every`` = k every k-th frame is dropped (the
        next one then carries two frames of motion, as the engine would report it)."""
        for i in range(count):
            step = 1
            if skip_every and i % skip_every == skip_every - 1:
                step = 2
            self.t_us += step * self.interval_us
            now = host_us()
            self.link.submit(self._sample(timestamp_us=self.t_us, capture_host_us=now,
                                          flow_x=flow_x * step, flow_y=flow_y * step, quality=quality))
            self.link.service(now)
            if peer is not None and sink is not None:
                sink.extend(peer.read())


def fly_and_close(link, peer: PtyPeer, count: int, *, fps: float, **frame_kw) -> bytes:
    """Feed ``count`` frames to ``link`` (see :meth:`FrameFeeder.frames`), close it, and
    return every byte the peer received, including what was flushed on close."""
    sink = bytearray()
    try:
        FrameFeeder(link, fps=fps).frames(count, peer=peer, sink=sink, **frame_kw)
    finally:
        link.close()
    sink.extend(peer.read())
    return bytes(sink)
