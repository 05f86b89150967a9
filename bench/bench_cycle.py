"""Cycle benchmark: the split runtime's cycle under load against a bare real-time loop, one run.

Part 1, all at once on one ``local`` CAN bus (``--seconds`` of motion, 60 by default):

- a bare loop in a process of its own (:class:`runtime.scheduler.CyclicTask` with the real-time
  settings of ``configs/sim.yaml``: SCHED_FIFO, mlockall, spin) that sends one frame (COB-ID
  0x7E0) as it wakes each period: the reference for wake-up lateness and frame timing on the bus;
- the runtime (supervisor, cycle, planner, HMI and simulated drives as processes) running the
  paper's curve again and again, the feed override changed every 100 ms (30..150 %), ten Modbus
  clients (a process of their own) reading the whole core status (one request) at 20 Hz, logging
  on;
- an independent listener process that timestamps every SYNC (0x80) and every bare frame.

Printed: wake-up lateness p50/p99/p99.9/max and missed periods of both loops (each measured by
itself over the whole run), SYNC and bare-frame intervals as seen on the bus (p99 and p99.9 of
|interval - period|, intervals above 1.5 periods), the ratios against the issue's targets, the
faults during the motion (there must be none), the periods from each override change to its first
re-planned setpoint (apart: those that came while the plan braked to a rest it had to reach
first, counted beyond that rest), what the Modbus clients saw, and the CPU time a hypervisor
took meanwhile (steal time).

Part 2: CPU time per period of the cycle process (from /proc) and its longest period, with 3 and
with 8 axes, the machine enabled and running the paper's curve for ``--cpu-seconds``; each with
the configured spin before the deadline (busy-waiting is CPU time) and without it.

Run: ``.venv/bin/python bench/bench_cycle.py [--seconds 60] [--cpu-seconds 10]`` as root (or
with CAP_SYS_NICE and CAP_IPC_LOCK). Figures depend on the kernel, the host and whatever else
runs: a measurement, not a test.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import multiprocessing
import os
import socket
import sys
import tempfile
import threading
import time
import uuid
from dataclasses import replace
from pathlib import Path

import can
import numpy as np

from drives.boot import BootPhase
from drives.bus import open_bus
from runtime.commands import CommandCode
from runtime.config import DEMO_CURVE_PATH, MachineConfig, RealtimeConfig, load_config
from runtime.curves import load_curve_file
from runtime.scheduler import CycleTick, CyclicTask
from runtime.status import MachineState, StatusSnapshot
from runtime.supervisor import CommandRefused, Runtime
from runtime.wakeups import host_steal_s

ROOT = Path(__file__).resolve().parents[1]
SYNC_COB_ID = 0x80
BARE_COB_ID = 0x7E0
#: The bare loop runs with the simulated machine's real-time settings (priority, spin).
SIM_REALTIME: RealtimeConfig = load_config(ROOT / "configs" / "sim.yaml").cycle.realtime
OVERRIDES = (30.0, 60.0, 100.0, 150.0, 80.0, 120.0)
OVERRIDE_EVERY_S = 0.1
CLIENTS = 10
CLIENT_RATE_HZ = 20.0
#: Longest wait for the machine to come back to STANDBY after a fault during the run [s].
RECOVER_TIMEOUT_S = 30.0


# -- helper processes ---------------------------------------------------------------------------


def bare_loop(channel: str, periods: int, period_s: float, results) -> None:
    """The reference: a bare real-time loop sending one frame as it wakes each period."""
    bus = open_bus("local", channel)
    message = can.Message(arbitration_id=BARE_COB_ID, data=b"", is_extended_id=False)
    done = threading.Event()

    def step(tick: CycleTick) -> None:
        bus.send(message)
        if tick.period_index + 1 >= periods:
            done.set()
            task.stop()

    task = CyclicTask(
        period_s,
        step,
        realtime=replace(SIM_REALTIME, gc="normal"),
        overrun_limit=periods,
        name="bare",
        lateness_window_cycles=periods,
    )
    task.run()
    figures = task.lateness_percentiles()
    stats = task.statistics()
    figures.update(cycles=stats.cycles, missed=stats.missed_periods)
    results.put(figures)
    bus.shutdown()


def listener(channel: str, stop, results) -> None:
    """Timestamps of every SYNC and bare frame on the bus."""
    bus = open_bus("local", channel)
    times: dict[int, list[float]] = {SYNC_COB_ID: [], BARE_COB_ID: []}
    while not stop.is_set():
        message = bus.recv(0.05)
        if message is not None and message.arbitration_id in times:
            times[message.arbitration_id].append(message.timestamp)
    bus.shutdown()
    results.put({k: np.array(v) for k, v in times.items()})


def modbus_clients(port: int, stop, results) -> None:
    """Ten clients reading the whole core status (one FC4 request of input registers 0 ..
    CORE_END - 1: identity, machine status, axes, cycle statistics) at 20 Hz each."""
    from pymodbus.client import ModbusTcpClient

    from runtime.hmi.registers import CORE_END

    latencies: list[float] = []
    errors = [0]
    lock = threading.Lock()

    def client() -> None:
        modbus = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        modbus.connect()
        next_s = time.monotonic()
        while not stop.is_set():
            begin = time.perf_counter()
            reply = modbus.read_input_registers(0, count=CORE_END, device_id=1)
            ok = not reply.isError()
            with lock:
                latencies.append(time.perf_counter() - begin)
                errors[0] += not ok
            next_s += 1.0 / CLIENT_RATE_HZ
            time.sleep(max(0.0, next_s - time.monotonic()))
        modbus.close()

    threads = [threading.Thread(target=client, daemon=True) for _ in range(CLIENTS)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    results.put({"reads": len(latencies), "errors": errors[0], "latency_s": np.array(latencies)})


# -- part 1 -------------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def bench_config(channel: str, seconds: float, axes: int = 3) -> MachineConfig:
    config = load_config(ROOT / "configs" / "sim.yaml")
    cycle = replace(config.cycle, statistics_window_s=min(3600.0, seconds + 30.0))
    axis_list = list(config.axes)
    for i in range(len(axis_list), axes):
        axis_list.append(replace(config.axes[0], name=f"A{i + 1}", node_id=i + 1))
    return replace(
        config,
        cycle=cycle,
        axes=tuple(axis_list),
        can=replace(config.can, channel=channel),
        modbus=replace(config.modbus, port=free_port()),
    )


def run_motion(runtime: Runtime, seconds: float, report: dict) -> None:
    """The paper's curve again and again, the override changed every 100 ms."""
    program = runtime.programs.add(
        load_curve_file(DEMO_CURVE_PATH), runtime.config, name="paper", crc32=0
    )
    runtime.command(CommandCode.LOAD_CURVE, program=program)
    runtime.command(CommandCode.ENABLE)
    runtime.wait_for(lambda s: s.state is MachineState.STANDBY, 30.0)
    faults: list[str] = []
    latencies: list[int] = []
    steal_at_start_s = host_steal_s()
    end = time.monotonic() + seconds
    next_change = time.monotonic()
    changes = 0
    applied = runtime.status().stats.overrides_applied
    while time.monotonic() < end:
        runtime.supervise()
        status = runtime.status()
        # A fault may come between the status read and the command: the command is then
        # refused, and the next pass sees the fault.
        with contextlib.suppress(CommandRefused):
            if status.state is MachineState.STANDBY:
                runtime.command(CommandCode.START)
            elif status.state is MachineState.ERROR_STOP:
                # The fault, not the message: a command applied in ErrorStop replaces that.
                faults.append(status.fault.text if status.fault else status.message)
                if not _recover(runtime):
                    faults.append(f"not recovered: {runtime.status().message}")
                    break
            elif status.state is MachineState.MOVING and time.monotonic() >= next_change:
                percent = OVERRIDES[changes % len(OVERRIDES)]
                changes += 1
                runtime.command(CommandCode.SET_OVERRIDE, override_percent=percent)
                next_change = time.monotonic() + OVERRIDE_EVERY_S
        if status.stats.overrides_applied != applied:
            applied = status.stats.overrides_applied
            latencies.append(
                (status.stats.override_latency_periods, status.stats.override_rest_wait_periods)
            )
        time.sleep(0.005)
    if runtime.status().state is MachineState.MOVING:
        runtime.command(CommandCode.STOP)
    report.update(
        faults=faults,
        override_changes=changes,
        latencies=latencies,
        seconds=seconds,
        steal_s=host_steal_s() - steal_at_start_s,
    )


