"""CANopen object indices, COB-IDs, PDO layouts and the CiA 402 object dictionary built in code.

Sources: CiA 301 (communication objects 0x1000-0x1A03, predefined connection set, NMT and
heartbeat codes) and CiA 402 (device profile objects 0x6007-0x6502, CSP mode 8).

Units: positions, windows and following errors in drive counts; 0x1006 and 0x1007 in µs; 0x1017,
0x1016 times, 0x6066 and PDO event timers in ms; 0x6084/0x6085 decelerations in counts/s²;
0x60C2 is sub1 × 10^sub2 s.

:func:`build_drive_od` returns the dictionary used by both sides: the simulated drive serves it
(``canopen.LocalNode``) and the master describes its drives with it (``canopen.RemoteNode``),
so ``node.rpdo[1].add_variable(CONTROLWORD)`` works without an EDS.
``configs/drives/softmotion-sim.eds`` is exported from it by :func:`export_drive_eds`.

Threading: constants and pure builders; safe from any thread.
Invariants: PDO mapping objects are RECORDs (canopen's ``PdoMap.save()`` writes no entry into an
ARRAY whose sub0 it has just cleared); node-relative defaults (COB-IDs, serial number) keep
``$NODEID`` in the EDS.
Not included: store/restore (0x1010/0x1011), software position limits (0x607D), offsets
(0x60B0-0x60B2) and every mode but CSP.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Final

import canopen
from canopen.objectdictionary import (
    INTEGER8,
    INTEGER16,
    INTEGER32,
    UNSIGNED8,
    UNSIGNED16,
    UNSIGNED32,
    ODArray,
    ODRecord,
    ODVariable,
)

# CiA 301 communication objects.
DEVICE_TYPE: Final[int] = 0x1000
ERROR_REGISTER: Final[int] = 0x1001
PREDEFINED_ERROR_FIELD: Final[int] = 0x1003
COB_ID_SYNC: Final[int] = 0x1005
COMM_CYCLE_PERIOD: Final[int] = 0x1006
SYNC_WINDOW: Final[int] = 0x1007
GUARD_TIME: Final[int] = 0x100C
LIFE_TIME_FACTOR: Final[int] = 0x100D
COB_ID_EMCY: Final[int] = 0x1014
CONSUMER_HEARTBEAT: Final[int] = 0x1016
PRODUCER_HEARTBEAT: Final[int] = 0x1017
IDENTITY: Final[int] = 0x1018
SYNC_COUNTER_OVERFLOW: Final[int] = 0x1019
RPDO_COMM: Final[int] = 0x1400  # + n - 1 for RPDO n
RPDO_MAP: Final[int] = 0x1600
TPDO_COMM: Final[int] = 0x1800
TPDO_MAP: Final[int] = 0x1A00

# CiA 402 device profile objects.
ABORT_CONNECTION_OPTION: Final[int] = 0x6007
ERROR_CODE: Final[int] = 0x603F
CONTROLWORD: Final[int] = 0x6040
STATUSWORD: Final[int] = 0x6041
QUICK_STOP_OPTION: Final[int] = 0x605A
FAULT_REACTION_OPTION: Final[int] = 0x605E
MODES_OF_OPERATION: Final[int] = 0x6060
MODES_OF_OPERATION_DISPLAY: Final[int] = 0x6061
POSITION_ACTUAL: Final[int] = 0x6064
FOLLOWING_ERROR_WINDOW: Final[int] = 0x6065
FOLLOWING_ERROR_TIMEOUT: Final[int] = 0x6066
VELOCITY_ACTUAL: Final[int] = 0x606C
TARGET_POSITION: Final[int] = 0x607A
PROFILE_DECELERATION: Final[int] = 0x6084
QUICK_STOP_DECELERATION: Final[int] = 0x6085
INTERPOLATION_PERIOD: Final[int] = 0x60C2  # sub1 value (U8), sub2 index (I8): sub1 × 10^sub2 s
INTERPOLATION_PERIOD_VALUE: Final[int] = 1
INTERPOLATION_PERIOD_INDEX: Final[int] = 2
FOLLOWING_ERROR_ACTUAL: Final[int] = 0x60F4
SUPPORTED_DRIVE_MODES: Final[int] = 0x6502

#: Modes of operation (0x6060 / 0x6061).
MODE_NONE: Final[int] = 0
MODE_CSP: Final[int] = 8
#: 0x6502 bit of CSP.
SUPPORTED_MODE_CSP: Final[int] = 1 << 7

# CiA 301 predefined connection set (function code base; add the node-ID where it applies).
NMT_COB_ID: Final[int] = 0x000
SYNC_COB_ID: Final[int] = 0x080
EMCY_COB_ID_BASE: Final[int] = 0x080
TPDO1_COB_ID_BASE: Final[int] = 0x180
RPDO1_COB_ID_BASE: Final[int] = 0x200
SDO_TX_COB_ID_BASE: Final[int] = 0x580  # server -> client
SDO_RX_COB_ID_BASE: Final[int] = 0x600  # client -> server
HEARTBEAT_COB_ID_BASE: Final[int] = 0x700
PDO_COB_ID_STEP: Final[int] = 0x100  # PDO n uses base + (n - 1) * 0x100, n = 1..4

#: COB-ID bits of 0x14xx/0x18xx sub1.
COB_ID_INVALID: Final[int] = 1 << 31
COB_ID_NO_RTR: Final[int] = 1 << 30
COB_ID_MASK: Final[int] = 0x7FF

#: PDOs per direction in :func:`build_drive_od`.
PDO_COUNT: Final[int] = 4
#: Mapping entries per PDO (8 bytes of at least 8 bits each).
PDO_MAX_ENTRIES: Final[int] = 8

#: PDO transmission types (0x14xx/0x18xx sub2).
TRANS_TYPE_SYNC_ACYCLIC: Final[int] = 0
TRANS_TYPE_SYNC_MAX: Final[int] = 240  # 1..240: every n-th SYNC
TRANS_TYPE_EVENT_VENDOR: Final[int] = 254
TRANS_TYPE_EVENT_PROFILE: Final[int] = 255

#: CSP process data: (index, subindex) per PDO, in mapping order.
CSP_RPDO1: Final = ((CONTROLWORD, 0), (TARGET_POSITION, 0))
CSP_TPDO1: Final = ((STATUSWORD, 0), (POSITION_ACTUAL, 0))
CSP_TPDO2: Final = ((MODES_OF_OPERATION_DISPLAY, 0), (FOLLOWING_ERROR_ACTUAL, 0))

#: Device type 0x1000: CiA 402 profile (0x0192), servo drive (additional information 0x0002).
DEVICE_TYPE_SERVO_402: Final[int] = 0x0002_0192
VENDOR_ID: Final[int] = 0x0000_0000  # unassigned: a simulation, not a product
PRODUCT_CODE: Final[int] = 0x0000_0402
REVISION_NUMBER: Final[int] = 0x0001_0000

#: Heartbeat consumer entries in 0x1016.
CONSUMER_HEARTBEAT_ENTRIES: Final[int] = 2


class NmtState(IntEnum):
    """NMT state as sent in the heartbeat byte (CiA 301); 0x00 is the boot-up message."""

    INITIALISING = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class NmtCommand(IntEnum):
    """NMT command specifier (byte 0 of COB-ID 0x000; byte 1 is the node-ID, 0 = all)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


