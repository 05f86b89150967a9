"""Writes ``docs/register-map.md`` from the register map and the command and status enums.

The document is generated, never edited by hand; a test compares it with :func:`render`. It
lists every register, the values of every enumerated register (from the enums' member
docstrings), the command protocol, the curve upload and the program library, and the Modbus
behaviour on the wire (functions, limits, exceptions and when each is sent, malformed frames).
Regenerate with ``python -m runtime.hmi.docgen`` (``--check`` exits 1 when it is out of date).

Enum member descriptions come from their attribute docstrings (the string literal below each
member), read from the source with :mod:`ast`, as Sphinx autodoc does.
"""

from __future__ import annotations

import argparse
import ast
import inspect
import sys
import textwrap
from enum import IntEnum
from pathlib import Path

from drives.cia402 import State as DriveState
from runtime.commands import ALLOWED, OVERRIDE_MAX_PERCENT, CommandCode, CommandResult
from runtime.hmi.protocol import (
    MAX_READ_REGISTERS,
    MAX_READ_WRITE_REGISTERS,
    MAX_WRITE_REGISTERS,
    ExceptionCode,
    FunctionCode,
)
from runtime.hmi.registers import (
    BLOCKS,
    CORE_END,
    DRIVE_STATE_UNKNOWN,
    FIELD,
    FIELDS,
    HISTORY,
    HMI_COMMANDS,
    HOLDING_HEAD_END,
    INPUT_SIZE,
    MAGIC,
    MAP_VERSION,
    MAX_DEGREE,
    MAX_KNOTS,
    MAX_POINTS,
    MESSAGE_CHARS,
    OVERRIDE_SCALE,
    STATE_STARTING,
    Field,
    Kind,
    StatusBit,
    Table,
)
from runtime.hmi.server import EXTRA_UNIT_IDS, IDENTITY, HmiServer
from runtime.hmi.upload import RULE_RESULTS, encode_staging
from runtime.status import FAULT_TEXTS, FaultKind, MachineState

#: Where the document lives, relative to the repository root.
DOCUMENT = Path("docs/register-map.md")

_KNOT = FIELD["KNOT"].address
#: Results the server gives itself (nothing is posted to the machine).
SERVER_RESULTS = frozenset(
    {CommandResult.STAGING_LOCKED, CommandResult.NO_SUCH_PROGRAM, CommandResult.CURVE_CRC_MISMATCH}
    | {r for r in CommandResult if r.name.startswith("CURVE_")}
)
#: Values some registers hold beside their enum's members.
_EXTRA_VALUES: dict[type[IntEnum], tuple[tuple[int, str, str], ...]] = {
    MachineState: (
        (
            STATE_STARTING,
            "STARTING",
            "The runtime has not published its first status: the other status registers read 0 "
            "(axis positions NaN, names and node ids from the configuration).",
        ),
    ),
    DriveState: ((DRIVE_STATE_UNKNOWN, "UNKNOWN", "The statusword matches no CiA 402 state."),),
}
_UNITS = " and ".join(str(u) for u in EXTRA_UNIT_IDS)


