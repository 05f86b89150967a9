"""Supervision of one drive: its TPDO1, heartbeat and EMCY as received, and the faults they show.

Source: CiA 301 heartbeat (0x700 + node, consumer side of 0x1017) and EMCY (0x80 + node, error
code and register 0x1001); CiA 402 statusword fault bit (0x6041 bit 3) and CSP following error
(|position actual - target| beyond the window 0x6065 for longer than 0x6066).

Units: positions in mm, ages in SYNC cycles (feedback) or seconds (heartbeat), times from the
master's monotonic clock.

Threading contract:
- ``on_tpdo``, ``on_heartbeat`` and ``on_emcy`` run in the python-can Notifier thread. They do
  O(1) work, store one new immutable record per frame by reference swap (a single attribute
  assignment, atomic under the GIL), and never raise: an exception is logged with
  ``logger.exception`` and the frame dropped.
- ``supervise`` runs in the cyclic thread. It reads each record once (so it works on one
  consistent snapshot per source) and keeps the latched fault and the following-error timer,
  which only that thread touches.

Invariants: a fault, once detected, stays latched until :meth:`AxisSupervisor.clear_fault`; only
a more severe one replaces it (order of :class:`FaultKind`), so the EMCY of an event replaces the
statusword fault bit seen one frame earlier, and a lost heartbeat replaces the stale feedback
that a silent drive shows first.

Not modelled: node guarding, the EMCY history (0x1003), bus-off and error frames.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

from canopen.emcy import EmcyError

from drives.cia402 import State
from drives.emcy import EMCY_ERROR_RESET, describe_emcy
from drives.objects import NmtState
from drives.scaling import AxisScaling

logger = logging.getLogger(__name__)


class FaultKind(Enum):
    """What detected a fault on an axis, most severe first."""

    EMCY = "EMCY"
    FAULT_STATE = "fault state"
    HEARTBEAT_LOSS = "heartbeat loss"
    STALE_FEEDBACK = "stale feedback"
    FOLLOWING_ERROR = "following error"
    BOOT = "boot"
    NMT = "NMT state"


#: Lower is more severe: the EMCY names the cause, a lost node explains its silence.
_SEVERITY = {
    FaultKind.EMCY: 0,
    FaultKind.FAULT_STATE: 1,
    FaultKind.HEARTBEAT_LOSS: 2,
    FaultKind.NMT: 3,
    FaultKind.BOOT: 4,
    FaultKind.STALE_FEEDBACK: 5,
    FaultKind.FOLLOWING_ERROR: 6,
}


@dataclass(frozen=True)
class AxisFault:
    """A fault raised on one axis, readable by the runtime in the cycle it was detected."""

    axis: str
    node_id: int
    kind: FaultKind
    emcy_code: int | None
    text: str
    """Readable cause, e.g. ``EMCY 0x8611 following error (register 0x20)``."""

    def __str__(self) -> str:
        return f"axis {self.axis} (node {self.node_id}): {self.text}"


@dataclass(frozen=True, slots=True)
class TpdoSample:
    """One TPDO1 as received: statusword, position actual and the SYNC it answered."""

    statusword: int
    position_counts: int
    sync_count: int
    """Number of SYNCs the master had sent when the frame arrived."""


@dataclass(frozen=True, slots=True)
class HeartbeatSample:
    """The last heartbeat (or boot-up, state 0) and when it arrived."""

    nmt_state: int
    received_s: float


@dataclass(frozen=True, slots=True)
class EmcyRecord:
    """The last EMCY with a non-zero error code since the last error reset."""

    code: int
    register: int
    received_s: float
    sequence: int
    """1 for the first EMCY of the node, counting up (acknowledging compares it)."""

    @property
    def text(self) -> str:
        return f"EMCY 0x{self.code:04X} {describe_emcy(self.code)} (register 0x{self.register:02X})"


class SyncCounter:
    """Number of SYNCs sent, shared by the master (writer) and the TPDO callbacks (readers)."""

    __slots__ = ("value",)

    def __init__(self) -> None:
        self.value = 0


@dataclass(frozen=True, slots=True)
class SupervisionLimits:
    """Thresholds of one axis's supervision."""

    heartbeat_loss_s: float
    """A heartbeat older than this is a loss (heartbeat_loss_periods × 0x1017 time)."""
    stale_feedback_cycles: int
    following_error_window_mm: float
    following_error_cycles: int
    """Cycles beyond the window before the following error is a fault (0x6066 in cycles)."""


