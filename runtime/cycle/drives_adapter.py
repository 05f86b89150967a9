"""TEMPORARY: the blocking master behind the cycle's per-period API (until drives lands)."""

from __future__ import annotations

from dataclasses import dataclass

import canopen

from drives.master import Cia402Master


@dataclass(frozen=True)
class _Feedback:
    axis: str
    node_id: int
    state: object
    statusword: int
    boot_phase: int
    position_mm: float
    following_error_mm: float
    fault: object


class LegacyDrives:
    def __init__(self, bus, axes, settings) -> None:
        self.network = canopen.Network(bus)
        self.network.connect()
        self.master = Cia402Master(self.network, axes, settings)
        self._faults = [None] * len(axes)
        self._events = []
        self._done = False

    def start(self) -> None:
        self.master.boot()

    def transmit_period(self) -> None:
        self.master.exchange()

    def receive(self, now_s: float) -> None:
        pass

    def update(self, now_s: float):
        out = []
        for i, fb in enumerate(self.master.read_feedback()):
            if fb.fault is not None and fb.fault is not self._faults[i]:
                self._events.append(fb.fault)
            self._faults[i] = fb.fault
            out.append(
                _Feedback(
                    fb.axis,
                    fb.node_id,
                    fb.state,
                    fb.statusword,
                    4,
                    fb.position_mm,
                    fb.following_error_mm,
                    fb.fault,
                )
            )
        return tuple(out)

    def take_fault_events(self):
        events, self._events = self._events, []
        return events

    def write_targets(self, positions_mm) -> None:
        self.master.write_targets(positions_mm)

    def request_enable(self) -> None:
        self.master.request_enable()

    def request_disable(self) -> None:
        self.master.request_disable()

    def request_quick_stop(self) -> None:
        self.master.request_quick_stop()

    def request_fault_reset(self) -> None:
        self.master.request_fault_reset()

    def begin_shutdown(self) -> None:
        self.master.shutdown()
        self._done = True

    @property
    def shutdown_done(self) -> bool:
        return self._done
