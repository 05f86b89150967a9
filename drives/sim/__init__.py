"""Simulated CiA 402 drives on a CAN bus: in-process for tests, or as their own process.

:mod:`drives.sim.drive` holds the drive, :mod:`drives.sim.dynamics` its motion model,
:mod:`drives.sim.quirks` the switches that make it behave like other vendors' drives and
:mod:`drives.sim.service` the ``softmotion sim-drive`` process entry.
"""

from drives.sim.drive import (
    DriveModel,
    SimulatedDrive,
    SimulatedDriveSet,
    start_simulated_drives,
)
from drives.sim.quirks import DriveQuirks

__all__ = [
    "DriveModel",
    "DriveQuirks",
    "SimulatedDrive",
    "SimulatedDriveSet",
    "start_simulated_drives",
]
