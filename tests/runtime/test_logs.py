"""Queued logging: records from any thread come out in order through one writer thread."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from runtime.logs import LOG_WRITER_THREAD, queued_logging


class Recorder(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[tuple[str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append((threading.current_thread().name, record.getMessage()))


@contextmanager
def bare_root() -> Iterator[logging.Logger]:
    """The root logger without handlers (pytest's own set aside), restored afterwards."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    root.handlers.clear()
    try:
        yield root
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


def test_records_of_every_thread_are_written_by_the_writer_in_order():
    recorder = Recorder()
    with bare_root() as root:
        with queued_logging("INFO", recorder):
            logger = logging.getLogger("softmotion.test")
            logger.info("first %d", 1)
            worker = threading.Thread(target=lambda: logger.warning("from %s", "a thread"))
            worker.start()
            worker.join()
            logger.debug("below the level")
            logger.info("last")
        assert root.handlers == []
    assert recorder.lines == [
        (LOG_WRITER_THREAD, "first 1"),
        (LOG_WRITER_THREAD, "from a thread"),
        (LOG_WRITER_THREAD, "last"),
    ]


def test_a_configured_root_logger_is_left_alone():
    configured = Recorder()
    with bare_root() as root:
        root.addHandler(configured)
        root.setLevel(logging.WARNING)
        with queued_logging("DEBUG", Recorder()):
            logging.getLogger("softmotion.test").warning("direct")
        assert root.handlers == [configured] and root.level == logging.WARNING
    assert configured.lines == [(threading.current_thread().name, "direct")]
