"""CiA 402 master for CSP axes, run by the cycle: one non-blocking call per step of the period.

Source: CiA 301 (NMT, SYNC, PDO, SDO, heartbeat, node guarding, EMCY) and CiA 402 device control
in cyclic synchronous position mode (0x6060 = 8): per axis one RPDO carries controlword 0x6040
and target position 0x607A, one or more TPDOs (transmission type 1) carry statusword 0x6041 and
position actual 0x6064, and optionally following error actual 0x60F4 and error code 0x603F.

The cycle, once per period, in this order (the cycle process's single thread):

1. :meth:`Cia402Master.transmit_period`: the RPDOs prepared last period (axes whose drive is
   started), then one SYNC;
2. :meth:`~Cia402Master.receive`: drain the bus without waiting and dispatch every frame (TPDOs,
   heartbeats and boot-ups, node-guarding answers, EMCY, SDO answers, the echo of our SYNC);
3. :meth:`~Cia402Master.update`: supervision, one step of each drive's boot or shutdown and of
   the heartbeat producer and node guarding; returns one :class:`AxisFeedback` per axis;
4. ``request_*`` as the machine decides;
5. :meth:`~Cia402Master.write_targets`: prepare the next RPDOs (controlword from the state seen
   this period; axes not in OPERATION ENABLED get their actual position).

Boot (:meth:`~Cia402Master.start`), reconfiguration of a drive that rebooted or came back, and
shutdown (:meth:`~Cia402Master.begin_shutdown` then ``update`` until
:attr:`~Cia402Master.shutdown_done`) all run through these calls (see :mod:`drives.boot`).
Nothing raises out of them for a drive problem: boot failures, lost drives and drive faults are
in the feedback and in the fault events (:meth:`~Cia402Master.take_fault_events`).

Feedback is matched to the SYNC it answered by its frame (:mod:`drives.sync`), and each axis's
following error compares the position it reports with the target sent ``feedback_lag_periods``
SYNCs before that one (0x60F4 instead when the drive maps it).

Units: positions in mm at the API, counts (INTEGER32) on the bus; times in s on the caller's
clock (``now_s``, monotonic); heartbeat and guard times in ms.

Threading: one thread calls everything; nothing blocks or sleeps; each call is O(axes) plus the
frames received; logging only on events (a fault, a boot step, an object skipped).
Invariants: an axis not in OPERATION ENABLED is sent its actual position, so enabling never
jumps; the 402 state machine moves one transition per period; targets are converted from
absolute millimetres every period (no drift).
Not done: modes other than CSP, several axes per node, bus-off recovery.
"""

from __future__ import annotations

import functools
import logging
import math
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import can
import canopen

from drives.boot import (
    BootPhase,
    NodeBoot,
    NodeSetup,
    Supervision,
    heartbeat_consumer_entry,
    period_us,
)
from drives.cia402 import (
    QUICK_STOP_OPTIONS_STAY_ACTIVE,
    Command,
    State,
    controlword_toward_disabled,
    controlword_toward_enabled,
    fault_reset_controlword,
    state_of_statusword,
)
from drives.emcy import EMCY_ERROR_RESET, EMCY_STRUCT, EMCY_SYNC_LENGTH, describe_emcy
from drives.errors import DriveError
from drives.guarding import NodeGuard, heartbeat_producer
from drives.monitor import (
    EVENT_QUEUE_LENGTH,
    AxisFault,
    FaultKind,
    FaultTracker,
    emcy_text,
    nmt_name,
)
from drives.objects import (
    EMCY_COB_ID_BASE,
    HEARTBEAT_COB_ID_BASE,
    NMT_COB_ID,
    SDO_TX_COB_ID_BASE,
    SYNC_COB_ID,
    NmtCommand,
    NmtState,
)
from drives.pdo import AxisPdoSpec, RpdoCodec, TpdoCodec
from drives.scaling import AxisScaling
from drives.sdo_client import SdoClient
from drives.sync import SyncProducer

__all__ = [
    "AxisFault",
    "AxisFeedback",
    "AxisSpec",
    "BootPhase",
    "Cia402Master",
    "FaultKind",
    "MasterSettings",
    "Supervision",
    "TravelLimitError",
]

logger = logging.getLogger(__name__)

#: Frames drained per :meth:`Cia402Master.receive` at most (the rest wait for the next period).
MAX_FRAMES_PER_PERIOD = 256

_FAULT_STATES = (State.FAULT, State.FAULT_REACTION_ACTIVE)
_SETTLED_STATES = (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, *_FAULT_STATES)
_STARTED_PHASES = (BootPhase.STARTING, BootPhase.READY)


class AxisRequest(Enum):
    """What the caller asked an axis to do; the master steps the drive toward it."""

    DISABLE = "disable"
    ENABLE = "enable"
    QUICK_STOP = "quick stop"


class TravelLimitError(DriveError, ValueError):
    """A target outside the axis travel range; no target of that period was prepared."""

    def __init__(self, axis: str, node_id: int, position_mm: float, scaling: AxisScaling) -> None:
        self.axis = axis
        self.position_mm = position_mm
        super().__init__(
            node_id,
            f"axis {axis}: target {position_mm!r} mm outside travel "
            f"[{scaling.travel_min_mm:g}, {scaling.travel_max_mm:g}] mm",
        )


