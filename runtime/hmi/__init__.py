"""The HMI over Modbus TCP: register map, server, curve upload, client and command line.

- :mod:`runtime.hmi.registers` — the register map, defined once as data, with the status encoder
  and decoder;
- :mod:`runtime.hmi.protocol` — Modbus TCP on the wire: MBAP framing, request PDUs, exceptions,
  device identification (pure);
- :mod:`runtime.hmi.link` — :class:`~runtime.hmi.link.MachineLink`, all the HMI process gets
  from the machine;
- :mod:`runtime.hmi.device` — the registers' semantics over a link: status, writes, commands,
  curve commits;
- :mod:`runtime.hmi.staging` — who may write the curve staging area;
- :mod:`runtime.hmi.library` — the program library (curve files numbered for the HMI);
- :mod:`runtime.hmi.upload` — curve staging: layout, CRC32, decoding and result codes;
- :mod:`runtime.hmi.server` — the asyncio server (``HmiServer``, ``serve_hmi``);
- :mod:`runtime.hmi.client` — a pymodbus client implementing the same protocol;
- :mod:`runtime.hmi.cli` — the ``softmotion hmi`` subcommand;
- :mod:`runtime.hmi.docgen` — writes ``docs/register-map.md`` from the map.
"""

from __future__ import annotations

from runtime.errors import RuntimeFault


class HmiError(RuntimeFault):
    """Base of every HMI error: server start-up, protocol mismatch, refused requests."""
