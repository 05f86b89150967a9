"""The ``softmotion`` command line.

``run`` is the main job (the machine: bus, drives, cyclic task, HMI server); ``plan`` plans a
curve offline and reports on it; ``hmi`` is a Modbus TCP client for the machine; ``sim-drive``
runs one simulated CiA-402 drive as its own process. A configuration that does not validate
prints its :class:`~runtime.errors.ConfigError` and exits with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from runtime.config import DEFAULT_CONFIG_PATH, load_config
from runtime.errors import ConfigError
from runtime.logs import queued_logging
from runtime.version import VERSION

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


def _config_parent() -> argparse.ArgumentParser:
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument(
        "--config",
        type=Path,
        default=DEFAULT_CONFIG_PATH,
        metavar="FILE",
        help=f"machine description (YAML); default {DEFAULT_CONFIG_PATH}",
    )
    return parent


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="softmotion",
        description=(
            "Soft-motion runtime: NURBS look-ahead interpolation streamed every period to "
            "CANopen CiA-402 drives, commanded over Modbus TCP."
        ),
    )
    parser.add_argument("--version", action="version", version=f"softmotion {VERSION}")
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        help="logging threshold (default INFO)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    config = _config_parent()

    run = sub.add_parser(
        "run",
        parents=[config],
        help="run the machine (the main job)",
        description=(
            "Start the CAN bus, the simulated drives when the configuration asks for them, the "
            "CiA-402 master, the cyclic task and the Modbus TCP server, then serve until SIGINT "
            "or SIGTERM (controlled stop, drives disabled, exit 0)."
        ),
    )
    run.add_argument(
        "--demo",
        action="store_true",
        help="run the paper's curve (or --curve) to the end, print a summary, exit",
    )
    run.add_argument("--curve", type=Path, metavar="CURVE.yaml", help="curve to load at start")

    plan = sub.add_parser(
        "plan",
        parents=[config],
        help="plan a curve offline and print its figures",
        description=(
            "Plan CURVE.yaml with the configuration's limits and print length, motion time, "
            "max feed, acceleration, jerk, chord error, feed fluctuation and planning speed."
        ),
    )
    plan.add_argument("curve", type=Path, metavar="CURVE.yaml", help="NURBS curve (YAML)")
    plan.add_argument(
        "--no-lookahead", action="store_true", help="feed from eq. (4) alone, for comparison"
    )
    plan.add_argument(
        "--update",
        choices=("taylor2", "corrected"),
        help="parameter update (default from the configuration)",
    )
    plan.add_argument("--trace", type=Path, metavar="OUT.csv", help="one CSV row per period")
    plan.add_argument(
        "--plot", type=Path, metavar="OUT.png", help="chord error, feed, acceleration, jerk"
    )

    hmi = sub.add_parser(
        "hmi",
        help="Modbus TCP client for a running machine",
        description="Upload curves, command the machine and watch its status over Modbus TCP.",
    )
    from runtime.hmi import cli as hmi_cli

    hmi_cli.add_arguments(hmi)

    sim_drive = sub.add_parser(
        "sim-drive",
        help="run one simulated CiA-402 drive on a CAN bus",
        description="A simulated CiA-402 servo drive as its own process (e.g. on vcan0).",
    )
    from drives.sim import service as sim_service

    sim_service.add_arguments(sim_drive)

    from runtime import doctor

    doctor.add_arguments(
        sub.add_parser(
            "doctor",
            parents=[config],
            help="check this machine for the configured cycle",
            description="One line per check (ok, warn, fail with its fix); exit 1 if any fails.",
        )
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``softmotion`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    with queued_logging(args.log_level):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    try:
        if args.command == "run":
            from runtime.app import run_machine

            return run_machine(
                load_config(args.config),
                demo=args.demo,
                curve_path=args.curve,
                log_level=args.log_level,
            )
        if args.command == "plan":
            return _plan(args)
        if args.command == "doctor":
            from runtime import doctor

            return doctor.run(args)
        if args.command == "hmi":
            from runtime.hmi import cli as hmi_cli

            return hmi_cli.run(args)
        from drives.sim import service as sim_service

        return sim_service.run(args)
    except ConfigError as exc:
        print(f"softmotion: {exc}", file=sys.stderr)
        return EXIT_USAGE


def _plan(args: argparse.Namespace) -> int:
    from planner.errors import PlannerError
    from runtime.curves import load_curve_file, planner_limits
    from runtime.plan_report import run_plan

    config = load_config(args.config)
    try:
        curve = load_curve_file(args.curve)
    except PlannerError as exc:
        print(f"softmotion: {args.curve}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    run_plan(
        curve,
        planner_limits(config),
        config.cycle.period_s,
        lookahead=config.planner.lookahead and not args.no_lookahead,
        update=args.update or config.planner.update,
        trace_path=args.trace,
        plot_path=args.plot,
        out=sys.stdout,
    )
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
