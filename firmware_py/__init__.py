"""emdflow appliance firmware: frame sources, the daemon, and the serial links to autopilots."""
