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
import gc
import logging
import os
import signal
import threading

from drives.sim.drive import DriveModel, start_simulated_drives
from drives.sim.quirks import DriveQuirks

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
    quirks = parser.add_argument_group(
        "quirks", "behave like drives of other vendors (see drives.sim.quirks)"
    )
    quirks.add_argument(
        "--boot-delay-s",
        type=float,
        default=0.0,
        help="delay before the boot-up message, after power-on or an NMT reset (s)",
    )
    for flag, help_text in _QUIRK_FLAGS.items():
        quirks.add_argument(f"--{flag.replace('_', '-')}", action="store_true", help=help_text)
    quirks.add_argument(
        "--sdo-delay-ms",
        type=float,
        nargs=2,
        metavar=("SHORTEST", "LONGEST"),
        default=(0.0, 0.0),
        help="each SDO answer comes this long after its request (ms, uniform)",
    )
    quirks.add_argument(
        "--late-tpdo-periods",
        type=int,
        default=0,
        help="send each synchronous TPDO this many SYNCs after the one it answers",
    )
    parser.add_argument(
        "--priority",
        type=int,
        default=0,
        help="SCHED_FIFO priority 1..99 of the drive's threads, as hardware that never waits "
        "for the host (default 0: the normal scheduler)",
    )
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging level (default: INFO)",
    )


#: Boolean quirks, as ``DriveQuirks`` field -> help text.
_QUIRK_FLAGS = {
    "no_optional_objects": "no 0x6066, 0x6007, 0x605A, 0x605E, 0x6065, 0x1016, 0x1017",
    "fixed_pdo_mapping": "PDOs valid from power-on in a vendor layout, all read-only",
    "interpolation_ms_only": "0x60C2:01 in 1..20 and 0x60C2:02 only -3",
    "fault_at_power_on": "power on in FAULT (EMCY 0x8130 latched earlier)",
    "guarding_only": "no heartbeat objects (0x1016, 0x1017): node guarding only",
}


def quirks_from_arguments(args: argparse.Namespace) -> DriveQuirks:
    """The quirks the parsed options ask for.

    :raises ValueError: on negative delays.
    """
    shortest_ms, longest_ms = args.sdo_delay_ms
    return DriveQuirks(
        **{flag: getattr(args, flag) for flag in _QUIRK_FLAGS},
        sdo_delay_s=(shortest_ms / 1000.0, longest_ms / 1000.0),
        boot_delay_s=args.boot_delay_s,
        late_tpdo_periods=args.late_tpdo_periods,
    )


def quirk_arguments(quirks: DriveQuirks) -> list[str]:
    """The options that give a drive process ``quirks`` (inverse of
    :func:`quirks_from_arguments`)."""
    arguments = [f"--{flag.replace('_', '-')}" for flag in _QUIRK_FLAGS if getattr(quirks, flag)]
    shortest_s, longest_s = quirks.sdo_delay_s
    if longest_s:
        arguments += ["--sdo-delay-ms", f"{shortest_s * 1000:g}", f"{longest_s * 1000:g}"]
    if quirks.boot_delay_s:
        arguments += ["--boot-delay-s", f"{quirks.boot_delay_s:g}"]
    if quirks.late_tpdo_periods:
        arguments += ["--late-tpdo-periods", str(quirks.late_tpdo_periods)]
    return arguments


def run(args: argparse.Namespace) -> int:
    """Run one simulated drive until SIGINT or SIGTERM; return the exit status (0).

    :raises ValueError: if a model option is out of range.
    :raises drives.errors.BusUnavailable: if the bus cannot be opened.
    """
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.priority:
        # Set before the bus and the drive start their threads: they inherit it.
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
        except OSError as exc:
            logger.warning("SCHED_FIFO %d refused (%s): normal scheduling", args.priority, exc)
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
            quirks={args.node: quirks_from_arguments(args)},
        ) as drive_set:
            drive = drive_set.drives[args.node]
            # What start-up built lives as long as the drive: kept from the collector, a full
            # collection (9 ms otherwise, on a 2-core host) never delays an answer to SYNC.
            gc.collect()
            gc.freeze()

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
