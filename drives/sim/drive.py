"""A simulated CiA 402 servo drive in CSP mode that behaves like a real one on a CANopen bus.

Sources: CiA 301 (boot-up, NMT states and commands, heartbeat producer 0x1017 and consumer 0x1016,
node guarding 0x100C / 0x100D with life guarding, SDO server, PDO communication and mapping
0x1400-0x1A03 with their write rules, SYNC 0x1005, cycle 0x1006 and counter 0x1019, EMCY 0x1014
with error register 0x1001 and history 0x1003) and CiA 402 (device
control state machine with transitions 1-16 from :mod:`drives.cia402`, quick stop 0x605A,
fault reaction 0x605E, abort connection 0x6007, CSP objects 0x6060/0x6061, 0x6064, 0x6065,
0x6066, 0x606C, 0x607A, 0x60C2, 0x60F4, EMCY 0x8611 following error).

Behaviour: power-on (:meth:`SimulatedDrive.start`) sends the boot-up message after the quirks'
``boot_delay_s`` and enters PRE-OPERATIONAL; the SDO server (``canopen.LocalNode``) answers in
PRE-OPERATIONAL and OPERATIONAL; PDOs flow only in OPERATIONAL. Sync RPDOs (types 0-240) are
latched and applied at the next SYNC, event RPDOs (254/255) at once. At each SYNC the drive
applies its RPDOs, steps the state machine and the motion model for one period (0x1006, or 0x60C2
while 0x1006 is 0), then sends its TPDOs (types 1-240 every n-th SYNC, type 0 and 254/255 when
their data changed). FAULT REACTION ACTIVE lasts at least one SYNC. The heartbeat producer is off
until 0x1017 is written (the CiA 301 default 0); while it is off the drive answers node guarding
remote frames. A SYNC whose length does not match 0x1019 (no data, or the counter byte) is not
used and raises EMCY 0x8240. A watchdog thread per drive sends heartbeats (and delayed SDO
answers, see :mod:`drives.sim.quirks`) and detects SYNC loss (no SYNC for
``sync_timeout_factor`` x 0x1006 while OPERATION ENABLED -> fault 0x8100), master heartbeat loss
(0x1016) and life guarding loss (0x100C × 0x100D), both EMCY 0x8130 and the 0x6007 reaction;
once SYNC is lost it also finishes running quick stop and fault reaction ramps on its own clock.
A watchdog that wakes more than a period late was stalled with its process (drives simulated in the
master's process share its interpreter), so SYNCs that went out meanwhile may still wait in the
receive thread: it gives them one period before it calls the silence SYNC loss.

Units: counts, counts/s, counts/s²; times per object (0x1006 µs, 0x1016/0x1017/0x6066 ms).

Threading: CAN callbacks run in the Network's notifier thread, the watchdog in its own thread,
the test/fault-injection API in the caller's thread; one lock per drive serialises them. Work per
SYNC is a few dictionary look-ups, struct packs and one frame per TPDO; the bus delivers only
the identifiers the drives subscribed to (a kernel filter on SocketCAN), so the other drives'
PDOs cost nothing here. Callbacks never raise into the notifier (errors are logged with
``logger.exception``).

Not modelled: bus arbitration, bus load, error frames and bus-off, remote frames other than node
guarding, SDO block transfers beyond canopen's server, LSS, store/restore, TPDO SYNC start value
(0x18xx sub6), RPDO deadline (0x8250), TPDO inhibit time and event timer, dummy mapping,
bit-granular mapping, a mode-switch delay, halt, modes other than CSP (8), coasting (code 0
stops at once), and the physics behind over-temperature or over-current (injected, not
simulated).
"""

from __future__ import annotations

import logging
import math
import random
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final

import can
import canopen
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from drives import cia402, emcy, objects
from drives.bus import open_bus
from drives.cia402 import State
from drives.objects import NmtCommand, NmtState
from drives.sdo_client import (
    ABORT_DEVICE_STATE,
    ABORT_MAPPING_TOO_LONG,
    ABORT_NOT_MAPPABLE,
    ABORT_VALUE_RANGE,
    ABORT_VALUE_TOO_HIGH,
    ABORT_VALUE_TOO_LOW,
)
from drives.sim.dynamics import Axis, DriveModel
from drives.sim.quirks import DriveQuirks, served_od

__all__ = ["DriveModel", "SimulatedDrive", "SimulatedDriveSet", "start_simulated_drives"]

logger = logging.getLogger(__name__)


#: Objects kept in the process image: PDO-mappable, served to SDO from memory, never blocking.
_PROCESS_OBJECTS: Final = (
    objects.ERROR_REGISTER,
    objects.ERROR_CODE,
    objects.CONTROLWORD,
    objects.STATUSWORD,
    objects.MODES_OF_OPERATION,
    objects.MODES_OF_OPERATION_DISPLAY,
    objects.POSITION_ACTUAL,
    objects.FOLLOWING_ERROR_WINDOW,
    objects.FOLLOWING_ERROR_TIMEOUT,
    objects.VELOCITY_ACTUAL,
    objects.TARGET_POSITION,
    objects.PROFILE_DECELERATION,
    objects.QUICK_STOP_DECELERATION,
    objects.FOLLOWING_ERROR_ACTUAL,
)

#: Allowed values of option codes and modes (others abort with 0x06090030).
_ALLOWED_VALUES: Final[Mapping[int, frozenset[int]]] = MappingProxyType(
    {
        objects.QUICK_STOP_OPTION: frozenset(range(0, 9)),
        objects.FAULT_REACTION_OPTION: frozenset(range(0, 5)),
        objects.ABORT_CONNECTION_OPTION: frozenset(range(0, 4)),
        objects.MODES_OF_OPERATION: frozenset({objects.MODE_NONE, objects.MODE_CSP}),
    }
)

#: Error register bits per EMCY code class, as (code, mask, bit); bit 0 "generic" is always set.
_REGISTER_BITS: Final = (
    (0x2000, 0xF000, emcy.ERROR_REGISTER_CURRENT),
    (0x3000, 0xF000, emcy.ERROR_REGISTER_VOLTAGE),
    (0x4000, 0xF000, emcy.ERROR_REGISTER_TEMPERATURE),
    (0x8100, 0xFF00, emcy.ERROR_REGISTER_COMMUNICATION),
    (0x8200, 0xFF00, emcy.ERROR_REGISTER_COMMUNICATION),
    (0x8600, 0xFF00, emcy.ERROR_REGISTER_PROFILE),
)

_MOTION_STATES: Final = (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)
_HISTORY_LENGTH: Final[int] = 4
#: Control period while neither 0x1006 nor 0x60C2 gives one, s.
DEFAULT_PERIOD_S: Final[float] = 0.004
_WINDOW_OFF: Final[int] = 0xFFFF_FFFF  # 0x6065 value that switches following control off


