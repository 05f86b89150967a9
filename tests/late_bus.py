"""A CAN bus wrapper that hands received frames over a period late, timestamps unchanged.

Models a USB CAN adapter that batches its receive path: the cycle reads each frame one period
later than on a direct bus, while the frame's ``timestamp`` still says when it was on the wire.
A period is counted in SYNCs sent through the wrapper: a frame received after the SYNC of
period k, which the cycle would read at period k + 1, is handed over at period k + 2 (once two
SYNCs went out after its timestamp). Frames keep their order. Sending is not delayed.
"""

from __future__ import annotations

import time
from collections import deque

import can

from drives.objects import SYNC_COB_ID


class LateDeliveryBus:
    """Wraps ``bus`` for the master.

    :param wall_clock: the clock the bus stamps frames with (``time.time`` for python-can's
        software buses and SocketCAN).
    """

    def __init__(self, bus: can.BusABC, wall_clock=time.time) -> None:
        self.bus = bus
        self.wall_clock = wall_clock
        self._held: deque[can.Message] = deque()
        self._syncs_s: deque[float] = deque([float("-inf")] * 2, maxlen=2)

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        if message.arbitration_id == SYNC_COB_ID:
            self._syncs_s.append(self.wall_clock())
        self.bus.send(message, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        while (message := self.bus.recv(0.0)) is not None:
            self._held.append(message)
        if self._held and self._held[0].timestamp < self._syncs_s[0]:
            return self._held.popleft()
        return None

    def shutdown(self) -> None:
        self.bus.shutdown()