@dataclass(frozen=True)
class Entry:
    """One object dictionary entry as the master addresses it: index, sub-index, name, CiA type.

    ``str(entry)`` is how messages name it: ``0x6066:00 following error timeout``.
    """

    index: int
    subindex: int
    name: str
    data_type: int

    @property
    def codec(self) -> struct.Struct:
        """Little-endian codec of the entry's data type."""
        return ODVariable.STRUCT_TYPES[self.data_type]

    @property
    def bits(self) -> int:
        """Length as PDO mapping entries give it."""
        return self.codec.size * 8

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X} {self.name}"


# Entries the master reads or writes (CiA 301 / CiA 402 data types).
DEVICE_TYPE_ENTRY: Final = Entry(DEVICE_TYPE, 0, "device type", UNSIGNED32)
COMM_CYCLE_PERIOD_ENTRY: Final = Entry(
    COMM_CYCLE_PERIOD, 0, "communication cycle period", UNSIGNED32
)
SYNC_WINDOW_ENTRY: Final = Entry(SYNC_WINDOW, 0, "synchronous window length", UNSIGNED32)
GUARD_TIME_ENTRY: Final = Entry(GUARD_TIME, 0, "guard time", UNSIGNED16)
LIFE_TIME_FACTOR_ENTRY: Final = Entry(LIFE_TIME_FACTOR, 0, "life time factor", UNSIGNED8)
CONSUMER_HEARTBEAT_ENTRY: Final = Entry(
    CONSUMER_HEARTBEAT, 1, "consumer heartbeat time", UNSIGNED32
)
PRODUCER_HEARTBEAT_ENTRY: Final = Entry(
    PRODUCER_HEARTBEAT, 0, "producer heartbeat time", UNSIGNED16
)
SYNC_COUNTER_OVERFLOW_ENTRY: Final = Entry(
    SYNC_COUNTER_OVERFLOW, 0, "synchronous counter overflow value", UNSIGNED8
)
ABORT_CONNECTION_ENTRY: Final = Entry(
    ABORT_CONNECTION_OPTION, 0, "abort connection option code", INTEGER16
)
ERROR_CODE_ENTRY: Final = Entry(ERROR_CODE, 0, "error code", UNSIGNED16)
CONTROLWORD_ENTRY: Final = Entry(CONTROLWORD, 0, "controlword", UNSIGNED16)
STATUSWORD_ENTRY: Final = Entry(STATUSWORD, 0, "statusword", UNSIGNED16)
QUICK_STOP_OPTION_ENTRY: Final = Entry(QUICK_STOP_OPTION, 0, "quick stop option code", INTEGER16)
FAULT_REACTION_OPTION_ENTRY: Final = Entry(
    FAULT_REACTION_OPTION, 0, "fault reaction option code", INTEGER16
)
MODES_OF_OPERATION_ENTRY: Final = Entry(MODES_OF_OPERATION, 0, "modes of operation", INTEGER8)
MODES_OF_OPERATION_DISPLAY_ENTRY: Final = Entry(
    MODES_OF_OPERATION_DISPLAY, 0, "modes of operation display", INTEGER8
)
POSITION_ACTUAL_ENTRY: Final = Entry(POSITION_ACTUAL, 0, "position actual value", INTEGER32)
FOLLOWING_ERROR_WINDOW_ENTRY: Final = Entry(
    FOLLOWING_ERROR_WINDOW, 0, "following error window", UNSIGNED32
)
FOLLOWING_ERROR_TIMEOUT_ENTRY: Final = Entry(
    FOLLOWING_ERROR_TIMEOUT, 0, "following error timeout", UNSIGNED16
)
TARGET_POSITION_ENTRY: Final = Entry(TARGET_POSITION, 0, "target position", INTEGER32)
INTERPOLATION_PERIOD_VALUE_ENTRY: Final = Entry(
    INTERPOLATION_PERIOD, INTERPOLATION_PERIOD_VALUE, "interpolation time period value", UNSIGNED8
)
INTERPOLATION_PERIOD_INDEX_ENTRY: Final = Entry(
    INTERPOLATION_PERIOD, INTERPOLATION_PERIOD_INDEX, "interpolation time index", INTEGER8
)
FOLLOWING_ERROR_ACTUAL_ENTRY: Final = Entry(
    FOLLOWING_ERROR_ACTUAL, 0, "following error actual value", INTEGER32
)
VELOCITY_ACTUAL_ENTRY: Final = Entry(VELOCITY_ACTUAL, 0, "velocity actual value", INTEGER32)