#: Model of a drive created without one.
DEFAULT_MODEL: Final = DriveModel()
#: Wire time of one 6-byte frame at 1 Mbit/s (115 bits with worst-case stuffing), s.
_FRAME_S: Final[float] = 115e-6
#: A drive that behaves as the full CiA 402 drive.
NO_QUIRKS: Final = DriveQuirks()


@dataclass(frozen=True)
class _PdoEntry:
    index: int
    codec: struct.Struct
    offset: int


@dataclass(frozen=True)
class _Pdo:
    number: int
    cob_id: int
    trans_type: int
    entries: tuple[_PdoEntry, ...]
    size: int


def _is_pdo_object(index: int, base: int) -> bool:
    return base <= index < base + objects.PDO_COUNT


def _check_range(variable: ODVariable, value: int) -> None:
    """Refuse a value outside the served object's range (its EDS LowLimit / HighLimit)."""
    low, high = variable.min, variable.max
    if low is not None and low == high and value != low:
        raise SdoAbortedError(ABORT_VALUE_RANGE)
    if high is not None and value > high:
        raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
    if low is not None and value < low:
        raise SdoAbortedError(ABORT_VALUE_TOO_LOW)


class SimulatedDrive:
    """One simulated CiA 402 drive (CSP) answering on ``network`` as node ``node_id``.

    :param network: a connected ``canopen.Network``; several drives may share it, the master
        needs its own (one node per id per Network).
    :param node_id: CANopen node-ID, 1..127.
    :param model: motion model and SYNC timeout factor.
    :param quirks: how the drive departs from the full CiA 402 drive (late boot, missing
        objects, fixed PDOs, ...; see :mod:`drives.sim.quirks`).
    :param clock: monotonic clock in seconds, for the watchdogs.
    :raises ValueError: if ``node_id`` is not in 1..127.
    """

    #: Longest sleep of the watchdog thread, s (bounds the reaction to configuration changes).
    WATCHDOG_MAX_WAIT_S: float = 0.05
    #: Free-running internal steps (quick stop or fault reaction without SYNC) start once SYNC
    #: is lost: after the larger of this many periods and the model's SYNC timeout factor.
    FREE_RUN_AFTER_PERIODS: float = 2.0

    def __init__(
        self,
        network: canopen.Network,
        node_id: int,
        *,
        model: DriveModel = DEFAULT_MODEL,
        quirks: DriveQuirks = NO_QUIRKS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"simulated drive: node_id = {node_id}, must be in 1..127")
        self.network = network
        self.node_id = node_id
        self.model = model
        self.quirks = quirks
        self._clock = clock
        # SDO answer delays drawn per drive, the same on every run.
        self._random = random.Random(node_id)
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._subscriptions: list[tuple[int, Callable]] = []
        self._pdo_subscriptions: list[tuple[int, Callable]] = []
        self._consumer_subscriptions: list[tuple[int, Callable]] = []

        # The full dictionary types and defaults the drive's model; the served one (what SDO
        # and the EDS see) lacks what the quirks remove.
        self._od = objects.build_drive_od(node_id)
        self._served = served_od(node_id, quirks)
        self._local = canopen.LocalNode(node_id, self._served)
        self._local.sdo.send_response = self._send_sdo_response
        # The drive produces its heartbeat itself (real NMT state, silence on demand); the
        # LocalNode's NmtSlave would start a second producer on every 0x1017 write.
        self._local._write_callbacks.remove(self._local.nmt.on_write)
        self._local.add_read_callback(self._on_sdo_read)
        self._local.add_write_callback(self._on_sdo_write)
        self._variables: dict[int, ODVariable] = {
            index: self._od.get_variable(index) for index in _PROCESS_OBJECTS
        }

        self._axis = Axis(model)
        self._powered = False
        self._answering = True
        self._nmt = NmtState.INITIALISING
        self._boot_at: float | None = None
        self._state = State.NOT_READY_TO_SWITCH_ON
        self._image: dict[int, int] = {}
        self._params: dict[tuple[int, int], int] = {}
        self._rpdos: dict[int, _Pdo] = {}
        self._tpdos: dict[int, _Pdo] = {}
        self._latched: dict[int, bytes] = {}
        self._tpdo_countdown: dict[int, int] = {}
        self._tpdo_last: dict[int, bytes] = {}
        self._pdo_length_error = False
        self._sync_length_error = False
        self._dirty: set[int] = set()
        self._previous_controlword = 0
        self._fault_reaction_reported = False
        self._fe_over_s = 0.0
        self._last_sync: float | None = None
        self._sync_grace_until: float | None = None
        self._last_step: float = 0.0
        self._next_heartbeat: float | None = None
        self._consumers: dict[int, float] = {}  # node-ID -> timeout s
        self._consumer_seen: dict[int, float] = {}
        self._consumer_lost: set[int] = set()
        self._fault_at_boot = False
        self._sdo_answers: deque[tuple[float, bytes]] = deque()
        self._late_tpdos: deque[list[tuple[int, bytes]]] = deque()
        self._guard_toggle = 0
        self._guarded_at: float | None = None
        self._life_lost = False
        self._reset_application()
        self._reset_communication()

    # ---------------------------------------------------------------- power and silence

    def start(self) -> None:
        """Power on: reload every object, boot (boot-up message) and enter PRE-OPERATIONAL.

        :raises RuntimeError: if the drive is already powered.
        """
        with self._lock:
            if self._powered:
                raise RuntimeError(f"simulated drive {self.node_id}: already started")
            self._local.data_store.clear()
            self._reset_application()
            self._reset_communication()
            self._axis.hold()
            self._powered = True
            self._answering = True
            self._fault_at_boot = self.quirks.fault_at_power_on
            self._begin_boot()
        if not self._local.has_network():
            # Association gives the SDO server its Network to answer on; the drive then
            # replaces the LocalNode's own SDO and NMT handlers with its gated ones.
            self._local.associate_network(self.network)
            self.network.unsubscribe(self._local.sdo.rx_cobid, self._local.sdo.on_request)
            self.network.unsubscribe(objects.NMT_COB_ID, self._local.nmt.on_command)
        self._subscribe(self._subscriptions, self._local.sdo.rx_cobid, self._on_sdo_request)
        self._subscribe(self._subscriptions, objects.NMT_COB_ID, self._on_nmt)
        # canopen drops remote frames before its subscribers: node guarding requests reach
        # the drive through a listener of its own, and the subscription lets them through
        # the bus filter.
        self._subscribe(
            self._subscriptions, objects.HEARTBEAT_COB_ID_BASE + self.node_id, self._ignore
        )
        self.network.notifier.add_listener(self._on_frame)
        with self._lock:
            self._resubscribe_sync()
            self._compile_pdos()
            self._configure_consumers()
        self._stopping.clear()
        self._thread = threading.Thread(
            target=self._watchdog_loop, name=f"sim-drive-{self.node_id}", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        """Power off: no more frames, callbacks or watchdog; safe to call twice."""
        with self._lock:
            if not self._powered:
                return
            self._powered = False
        self._stopping.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        for subscriptions in (
            self._subscriptions,
            self._pdo_subscriptions,
            self._consumer_subscriptions,
        ):
            self._unsubscribe_all(subscriptions)
        self.network.notifier.remove_listener(self._on_frame)
        with self._lock:
            self._nmt = NmtState.INITIALISING
            self._sdo_answers.clear()

    def stop_answering(self) -> None:
        """Go silent, like a cut cable: no heartbeat, TPDO, SDO reply or EMCY, and nothing is
        received; the drive's own supervision keeps running (SYNC loss still faults it)."""
        with self._lock:
            self._answering = False
        logger.info("node %d: simulated drive stops answering", self.node_id)

    def resume_answering(self) -> None:
        """Reconnect after :meth:`stop_answering`; the drive keeps the state it reached."""
        with self._lock:
            self._answering = True
            self._next_heartbeat = None
        self._wake.set()
        logger.info("node %d: simulated drive answers again", self.node_id)

    # ---------------------------------------------------------------- fault injection

    def inject_following_error(self) -> None:
        """Push the actual position away from the demand by more than the following error
        window for longer than the timeout (0x6065/0x6066), so an enabled CSP axis faults with
        EMCY 0x8611 at the next SYNCs. Without following control (window 0xFFFFFFFF) the axis is
        only displaced."""
        with self._lock:
            window = self._image[objects.FOLLOWING_ERROR_WINDOW]
            timeout_s = self._image[objects.FOLLOWING_ERROR_TIMEOUT] / 1000.0
            recoverable_counts = self.model.max_velocity_counts_s * (
                timeout_s + 4 * self._period_s()
            )
            self._axis.disturb(-(min(window, 1 << 30) + recoverable_counts + 1))

    def inject_fault(self, emcy_code: int = emcy.EMCY_EXCESS_TEMPERATURE_DEVICE) -> None:
        """Raise a drive fault with ``emcy_code`` (default 0x4210 excess temperature device):
        EMCY, 0x603F, 0x1001, transition 13, then 14 after the 0x605E reaction."""
        with self._lock:
            self._fault(emcy_code)

    # ---------------------------------------------------------------- observation

    @property
    def state(self) -> State:
        """CiA 402 state."""
        with self._lock:
            return self._state

    @property
    def statusword(self) -> int:
        """0x6041 as the drive reports it."""
        with self._lock:
            return self._image[objects.STATUSWORD]

    @property
    def controlword(self) -> int:
        """0x6040 last applied."""
        with self._lock:
            return self._image[objects.CONTROLWORD]

    @property
    def position_actual_counts(self) -> int:
        """0x6064."""
        with self._lock:
            return self._image[objects.POSITION_ACTUAL]

    @property
    def target_counts(self) -> int:
        """0x607A last applied."""
        with self._lock:
            return self._image[objects.TARGET_POSITION]

    @property
    def following_error_counts(self) -> int:
        """0x60F4."""
        with self._lock:
            return self._image[objects.FOLLOWING_ERROR_ACTUAL]

    @property
    def error_code(self) -> int:
        """0x603F."""
        with self._lock:
            return self._image[objects.ERROR_CODE]

    @property
    def mode_display(self) -> int:
        """0x6061."""
        with self._lock:
            return self._image[objects.MODES_OF_OPERATION_DISPLAY]

    @property
    def nmt_state(self) -> NmtState:
        """NMT state (INITIALISING while booting or powered off)."""
        with self._lock:
            return self._nmt

    # ---------------------------------------------------------------- NMT

    def _begin_boot(self) -> None:
        self._nmt = NmtState.INITIALISING
        self._boot_at = self._clock() + self.quirks.boot_delay_s
        self._wake.set()

    def _finish_boot(self) -> None:
        self._boot_at = None
        if self._state is State.NOT_READY_TO_SWITCH_ON:
            self._set_state(*cia402.drive_transition(self._state, 0, quick_stop_option=0))
        self._send(objects.HEARTBEAT_COB_ID_BASE + self.node_id, bytes([NmtState.INITIALISING]))
        self._set_nmt(NmtState.PRE_OPERATIONAL)
        self._next_heartbeat = None
        if self._fault_at_boot:
            # A fault latched before power-off: the drive comes up in FAULT and says why.
            self._fault_at_boot = False
            self._fault(emcy.EMCY_HEARTBEAT)
            self._set_state(*cia402.fault_reaction_complete(self._state))

    def _set_nmt(self, nmt: NmtState) -> None:
        if nmt is self._nmt:
            return
        logger.info("node %d: NMT %s -> %s", self.node_id, self._nmt.name, nmt.name)
        if self._nmt is NmtState.OPERATIONAL:
            self._abort_connection(emcy.EMCY_COMMUNICATION, f"NMT {nmt.name}")
        self._nmt = nmt
        self._latched.clear()
        self._next_heartbeat = None
        self._wake.set()

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        try:
            with self._lock:
                if not self._answering or self._boot_at is not None or len(data) < 2:
                    return
                command, target = data[0], data[1]
                if target not in (0, self.node_id):
                    return
                if command == NmtCommand.START:
                    self._set_nmt(NmtState.OPERATIONAL)
                elif command == NmtCommand.STOP:
                    self._set_nmt(NmtState.STOPPED)
                elif command == NmtCommand.ENTER_PRE_OPERATIONAL:
                    self._set_nmt(NmtState.PRE_OPERATIONAL)
                elif command == NmtCommand.RESET_NODE:
                    self._reset(application=True)
                elif command == NmtCommand.RESET_COMMUNICATION:
                    self._reset(application=False)
        except Exception:
            logger.exception("node %d: NMT command %s", self.node_id, bytes(data).hex())

    def _reset(self, *, application: bool) -> None:
        logger.info(
            "node %d: NMT reset %s", self.node_id, "node" if application else "communication"
        )
        self._set_nmt(NmtState.INITIALISING)
        for index in list(self._local.data_store):
            if application or index < 0x2000:
                del self._local.data_store[index]
        if application:
            self._reset_application()
            self._axis.hold()
        self._reset_communication()
        self._resubscribe_sync()
        self._compile_pdos()
        self._configure_consumers()
        self._begin_boot()

    def _reset_application(self) -> None:
        for index, var in self._variables.items():
            self._image[index] = var.default
        self._image[objects.POSITION_ACTUAL] = round(self._axis.position_counts)
        self._image[objects.TARGET_POSITION] = round(self._axis.position_counts)
        for index in (
            objects.QUICK_STOP_OPTION,
            objects.FAULT_REACTION_OPTION,
            objects.ABORT_CONNECTION_OPTION,
        ):
            self._params[(index, 0)] = self._od[index].default
        for sub in (objects.INTERPOLATION_PERIOD_VALUE, objects.INTERPOLATION_PERIOD_INDEX):
            self._params[(objects.INTERPOLATION_PERIOD, sub)] = self._od.get_variable(
                objects.INTERPOLATION_PERIOD, sub
            ).default
        self._state = State.NOT_READY_TO_SWITCH_ON
        self._previous_controlword = 0
        self._fe_over_s = 0.0
        self._update_statusword()

    def _reset_communication(self) -> None:
        for index in (
            objects.COB_ID_SYNC,
            objects.COMM_CYCLE_PERIOD,
            objects.COB_ID_EMCY,
            objects.PRODUCER_HEARTBEAT,
            objects.GUARD_TIME,
            objects.LIFE_TIME_FACTOR,
            objects.SYNC_COUNTER_OVERFLOW,
        ):
            self._params[(index, 0)] = self._od[index].default
        self._last_sync = None
        self._tpdo_countdown.clear()
        self._tpdo_last.clear()
        self._latched.clear()
        self._late_tpdos.clear()
        self._guard_toggle = 0
        self._guarded_at = None
        self._life_lost = False

    # ---------------------------------------------------------------- SDO

    def _on_sdo_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        try:
            with self._lock:
                if not self._answering or self._nmt in (
                    NmtState.INITIALISING,
                    NmtState.STOPPED,
                ):
                    return
                self._dirty.clear()
                self._local.sdo.on_request(can_id, data, timestamp)
                if self._dirty:
                    self._apply_written(self._dirty)
        except Exception:
            logger.exception("node %d: SDO request %s", self.node_id, bytes(data).hex())

    def _on_sdo_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        if subindex == 0 and index in self._image:
            return self._image[index]
        return None

    def _on_sdo_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """Validate a write before canopen stores it; raise SdoAbortedError to refuse it."""
        value = od.decode_raw(data)
        allowed = _ALLOWED_VALUES.get(index)
        if allowed is not None and value not in allowed:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        _check_range(od, value)
        if index == objects.SYNC_COUNTER_OVERFLOW:
            if value == 1 or value > 240:
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # CiA 301: 0 or 2..240
            if self._params[(objects.COMM_CYCLE_PERIOD, 0)]:
                raise SdoAbortedError(ABORT_DEVICE_STATE)  # changed only while 0x1006 is 0
        if _is_pdo_object(index, objects.RPDO_COMM) or _is_pdo_object(index, objects.TPDO_COMM):
            self._check_comm_write(index, subindex, value)
        elif _is_pdo_object(index, objects.RPDO_MAP):
            self._check_map_write(index, subindex, value, objects.RPDO_COMM - objects.RPDO_MAP)
        elif _is_pdo_object(index, objects.TPDO_MAP):
            self._check_map_write(index, subindex, value, objects.TPDO_COMM - objects.TPDO_MAP)
        elif index == objects.PREDEFINED_ERROR_FIELD and value != 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)  # only 0 (clear the history) is allowed
        if index in self._image and subindex == 0:
            self._image[index] = value
        else:
            self._params[(index, subindex)] = value
        self._dirty.add(index)

    def _check_comm_write(self, index: int, subindex: int, value: int) -> None:
        if subindex == 1:
            current = self._read(index, 1)
            valid_now = not current & objects.COB_ID_INVALID
            valid_next = not value & objects.COB_ID_INVALID
            if valid_now and valid_next and (current ^ value) & objects.COB_ID_MASK:
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # change the COB-ID only while invalid
        elif subindex == 2 and objects.TRANS_TYPE_SYNC_MAX < value < 254:
            raise SdoAbortedError(ABORT_VALUE_RANGE)

    def _check_map_write(self, index: int, subindex: int, value: int, comm_offset: int) -> None:
        if not self._read(index + comm_offset, 1) & objects.COB_ID_INVALID:
            raise SdoAbortedError(ABORT_DEVICE_STATE)  # CiA 301: map only an invalid PDO
        is_rpdo = index < objects.TPDO_MAP
        if subindex == 0:
            if value > objects.PDO_MAX_ENTRIES:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            bits = sum(self._read(index, sub) & 0xFF for sub in range(1, value + 1))
            if bits > 64:
                raise SdoAbortedError(ABORT_MAPPING_TOO_LONG)
            return
        if self._read(index, 0) != 0:
            raise SdoAbortedError(ABORT_DEVICE_STATE)  # entries only while sub0 is 0
        if value == 0:
            return
        obj_index, obj_sub, bits = objects.decode_mapping_entry(value)
        var = self._od.get_variable(obj_index, obj_sub)
        if (
            var is None
            or not var.pdo_mappable
            or obj_sub != 0
            or obj_index not in self._image
            or bits != len(var)
            or (is_rpdo and not var.writable)
        ):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)

    def _apply_written(self, indices: set[int]) -> None:
        if objects.CONTROLWORD in indices:
            self._apply_controlword()
        if objects.MODES_OF_OPERATION in indices:
            self._apply_mode()
        if objects.COB_ID_SYNC in indices:
            self._resubscribe_sync()
        if any(0x1400 <= index < 0x1C00 for index in indices):
            self._compile_pdos()
        if objects.CONSUMER_HEARTBEAT in indices:
            self._configure_consumers()
        if objects.PREDEFINED_ERROR_FIELD in indices:
            for sub in range(1, _HISTORY_LENGTH + 1):
                self._local.data_store[objects.PREDEFINED_ERROR_FIELD].pop(sub, None)
        if objects.PRODUCER_HEARTBEAT in indices:
            self._next_heartbeat = None
        self._update_statusword()
        self._send_event_tpdos()
        self._wake.set()

    def _read(self, index: int, subindex: int) -> int:
        var = self._od.get_variable(index, subindex)
        return var.decode_raw(self._local.get_data(index, subindex))

    # ---------------------------------------------------------------- PDO

    def _compile_pdos(self) -> None:
        self._unsubscribe_all(self._pdo_subscriptions)
        self._rpdos = self._compile(objects.RPDO_COMM, objects.RPDO_MAP)
        self._tpdos = self._compile(objects.TPDO_COMM, objects.TPDO_MAP)
        self._latched.clear()
        self._tpdo_countdown = {n: pdo.trans_type for n, pdo in self._tpdos.items()}
        self._tpdo_last.clear()
        for pdo in self._rpdos.values():
            self._subscribe(self._pdo_subscriptions, pdo.cob_id, self._on_rpdo)

    def _compile(self, comm_base: int, map_base: int) -> dict[int, _Pdo]:
        compiled = {}
        for n in range(1, objects.PDO_COUNT + 1):
            cob_id = self._read(comm_base + n - 1, 1)
            if cob_id & objects.COB_ID_INVALID:
                continue
            entries = []
            offset = 0
            for sub in range(1, self._read(map_base + n - 1, 0) + 1):
                index, _, bits = objects.decode_mapping_entry(self._read(map_base + n - 1, sub))
                codec = ODVariable.STRUCT_TYPES[self._variables[index].data_type]
                entries.append(_PdoEntry(index, codec, offset))
                offset += bits // 8
            compiled[n] = _Pdo(
                number=n,
                cob_id=cob_id & objects.COB_ID_MASK,
                trans_type=self._read(comm_base + n - 1, 2),
                entries=tuple(entries),
                size=offset,
            )
        return compiled

    def _on_rpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        try:
            with self._lock:
                if not self._answering or self._nmt is not NmtState.OPERATIONAL:
                    return
                for pdo in self._rpdos.values():
                    if pdo.cob_id == can_id:
                        self._receive_rpdo(pdo, bytes(data))
        except Exception:
            logger.exception("node %d: RPDO 0x%03X", self.node_id, can_id)

    def _receive_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        if len(data) != pdo.size:
            if not self._pdo_length_error:
                self._pdo_length_error = True
                code = (
                    emcy.EMCY_PDO_LENGTH if len(data) < pdo.size else emcy.EMCY_PDO_LENGTH_EXCEEDED
                )
                self._send_emcy(code, self._image[objects.ERROR_REGISTER])
            return
        self._pdo_length_error = False
        if pdo.trans_type <= objects.TRANS_TYPE_SYNC_MAX:
            self._latched[pdo.number] = data
            return
        written = self._unpack(pdo, data)
        self._apply_written(written)

    def _unpack(self, pdo: _Pdo, data: bytes) -> set[int]:
        for entry in pdo.entries:
            (self._image[entry.index],) = entry.codec.unpack_from(data, entry.offset)
        return {entry.index for entry in pdo.entries}

    def _pack(self, pdo: _Pdo) -> bytes:
        buffer = bytearray(pdo.size)
        for entry in pdo.entries:
            entry.codec.pack_into(buffer, entry.offset, self._image[entry.index])
        return bytes(buffer)

    def _send_sync_tpdos(self, sync_s: float) -> None:
        """The synchronous TPDOs answering the SYNC received with timestamp ``sync_s``: on the
        wire right after it, one frame time apart, however late this thread runs (a real
        drive answers within the period; a simulated one shares its host with the master)."""
        frames = []
        for n, pdo in self._tpdos.items():
            trans_type = pdo.trans_type
            if trans_type == objects.TRANS_TYPE_SYNC_ACYCLIC:
                self._send_tpdo_if_changed(pdo)
            elif trans_type <= objects.TRANS_TYPE_SYNC_MAX:
                self._tpdo_countdown[n] -= 1
                if self._tpdo_countdown[n] <= 0:
                    self._tpdo_countdown[n] = trans_type
                    data = self._pack(pdo)
                    self._tpdo_last[n] = data
                    frames.append((pdo.cob_id, data))
        late = self.quirks.late_tpdo_periods
        if late:
            # Sent ``late`` SYNCs after the one they answer, with the data of that one.
            self._late_tpdos.append(frames)
            frames = self._late_tpdos.popleft() if len(self._late_tpdos) > late else []
        for number, (cob_id, data) in enumerate(frames, start=1):
            self._send(cob_id, data, sync_s + number * _FRAME_S)

    def _send_event_tpdos(self) -> None:
        if self._nmt is not NmtState.OPERATIONAL:
            return
        for pdo in self._tpdos.values():
            if pdo.trans_type > objects.TRANS_TYPE_SYNC_MAX:
                self._send_tpdo_if_changed(pdo)

    def _send_tpdo_if_changed(self, pdo: _Pdo) -> None:
        data = self._pack(pdo)
        if self._tpdo_last.get(pdo.number) != data:
            self._tpdo_last[pdo.number] = data
            self._send(pdo.cob_id, data)

    # ---------------------------------------------------------------- SYNC and the control step

    def _resubscribe_sync(self) -> None:
        for can_id, callback in list(self._subscriptions):
            if callback == self._on_sync:
                self.network.unsubscribe(can_id, callback)
                self._subscriptions.remove((can_id, callback))
        self._filter_bus()
        if self._powered:
            cob_id = self._params[(objects.COB_ID_SYNC, 0)] & objects.COB_ID_MASK
            self._subscribe(self._subscriptions, cob_id, self._on_sync)

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        try:
            with self._lock:
                if not self._answering or self._nmt not in (
                    NmtState.PRE_OPERATIONAL,
                    NmtState.OPERATIONAL,
                ):
                    return
                expected = 1 if self._params[(objects.SYNC_COUNTER_OVERFLOW, 0)] > 1 else 0
                if len(data) != expected:
                    if not self._sync_length_error:
                        self._sync_length_error = True
                        self._send_emcy(emcy.EMCY_SYNC_LENGTH, self._image[objects.ERROR_REGISTER])
                    return
                self._sync_length_error = False
                now = self._clock()
                if self._last_sync is None:
                    self._wake.set()  # SYNC supervision starts: the watchdog learns its limit
                self._last_sync = now
                operational = self._nmt is NmtState.OPERATIONAL
                if operational and self._latched:
                    written: set[int] = set()
                    for number, payload in self._latched.items():
                        written |= self._unpack(self._rpdos[number], payload)
                    self._latched.clear()
                    if objects.MODES_OF_OPERATION in written:
                        self._apply_mode()
                self._step(self._period_s(), now)
                if operational:
                    self._send_sync_tpdos(timestamp)
                    self._send_event_tpdos()
        except Exception:
            logger.exception("node %d: SYNC step", self.node_id)

    def _period_s(self) -> float:
        cycle_us = self._params[(objects.COMM_CYCLE_PERIOD, 0)]
        if cycle_us > 0:
            return cycle_us * 1e-6
        value = self._params[(objects.INTERPOLATION_PERIOD, 1)]
        exponent = self._params[(objects.INTERPOLATION_PERIOD, 2)]
        return value * 10.0**exponent if value > 0 else DEFAULT_PERIOD_S

    def _step(self, period_s: float, now: float) -> None:
        """One control period: state machine, motion, following error, statusword."""
        self._last_step = now
        self._apply_controlword()
        state = self._state
        axis = self._axis
        if state is State.OPERATION_ENABLED:
            if self._image[objects.MODES_OF_OPERATION_DISPLAY] == objects.MODE_CSP:
                axis.follow(float(self._image[objects.TARGET_POSITION]), period_s)
                self._check_following_error(period_s)
            else:
                axis.hold()
        elif state is State.QUICK_STOP_ACTIVE:
            option = self._params[(objects.QUICK_STOP_OPTION, 0)]
            ramp = option - 4 if option > 4 else option  # 5..8 use the ramps of 1..4
            if axis.brake(self._stop_decel(ramp), period_s):
                self._set_state(*cia402.quick_stop_complete(state, quick_stop_option=option))
        elif state is State.FAULT_REACTION_ACTIVE:
            stopped = axis.brake(
                self._stop_decel(self._params[(objects.FAULT_REACTION_OPTION, 0)]), period_s
            )
            if stopped and self._fault_reaction_reported:
                self._set_state(*cia402.fault_reaction_complete(state))
            self._fault_reaction_reported = True
        else:
            axis.hold()
        self._update_motion_objects()
        self._update_statusword()

    def _stop_decel(self, option: int) -> float:
        """Deceleration of a quick stop (0x605A 1..4) or fault reaction (0x605E 0..4) code."""
        if option == 0:
            return math.inf
        if option == 1:
            return float(self._image[objects.PROFILE_DECELERATION]) or math.inf
        if option == 2:
            return float(self._image[objects.QUICK_STOP_DECELERATION]) or math.inf
        return self.model.max_accel_counts_s2

    def _check_following_error(self, period_s: float) -> None:
        window = self._image[objects.FOLLOWING_ERROR_WINDOW]
        if window == _WINDOW_OFF or abs(self._axis.following_error_counts) <= window:
            self._fe_over_s = 0.0
            return
        self._fe_over_s += period_s
        if self._fe_over_s * 1000.0 > self._image[objects.FOLLOWING_ERROR_TIMEOUT]:
            self._fe_over_s = 0.0
            self._fault(emcy.EMCY_FOLLOWING_ERROR)

    def _update_motion_objects(self) -> None:
        axis = self._axis
        image = self._image
        image[objects.POSITION_ACTUAL] = round(axis.position_counts)
        image[objects.VELOCITY_ACTUAL] = round(axis.velocity_counts_s)
        following_error = (
            round(axis.following_error_counts) if self._state is State.OPERATION_ENABLED else 0
        )
        image[objects.FOLLOWING_ERROR_ACTUAL] = max(min(following_error, 2**31 - 1), -(2**31))

    def _update_statusword(self) -> None:
        window = self._image[objects.FOLLOWING_ERROR_WINDOW]
        following_error = self._image[objects.FOLLOWING_ERROR_ACTUAL]
        self._image[objects.STATUSWORD] = cia402.encode_statusword(
            self._state,
            warning=bool(self._consumer_lost) or self._life_lost,
            internal_limit=self._axis.limited and self._state is State.OPERATION_ENABLED,
            following=(
                self._state is State.OPERATION_ENABLED
                and self._image[objects.MODES_OF_OPERATION_DISPLAY] == objects.MODE_CSP
            ),
            following_error=window != _WINDOW_OFF and abs(following_error) > window,
        )

    # ---------------------------------------------------------------- 402 state machine

    def _apply_controlword(self) -> None:
        controlword = self._image[objects.CONTROLWORD]
        transition = cia402.drive_transition(
            self._state,
            controlword,
            quick_stop_option=self._params[(objects.QUICK_STOP_OPTION, 0)],
            previous_controlword=self._previous_controlword,
        )
        self._previous_controlword = controlword
        self._set_state(*transition)

    def _apply_mode(self) -> None:
        mode = self._image[objects.MODES_OF_OPERATION]
        if mode in _ALLOWED_VALUES[objects.MODES_OF_OPERATION]:
            self._image[objects.MODES_OF_OPERATION_DISPLAY] = mode

    def _set_state(self, state: State, transition: int | None) -> None:
        if transition is None:
            return
        previous = self._state
        self._state = state
        logger.info(
            "node %d: CiA 402 %s -> %s (transition %d)",
            self.node_id,
            previous.name,
            state.name,
            transition,
        )
        if state is State.OPERATION_ENABLED:
            self._axis.hold()  # on enable the demand is the actual position
            self._fe_over_s = 0.0
            if self._last_sync is not None:
                self._last_sync = self._clock()  # SYNC supervision restarts with the enable
                self._sync_grace_until = None
                self._wake.set()
        elif transition == 15:
            self._image[objects.ERROR_CODE] = emcy.EMCY_ERROR_RESET
            self._image[objects.ERROR_REGISTER] = 0
            self._send_emcy(emcy.EMCY_ERROR_RESET, 0)
        self._update_motion_objects()
        self._update_statusword()

    def _fault(self, code: int) -> None:
        """A fault inside the drive: EMCY, 0x603F, 0x1001, 0x1003 and transition 13."""
        register = self._image[objects.ERROR_REGISTER] | emcy.ERROR_REGISTER_GENERIC
        for value, mask, bit in _REGISTER_BITS:
            if code & mask == value:
                register |= bit
        self._image[objects.ERROR_CODE] = code
        self._image[objects.ERROR_REGISTER] = register
        self._push_history(code)
        logger.warning(
            "node %d: fault EMCY 0x%04X (%s)", self.node_id, code, emcy.describe_emcy(code)
        )
        self._send_emcy(code, register)
        state, transition = cia402.fault_detected(self._state)
        if transition is not None:
            self._fault_reaction_reported = False
            self._set_state(state, transition)
        self._update_statusword()
        self._send_event_tpdos()
        self._wake.set()

    def _push_history(self, code: int) -> None:
        store = self._local.data_store.setdefault(objects.PREDEFINED_ERROR_FIELD, {})
        history = [self._read(objects.PREDEFINED_ERROR_FIELD, sub) for sub in range(1, 4)]
        count = min(self._read(objects.PREDEFINED_ERROR_FIELD, 0) + 1, _HISTORY_LENGTH)
        for sub, value in enumerate([code, *history], start=1):
            store[sub] = struct.pack("<L", value)
        store[0] = bytes([count])

    def _abort_connection(self, code: int, reason: str) -> bool:
        """Apply 0x6007 (0 none, 1 fault with EMCY ``code``, 2 disable voltage, 3 quick stop)
        if OPERATION ENABLED; return True if it raised the fault (and so sent the EMCY)."""
        if self._state is not State.OPERATION_ENABLED:
            return False
        option = self._params[(objects.ABORT_CONNECTION_OPTION, 0)]
        logger.warning("node %d: connection lost (%s), 0x6007 = %d", self.node_id, reason, option)
        if option == 1:
            self._fault(code)
            return True
        if option in (2, 3):
            command = cia402.Command.DISABLE_VOLTAGE if option == 2 else cia402.Command.QUICK_STOP
            self._image[objects.CONTROLWORD] = int(command)
            self._apply_controlword()
        return False

    # ---------------------------------------------------------------- EMCY and frames

    def _send_emcy(self, code: int, register: int) -> None:
        cob_id = self._params[(objects.COB_ID_EMCY, 0)]
        if cob_id & objects.COB_ID_INVALID or self._nmt is NmtState.INITIALISING:
            return
        self._send(cob_id & objects.COB_ID_MASK, emcy.pack_emcy(code, register))

    def _send(self, can_id: int, data: bytes, wire_s: float | None = None) -> None:
        """Send a frame stamped with when it is on the wire: ``wire_s``, or now (the stamp
        reaches the other buses of a ``virtual`` channel, see :func:`start_simulated_drives`)."""
        if self._answering and self._powered:
            message = can.Message(
                arbitration_id=can_id,
                data=data,
                is_extended_id=False,
                timestamp=time.time() if wire_s is None else wire_s,
            )
            with self.network.send_lock:
                self.network.bus.send(message)

    def _send_sdo_response(self, response: bytes) -> None:
        """The SDO server's answer: at once, or after the quirks' SDO delay (the watchdog
        sends it; answers keep their order)."""
        low, high = self.quirks.sdo_delay_s
        if high <= 0:
            self._send(self._local.sdo.tx_cobid, response)
            return
        due = self._clock() + self._random.uniform(low, high)
        if self._sdo_answers:
            due = max(due, self._sdo_answers[-1][0])
        self._sdo_answers.append((due, bytes(response)))
        self._wake.set()

    def _ignore(self, can_id: int, data: bytes, timestamp: float) -> None:
        """Data frames on a subscription held only for the bus filter."""

    def _on_frame(self, message: can.Message) -> None:
        """Frames canopen does not dispatch: the node guarding request (a remote frame)."""
        if not message.is_remote_frame:
            return
        if message.arbitration_id != objects.HEARTBEAT_COB_ID_BASE + self.node_id:
            return
        try:
            with self._lock:
                # A node guards only while its heartbeat producer is off (CiA 301).
                if (
                    not self._answering
                    or not self._powered
                    or self._nmt is NmtState.INITIALISING
                    or self._params[(objects.PRODUCER_HEARTBEAT, 0)]
                ):
                    return
                self._send(message.arbitration_id, bytes([self._guard_toggle | self._nmt]))
                self._guard_toggle ^= 0x80
                self._guarded_at = self._clock()
                if self._life_lost:
                    self._life_lost = False
                    self._update_statusword()
                self._wake.set()
        except Exception:
            logger.exception("node %d: node guarding request", self.node_id)

    def _subscribe(self, registry: list, can_id: int, callback: Callable) -> None:
        self.network.subscribe(can_id, callback)
        registry.append((can_id, callback))
        self._filter_bus()

    def _unsubscribe_all(self, registry: list) -> None:
        for can_id, callback in registry:
            if callback in self.network.subscribers.get(can_id, ()):
                self.network.unsubscribe(can_id, callback)
        registry.clear()
        self._filter_bus()

    def _filter_bus(self) -> None:
        """Let the bus deliver only the identifiers subscribed on this Network.

        Every frame received costs the notifier thread a read and a dispatch, and most of the
        bus (the other drives' RPDOs and TPDOs) concerns no drive here. On SocketCAN the kernel
        drops them; other interfaces filter in python-can, still before canopen's dispatch.
        """
        bus = self.network.bus
        if bus is not None:
            # list() of a dict's keys runs in C under the GIL: another drive of the set may
            # subscribe meanwhile from its own thread.
            subscribed = list(self.network.subscribers)
            bus.set_filters(
                [
                    {"can_id": can_id, "can_mask": objects.COB_ID_MASK, "extended": False}
                    for can_id in subscribed
                ]
            )

    # ---------------------------------------------------------------- heartbeat consumer

    def _configure_consumers(self) -> None:
        self._unsubscribe_all(self._consumer_subscriptions)
        self._consumers.clear()
        self._consumer_seen.clear()
        self._consumer_lost.clear()
        if objects.CONSUMER_HEARTBEAT not in self._served:
            return
        for sub in range(1, objects.CONSUMER_HEARTBEAT_ENTRIES + 1):
            entry = self._read(objects.CONSUMER_HEARTBEAT, sub)
            node, time_ms = (entry >> 16) & 0x7F, entry & 0xFFFF
            if node and time_ms:
                self._consumers[node] = time_ms / 1000.0
                if self._powered:
                    self._subscribe(
                        self._consumer_subscriptions,
                        objects.HEARTBEAT_COB_ID_BASE + node,
                        self._on_consumed_heartbeat,
                    )

    def _on_consumed_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        try:
            with self._lock:
                if not self._answering:
                    return
                node = can_id - objects.HEARTBEAT_COB_ID_BASE
                self._consumer_seen[node] = self._clock()
                self._consumer_lost.discard(node)
        except Exception:
            logger.exception("node %d: heartbeat of node %d", self.node_id, can_id & 0x7F)

    # ---------------------------------------------------------------- watchdog thread

    def _watchdog_loop(self) -> None:
        while not self._stopping.is_set():
            try:
                with self._lock:
                    deadline = self._supervise(self._clock())
            except Exception:
                logger.exception("node %d: watchdog", self.node_id)
                deadline = self._clock() + self.WATCHDOG_MAX_WAIT_S
            wait_s = min(max(deadline - self._clock(), 0.0), self.WATCHDOG_MAX_WAIT_S)
            self._wake.wait(wait_s)
            self._wake.clear()

    def _supervise_life_guarding(self, now: float) -> float:
        """Life guarding (CiA 301): once guarded, a node not guarded for 0x100C × 0x100D
        raises EMCY 0x8130 and applies 0x6007. Returns when it is next due."""
        guard_ms = self._params[(objects.GUARD_TIME, 0)]
        factor = self._params[(objects.LIFE_TIME_FACTOR, 0)]
        if not guard_ms or not factor or self._guarded_at is None or self._life_lost:
            return math.inf
        limit = self._guarded_at + guard_ms * factor / 1000.0
        if now <= limit:
            return limit
        self._life_lost = True
        logger.warning(
            "node %d: life guarding: not guarded for %.3f s", self.node_id, now - self._guarded_at
        )
        if not self._abort_connection(emcy.EMCY_HEARTBEAT, "life guarding"):
            self._send_emcy(emcy.EMCY_HEARTBEAT, self._image[objects.ERROR_REGISTER])
        self._update_statusword()
        return math.inf

    def _supervise(self, now: float) -> float:
        """Run the time-driven duties due at ``now``; return the next time one is due."""
        deadline = now + self.WATCHDOG_MAX_WAIT_S
        if not self._powered:
            return deadline
        if self._boot_at is not None:
            if now < self._boot_at:
                return min(deadline, self._boot_at)
            self._finish_boot()

        while self._sdo_answers and self._sdo_answers[0][0] <= now:
            self._send(self._local.sdo.tx_cobid, self._sdo_answers.popleft()[1])
        if self._sdo_answers:
            deadline = min(deadline, self._sdo_answers[0][0])

        deadline = min(deadline, self._supervise_life_guarding(now))

        heartbeat_ms = self._params[(objects.PRODUCER_HEARTBEAT, 0)]
        if heartbeat_ms > 0 and self._answering:
            if self._next_heartbeat is None or now >= self._next_heartbeat:
                self._send(objects.HEARTBEAT_COB_ID_BASE + self.node_id, bytes([self._nmt]))
                previous = now if self._next_heartbeat is None else self._next_heartbeat
                self._next_heartbeat = previous + heartbeat_ms / 1000.0
                if self._next_heartbeat <= now:  # woke late: skip the missed beats, no burst
                    self._next_heartbeat = now + heartbeat_ms / 1000.0
            deadline = min(deadline, self._next_heartbeat)

        period_s = self._period_s()
        if (
            self._state is State.OPERATION_ENABLED
            and self._last_sync is not None
            and self._params[(objects.COMM_CYCLE_PERIOD, 0)] > 0
        ):
            limit = self._last_sync + self.model.sync_timeout_factor * period_s
            if now <= limit:
                self._sync_grace_until = None
                deadline = min(deadline, limit)
            elif self._sync_grace_until is None and now - limit > period_s:
                # The watchdog is woken whenever SYNC supervision (re)starts, so it always waits
                # for ``limit`` at the latest: this late, the whole process stalled.
                self._sync_grace_until = now + period_s
                deadline = min(deadline, self._sync_grace_until)
            elif self._sync_grace_until is not None and now < self._sync_grace_until:
                deadline = min(deadline, self._sync_grace_until)
            else:
                self._sync_grace_until = None
                self._fault(emcy.EMCY_COMMUNICATION)

        if self._state in _MOTION_STATES:
            silent_periods = max(self.FREE_RUN_AFTER_PERIODS, self.model.sync_timeout_factor)
            free_run_at = self._last_step + silent_periods * period_s
            if now >= free_run_at:
                self._step(min(now - self._last_step, 10 * period_s), now)
                free_run_at = now + period_s
            deadline = min(deadline, free_run_at)

        for node, timeout_s in self._consumers.items():
            seen = self._consumer_seen.get(node)
            if seen is None or node in self._consumer_lost:
                continue  # monitoring starts with the first heartbeat (CiA 301)
            if now > seen + timeout_s:
                self._consumer_lost.add(node)
                logger.warning("node %d: heartbeat of node %d lost", self.node_id, node)
                if not self._abort_connection(emcy.EMCY_HEARTBEAT, f"heartbeat of node {node}"):
                    self._send_emcy(emcy.EMCY_HEARTBEAT, self._image[objects.ERROR_REGISTER])
                self._update_statusword()
            else:
                deadline = min(deadline, seen + timeout_s)
        return deadline


