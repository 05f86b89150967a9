"""A Modbus TCP client for the machine's HMI register map, built on pymodbus.

Implements the protocol of :mod:`runtime.hmi.registers` from the HMI's side: identity check
(magic, map version, test float), status decoding, commands by sequence counter with their
acknowledgement, the curve upload (staging writes of at most :data:`CHUNK_REGISTERS` registers
per FC16, CRC32, commit, wait until the machine has loaded the curve) and the HMI heartbeat.

Errors are :class:`~runtime.hmi.HmiError`: :class:`ModbusReplyError` for a Modbus exception
answer (its code and meaning), :class:`CommandRefused` for a command or commit the server
refused (with the result code it published), :class:`HmiError` itself for connection
problems, timeouts and a server that is not a softmotion machine.

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
from runtime.hmi.registers import (
    FIELD,
    INPUT_SIZE,
    MAGIC,
    MAP_VERSION,
    MAX_READ_REGISTERS,
    MAX_WRITE_REGISTERS,
    OVERRIDE_SCALE,
    POINT_REGISTERS,
    HmiStatus,
    Identity,
    as_enum,
    decode_identity,
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
#: Polling interval while waiting for the machine to acknowledge.
POLL_S = 0.01

_SEQ = FIELD["COMMAND_SEQ"].address
_HEADER = FIELD["CURVE_DEGREE"].address
_POINTS = FIELD["POINT_X"].address
_KNOTS = FIELD["KNOT"].address
_HEARTBEAT = FIELD["HMI_HEARTBEAT"].address


class ModbusReplyError(HmiError):
    """The server answered a request with a Modbus exception."""

    def __init__(self, request: str, exception_code: int) -> None:
        self.request = request
        self.exception_code = exception_code
        self.meaning = EXCEPTION_MEANINGS.get(exception_code, "unknown exception")
        super().__init__(f"{request}: Modbus exception {exception_code} ({self.meaning})")


class CommandRefused(HmiError):
    """A command (or curve commit) the server refused; nothing was changed.

    ``result`` is the code the server published in ``REQUEST_RESULT`` (``UPLOAD_RESULT`` for a
    commit), ``exception_code`` the Modbus exception it answered.
    """

    def __init__(self, command: CommandCode, result: CommandResult | int, exception_code: int):
        self.command = command
        self.result = result
        self.exception_code = exception_code
        name = result.name if isinstance(result, CommandResult) else str(result)
        meaning = EXCEPTION_MEANINGS.get(exception_code, "unknown exception")
        super().__init__(
            f"{command.name} refused: {name} (Modbus exception {exception_code}, {meaning})"
        )


@dataclass(frozen=True)
class Outcome:
    """A command the machine has executed: its sequence value and result."""

    seq: int
    result: CommandResult | int


class HmiClient:
    """A connection to a machine's HMI server.

    :param host: server address.
    :param port: server TCP port.
    :param unit: unit id sent with every request.
    :param timeout_s: timeout of one request, and default wait for an acknowledgement.
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
        """The machine's status (one FC4 request)."""
        return decode_status(self.read_input(0, INPUT_SIZE))

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
                raise HmiError(
                    f"modbus: timed out waiting for {what or 'the machine'} "
                    f"(state {status.snapshot.state!r}, message {status.snapshot.message!r})"
                )
            time.sleep(poll_s)

    # -- commands -----------------------------------------------------------------------------

    def send(self, code: CommandCode, *, override_percent: float | None = None) -> int:
        """Write ``code`` (and the override parameter) with a new ``COMMAND_SEQ`` in one FC16;
        returns the sequence value once the server has queued the command.

        :raises CommandRefused: if the server refused it (exception 3 or 6).
        """
        seq = (self.read_holding(_SEQ, 1)[0] + 1) & 0xFFFF
        values = [int(code), seq]
        if override_percent is not None:
            setpoint = round(override_percent * OVERRIDE_SCALE)
            if not 0 <= setpoint <= 0xFFFF:
                raise HmiError(f"override {override_percent:g} %: must be 0 % or more")
            values.append(setpoint)
        try:
            self.write(FIELD["COMMAND_CODE"].address, values)
        except ModbusReplyError as exc:
            if exc.exception_code not in (3, 6):
                raise
            server = self.status().server
            if code is CommandCode.LOAD_CURVE and server.upload_seq == seq:
                raise CommandRefused(code, server.upload_result, exc.exception_code) from exc
            result = server.request_result if server.request_seq == seq else exc.exception_code
            raise CommandRefused(code, result, exc.exception_code) from exc
        return seq

    def command(
        self,
        code: CommandCode,
        *,
        override_percent: float | None = None,
        timeout_s: float | None = None,
    ) -> Outcome:
        """Send a command and wait until the machine has executed it.

        :raises CommandRefused: if the server refused it.
        :raises HmiError: if the machine does not acknowledge it in time.
        """
        seq = self.send(code, override_percent=override_percent)
        status = self.wait_for(
            lambda s: s.snapshot.last_command_seq == seq, timeout_s, f"{code.name} seq {seq}"
        )
        return Outcome(seq, as_enum(CommandResult, status.snapshot.last_command_result))

    # -- curve upload -------------------------------------------------------------------------

    def stage(self, staging: Staging, *, crc32: int | None = None) -> None:
        """Write a curve into the staging area: header and CRC32 (``crc32`` overrides the
        correct one, for tests), then points and knots in chunks."""
        crc = staging.crc32 if crc32 is None else crc32
        self.write(_HEADER, [*staging.header, crc >> 16, crc & 0xFFFF])
        points_chunk = CHUNK_REGISTERS - CHUNK_REGISTERS % POINT_REGISTERS
        for base, registers, chunk in (
            (_POINTS, staging.points, points_chunk),
            (_KNOTS, staging.knots, CHUNK_REGISTERS),
        ):
            for offset in range(0, len(registers), chunk):
                self.write(base + offset, registers[offset : offset + chunk])

    def load_curve(self, curve: NurbsCurve | Staging, *, timeout_s: float | None = None) -> Outcome:
        """Upload, commit and wait until the machine has loaded ``curve``.

        :raises CommandRefused: if the commit was refused (``result`` is the upload result
            code: a curve rule, CRC, capacity, or REJECTED_STATE while moving).
        """
        staging = curve if isinstance(curve, Staging) else staging_of(curve)
        self.stage(staging)
        return self.command(CommandCode.LOAD_CURVE, timeout_s=timeout_s)
