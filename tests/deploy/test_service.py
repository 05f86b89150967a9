"""deploy/: the systemd unit, its drop-in and the service user, checked by systemd's own tools
(``systemd-analyze verify``, ``systemd-sysusers``) and for what they must grant."""

from __future__ import annotations

import configparser
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
UNIT = DEPLOY / "softmotion.service"
DROP_IN = DEPLOY / "softmotion.service.d" / "modbus-port-below-1024.conf"
SOFTMOTION = Path(sys.executable).with_name("softmotion")


def systemd_tool(name: str) -> str:
    """The path of a systemd tool; skipped where it is absent, except under CI (which installs
    Debian's systemd package through scripts/system-packages)."""
    path = shutil.which(name) or shutil.which(name, path="/usr/bin:/bin:/usr/sbin:/sbin")
    if path is None:
        message = f"{name} is not installed (Debian package systemd; scripts/system-packages)"
        if os.environ.get("CI", "") not in ("", "false", "0"):
            pytest.fail(message)
        pytest.skip(message)
    return path


def service_section(*paths: Path) -> dict[str, list[str]]:
    """Every key of [Service] in ``paths`` (unit, then drop-ins), values in order."""
    keys: dict[str, list[str]] = {}
    for path in paths:
        parser = configparser.ConfigParser(strict=False, interpolation=None)
        parser.optionxform = str  # type: ignore[assignment,method-assign]
        parser.read_string(path.read_text())
        for key, value in parser["Service"].items():
            keys.setdefault(key, []).append(value)
    return keys


def test_systemd_analyze_verifies_the_unit_and_its_drop_in(tmp_path: Path) -> None:
    analyze = systemd_tool("systemd-analyze")
    # verify needs ExecStart's program to exist: the unit's /opt/softmotion is this venv here.
    unit = tmp_path / UNIT.name
    unit.write_text(UNIT.read_text().replace("/opt/softmotion/bin/softmotion", str(SOFTMOTION)))
    shutil.copytree(DROP_IN.parent, tmp_path / DROP_IN.parent.name)
    done = subprocess.run(
        [analyze, "verify", "--man=no", str(unit)], capture_output=True, text=True, check=False
    )
    # verify exits 0 on unknown keys and merely prints them: any output is a finding.
    assert (done.returncode, done.stdout + done.stderr) == (0, "")


def test_systemd_sysusers_creates_the_service_user(tmp_path: Path) -> None:
    sysusers = systemd_tool("systemd-sysusers")
    (tmp_path / "etc").mkdir()
    subprocess.run(
        [sysusers, f"--root={tmp_path}", str(DEPLOY / "softmotion.sysusers")],
        capture_output=True,
        check=True,
    )
    (entry,) = [
        line
        for line in (tmp_path / "etc" / "passwd").read_text().splitlines()
        if line.startswith("softmotion:")
    ]
    _, _, uid, _, _, _, shell = entry.split(":")
    assert 0 < int(uid) < 1000 and shell.endswith("nologin")


def test_the_unit_grants_only_what_the_cycle_needs() -> None:
    service = service_section(UNIT)
    assert service["User"] == ["softmotion"]
    assert service["AmbientCapabilities"] == ["CAP_SYS_NICE CAP_IPC_LOCK"]
    assert service["CapabilityBoundingSet"] == ["CAP_SYS_NICE CAP_IPC_LOCK"]
    assert service["LimitMEMLOCK"] == ["infinity"]
    assert int(service["LimitRTPRIO"][0]) >= 80  # the shipped configs' cycle.realtime.priority
    assert service["Restart"] == ["on-failure"]
    assert service["ConfigurationDirectory"] == ["softmotion"]
    assert service["ExecStart"] == [
        "/opt/softmotion/bin/softmotion run --config /etc/softmotion/softmotion.yaml"
    ]
    with_port_502 = service_section(UNIT, DROP_IN)
    assert with_port_502["AmbientCapabilities"][-1] == "CAP_NET_BIND_SERVICE"
    assert "always starts Disabled" in UNIT.read_text()
