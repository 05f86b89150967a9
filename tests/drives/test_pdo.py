"""PDO specifications, layouts read from drives, and the RPDO/TPDO codecs."""

from __future__ import annotations

import struct

import pytest

from drives.objects import (
    CONTROLWORD,
    ERROR_CODE,
    FOLLOWING_ERROR_ACTUAL,
    MODES_OF_OPERATION,
    POSITION_ACTUAL,
    STATUSWORD,
    TARGET_POSITION,
    VELOCITY_ACTUAL,
)
from drives.pdo import (
    AxisPdoSpec,
    Direction,
    PdoLayout,
    PdoSpec,
    RpdoCodec,
    TpdoCodec,
    layout_problem,
    missing_objects,
)


def _layout(direction: Direction, entries, trans_type: int = 1, valid: bool = True) -> PdoLayout:
    return PdoLayout(direction, 1, 0x181, valid, trans_type, tuple(entries))


def test_default_spec_is_the_csp_minimum() -> None:
    spec = AxisPdoSpec()
    assert spec.rpdo.objects == (CONTROLWORD, TARGET_POSITION)
    assert [pdo.objects for pdo in spec.tpdos] == [(STATUSWORD, POSITION_ACTUAL)]
    assert spec.rpdo.mapping_entries() == (0x6040_0010, 0x607A_0020)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (
            lambda: AxisPdoSpec(rpdo=PdoSpec(1, (CONTROLWORD,))),
            "0x607A target position is required",
        ),
        (
            lambda: AxisPdoSpec(tpdos=(PdoSpec(1, (STATUSWORD,)),)),
            "0x6064 position actual value is required",
        ),
        (lambda: AxisPdoSpec(rpdo=PdoSpec(1, (CONTROLWORD, TARGET_POSITION, 0x60FF))), "0x60FF"),
        (
            lambda: PdoSpec(1, (STATUSWORD, POSITION_ACTUAL, FOLLOWING_ERROR_ACTUAL)),
            "take 10 bytes, at most 8",
        ),
        (lambda: PdoSpec(513, (STATUSWORD,)), "must be in 1..512"),
        (
            lambda: AxisPdoSpec(
                tpdos=(PdoSpec(1, (STATUSWORD, POSITION_ACTUAL)), PdoSpec(1, (ERROR_CODE,)))
            ),
            "repeat a PDO",
        ),
    ],
)
def test_spec_errors_name_the_object(make, message) -> None:
    with pytest.raises(ValueError, match=message):
        make()


def test_rpdo_codec_follows_the_drive_layout() -> None:
    layout = _layout(
        Direction.RPDO,
        [(TARGET_POSITION, 0, 32), (MODES_OF_OPERATION, 0, 8), (CONTROLWORD, 0, 16)],
        trans_type=255,
    )
    codec = RpdoCodec(layout)
    assert bytes(codec.pack(0x0F, -1234)) == struct.pack("<ibH", -1234, 8, 0x0F)


def test_tpdo_codec_skips_unknown_entries() -> None:
    layout = _layout(
        Direction.TPDO, [(POSITION_ACTUAL, 0, 32), (0x2100, 0, 8), (STATUSWORD, 0, 16)]
    )
    codec = TpdoCodec(layout)
    values = codec.unpack(struct.pack("<iBH", 777, 9, 0x1237))
    assert codec.size == 7
    assert values[codec.position_at] == 777 and values[codec.statusword_at] == 0x1237
    assert codec.following_error_at is None


def test_layout_problems_and_missing_objects() -> None:
    good = _layout(Direction.TPDO, [(STATUSWORD, 0, 16), (POSITION_ACTUAL, 0, 32)])
    assert layout_problem(good) is None
    assert "not valid" in layout_problem(_layout(Direction.TPDO, good.entries, valid=False))
    assert "type 255: the feedback needs 1" in layout_problem(
        _layout(Direction.TPDO, good.entries, trans_type=255)
    )
    assert layout_problem(_layout(Direction.RPDO, [(CONTROLWORD, 0, 16)], 255)) is None
    assert "12 bits" in layout_problem(_layout(Direction.TPDO, [(STATUSWORD, 0, 12)]))
    velocity = _layout(Direction.TPDO, [(VELOCITY_ACTUAL, 0, 32)])
    assert missing_objects([velocity], (STATUSWORD, POSITION_ACTUAL)) == (
        STATUSWORD,
        POSITION_ACTUAL,
    )
    assert good.describe() == "TPDO1 on 0x181 (type 1): 0x6041, 0x6064"
