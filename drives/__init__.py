"""Drives: CANopen CiA-402 for servo axes in cyclic synchronous position mode.

The pure codec (``cia402``, ``objects``, ``emcy``, ``pdo``), the bus factory, the master run by
the cycle (``master``: the period's calls; ``boot``: boot, configuration and shutdown of each
drive; ``sdo_client``: non-blocking SDO; ``sync``: SYNC and the matching of feedback to it;
``guarding``: heartbeat producer and node guarding; ``monitor``: faults and fault events), axis
scaling mm <-> counts, and a simulated CiA-402 drive with the quirks of other vendors' drives
(``drives.sim``). Knows nothing about curves. ``docs/drives.md`` tells how to connect real drives.
"""
