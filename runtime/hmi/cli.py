"""The ``softmotion hmi`` subcommand: a Modbus TCP client for a running machine.

``softmotion hmi [--host H] [--port P] [--unit U] ACTION``, ACTION one of ``status``,
``load CURVE.yaml``, ``load-program N``, ``library [N]``, ``start``, ``hold``, ``resume``,
``stop``, ``quick-stop``, ``reset``, ``enable``, ``disable``, ``clear-next``,
``override PERCENT``, ``abort-upload``, ``watch``. Every command waits for the outcome of its own
request (its sequence value in the server's request history), and enable, disable and reset then
for the machine to reach the state they lead to; ``watch`` prints one status line per refresh
and advances the HMI heartbeat, until Ctrl-C (exit 0), ``--count`` refreshes, or with
``--until-idle`` until the machine rests.

Exit status: 0 success; 1 refused command or curve, Modbus exception, connection failure or
timeout (the message names the Modbus exception or the result code and reason); 1 also when
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
from runtime.hmi.registers import HmiStatus, LibraryEntry, LibraryState, StatusBit, as_enum
from runtime.status import MachineState

if TYPE_CHECKING:
    from runtime.hmi.client import HmiClient, Outcome

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
    "clear-next": CommandCode.CLEAR_NEXT,
}
#: Commands whose effect takes more than one cycle (drives switching on or off), and the states
#: the command line waits for once the machine has executed them.
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
        help="seconds to wait for an answer or an outcome (5)",
    )
    actions = parser.add_subparsers(dest="hmi_action", required=True, metavar="ACTION")
    actions.add_parser("status", help="print the machine's status")
    load = actions.add_parser("load", help="upload a curve and commit it, wait for its outcome")
    load.add_argument("curve", metavar="CURVE.yaml", help="NURBS curve (YAML)")
    program = actions.add_parser("load-program", help="load library program N")
    program.add_argument("number", type=int, metavar="N", help="1-based program number")
    library = actions.add_parser("library", help="list the program library (or program N)")
    library.add_argument("number", type=int, nargs="?", metavar="N", help="only program N")
    actions.add_parser("abort-upload", help="clear the staging area and give it free")
    for name, code in SIMPLE_COMMANDS.items():
        actions.add_parser(name, help=f"send {code.name} and wait for its outcome")
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


def _name(value: object) -> str:
    return getattr(value, "name", str(value))


def _result_text(result: CommandResult | int) -> str:
    from runtime.hmi.docgen import member_descriptions

    if isinstance(result, CommandResult):
        return f"{result.name} ({member_descriptions(CommandResult)[result.name]})"
    return str(result)


def _drive_state(value: int) -> str:
    state = as_enum(DriveState, value)
    return state.name if isinstance(state, DriveState) else str(value)


def _bits(word: int) -> str:
    return " ".join(bit.name for bit in StatusBit if word & bit) or "-"


def format_status(status: HmiStatus) -> str:
    """The status as readable lines."""
    s, server = status.snapshot, status.server
    if s is None:
        return "machine   STARTING (the runtime has not published its status yet)"
    fault = "none"
    if s.fault is not None:
        where = f" on axis {s.fault.axis}" if s.fault.axis else ""
        emcy = f", EMCY 0x{s.fault.emcy_code:04X}" if s.fault.emcy_code else ""
        later = f" (+{status.later_fault_count} later)" if status.later_fault_count else ""
        fault = f"{_name(s.fault.kind)}{where}: {s.fault.text}{emcy}{later}"
    lines = [
        f"machine   {_name(s.state)}  phase {_name(s.phase)}  override "
        f"{s.override_percent:.1f} %  message: {s.message or '-'}",
        f"status    {_bits(status.status_word)}",
        f"fault     {fault}",
        f"path      {s.path_s_mm:.3f} / {s.path_length_mm:.3f} mm  ({s.progress_permille} ‰)  "
        f"feed {s.feed_mm_s:.2f} mm/s",
    ]
    for axis in s.axes:
        lines.append(
            f"axis {axis.name:<4} commanded {axis.commanded_mm:10.4f}  actual "
            f"{axis.actual_mm:10.4f}  following error {axis.following_error_mm:8.4f} mm  "
            f"statusword 0x{axis.statusword:04X}  node {axis.node_id} "
            f"{_drive_state(axis.drive_state)}"
        )
    for label, program in (("program", s.program), ("next", s.next_program)):
        if program is not None:
            lines.append(
                f"{label:<9} id {program.program_id} {program.name!r}  crc32 "
                f"0x{program.crc32:08X}  {program.length_mm:.3f} mm"
            )
    last = s.last_command
    if last is not None:
        lines.append(
            f"command   ticket {last.ticket} {_name(last.code)} from {_name(last.origin)} "
            f"(seq {last.seq}): {_name(last.result)}"
        )
    for request in server.requests[:1]:
        lines.append(
            f"request   seq {request.seq} {_name(request.code)} (ticket {request.ticket}): "
            f"{_name(request.result)}"
            + (f": {server.request_message}" if server.request_message else "")
        )
    staging = server.staging
    if staging.owner_port:
        lines.append(
            f"staging   held by {_ipv4(staging.owner_ip)}:{staging.owner_port} for "
            f"{staging.hold_left_ms} ms more"
        )
    st = s.stats
    lines += [
        f"cycles    {st.cycles}  lateness last {st.lateness_last_us:.0f} µs  p50 "
        f"{st.lateness_p50_us:.0f} µs  p99 {st.lateness_p99_us:.0f} µs  max "
        f"{st.lateness_max_us:.0f} µs  missed periods {st.missed_periods}",
        f"watchdog  {_name(s.watchdog)}  heartbeat {s.heartbeat}",
    ]
    return "\n".join(lines)


def _ipv4(value: int) -> str:
    return ".".join(str((value >> shift) & 0xFF) for shift in (24, 16, 8, 0))


def format_line(status: HmiStatus) -> str:
    """The status as one line, for ``watch``."""
    s = status.snapshot
    if s is None:
        return "STARTING"
    axes = "  ".join(f"{a.name} {a.actual_mm:9.3f}" for a in s.axes)
    return (
        f"{_name(s.state):<10} {_name(s.phase):<8} {s.path_s_mm:9.3f}/{s.path_length_mm:.3f} mm "
        f"{s.progress_permille:4d} ‰  feed {s.feed_mm_s:7.2f} mm/s  {axes}  "
        f"missed {s.stats.missed_periods}"
    )


def format_entry(entry: LibraryEntry) -> str:
    """A library program as one line."""
    if entry.state == LibraryState.VALID:
        return (
            f"{entry.number:4d}  {entry.name}  {entry.points} points  {entry.length_mm:.3f} mm  "
            f"crc32 0x{entry.crc32:08X}"
        )
    why = f": {_name(entry.result)}" if entry.state == LibraryState.INVALID else ""
    return f"{entry.number:4d}  {entry.name or '-'}  {_name(entry.state)}{why}"


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
            state = status.snapshot.state if status.snapshot is not None else None
            if args.until_idle and state in IDLE_STATES:
                if state is MachineState.ERROR_STOP:
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
    print(
        f"loaded {path}: degree {curve.degree}, {len(curve.control_points)} points: "
        f"{_loaded(client, outcome)}",
        file=out,
    )
    return EXIT_OK


def _loaded(client: HmiClient, outcome: Outcome) -> str:
    s = client.status().snapshot
    if s is None:
        return f"seq {outcome.seq} {_name(outcome.result)}"
    moving = s.next_program is not None and s.state is not MachineState.STANDBY
    program = s.next_program if moving else s.program
    where = "next program" if moving else "program"
    if program is None:
        return f"seq {outcome.seq} {_name(outcome.result)}"
    return (
        f"{where} {program.program_id} {program.name!r}, crc32 0x{program.crc32:08X}, "
        f"{program.length_mm:.3f} mm (seq {outcome.seq})"
    )


def _library(client: HmiClient, number: int | None, out: TextIO) -> int:
    if number is not None:
        entry = client.library_entry(number)
        print(format_entry(entry), file=out)
        return EXIT_OK if entry.state == LibraryState.VALID else EXIT_FAILURE
    count = client.library_count()
    if not count:
        print("the program library is empty (or not configured: programs.library_dir)", file=out)
    for n in range(1, count + 1):
        print(format_entry(client.library_entry(n)), file=out)
    return EXIT_OK


def _settle(client: HmiClient, code: CommandCode, started: MachineState | None) -> int:
    """Wait for the state ``code`` leads to; ERROR_STOP ends the wait when it is new."""
    settled = SETTLED_STATES[code]

    def done(status: HmiStatus) -> bool:
        s = status.snapshot
        if s is None:
            return False
        return s.state in settled or (
            s.state is MachineState.ERROR_STOP and started is not MachineState.ERROR_STOP
        )

    state = client.wait_for(done, what=f"{code.name.lower()} to take effect").snapshot.state  # type: ignore[union-attr]
    if state not in settled:
        print(f"{code.name.lower()}: machine in {_name(state)}", file=sys.stderr)
        return EXIT_FAILURE
    return EXIT_OK


def _dispatch(client: HmiClient, args: argparse.Namespace, out: TextIO) -> int:
    action = args.hmi_action
    if action == "status":
        print(format_status(client.status()), file=out)
        return EXIT_OK
    if action == "watch":
        return _watch(client, args, out)
    if action == "load":
        return _load(client, args.curve, out)
    if action == "library":
        return _library(client, args.number, out)
    if action == "abort-upload":
        client.abort_upload()
        print("staging area cleared and free", file=out)
        return EXIT_OK
    if action == "load-program":
        outcome = client.load_program(args.number)
        print(f"loaded library program {args.number}: {_loaded(client, outcome)}", file=out)
        return EXIT_OK
    if action == "override":
        outcome = client.command(CommandCode.SET_OVERRIDE, override_percent=args.percent)
    else:
        code = SIMPLE_COMMANDS[action]
        before = client.status().snapshot
        outcome = client.command(code)
        if code in SETTLED_STATES:
            settled = _settle(client, code, before.state if before is not None else None)
            if settled != EXIT_OK:
                return settled
    print(f"{action}: seq {outcome.seq}: {_result_text(outcome.result)}", file=out)
    return EXIT_OK


def run(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    """Run ``softmotion hmi`` with parsed ``args``; returns the exit status."""
    # Imported here so that building the command line's parser does not import pymodbus.
    from runtime.hmi.client import CommandRefused, HmiClient

    client = HmiClient(args.host, args.port, unit=args.unit, timeout_s=args.timeout)
    try:
        client.connect()
        return _dispatch(client, args, out)
    except CommandRefused as exc:
        print(f"softmotion hmi: {exc} ({_result_text(exc.result)})", file=sys.stderr)
    except HmiError as exc:
        print(f"softmotion hmi: {exc}", file=sys.stderr)
    finally:
        client.close()
    return EXIT_FAILURE