#: The process data objects the master knows by name, keyed by index (sub-index 0).
PROCESS_ENTRIES: Final = {
    entry.index: entry
    for entry in (
        CONTROLWORD_ENTRY,
        TARGET_POSITION_ENTRY,
        MODES_OF_OPERATION_ENTRY,
        STATUSWORD_ENTRY,
        POSITION_ACTUAL_ENTRY,
        FOLLOWING_ERROR_ACTUAL_ENTRY,
        ERROR_CODE_ENTRY,
        MODES_OF_OPERATION_DISPLAY_ENTRY,
        VELOCITY_ACTUAL_ENTRY,
    )
}


def describe_object(index: int) -> str:
    """``0x6064 position actual value`` for a known process object, else ``0x2100``."""
    entry = PROCESS_ENTRIES.get(index)
    return f"0x{index:04X}" if entry is None else f"0x{index:04X} {entry.name}"


def rpdo_cob_id(pdo_number: int, node_id: int) -> int:
    """Predefined COB-ID of RPDO ``pdo_number`` (1..4) of ``node_id``."""
    return RPDO1_COB_ID_BASE + (pdo_number - 1) * PDO_COB_ID_STEP + node_id


def tpdo_cob_id(pdo_number: int, node_id: int) -> int:
    """Predefined COB-ID of TPDO ``pdo_number`` (1..4) of ``node_id``."""
    return TPDO1_COB_ID_BASE + (pdo_number - 1) * PDO_COB_ID_STEP + node_id


