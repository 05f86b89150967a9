"""Non-blocking SDO client for one node: expedited and segmented upload and download.

Source: CiA 301 §7.2.4 (SDO protocols "initiate domain download/upload", "download/upload domain
segment", "abort SDO transfer"; client -> server on 0x600 + node-ID, server -> client on
0x580 + node-ID, always 8 data bytes) and the abort code table of §7.2.4.3.17.

Units: times in seconds on the caller's clock (the cycle's ``now_s``).

Threading: one thread (the cycle). Nothing blocks: :meth:`SdoClient.upload` and
:meth:`SdoClient.download` send the first request and return an :class:`SdoTransfer`;
:meth:`SdoClient.on_response` (from the cycle's ``receive``) answers each segment at once and
completes the transfer; :meth:`SdoClient.poll` (from ``update``) retries or gives up on a timeout.

Invariants: at most one transfer per node is in flight (CiA 301 allows one per SDO channel); an
initiate or abort response is accepted only if its index and sub-index are the transfer's, so the
late answer of a cancelled transfer is never taken for the next one's; a transfer that timed out
is aborted on the bus (0x05040000) before it is retried from its first request.

Not done: block transfers (CiA 301 §7.2.4.3.9-15; drives answer segmented transfers too), more
than one SDO channel per node, SDO server.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from enum import Enum
from typing import Final

from canopen.sdo.exceptions import SdoAbortedError

from drives.objects import SDO_RX_COB_ID_BASE

# Command specifiers (byte 0).
_CCS_DOWNLOAD_SEGMENT: Final[int] = 0x00
_CCS_INITIATE_DOWNLOAD: Final[int] = 0x20
_CCS_INITIATE_UPLOAD: Final[int] = 0x40
_CCS_UPLOAD_SEGMENT: Final[int] = 0x60
_CS_ABORT: Final[int] = 0x80
_SCS_UPLOAD_SEGMENT: Final[int] = 0x00
_SCS_DOWNLOAD_SEGMENT: Final[int] = 0x20
_SCS_INITIATE_UPLOAD: Final[int] = 0x40
_SCS_INITIATE_DOWNLOAD: Final[int] = 0x60
_SCS_MASK: Final[int] = 0xE0
_EXPEDITED: Final[int] = 0x02
_SIZE_INDICATED: Final[int] = 0x01
_TOGGLE: Final[int] = 0x10
_LAST_SEGMENT: Final[int] = 0x01

#: Index, sub-index and four data bytes after byte 0.
_MUX_DATA = struct.Struct("<HBL")
_MUX = struct.Struct("<HB")
_SEGMENT_BYTES: Final[int] = 7

# Abort codes (CiA 301 §7.2.4.3.17) the client produces or classifies.
ABORT_TOGGLE: Final[int] = 0x0503_0000
ABORT_TIMEOUT: Final[int] = 0x0504_0000
ABORT_COMMAND: Final[int] = 0x0504_0001
ABORT_WRITE_ONLY: Final[int] = 0x0601_0001
ABORT_READ_ONLY: Final[int] = 0x0601_0002
ABORT_NO_OBJECT: Final[int] = 0x0602_0000
ABORT_NOT_MAPPABLE: Final[int] = 0x0604_0041
ABORT_MAPPING_TOO_LONG: Final[int] = 0x0604_0042
ABORT_LENGTH: Final[int] = 0x0607_0010
ABORT_NO_SUBINDEX: Final[int] = 0x0609_0011
ABORT_VALUE_RANGE: Final[int] = 0x0609_0030
ABORT_VALUE_TOO_HIGH: Final[int] = 0x0609_0031
ABORT_VALUE_TOO_LOW: Final[int] = 0x0609_0032
ABORT_MAX_BELOW_MIN: Final[int] = 0x0609_0036
ABORT_DEVICE_STATE: Final[int] = 0x0800_0022


class AbortKind(Enum):
    """What an abort code means for the boot: skip, report a value, or fail."""

    MISSING = "object does not exist"
    READ_ONLY = "read-only"
    OUT_OF_RANGE = "value out of range"
    TIMEOUT = "timeout"
    OTHER = "refused"


_KINDS: Final = {
    ABORT_NO_OBJECT: AbortKind.MISSING,
    ABORT_NO_SUBINDEX: AbortKind.MISSING,
    ABORT_READ_ONLY: AbortKind.READ_ONLY,
    ABORT_VALUE_RANGE: AbortKind.OUT_OF_RANGE,
    ABORT_VALUE_TOO_HIGH: AbortKind.OUT_OF_RANGE,
    ABORT_VALUE_TOO_LOW: AbortKind.OUT_OF_RANGE,
    ABORT_MAX_BELOW_MIN: AbortKind.OUT_OF_RANGE,
    ABORT_TIMEOUT: AbortKind.TIMEOUT,
}


def classify_abort(code: int) -> AbortKind:
    """The kind of an SDO abort code (codes not listed are :attr:`AbortKind.OTHER`)."""
    return _KINDS.get(code, AbortKind.OTHER)


def abort_text(code: int) -> str:
    """``abort 0x06020000 (object does not exist)``: the code and CiA 301's meaning."""
    meaning = SdoAbortedError.CODES.get(code)
    if meaning is None:
        return f"abort 0x{code:08X}"
    return f"abort 0x{code:08X} ({meaning[0].lower()}{meaning[1:]})"


