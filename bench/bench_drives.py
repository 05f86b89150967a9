"""Benchmark of the CiA 402 master's period: CPU time per period and CAN bus load per period.

For 3 and 8 axes, the master boots simulated drives in-process on python-can's ``virtual`` bus,
enables them and moves them. Each period is the cycle process's sequence ``transmit_period`` +
``receive`` + ``update`` + ``write_targets``; the CPU time of the calling thread
(``time.thread_time()``) is taken around those four calls. Three figures per axis count, all
measured in the same run:

- **virtual**: the master with the simulated drives on ``virtual``; between periods the loop
  waits (unmeasured) until every drive has answered the SYNC, so each period receives fresh
  TPDOs. python-can's ``virtual`` bus deep-copies every frame for every other bus on the
  channel, so this includes the frame I/O, which on SocketCAN is one system call per frame;
- **I/O reference**: the python-can I/O alone of one such period (the same RPDOs and SYNC sent,
  the same TPDOs received, on a channel with as many buses), no master;
- **master alone**: the same master, same drives configured, on a loopback bus that answers each
  SYNC with the TPDOs of ideal drives (position = last target) and heartbeats at their rate,
  at almost no cost: the master's own work.

Also reported: frames per period counted on the bus, bits per period at the nominal frame lengths
of CAN 2.0A data frames with worst-case stuffing, ``bits(n) = 47 + 8 n + floor((34 + 8 n - 1) /
4)`` for ``n`` data bytes (6-byte PDO = 115 bits, SYNC = 55, heartbeat = 65), and the bus load at
1 Mbit/s (computed: ``virtual`` models no bit timing).

Run: ``.venv/bin/python bench/bench_drives.py [--periods N]``. Figures depend on the machine.
"""

from __future__ import annotations

import argparse
import statistics
import struct
import time
import uuid
from collections import Counter, deque
from collections.abc import Callable

import can

from drives.bus import open_bus
from drives.cia402 import State, encode_statusword
from drives.master import AxisSpec, Cia402Master, MasterSettings
from drives.objects import HEARTBEAT_COB_ID_BASE, SYNC_COB_ID, NmtState, rpdo_cob_id, tpdo_cob_id
from drives.scaling import AxisScaling
from drives.sim import DriveModel, start_simulated_drives

PERIOD_S = 0.004
BITRATE = 1_000_000
HEARTBEAT_MS = 100
BUDGET_US = 500.0
WARM_UP_PERIODS = 50
RPDO1 = struct.Struct("<Hi")


def frame_bits(data_bytes: int) -> int:
    """Bits of a CAN 2.0A data frame with ``data_bytes`` bytes, worst-case bit stuffing."""
    stuffed_region = 34 + 8 * data_bytes
    return 47 + 8 * data_bytes + (stuffed_region - 1) // 4


class _Answers:
    """A bus of its own that waits until every drive has answered the last SYNC (their TPDOs
    then wait in the master's queue too, for the measured ``receive``) and counts the frames
    by length."""

    def __init__(self, bus: can.BusABC, node_ids: list[int]) -> None:
        self.bus = bus
        self.tpdo_ids = {tpdo_cob_id(1, node_id) for node_id in node_ids}
        self.by_length: Counter[int] = Counter()

    def wait(self) -> None:
        pending = set(self.tpdo_ids)
        deadline = time.monotonic() + 1.0
        seen_sync = False
        while pending and time.monotonic() < deadline:
            frame = self.bus.recv(0.001)
            if frame is None:
                continue
            if not frame.is_remote_frame:
                self.by_length[frame.dlc] += 1
            if frame.arbitration_id == SYNC_COB_ID:
                seen_sync, pending = True, set(self.tpdo_ids)
            elif seen_sync:
                pending.discard(frame.arbitration_id)


