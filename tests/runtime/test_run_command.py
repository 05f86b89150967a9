"""``softmotion run`` as the main job, in a subprocess: the demo, a clean SIGTERM, a bad config."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import yaml
from sim_machine import free_port, sim_document

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow


def machine_config(tmp_path: Path) -> Path:
    document = sim_document(
        {"can": {"channel": f"run-{uuid.uuid4().hex[:8]}"}, "modbus": {"port": free_port()}}
    )
    path = tmp_path / "machine.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def softmotion(*args: str) -> list[str]:
    return [sys.executable, "-m", "runtime.cli", *args]


def test_demo_runs_the_paper_curve_and_prints_its_summary(tmp_path: Path) -> None:
    done = subprocess.run(
        softmotion("run", "--config", str(machine_config(tmp_path)), "--demo"),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    assert "demo summary" in out
    assert "curve finished" in out
    for axis, end in (("X", "132.0000"), ("Y", "40.0000"), ("Z", "41.0000")):
        assert f"final {axis}: {end} mm" in out
        assert f"max following error {axis}:" in out
    assert "cycle lateness      p50" in out
    assert "missed periods" in out


def test_sigterm_stops_the_machine_cleanly(tmp_path: Path) -> None:
    process = subprocess.Popen(
        softmotion("run", "--config", str(machine_config(tmp_path))),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        lines = []
        for line in process.stdout:
            lines.append(line)
            if "machine running" in line:
                break
            assert time.monotonic() < deadline, "".join(lines)
        time.sleep(0.5)
        process.send_signal(signal.SIGTERM)
        rest, _ = process.communicate(timeout=30)
    finally:
        process.kill()
    log = "".join(lines) + rest
    assert process.returncode == 0, log
    assert "shutting down" in log
    assert "Traceback" not in log


def test_bad_config_exits_2_without_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    document = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    document["axes"][1]["node_id"] = 0
    bad.write_text(yaml.safe_dump(document))
    done = subprocess.run(
        softmotion("run", "--config", str(bad)), cwd=ROOT, capture_output=True, text=True
    )
    assert done.returncode == 2
    assert done.stderr.strip() == (
        "softmotion: config: axes[1].node_id = 0: expected a value in 1..127"
    )
    assert "Traceback" not in done.stderr


def test_version_and_help() -> None:
    version = subprocess.run(softmotion("--version"), cwd=ROOT, capture_output=True, text=True)
    assert version.returncode == 0 and version.stdout.startswith("softmotion ")
    helped = subprocess.run(softmotion("--help"), cwd=ROOT, capture_output=True, text=True)
    for command in ("run", "plan", "hmi", "sim-drive"):
        assert command in helped.stdout


def test_demo_with_a_drive_faulted_at_power_on_says_so_and_exits_1(tmp_path: Path) -> None:
    path = machine_config(tmp_path)
    document = yaml.safe_load(path.read_text())
    document["simulation"]["quirks"] = {"Y": {"fault_at_power_on": True}}
    path.write_text(yaml.safe_dump(document))
    done = subprocess.run(
        softmotion("run", "--config", str(path), "--demo"),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr
    assert "softmotion: drives not enabled: error stop: axis Y: " in done.stderr
    assert "0x8130" in done.stderr  # the cause the drive gives, in its EMCY or in 0x603F