def mapping_entry(index: int, subindex: int, bits: int) -> int:
    """Encode a PDO mapping entry (0x16xx/0x1Axx sub n): ``index << 16 | subindex << 8 | bits``."""
    return index << 16 | subindex << 8 | bits


def decode_mapping_entry(entry: int) -> tuple[int, int, int]:
    """Return ``(index, subindex, bits)`` of a PDO mapping entry."""
    return entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF


def _variable(
    name: str,
    index: int,
    subindex: int = 0,
    *,
    data_type: int,
    access: str,
    default: int | None = None,
    default_raw: str | None = None,
    mappable: bool = False,
) -> ODVariable:
    var = ODVariable(name, index, subindex)
    var.data_type = data_type
    var.access_type = access
    var.default = default
    var.pdo_mappable = mappable
    if default is not None and default < 0:
        # canopen 2.4.1 exports negative defaults as "0x-3"; CiA 306 also accepts decimal.
        var.default_raw = str(default)
    if default_raw is not None:
        # Keeps "$NODEID+..." in the exported EDS (canopen's export reads default_raw).
        var.default_raw = default_raw
        var.relative = True
    return var


def _node_relative(name: str, index: int, subindex: int, base: int, node_id: int) -> ODVariable:
    return _variable(
        name,
        index,
        subindex,
        data_type=UNSIGNED32,
        access="rw",
        default=base + node_id,
        default_raw=f"$NODEID+0x{base:X}",
    )


def _record(name: str, index: int, members: list[ODVariable]) -> ODRecord:
    record = ODRecord(name, index)
    for member in members:
        record.add_member(member)
    return record


def _highest_subindex(index: int, value: int, access: str = "ro") -> ODVariable:
    return _variable(
        "Highest sub-index supported", index, 0, data_type=UNSIGNED8, access=access, default=value
    )


def _pdo_mapping(name: str, index: int, entries: tuple[tuple[int, int], ...], od) -> ODRecord:
    members = [
        _variable(
            "Number of mapped objects",
            index,
            0,
            data_type=UNSIGNED8,
            access="rw",
            default=len(entries),
        )
    ]
    for sub in range(1, PDO_MAX_ENTRIES + 1):
        if sub <= len(entries):
            obj_index, obj_sub = entries[sub - 1]
            default = mapping_entry(obj_index, obj_sub, len(od.get_variable(obj_index, obj_sub)))
        else:
            default = 0
        members.append(
            _variable(
                f"Mapped object {sub}",
                index,
                sub,
                data_type=UNSIGNED32,
                access="rw",
                default=default,
            )
        )
    return _record(name, index, members)


def _add_profile_objects(od: canopen.ObjectDictionary) -> None:
    for name, index, data_type, access, default, mappable in (
        ("Abort connection option code", ABORT_CONNECTION_OPTION, INTEGER16, "rw", 1, False),
        ("Error code", ERROR_CODE, UNSIGNED16, "ro", 0, True),
        ("Controlword", CONTROLWORD, UNSIGNED16, "rw", 0, True),
        ("Statusword", STATUSWORD, UNSIGNED16, "ro", 0, True),
        ("Quick stop option code", QUICK_STOP_OPTION, INTEGER16, "rw", 2, False),
        ("Fault reaction option code", FAULT_REACTION_OPTION, INTEGER16, "rw", 2, False),
        ("Modes of operation", MODES_OF_OPERATION, INTEGER8, "rw", MODE_NONE, True),
        ("Modes of operation display", MODES_OF_OPERATION_DISPLAY, INTEGER8, "ro", 0, True),
        ("Position actual value", POSITION_ACTUAL, INTEGER32, "ro", 0, True),
        ("Following error window", FOLLOWING_ERROR_WINDOW, UNSIGNED32, "rw", 10_000, True),
        ("Following error time out", FOLLOWING_ERROR_TIMEOUT, UNSIGNED16, "rw", 10, True),
        ("Velocity actual value", VELOCITY_ACTUAL, INTEGER32, "ro", 0, True),
        ("Target position", TARGET_POSITION, INTEGER32, "rw", 0, True),
        ("Profile deceleration", PROFILE_DECELERATION, UNSIGNED32, "rw", 5_000_000, True),
        ("Quick stop deceleration", QUICK_STOP_DECELERATION, UNSIGNED32, "rw", 10_000_000, True),
        ("Following error actual value", FOLLOWING_ERROR_ACTUAL, INTEGER32, "ro", 0, True),
        (
            "Supported drive modes",
            SUPPORTED_DRIVE_MODES,
            UNSIGNED32,
            "ro",
            SUPPORTED_MODE_CSP,
            False,
        ),
    ):
        od.add_object(
            _variable(
                name, index, data_type=data_type, access=access, default=default, mappable=mappable
            )
        )
    od.add_object(
        _record(
            "Interpolation time period",
            INTERPOLATION_PERIOD,
            [
                _highest_subindex(INTERPOLATION_PERIOD, 2),
                _variable(
                    "Interpolation time period value",
                    INTERPOLATION_PERIOD,
                    INTERPOLATION_PERIOD_VALUE,
                    data_type=UNSIGNED8,
                    access="rw",
                    default=4,
                ),
                _variable(
                    "Interpolation time index",
                    INTERPOLATION_PERIOD,
                    INTERPOLATION_PERIOD_INDEX,
                    data_type=INTEGER8,
                    access="rw",
                    default=-3,
                ),
            ],
        )
    )


