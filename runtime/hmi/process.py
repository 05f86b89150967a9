"""The HMI process: the Modbus TCP server, on the machine's shared memory.

Started (and restarted when it dies) by the supervisor (:func:`hmi_main`). It runs at the normal
scheduling class (:mod:`runtime.processes` says why) and never touches the cycle: status comes
from the shared snapshot, commands go to the HMI mailbox, curves to the program store
(:class:`runtime.hmi.link.SharedMachineLink`).
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path

from runtime.config import MachineConfig
from runtime.hmi.link import SharedMachineLink
from runtime.hmi.server import HmiServer
from runtime.logs import queued_logging
from runtime.processes import freeze_start_up_objects, prepare_child
from runtime.programs import ProgramStore
from runtime.shared import SharedState, shared_path


def hmi_main(config: MachineConfig, run_dir: str, log_level: str, parent_pid: int) -> None:
    """The HMI process's entry point: serve until SIGTERM."""
    prepare_child(parent_pid=parent_pid)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    with queued_logging(log_level):
        shared = SharedState.attach(shared_path(run_dir), tuple(axis.name for axis in config.axes))
        link = SharedMachineLink(config, shared, ProgramStore(Path(run_dir) / "programs"))
        server = HmiServer(link, config.modbus)
        server.start()
        freeze_start_up_objects()
        try:
            while not stop.wait(0.5):
                pass
        finally:
            server.stop()
