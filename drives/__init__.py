"""Drives: CANopen CiA-402 for servo axes in cyclic synchronous position mode.

The pure codec (``cia402``, ``objects``, ``emcy``), the bus factory, the master (boot, SDO
configuration, supervision, the per-cycle exchange), axis scaling mm <-> counts, and a simulated
CiA-402 drive (``drives.sim``). Knows nothing about curves.
"""
