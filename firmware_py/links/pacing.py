"""When a flow report goes on the wire: on the capture clock, a fixed delay after its frame.

An autopilot that divides a report's counts by the time since the previous report *arrived*
(INAV's MSP flow: ``rate = motion × 1e6 / Δt_us``) reads the processing time's variation
as flow-rate noise when each report goes out as soon as its frame is processed: a frame
that took 3 ms longer makes one interval 3 ms longer and the next 3 ms shorter, at 50 Hz
±15 % on two rates. Sent ``delay`` after its newest frame's capture instead, the reports
arrive as far apart as their frames were captured, and the counts match the time INAV
divides them by. The daemon's report writer thread sends them when due, whatever its frame
loop is doing (most of a frame period it is in the engine).

:class:`ReportPacer` picks that delay: fixed, or (automatic) just above the slowest of the
recent ready times (capture to the report's queueing: delivery, waiting, engine, summary;
:data:`AUTO_QUANTILE` of the last :data:`AUTO_WINDOW` reports plus :data:`AUTO_MARGIN_US`),
never more than :data:`AUTO_MAX_US`. Each change of the delay moves one arrival by the
change: it is raised at once when frames get slower (or each report would be late), and
lowered by :data:`AUTO_STEP_DOWN_US` a report once the quantile is well below it (fewer
than 1 % of the window as slow as before). A report
ready after its due time goes out at once, and one written more than :data:`LATE_US` after
it (a stalled writer) is counted too: both arrive late, as every report did before.
Frames that do not come in real time (a recording read as fast as it decodes, a test
feeding frames in a loop: their host times advance less than half as fast as their capture
times) are not paced: there is no capture clock to keep to, and holding them would only
fill the queue (the caller then lets the reports it holds go, :attr:`ReportPacer.real_time`).
"""

from __future__ import annotations

from collections import deque

__all__ = ["ReportPacer", "AUTO_WINDOW", "AUTO_QUANTILE", "AUTO_MARGIN_US", "AUTO_MAX_US",
           "AUTO_STEP_DOWN_US", "LATE_US"]

#: Reports whose ready times the automatic delay looks at (5 s at 50 Hz).
AUTO_WINDOW = 256
#: The share of those the delay covers: the slowest 1 % go out late, as they are ready.
AUTO_QUANTILE = 0.99
#: Added to that quantile: scheduling and the write itself, µs.
AUTO_MARGIN_US = 1000
#: The automatic delay's ceiling, µs: INAV compensates rotation with its gyro over the
#: arrival interval, so a later report compares its flow with a later gyro window; past
#: this, that costs more than steadier intervals gain (a fixed delay may go to 50 ms).
AUTO_MAX_US = 25_000
#: Ready times seen before the automatic delay follows the quantile (until then: the
#: slowest seen, plus the margin).
AUTO_WARMUP = 16
#: Most the automatic delay is lowered by from one report to the next, µs: each report's
#: interval is that much shorter than its counts' (2.5 % at 50 Hz).
AUTO_STEP_DOWN_US = 500
#: A report written more than this after its due time counts as late, µs.
LATE_US = 2000


def _quantile(values, q: float) -> float:
    """``numpy.quantile(values, q)`` (linear, and its lerp's two forms, bit for bit) of a
    few hundred ints by a sort: a sixth of numpy's time per report (~10 against ~60 µs),
    spent under the link's lock, which the report writer waits for."""
    s = sorted(values)
    position = q * (len(s) - 1)
    lo = int(position)
    t = position - lo
    a, b = s[lo], s[min(lo + 1, len(s) - 1)]
    return b - (b - a) * (1 - t) if t >= 0.5 else a + (b - a) * t


class ReportPacer:
    """Send times of flow reports on the capture clock (see the module docstring).

    Parameters
    ----------
    delay_us : int or None
        Fixed delay after the newest frame's capture, µs; 0: no pacing (each report goes out
        when processed); None: automatic.
    """

    def __init__(self, delay_us: int | None):
        if delay_us is not None and delay_us < 0:
            raise ValueError(f"report delay must be >= 0 µs or automatic (None), got {delay_us}")
        self.fixed_us = None if delay_us is None else int(delay_us)
        self._ready_us: deque[int] = deque(maxlen=AUTO_WINDOW)
        self._auto_us = 0
        self._previous: tuple[int, int] | None = None  # (capture_host_us, capture_us) of the last report
        #: whether the last report's frames came in real time (False: not paced)
        self.real_time = True
        #: reports ready after their due time (sent at once) or written > LATE_US after it
        self.late = 0

    @property
    def delay_us(self) -> int:
        """The current delay after capture, µs (0: not pacing)."""
        return self.fixed_us if self.fixed_us is not None else self._auto_us

    def send_at(self, capture_host_us: int | None, capture_us: int, now_us: int) -> int | None:
        """Host time (µs) to hand the report of a frame captured at ``capture_host_us`` (host
        clock; ``capture_us`` on the capture clock) to the port, which is ready at
        ``now_us``; None: at once (no capture time: a keep-alive; not pacing; frames that
        do not come in real time). The first report is paced: the one after it counts from
        its arrival."""
        if capture_host_us is None or self.fixed_us == 0:
            return None
        previous, self._previous = self._previous, (int(capture_host_us), int(capture_us))
        self.real_time = previous is None or 2 * (capture_host_us - previous[0]) >= capture_us - previous[1]
        if not self.real_time:
            return None
        if self.fixed_us is None:
            self._learn(max(0, int(now_us) - int(capture_host_us)))
        due = int(capture_host_us) + self.delay_us
        if due < now_us:
            self.late += 1
            return None
        return due

    def written(self, after_due_us: int) -> None:
        """A held report was written ``after_due_us`` µs after its due time."""
        if after_due_us > LATE_US:
            self.late += 1

    def _learn(self, ready_us: int) -> None:
        self._ready_us.append(ready_us)
        if len(self._ready_us) < AUTO_WARMUP:
            wanted = max(self._ready_us) + AUTO_MARGIN_US
        else:
            wanted = int(_quantile(self._ready_us, AUTO_QUANTILE)) + AUTO_MARGIN_US
        wanted = min(AUTO_MAX_US, wanted)
        if wanted > self._auto_us:  # slower: follow at once, or every report is late
            self._auto_us = wanted
        elif self._auto_us - wanted > AUTO_MARGIN_US:
            # (the quantile is of the whole window: the slow frames have (nearly) left it,
            # this is no lull between two slow spells)
            self._auto_us = max(wanted, self._auto_us - AUTO_STEP_DOWN_US)
