"""Logging that never blocks the thread that logs.

A log line is a write to a terminal, pipe or file, and a write can block: on a host busy with
other I/O the kernel throttles writers of dirty pages, and a full pipe blocks until its reader
catches up. So no process of the runtime writes log output from the thread that logs:

- the cycle process puts each record into the shared log ring (:class:`SharedLogHandler`,
  :class:`runtime.shared.LogRing`): formatting its message is the only work left in the cycle,
  and a record that does not fit is dropped and counted; the supervisor writes them out
  (:func:`forward_shared_log`);
- every other process queues its records in memory and one writer thread of its own does the
  output (:func:`queued_logging`).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from logging.handlers import QueueHandler
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from runtime.shared import LogRing

#: Name of the writer thread (the runtime gives it the lowest real-time priority).
LOG_WRITER_THREAD: Final = "log-writer"
#: Line format of every log record.
LOG_FORMAT: Final = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


#: Libraries whose INFO records are noise at the runtime's INFO level (canopen logs every SDO
#: transfer and PDO mapping step).
QUIET_LIBRARIES: Final = ("canopen",)


def quiet_libraries(level: str | int) -> None:
    """Below DEBUG, keep chatty libraries at WARNING (every process of the runtime calls it)."""
    if logging.getLevelName(level) != "DEBUG" and level != logging.DEBUG:
        for name in QUIET_LIBRARIES:
            logging.getLogger(name).setLevel(logging.WARNING)


@contextmanager
def queued_logging(level: str | int, output: logging.Handler | None = None) -> Iterator[None]:
    """Within the block, the root logger's records are queued by the threads that log and
    written by one writer thread; on leaving, what is queued is written.

    Like :func:`logging.basicConfig`, it leaves a root logger that already has handlers (an
    embedding application, a test runner) as it is.

    :param level: root logger level, e.g. ``"INFO"``.
    :param output: the handler that writes (default: stderr with :data:`LOG_FORMAT`).
    """
    quiet_libraries(level)
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


class SharedLogHandler(logging.Handler):
    """Log records of the cycle process into the shared log ring (:class:`runtime.shared.LogRing`):
    formatting the message is the only work left in the cycle; a record that does not fit is
    dropped and counted, never waited for."""

    def __init__(self, ring: LogRing) -> None:
        super().__init__()
        self._ring = ring

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
            if record.exc_info:
                message += "\n" + logging.Formatter().formatException(record.exc_info)
            self._ring.write(record.levelno, record.name, message)
        except Exception:
            self.handleError(record)


def forward_shared_log(ring: LogRing) -> int:
    """Emit every record queued in ``ring`` through this process's logging (the supervisor).

    :returns: the number of records forwarded.
    """
    entries = ring.read()
    for entry in entries:
        logging.getLogger(entry.logger).log(entry.level, "%s", entry.message)
    return len(entries)
