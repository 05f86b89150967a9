"""A CAN bus wrapper that hands received frames over late, timestamps unchanged.

Models a USB CAN adapter that batches its receive path: every frame reaches the reader
``delay_s`` after it was on the wire (its ``timestamp``), while the timestamp still says when
that was. Sending is not delayed. With ``delay_s`` one cycle period, the cycle reads each TPDO
one period later than on a direct bus.
"""

from __future__ import annotations

import time
from collections import deque

import can


class LateDeliveryBus:
    """Wraps ``bus`` for the master: ``recv`` returns only frames older than ``delay_s``.

    :param wall_clock: the clock the bus stamps frames with (``time.time`` for python-can's
        software buses and SocketCAN).
    """

    def __init__(self, bus: can.BusABC, delay_s: float, wall_clock=time.time) -> None:
        self.bus = bus
        self.delay_s = delay_s
        self.wall_clock = wall_clock
        self._held: deque[can.Message] = deque()

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        self.bus.send(message, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        while (message := self.bus.recv(0.0)) is not None:
            self._held.append(message)
        if self._held and self._held[0].timestamp + self.delay_s <= self.wall_clock():
            return self._held.popleft()
        return None

    def set_filters(self, filters) -> None:
        self.bus.set_filters(filters)

    def shutdown(self) -> None:
        self.bus.shutdown()
