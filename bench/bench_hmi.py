"""Benchmark of the HMI over Modbus TCP: status read round trip and curve upload.

Prints a table: status read (one FC4 request of the whole input image, decoded) round trip p50,
p99 and max with 1 and with 10 clients reading back to back, and the time to upload and commit a
1,000-point curve (staging writes, CRC, commit, until the machine acknowledges it).

By default it starts an in-process server on a free port with a stand-in machine that publishes
a new snapshot every 4 ms and accepts every command at once (curve preparation = travel check
only), so the figures are those of the HMI path alone. ``--port P`` measures a running
``softmotion run`` instead (its machine must be DISABLED or STANDBY for the upload).

Then, unless ``--port`` is given, the cost of HMI traffic to the cycle: ``softmotion run`` on the
simulated machine (a subprocess) runs the paper's curve alone and with ten clients reading the
status at 20 Hz, ``--runs`` times each, alternating; the table gives the periods the cycle missed
during each motion. On a shared host the run-to-run spread is part of the figure.

Usage: ``python bench/bench_hmi.py [--port P] [--seconds S] [--runs N]``
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from runtime.commands import Command, CommandCode, CommandResult
from runtime.config import ModbusConfig, load_config
from runtime.curves import check_travel
from runtime.hmi.client import HmiClient
from runtime.hmi.server import HmiServer
from runtime.status import AxisStatus, StatusSnapshot

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from machine_process import Machine, run_paper_polled  # noqa: E402

SIM = load_config(ROOT / "configs" / "sim.yaml")


class StandInMachine:
    """Publishes a snapshot every period; applies every command at once."""

    axis_names = tuple(a.name for a in SIM.axes)

    def __init__(self, period_s: float = 0.004) -> None:
        self._snapshot = StatusSnapshot(
            axes=tuple(AxisStatus(a.name, a.node_id, 0.0, 0.0, 4, 0.0) for a in SIM.axes)
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._cycle, args=(period_s,), daemon=True)
        self._thread.start()

    def _cycle(self, period_s: float) -> None:
        n = 0
        while not self._stop.wait(period_s):
            n += 1
            self._snapshot = replace(self._snapshot, heartbeat=n, path_s_mm=0.01 * n)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()

    def snapshot(self) -> StatusSnapshot:
        return self._snapshot

    def submit(self, command: Command) -> CommandResult:
        crc = command.curve[1] if command.code is CommandCode.LOAD_CURVE else 0
        self._snapshot = replace(
            self._snapshot,
            last_command_seq=command.seq or 0,
            last_command_result=CommandResult.DONE,
            curve_crc=crc or self._snapshot.curve_crc,
        )
        return CommandResult.PENDING

    def prepare_curve(self, curve: object, crc32: int) -> object:
        check_travel(curve, SIM.axes)  # type: ignore[arg-type]
        return (curve, crc32)


def spiral_curve(points: int = 1000) -> tuple[int, np.ndarray, np.ndarray]:
    """A cubic B-spline with ``points`` control points on a rising spiral inside the travel."""
    t = np.linspace(0.0, 12 * np.pi, points)
    control = np.column_stack(
        [100 + 60 * np.cos(t), 80 + 60 * np.sin(t), np.linspace(5.0, 60.0, points)]
    )
    degree = 3
    inner = np.linspace(0.0, 1.0, points - degree + 1)[1:-1]
    knots = np.r_[np.zeros(degree + 1), inner, np.ones(degree + 1)]
    return degree, control, knots


def _read_loop(port: int, seconds: float, out: list[float], start: threading.Barrier) -> None:
    with HmiClient(port=port) as client:
        start.wait()
        end = time.perf_counter() + seconds
        while (now := time.perf_counter()) < end:
            client.status()
            out.append(time.perf_counter() - now)


def status_round_trip(port: int, clients: int, seconds: float) -> np.ndarray:
    """Round-trip times (s) of status reads by ``clients`` clients reading back to back."""
    samples: list[list[float]] = [[] for _ in range(clients)]
    barrier = threading.Barrier(clients)
    threads = [
        threading.Thread(target=_read_loop, args=(port, seconds, samples[i], barrier))
        for i in range(clients)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return np.concatenate([np.array(s) for s in samples])


def upload_time(port: int, repeats: int = 3) -> list[float]:
    """Seconds to stage, commit and see acknowledged a 1,000-point curve."""
    from runtime.hmi.upload import encode_staging

    degree, control, knots = spiral_curve()
    staging = encode_staging(degree, control, knots)
    times = []
    with HmiClient(port=port, timeout_s=30.0) as client:
        for _ in range(repeats):
            started = time.perf_counter()
            outcome = client.load_curve(staging)
            times.append(time.perf_counter() - started)
            assert outcome.result is CommandResult.DONE, outcome
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, help="bench a running machine on this port")
    parser.add_argument("--seconds", type=float, default=3.0, help="per read measurement")
    parser.add_argument("--runs", type=int, default=3, help="curve runs per cycle measurement")
    args = parser.parse_args()
    machine = server = None
    port = args.port
    if port is None:
        machine = StandInMachine()
        server = HmiServer(replace(ModbusConfig(), port=0), machine)
        server.start()
        port = server.port
    try:
        print(
            f"HMI benchmark on 127.0.0.1:{port} ({'in-process' if server else 'running machine'})"
        )
        print(f"{'measurement':<38} {'n':>7} {'p50':>10} {'p99':>10} {'max':>10}")
        for clients in (1, 10):
            rt = status_round_trip(port, clients, args.seconds) * 1e3
            print(
                f"{f'status read, {clients} client(s)':<38} {len(rt):>7} "
                f"{np.percentile(rt, 50):>8.3f}ms {np.percentile(rt, 99):>8.3f}ms "
                f"{rt.max():>8.3f}ms"
            )
        up = np.array(upload_time(port)) * 1e3
        print(
            f"{'upload + commit, 1000-point curve':<38} {len(up):>7} "
            f"{np.percentile(up, 50):>8.1f}ms {np.percentile(up, 99):>8.1f}ms {up.max():>8.1f}ms"
        )
    finally:
        if server is not None:
            server.stop()
        if machine is not None:
            machine.close()
    if args.port is None:
        # pymodbus logs every refused connection while a machine boots.
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        missed = cycle_misses(args.runs)
        print()
        print("periods the cycle missed during the paper's curve (softmotion run, simulated)")
        for clients, counts in missed.items():
            label = "alone" if clients == 0 else f"{clients} clients at 20 Hz"
            print(f"  {label:<22} {' '.join(f'{n:>4d}' for n in counts)}")


def cycle_misses(runs: int) -> dict[int, list[int]]:
    """Periods missed during the paper's curve by a fresh ``softmotion run``, per client count."""
    missed: dict[int, list[int]] = {0: [], 10: []}
    with tempfile.TemporaryDirectory() as tmp:
        for run in range(runs):
            for clients, counts in missed.items():
                machine = Machine(Path(tmp) / f"{clients}-{run}")
                try:
                    counts.append(run_paper_polled(machine, clients)[0])
                finally:
                    machine.stop()
    return missed


if __name__ == "__main__":
    main()
