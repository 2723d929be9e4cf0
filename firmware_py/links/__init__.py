"""Serial links from the flow summary to flight controllers.

One role per module: :mod:`.base` (sample/config types, scheduling), :mod:`.serial_port`
(non-blocking self-healing transport), :mod:`.mavlink` (ArduPilot/PX4), :mod:`.msp` (INAV),
:mod:`.message_log` (CSV / JSON-lines record). This package does not import emdflow: the
daemon converts the engine's summary into :class:`FlowSample`.

Example
-------
>>> link = open_link(LinkConfig(port="/dev/ttyAMA0", baud=115200, autopilot="ardupilot",
...                             focal_length_px=400.0))            # doctest: +SKIP
>>> link.submit(FlowSample(timestamp_us=t, capture_host_us=h, flow_x=0.3, flow_y=-1.2,
...                        quality=180))                           # doctest: +SKIP
>>> link.service(now_host_us)                                      # doctest: +SKIP
"""

from __future__ import annotations

from .base import FlowLink, FlowSample, LinkConfig, resolve_protocol

__all__ = ["open_link", "line_problem", "LinkConfig", "FlowSample", "FlowLink", "resolve_protocol"]


def _link_class(config: LinkConfig) -> type[FlowLink]:
    if resolve_protocol(config) == "msp":
        from .msp import MspLink

        return MspLink
    from .mavlink import MavlinkLink

    return MavlinkLink


def line_problem(config: LinkConfig) -> str | None:
    """Why ``config.baud`` cannot carry even the fewest flow reports the autopilots accept
    (:data:`~firmware_py.links.base.MIN_MESSAGE_RATE_HZ`), or None; the text continues
    "baud N is ". :func:`open_link` raises ValueError with it; ``emdflowd`` checks it at
    start-up (exit 2)."""
    return _link_class(config).line_problem(config)


def open_link(config: LinkConfig) -> FlowLink:
    """Create the link the config asks for and try to open its port.

    Parameters
    ----------
    config : LinkConfig
        Link settings.

    Returns
    -------
    FlowLink
        A :class:`~firmware_py.links.mavlink.MavlinkLink` or
        :class:`~firmware_py.links.msp.MspLink`. A missing or unopenable port is not an
        error: it is logged and retried with back-off from :meth:`FlowLink.service`.

    Raises
    ------
    ValueError
        For an invalid configuration (unknown autopilot/protocol, bad mounting, a baud rate
        too low for the flow messages: :func:`line_problem`, ...).
    """
    if not isinstance(config, LinkConfig):
        raise TypeError(f"open_link needs a LinkConfig, got {type(config).__name__}")
    return _link_class(config)(config)