class TransferStatus(Enum):
    """Where a transfer stands."""

    PENDING = "pending"
    DONE = "done"
    ABORTED = "aborted"
    TIMED_OUT = "timed out"


class _Phase(Enum):
    INITIATE = 0
    SEGMENTS = 1


class SdoTransfer:
    """One upload (read) or download (write) of an object entry, and its outcome.

    ``data`` is what to write (download) or what was read (upload, once ``status`` is DONE);
    ``abort_code`` is set when the server or the client aborted it.
    """

    __slots__ = (
        "_buffer",
        "_offset",
        "_phase",
        "_sent_s",
        "_size",
        "_toggle",
        "abort_code",
        "attempts",
        "data",
        "index",
        "status",
        "subindex",
        "upload",
    )

    def __init__(self, index: int, subindex: int, upload: bool, data: bytes = b"") -> None:
        self.index = index
        self.subindex = subindex
        self.upload = upload
        self.data = data
        self.status = TransferStatus.PENDING
        self.abort_code: int | None = None
        self.attempts = 0
        self._buffer = bytearray()
        self._offset = 0
        self._phase = _Phase.INITIATE
        self._sent_s = 0.0
        self._size: int | None = None
        self._toggle = 0

    @property
    def done(self) -> bool:
        """True once the transfer succeeded, was aborted or timed out."""
        return self.status is not TransferStatus.PENDING

    @property
    def ok(self) -> bool:
        return self.status is TransferStatus.DONE

    def describe_failure(self, timeout_s: float) -> str:
        """Why the transfer failed, as a message names it."""
        if self.status is TransferStatus.TIMED_OUT:
            return f"no SDO answer within {timeout_s:g} s ({self.attempts} attempts)"
        if self.abort_code is not None:
            return abort_text(self.abort_code)
        return self.status.value