def _recover(runtime: Runtime) -> bool:
    """Reset and enable again after a fault; whether the machine is in STANDBY within
    :data:`RECOVER_TIMEOUT_S`. A host that stalls the cycle again while the drives come back
    faults them again: the reset is repeated (the faults meanwhile count as one)."""
    deadline = time.monotonic() + RECOVER_TIMEOUT_S
    while time.monotonic() < deadline:
        state = runtime.status().state
        if state is MachineState.STANDBY:
            return True
        code = CommandCode.ENABLE if state is MachineState.DISABLED else CommandCode.RESET
        with contextlib.suppress(CommandRefused, TimeoutError):
            runtime.command(code)
            runtime.wait_for(lambda s, before=state: s.state is not before, 5.0)
    return runtime.status().state is MachineState.STANDBY


def interval_figures(times_s: np.ndarray, period_s: float) -> dict[str, float]:
    intervals = np.diff(np.sort(times_s))
    jitter = np.abs(intervals - period_s)
    return {
        "count": len(intervals),
        "p99_us": float(np.percentile(jitter, 99)) * 1e6,
        "p999_us": float(np.percentile(jitter, 99.9)) * 1e6,
        "max_us": float(jitter.max()) * 1e6,
        "long": int(np.sum(intervals > 1.5 * period_s)),
    }