class _Loopback:
    """A bus with ideal drives inside: every SYNC is answered by one TPDO1 per node (statusword
    OPERATION ENABLED, position = the node's last target), every 100 ms by heartbeats. The
    frames are built once and updated in place, so the bus costs next to nothing."""

    def __init__(self, node_ids: list[int], targets: dict[int, int]) -> None:
        enabled = encode_statusword(State.OPERATION_ENABLED)
        self._targets = dict(targets)
        self._tpdos = {
            rpdo_cob_id(1, n): can.Message(
                arbitration_id=tpdo_cob_id(1, n),
                data=bytearray(RPDO1.pack(enabled, targets[n])),
                is_extended_id=False,
            )
            for n in node_ids
        }
        self._heartbeats = [
            can.Message(
                arbitration_id=HEARTBEAT_COB_ID_BASE + n,
                data=bytearray([NmtState.OPERATIONAL]),
                is_extended_id=False,
            )
            for n in node_ids
        ]
        self._queue: deque[can.Message] = deque()
        self._syncs = 0
        self._heartbeat_every = round(HEARTBEAT_MS / 1000.0 / PERIOD_S)

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        tpdo = self._tpdos.get(message.arbitration_id)
        if tpdo is not None:
            struct.pack_into("<i", tpdo.data, 2, struct.unpack_from("<i", message.data, 2)[0])
        elif message.arbitration_id == SYNC_COB_ID:
            now = time.time()
            self._syncs += 1
            for answer in self._tpdos.values():
                answer.timestamp = now
                self._queue.append(answer)
            if self._syncs % self._heartbeat_every == 0:
                self._queue.extend(self._heartbeats)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        return self._queue.popleft() if self._queue else None

    def shutdown(self) -> None:
        self._queue.clear()


def _real_time_period(master: Cia402Master) -> None:
    """One period at the real pace (boot and shutdown: SDO answers and heartbeats need it)."""
    master.transmit_period()
    time.sleep(PERIOD_S)
    now_s = time.monotonic()
    master.receive(now_s)
    master.update(now_s)
    master.write_targets(None)


def _measure(master: Cia402Master, periods: int, between: Callable[[], None]) -> list[float]:
    """CPU µs of each period's four calls, every axis moving; ``between`` runs unmeasured."""
    targets: list[float | None] = [None] * len(master.axis_names)
    cpu_us: list[float] = []
    for _ in range(periods):
        cpu0 = time.thread_time()
        master.transmit_period()
        now_s = time.monotonic()
        master.receive(now_s)
        feedback = master.update(now_s)
        for i, item in enumerate(feedback):
            targets[i] = item.commanded_mm + 0.01 if item.enabled else None
        master.write_targets(targets)
        cpu_us.append((time.thread_time() - cpu0) * 1e6)
        between()
    faults = [str(f.fault) for f in master.feedback if f.fault is not None]
    if faults or not master.all_enabled:
        raise RuntimeError(f"faults during the benchmark: {faults}")
    return cpu_us


def _io_reference_us(axes_count: int, periods: int) -> float:
    """CPU per period of the frames alone: one RPDO per axis and a SYNC sent, one TPDO per
    axis received, on a channel with as many buses as the virtual run (µs, mean)."""
    channel = f"bench-io-{uuid.uuid4().hex}"
    buses = [open_bus("virtual", channel) for _ in range(3)]
    master_bus, drive_bus, _ = buses
    rpdo = can.Message(arbitration_id=0x201, data=bytes(6), is_extended_id=False)
    sync = can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)
    tpdo = can.Message(arbitration_id=0x181, data=bytes(6), is_extended_id=False)
    samples = []
    try:
        for _ in range(periods):
            for _ in range(axes_count):
                drive_bus.send(tpdo)  # the answers, sent unmeasured
            cpu0 = time.thread_time()
            for _ in range(axes_count):
                master_bus.send(rpdo)
            master_bus.send(sync)
            while master_bus.recv(0.0) is not None:
                pass
            samples.append((time.thread_time() - cpu0) * 1e6)
            for bus in buses[1:]:
                while bus.recv(0.0) is not None:
                    pass
    finally:
        for bus in buses:
            bus.shutdown()
    return statistics.fmean(samples)


def _stats(cpu_us: list[float]) -> tuple[float, float, float]:
    ordered = sorted(cpu_us)
    return (
        statistics.fmean(cpu_us),
        statistics.median(cpu_us),
        ordered[int(0.99 * (len(ordered) - 1))],
    )