class SdoClient:
    """The SDO client channel of one node (COB-IDs 0x600 + node-ID / 0x580 + node-ID).

    :param node_id: the server's node-ID, 1..127.
    :param send: sends one frame: ``send(can_id, data)``; must not block.
    :param timeout_s: time allowed for each answer of the server.
    :param retries: how often a transfer that timed out is started again.
    """

    def __init__(
        self,
        node_id: int,
        send: Callable[[int, bytes], None],
        *,
        timeout_s: float,
        retries: int,
    ) -> None:
        if not timeout_s > 0:
            raise ValueError(f"SDO timeout_s = {timeout_s!r}, must be > 0")
        if retries < 0:
            raise ValueError(f"SDO retries = {retries}, must be >= 0")
        self.node_id = node_id
        self.timeout_s = timeout_s
        self.retries = retries
        self._send = send
        self._request_id = SDO_RX_COB_ID_BASE + node_id
        self._transfer: SdoTransfer | None = None

    @property
    def busy(self) -> bool:
        """True while a transfer waits for the server."""
        return self._transfer is not None

    def upload(self, index: int, subindex: int, now_s: float) -> SdoTransfer:
        """Start reading ``index:subindex``; the value arrives in ``transfer.data``.

        :raises RuntimeError: if a transfer is already in flight.
        """
        return self._start(SdoTransfer(index, subindex, upload=True), now_s)

    def download(self, index: int, subindex: int, data: bytes, now_s: float) -> SdoTransfer:
        """Start writing ``data`` (the encoded value) to ``index:subindex``.

        Up to 4 bytes go expedited, longer data segmented.

        :raises RuntimeError: if a transfer is already in flight.
        """
        return self._start(SdoTransfer(index, subindex, upload=False, data=bytes(data)), now_s)

    def cancel(self) -> None:
        """Forget the transfer in flight without a word on the bus (the node is gone or
        restarting); a late answer is recognised by its index and ignored."""
        if self._transfer is not None:
            self._transfer.status = TransferStatus.ABORTED
            self._transfer = None

    def poll(self, now_s: float) -> None:
        """Retry or give up a transfer whose answer is overdue."""
        transfer = self._transfer
        if transfer is None or now_s - transfer._sent_s <= self.timeout_s:
            return
        self._abort(transfer, ABORT_TIMEOUT)
        if transfer.attempts <= self.retries:
            self._initiate(transfer, now_s)
        else:
            self._finish(transfer, TransferStatus.TIMED_OUT)

    def on_response(self, data: bytes, now_s: float) -> None:
        """Handle a frame from 0x580 + node-ID: next segment, completion or abort."""
        transfer = self._transfer
        if transfer is None or len(data) < 8:
            return
        command = data[0]
        if transfer._phase is _Phase.INITIATE or command == _CS_ABORT:
            index, subindex = _MUX.unpack_from(data, 1)
            if (index, subindex) != (transfer.index, transfer.subindex):
                return  # the late answer of a transfer given up before this one
        if command == _CS_ABORT:
            (code,) = struct.unpack_from("<L", data, 4)
            if code == ABORT_TIMEOUT and transfer.attempts <= self.retries:
                self._initiate(transfer, now_s)
                return
            transfer.abort_code = code
            self._finish(transfer, TransferStatus.ABORTED)
            return
        if transfer.upload:
            self._on_upload(transfer, command, data, now_s)
        else:
            self._on_download(transfer, command, now_s)

    # -- protocol ----------------------------------------------------------------------------

    def _start(self, transfer: SdoTransfer, now_s: float) -> SdoTransfer:
        if self._transfer is not None:
            raise RuntimeError(
                f"node {self.node_id}: SDO 0x{transfer.index:04X}:{transfer.subindex:02X} "
                f"while 0x{self._transfer.index:04X}:{self._transfer.subindex:02X} is in flight"
            )
        self._transfer = transfer
        self._initiate(transfer, now_s)
        return transfer

    def _initiate(self, transfer: SdoTransfer, now_s: float) -> None:
        transfer.attempts += 1
        transfer._phase = _Phase.INITIATE
        transfer._toggle = 0
        transfer._offset = 0
        transfer._buffer.clear()
        transfer._size = None
        request = bytearray(8)
        _MUX.pack_into(request, 1, transfer.index, transfer.subindex)
        if transfer.upload:
            request[0] = _CCS_INITIATE_UPLOAD
        elif len(transfer.data) <= 4:
            unused = 4 - len(transfer.data)
            request[0] = _CCS_INITIATE_DOWNLOAD | unused << 2 | _EXPEDITED | _SIZE_INDICATED
            request[4 : 4 + len(transfer.data)] = transfer.data
        else:
            request[0] = _CCS_INITIATE_DOWNLOAD | _SIZE_INDICATED
            struct.pack_into("<L", request, 4, len(transfer.data))
        self._transmit(transfer, request, now_s)

    def _on_upload(self, transfer: SdoTransfer, command: int, data: bytes, now_s: float) -> None:
        if transfer._phase is _Phase.INITIATE:
            if command & _SCS_MASK != _SCS_INITIATE_UPLOAD:
                self._protocol_error(transfer, ABORT_COMMAND)
                return
            if command & _EXPEDITED:
                size = 4 - (command >> 2 & 0x03) if command & _SIZE_INDICATED else 4
                transfer.data = bytes(data[4 : 4 + size])
                self._finish(transfer, TransferStatus.DONE)
                return
            if command & _SIZE_INDICATED:
                (transfer._size,) = struct.unpack_from("<L", data, 4)
            transfer._phase = _Phase.SEGMENTS
            self._request_upload_segment(transfer, now_s)
            return
        if command & _SCS_MASK != _SCS_UPLOAD_SEGMENT:
            self._protocol_error(transfer, ABORT_COMMAND)
            return
        if command & _TOGGLE != transfer._toggle:
            self._protocol_error(transfer, ABORT_TOGGLE)
            return
        unused = command >> 1 & 0x07
        transfer._buffer += data[1 : 1 + _SEGMENT_BYTES - unused]
        transfer._toggle ^= _TOGGLE
        if command & _LAST_SEGMENT:
            if transfer._size is not None and len(transfer._buffer) != transfer._size:
                self._protocol_error(transfer, ABORT_LENGTH)
                return
            transfer.data = bytes(transfer._buffer)
            self._finish(transfer, TransferStatus.DONE)
        else:
            self._request_upload_segment(transfer, now_s)

    def _request_upload_segment(self, transfer: SdoTransfer, now_s: float) -> None:
        request = bytearray(8)
        request[0] = _CCS_UPLOAD_SEGMENT | transfer._toggle
        self._transmit(transfer, request, now_s)

    def _on_download(self, transfer: SdoTransfer, command: int, now_s: float) -> None:
        if transfer._phase is _Phase.INITIATE:
            if command != _SCS_INITIATE_DOWNLOAD:
                self._protocol_error(transfer, ABORT_COMMAND)
                return
            if len(transfer.data) <= 4:
                self._finish(transfer, TransferStatus.DONE)
                return
            transfer._phase = _Phase.SEGMENTS
            self._send_download_segment(transfer, now_s)
            return
        if command & _SCS_MASK != _SCS_DOWNLOAD_SEGMENT:
            self._protocol_error(transfer, ABORT_COMMAND)
            return
        if command & _TOGGLE != transfer._toggle:
            self._protocol_error(transfer, ABORT_TOGGLE)
            return
        transfer._toggle ^= _TOGGLE
        if transfer._offset >= len(transfer.data):
            self._finish(transfer, TransferStatus.DONE)
        else:
            self._send_download_segment(transfer, now_s)

    def _send_download_segment(self, transfer: SdoTransfer, now_s: float) -> None:
        chunk = transfer.data[transfer._offset : transfer._offset + _SEGMENT_BYTES]
        transfer._offset += len(chunk)
        last = transfer._offset >= len(transfer.data)
        request = bytearray(8)
        request[0] = (
            _CCS_DOWNLOAD_SEGMENT
            | transfer._toggle
            | (_SEGMENT_BYTES - len(chunk)) << 1
            | (_LAST_SEGMENT if last else 0)
        )
        request[1 : 1 + len(chunk)] = chunk
        self._transmit(transfer, request, now_s)

    def _protocol_error(self, transfer: SdoTransfer, code: int) -> None:
        self._abort(transfer, code)
        transfer.abort_code = code
        self._finish(transfer, TransferStatus.ABORTED)

    def _abort(self, transfer: SdoTransfer, code: int) -> None:
        request = bytearray(8)
        request[0] = _CS_ABORT
        _MUX_DATA.pack_into(request, 1, transfer.index, transfer.subindex, code)
        self._send(self._request_id, bytes(request))

    def _transmit(self, transfer: SdoTransfer, request: bytearray, now_s: float) -> None:
        transfer._sent_s = now_s
        self._send(self._request_id, bytes(request))

    def _finish(self, transfer: SdoTransfer, status: TransferStatus) -> None:
        transfer.status = status
        self._transfer = None
