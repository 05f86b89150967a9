"""A runtime that died while moving comes back Disabled when it is started again (what
Restart=on-failure does): nothing moves until the HMI enables and starts it anew."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from machine_files import write_machine
from sim_machine import HOST_STALL_LIMITS

pytestmark = pytest.mark.slow

SOFTMOTION = Path(sys.executable).with_name("softmotion")
PAPER = Path(__file__).resolve().parents[2] / "configs" / "curves" / "paper.yaml"
BOOT_TIMEOUT_S = 30.0
CHILDREN_EXIT_TIMEOUT_S = 30.0


def hmi(port: int, *action: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(SOFTMOTION), "hmi", "--port", str(port), *action],
        capture_output=True,
        text=True,
        timeout=60,
    )


def start_machine(config: Path, port: int, log: Path) -> subprocess.Popen:
    """``softmotion run`` on ``config``, once it answers ``hmi status``."""
    process = subprocess.Popen(
        [str(SOFTMOTION), "run", "--config", str(config)],
        stdout=log.open("a"),
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its processes in a group of their own, as in a service's cgroup
    )
    deadline = time.monotonic() + BOOT_TIMEOUT_S
    while hmi(port, "status").returncode != 0:
        assert process.poll() is None, log.read_text()
        assert time.monotonic() < deadline, f"no answer on port {port}:\n{log.read_text()}"
        time.sleep(0.2)
    return process


def wait_until_group_gone(group: int, timeout_s: float) -> None:
    """Wait until no live process is left in process group ``group``, as systemd waits for a
    service's cgroup to empty before it restarts the service."""
    deadline = time.monotonic() + timeout_s
    while True:
        alive = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                # After "(comm)": state, ppid, pgrp.
                state, _, pgrp = stat.read_text().rpartition(")")[2].split()[:3]
            except OSError:
                continue  # gone while we looked
            if int(pgrp) == group and state != "Z":
                alive.append(stat.parent.name)
        if not alive:
            return
        assert time.monotonic() < deadline, f"processes {alive} of the killed runtime still run"
        time.sleep(0.1)


def machine_state(port: int) -> tuple[str, list[str]]:
    """The machine state and each axis's drive state, from ``softmotion hmi status``."""
    status = hmi(port, "status")
    assert status.returncode == 0, status.stderr
    machine = re.search(r"^machine\s+(\w+)", status.stdout, re.MULTILINE)
    drives = re.findall(r"node \d+ (\w+)$", status.stdout, re.MULTILINE)
    assert machine and drives, status.stdout
    return machine.group(1), drives


def test_a_runtime_killed_while_moving_restarts_disabled(tmp_path: Path) -> None:
    config = write_machine(tmp_path, HOST_STALL_LIMITS)
    port = int(re.search(r"port: (\d+)", config.read_text()).group(1))
    log = tmp_path / "machine.log"
    process = start_machine(config, port, log)
    try:
        # At 20 % the curve moves for about 9 s: still moving when a slow host has started the
        # status command below.
        for action in (("enable",), ("load", str(PAPER)), ("override", "20"), ("start",)):
            done = hmi(port, *action)
            assert done.returncode == 0, (action, done.stdout, done.stderr, log.read_text())
        state, drives = machine_state(port)
        assert state == "MOVING" and set(drives) == {"OPERATION_ENABLED"}, (state, drives)
        process.send_signal(signal.SIGKILL)  # a crash: no controlled stop, nothing cleaned up
        process.wait(10)
        # Its children end on their own (they stop on the path and exit when the supervisor
        # dies); until then the old HMI process may still answer on the port.
        wait_until_group_gone(process.pid, CHILDREN_EXIT_TIMEOUT_S)

        process = start_machine(config, port, log)
        state, drives = machine_state(port)
        assert state == "DISABLED", log.read_text()
        assert "OPERATION_ENABLED" not in drives, drives
        time.sleep(1.0)  # and it stays so: no command, no motion
        assert machine_state(port)[0] == "DISABLED"
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(30)
