"""Fixtures of the HMI tests: a fake machine, the HMI server on a free port in front of it, and
clients (raw frames and the project's client)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fake_machine_link import FakeMachine, hmi_config
from modbus_wire import Wire

from runtime.hmi.client import HmiClient
from runtime.hmi.server import HmiServer


@pytest.fixture
def fake(tmp_path: Path) -> Iterator[FakeMachine]:
    """A fake machine stepping every 4 ms, with its first snapshot published."""
    machine = FakeMachine(tmp_path / "programs").start()
    machine.wait_periods(1)
    yield machine
    machine.close()


@pytest.fixture
def hmi(fake: FakeMachine) -> Iterator[HmiServer]:
    with HmiServer(fake, hmi_config()) as server:
        yield server


@pytest.fixture
def wire(hmi: HmiServer) -> Iterator[Wire]:
    with Wire(hmi.port) as connection:
        yield connection


@pytest.fixture
def client(hmi: HmiServer) -> Iterator[HmiClient]:
    with HmiClient(port=hmi.port, timeout_s=3.0) as connection:
        yield connection
