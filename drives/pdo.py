"""PDO layouts of a CSP axis: what the configuration asks for, what the drive has, and the codecs.

Source: CiA 301 §7.2.2 and §7.5.2.35-38 (RPDO communication 0x1400 + n - 1 and mapping
0x1600 + n - 1, TPDO communication 0x1800 + n - 1 and mapping 0x1A00 + n - 1; sub1 COB-ID with
bit 31 "PDO not valid" and bit 30 "no RTR", sub2 transmission type, mapping entries
``index << 16 | subindex << 8 | bits``) and the CiA 402 process data of CSP (RPDO: controlword
0x6040, target position 0x607A, optionally modes of operation 0x6060; TPDO: statusword 0x6041,
position actual 0x6064, optionally following error actual 0x60F4, error code 0x603F, modes of
operation display 0x6061, velocity actual 0x606C).

Units: bytes and bits as the mapping gives them; COB-IDs 11-bit.

Threading: immutable records and codecs; the RPDO codec packs into its own preallocated buffer,
so one codec belongs to one axis of one cycle thread.

Invariants: a layout is what was read back from the drive, never what was only written; a codec
is built only from a layout that carries the required objects (:func:`missing_objects`), so the
cycle never meets a PDO without statusword or position.

Not done: bit-granular or dummy mapping entries (a layout with an entry that is not a whole
number of bytes is refused), extended (29-bit) COB-IDs, more than 8 bytes per PDO (CAN FD).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Final

from drives.objects import (
    COB_ID_MASK,
    CONTROLWORD,
    ERROR_CODE,
    FOLLOWING_ERROR_ACTUAL,
    MODE_CSP,
    MODES_OF_OPERATION,
    MODES_OF_OPERATION_DISPLAY,
    POSITION_ACTUAL,
    PROCESS_ENTRIES,
    RPDO1_COB_ID_BASE,
    RPDO_COMM,
    RPDO_MAP,
    STATUSWORD,
    TARGET_POSITION,
    TPDO1_COB_ID_BASE,
    TPDO_COMM,
    TPDO_MAP,
    TRANS_TYPE_EVENT_PROFILE,
    TRANS_TYPE_EVENT_VENDOR,
    TRANS_TYPE_SYNC_MAX,
    VELOCITY_ACTUAL,
    describe_object,
)

#: Highest PDO number (CiA 301: 512 per direction).
PDO_NUMBER_MAX: Final[int] = 512
#: Data bytes of a classic CAN frame.
PDO_MAX_BYTES: Final[int] = 8
#: TPDO transmission type of the feedback: sent at every SYNC.
TRANS_TYPE_EVERY_SYNC: Final[int] = 1
#: COB-ID bit 29: 29-bit identifier.
COB_ID_EXTENDED: Final[int] = 1 << 29

RPDO_REQUIRED: Final = (CONTROLWORD, TARGET_POSITION)
RPDO_OPTIONAL: Final = (MODES_OF_OPERATION,)
TPDO_REQUIRED: Final = (STATUSWORD, POSITION_ACTUAL)
TPDO_OPTIONAL: Final = (
    FOLLOWING_ERROR_ACTUAL,
    ERROR_CODE,
    MODES_OF_OPERATION_DISPLAY,
    VELOCITY_ACTUAL,
)


class Direction(Enum):
    """RPDO (master -> drive) or TPDO (drive -> master), with their object ranges."""

    RPDO = (RPDO_COMM, RPDO_MAP, RPDO1_COB_ID_BASE)
    TPDO = (TPDO_COMM, TPDO_MAP, TPDO1_COB_ID_BASE)

    @property
    def comm_base(self) -> int:
        return self.value[0]

    @property
    def map_base(self) -> int:
        return self.value[1]

    def comm_index(self, number: int) -> int:
        return self.value[0] + number - 1

    def map_index(self, number: int) -> int:
        return self.value[1] + number - 1

    def predefined_cob_id(self, number: int, node_id: int) -> int | None:
        """The CiA 301 predefined COB-ID of PDOs 1-4; None for the others."""
        if number > 4:
            return None
        return self.value[2] + (number - 1) * 0x100 + node_id


class MappingPolicy(Enum):
    """How the boot treats the drive's PDO mapping.

    AUTO keeps the drive's mapping of a PDO when it already carries every object asked for,
    writes the configured one otherwise, and keeps a read-only mapping that still carries the
    required objects (the optional ones it lacks are reported). WRITE always writes the
    configured mapping (a read-only one is treated as in AUTO). KEEP never writes a mapping.
    """

    AUTO = "auto"
    WRITE = "write"
    KEEP = "keep"


@dataclass(frozen=True)
class PdoSpec:
    """One PDO as the configuration asks for it.

    :param number: PDO number, 1..512 (RPDO n is 0x1400 + n - 1 / 0x1600 + n - 1).
    :param objects: object indices (sub-index 0) in mapping order.
    :param cob_id: 11-bit COB-ID; None keeps the drive's.
    """

    number: int
    objects: tuple[int, ...]
    cob_id: int | None = None

    def __post_init__(self) -> None:
        if not 1 <= self.number <= PDO_NUMBER_MAX:
            raise ValueError(f"PDO number {self.number}: must be in 1..{PDO_NUMBER_MAX}")
        if self.cob_id is not None and not 0x001 <= self.cob_id <= COB_ID_MASK:
            raise ValueError(f"PDO {self.number}: cob_id 0x{self.cob_id:X}, must be 0x1..0x7FF")
        if len(set(self.objects)) != len(self.objects):
            raise ValueError(f"PDO {self.number}: objects repeat an index")
        for index in self.objects:
            if index not in PROCESS_ENTRIES:
                known = ", ".join(describe_object(i) for i in sorted(PROCESS_ENTRIES))
                raise ValueError(f"PDO {self.number}: object 0x{index:04X} is not one of {known}")
        size = sum(PROCESS_ENTRIES[index].codec.size for index in self.objects)
        if size > PDO_MAX_BYTES:
            raise ValueError(
                f"PDO {self.number}: objects take {size} bytes, at most {PDO_MAX_BYTES} fit a frame"
            )

    def mapping_entries(self) -> tuple[int, ...]:
        """The mapping entries (0x16xx/0x1Axx sub 1..n) of ``objects``."""
        return tuple(index << 16 | PROCESS_ENTRIES[index].bits for index in self.objects)


@dataclass(frozen=True)
class AxisPdoSpec:
    """The PDOs of one axis: one RPDO for the commands, one or more TPDOs for the feedback.

    :raises ValueError: an object that is not process data of CSP, a required object missing,
        TPDO numbers repeated, or a PDO longer than 8 bytes.
    """

    mapping: MappingPolicy = MappingPolicy.AUTO
    rpdo: PdoSpec = PdoSpec(1, RPDO_REQUIRED)
    tpdos: tuple[PdoSpec, ...] = (PdoSpec(1, TPDO_REQUIRED),)

    def __post_init__(self) -> None:
        _check_objects("RPDO", [self.rpdo], RPDO_REQUIRED, RPDO_OPTIONAL)
        _check_objects("TPDO", self.tpdos, TPDO_REQUIRED, TPDO_OPTIONAL)
        numbers = [pdo.number for pdo in self.tpdos]
        if len(set(numbers)) != len(numbers):
            raise ValueError(f"TPDO numbers {numbers} repeat a PDO")


def _check_objects(
    label: str, pdos: Sequence[PdoSpec], required: Iterable[int], optional: Iterable[int]
) -> None:
    if not pdos:
        raise ValueError(f"{label}: at least one PDO is required")
    allowed = set(required) | set(optional)
    mapped = [index for pdo in pdos for index in pdo.objects]
    for index in mapped:
        if index not in allowed:
            known = ", ".join(describe_object(i) for i in sorted(allowed))
            raise ValueError(f"{label}: object 0x{index:04X} is not one of {known}")
    for index in required:
        if index not in mapped:
            raise ValueError(f"{label}: {describe_object(index)} is required")


@dataclass(frozen=True)
class PdoLayout:
    """One PDO as read from the drive: COB-ID, validity, transmission type, mapping."""

    direction: Direction
    number: int
    cob_id: int
    """11-bit identifier (sub1 & 0x7FF)."""
    valid: bool
    trans_type: int
    entries: tuple[tuple[int, int, int], ...]
    """(index, subindex, bits) per mapped object, in order."""

    @property
    def label(self) -> str:
        return f"{self.direction.name}{self.number}"

    @property
    def objects(self) -> tuple[int, ...]:
        return tuple(index for index, _, _ in self.entries)

    @property
    def size(self) -> int:
        """Payload bytes."""
        return sum(bits for _, _, bits in self.entries) // 8

    def carries(self, indices: Iterable[int]) -> bool:
        return set(indices) <= set(self.objects)

    def describe(self) -> str:
        """``TPDO1 on 0x181 (type 1): 0x6041, 0x6064``."""
        mapped = ", ".join(f"0x{index:04X}" for index in self.objects) or "nothing"
        state = "" if self.valid else ", not valid"
        return f"{self.label} on 0x{self.cob_id:03X} (type {self.trans_type}{state}): {mapped}"


def missing_objects(layouts: Sequence[PdoLayout], required: Iterable[int]) -> tuple[int, ...]:
    """The required objects none of ``layouts`` carries, in the order given."""
    carried = {index for layout in layouts for index in layout.objects}
    return tuple(index for index in required if index not in carried)


def rpdo_type_usable(trans_type: int) -> bool:
    """Whether an RPDO of this transmission type takes the target of each period: synchronous
    types apply it at the SYNC that follows it, event types at once, before that SYNC."""
    return trans_type <= TRANS_TYPE_SYNC_MAX or trans_type in (
        TRANS_TYPE_EVENT_VENDOR,
        TRANS_TYPE_EVENT_PROFILE,
    )


def layout_problem(layout: PdoLayout) -> str | None:
    """Why the cycle cannot use ``layout`` (not valid, wrong type, odd entries), or None."""
    if not layout.valid:
        return f"{layout.label} is not valid (COB-ID bit 31 set)"
    if layout.direction is Direction.TPDO and layout.trans_type != TRANS_TYPE_EVERY_SYNC:
        return (
            f"{layout.label} transmission type {layout.trans_type}: the feedback needs "
            f"{TRANS_TYPE_EVERY_SYNC} (every SYNC)"
        )
    if layout.direction is Direction.RPDO and not rpdo_type_usable(layout.trans_type):
        return f"{layout.label} transmission type {layout.trans_type} is reserved"
    for index, subindex, bits in layout.entries:
        if bits % 8:
            return f"{layout.label} maps 0x{index:04X}:{subindex:02X} with {bits} bits"
    if layout.size > PDO_MAX_BYTES:
        return f"{layout.label} maps {layout.size} bytes"
    return None


def _codec_format(layout: PdoLayout) -> tuple[str, dict[int, int]]:
    """A struct format covering the payload (pads for entries the master does not use) and
    each known object's position in the unpacked tuple."""
    parts = ["<"]
    positions: dict[int, int] = {}
    for index, subindex, bits in layout.entries:
        entry = PROCESS_ENTRIES.get(index)
        if entry is not None and subindex == 0 and entry.bits == bits and index not in positions:
            positions[index] = len(positions)
            parts.append(entry.codec.format.lstrip("<"))
        else:
            parts.append(f"{bits // 8}x")
    return "".join(parts), positions


