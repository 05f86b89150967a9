"""Modbus TCP on the wire: MBAP framing, the request PDUs the HMI server implements, exception
responses and device identification. Pure: bytes in, bytes out.

Sources: MODBUS Messaging on TCP/IP Implementation Guide V1.0b §3.1.3 (MBAP header:
transaction id, protocol id 0, length = unit id + PDU, unit id) and MODBUS Application Protocol
Specification V1.1b3 (§6.3, 6.4, 6.6, 6.12, 6.13, 6.17, 6.21 the functions below; §7 exception
responses: the request's function code with bit 7 set, then the exception code).

Implemented functions: 3 read holding registers, 4 read input registers, 6 write single
register, 16 write multiple registers, 23 read/write multiple registers, 17 report server id,
43/14 read device identification (basic objects, stream and individual access). Every other
function code answers exception 1 with that function code.

Checks, in the order of the standard's state diagrams: function implemented (1), PDU length and
quantities (3: reads 1..125, writes 1..123, FC23 writes 1..121, byte count = 2 x quantity),
then addresses and values, which the :class:`RegisterDevice` judges (2, 3, 6).

A malformed MBAP header (protocol id other than 0, length below 2 or above 254) cannot be
answered: the stream has lost its framing, so :func:`read_frames` reports it and the caller closes
the connection.

Threading: none; the server calls these on its event loop thread.
"""

from __future__ import annotations

import struct
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Protocol

from runtime.hmi import HmiError

#: MBAP header: transaction id, protocol id, length (unit id + PDU bytes), unit id.
MBAP = struct.Struct(">HHHB")
MBAP_BYTES = MBAP.size
#: Smallest and largest MBAP length: unit id + function code, unit id + a 253-byte PDU.
MIN_LENGTH = 2
MAX_LENGTH = 254
#: Most registers one request may read (FC3, FC4, the read part of FC23).
MAX_READ_REGISTERS = 125
#: Most registers one FC16 request may write.
MAX_WRITE_REGISTERS = 123
#: Most registers the write part of one FC23 request may carry.
MAX_READ_WRITE_REGISTERS = 121

_ADDRESS_COUNT = struct.Struct(">HH")
_WRITE_MULTIPLE = struct.Struct(">HHB")
_READ_WRITE = struct.Struct(">HHHHB")
_MEI_READ_DEVICE_ID = 0x0E
_RUN_INDICATOR_ON = 0xFF
#: Conformity level: basic identification, stream and individual access.
_CONFORMITY_BASIC = 0x81


class FunctionCode(IntEnum):
    """The function codes the server implements."""

    READ_HOLDING_REGISTERS = 3
    READ_INPUT_REGISTERS = 4
    WRITE_SINGLE_REGISTER = 6
    WRITE_MULTIPLE_REGISTERS = 16
    REPORT_SERVER_ID = 17
    READ_WRITE_MULTIPLE_REGISTERS = 23
    ENCAPSULATED_INTERFACE = 43


class ExceptionCode(IntEnum):
    """Modbus exception codes the server sends, and when."""

    ILLEGAL_FUNCTION = 1
    """A function code the server does not implement (anything but 3, 4, 6, 16, 17, 23 and
    43 with MEI type 14: coils and discrete inputs do not exist), with that function code."""
    ILLEGAL_DATA_ADDRESS = 2
    """An address outside the map (a gap, past the end); a write to a register that cannot be
    written (every write when the server is read-only; the staging area while another client
    holds it); FC43/14 individual access to an object that does not exist."""
    ILLEGAL_DATA_VALUE = 3
    """A request whose PDU length, quantity (reads 1..125, FC16 writes 1..123, FC23 writes
    1..121) or byte count is wrong; a value above a holding register's maximum (reserved
    registers take only 0); a write that starts or ends inside a 32-bit value; a change of
    COMMAND_SEQ while COMMAND_CODE is 0; FC43/14 with a read device id code other than 1..4.
    Nothing of the request is applied."""
    SERVER_DEVICE_FAILURE = 4
    """Never a refusal: only an internal error of the server (logged with its traceback)."""
    SERVER_DEVICE_BUSY = 6
    """Only for a command the machine's mailbox had no room for: nothing was queued and the
    write was not applied, so sending it again is safe."""
    GATEWAY_TARGET_FAILED = 11
    """A unit id other than the configured one, 0 and 255."""


class FrameError(HmiError):
    """A malformed MBAP header: the byte stream cannot be resynchronised."""


@dataclass(frozen=True, slots=True)
class Frame:
    """One request ADU."""

    transaction_id: int
    unit_id: int
    pdu: bytes


