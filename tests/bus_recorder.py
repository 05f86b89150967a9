"""An independent listener on a CAN bus: records every frame with its timestamp, in a thread.

Used by tests and benchmarks to check what the drives actually receive (targets by RPDO, one
SYNC per period) without going through the runtime's own status.
"""

from __future__ import annotations

import struct
import threading
from dataclasses import dataclass

import numpy as np

from drives.bus import open_bus

SYNC_COB_ID = 0x80
RPDO1_BASE = 0x200
#: RPDO1 payload: controlword (U16), target position (I32), little endian.
RPDO1 = struct.Struct("<Hi")


@dataclass(frozen=True)
class Frame:
    timestamp_s: float
    can_id: int
    data: bytes


class BusRecorder:
    """Records every frame on ``channel`` of ``interface`` until :meth:`close`."""

    def __init__(self, interface: str, channel: str) -> None:
        self._bus = open_bus(interface, channel)
        self.frames: list[Frame] = []
        self._running = True
        self._thread = threading.Thread(target=self._read, name="bus-recorder", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while self._running:
            message = self._bus.recv(0.05)
            if message is not None:
                self.frames.append(
                    Frame(message.timestamp, message.arbitration_id, bytes(message.data or b""))
                )

    def close(self) -> None:
        self._running = False
        self._thread.join(2.0)
        self._bus.shutdown()

    def __enter__(self) -> BusRecorder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def sync_times_s(self) -> np.ndarray:
        return np.array([f.timestamp_s for f in list(self.frames) if f.can_id == SYNC_COB_ID])

    def targets_counts(self, node_ids: tuple[int, ...]) -> np.ndarray:
        """(SYNCs, axes) target positions latched at each SYNC: the last RPDO1 of each node
        before it (rows before every node has sent one are dropped)."""
        last: dict[int, int] = {}
        rows = []
        for frame in list(self.frames):
            if frame.can_id == SYNC_COB_ID:
                if len(last) == len(node_ids):
                    rows.append([last[n] for n in node_ids])
            elif frame.can_id - RPDO1_BASE in node_ids and len(frame.data) == RPDO1.size:
                last[frame.can_id - RPDO1_BASE] = RPDO1.unpack(frame.data)[1]
        return np.array(rows, dtype=np.int64)
