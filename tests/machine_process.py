"""Waiting for a ``softmotion run`` subprocess to answer on its Modbus port."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

from runtime.hmi.client import HmiClient


def connect_hmi(
    process: subprocess.Popen, port: int, log: Path, *, timeout_s: float, client_timeout_s: float
) -> HmiClient:
    """An HMI client connected to the machine, once it listens.

    :raises AssertionError: with the machine's log, if the process exits first.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        if process.poll() is not None:
            raise AssertionError(f"softmotion run exited:\n{log.read_text()}")
        client = HmiClient(port=port, timeout_s=client_timeout_s)
        try:
            client.connect()
            return client
        except Exception:
            client.close()
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)
