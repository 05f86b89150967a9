"""A Modbus TCP client made of hand-built frames on a plain socket, for tests that check the
server on the wire (independently of pymodbus and of the project's own codec)."""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Sequence


def adu(pdu: bytes, tid: int = 1, unit: int = 1, protocol: int = 0) -> bytes:
    """An MBAP header and ``pdu``."""
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1, unit) + pdu


def read_pdu(address: int, count: int, function: int = 4) -> bytes:
    return struct.pack(">BHH", function, address, count)


def write_pdu(address: int, values: Sequence[int]) -> bytes:
    return struct.pack(f">BHHB{len(values)}H", 16, address, len(values), 2 * len(values), *values)


class WireError(AssertionError):
    """The server answered with an exception; ``code`` is the exception code."""

    def __init__(self, function: int, code: int) -> None:
        self.function = function
        self.code = code
        super().__init__(f"exception {code} to function {function}")


class Wire:
    """One TCP connection to the server."""

    def __init__(self, port: int, timeout_s: float = 3.0) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
        self._tid = 0
        self._pending = b""

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> Wire:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def next_tid(self) -> int:
        self._tid = (self._tid + 1) & 0xFFFF
        return self._tid

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def _read_exactly(self, size: int) -> bytes:
        while len(self._pending) < size:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError(f"closed with {len(self._pending)} of {size} bytes read")
            self._pending += chunk
        data, self._pending = self._pending[:size], self._pending[size:]
        return data

    def response(self) -> tuple[int, int, bytes]:
        """The next response ADU: (transaction id, unit id, PDU)."""
        tid, protocol, length, unit = struct.unpack(">HHHB", self._read_exactly(7))
        assert protocol == 0, protocol
        return tid, unit, self._read_exactly(length - 1)

    def ask(self, pdu: bytes, unit: int = 1) -> bytes:
        """Send one request and return its response PDU (transaction id and unit checked)."""
        tid = self.next_tid()
        self.send(adu(pdu, tid, unit))
        got_tid, got_unit, answer = self.response()
        assert (got_tid, got_unit) == (tid, unit), (got_tid, got_unit, tid, unit)
        return answer

    def registers(self, pdu: bytes, unit: int = 1) -> list[int]:
        answer = self.ask(pdu, unit)
        if answer[0] & 0x80:
            raise WireError(answer[0] & 0x7F, answer[1])
        assert answer[0] == pdu[0] and answer[1] == len(answer) - 2, answer.hex(" ")
        return list(struct.unpack(f">{answer[1] // 2}H", answer[2:]))

    def read_input(self, address: int, count: int, unit: int = 1) -> list[int]:
        return self.registers(read_pdu(address, count, 4), unit)

    def read_holding(self, address: int, count: int) -> list[int]:
        return self.registers(read_pdu(address, count, 3))

    def write(self, address: int, values: Sequence[int]) -> None:
        """FC16; raises :class:`WireError` on an exception answer."""
        answer = self.ask(write_pdu(address, values))
        if answer[0] & 0x80:
            raise WireError(answer[0] & 0x7F, answer[1])
        assert answer == struct.pack(">BHH", 16, address, len(values)), answer.hex(" ")

    def closed_by_server(self, timeout_s: float = 3.0) -> bool:
        """Whether the server closes the connection within ``timeout_s`` (sending nothing)."""
        self.sock.settimeout(timeout_s)
        end = time.monotonic() + timeout_s
        try:
            while time.monotonic() < end:
                data = self.sock.recv(4096)
                if not data:
                    return True
                raise AssertionError(f"server sent {data.hex(' ')} instead of closing")
        except (ConnectionResetError, BrokenPipeError):
            return True
        except TimeoutError:
            return False
        return False
