"""Boot, configuration and shutdown of one drive as a state machine the cycle steps.

Source: CiA 301 (NMT reset communication, boot-up 0x700 + node-ID = 0x00, PRE-OPERATIONAL for
SDO configuration, 0x1000 device type, 0x1006 cycle period µs, 0x1007 sync window µs, 0x1019
SYNC counter overflow, 0x1016 heartbeat consumer ``node << 16 | ms``, 0x1017 heartbeat producer
ms, 0x100C guard time ms / 0x100D life time factor, PDO objects 0x1400-0x1BFF) and CiA 402 (0x6060
/ 0x6061 modes of operation, CSP = 8; 0x60C2 interpolation time period = sub1 × 10^sub2 s;
0x6065 / 0x6066 following error window / timeout; 0x605A quick stop, 0x605E fault reaction,
0x6007 abort connection option codes; 0x6041 / 0x6064 read to seed the feedback).

Phases (:class:`BootPhase`): WAITING (NMT reset communication when configured, then boot-up,
a heartbeat or an answer to an SDO probe of 0x1000; a drive silent past the boot timeout is
reported and looked for still) -> CONFIGURING (SDO in PRE-OPERATIONAL) -> STARTING (NMT start,
until the drive reports OPERATIONAL or sends a TPDO) -> READY; FAILED when the drive refuses its
configuration. A drive lost during configuration is looked for again.

What adapts to the drive. Required: 0x6060/0x6061, 0x60C2, the PDOs (which carry 0x6040, 0x6041,
0x607A, 0x6064) and, with a counted SYNC, 0x1019. Optional: the rest. An optional object that
does not exist or is read-only is skipped with one warning naming node and object, and listed in
``skipped``; an EDS, when given, decides beforehand what exists, what is writable and each value's
range. Abort codes are classified (:func:`drives.sdo_client.classify_abort`): a missing optional
object is skipped; a value out of range fails the boot with a message naming object, value and
the drive's range (from the EDS, else as the abort code states it); a read-only object that
already holds the value is fine. Heartbeat supervision falls back to node guarding on a drive
without 0x1017. The PDO mapping follows :class:`drives.pdo.MappingPolicy`; the layouts used are
the ones read back from the drive.

Threading: the cycle thread. :meth:`NodeBoot.step` runs the state machine up to its next SDO
request (or its next check) and returns; the machine is a generator that yields the SDO transfer
it waits for (resumed once the transfer is done) or None (resumed at the next step).
Invariants: one SDO transfer per node at a time; nothing here blocks or sleeps; every object
written that would supervise us after we leave (0x1016, 0x100C/0x100D, 0x1006) is remembered
and written back to 0 by the shutdown before NMT PRE-OPERATIONAL.
Not done: storing parameters (0x1010), modes other than CSP, reading an EDS from the drive.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from enum import Enum, IntEnum
from typing import Final

from canopen import ObjectDictionary
from canopen.objectdictionary import UNSIGNED8, UNSIGNED32

from drives.cia402 import SW_FAULT
from drives.objects import (
    ABORT_CONNECTION_ENTRY,
    COB_ID_INVALID,
    COB_ID_MASK,
    COB_ID_NO_RTR,
    COMM_CYCLE_PERIOD_ENTRY,
    CONSUMER_HEARTBEAT_ENTRY,
    DEVICE_TYPE_ENTRY,
    ERROR_CODE_ENTRY,
    FAULT_REACTION_OPTION_ENTRY,
    FOLLOWING_ERROR_TIMEOUT_ENTRY,
    FOLLOWING_ERROR_WINDOW_ENTRY,
    GUARD_TIME_ENTRY,
    INTERPOLATION_PERIOD_INDEX_ENTRY,
    INTERPOLATION_PERIOD_VALUE_ENTRY,
    LIFE_TIME_FACTOR_ENTRY,
    MODE_CSP,
    MODES_OF_OPERATION_DISPLAY_ENTRY,
    MODES_OF_OPERATION_ENTRY,
    POSITION_ACTUAL_ENTRY,
    PROCESS_ENTRIES,
    PRODUCER_HEARTBEAT_ENTRY,
    QUICK_STOP_OPTION_ENTRY,
    STATUSWORD_ENTRY,
    SYNC_COUNTER_OVERFLOW_ENTRY,
    SYNC_WINDOW_ENTRY,
    Entry,
    NmtCommand,
    NmtState,
    decode_mapping_entry,
    describe_object,
)
from drives.pdo import (
    COB_ID_EXTENDED,
    RPDO_REQUIRED,
    TPDO_REQUIRED,
    TRANS_TYPE_EVERY_SYNC,
    AxisPdoSpec,
    Direction,
    MappingPolicy,
    PdoLayout,
    PdoSpec,
    layout_problem,
    missing_objects,
    rpdo_type_usable,
)
from drives.sdo_client import (
    ABORT_VALUE_TOO_HIGH,
    ABORT_VALUE_TOO_LOW,
    AbortKind,
    SdoClient,
    SdoTransfer,
    TransferStatus,
    abort_text,
    classify_abort,
)

logger = logging.getLogger(__name__)

#: Highest sub1 of 0x60C2 (UNSIGNED8).
_PERIOD_VALUE_MAX: Final[int] = 255


class BootPhase(IntEnum):
    """Where the boot of a drive stands."""

    WAITING = 0
    """Looking for the drive: boot-up, heartbeat or an answer to an SDO probe."""
    CONFIGURING = 1
    STARTING = 2
    """NMT start sent; waiting for OPERATIONAL."""
    READY = 3
    FAILED = 4
    """The drive refused its configuration (see ``problem``); tried again on its next boot-up
    or on a fault reset."""


class Supervision(Enum):
    """How the master knows a drive is alive, and the drive that the master is."""

    HEARTBEAT = "heartbeat"
    """0x1017 producer on the drive, 0x1016 consumer of the master's heartbeat."""
    GUARDING = "guarding"
    """Node guarding (0x100C / 0x100D): remote frames from the master, life guarding on the
    drive."""