class SimulatedDriveSet:
    """Simulated drives sharing one Network (one bus) of their own; close it to power them off.

    :param network: the drives' connected Network, owned by the set.
    :param drives: the drives by node-ID.
    """

    def __init__(self, network: canopen.Network, drives: Mapping[int, SimulatedDrive]) -> None:
        self.network = network
        self.drives: Mapping[int, SimulatedDrive] = MappingProxyType(dict(drives))

    def close(self) -> None:
        """Power off every drive and disconnect the Network; safe to call twice."""
        for drive in self.drives.values():
            drive.stop()
        if self.network.bus is not None:
            self.network.disconnect()

    def __enter__(self) -> SimulatedDriveSet:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


#: Notifier receive timeout of a drive set's Network, s (bounds how long closing waits).
SIM_NOTIFIER_CYCLE_S: Final[float] = 0.05
#: Time closing a drive set waits for its notifier thread, s.
SIM_NOTIFIER_SHUTDOWN_TIMEOUT_S: Final[float] = 0.5


def start_simulated_drives(
    interface: str,
    channel: str,
    node_ids: Sequence[int],
    *,
    model: DriveModel = DEFAULT_MODEL,
    bitrate: int | None = None,
    quirks: Mapping[int, DriveQuirks] | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> SimulatedDriveSet:
    """Open a bus of their own, create one simulated drive per node-ID and power them on
    (``model`` and ``clock`` as for :class:`SimulatedDrive`; ``quirks`` by node-ID, the
    others behave as the full drive).

    :raises ValueError: if a node-ID is outside 1..127 or repeated.
    :raises drives.errors.BusUnavailable: if the bus cannot be opened.
    """
    if len(set(node_ids)) != len(node_ids):
        raise ValueError(f"simulated drives: node_ids {list(node_ids)} repeat a node-ID")
    # On a virtual or local channel the drives' frames keep the stamps they are sent with (when
    # they are on the wire); SocketCAN and other buses stamp them on reception anyway.
    options = {"preserve_timestamps": True} if interface in ("virtual", "local") else {}
    network = canopen.Network(open_bus(interface, channel, bitrate, **options))
    network.NOTIFIER_CYCLE = SIM_NOTIFIER_CYCLE_S
    network.NOTIFIER_SHUTDOWN_TIMEOUT = SIM_NOTIFIER_SHUTDOWN_TIMEOUT_S
    network.connect()
    drive_set = SimulatedDriveSet(network, {})
    try:
        drives = {
            node_id: SimulatedDrive(
                network,
                node_id,
                model=model,
                quirks=(quirks or {}).get(node_id, NO_QUIRKS),
                clock=clock,
            )
            for node_id in node_ids
        }
        drive_set = SimulatedDriveSet(network, drives)
        for drive in drives.values():
            drive.start()
    except BaseException:
        drive_set.close()
        raise
    return drive_set
