"""The ``softmotion sim-drive`` process: one simulated CiA 402 drive on a CAN interface.

Runs :class:`drives.sim.drive.SimulatedDrive` on its own bus (for example SocketCAN ``vcan0``)
until SIGINT or SIGTERM, logging its NMT and CiA 402 state changes and its faults, then exits 0.
SIGUSR1 injects an over-temperature fault (EMCY 0x4210), so another process (a test) can fault
it. ``python -m drives.sim`` runs the same entry point.

Threading: the main thread waits for the signal; the drive works in the bus notifier thread and
its watchdog thread.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading

from drives.sim.drive import DriveModel, start_simulated_drives

logger = logging.getLogger(__name__)


def _node_id(text: str) -> int:
    value = int(text, 0)
    if not 1 <= value <= 127:
        raise argparse.ArgumentTypeError(f"--node {text}: must be in 1..127")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the sim-drive options to ``parser``."""
    defaults = DriveModel()
    parser.add_argument("--node", type=_node_id, required=True, help="CANopen node-ID, 1..127")
    parser.add_argument(
        "--interface", default="socketcan", help="python-can interface (default: socketcan)"
    )
    parser.add_argument("--channel", default="vcan0", help="CAN channel (default: vcan0)")
    parser.add_argument("--bitrate", type=int, default=None, help="bit/s, where the bus sets it")
    parser.add_argument(
        "--max-velocity-counts-s",
        type=float,
        default=defaults.max_velocity_counts_s,
        help="velocity limit of the simulated axis (counts/s)",
    )
    parser.add_argument(
        "--max-accel-counts-s2",
        type=float,
        default=defaults.max_accel_counts_s2,
        help="acceleration limit of the simulated axis (counts/s^2)",
    )
    parser.add_argument(
        "--lag-periods",
        type=int,
        default=defaults.lag_periods,
        help="SYNC periods between a received target and its use as demand",
    )
    parser.add_argument(
        "--sync-timeout-factor",
        type=float,
        default=defaults.sync_timeout_factor,
        help="SYNC-loss fault after this many 0x1006 periods without SYNC",
    )
    parser.add_argument(
        "--boot-delay-s", type=float, default=0.0, help="delay before the boot-up message (s)"
    )
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging level (default: INFO)",
    )


def run(args: argparse.Namespace) -> int:
    """Run one simulated drive until SIGINT or SIGTERM; return the exit status (0).

    :raises ValueError: if a model option is out of range.
    :raises drives.errors.BusUnavailable: if the bus cannot be opened.
    """
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    model = DriveModel(
        max_velocity_counts_s=args.max_velocity_counts_s,
        max_accel_counts_s2=args.max_accel_counts_s2,
        lag_periods=args.lag_periods,
        sync_timeout_factor=args.sync_timeout_factor,
    )
    stop = threading.Event()

    def _on_signal(signum: int, frame: object) -> None:
        logger.info("signal %s: powering off", signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with start_simulated_drives(
            args.interface,
            args.channel,
            [args.node],
            model=model,
            bitrate=args.bitrate,
            boot_delay_s=args.boot_delay_s,
        ) as drive_set:
            drive = drive_set.drives[args.node]

            def _on_fault_signal(signum: int, frame: object) -> None:
                logger.info("signal SIGUSR1: injecting an over-temperature fault")
                drive.inject_fault()

            # Fault injection from another process (tests on vcan0): SIGUSR1 = over-temperature.
            previous[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, _on_fault_signal)
            logger.info("simulated drive node %d on %s:%s", args.node, args.interface, args.channel)
            while not stop.wait(1.0):
                pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
