"""The drive scenarios of ``tests/drive_scenarios.py`` on SocketCAN vcan0, one process per drive.

Each simulated drive runs as ``python -m drives.sim --node N --interface socketcan --channel
vcan0`` with its quirks as options, so master and drives talk only through the kernel's CAN
layer. A drive is silenced with
SIGSTOP (like a cut cable: no heartbeat, no TPDO) and faulted with SIGUSR1, which the drive process
turns into ``SimulatedDrive.inject_fault()`` (EMCY 0x4210).

The vcan stage may run inside an emulated VM (``SOFTMOTION_VCAN_VM=1``) where Python runs about
nine times slower: process start-up, SDO round trips and thread wake-ups all stretch. There every
wall-clock wait is scaled by ``TIMEOUT_SCALE``, the heartbeat period is lengthened (its sender and
our cycle are threads that the VM can stall for tens of milliseconds, which would otherwise read as
a lost heartbeat) and the cycle period is longer, so that the drives' SYNC-loss supervision (a
multiple of 0x1006) is not tripped by a stalled test loop. The assertions stay the same: they are
stated in heartbeat periods and cycles, not in absolute time.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Mapping, Sequence

import can
from drive_scenarios import DriveScenarios

from drives.bus import open_bus
from drives.sim import DriveQuirks
from drives.sim.service import quirk_arguments

CHANNEL = "vcan0"
IN_VM = os.environ.get("SOFTMOTION_VCAN_VM") == "1"
#: The drives' SYNC-loss limit in 0x1006 periods; generous for the same reason as on virtual.
SYNC_TIMEOUT_FACTOR = 50.0
#: Seconds a drive process gets to exit on SIGTERM before it is killed.
EXIT_TIMEOUT_S = 10.0


class ProcessDrives:
    """One ``python -m drives.sim`` process per node on SocketCAN."""

    def __init__(
        self, channel: str, node_ids: Sequence[int], quirks: Mapping[int, DriveQuirks]
    ) -> None:
        self.processes: dict[int, subprocess.Popen[bytes]] = {}
        try:
            for node_id in node_ids:
                self.processes[node_id] = subprocess.Popen(
                    [
                        sys.executable,
                        "-m",
                        "drives.sim",
                        "--node",
                        str(node_id),
                        "--interface",
                        "socketcan",
                        "--channel",
                        channel,
                        "--sync-timeout-factor",
                        str(SYNC_TIMEOUT_FACTOR),
                        "--log-level",
                        "WARNING",
                        *quirk_arguments(quirks.get(node_id, DriveQuirks())),
                    ]
                )
        except BaseException:
            self.close()
            raise

    def _pid(self, node_id: int) -> int:
        process = self.processes[node_id]
        assert process.poll() is None, f"drive process {node_id} exited with {process.returncode}"
        return process.pid

    def stop_answering(self, node_id: int) -> None:
        os.kill(self._pid(node_id), signal.SIGSTOP)

    def inject_fault(self, node_id: int, emcy_code: int) -> None:
        assert emcy_code == 0x4210, "the drive process injects its default fault only"
        os.kill(self._pid(node_id), signal.SIGUSR1)

    def close(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                os.kill(process.pid, signal.SIGCONT)
                process.terminate()
        for process in self.processes.values():
            try:
                process.wait(timeout=EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


class TestDrivesVcan(DriveScenarios):
    TIMEOUT_SCALE = 10.0 if IN_VM else 1.0
    HEARTBEAT_MS = 1000 if IN_VM else 100
    PERIOD_S = 0.020 if IN_VM else 0.004
    # The VM can deliver a drive's TPDO a few periods late on its emulated CPUs.
    STALE_FEEDBACK_CYCLES = 10 if IN_VM else 3

    def make_channel(self) -> str:
        return CHANNEL

    def open_bus(self, channel: str, **options: object) -> can.BusABC:
        return open_bus("socketcan", channel, **options)

    def launch_drives(
        self, channel: str, node_ids: Sequence[int], quirks: Mapping[int, DriveQuirks]
    ) -> ProcessDrives:
        return ProcessDrives(channel, node_ids, quirks)
