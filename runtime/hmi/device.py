"""The HMI's registers over a machine link: status reads, parameter writes, commands by sequence
counter, curve commits from the staging area or the program library.

Implements :class:`runtime.hmi.protocol.RegisterDevice` for the map of
:mod:`runtime.hmi.registers`:

- Input reads ("pull on read"): the link's latest snapshot and the server's own state are
  encoded once into the input image (cached until either changes) and the request is served from
  its bytes, so one read never mixes two snapshots. Before the cycle's first snapshot the image
  says the runtime is starting (MACHINE_STATE 65535, configured axis names and node ids).
- Holding writes are checked before anything is applied: addresses (exception 2 outside the
  map, in the staging area while another client holds it, and every write when read-only), then
  values (exception 3 above a field's maximum, reserved registers other than 0, a 32-bit value
  split, a sequence change with COMMAND_CODE 0).
- A write that changes COMMAND_SEQ is a request: the command is posted to the link with the new
  sequence value and the write is applied; its ticket and result (PENDING, then the machine's
  record for that ticket) appear in the request history under that sequence value. A full
  mailbox answers exception 6 and applies nothing. The machine judges the state, never the
  server: a refusal in the current state is a result, not an exception.
- LOAD_CURVE (PROGRAM_NUMBER 0: the staging area; n: library program n) decodes, checks and
  stores the curve in a worker thread before it posts the command; a curve the server refuses
  (CRC, header, curve rules, travel, staging held by another client, unknown program) is
  answered normally and recorded with its result and reason (REQUEST_MESSAGE), nothing posted.

Threading: every method runs on the server's event loop thread; blocking work (curve decoding,
validation, arc length, file I/O) runs in one worker thread at normal scheduling (SCHED_OTHER):
the HMI process may run at a real-time priority, and a long computation there would count
against the real-time budget the cycle and the drives share.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

from planner.errors import CurveError
from runtime.commands import Command, CommandCode, CommandOrigin, CommandResult
from runtime.config import ModbusConfig
from runtime.hmi.library import ProgramLibrary
from runtime.hmi.link import MachineLink
from runtime.hmi.protocol import Answer, ExceptionCode, WriteOutcome, registers_bytes
from runtime.hmi.registers import (
    BLOCKS,
    FIELD,
    FIELDS,
    HISTORY,
    HOLDING_HEAD_END,
    HOLDING_SIZE,
    INPUT_SIZE,
    OVERRIDE_SCALE,
    AxisIdentity,
    HmiRequest,
    Kind,
    LibraryEntry,
    LibraryState,
    ServerView,
    StagingControl,
    StagingView,
    StatusEncoder,
    Table,
    static_image,
)
from runtime.hmi.staging import Peer, StagingHold
from runtime.hmi.upload import CurveRefused, decode_staging, result_for
from runtime.programs import Program
from runtime.status import StatusSnapshot

log = logging.getLogger(__name__)
T = TypeVar("T")

_SINGLE, _HIGH, _LOW = 1, 2, 3
_CODE = FIELD["COMMAND_CODE"].address
_SEQ = FIELD["COMMAND_SEQ"].address
_OVERRIDE = FIELD["OVERRIDE_SETPOINT"].address
_HEARTBEAT = FIELD["HMI_HEARTBEAT"].address
_PROGRAM = FIELD["PROGRAM_NUMBER"].address
_LIBRARY_SELECT = FIELD["LIBRARY_SELECT"].address
_STAGING_CONTROL = FIELD["STAGING_CONTROL"].address
_STAGING_START = FIELD["CURVE_DEGREE"].address


def _holding_ranges() -> tuple[tuple[int, int], ...]:
    """The holding address ranges, adjacent blocks merged."""
    ranges: list[tuple[int, int]] = []
    for _title, table, first, end in BLOCKS:
        if table is not Table.HOLDING:
            continue
        if ranges and ranges[-1][1] == first:
            ranges[-1] = (ranges[-1][0], end)
        else:
            ranges.append((first, end))
    return tuple(ranges)


_HOLDING_RANGES = _holding_ranges()


def _holding_layout() -> tuple[list[int], list[int]]:
    """Per holding address: its role in a value (single, high or low word) and the largest value
    a write may carry (0 for reserved registers)."""
    roles = [0] * HOLDING_SIZE
    maxima = [0] * HOLDING_HEAD_END
    for field in FIELDS:
        if field.table is not Table.HOLDING:
            continue
        for i in range(field.repeat):
            at = field.address_of(i)
            if field.kind is Kind.U16:
                roles[at] = _SINGLE
            else:
                roles[at], roles[at + 1] = _HIGH, _LOW
            for address in range(at, min(at + field.width, HOLDING_HEAD_END)):
                maxima[address] = 0xFFFF if field.maximum is None else field.maximum
    return roles, maxima


def _normal_scheduling() -> None:
    """Run the calling (worker) thread at normal scheduling, whatever the process's class."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def _mapped(address: int, end: int) -> bool:
    return any(first <= address and end <= last for first, last in _HOLDING_RANGES)