@dataclass(frozen=True)
class AxisSpec:
    """One axis: its drive, how its millimetres map to counts, its PDOs and supervision."""

    name: str
    node_id: int
    scaling: AxisScaling
    following_error_window_mm: float
    following_error_timeout_ms: int
    eds: Path | None = None
    """The drive's EDS; it decides beforehand which objects exist and their ranges."""
    pdo: AxisPdoSpec = field(default_factory=AxisPdoSpec)
    supervision: Supervision = Supervision.HEARTBEAT
    """HEARTBEAT falls back to node guarding on a drive without 0x1017."""
    guard_time_ms: int = 100
    """0x100C, when the drive is guarded."""
    life_time_factor: int = 3
    """0x100D: the drive is lost after guard time × factor without an answer."""
    feedback_lag_periods: int = 1
    """SYNCs between the target and the TPDO that reports the position reached for it: 1 for a
    drive that takes the target at SYNC n and reports at SYNC n + 1 (after its step); 2 when it
    samples its position before applying the new target; more for one that sends late."""

    def __post_init__(self) -> None:
        if not 1 <= self.node_id <= 127:
            raise ValueError(f"axis {self.name}: node_id = {self.node_id}, must be in 1..127")
        if not (
            math.isfinite(self.following_error_window_mm) and self.following_error_window_mm > 0
        ):
            raise ValueError(
                f"axis {self.name}: following_error_window_mm = "
                f"{self.following_error_window_mm!r}, must be finite and > 0"
            )
        for name, value, low in (
            ("following_error_timeout_ms", self.following_error_timeout_ms, 0),
            ("guard_time_ms", self.guard_time_ms, 1),
            ("life_time_factor", self.life_time_factor, 1),
            ("feedback_lag_periods", self.feedback_lag_periods, 0),
        ):
            if value < low:
                raise ValueError(f"axis {self.name}: {name} = {value}, must be >= {low}")


@dataclass(frozen=True)
class MasterSettings:
    """Bus-wide timing, SDO and the drive options written at boot."""

    period_s: float
    heartbeat_ms: int = 100
    """Producer heartbeat time configured on every drive (0x1017)."""
    master_node_id: int = 127
    master_heartbeat_ms: int = 100
    """Our heartbeat, consumed by the drives (0x1016); 0 = neither sent nor consumed."""
    heartbeat_loss_periods: float = 2.5
    """Heartbeat loss after this many heartbeat periods without one (also the drives' 0x1016)."""
    boot_timeout_s: float = 5.0
    sdo_timeout_s: float = 1.0
    """Time allowed for each SDO answer: slow drives take hundreds of ms."""
    sdo_retries: int = 2
    """A transfer that timed out is tried this many times more."""
    stale_feedback_cycles: int = 3
    """An axis enabled or asked to enable is faulted once this many SYNCs in a row went
    unanswered (the newest TPDO answers the SYNC ``stale_feedback_cycles + 1`` back)."""
    quick_stop_option: int = 2
    """0x605A: 2 = quick stop ramp, then SWITCH ON DISABLED."""
    fault_reaction_option: int = 2
    """0x605E: 2 = quick stop ramp."""
    abort_connection_option: int = 1
    """0x6007: 1 = fault on heartbeat loss, SYNC loss or leaving OPERATIONAL."""
    sync_window_us: int = 0
    """0x1007; 0 = not written."""
    sync_counter_overflow: int = 0
    """0 = SYNC without data, matched by timestamp; 2..240 = counted SYNC (0x1019 on every
    drive), matched by the order of our SYNC's echo when the bus delivers own frames."""
    reset_communication: bool = True
    """Send NMT reset communication at start, so drives that booted earlier boot again."""
    shutdown_timeout_s: float = 3.0
    """The whole shutdown, disabling and disarming included."""

    def __post_init__(self) -> None:
        period_us(self.period_s)  # raises ValueError naming the period
        if self.heartbeat_ms <= 0:
            raise ValueError(f"heartbeat_ms = {self.heartbeat_ms}, must be > 0")
        if not 1 <= self.master_node_id <= 127:
            raise ValueError(f"master_node_id = {self.master_node_id}, must be in 1..127")
        if not 1.0 < self.heartbeat_loss_periods < 3.0:
            raise ValueError(
                f"heartbeat_loss_periods = {self.heartbeat_loss_periods}, must be in (1, 3)"
            )
        if self.stale_feedback_cycles < 1:
            raise ValueError(f"stale_feedback_cycles = {self.stale_feedback_cycles}, must be >= 1")
        if self.sdo_retries < 0:
            raise ValueError(f"sdo_retries = {self.sdo_retries}, must be >= 0")
        for name in ("boot_timeout_s", "sdo_timeout_s", "shutdown_timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} = {getattr(self, name)!r}, must be > 0")


