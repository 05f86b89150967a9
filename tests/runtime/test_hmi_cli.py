"""``softmotion hmi`` against the HMI server and a fake machine: every command waits for the
outcome of its own request, and enable, disable and reset for the state they lead to."""

from __future__ import annotations

import argparse
import io
from dataclasses import replace
from pathlib import Path

import pytest
from fake_machine_link import SIM, FakeMachine, hmi_config

from runtime.config import ProgramsConfig
from runtime.hmi import cli
from runtime.hmi.server import HmiServer
from runtime.status import FaultKind, MachineState

ROOT = Path(__file__).resolve().parents[2]
PAPER_FILE = ROOT / "configs" / "curves" / "paper.yaml"
S = MachineState


def _cli(port: int, *argv: str) -> tuple[int, str]:
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    out = io.StringIO()
    return cli.run(parser.parse_args(["--port", str(port), *argv]), out), out.getvalue()


def test_status_commands_and_refusals(
    hmi: HmiServer, fake: FakeMachine, capsys: pytest.CaptureFixture[str]
) -> None:
    code, text = _cli(hmi.port, "status")
    assert code == 0 and "machine   DISABLED" in text and "axis X" in text
    assert "status    STATUS_VALID" in text and "statusword 0x0250  node 1 " in text
    code, _ = _cli(hmi.port, "start")
    assert code == 1
    err = capsys.readouterr().err
    assert "REJECTED_STATE" in err and "exception" not in err
    code, text = _cli(hmi.port, "enable")
    assert code == 0 and text.startswith("enable: seq 2: DONE")
    assert fake.snapshot().state is S.STANDBY
    code, text = _cli(hmi.port, "load", str(PAPER_FILE))
    assert code == 0 and "7 points" in text and "program" in text
    assert _cli(hmi.port, "override", "80")[0] == 0
    assert fake.snapshot().override_percent == 80.0
    assert _cli(hmi.port, "override", "151")[0] == 1
    assert "illegal data value" in capsys.readouterr().err
    code, text = _cli(hmi.port, "watch", "--count", "3", "--interval", "0.01")
    assert code == 0 and len(text.splitlines()) == 3
    code, text = _cli(hmi.port, "watch", "--until-idle", "--interval", "0.01")
    assert code == 0 and text.startswith("STANDBY")


def test_reset_waits_for_its_own_outcome_not_the_state_it_starts_from(
    hmi: HmiServer, fake: FakeMachine
) -> None:
    assert _cli(hmi.port, "enable")[0] == 0
    fake.fault(FaultKind.FOLLOWING_ERROR, "axis X: following error", axis="X")
    code, text = _cli(hmi.port, "reset")  # the fake takes 10 periods to leave ERROR_STOP
    assert code == 0, text
    assert text.startswith("reset: seq 2: DONE")
    assert fake.snapshot().state is S.STANDBY
    code, _ = _cli(hmi.port, "reset")  # nothing to reset now: its own refusal
    assert code == 1


def test_disable_from_error_stop(hmi: HmiServer, fake: FakeMachine) -> None:
    fake.fault(FaultKind.DRIVE_FAULT, "node 1: EMCY 0x2310", axis="X")
    code, _ = _cli(hmi.port, "disable")
    assert code == 0 and fake.snapshot().state is S.DISABLED


def test_library_load_program_next_and_abort(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    library = tmp_path / "library"
    library.mkdir()
    (library / "paper.yaml").write_bytes(PAPER_FILE.read_bytes())
    config = replace(SIM, programs=ProgramsConfig(library_dir=library))
    machine = FakeMachine(tmp_path / "store", config=config).start()
    try:
        with HmiServer(machine, hmi_config()) as hmi:
            code, text = _cli(hmi.port, "library")
            assert code == 0 and "paper.yaml  7 points  173." in text
            assert _cli(hmi.port, "library", "2") == (1, "   2  -  NOT_FOUND\n")
            code, text = _cli(hmi.port, "load-program", "1")
            assert code == 0 and "program" in text and "'paper.yaml'" in text
            assert _cli(hmi.port, "override", "10")[0] == 0
            assert _cli(hmi.port, "enable")[0] == 0
            assert _cli(hmi.port, "start")[0] == 0
            code, text = _cli(hmi.port, "load-program", "1")
            assert code == 0 and text.startswith("loaded library program 1: next program")
            assert machine.snapshot().next_program is not None
            assert _cli(hmi.port, "clear-next")[0] == 0
            assert machine.snapshot().next_program is None
            assert _cli(hmi.port, "load-program", "5")[0] == 1
            assert "NO_SUCH_PROGRAM" in capsys.readouterr().err
            assert _cli(hmi.port, "abort-upload") == (0, "staging area cleared and free\n")
    finally:
        machine.close()


def test_cli_reports_an_unreachable_machine(capsys: pytest.CaptureFixture[str]) -> None:
    code, _ = _cli(1, "status")
    assert code == 1
    assert "cannot connect" in capsys.readouterr().err


def test_status_while_the_runtime_starts(tmp_path: Path) -> None:
    machine = FakeMachine(tmp_path)
    with HmiServer(machine, hmi_config()) as hmi:
        code, text = _cli(hmi.port, "status")
    assert code == 0 and "STARTING" in text
