"""Real-time settings: each one applied or refused with exactly one clear log line."""

from __future__ import annotations

import errno
import gc
import logging
import os
import subprocess
import sys
import threading

import pytest

from runtime import realtime
from runtime.config import RealtimeConfig
from runtime.realtime import SWITCH_INTERVAL_S, AppliedRealtime, GcPolicy, apply_realtime

NOTHING = RealtimeConfig(priority=0, cpu=None, lock_memory=False, gc="normal")


def apply_in_thread(config: RealtimeConfig) -> AppliedRealtime:
    """Apply in a throwaway thread: the thread-level settings die with it."""
    result: list[AppliedRealtime] = []
    thread = threading.Thread(target=lambda: result.append(apply_realtime(config)))
    thread.start()
    thread.join()
    [applied] = result
    applied.restore()
    return applied


def records_about(caplog: pytest.LogCaptureFixture, text: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if text in r.getMessage()]


def test_one_report_line_and_one_info_record_per_setting(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.INFO, logger="runtime.realtime"):
        applied = apply_in_thread(NOTHING)
    assert len(applied.report) == 6
    assert [r.levelno for r in caplog.records] == [logging.INFO] * 6
    assert [r.getMessage() for r in caplog.records] == [
        f"cyclic: {line}" for line in applied.report
    ]
    assert "SCHED_FIFO not requested" in applied.report[0]


def test_refused_priority_gives_one_warning_naming_the_capability(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refuse(pid: int, policy: int, param: os.sched_param) -> None:
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with caplog.at_level(logging.INFO, logger="runtime.realtime"):
        applied = apply_in_thread(RealtimeConfig(priority=80, lock_memory=False, gc="normal"))
    [warning] = [r for r in caplog.records if r.levelno == logging.WARNING]
    message = warning.getMessage()
    assert "SCHED_FIFO priority 80 not applied" in message
    assert "PermissionError" in message and "CAP_SYS_NICE" in message
    assert len(records_about(caplog, "SCHED_FIFO")) == 1
    assert message.endswith(applied.report[0])


def test_unavailable_cpu_gives_one_warning_and_leaves_affinity(
    caplog: pytest.LogCaptureFixture,
) -> None:
    before = os.sched_getaffinity(0)
    with caplog.at_level(logging.INFO, logger="runtime.realtime"):
        apply_in_thread(RealtimeConfig(priority=0, cpu=4095, lock_memory=False, gc="normal"))
    [warning] = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "CPU affinity {4095} not applied" in warning.getMessage()
    assert os.sched_getaffinity(0) == before


def test_refused_memory_lock_gives_one_warning_with_errno(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(realtime, "_mlockall", lambda flags: errno.ENOMEM)
    with caplog.at_level(logging.INFO, logger="runtime.realtime"):
        applied = apply_in_thread(RealtimeConfig(priority=0, lock_memory=True, gc="normal"))
    [warning] = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT) not applied: ENOMEM" in (
        warning.getMessage()
    )
    assert "CAP_IPC_LOCK" in warning.getMessage()
    assert not applied.memory_locked


