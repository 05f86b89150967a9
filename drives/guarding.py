"""NMT error control of the master: its heartbeat producer and node guarding of one drive.

Source: CiA 301 §7.2.8.3.2 (node guarding: the master sends a remote frame on 0x700 + node-ID
every guard time 0x100C; the node answers one byte, bit 7 a toggle that alternates with every
answer and bits 6..0 its NMT state; the node's life time is 0x100C × 0x100D, after which a node
that was guarded and is guarded no more raises a life guarding event, and the master calls a
node that has not answered for that long lost) and §7.2.8.3.2.2 (heartbeat: one byte NMT state
on 0x700 + node-ID every producer time).

Units: times in seconds on the cycle's clock (``now_s``); 0x100C and heartbeat times in ms.

Threading: the cycle thread only; each ``poll`` sends at most one frame and never blocks.
Invariants: a poll that comes late sends once and schedules the next frame a full period later
(no bursts after a stall); the first answer of a guarded node is accepted whatever its toggle
bit (the node may have been guarded by an earlier session), every later one must alternate.
Not done: the heartbeat consumer (the master notes each heartbeat's time itself), node guarding
of the master by the drives (that is their life guarding, armed through 0x100C/0x100D).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

import can

from drives.objects import HEARTBEAT_COB_ID_BASE, NmtState

#: Bit 7 of a node guarding answer.
GUARD_TOGGLE: Final[int] = 0x80


class PeriodicFrame:
    """One frame sent every ``period_s`` while running: the first at the first poll after
    :meth:`start`, each next one a period after the last was due, once only if the poll came
    late (no burst after a stall). A period of 0 sends nothing."""

    def __init__(
        self, message: can.Message, send: Callable[[can.Message], None], period_s: float
    ) -> None:
        self.message = message
        self.period_s = period_s
        self._send = send
        self._due_s: float | None = None
        self.running = False

    def start(self) -> None:
        self.running = self.period_s > 0
        self._due_s = None

    def stop(self) -> None:
        self.running = False

    def poll(self, now_s: float) -> None:
        """Send the frame when it is due."""
        if not self.running:
            return
        due_s = self._due_s
        if due_s is not None and now_s < due_s:
            return
        self._send(self.message)
        due_s = now_s if due_s is None else due_s + self.period_s
        self._due_s = due_s if due_s > now_s else now_s + self.period_s


def heartbeat_producer(
    node_id: int, send: Callable[[can.Message], None], period_s: float
) -> PeriodicFrame:
    """The master's own heartbeat (OPERATIONAL) on 0x700 + ``node_id`` every ``period_s``."""
    message = can.Message(
        arbitration_id=HEARTBEAT_COB_ID_BASE + node_id,
        is_extended_id=False,
        data=bytearray([NmtState.OPERATIONAL]),
    )
    return PeriodicFrame(message, send, period_s)


class NodeGuard:
    """Node guarding of one drive: remote frames every guard time, answers checked.

    :param guard_time_s: 0x100C, the interval of the remote frames.
    :param life_time_factor: 0x100D; the node is lost after guard time × factor without answer.
    """

    def __init__(
        self,
        node_id: int,
        send: Callable[[can.Message], None],
        guard_time_s: float,
        life_time_factor: int,
    ) -> None:
        if not guard_time_s > 0 or life_time_factor < 1:
            raise ValueError(
                f"node {node_id}: guard time {guard_time_s!r} s and life time factor "
                f"{life_time_factor}: must be > 0 and >= 1"
            )
        self.node_id = node_id
        self.guard_time_s = guard_time_s
        self.life_time_s = guard_time_s * life_time_factor
        request = can.Message(
            arbitration_id=HEARTBEAT_COB_ID_BASE + node_id,
            is_extended_id=False,
            is_remote_frame=True,
            dlc=1,
        )
        self._requests = PeriodicFrame(request, send, guard_time_s)
        self._expected_toggle: int | None = None
        self.started_s = 0.0
        self.last_answer_s: float | None = None
        self.nmt_state: int | None = None
        self.toggle_errors = 0

    @property
    def running(self) -> bool:
        return self._requests.running

    def start(self, now_s: float) -> None:
        """Begin guarding: the first remote frame goes out at the next poll."""
        self._requests.start()
        self._expected_toggle = None
        self.started_s = now_s
        self.last_answer_s = None
        self.nmt_state = None

    def stop(self) -> None:
        self._requests.stop()

    def poll(self, now_s: float) -> None:
        """Send the remote frame when it is due."""
        self._requests.poll(now_s)

    def on_answer(self, value: int, now_s: float) -> bool:
        """Take an answer byte; return False if its toggle bit did not alternate."""
        toggle = value & GUARD_TOGGLE
        in_order = self._expected_toggle is None or toggle == self._expected_toggle
        if not in_order:
            self.toggle_errors += 1
        self._expected_toggle = toggle ^ GUARD_TOGGLE
        self.nmt_state = value & ~GUARD_TOGGLE & 0xFF
        self.last_answer_s = now_s
        return in_order

    def silence_s(self, now_s: float) -> float:
        """Seconds since the last answer (since guarding began, before the first)."""
        last = self.started_s if self.last_answer_s is None else self.last_answer_s
        return now_s - last
