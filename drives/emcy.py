"""EMCY frames: the wire layout, the codes the drives use and their readable descriptions.

Source: CiA 301 §7.2.7 (EMCY object, COB-ID 0x80 + node-ID, error code table) and CiA 402
(0x8611 following error). Frame layout: error code (U16), error register 0x1001 (U8), five bytes
of manufacturer-specific data; little endian.

Threading: constants and pure functions; safe from any thread.
Invariant: :func:`describe_emcy` always returns a non-empty text (exact code first, then the
longest matching class, then "unknown").
"""

from __future__ import annotations

import struct
from typing import Final

#: Error code, error register, manufacturer-specific data.
EMCY_STRUCT: Final = struct.Struct("<HB5s")

# Codes used by the drives package.
EMCY_ERROR_RESET: Final[int] = 0x0000
EMCY_GENERIC: Final[int] = 0x1000
EMCY_OVERCURRENT: Final[int] = 0x2310
EMCY_EXCESS_TEMPERATURE_DEVICE: Final[int] = 0x4210
EMCY_HARDWARE: Final[int] = 0x5000
EMCY_COMMUNICATION: Final[int] = 0x8100  # SYNC timeout
EMCY_CAN_OVERRUN: Final[int] = 0x8110
EMCY_ERROR_PASSIVE: Final[int] = 0x8120
EMCY_HEARTBEAT: Final[int] = 0x8130  # heartbeat / life guard error
EMCY_BUS_OFF_RECOVERED: Final[int] = 0x8140
EMCY_PDO_LENGTH: Final[int] = 0x8210  # PDO not processed due to length error
EMCY_PDO_LENGTH_EXCEEDED: Final[int] = 0x8220
EMCY_SYNC_LENGTH: Final[int] = 0x8240
EMCY_RPDO_TIMEOUT: Final[int] = 0x8250
EMCY_FOLLOWING_ERROR: Final[int] = 0x8611

# Error register 0x1001 bits (CiA 301).
ERROR_REGISTER_GENERIC: Final[int] = 1 << 0
ERROR_REGISTER_CURRENT: Final[int] = 1 << 1
ERROR_REGISTER_VOLTAGE: Final[int] = 1 << 2
ERROR_REGISTER_TEMPERATURE: Final[int] = 1 << 3
ERROR_REGISTER_COMMUNICATION: Final[int] = 1 << 4
ERROR_REGISTER_PROFILE: Final[int] = 1 << 5
ERROR_REGISTER_MANUFACTURER: Final[int] = 1 << 7

_EXACT: Final[dict[int, str]] = {
    EMCY_ERROR_RESET: "error reset / no error",
    EMCY_OVERCURRENT: "continuous over-current",
    EMCY_EXCESS_TEMPERATURE_DEVICE: "excess temperature device",
    EMCY_HARDWARE: "device hardware",
    EMCY_COMMUNICATION: "communication (SYNC timeout)",
    EMCY_CAN_OVERRUN: "CAN overrun (objects lost)",
    EMCY_ERROR_PASSIVE: "CAN in error passive mode",
    EMCY_HEARTBEAT: "heartbeat / life guard error",
    EMCY_BUS_OFF_RECOVERED: "recovered from bus-off",
    EMCY_PDO_LENGTH: "PDO not processed due to length error",
    EMCY_PDO_LENGTH_EXCEEDED: "PDO length exceeded",
    EMCY_SYNC_LENGTH: "unexpected SYNC data length",
    EMCY_RPDO_TIMEOUT: "RPDO timeout",
    EMCY_FOLLOWING_ERROR: "following error",
}

# (code, mask, description), most specific first, as CiA 301 table 21 groups the codes.
_CLASSES: Final[tuple[tuple[int, int, str], ...]] = (
    (0x0000, 0xFF00, "error reset / no error"),
    (0x1000, 0xFF00, "generic error"),
    (0x2000, 0xF000, "current"),
    (0x3000, 0xF000, "voltage"),
    (0x4000, 0xF000, "temperature"),
    (0x5000, 0xFF00, "device hardware"),
    (0x6000, 0xF000, "device software"),
    (0x7000, 0xFF00, "additional modules"),
    (0x8100, 0xFF00, "communication"),
    (0x8200, 0xFF00, "protocol error"),
    (0x8600, 0xFF00, "positioning controller"),
    (0x8000, 0xF000, "monitoring"),
    (0x9000, 0xFF00, "external error"),
    (0xF000, 0xFF00, "additional functions"),
    (0xFF00, 0xFF00, "device specific"),
)


def describe_emcy(code: int) -> str:
    """Return a readable description of an EMCY error code, e.g. 0x8611 -> "following error"."""
    exact = _EXACT.get(code)
    if exact is not None:
        return exact
    for value, mask, description in _CLASSES:
        if code & mask == value:
            return description
    return "unknown"


def pack_emcy(code: int, register: int, data: bytes = b"") -> bytes:
    """Encode an EMCY frame payload (8 bytes; ``data`` is padded or must fit in 5 bytes).

    :raises ValueError: if ``data`` is longer than 5 bytes.
    """
    if len(data) > 5:
        raise ValueError(f"EMCY manufacturer data: {len(data)} bytes, must be <= 5")
    return EMCY_STRUCT.pack(code, register, data)


def unpack_emcy(payload: bytes) -> tuple[int, int, bytes]:
    """Decode an EMCY frame payload into ``(code, register, data)``.

    :raises ValueError: if the payload is not 8 bytes long.
    """
    if len(payload) != EMCY_STRUCT.size:
        raise ValueError(f"EMCY frame: {len(payload)} bytes, must be {EMCY_STRUCT.size}")
    return EMCY_STRUCT.unpack(payload)