@dataclass(frozen=True)
class NodeSetup:
    """What one drive is configured with."""

    node_id: int
    period_us: int
    """0x1006, and 0x60C2 as value × 10^index s."""
    boot_timeout_s: float
    """Silence in WAITING before the drive is reported; also the limits of NMT start and of the
    mode switch (0x6061)."""
    supervision: Supervision
    heartbeat_ms: int
    """0x1017."""
    master_heartbeat_consumer: int
    """0x1016:01 word, ``master node << 16 | ms``; 0 turns the drive's consumer off."""
    guard_time_ms: int
    life_time_factor: int
    sync_counter_overflow: int
    """0x1019; 0 = SYNC without counter (0x1019 untouched)."""
    sync_window_us: int
    """0x1007; 0 = untouched."""
    following_error_window_counts: int
    following_error_timeout_ms: int
    quick_stop_option: int
    fault_reaction_option: int
    abort_connection_option: int
    pdo: AxisPdoSpec = field(default_factory=AxisPdoSpec)
    od: ObjectDictionary | None = None
    """The drive's EDS, imported; None: nothing is known beforehand."""
    eds_name: str = ""


def interpolation_period(period_us: int) -> tuple[int, int]:
    """0x60C2 (value, index) for a cycle period: value × 10^index s.

    Whole milliseconds give (ms, -3), the form every CSP drive accepts: 4000 µs -> (4, -3),
    1000 µs -> (1, -3). Other periods take the smallest exact form: 2500 µs -> (25, -4),
    500 µs -> (5, -4).

    :raises ValueError: if no value 1..255 represents the period exactly.
    """
    if period_us % 1000 == 0 and 1 <= period_us // 1000 <= _PERIOD_VALUE_MAX:
        return period_us // 1000, -3
    for index in range(0, -7, -1):
        scale = 10 ** (6 + index)
        if period_us % scale == 0 and 1 <= period_us // scale <= _PERIOD_VALUE_MAX:
            return period_us // scale, index
    raise ValueError(
        f"cycle period {period_us} µs: not representable in 0x60C2 as value × 10^index s"
        f" with value 1..{_PERIOD_VALUE_MAX}"
    )


