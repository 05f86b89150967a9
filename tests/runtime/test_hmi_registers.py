"""The register map's invariants, the word encodings, the staging CRC and the generated document."""

from __future__ import annotations

import itertools
import struct
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from planner.errors import CurveRule
from runtime.commands import CommandCode, CommandOrigin, CommandRecord, CommandResult
from runtime.hmi import docgen
from runtime.hmi.protocol import MAX_READ_REGISTERS, ExceptionCode
from runtime.hmi.registers import (
    BLOCKS,
    FIELD,
    FIELDS,
    HOLDING_HEAD_END,
    INPUT_SIZE,
    MESSAGE_CHARS,
    AxisIdentity,
    HmiRequest,
    Kind,
    LibraryEntry,
    LibraryState,
    ServerView,
    StagingState,
    StagingView,
    StatusBit,
    Table,
    ascii_text,
    ascii_words,
    decode_identity,
    decode_status,
    encode_status,
    f32_words,
    static_image,
    u32_words,
    words_ascii,
)
from runtime.hmi.upload import RULE_RESULTS, CurveRefused, decode_staging, encode_staging
from runtime.status import (
    AxisStatus,
    CycleStatistics,
    MachineState,
    MotionPhase,
    ProgramStatus,
    StatusSnapshot,
    WatchdogState,
)

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


def test_every_block_fits_one_read_and_the_image_is_contiguous() -> None:
    inputs = [(first, end) for _t, table, first, end in BLOCKS if table is Table.INPUT]
    assert inputs[0][0] == 0 and inputs[-1][1] == INPUT_SIZE
    assert all(a[1] == b[0] for a, b in itertools.pairwise(inputs))
    assert all(end - first <= MAX_READ_REGISTERS for first, end in inputs)
    holding = [(first, end) for _t, table, first, end in BLOCKS if table is Table.HOLDING]
    assert holding[0] == (0, 16) and holding[1] == (16, HOLDING_HEAD_END)


def test_word_encodings_are_abcd() -> None:
    assert f32_words(123456.0) == (0x47F1, 0x2000)
    assert f32_words(12.5) == (0x4148, 0)
    assert f32_words(1e39) == (0x7F80, 0)  # beyond float32: +inf
    assert u32_words(0x12345678) == (0x1234, 0x5678)
    assert u32_words(-5) == (0, 0) and u32_words(2**40) == (0xFFFF, 0xFFFF)
    assert ascii_words("AB C", 3) == [0x4142, 0x2043, 0]
    assert words_ascii([0x4142, 0x2043, 0]) == "AB C"


def test_text_is_written_in_ascii_and_long_text_ends_in_dots() -> None:
    assert ascii_text("beyond ±1 mm at 12 µs, 3 °, café – ok ✓") == (
        "beyond +/-1 mm at 12 us, 3  deg, cafe - ok ?"
    )
    words = ascii_words("x" * 300, MESSAGE_CHARS // 2)
    assert words_ascii(words) == "x" * (MESSAGE_CHARS - 3) + "..."


AXES = (AxisIdentity("X", 1), AxisIdentity("Y", 2))


def test_identity_round_trip() -> None:
    image = static_image(
        axes=AXES, unit_id=7, read_only=True, watchdog_timeout_ms=70000, staging_timeout_ms=5000
    )
    assert image[2:6] == [0x47F1, 0x2000, 0x1234, 0x5678]
    identity = decode_identity(image)
    assert (identity.axis_count, identity.unit_id, identity.read_only) == (2, 7, True)
    assert identity.watchdog_timeout_ms == 0  # read-only: no watchdog
    image = static_image(
        axes=AXES, unit_id=7, read_only=False, watchdog_timeout_ms=70000, staging_timeout_ms=5000
    )
    assert decode_identity(image).watchdog_timeout_ms == 70000


def test_status_round_trip() -> None:
    hmi = [
        CommandRecord(t, CommandOrigin.HMI, t + 100, CommandCode.ENABLE, CommandResult.DONE)
        for t in range(1, 12)
    ]
    watchdog = CommandRecord(12, CommandOrigin.WATCHDOG, 0, CommandCode.HOLD, CommandResult.DONE)
    records = (*hmi, watchdog)
    snapshot = StatusSnapshot(
        state=MachineState.HOLDING,
        axes=(
            AxisStatus("X", 1, 1.5, 1.25, 4, -0.25, peak_following_error_mm=0.5, statusword=0x1237),
            AxisStatus("Y", 2, 2.5, 2.0, -1, 0.5, statusword=0x0008),
        ),
        phase=MotionPhase.BRAKING,
        feed_mm_s=10.0,
        path_s_mm=50.0,
        path_length_mm=100.0,
        in_position=True,
        program=ProgramStatus(3, "upload CAFEF00D", 0xCAFEF00D, 173.5),
        next_program=ProgramStatus(4, "a-paper.yaml", 0x12345678, 10.0),
        override_percent=55.5,
        stats=CycleStatistics(
            cycles=2**32 + 7,
            lateness_p99_us=801.0,
            lateness_p999_us=2500.0,
            missed_periods=3,
            override_latency_periods=2,
            overrides_applied=4,
        ),
        last_command=records[-1],
        recent_commands=records[-8:],
        watchdog=WatchdogState.TRIPPED,
        heartbeat=123,
        message="hold by watchdog: HMI link silent for 1.0 s",
    )
    server = ServerView(
        requests=(HmiRequest(11, 111, CommandCode.ENABLE, CommandResult.DONE),),
        upload=HmiRequest(9, 99, CommandCode.LOAD_CURVE, CommandResult.CURVE_CRC_MISMATCH),
        staging=StagingView(StagingState.HELD, 0x7F000001, 40000, 1200),
        library_count=2,
        library=LibraryEntry(1, LibraryState.VALID, CommandResult.NONE, "a.yaml", 7, 173.5, 5),
        request_message="CURVE_CRC32 = 0x1",
    )
    static = static_image(
        axes=AXES, unit_id=1, read_only=False, watchdog_timeout_ms=500, staging_timeout_ms=5000
    )
    decoded = decode_status(encode_status(static, snapshot, server))
    expected_stats = replace(snapshot.stats, cycles=7)  # CYCLE_COUNT wraps at 2**32
    assert decoded.snapshot == replace(snapshot, stats=expected_stats)
    assert decoded.server == replace(server, upload=replace(server.upload, ticket=0))
    bits = StatusBit
    assert decoded.status_word == (
        bits.STATUS_VALID
        | bits.ENABLED
        | bits.HOLDING
        | bits.IN_POSITION
        | bits.PROGRAM_LOADED
        | bits.NEXT_PROGRAM
        | bits.BRAKING
        | bits.WATCHDOG_TRIPPED
        | bits.STAGING_HELD
    )


def test_drive_state_unknown_reads_65535() -> None:
    static = static_image(
        axes=AXES, unit_id=1, read_only=False, watchdog_timeout_ms=0, staging_timeout_ms=5000
    )
    snapshot = StatusSnapshot(axes=(AxisStatus("X", 1, 0.0, 0.0, -1, 0.0),))
    image = encode_status(static, snapshot, ServerView())
    assert image[FIELD["AXIS_DRIVE_STATE"].address] == 0xFFFF


def test_every_exception_code_is_documented() -> None:
    text = docgen.render()
    for code in ExceptionCode:
        assert f"| {code.value} ({code.name.lower().replace('_', ' ')}) |" in text


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
    with pytest.raises(CurveRefused) as rejected:
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
