"""Machine configuration: a YAML machine description loaded into typed, validated records.

Every key carries its unit in its name (``period_ms``, ``vmax_mm_s``, ``counts_per_mm``). Loading
is strict, like Klipper's unread-option rule: unknown keys, wrong types, out-of-range values and
contradictions (duplicate node ids, a bind address that is not an IP address, ...) raise
:class:`ConfigError`, whose message names the key path (``axes[1].node_id``), the value found and
what was expected. Optional sections and keys take the defaults of the simulated machine.

Pure: reads one file (``load_config``) or a mapping (``parse_config``); no threads.
"""

from __future__ import annotations

import ipaddress
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import yaml

from drives.boot import Supervision
from drives.objects import PROCESS_ENTRIES, describe_object
from drives.pdo import RPDO_REQUIRED, AxisPdoSpec, MappingPolicy, PdoSpec
from drives.sim.quirks import DriveQuirks
from runtime.errors import ConfigError

#: The shipped configurations (``sim.yaml``, ``vcan.yaml``, ``ipc-example.yaml``, ``curves/``,
#: ``drives/``): the package data ``runtime/configs``, which in a checkout is a symbolic link to
#: the repository's ``configs/`` (``pyproject.toml``). Found from any working directory.
SHIPPED_CONFIGS_DIR = (Path(__file__).parent / "configs").resolve()
#: The configuration the command line uses when ``--config`` is not given: the simulated machine.
DEFAULT_CONFIG_PATH = SHIPPED_CONFIGS_DIR / "sim.yaml"
#: The curve ``softmotion run --demo`` runs: Table 1 of the paper.
DEMO_CURVE_PATH = SHIPPED_CONFIGS_DIR / "curves" / "paper.yaml"

UPDATE_METHODS = ("corrected", "taylor2")
GC_MODES = ("freeze", "disable", "normal")
FAULT_REACTIONS = ("stop", "quick_stop")
WATCHDOG_ACTIONS = ("hold", "stop")
AXIS_MODES = ("csp",)
SUPERVISIONS = tuple(kind.value for kind in Supervision)
MAPPING_POLICIES = tuple(policy.value for policy in MappingPolicy)
#: Boolean switches of a simulated drive's quirks (drives.sim.quirks.DriveQuirks).
QUIRK_FLAGS = (
    "no_optional_objects",
    "fixed_pdo_mapping",
    "interpolation_ms_only",
    "fault_at_power_on",
    "guarding_only",
)


@dataclass(frozen=True)
class RealtimeConfig:
    """Real-time settings of the cyclic thread, applied where the OS permits."""

    priority: int = 80
    """SCHED_FIFO priority 1..99; 0 keeps the default scheduler."""
    cpu: int | None = None
    """CPU the cyclic thread is pinned to; None leaves affinity alone."""
    lock_memory: bool = True
    """mlockall(MCL_CURRENT | MCL_FUTURE) so page faults never stall a cycle, and malloc
    keeps freed memory for reuse (see runtime.realtime)."""
    gc: str = "freeze"
    """Garbage collector while moving: freeze (gc.freeze + disable), disable, or normal."""
    spin_us: float = 200.0
    """Busy-wait this long before each deadline instead of sleeping through it."""


@dataclass(frozen=True)
class CycleConfig:
    """The cyclic task."""

    period_ms: float = 4.0
    realtime: RealtimeConfig = RealtimeConfig()
    overrun_limit: int = 3
    """More consecutive missed periods than this stop the machine (ErrorStop)."""
    statistics_window_s: float = 10.0
    """The lateness percentiles in the status cover the periods of this last stretch."""

    @property
    def period_s(self) -> float:
        return self.period_ms / 1000.0


@dataclass(frozen=True)
class PlannerConfig:
    """Path limits and planning options (paper section 3 uses 100, 1000, 20000)."""

    vmax_mm_s: float = 100.0
    amax_mm_s2: float = 1000.0
    jmax_mm_s3: float = 20000.0
    chord_error_mm: float = 0.001
    lookahead: bool = True
    update: str = "corrected"
    """Parameter update: ``corrected`` (Newton on arc length) or ``taylor2`` (paper eq. (2))."""
    normal_accel_mm_s2: float | None = None
    """Optional centripetal acceleration limit (not in the paper); None = off."""