def test_memory_lock_falls_back_without_onfault_on_old_kernels(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    tried: list[int] = []

    def old_kernel(flags: int) -> int:
        tried.append(flags)
        return errno.EINVAL if flags & realtime.MCL_ONFAULT else 0

    monkeypatch.setattr(realtime, "_mlockall", old_kernel)
    monkeypatch.setattr(realtime, "_munlockall", lambda: None)
    applied = apply_in_thread(RealtimeConfig(priority=0, lock_memory=True, gc="normal"))
    assert tried == [7, 3]
    assert applied.memory_locked
    assert "mlockall(MCL_CURRENT|MCL_FUTURE) applied" in applied.report[2]


def test_priority_and_affinity_apply_to_the_calling_thread_only() -> None:
    cpu = min(os.sched_getaffinity(0))
    seen: list[tuple[str, int, set[int]]] = []

    def tuned() -> None:
        applied = apply_realtime(RealtimeConfig(priority=10, cpu=cpu, lock_memory=False))
        seen.append((applied.report[0], os.sched_getscheduler(0), os.sched_getaffinity(0)))
        applied.restore()

    main_policy, main_cpus = os.sched_getscheduler(0), os.sched_getaffinity(0)
    thread = threading.Thread(target=tuned)
    thread.start()
    thread.join()
    [(priority_line, policy, cpus)] = seen
    # The report tells the truth: FIFO when it says applied (root, CAP_SYS_NICE), else unchanged.
    expected = (
        os.SCHED_FIFO if priority_line.endswith("applied to the cyclic thread") else main_policy
    )
    assert policy == expected
    assert cpus == {cpu}
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == (main_policy, main_cpus)


def test_switch_interval_applied_and_restored() -> None:
    before = sys.getswitchinterval()
    applied = apply_realtime(NOTHING)
    try:
        assert sys.getswitchinterval() == pytest.approx(SWITCH_INTERVAL_S)
    finally:
        applied.restore()
    assert sys.getswitchinterval() == before


def child_lines(code: str) -> list[str]:
    """What a child Python running ``code`` prints, line by line (process-wide settings are
    exercised in a child so the test process keeps its own)."""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    return result.stdout.splitlines()


def test_memory_lock_in_a_separate_process() -> None:
    # mlockall is process-wide: the test process stays unlocked.
    code = (
        "from runtime.config import RealtimeConfig\n"
        "from runtime.realtime import apply_realtime\n"
        "a = apply_realtime(RealtimeConfig(priority=0, lock_memory=True, gc='normal'))\n"
        "lck = lambda: [l for l in open('/proc/self/status') if l.startswith('VmLck')][0]\n"
        "print(a.report[2]); print(lck().split()[1]); a.restore(); print(lck().split()[1])\n"
    )
    line, locked_kb, after_kb = child_lines(code)
    if "not applied" in line:
        assert "CAP_IPC_LOCK" in line  # unprivileged: the refusal is reported, nothing locked
        assert int(locked_kb) == 0
    else:
        assert int(locked_kb) > 0
        assert int(after_kb) == 0


def test_heap_policy_in_a_separate_process() -> None:
    # Under malloc's defaults a freed 40 MB buffer goes back to the OS (resident memory falls
    # again); once the heap keeps freed memory, it stays resident for the next buffer.
    code = (
        "import numpy as np\n"
        "from runtime.config import RealtimeConfig\n"
        "from runtime.realtime import apply_realtime\n"
        "rss = lambda: int([l for l in open('/proc/self/status') if l.startswith('VmRSS')][0]"
        ".split()[1])\n"
        "def kept_kb():\n"
        "    before = rss()\n"
        "    buffer = np.ones(5 << 20)\n"
        "    del buffer\n"
        "    return rss() - before\n"
        "a = apply_realtime(RealtimeConfig(priority=0, lock_memory=False, gc='normal'))\n"
        "print(a.report[3]); print(kept_kb())\n"
        "a = apply_realtime(RealtimeConfig(priority=0, lock_memory=True, gc='normal'))\n"
        "print(a.report[3]); print(kept_kb())\n"
    )
    off_line, returned_kb, on_line, kept_kb = child_lines(code)
    assert off_line == "malloc policy not requested: freed memory may go back to the OS"
    assert on_line.startswith("malloc keeps freed memory (M_MMAP_MAX 0, no trimming)")
    assert int(returned_kb) < 4_000
    assert int(kept_kb) > 36_000


def test_gc_policy_disable_and_normal() -> None:
    assert gc.isenabled()
    policy = GcPolicy("disable")
    policy.set_moving(True)
    policy.set_moving(True)
    try:
        assert not gc.isenabled() and gc.get_freeze_count() == 0
    finally:
        policy.restore()
    assert gc.isenabled()
    normal = GcPolicy("normal")
    normal.set_moving(True)
    assert gc.isenabled() and normal.moving
    normal.restore()


def test_gc_policy_keeps_a_collector_that_was_off_off() -> None:
    gc.disable()
    try:
        policy = GcPolicy("freeze")
        policy.set_moving(True)
        assert gc.get_freeze_count() > 0
        policy.set_moving(False)
        assert not gc.isenabled()
        # Never unfrozen: a full collection of the whole heap would stall the cycle.
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
        gc.enable()


def test_gc_policy_rejects_unknown_mode() -> None:
    with pytest.raises(ValueError, match="'sometimes'"):
        GcPolicy("sometimes")
