"""The non-blocking SDO client against byte-exact conversations (CiA 301 §7.2.4)."""

from __future__ import annotations

import pytest

from drives.sdo_client import (
    ABORT_NO_OBJECT,
    ABORT_READ_ONLY,
    ABORT_VALUE_TOO_HIGH,
    AbortKind,
    SdoClient,
    TransferStatus,
    abort_text,
    classify_abort,
)

NODE = 5
REQUEST_ID = 0x605


class Wire:
    """The frames the client sends, as (COB-ID, 8 bytes)."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, bytes]] = []

    def __call__(self, can_id: int, data: bytes) -> None:
        assert len(data) == 8
        self.sent.append((can_id, bytes(data)))

    def take(self) -> list[bytes]:
        assert all(can_id == REQUEST_ID for can_id, _ in self.sent)
        frames = [data for _, data in self.sent]
        self.sent.clear()
        return frames


def _client(wire: Wire, timeout_s: float = 1.0, retries: int = 2) -> SdoClient:
    return SdoClient(NODE, wire, timeout_s=timeout_s, retries=retries)


def test_expedited_download_then_answer() -> None:
    wire = Wire()
    client = _client(wire)
    transfer = client.download(0x60C2, 1, bytes([4]), now_s=0.0)
    assert wire.take() == [bytes.fromhex("2fc2600104000000")]
    assert client.busy and not transfer.done
    client.on_response(bytes.fromhex("60c2600100000000"), now_s=0.001)
    assert transfer.ok and not client.busy


def test_expedited_upload_of_each_size() -> None:
    wire = Wire()
    client = _client(wire)
    for answer, value in (
        ("4f61600008000000", b"\x08"),  # 1 byte (n = 3)
        ("4b41600037020000", b"\x37\x02"),  # 2 bytes (n = 2)
        ("4364600010270000", b"\x10\x27\x00\x00"),  # 4 bytes (n = 0)
        ("4264600010270000", b"\x10\x27\x00\x00"),  # size not indicated: 4 bytes
    ):
        index = int.from_bytes(bytes.fromhex(answer)[1:3], "little")
        transfer = client.upload(index, 0, now_s=0.0)
        assert wire.take() == [bytes([0x40]) + index.to_bytes(2, "little") + bytes(5)]
        client.on_response(bytes.fromhex(answer), now_s=0.0)
        assert transfer.ok and transfer.data == value


def test_segmented_upload_with_toggle() -> None:
    wire = Wire()
    client = _client(wire)
    transfer = client.upload(0x1008, 0, now_s=0.0)
    assert wire.take() == [bytes.fromhex("4008100000000000")]
    client.on_response(bytes.fromhex("410810000a000000"), now_s=0.0)  # 10 bytes, segmented
    assert wire.take() == [bytes.fromhex("6000000000000000")]
    client.on_response(b"\x00" + b"softmot", now_s=0.0)  # toggle 0, 7 bytes, more
    assert wire.take() == [bytes.fromhex("7000000000000000")]
    client.on_response(b"\x19" + b"ion\x00\x00\x00\x00", now_s=0.0)  # toggle 1, n = 4, last
    assert transfer.ok and transfer.data == b"softmotion"
    assert wire.take() == []


def test_segmented_download() -> None:
    wire = Wire()
    client = _client(wire)
    transfer = client.download(0x2000, 1, b"0123456789", now_s=0.0)
    assert wire.take() == [bytes.fromhex("210020010a000000")]
    client.on_response(bytes.fromhex("6000200100000000"), now_s=0.0)
    assert wire.take() == [b"\x00" + b"0123456"]
    client.on_response(bytes.fromhex("2000000000000000"), now_s=0.0)
    assert wire.take() == [b"\x19" + b"789\x00\x00\x00\x00"]  # toggle 1, n = 4, last
    client.on_response(bytes.fromhex("3000000000000000"), now_s=0.0)
    assert transfer.ok


def test_server_abort_is_the_outcome() -> None:
    wire = Wire()
    client = _client(wire)
    transfer = client.download(0x6066, 0, b"\x14\x00", now_s=0.0)
    wire.take()
    client.on_response(bytes.fromhex("8066600000000206"), now_s=0.0)
    assert transfer.status is TransferStatus.ABORTED
    assert transfer.abort_code == ABORT_NO_OBJECT
    assert transfer.describe_failure(1.0) == "abort 0x06020000 (object does not exist)"


def test_timeout_aborts_and_retries_then_gives_up() -> None:
    wire = Wire()
    client = _client(wire, timeout_s=1.0, retries=2)
    transfer = client.upload(0x1000, 0, now_s=0.0)
    request = bytes.fromhex("4000100000000000")
    timeout_abort = bytes.fromhex("8000100000000405")
    assert wire.take() == [request]
    client.poll(now_s=1.0)  # not yet: the limit is inclusive
    assert wire.take() == []
    for now_s in (1.01, 2.02):
        client.poll(now_s=now_s)
        assert wire.take() == [timeout_abort, request]
        assert not transfer.done
    client.poll(now_s=3.03)
    assert wire.take() == [timeout_abort]
    assert transfer.status is TransferStatus.TIMED_OUT
    assert transfer.attempts == 3
    assert transfer.describe_failure(1.0) == "no SDO answer within 1 s (3 attempts)"
    assert not client.busy


def test_a_retry_answered_late_succeeds() -> None:
    wire = Wire()
    client = _client(wire, timeout_s=0.1, retries=1)
    transfer = client.upload(0x6041, 0, now_s=0.0)
    client.poll(now_s=0.2)
    client.on_response(bytes.fromhex("4b41600040020000"), now_s=0.25)
    assert transfer.ok and transfer.data == b"\x40\x02"


def test_late_answer_of_a_cancelled_transfer_is_not_taken_for_the_next() -> None:
    wire = Wire()
    client = _client(wire)
    client.upload(0x1000, 0, now_s=0.0)
    client.cancel()
    transfer = client.upload(0x6061, 0, now_s=0.0)
    client.on_response(bytes.fromhex("4300100092010200"), now_s=0.0)  # 0x1000's answer
    client.on_response(bytes.fromhex("8000100000000206"), now_s=0.0)  # or its abort
    assert not transfer.done
    client.on_response(bytes.fromhex("4f61600008000000"), now_s=0.0)
    assert transfer.ok and transfer.data == b"\x08"


def test_toggle_error_aborts_the_transfer() -> None:
    wire = Wire()
    client = _client(wire)
    transfer = client.upload(0x1008, 0, now_s=0.0)
    client.on_response(bytes.fromhex("410810000a000000"), now_s=0.0)
    wire.take()
    client.on_response(b"\x10" + b"softmot", now_s=0.0)  # toggle 1 where 0 was due
    assert wire.take() == [bytes.fromhex("8008100000000305")]
    assert transfer.abort_code == 0x0503_0000


def test_one_transfer_at_a_time() -> None:
    client = _client(Wire())
    client.upload(0x1000, 0, now_s=0.0)
    with pytest.raises(RuntimeError, match="node 5: SDO 0x6041:00 while 0x1000:00 is in flight"):
        client.upload(0x6041, 0, now_s=0.0)


def test_abort_classes() -> None:
    assert classify_abort(ABORT_NO_OBJECT) is AbortKind.MISSING
    assert classify_abort(0x0609_0011) is AbortKind.MISSING
    assert classify_abort(ABORT_READ_ONLY) is AbortKind.READ_ONLY
    assert classify_abort(ABORT_VALUE_TOO_HIGH) is AbortKind.OUT_OF_RANGE
    assert classify_abort(0x0800_0022) is AbortKind.OTHER
    assert abort_text(0x1234_5678) == "abort 0x12345678"