@dataclass(frozen=True)
class CanConfig:
    """The CAN bus and the CANopen services the master runs on it."""

    interface: str = "virtual"
    """python-can interface name (virtual, socketcan, pcan, kvaser, ...)."""
    channel: str = "softmotion"
    bitrate: int = 1_000_000
    master_node_id: int = 127
    heartbeat_ms: int = 100
    """Heartbeat producer time configured on every drive (0x1017)."""
    master_heartbeat_ms: int = 100
    """Our own heartbeat, consumed by the drives (0x1016); 0 = not sent."""
    heartbeat_loss_periods: float = 2.5
    """A drive is lost after this many heartbeat periods without one (< 3 by design)."""
    sync_window_us: int = 0
    """Synchronous window length (0x1007); 0 = not used."""
    boot_timeout_s: float = 5.0
    """A drive silent this long at start is reported (and still looked for)."""
    sdo_timeout_s: float = 1.0
    """Time allowed for each SDO answer (slow drives take hundreds of ms)."""
    sdo_retries: int = 2
    """A transfer that timed out is tried this many times more."""
    stale_feedback_cycles: int = 3
    """An axis is faulted once this many SYNCs in a row went unanswered by its TPDO."""
    sync_counter_overflow: int = 0
    """0: SYNC without data, feedback matched by timestamp; 2..240: counted SYNC (0x1019 on
    every drive), feedback matched by the order of our SYNC's echo."""
    reset_communication: bool = True
    """NMT reset communication at start, so drives that booted earlier boot again."""
    shutdown_timeout_s: float = 3.0
    """The whole clean shutdown (disable, disarm the drives' supervision of us, PRE-OP)."""


@dataclass(frozen=True)
class AxisConfig:
    """One servo axis on the bus, driven in cyclic synchronous position mode."""

    name: str
    node_id: int
    counts_per_mm: float
    direction: int = 1
    mode: str = "csp"
    travel_min_mm: float = -math.inf
    travel_max_mm: float = math.inf
    following_error_window_mm: float = 1.0
    following_error_timeout_ms: int = 20
    vmax_mm_s: float | None = None
    amax_mm_s2: float | None = None
    eds: Path | None = None
    supervision: Supervision = Supervision.HEARTBEAT
    """heartbeat (falls back to node guarding on a drive without 0x1017) or guarding."""
    guard_time_ms: int = 100
    life_time_factor: int = 3
    feedback_lag_periods: int = 1
    """SYNCs between a target and the TPDO reporting the position reached for it."""
    pdo: AxisPdoSpec = field(default_factory=AxisPdoSpec)


@dataclass(frozen=True)
class SimulationConfig:
    """Simulated CiA-402 drives on the configured bus, in this process."""

    drives: bool = False
    quirks: Mapping[str, DriveQuirks] = field(default_factory=dict)
    """Per axis name: how its simulated drive behaves like other vendors' drives."""


@dataclass(frozen=True)
class WatchdogConfig:
    """HMI link watchdog: the HMI heartbeat register must keep changing while moving."""

    timeout_ms: int = 0
    """0 turns the watchdog off."""
    action: str = "hold"


@dataclass(frozen=True)
class ModbusConfig:
    """The Modbus TCP server the HMI talks to."""

    enabled: bool = True
    bind: str = "127.0.0.1"
    port: int = 1502
    unit_id: int = 1
    allowed_networks: tuple[str, ...] = ("127.0.0.0/8",)
    read_only: bool = False
    watchdog: WatchdogConfig = WatchdogConfig()
    staging_timeout_ms: int = 30_000
    """A client's hold on the curve staging area lapses this long after its last staging write."""


