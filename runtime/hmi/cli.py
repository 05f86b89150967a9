"""The ``softmotion hmi`` subcommand: a Modbus TCP client for a running machine.

``softmotion hmi [--host H] [--port P] [--unit U] ACTION``, ACTION one of ``status``,
``load CURVE.yaml``, ``start``, ``hold``, ``resume``, ``stop``, ``quick-stop``, ``reset``,
``enable``, ``disable``, ``override PERCENT``, ``watch``. Commands wait until the machine has
executed them; ``watch`` prints one status line per refresh and advances the HMI heartbeat, until
Ctrl-C (exit 0), ``--count`` refreshes, or with ``--until-idle`` until the machine rests.

Exit status: 0 success; 1 refused command or curve, Modbus exception, connection failure or
timeout (the message names the Modbus exception and the result code); 1 also when
``watch --until-idle`` ends in ERROR_STOP.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING, TextIO

from drives.cia402 import State as DriveState
from planner.errors import PlannerError
from runtime.commands import CommandCode, CommandResult
from runtime.config import ModbusConfig
from runtime.hmi import HmiError
from runtime.hmi.registers import HmiStatus, as_enum
from runtime.status import MachineState

if TYPE_CHECKING:
    from runtime.hmi.client import HmiClient

EXIT_OK = 0
EXIT_FAILURE = 1

#: Actions that are one machine command, without parameters.
SIMPLE_COMMANDS: dict[str, CommandCode] = {
    "enable": CommandCode.ENABLE,
    "disable": CommandCode.DISABLE,
    "start": CommandCode.START,
    "hold": CommandCode.HOLD,
    "resume": CommandCode.RESUME,
    "stop": CommandCode.STOP,
    "quick-stop": CommandCode.QUICK_STOP,
    "reset": CommandCode.RESET,
}
#: Commands whose effect takes more than one cycle (drives switching on or off), and the states
#: the command line waits for after the acknowledgement (ERROR_STOP ends the wait too).
SETTLED_STATES: dict[CommandCode, frozenset[MachineState]] = {
    CommandCode.ENABLE: frozenset({MachineState.STANDBY}),
    CommandCode.DISABLE: frozenset({MachineState.DISABLED}),
    CommandCode.RESET: frozenset({MachineState.STANDBY, MachineState.DISABLED}),
}
#: States in which ``watch --until-idle`` stops watching.
IDLE_STATES = frozenset({MachineState.DISABLED, MachineState.STANDBY, MachineState.ERROR_STOP})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options and actions of ``softmotion hmi`` to ``parser``."""
    default = ModbusConfig()
    parser.add_argument("--host", default="127.0.0.1", help="machine address (127.0.0.1)")
    parser.add_argument(
        "--port", type=int, default=default.port, help=f"Modbus TCP port ({default.port})"
    )
    parser.add_argument("--unit", type=int, default=default.unit_id, help="unit id (1)")
    parser.add_argument(
        "--timeout",
        type=float,
        default=5.0,
        metavar="S",
        help="seconds to wait for an answer or an acknowledgement (5)",
    )
    actions = parser.add_subparsers(dest="hmi_action", required=True, metavar="ACTION")
    actions.add_parser("status", help="print the machine's status")
    load = actions.add_parser("load", help="upload a curve, commit it, wait until loaded")
    load.add_argument("curve", metavar="CURVE.yaml", help="NURBS curve (YAML)")
    for name, code in SIMPLE_COMMANDS.items():
        actions.add_parser(name, help=f"send {code.name} and wait until executed")
    override = actions.add_parser("override", help="set the feed override")
    override.add_argument("percent", type=float, metavar="PERCENT", help="0..150")
    watch = actions.add_parser("watch", help="refresh the status until interrupted")
    watch.add_argument("--interval", type=float, default=0.2, metavar="S", help="(0.2 s)")
    watch.add_argument("--count", type=int, metavar="N", help="stop after N refreshes")
    watch.add_argument(
        "--until-idle", action="store_true", help="stop when the machine is no longer moving"
    )
    watch.add_argument(
        "--no-heartbeat", action="store_true", help="only read (do not feed the watchdog)"
    )


def _result_text(result: CommandResult | int) -> str:
    from runtime.hmi.docgen import member_descriptions

    if isinstance(result, CommandResult):
        return f"{result.name} ({member_descriptions(CommandResult)[result.name]})"
    return str(result)


def _drive_state(value: int) -> str:
    state = as_enum(DriveState, value)
    return state.name if isinstance(state, DriveState) else str(value)


