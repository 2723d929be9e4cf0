"""Serial transport that never blocks the frame loop.

* The port is opened with pyserial (``timeout=0``), writes go straight to the file
  descriptor with ``os.write`` on the non-blocking descriptor: pyserial's own ``write`` with
  ``write_timeout=0`` spins on ``EAGAIN`` when the kernel buffer is full.
* Messages wait in a small bounded queue; a full queue drops the **oldest** whole message
  (counted), and a message older than ``max_age_s`` is dropped instead of sent — the link
  never lags behind real time. A message already partly written is always finished, so the
  wire never carries a torn frame.
* The kernel's tty buffer can hold seconds of data at low baud rates (4 kB at 57600 baud is
  0.7 s). Before each write the driver's output queue (``TIOCOUTQ``, pyserial's
  ``out_waiting``) is checked, and nothing more is handed over while it holds more than
  ``max_kernel_lag_s`` worth of bytes; our own queue then ages out instead.
* A vanished port (USB adapter unplugged, pty closed) closes the descriptor; :meth:`service`
  reopens it with exponential back-off (0.5 s doubling to 8 s). The back-off starts again
  from 0.5 s only once a port has stayed open for ``stable_after_s`` (5 s): a port that
  opens but fails at once (a dying adapter, a hung-up line) is retried ever more slowly, not
  every 0.5 s forever. The first loss is a warning, the first repeat says the port keeps
  failing; further repeats are debug lines with a warning summary every ``summary_s``
  (60 s). Times are the ``now_us`` the caller passes (the link's host clock). Every log line
  and error text names the port.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import time
from collections import deque
from dataclasses import dataclass, field

from ..clock import host_us

__all__ = ["SerialTransport", "OutgoingMessage", "port_problem"]

log = logging.getLogger(__name__)


def port_problem(port: str) -> str | None:
    """Why ``port`` can never be a serial port, or None. A path that does not exist (yet) is
    no problem: a USB adapter or a udev link appears when plugged in, and the link retries.
    The path must be absolute (a relative one depends on the working directory, which is
    ``/`` under systemd). A path that exists must be a character device, and on Linux not
    one that sysfs files under another subsystem than ``tty`` (``/dev/null`` is ``mem``:
    it fails every ioctl and would be retried for ever). The port is never opened here:
    opening a serial port raises DTR, which resets some flight controllers."""
    import stat

    if port != port.strip():
        # (a stray space from a config file: "/dev/ttyUSB0 " never appears, retried for ever)
        return "has leading or trailing whitespace; a device path has none"
    if "://" in port:
        # (pyserial's URLs, socket:// or rfc2217://, open through serial_for_url, which this
        # link does not use: such a port failed to open and was retried for ever)
        return "is a URL; the link writes to a serial device path (a tty or pseudo-terminal)"
    if os.name == "posix" and not os.path.isabs(port):
        # ('ttyUSB0' for /dev/ttyUSB0 never appeared in the working directory: retried for ever)
        if os.path.exists(port):  # (e.g. a socat link made in the current folder)
            return (f"is a relative path (to the working directory, / under systemd); give it as "
                    f"{os.path.abspath(port)}")
        bare = port[2:] if port.startswith("./") else port
        guess = "/" + bare if bare.startswith("dev/") else os.path.join("/dev", bare)
        if not os.path.exists(guess):
            return f"is a relative path; give the device's absolute path (there is no {guess} now)"
        if port_problem(guess) is None:
            return f"is a relative path; did you mean {guess}?"
        return "is a relative path; give the serial device's absolute path"
    try:
        st = os.stat(port)
    except OSError:
        return None  # missing: retried
    mode = st.st_mode
    if stat.S_ISCHR(mode):
        subsystem = _char_device_subsystem(st.st_rdev)
        if subsystem is None or subsystem == "tty":
            return None  # a tty, or sysfs cannot tell (pseudo-terminals have no entry): tried
        return (f"is a character device of the '{subsystem}' subsystem "
                f"({os.major(st.st_rdev)}:{os.minor(st.st_rdev)}), not a serial port (tty)")
    if stat.S_ISDIR(mode):
        return "is a directory, not a serial device"
    if stat.S_ISREG(mode):
        return "is a regular file, not a serial device"
    return "is not a character device (a serial port is one)"


def _char_device_subsystem(rdev: int) -> str | None:
    """The Linux sysfs subsystem of a character device (``tty`` for ttyS, ttyUSB, ttyACM,
    ttyAMA, /dev/tty, /dev/ptmx; ``mem`` for /dev/null), from the target of
    ``/sys/dev/char/MAJOR:MINOR/subsystem``; None when it cannot tell (no /sys, not Linux,
    no entry: the /dev/pts/N pseudo-terminals have none)."""
    try:
        target = os.readlink(f"/sys/dev/char/{os.major(rdev)}:{os.minor(rdev)}/subsystem")
    except (OSError, ValueError, AttributeError):
        return None
    return os.path.basename(target.rstrip("/")) or None


@dataclass(slots=True)
class OutgoingMessage:
    """One encoded message waiting for the port.

    Attributes
    ----------
    name : str
        Message name for counters and the log (``OPTICAL_FLOW``, ``HEARTBEAT``, ...).
    data : bytes
        The complete frame.
    queued_host_us : int
        Host monotonic time when it was queued, µs (set by :meth:`SerialTransport.enqueue`).
    capture_host_us : int or None
        Host time of the frame capture it reports, µs; None for messages without one.
    fields : dict
        Decoded values, for the message log.
    flow : bool
        A flow report (the autopilot times its interval from one to the next).
    marker : bool
        A flow report with quality 0 (the autopilot starts its next interval there and
        uses nothing else of it).
    not_before_host_us : int or None
        Host time before which it is not written, µs (a report paced on the capture clock,
        :mod:`firmware_py.links.pacing`); the messages behind it wait too. None: at once.
    written_after_due_us : int or None
        Set when a held message is handed to the OS: how long after ``not_before_host_us``,
        µs, on the clock of the :meth:`SerialTransport.pump` call that wrote it.
    """

    name: str
    data: bytes
    queued_host_us: int = 0
    capture_host_us: int | None = None
    fields: dict = field(default_factory=dict)
    flow: bool = False
    marker: bool = False
    not_before_host_us: int | None = None
    written_after_due_us: int | None = None


class SerialTransport:
    """Non-blocking, self-healing serial port writer/reader.

    Parameters
    ----------
    port : str or None
        Device path; None disables the port (messages are counted as dropped).
    baud : int
        Baud rate.
    stats : dict
        Counter dict shared with the link (updated in place).
    max_queue_messages : int
        Messages waiting in user space before the oldest is dropped.
    max_age_s : float
        A queued message older than this is dropped instead of written, s.
    max_kernel_lag_s : float
        Stop handing bytes to the kernel while its output queue holds more than this much
        transmit time, s.
    reopen_initial_s, reopen_max_s : float
        Back-off between reopen attempts: starts at the first, doubles up to the second, s.
    stable_after_s : float
        A port open this long without failing is healthy again: the back-off and the
        warnings start afresh at its next loss, s.
    summary_s : float
        While a port keeps failing right after each open, one warning summary per this
        many seconds (the single failures are debug lines), s.
    on_open : callable, optional
        Called after every successful (re)open, e.g. to queue a heartbeat; the messages
        queued while there was no port are dropped (counted as stale) before it, and the
        open is a flow gap (``on_flow_gap``).
    on_sent : callable, optional
        ``on_sent(message, host_us, latency_us)`` after a message was fully handed to the OS.
    on_flow_gap : callable, optional
        Called at every (re)open, and when a good flow report is dropped because one before
        it was (a stalled line: the queue overflowed or its messages went stale). INAV and PX4
        time a report's counts from the report before it, which the autopilot did not
        get: good reports are held back until a quality-0 one (``marker``) has gone out,
        which the caller should make its next.
    """

    def __init__(self, *, port: str | None, baud: int, stats: dict, max_queue_messages: int = 16,
                 max_age_s: float = 0.25, max_kernel_lag_s: float = 0.05,
                 reopen_initial_s: float = 0.5, reopen_max_s: float = 8.0,
                 stable_after_s: float = 5.0, summary_s: float = 60.0,
                 on_open=None, on_sent=None, on_flow_gap=None):
        self.port = port
        self.baud = int(baud)
        self.stats = stats
        self.max_queue_messages = max(1, int(max_queue_messages))
        self.max_age_us = int(max_age_s * 1e6)
        self.kernel_limit_bytes = max(64, int(self.baud / 10 * max_kernel_lag_s))
        self.reopen_initial_us = int(reopen_initial_s * 1e6)
        self.reopen_max_us = int(reopen_max_s * 1e6)
        self.stable_after_us = int(stable_after_s * 1e6)
        self.summary_us = int(summary_s * 1e6)
        self.on_open = on_open
        self.on_sent = on_sent
        self.on_flow_gap = on_flow_gap
        #: a flow report was dropped with the port open, and no quality-0 one has gone out since
        self._flow_gap = False
        self.latencies_us: deque[int] = deque(maxlen=4096)
        self._serial = None
        self._fd: int | None = None
        self._queue: deque[OutgoingMessage] = deque()
        self._current: OutgoingMessage | None = None
        self._current_offset = 0
        self._next_open_us = 0
        self._backoff_us = self.reopen_initial_us
        self._ever_opened = False
        self._failures_logged = 0
        self._opened_us: int | None = None    # when the open port was opened, None once healthy
        self._losses = 0                      # losses since the port was last healthy
        self._summary_due_us: int | None = None
        self._since_summary = 0               # repeated losses not yet in a summary
        self._out_waiting_works = True
        for key in ("bytes_written", "dropped_messages", "stale_messages", "reopen_count", "open_failures",
                    "write_errors", "read_errors", "rx_bytes"):
            stats.setdefault(key, 0)
        stats.setdefault("messages_sent", {})
        stats.setdefault("dropped_by_type", {})
        stats.setdefault("port_open", False)
        stats.setdefault("last_error", None)

    # -- open / close ----------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        """True while the port is open."""
        return self._fd is not None

    def try_open(self, now_us: int | None = None) -> bool:
        """Open the port now if it is closed and the back-off allows (never raises)."""
        if self._fd is not None or self.port is None:
            return self._fd is not None
        now_us = host_us() if now_us is None else now_us
        if now_us < self._next_open_us:
            return False
        import serial  # pyserial; imported late so the module loads without it for docs

        try:
            # exclusive (an advisory lock, flock): a second emdflowd on the same port, e.g.
            # one started by hand beside the service, must not interleave its messages
            ser = serial.Serial(self.port, self.baud, timeout=0, write_timeout=0, exclusive=True)
            fd = ser.fileno()
            os.set_blocking(fd, False)
        except (OSError, ValueError, serial.SerialException) as exc:
            self.stats["open_failures"] += 1
            if getattr(exc, "errno", None) in (errno.EAGAIN, errno.EWOULDBLOCK):
                why = ("in use: locked by another process (another emdflowd, e.g. the service while "
                       "one runs by hand?); not writing to it")
            else:
                why = str(exc)
            self._fail(f"cannot open serial port {self.port} at {self.baud} baud: {why}",
                       first=self._failures_logged == 0)
            self._failures_logged += 1
            self._next_open_us = now_us + self._backoff_us
            self._backoff_us = min(self.reopen_max_us, self._backoff_us * 2)
            return False
        self._serial, self._fd = ser, fd
        # (the back-off and the open-failure warnings start afresh only once the port has
        # stayed open: _note_stable)
        self._opened_us = now_us
        self._out_waiting_works = True
        self.stats["port_open"] = True
        if self._ever_opened:
            self.stats["reopen_count"] += 1
            # a port that keeps failing right after each open: its reopens are debug lines too
            (log.warning if self._losses < 2 else log.debug)(
                "serial port %s reopened (%d reopen(s) so far)", self.port, self.stats["reopen_count"])
        else:
            log.info("serial port %s open at %d baud", self.port, self.baud)
        self._ever_opened = True
        # What was queued while the port was away belongs to the connection before: sent now
        # it would be a burst of old reports, which INAV divides by
        # the time since the message before (1.6 ms apart at 115200 baud, not a report
        # period) and ArduPilot's MAVLink driver fuses as current.
        # The autopilot's next interval begins at the first flow report on this connection,
        # after the caller's pending one began: a flow gap, as after a drop on a stalled line.
        while self._queue:
            self._count_drop(self._queue.popleft(), stale=True)
        self._flow_gap = True
        if self.on_flow_gap is not None:
            self.on_flow_gap()
        if self.on_open is not None:
            self.on_open(now_us)
        return True

    def _fail(self, text: str, *, first: bool = True) -> None:
        self.stats["last_error"] = text
        # The first failure of a series is a warning, the retries are debug noise.
        (log.warning if first else log.debug)("%s", text)

    def _note_stable(self, now_us: int) -> None:
        """A port open for ``stable_after_s`` is healthy: its next loss starts the back-off
        and the warnings afresh."""
        if self._opened_us is None or now_us - self._opened_us < self.stable_after_us:
            return
        if self._losses > 1:
            log.info("serial port %s has stayed open for %.0f s after %d failure(s) in a row: healthy again",
                     self.port, self.stable_after_us / 1e6, self._losses)
        self._opened_us = None
        self._backoff_us = self.reopen_initial_us
        self._failures_logged = 0
        self._losses = self._since_summary = 0
        self._summary_due_us = None

    def _lost(self, what: str, exc: BaseException, now_us: int | None) -> None:
        """The port failed: close it and schedule a reopen, later after every failure that
        comes before the port was healthy again (:meth:`_note_stable`)."""
        now_us = host_us() if now_us is None else now_us
        self._note_stable(now_us)
        self._losses += 1
        text = f"serial port {self.port}: {what} failed ({exc}); closing, will reopen"
        if self._losses == 1:
            self._fail(text)
        else:
            # Reopened but failed again before it was healthy: not a recovery, so the
            # back-off keeps doubling, and only the first repeat is a warning.
            self._backoff_us = min(self.reopen_max_us, self._backoff_us * 2)
            if self._losses == 2:
                up_s = (now_us - self._opened_us) / 1e6 if self._opened_us is not None else 0.0
                self._fail(f"{text} (again, {up_s:.1f} s after reopening: the port fails soon after each "
                           f"open; retrying with back-off up to {self.reopen_max_us / 1e6:.0f} s, repeats "
                           f"are logged at debug level with a summary every {self.summary_us / 1e6:.0f} s)")
                self._summary_due_us = now_us + self.summary_us
            else:
                self._fail(text, first=False)
                self._since_summary += 1
                if now_us >= self._summary_due_us:
                    log.warning("serial port %s still fails soon after each open: %d failure(s) in the last "
                                "%.0f s (last: %s failed: %s); next attempt in %.0f s", self.port,
                                self._since_summary, (now_us - self._summary_due_us + self.summary_us) / 1e6,
                                what, exc, self._backoff_us / 1e6)
                    self._since_summary = 0
                    self._summary_due_us = now_us + self.summary_us
        self._opened_us = None
        self._close_fd()
        self._next_open_us = now_us + self._backoff_us
        # The partly written message is lost with the port: the peer's parser resynchronises.
        if self._current is not None:
            self._count_drop(self._current)
            self._current = None
            self._current_offset = 0

    def _close_fd(self) -> None:
        ser, self._serial, self._fd = self._serial, None, None
        self.stats["port_open"] = False
        if ser is not None:
            try:
                ser.close()
            except Exception as exc:  # noqa: BLE001 - a dead USB adapter can raise anything here
                log.debug("serial port %s: close: %s", self.port, exc)

    def close(self, *, flush_timeout_s: float = 0.2) -> None:
        """Write what is queued (best effort, bounded time) and close the port."""
        deadline = host_us() + int(flush_timeout_s * 1e6)
        while self._fd is not None and (self._queue or self._current) and host_us() < deadline:
            before = (len(self._queue), self._current_offset)
            self.pump()  # (a report held for its send time goes when due: at most 50 ms)
            if (len(self._queue), self._current_offset) == before:
                time.sleep(0.002)
        self._close_fd()

    # -- output ----------------------------------------------------------------------
    def enqueue(self, message: OutgoingMessage, *, first: bool = False) -> None:
        """Queue a message, dropping the oldest queued one when full (never blocks).

        ``first`` puts it before everything queued (the greeting heartbeat after an open).
        """
        # Age is measured on the real monotonic clock whatever clock the caller uses.
        message.queued_host_us = host_us()
        while len(self._queue) >= self.max_queue_messages:
            self._count_drop(self._queue.popleft())
        if first:
            self._queue.appendleft(message)
        else:
            self._queue.append(message)

    def _count_drop(self, message: OutgoingMessage, *, stale: bool = False) -> None:
        if message.flow and self._fd is not None:
            self._flow_gap = True  # (with no port, the reopen starts afresh)
        self.stats["dropped_messages"] += 1
        if stale:
            self.stats["stale_messages"] += 1
        per = self.stats["dropped_by_type"]
        per[message.name] = per.get(message.name, 0) + 1

    def _kernel_backlog(self) -> int:
        if not self._out_waiting_works or self._serial is None:
            return 0
        try:
            return int(self._serial.out_waiting)
        except Exception:  # noqa: BLE001 - some drivers do not implement TIOCOUTQ
            self._out_waiting_works = False
            return 0

    def pump(self, now_us: int | None = None) -> None:
        """Hand queued bytes to the OS as far as it accepts them without waiting.

        ``now_us``: the caller's host time (its clock times the messages' ``not_before_host_us``;
        default: now)."""
        if self._fd is None:
            # No port: keep only fresh messages so a reopen does not send stale data.
            now_us = host_us()
            while self._queue and now_us - self._queue[0].queued_host_us > self.max_age_us:
                self._count_drop(self._queue.popleft(), stale=True)
            return
        while True:
            if self._current is None:
                if not self._queue:
                    return
                if self._kernel_backlog() > self.kernel_limit_bytes:
                    return
                now = host_us()
                due = self._queue[0].not_before_host_us
                if due is not None and (now if now_us is None else now_us) < due:
                    return  # (paced: the caller wakes at next_due_us())
                message = self._queue.popleft()
                if due is not None:
                    message.written_after_due_us = (now if now_us is None else now_us) - due
                if now - message.queued_host_us > self.max_age_us:
                    self._count_drop(message, stale=True)
                    continue
                if message.flow and self._flow_gap:
                    if not message.marker:
                        # its counts follow a report the autopilot never got, which its
                        # interval would span: wait for a quality-0 report to restart it
                        self._count_drop(message)
                        if self.on_flow_gap is not None:
                            self.on_flow_gap()
                        continue
                    self._flow_gap = False
                self._current, self._current_offset = message, 0
            message = self._current
            try:
                n = os.write(self._fd, memoryview(message.data)[self._current_offset:])
            except BlockingIOError:
                return
            except InterruptedError:
                continue
            except OSError as exc:
                self.stats["write_errors"] += 1
                self._lost("write", exc, now_us)
                return
            self._current_offset += n
            if self._current_offset < len(message.data):
                return  # the kernel buffer is full; finish this message next time
            done_us = host_us()
            self._current, self._current_offset = None, 0
            self.stats["bytes_written"] += len(message.data)
            sent = self.stats["messages_sent"]
            sent[message.name] = sent.get(message.name, 0) + 1
            latency = None
            if message.capture_host_us is not None:
                latency = done_us - message.capture_host_us
                self.latencies_us.append(latency)
            if self.on_sent is not None:
                self.on_sent(message, done_us, latency)

    def release_held(self) -> None:
        """Let the queued messages held for their send time go with the next :meth:`pump`."""
        for message in self._queue:
            message.not_before_host_us = None
            message.fields.pop("paced_us", None)  # (not held after all)

    def next_due_us(self) -> int | None:
        """Host time (µs) at which :meth:`pump` has a held message to write, None if none
        is held or if it could not be written then anyway (no port, a message partly written,
        the kernel's buffer full: the caller's usual polling serves). A message at the head
        that is not held (queued while the kernel's buffer was full) is due now (0): held
        ones may wait behind it."""
        if self._current is not None or not self._queue or self._fd is None:
            return None
        if self._kernel_backlog() > self.kernel_limit_bytes:
            return None
        if self._queue[0].not_before_host_us is None:
            return 0 if any(m.not_before_host_us is not None for m in self._queue) else None
        return self._queue[0].not_before_host_us

    @property
    def queued_messages(self) -> int:
        """Messages waiting in user space (including a partly written one)."""
        return len(self._queue) + (self._current is not None)

    # -- input -----------------------------------------------------------------------
    def read_available(self, *, max_bytes: int = 65536, now_us: int | None = None) -> bytes:
        """Return whatever the peer sent, without waiting (b'' if nothing or no port)."""
        if self._fd is None:
            return b""
        chunks = []
        total = 0
        while total < max_bytes:
            try:
                chunk = os.read(self._fd, min(4096, max_bytes - total))
            except BlockingIOError:
                break
            except InterruptedError:
                continue
            except OSError as exc:
                if exc.errno == errno.EAGAIN:
                    break
                self.stats["read_errors"] += 1
                self._lost("read", exc, now_us)
                break
            if not chunk:
                # pyserial's timeout=0 makes an idle tty read return b''; only a hang-up
                # reported by poll() means the device is gone.
                if self._hung_up():
                    self.stats["read_errors"] += 1
                    self._lost("read", OSError(errno.EIO, "device hung up"), now_us)
                break
            chunks.append(chunk)
            total += len(chunk)
        data = b"".join(chunks)
        self.stats["rx_bytes"] += len(data)
        return data

    def _hung_up(self) -> bool:
        poller = select.poll()
        poller.register(self._fd, select.POLLIN | select.POLLHUP | select.POLLERR)
        try:
            events = poller.poll(0)
        except OSError:
            return True
        return any(ev & (select.POLLHUP | select.POLLERR | select.POLLNVAL) for _, ev in events)

    # -- housekeeping ----------------------------------------------------------------
    def service(self, now_us: int) -> None:
        """Reopen if needed and push queued bytes (never blocks, never raises)."""
        if self._fd is None:
            self.try_open(now_us)
        else:
            self._note_stable(now_us)
        self.pump(now_us)