@dataclass(frozen=True)
class ProgramsConfig:
    """Where programs come from besides uploads."""

    library_dir: Path | None = None
    """A directory of curve files (``*.yaml``) the HMI lists and loads by number; None: no
    library. Relative to the configuration file."""


@dataclass(frozen=True)
class MachineBehaviourConfig:
    """How the machine reacts to faults."""

    fault_reaction: str = "stop"
    """Reaction to faults that leave every drive able to follow the path (planner, cycle
    overrun, HMI link, following error...): ``stop`` brakes jerk-limited along the path;
    ``quick_stop`` asks every drive for its quick stop (605A)."""
    axis_fault_reaction: str = "quick_stop"
    """Reaction of the other axes when an axis's drive faults or is lost (that axis stops on
    its own fault reaction, 605E): ``quick_stop`` stops every axis as fast as its drive can,
    the least deviation from the path; ``stop`` brakes the others along the path (they keep
    the path while the faulted axis stands, so the tool leaves it by what the faulted axis
    misses)."""


@dataclass(frozen=True)
class MachineConfig:
    """A whole machine description."""

    cycle: CycleConfig
    planner: PlannerConfig
    can: CanConfig
    axes: tuple[AxisConfig, ...]
    simulation: SimulationConfig
    modbus: ModbusConfig
    machine: MachineBehaviourConfig
    source: Path | None = None
    programs: ProgramsConfig = ProgramsConfig()

    def axis(self, name: str) -> AxisConfig:
        """The axis called ``name``.

        :raises KeyError: if no axis has that name.
        """
        for axis in self.axes:
            if axis.name == name:
                return axis
        raise KeyError(name)


T = TypeVar("T")


class _Section:
    """Reads one mapping of the YAML tree, remembering its key path for messages."""

    def __init__(self, data: Any, path: str) -> None:
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise ConfigError(path or "config", data, "a mapping of keys to values")
        self.data = dict(data)
        self.path = path
        self.read: set[str] = set()

    def key_path(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str, default: Any) -> Any:
        self.read.add(key)
        return self.data.get(key, default)

    def section(self, key: str) -> _Section:
        return _Section(self.raw(key, None), self.key_path(key))

    def number(
        self,
        key: str,
        default: float | None,
        *,
        minimum: float | None = None,
        maximum: float | None = None,
        positive: bool = False,
        optional: bool = False,
    ) -> float | None:
        value = self.raw(key, default)
        path = self.key_path(key)
        if value is None and optional:
            return None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(path, value, "a number")
        if not math.isfinite(value):
            raise ConfigError(path, value, "a finite number")
        _check_range(path, value, minimum, maximum, positive)
        return float(value)

    def integer(
        self,
        key: str,
        default: int | None,
        *,
        minimum: int | None = None,
        maximum: int | None = None,
        optional: bool = False,
    ) -> int | None:
        value = self.raw(key, default)
        path = self.key_path(key)
        if value is None and optional:
            return None
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, value, "an integer")
        _check_range(path, value, minimum, maximum, False)
        return value

    def boolean(self, key: str, default: bool) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise ConfigError(self.key_path(key), value, "true or false")
        return value

    def string(self, key: str, default: str | None, *, choices: tuple[str, ...] = ()) -> str:
        value = self.raw(key, default)
        path = self.key_path(key)
        if value is None:
            raise ConfigError(path, value, "a value (the key is required)")
        if not isinstance(value, str) or not value:
            raise ConfigError(path, value, "a non-empty string")
        if choices and value not in choices:
            raise ConfigError(path, value, "one of " + ", ".join(choices))
        return value

    def items(self, key: str, parse: Callable[[_Section], T], *, required: bool) -> list[T]:
        value = self.raw(key, None)
        path = self.key_path(key)
        if value is None and not required:
            return []
        if not isinstance(value, list) or (required and not value):
            raise ConfigError(path, value, "a non-empty list")
        return [parse(_Section(item, f"{path}[{i}]")) for i, item in enumerate(value)]

    def finish(self) -> None:
        """Reject keys nobody read: a typo must not silently fall back to a default."""
        unknown = sorted(set(self.data) - self.read, key=str)
        if unknown:
            key = unknown[0]
            expected = "one of " + ", ".join(sorted(self.read)) if self.read else "no keys"
            raise ConfigError(self.key_path(str(key)), self.data[key], f"a known key ({expected})")


