"""A Modbus TCP client for the machine's HMI register map, built on pymodbus.

Implements the protocol of :mod:`runtime.hmi.registers` from the HMI's side: identity check
(magic, map version), status decoding, commands by sequence counter with the outcome of each
one's own sequence value (from the request history), the curve upload (staging writes of at most
:data:`CHUNK_REGISTERS` registers per FC16, CRC32, commit), library programs and the HMI
heartbeat.

Errors are :class:`~runtime.hmi.HmiError`: :class:`ModbusReplyError` for a Modbus exception
answer (its code and meaning), :class:`CommandRefused` for a command whose outcome is not DONE
(with its result code and the server's reason), :class:`HmiError` itself for connection
problems, timeouts and a server that is not a softmotion machine of this map version.

Threading: one client per thread; each call blocks until answered (``timeout_s``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException

from planner.nurbs import NurbsCurve
from runtime.commands import CommandCode, CommandResult
from runtime.hmi import HmiError
from runtime.hmi.protocol import MAX_READ_REGISTERS, MAX_WRITE_REGISTERS, ExceptionCode
from runtime.hmi.registers import (
    BLOCKS,
    CORE_END,
    FIELD,
    HISTORY,
    INPUT_SIZE,
    MAGIC,
    MAP_VERSION,
    MAX_KNOTS,
    OVERRIDE_SCALE,
    POINT_REGISTERS,
    HmiRequest,
    HmiStatus,
    Identity,
    LibraryEntry,
    LibraryState,
    StagingControl,
    Table,
    decode_identity,
    decode_server,
    decode_status,
)
from runtime.hmi.upload import Staging, staging_of

#: Meanings of Modbus exception codes (Modbus Application Protocol v1.1b3, §7).
EXCEPTION_MEANINGS: dict[int, str] = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}
#: Registers per staging write: even (floats are never split) and within the FC16 limit.
CHUNK_REGISTERS = MAX_WRITE_REGISTERS - 1
#: Polling interval while waiting for the machine.
POLL_S = 0.01

_CODE = FIELD["COMMAND_CODE"].address
_SEQ = FIELD["COMMAND_SEQ"].address
_PROGRAM = FIELD["PROGRAM_NUMBER"].address
_LIBRARY_SELECT = FIELD["LIBRARY_SELECT"].address
_STAGING_CONTROL = FIELD["STAGING_CONTROL"].address
_HEADER = FIELD["CURVE_DEGREE"].address
_POINTS = FIELD["POINT_X"].address
_KNOTS = FIELD["KNOT"].address
_HEARTBEAT = FIELD["HMI_HEARTBEAT"].address
_REQUESTS = FIELD["REQUEST_TICKET"]


def _read_plan() -> list[tuple[int, int]]:
    """FC4 requests that read the input image without splitting a block."""
    plan: list[tuple[int, int]] = []
    for _title, table, first, end in BLOCKS:
        if table is not Table.INPUT:
            continue
        if plan and end - plan[-1][0] <= MAX_READ_REGISTERS:
            plan[-1] = (plan[-1][0], end)
        else:
            plan.append((first, end))
    return plan


_READ_PLAN = _read_plan()


class ModbusReplyError(HmiError):
    """The server answered a request with a Modbus exception."""

    def __init__(self, request: str, exception_code: int) -> None:
        self.request = request
        self.exception_code = exception_code
        self.meaning = EXCEPTION_MEANINGS.get(exception_code, "unknown exception")
        super().__init__(f"{request}: Modbus exception {exception_code} ({self.meaning})")


@dataclass(frozen=True)
class Outcome:
    """A request's outcome: its sequence value, ticket (0 when the server refused it itself),
    result, and the server's reason for a refusal of its own."""

    seq: int
    ticket: int
    result: CommandResult | int
    message: str = ""


