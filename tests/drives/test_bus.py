"""Bus factory and the SocketCAN vcan probe."""

from __future__ import annotations

import errno
import socket
import uuid
from pathlib import Path

import can
import pytest

from drives import bus as bus_module
from drives.bus import open_bus, vcan_status
from drives.errors import BusUnavailable, DriveError


def test_virtual_buses_exchange_frames() -> None:
    channel = f"test-bus-{uuid.uuid4().hex}"
    sender = open_bus("virtual", channel, bitrate=1_000_000)
    receiver = open_bus("virtual", channel)
    try:
        sender.send(can.Message(arbitration_id=0x201, data=b"\x0f\x00\x10\x27\x00\x00"))
        frame = receiver.recv(timeout=1.0)
        assert frame is not None
        assert frame.arbitration_id == 0x201
        assert bytes(frame.data) == b"\x0f\x00\x10\x27\x00\x00"
        # Own frames are not echoed back to the sender.
        assert sender.recv(timeout=0.05) is None
    finally:
        sender.shutdown()
        receiver.shutdown()


def test_unknown_interface_names_the_interface() -> None:
    with pytest.raises(BusUnavailable) as caught:
        open_bus("no-such-interface", "can0")
    assert isinstance(caught.value, DriveError)
    assert "no-such-interface:can0" in str(caught.value)
    assert "virtual" in str(caught.value)


def test_open_failure_is_a_drive_error(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(**kwargs: object) -> can.BusABC:
        raise can.CanInitializationError("device busy")

    monkeypatch.setattr(bus_module.can, "Bus", refuse)
    with pytest.raises(BusUnavailable, match="pcan:PCAN_USBBUS1: CanInitializationError"):
        open_bus("pcan", "PCAN_USBBUS1", bitrate=500_000)


def test_bitrate_passed_only_where_the_interface_sets_it(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[dict[str, object]] = []

    def record(**kwargs: object) -> str:
        seen.append(kwargs)
        return "bus"

    monkeypatch.setattr(bus_module.can, "Bus", record)
    open_bus("pcan", "PCAN_USBBUS1", bitrate=500_000)
    open_bus("socketcan", "vcan0", bitrate=500_000)
    assert seen[0]["bitrate"] == 500_000
    assert "bitrate" not in seen[1]
    assert seen[1]["local_loopback"] is True


def test_vcan_status_reports_a_reason() -> None:
    usable, reason = vcan_status("vcan0")
    assert isinstance(usable, bool)
    assert reason


class _FakeCanSocket:
    def __init__(self, *args: object) -> None:
        self.bound: tuple[str, ...] | None = None

    def __enter__(self) -> _FakeCanSocket:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def bind(self, address: tuple[str, ...]) -> None:
        self.bound = address


def _fake_sysfs(root: Path, name: str, link_type: int, flags: str) -> None:
    (root / name).mkdir()
    (root / name / "type").write_text(f"{link_type}\n")
    (root / name / "flags").write_text(f"{flags}\n")


@pytest.fixture
def fake_can(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    monkeypatch.setattr(socket, "AF_CAN", 29, raising=False)
    monkeypatch.setattr(socket, "CAN_RAW", 1, raising=False)
    monkeypatch.setattr(bus_module.socket, "socket", _FakeCanSocket)
    monkeypatch.setattr(bus_module, "SYSFS_NET", tmp_path)
    return tmp_path


def test_vcan_status_usable(fake_can: Path) -> None:
    _fake_sysfs(fake_can, "vcan0", 280, "0x41")
    assert vcan_status("vcan0") == (True, "vcan0 is a usable SocketCAN interface")


def test_vcan_status_missing_link(fake_can: Path) -> None:
    usable, reason = vcan_status("vcan0")
    assert not usable
    assert "no network interface vcan0" in reason


def test_vcan_status_not_a_can_link(fake_can: Path) -> None:
    _fake_sysfs(fake_can, "vcan0", 1, "0x1003")
    usable, reason = vcan_status("vcan0")
    assert not usable
    assert "type 1, expected 280" in reason


def test_vcan_status_link_down(fake_can: Path) -> None:
    _fake_sysfs(fake_can, "vcan0", 280, "0x40")
    usable, reason = vcan_status("vcan0")
    assert not usable
    assert "down" in reason


def test_vcan_status_kernel_without_can(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_can(*args: object) -> socket.socket:
        raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")

    monkeypatch.setattr(socket, "AF_CAN", 29, raising=False)
    monkeypatch.setattr(socket, "CAN_RAW", 1, raising=False)
    monkeypatch.setattr(bus_module.socket, "socket", no_can)
    usable, reason = vcan_status("vcan0")
    assert not usable
    assert "errno 97" in reason
