"""Optional flight-debugging log of every message handed to the serial port.

One row per message: host time (µs, monotonic), message name, wire size, latency from frame
capture to write (µs, empty for heartbeats), and the message's fields. ``.csv`` gets a fixed
header (the union of all field names the links use; empty cells where a field does not
apply), anything else (``.jsonl``, ``.json``, ``.ndjson``) gets one JSON object per line.

The file is appended to: a restarted daemon (systemd after a watchdog kill or a hung camera)
continues the log of the flight instead of erasing it. The CSV header is written only into
a new or empty file; host times start again from the new process's monotonic clock.

Logging never stops the link: a write error disables the log with one warning.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os

__all__ = ["MessageLog", "LOG_COLUMNS"]

log = logging.getLogger(__name__)

#: Columns of the CSV form, in order.
LOG_COLUMNS = (
    "host_us", "message", "bytes", "latency_us", "seq",
    "time_usec", "integration_time_us", "integrated_x", "integrated_y",
    "flow_rate_x", "flow_rate_y", "flow_x", "flow_y", "motion_x", "motion_y",
    "quality", "distance", "sensor_id", "frames", "name", "value", "paced_us",
)

_FLUSH_EVERY_S = 1.0  # bounded loss on power-off without a flush per message on an SD card


class MessageLog:
    """Append-only log of sent messages.

    Parameters
    ----------
    path : str or os.PathLike
        ``*.csv`` for CSV, anything else for JSON lines. Parent folders are created.
    """

    def __init__(self, path):
        self.path = os.fspath(path)
        self.is_csv = self.path.lower().endswith(".csv")
        self.rows = 0
        self._open()

    def _open(self) -> None:
        parent = os.path.dirname(self.path)
        if parent:
            os.makedirs(parent, exist_ok=True)
        if self.is_csv:
            self._set_aside_other_columns()
        self._file = open(self.path, "a", newline="" if self.is_csv else None, encoding="utf-8")
        self._writer = None
        if self._file.tell() > 0:
            self._end_torn_line()
        if self.is_csv:
            self._writer = csv.DictWriter(self._file, fieldnames=LOG_COLUMNS, extrasaction="ignore")
            if self._file.tell() == 0:
                self._writer.writeheader()
        self._last_flush_us = None

    def _set_aside_other_columns(self) -> None:
        """A CSV log whose header is not :data:`LOG_COLUMNS` (written by an earlier version,
        whose columns were fewer) is renamed to ``<path>.old`` with a warning: rows appended
        under it would not match its header."""
        try:
            with open(self.path, encoding="utf-8", errors="replace") as f:
                header = f.readline().rstrip("\r\n")
        except OSError:
            return  # (no file yet, or unreadable: opening it says so)
        if header and header != ",".join(LOG_COLUMNS):
            old = self.path + ".old"
            os.replace(self.path, old)
            log.warning("message log %s: its columns are another version's; moved to %s, a new log starts",
                        self.path, old)

    def _end_torn_line(self) -> None:
        """Terminate a last row cut off by a power loss, so the next row starts on its own line."""
        with open(self.path, "rb") as f:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                self._file.write("\n")

    def write(self, *, host_us: int, message: str, size: int, latency_us: int | None, fields: dict) -> None:
        """Record one message (never raises)."""
        if self._file is None:
            return
        row = {"host_us": int(host_us), "message": message, "bytes": int(size),
               "latency_us": None if latency_us is None else int(latency_us)}
        for key, value in fields.items():
            # JSON has no NaN: the gyro fields of OPTICAL_FLOW_RAD are NaN on purpose.
            row[key] = None if isinstance(value, float) and not math.isfinite(value) else value
        try:
            if self._writer is not None:
                self._writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
            else:
                self._file.write(json.dumps(row, separators=(",", ":")) + "\n")
            self.rows += 1
            if self._last_flush_us is None or host_us - self._last_flush_us >= _FLUSH_EVERY_S * 1e6:
                self._file.flush()
                self._last_flush_us = host_us
        except (OSError, ValueError) as exc:
            log.warning("message log %s: %s; logging disabled", self.path, exc)
            self._close_quietly()

    def reopen(self) -> None:
        """Close the file and open ``path`` afresh (never raises): after a log rotation
        (``logrotate`` moves the file, then sends SIGHUP) the rows go to a new file with its
        own CSV header; a log disabled by a write error starts again."""
        self._close_quietly()
        try:
            self._open()
        except OSError as exc:
            log.warning("message log %s cannot be reopened: %s; logging disabled", self.path, exc)
            self._file = None

    def close(self) -> None:
        """Flush and close (never raises)."""
        self._close_quietly()

    def _close_quietly(self) -> None:
        f, self._file = self._file, None
        if f is not None:
            try:
                f.close()
            except OSError as exc:
                log.warning("message log %s: %s", self.path, exc)
