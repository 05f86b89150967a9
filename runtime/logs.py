"""Logging that never blocks the thread that logs.

A log line written from the cyclic thread (a state change, a command) or from a CAN receive
thread (a drive's state transition) is a write to a terminal, pipe or file, and a write can
block: on a host busy with other I/O the kernel throttles writers of dirty pages, and a full
pipe blocks until its reader catches up. A receive thread held up that way delays every frame
behind it, and the master sees a drive fall silent. So every record goes to an in-memory queue
(formatting its message is the only work left in the thread that logs) and one writer thread
of its own does the output; it runs at the lowest real-time priority (:mod:`runtime.priorities`).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from logging.handlers import QueueHandler
from typing import Final

#: Name of the writer thread (the runtime gives it the lowest real-time priority).
LOG_WRITER_THREAD: Final = "log-writer"
#: Line format of every log record.
LOG_FORMAT: Final = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


@contextmanager
def queued_logging(level: str | int, output: logging.Handler | None = None) -> Iterator[None]:
    """Within the block, the root logger's records are queued by the threads that log and
    written by one writer thread; on leaving, what is queued is written.

    Like :func:`logging.basicConfig`, it leaves a root logger that already has handlers (an
    embedding application, a test runner) as it is.

    :param level: root logger level, e.g. ``"INFO"``.
    :param output: the handler that writes (default: stderr with :data:`LOG_FORMAT`).
    """
    root = logging.getLogger()
    if root.handlers:
        yield
        return
    if output is None:
        output = logging.StreamHandler()
        output.setFormatter(logging.Formatter(LOG_FORMAT))
    records: queue.SimpleQueue[logging.LogRecord | None] = queue.SimpleQueue()

    def write() -> None:
        while (record := records.get()) is not None:
            output.handle(record)

    writer = threading.Thread(target=write, name=LOG_WRITER_THREAD, daemon=True)
    handler = QueueHandler(records)
    root.setLevel(level)
    root.addHandler(handler)
    writer.start()
    try:
        yield
    finally:
        root.removeHandler(handler)
        records.put(None)
        writer.join()
        output.flush()