def period_us(period_s: float) -> int:
    """The cycle period in whole µs.

    :raises ValueError: if the period is not a positive whole number of µs.
    """
    period = round(period_s * 1e6)
    if period <= 0 or not math.isclose(period, period_s * 1e6, abs_tol=1e-3):
        raise ValueError(f"period_s = {period_s!r}: must be a positive whole number of µs")
    return period


def heartbeat_consumer_entry(producer_node_id: int, time_ms: int) -> int:
    """0x1016 sub-entry: monitor ``producer_node_id`` with ``time_ms`` (0 = off)."""
    if time_ms <= 0:
        return 0
    return producer_node_id << 16 | time_ms


class _BootFailed(Exception):
    """The drive refused its configuration; the text names object, value and rule."""


class _NodeLost(Exception):
    """The drive stopped answering; look for it again."""


#: What the state machine yields: a transfer to wait for, or None for "next step".
_Steps = Generator[SdoTransfer | None, SdoTransfer | None, None]


def _pdo_entry(direction: Direction, number: int, comm: bool, subindex: int) -> Entry:
    label = f"{direction.name}{number}"
    if comm:
        index = direction.comm_index(number)
        name, data_type = (
            (f"{label} COB-ID", UNSIGNED32) if subindex == 1 else (f"{label} type", UNSIGNED8)
        )
    else:
        index = direction.map_index(number)
        name, data_type = (
            (f"{label} number of mapped objects", UNSIGNED8)
            if subindex == 0
            else (f"{label} mapped object {subindex}", UNSIGNED32)
        )
    return Entry(index, subindex, name, data_type)


