"""Programs: validated curves stored for the planner process, and what the cycle knows of them.

A curve reaches the machine from a file (command line, demo, the program library) or from the
HMI's staging registers. Wherever it comes from, the process that receives it validates it
(planner rules), checks it against every axis's travel (:func:`runtime.curves.check_travel`),
measures its length, and stores a frozen copy in the runtime's program directory: a
:class:`Program` is then a small record that crosses process boundaries (the cycle's mailbox) and
names the file the planner process loads. The cycle never touches the curve itself; it only needs
the program's start point (for the approach move), its length (progress) and its identity.

Threading: :meth:`ProgramStore.add` blocks on file I/O and the length computation; call it
outside the cycle (HMI worker thread, supervisor). Ids come from a counter file under an
exclusive ``flock``, so several processes can add programs to one store.
"""

from __future__ import annotations

import fcntl
import os
from dataclasses import dataclass
from pathlib import Path as FilePath

import numpy as np

from planner.errors import CurveError, CurveRule
from planner.nurbs import NurbsCurve
from runtime.config import MachineConfig
from runtime.curves import check_travel, limits_for_curve, planner_limits

#: Longest program name kept (UTF-8 bytes); longer names are cut.
NAME_BYTES = 64
#: Longest path of a stored program file (UTF-8 bytes).
SOURCE_BYTES = 256


@dataclass(frozen=True)
class Program:
    """A validated curve ready to run, as it crosses process boundaries."""

    program_id: int
    source: str
    """The stored curve file (``.npz``) the planner process loads."""
    name: str
    crc32: int
    """Staging CRC32 of an uploaded curve; the file's CRC32 for a library program."""
    length_mm: float
    start_mm: tuple[float, ...]
    end_mm: tuple[float, ...]

    @property
    def dimension(self) -> int:
        return len(self.start_mm)


def curve_length_mm(curve: NurbsCurve, config: MachineConfig) -> float:
    """The arc length of ``curve`` as the planner measures it [mm]."""
    from planner.stream import Path

    limits = limits_for_curve(planner_limits(config), curve.dimension)
    return float(Path(curve, limits, config.cycle.period_s).length_mm)


class ProgramStore:
    """A directory of frozen program files, shared by the runtime's processes."""

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = FilePath(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def add(self, curve: NurbsCurve, config: MachineConfig, *, name: str, crc32: int) -> Program:
        """Check ``curve`` for this machine, store it and return its record.

        :raises CurveError: (``TravelError`` for travel) if the machine cannot run it.
        """
        check_travel(curve, config.axes)
        length_mm = curve_length_mm(curve, config)
        program_id = self._next_id()
        source = self.directory / f"program-{program_id}.npz"
        if len(str(source).encode()) > SOURCE_BYTES:
            raise CurveError(
                "program",
                f"store path {source} longer than {SOURCE_BYTES} bytes",
                rule=CurveRule.FORMAT,
            )
        partial = source.with_suffix(".partial.npz")
        np.savez(
            partial,
            degree=np.array(curve.degree),
            control_points=curve.control_points,
            weights=curve.weights,
            knots=curve.knots,
        )
        os.replace(partial, source)
        return Program(
            program_id=program_id,
            source=str(source),
            name=_cut(name, NAME_BYTES),
            crc32=crc32 & 0xFFFF_FFFF,
            length_mm=length_mm,
            start_mm=tuple(float(v) for v in curve.start_point),
            end_mm=tuple(float(v) for v in curve.end_point),
        )

    def _next_id(self) -> int:
        with open(self.directory / "next-id", "a+b") as counter:
            fcntl.flock(counter, fcntl.LOCK_EX)
            counter.seek(0)
            text = counter.read().decode() or "1"
            program_id = int(text)
            counter.seek(0)
            counter.truncate()
            counter.write(str(program_id + 1).encode())
        return program_id


def load_program_curve(program: Program) -> NurbsCurve:
    """The curve of a stored program (in the planner process).

    :raises CurveError: if the file is gone or unreadable.
    """
    try:
        with np.load(program.source) as data:
            return NurbsCurve.from_arrays(
                int(data["degree"]), data["control_points"], data["knots"], data["weights"]
            )
    except (OSError, KeyError, ValueError) as exc:
        raise CurveError(
            "program", f"{program.source}: cannot be loaded ({exc})", rule=CurveRule.FORMAT
        ) from None


def _cut(text: str, limit: int) -> str:
    return text.encode()[:limit].decode(errors="ignore")
