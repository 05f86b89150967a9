"""Collection rules and fixtures of the SocketCAN tests in tests/vcan.

Every test in this directory is marked ``vcan``: the normal run deselects them (``-m "not vcan"``)
and ``scripts/vcan-stage`` runs them on vcan0, on the host when its kernel has CAN and otherwise
inside a virtme-ng VM. Where vcan0 is not usable they skip with the reason, except under the stage
(``SOFTMOTION_VCAN_REQUIRED=1``), where a missing vcan0 is a setup failure, not a skip.

Inside the VM (``SOFTMOTION_VCAN_VM=1``) the CPU is emulated: CPU-bound Python measured 14 to 17
times slower than on the host, and starting a Python process takes about a second;
``vcan_timing_factor`` is the factor tests multiply their wall-clock timeouts by.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from canlisten import CanListener

from drives.bus import vcan_status

#: The SocketCAN interface the vcan tests use.
VCAN_CHANNEL = "vcan0"

#: Logs of processes a test started; their tails are added to the report of a failing test.
DIAGNOSTIC_LOGS: list[Path] = []
#: Lines of each log shown.
DIAGNOSTIC_TAIL_LINES = 40

#: Timeout factor inside the emulated VM, with a margin over the measured 14 to 17.
VM_TIMING_FACTOR = 20.0

_VCAN_DIR = Path(__file__).resolve().parent


def running_in_vcan_vm() -> bool:
    """Whether the tests run inside the vcan stage's emulated VM."""
    return os.environ.get("SOFTMOTION_VCAN_VM") == "1"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the tests of this directory ``vcan`` (before ``-m`` selects) and skip them without
    a usable vcan0."""
    vcan_items = [item for item in items if _VCAN_DIR in item.path.resolve().parents]
    for item in vcan_items:
        item.add_marker(pytest.mark.vcan)
    if not vcan_items:
        return
    usable, reason = vcan_status(VCAN_CHANNEL)
    if usable:
        return
    if os.environ.get("SOFTMOTION_VCAN_REQUIRED") == "1":
        raise pytest.UsageError(f"the vcan stage needs SocketCAN {VCAN_CHANNEL}: {reason}")
    skip = pytest.mark.skip(reason=f"SocketCAN {VCAN_CHANNEL} not usable: {reason}")
    for item in vcan_items:
        item.add_marker(skip)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    """Show the tails of the started processes' logs with a failure: inside the VM the
    temporary files are gone once it stops."""
    outcome = yield
    report = outcome.get_result()
    if not report.failed:
        return
    for log in DIAGNOSTIC_LOGS:
        if log.exists():
            tail = log.read_text(errors="replace").splitlines()[-DIAGNOSTIC_TAIL_LINES:]
            report.sections.append((f"log {log.name}", "\n".join(tail)))


@pytest.fixture(scope="session")
def vcan_in_vm() -> bool:
    """Whether the tests run inside the vcan stage's emulated VM."""
    return running_in_vcan_vm()


@pytest.fixture(scope="session")
def vcan_timing_factor() -> float:
    """Factor for wall-clock timeouts: 1 on a host, ``VM_TIMING_FACTOR`` in the VM.

    ``SOFTMOTION_VCAN_TIMING_FACTOR`` overrides it (a slower machine, a debugger).
    """
    override = os.environ.get("SOFTMOTION_VCAN_TIMING_FACTOR")
    if override is not None:
        return float(override)
    return VM_TIMING_FACTOR if running_in_vcan_vm() else 1.0


@pytest.fixture
def vcan_listener() -> Iterator[CanListener]:
    """A raw-socket recorder of every frame on vcan0, started before the test body runs."""
    with CanListener(VCAN_CHANNEL) as listener:
        yield listener