def part_one(seconds: float, period_s: float) -> None:
    context = multiprocessing.get_context("spawn")
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    config = bench_config(channel, seconds)
    log_file = Path(tempfile.mkstemp(prefix="softmotion-bench-", suffix=".log")[1])
    logging.basicConfig(filename=log_file, level=logging.INFO)
    stop = context.Event()
    results = {name: context.Queue() for name in ("bare", "listener", "clients")}
    # Daemons: should the run fail, a helper left holding unread results never keeps the
    # bench from exiting.
    listen = context.Process(
        target=listener, args=(channel, stop, results["listener"]), daemon=True
    )
    listen.start()
    runtime = Runtime(config, log_level="INFO")
    report: dict = {}
    try:
        runtime.start()
        runtime.wait_for(lambda s: all(a.boot_phase == BootPhase.READY for a in s.axes), 30.0)
        clients = context.Process(
            target=modbus_clients, args=(config.modbus.port, stop, results["clients"]), daemon=True
        )
        clients.start()
        periods = round((seconds + 10.0) / period_s)
        bare = context.Process(
            target=bare_loop, args=(channel, periods, period_s, results["bare"]), daemon=True
        )
        bare.start()
        time.sleep(2.0)  # everything running before the measured motion
        run_motion(runtime, seconds, report)
        status = runtime.status()
        bare_figures = results["bare"].get(timeout=60)
        bare.join(10)
    finally:
        stop.set()
        runtime.stop()
    times = results["listener"].get(timeout=30)
    client_figures = results["clients"].get(timeout=30)
    listen.join(10)
    clients.join(10)
    print_part_one(status, bare_figures, times, client_figures, report, period_s, log_file)


def print_part_one(
    status: StatusSnapshot,
    bare: dict,
    times: dict,
    clients: dict,
    report: dict,
    period_s: float,
    log_file: Path,
) -> None:
    stats = status.stats
    runtime = {
        "p50": stats.lateness_p50_us,
        "p99": stats.lateness_p99_us,
        "p99.9": stats.lateness_p999_us,
        "max": stats.lateness_max_us,
        "cycles": stats.cycles,
        "missed": stats.missed_periods,
    }
    print("wake-up lateness (µs), each loop measured by itself over the run")
    print(
        f"{'loop':<44} {'p50':>8} {'p99':>8} {'p99.9':>8} {'max':>9} {'periods':>8} {'missed':>6}"
    )
    for label, figures in (
        ("bare SCHED_FIFO 80 + mlockall", bare),
        ("runtime cycle under load", runtime),
    ):
        print(
            f"{label:<44} {figures['p50']:>8.1f} {figures['p99']:>8.1f} {figures['p99.9']:>8.1f}"
            f" {figures['max']:>9.1f} {int(figures['cycles']):>8d} {int(figures['missed']):>6d}"
        )
    ratio99 = runtime["p99"] / max(bare["p99"], 1e-9)
    ratio999 = runtime["p99.9"] / max(bare["p99.9"], 1e-9)
    print(
        f"ratios: p99 {ratio99:.2f} (target <= 2), p99.9 {ratio999:.2f} (target <= 1.3), "
        f"missed {runtime['missed']} vs bare {bare['missed']} (target <=)"
    )
    sync = interval_figures(times[SYNC_COB_ID], period_s)
    reference = interval_figures(times[BARE_COB_ID], period_s)
    print("\nframe intervals on the bus, independent listener (|interval - period|, µs)")
    print(f"{'sender':<44} {'p99':>8} {'p99.9':>8} {'max':>9} {'frames':>8} {'>1.5T':>6}")
    for label, figures in (("bare sender (0x7E0)", reference), ("runtime SYNC (0x80)", sync)):
        print(
            f"{label:<44} {figures['p99_us']:>8.1f} {figures['p999_us']:>8.1f}"
            f" {figures['max_us']:>9.1f} {figures['count']:>8d} {figures['long']:>6d}"
        )
    print(
        f"ratios: p99 {sync['p99_us'] / max(reference['p99_us'], 1e-9):.2f} (target <= 2), "
        f"p99.9 {sync['p999_us'] / max(reference['p999_us'], 1e-9):.2f} (target <= 1.5), "
        f"long intervals {sync['long']} vs {reference['long']} (target <=)"
    )
    faults = report.get("faults", [])
    print(f"\nfaults during the motion: {len(faults)}" + "".join(f"\n  {f}" for f in faults))
    print_override_latency(report)
    latency_ms = clients["latency_s"] * 1000
    print(
        f"Modbus: {clients['reads']} whole-status reads by {CLIENTS} clients, {clients['errors']} "
        f"with errors, p50 {np.percentile(latency_ms, 50):.2f} ms, "
        f"p99 {np.percentile(latency_ms, 99):.2f} ms"
    )
    # Both loops above lose what a hypervisor takes: without it, the figures compare loops;
    # with it, they also show how the host shared its CPUs.
    print(
        f"host steal time during the motion: {report.get('steal_s', 0.0):.2f} s of "
        f"{report.get('seconds', 0.0):g} s on {os.cpu_count()} CPUs"
    )
    print(f"runtime log: {log_file}")


