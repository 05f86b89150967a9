"""``local``: a software CAN bus between the processes of one host (python-can interface).

python-can's ``virtual`` bus connects buses inside one process; the runtime's cycle process and
the simulated drives are separate processes, and a host without kernel CAN has no ``vcan0``.
Every :class:`LocalBus` creates a named pipe (FIFO) in a directory per channel (under
``/dev/shm``, else the temporary directory) and writes each frame it sends into the pipe of every
other bus there: every bus on a channel receives every frame any other bus sends, in the order
each sender sent them, like nodes on one CAN segment. A frame is one fixed-size write, far below
``PIPE_BUF``, so writes from several senders never interleave; a pipe holds about 40,000 frames
(``F_SETPIPE_SZ`` of 1 MiB), so a receiver held up for a while loses nothing. (Unix datagram
sockets were the first choice, but their queue is ``net.unix.max_dgram_qlen`` datagrams: 10
unless the host raised it.)

Frames carry the time the sender handed them to the bus (``time.time()``, as the timestamps of
python-can's SocketCAN and virtual buses), standing for the time the frame was on the wire:
a receiver that reads late still sees when the frame was sent. With ``receive_own_messages``
a bus also receives its own frames (``is_rx`` False, as python-can marks them), through its pipe,
in order with the others. :meth:`LocalBus.send_frames` sends several frames in one write per
receiver: the cycle hands a period's RPDOs and its SYNC over at once. With ``preserve_timestamps``
(as python-can's virtual bus has it) a frame keeps the timestamp its message carries: simulated
hardware stamps its answers with when a real device would have put them on the wire, however
late its process got to send them.

Units: seconds (timestamps). Threading: one bus per thread, like python-can's buses; ``recv``
blocks at most its timeout, ``send`` never blocks.

Not modelled (as with ``virtual``): arbitration, bit timing and bus load, error frames. A frame
that finds a receiver's pipe full is dropped for that receiver and counted in
:attr:`LocalBus.frames_dropped` (a controller overrun); a receiver that is gone is forgotten.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import itertools
import os
import select
import struct
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can

#: timestamp (s), arbitration id, DLC, flags, data.
FRAME = struct.Struct("<dIBB8s")
_EXTENDED, _REMOTE, _ERROR, _OWN = 1, 2, 4, 8
#: Frames one write may carry (a pipe write of up to PIPE_BUF bytes is never interleaved).
MAX_FRAMES_PER_WRITE = select.PIPE_BUF // FRAME.size
_SEQUENCE = itertools.count(1)
#: fcntl command to resize a pipe (Linux; missing from Python's fcntl before 3.10's constants).
F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)
PIPE_BYTES = 1 << 20
#: Longest time before a bus sends to a bus that joined the channel [s].
PEER_CHECK_S = 0.02


def channel_directory(channel: str) -> Path:
    """Where the sockets of ``channel`` live (created on first use)."""
    base = Path("/dev/shm") if Path("/dev/shm").is_dir() else Path(tempfile.gettempdir())
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in channel)
    directory = base / f"softmotion-can-{os.getuid()}" / safe
    directory.mkdir(parents=True, exist_ok=True, mode=0o700)
    return directory


class LocalBus(can.BusABC):
    """A python-can bus whose frames reach every other :class:`LocalBus` of ``channel`` on
    this host.

    :param channel: the bus name; buses with the same name are connected.
    :param receive_own_messages: also receive the frames this bus sends.
    :param preserve_timestamps: send a message's own timestamp instead of the time of sending
        (a message without one, 0, still gets the time of sending).
    :param can_filters: python-can filters (applied in software).
    """

    def __init__(
        self,
        channel: str = "softmotion",
        receive_own_messages: bool = False,
        preserve_timestamps: bool = False,
        can_filters: can.typechecking.CanFilters | None = None,
        **kwargs: Any,
    ) -> None:
        self.channel = str(channel)
        self.channel_info = f"local bus {channel}"
        name = f"{os.getpid()}-{next(_SEQUENCE)}"
        while True:
            self._directory = channel_directory(self.channel)
            self._address = str(self._directory / name)
            try:
                os.mkfifo(self._address, 0o600)
                break
            except FileNotFoundError:
                continue  # the channel's last bus removed the directory just now
        # Read and write: the pipe never reports end-of-file while no other bus writes to it.
        self._fifo = os.open(self._address, os.O_RDWR | os.O_NONBLOCK)
        _enlarge(self._fifo)
        self._own = receive_own_messages
        self._preserve_timestamps = preserve_timestamps
        self._writers: dict[str, int] = {}
        self._peers: list[str] = []
        self._peers_stamp = -1
        self._next_peer_check_s = 0.0
        self.frames_dropped = 0
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)

    def fileno(self) -> int:
        return self._fifo

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` to every other bus on the channel (never blocks)."""
        self.send_frames((msg,))

    def send_frames(self, messages: Sequence[can.Message]) -> None:
        """Send ``messages`` back to back, one write per receiving bus (never blocks).

        At most :data:`MAX_FRAMES_PER_WRITE` at once: one write stays atomic in a pipe. A
        receiver whose pipe has no room for them all loses them all (counted per frame).

        :raises ValueError: for more than :data:`MAX_FRAMES_PER_WRITE` frames.
        """
        if len(messages) > MAX_FRAMES_PER_WRITE:
            raise ValueError(f"{len(messages)} frames, at most {MAX_FRAMES_PER_WRITE} at once")
        now = time.time()
        stamps = [
            message.timestamp if self._preserve_timestamps and message.timestamp else now
            for message in messages
        ]
        frames = b"".join(_pack(m, stamp, 0) for m, stamp in zip(messages, stamps, strict=True))
        own = (
            b"".join(_pack(m, stamp, _OWN) for m, stamp in zip(messages, stamps, strict=True))
            if self._own
            else b""
        )
        self._refresh_peers()
        for peer in self._peers:
            if peer == self._address:
                if own:
                    self._write(self._fifo, own, len(messages))
                continue
            fd = self._writers.get(peer)
            if fd is None:
                fd = self._open_peer(peer)
                if fd is None:
                    continue
            try:
                self._write(fd, frames, len(messages))
            except BrokenPipeError:
                self._forget(peer)

    def _write(self, fd: int, frames: bytes, count: int) -> None:
        try:
            os.write(fd, frames)
        except BlockingIOError:
            self.frames_dropped += count

    def _open_peer(self, peer: str) -> int | None:
        try:
            fd = os.open(peer, os.O_WRONLY | os.O_NONBLOCK)
        except FileNotFoundError:
            return None
        except OSError as exc:
            if exc.errno != errno.ENXIO:  # no reader: its process is gone
                raise
            self._forget(peer)
            return None
        self._writers[peer] = fd
        return fd

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            frame = os.read(self._fifo, FRAME.size)
        except BlockingIOError:
            if timeout == 0:
                return None, False
            ready, _, _ = select.select([self._fifo], [], [], timeout)
            if not ready:
                return None, False
            frame = os.read(self._fifo, FRAME.size)
        timestamp, arbitration_id, dlc, flags, data = FRAME.unpack(frame)
        message = can.Message(
            timestamp=timestamp,
            arbitration_id=arbitration_id,
            is_extended_id=bool(flags & _EXTENDED),
            is_remote_frame=bool(flags & _REMOTE),
            is_error_frame=bool(flags & _ERROR),
            is_rx=not flags & _OWN,
            dlc=dlc,
            data=None if flags & _REMOTE else data[: min(dlc, 8)],
            channel=self.channel,
        )
        return message, False

    def shutdown(self) -> None:
        """Close the pipes and remove this bus's."""
        super().shutdown()
        for fd in self._writers.values():
            os.close(fd)
        self._writers.clear()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._address)
        os.close(self._fifo)
        with contextlib.suppress(OSError):
            self._directory.rmdir()  # the channel's last bus

    def _refresh_peers(self) -> None:
        # Creating or removing a pipe changes the directory's mtime: list it again only then,
        # and look at the mtime at most every PEER_CHECK_S (a joining bus, like a node powering
        # up, misses what is sent before it is seen).
        now_s = time.monotonic()
        if now_s < self._next_peer_check_s:
            return
        self._next_peer_check_s = now_s + PEER_CHECK_S
        stamp = os.stat(self._directory).st_mtime_ns
        if stamp == self._peers_stamp:
            return
        self._peers_stamp = stamp
        self._peers = sorted(entry.path for entry in os.scandir(self._directory))
        for gone in set(self._writers) - set(self._peers):
            os.close(self._writers.pop(gone))

    def _forget(self, peer: str) -> None:
        """A pipe whose bus is gone (its process ended without removing it)."""
        fd = self._writers.pop(peer, None)
        if fd is not None:
            os.close(fd)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(peer)
        self._peers = [p for p in self._peers if p != peer]


def _pack(message: can.Message, stamp: float, own: int) -> bytes:
    flags = (
        (_EXTENDED if message.is_extended_id else 0)
        | (_REMOTE if message.is_remote_frame else 0)
        | (_ERROR if message.is_error_frame else 0)
        | own
    )
    data = bytes(message.data or b"")[:8]
    return FRAME.pack(stamp, message.arbitration_id, message.dlc, flags, data)


def _enlarge(fd: int) -> None:
    """Give the pipe the largest buffer an unprivileged process may (fs.pipe-max-size)."""
    # Refused (a lower limit): the default 64 KiB still holds about 2,900 frames.
    with contextlib.suppress(OSError):
        fcntl.fcntl(fd, F_SETPIPE_SZ, PIPE_BYTES)
