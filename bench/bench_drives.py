"""Benchmark of the CiA 402 master's cycle: CPU time per cycle and CAN bus load per cycle.

For 1, 3 and 8 axes, simulated drives answer in-process on python-can's ``virtual`` bus. Each
cycle is ``read_feedback`` + ``write_targets`` + ``exchange``; the loop then waits (unmeasured)
until every drive has answered the SYNC, so every cycle works on fresh feedback. Reported:

- master CPU per cycle: ``time.thread_time()`` of the cycling thread around the three calls
  (the Notifier and drive threads are not included), mean and 99th percentile, in µs;
- wall time of the same three calls (includes GIL waits behind the drive threads);
- frames per cycle, counted by an independent listener bus over the run;
- bits per cycle at the nominal frame lengths of CAN 2.0A data frames with worst-case stuffing:
  ``bits(n) = 47 + 8 n + floor((34 + 8 n - 1) / 4)`` for ``n`` data bytes (47 fixed bits: SOF,
  11-bit ID, RTR, IDE, r0, DLC, CRC 15 + delimiter, ACK 2, EOF 7, IFS 3; stuffing can insert one
  bit per 4 after the first among the 34 + 8n bits from SOF to CRC). 6-byte PDO = 115 bits,
  SYNC (0 bytes) = 55, heartbeat (1 byte) = 65;
- bus load at 1 Mbit/s: bits per cycle / (period × 1e6).

Run: ``.venv/bin/python bench/bench_drives.py [--cycles N]``. Figures depend on the machine;
``virtual`` models no arbitration or bit timing, so the load is computed, not measured.
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time
import uuid
from collections import Counter

import can
import canopen

from drives.bus import open_bus
from drives.master import AxisSpec, Cia402Master, MasterSettings
from drives.scaling import AxisScaling
from drives.sim import DriveModel, start_simulated_drives

PERIOD_S = 0.004
BITRATE = 1_000_000
HEARTBEAT_MS = 100


def frame_bits(data_bytes: int) -> int:
    """Bits of a CAN 2.0A data frame with ``data_bytes`` bytes, worst-case bit stuffing."""
    stuffed_region = 34 + 8 * data_bytes
    return 47 + 8 * data_bytes + (stuffed_region - 1) // 4


class _Counter(can.Listener):
    def __init__(self) -> None:
        self.by_length: Counter[int] = Counter()
        self.frames = 0
        self._lock = threading.Lock()
        self.counting = False

    def on_message_received(self, msg: can.Message) -> None:
        if self.counting:
            with self._lock:
                self.by_length[msg.dlc] += 1
                self.frames += 1


def run(axes_count: int, cycles: int) -> dict[str, float]:
    channel = f"bench-{uuid.uuid4().hex}"
    node_ids = list(range(1, axes_count + 1))
    listener_bus = open_bus("virtual", channel)
    counter = _Counter()
    notifier = can.Notifier(listener_bus, [counter], timeout=0.05)
    network = canopen.Network(open_bus("virtual", channel))
    network.NOTIFIER_SHUTDOWN_TIMEOUT = 0.0
    network.connect()
    axes = [AxisSpec(f"A{n}", n, AxisScaling(1000.0), 1.0, 20) for n in node_ids]
    master = Cia402Master(
        network,
        axes,
        MasterSettings(
            period_s=PERIOD_S, heartbeat_ms=HEARTBEAT_MS, master_heartbeat_ms=HEARTBEAT_MS
        ),
    )
    drives = start_simulated_drives(
        "virtual", channel, node_ids, model=DriveModel(sync_timeout_factor=100.0)
    )
    try:
        master.boot()
        master.request_enable()
        targets: list[float | None] = [None] * axes_count
        cpu_us: list[float] = []
        wall_us: list[float] = []
        started = time.monotonic()
        counter.counting = True
        for k in range(cycles + 20):
            if k == 20:  # enabled by now; measure the steady state
                cpu_us.clear()
                wall_us.clear()
            wall0 = time.perf_counter()
            cpu0 = time.thread_time()
            feedback = master.read_feedback()
            for i, item in enumerate(feedback):
                targets[i] = item.commanded_mm + 0.01 if item.enabled else None
            master.write_targets(targets)
            master.exchange()
            cpu_us.append((time.thread_time() - cpu0) * 1e6)
            wall_us.append((time.perf_counter() - wall0) * 1e6)
            deadline = time.monotonic() + 1.0
            while not master.feedback_complete and time.monotonic() < deadline:
                time.sleep(0.00005)
        counter.counting = False
        elapsed_s = time.monotonic() - started
        faults = [str(f.fault) for f in master.read_feedback() if f.fault is not None]
        if faults:
            raise RuntimeError(f"faults during the benchmark: {faults}")
        master.shutdown()
    finally:
        drives.close()
        network.disconnect()
        notifier.stop()
        listener_bus.shutdown()
    total_cycles = cycles + 20
    pdo_frames = counter.by_length[6]
    sync_frames = counter.by_length[0]
    other = counter.frames - pdo_frames - sync_frames
    # Heartbeats per 4 ms cycle at their real rate (the run is faster than real time).
    heartbeat_frames = (axes_count + 1) * PERIOD_S / (HEARTBEAT_MS / 1000.0)
    frames = (pdo_frames + sync_frames) / total_cycles + heartbeat_frames
    bits = (
        pdo_frames / total_cycles * frame_bits(6)
        + sync_frames / total_cycles * frame_bits(0)
        + heartbeat_frames * frame_bits(1)
    )
    cpu_sorted = sorted(cpu_us)
    return {
        "axes": axes_count,
        "cpu_mean_us": statistics.fmean(cpu_us),
        "cpu_p99_us": cpu_sorted[int(0.99 * (len(cpu_sorted) - 1))],
        "wall_mean_us": statistics.fmean(wall_us),
        "frames": frames,
        "bits": bits,
        "load_pct": bits / (PERIOD_S * BITRATE) * 100.0,
        "other_frames": other,
        "elapsed_s": elapsed_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=2000)
    args = parser.parse_args()
    print(
        f"CiA 402 master cycle, {args.cycles} cycles, period {PERIOD_S * 1e3:g} ms, "
        f"heartbeat {HEARTBEAT_MS} ms, CAN {BITRATE / 1e6:g} Mbit/s"
    )
    header = (
        f"{'axes':>4} {'CPU mean µs':>12} {'CPU p99 µs':>11} {'wall mean µs':>13} "
        f"{'frames/cycle':>13} {'bits/cycle':>11} {'load @1M':>9}"
    )
    print(header)
    print("-" * len(header))
    for axes_count in (1, 3, 8):
        r = run(axes_count, args.cycles)
        print(
            f"{r['axes']:>4} {r['cpu_mean_us']:>12.1f} {r['cpu_p99_us']:>11.1f} "
            f"{r['wall_mean_us']:>13.1f} {r['frames']:>13.2f} {r['bits']:>11.0f} "
            f"{r['load_pct']:>8.1f}%"
        )
    print(
        "frames/cycle = RPDO1 + SYNC + TPDO1 counted on the bus + heartbeats (axes + master) "
        f"at one per {HEARTBEAT_MS} ms; bits(n) = 47 + 8n + floor((33 + 8n) / 4)"
    )


if __name__ == "__main__":
    main()
