"""The real arrangement on SocketCAN vcan0: ``softmotion run`` in one process, each simulated drive
as its own ``softmotion sim-drive`` process, the machine driven over Modbus TCP, and an
independent raw-socket listener checking the frames on the bus.

One machine serves the scenarios in order (boot and SDO configuration, a curve run to the end,
an injected drive fault, a drive process killed mid-motion, then restarted and recovered by
reset), because starting the processes is the slowest part inside the emulated VM.

Timing inside the VM (``SOFTMOTION_VCAN_VM=1``): the CPU is emulated (no KVM), Python runs about
15 times slower on two virtual CPUs shared by the runtime's four processes, three drive
processes and this test with its frame listener, and the guest's timer wake-ups are coarse. So
there, and only there:

- the cycle is 50 ms instead of 4 ms: at 20 ms the cycle and the drives' work per period took
  more than the two CPUs have (SYNC intervals of 38 ms on average at rest, 92 ms during
  motion, stalls of two seconds); the curve is a quarter circle with a 10 µm chord
  error instead of the paper's curve (see ``CURVE``), run at 25 % feed override;
- the drive and master heartbeats are 1000 ms instead of 100 ms (10x), the feedback may be 25
  cycles old instead of 10 (a drive process preempted for half a second answers SYNCs that
  long after), and boot and recovery timeouts are 60 s;
- the following-error window is 5 mm instead of 1 mm: a drive process that answers a SYNC only
  after the next ones were sent is compared with a later target, 1.25 mm per period late at
  25 % override. Measured at 20 ms on two virtual CPUs (``scripts/vcan-stage``) over five
  runs: 70 to 99 % of the TPDOs answered before the next SYNC, the latest 1 to 4 periods late
  (up to 1.9 mm, with both host cores also busy elsewhere); on one virtual CPU the five
  processes need more than it has, the answers fell 11 periods behind and the check tripped at
  5.4 mm;
- the cycle may miss up to 100 consecutive periods (5 s) before it stops the machine, instead of
  3: the emulated VM was seen to stall the process for two seconds; the drives' SYNC-loss
  limit is 100 periods instead of 10 for the same reason;
- the runtime and the drives keep the normal scheduler: on two emulated CPUs, real-time
  processes that stand for an IPC and three drives (each with hardware of its own on a real
  bus) took both CPUs, starved this test's frame listener and stalled each other's periods;
- the test polls the machine's status every 100 ms instead of 10 ms: each read also costs the
  runtime's Modbus thread CPU time that the cycle and the drives need.

The curve's run reports how late the drives answered, in SYNCs, as seen on the bus.

The frame checks are the same everywhere, and so are the SYNC checks that do not depend on the
clock: one SYNC per executed cycle, and no burst (any ten consecutive SYNC intervals span at
least nine periods; eight in the VM, see ``BURST_SPAN_PERIODS``). On a host the intervals are
also bounded (median within 2 % of the period, none shorter than half a period); inside the VM
they are only reported: a thread preempted between its deadline and its SYNC there shortens the
next interval, so they measure the emulator's scheduler, not ours.
"""

from __future__ import annotations

import math
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from canlisten import CanListener, RecordedFrame
from conftest import DIAGNOSTIC_LOGS, VCAN_CHANNEL, running_in_vcan_vm
from machine_process import connect_hmi
from sim_machine import free_port

from drives.boot import BootPhase
from planner.nurbs import NurbsCurve
from runtime.commands import CommandCode, CommandResult
from runtime.curves import load_curve_file
from runtime.hmi.client import HmiClient
from runtime.status import FaultKind, MachineState, StatusSnapshot