def _format_bound(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def _check_range(
    path: str, value: float, minimum: float | None, maximum: float | None, positive: bool
) -> None:
    if positive and value <= 0:
        raise ConfigError(path, value, "a number > 0")
    if minimum is not None and value < minimum:
        high = f"..{_format_bound(maximum)}" if maximum is not None else " or more"
        raise ConfigError(path, value, f"a value in {_format_bound(minimum)}{high}")
    if maximum is not None and value > maximum:
        low = f"{_format_bound(minimum)}.." if minimum is not None else "at most "
        raise ConfigError(path, value, f"a value in {low}{_format_bound(maximum)}")


def _parse_realtime(s: _Section) -> RealtimeConfig:
    d = RealtimeConfig()
    config = RealtimeConfig(
        priority=s.integer("priority", d.priority, minimum=0, maximum=99),
        cpu=s.integer("cpu", d.cpu, minimum=0, optional=True),
        lock_memory=s.boolean("lock_memory", d.lock_memory),
        gc=s.string("gc", d.gc, choices=GC_MODES),
        spin_us=s.number("spin_us", d.spin_us, minimum=0),
    )
    s.finish()
    return config


def _parse_cycle(s: _Section) -> CycleConfig:
    d = CycleConfig()
    config = CycleConfig(
        period_ms=s.number("period_ms", d.period_ms, minimum=0.5, maximum=100),
        realtime=_parse_realtime(s.section("realtime")),
        overrun_limit=s.integer("overrun_limit", d.overrun_limit, minimum=0, maximum=1000),
        statistics_window_s=s.number(
            "statistics_window_s", d.statistics_window_s, minimum=1, maximum=3600
        ),
    )
    s.finish()
    if config.realtime.spin_us >= config.period_ms * 1000:
        raise ConfigError(
            s.key_path("realtime.spin_us"),
            config.realtime.spin_us,
            f"less than the period ({_format_bound(config.period_ms * 1000)} us)",
        )
    return config


def _parse_planner(s: _Section) -> PlannerConfig:
    d = PlannerConfig()
    config = PlannerConfig(
        vmax_mm_s=s.number("vmax_mm_s", d.vmax_mm_s, positive=True),
        amax_mm_s2=s.number("amax_mm_s2", d.amax_mm_s2, positive=True),
        jmax_mm_s3=s.number("jmax_mm_s3", d.jmax_mm_s3, positive=True),
        chord_error_mm=s.number("chord_error_mm", d.chord_error_mm, positive=True),
        lookahead=s.boolean("lookahead", d.lookahead),
        update=s.string("update", d.update, choices=UPDATE_METHODS),
        normal_accel_mm_s2=s.number("normal_accel_mm_s2", None, positive=True, optional=True),
    )
    s.finish()
    return config


def _parse_can(s: _Section) -> CanConfig:
    d = CanConfig()
    config = CanConfig(
        interface=s.string("interface", d.interface),
        channel=str(s.string("channel", d.channel)),
        bitrate=s.integer("bitrate", d.bitrate, minimum=10_000, maximum=1_000_000),
        master_node_id=s.integer("master_node_id", d.master_node_id, minimum=1, maximum=127),
        heartbeat_ms=s.integer("heartbeat_ms", d.heartbeat_ms, minimum=1, maximum=65535),
        master_heartbeat_ms=s.integer(
            "master_heartbeat_ms", d.master_heartbeat_ms, minimum=0, maximum=65535
        ),
        heartbeat_loss_periods=s.number(
            "heartbeat_loss_periods", d.heartbeat_loss_periods, minimum=1.5, maximum=3
        ),
        sync_window_us=s.integer("sync_window_us", d.sync_window_us, minimum=0),
        boot_timeout_s=s.number("boot_timeout_s", d.boot_timeout_s, positive=True),
        sdo_timeout_s=s.number("sdo_timeout_s", d.sdo_timeout_s, positive=True),
        sdo_retries=s.integer("sdo_retries", d.sdo_retries, minimum=0, maximum=10),
        stale_feedback_cycles=s.integer(
            "stale_feedback_cycles", d.stale_feedback_cycles, minimum=1, maximum=1000
        ),
        sync_counter_overflow=s.integer(
            "sync_counter_overflow", d.sync_counter_overflow, minimum=0, maximum=240
        ),
        reset_communication=s.boolean("reset_communication", d.reset_communication),
        shutdown_timeout_s=s.number("shutdown_timeout_s", d.shutdown_timeout_s, positive=True),
    )
    s.finish()
    if config.sync_counter_overflow == 1:
        raise ConfigError(s.key_path("sync_counter_overflow"), 1, "0 or a value in 2..240")
    return config


def _parse_pdo_objects(s: _Section, default: tuple[int, ...] | None) -> tuple[int, ...]:
    value = s.raw("objects", None if default is None else list(default))
    path = s.key_path("objects")
    if not isinstance(value, list) or not value:
        raise ConfigError(path, value, "a non-empty list of object indices such as 0x6041")
    known = ", ".join(describe_object(index) for index in sorted(PROCESS_ENTRIES))
    for i, index in enumerate(value):
        if isinstance(index, bool) or index not in PROCESS_ENTRIES:
            raise ConfigError(f"{path}[{i}]", index, f"one of {known}")
    return tuple(value)


def _parse_pdo_spec(s: _Section, default: PdoSpec | None) -> PdoSpec:
    number = s.integer(
        "number", None if default is None else default.number, minimum=1, maximum=512
    )
    cob_id = s.integer("cob_id", None, minimum=1, maximum=0x7FF, optional=True)
    objects = _parse_pdo_objects(s, None if default is None else default.objects)
    s.finish()
    try:
        return PdoSpec(number, objects, cob_id)
    except ValueError as exc:
        raise ConfigError(s.key_path("objects"), list(objects), str(exc)) from None


def _parse_pdo(s: _Section) -> AxisPdoSpec:
    d = AxisPdoSpec()
    mapping = s.string("mapping", d.mapping.value, choices=MAPPING_POLICIES)
    rpdo = _parse_pdo_spec(s.section("rpdo"), PdoSpec(1, RPDO_REQUIRED))
    tpdos = s.items("tpdo", lambda item: _parse_pdo_spec(item, None), required=False)
    s.finish()
    try:
        return AxisPdoSpec(MappingPolicy(mapping), rpdo, tuple(tpdos) or d.tpdos)
    except ValueError as exc:
        raise ConfigError(s.path, s.data, str(exc)) from None


def _parse_axis(s: _Section) -> AxisConfig:
    name = s.string("name", None)
    travel = s.raw("travel_mm", None)
    if travel is None:
        travel_min, travel_max = -math.inf, math.inf
    else:
        ok = (
            isinstance(travel, list)
            and len(travel) == 2
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in travel)
            and all(math.isfinite(v) for v in travel)
        )
        if not ok:
            raise ConfigError(s.key_path("travel_mm"), travel, "[min, max] in mm")
        travel_min, travel_max = float(travel[0]), float(travel[1])
        if travel_min >= travel_max:
            raise ConfigError(s.key_path("travel_mm"), travel, "min < max")
    direction = s.integer("direction", 1)
    if direction not in (1, -1):
        raise ConfigError(s.key_path("direction"), direction, "1 or -1")
    eds = s.raw("eds", None)
    if eds is not None and (not isinstance(eds, str) or not eds):
        raise ConfigError(s.key_path("eds"), eds, "a path to an EDS file")
    config = AxisConfig(
        name=name,
        node_id=s.integer("node_id", None, minimum=1, maximum=127),
        counts_per_mm=s.number("counts_per_mm", None, positive=True),
        direction=direction,
        mode=s.string("mode", "csp", choices=AXIS_MODES),
        travel_min_mm=travel_min,
        travel_max_mm=travel_max,
        following_error_window_mm=s.number("following_error_window_mm", 1.0, positive=True),
        following_error_timeout_ms=s.integer(
            "following_error_timeout_ms", 20, minimum=0, maximum=65535
        ),
        vmax_mm_s=s.number("vmax_mm_s", None, positive=True, optional=True),
        amax_mm_s2=s.number("amax_mm_s2", None, positive=True, optional=True),
        eds=Path(eds) if eds is not None else None,
        supervision=Supervision(s.string("supervision", "heartbeat", choices=SUPERVISIONS)),
        guard_time_ms=s.integer("guard_time_ms", 100, minimum=1, maximum=65535),
        life_time_factor=s.integer("life_time_factor", 3, minimum=1, maximum=255),
        feedback_lag_periods=s.integer("feedback_lag_periods", 1, minimum=0, maximum=100),
        pdo=_parse_pdo(s.section("pdo")),
    )
    s.finish()
    return config


