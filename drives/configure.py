"""Blocking set-up of one CiA 402 drive by SDO: CSP mode, timing, supervision and PDO mapping.

Source: CiA 301 objects 0x1006 (cycle period µs), 0x1007 (sync window µs), 0x1016 (consumer
heartbeat, ``node << 16 | ms``), 0x1017 (producer heartbeat ms), 0x1400/0x1600 (RPDO1) and
0x1800/0x1A00 (TPDO1); CiA 402 objects 0x6060/0x6061 (mode, CSP = 8), 0x60C2 (interpolation
period, sub1 × 10^sub2 s), 0x6065/0x6066 (following-error window counts / timeout ms), 0x605A
(quick stop option), 0x605E (fault reaction option), 0x6007 (abort connection option).

Units: as the objects: µs, ms, counts.

Threading: main thread only, before the cycle starts. Every call blocks on SDO round trips; the
SDO client of a node is not thread-safe, so one node is configured by one caller at a time.

Invariants: every object written is read back and compared (``ConfigurationMismatch``
otherwise); PDO maps go through ``node.rpdo[1]`` / ``node.tpdo[1]`` (``node.pdo[0x1600]`` returns
TPDO1 in canopen 2.4.1) and are written in PRE-OPERATIONAL, as CiA 301 requires.

Not done: storing parameters (0x1010), PDOs other than RPDO1/TPDO1, modes other than CSP.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import canopen
from canopen.sdo import SdoVariable

from drives.errors import ConfigurationFailed, ConfigurationMismatch, DriveError
from drives.objects import (
    ABORT_CONNECTION_OPTION,
    COB_ID_INVALID,
    COB_ID_MASK,
    COMM_CYCLE_PERIOD,
    CONSUMER_HEARTBEAT,
    CONTROLWORD,
    CSP_RPDO1,
    CSP_TPDO1,
    FAULT_REACTION_OPTION,
    FOLLOWING_ERROR_TIMEOUT,
    FOLLOWING_ERROR_WINDOW,
    INTERPOLATION_PERIOD,
    INTERPOLATION_PERIOD_INDEX,
    INTERPOLATION_PERIOD_VALUE,
    MODE_CSP,
    MODES_OF_OPERATION,
    MODES_OF_OPERATION_DISPLAY,
    POSITION_ACTUAL,
    PRODUCER_HEARTBEAT,
    QUICK_STOP_OPTION,
    RPDO_COMM,
    RPDO_MAP,
    STATUSWORD,
    SYNC_WINDOW,
    TARGET_POSITION,
    TPDO_COMM,
    TPDO_MAP,
    NmtCommand,
    mapping_entry,
    rpdo_cob_id,
    tpdo_cob_id,
)

#: PDO transmission type of RPDO1 and TPDO1: act on / send at every SYNC.
PDO_TRANS_TYPE_EVERY_SYNC = 1

#: Bits of the PDO mapping entries (0x6040 / 0x6041 U16, 0x607A / 0x6064 I32).
_BITS = {CONTROLWORD: 16, STATUSWORD: 16, TARGET_POSITION: 32, POSITION_ACTUAL: 32}

#: Seconds between reads of 0x6061 while the drive switches to CSP.
_MODE_POLL_S = 0.01


@dataclass(frozen=True)
class DriveSetup:
    """The values one drive is configured with at boot."""

    cycle_period_us: int
    """0x1006 and, as value × 10^index s, 0x60C2."""
    heartbeat_producer_ms: int
    """0x1017."""
    master_heartbeat_consumer: int
    """0x1016:01 word, ``master node << 16 | consumer time ms``; 0 turns consumption off."""
    following_error_window_counts: int
    following_error_timeout_ms: int
    quick_stop_option: int
    fault_reaction_option: int
    abort_connection_option: int
    sync_window_us: int = 0
    """0x1007; 0 leaves the object untouched (drives without it still boot)."""


@dataclass(frozen=True)
class _Expected:
    index: int
    subindex: int
    name: str
    value: int
    mask: int = -1


def interpolation_period(cycle_period_us: int) -> tuple[int, int]:
    """0x60C2 (value, index) for a cycle period: value × 10^index s with value in 1..255.

    4000 µs -> (4, -3); 2500 µs -> (25, -4); 500 µs -> (5, -4).

    :raises ValueError: if no such pair represents the period exactly.
    """
    for index in range(-6, 1):
        value = cycle_period_us * 10 ** (-6 - index)
        if value == int(value) and 1 <= value <= 255:
            return int(value), index
    raise ValueError(
        f"cycle period {cycle_period_us} µs: not representable in 0x60C2 as value × 10^index s"
        " with value 1..255"
    )


def heartbeat_consumer_entry(producer_node_id: int, time_ms: int) -> int:
    """0x1016 sub-entry: monitor ``producer_node_id`` with ``time_ms`` (0 = off)."""
    if time_ms <= 0:
        return 0
    return producer_node_id << 16 | time_ms


def period_us(period_s: float) -> int:
    """The cycle period in whole µs.

    :raises ValueError: if the period is not a positive whole number of µs.
    """
    period = round(period_s * 1e6)
    if period <= 0 or not math.isclose(period, period_s * 1e6, abs_tol=1e-3):
        raise ValueError(f"period_s = {period_s!r}: must be a positive whole number of µs")
    return period


def enter_pre_operational(node: canopen.RemoteNode) -> None:
    """Send NMT enter PRE-OPERATIONAL (PDO mapping may only change there)."""
    node.nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)


def configure_drive(node: canopen.RemoteNode, setup: DriveSetup, mode_timeout_s: float) -> None:
    """Configure a drive for CSP, read every object back, and wait for 0x6061 = CSP.

    The node must be PRE-OPERATIONAL (see :func:`enter_pre_operational`).

    :raises ConfigurationFailed: an SDO transfer was aborted or timed out.
    :raises ConfigurationMismatch: an object read back differs from what was written, or the
        mode display 0x6061 did not reach CSP within ``mode_timeout_s``.
    """
    value, index = interpolation_period(setup.cycle_period_us)
    written = [
        _Expected(MODES_OF_OPERATION, 0, "modes of operation", MODE_CSP),
        _Expected(INTERPOLATION_PERIOD, INTERPOLATION_PERIOD_VALUE, "interpolation period", value),
        _Expected(INTERPOLATION_PERIOD, INTERPOLATION_PERIOD_INDEX, "interpolation index", index),
        _Expected(COMM_CYCLE_PERIOD, 0, "communication cycle period", setup.cycle_period_us),
        _Expected(PRODUCER_HEARTBEAT, 0, "producer heartbeat time", setup.heartbeat_producer_ms),
        _Expected(
            CONSUMER_HEARTBEAT, 1, "consumer heartbeat time", setup.master_heartbeat_consumer
        ),
        _Expected(
            FOLLOWING_ERROR_WINDOW,
            0,
            "following error window",
            setup.following_error_window_counts,
        ),
        _Expected(
            FOLLOWING_ERROR_TIMEOUT, 0, "following error timeout", setup.following_error_timeout_ms
        ),
        _Expected(QUICK_STOP_OPTION, 0, "quick stop option code", setup.quick_stop_option),
        _Expected(
            FAULT_REACTION_OPTION, 0, "fault reaction option code", setup.fault_reaction_option
        ),
        _Expected(
            ABORT_CONNECTION_OPTION,
            0,
            "abort connection option code",
            setup.abort_connection_option,
        ),
    ]
    if setup.sync_window_us > 0:
        written.append(_Expected(SYNC_WINDOW, 0, "synchronous window length", setup.sync_window_us))
    for item in written:
        with _sdo(node, item.index, item.subindex, item.name):
            _entry(node, item.index, item.subindex).raw = item.value
    _map_pdo(node, node.rpdo[1], "RPDO1", rpdo_cob_id(1, node.id), CSP_RPDO1)
    _map_pdo(node, node.tpdo[1], "TPDO1", tpdo_cob_id(1, node.id), CSP_TPDO1)
    for item in written + _pdo_expectations(node.id):
        _verify(node, item)
    _wait_for_mode(node, mode_timeout_s)


def read_feedback_by_sdo(node: canopen.RemoteNode) -> tuple[int, int]:
    """(statusword 0x6041, position actual 0x6064 in counts) read by SDO.

    :raises ConfigurationFailed: an SDO transfer was aborted or timed out.
    """
    with _sdo(node, STATUSWORD, 0, "statusword"):
        statusword = node.sdo[STATUSWORD].raw
    with _sdo(node, POSITION_ACTUAL, 0, "position actual value"):
        position = node.sdo[POSITION_ACTUAL].raw
    return int(statusword), int(position)


def _map_pdo(
    node: canopen.RemoteNode,
    pdo: canopen.pdo.PdoMap,
    label: str,
    cob_id: int,
    entries: tuple[tuple[int, int], ...],
) -> None:
    comm_index = pdo.com_record.od.index
    with _sdo(node, comm_index, 0, f"{label} communication and mapping"):
        pdo.read()
        pdo.clear()
        for obj_index, obj_sub in entries:
            pdo.add_variable(obj_index, obj_sub)
        pdo.cob_id = cob_id
        pdo.trans_type = PDO_TRANS_TYPE_EVERY_SYNC
        pdo.enabled = True
        pdo.save()


def _pdo_expectations(node_id: int) -> list[_Expected]:
    expected = []
    for comm, mapping, label, cob_id, entries in (
        (RPDO_COMM, RPDO_MAP, "RPDO1", rpdo_cob_id(1, node_id), CSP_RPDO1),
        (TPDO_COMM, TPDO_MAP, "TPDO1", tpdo_cob_id(1, node_id), CSP_TPDO1),
    ):
        expected.append(
            _Expected(comm, 1, f"{label} COB-ID (valid)", cob_id, COB_ID_INVALID | COB_ID_MASK)
        )
        expected.append(_Expected(comm, 2, f"{label} transmission type", PDO_TRANS_TYPE_EVERY_SYNC))
        expected.append(_Expected(mapping, 0, f"{label} number of mapped objects", len(entries)))
        for sub, (obj_index, obj_sub) in enumerate(entries, start=1):
            entry = mapping_entry(obj_index, obj_sub, _BITS[obj_index])
            expected.append(_Expected(mapping, sub, f"{label} mapped object {sub}", entry))
    return expected


def _verify(node: canopen.RemoteNode, item: _Expected) -> None:
    with _sdo(node, item.index, item.subindex, item.name):
        read = int(_entry(node, item.index, item.subindex).raw)
    if read & item.mask != item.value:
        raise ConfigurationMismatch(
            node.id, item.index, item.subindex, item.name, item.value, read & item.mask
        )


def _wait_for_mode(node: canopen.RemoteNode, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        with _sdo(node, MODES_OF_OPERATION_DISPLAY, 0, "modes of operation display"):
            shown = int(node.sdo[MODES_OF_OPERATION_DISPLAY].raw)
        if shown == MODE_CSP:
            return
        if time.monotonic() >= deadline:
            raise ConfigurationMismatch(
                node.id,
                MODES_OF_OPERATION_DISPLAY,
                0,
                f"modes of operation display after {timeout_s:g} s",
                MODE_CSP,
                shown,
            )
        time.sleep(_MODE_POLL_S)


def _entry(node: canopen.RemoteNode, index: int, subindex: int) -> SdoVariable:
    obj = node.sdo[index]
    if isinstance(obj, SdoVariable):
        return obj
    return obj[subindex]


@contextmanager
def _sdo(node: canopen.RemoteNode, index: int, subindex: int, name: str) -> Iterator[None]:
    """Turn canopen's SDO errors (and a missing object) into ConfigurationFailed naming it."""
    try:
        yield
    except DriveError:
        raise
    except (canopen.SdoAbortedError, canopen.SdoCommunicationError, KeyError) as exc:
        cause = f"not in the object dictionary ({exc})" if isinstance(exc, KeyError) else str(exc)
        raise ConfigurationFailed(node.id, index, subindex, name, cause) from exc
