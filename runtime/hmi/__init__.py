"""The HMI over Modbus TCP: register map, server, curve upload, client and command line.

- :mod:`runtime.hmi.registers` — the register map, defined once as data, with the status encoder
  and decoder;
- :mod:`runtime.hmi.upload` — curve staging: layout, CRC32, decoding and result codes;
- :mod:`runtime.hmi.server` — the pymodbus server in its own thread and event loop;
- :mod:`runtime.hmi.client` — a pymodbus client implementing the same protocol;
- :mod:`runtime.hmi.cli` — the ``softmotion hmi`` subcommand;
- :mod:`runtime.hmi.docgen` — writes ``docs/register-map.md`` from the map.
"""

from __future__ import annotations

from runtime.errors import RuntimeFault


class HmiError(RuntimeFault):
    """Base of every HMI error: server start-up, protocol mismatch, refused requests."""
