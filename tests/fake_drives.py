"""Drives without a bus, for testing the machine logic period by period.

:class:`FakeDrives` has the cycle API of :class:`drives.master.Cia402Master` (``start``,
``transmit_period``, ``receive``, ``update``, ``write_targets``, the requests, the fault
events, ``begin_shutdown`` / ``shutdown_done``) with ideal drives: each axis is ready at once,
steps one CiA 402 transition per period toward what was requested, follows its target one
period late, and can be given a fault. Feedback records and fault events are the master's own
types.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from drives.boot import BootPhase
from drives.cia402 import State, encode_statusword
from drives.master import AxisFeedback
from drives.monitor import AxisFault, FaultKind


@dataclass
class FakeAxis:
    name: str
    node_id: int
    state: State = State.SWITCH_ON_DISABLED
    position_mm: float = 0.0
    target_mm: float = 0.0
    followed_mm: float = 0.0
    request: str = "disable"
    fault: AxisFault | None = None
    reset_pending: bool = False


class FakeDrives:
    """The master's cycle API with ideal drives (1000 counts per mm)."""

    def __init__(self, names: Sequence[str] = ("X", "Y", "Z")) -> None:
        self.axes = [FakeAxis(name, i + 1) for i, name in enumerate(names)]
        self.requests: list[str] = []
        self.periods = 0
        self.events: list[AxisFault] = []
        self.feedback: tuple[AxisFeedback, ...] = ()
        self.started = False
        self.shutting_down = False

    @property
    def axis_names(self) -> tuple[str, ...]:
        return tuple(axis.name for axis in self.axes)

    # boot and shutdown
    def start(self) -> None:
        self.started = True

    def begin_shutdown(self) -> None:
        self.shutting_down = True
        self._request("disable", None)

    @property
    def shutdown_done(self) -> bool:
        return self.shutting_down and all(
            axis.state in (State.SWITCH_ON_DISABLED, State.FAULT) for axis in self.axes
        )

    # requests
    def request_enable(self, axes: Iterable[str] | None = None) -> None:
        self._request("enable", axes)

    def request_disable(self, axes: Iterable[str] | None = None) -> None:
        self._request("disable", axes)

    def request_quick_stop(self, axes: Iterable[str] | None = None) -> None:
        self._request("quick_stop", axes)

    def request_fault_reset(self, axes: Iterable[str] | None = None) -> None:
        self.requests.append("fault_reset")
        for axis in self._select(axes):
            axis.reset_pending = True

    def _request(self, what: str, axes: Iterable[str] | None) -> None:
        self.requests.append(what)
        for axis in self._select(axes):
            axis.request = what

    def _select(self, axes: Iterable[str] | None) -> list[FakeAxis]:
        if axes is None:
            return self.axes
        names = {axes} if isinstance(axes, str) else set(axes)
        return [axis for axis in self.axes if axis.name in names]

    # faults
    def inject_fault(
        self, index: int, *, emcy_code: int = 0x4210, text: str = "over-temperature"
    ) -> None:
        """The drive of axis ``index`` faults with an EMCY now (an event at the next update)."""
        axis = self.axes[index]
        axis.state = State.FAULT
        axis.request = "disable"
        fault = AxisFault(axis.name, axis.node_id, FaultKind.EMCY, emcy_code, text)
        axis.fault = axis.fault or fault
        self.events.append(fault)

    def take_fault_events(self) -> tuple[AxisFault, ...]:
        events = tuple(self.events)
        self.events.clear()
        return events

    # the period
    def transmit_period(self) -> None:
        self.periods += 1
        for axis in self.axes:
            if axis.state is State.OPERATION_ENABLED:
                axis.followed_mm = axis.position_mm = axis.target_mm
            else:
                axis.followed_mm = axis.target_mm = axis.position_mm
            axis.state = _next_state(axis)

    def receive(self, now_s: float) -> int:
        return 0

    def update(self, now_s: float) -> tuple[AxisFeedback, ...]:
        for axis in self.axes:
            if axis.reset_pending and axis.state is State.FAULT:
                axis.state = State.SWITCH_ON_DISABLED
            if axis.reset_pending:
                axis.reset_pending = False
                axis.fault = None
        self.feedback = tuple(
            AxisFeedback(
                axis=a.name,
                node_id=a.node_id,
                phase=BootPhase.READY if self.started else BootPhase.WAITING,
                state=a.state,
                statusword=encode_statusword(a.state),
                position_counts=round(a.position_mm * 1000),
                position_mm=a.position_mm,
                commanded_mm=a.target_mm,
                target_mm=a.followed_mm,
                following_error_mm=a.position_mm - a.followed_mm,
                feedback_age_cycles=1,
                heartbeat_age_s=0.0,
                error_code=(a.fault.emcy_code or 0) if a.fault else 0,
                skipped_objects=(),
                fault=a.fault,
                fault_reset_pending=a.reset_pending,
            )
            for a in self.axes
        )
        return self.feedback

    def write_targets(self, positions_mm: Sequence[float | None] | None) -> None:
        if positions_mm is None:
            return
        for axis, target in zip(self.axes, positions_mm, strict=True):
            if target is not None and axis.state is State.OPERATION_ENABLED:
                axis.target_mm = target


def _next_state(axis: FakeAxis) -> State:
    state = axis.state
    if state is State.FAULT:
        return state
    if axis.request == "enable":
        return {
            State.SWITCH_ON_DISABLED: State.READY_TO_SWITCH_ON,
            State.READY_TO_SWITCH_ON: State.SWITCHED_ON,
            State.SWITCHED_ON: State.OPERATION_ENABLED,
            State.QUICK_STOP_ACTIVE: State.SWITCH_ON_DISABLED,
        }.get(state, state)
    if axis.request == "quick_stop" and state is State.OPERATION_ENABLED:
        return State.QUICK_STOP_ACTIVE
    return State.SWITCH_ON_DISABLED