ROOT = Path(__file__).resolve().parents[2]
IN_VM = running_in_vcan_vm()
#: A quarter circle of radius 60 mm (rational quadratic); its plan is cheap.
ARC = NurbsCurve.from_arrays(
    2, [[10, 10, 5], [70, 10, 5], [70, 70, 5]], [0, 0, 0, 1, 1, 1], [1, math.sqrt(0.5), 1]
)
#: The curve run: the paper's on a host; in the VM the arc, because planning the paper's curve
#: there costs about three times its motion time (the planner runs ~8x faster than real time on
#: a host, Python ~15x slower in the VM), which would underrun the setpoint buffer.
CURVE: NurbsCurve = ARC if IN_VM else load_curve_file(ROOT / "configs" / "curves" / "paper.yaml")
PERIOD_MS = 50 if IN_VM else 4
HEARTBEAT_MS = 1000 if IN_VM else 100
TIMEOUT_SCALE = 10.0 if IN_VM else 1.0
NODES = (1, 2, 3)
#: Upload of 0x1000:00 (the device type) as it appears in bytes 1-3 of an SDO frame.
DEVICE_TYPE_PROBE = bytes([0x00, 0x10, 0x00])
#: Least span of ten consecutive SYNC intervals, in periods. A catch-up burst would shorten it by
#: the periods caught up. In the VM the cyclic thread can be preempted for a whole period between
#: its deadline and its SYNC, which shortens one span by that much without any burst (measured
#: during motion: 179.7 ms for ten intervals at 20 ms, 8.99 periods).
BURST_SPAN_PERIODS = 8 if IN_VM else 9
#: Interval of the status polls while waiting: every read also costs the runtime's Modbus thread.
STATUS_POLL_S = 0.1 if IN_VM else 0.01
#: Feed override inside the VM: a drive process there can answer several periods late, and at
#: full feed each period late is 2 mm of following error.
VM_OVERRIDE_PERCENT = 25.0
COUNTS_PER_MM = 1000
#: SCHED_FIFO priority of the drive processes: below the cycle's (80), above everything else.
DRIVE_PRIORITY = 70
SYNC, RPDO1, TPDO1 = 0x80, 0x200, 0x180
S = MachineState
#: Controlwords a CSP axis legitimately sends (CiA 402: disable voltage, quick stop, shutdown,
#: switch on / disable operation, enable operation, fault reset).
CONTROLWORDS = {0x00, 0x02, 0x06, 0x07, 0x0F, 0x80}