def _parse_modbus(s: _Section) -> ModbusConfig:
    d = ModbusConfig()
    bind = s.string("bind", d.bind)
    try:
        ipaddress.ip_address(bind)
    except ValueError:
        raise ConfigError(s.key_path("bind"), bind, "an IPv4 or IPv6 address") from None
    networks = s.raw("allowed_networks", list(d.allowed_networks))
    if not isinstance(networks, list) or not networks:
        raise ConfigError(s.key_path("allowed_networks"), networks, "a non-empty list")
    for i, network in enumerate(networks):
        try:
            ipaddress.ip_network(str(network), strict=False)
        except ValueError:
            raise ConfigError(
                f"{s.key_path('allowed_networks')}[{i}]", network, "a network such as 10.0.0.0/8"
            ) from None
    watchdog = s.section("watchdog")
    wd = WatchdogConfig(
        timeout_ms=watchdog.integer("timeout_ms", 0, minimum=0, maximum=600_000),
        action=watchdog.string("action", "hold", choices=WATCHDOG_ACTIONS),
    )
    watchdog.finish()
    config = ModbusConfig(
        enabled=s.boolean("enabled", d.enabled),
        bind=bind,
        port=s.integer("port", d.port, minimum=1, maximum=65535),
        unit_id=s.integer("unit_id", d.unit_id, minimum=1, maximum=247),
        allowed_networks=tuple(str(n) for n in networks),
        read_only=s.boolean("read_only", d.read_only),
        watchdog=wd,
        staging_timeout_ms=s.integer(
            "staging_timeout_ms", d.staging_timeout_ms, minimum=1000, maximum=3_600_000
        ),
    )
    s.finish()
    return config


