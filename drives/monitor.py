"""Faults of one axis: what detected them, the latched fault and the stream of fault events.

Source: CiA 301 EMCY (0x80 + node-ID: error code, error register 0x1001), heartbeat and node
guarding (lost node, NMT state), CiA 402 statusword fault bit (0x6041 bit 3) and CSP following
error (|actual - target| beyond the window for longer than the timeout), plus the master's own
checks: feedback that stopped answering the SYNCs, and the boot of the drive.

Two views of the same faults:

- events: every fault when it happens, in the order detected: each EMCY frame with an error
  code, and each condition (drive in FAULT, heartbeat lost, ...) when it appears; a condition
  that persists is one event, one that goes and comes back is two. The runtime takes them with
  ``Cia402Master.take_fault_events`` and reports all of them, also while it is already stopping;
- the latched fault of the axis: the most severe fault since the last fault reset (order of
  :class:`FaultKind`), so the EMCY that names a cause replaces the statusword fault bit seen
  one frame earlier, and a lost heartbeat replaces the stale feedback a silent drive shows first.

Units: times in seconds on the cycle's clock.
Threading: the cycle thread only.
Not done: the EMCY history (0x1003), bus-off and error frames.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum
from typing import Final

from drives.emcy import describe_emcy
from drives.objects import NmtState


class FaultKind(Enum):
    """What detected a fault on an axis, most severe first."""

    EMCY = "EMCY"
    FAULT_STATE = "fault state"
    HEARTBEAT_LOSS = "heartbeat loss"
    GUARDING = "node guarding"
    NMT = "NMT state"
    BOOT = "boot"
    STALE_FEEDBACK = "stale feedback"
    FOLLOWING_ERROR = "following error"


#: Lower is more severe.
_SEVERITY: Final = {kind: rank for rank, kind in enumerate(FaultKind)}

#: Fault events kept for the runtime to take; older ones are dropped first (an EMCY flood
#: must not grow memory without bound).
EVENT_QUEUE_LENGTH: Final[int] = 256


@dataclass(frozen=True, slots=True)
class AxisFault:
    """A fault on one axis: as an event, and as the axis's latched fault."""

    axis: str
    node_id: int
    kind: FaultKind
    emcy_code: int | None
    text: str
    """Readable cause, e.g. ``EMCY 0x8611 following error (register 0x20)``."""
    detected_s: float = 0.0
    """The cycle time (``now_s``) at which the master saw it."""

    def __str__(self) -> str:
        return f"axis {self.axis} (node {self.node_id}): {self.text}"


def emcy_text(code: int, register: int) -> str:
    """``EMCY 0x8611 following error (register 0x20)``."""
    return f"EMCY 0x{code:04X} {describe_emcy(code)} (register 0x{register:02X})"


def nmt_name(nmt_state: int) -> str:
    """``PRE_OPERATIONAL`` for a known NMT state byte, else its hex value."""
    try:
        return NmtState(nmt_state).name
    except ValueError:
        return f"0x{nmt_state:02X}"


class FaultTracker:
    """The faults of one axis: condition edges, events and the latched fault.

    :param events: the master's event queue, shared by every axis (one order for all).
    """

    __slots__ = ("_active", "_events", "axis", "fault", "node_id")

    def __init__(self, axis: str, node_id: int, events: deque[AxisFault]) -> None:
        self.axis = axis
        self.node_id = node_id
        self.fault: AxisFault | None = None
        self._active: set[FaultKind] = set()
        self._events = events

    def rising(self, kind: FaultKind) -> bool:
        """Mark the condition ``kind`` present; True if it was not (report it then)."""
        if kind in self._active:
            return False
        self._active.add(kind)
        return True

    def falling(self, kind: FaultKind) -> None:
        """Mark the condition ``kind`` gone; it is reported again when it comes back."""
        if self._active:  # the cycle's usual case, no condition present, costs a test
            self._active.discard(kind)

    def report(
        self, kind: FaultKind, text: str, now_s: float, emcy_code: int | None = None
    ) -> AxisFault:
        """Queue a fault event and latch it if it is more severe than the latched one."""
        fault = AxisFault(self.axis, self.node_id, kind, emcy_code, text, now_s)
        self._events.append(fault)
        latched = self.fault
        if latched is None or _SEVERITY[kind] < _SEVERITY[latched.kind]:
            self.fault = fault
        return fault

    def clear(self) -> None:
        """Forget the latched fault and the present conditions (fault reset): a condition
        still there is reported and latched again at the next check."""
        self.fault = None
        self._active.clear()
