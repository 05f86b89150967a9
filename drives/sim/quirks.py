"""Switches that make the simulated drive behave like CiA 402 drives of other vendors.

Each switch reproduces a way real drives differ from the full object dictionary of
:func:`drives.objects.build_drive_od`, as met in the field:

- ``no_optional_objects``: 0x6066, 0x6007, 0x605A, 0x605E, 0x6065, 0x1016 and 0x1017 do not
  exist (SDO abort 0x06020000); without 0x1017 the drive is supervised by node guarding;
- ``fixed_pdo_mapping``: the PDOs are valid from power-on in a vendor layout and every PDO
  communication and mapping object is read-only (abort 0x06010002): RPDO1 on 0x200 + node-ID =
  0x6040, 0x607A; TPDO1 on 0x280 + node-ID = 0x6064, 0x6041 (position first, on TPDO2's
  predefined COB-ID); TPDO2 on 0x380 + node-ID = 0x60F4, 0x603F; TPDO3 on the free 0x180 +
  node-ID, not valid = 0x606C;
- ``interpolation_ms_only``: 0x60C2:01 accepts 1..20 (abort 0x06090031 above, 0x06090032 below)
  and 0x60C2:02 only -3 (abort 0x06090030), as drives that interpolate in whole ms;
- ``fault_at_power_on``: the drive powers on in FAULT with EMCY 0x8130 (a heartbeat error
  latched in an earlier session); a fault reset clears it;
- ``guarding_only``: no heartbeat objects (0x1016, 0x1017): node guarding only;
- ``sdo_delay_s``: every SDO answer comes between the two delays after its request;
- ``boot_delay_s``: the boot-up comes this long after power-on or an NMT reset;
- ``late_tpdo_periods``: each synchronous TPDO goes out that many SYNCs after the one it
  answers (its data is the drive's state at the earlier SYNC).

Every simulated drive answers node guarding (0x100C / 0x100D) while its heartbeat producer is off.

Threading: immutable; :func:`served_od` builds a new dictionary per drive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import canopen

from drives import objects

#: Objects a minimal CiA 402 drive lacks (``no_optional_objects``).
OPTIONAL_OBJECTS: Final = frozenset(
    {
        objects.FOLLOWING_ERROR_TIMEOUT,
        objects.ABORT_CONNECTION_OPTION,
        objects.QUICK_STOP_OPTION,
        objects.FAULT_REACTION_OPTION,
        objects.FOLLOWING_ERROR_WINDOW,
        objects.CONSUMER_HEARTBEAT,
        objects.PRODUCER_HEARTBEAT,
    }
)
#: Objects a drive with node guarding only lacks (``guarding_only``).
HEARTBEAT_OBJECTS: Final = frozenset({objects.CONSUMER_HEARTBEAT, objects.PRODUCER_HEARTBEAT})

#: ``interpolation_ms_only``: the range of 0x60C2:01 and the one index accepted.
INTERPOLATION_VALUE_RANGE: Final = (1, 20)
INTERPOLATION_INDEX_MS: Final[int] = -3

#: ``fixed_pdo_mapping``: (COB-ID base or None for not valid, transmission type, objects).
FIXED_RPDOS: Final = {1: (objects.RPDO1_COB_ID_BASE, 255, objects.CSP_RPDO1)}
FIXED_TPDOS: Final = {
    1: (0x280, 1, ((objects.POSITION_ACTUAL, 0), (objects.STATUSWORD, 0))),
    2: (0x380, 1, ((objects.FOLLOWING_ERROR_ACTUAL, 0), (objects.ERROR_CODE, 0))),
    3: (None, 1, ((objects.VELOCITY_ACTUAL, 0),)),  # on 0x180 + node-ID, not valid
}


@dataclass(frozen=True)
class DriveQuirks:
    """How a simulated drive departs from the full CiA 402 drive (all off by default).

    :raises ValueError: on negative or inverted delays.
    """

    no_optional_objects: bool = False
    fixed_pdo_mapping: bool = False
    interpolation_ms_only: bool = False
    fault_at_power_on: bool = False
    guarding_only: bool = False
    sdo_delay_s: tuple[float, float] = (0.0, 0.0)
    """(shortest, longest) time between an SDO request and its answer."""
    boot_delay_s: float = 0.0
    late_tpdo_periods: int = 0

    def __post_init__(self) -> None:
        low, high = self.sdo_delay_s
        if not (math.isfinite(low) and math.isfinite(high) and 0 <= low <= high):
            raise ValueError(
                f"sdo_delay_s = {self.sdo_delay_s!r}: must be 0 <= shortest <= longest"
            )
        if not (math.isfinite(self.boot_delay_s) and self.boot_delay_s >= 0):
            raise ValueError(f"boot_delay_s = {self.boot_delay_s!r}: must be >= 0")
        if self.late_tpdo_periods < 0:
            raise ValueError(f"late_tpdo_periods = {self.late_tpdo_periods}: must be >= 0")

    @property
    def missing_objects(self) -> frozenset[int]:
        """The objects the drive does not have."""
        missing: frozenset[int] = frozenset()
        if self.no_optional_objects:
            missing |= OPTIONAL_OBJECTS
        if self.guarding_only:
            missing |= HEARTBEAT_OBJECTS
        return missing


def served_od(node_id: int, quirks: DriveQuirks) -> canopen.ObjectDictionary:
    """The object dictionary a drive with ``quirks`` serves (and its EDS describes)."""
    od = objects.build_drive_od(node_id)
    for index in quirks.missing_objects:
        del od[index]
    if quirks.interpolation_ms_only:
        period = od[objects.INTERPOLATION_PERIOD]
        value = period[objects.INTERPOLATION_PERIOD_VALUE]
        value.min, value.max = INTERPOLATION_VALUE_RANGE
        index = period[objects.INTERPOLATION_PERIOD_INDEX]
        index.min = index.max = index.default = INTERPOLATION_INDEX_MS
    if quirks.fixed_pdo_mapping:
        _fix_pdos(od, node_id, objects.RPDO_COMM, objects.RPDO_MAP, FIXED_RPDOS)
        _fix_pdos(od, node_id, objects.TPDO_COMM, objects.TPDO_MAP, FIXED_TPDOS)
        for base in (objects.RPDO_COMM, objects.RPDO_MAP, objects.TPDO_COMM, objects.TPDO_MAP):
            for n in range(objects.PDO_COUNT):
                for variable in od[base + n].values():
                    variable.access_type = "ro"
    return od


def _fix_pdos(
    od: canopen.ObjectDictionary,
    node_id: int,
    comm_base: int,
    map_base: int,
    layouts: dict[int, tuple[int | None, int, tuple[tuple[int, int], ...]]],
) -> None:
    for number, (cob_base, trans_type, entries) in layouts.items():
        comm = od[comm_base + number - 1]
        cob_id = comm[1]
        flags = cob_id.default & objects.COB_ID_NO_RTR
        if cob_base is None:
            cob_id.default = flags | objects.COB_ID_INVALID | (objects.TPDO1_COB_ID_BASE + node_id)
        else:
            cob_id.default = flags | (cob_base + node_id)
        cob_id.default_raw = None
        cob_id.relative = False
        comm[2].default = trans_type
        mapping = od[map_base + number - 1]
        mapping[0].default = len(entries)
        for sub in range(1, objects.PDO_MAX_ENTRIES + 1):
            if sub <= len(entries):
                index, subindex = entries[sub - 1]
                bits = len(od.get_variable(index, subindex))
                mapping[sub].default = objects.mapping_entry(index, subindex, bits)
            else:
                mapping[sub].default = 0
