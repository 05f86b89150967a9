"""A small cycle loop that steps a CiA 402 master the way the cycle process does.

Per step: ``transmit_period`` (RPDOs, SYNC), ``receive``, ``update`` (feedback), then
``write_targets``; requests made between steps take effect at the next ``write_targets``, as the
machine's requests do after ``update`` in the cycle. Fault events are collected in ``events``.

Two paces:

- real time (default): each step starts at its absolute deadline on the loop's clock, missed
  deadlines are skipped, as the cycle does; heartbeats, SDO time-outs and SYNC supervision of the
  drives all see real periods;
- fast: each step waits, after its SYNC, until every started drive has answered that SYNC and
  no SDO answer is outstanding (bounded by ``answer_wait_s``), then goes on at once, so motion
  runs faster than real time while the simulated drives still step once per SYNC.

Reused by the runtime's tests: nothing here is specific to one scenario.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from drives.master import AxisFeedback, Cia402Master
from drives.monitor import AxisFault

Targets = (
    Sequence[float | None]
    | None
    | Callable[[tuple[AxisFeedback, ...]], Sequence[float | None] | None]
)


class CycleLoop:
    """Steps ``master`` once per period.

    :param realtime: pace the steps at ``period_s`` (else as fast as the drives answer).
    :param answer_wait_s: in fast mode, the longest wait for the drives' answers per step.
    """

    def __init__(
        self,
        master: Cia402Master,
        period_s: float,
        *,
        realtime: bool = True,
        clock: Callable[[], float] = time.monotonic,
        answer_wait_s: float = 0.05,
    ) -> None:
        self.master = master
        self.period_s = period_s
        self.realtime = realtime
        self.clock = clock
        self.answer_wait_s = answer_wait_s
        self.events: list[AxisFault] = []
        self.feedback: tuple[AxisFeedback, ...] = ()
        self.steps = 0
        self.missed = 0
        self._deadline_s: float | None = None

    def step(self, targets: Targets = None) -> tuple[AxisFeedback, ...]:
        """One period; ``targets`` are positions in mm, or a function of this period's
        feedback returning them."""
        master = self.master
        self._pace()
        master.transmit_period()
        if not self.realtime:
            self._wait_for_answers()
        now_s = self.clock()
        master.receive(now_s)
        feedback = master.update(now_s)
        self.events.extend(master.take_fault_events())
        master.write_targets(targets(feedback) if callable(targets) else targets)
        self.feedback = feedback
        self.steps += 1
        return feedback

    def run_until(
        self,
        predicate: Callable[[tuple[AxisFeedback, ...]], bool],
        timeout_s: float,
        targets: Targets = None,
        what: str = "condition",
    ) -> tuple[AxisFeedback, ...]:
        """Step until ``predicate(feedback)`` holds.

        :raises AssertionError: after ``timeout_s`` (wall clock), naming ``what`` and the
            last feedback.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            feedback = self.step(targets)
            if predicate(feedback):
                return feedback
            if time.monotonic() > deadline:
                raise AssertionError(f"{what} not reached in {timeout_s:g} s: {_show(feedback)}")

    def run_for(self, duration_s: float, targets: Targets = None) -> tuple[AxisFeedback, ...]:
        """Step for ``duration_s`` of loop time (real time, or periods in fast mode)."""
        feedback = self.feedback
        for _ in range(max(1, round(duration_s / self.period_s))):
            feedback = self.step(targets)
        return feedback

    def boot(self, timeout_s: float = 10.0) -> tuple[AxisFeedback, ...]:
        """Start the master and step until every drive is ready."""
        self.master.start()
        return self.run_until(
            lambda feedback: all(f.ready for f in feedback), timeout_s, what="every drive ready"
        )

    def enable(self, timeout_s: float = 5.0) -> tuple[AxisFeedback, ...]:
        self.master.request_enable()
        return self.run_until(
            lambda feedback: all(f.enabled for f in feedback), timeout_s, what="every axis enabled"
        )

    def shutdown(self, timeout_s: float = 10.0) -> None:
        """Run the master's clean shutdown to its end."""
        self.master.begin_shutdown()
        self.run_until(lambda _: self.master.shutdown_done, timeout_s, what="shutdown done")

    def _pace(self) -> None:
        if not self.realtime:
            return
        now_s = self.clock()
        if self._deadline_s is None:
            self._deadline_s = now_s
        elif now_s > self._deadline_s + self.period_s:
            skipped = int((now_s - self._deadline_s) / self.period_s)
            self.missed += skipped
            self._deadline_s += skipped * self.period_s
        delay_s = self._deadline_s - now_s
        if delay_s > 0:
            time.sleep(delay_s)
        self._deadline_s += self.period_s

    def _wait_for_answers(self) -> None:
        master = self.master
        deadline = time.monotonic() + self.answer_wait_s
        master.receive(self.clock())
        while not master.feedback_complete or master.sdo_in_flight:
            if time.monotonic() > deadline:
                return
            time.sleep(0.0001)
            master.receive(self.clock())


def _show(feedback: tuple[AxisFeedback, ...]) -> str:
    return "; ".join(
        f"{f.axis}: {f.phase.name} {f.state.name if f.state else None} fault={f.fault}"
        for f in feedback
    )