@dataclass(frozen=True, slots=True)
class AxisFeedback:
    """One axis as :meth:`Cia402Master.update` saw it this period."""

    axis: str
    node_id: int
    phase: BootPhase
    state: State | None
    """Decoded statusword once the drive is started; None before, or if it matched no CiA 402
    state (then ``fault`` says so)."""
    statusword: int
    position_counts: int
    position_mm: float
    commanded_mm: float
    """The target sent with the last SYNC (the actual position while not enabled)."""
    target_mm: float
    """The target the reported position should have reached: the one sent
    ``feedback_lag_periods`` SYNCs before the SYNC the feedback answered; NaN if unknown."""
    following_error_mm: float
    """Actual position minus ``target_mm`` (from 0x60F4 when mapped: minus 0x60F4, the drive's
    demand minus actual); NaN if unknown."""
    feedback_age_cycles: int
    """SYNCs sent since the SYNC the feedback answered (1 = answer to the previous SYNC, what
    the cycle normally reads right after sending the next)."""
    heartbeat_age_s: float
    """Seconds since the drive's last heartbeat (or node-guarding answer); inf before one."""
    error_code: int
    """0x603F when mapped, else the code of the last EMCY (0 after an error reset)."""
    skipped_objects: tuple[int, ...]
    """Optional objects the drive does not have (or refused), by index."""
    fault: AxisFault | None
    """The latched fault: the most severe since the last fault reset."""
    fault_reset_pending: bool
    """A fault reset is under way (the bit 7 edge until the drive leaves FAULT); once False,
    ``fault`` tells the outcome: None if the reset cleared it."""

    @property
    def enabled(self) -> bool:
        return self.state is State.OPERATION_ENABLED

    @property
    def ready(self) -> bool:
        return self.phase is BootPhase.READY


class _ShutdownStep(Enum):
    RUNNING = 0
    DISABLING = 1
    DISARMING = 2
    DONE = 3


class _Axis:
    """Everything the master keeps about one axis (cycle thread only)."""

    def __init__(
        self, spec: AxisSpec, boot: NodeBoot, sdo: SdoClient, tracker: FaultTracker, history: int
    ) -> None:
        self.spec = spec
        self.scaling = spec.scaling
        self.node_id = spec.node_id
        self.boot = boot
        self.sdo = sdo
        self.guard: NodeGuard | None = None
        self.tracker = tracker
        self.phase = BootPhase.WAITING
        self.sending = False
        self.rpdo_codec: RpdoCodec | None = None
        self.rpdo_message: can.Message | None = None
        self.tpdo_ids: tuple[int, ...] = ()
        self.tpdo_has_error_code = False
        self.request = AxisRequest.DISABLE
        self.reset_pending = False
        self.reset_cycle = 0
        self.state: State | None = None
        # Received (written by the frame handlers).
        self.statusword = 0
        self.position_counts = 0
        self.answered_sync = 0
        self.fresh = False
        self.drive_following_error: int | None = None
        self.error_code = 0
        self.heartbeat_s: float | None = None
        self.nmt_state: int | None = None
        self.emcys: list[tuple[int, int]] = []
        self.toggle_errors = 0
        self.problem_serial = 0
        # Targets: prepared for the next SYNC, and sent, by SYNC number.
        self.prepared_counts = 0
        self.sent_counts = [0] * history
        self.beyond_window = 0
        self.following_error_periods = 1


