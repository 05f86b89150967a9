"""Simulated CiA 402 drives on a CAN bus: in-process for tests, or as their own process.

:mod:`drives.sim.drive` holds the drive, :mod:`drives.sim.dynamics` its motion model and
:mod:`drives.sim.service` the ``softmotion sim-drive`` process entry.
"""

from drives.sim.drive import (
    DriveModel,
    SimulatedDrive,
    SimulatedDriveSet,
    start_simulated_drives,
)

__all__ = ["DriveModel", "SimulatedDrive", "SimulatedDriveSet", "start_simulated_drives"]