# -- part 2 -------------------------------------------------------------------------------------


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def print_override_latency(report: dict) -> None:
    """Periods from each override change to its first re-planned setpoint; apart, those that
    came while the plan braked to a rest it had to reach first, counted beyond that rest."""
    pairs = np.array(report.get("latencies", []) or [(0, 0)]).reshape(-1, 2)
    latencies, rest_waits = pairs[:, 0], pairs[:, 1]
    print(
        f"override changes: {report.get('override_changes', 0)}; periods from the change to its "
        f"first re-planned setpoint ({len(latencies)} seen): median {np.median(latencies):.0f}, "
        f"p90 {np.percentile(latencies, 90):.0f}, p99 {np.percentile(latencies, 99):.0f}, "
        f"max {latencies.max()}, {np.mean(latencies <= 2):.0%} within 2 (target <= 2); "
        "hold: braking starts in the period the command is applied (0)"
    )
    waited = rest_waits > 0
    beyond = latencies[waited] - rest_waits[waited]
    free = latencies[~waited]
    print(
        f"  {waited.sum()} came while the plan braked to a rest it had to reach first (the "
        "approach's end or a sharp corner: no setpoint before it can change); periods beyond "
        f"that rest: max {beyond.max() if len(beyond) else 0}. The other {len(free)}: "
        f"{np.mean(free <= 2) if len(free) else 1.0:.1%} within 2, "
        f"max {free.max() if len(free) else 0}"
    )


def part_two(seconds: float) -> None:
    """CPU time of the cycle process per period, with the configured spin before each deadline
    (busy-waiting, counted as CPU time) and without it (the period's work alone)."""
    spin_us = SIM_REALTIME.spin_us
    print(f"\ncycle process CPU per period, machine enabled and moving, {seconds:g} s each")
    print(f"{'axes':>5} {'spin (µs)':>10} {'CPU per period (µs)':>20} {'longest period (µs)':>20}")
    for axes in (3, 8):
        for spin in (spin_us, 0.0):
            config = bench_config(f"cpu-{uuid.uuid4().hex[:8]}", seconds, axes)
            realtime = replace(config.cycle.realtime, spin_us=spin)
            config = replace(
                config,
                modbus=replace(config.modbus, enabled=False),
                cycle=replace(config.cycle, realtime=realtime),
            )
            with Runtime(config, log_level="WARNING") as runtime:
                runtime.wait_for(
                    lambda s: all(a.boot_phase == BootPhase.READY for a in s.axes), 30.0
                )
                pid = runtime.process("cycle").pid
                report: dict = {}
                before_cpu, before = _cpu_s(pid), runtime.status().stats.cycles
                run_motion(runtime, seconds, report)
                status = runtime.status()
                cpu, periods = _cpu_s(pid) - before_cpu, status.stats.cycles - before
            print(
                f"{axes:>5} {spin:>10g} {cpu / max(periods, 1) * 1e6:>20.1f} "
                f"{status.stats.execution_max_us:>20.1f}"
            )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="motion under load")
    parser.add_argument("--cpu-seconds", type=float, default=10.0, help="motion per axis count")
    args = parser.parse_args(argv)
    period_s = load_config(ROOT / "configs" / "sim.yaml").cycle.period_s
    part_one(args.seconds, period_s)
    part_two(args.cpu_seconds)


if __name__ == "__main__":
    sys.exit(main())