class Cia402Master:
    """CiA 402 master for a set of CSP axes on one CAN bus.

    :param bus: a python-can bus (``drives.bus.open_bus``) owned by the caller's thread; the
        master reads it with ``recv(timeout=0)`` and nothing else may read it.
    :param axes: the axes, in the order of every per-axis sequence of this API.
    :param settings: bus timing, SDO and drive options.
    :raises ValueError: on duplicate axis names or node-IDs, a node-ID equal to the master's,
        or an EDS that cannot be read.
    """

    def __init__(self, bus: can.BusABC, axes: Sequence[AxisSpec], settings: MasterSettings) -> None:
        _check_axes(axes, settings)
        self.bus = bus
        self.settings = settings
        self._period_us = period_us(settings.period_s)
        self._history = (
            settings.stale_feedback_cycles + max(spec.feedback_lag_periods for spec in axes) + 2
        )
        self._sync = SyncProducer(
            self._send,
            history=self._history,
            counter_overflow=settings.sync_counter_overflow,
        )
        self._heartbeat = heartbeat_producer(
            settings.master_node_id, self._send, settings.master_heartbeat_ms / 1000.0
        )
        self._events: deque[AxisFault] = deque(maxlen=EVENT_QUEUE_LENGTH)
        self._heartbeat_loss_s = settings.heartbeat_loss_periods * settings.heartbeat_ms / 1000.0
        self._dispatch: dict[int, Callable[[can.Message, float], None]] = {
            SYNC_COB_ID: self._on_sync_echo
        }
        self._axes = tuple(self._add_axis(spec) for spec in axes)
        self._by_name = {axis.spec.name: axis for axis in self._axes}
        self._sending: list[_Axis] = []
        self._period_frames: list[can.Message] = []
        self._started = False
        self._shutdown = _ShutdownStep.RUNNING
        self._shutdown_deadline_s: float | None = None
        self._disable_deadline_s = 0.0
        self._send_errors = 0
        self.feedback: tuple[AxisFeedback, ...] = ()
        """What the last :meth:`update` returned."""

    def _add_axis(self, spec: AxisSpec) -> _Axis:
        settings = self.settings
        try:
            od = canopen.import_od(str(spec.eds), spec.node_id) if spec.eds else None
        except Exception as exc:
            raise ValueError(f"axis {spec.name}: EDS {spec.eds}: {exc}") from exc
        node_id = spec.node_id
        sdo = SdoClient(
            node_id,
            self._send_data,
            timeout_s=settings.sdo_timeout_s,
            retries=settings.sdo_retries,
        )
        setup = NodeSetup(
            node_id=node_id,
            period_us=self._period_us,
            boot_timeout_s=settings.boot_timeout_s,
            supervision=spec.supervision,
            heartbeat_ms=settings.heartbeat_ms,
            master_heartbeat_consumer=heartbeat_consumer_entry(
                settings.master_node_id,
                round(settings.master_heartbeat_ms * settings.heartbeat_loss_periods),
            ),
            guard_time_ms=spec.guard_time_ms,
            life_time_factor=spec.life_time_factor,
            sync_counter_overflow=settings.sync_counter_overflow,
            sync_window_us=settings.sync_window_us,
            following_error_window_counts=round(
                spec.following_error_window_mm * spec.scaling.counts_per_mm
            ),
            following_error_timeout_ms=spec.following_error_timeout_ms,
            quick_stop_option=settings.quick_stop_option,
            fault_reaction_option=settings.fault_reaction_option,
            abort_connection_option=settings.abort_connection_option,
            pdo=spec.pdo,
            od=od,
            eds_name=str(spec.eds or ""),
        )
        boot = NodeBoot(setup, sdo, functools.partial(self._send_nmt, node_id))
        tracker = FaultTracker(spec.name, node_id, self._events)
        axis = _Axis(spec, boot, sdo, tracker, self._history)
        axis.following_error_periods = math.ceil(
            spec.following_error_timeout_ms * 1000 / self._period_us
        )
        self._dispatch[SDO_TX_COB_ID_BASE + node_id] = functools.partial(self._on_sdo, axis)
        self._dispatch[HEARTBEAT_COB_ID_BASE + node_id] = functools.partial(
            self._on_error_control, axis
        )
        self._dispatch[EMCY_COB_ID_BASE + node_id] = functools.partial(self._on_emcy, axis)
        return axis

    # -- boot and shutdown ------------------------------------------------------------------------

    def start(self) -> None:
        """Begin the boot of every drive (NMT reset communication when configured) and our
        heartbeat; :meth:`update` carries it on. Calling it again does nothing."""
        if self._started:
            return
        self._started = True
        self._heartbeat.start()
        for axis in self._axes:
            axis.boot.begin(reset_communication=self.settings.reset_communication)

    def begin_shutdown(self) -> None:
        """Begin the clean shutdown: disable every axis through the controlword, then on every
        drive set back to 0 what would supervise us after we leave (0x1016 consumer, life
        guarding, 0x1006), NMT PRE-OPERATIONAL, stop our heartbeat. :meth:`update` carries it
        on (bounded by ``shutdown_timeout_s``) until :attr:`shutdown_done`."""
        if self._shutdown is not _ShutdownStep.RUNNING:
            return
        self._shutdown = _ShutdownStep.DISABLING
        self._shutdown_deadline_s = None
        self.request_disable()

    @property
    def shutdown_done(self) -> bool:
        """True once the shutdown has finished (or was never needed: never started)."""
        return self._shutdown is _ShutdownStep.DONE or (
            not self._started and self._shutdown is not _ShutdownStep.RUNNING
        )

    # -- the period ---------------------------------------------------------------------------

    def transmit_period(self) -> None:
        """Send the prepared RPDO of every started drive, then the SYNC.

        A bus that takes several frames in one call (``send_frames``, the ``local`` bus) gets
        them so: the SYNC then leaves as soon after the wake-up as a single frame would.
        """
        slot = (self._sync.sent + 1) % self._history
        for axis in self._sending:
            axis.sent_counts[slot] = axis.prepared_counts
        send_frames = getattr(self.bus, "send_frames", None)
        if send_frames is None:
            for axis in self._sending:
                self._send(axis.rpdo_message)
            self._sync.transmit()  # dated just before it goes out, after the RPDOs
            return
        frames = self._period_frames
        frames.clear()
        frames.extend(axis.rpdo_message for axis in self._sending)
        frames.append(self._sync.next_message())
        try:
            send_frames(frames)
        except can.CanError as exc:
            self._send_failed("the period's frames", exc)

    def receive(self, now_s: float) -> int:
        """Drain the bus without waiting and dispatch every frame; return how many.

        Frames nobody handles are dropped here, not by bus filters: python-can filters in
        software on most interfaces, and there ``recv(timeout=0)`` returns None at the first
        frame it filters out, which would end the drain with frames still queued.
        """
        recv = self.bus.recv
        dispatch = self._dispatch
        count = 0
        while count < MAX_FRAMES_PER_PERIOD:
            message = recv(0.0)
            if message is None:
                break
            count += 1
            if message.is_error_frame or message.is_extended_id:
                continue
            handler = dispatch.get(message.arbitration_id)
            if handler is not None:
                handler(message, now_s)
        return count

    def update(self, now_s: float) -> tuple[AxisFeedback, ...]:
        """Supervise, step the boots or the shutdown, and return one record per axis."""
        if self._shutdown is not _ShutdownStep.RUNNING:
            self._step_shutdown(now_s)
        self._heartbeat.poll(now_s)
        feedback = tuple(self._update_axis(axis, now_s) for axis in self._axes)
        self.feedback = feedback
        return feedback

    def write_targets(self, positions_mm: Sequence[float | None] | None) -> None:
        """Prepare the next period's RPDOs: controlword toward each axis's request, and the
        target in mm (None, for all or one axis: keep the last).

        Targets apply to axes in OPERATION ENABLED (as of the last :meth:`update`); the others
        get their actual position. All targets are checked before any is prepared.

        :raises ValueError: if the sequence length differs from the number of axes.
        :raises TravelLimitError: a target outside its axis's travel range.
        :raises ScalingError: a target with no INTEGER32 count value.
        """
        axes = self._axes
        if positions_mm is not None:
            if len(positions_mm) != len(axes):
                raise ValueError(
                    f"write_targets: {len(positions_mm)} positions for {len(axes)} axes"
                )
            counts: list[int | None] = []
            for axis, position_mm in zip(axes, positions_mm, strict=True):
                if position_mm is None or axis.state is not State.OPERATION_ENABLED:
                    counts.append(None)
                    continue
                scaling = axis.scaling
                if not scaling.within_travel(position_mm):
                    raise TravelLimitError(axis.spec.name, axis.node_id, position_mm, scaling)
                counts.append(scaling.to_counts(position_mm))
        else:
            counts = [None] * len(axes)
        for axis, target in zip(axes, counts, strict=True):
            if not axis.sending:
                continue
            if axis.state is not State.OPERATION_ENABLED:
                axis.prepared_counts = axis.position_counts
            elif target is not None:
                axis.prepared_counts = target
            axis.rpdo_codec.pack(self._controlword(axis), axis.prepared_counts)

    def take_fault_events(self) -> tuple[AxisFault, ...]:
        """Every fault event since the last call, oldest first (each EMCY, and each fault
        condition when it appears, on any axis, also while faults are already latched)."""
        events = tuple(self._events)
        self._events.clear()
        return events

    # -- requests -----------------------------------------------------------------------------

    def request_enable(self, axes: Iterable[str] | None = None) -> None:
        """Step the axes toward OPERATION ENABLED, one transition per period, from their
        actual position. An axis in FAULT stays there until a fault reset."""
        for axis in self._select(axes):
            axis.request = AxisRequest.ENABLE

    def request_disable(self, axes: Iterable[str] | None = None) -> None:
        """Step the axes down to SWITCH ON DISABLED (disable operation, shutdown, voltage off)."""
        for axis in self._select(axes):
            axis.request = AxisRequest.DISABLE

    def request_quick_stop(self, axes: Iterable[str] | None = None) -> None:
        """Quick stop (controlword 0x02): the drive brakes per 0x605A; then the axis is
        disabled."""
        for axis in self._select(axes):
            axis.request = AxisRequest.QUICK_STOP

    def request_fault_reset(self, axes: Iterable[str] | None = None) -> None:
        """Clear the axes' latched faults. A started drive in FAULT gets the bit 7 edge
        (0x00, 0x80, ...) until it leaves FAULT, then its fault is cleared; a drive being
        configured (one that came back and booted again) is reset once it is ready; a drive
        whose boot FAILED is booted again (its fault stays until it is ready and reset again);
        a drive still being looked for keeps its fault. The enable request is kept: to
        re-enable after a fault, also call :meth:`request_enable`."""
        for axis in self._select(axes):
            axis.boot.retry()
            axis.reset_pending = True
            axis.reset_cycle = 0

    def _select(self, axes: Iterable[str] | None) -> Iterable[_Axis]:
        if axes is None:
            return self._axes
        if isinstance(axes, str):
            axes = (axes,)
        try:
            return [self._by_name[name] for name in axes]
        except KeyError as exc:
            known = ", ".join(self._by_name)
            raise ValueError(f"no axis named {exc.args[0]!r} (axes: {known})") from None

    # -- state --------------------------------------------------------------------------------

    @property
    def axis_names(self) -> tuple[str, ...]:
        return tuple(axis.spec.name for axis in self._axes)

    @property
    def syncs_sent(self) -> int:
        return self._sync.sent

    @property
    def all_ready(self) -> bool:
        return all(axis.phase is BootPhase.READY for axis in self._axes)

    @property
    def enabled_mask(self) -> tuple[bool, ...]:
        """Per axis, whether it was in OPERATION ENABLED at the last :meth:`update`."""
        return tuple(axis.state is State.OPERATION_ENABLED for axis in self._axes)

    @property
    def all_enabled(self) -> bool:
        return all(self.enabled_mask)

    @property
    def feedback_complete(self) -> bool:
        """Whether every started drive has answered the last SYNC (for test loops that run
        faster than real time)."""
        sent = self._sync.sent
        return all(axis.answered_sync >= sent for axis in self._sending)

    @property
    def sdo_in_flight(self) -> bool:
        """Whether some drive's SDO transfer waits for its answer."""
        return any(axis.sdo.busy for axis in self._axes)

    @property
    def send_errors(self) -> int:
        """Frames the bus refused to send (a full transmit queue, a bus without drives)."""
        return self._send_errors

    # -- frames -------------------------------------------------------------------------------

    def _send(self, message: can.Message) -> None:
        try:
            self.bus.send(message)
        except can.CanError as exc:
            self._send_failed(f"0x{message.arbitration_id:03X}", exc)

    def _send_failed(self, what: str, exc: can.CanError) -> None:
        # Counted always, logged once: a bus that fails every period must not flood the log.
        self._send_errors += 1
        if self._send_errors == 1:
            logger.warning("CAN send of %s failed: %s", what, exc)

    def _send_data(self, can_id: int, data: bytes) -> None:
        self._send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def _send_nmt(self, node_id: int, command: NmtCommand) -> None:
        self._send_data(NMT_COB_ID, bytes([command, node_id]))

    def _on_sync_echo(self, message: can.Message, now_s: float) -> None:
        if not message.is_rx:
            self._sync.on_echo(message)

    def _on_sdo(self, axis: _Axis, message: can.Message, now_s: float) -> None:
        axis.sdo.on_response(message.data, now_s)

    def _on_emcy(self, axis: _Axis, message: can.Message, now_s: float) -> None:
        if len(message.data) != EMCY_STRUCT.size:
            return
        code, register, _ = EMCY_STRUCT.unpack(message.data)
        if not axis.tpdo_has_error_code:
            axis.error_code = code
        if code != EMCY_ERROR_RESET:
            axis.emcys.append((code, register))

    def _on_error_control(self, axis: _Axis, message: can.Message, now_s: float) -> None:
        """Heartbeat, boot-up or node-guarding answer on 0x700 + node-ID."""
        if message.is_remote_frame or not message.data:
            return
        value = message.data[0]
        boot = axis.boot
        if value == NmtState.INITIALISING:
            axis.nmt_state = NmtState.INITIALISING
            if self._shutdown is not _ShutdownStep.RUNNING:
                return
            if boot.phase is BootPhase.WAITING:
                boot.alive = True
            else:
                if boot.phase is BootPhase.READY:
                    axis.tracker.report(
                        FaultKind.NMT, "drive rebooted (boot-up while running)", now_s
                    )
                logger.warning("node %d: boot-up: configuring again", axis.node_id)
                boot.rebooted()
            return
        guard = axis.guard
        if guard is not None and guard.running:
            if not guard.on_answer(value, now_s):
                axis.toggle_errors += 1
            state = guard.nmt_state
        else:
            axis.heartbeat_s = now_s
            state = value
        axis.nmt_state = state
        boot.nmt_state = state
        boot.alive = True

    def _on_tpdo(self, axis: _Axis, codec: TpdoCodec, message: can.Message, now_s: float) -> None:
        data = message.data
        if len(data) != codec.size:
            return
        values = codec.unpack(data)
        if codec.statusword_at is not None:
            axis.statusword = values[codec.statusword_at]
        if codec.position_at is not None:
            axis.position_counts = values[codec.position_at]
            axis.answered_sync = self._sync.answered(message.timestamp)
            axis.fresh = True
        if codec.following_error_at is not None:
            axis.drive_following_error = values[codec.following_error_at]
        if codec.error_code_at is not None:
            axis.error_code = values[codec.error_code_at]
        axis.boot.tpdo_seen = True

    # -- per axis, per period ------------------------------------------------------------------

    def _update_axis(self, axis: _Axis, now_s: float) -> AxisFeedback:
        boot = axis.boot
        axis.sdo.poll(now_s)
        boot.step(now_s)
        phase = boot.phase
        if phase is not axis.phase:
            self._phase_changed(axis, phase, now_s)
        tracker = axis.tracker
        if boot.problem is not None and boot.problem_serial != axis.problem_serial:
            axis.problem_serial = boot.problem_serial
            tracker.report(FaultKind.BOOT, boot.problem, now_s)
        elif boot.problem is None:
            tracker.falling(FaultKind.BOOT)
        guard = axis.guard
        if guard is not None:
            guard.poll(now_s)
        if axis.emcys:
            for code, register in axis.emcys:
                if code == EMCY_SYNC_LENGTH and self._sync.counter_overflow and phase < 3:
                    # Counted SYNCs reach a drive before its 0x1019 is configured: expected.
                    continue
                tracker.report(FaultKind.EMCY, emcy_text(code, register), now_s, code)
            axis.emcys.clear()
        if axis.toggle_errors:
            axis.toggle_errors = 0
            tracker.report(FaultKind.GUARDING, "node guarding answer out of toggle", now_s)

        scaling = axis.scaling
        position_counts = axis.position_counts
        target_mm = following_error_mm = math.nan
        if phase in _STARTED_PHASES:
            state = state_of_statusword(axis.statusword)
            self._follow_state(axis, state)
            lagged = axis.answered_sync - axis.spec.feedback_lag_periods
            if lagged >= 1 and self._sync.sent - lagged < self._history:
                target_counts = axis.sent_counts[lagged % self._history]
                target_mm = scaling.to_mm(target_counts)
                if axis.drive_following_error is not None:
                    following_error_mm = scaling.to_mm(-axis.drive_following_error)
                else:
                    following_error_mm = scaling.to_mm(position_counts - target_counts)
            if phase is BootPhase.READY and self._shutdown is _ShutdownStep.RUNNING:
                self._supervise(axis, state, following_error_mm, now_s)
        else:
            state = axis.state = None
        axis.fresh = False
        if axis.reset_pending:
            self._carry_reset(axis, state)
        guard_age = guard.silence_s(now_s) if guard is not None and guard.running else None
        return AxisFeedback(
            axis=axis.spec.name,
            node_id=axis.node_id,
            phase=boot.phase,
            state=state,
            statusword=axis.statusword,
            position_counts=position_counts,
            position_mm=scaling.to_mm(position_counts),
            commanded_mm=scaling.to_mm(axis.prepared_counts),
            target_mm=target_mm,
            following_error_mm=following_error_mm,
            feedback_age_cycles=self._sync.sent - axis.answered_sync,
            heartbeat_age_s=(
                guard_age
                if guard_age is not None
                else math.inf
                if axis.heartbeat_s is None
                else now_s - axis.heartbeat_s
            ),
            error_code=axis.error_code,
            skipped_objects=boot.skipped,
            fault=tracker.fault,
            fault_reset_pending=axis.reset_pending,
        )

    def _follow_state(self, axis: _Axis, state: State | None) -> None:
        previous = axis.state
        if state in _FAULT_STATES and previous not in _FAULT_STATES:
            # The drive disabled itself: re-enabling takes an explicit request.
            axis.request = AxisRequest.DISABLE
        if axis.request is AxisRequest.QUICK_STOP and state is State.SWITCH_ON_DISABLED:
            axis.request = AxisRequest.DISABLE
        if state is State.OPERATION_ENABLED and previous is not State.OPERATION_ENABLED:
            # Newly enabled: hold where the drive is.
            axis.prepared_counts = axis.position_counts
        axis.state = state

    def _supervise(
        self, axis: _Axis, state: State | None, following_error_mm: float, now_s: float
    ) -> None:
        tracker = axis.tracker
        spec = axis.spec
        if state is None or state in _FAULT_STATES:
            if tracker.rising(FaultKind.FAULT_STATE):
                shown = "no CiA 402 state" if state is None else state.name
                code = axis.error_code
                cause = f", error code 0x{code:04X} {describe_emcy(code)}" if code else ""
                tracker.report(
                    FaultKind.FAULT_STATE,
                    f"drive in {shown} (statusword 0x{axis.statusword:04X}{cause})",
                    now_s,
                )
        else:
            tracker.falling(FaultKind.FAULT_STATE)
        if self._lost(axis, now_s):
            return
        nmt_state = axis.nmt_state
        if nmt_state is not None and nmt_state != NmtState.OPERATIONAL:
            tracker.report(
                FaultKind.NMT, f"NMT state {nmt_name(nmt_state)}, not OPERATIONAL", now_s
            )
            axis.boot.rebooted()
            return
        # Age 1 is on time: the answer to the SYNC just sent cannot be here yet. So the
        # answers missing are one fewer than the age, and the limit counts those.
        missing = self._sync.sent - axis.answered_sync - 1
        limit = self.settings.stale_feedback_cycles
        # An axis left disabled follows no target: late feedback there (a host that stalled
        # at start-up) is no danger, and a drive that went silent is the heartbeat's to find.
        if missing >= limit and axis.request is not AxisRequest.DISABLE:
            if tracker.rising(FaultKind.STALE_FEEDBACK):
                tracker.report(
                    FaultKind.STALE_FEEDBACK,
                    f"no TPDO for {missing} cycles (limit {limit})",
                    now_s,
                )
        else:
            tracker.falling(FaultKind.STALE_FEEDBACK)
        if state is State.OPERATION_ENABLED and axis.fresh:
            if abs(following_error_mm) > spec.following_error_window_mm:
                axis.beyond_window += 1
            else:
                axis.beyond_window = 0
        elif state is not State.OPERATION_ENABLED:
            axis.beyond_window = 0
        if axis.beyond_window > axis.following_error_periods:
            if tracker.rising(FaultKind.FOLLOWING_ERROR):
                tracker.report(
                    FaultKind.FOLLOWING_ERROR,
                    f"following error {following_error_mm:+.4f} mm beyond "
                    f"±{spec.following_error_window_mm:g} mm for {axis.beyond_window} periods",
                    now_s,
                )
        else:
            tracker.falling(FaultKind.FOLLOWING_ERROR)

    def _lost(self, axis: _Axis, now_s: float) -> bool:
        """Heartbeat or node-guarding silence beyond its limit: report and look again."""
        guard = axis.guard
        if guard is not None and guard.running:
            silence_s = guard.silence_s(now_s)
            limit_s = guard.life_time_s
            kind, what = FaultKind.GUARDING, "node-guarding answer"
        else:
            last = axis.heartbeat_s
            silence_s = math.inf if last is None else now_s - last
            if silence_s <= self._heartbeat_loss_s:
                return False
            limit_s = self._heartbeat_loss_s
            kind, what = FaultKind.HEARTBEAT_LOSS, "heartbeat"
        if silence_s <= limit_s:
            return False
        text = f"no {what} for {silence_s:.3f} s (limit {limit_s:.3f} s)"
        axis.tracker.report(kind, text, now_s)
        axis.boot.look_again(text)
        axis.problem_serial = axis.boot.problem_serial  # reported just now, as the loss
        return True

    def _carry_reset(self, axis: _Axis, state: State | None) -> None:
        if axis.phase in (BootPhase.CONFIGURING, BootPhase.STARTING):
            return  # an operator who resets a drive coming back means it once it is ready
        if axis.phase is not BootPhase.READY:
            axis.reset_pending = False  # nothing to reset yet: the fault stays
        elif state is not None and state not in _FAULT_STATES:
            axis.reset_pending = False
            axis.beyond_window = 0
            axis.tracker.clear()

    def _phase_changed(self, axis: _Axis, phase: BootPhase, now_s: float) -> None:
        previous = axis.phase
        axis.phase = phase
        boot = axis.boot
        if phase in _STARTED_PHASES and previous not in _STARTED_PHASES:
            self._install_pdos(axis, now_s)
        elif phase not in _STARTED_PHASES and previous in _STARTED_PHASES:
            self._remove_pdos(axis)
        if phase is BootPhase.READY:
            # Silence is counted from here: a drive found by its boot-up may not have sent a
            # heartbeat yet, and one that was lost has an old one.
            axis.heartbeat_s = now_s
            if boot.tpdo_seen:
                axis.nmt_state = NmtState.OPERATIONAL
        if boot.supervision is Supervision.GUARDING and phase in _STARTED_PHASES:
            if axis.guard is None or not axis.guard.running:
                axis.guard = axis.guard or NodeGuard(
                    axis.node_id,
                    self._send,
                    axis.spec.guard_time_ms / 1000.0,
                    axis.spec.life_time_factor,
                )
                axis.guard.start(now_s)
        elif axis.guard is not None and phase not in _STARTED_PHASES:
            axis.guard.stop()

    def _install_pdos(self, axis: _Axis, now_s: float) -> None:
        """The drive is configured: seed its feedback and targets, take its PDO layouts."""
        boot = axis.boot
        axis.statusword = boot.seed_statusword
        axis.position_counts = boot.seed_position_counts
        axis.answered_sync = self._sync.sent
        axis.drive_following_error = None
        axis.error_code = boot.seed_error_code
        axis.prepared_counts = boot.seed_position_counts
        axis.sent_counts = [boot.seed_position_counts] * self._history
        axis.request = AxisRequest.DISABLE
        axis.state = None
        axis.rpdo_codec = RpdoCodec(boot.rpdo)
        axis.rpdo_message = can.Message(
            arbitration_id=boot.rpdo.cob_id, is_extended_id=False, data=axis.rpdo_codec.buffer
        )
        axis.rpdo_codec.pack(Command.DISABLE_VOLTAGE, axis.prepared_counts)
        axis.tpdo_has_error_code = False
        ids = []
        for layout in boot.tpdos:
            codec = TpdoCodec(layout)
            axis.tpdo_has_error_code |= codec.error_code_at is not None
            self._dispatch[layout.cob_id] = functools.partial(self._on_tpdo, axis, codec)
            ids.append(layout.cob_id)
        axis.tpdo_ids = tuple(ids)
        axis.sending = True
        self._sending = [a for a in self._axes if a.sending]

    def _remove_pdos(self, axis: _Axis) -> None:
        for can_id in axis.tpdo_ids:
            self._dispatch.pop(can_id, None)
        axis.tpdo_ids = ()
        axis.sending = False
        axis.request = AxisRequest.DISABLE
        self._sending = [a for a in self._axes if a.sending]

    def _controlword(self, axis: _Axis) -> int:
        state = axis.state
        if state is None or state is State.FAULT_REACTION_ACTIVE:
            return Command.DISABLE_VOLTAGE
        if state is State.FAULT:
            if not axis.reset_pending:
                return Command.DISABLE_VOLTAGE
            controlword = fault_reset_controlword(axis.reset_cycle)
            axis.reset_cycle += 1
            return controlword
        if state is State.QUICK_STOP_ACTIVE:
            stays = self.settings.quick_stop_option in QUICK_STOP_OPTIONS_STAY_ACTIVE
            if stays and axis.request is AxisRequest.ENABLE:
                return Command.ENABLE_OPERATION  # transition 16
            if stays and axis.request is AxisRequest.DISABLE:
                return Command.DISABLE_VOLTAGE  # transition 12
            return Command.QUICK_STOP  # let the drive finish its ramp
        if axis.request is AxisRequest.ENABLE:
            return controlword_toward_enabled(state)
        if axis.request is AxisRequest.QUICK_STOP and state is not State.SWITCH_ON_DISABLED:
            return Command.QUICK_STOP
        return controlword_toward_disabled(state)

    # -- shutdown -----------------------------------------------------------------------------

    def _step_shutdown(self, now_s: float) -> None:
        if self._shutdown_deadline_s is None:
            timeout_s = self.settings.shutdown_timeout_s
            self._shutdown_deadline_s = now_s + timeout_s
            self._disable_deadline_s = now_s + timeout_s / 2
        late = now_s > self._shutdown_deadline_s
        if self._shutdown is _ShutdownStep.DISABLING:
            settled = all(
                axis.phase is not BootPhase.READY or axis.state in _SETTLED_STATES
                for axis in self._axes
            )
            if settled or now_s > self._disable_deadline_s:
                self._shutdown = _ShutdownStep.DISARMING
                for axis in self._axes:
                    axis.boot.begin_shutdown()
        elif self._shutdown is _ShutdownStep.DISARMING:
            for axis in self._axes:
                if axis.boot.shutdown_done and axis.sending:
                    axis.sending = False
                    self._sending = [a for a in self._axes if a.sending]
            if late or all(axis.boot.shutdown_done for axis in self._axes):
                if late:
                    pending = [a.node_id for a in self._axes if not a.boot.shutdown_done]
                    logger.warning("shutdown: timed out; nodes %s not disarmed", pending)
                for axis in self._axes:
                    if axis.guard is not None:
                        axis.guard.stop()
                    axis.sending = False
                self._sending = []
                self._heartbeat.stop()
                self._shutdown = _ShutdownStep.DONE


def _check_axes(axes: Sequence[AxisSpec], settings: MasterSettings) -> None:
    if not axes:
        raise ValueError("at least one axis is required")
    names = [axis.name for axis in axes]
    nodes = [axis.node_id for axis in axes]
    for label, values in (("name", names), ("node_id", nodes)):
        duplicates = sorted({str(v) for v in values if values.count(v) > 1})
        if duplicates:
            raise ValueError(f"axes: duplicate {label} {', '.join(duplicates)}")
    if settings.master_node_id in nodes:
        raise ValueError(f"master_node_id = {settings.master_node_id} is also an axis node_id")
