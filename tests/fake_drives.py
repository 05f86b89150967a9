"""Drives without a bus, for testing the cycle and the machine period by period.

The per-period API of the CiA-402 master (:class:`runtime.cycle.cycle.CycleDrives`) with ideal
drives: each axis steps one CiA 402 transition per period toward what was requested, follows
its target one period late (the target sent with a SYNC is reached by the next), and can be
given a fault, which is reported once as an event and stays latched until a fault reset.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from drives.cia402 import State
from drives.monitor import FaultKind


@dataclass(frozen=True)
class FakeFault:
    axis: str
    node_id: int
    kind: FaultKind
    emcy_code: int | None
    text: str


@dataclass(frozen=True)
class FakeFeedback:
    axis: str
    node_id: int
    state: State | None
    statusword: int
    boot_phase: int
    position_mm: float
    following_error_mm: float
    fault: FakeFault | None


@dataclass
class FakeAxis:
    name: str
    node_id: int
    state: State = State.SWITCH_ON_DISABLED
    position_mm: float = 0.0
    target_mm: float = 0.0
    sent_mm: float = 0.0
    request: str = "disable"
    fault: FakeFault | None = None


class FakeDrives:
    """Ideal drives behind the master's per-period API; see the module docstring."""

    def __init__(self, names: Sequence[str] = ("X", "Y", "Z")) -> None:
        self.axes = [FakeAxis(name, i + 1) for i, name in enumerate(names)]
        self.requests: list[str] = []
        self.periods = 0
        self.started = False
        self.shutting_down = False
        self._events: list[FakeFault] = []

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        self.started = True

    def begin_shutdown(self) -> None:
        self.shutting_down = True

    @property
    def shutdown_done(self) -> bool:
        return self.shutting_down and all(a.state is not State.OPERATION_ENABLED for a in self.axes)

    # -- requests ----------------------------------------------------------------------------

    def request_enable(self) -> None:
        self._request("enable")

    def request_disable(self) -> None:
        self._request("disable")

    def request_quick_stop(self) -> None:
        self._request("quick_stop")

    def request_fault_reset(self) -> None:
        self.requests.append("fault_reset")
        for axis in self.axes:
            if axis.state is State.FAULT:
                axis.state = State.SWITCH_ON_DISABLED
            axis.fault = None

    def _request(self, what: str) -> None:
        self.requests.append(what)
        for axis in self.axes:
            axis.request = what

    # -- faults ------------------------------------------------------------------------------

    def inject_fault(
        self, index: int, *, emcy_code: int = 0x4210, text: str = "EMCY 0x4210 over-temperature"
    ) -> None:
        axis = self.axes[index]
        axis.state = State.FAULT
        axis.fault = FakeFault(axis.name, axis.node_id, FaultKind.EMCY, emcy_code, text)
        self._events.append(axis.fault)

    # -- the period --------------------------------------------------------------------------

    def transmit_period(self) -> None:
        self.periods += 1
        for axis in self.axes:
            if axis.state is State.OPERATION_ENABLED:
                axis.position_mm = axis.sent_mm
            axis.sent_mm = axis.target_mm
            axis.state = _next_state(axis)

    def receive(self, now_s: float) -> None:
        pass

    def update(self, now_s: float) -> tuple[FakeFeedback, ...]:
        return tuple(
            FakeFeedback(
                axis=a.name,
                node_id=a.node_id,
                state=a.state,
                statusword=0,
                boot_phase=4,
                position_mm=a.position_mm,
                following_error_mm=(
                    a.position_mm - a.sent_mm if a.state is State.OPERATION_ENABLED else 0.0
                ),
                fault=a.fault,
            )
            for a in self.axes
        )

    def take_fault_events(self) -> list[FakeFault]:
        events, self._events = self._events, []
        return events

    def write_targets(self, positions_mm: Sequence[float | None] | None) -> None:
        if positions_mm is None:
            return
        for axis, target in zip(self.axes, positions_mm, strict=True):
            if axis.state is not State.OPERATION_ENABLED:
                axis.target_mm = axis.position_mm
            elif target is not None:
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
