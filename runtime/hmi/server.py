"""The Modbus TCP server of the HMI: pymodbus 3.16 in its own thread and event loop.

The only module that imports the pymodbus server (reference/modbus-hmi.md §1-3). One
``SimDevice`` with separate holding and input blocks laid out by :mod:`runtime.hmi.registers`;
its action hook does all the work, on the server's loop thread:

- FC4 reads ("pull on read"): the latest :meth:`MachineLink.snapshot` is encoded once into the
  input image (cached per snapshot object, so many clients cost one encoding per cycle at most)
  and the requested registers are copied from that image: a read never mixes two snapshots.
- Holding writes are validated before pymodbus applies them: a write that starts or ends inside
  a 32-bit value, or carries a value above a field's maximum (override > 150.0 %, unknown
  command code), answers exception 3; addresses outside the map answer exception 2 (pymodbus
  checks that before the action). A write that changes ``COMMAND_SEQ`` runs ``COMMAND_CODE``
  once through :meth:`MachineLink.submit`, which queues it for the start of the next cycle; a
  refusal answers exception 6 (state, no curve, drives not ready) or 3 (invalid parameter) and
  the write is not applied. ``LOAD_CURVE`` is the curve commit: the staged curve is decoded,
  validated and prepared in a worker thread (not on the cycle), then submitted; a bad curve
  answers exception 3 with its code in ``UPLOAD_RESULT``. The server's own judgement of the last
  command and commit is published in ``REQUEST_*`` and ``UPLOAD_*``.
- Coils and discrete inputs do not exist: exception 2.

Access: binds to ``config.bind``; connections from peers outside ``config.allowed_networks`` are
closed as soon as they are accepted; requests to unit ids other than ``config.unit_id``, 0 and
255 answer exception 0x0B (gateway target failed to respond); ``read_only`` marks every holding
register read-only, so every write answers exception 2.

HMI link watchdog (``config.watchdog.timeout_ms`` > 0, not read-only): a change of
``HMI_HEARTBEAT`` or an accepted command restarts the timer; when it runs out while the machine
is MOVING, ``HOLD`` (or ``STOP``) is submitted once with origin ``"hmi watchdog"``.

Threading: :meth:`HmiServer.start` returns once the server listens; every callback runs on the
server thread; the link must tolerate ``snapshot``/``submit`` from that thread and
``prepare_curve`` from a worker thread.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Protocol

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from planner.errors import CurveError
from planner.nurbs import NurbsCurve
from runtime.commands import Command, CommandCode, CommandResult, check_allowed
from runtime.config import ModbusConfig
from runtime.hmi import HmiError
from runtime.hmi.registers import (
    BLOCKS,
    FIELD,
    FIELDS,
    INPUT_SIZE,
    OVERRIDE_SCALE,
    Kind,
    ServerStatus,
    Table,
    WatchdogState,
    encode_status,
    identity_image,
)
from runtime.hmi.upload import UploadRejected, decode_staging, result_for
from runtime.status import MachineState, StatusSnapshot

log = logging.getLogger(__name__)


class MachineLink(Protocol):
    """What the HMI server needs from the machine."""

    axis_names: tuple[str, ...]

    def snapshot(self) -> StatusSnapshot:
        """The last complete status (never half-updated)."""
        ...

    def submit(self, command: Command) -> CommandResult:
        """Check ``command`` against the current state and queue it for the next cycle
        (PENDING), or refuse it (nothing queued or changed)."""
        ...

    def prepare_curve(self, curve: NurbsCurve, crc32: int) -> object:
        """Check travel and prepare ``curve`` for planning; the result goes into a LOAD_CURVE
        command. Raises :class:`planner.errors.CurveError`."""
        ...


#: Refusals that mean "well formed, but not now": Modbus exception 6 (device busy).
BUSY_RESULTS = frozenset(
    {CommandResult.REJECTED_STATE, CommandResult.NO_CURVE, CommandResult.DRIVES_NOT_READY}
)
#: Results of an accepted command.
ACCEPTED_RESULTS = frozenset({CommandResult.PENDING, CommandResult.DONE})
#: Unit ids answered besides the configured one (libmodbus and many HMIs send 255 over TCP).
EXTRA_UNIT_IDS = (0, 255)

_SINGLE, _HIGH, _LOW = 1, 2, 3
_BIT_FUNCTIONS = frozenset({1, 2, 5, 15})
_READ_INPUT = 4
_CODE = FIELD["COMMAND_CODE"].address
_SEQ = FIELD["COMMAND_SEQ"].address
_OVERRIDE = FIELD["OVERRIDE_SETPOINT"].address
_HEARTBEAT = FIELD["HMI_HEARTBEAT"].address


def _holding_layout() -> tuple[list[int], dict[int, int]]:
    """Per holding address: its role in a value (single, high or low word), and maxima."""
    end = max(f.end for f in FIELDS if f.table is Table.HOLDING)
    roles = [0] * end
    maxima: dict[int, int] = {}
    for field in FIELDS:
        if field.table is not Table.HOLDING:
            continue
        for i in range(field.repeat):
            at = field.address_of(i)
            if field.kind is Kind.U16:
                roles[at] = _SINGLE
            else:
                roles[at], roles[at + 1] = _HIGH, _LOW
            if field.maximum is not None:
                maxima[at] = field.maximum
    return roles, maxima


def _exception_for(result: CommandResult) -> ExcCodes | None:
    if result in ACCEPTED_RESULTS:
        return None
    if result in BUSY_RESULTS:
        return ExcCodes.DEVICE_BUSY
    return ExcCodes.ILLEGAL_VALUE


class _UnitFilter:
    """The server context, answering only the configured unit id and 0 and 255."""

    def __init__(self, context: object, unit_ids: frozenset[int]) -> None:
        self._context = context
        self._unit_ids = unit_ids

    def _check(self, device_id: int) -> None:
        if device_id not in self._unit_ids:
            raise NoSuchIdException(f"unit id {device_id} (answered: {sorted(self._unit_ids)})")

    def device_ids(self) -> list[int]:
        return sorted(self._unit_ids)

    async def async_getValues(self, device_id: int, func_code: int, address: int, count: int = 1):
        self._check(device_id)
        return await self._context.async_getValues(device_id, func_code, address, count)

    async def async_setValues(self, device_id: int, func_code: int, address: int, values):
        self._check(device_id)
        return await self._context.async_setValues(device_id, func_code, address, values)


class _GuardedHandler(ServerRequestHandler):
    """A client connection that is closed at once when its peer is not allowed."""

    def callback_connected(self) -> None:
        peer = self.transport.get_extra_info("peername")
        if not self.server.allows(peer[0] if peer else ""):
            log.warning("modbus: refused connection from %s (not in allowed_networks)", peer)
            self.close()
            return
        super().callback_connected()


class _TcpServer(ModbusTcpServer):
    def __init__(self, device: SimDevice, config: ModbusConfig) -> None:
        super().__init__(device, address=(config.bind, config.port))
        self.context = _UnitFilter(self.context, frozenset({config.unit_id, *EXTRA_UNIT_IDS}))
        self._networks = [ipaddress.ip_network(n, strict=False) for n in config.allowed_networks]

    def allows(self, host: str) -> bool:
        """Whether a peer at ``host`` may connect."""
        try:
            address = ipaddress.ip_address(host)
        except ValueError:
            return False
        if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
            address = address.ipv4_mapped
        return any(address in network for network in self._networks)

    def callback_new_connection(self) -> ServerRequestHandler:
        return _GuardedHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class HmiServer:
    """The HMI's Modbus TCP server for one machine.

    :param config: the ``modbus`` section of the machine description.
    :param link: the machine.
    :param start_timeout_s: how long :meth:`start` waits for the server to listen.
    """

    def __init__(
        self, config: ModbusConfig, link: MachineLink, *, start_timeout_s: float = 5.0
    ) -> None:
        self.config = config
        self._link = link
        self._start_timeout_s = start_timeout_s
        self._roles, self._maxima = _holding_layout()
        watchdog_on = config.watchdog.timeout_ms > 0 and not config.read_only
        self._identity = identity_image(
            axis_count=len(link.axis_names),
            unit_id=config.unit_id,
            read_only=config.read_only,
            watchdog_timeout_ms=config.watchdog.timeout_ms if watchdog_on else 0,
        )
        self._status = ServerStatus(
            watchdog=WatchdogState.WATCHING if watchdog_on else WatchdogState.OFF
        )
        self._watchdog_on = watchdog_on
        self._cache: tuple[StatusSnapshot | None, ServerStatus | None, list[int]] = (None, None, [])
        self._last_activity = time.monotonic()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: _TcpServer | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._port = 0
        self._commit_lock: asyncio.Lock | None = None

    # -- life cycle (caller's thread) -------------------------------------------------------

    @property
    def port(self) -> int:
        """The TCP port the server listens on (resolves port 0 to the one chosen)."""
        return self._port

    def start(self) -> None:
        """Start the server thread and return once it listens.

        :raises HmiError: if it cannot listen (address in use, bad bind address) in time.
        """
        if self._thread is not None:
            raise HmiError("modbus: server already started")
        self._thread = threading.Thread(target=self._run, name="hmi-modbus", daemon=True)
        self._thread.start()
        where = f"{self.config.bind}:{self.config.port}"
        if not self._ready.wait(self._start_timeout_s):
            raise HmiError(f"modbus: server on {where} did not start in {self._start_timeout_s} s")
        if self._error is not None:
            self._thread.join(self._start_timeout_s)
            self._thread = None
            raise HmiError(f"modbus: cannot listen on {where}: {self._error}")
        log.info(
            "modbus: serving on %s:%d (unit %d)", self.config.bind, self._port, self.config.unit_id
        )

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close every connection, stop the server and join its thread (idempotent)."""
        thread, loop, server = self._thread, self._loop, self._server
        if thread is None or loop is None or server is None:
            return
        if thread.is_alive():
            asyncio.run_coroutine_threadsafe(server.shutdown(), loop).result(timeout_s)
            thread.join(timeout_s)
        self._thread = None

    def __enter__(self) -> HmiServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- server thread ------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported to start(); the thread must not die silently
            self._error = exc
            self._ready.set()

    def _device(self) -> SimDevice:
        holding = [
            SimData(
                first,
                count=end - first,
                datatype=DataType.REGISTERS,
                readonly=self.config.read_only,
            )
            for _title, table, first, end in BLOCKS
            if table is Table.HOLDING
        ]
        inputs = [SimData(0, count=INPUT_SIZE, datatype=DataType.REGISTERS, readonly=True)]
        # Coils and discrete inputs need a block to build; the action refuses them.
        bits = [SimData(0, datatype=DataType.BITS, readonly=True)]
        return SimDevice(0, simdata=(bits, list(bits), holding, inputs), action=self._action)

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._commit_lock = asyncio.Lock()
        self._server = _TcpServer(self._device(), self.config)
        await self._server.serve_forever(background=True)
        self._port = self._server.transport.sockets[0].getsockname()[1]
        watchdog = asyncio.create_task(self._watchdog()) if self._watchdog_on else None
        self._ready.set()
        try:
            await self._server.serving
        finally:
            if watchdog is not None:
                watchdog.cancel()

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if function_code in _BIT_FUNCTIONS:
            return ExcCodes.ILLEGAL_ADDRESS
        if function_code == _READ_INPUT:
            image = self._status_image()
            at = address - start_address
            registers[at : at + count] = image[address : address + count]
            return None
        if values is None:
            return None
        return await self._write(address - start_address, registers, list(map(int, values)))

    # -- status -------------------------------------------------------------------------------

    def _status_image(self) -> list[int]:
        snapshot = self._link.snapshot()
        self._settle(snapshot)
        cached_snapshot, cached_status, image = self._cache
        if snapshot is not cached_snapshot or self._status is not cached_status:
            image = encode_status(self._identity, snapshot, self._status, self._link.axis_names)
            self._cache = (snapshot, self._status, image)
        return image

    def _settle(self, snapshot: StatusSnapshot) -> None:
        """Replace PENDING by the machine's result once it has executed that command."""
        status = self._status
        done_seq, done_result = snapshot.last_command_seq & 0xFFFF, snapshot.last_command_result
        if status.request_result is CommandResult.PENDING and status.request_seq == done_seq:
            status = replace(status, request_result=CommandResult(done_result))
        if status.upload_result is CommandResult.PENDING and status.upload_seq == done_seq:
            status = replace(status, upload_result=CommandResult(done_result))
        self._status = status

    # -- writes -------------------------------------------------------------------------------

    async def _write(self, at: int, registers: list[int], values: list[int]) -> ExcCodes | None:
        end = at + len(values)
        if self._roles[at] == _LOW or self._roles[end - 1] == _HIGH:
            return ExcCodes.ILLEGAL_VALUE

        def new(address: int) -> int:
            return values[address - at] if at <= address < end else registers[address]

        commits = at <= _SEQ < end and new(_SEQ) != registers[_SEQ]
        for address, value in zip(range(at, end), values, strict=True):
            maximum = self._maxima.get(address)
            if maximum is not None and value > maximum:
                if commits:
                    self._judged(new(_SEQ), CommandResult.INVALID_PARAMETER)
                return ExcCodes.ILLEGAL_VALUE
        if commits:
            refusal = await self._commit(new(_CODE), new(_SEQ), new(_OVERRIDE), registers)
            if refusal is not None:
                return refusal
        if at <= _HEARTBEAT < end and new(_HEARTBEAT) != registers[_HEARTBEAT]:
            self._activity()
        return None

    async def _commit(
        self, code: int, seq: int, override: int, registers: list[int]
    ) -> ExcCodes | None:
        if code == 0:
            self._judged(seq, CommandResult.INVALID_PARAMETER)
            return ExcCodes.ILLEGAL_VALUE
        assert self._commit_lock is not None
        async with self._commit_lock:
            command = CommandCode(code)
            if command is CommandCode.LOAD_CURVE:
                result = await self._load_curve(seq, registers)
            else:
                percent = override / OVERRIDE_SCALE if command is CommandCode.SET_OVERRIDE else None
                result = self._link.submit(
                    Command(command, override_percent=percent, seq=seq, origin="hmi")
                )
            self._judged(seq, result)
            log.info("modbus: %s seq %d -> %s", command.name, seq, result.name)
            if result in ACCEPTED_RESULTS:
                self._activity()
            return _exception_for(result)

    def _judged(self, seq: int, result: CommandResult) -> None:
        self._status = replace(self._status, request_seq=seq, request_result=result)

    async def _load_curve(self, seq: int, registers: list[int]) -> CommandResult:
        if check_allowed(self._link.snapshot().state, CommandCode.LOAD_CURVE) is not None:
            result = CommandResult.REJECTED_STATE
        else:
            holding = list(registers)  # the staged data as of this commit
            try:
                loaded = await asyncio.to_thread(self._prepare, holding)
            except UploadRejected as exc:
                log.info("modbus: curve commit seq %d rejected: %s", seq, exc.reason)
                result = exc.result
            else:
                result = self._link.submit(
                    Command(CommandCode.LOAD_CURVE, curve=loaded, seq=seq, origin="hmi")
                )
        self._status = replace(self._status, upload_seq=seq, upload_result=result)
        return result

    def _prepare(self, holding: Sequence[int]) -> object:
        curve, crc = decode_staging(holding)
        try:
            return self._link.prepare_curve(curve, crc)
        except CurveError as exc:
            raise UploadRejected(result_for(exc), str(exc)) from exc

    # -- watchdog -----------------------------------------------------------------------------

    def _activity(self) -> None:
        self._last_activity = time.monotonic()
        if self._status.watchdog is WatchdogState.TRIPPED:
            self._status = replace(self._status, watchdog=WatchdogState.WATCHING)

    async def _watchdog(self) -> None:
        timeout_s = self.config.watchdog.timeout_ms / 1000.0
        poll_s = min(max(timeout_s / 10.0, 0.005), 0.1)
        action = CommandCode.STOP if self.config.watchdog.action == "stop" else CommandCode.HOLD
        while True:
            await asyncio.sleep(poll_s)
            if self._status.watchdog is WatchdogState.TRIPPED:
                continue
            silent_s = time.monotonic() - self._last_activity
            if silent_s < timeout_s or self._link.snapshot().state is not MachineState.MOVING:
                continue
            result = self._link.submit(Command(action, origin="hmi watchdog"))
            self._status = replace(self._status, watchdog=WatchdogState.TRIPPED)
            log.warning(
                "modbus: HMI heartbeat silent for %.0f ms while moving: %s -> %s",
                silent_s * 1000.0,
                action.name,
                result.name,
            )