def member_descriptions(enum: type[IntEnum]) -> dict[str, str]:
    """Attribute docstrings of an enum's members, by member name ("" when there is none)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(enum)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    found: dict[str, str] = {}
    for node, after in zip(body, [*body[1:], None], strict=True):
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            text = ""
            if (
                isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)
            ):
                text = " ".join(after.value.value.split())
            found[node.targets[0].id] = text
    return {member.name: found.get(member.name, "") for member in enum}


def _address(field: Field) -> str:
    if field.repeat == 1:
        last = field.end - 1
        return str(field.address) if last == field.address else f"{field.address}–{last}"
    return f"{field.address} + {field.stride}·i"


def _type(field: Field) -> str:
    if field.kind is Kind.ASCII:
        return f"ascii[{2 * field.registers}]"
    return field.kind.value


def _field_rows(table: Table, first: int, end: int) -> list[str]:
    rows = []
    for field in FIELDS:
        if field.table is table and first <= field.address < end:
            index = f" (i < {field.repeat})" if field.repeat > 1 else ""
            values = (
                f" — values: [{_enum_name(field.values)}](#{_anchor(field.values)})"
                if field.values
                else ""
            )
            maximum = ""
            if field.table is Table.HOLDING and field.maximum is not None:
                maximum = f" (at most {field.maximum})"
            rows.append(
                f"| {_address(field)} | `{field.name}`{index} | {_type(field)} | "
                f"{field.unit} | {field.description}{maximum}{values} |"
            )
    return rows


def _enum_name(enum: type[IntEnum]) -> str:
    return "DriveState" if enum is DriveState else enum.__name__


def _anchor(enum: type[IntEnum]) -> str:
    return _enum_name(enum).lower()


def _enums() -> list[type[IntEnum]]:
    found: list[type[IntEnum]] = []
    for field in FIELDS:
        if field.values is not None and field.values not in found:
            found.append(field.values)
    return found


def _enum_section(enum: type[IntEnum]) -> list[str]:
    descriptions = member_descriptions(enum)
    users = ", ".join(f"`{f.name}`" for f in FIELDS if f.values is enum)
    bits = enum is StatusBit or enum.__name__ == "AccessFlag"
    heading = "bit | value" if bits else "value"
    rows = [
        f"### {_enum_name(enum)}",
        "",
        f'<a id="{_anchor(enum)}"></a>Used by {users}.',
        "",
        f"| {heading} | name | meaning |",
        "|---|---|---|" + ("---|" if bits else ""),
    ]
    for member in enum:
        first = (
            f"{member.value.bit_length() - 1} | 0x{member.value:04X}" if bits else str(member.value)
        )
        rows.append(f"| {first} | `{member.name}` | {descriptions[member.name]} |")
    for value, name, text in _EXTRA_VALUES.get(enum, ()):
        rows.append(f"| {value} | `{name}` | {text} |")
    if enum is FaultKind:
        rows += ["", "Fault texts:", "", "| value | text |", "|---|---|"]
        rows += [f"| {k.value} | {FAULT_TEXTS[k]} |" for k in FaultKind]
    if enum is CommandCode:
        rows += ["", "| code | allowed in states (judged by the machine) |", "|---|---|"]
        for code in HMI_COMMANDS:
            allowed = [s.name for s in MachineState if code in ALLOWED[s]]
            rows.append(f"| {code.value} `{code.name}` | {', '.join(allowed)} |")
        rows += [
            "",
            f"`{CommandCode.SHUTDOWN.name}` ({CommandCode.SHUTDOWN.value}) is the supervisor's: "
            "written to `COMMAND_CODE` it answers exception 3.",
        ]
    if enum is CommandResult:
        rows += [
            "",
            "Results the server gives itself, without posting the command: "
            + ", ".join(f"`{r.name}`" for r in CommandResult if r in SERVER_RESULTS)
            + ". The planner rules behind the curve results: "
            + "; ".join(
                f"`{result.name}` ← {', '.join(rule.name for rule in rules)}"
                for result, rules in _rules_by_result().items()
            )
            + ".",
        ]
    return [*rows, ""]


def _rules_by_result() -> dict[CommandResult, list[object]]:
    found: dict[CommandResult, list[object]] = {}
    for rule, result in RULE_RESULTS.items():
        found.setdefault(result, []).append(rule)
    return found


def _crc_example() -> list[str]:
    staging = encode_staging(1, [[0.0, 0.0], [10.0, 5.0]], [0.0, 0.0, 1.0, 1.0])
    words = [*staging.header, *staging.points, *staging.knots]
    return [
        "Example: the straight line from (0, 0) to (10, 5) mm, degree 1, weights 1, knots "
        "[0, 0, 1, 1]. Registers covered, in order (hex):",
        "",
        "```",
        "header  16..19  " + " ".join(f"{w:04X}" for w in staging.header),
        "points  1000..1015  " + " ".join(f"{w:04X}" for w in staging.points),
        f"knots   {_KNOT}..{_KNOT + 7}  " + " ".join(f"{w:04X}" for w in staging.knots),
        "```",
        "",
        f"{len(words)} registers = {2 * len(words)} bytes; `zlib.crc32` of those bytes = "
        f"0x{staging.crc32:08X}, written as `CURVE_CRC32` = "
        f"[0x{staging.crc32 >> 16:04X}, 0x{staging.crc32 & 0xFFFF:04X}].",
    ]


def _wire() -> list[str]:
    functions = ", ".join(f"{f.value} ({f.name.lower().replace('_', ' ')})" for f in FunctionCode)
    exceptions = member_descriptions(ExceptionCode)
    return [
        "## Modbus TCP on the wire",
        "",
        f"- Functions: {functions}; FC43 only with MEI type 14 (read device identification). "
        "Every other function code (coils and discrete inputs included) answers exception 1 "
        "with that function code (`fc | 0x80`, `01`).",
        f"- Limits: reads (FC3, FC4, FC23's read) 1–{MAX_READ_REGISTERS} registers, FC16 writes "
        f"1–{MAX_WRITE_REGISTERS}, FC23 writes 1–{MAX_READ_WRITE_REGISTERS}, byte count = 2 × "
        "quantity; anything else answers exception 3 with the request's function code.",
        "- Every complete request is answered, in the order received, whatever way the frames "
        "are cut into TCP segments (several per segment, one split across segments). A request "
        "whose answer must wait (a curve commit) holds back the later ones of its connection "
        "only.",
        "- A malformed MBAP header (protocol id other than 0, length 0, 1 or above 254) closes "
        "the connection after the requests before it are answered; so does a frame left "
        f"incomplete for {HmiServer.frame_timeout_s:g} s (a header cut short). The server logs "
        "each with the peer's address. A length that is valid but does not fit the function "
        "(e.g. FC3 with 6 data bytes) answers exception 3.",
        f"- Unit ids: `modbus.unit_id`, {_UNITS} (libmodbus and many HMIs send 255); others "
        "answer exception 11.",
        f"- FC17 (report server id): server id `{IDENTITY.product_code} <version>` (ASCII, the "
        "softmotion version), run indicator 0xFF (on).",
        f"- FC43/14 (read device identification, conformity level 0x81: basic, stream and "
        f"individual access): VendorName (0) `{IDENTITY.vendor_name}`, ProductCode (1) "
        f"`{IDENTITY.product_code}`, MajorMinorRevision (2) = the softmotion version "
        "(`FIRMWARE_*`). Read device id codes 1–3 stream the three objects "
        "(from the object id asked for, or from 0 when it does not exist); code 4 reads one "
        "(exception 2 for another object id); other codes answer exception 3.",
        "",
        "### Exceptions",
        "",
        "| code | when |",
        "|---|---|",
        *[
            f"| {c.value} ({c.name.lower().replace('_', ' ')}) | {exceptions[c.name]} |"
            for c in ExceptionCode
        ],
        "",
    ]


def render() -> str:
    """The whole document."""
    message_registers = MESSAGE_CHARS // 2
    out: list[str] = [
        "# HMI register map (Modbus TCP)",
        "",
        "Generated by `python -m runtime.hmi.docgen` from `runtime/hmi/registers.py`; do not "
        "edit by hand (a test checks that this file is up to date).",
        "",
        f"Register map version {MAP_VERSION}, magic 0x{MAGIC:04X} ('SM').",
        "",
        "## Conventions",
        "",
        "- Addresses are **0-based PDU addresses**. Tools that count from 1 (`mbpoll -r`, "
        "'3xxxx/4xxxx' notation) add 1: input register 17 is `mbpoll -t 3 -r 18`.",
        "- u16 values are unsigned 16-bit. **32-bit values** (u32, f32 IEEE 754) take two "
        "registers at an even address, **high word first (ABCD)**: 123456.0 = [0x47F1, 0x2000]. "
        "mbpoll defaults to CDAB: use `-B`.",
        "- ascii: two characters per register, first in the high byte, NUL padded. Texts are "
        "written in ASCII: '±' is '+/-', 'µ' is 'u', accents are dropped, anything else is '?'. "
        f"`MESSAGE` and `REQUEST_MESSAGE` hold {MESSAGE_CHARS} characters "
        f"({message_registers} registers, one request); a longer text ends in '...'.",
        "- Status is in **input registers** (FC4, read-only). Commands, parameters and the curve "
        "staging area are in **holding registers** (FC3 read, FC6/FC16/FC23 write).",
        f"- The input image is one block of {INPUT_SIZE} registers (0–{INPUT_SIZE - 1}); "
        "reserved registers read 0; addresses from "
        f"{INPUT_SIZE} on answer exception 2. Every request is served from one snapshot of one "
        "cycle, and every block below fits one request: a block read at once is never half of "
        f"one cycle and half of the next. The core status (identity, machine status, axes, "
        f"cycle statistics) is input registers 0–{CORE_END - 1}: one request.",
        f"- Holding registers 0–{HOLDING_HEAD_END - 1} are contiguous: one FC3 reads them all, "
        "reserved ones read 0 and take only 0 (a block write that carries them unchanged is "
        "accepted). The staging data follows at "
        f"{FIELD['POINT_X'].address}. Other addresses answer exception 2.",
        "- A value above a holding register's maximum answers exception 3 at write time, and "
        "nothing of that write is applied.",
        "- Values that wrap: `HEARTBEAT` (u16, 65535 → 0, +1 per cycle), `CYCLE_COUNT` (u32, "
        "4294967295 → 0, after 198 days at 4 ms), `COMMAND_SEQ` (any u16 value).",
        "- Sign of the following error: `AXIS_FOLLOWING_ERROR` = actual position − the target "
        "commanded for that instant (the feedback's SYNC), in the axis's positive direction.",
        "",
    ]
    for title, table, first, end in BLOCKS:
        kind = "input" if table is Table.INPUT else "holding"
        out += [
            f"## {title} ({kind} registers {first}–{end - 1})",
            "",
            "| address | name | type | unit | description |",
            "|---|---|---|---|---|",
            *_field_rows(table, first, end),
            "",
        ]
    out += [
        "## Commands",
        "",
        "Write `COMMAND_CODE` (and its parameter: `OVERRIDE_SETPOINT` for SET_OVERRIDE, "
        "`PROGRAM_NUMBER` for LOAD_CURVE), then change `COMMAND_SEQ`; one FC16 from address 0 "
        "can carry `[code, seq, override]`. A new `COMMAND_SEQ` value (any value different from "
        "the current one) is a **request**: the server posts the command to the machine's "
        "mailbox and **applies the write** (the answer is a normal one). Writing the same value "
        "again does nothing, so a client that lost an answer can send the same write again.",
        "",
        "- The machine judges each command at the start of a cycle, **in the order posted, "
        "against the state it will run in**: a HOLD written right after an accepted START is "
        "judged after the START, in MOVING. A command not allowed then is a **result** "
        "(`REJECTED_STATE`, `NO_CURVE`, `DRIVES_NOT_READY`, ...), never a Modbus exception.",
        f"- `REQUEST_*` (the server's last {HISTORY} requests, element 0 the newest) show each "
        "request under its own sequence value: `REQUEST_TICKET` (the runtime's ticket for the "
        "posted command, 0 when the server refused it itself) and `REQUEST_RESULT`: `PENDING` "
        "until the machine has judged it, then its result. A refusal of the server's own (curve "
        "rules, CRC, staging held by another client, unknown library program) is recorded "
        "there at once with its reason in `REQUEST_MESSAGE`.",
        f"- `COMMAND_*` (the last {HISTORY} commands the machine judged, element 0 the newest; "
        "element 0 is the acknowledgement of the last one) name the **origin** of each (HMI, "
        "watchdog, command line, fault, shutdown), its ticket, code, sequence value (0 when not "
        "from an HMI) and result, all from one record: after a watchdog HOLD, `COMMAND_*[0]` "
        "is that HOLD.",
        "- Exceptions: 3 for a value out of range (`OVERRIDE_SETPOINT` > "
        f"{OVERRIDE_MAX_PERCENT * OVERRIDE_SCALE:g}, a `COMMAND_CODE` not listed, a change of "
        "`COMMAND_SEQ` while `COMMAND_CODE` is 0), 2 for addresses, and **6 only when the "
        "machine's mailbox is full**: then nothing was queued and the write was not applied "
        "(`COMMAND_SEQ` keeps its value), so sending the same write again is safe.",
        "- An accepted request or a change of `HMI_HEARTBEAT` restarts the HMI link watchdog.",
        "",
        f"Override: `OVERRIDE_SETPOINT` and `OVERRIDE` are in 0.1 % (1000 = 100.0 %, range "
        f"0–{OVERRIDE_MAX_PERCENT * OVERRIDE_SCALE:g}); it scales the feed limit vmax.",
        "",
        "## Programs",
        "",
        "`LOAD_CURVE` loads a program: from the staging area (`PROGRAM_NUMBER` 0) or from the "
        "program library (`PROGRAM_NUMBER` n). At rest it becomes the active program "
        "(`PROGRAM_*[0]`); **while the machine moves (or holds, or stops) it becomes the next "
        "program** (`PROGRAM_*[1]`) and the running one is untouched: the next program starts "
        "when the current one ends, or on START. `CLEAR_NEXT` forgets the next program. During "
        "the approach move to a program's start, `MOTION_PHASE` is APPROACH and `PATH_*` "
        "measure the approach line; then PROGRAM and the curve.",
        "",
        "### Curve upload",
        "",
        "1. Take the staging area: the first write to the staging header or data takes it when "
        "no other client holds it (or write `STAGING_CONTROL` = 1). The hold lasts "
        "`STAGING_TIMEOUT_MS` after this client's last staging write "
        "(`modbus.staging_timeout_ms`), and ends at an accepted commit, an abort "
        "(`STAGING_CONTROL` = 2, which also clears the header) or when the connection closes. "
        "Meanwhile other clients' staging writes answer exception 2 and their commits from the "
        "staging area are refused with `STAGING_LOCKED`; `STAGING_STATE`, "
        "`STAGING_OWNER_IP`/`PORT` and `STAGING_HOLD_LEFT_MS` say who holds it and for how long.",
        "2. Write the header: `CURVE_DEGREE` p (1–"
        f"{MAX_DEGREE}), `CURVE_DIMENSION` (2 or 3), `CURVE_POINTS` n (at most {MAX_POINTS}), "
        f"`CURVE_KNOTS` (n + p + 1, at most {MAX_KNOTS}) and `CURVE_CRC32` (one FC16 at 16, "
        "6 registers). Values above these maxima answer exception 3 at once.",
        "3. Write control point i as x, y, z, weight (4 × f32, 8 registers) at 1000 + 8·i "
        "(z = 0 for planar curves), and knot j at "
        f"{_KNOT} + 2·j, in FC16 chunks of at most {MAX_WRITE_REGISTERS} registers that "
        "never split a float (a write that starts or ends inside a 32-bit value answers "
        "exception 3).",
        "4. Commit: `COMMAND_CODE` = 10 (`LOAD_CURVE`), `PROGRAM_NUMBER` = 0, a new "
        "`COMMAND_SEQ`. The server copies the staged data, then checks capacity "
        "(`CURVE_TOO_LARGE`), the CRC (`CURVE_CRC_MISMATCH`), the header "
        "(`CURVE_BAD_HEADER`), the planner's curve rules and the travel limits, and stores the "
        "curve before it answers; each attempt is its own request with its own sequence value "
        "and result (`UPLOAD_SEQ`/`UPLOAD_RESULT` follow the last one). A refused curve changes "
        "nothing: the loaded programs stay. An accepted one is `PENDING` until the machine has "
        "loaded it, then `DONE`, and `PROGRAM_CRC32` equals the CRC written.",
        "",
        "**CRC32**: CRC-32 of IEEE 802.3 / zlib (reflected polynomial 0xEDB88320, initial value "
        "and final XOR 0xFFFFFFFF) over the big-endian bytes of, in this order: the 4 header "
        "registers 16–19, the 8·n point registers from 1000, the 2·k knot registers from "
        f"{_KNOT}. `CURVE_CRC32` itself is not covered.",
        "",
        *_crc_example(),
        "",
        "### Program library",
        "",
        "`programs.library_dir` names a directory of curve files (`*.yaml`, as "
        "`softmotion plan` reads them). Program n is the n-th file by name (1-based); the "
        "directory is listed again at each write of `LIBRARY_SELECT` and each library load, so "
        "`LIBRARY_COUNT` and the numbers follow files added or removed. Write n to "
        "`LIBRARY_SELECT` to see program n: `LIBRARY_STATE` is READING while the server reads "
        "and checks the file, then VALID with its name, points, length and CRC32 (of the "
        "file's bytes), INVALID with the reason in `LIBRARY_RESULT`, or NOT_FOUND. Load it with "
        "`LOAD_CURVE` and `PROGRAM_NUMBER` = n: large paths need no staging. The loaded "
        "program's name and CRC32 appear in `PROGRAM_*`.",
        "",
        "## Values of the enumerated registers",
        "",
    ]
    for enum in _enums():
        out += _enum_section(enum)
    out += [
        *_wire(),
        "## Access",
        "",
        "- The server binds to `modbus.bind` (127.0.0.1 unless configured otherwise) on "
        "`modbus.port`; a connection from an address outside `modbus.allowed_networks` is "
        "closed as soon as it is accepted.",
        "- `modbus.read_only: true` makes every write answer exception 2; status stays readable.",
        "- HMI link watchdog (`modbus.watchdog.timeout_ms` > 0, not read-only), run by the "
        "machine's cycle: a change of `HMI_HEARTBEAT` or an accepted request restarts it. When "
        "it runs out while the machine moves it sends HOLD (or STOP, "
        "`modbus.watchdog.action`) with origin WATCHDOG (shown in `COMMAND_*` and `MESSAGE`), "
        "and `WATCHDOG_STATE` is TRIPPED until the next heartbeat change or request.",
        "",
    ]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """Write (or with ``--check`` compare) the document; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m runtime.hmi.docgen", description=__doc__)
    parser.add_argument("--check", action="store_true", help="exit 1 if the file is stale")
    parser.add_argument("--output", type=Path, default=DOCUMENT)
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        current = args.output.read_text(encoding="utf-8") if args.output.exists() else ""
        if current != text:
            print(
                f"{args.output} is out of date: run python -m runtime.hmi.docgen", file=sys.stderr
            )
            return 1
        return 0
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
