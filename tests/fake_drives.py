"""Drives without a bus, for testing the machine logic cycle by cycle.

Each axis steps one CiA 402 transition per cycle toward what was requested, follows its target
exactly one cycle late, and can be given a fault. Feedback records are the master's own
:class:`drives.master.AxisFeedback`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from drives.cia402 import State
from drives.master import AxisFeedback
from drives.monitor import AxisFault, FaultKind


@dataclass
class FakeAxis:
    name: str
    node_id: int
    state: State = State.SWITCH_ON_DISABLED
    position_mm: float = 0.0
    target_mm: float = 0.0
    request: str = "disable"
    fault: AxisFault | None = None


class FakeDrives:
    """The cyclic API of :class:`drives.master.Cia402Master`, with ideal drives."""

    def __init__(self, names: Sequence[str] = ("X", "Y", "Z")) -> None:
        self.axes = [FakeAxis(name, i + 1) for i, name in enumerate(names)]
        self.requests: list[str] = []
        self.exchanges = 0

    # requests
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

    def recover(self) -> tuple[str, ...]:
        self.requests.append("recover")
        return ()

    # faults
    def inject_fault(self, index: int, *, emcy_code: int = 0x4210, text: str = "over-temperature"):
        axis = self.axes[index]
        axis.state = State.FAULT
        axis.fault = AxisFault(axis.name, axis.node_id, FaultKind.EMCY, emcy_code, text)

    # cycle
    def read_feedback(self) -> tuple[AxisFeedback, ...]:
        return tuple(
            AxisFeedback(
                axis=a.name,
                node_id=a.node_id,
                state=a.state,
                statusword=0,
                position_counts=round(a.position_mm * 1000),
                position_mm=a.position_mm,
                commanded_mm=a.target_mm,
                following_error_mm=a.position_mm - a.target_mm,
                feedback_age_cycles=0,
                heartbeat_age_s=0.0,
                fault=a.fault,
            )
            for a in self.axes
        )

    def write_targets(self, positions_mm: Sequence[float | None] | None) -> None:
        if positions_mm is None:
            return
        for axis, target in zip(self.axes, positions_mm, strict=True):
            if target is not None:
                axis.target_mm = target

    def exchange(self) -> None:
        self.exchanges += 1
        for axis in self.axes:
            if axis.state is State.OPERATION_ENABLED:
                axis.position_mm = axis.target_mm
            else:
                axis.target_mm = axis.position_mm
            axis.state = _next_state(axis)


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
