"""Curve staging: the registers a curve is uploaded into, their CRC32, and the commit's verdict.

Layout (holding registers, see :mod:`runtime.hmi.registers`): the header ``CURVE_DEGREE``,
``CURVE_DIMENSION``, ``CURVE_POINTS``, ``CURVE_KNOTS`` (16..19) and ``CURVE_CRC32`` (20..21);
control point ``i`` as four float32 x, y, z, weight at ``POINT_X[i]`` = 1000 + 8·i (z is written
0 for planar curves); knot ``j`` as a float32 at ``KNOT[j]``.

CRC32: the CRC-32 of IEEE 802.3 / zlib (polynomial 0x04C11DB7 reflected, initial value and final
XOR 0xFFFFFFFF; ``zlib.crc32``) over the big-endian bytes of these registers, in this order:
the 4 header registers 16..19, then the ``8·n`` point registers from 1000, then the ``2·k`` knot
registers from ``KNOT[0]`` (n points, k knots as the header says). ``CURVE_CRC32`` itself is not
covered.

A commit is judged in this order: capacity (``CURVE_TOO_LARGE``), CRC (``CURVE_CRC_MISMATCH``),
header ranges (``CURVE_BAD_HEADER``), then the planner's curve rules and the travel limits,
mapped by :data:`RULE_RESULTS`. Decoding copies the data out of the register image into numpy
arrays, so later writes to the staging area cannot change a committed curve.

Pure: no I/O, no threads.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from planner.errors import CurveError, CurveRule
from planner.nurbs import NurbsCurve
from runtime.commands import CommandResult
from runtime.hmi import HmiError
from runtime.hmi.registers import FIELD, MAX_DEGREE, MAX_KNOTS, MAX_POINTS, POINT_REGISTERS

_R = CommandResult
#: The commit result of every planner curve rule.
RULE_RESULTS: dict[CurveRule, CommandResult] = {
    CurveRule.DEGREE: _R.CURVE_BAD_HEADER,
    CurveRule.DIMENSION: _R.CURVE_BAD_HEADER,
    CurveRule.TOO_FEW_POINTS: _R.CURVE_DEGREE_TOO_HIGH,
    CurveRule.NOT_FINITE: _R.CURVE_NOT_FINITE,
    CurveRule.WEIGHT: _R.CURVE_BAD_WEIGHT,
    CurveRule.KNOT_COUNT: _R.CURVE_KNOT_COUNT,
    CurveRule.KNOT_ORDER: _R.CURVE_KNOTS_DECREASING,
    CurveRule.KNOT_CLAMP: _R.CURVE_KNOTS_NOT_CLAMPED,
    CurveRule.KNOT_MULTIPLICITY: _R.CURVE_INVALID,
    CurveRule.KNOT_SPACING: _R.CURVE_INVALID,
    CurveRule.ZERO_LENGTH: _R.CURVE_ZERO_LENGTH,
    CurveRule.FORMAT: _R.CURVE_INVALID,
    CurveRule.PARAMETER: _R.CURVE_INVALID,
    CurveRule.TRAVEL: _R.CURVE_OUTSIDE_TRAVEL,
}

_HEADER = FIELD["CURVE_DEGREE"].address
_HEADER_REGISTERS = 4
_POINTS = FIELD["POINT_X"].address
_KNOTS = FIELD["KNOT"].address


class CurveRefused(HmiError):
    """A curve the server refuses to load (a staged upload or a library program); ``result`` is
    the code the HMI sees, ``reason`` the text for REQUEST_MESSAGE."""

    def __init__(self, result: CommandResult, reason: str) -> None:
        self.result = result
        self.reason = reason
        super().__init__(f"curve refused: {result.name}: {reason}")


def result_for(error: CurveError) -> CommandResult:
    """The commit result code of a planner (or travel) curve error."""
    return RULE_RESULTS[error.rule]


@dataclass(frozen=True)
class Staging:
    """A curve as staging registers: what a client writes, and its CRC32."""

    header: tuple[int, int, int, int]
    """degree, dimension, number of points, number of knots."""
    points: list[int]
    """8 registers per control point: x, y, z, weight (float32, high word first)."""
    knots: list[int]
    """2 registers per knot (float32, high word first)."""
    crc32: int


def staging_crc(header: Sequence[int], points: Sequence[int], knots: Sequence[int]) -> int:
    """CRC32 (zlib) over the big-endian bytes of header, point and knot registers, in order."""
    words = [*header, *points, *knots]
    return zlib.crc32(struct.pack(f">{len(words)}H", *words))


def _f32_registers(values: np.ndarray) -> list[int]:
    return np.asarray(values, dtype=">f4").view(">u2").astype(int).tolist()


def encode_staging(
    degree: int,
    control_points: ArrayLike,
    knots: ArrayLike,
    weights: ArrayLike | None = None,
) -> Staging:
    """Staging registers of a curve given as arrays; nothing is validated (a client may stage a
    bad curve on purpose), except that points must be (n, 2) or (n, 3).

    :raises HmiError: if the points are not an (n, 2) or (n, 3) array.
    """
    points = np.asarray(control_points, dtype=float)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise HmiError(f"curve upload: control points of shape {points.shape}, need (n, 2|3)")
    n, dim = points.shape
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float).reshape(n)
    records = np.zeros((n, 4))
    records[:, :dim] = points
    records[:, 3] = w
    knot_values = np.asarray(knots, dtype=float).ravel()
    header = (int(degree), dim, n, len(knot_values))
    point_regs = _f32_registers(records.ravel())
    knot_regs = _f32_registers(knot_values)
    return Staging(header, point_regs, knot_regs, staging_crc(header, point_regs, knot_regs))


def staging_of(curve: NurbsCurve) -> Staging:
    """Staging registers of a valid curve."""
    return encode_staging(curve.degree, curve.control_points, curve.knots, curve.weights)


def _floats(registers: Sequence[int]) -> np.ndarray:
    return np.array(registers, dtype=">u2").view(">f4").astype(float)


def decode_staging(holding: Sequence[int]) -> tuple[NurbsCurve, int]:
    """The staged curve and its CRC32, from a holding register image starting at address 0.

    :raises CurveRefused: with the result code of the first rule broken (order in the module
        docstring).
    """
    degree, dimension, n, k = holding[_HEADER : _HEADER + _HEADER_REGISTERS]
    if n > MAX_POINTS or k > MAX_KNOTS:
        raise CurveRefused(
            _R.CURVE_TOO_LARGE,
            f"CURVE_POINTS = {n}, CURVE_KNOTS = {k}: the staging area holds at most "
            f"{MAX_POINTS} points and {MAX_KNOTS} knots",
        )
    crc_at = FIELD["CURVE_CRC32"].address
    expected = (holding[crc_at] << 16) | holding[crc_at + 1]
    header = holding[_HEADER : _HEADER + _HEADER_REGISTERS]
    point_regs = holding[_POINTS : _POINTS + POINT_REGISTERS * n]
    knot_regs = holding[_KNOTS : _KNOTS + 2 * k]
    actual = staging_crc(header, point_regs, knot_regs)
    if actual != expected:
        raise CurveRefused(
            _R.CURVE_CRC_MISMATCH,
            f"CURVE_CRC32 = 0x{expected:08X}, the staged data has CRC32 0x{actual:08X}",
        )
    if not 1 <= degree <= MAX_DEGREE:
        raise CurveRefused(_R.CURVE_BAD_HEADER, f"CURVE_DEGREE = {degree}, must be 1..{MAX_DEGREE}")
    if dimension not in (2, 3):
        raise CurveRefused(_R.CURVE_BAD_HEADER, f"CURVE_DIMENSION = {dimension}, must be 2 or 3")
    records = _floats(point_regs).reshape(n, 4)
    try:
        curve = NurbsCurve.from_arrays(
            degree, records[:, :dimension], _floats(knot_regs), weights=records[:, 3]
        )
    except CurveError as exc:
        raise CurveRefused(result_for(exc), str(exc)) from exc
    return curve, expected
