"""The master with three simulated drives in-process on python-can's ``virtual`` bus."""

from __future__ import annotations

import uuid
from collections.abc import Sequence

import can
from drive_scenarios import DriveScenarios

from drives.bus import open_bus
from drives.sim import DriveModel, SimulatedDriveSet, start_simulated_drives

#: The drives' SYNC-loss limit in periods (0x1006). The test loop runs faster than real time,
#: but a 2-core CI machine can stall the test thread for longer than the default 2 periods
#: (8 ms); the scenarios here are not about SYNC loss.
SYNC_TIMEOUT_FACTOR = 50.0


class InProcessDrives:
    """Simulated drives on their own Network in this process."""

    def __init__(self, channel: str, node_ids: Sequence[int]) -> None:
        self.drive_set: SimulatedDriveSet = start_simulated_drives(
            "virtual",
            channel,
            list(node_ids),
            model=DriveModel(sync_timeout_factor=SYNC_TIMEOUT_FACTOR),
        )

    def stop_answering(self, node_id: int) -> None:
        self.drive_set.drives[node_id].stop_answering()

    def inject_fault(self, node_id: int, emcy_code: int) -> None:
        self.drive_set.drives[node_id].inject_fault(emcy_code)

    def close(self) -> None:
        self.drive_set.close()


class TestDrivesVirtual(DriveScenarios):
    def make_channel(self) -> str:
        return f"drives-{uuid.uuid4().hex}"

    def open_bus(self, channel: str) -> can.BusABC:
        return open_bus("virtual", channel)

    def launch_drives(self, channel: str, node_ids: Sequence[int]) -> InProcessDrives:
        return InProcessDrives(channel, node_ids)
