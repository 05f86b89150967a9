"""The wheel a user builds (``python -m build``), installed into a fresh virtual environment and
run from an empty directory: version, doctor, the demo, plan and a simulated drive.

The build works on a copy of the source tree (a build writes ``build/`` and egg-info beside the
sources). pip may reuse its cache and installs the dependencies from the package index.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from machine_files import DOCTOR_CHECKS, ROOT, report_lines
from sim_machine import HOST_STALL_LIMITS

from runtime.version import VERSION

pytestmark = pytest.mark.slow

SOURCE_IGNORED = shutil.ignore_patterns(
    ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", ".*_cache", ".hypothesis", "out"
)


def run(*command: str | Path, cwd: Path, timeout_s: float = 600) -> subprocess.CompletedProcess:
    done = subprocess.run(
        [str(part) for part in command], cwd=cwd, capture_output=True, text=True, timeout=timeout_s
    )
    assert done.returncode == 0, f"{command}:\n{done.stdout}\n{done.stderr}"
    return done


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bin directory of a fresh venv with the built wheel installed."""
    base = tmp_path_factory.mktemp("wheel")
    source = base / "source"
    shutil.copytree(ROOT, source, ignore=SOURCE_IGNORED)
    run(sys.executable, "-m", "build", "--wheel", "--outdir", base / "dist", cwd=source)
    (wheel,) = (base / "dist").glob("softmotion-*.whl")
    assert wheel.name == f"softmotion-{VERSION}-py3-none-any.whl"
    venv = base / "venv"
    run(sys.executable, "-m", "venv", venv, cwd=base)
    run(venv / "bin" / "python", "-m", "pip", "install", "-q", wheel, cwd=base)
    return venv / "bin"


@pytest.fixture
def empty_dir(tmp_path: Path) -> Path:
    directory = tmp_path / "elsewhere"
    directory.mkdir()
    return directory


def shipped(bin_dir: Path, relative: str) -> Path:
    """A file of the installed package data runtime/configs."""
    (path,) = (bin_dir.parent / "lib").glob(f"python3*/site-packages/runtime/configs/{relative}")
    return path


def test_version_is_the_one_of_the_sources(installed: Path, empty_dir: Path) -> None:
    assert run(installed / "softmotion", "--version", cwd=empty_dir).stdout == (
        f"softmotion {VERSION}\n"
    )
    metadata = run(
        installed / "python",
        "-c",
        "import importlib.metadata as m; print(m.version('softmotion'))",
        cwd=empty_dir,
    )
    assert metadata.stdout.strip() == VERSION


def test_doctor_reports_every_check_on_the_shipped_machine(
    installed: Path, empty_dir: Path
) -> None:
    done = subprocess.run(
        [str(installed / "softmotion"), "doctor", "--latency-s", "0.5"],
        cwd=empty_dir,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.stdout.startswith(f"softmotion {VERSION} doctor: "), done.stdout + done.stderr
    lines = report_lines(done.stdout)
    assert set(lines) == set(DOCTOR_CHECKS), done.stdout + done.stderr
    assert f"ok    config         {shipped(installed, 'sim.yaml')}: X node 1" in lines["config"]
    failed = [line for line in lines.values() if line.startswith("fail")]
    assert done.returncode == (1 if failed else 0), done.stdout


def test_the_demo_runs_from_any_directory(installed: Path, empty_dir: Path) -> None:
    """The packaged demo curve with the packaged configuration, given the suite's host-stall
    tolerance (the doctor test above checks that the configuration is found by default)."""
    config = empty_dir.parent / "sim.yaml"
    document = yaml.safe_load(shipped(installed, "sim.yaml").read_text())
    for section, values in HOST_STALL_LIMITS.items():
        document[section].update(values)
    config.write_text(yaml.safe_dump(document))
    done = run(
        installed / "softmotion", "run", "--config", config, "--demo", cwd=empty_dir, timeout_s=120
    )
    assert "demo summary" in done.stdout, done.stdout + done.stderr
    assert list(empty_dir.iterdir()) == []


def test_plan_a_shipped_curve_and_run_a_simulated_drive(installed: Path, empty_dir: Path) -> None:
    plan = run(
        installed / "softmotion", "plan", shipped(installed, "curves/paper.yaml"), cwd=empty_dir
    )
    assert "length" in plan.stdout
    log = empty_dir.parent / "sim-drive.log"
    with log.open("w") as output:
        drive = subprocess.Popen(
            [str(installed / "softmotion"), "sim-drive", "--node", "5", "--interface", "virtual"],
            cwd=empty_dir,
            stdout=output,
            stderr=subprocess.STDOUT,
        )
    deadline = time.monotonic() + 30
    while "simulated drive node 5 on virtual" not in log.read_text():
        assert drive.poll() is None and time.monotonic() < deadline, log.read_text()
        time.sleep(0.1)
    drive.send_signal(signal.SIGTERM)
    assert drive.wait(30) == 0, log.read_text()
