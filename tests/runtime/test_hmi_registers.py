"""The register map's invariants, the word encodings, the staging CRC and the generated document."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from planner.errors import CurveRule
from runtime.commands import CommandResult
from runtime.hmi import docgen
from runtime.hmi.registers import (
    BLOCKS,
    FIELD,
    FIELDS,
    INPUT_SIZE,
    MAX_READ_REGISTERS,
    Kind,
    ServerStatus,
    Table,
    WatchdogState,
    ascii_words,
    decode_identity,
    decode_status,
    encode_status,
    f32_words,
    identity_image,
    u32_words,
    words_ascii,
)
from runtime.hmi.upload import RULE_RESULTS, UploadRejected, decode_staging, encode_staging
from runtime.status import AxisStatus, MachineState, StatusSnapshot

ROOT = Path(__file__).resolve().parents[2]


def _addresses(field):
    for i in range(field.repeat):
        yield from range(field.address_of(i), field.address_of(i) + field.width)


@pytest.mark.parametrize("table", list(Table))
def test_fields_never_overlap_and_lie_in_their_blocks(table: Table) -> None:
    owner: dict[int, str] = {}
    blocks = [(first, end) for _t, t, first, end in BLOCKS if t is table]
    for field in FIELDS:
        if field.table is not table:
            continue
        for address in _addresses(field):
            assert address not in owner, f"{field.name} overlaps {owner.get(address)}"
            owner[address] = field.name
            assert any(first <= address < end for first, end in blocks), field.name


def test_32_bit_values_are_even_aligned_and_names_unique() -> None:
    assert len(FIELD) == len(FIELDS)
    for field in FIELDS:
        if field.kind in (Kind.U32, Kind.F32):
            assert field.address % 2 == 0 and field.stride % 2 == 0, field.name


def test_the_whole_status_fits_one_read() -> None:
    assert INPUT_SIZE <= MAX_READ_REGISTERS
    assert max(end for _t, table, _f, end in BLOCKS if table is Table.INPUT) == INPUT_SIZE


def test_word_encodings_are_abcd() -> None:
    assert f32_words(123456.0) == (0x47F1, 0x2000)
    assert f32_words(12.5) == (0x4148, 0)
    assert f32_words(1e39) == (0x7F80, 0)  # beyond float32: +inf
    assert u32_words(0x12345678) == (0x1234, 0x5678)
    assert u32_words(-5) == (0, 0) and u32_words(2**40) == (0xFFFF, 0xFFFF)
    assert ascii_words("AB C", 3) == [0x4142, 0x2043, 0]
    assert words_ascii([0x4142, 0x2043, 0]) == "AB C"


def test_identity_round_trip() -> None:
    image = identity_image(axis_count=2, unit_id=7, read_only=True, watchdog_timeout_ms=70000)
    assert image[2:6] == [0x47F1, 0x2000, 0x1234, 0x5678]
    identity = decode_identity(image)
    assert (identity.axis_count, identity.unit_id, identity.read_only) == (2, 7, True)
    assert identity.watchdog_timeout_ms == 70000


def test_status_round_trip() -> None:
    snapshot = StatusSnapshot(
        state=MachineState.HOLDING,
        axes=(AxisStatus("X", 1, 1.5, 1.25, 4, 0.25), AxisStatus("Y", 2, 2.5, 2.0, 4, 0.5)),
        feed_mm_s=10.0,
        path_s_mm=50.0,
        path_length_mm=100.0,
        override_percent=55.5,
        last_command_seq=9,
        last_command_result=1,
        curve_id=3,
        curve_crc=0xCAFEF00D,
        heartbeat=123,
        message="hold by hmi watchdog",
    )
    server = ServerStatus(9, CommandResult.DONE, 8, CommandResult.DONE, WatchdogState.TRIPPED)
    identity = identity_image(axis_count=2, unit_id=1, read_only=False, watchdog_timeout_ms=500)
    decoded = decode_status(encode_status(identity, snapshot, server, ("X", "Y")))
    assert decoded.snapshot == snapshot
    assert decoded.server == server


def test_staging_crc_is_zlib_over_big_endian_registers() -> None:
    staging = encode_staging(1, [[0.0, 0.0], [10.0, 5.0]], [0.0, 0.0, 1.0, 1.0])
    assert staging.header == (1, 2, 2, 4)
    data = struct.pack(">4H", *staging.header)
    data += np.array([0, 0, 0, 1, 10, 5, 0, 1, 0, 0, 1, 1], dtype=">f4").tobytes()
    assert staging.crc32 == zlib.crc32(data)


def _holding(staging, crc: int) -> list[int]:
    image = [0] * max(f.end for f in FIELDS if f.table is Table.HOLDING)
    image[16:20] = staging.header
    image[20:22] = u32_words(crc)
    points, knots = FIELD["POINT_X"].address, FIELD["KNOT"].address
    image[points : points + len(staging.points)] = staging.points
    image[knots : knots + len(staging.knots)] = staging.knots
    return image


def test_decode_staging_round_trip_and_crc_check() -> None:
    points = [[0.0, 0.0, 0.0], [10.0, 5.0, 1.0], [20.0, 0.0, 2.0]]
    staging = encode_staging(2, points, [0, 0, 0, 1, 1, 1], [1.0, 0.5, 1.0])
    curve, crc = decode_staging(_holding(staging, staging.crc32))
    assert crc == staging.crc32
    np.testing.assert_array_equal(curve.control_points, points)
    np.testing.assert_array_equal(curve.weights, [1.0, 0.5, 1.0])
    with pytest.raises(UploadRejected) as rejected:
        decode_staging(_holding(staging, staging.crc32 ^ 0x8000_0000))
    assert rejected.value.result is CommandResult.CURVE_CRC_MISMATCH


def test_every_curve_rule_has_a_result_code() -> None:
    assert set(RULE_RESULTS) == set(CurveRule)


def test_every_result_code_and_fault_text_is_documented() -> None:
    text = docgen.render()
    descriptions = docgen.member_descriptions(CommandResult)
    for result in CommandResult:
        assert descriptions[result.name], result.name
        assert f"| {result.value} | `{result.name}` | {descriptions[result.name]}" in text
    for name in ("FOLLOWING_ERROR", "HMI_LINK_LOSS", "CYCLE_OVERRUN"):
        assert f"`{name}`" in text


def test_the_register_map_document_is_up_to_date() -> None:
    document = ROOT / docgen.DOCUMENT
    assert document.read_text(encoding="utf-8") == docgen.render(), (
        "docs/register-map.md is out of date: run python -m runtime.hmi.docgen"
    )