def _add_communication_objects(od: canopen.ObjectDictionary, node_id: int) -> None:
    for name, index, data_type, access, default, mappable in (
        ("Device type", DEVICE_TYPE, UNSIGNED32, "ro", DEVICE_TYPE_SERVO_402, False),
        ("Error register", ERROR_REGISTER, UNSIGNED8, "ro", 0, True),
        ("COB-ID SYNC message", COB_ID_SYNC, UNSIGNED32, "rw", SYNC_COB_ID, False),
        ("Communication cycle period", COMM_CYCLE_PERIOD, UNSIGNED32, "rw", 0, False),
        ("Synchronous window length", SYNC_WINDOW, UNSIGNED32, "rw", 0, False),
        ("Guard time", GUARD_TIME, UNSIGNED16, "rw", 0, False),
        ("Life time factor", LIFE_TIME_FACTOR, UNSIGNED8, "rw", 0, False),
        ("Producer heartbeat time", PRODUCER_HEARTBEAT, UNSIGNED16, "rw", 0, False),
        ("Synchronous counter overflow value", SYNC_COUNTER_OVERFLOW, UNSIGNED8, "rw", 0, False),
    ):
        od.add_object(
            _variable(
                name, index, data_type=data_type, access=access, default=default, mappable=mappable
            )
        )
    od.add_object(_node_relative("COB-ID EMCY", COB_ID_EMCY, 0, EMCY_COB_ID_BASE, node_id))

    history = ODArray("Pre-defined error field", PREDEFINED_ERROR_FIELD)
    history.add_member(
        _variable(
            "Number of errors",
            PREDEFINED_ERROR_FIELD,
            0,
            data_type=UNSIGNED8,
            access="rw",
            default=0,
        )
    )
    for sub in range(1, 5):
        history.add_member(
            _variable(
                f"Standard error field {sub}",
                PREDEFINED_ERROR_FIELD,
                sub,
                data_type=UNSIGNED32,
                access="ro",
                default=0,
            )
        )
    od.add_object(history)

    consumer = ODArray("Consumer heartbeat time", CONSUMER_HEARTBEAT)
    consumer.add_member(_highest_subindex(CONSUMER_HEARTBEAT, CONSUMER_HEARTBEAT_ENTRIES))
    for sub in range(1, CONSUMER_HEARTBEAT_ENTRIES + 1):
        consumer.add_member(
            _variable(
                f"Consumer heartbeat time {sub}",
                CONSUMER_HEARTBEAT,
                sub,
                data_type=UNSIGNED32,
                access="rw",
                default=0,
            )
        )
    od.add_object(consumer)

    identity_values = (
        ("Vendor-ID", VENDOR_ID),
        ("Product code", PRODUCT_CODE),
        ("Revision number", REVISION_NUMBER),
    )
    identity = [_highest_subindex(IDENTITY, 4)]
    for sub, (name, value) in enumerate(identity_values, start=1):
        identity.append(
            _variable(name, IDENTITY, sub, data_type=UNSIGNED32, access="ro", default=value)
        )
    serial = _node_relative("Serial number", IDENTITY, 4, 0, node_id)
    serial.access_type = "ro"
    identity.append(serial)
    od.add_object(_record("Identity object", IDENTITY, identity))