class RpdoCodec:
    """Packs controlword and target position into an RPDO laid out as the drive maps it.

    Objects the master does not command are sent as 0, except 0x6060, which carries CSP.
    """

    __slots__ = ("_codec", "_controlword_at", "_mode_at", "_target_at", "_values", "buffer")

    def __init__(self, layout: PdoLayout) -> None:
        fmt, positions = _codec_format(layout)
        self._codec = struct.Struct(fmt)
        self.buffer = bytearray(self._codec.size)
        self._values = [0] * len(positions)
        self._controlword_at = positions[CONTROLWORD]
        self._target_at = positions[TARGET_POSITION]
        mode_at = positions.get(MODES_OF_OPERATION)
        if mode_at is not None:
            self._values[mode_at] = MODE_CSP

    def pack(self, controlword: int, target_counts: int) -> bytearray:
        """Fill and return the codec's buffer (reused every call)."""
        values = self._values
        values[self._controlword_at] = controlword
        values[self._target_at] = target_counts
        self._codec.pack_into(self.buffer, 0, *values)
        return self.buffer


class TpdoCodec:
    """Unpacks a TPDO laid out as the drive maps it; ``*_at`` give each known object's
    position in the tuple :meth:`unpack` returns (None when not mapped)."""

    __slots__ = (
        "error_code_at",
        "following_error_at",
        "mode_display_at",
        "position_at",
        "size",
        "statusword_at",
        "unpack",
    )

    def __init__(self, layout: PdoLayout) -> None:
        fmt, positions = _codec_format(layout)
        codec = struct.Struct(fmt)
        self.size = codec.size
        self.unpack = codec.unpack
        self.statusword_at = positions.get(STATUSWORD)
        self.position_at = positions.get(POSITION_ACTUAL)
        self.following_error_at = positions.get(FOLLOWING_ERROR_ACTUAL)
        self.error_code_at = positions.get(ERROR_CODE)
        self.mode_display_at = positions.get(MODES_OF_OPERATION_DISPLAY)