class NodeBoot:
    """The boot state machine of one drive.

    The master feeds it what it sees of the drive (``alive``, ``nmt_state``, ``tpdo_seen``)
    and steps it once per period.

    :param setup: what to configure.
    :param sdo: the node's SDO client.
    :param send_nmt: sends an NMT command to this node.
    """

    def __init__(
        self, setup: NodeSetup, sdo: SdoClient, send_nmt: Callable[[NmtCommand], None]
    ) -> None:
        self.setup = setup
        self.node_id = setup.node_id
        self._sdo = sdo
        self._send_nmt = send_nmt
        self.phase = BootPhase.WAITING
        self.now_s = 0.0
        # What the master saw of the drive (set by the master, read here).
        self.alive = False
        self.nmt_state: int | None = None
        self.tpdo_seen = False
        # Results.
        self.problem: str | None = None
        """Why the drive is not ready (reported as a BOOT fault); None once READY."""
        self.problem_serial = 0
        """Counts the distinct problems reported, so each is one event."""
        self.supervision = setup.supervision
        self.skipped: tuple[int, ...] = ()
        self.rpdo: PdoLayout | None = None
        self.tpdos: tuple[PdoLayout, ...] = ()
        self.seed_statusword = 0
        self.seed_position_counts = 0
        self.seed_error_code = 0
        """0x603F read at boot when the drive was already in FAULT (0 otherwise)."""
        self.shutdown_done = False
        self._armed: list[tuple[Entry, int]] = []
        self._warned: set[tuple[int, int]] = set()
        self._task: _Steps | None = None
        self._awaited: SdoTransfer | None = None

    # -- control (master) ----------------------------------------------------------------------

    def begin(self, *, reset_communication: bool) -> None:
        """Start looking for the drive (after NMT reset communication when asked)."""
        self._relive(reset_communication=reset_communication, found=False)

    def look_again(self, reason: str) -> None:
        """The drive was lost: report ``reason`` and look for it again."""
        self._set_problem(f"{reason}; looking for the drive")
        self._relive(reset_communication=False, found=False)

    def rebooted(self) -> None:
        """A boot-up arrived: configure the drive again from the start."""
        self._relive(reset_communication=False, found=True)

    def retry(self) -> None:
        """After FAILED: look for the drive and configure it again (a fault reset)."""
        if self.phase is BootPhase.FAILED:
            self._relive(reset_communication=False, found=False)

    def begin_shutdown(self) -> None:
        """Write back to 0 what would supervise us after we leave, then NMT PRE-OPERATIONAL."""
        alive = self.phase is not BootPhase.WAITING
        self._run(self._shutdown() if alive else None)
        self.shutdown_done = not alive

    def step(self, now_s: float) -> None:
        """Run the state machine up to its next SDO request or check."""
        self.now_s = now_s
        task = self._task
        if task is None:
            return
        awaited = self._awaited
        if awaited is not None and not awaited.done:
            return
        try:
            self._awaited = task.send(awaited)
        except StopIteration:
            self._task = None
            self._awaited = None
        except _BootFailed as exc:
            self._task = None
            self._awaited = None
            self.phase = BootPhase.FAILED
            self._set_problem(str(exc))
            logger.error("node %d: boot failed: %s", self.node_id, exc)
        except _NodeLost as exc:
            self.look_again(str(exc))

    # -- the state machine -------------------------------------------------------------------

    def _run(self, task: _Steps | None) -> None:
        if self._task is not None:
            self._task.close()
        self._sdo.cancel()
        self._task = task
        self._awaited = None

    def _relive(self, *, reset_communication: bool, found: bool) -> None:
        """(Re)start the lifecycle; the phase is WAITING from now on, not from the next step."""
        self._run(self._lifecycle(reset_communication=reset_communication, found=found))
        self.phase = BootPhase.WAITING

    def _set_problem(self, text: str) -> None:
        if text != self.problem:
            self.problem = text
            self.problem_serial += 1

    def _lifecycle(self, *, reset_communication: bool, found: bool) -> _Steps:
        self.phase = BootPhase.WAITING
        self.alive = found
        self.nmt_state = None
        self.tpdo_seen = False
        if reset_communication:
            self._send_nmt(NmtCommand.RESET_COMMUNICATION)
        yield from self._look()
        self.phase = BootPhase.CONFIGURING
        logger.info("node %d: configuring", self.node_id)
        yield from self._configure()
        self.phase = BootPhase.STARTING
        yield from self._start()
        self.phase = BootPhase.READY
        self.problem = None
        logger.info(
            "node %d: ready (%s, %s; %s)",
            self.node_id,
            self.supervision.value,
            self.rpdo.describe() if self.rpdo else "",
            "; ".join(layout.describe() for layout in self.tpdos),
        )

    def _look(self) -> _Steps:
        started_s = self.now_s
        timeout_s = self.setup.boot_timeout_s
        probe: SdoTransfer | None = None
        while not self.alive:
            if probe is not None and probe.ok:
                break
            if probe is None or probe.done:
                probe = self._sdo.upload(DEVICE_TYPE_ENTRY.index, 0, self.now_s)
            if self.problem is None and self.now_s - started_s > timeout_s:
                self._set_problem(
                    f"no boot-up, heartbeat or SDO answer within {timeout_s:g} s; "
                    "looking for the drive"
                )
                logger.warning("node %d: %s", self.node_id, self.problem)
            yield None
        self._sdo.cancel()

    def _configure(self) -> _Steps:
        setup = self.setup
        self._armed = []
        self.skipped = ()
        self.supervision = setup.supervision
        self._send_nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
        yield from self._write(MODES_OF_OPERATION_ENTRY, MODE_CSP, required=True)
        yield from self._interpolation_period()
        if setup.sync_counter_overflow:
            # 0x1019 may change only while 0x1006 is 0 (CiA 301).
            yield from self._write(COMM_CYCLE_PERIOD_ENTRY, 0, required=False, quiet=True)
            yield from self._write(
                SYNC_COUNTER_OVERFLOW_ENTRY, setup.sync_counter_overflow, required=True
            )
            self._armed.append((SYNC_COUNTER_OVERFLOW_ENTRY, 0))
        if (yield from self._write(COMM_CYCLE_PERIOD_ENTRY, setup.period_us, required=False)):
            self._armed.append((COMM_CYCLE_PERIOD_ENTRY, 0))
        if setup.sync_window_us > 0:
            yield from self._write(SYNC_WINDOW_ENTRY, setup.sync_window_us, required=False)
        yield from self._supervision()
        for entry, value in (
            (FOLLOWING_ERROR_WINDOW_ENTRY, setup.following_error_window_counts),
            (FOLLOWING_ERROR_TIMEOUT_ENTRY, setup.following_error_timeout_ms),
            (QUICK_STOP_OPTION_ENTRY, setup.quick_stop_option),
            (FAULT_REACTION_OPTION_ENTRY, setup.fault_reaction_option),
            (ABORT_CONNECTION_ENTRY, setup.abort_connection_option),
        ):
            yield from self._write(entry, value, required=False)
        yield from self._pdos()
        yield from self._wait_for_csp()
        self.seed_statusword = yield from self._read(STATUSWORD_ENTRY)
        self.seed_position_counts = yield from self._read(POSITION_ACTUAL_ENTRY)
        self.seed_error_code = 0
        if self.seed_statusword & SW_FAULT:
            # Already in FAULT (latched before we came): its error code names the cause.
            self.seed_error_code = (yield from self._read(ERROR_CODE_ENTRY, required=False)) or 0

    def _interpolation_period(self) -> _Steps:
        value, index = interpolation_period(self.setup.period_us)
        yield from self._write(INTERPOLATION_PERIOD_VALUE_ENTRY, value, required=True)
        yield from self._write(INTERPOLATION_PERIOD_INDEX_ENTRY, index, required=True)
        read_value = yield from self._read(INTERPOLATION_PERIOD_VALUE_ENTRY)
        read_index = yield from self._read(INTERPOLATION_PERIOD_INDEX_ENTRY)
        if (read_value, read_index) != (value, index):
            raise _BootFailed(
                f"0x60C2 interpolation time period: wrote {value} × 10^{index} s, "
                f"read back {read_value} × 10^{read_index} s"
            )

    def _supervision(self) -> _Steps:
        setup = self.setup
        if setup.supervision is Supervision.HEARTBEAT:
            if (
                yield from self._write(PRODUCER_HEARTBEAT_ENTRY, setup.heartbeat_ms, required=False)
            ):
                armed = yield from self._write(
                    CONSUMER_HEARTBEAT_ENTRY, setup.master_heartbeat_consumer, required=False
                )
                if armed and setup.master_heartbeat_consumer:
                    self._armed.append((CONSUMER_HEARTBEAT_ENTRY, 0))
                return
            self.supervision = Supervision.GUARDING
            logger.warning(
                "node %d: no heartbeat producer (0x1017): supervised by node guarding",
                self.node_id,
            )
        else:
            # A drive guards only while its heartbeat producer is off (CiA 301).
            yield from self._write(PRODUCER_HEARTBEAT_ENTRY, 0, required=False, quiet=True)
        try:
            yield from self._write(GUARD_TIME_ENTRY, setup.guard_time_ms, required=True)
            yield from self._write(LIFE_TIME_FACTOR_ENTRY, setup.life_time_factor, required=True)
        except _BootFailed as exc:
            raise _BootFailed(
                f"no node guarding either, the drive cannot be supervised: {exc}"
            ) from exc
        self._armed += [(GUARD_TIME_ENTRY, 0), (LIFE_TIME_FACTOR_ENTRY, 0)]

    def _wait_for_csp(self) -> _Steps:
        deadline_s = self.now_s + self.setup.boot_timeout_s
        while True:
            shown = yield from self._read(MODES_OF_OPERATION_DISPLAY_ENTRY)
            if shown == MODE_CSP:
                return
            if self.now_s > deadline_s:
                raise _BootFailed(
                    f"{MODES_OF_OPERATION_DISPLAY_ENTRY} shows {shown}, not {MODE_CSP} (CSP), "
                    f"{self.setup.boot_timeout_s:g} s after 0x6060 = {MODE_CSP}"
                )
            yield None

    def _start(self) -> _Steps:
        self.nmt_state = None
        self.tpdo_seen = False
        self._send_nmt(NmtCommand.START)
        deadline_s = self.now_s + self.setup.boot_timeout_s
        while self.nmt_state != NmtState.OPERATIONAL and not self.tpdo_seen:
            if self.now_s > deadline_s:
                raise _NodeLost(f"not OPERATIONAL {self.setup.boot_timeout_s:g} s after NMT start")
            yield None

    def _shutdown(self) -> _Steps:
        for entry, value in reversed(self._armed):
            try:
                refused = yield from self._try_write(entry, value)
            except (_BootFailed, _NodeLost) as exc:
                refused = str(exc)
            if refused:
                logger.warning(
                    "node %d: shutdown: %s not set to %d: %s", self.node_id, entry, value, refused
                )
        self._armed = []
        self._send_nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
        self.shutdown_done = True

    # -- PDOs --------------------------------------------------------------------------------

    def _pdos(self) -> _Steps:
        spec = self.setup.pdo
        rpdo, rpdo_note = yield from self._pdo(Direction.RPDO, spec.rpdo, spec.mapping)
        tpdos = []
        notes = [rpdo_note] if rpdo_note else []
        for tpdo_spec in spec.tpdos:
            layout, note = yield from self._pdo(Direction.TPDO, tpdo_spec, spec.mapping)
            tpdos.append(layout)
            if note:
                notes.append(note)
        why = f" ({'; '.join(notes)})" if notes else ""
        for layouts, required in (([rpdo], RPDO_REQUIRED), (tpdos, TPDO_REQUIRED)):
            missing = missing_objects(layouts, required)
            if missing:
                mapped = "; ".join(layout.describe() for layout in layouts)
                lacked = ", ".join(describe_object(index) for index in missing)
                raise _BootFailed(f"{mapped}: lacks {lacked}{why}")
        for layout in (rpdo, *tpdos):
            problem = layout_problem(layout)
            if problem:
                raise _BootFailed(problem + why)
        asked = [index for pdo in (spec.rpdo, *spec.tpdos) for index in pdo.objects]
        for index in missing_objects([rpdo, *tpdos], asked):
            self._skip(PROCESS_ENTRIES[index], f"not mapped{why}")
        self.rpdo = rpdo
        self.tpdos = tuple(tpdos)

    def _pdo(
        self, direction: Direction, spec: PdoSpec, policy: MappingPolicy
    ) -> Generator[SdoTransfer | None, SdoTransfer | None, tuple[PdoLayout, str | None]]:
        """Configure one PDO; return its layout as read back and why it differs from the
        configuration (a refused write), if it does."""
        raw, layout = yield from self._read_layout(direction, spec.number)
        wanted_cob_id = (
            spec.cob_id or layout.cob_id or direction.predefined_cob_id(spec.number, self.node_id)
        )
        if wanted_cob_id is None:
            raise _BootFailed(f"{layout.label} has no COB-ID: configure its cob_id")
        wanted_type = (
            layout.trans_type
            if direction is Direction.RPDO and rpdo_type_usable(layout.trans_type)
            else TRANS_TYPE_EVERY_SYNC
        )
        write_map = policy is MappingPolicy.WRITE or (
            policy is MappingPolicy.AUTO and not layout.carries(spec.objects)
        )
        note = None
        if (
            write_map
            or not layout.valid
            or layout.cob_id != wanted_cob_id
            or layout.trans_type != wanted_type
        ):
            note = yield from self._rewrite_pdo(
                direction, spec, raw, layout, wanted_cob_id, wanted_type, write_map
            )
            _, layout = yield from self._read_layout(
                direction, spec.number, entries=None if write_map else layout.entries
            )
        return layout, note

    def _rewrite_pdo(
        self,
        direction: Direction,
        spec: PdoSpec,
        raw_cob_id: int,
        layout: PdoLayout,
        cob_id: int,
        trans_type: int,
        write_map: bool,
    ) -> Generator[SdoTransfer | None, SdoTransfer | None, str | None]:
        """CiA 301 order: invalidate, type, mapping (count 0, entries, count), validate."""
        cob_entry = _pdo_entry(direction, spec.number, True, 1)
        notes = []
        if layout.valid:
            refused = yield from self._try_write(cob_entry, raw_cob_id | COB_ID_INVALID)
            if refused:
                return f"{layout.label} communication parameters fixed: {refused}"
        if layout.trans_type != trans_type:
            refused = yield from self._try_write(
                _pdo_entry(direction, spec.number, True, 2), trans_type
            )
            if refused:
                notes.append(f"{layout.label} type fixed: {refused}")
        if write_map:
            count_entry = _pdo_entry(direction, spec.number, False, 0)
            refused = yield from self._try_write(count_entry, 0)
            if refused:
                notes.append(f"{layout.label} mapping fixed: {refused}")
            else:
                entries = spec.mapping_entries()
                for sub, (index, value) in enumerate(zip(spec.objects, entries, strict=True), 1):
                    refused = yield from self._try_write(
                        _pdo_entry(direction, spec.number, False, sub), value
                    )
                    if refused:
                        raise _BootFailed(
                            f"{layout.label} cannot map {describe_object(index)}: {refused}"
                        )
                refused = yield from self._try_write(count_entry, len(entries))
                if refused:
                    raise _BootFailed(
                        f"{layout.label} mapping of {len(entries)} objects: {refused}"
                    )
        flags = raw_cob_id & COB_ID_NO_RTR
        refused = yield from self._try_write(cob_entry, flags | cob_id)
        if refused:
            notes.append(f"{layout.label} COB-ID 0x{cob_id:03X}: {refused}")
        return "; ".join(notes) or None

    def _read_layout(
        self,
        direction: Direction,
        number: int,
        entries: tuple[tuple[int, int, int], ...] | None = None,
    ) -> Generator[SdoTransfer | None, SdoTransfer | None, tuple[int, PdoLayout]]:
        """Read a PDO's communication parameters and, unless ``entries`` are known (a mapping
        just read and not written since), its mapping."""
        raw = yield from self._read(_pdo_entry(direction, number, True, 1))
        if raw & COB_ID_EXTENDED:
            raise _BootFailed(f"{direction.name}{number} uses a 29-bit COB-ID (0x{raw:08X})")
        trans_type = yield from self._read(_pdo_entry(direction, number, True, 2))
        if entries is None:
            count = yield from self._read(_pdo_entry(direction, number, False, 0))
            mapped = []
            for sub in range(1, count + 1):
                value = yield from self._read(_pdo_entry(direction, number, False, sub))
                mapped.append(decode_mapping_entry(value))
            entries = tuple(mapped)
        layout = PdoLayout(
            direction,
            number,
            cob_id=raw & COB_ID_MASK,
            valid=not raw & COB_ID_INVALID,
            trans_type=trans_type,
            entries=entries,
        )
        return raw, layout

    # -- SDO with the boot's rules -------------------------------------------------------------

    def _write(
        self, entry: Entry, value: int, *, required: bool, quiet: bool = False
    ) -> Generator[SdoTransfer | None, SdoTransfer | None, bool]:
        """Write ``value``; True once the drive holds it, False if an optional entry was
        skipped (``quiet``: without a warning or a place in ``skipped``)."""
        refused = yield from self._try_write(entry, value)
        if refused is None:
            return True
        if required:
            raise _BootFailed(f"{entry} = {value}: {refused} (required)")
        if not quiet:
            self._skip(entry, refused)
        return False

    def _try_write(
        self, entry: Entry, value: int
    ) -> Generator[SdoTransfer | None, SdoTransfer | None, str | None]:
        """Write ``value``; None once the drive holds it, else why it does not.

        :raises _BootFailed: the value is outside the drive's range.
        :raises _NodeLost: no answer.
        """
        variable = self._eds_variable(entry)
        if variable is False:
            return f"not in the EDS {self.setup.eds_name}"
        if variable is not None:
            low, high = variable.min, variable.max
            if (low is not None and value < low) or (high is not None and value > high):
                raise _BootFailed(
                    f"{entry} = {value} outside the drive's range {_range(low, high)} "
                    f"(EDS {self.setup.eds_name})"
                )
        if variable is None or variable.writable:
            transfer = yield self._sdo.download(
                entry.index, entry.subindex, entry.codec.pack(value), self.now_s
            )
            if transfer.ok:
                return None
            kind = self._classify(transfer)
            if kind is AbortKind.OUT_OF_RANGE:
                raise _BootFailed(
                    f"{entry} = {value} refused: {abort_text(transfer.abort_code)}; "
                    f"{self._range_text(entry, transfer.abort_code, value)}"
                )
            if kind is not AbortKind.READ_ONLY:
                return abort_text(transfer.abort_code)
            refusal = abort_text(transfer.abort_code)
        else:
            refusal = f"read-only in the EDS {self.setup.eds_name}"
        held = yield from self._read(entry, required=False)
        if held == value:
            return None
        shown = f"0x{held:08X}" if entry.data_type == UNSIGNED32 and held is not None else held
        return f"{refusal}, holds {shown}"

    def _read(
        self, entry: Entry, *, required: bool = True
    ) -> Generator[SdoTransfer | None, SdoTransfer | None, int | None]:
        """Read and decode ``entry``; None when an optional one cannot be read."""
        if self._eds_variable(entry) is False:
            if required:
                raise _BootFailed(f"{entry}: not in the EDS {self.setup.eds_name} (required)")
            return None
        transfer = yield self._sdo.upload(entry.index, entry.subindex, self.now_s)
        if transfer.ok:
            size = entry.codec.size
            if len(transfer.data) < size:
                raise _BootFailed(f"{entry}: {len(transfer.data)} bytes read, {size} expected")
            return entry.codec.unpack(transfer.data[:size])[0]
        self._classify(transfer)
        if required:
            raise _BootFailed(f"{entry}: {abort_text(transfer.abort_code)} (required)")
        return None

    def _classify(self, transfer: SdoTransfer) -> AbortKind:
        """The kind of a failed transfer.

        :raises _NodeLost: it timed out.
        """
        if transfer.status is TransferStatus.TIMED_OUT:
            raise _NodeLost(
                f"0x{transfer.index:04X}:{transfer.subindex:02X}: "
                f"{transfer.describe_failure(self._sdo.timeout_s)}"
            )
        kind = classify_abort(transfer.abort_code or 0)
        if kind is AbortKind.TIMEOUT:
            raise _NodeLost(
                f"0x{transfer.index:04X}:{transfer.subindex:02X}: {abort_text(transfer.abort_code)}"
            )
        return kind

    def _eds_variable(self, entry: Entry):
        """The EDS variable of ``entry``; None without an EDS, False if the EDS lacks it."""
        od = self.setup.od
        if od is None:
            return None
        variable = od.get_variable(entry.index, entry.subindex)
        return False if variable is None else variable

    def _range_text(self, entry: Entry, code: int | None, value: int) -> str:
        variable = self._eds_variable(entry)
        if variable and (variable.min is not None or variable.max is not None):
            return f"the drive's range is {_range(variable.min, variable.max)} (EDS)"
        if code == ABORT_VALUE_TOO_HIGH:
            return f"the drive's maximum is below {value}"
        if code == ABORT_VALUE_TOO_LOW:
            return f"the drive's minimum is above {value}"
        return "outside the drive's range (an EDS would give it)"

    def _skip(self, entry: Entry, reason: str) -> None:
        if entry.index not in self.skipped:
            self.skipped = (*self.skipped, entry.index)
        key = (entry.index, entry.subindex)
        if key not in self._warned:
            self._warned.add(key)
            logger.warning("node %d: %s skipped: %s", self.node_id, entry, reason)


def _range(low: int | None, high: int | None) -> str:
    return f"{'' if low is None else low}..{'' if high is None else high}"
