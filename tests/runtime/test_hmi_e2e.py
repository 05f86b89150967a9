"""End to end: ``softmotion run`` on the simulated machine in a subprocess, driven over Modbus TCP
by the HMI client, the ``softmotion hmi`` command line and Debian's mbpoll.

mbpoll must be installed (``apt-get install -y mbpoll``; the test command installs it); where it
cannot be, set ``SOFTMOTION_NO_MBPOLL=1`` and the mbpoll test is skipped with that reason.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from machine_process import (
    PAPER,
    RUN_TIMEOUT_S,
    Machine,
    assert_drives_reach_the_end,
    enable_and_start,
    run_paper_polled,
)

from runtime.commands import ALLOWED, CommandCode, CommandOrigin, CommandResult
from runtime.hmi.client import CommandRefused, ModbusReplyError
from runtime.hmi.registers import FIELD, HMI_COMMANDS, MAGIC, MAP_VERSION
from runtime.hmi.upload import encode_staging, staging_of
from runtime.status import MachineState, WatchdogState

S = MachineState

pytestmark = pytest.mark.slow


@pytest.fixture
def machine(tmp_path: Path) -> Iterator[Machine]:
    running = Machine(tmp_path)
    yield running
    running.stop()


def _bad_uploads() -> list[tuple[str, CommandResult, object]]:
    cases: list[tuple[str, CommandResult, object]] = []
    points, knots, weights = PAPER.control_points, PAPER.knots, PAPER.weights

    def variant(**changes: object) -> object:
        arrays = {"degree": 3, "points": points.copy(), "knots": knots.copy()}
        arrays["weights"] = weights.copy()
        arrays.update(changes)
        return encode_staging(
            arrays["degree"], arrays["points"], arrays["knots"], arrays["weights"]
        )

    decreasing = knots.copy()
    decreasing[5] = 0.3
    cases.append(
        ("decreasing knots", CommandResult.CURVE_KNOTS_DECREASING, variant(knots=decreasing))
    )
    cases.append(("wrong knot count", CommandResult.CURVE_KNOT_COUNT, variant(knots=knots[:-1])))
    for label, value in (("weight 0", 0.0), ("negative weight", -0.5)):
        w = weights.copy()
        w[2] = value
        cases.append((label, CommandResult.CURVE_BAD_WEIGHT, variant(weights=w)))
    nan = points.copy()
    nan[3, 1] = float("nan")
    cases.append(("NaN", CommandResult.CURVE_NOT_FINITE, variant(points=nan)))
    cases.append(
        (
            "degree too high",
            CommandResult.CURVE_DEGREE_TOO_HIGH,
            variant(
                degree=7,
                points=points[:5],
                weights=weights[:5],
                knots=np.r_[np.zeros(8), np.ones(4)],
            ),
        )
    )
    outside = points.copy()
    outside[-1, 0] = 350.0
    cases.append(("outside travel", CommandResult.CURVE_OUTSIDE_TRAVEL, variant(points=outside)))
    return cases


def test_upload_reject_bad_curves_run_to_the_end(machine: Machine) -> None:
    client = machine.client
    assert client.status().snapshot.state is S.DISABLED
    assert client.load_curve(PAPER).result is CommandResult.DONE
    crc = staging_of(PAPER).crc32
    assert client.status().snapshot.program.crc32 == crc
    # Wrong CRC: the commit is answered, its own request carries the refusal.
    client.stage(staging_of(PAPER), crc32=crc ^ 0x1)
    with pytest.raises(CommandRefused) as refused:
        client.command(CommandCode.LOAD_CURVE, program_number=0)
    assert refused.value.result is CommandResult.CURVE_CRC_MISMATCH
    assert refused.value.outcome.ticket == 0 and "CURVE_CRC32" in refused.value.outcome.message
    # Every bad curve, then too many points for the staging area (refused at write time).
    for label, expected, staging in _bad_uploads():
        with pytest.raises(CommandRefused) as refused:
            client.load_curve(staging)
        assert refused.value.result is expected, label
        assert client.status().snapshot.program.crc32 == crc, label
    with pytest.raises(ModbusReplyError) as error:
        client.write(FIELD["CURVE_DEGREE"].address, [3, 3, 2001, 2005, 0, 0])
    assert error.value.exception_code == 3
    assert client.status().snapshot.program.crc32 == crc
    # The paper's curve is still the one that runs, to its end point.
    enable_and_start(client)
    result = machine.hmi("--timeout", str(RUN_TIMEOUT_S), "watch", "--until-idle")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "MOVING" in result.stdout
    status = client.status()
    assert status.snapshot.state is S.STANDBY
    assert status.snapshot.progress_permille == 1000
    assert_drives_reach_the_end(client)


def test_refused_commands_are_results_and_unmapped_addresses_answer_2(machine: Machine) -> None:
    client = machine.client
    state = client.status().snapshot.state
    refused_here = [c for c in HMI_COMMANDS if c not in ALLOWED[state]]
    assert refused_here
    for code in refused_here:
        with pytest.raises(CommandRefused) as refused:
            client.command(code)  # answered normally; the machine's refusal is its result
        assert refused.value.result is CommandResult.REJECTED_STATE, code
        assert refused.value.outcome.ticket > 0, code
    status = client.status()
    assert status.snapshot.state is state
    assert status.snapshot.last_command.origin is CommandOrigin.HMI
    for address in (22, 999, 21016):
        with pytest.raises(ModbusReplyError) as error:
            client.write(address, [1])
        assert error.value.exception_code == 2
    with pytest.raises(ModbusReplyError) as error:
        client.write(7, [1])  # reserved: only 0
    assert error.value.exception_code == 3
    result = machine.hmi(refused_here[0].name.lower().replace("_", "-"))
    assert result.returncode == 1
    assert "REJECTED_STATE" in result.stderr and "exception" not in result.stderr


def _mbpoll() -> str:
    path = shutil.which("mbpoll")
    if path is None:
        if os.environ.get("SOFTMOTION_NO_MBPOLL"):
            pytest.skip("mbpoll cannot be installed here (SOFTMOTION_NO_MBPOLL is set)")
        pytest.fail(
            "mbpoll is not installed: apt-get install -y mbpoll "
            "(or set SOFTMOTION_NO_MBPOLL=1 where it cannot be installed)"
        )
    return path


def _values(output: str) -> list[str]:
    """The values of mbpoll's ``[address]: value`` lines."""
    return [line.split(":", 1)[1].strip() for line in output.splitlines() if line.startswith("[")]


