"""``softmotion doctor`` as an operator runs it: the report, its fixes and its exit status."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from machine_files import DOCTOR_CHECKS, report_lines, write_machine

SOFTMOTION = Path(sys.executable).with_name("softmotion")


def doctor(config: Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(SOFTMOTION), "doctor", "--config", str(config), "--latency-s", "0.3"],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_missing_can_interface_fails_with_its_fix_and_exit_1(tmp_path: Path) -> None:
    config = write_machine(
        tmp_path,
        {"can": {"interface": "socketcan", "channel": "smnocan9"}, "simulation": {"drives": False}},
    )
    done = doctor(config, tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    lines = report_lines(done.stdout)
    assert lines["can link"].startswith("fail  can link       no interface smnocan9 ("), lines
    assert "; fix: connect the adapter and load its driver" in lines["can link"]
    assert set(DOCTOR_CHECKS) <= set(lines), done.stdout
    assert done.stdout.splitlines()[-1].endswith(
        f"{sum(line.startswith('fail') for line in lines.values())} fail"
    )


def test_an_invalid_configuration_fails_and_names_the_key(tmp_path: Path) -> None:
    config = write_machine(tmp_path, {"cycle": {"period_ms": 0.1}})
    done = doctor(config, tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    line = report_lines(done.stdout)["config"]
    assert "config: cycle.period_ms = 0.1: expected a value in 0.5..100" in line
    assert "ipc-example.yaml lists every key" in line


def test_exit_status_follows_the_report(tmp_path: Path) -> None:
    done = doctor(write_machine(tmp_path), tmp_path)
    lines = report_lines(done.stdout)
    assert set(lines) == set(DOCTOR_CHECKS), done.stdout + done.stderr
    failed = [line for line in lines.values() if line.startswith("fail")]
    assert done.returncode == (1 if failed else 0), done.stdout
    assert lines["latency"].split()[2].isdigit()  # "<n> wake-ups in 0.3 s at 4 ms: p50 ..."
    assert " wake-ups in 0.3 s at 4 ms: p50 " in lines["latency"]
