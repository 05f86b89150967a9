"""The HMI's Modbus TCP server: asyncio connections that frame the byte stream, answer every
request in order, and serve the registers of :class:`runtime.hmi.device.HmiDevice`.

Why not pymodbus's server (3.16.1, pinned; the client side still uses pymodbus): its request
handler keeps one request per connection, so pipelined requests (several in one TCP segment, or
a frame split across segments after another) lose all but one; its framer waits forever after a
bad MBAP header, so the connection is wedged; requests it cannot decode answer function code 0
with exception 1. This module replaces its framer and request handler (:mod:`.protocol`).

Per connection:

- bytes are appended to a buffer; every complete frame is answered, in order, however the
  frames were cut into segments; responses produced together are written together;
- a malformed MBAP header (protocol id other than 0, length 0, 1 or above 254) or a frame left
  incomplete for :attr:`HmiServer.frame_timeout_s` closes the connection, after the frames
  before it are answered, with a warning naming the peer;
- a request whose answer must wait (a curve commit) holds back the ones after it on that
  connection, so answers stay in order; other connections go on meanwhile;
- reading pauses while the peer does not read its answers (transport flow control) or while
  :data:`MAX_QUEUED_FRAMES` requests wait.

Access: binds to ``config.bind``; a connection from outside ``config.allowed_networks`` is
closed as soon as it is accepted; unit ids other than ``config.unit_id``, 0 and 255 answer
exception 11.

Threading: :class:`HmiServer` runs its event loop in a thread of its own (:meth:`HmiServer.start`
returns once it listens) or, through :func:`serve_hmi`, in the calling thread (the HMI
process's main thread). The link's methods are called from the loop thread only.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import signal
import threading
from collections import deque
from collections.abc import Awaitable

from runtime.config import ModbusConfig
from runtime.hmi import HmiError
from runtime.hmi.device import HmiDevice
from runtime.hmi.link import MachineLink
from runtime.hmi.protocol import (
    DeviceIdentity,
    ExceptionCode,
    Frame,
    answer,
    exception_pdu,
    frame_bytes,
    read_frames,
)
from runtime.hmi.staging import Peer
from runtime.version import VERSION

log = logging.getLogger(__name__)

#: Unit ids answered besides the configured one (libmodbus and many HMIs send 255 over TCP).
EXTRA_UNIT_IDS = (0, 255)
#: Requests read ahead of their answers on one connection before reading pauses.
MAX_QUEUED_FRAMES = 64
#: What FC17 and FC43/14 report.
IDENTITY = DeviceIdentity(vendor_name="softmotion", product_code="softmotion", revision=VERSION)


class _Connection(asyncio.Protocol):
    """One client connection."""

    def __init__(self, server: HmiServer) -> None:
        self._server = server
        self._transport: asyncio.Transport | None = None
        self.peer = Peer("", 0)
        self._buffer = bytearray()
        self._queue: deque[Frame] = deque()
        self._waiting: asyncio.Task[None] | None = None
        """The answer being awaited (a commit); later frames wait for it."""
        self._write_paused = False
        self._read_paused = False
        self._close_reason: str | None = None
        self._incomplete: asyncio.TimerHandle | None = None

    # -- asyncio callbacks --------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport
        peer = transport.get_extra_info("peername") or ("", 0)
        self.peer = Peer(str(peer[0]), int(peer[1]))
        if not self._server.allows(self.peer.host):
            log.warning("modbus: refused connection from %s (not in allowed_networks)", self.peer)
            transport.close()
            return
        self._server.connections.add(self)
        log.debug("modbus: %s connected", self.peer)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._incomplete is not None:
            self._incomplete.cancel()
        if self in self._server.connections:
            self._server.connections.discard(self)
            self._server.device.disconnected(self.peer)
            log.debug("modbus: %s disconnected (%s)", self.peer, exc or "closed")

    def data_received(self, data: bytes) -> None:
        if self._close_reason is not None:
            return
        self._buffer += data
        frames, used, error = read_frames(self._buffer)
        del self._buffer[:used]
        self._queue.extend(frames)
        if error is not None:
            self._close_after_answers(f"{error}")
        else:
            self._watch_incomplete(progress=used > 0)
        self._process()

    def pause_writing(self) -> None:
        self._write_paused = True

    def resume_writing(self) -> None:
        self._write_paused = False
        self._process()

    # -- frames -------------------------------------------------------------------------------

    def _watch_incomplete(self, *, progress: bool) -> None:
        """Time an incomplete frame from when the last complete one ended."""
        if self._incomplete is not None and (progress or not self._buffer):
            self._incomplete.cancel()
            self._incomplete = None
        if self._buffer and self._incomplete is None:
            self._incomplete = asyncio.get_running_loop().call_later(
                self._server.frame_timeout_s, self._incomplete_timed_out
            )

    def _incomplete_timed_out(self) -> None:
        self._incomplete = None
        self._close_after_answers(
            f"incomplete frame ({len(self._buffer)} bytes) for {self._server.frame_timeout_s:g} s"
        )
        self._process()

    def _close_after_answers(self, reason: str) -> None:
        self._close_reason = reason
        self._buffer.clear()
        log.warning("modbus: %s: %s; closing the connection", self.peer, reason)

    def _process(self) -> None:
        """Answer queued frames in order until one must wait, then write the answers at once."""
        transport = self._transport
        if transport is None or transport.is_closing():
            return
        replies: list[bytes] = []
        while self._queue and self._waiting is None and not self._write_paused:
            frame = self._queue.popleft()
            pdu = self._answer(frame)
            if isinstance(pdu, bytes):
                replies.append(frame_bytes(frame.transaction_id, frame.unit_id, pdu))
            else:
                self._waiting = asyncio.get_running_loop().create_task(
                    self._answer_later(frame, pdu)
                )
        if replies:
            transport.write(b"".join(replies))
        idle = not self._queue and self._waiting is None
        if self._close_reason is not None and idle:
            transport.close()
            return
        self._flow(len(self._queue) >= MAX_QUEUED_FRAMES or self._write_paused)

    def _flow(self, pause: bool) -> None:
        assert self._transport is not None
        if pause and not self._read_paused:
            self._transport.pause_reading()
        elif not pause and self._read_paused:
            self._transport.resume_reading()
        self._read_paused = pause

    def _answer(self, frame: Frame) -> bytes | Awaitable[bytes]:
        function_code = frame.pdu[0]
        if frame.unit_id not in self._server.unit_ids:
            return exception_pdu(function_code, ExceptionCode.GATEWAY_TARGET_FAILED)
        try:
            return answer(frame.pdu, self._server.device, IDENTITY, self.peer)
        except Exception:  # a bug: answer 4 rather than lose the connection's order
            log.exception("modbus: %s: request %s failed", self.peer, frame.pdu.hex(" "))
            return exception_pdu(function_code, ExceptionCode.SERVER_DEVICE_FAILURE)

    async def _answer_later(self, frame: Frame, pending: Awaitable[bytes]) -> None:
        try:
            pdu = await pending
        except Exception:  # a bug: answer 4 rather than lose the connection's order
            log.exception("modbus: %s: request %s failed", self.peer, frame.pdu.hex(" "))
            pdu = exception_pdu(frame.pdu[0], ExceptionCode.SERVER_DEVICE_FAILURE)
        self._waiting = None
        transport = self._transport
        if transport is not None and not transport.is_closing():
            transport.write(frame_bytes(frame.transaction_id, frame.unit_id, pdu))
        self._process()

    def close(self) -> None:
        """Close the connection (server shutdown)."""
        if self._transport is not None:
            self._transport.close()


class HmiServer:
    """The HMI's Modbus TCP server for one machine.

    :param link: the machine.
    :param config: the ``modbus`` section of the machine description.
    :param start_timeout_s: how long :meth:`start` waits for the server to listen.
    """

    #: Seconds an incomplete frame may wait for its remaining bytes before the connection is
    #: closed (a cut header cannot be told from a slow one sooner).
    frame_timeout_s = 1.0

    def __init__(
        self, link: MachineLink, config: ModbusConfig, *, start_timeout_s: float = 5.0
    ) -> None:
        self.config = config
        self.link = link
        self.device = HmiDevice(link, config)
        self.unit_ids = frozenset({config.unit_id, *EXTRA_UNIT_IDS})
        self.connections: set[_Connection] = set()
        self._networks = [ipaddress.ip_network(n, strict=False) for n in config.allowed_networks]
        self._settle_period_s = link.config.cycle.period_s
        self._start_timeout_s = start_timeout_s
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._port = 0

    @property
    def port(self) -> int:
        """The TCP port the server listens on (resolves port 0 to the one chosen)."""
        return self._port

    def allows(self, host: str) -> bool:
        """Whether a peer at ``host`` may connect."""
        try:
            address = ipaddress.ip_address(host)
        except ValueError:
            return False
        if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
            address = address.ipv4_mapped
        return any(address in network for network in self._networks)

    # -- in a thread of its own ---------------------------------------------------------------

    def start(self) -> None:
        """Start the server thread and return once it listens.

        :raises HmiError: if it cannot listen (address in use, bad bind address) in time.
        """
        if self._thread is not None:
            raise HmiError("modbus: server already started")
        self._thread = threading.Thread(target=self._run_thread, name="hmi-modbus", daemon=True)
        self._thread.start()
        where = f"{self.config.bind}:{self.config.port}"
        if not self._ready.wait(self._start_timeout_s):
            raise HmiError(f"modbus: server on {where} did not start in {self._start_timeout_s} s")
        if self._error is not None:
            self._thread.join(self._start_timeout_s)
            self._thread = None
            raise HmiError(f"modbus: cannot listen on {where}: {self._error}")

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close every connection, stop the server and join its thread (idempotent)."""
        thread, loop, stopping = self._thread, self._loop, self._stopping
        if thread is None or loop is None or stopping is None:
            return
        if thread.is_alive():
            loop.call_soon_threadsafe(stopping.set)
            thread.join(timeout_s)
        self._thread = None

    def __enter__(self) -> HmiServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run_thread(self) -> None:
        try:
            asyncio.run(self.serve())
        except BaseException as exc:  # reported to start(); the thread must not die silently
            self._error = exc
            self._ready.set()

    # -- the server ---------------------------------------------------------------------------

    async def serve(self, *, stop_signals: bool = False) -> None:
        """Serve until :meth:`stop` (or, with ``stop_signals``, SIGTERM or SIGINT)."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._stopping = asyncio.Event()
        if stop_signals:
            for signum in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(signum, self._stopping.set)
        server = await loop.create_server(
            lambda: _Connection(self), host=self.config.bind, port=self.config.port
        )
        self._port = server.sockets[0].getsockname()[1]
        settle = loop.create_task(self._settle())
        await self.device.list_library()
        log.info(
            "modbus: serving on %s:%d (unit %d)", self.config.bind, self._port, self.config.unit_id
        )
        self._ready.set()
        try:
            await self._stopping.wait()
        finally:
            settle.cancel()
            server.close()
            for connection in list(self.connections):
                connection.close()
            with contextlib.suppress(asyncio.CancelledError):
                await settle
            await server.wait_closed()
            self.device.close()

    async def _settle(self) -> None:
        """Collect the machine's results of posted requests even when nobody reads status."""
        while True:
            await asyncio.sleep(self._settle_period_s)
            if self.device.pending:
                self.device.settle()


def serve_hmi(link: MachineLink, config: ModbusConfig) -> None:
    """Run the HMI server in the calling thread (the HMI process's main thread) until SIGTERM
    or SIGINT.

    :raises OSError: if it cannot listen on ``config.bind``:``config.port``.
    """
    asyncio.run(HmiServer(link, config).serve(stop_signals=True))