def run(axes_count: int, periods: int) -> dict[str, float]:
    channel = f"bench-{uuid.uuid4().hex}"
    node_ids = list(range(1, axes_count + 1))
    answers = _Answers(open_bus("virtual", channel), node_ids)
    bus = open_bus("virtual", channel)
    axes = [AxisSpec(f"A{n}", n, AxisScaling(1000.0), 1.0, 20) for n in node_ids]
    master = Cia402Master(
        bus,
        axes,
        MasterSettings(
            period_s=PERIOD_S,
            heartbeat_ms=HEARTBEAT_MS,
            master_heartbeat_ms=HEARTBEAT_MS,
            stale_feedback_cycles=25,
        ),
    )
    drives = start_simulated_drives(
        "virtual", channel, node_ids, model=DriveModel(sync_timeout_factor=1000.0)
    )
    try:
        master.start()
        deadline = time.monotonic() + 20.0
        while not (master.feedback and all(f.ready for f in master.feedback)):
            if time.monotonic() > deadline:
                raise RuntimeError(f"drives not ready: {master.feedback}")
            _real_time_period(master)
        master.request_enable()
        _measure(master, WARM_UP_PERIODS, answers.wait)
        answers.by_length.clear()
        virtual_us = _measure(master, periods, answers.wait)
        frames_by_length = Counter(answers.by_length)
        # The same master, its drives switched off, on the loopback bus.
        drives.close()
        positions = {f.node_id: f.position_counts for f in master.feedback}
        master.bus = _Loopback(node_ids, positions)
        _measure(master, WARM_UP_PERIODS, lambda: None)
        alone_us = _measure(master, periods, lambda: None)
    finally:
        drives.close()
        bus.shutdown()
        answers.bus.shutdown()
    pdo_frames = frames_by_length[6]
    sync_frames = frames_by_length[0]
    # Heartbeats per 4 ms period at their real rate (the run is faster than real time).
    heartbeat_frames = (axes_count + 1) * PERIOD_S / (HEARTBEAT_MS / 1000.0)
    frames = (pdo_frames + sync_frames) / periods + heartbeat_frames
    bits = (
        pdo_frames / periods * frame_bits(6)
        + sync_frames / periods * frame_bits(0)
        + heartbeat_frames * frame_bits(1)
    )
    reference_us = _io_reference_us(axes_count, periods)
    virtual = _stats(virtual_us)
    alone = _stats(alone_us)
    return {
        "axes": axes_count,
        "virtual_mean_us": virtual[0],
        "virtual_p99_us": virtual[2],
        "reference_us": reference_us,
        "alone_mean_us": alone[0],
        "alone_median_us": alone[1],
        "alone_p99_us": alone[2],
        "frames": frames,
        "bits": bits,
        "load_pct": bits / (PERIOD_S * BITRATE) * 100.0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--periods", type=int, default=3000)
    args = parser.parse_args()
    print(
        "CiA 402 master period: transmit_period + receive + update + write_targets, CPU µs, "
        f"{args.periods} periods, {PERIOD_S * 1e3:g} ms, heartbeat {HEARTBEAT_MS} ms"
    )
    header = (
        f"{'axes':>4} | {'virtual mean':>12} {'p99':>6} {'of 0.5 ms':>9} | {'I/O ref':>7} "
        f"{'× ref':>5} | {'alone mean':>10} {'median':>6} {'p99':>6} {'× ref':>5} | "
        f"{'frames':>6} {'bits':>5} {'@1M':>6}"
    )
    print(header)
    print("-" * len(header))
    for axes_count in (3, 8):
        r = run(axes_count, args.periods)
        print(
            f"{r['axes']:>4} | {r['virtual_mean_us']:>12.1f} {r['virtual_p99_us']:>6.1f} "
            f"{r['virtual_mean_us'] / BUDGET_US:>9.0%} | {r['reference_us']:>7.1f} "
            f"{r['virtual_mean_us'] / r['reference_us']:>5.2f} | {r['alone_mean_us']:>10.1f} "
            f"{r['alone_median_us']:>6.1f} {r['alone_p99_us']:>6.1f} "
            f"{r['alone_mean_us'] / r['reference_us']:>5.2f} | {r['frames']:>6.2f} "
            f"{r['bits']:>5.0f} {r['load_pct']:>5.1f}%"
        )
    print(
        "virtual: with in-process simulated drives on python-can's virtual bus; I/O ref: the "
        "same frames sent and received with python-can alone; alone: the master on a loopback "
        "bus (its own work). frames = RPDO + SYNC + TPDO counted on the bus + heartbeats "
        f"(axes + master) at one per {HEARTBEAT_MS} ms; bits(n) = 47 + 8n + floor((33 + 8n) / 4)"
    )


if __name__ == "__main__":
    main()
