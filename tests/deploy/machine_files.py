"""Machine descriptions for tests that drive the ``softmotion`` command from outside: the
shipped simulated machine with its own Modbus port and virtual CAN channel, changed as asked."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import yaml
from sim_machine import free_port, sim_document

ROOT = Path(__file__).resolve().parents[2]

#: Every check ``softmotion doctor`` reports for a configuration that loads (virtual bus).
DOCTOR_CHECKS = (
    "kernel",
    "timer",
    "cpu pinning",
    "cpu isolation",
    "cpu frequency",
    "rtprio",
    "memlock",
    "realtime",
    "config",
    "eds",
    "can link",
    "modbus port",
    "modbus access",
    "shared memory",
    "latency",
)


def write_machine(tmp_path: Path, changes: dict[str, dict[str, Any]] | None = None) -> Path:
    """configs/sim.yaml with a fresh virtual channel and Modbus port, sections updated by
    ``changes`` (``{"can": {"interface": "socketcan"}}``); returns the file's path."""
    document = sim_document(
        {"can": {"channel": f"deploy-{uuid.uuid4().hex[:8]}"}, "modbus": {"port": free_port()}},
        changes or {},
        host_stall_limits=False,
    )
    path = tmp_path / "machine.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


def report_lines(stdout: str) -> dict[str, str]:
    """The doctor's check lines by check name (the first line of each name)."""
    lines: dict[str, str] = {}
    for line in stdout.splitlines():
        # "<verdict:4>  <name:14> <detail>[; fix: <fix>]"
        if line[:4].strip() in ("ok", "warn", "fail"):
            lines.setdefault(line[6:20].strip(), line)
    return lines
