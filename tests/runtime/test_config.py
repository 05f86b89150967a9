"""Every validation rule of the machine configuration, with its message."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import pytest
import yaml

from drives.boot import Supervision
from drives.pdo import AxisPdoSpec, MappingPolicy, PdoSpec
from drives.sim.quirks import DriveQuirks
from runtime.config import (
    DEFAULT_CONFIG_PATH,
    DEMO_CURVE_PATH,
    CanConfig,
    MachineConfig,
    load_config,
    parse_config,
)
from runtime.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]


def sim_document() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())


def test_shipped_configs_load() -> None:
    sim = load_config(ROOT / "configs" / "sim.yaml")
    assert [a.name for a in sim.axes] == ["X", "Y", "Z"]
    assert [a.node_id for a in sim.axes] == [1, 2, 3]
    assert sim.can.interface == "local"
    assert sim.cycle.overrun_limit == 3 and sim.can.stale_feedback_cycles == 3
    assert sim.simulation.drives is True
    assert sim.cycle.period_ms == 4 and sim.cycle.period_s == pytest.approx(0.004)
    assert (sim.planner.vmax_mm_s, sim.planner.amax_mm_s2, sim.planner.jmax_mm_s3) == (
        100,
        1000,
        20000,
    )
    assert sim.modbus.bind == "127.0.0.1"
    vcan = load_config(ROOT / "configs" / "vcan.yaml")
    assert (vcan.can.interface, vcan.can.channel) == ("socketcan", "vcan0")
    assert vcan.axes == sim.axes and vcan.planner == sim.planner
    ipc = load_config(ROOT / "configs" / "ipc-example.yaml")
    assert ipc.axes[2].direction == -1 and ipc.cycle.realtime.cpu == 3


def test_defaults_are_the_checkouts_configs_from_any_directory() -> None:
    # In a checkout (editable install) the shipped files are the repository's configs/; the
    # installed wheel's copy is checked by tests/deploy/test_wheel.py.
    assert DEFAULT_CONFIG_PATH == ROOT / "configs" / "sim.yaml"
    assert DEMO_CURVE_PATH == ROOT / "configs" / "curves" / "paper.yaml"


def test_minimal_config_takes_defaults() -> None:
    config = parse_config({"axes": [{"name": "X", "node_id": 5, "counts_per_mm": 100}]})
    assert isinstance(config, MachineConfig)
    axis = config.axes[0]
    assert axis.direction == 1 and axis.mode == "csp"
    assert axis.travel_min_mm == -math.inf and axis.travel_max_mm == math.inf
    assert config.planner.update == "corrected" and config.planner.normal_accel_mm_s2 is None
    assert config.modbus.allowed_networks == ("127.0.0.0/8",)
    assert config.axis("X") is axis
    with pytest.raises(KeyError):
        config.axis("Q")


def test_eds_path_is_relative_to_the_config_file(tmp_path: Path) -> None:
    doc = sim_document()
    doc["axes"][0]["eds"] = "drives/x.eds"
    path = tmp_path / "machine.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert load_config(path).axes[0].eds == tmp_path / "drives" / "x.eds"


def test_library_dir_is_relative_to_the_config_file(tmp_path: Path) -> None:
    (tmp_path / "programs").mkdir()
    doc = sim_document()
    doc["programs"] = {"library_dir": "programs"}
    doc["modbus"]["staging_timeout_ms"] = 5000
    path = tmp_path / "machine.yaml"
    path.write_text(yaml.safe_dump(doc))
    config = load_config(path)
    assert config.programs.library_dir == tmp_path / "programs"
    assert config.modbus.staging_timeout_ms == 5000
    assert parse_config(sim_document()).programs.library_dir is None


def _set(doc: dict[str, Any], path: str, value: Any) -> None:
    """Set ``a.b[1].c`` in a nested document; the value ``DELETE`` removes the key."""
    node: Any = doc
    parts = path.replace("]", "").replace("[", ".").split(".")
    for part in parts[:-1]:
        node = node[int(part)] if part.isdigit() else node.setdefault(part, {})
    last = parts[-1]
    if value is DELETE:
        del node[int(last) if last.isdigit() else last]
    elif last.isdigit():
        node[int(last)] = value
    else:
        node[last] = value


DELETE = object()

CASES = [
    # key path, value, message
    ("cycle", 5, "config: cycle = 5: expected a mapping of keys to values"),
    (
        "cycle.period_ms",
        "4ms",
        "config: cycle.period_ms = '4ms': expected a number",
    ),
    ("cycle.period_ms", True, "config: cycle.period_ms = True: expected a number"),
    ("cycle.period_ms", 0.1, "config: cycle.period_ms = 0.1: expected a value in 0.5..100"),
    ("cycle.period_ms", 250, "config: cycle.period_ms = 250: expected a value in 0.5..100"),
    ("cycle.period_ms", math.nan, "config: cycle.period_ms = nan: expected a finite number"),
    ("cycle.overrun_limit", 1.5, "config: cycle.overrun_limit = 1.5: expected an integer"),
    ("cycle.overrun_limit", -1, "config: cycle.overrun_limit = -1: expected a value in 0..1000"),
    (
        "cycle.realtime.priority",
        120,
        "config: cycle.realtime.priority = 120: expected a value in 0..99",
    ),
    ("cycle.realtime.cpu", -1, "config: cycle.realtime.cpu = -1: expected a value in 0 or more"),
    (
        "cycle.realtime.lock_memory",
        "yes please",
        "config: cycle.realtime.lock_memory = 'yes please': expected true or false",
    ),
    (
        "cycle.realtime.gc",
        "sometimes",
        "config: cycle.realtime.gc = 'sometimes': expected one of freeze, disable, normal",
    ),
    (
        "cycle.realtime.spin_us",
        4000,
        "config: cycle.realtime.spin_us = 4000.0: expected less than the period (4000 us)",
    ),
    (
        "cycle.realtime.nice",
        5,
        "config: cycle.realtime.nice = 5: expected a known key "
        "(one of cpu, gc, lock_memory, priority, spin_us)",
    ),
    ("planner.vmax_mm_s", 0, "config: planner.vmax_mm_s = 0: expected a number > 0"),
    ("planner.amax_mm_s2", -1000, "config: planner.amax_mm_s2 = -1000: expected a number > 0"),
    ("planner.jmax_mm_s3", "fast", "config: planner.jmax_mm_s3 = 'fast': expected a number"),
    ("planner.chord_error_mm", 0.0, "config: planner.chord_error_mm = 0.0: expected a number > 0"),
    ("planner.lookahead", 1, "config: planner.lookahead = 1: expected true or false"),
    (
        "planner.update",
        "taylor1",
        "config: planner.update = 'taylor1': expected one of corrected, taylor2",
    ),
    (
        "planner.normal_accel_mm_s2",
        -5,
        "config: planner.normal_accel_mm_s2 = -5: expected a number > 0",
    ),
    (
        "planner.vmax",
        100,
        "config: planner.vmax = 100: expected a known key (one of amax_mm_s2, chord_error_mm, "
        "jmax_mm_s3, lookahead, normal_accel_mm_s2, update, vmax_mm_s)",
    ),
    ("can.interface", "", "config: can.interface = '': expected a non-empty string"),
    ("can.channel", 0, "config: can.channel = 0: expected a non-empty string"),
    ("can.bitrate", 5000, "config: can.bitrate = 5000: expected a value in 10000..1000000"),
    ("can.heartbeat_ms", 0, "config: can.heartbeat_ms = 0: expected a value in 1..65535"),
    (
        "can.heartbeat_loss_periods",
        4,
        "config: can.heartbeat_loss_periods = 4: expected a value in 1.5..3",
    ),
    ("can.boot_timeout_s", 0, "config: can.boot_timeout_s = 0: expected a number > 0"),
    ("can.master_node_id", 128, "config: can.master_node_id = 128: expected a value in 1..127"),
    ("axes", [], "config: axes = []: expected a non-empty list"),
    ("axes", DELETE, "config: axes = None: expected a non-empty list"),
    ("axes", {"name": "X"}, "config: axes = {'name': 'X'}: expected a non-empty list"),
    ("axes[0]", "X", "config: axes[0] = 'X': expected a mapping of keys to values"),
    ("axes[1].node_id", 0, "config: axes[1].node_id = 0: expected a value in 1..127"),
    ("axes[1].node_id", 128, "config: axes[1].node_id = 128: expected a value in 1..127"),
    ("axes[1].node_id", "2", "config: axes[1].node_id = '2': expected an integer"),
    ("axes[1].node_id", DELETE, "config: axes[1].node_id = None: expected an integer"),
    ("axes[2].name", DELETE, "config: axes[2].name = None: expected a value (the key is required)"),
    ("axes[0].counts_per_mm", 0, "config: axes[0].counts_per_mm = 0: expected a number > 0"),
    ("axes[0].direction", 2, "config: axes[0].direction = 2: expected 1 or -1"),
    ("axes[0].mode", "pp", "config: axes[0].mode = 'pp': expected one of csp"),
    ("axes[0].travel_mm", [5], "config: axes[0].travel_mm = [5]: expected [min, max] in mm"),
    (
        "axes[0].travel_mm",
        ["a", 5],
        "config: axes[0].travel_mm = ['a', 5]: expected [min, max] in mm",
    ),
    ("axes[0].travel_mm", [5, 5], "config: axes[0].travel_mm = [5, 5]: expected min < max"),
    (
        "axes[0].following_error_window_mm",
        -0.1,
        "config: axes[0].following_error_window_mm = -0.1: expected a number > 0",
    ),
    ("axes[0].vmax_mm_s", 0, "config: axes[0].vmax_mm_s = 0: expected a number > 0"),
    ("axes[0].eds", 7, "config: axes[0].eds = 7: expected a path to an EDS file"),
    (
        "axes[0].speed",
        7,
        "config: axes[0].speed = 7: expected a known key (one of amax_mm_s2, counts_per_mm, "
        "direction, eds, feedback_lag_periods, following_error_timeout_ms, "
        "following_error_window_mm, guard_time_ms, life_time_factor, mode, name, node_id, pdo, "
        "supervision, travel_mm, vmax_mm_s)",
    ),
    ("can.sdo_retries", -1, "config: can.sdo_retries = -1: expected a value in 0..10"),
    ("can.sdo_timeout_s", 0, "config: can.sdo_timeout_s = 0: expected a number > 0"),
    (
        "can.sync_counter_overflow",
        1,
        "config: can.sync_counter_overflow = 1: expected 0 or a value in 2..240",
    ),
    (
        "can.sync_counter_overflow",
        241,
        "config: can.sync_counter_overflow = 241: expected a value in 0..240",
    ),
    (
        "can.reset_communication",
        "yes",
        "config: can.reset_communication = 'yes': expected true or false",
    ),
    ("can.shutdown_timeout_s", 0, "config: can.shutdown_timeout_s = 0: expected a number > 0"),
    (
        "axes[0].supervision",
        "both",
        "config: axes[0].supervision = 'both': expected one of heartbeat, guarding",
    ),
    ("axes[0].guard_time_ms", 0, "config: axes[0].guard_time_ms = 0: expected a value in 1..65535"),
    (
        "axes[0].life_time_factor",
        256,
        "config: axes[0].life_time_factor = 256: expected a value in 1..255",
    ),
    (
        "axes[0].feedback_lag_periods",
        -1,
        "config: axes[0].feedback_lag_periods = -1: expected a value in 0..100",
    ),
    (
        "axes[0].pdo.mapping",
        "rewrite",
        "config: axes[0].pdo.mapping = 'rewrite': expected one of auto, write, keep",
    ),
    (
        "axes[0].pdo.rpdo.objects",
        [0x6040],
        "config: axes[0].pdo = {'rpdo': {'objects': [24640]}}: expected RPDO: 0x607A target "
        "position is required",
    ),
    (
        "axes[0].pdo.tpdo",
        [{"number": 1, "objects": [0x6041, 0x6064, 0x60F4]}],
        "config: axes[0].pdo.tpdo[0].objects = [24641, 24676, 24820]: expected PDO 1: objects "
        "take 10 bytes, at most 8 fit a frame",
    ),
    (
        "axes[0].pdo.tpdo",
        [{"objects": [0x6041, 0x6064]}],
        "config: axes[0].pdo.tpdo[0].number = None: expected an integer",
    ),
    (
        "axes[0].pdo.rpdo.cob_id",
        0x800,
        "config: axes[0].pdo.rpdo.cob_id = 2048: expected a value in 1..2047",
    ),
    (
        "simulation.quirks",
        {"W": {}},
        "config: simulation.quirks.W = 'W': expected the name of an axis (X, Y, Z)",
    ),
    (
        "simulation.quirks",
        {"X": {"sdo_delay_ms": [400, 150]}},
        "config: simulation.quirks.X.sdo_delay_ms = [400, 150]: expected [shortest, longest] "
        "in ms, >= 0",
    ),
    (
        "simulation.quirks",
        {"X": {"late_boot": True}},
        "config: simulation.quirks.X.late_boot = True: expected a known key (one of "
        "boot_delay_s, fault_at_power_on, fixed_pdo_mapping, guarding_only, "
        "interpolation_ms_only, late_tpdo_periods, no_optional_objects, sdo_delay_ms)",
    ),
    ("axes[2].node_id", 1, "config: axes[2].node_id = 1: expected a node id not used by axes[0]"),
    (
        "axes[2].node_id",
        127,
        "config: axes[2].node_id = 127: expected a node id other than can.master_node_id",
    ),
    ("axes[1].name", "X", "config: axes[1].name = 'X': expected a name not used by axes[0]"),
    ("simulation.drives", "on", "config: simulation.drives = 'on': expected true or false"),
    (
        "modbus.bind",
        "localhost",
        "config: modbus.bind = 'localhost': expected an IPv4 or IPv6 address",
    ),
    (
        "modbus.bind",
        "10.0.0.300",
        "config: modbus.bind = '10.0.0.300': expected an IPv4 or IPv6 address",
    ),
    ("modbus.port", 70000, "config: modbus.port = 70000: expected a value in 1..65535"),
    ("modbus.unit_id", 0, "config: modbus.unit_id = 0: expected a value in 1..247"),
    (
        "modbus.allowed_networks",
        "127.0.0.0/8",
        "config: modbus.allowed_networks = '127.0.0.0/8': expected a non-empty list",
    ),
    (
        "modbus.allowed_networks",
        ["10.0.0.0/8", "office"],
        "config: modbus.allowed_networks[1] = 'office': expected a network such as 10.0.0.0/8",
    ),
    ("modbus.read_only", "no", "config: modbus.read_only = 'no': expected true or false"),
    (
        "modbus.watchdog.timeout_ms",
        -1,
        "config: modbus.watchdog.timeout_ms = -1: expected a value in 0..600000",
    ),
    (
        "modbus.watchdog.action",
        "panic",
        "config: modbus.watchdog.action = 'panic': expected one of hold, stop",
    ),
    (
        "modbus.staging_timeout_ms",
        500,
        "config: modbus.staging_timeout_ms = 500: expected a value in 1000..3600000",
    ),
    (
        "programs.library_dir",
        "/nonexistent/programs",
        "config: programs.library_dir = '/nonexistent/programs': expected an existing directory "
        "(/nonexistent/programs is none)",
    ),
    ("programs.library_dir", 5, "config: programs.library_dir = 5: expected a directory path"),
    (
        "programs.library",
        "x",
        "config: programs.library = 'x': expected a known key (one of library_dir)",
    ),
    (
        "machine.fault_reaction",
        "coast",
        "config: machine.fault_reaction = 'coast': expected one of stop, quick_stop",
    ),
    (
        "hmi",
        {},
        "config: hmi = {}: expected a known key (one of axes, can, cycle, machine, modbus, "
        "planner, programs, simulation)",
    ),
]


@pytest.mark.parametrize(("key_path", "value", "message"), CASES, ids=[c[0] for c in CASES])
def test_rejected_with_message(key_path: str, value: Any, message: str) -> None:
    doc = sim_document()
    _set(doc, key_path, value)
    with pytest.raises(ConfigError) as info:
        parse_config(doc)
    assert str(info.value) == message
    assert info.value.key_path == message.split(" = ")[0].removeprefix("config: ")


def test_pdo_objects_must_be_process_data_of_csp() -> None:
    doc = sim_document()
    doc["axes"][0]["pdo"] = {"tpdo": [{"number": 1, "objects": [0x6041, 0x6077]}]}
    with pytest.raises(ConfigError) as info:
        parse_config(doc)
    assert str(info.value).startswith(
        "config: axes[0].pdo.tpdo[0].objects[1] = 24695: expected one of 0x603F error code, "
        "0x6040 controlword, 0x6041 statusword"
    )


def test_drive_keys_reach_the_master_and_the_simulated_drives() -> None:
    doc = sim_document()
    doc["can"].update(sdo_timeout_s=1.5, sdo_retries=3, sync_counter_overflow=16)
    doc["axes"][1].update(
        supervision="guarding",
        guard_time_ms=50,
        life_time_factor=4,
        feedback_lag_periods=2,
        pdo={
            "mapping": "keep",
            "rpdo": {"number": 2, "cob_id": 0x301, "objects": [0x6040, 0x607A, 0x6060]},
            "tpdo": [
                {"number": 1, "objects": [0x6041, 0x6064]},
                {"number": 2, "objects": [0x60F4, 0x603F]},
            ],
        },
    )
    doc["simulation"]["quirks"] = {
        "Y": {"guarding_only": True, "sdo_delay_ms": [150, 400], "late_tpdo_periods": 1}
    }
    config = parse_config(doc)
    assert (config.can.sdo_timeout_s, config.can.sdo_retries) == (1.5, 3)
    assert config.can.sync_counter_overflow == 16 and config.can.reset_communication
    y = config.axes[1]
    assert y.supervision is Supervision.GUARDING
    assert (y.guard_time_ms, y.life_time_factor, y.feedback_lag_periods) == (50, 4, 2)
    assert y.pdo == AxisPdoSpec(
        MappingPolicy.KEEP,
        PdoSpec(2, (0x6040, 0x607A, 0x6060), 0x301),
        (PdoSpec(1, (0x6041, 0x6064)), PdoSpec(2, (0x60F4, 0x603F))),
    )
    assert config.axes[0].pdo == AxisPdoSpec()
    assert config.simulation.quirks == {
        "Y": DriveQuirks(guarding_only=True, sdo_delay_s=(0.15, 0.4), late_tpdo_periods=1)
    }
    assert CanConfig().sdo_timeout_s == 1.0 and CanConfig().sdo_retries == 2


def test_more_than_three_axes_rejected() -> None:
    doc = sim_document()
    doc["axes"].append({"name": "A", "node_id": 4, "counts_per_mm": 10})
    with pytest.raises(ConfigError) as info:
        parse_config(doc)
    assert str(info.value) == "config: axes = 4: expected at most 3 axes (x, y, z of the path)"


def test_root_must_be_a_mapping() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(["axes"])
    assert str(info.value) == "config: config = ['axes']: expected a mapping of keys to values"


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError) as info:
        load_config(missing)
    assert str(info.value) == (
        f"config: {missing} = None: expected a readable file (No such file or directory)"
    )
    broken = tmp_path / "broken.yaml"
    broken.write_text("axes: [\n")
    with pytest.raises(ConfigError) as info:
        load_config(broken)
    assert str(info.value).startswith(f"config: {broken} = None: expected valid YAML (")


def test_document_is_not_modified() -> None:
    doc = sim_document()
    before = copy.deepcopy(doc)
    parse_config(doc)
    assert doc == before