class HmiDevice:
    """The HMI register tables of one machine.

    :param link: the machine.
    :param config: the ``modbus`` section of the machine description.
    :param clock_s: monotonic clock (seconds) for the staging hold's timeout.
    """

    def __init__(
        self,
        link: MachineLink,
        config: ModbusConfig,
        *,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self._link = link
        self._config = config
        self._clock_s = clock_s
        self._encoder = StatusEncoder(
            static_image(
                axes=[AxisIdentity(a.name, a.node_id) for a in link.config.axes],
                unit_id=config.unit_id,
                read_only=config.read_only,
                watchdog_timeout_ms=config.watchdog.timeout_ms,
                staging_timeout_ms=config.staging_timeout_ms,
            )
        )
        self._holding = [0] * HOLDING_SIZE
        self._roles, self._maxima = _holding_layout()
        self._staging = StagingHold(config.staging_timeout_ms / 1000.0)
        self._library = ProgramLibrary(link.config.programs.library_dir)
        self._library_count = 0
        self._library_entry = LibraryEntry()
        self._requests: deque[HmiRequest] = deque(maxlen=HISTORY)
        self._upload: HmiRequest | None = None
        self._pending: set[int] = set()
        self._request_message = ""
        self._version = 0
        self._cache: tuple[StatusSnapshot | None, int, StagingView, bytes] | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._worker = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="hmi-curves", initializer=_normal_scheduling
        )

    # -- status -------------------------------------------------------------------------------

    def read_input(self, address: int, count: int) -> Answer:
        """Input registers from the latest snapshot."""
        if address + count > INPUT_SIZE:
            return ExceptionCode.ILLEGAL_DATA_ADDRESS
        image = self._image()
        return image[2 * address : 2 * (address + count)]

    def _image(self) -> bytes:
        snapshot = self._link.snapshot()
        self._settle(snapshot)
        staging = self._staging.view(self._clock_s())
        cache = self._cache
        if (
            cache is not None
            and cache[0] is snapshot
            and cache[1] == self._version
            and cache[2] == staging
        ):
            return cache[3]
        server = ServerView(
            requests=tuple(reversed(self._requests)),
            upload=self._upload,
            staging=staging,
            library_count=self._library_count,
            library=self._library_entry,
            request_message=self._request_message,
        )
        image = registers_bytes(self._encoder.encode(snapshot, server))
        self._cache = (snapshot, self._version, staging, image)
        return image

    @property
    def pending(self) -> bool:
        """Whether a posted request still waits for the machine's record."""
        return bool(self._pending)

    def settle(self) -> None:
        """Take the machine's results of posted requests from the latest snapshot."""
        self._settle(self._link.snapshot())

    def _settle(self, snapshot: StatusSnapshot | None) -> None:
        if not self._pending or snapshot is None:
            return
        records = snapshot.recent_commands or (
            (snapshot.last_command,) if snapshot.last_command is not None else ()
        )
        results = {
            r.ticket: r.result
            for r in records
            if r.origin is CommandOrigin.HMI and r.ticket in self._pending
        }
        if not results:
            return
        self._pending -= results.keys()
        self._requests = deque(
            (
                HmiRequest(r.ticket, r.seq, r.code, results[r.ticket]) if r.ticket in results else r
                for r in self._requests
            ),
            maxlen=HISTORY,
        )
        upload = self._upload
        if upload is not None and upload.ticket in results:
            self._upload = HmiRequest(
                upload.ticket, upload.seq, upload.code, results[upload.ticket]
            )
        self._version += 1

    # -- holding registers --------------------------------------------------------------------

    def read_holding(self, address: int, count: int) -> Answer:
        """Holding registers as last written (STAGING_CONTROL reads 0)."""
        if not _mapped(address, address + count):
            return ExceptionCode.ILLEGAL_DATA_ADDRESS
        return registers_bytes(self._holding[address : address + count])

    def write_holding(
        self, address: int, values: Sequence[int], client: object
    ) -> WriteOutcome | Awaitable[WriteOutcome]:
        """Check and apply a write from ``client`` (a :class:`Peer`); see the module docstring."""
        assert isinstance(client, Peer)
        end = address + len(values)
        if self._config.read_only or not _mapped(address, end):
            return ExceptionCode.ILLEGAL_DATA_ADDRESS
        if self._roles[address] == _LOW or self._roles[end - 1] == _HIGH:
            return ExceptionCode.ILLEGAL_DATA_VALUE
        for at in range(address, min(end, HOLDING_HEAD_END)):
            if values[at - address] > self._maxima[at]:
                return ExceptionCode.ILLEGAL_DATA_VALUE
        holding = self._holding

        def new(at: int) -> int:
            return values[at - address] if address <= at < end else holding[at]

        touches_staging = end > _STAGING_START or (
            address <= _STAGING_CONTROL < end and new(_STAGING_CONTROL) != StagingControl.NONE
        )
        if touches_staging and not self._staging.may_write(client, self._clock_s()):
            return ExceptionCode.ILLEGAL_DATA_ADDRESS
        if not address <= _SEQ < end or new(_SEQ) == holding[_SEQ]:
            self._apply(address, values, client)
            return None
        code = new(_CODE)
        if code == 0:
            return ExceptionCode.ILLEGAL_DATA_VALUE
        request = _Write(address, tuple(values), client, CommandCode(code), new(_SEQ))
        if request.code is not CommandCode.LOAD_CURVE:
            percent = None
            if request.code is CommandCode.SET_OVERRIDE:
                percent = new(_OVERRIDE) / OVERRIDE_SCALE
            return self._post(request, override_percent=percent)
        number = new(_PROGRAM)
        if number:
            return self._commit(
                request,
                lambda: self._library.program(number, self._link.config, self._link.programs),
                staged=False,
            )
        if not self._staging.may_write(client, self._clock_s()):
            holder = self._staging.holder(self._clock_s())
            self._refuse(
                request,
                CommandResult.STAGING_LOCKED,
                f"the staging area is held by {holder}; commit from there or wait for its "
                f"hold to end",
            )
            return None
        staged = list(holding)
        staged[address:end] = values
        return self._commit(request, lambda: self._staged_program(staged), staged=True)

    def _apply(self, address: int, values: Sequence[int], client: Peer) -> None:
        end = address + len(values)
        holding = self._holding
        if address <= _HEARTBEAT < end and values[_HEARTBEAT - address] != holding[_HEARTBEAT]:
            self._link.note_activity()
        holding[address:end] = values
        if address <= _LIBRARY_SELECT < end:
            self._browse(holding[_LIBRARY_SELECT])
        control = StagingControl.NONE
        if address <= _STAGING_CONTROL < end:
            control = StagingControl(holding[_STAGING_CONTROL])
            holding[_STAGING_CONTROL] = 0
        if control is StagingControl.ABORT:
            holding[_STAGING_START:HOLDING_HEAD_END] = [0] * (HOLDING_HEAD_END - _STAGING_START)
            self._staging.release(client)
            log.info("modbus: %s aborted the upload", client)
        elif control is StagingControl.TAKE or end > _STAGING_START:
            self._staging.touch(client, self._clock_s())

    def _post(
        self,
        request: _Write,
        *,
        override_percent: float | None = None,
        program: Program | None = None,
    ) -> WriteOutcome:
        command = Command(
            request.code,
            origin=CommandOrigin.HMI,
            override_percent=override_percent,
            program=program,
            seq=request.seq,
        )
        ticket = self._link.post(command)
        if ticket is None:
            log.warning(
                "modbus: %s: %s seq %d refused: mailbox full",
                request.client,
                request.code.name,
                request.seq,
            )
            return ExceptionCode.SERVER_DEVICE_BUSY
        self._apply(request.address, request.values, request.client)
        self._record(HmiRequest(ticket, request.seq, request.code, CommandResult.PENDING), "")
        self._pending.add(ticket)
        self._link.note_activity()
        log.info(
            "modbus: %s: %s seq %d posted (ticket %d)",
            request.client,
            request.code.name,
            request.seq,
            ticket,
        )
        return None

    def _refuse(self, request: _Write, result: CommandResult, reason: str) -> None:
        self._apply(request.address, request.values, request.client)
        self._record(HmiRequest(0, request.seq, request.code, result), reason)
        log.info(
            "modbus: %s: %s seq %d refused: %s: %s",
            request.client,
            request.code.name,
            request.seq,
            result.name,
            reason,
        )

    def _record(self, request: HmiRequest, message: str) -> None:
        self._requests.append(request)
        if request.code is CommandCode.LOAD_CURVE:
            self._upload = request
        self._request_message = message
        self._version += 1

    def _commit(
        self, request: _Write, prepare: Callable[[], Program], *, staged: bool
    ) -> Awaitable[WriteOutcome]:
        async def commit() -> WriteOutcome:
            try:
                program = await self._in_worker(prepare)
            except CurveRefused as exc:
                self._refuse(request, exc.result, exc.reason)
                return None
            finally:
                if not staged:
                    await self.list_library()
            outcome = self._post(request, program=program)
            if outcome is None and staged:
                self._staging.release(request.client)
            return outcome

        return commit()

    def _staged_program(self, holding: Sequence[int]) -> Program:
        curve, crc = decode_staging(holding)
        try:
            return self._link.programs.add(
                curve, self._link.config, name=f"upload {crc:08X}", crc32=crc
            )
        except CurveError as exc:
            raise CurveRefused(result_for(exc), str(exc)) from exc

    # -- program library ----------------------------------------------------------------------

    async def list_library(self) -> None:
        """List the library directory again (LIBRARY_COUNT)."""
        self._library_count = len(await self._in_worker(self._library.names))
        self._version += 1

    def _browse(self, number: int) -> None:
        self._library_entry = LibraryEntry(number, LibraryState.READING)
        self._version += 1

        async def read() -> None:
            names = await self._in_worker(self._library.names)
            entry = await self._in_worker(lambda: self._library.entry(number, self._link.config))
            if self._holding[_LIBRARY_SELECT] == number:
                self._library_count = len(names)
                self._library_entry = entry
                self._version += 1

        task = asyncio.get_running_loop().create_task(read())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _in_worker(self, work: Callable[[], T]) -> Awaitable[T]:
        return asyncio.get_running_loop().run_in_executor(self._worker, work)

    def close(self) -> None:
        """Stop the worker thread (after the work it has)."""
        self._worker.shutdown(wait=True)

    # -- connections --------------------------------------------------------------------------

    def disconnected(self, client: Peer) -> None:
        """``client``'s connection closed: its staging hold ends."""
        if self._staging.release(client):
            log.info("modbus: %s closed its connection: staging area free", client)


@dataclass(frozen=True, slots=True)
class _Write:
    """A holding write that changes COMMAND_SEQ, kept until it is applied or refused."""

    address: int
    values: tuple[int, ...]
    client: Peer
    code: CommandCode
    seq: int