def read_frames(buffer: bytes | bytearray) -> tuple[list[Frame], int, FrameError | None]:
    """The complete frames at the start of ``buffer``, the bytes they take, and the header error
    that stopped the parse (None when the rest is only an incomplete frame)."""
    frames: list[Frame] = []
    at, size = 0, len(buffer)
    while size - at >= MBAP_BYTES:
        tid, protocol, length, unit = MBAP.unpack_from(buffer, at)
        if protocol != 0:
            return frames, at, FrameError(f"protocol id {protocol}, expected 0")
        if not MIN_LENGTH <= length <= MAX_LENGTH:
            return (
                frames,
                at,
                FrameError(f"MBAP length {length}, expected {MIN_LENGTH}..{MAX_LENGTH}"),
            )
        end = at + MBAP_BYTES - 1 + length
        if end > size:
            break
        frames.append(Frame(tid, unit, bytes(buffer[at + MBAP_BYTES : end])))
        at = end
    return frames, at, None


def frame_bytes(transaction_id: int, unit_id: int, pdu: bytes) -> bytes:
    """The ADU of a response PDU."""
    return MBAP.pack(transaction_id, 0, len(pdu) + 1, unit_id) + pdu


def exception_pdu(function_code: int, code: ExceptionCode) -> bytes:
    """The exception response to a request with ``function_code``."""
    return bytes((function_code | 0x80, code))


def registers_bytes(registers: Sequence[int]) -> bytes:
    """Registers as big-endian bytes."""
    return struct.pack(f">{len(registers)}H", *registers)


@dataclass(frozen=True)
class DeviceIdentity:
    """What FC17 and FC43/14 report."""

    vendor_name: str
    product_code: str
    revision: str

    def objects(self) -> tuple[bytes, ...]:
        """Basic device identification objects 0, 1, 2 (ASCII)."""
        return tuple(
            text.encode("ascii", "replace")
            for text in (self.vendor_name, self.product_code, self.revision)
        )

    def server_id(self) -> bytes:
        """FC17 server id: 'product revision' (ASCII)."""
        return f"{self.product_code} {self.revision}".encode("ascii", "replace")


#: What a read gives: the registers' bytes, or a refusal.
Answer = bytes | ExceptionCode
#: What a write gives: None when applied, or a refusal.
WriteOutcome = ExceptionCode | None


class RegisterDevice(Protocol):
    """The register tables behind the server (the HMI's map)."""

    def read_input(self, address: int, count: int) -> Answer:
        """Big-endian bytes of ``count`` input registers from ``address``, or a refusal."""
        ...

    def read_holding(self, address: int, count: int) -> Answer:
        """Big-endian bytes of ``count`` holding registers from ``address``, or a refusal."""
        ...

    def write_holding(
        self, address: int, values: Sequence[int], client: object
    ) -> WriteOutcome | Awaitable[WriteOutcome]:
        """Write ``values`` from ``address`` for ``client`` (the connection): None when applied,
        or a refusal (nothing applied); awaitable when the write must wait (a curve commit)."""
        ...


def answer(
    pdu: bytes, device: RegisterDevice, identity: DeviceIdentity, client: object
) -> bytes | Awaitable[bytes]:
    """The response PDU to a request PDU (awaitable when the device's write is)."""
    function_code = pdu[0]
    handler = _HANDLERS.get(function_code)
    if handler is None:
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_FUNCTION)
    return handler(pdu, device, identity, client)


def _reply(function_code: int, answer: Answer, prefix: bytes = b"") -> bytes:
    if isinstance(answer, ExceptionCode):
        return exception_pdu(function_code, answer)
    if prefix:
        return prefix + answer
    return bytes((function_code, len(answer))) + answer


def _read(pdu: bytes, device: RegisterDevice, _identity: DeviceIdentity, _client: object) -> bytes:
    function_code = pdu[0]
    if len(pdu) != 5:
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_DATA_VALUE)
    address, count = _ADDRESS_COUNT.unpack_from(pdu, 1)
    if not 1 <= count <= MAX_READ_REGISTERS:
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_DATA_VALUE)
    if function_code == FunctionCode.READ_INPUT_REGISTERS:
        return _reply(function_code, device.read_input(address, count))
    return _reply(function_code, device.read_holding(address, count))


def _after_write(
    outcome: WriteOutcome | Awaitable[WriteOutcome], finish: Callable[[WriteOutcome], bytes]
) -> bytes | Awaitable[bytes]:
    if outcome is None or isinstance(outcome, ExceptionCode):
        return finish(outcome)

    async def later() -> bytes:
        return finish(await outcome)  # type: ignore[misc]

    return later()