def _parse_programs(s: _Section, base: Path | None) -> ProgramsConfig:
    library = s.raw("library_dir", None)
    path = s.key_path("library_dir")
    s.finish()
    if library is None:
        return ProgramsConfig()
    if not isinstance(library, str) or not library:
        raise ConfigError(path, library, "a directory path")
    directory = Path(library)
    if base is not None and not directory.is_absolute():
        directory = base / directory
    if not directory.is_dir():
        raise ConfigError(path, library, f"an existing directory ({directory} is none)")
    return ProgramsConfig(library_dir=directory)


def _parse_quirks(s: _Section) -> DriveQuirks:
    flags = {flag: s.boolean(flag, False) for flag in QUIRK_FLAGS}
    delay = s.raw("sdo_delay_ms", [0, 0])
    ok = (
        isinstance(delay, list)
        and len(delay) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in delay)
        and all(math.isfinite(v) and v >= 0 for v in delay)
        and delay[0] <= delay[1]
    )
    if not ok:
        raise ConfigError(s.key_path("sdo_delay_ms"), delay, "[shortest, longest] in ms, >= 0")
    quirks = DriveQuirks(
        **flags,
        sdo_delay_s=(delay[0] / 1000.0, delay[1] / 1000.0),
        boot_delay_s=s.number("boot_delay_s", 0.0, minimum=0),
        late_tpdo_periods=s.integer("late_tpdo_periods", 0, minimum=0, maximum=100),
    )
    s.finish()
    return quirks


