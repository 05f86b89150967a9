"""The program library: curve files in a configured directory, numbered for the HMI.

Program n is the n-th file (1-based) of ``*.yaml`` / ``*.yml`` files in
``programs.library_dir``, sorted by name; the directory is listed again on each request, so files
added or removed renumber the ones after them (the HMI shows the name and CRC32 of what it
selects and of what was loaded). A program's details (points, length, CRC32 of the file's bytes)
come from reading and checking the file as a load would: curve rules, travel limits, the
planner's arc length. They are cached per file name, size and modification time.

Threading: :meth:`ProgramLibrary.entry` and :meth:`ProgramLibrary.program` read files and
compute lengths: call them from a worker thread, never from the event loop. The cache is
guarded by a lock.
"""

from __future__ import annotations

import threading
import zlib
from dataclasses import dataclass
from pathlib import Path

from planner.errors import CurveError
from planner.nurbs import NurbsCurve
from runtime.commands import CommandResult
from runtime.config import MachineConfig
from runtime.curves import check_travel, load_curve_file
from runtime.hmi.registers import LibraryEntry, LibraryState
from runtime.hmi.upload import CurveRefused, result_for
from runtime.programs import Program, ProgramStore, curve_length_mm

#: File name suffixes of library programs.
SUFFIXES = (".yaml", ".yml")


@dataclass(frozen=True)
class _Checked:
    curve: NurbsCurve
    crc32: int
    length_mm: float


class ProgramLibrary:
    """The curve files of one directory (None: no library configured)."""

    def __init__(self, directory: Path | None) -> None:
        self.directory = directory
        self._lock = threading.Lock()
        self._cache: dict[str, tuple[tuple[int, int], _Checked | CurveRefused]] = {}

    def names(self) -> list[str]:
        """The file names, in program number order (empty without a library)."""
        if self.directory is None:
            return []
        try:
            return sorted(
                p.name for p in self.directory.iterdir() if p.suffix in SUFFIXES and p.is_file()
            )
        except OSError:
            return []

    def entry(self, number: int, config: MachineConfig) -> LibraryEntry:
        """What the library registers show for program ``number``."""
        if number == 0:
            return LibraryEntry()
        names = self.names()
        if not 1 <= number <= len(names):
            return LibraryEntry(number, LibraryState.NOT_FOUND)
        name = names[number - 1]
        checked = self._check(name, config)
        if isinstance(checked, CurveRefused):
            return LibraryEntry(number, LibraryState.INVALID, checked.result, name)
        return LibraryEntry(
            number,
            LibraryState.VALID,
            CommandResult.NONE,
            name,
            len(checked.curve.control_points),
            checked.length_mm,
            checked.crc32,
        )

    def program(self, number: int, config: MachineConfig, store: ProgramStore) -> Program:
        """Program ``number``, checked and stored for the planner.

        :raises CurveRefused: NO_SUCH_PROGRAM, or the curve's result code.
        """
        names = self.names()
        if not 1 <= number <= len(names):
            where = self.directory if self.directory is not None else "no library configured"
            raise CurveRefused(
                CommandResult.NO_SUCH_PROGRAM,
                f"PROGRAM_NUMBER = {number}: the library ({where}) has {len(names)} programs",
            )
        name = names[number - 1]
        checked = self._check(name, config)
        if isinstance(checked, CurveRefused):
            raise checked
        try:
            return store.add(checked.curve, config, name=name, crc32=checked.crc32)
        except CurveError as exc:
            raise CurveRefused(result_for(exc), f"{name}: {exc}") from exc

    def _check(self, name: str, config: MachineConfig) -> _Checked | CurveRefused:
        assert self.directory is not None
        path = self.directory / name
        try:
            stat = path.stat()
        except OSError as exc:
            return CurveRefused(CommandResult.NO_SUCH_PROGRAM, f"{name}: {exc.strerror}")
        key = (stat.st_size, stat.st_mtime_ns)
        with self._lock:
            cached = self._cache.get(name)
        if cached is not None and cached[0] == key:
            return cached[1]
        checked: _Checked | CurveRefused
        try:
            crc32 = zlib.crc32(path.read_bytes())
            curve = load_curve_file(path)
            check_travel(curve, config.axes)
            checked = _Checked(curve, crc32, curve_length_mm(curve, config))
        except OSError as exc:
            checked = CurveRefused(CommandResult.NO_SUCH_PROGRAM, f"{name}: {exc.strerror}")
        except CurveError as exc:
            checked = CurveRefused(result_for(exc), f"{name}: {exc}")
        with self._lock:
            self._cache[name] = (key, checked)
        return checked
