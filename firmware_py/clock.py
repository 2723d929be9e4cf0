"""The one host clock the appliance stamps with: frame capture, the link's queue, latency."""

from __future__ import annotations

import time

__all__ = ["host_us"]


def host_us() -> int:
    """Host monotonic clock in microseconds (``CLOCK_MONOTONIC``, as V4L2 and DepthAI stamp
    their frames)."""
    return time.monotonic_ns() // 1000