def _parse_simulation(s: _Section) -> SimulationConfig:
    drives = s.boolean("drives", False)
    section = s.section("quirks")
    quirks = {
        str(name): _parse_quirks(_Section(section.raw(name, None), section.key_path(str(name))))
        for name in list(section.data)
    }
    config = SimulationConfig(drives=drives, quirks=quirks)
    s.finish()
    return config


def _parse_machine(s: _Section) -> MachineBehaviourConfig:
    config = MachineBehaviourConfig(
        fault_reaction=s.string("fault_reaction", "stop", choices=FAULT_REACTIONS),
        axis_fault_reaction=s.string("axis_fault_reaction", "quick_stop", choices=FAULT_REACTIONS),
    )
    s.finish()
    return config


def _check_axes(axes: list[AxisConfig], can: CanConfig) -> None:
    seen_ids: dict[int, int] = {}
    seen_names: dict[str, int] = {}
    for i, axis in enumerate(axes):
        if axis.node_id in seen_ids:
            raise ConfigError(
                f"axes[{i}].node_id",
                axis.node_id,
                f"a node id not used by axes[{seen_ids[axis.node_id]}]",
            )
        if axis.node_id == can.master_node_id:
            raise ConfigError(
                f"axes[{i}].node_id", axis.node_id, "a node id other than can.master_node_id"
            )
        if axis.name in seen_names:
            raise ConfigError(
                f"axes[{i}].name", axis.name, f"a name not used by axes[{seen_names[axis.name]}]"
            )
        seen_ids[axis.node_id] = i
        seen_names[axis.name] = i
    if len(axes) > 3:
        raise ConfigError("axes", len(axes), "at most 3 axes (x, y, z of the path)")


def _check_simulation(simulation: SimulationConfig, axes: list[AxisConfig]) -> None:
    names = [axis.name for axis in axes]
    for name in simulation.quirks:
        if name not in names:
            raise ConfigError(
                f"simulation.quirks.{name}", name, f"the name of an axis ({', '.join(names)})"
            )


def parse_config(data: Any, source: Path | None = None) -> MachineConfig:
    """Validate a parsed YAML document into a :class:`MachineConfig`.

    :raises ConfigError: naming the first offending key path, its value and what was expected.
    """
    root = _Section(data, "")
    cycle = _parse_cycle(root.section("cycle"))
    planner = _parse_planner(root.section("planner"))
    can = _parse_can(root.section("can"))
    axes = root.items("axes", _parse_axis, required=True)
    simulation = _parse_simulation(root.section("simulation"))
    modbus = _parse_modbus(root.section("modbus"))
    machine = _parse_machine(root.section("machine"))
    programs = _parse_programs(root.section("programs"), source.parent if source else None)
    root.finish()
    _check_axes(axes, can)
    _check_simulation(simulation, axes)
    if source is not None:
        axes = [_resolve_eds(axis, source.parent) for axis in axes]
    return MachineConfig(
        cycle=cycle,
        planner=planner,
        can=can,
        axes=tuple(axes),
        simulation=simulation,
        modbus=modbus,
        machine=machine,
        source=source,
        programs=programs,
    )


def _resolve_eds(axis: AxisConfig, base: Path) -> AxisConfig:
    if axis.eds is None or axis.eds.is_absolute():
        return axis
    return replace(axis, eds=base / axis.eds)


def load_config(path: str | Path) -> MachineConfig:
    """Read and validate a machine description.

    :raises ConfigError: if the file cannot be read, is not YAML, or does not validate.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), None, f"a readable file ({exc.strerror})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), None, f"valid YAML ({exc})") from None
    return parse_config(data, source=path)