class VcanMachine:
    """``softmotion run --config configs/vcan.yaml`` (adapted) plus one process per drive."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        document = yaml.safe_load((ROOT / "configs" / "vcan.yaml").read_text())
        self.port = free_port()
        document["modbus"]["port"] = self.port
        document["cycle"]["period_ms"] = PERIOD_MS
        document["cycle"]["overrun_limit"] = 100 if IN_VM else 3
        if IN_VM:
            document["cycle"]["realtime"].update(priority=0, spin_us=0)
            # At 50 ms a 1 µm chord error would limit the arc's feed to 14 mm/s.
            document["planner"]["chord_error_mm"] = 0.01
            # A TPDO that the VM delivers after the next SYNC is compared with the wrong target:
            # one period at the arc's 25 mm/s is 1.25 mm, so the window must exceed it.
            for axis in document["axes"]:
                axis["following_error_window_mm"] = 5.0
        document["can"].update(
            stale_feedback_cycles=25 if IN_VM else 10,
            heartbeat_ms=HEARTBEAT_MS,
            master_heartbeat_ms=HEARTBEAT_MS,
            boot_timeout_s=60 if IN_VM else 10,
            sdo_timeout_s=2.0 if IN_VM else 0.3,
        )
        self.config = tmp / "vcan.yaml"
        self.config.write_text(yaml.safe_dump(document))
        self.drives: dict[int, subprocess.Popen[bytes]] = {}
        for node in NODES:
            self.start_drive(node)
        self.log = tmp / "run.log"
        DIAGNOSTIC_LOGS.append(self.log)
        with self.log.open("w") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "runtime.cli", "run", "--config", str(self.config)],
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=ROOT,
            )
        self.client = connect_hmi(
            self.process,
            self.port,
            self.log,
            timeout_s=60 * TIMEOUT_SCALE,
            client_timeout_s=5.0 * TIMEOUT_SCALE,
        )

    def start_drive(self, node: int) -> None:
        path = self.tmp / f"drive-{node}.log"
        if path not in DIAGNOSTIC_LOGS:
            DIAGNOSTIC_LOGS.append(path)
        log = path.open("a")
        self.drives[node] = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "runtime.cli",
                "sim-drive",
                "--node",
                str(node),
                "--interface",
                "socketcan",
                "--channel",
                VCAN_CHANNEL,
                # SYNC loss after that many periods: the runtime's overrun limit comes first.
                "--sync-timeout-factor",
                "100" if IN_VM else "10",
                # On a host, real time just below the cycle: hardware never waits for the host.
                "--priority",
                "0" if IN_VM else str(DRIVE_PRIORITY),
                "--log-level",
                "INFO",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
        )

    def wait_for(self, condition, timeout_s: float, what: str):
        return self.client.wait_for(
            condition, timeout_s * TIMEOUT_SCALE, what, poll_s=STATUS_POLL_S
        )

    def close(self) -> None:
        self.client.close()
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(30 * TIMEOUT_SCALE)
        except subprocess.TimeoutExpired:
            self.process.kill()
        for drive in self.drives.values():
            if drive.poll() is None:
                drive.send_signal(signal.SIGTERM)
        for drive in self.drives.values():
            try:
                drive.wait(10 * TIMEOUT_SCALE)
            except subprocess.TimeoutExpired:
                drive.kill()


@pytest.fixture(scope="module")
def listener() -> Iterator[CanListener]:
    with CanListener(VCAN_CHANNEL) as recorder:
        yield recorder


@pytest.fixture(scope="module")
def machine(tmp_path_factory: pytest.TempPathFactory, listener: CanListener) -> Iterator:
    running = VcanMachine(tmp_path_factory.mktemp("vcan-machine"))
    yield running
    running.close()
    assert running.process.returncode == 0, running.log.read_text()


def rpdo_targets(frames: list[RecordedFrame], node: int) -> np.ndarray:
    data = [f.data for f in frames if f.can_id == RPDO1 + node]
    return np.array([int.from_bytes(d[2:6], "little", signed=True) for d in data])


def end_counts() -> list[int]:
    return [round(float(v) * COUNTS_PER_MM) for v in CURVE.end_point]


def run_paper_to_the_end(machine: VcanMachine) -> None:
    """Start the curve and wait for its end, then for the drives' last feedback.

    The runtime reports the curve finished when it has sent the last setpoint; the drives'
    actual positions reach it one period later, and in the VM several periods later.
    """
    client = machine.client
    assert client.command(CommandCode.START).result is CommandResult.DONE
    status = machine.wait_for(lambda s: s.snapshot.state is not S.MOVING, 60, "the curve's end")
    assert status.snapshot.state is S.STANDBY, status.snapshot.message
    time.sleep(10 * PERIOD_MS / 1000 * TIMEOUT_SCALE)


def assert_axes_at_the_end(status: StatusSnapshot) -> None:
    for axis, target in zip(status.axes, end_counts(), strict=True):
        assert abs(axis.actual_mm * COUNTS_PER_MM - target) <= 1.0, (axis.name, axis.actual_mm)


def test_boot_configures_every_drive_by_sdo(machine: VcanMachine, listener: CanListener) -> None:
    # The runtime serves while the cycle boots the drives: wait until every one is ready.
    machine.wait_for(
        lambda s: all(a.boot_phase == BootPhase.READY for a in s.snapshot.axes), 30, "boot"
    )
    for node in NODES:
        # NMT start of that node after its configuration (the listener, on a thread of its
        # own, records it after every frame before it on the bus).
        start = listener.wait_for(
            lambda f, n=node: f.can_id == 0 and f.data == bytes([1, n]), 1, 5 * TIMEOUT_SCALE
        )
        frames = listener.frames()
        frames = frames[: frames.index(start[0])]
        # Configured and read back over the bus: every object asked for (index and sub-index
        # of an initiate request; segments carry none) was answered. The probes of the device
        # type (0x1000:00) that look for the drive may go unanswered while it resets (its
        # boot-up finds it then), so they are not configuration, and frames are not counted.
        requests = [f for f in frames if f.can_id == 0x600 + node]
        answers = [f for f in frames if f.can_id == 0x580 + node]
        asked = {bytes(f.data[1:4]) for f in requests if f.data[0] & 0xE0 in (0x20, 0x40)}
        asked.discard(DEVICE_TYPE_PROBE)
        answered = {bytes(f.data[1:4]) for f in answers if f.data[0] & 0xE0 in (0x40, 0x60)}
        assert len(requests) >= 20 and asked <= answered, sorted(asked - answered)
        assert all(len(f.data) == 8 for f in requests + answers)
        assert not any(f.data[0] == 0x80 for f in answers), "an SDO transfer was aborted"
    status = machine.client.status().snapshot
    assert status.state is S.DISABLED and status.fault is None


def timed_status(client: HmiClient) -> tuple[StatusSnapshot, float]:
    """The status and how long reading it took (s)."""
    started = time.monotonic()
    status = client.status().snapshot
    return status, time.monotonic() - started


def check_sync_stream(
    syncs: list[RecordedFrame],
    cycles_run: int,
    reads_s: float,
    capsys: pytest.CaptureFixture[str],
    what: str,
) -> None:
    """One SYNC (COB-ID 0x80, no data) per executed cycle and no burst; report the period.

    ``reads_s``: time spent reading the two cycle counts that bracket the recording; cycles
    that ran meanwhile may or may not be among the SYNCs recorded.
    """
    assert syncs and all(f.data == b"" for f in syncs)
    times_s = np.array([f.timestamp_ns for f in syncs]) * 1e-9
    intervals_ms = np.diff(times_s) * 1000
    with capsys.disabled():
        print(
            f"\nSYNC on {VCAN_CHANNEL} {what} ({'VM' if IN_VM else 'host'}, period {PERIOD_MS} ms):"
            f" {len(intervals_ms)} intervals, mean {intervals_ms.mean():.3f} ms, jitter (std)"
            f" {intervals_ms.std():.3f} ms, median {np.median(intervals_ms):.3f} ms,"
            f" p99 {np.percentile(intervals_ms, 99):.3f} ms, min {intervals_ms.min():.3f} ms,"
            f" max {intervals_ms.max():.3f} ms"
        )
    # One SYNC per executed cycle, and never a catch-up burst: any ten consecutive intervals
    # span at least BURST_SPAN_PERIODS periods.
    slack = 2 + math.ceil(reads_s / (PERIOD_MS / 1000))
    assert abs(len(syncs) - cycles_run) <= slack, (len(syncs), cycles_run, slack)
    spans_ms = (times_s[10:] - times_s[:-10]) * 1000
    assert spans_ms.min() >= BURST_SPAN_PERIODS * PERIOD_MS, (
        f"ten SYNC intervals in {spans_ms.min():.1f} ms, "
        f"under {BURST_SPAN_PERIODS} periods: a burst"
    )
    if not IN_VM:
        # Skipped periods stretch an interval by whole periods; the median ignores them.
        assert statistics.median(intervals_ms.tolist()) == pytest.approx(PERIOD_MS, rel=0.02)
        assert intervals_ms.min() >= PERIOD_MS / 2, "SYNCs closer than half a period: a burst"


def report_answer_lateness(frames: list[RecordedFrame], capsys: pytest.CaptureFixture[str]) -> None:
    """Print, per drive, how many SYNCs went out on the bus between the SYNC a TPDO1 answered
    and that TPDO1 (0 = before the next SYNC).

    A drive answers each SYNC once, in order, so its k-th TPDO1 answers the k-th SYNC after some
    offset; the offset is taken from the earliest answer, which the machine at rest before the
    start gives in time. A report, not a check: the following-error supervision is the check.
    """
    lines = []
    for node in NODES:
        syncs_before = []
        count = 0
        for frame in frames:
            if frame.can_id == SYNC:
                count += 1
            elif frame.can_id == TPDO1 + node:
                syncs_before.append(count)
        if not syncs_before:
            continue
        behind = np.array(syncs_before) - np.arange(len(syncs_before))
        late = behind - behind.min()
        shares = ", ".join(
            f"{periods}: {n}" for periods, n in enumerate(np.bincount(late).tolist()) if n
        )
        lines.append(
            f"node {node}: {len(late)} TPDO1, mean {late.mean():.2f} SYNCs late, max"
            f" {late.max()} (count per SYNCs late: {shares})"
        )
    with capsys.disabled():
        print(f"\nTPDO1 answers on {VCAN_CHANNEL} during motion:\n  " + "\n  ".join(lines))


def test_sync_and_rpdos_every_cycle_at_rest(
    machine: VcanMachine, listener: CanListener, capsys: pytest.CaptureFixture[str]
) -> None:
    client = machine.client
    listener.clear()
    before, read_before_s = timed_status(client)
    time.sleep(200 * PERIOD_MS / 1000)
    status, read_after_s = timed_status(client)
    frames = listener.frames()
    assert status.state is S.DISABLED
    for node in NODES:
        rpdos = [f for f in frames if f.can_id == RPDO1 + node]
        assert rpdos and all(len(f.data) == 6 for f in rpdos)
        # Disabled: controlword "disable voltage", target = where the drive stands (0 at boot).
        assert {int.from_bytes(f.data[0:2], "little") for f in rpdos} == {0x00}
        assert set(rpdo_targets(frames, node).tolist()) == {0}
    syncs = [f for f in frames if f.can_id == SYNC]
    cycles_run = status.stats.cycles - before.stats.cycles
    check_sync_stream(syncs, cycles_run, read_before_s + read_after_s, capsys, "at rest")


def test_curve_runs_to_the_end_with_exact_frames(
    machine: VcanMachine, listener: CanListener, capsys: pytest.CaptureFixture[str]
) -> None:
    client = machine.client
    assert client.load_curve(CURVE).result is CommandResult.DONE
    if IN_VM:
        result = client.command(CommandCode.SET_OVERRIDE, override_percent=VM_OVERRIDE_PERCENT)
        assert result.result is CommandResult.DONE
    assert client.command(CommandCode.ENABLE).result is CommandResult.DONE
    machine.wait_for(lambda s: s.snapshot.state is S.STANDBY, 10, "STANDBY")
    listener.clear()
    before, read_before_s = timed_status(client)
    run_paper_to_the_end(machine)
    status, read_after_s = timed_status(client)
    frames = listener.frames()
    cycles_run = status.stats.cycles - before.stats.cycles
    assert_axes_at_the_end(status)

    syncs = [f for f in frames if f.can_id == SYNC]
    period_s = PERIOD_MS / 1000
    step_limit = 100.0 * period_s * COUNTS_PER_MM * 1.001  # vmax·T in counts
    for node, target in zip(NODES, end_counts(), strict=True):
        rpdos = [f for f in frames if f.can_id == RPDO1 + node]
        assert all(len(f.data) == 6 for f in rpdos)
        controlwords = {int.from_bytes(f.data[0:2], "little") for f in rpdos}
        assert controlwords == {0x0F}, controlwords  # enabled throughout the run
        targets = rpdo_targets(frames, node)
        assert targets[-1] == target
        assert np.abs(np.diff(targets)).max() <= step_limit
    # Every period: the three RPDOs of the cycle, then its SYNC.
    order = [f.can_id for f in frames if f.can_id == SYNC or RPDO1 < f.can_id <= RPDO1 + 3]
    first = order.index(SYNC)
    cycles = order[first + 1 :]
    for i in range(0, len(cycles) - 4, 4):
        assert sorted(cycles[i : i + 3]) == [0x201, 0x202, 0x203] and cycles[i + 3] == SYNC

    check_sync_stream(syncs, cycles_run, read_before_s + read_after_s, capsys, "during motion")
    report_answer_lateness(frames, capsys)


def test_injected_drive_fault_stops_every_axis(machine: VcanMachine, listener: CanListener) -> None:
    client = machine.client
    assert client.status().snapshot.state is S.STANDBY
    assert client.command(CommandCode.START).result is CommandResult.DONE
    machine.wait_for(lambda s: s.snapshot.path_s_mm > 40.0, 30, "mid-curve")
    machine.drives[2].send_signal(signal.SIGUSR1)
    status = machine.wait_for(lambda s: s.snapshot.state is S.ERROR_STOP, 5, "ERROR_STOP")
    fault = status.snapshot.fault
    assert fault.kind is FaultKind.DRIVE_FAULT and fault.emcy_code == 0x4210, fault
    assert any(f.can_id == 0x82 and f.data[:2] == bytes([0x10, 0x42]) for f in listener.frames())
    stopped = machine.wait_for(lambda s: s.snapshot.feed_mm_s == 0.0, 5, "standstill")
    listener.clear()
    time.sleep(20 * PERIOD_MS / 1000 * TIMEOUT_SCALE)
    frames = listener.frames()
    for node in (1, 3):
        targets = rpdo_targets(frames, node)
        assert len(targets) > 0 and np.all(targets == targets[0]), "axis still moving"
    assert stopped.snapshot.state is S.ERROR_STOP
    assert client.command(CommandCode.RESET).result is CommandResult.DONE
    machine.wait_for(lambda s: s.snapshot.state is S.STANDBY, 20, "STANDBY after reset")
    run_paper_to_the_end(machine)


def test_killed_drive_is_detected_then_restarted_and_recovered(
    machine: VcanMachine, listener: CanListener
) -> None:
    client = machine.client
    assert client.command(CommandCode.START).result is CommandResult.DONE
    machine.wait_for(lambda s: s.snapshot.path_s_mm > 40.0, 30, "mid-curve")
    machine.drives[3].kill()
    machine.drives[3].wait()
    status = machine.wait_for(lambda s: s.snapshot.state is S.ERROR_STOP, 5, "ERROR_STOP")
    assert status.snapshot.fault.kind in (FaultKind.STALE_FEEDBACK, FaultKind.HEARTBEAT_LOSS)
    # The heartbeat loss is the cause, or listed after the stale feedback that came first.
    lost = machine.wait_for(
        lambda s: (
            s.snapshot.fault.kind is FaultKind.HEARTBEAT_LOSS
            or "further fault: axis Z: no heartbeat" in machine.log.read_text()
        ),
        5,
        "heartbeat loss",
    )
    detected_s = time.time()
    last_heartbeat_s = max(f.timestamp_ns for f in listener.frames() if f.can_id == 0x703) * 1e-9
    # Within 3 heartbeat periods of the last heartbeat, plus our status polling.
    assert detected_s - last_heartbeat_s <= 3 * HEARTBEAT_MS / 1000 + (1.0 if IN_VM else 0.1)
    assert lost.snapshot.state is S.ERROR_STOP and lost.snapshot.fault.axis == "Z"
    machine.wait_for(lambda s: s.snapshot.feed_mm_s == 0.0, 5, "standstill")
    listener.clear()
    time.sleep(20 * PERIOD_MS / 1000 * TIMEOUT_SCALE)
    for node in (1, 2):
        targets = rpdo_targets(listener.frames(), node)
        assert len(targets) > 0 and np.all(targets == targets[0]), "axis still moving"
    machine.start_drive(3)
    listener.wait_for_count(0x703, 1, 30 * TIMEOUT_SCALE)  # its boot-up
    assert client.command(CommandCode.RESET).result is CommandResult.DONE
    machine.wait_for(lambda s: s.snapshot.state is S.STANDBY, 60, "STANDBY after reset")
    run_paper_to_the_end(machine)
    assert_axes_at_the_end(client.status().snapshot)