class AxisSupervisor:
    """Receives one drive's frames and turns them into at most one latched fault."""

    def __init__(
        self,
        axis: str,
        node_id: int,
        scaling: AxisScaling,
        limits: SupervisionLimits,
        syncs: SyncCounter,
        clock: Callable[[], float],
    ) -> None:
        self.axis = axis
        self.node_id = node_id
        self.scaling = scaling
        self.limits = limits
        self._syncs = syncs
        self._clock = clock
        #: Set by the first boot-up or heartbeat (boot waits on it).
        self.alive = threading.Event()
        # Written by the Notifier thread only (reference swap).
        self.tpdo: TpdoSample | None = None
        self.heartbeat: HeartbeatSample | None = None
        self.emcy: EmcyRecord | None = None
        self._emcy_count = 0
        # Cyclic thread only.
        self._emcy_acknowledged = 0
        self.fault: AxisFault | None = None
        self._cycles_beyond_window = 0

    # -- Notifier thread ------------------------------------------------------------------------

    def on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """TPDO1 frame (``Network.subscribe`` callback): keep statusword and position actual
        with the current SYNC count."""
        try:
            self.tpdo = TpdoSample(
                statusword=int.from_bytes(data[0:2], "little"),
                position_counts=int.from_bytes(data[2:6], "little", signed=True),
                sync_count=self._syncs.value,
            )
        except Exception:
            logger.exception("node %d: TPDO1 %r dropped", self.node_id, data)

    def on_heartbeat(self, nmt_state: int) -> None:
        """Heartbeat / boot-up callback: keep the NMT state and our own reception time.

        The frame timestamp is not used: it is wall-clock (virtual) or kernel time (socketcan),
        whereas ages are measured on the master's monotonic clock.
        """
        try:
            self.heartbeat = HeartbeatSample(nmt_state, self._clock())
            self.alive.set()
        except Exception:
            logger.exception("node %d: heartbeat %r dropped", self.node_id, nmt_state)

    def on_emcy(self, error: EmcyError) -> None:
        """EMCY callback: keep the last error; the error-reset EMCY (0x0000) clears it."""
        try:
            if error.code == EMCY_ERROR_RESET:
                self.emcy = None
            else:
                self._emcy_count += 1
                self.emcy = EmcyRecord(error.code, error.register, self._clock(), self._emcy_count)
        except Exception:
            logger.exception("node %d: EMCY dropped", self.node_id)

    def seed(self, statusword: int, position_counts: int) -> None:
        """Store the feedback read by SDO at boot, as if answered to the current SYNC."""
        self.tpdo = TpdoSample(statusword, position_counts, self._syncs.value)

    # -- cyclic thread --------------------------------------------------------------------------

    def supervise(
        self,
        state: State | None,
        sample: TpdoSample,
        heartbeat: HeartbeatSample | None,
        emcy: EmcyRecord | None,
        following_error_mm: float,
        now_s: float,
    ) -> AxisFault | None:
        """Update and return the latched fault from this cycle's snapshot.

        :param state: the decoded statusword, None if it matched no CiA 402 state.
        :param sample: the TPDO1 snapshot read this cycle.
        :param following_error_mm: actual minus the target the drive was following, 0 when
            the axis is not in OPERATION ENABLED.
        """
        if abs(following_error_mm) > self.limits.following_error_window_mm:
            self._cycles_beyond_window += 1
        else:
            self._cycles_beyond_window = 0
        if emcy is not None and emcy.sequence <= self._emcy_acknowledged:
            emcy = None
        detected = self._detect(state, sample, heartbeat, emcy, following_error_mm, now_s)
        latched = self.fault
        if detected is not None and (
            latched is None or _SEVERITY[detected.kind] < _SEVERITY[latched.kind]
        ):
            self.fault = detected
        return self.fault

    def _detect(
        self,
        state: State | None,
        sample: TpdoSample,
        heartbeat: HeartbeatSample | None,
        emcy: EmcyRecord | None,
        following_error_mm: float,
        now_s: float,
    ) -> AxisFault | None:
        if emcy is not None:
            return self._make(FaultKind.EMCY, emcy.code, emcy.text)
        if state is None:
            return self._make(
                FaultKind.FAULT_STATE,
                None,
                f"statusword 0x{sample.statusword:04X} matches no CiA 402 state",
            )
        if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return self._make(
                FaultKind.FAULT_STATE,
                None,
                f"drive in {state.name} (statusword 0x{sample.statusword:04X})",
            )
        if heartbeat is None:
            return self._make(FaultKind.HEARTBEAT_LOSS, None, "no heartbeat received")
        heartbeat_age_s = now_s - heartbeat.received_s
        if heartbeat_age_s > self.limits.heartbeat_loss_s:
            return self._make(
                FaultKind.HEARTBEAT_LOSS,
                None,
                f"no heartbeat for {heartbeat_age_s:.3f} s "
                f"(limit {self.limits.heartbeat_loss_s:.3f} s)",
            )
        if heartbeat.nmt_state != NmtState.OPERATIONAL:
            return self._make(
                FaultKind.NMT, None, f"NMT state {_nmt_name(heartbeat.nmt_state)}, not OPERATIONAL"
            )
        age = self._syncs.value - sample.sync_count
        if age >= self.limits.stale_feedback_cycles:
            return self._make(
                FaultKind.STALE_FEEDBACK,
                None,
                f"no TPDO for {age} cycles (limit {self.limits.stale_feedback_cycles})",
            )
        if self._cycles_beyond_window > self.limits.following_error_cycles:
            return self._make(
                FaultKind.FOLLOWING_ERROR,
                None,
                f"following error {following_error_mm:+.4f} mm beyond "
                f"±{self.limits.following_error_window_mm:g} mm for "
                f"{self._cycles_beyond_window} cycles",
            )
        return None

    def clear_fault(self) -> None:
        """Forget the latched fault and the EMCYs received so far.

        A condition still present (statusword fault, lost heartbeat, ...) latches again at the
        next :meth:`supervise`; an EMCY received after this call is a new fault.
        """
        emcy = self.emcy
        if emcy is not None:
            self._emcy_acknowledged = emcy.sequence
        self.fault = None
        self._cycles_beyond_window = 0

    def _make(self, kind: FaultKind, emcy_code: int | None, text: str) -> AxisFault:
        return AxisFault(self.axis, self.node_id, kind, emcy_code, text)


def _nmt_name(nmt_state: int) -> str:
    try:
        return NmtState(nmt_state).name
    except ValueError:
        return f"0x{nmt_state:02X}"