def _write_single(
    pdu: bytes, device: RegisterDevice, _identity: DeviceIdentity, client: object
) -> bytes | Awaitable[bytes]:
    if len(pdu) != 5:
        return exception_pdu(pdu[0], ExceptionCode.ILLEGAL_DATA_VALUE)
    address, value = _ADDRESS_COUNT.unpack_from(pdu, 1)
    return _after_write(
        device.write_holding(address, (value,), client),
        lambda refusal: exception_pdu(pdu[0], refusal) if refusal is not None else pdu,
    )


def _write_multiple(
    pdu: bytes, device: RegisterDevice, _identity: DeviceIdentity, client: object
) -> bytes | Awaitable[bytes]:
    function_code = pdu[0]
    if len(pdu) < 6:
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_DATA_VALUE)
    address, count, byte_count = _WRITE_MULTIPLE.unpack_from(pdu, 1)
    if (
        not 1 <= count <= MAX_WRITE_REGISTERS
        or byte_count != 2 * count
        or len(pdu) != 6 + byte_count
    ):
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_DATA_VALUE)
    values = struct.unpack_from(f">{count}H", pdu, 6)
    return _after_write(
        device.write_holding(address, values, client),
        lambda refusal: exception_pdu(function_code, refusal) if refusal is not None else pdu[:5],
    )


def _read_write(
    pdu: bytes, device: RegisterDevice, _identity: DeviceIdentity, client: object
) -> bytes | Awaitable[bytes]:
    function_code = pdu[0]
    if len(pdu) < 10:
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_DATA_VALUE)
    read_at, read_count, write_at, write_count, byte_count = _READ_WRITE.unpack_from(pdu, 1)
    if (
        not 1 <= read_count <= MAX_READ_REGISTERS
        or not 1 <= write_count <= MAX_READ_WRITE_REGISTERS
        or byte_count != 2 * write_count
        or len(pdu) != 10 + byte_count
    ):
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_DATA_VALUE)
    values = struct.unpack_from(f">{write_count}H", pdu, 10)

    def then_read(refusal: WriteOutcome) -> bytes:
        if refusal is not None:
            return exception_pdu(function_code, refusal)
        return _reply(function_code, device.read_holding(read_at, read_count))

    # The standard performs the write before the read.
    return _after_write(device.write_holding(write_at, values, client), then_read)


def _report_server_id(
    pdu: bytes, _device: RegisterDevice, identity: DeviceIdentity, _client: object
) -> bytes:
    if len(pdu) != 1:
        return exception_pdu(pdu[0], ExceptionCode.ILLEGAL_DATA_VALUE)
    data = identity.server_id() + bytes((_RUN_INDICATOR_ON,))
    return bytes((pdu[0], len(data))) + data


def _device_identification(
    pdu: bytes, _device: RegisterDevice, identity: DeviceIdentity, _client: object
) -> bytes:
    function_code = pdu[0]
    if len(pdu) < 2 or pdu[1] != _MEI_READ_DEVICE_ID:
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_FUNCTION)
    if len(pdu) != 4 or not 1 <= pdu[2] <= 4:
        return exception_pdu(function_code, ExceptionCode.ILLEGAL_DATA_VALUE)
    read_code, object_id = pdu[2], pdu[3]
    objects = identity.objects()
    if read_code == 4:
        if object_id >= len(objects):
            return exception_pdu(function_code, ExceptionCode.ILLEGAL_DATA_ADDRESS)
        chosen = [object_id]
    else:
        # Stream access (codes 1-3; only basic objects exist): an unknown first object
        # restarts at object 0, as the standard says.
        first = object_id if object_id < len(objects) else 0
        chosen = list(range(first, len(objects)))
    body = b"".join(bytes((i, len(objects[i]))) + objects[i] for i in chosen)
    header = bytes(
        (function_code, _MEI_READ_DEVICE_ID, read_code, _CONFORMITY_BASIC, 0, 0, len(chosen))
    )
    return header + body


_HANDLERS: dict[
    int,
    Callable[[bytes, RegisterDevice, DeviceIdentity, object], bytes | Awaitable[bytes]],
] = {
    FunctionCode.READ_HOLDING_REGISTERS: _read,
    FunctionCode.READ_INPUT_REGISTERS: _read,
    FunctionCode.WRITE_SINGLE_REGISTER: _write_single,
    FunctionCode.WRITE_MULTIPLE_REGISTERS: _write_multiple,
    FunctionCode.READ_WRITE_MULTIPLE_REGISTERS: _read_write,
    FunctionCode.REPORT_SERVER_ID: _report_server_id,
    FunctionCode.ENCAPSULATED_INTERFACE: _device_identification,
}
