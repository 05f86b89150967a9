"""SYNC producer and the matching of received feedback to the SYNC it answered.

Source: CiA 301 §7.2.5 (SYNC on COB-ID 0x080, no data, or one byte counter 1..0x1019 when the
synchronous counter overflow value 0x1019 is 2..240) and python-can's frame timestamps
(``Message.timestamp``: the bus's clock; ``virtual``, ``socketcan`` and software buses stamp with
the host's wall clock, ``time.time()``).

A TPDO answers the last SYNC that went out before it. Which one that was is decided from the
frame, not from when the cycle reads it, so an adapter that hands frames over a period late does
not shift the answer:

- by timestamp (default): the latest SYNC whose bus time is not after the frame's timestamp.
  A SYNC's bus time is the wall clock read just before it was sent; once the bus delivers our
  own frames (``receive_own_messages``), the echo of each SYNC gives its time on the bus's own
  clock, and only echoed SYNCs are used from then on (adapters that stamp with a clock of their
  own are matched correctly that way);
- by SYNC counter (``counter_overflow`` 2..240): every SYNC carries its counter, and a frame
  answers the SYNC whose echo it follows in the bus's receive order. Until the first echo (a bus
  that does not deliver own frames) it falls back to timestamps.

SYNC numbers count from 1 (the first SYNC sent); 0 means "before any SYNC".

Threading: the cycle thread only; O(1) per SYNC, O(history) at worst per matched frame.
Not done: SYNC consumers (another SYNC producer on the bus is taken for our echo), the SYNC window
(0x1007 is written to the drives by the boot, not enforced here).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Final

import can

from drives.objects import SYNC_COB_ID

#: CiA 301 range of 0x1019 values that put a counter into the SYNC.
SYNC_COUNTER_MIN: Final[int] = 2
SYNC_COUNTER_MAX: Final[int] = 240


class SyncProducer:
    """Sends the SYNC of each period and tells which SYNC a received frame answered.

    :param send: sends one frame on the bus (never blocks).
    :param history: SYNCs remembered for matching; older answers count as that old.
    :param counter_overflow: 0 for SYNC without data, else 2..240 (the drives' 0x1019).
    :param wall_clock: the clock the bus stamps frames with when it has none of its own.
    :raises ValueError: on a counter overflow outside 0 and 2..240, or history < 2.
    """

    def __init__(
        self,
        send: Callable[[can.Message], None],
        *,
        history: int,
        counter_overflow: int = 0,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        if counter_overflow and not SYNC_COUNTER_MIN <= counter_overflow <= SYNC_COUNTER_MAX:
            raise ValueError(
                f"SYNC counter overflow {counter_overflow}: must be 0 or "
                f"{SYNC_COUNTER_MIN}..{SYNC_COUNTER_MAX}"
            )
        if history < 2:
            raise ValueError(f"SYNC history {history}: must be >= 2")
        self._send = send
        self._wall_clock = wall_clock
        self.counter_overflow = counter_overflow
        self.history = history
        self.sent = 0
        """SYNCs sent so far (the number of the last one)."""
        self._sent_stamps = [-math.inf] * history
        self._echo_stamps = [math.inf] * history
        self._echoed = 0
        self._echo_order_number = 0
        self._last_echo_bus_s = 0.0
        self._last_echo_sent_s = 0.0
        self._message = can.Message(
            arbitration_id=SYNC_COB_ID,
            is_extended_id=False,
            data=bytearray(1 if counter_overflow else 0),
        )

    @property
    def echoes_seen(self) -> bool:
        """Whether the bus delivers our own SYNCs back to us."""
        return self._echoed > 0

    def counter(self, number: int) -> int:
        """The counter byte SYNC ``number`` carries (1, 2, ..., overflow, 1, ...)."""
        return (number - 1) % self.counter_overflow + 1

    def transmit(self) -> None:
        """Send the next SYNC (with its counter when configured) and note its time."""
        self._send(self.next_message())

    def next_message(self) -> can.Message:
        """The next SYNC, counted and timed as sent now: the caller sends it at once (with
        other frames, on a bus that takes several in one call)."""
        number = self.sent + 1
        slot = number % self.history
        self._echo_stamps[slot] = math.inf
        if self.counter_overflow:
            self._message.data[0] = self.counter(number)
        self._sent_stamps[slot] = self._wall_clock()
        self.sent = number
        return self._message

    def on_echo(self, message: can.Message) -> None:
        """Our own SYNC received back from the bus: note its bus time (and its place in the
        receive order, for counter matching)."""
        if self.counter_overflow and len(message.data) == 1:
            number = self.sent
            counter = message.data[0]
            while number > self._echoed and self.counter(number) != counter:
                number -= 1
            if number <= self._echoed:
                return  # not one of ours, or already seen
        else:
            number = self._echo_number_by_interval(message.timestamp)
            if number is None:
                return
        self._echoed = number
        self._last_echo_bus_s = message.timestamp
        self._last_echo_sent_s = self._sent_stamps[number % self.history]
        self._echo_order_number = number
        self._echo_stamps[number % self.history] = message.timestamp

    def _echo_number_by_interval(self, bus_s: float) -> int | None:
        """Which SYNC an echo without counter is: the next one unless echoes were lost (a
        receive queue that overflowed during a stall), then the one whose send time lies as far
        after the last echoed SYNC's as the echo's bus time after that echo's. Counting alone
        would shift every later match by each lost echo for good."""
        first = self._echoed + 1
        if first > self.sent:
            return None
        if not self._echoed or first == self.sent:
            return first
        bus_interval_s = bus_s - self._last_echo_bus_s
        oldest = max(first, self.sent - self.history + 1)
        return min(
            range(oldest, self.sent + 1),
            key=lambda n: abs(
                self._sent_stamps[n % self.history] - self._last_echo_sent_s - bus_interval_s
            ),
        )

    def answered(self, timestamp: float) -> int:
        """The number of the SYNC that a frame received with ``timestamp`` answered; 0 when it
        is older than every SYNC remembered."""
        if self.counter_overflow and self._echoed:
            return self._echo_order_number
        stamps = self._echo_stamps if self._echoed else self._sent_stamps
        history = self.history
        number = self.sent
        oldest = max(1, number - history + 1)
        while number >= oldest:
            if stamps[number % history] <= timestamp:
                return number
            number -= 1
        return 0
