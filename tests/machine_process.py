"""``softmotion run`` on the simulated machine as a subprocess, driven over Modbus TCP: starting
it, waiting for it to answer, running the paper's curve and polling it (tests and benches)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml
from sim_machine import free_port, sim_document

from runtime.commands import CommandCode, CommandResult
from runtime.curves import load_curve_file
from runtime.hmi.client import HmiClient
from runtime.hmi.registers import HmiStatus
from runtime.status import MachineState
from runtime.wakeups import host_steal_s

ROOT = Path(__file__).resolve().parents[1]
PAPER = load_curve_file(ROOT / "configs" / "curves" / "paper.yaml")
SOFTMOTION = Path(sys.executable).with_name("softmotion")
#: Seconds a started machine may take to answer on its Modbus port.
BOOT_TIMEOUT_S = float(os.environ.get("SOFTMOTION_E2E_BOOT_S", "30"))
#: Seconds the paper's curve may take to run (about 2.5 s of motion).
RUN_TIMEOUT_S = float(os.environ.get("SOFTMOTION_E2E_RUN_S", "30"))
#: Seconds the drives' feedback may take to show the last setpoint (many periods).
FEEDBACK_SETTLE_S = 0.5


def connect_hmi(
    process: subprocess.Popen, port: int, log: Path, *, timeout_s: float, client_timeout_s: float
) -> HmiClient:
    """An HMI client connected to the machine, once it listens and has a status.

    :raises AssertionError: with the machine's log, if the process exits first.
    """

    def check() -> None:
        if process.poll() is not None:
            raise AssertionError(f"softmotion run exited:\n{log.read_text()}")

    return connect_when_listening(
        port, timeout_s=timeout_s, client_timeout_s=client_timeout_s, check=check
    )


def connect_when_listening(
    port: int,
    *,
    timeout_s: float = 10.0,
    client_timeout_s: float = 2.0,
    check: Callable[[], None] = lambda: None,
) -> HmiClient:
    """An HMI client connected once the server listens and the machine has a status;
    ``check`` is called before each try (it raises to give up)."""
    deadline = time.monotonic() + timeout_s
    while True:
        check()
        client = HmiClient(port=port, timeout_s=client_timeout_s)
        try:
            client.connect()
            # The HMI answers before the cycle's first status (MACHINE_STATE STARTING).
            client.wait_for(lambda s: s.snapshot is not None, timeout_s, "the first status")
            return client
        except Exception:
            client.close()
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


class Machine:
    """``softmotion run`` in a subprocess with its own Modbus port."""

    def __init__(self, tmp: Path, **modbus: object) -> None:
        tmp.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        document = sim_document({"modbus": {"port": self.port, **modbus}})
        self.config = tmp / "machine.yaml"
        self.config.write_text(yaml.safe_dump(document))
        self.log = tmp / "run.log"
        self.steal_at_start_s = host_steal_s()
        with self.log.open("w") as log:
            self.process = subprocess.Popen(
                [str(SOFTMOTION), "run", "--config", str(self.config)],
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=ROOT,
            )
        self.client = connect_hmi(
            self.process, self.port, self.log, timeout_s=BOOT_TIMEOUT_S, client_timeout_s=5.0
        )

    def stop(self) -> None:
        self.client.close()
        self.process.send_signal(signal.SIGINT)
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(5)
        # Printed for pytest to show beside a failure: what the machine logged as going wrong,
        # and how long its host took the CPUs away meanwhile.
        for line in self.log.read_text(errors="replace").splitlines():
            if " WARNING " in line or " ERROR " in line:
                print(line)
        print(f"host steal time while the machine ran: {host_steal_s() - self.steal_at_start_s} s")

    def hmi(self, *argv: str) -> subprocess.CompletedProcess[str]:
        """``softmotion hmi --port P ARGV`` as a subprocess."""
        return subprocess.run(
            [str(SOFTMOTION), "hmi", "--port", str(self.port), *argv],
            capture_output=True,
            text=True,
            timeout=RUN_TIMEOUT_S + 10,
            cwd=ROOT,
        )


def enable_and_start(client: HmiClient) -> None:
    """ENABLE, wait for STANDBY, START."""
    assert client.command(CommandCode.ENABLE).result is CommandResult.DONE
    client.wait_for(lambda s: s.snapshot.state is MachineState.STANDBY, 10.0, "STANDBY")
    assert client.command(CommandCode.START).result is CommandResult.DONE


def end_positions(status: HmiStatus) -> np.ndarray:
    """The actual positions of the paper curve's axes."""
    return np.array([a.actual_mm for a in status.snapshot.axes][: PAPER.dimension])


def poll_status(port: int, stop: threading.Event, answers: list[int], errors: list[str]) -> None:
    """Read the status at 20 Hz until ``stop``; heartbeats to ``answers``, failures to
    ``errors``."""
    with HmiClient(port=port, timeout_s=2.0) as client:
        while not stop.is_set():
            started = time.monotonic()
            try:
                status = client.core_status()
                snapshot = status.snapshot
                assert isinstance(snapshot.state, MachineState)
                assert len(snapshot.axes) == 3 and 0 <= snapshot.progress_permille <= 1000
                answers.append(snapshot.heartbeat)
            except Exception as exc:
                errors.append(repr(exc))
            stop.wait(max(0.0, 0.05 - (time.monotonic() - started)))


def run_paper(machine: Machine) -> tuple[HmiStatus, int]:
    """Load, enable, start and run the paper's curve to its end; returns the final status and
    the periods missed during the motion."""
    client = machine.client
    client.load_curve(PAPER)
    enable_and_start(client)
    before = client.status().snapshot.stats.missed_periods
    status = client.wait_for(
        lambda s: s.snapshot.state is not MachineState.MOVING, RUN_TIMEOUT_S, "the end"
    )
    assert status.snapshot.state is MachineState.STANDBY, status.snapshot.message
    assert_drives_reach_the_end(client)
    return status, status.snapshot.stats.missed_periods - before


def assert_drives_reach_the_end(client: HmiClient) -> None:
    """The actual positions come to the paper curve's end point within 1 µm.

    The machine is done when it has sent the last setpoint; the drives' feedback shows it a
    period or more later, so a status read at that moment may still show the step before.
    """
    deadline = time.monotonic() + FEEDBACK_SETTLE_S
    status = client.status()
    while not np.allclose(end_positions(status), PAPER.end_point, rtol=0, atol=1e-3):
        if time.monotonic() > deadline:
            break
        time.sleep(0.01)
        status = client.status()
    np.testing.assert_allclose(end_positions(status), PAPER.end_point, rtol=0, atol=1e-3)


def run_paper_polled(machine: Machine, clients: int) -> tuple[int, list[int], list[str]]:
    """Run the paper's curve while ``clients`` HMI clients read the status at 20 Hz; returns
    the periods missed during the motion, the heartbeats read and the failed reads."""
    stop = threading.Event()
    answers: list[int] = []
    errors: list[str] = []
    pollers = [
        threading.Thread(target=poll_status, args=(machine.port, stop, answers, errors))
        for _ in range(clients)
    ]
    try:
        for poller in pollers:
            poller.start()
        _, missed = run_paper(machine)
    finally:
        stop.set()
        for poller in pollers:
            poller.join(5)
    return missed, answers, errors