def format_status(status: HmiStatus) -> str:
    """The status as readable lines."""
    s, server = status.snapshot, status.server
    state = s.state.name if isinstance(s.state, MachineState) else str(s.state)
    fault = "none"
    if s.fault is not None:
        where = f" on axis {s.fault.axis}" if s.fault.axis else ""
        emcy = f", EMCY 0x{s.fault.emcy_code:04X}" if s.fault.emcy_code else ""
        fault = f"{s.fault.kind.name}{where}: {s.fault.text}{emcy}"
    lines = [
        f"machine   {state}  override {s.override_percent:.1f} %  message: {s.message or '-'}",
        f"fault     {fault}",
        f"path      {s.path_s_mm:.3f} / {s.path_length_mm:.3f} mm  ({s.progress_permille} ‰)  "
        f"feed {s.feed_mm_s:.2f} mm/s",
    ]
    for axis in s.axes:
        lines.append(
            f"axis {axis.name:<4} commanded {axis.commanded_mm:10.4f}  actual "
            f"{axis.actual_mm:10.4f}  following error {axis.following_error_mm:8.4f} mm  "
            f"node {axis.node_id} {_drive_state(axis.drive_state)}"
        )
    st = s.stats
    result = as_enum(CommandResult, s.last_command_result)
    lines += [
        f"curve     id {s.curve_id}  crc32 0x{s.curve_crc:08X}",
        f"command   seq {s.last_command_seq}: "
        f"{result.name if isinstance(result, CommandResult) else result}  "
        f"(request seq {server.request_seq}: {_name(server.request_result)}, "
        f"upload seq {server.upload_seq}: {_name(server.upload_result)})",
        f"cycles    {st.cycles}  lateness last {st.lateness_last_us:.0f} µs  p50 "
        f"{st.lateness_p50_us:.0f} µs  p99 {st.lateness_p99_us:.0f} µs  max "
        f"{st.lateness_max_us:.0f} µs  missed periods {st.missed_periods}",
        f"watchdog  {_name(server.watchdog)}  heartbeat {s.heartbeat}",
    ]
    return "\n".join(lines)


def _name(value: object) -> str:
    return getattr(value, "name", str(value))


def format_line(status: HmiStatus) -> str:
    """The status as one line, for ``watch``."""
    s = status.snapshot
    axes = "  ".join(f"{a.name} {a.actual_mm:9.3f}" for a in s.axes)
    return (
        f"{_name(s.state):<10} {s.path_s_mm:9.3f}/{s.path_length_mm:.3f} mm "
        f"{s.progress_permille:4d} ‰  feed {s.feed_mm_s:7.2f} mm/s  {axes}  "
        f"missed {s.stats.missed_periods}"
    )


def _watch(client: HmiClient, args: argparse.Namespace, out: TextIO) -> int:
    heartbeat = not args.no_heartbeat and not client.identity.read_only
    refreshes = 0
    try:
        while True:
            if heartbeat:
                client.heartbeat()
            status = client.status()
            print(format_line(status), file=out, flush=True)
            refreshes += 1
            if args.until_idle and status.snapshot.state in IDLE_STATES:
                if status.snapshot.state is MachineState.ERROR_STOP:
                    print(format_status(status), file=out)
                    return EXIT_FAILURE
                return EXIT_OK
            if args.count is not None and refreshes >= args.count:
                return EXIT_OK
            time.sleep(args.interval)
    except KeyboardInterrupt:
        return EXIT_OK


def _load(client: HmiClient, path: str, out: TextIO) -> int:
    from runtime.curves import load_curve_file

    try:
        curve = load_curve_file(path)
    except PlannerError as exc:
        print(f"softmotion hmi: {path}: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    outcome = client.load_curve(curve)
    status = client.status().snapshot
    print(
        f"loaded {path}: degree {curve.degree}, {len(curve.control_points)} points, "
        f"curve id {status.curve_id}, crc32 0x{status.curve_crc:08X}: {_name(outcome.result)}",
        file=out,
    )
    return EXIT_OK if outcome.result is CommandResult.DONE else EXIT_FAILURE


def _dispatch(client: HmiClient, args: argparse.Namespace, out: TextIO) -> int:
    action = args.hmi_action
    if action == "status":
        print(format_status(client.status()), file=out)
        return EXIT_OK
    if action == "watch":
        return _watch(client, args, out)
    if action == "load":
        return _load(client, args.curve, out)
    if action == "override":
        outcome = client.command(CommandCode.SET_OVERRIDE, override_percent=args.percent)
    else:
        code = SIMPLE_COMMANDS[action]
        outcome = client.command(code)
        if outcome.result is CommandResult.DONE and code in SETTLED_STATES:
            settled = SETTLED_STATES[code] | {MachineState.ERROR_STOP}
            state = client.wait_for(
                lambda s: s.snapshot.state in settled, what=f"{action} to take effect"
            ).snapshot.state
            if state not in SETTLED_STATES[code]:
                print(f"{action}: machine in {_name(state)}", file=sys.stderr)
                return EXIT_FAILURE
    print(f"{action}: seq {outcome.seq}: {_result_text(outcome.result)}", file=out)
    return EXIT_OK if outcome.result is CommandResult.DONE else EXIT_FAILURE


def run(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    """Run ``softmotion hmi`` with parsed ``args``; returns the exit status."""
    # Imported here so that building the command line's parser does not import pymodbus.
    from runtime.hmi.client import CommandRefused, HmiClient

    client = HmiClient(args.host, args.port, unit=args.unit, timeout_s=args.timeout)
    try:
        client.connect()
        return _dispatch(client, args, out)
    except CommandRefused as exc:
        print(f"softmotion hmi: {exc}: {_result_text(exc.result)}", file=sys.stderr)
    except HmiError as exc:
        print(f"softmotion hmi: {exc}", file=sys.stderr)
    finally:
        client.close()
    return EXIT_FAILURE
