"""The HMI process's link to the machine: the :class:`MachineLink` protocol the server needs,
and :class:`SharedMachineLink`, its implementation on the runtime's shared memory.

The Modbus server (:mod:`runtime.hmi.server`) sees the machine only through a
:class:`MachineLink`: the cycle's last status snapshot, the HMI mailbox (commands judged by the
cycle, in order), the activity counter the cycle's HMI link watchdog watches, and the program
store where validated curves go for the planner. :class:`SharedMachineLink` carries it over
shared memory (a seqlock read of the status); tests use an in-process fake.

Threading: the server's event loop thread calls :meth:`MachineLink.snapshot`,
:meth:`MachineLink.post` and :meth:`MachineLink.note_activity` (they must not block; the shared
snapshot's decoding is cached per published period); a worker thread calls ``programs.add``.
"""

from __future__ import annotations

from typing import Protocol

from runtime.commands import Command
from runtime.config import MachineConfig
from runtime.programs import ProgramStore
from runtime.shared import SharedState
from runtime.status import StatusSnapshot


class MachineLink(Protocol):
    """The machine as the HMI process sees it."""

    config: MachineConfig
    """The whole machine description."""
    axis_names: tuple[str, ...]
    programs: ProgramStore
    """Where validated curves are stored for the planner."""

    def snapshot(self) -> StatusSnapshot | None:
        """The last period's status; None until the cycle has published its first one."""
        ...

    def post(self, command: Command) -> int | None:
        """Queue ``command`` for the cycle (judged there, in queue order, against the state it
        will run in). Returns its ticket (unique in this runtime, increasing), or None when the
        mailbox is full (nothing queued). Never blocks."""
        ...

    def note_activity(self) -> None:
        """An HMI heartbeat change or an accepted command: restarts the HMI link watchdog, which
        the cycle runs."""
        ...


class SharedMachineLink:
    """What the HMI server needs of the machine, over the runtime's shared memory."""

    def __init__(self, config: MachineConfig, shared: SharedState, programs: ProgramStore) -> None:
        self.config = config
        self.axis_names = tuple(axis.name for axis in config.axes)
        self.programs = programs
        self._shared = shared

    def snapshot(self) -> StatusSnapshot | None:
        """The last period's status; None until the cycle has published its first one."""
        return self._shared.status.snapshot()

    def post(self, command: Command) -> int | None:
        """Queue ``command`` for the cycle; its ticket, or None when the mailbox is full."""
        return self._shared.hmi_mailbox.post(command)

    def note_activity(self) -> None:
        """An HMI heartbeat change or an accepted command: restarts the HMI link watchdog."""
        self._shared.hmi_activity.value += 1
