"""Stage description, raw-capture layout, HDR frame I/O, capture validation and the simulator."""