def test_mbpoll_reads_identity_and_status_and_writes_a_command(machine: Machine) -> None:
    mbpoll = _mbpoll()
    base = [mbpoll, "-m", "tcp", "-p", str(machine.port), "-1", "-0"]

    def run(*args: str) -> str:
        done = subprocess.run([*base, *args], capture_output=True, text=True, timeout=10)
        assert done.returncode == 0, done.stdout + done.stderr
        return done.stdout

    identity = _values(run("-a", "1", "-t", "3:hex", "-r", "0", "-c", "6", "127.0.0.1"))
    assert [int(v, 16) for v in identity] == [MAGIC, MAP_VERSION, 0x47F1, 0x2000, 0x1234, 0x5678]
    (test_float,) = _values(
        run("-a", "255", "-t", "3:float", "-B", "-r", "2", "-c", "1", "127.0.0.1")
    )
    assert float(test_float) == 123456.0
    state = _values(
        run("-t", "3", "-r", str(FIELD["MACHINE_STATE"].address), "-c", "1", "127.0.0.1")
    )
    assert int(state[0]) == machine.client.status().snapshot.state
    seq = (machine.client.read_holding(FIELD["COMMAND_SEQ"].address, 1)[0] + 1) & 0xFFFF
    run("-t", "4", "-r", "0", "127.0.0.1", str(int(CommandCode.SET_OVERRIDE)), str(seq), "800")
    outcome = machine.client.outcome(seq, CommandCode.SET_OVERRIDE, timeout_s=5.0)
    assert outcome.result is CommandResult.DONE
    assert machine.client.status().snapshot.override_percent == 80.0
    # A refused write: mbpoll reports the Modbus exception and exits 1.
    refused = subprocess.run(
        [*base, "-t", "4", "-r", "2", "127.0.0.1", "1600"],
        capture_output=True,
        text=True,
        timeout=10,
    )
    assert refused.returncode != 0 and "Illegal data value" in refused.stderr + refused.stdout


def test_ten_clients_at_20_hz_while_a_curve_runs(tmp_path: Path) -> None:
    # The curve runs to its end point with every read answered. How many periods the cycle
    # misses with and without the clients is a timing figure: bench/bench_hmi.py measures it.
    busy = Machine(tmp_path)
    try:
        _, answers, errors = run_paper_polled(busy, clients=10)
    finally:
        busy.stop()
    assert errors == []
    assert len(answers) >= 10 * 20 * 2  # ten clients, 20 Hz, the ~2.5 s of motion


def test_watchdog_holds_when_the_hmi_falls_silent(tmp_path: Path) -> None:
    timeout_ms = 300
    machine = Machine(tmp_path, watchdog={"timeout_ms": timeout_ms, "action": "hold"})
    try:
        client = machine.client
        assert client.identity.watchdog_timeout_ms == timeout_ms
        client.load_curve(PAPER)
        enable_and_start(client)
        started = time.monotonic()
        status = client.wait_for(lambda s: s.snapshot.state is S.HOLDING, 5.0, "the hold")
        # Within the timeout plus the watchdog's poll, one cycle and the status poll.
        assert time.monotonic() - started < timeout_ms / 1000 + 0.5
        last = status.snapshot.last_command
        assert (last.origin, last.code, last.seq) == (CommandOrigin.WATCHDOG, CommandCode.HOLD, 0)
        assert status.snapshot.watchdog is WatchdogState.TRIPPED
        assert status.snapshot.progress_permille < 1000
    finally:
        machine.stop()