def _add_pdo_objects(od: canopen.ObjectDictionary, node_id: int) -> None:
    default_rpdo_maps = {1: CSP_RPDO1}
    default_tpdo_maps = {1: CSP_TPDO1, 2: CSP_TPDO2}
    for n in range(1, PDO_COUNT + 1):
        step = (n - 1) * PDO_COB_ID_STEP
        comm = RPDO_COMM + n - 1
        od.add_object(
            _record(
                f"RPDO{n} communication parameter",
                comm,
                [
                    _highest_subindex(comm, 5),
                    _node_relative(
                        "COB-ID used by RPDO",
                        comm,
                        1,
                        COB_ID_INVALID | RPDO1_COB_ID_BASE + step,
                        node_id,
                    ),
                    _variable(
                        "Transmission type",
                        comm,
                        2,
                        data_type=UNSIGNED8,
                        access="rw",
                        default=TRANS_TYPE_EVENT_PROFILE,
                    ),
                    _variable("Event timer", comm, 5, data_type=UNSIGNED16, access="rw", default=0),
                ],
            )
        )
        od.add_object(
            _pdo_mapping(
                f"RPDO{n} mapping parameter", RPDO_MAP + n - 1, default_rpdo_maps.get(n, ()), od
            )
        )
        comm = TPDO_COMM + n - 1
        od.add_object(
            _record(
                f"TPDO{n} communication parameter",
                comm,
                [
                    _highest_subindex(comm, 6),
                    _node_relative(
                        "COB-ID used by TPDO",
                        comm,
                        1,
                        COB_ID_INVALID | COB_ID_NO_RTR | TPDO1_COB_ID_BASE + step,
                        node_id,
                    ),
                    _variable(
                        "Transmission type",
                        comm,
                        2,
                        data_type=UNSIGNED8,
                        access="rw",
                        default=TRANS_TYPE_EVENT_PROFILE,
                    ),
                    _variable(
                        "Inhibit time", comm, 3, data_type=UNSIGNED16, access="rw", default=0
                    ),
                    _variable("Event timer", comm, 5, data_type=UNSIGNED16, access="rw", default=0),
                    _variable(
                        "SYNC start value", comm, 6, data_type=UNSIGNED8, access="rw", default=0
                    ),
                ],
            )
        )
        od.add_object(
            _pdo_mapping(
                f"TPDO{n} mapping parameter", TPDO_MAP + n - 1, default_tpdo_maps.get(n, ()), od
            )
        )


def build_drive_od(node_id: int) -> canopen.ObjectDictionary:
    """Build the object dictionary of a CiA 402 servo drive in CSP mode for ``node_id``.

    About 40 objects: the CiA 301 communication objects (0x1000-0x1018), four RPDOs and four
    TPDOs (0x1400-0x1403, 0x1600-0x1603, 0x1800-0x1803, 0x1A00-0x1A03; every PDO invalid by
    default, RPDO1 pre-mapped to 6040/607A, TPDO1 to 6041/6064, TPDO2 to 6061/60F4) and the
    CiA 402 objects of CSP, with CiA access types, data types, defaults and PDO mappability.

    :raises ValueError: if ``node_id`` is not in 1..127.
    """
    if not 1 <= node_id <= 127:
        raise ValueError(f"node_id = {node_id}, must be in 1..127")
    od = canopen.ObjectDictionary()
    od.node_id = node_id
    od.device_information.product_name = "softmotion simulated CiA 402 drive"
    od.device_information.allowed_baudrates = {125_000, 250_000, 500_000, 1_000_000}
    od.device_information.nr_of_RXPDO = PDO_COUNT
    od.device_information.nr_of_TXPDO = PDO_COUNT
    _add_communication_objects(od, node_id)
    _add_profile_objects(od)
    _add_pdo_objects(od, node_id)
    return od


#: Node-ID written into the exported EDS; defaults relative to it keep ``$NODEID``.
EDS_NODE_ID: Final[int] = 1


def export_drive_eds(path: str | Path) -> None:
    """Write the EDS of :func:`build_drive_od` to ``path`` (configs/drives/softmotion-sim.eds)."""
    od = build_drive_od(EDS_NODE_ID)
    od.node_id = None  # an EDS describes the device type, not one commissioned node
    canopen.export_od(od, str(path), doc_type="eds")