class CommandRefused(HmiError):
    """A command (or curve commit) whose outcome is not DONE; nothing was changed."""

    def __init__(self, command: CommandCode, outcome: Outcome) -> None:
        self.command = command
        self.outcome = outcome
        self.result = outcome.result
        name = getattr(outcome.result, "name", str(outcome.result))
        reason = f": {outcome.message}" if outcome.message else ""
        super().__init__(f"{command.name} seq {outcome.seq} refused: {name}{reason}")


class HmiClient:
    """A connection to a machine's HMI server.

    :param host: server address.
    :param port: server TCP port.
    :param unit: unit id sent with every request.
    :param timeout_s: timeout of one request, and default wait for an outcome.
    """

    def __init__(
        self, host: str = "127.0.0.1", port: int = 1502, *, unit: int = 1, timeout_s: float = 3.0
    ) -> None:
        self.host = host
        self.port = port
        self.unit = unit
        self.timeout_s = timeout_s
        self._client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=1)
        self._identity: Identity | None = None

    # -- connection ---------------------------------------------------------------------------

    def connect(self) -> Identity:
        """Connect and check that the server speaks this register map.

        :raises HmiError: if the server cannot be reached or is not a softmotion machine of
            this map version.
        """
        if not self._client.connect():
            raise HmiError(f"modbus: cannot connect to {self.host}:{self.port}")
        identity = decode_identity(self.read_input(0, FIELD["WATCHDOG_TIMEOUT_MS"].end))
        if identity.magic != MAGIC or identity.map_version != MAP_VERSION:
            raise HmiError(
                f"modbus: {self.host}:{self.port} is not a softmotion machine of register map "
                f"{MAP_VERSION} (magic 0x{identity.magic:04X}, map {identity.map_version})"
            )
        self._identity = identity
        return identity

    def close(self) -> None:
        """Close the connection."""
        self._client.close()

    def __enter__(self) -> HmiClient:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def identity(self) -> Identity:
        """The identity read by :meth:`connect`."""
        if self._identity is None:
            raise HmiError("modbus: not connected")
        return self._identity

    # -- raw access ---------------------------------------------------------------------------

    def _call(self, request: str, send: Callable[[], object]) -> list[int]:
        try:
            reply = send()
        except (ModbusException, OSError) as exc:
            raise HmiError(f"modbus: {request} to {self.host}:{self.port}: {exc}") from exc
        if reply.isError():  # type: ignore[attr-defined]
            raise ModbusReplyError(request, reply.exception_code)  # type: ignore[attr-defined]
        return list(getattr(reply, "registers", []))

    def read_input(self, address: int, count: int) -> list[int]:
        """Input registers ``address`` .. ``address + count - 1`` (split into FC4 requests)."""
        registers: list[int] = []
        for at in range(address, address + count, MAX_READ_REGISTERS):
            n = min(MAX_READ_REGISTERS, address + count - at)
            registers += self._call(
                f"read input registers {at}..{at + n - 1}",
                lambda at=at, n=n: self._client.read_input_registers(
                    at, count=n, device_id=self.unit
                ),
            )
        return registers

    def read_holding(self, address: int, count: int) -> list[int]:
        """Holding registers ``address`` .. ``address + count - 1`` (one FC3 request)."""
        return self._call(
            f"read holding registers {address}..{address + count - 1}",
            lambda: self._client.read_holding_registers(address, count=count, device_id=self.unit),
        )

    def write(self, address: int, values: Sequence[int]) -> None:
        """Write holding registers from ``address`` (one FC16 request, at most 123)."""
        self._call(
            f"write holding registers {address}..{address + len(values) - 1}",
            lambda: self._client.write_registers(address, list(values), device_id=self.unit),
        )

    # -- status -------------------------------------------------------------------------------

    def status(self) -> HmiStatus:
        """The machine's status: one FC4 request per group of whole blocks (each block is one
        snapshot; the groups may be one period apart)."""
        image = [0] * INPUT_SIZE
        for first, end in _READ_PLAN:
            image[first:end] = self.read_input(first, end - first)
        return decode_status(image)

    def core_status(self) -> HmiStatus:
        """The machine's core status in one FC4 request (one snapshot): state, status word,
        fault, path, axes, cycle statistics; no histories, programs or messages (the decoded
        snapshot has none)."""
        image = [0] * INPUT_SIZE
        image[:CORE_END] = self.read_input(0, CORE_END)
        return decode_status(image)

    def requests(self) -> tuple[HmiRequest, ...]:
        """The server's request history, newest first (one FC4 request)."""
        first, end = _REQUESTS.address, _REQUESTS.end
        image = [0] * INPUT_SIZE
        image[first:end] = self.read_input(first, end - first)
        return decode_server(image).requests

    def heartbeat(self) -> int:
        """Advance ``HMI_HEARTBEAT`` (the watchdog's sign of life); returns the value written."""
        value = (self.read_holding(_HEARTBEAT, 1)[0] + 1) & 0xFFFF
        self.write(_HEARTBEAT, [value])
        return value

    def wait_for(
        self,
        done: Callable[[HmiStatus], bool],
        timeout_s: float | None = None,
        what: str = "",
        *,
        poll_s: float = POLL_S,
    ) -> HmiStatus:
        """Poll the status every ``poll_s`` seconds until ``done(status)``; returns that status.

        :raises HmiError: when ``timeout_s`` (default ``self.timeout_s``) passes first.
        """
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            status = self.status()
            if done(status):
                return status
            if time.monotonic() > deadline:
                snapshot = status.snapshot
                where = (
                    "the runtime is starting"
                    if snapshot is None
                    else f"state {getattr(snapshot.state, 'name', snapshot.state)}, message "
                    f"{snapshot.message!r}"
                )
                raise HmiError(f"modbus: timed out waiting for {what or 'the machine'} ({where})")
            time.sleep(poll_s)

    # -- commands -----------------------------------------------------------------------------

    def send(
        self,
        code: CommandCode,
        *,
        override_percent: float | None = None,
        program_number: int | None = None,
        timeout_s: float | None = None,
    ) -> int:
        """Write ``code`` (and its parameter) with a new ``COMMAND_SEQ``; returns the sequence
        value once the server has taken the request. A full mailbox (exception 6: nothing
        queued) is tried again until ``timeout_s``.

        :raises ModbusReplyError: for any other exception answer (3: a value out of range).
        """
        if program_number is not None:
            self.write(_PROGRAM, [program_number])
        seq = (self.read_holding(_SEQ, 1)[0] + 1) & 0xFFFF
        values = [int(code), seq]
        if override_percent is not None:
            setpoint = round(override_percent * OVERRIDE_SCALE)
            if not 0 <= setpoint <= 0xFFFF:
                raise HmiError(f"override {override_percent:g} %: must be 0 % or more")
            values.append(setpoint)
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            try:
                self.write(_CODE, values)
                return seq
            except ModbusReplyError as exc:
                busy = exc.exception_code == ExceptionCode.SERVER_DEVICE_BUSY
                if not busy or time.monotonic() > deadline:
                    raise
            time.sleep(POLL_S)

    def outcome(self, seq: int, code: CommandCode, *, timeout_s: float | None = None) -> Outcome:
        """Wait for the outcome of the request with sequence value ``seq``.

        :raises HmiError: if it does not come within ``timeout_s``, or the request left the
            history unseen (more than eight requests since).
        """
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            requests = self.requests()
            mine = [r for r in requests if r.seq == seq and r.code == code]
            if mine and mine[0].result != CommandResult.PENDING:
                request = mine[0]
                message = ""
                if request.ticket == 0 and requests[0] is request:
                    message = str(self.status().server.request_message)
                return Outcome(seq, request.ticket, request.result, message)
            if not mine and len(requests) == HISTORY:
                raise HmiError(f"modbus: {code.name} seq {seq} left the request history unseen")
            if time.monotonic() > deadline:
                raise HmiError(
                    f"modbus: timed out waiting for the outcome of {code.name} seq {seq}"
                )
            time.sleep(POLL_S)

    def command(
        self,
        code: CommandCode,
        *,
        override_percent: float | None = None,
        program_number: int | None = None,
        timeout_s: float | None = None,
    ) -> Outcome:
        """Send a command and wait for its own outcome.

        :raises CommandRefused: if the outcome is not DONE.
        :raises HmiError: if no outcome comes in time.
        """
        seq = self.send(
            code,
            override_percent=override_percent,
            program_number=program_number,
            timeout_s=timeout_s,
        )
        outcome = self.outcome(seq, code, timeout_s=timeout_s)
        if outcome.result != CommandResult.DONE:
            raise CommandRefused(code, outcome)
        return outcome

    # -- curve upload and library -------------------------------------------------------------

    def stage(self, staging: Staging, *, crc32: int | None = None) -> None:
        """Write a curve into the staging area (the first write takes it): header and CRC32
        (``crc32`` overrides the correct one, for tests), then points and knots in chunks."""
        crc = staging.crc32 if crc32 is None else crc32
        self.write(_HEADER, [*staging.header, crc >> 16, crc & 0xFFFF])
        points_chunk = CHUNK_REGISTERS - CHUNK_REGISTERS % POINT_REGISTERS
        for base, registers, chunk in (
            (_POINTS, staging.points, points_chunk),
            (_KNOTS, staging.knots, CHUNK_REGISTERS),
        ):
            for offset in range(0, len(registers), chunk):
                self.write(base + offset, registers[offset : offset + chunk])

    def abort_upload(self) -> None:
        """Clear the staging header and give the staging area free."""
        self.write(_STAGING_CONTROL, [StagingControl.ABORT])

    def load_curve(self, curve: NurbsCurve | Staging, *, timeout_s: float | None = None) -> Outcome:
        """Upload and commit ``curve``, and wait for the machine to load it (the active program
        at rest, the next one while moving).

        :raises CommandRefused: if the commit is refused (curve rules, CRC, staging held by
            another client, ...).
        """
        staging = curve if isinstance(curve, Staging) else staging_of(curve)
        points, knots = staging.header[2], staging.header[3]
        if points > self.identity.max_points or knots > MAX_KNOTS:
            raise HmiError(
                f"curve upload: {points} control points, {knots} knots: the staging area holds "
                f"{self.identity.max_points} points and {MAX_KNOTS} knots; put the curve in the "
                "program library (programs.library_dir) and load it by number"
            )
        self.stage(staging)
        return self.command(CommandCode.LOAD_CURVE, program_number=0, timeout_s=timeout_s)

    def load_program(self, number: int, *, timeout_s: float | None = None) -> Outcome:
        """Load library program ``number``.

        :raises CommandRefused: if it is refused (NO_SUCH_PROGRAM, curve rules, ...).
        """
        return self.command(CommandCode.LOAD_CURVE, program_number=number, timeout_s=timeout_s)

    def library_entry(self, number: int, *, timeout_s: float | None = None) -> LibraryEntry:
        """Library program ``number`` as the server shows it (name, points, length, CRC32);
        number 0 selects none (and lists the library again)."""
        return self._browse(number, timeout_s).server.library

    def library_count(self, *, timeout_s: float | None = None) -> int:
        """The number of library programs, listed again now."""
        return self._browse(0, timeout_s).server.library_count

    def _browse(self, number: int, timeout_s: float | None) -> HmiStatus:
        self.write(_LIBRARY_SELECT, [number])
        return self.wait_for(
            lambda s: (
                s.server.library.number == number and s.server.library.state != LibraryState.READING
            ),
            timeout_s,
            f"library program {number}",
        )
