"""An independent recorder of the frames on a SocketCAN interface, for the vcan tests.

It reads a raw ``AF_CAN`` socket with the standard ``socket`` module only (no python-can, no
canopen), so what it records is what the kernel carried, not what the code under test believes it
sent. A background thread stores every classic CAN frame with the kernel's receive time.

Source: Linux SocketCAN (``Documentation/networking/can.rst``): ``struct can_frame`` is 16 bytes
(``can_id`` u32 with the EFF/RTR/ERR flags in its top bits, ``len`` u8, 3 padding bytes, 8 data
bytes); ``CAN_RAW_FILTER`` takes ``struct can_filter`` pairs (id, mask); ``SO_TIMESTAMPNS`` adds
a ``struct timespec`` receive time; ``SO_RXQ_OVFL`` adds the socket's running drop count.

Units: ``timestamp_ns`` is the kernel's receive time on ``CLOCK_REALTIME`` in nanoseconds, the
same clock as ``time.time_ns()``; timeouts are in seconds.

Threading: one reader thread per listener; every public method may be called from any thread.

Invariants: the socket is bound before ``start()`` returns, so every frame sent after that is
recorded; frames are kept in receive order; a frame the socket had to drop is counted in
``dropped``, never silently lost.

Not modelled: CAN FD frames and error frames (the socket receives neither), sending.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from types import TracebackType

#: ``struct can_frame``: can_id, len, 3 padding bytes, 8 data bytes.
_CAN_FRAME = struct.Struct("=IB3x8s")
#: ``struct can_filter``: can_id, can_mask.
_CAN_FILTER = struct.Struct("=II")
#: ``struct timespec`` on 64-bit Linux: seconds, nanoseconds.
_TIMESPEC = struct.Struct("=qq")
#: ``SO_RXQ_OVFL`` ancillary data: the socket's drop counter (u32).
_DROP_COUNT = struct.Struct("=I")

_CAN_EFF_FLAG = 0x80000000
_CAN_RTR_FLAG = 0x40000000
_CAN_EFF_MASK = 0x1FFFFFFF
_CAN_SFF_MASK = 0x000007FF

# From <asm-generic/socket.h>; the socket module does not name them.
_SO_TIMESTAMPNS = 35
_SO_RXQ_OVFL = 40

#: How often the reader thread looks at its stop flag.
_POLL_S = 0.05
#: Receive buffer asked for, so that bursts are not dropped while the reader thread waits.
_RCVBUF_BYTES = 1 << 20


@dataclass(frozen=True)
class RecordedFrame:
    """One classic CAN frame as the kernel delivered it.

    :ivar timestamp_ns: kernel receive time, ``CLOCK_REALTIME`` ns (as ``time.time_ns()``).
    :ivar can_id: the 11-bit (or 29-bit when ``is_extended``) identifier, flags removed.
    :ivar data: the payload, ``len`` bytes (empty for a remote frame).
    :ivar is_extended: 29-bit identifier.
    :ivar is_remote: remote transmission request (RTR) frame.
    """

    timestamp_ns: int
    can_id: int
    data: bytes
    is_extended: bool = False
    is_remote: bool = False


class CanListener:
    """Records every frame on a SocketCAN interface from a background thread.

    Use as a context manager, or call ``start()`` and ``stop()``::

        with CanListener("vcan0") as listener:
            ...  # make the code under test send
            sync = listener.wait_for_count(0x80, 10, timeout_s=2.0)
    """

    def __init__(self, channel: str = "vcan0", cob_ids: Iterable[int] | None = None) -> None:
        """Prepare a listener; nothing is opened until ``start()``.

        :param channel: the SocketCAN interface name.
        :param cob_ids: if given, only frames (data or remote) with these 11-bit identifiers
            are recorded, by a kernel filter; by default every frame is.
        """
        self.channel = channel
        self._cob_ids = None if cob_ids is None else tuple(cob_ids)
        self._frames: list[RecordedFrame] = []
        self._dropped = 0
        self._changed = threading.Condition()
        self._stopping = threading.Event()
        self._socket: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def start(self) -> CanListener:
        """Open and bind the raw socket, then start the reader thread.

        :raises OSError: if the interface does not exist or the kernel has no CAN support.
        :raises RuntimeError: if the listener is already running.
        """
        if self._socket is not None:
            raise RuntimeError(f"listener on {self.channel} is already running")
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        try:
            if self._cob_ids is not None:
                filters = b"".join(
                    _CAN_FILTER.pack(cob_id, _CAN_EFF_FLAG | _CAN_SFF_MASK)
                    for cob_id in self._cob_ids
                )
                sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, filters)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF_BYTES)
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
            sock.settimeout(_POLL_S)
            sock.bind((self.channel,))
        except BaseException:
            sock.close()
            raise
        self._socket = sock
        self._stopping.clear()
        self._thread = threading.Thread(
            target=self._read_loop, name=f"canlisten-{self.channel}", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the reader thread and close the socket; the recorded frames stay readable.

        :raises RuntimeError: if the reader thread had failed (its error is the cause).
        """
        if self._thread is not None:
            self._stopping.set()
            self._thread.join()
            self._thread = None
        if self._socket is not None:
            self._socket.close()
            self._socket = None
        if self._error is not None:
            raise RuntimeError(f"listener on {self.channel} failed") from self._error

    def __enter__(self) -> CanListener:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    @property
    def dropped(self) -> int:
        """Frames the kernel dropped because this socket's receive queue was full."""
        with self._changed:
            return self._dropped

    def frames(self) -> list[RecordedFrame]:
        """Every frame recorded so far, in receive order."""
        with self._changed:
            return list(self._frames)

    def frames_with_id(self, cob_id: int) -> list[RecordedFrame]:
        """The recorded frames whose identifier is ``cob_id``, in receive order."""
        return self.frames_matching(lambda frame: frame.can_id == cob_id)

    def frames_matching(self, predicate: Callable[[RecordedFrame], bool]) -> list[RecordedFrame]:
        """The recorded frames for which ``predicate`` is true, in receive order."""
        with self._changed:
            return [frame for frame in self._frames if predicate(frame)]

    def clear(self) -> None:
        """Forget the frames recorded so far (the drop count stays)."""
        with self._changed:
            self._frames.clear()

    def wait_for_count(self, cob_id: int, count: int, timeout_s: float) -> list[RecordedFrame]:
        """Wait until at least ``count`` frames with identifier ``cob_id`` were recorded.

        :returns: all recorded frames with that identifier (``count`` or more).
        :raises TimeoutError: naming the identifier and how many arrived, after ``timeout_s``.
        """
        return self.wait_for(lambda frame: frame.can_id == cob_id, count, timeout_s, f"{cob_id:#x}")

    def wait_for(
        self,
        predicate: Callable[[RecordedFrame], bool],
        count: int,
        timeout_s: float,
        description: str = "matching",
    ) -> list[RecordedFrame]:
        """Wait until at least ``count`` recorded frames satisfy ``predicate``.

        :returns: all recorded frames that satisfy it.
        :raises TimeoutError: naming ``description`` and how many arrived, after ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                matching = [frame for frame in self._frames if predicate(frame)]
                remaining_s = deadline - time.monotonic()
                if len(matching) >= count or remaining_s <= 0 or self._error is not None:
                    break
                self._changed.wait(remaining_s)
        if len(matching) < count:
            raise TimeoutError(
                f"{self.channel}: {len(matching)} of {count} {description} frames "
                f"within {timeout_s:g} s ({self.dropped} dropped by the socket)"
            )
        return matching

    def _read_loop(self) -> None:
        assert self._socket is not None
        ancillary_size = socket.CMSG_SPACE(_TIMESPEC.size) + socket.CMSG_SPACE(_DROP_COUNT.size)
        try:
            while not self._stopping.is_set():
                try:
                    raw, ancillary, _flags, _address = self._socket.recvmsg(
                        _CAN_FRAME.size, ancillary_size
                    )
                except TimeoutError:
                    continue
                self._record(raw, ancillary)
        except BaseException as exc:
            with self._changed:
                self._error = exc
                self._changed.notify_all()

    def _record(self, raw: bytes, ancillary: list[tuple[int, int, bytes]]) -> None:
        timestamp_ns = time.time_ns()
        dropped = None
        for level, kind, payload in ancillary:
            if level != socket.SOL_SOCKET:
                continue
            if kind == _SO_TIMESTAMPNS:
                seconds, nanoseconds = _TIMESPEC.unpack(payload[: _TIMESPEC.size])
                timestamp_ns = seconds * 1_000_000_000 + nanoseconds
            elif kind == _SO_RXQ_OVFL:
                (dropped,) = _DROP_COUNT.unpack(payload[: _DROP_COUNT.size])
        raw_id, length, payload = _CAN_FRAME.unpack(raw)
        is_extended = bool(raw_id & _CAN_EFF_FLAG)
        is_remote = bool(raw_id & _CAN_RTR_FLAG)
        frame = RecordedFrame(
            timestamp_ns=timestamp_ns,
            can_id=raw_id & (_CAN_EFF_MASK if is_extended else _CAN_SFF_MASK),
            data=b"" if is_remote else payload[:length],
            is_extended=is_extended,
            is_remote=is_remote,
        )
        with self._changed:
            self._frames.append(frame)
            if dropped is not None:
                self._dropped = dropped
            self._changed.notify_all()
