"""``softmotion doctor``: is this machine ready to run the configured cycle?

One line per check, ``ok``, ``warn`` or ``fail``, each warn and fail with its fix; the exit status
is 0 when nothing fails, 1 otherwise. The checks follow what ``softmotion run`` needs on an
industrial PC: its cycle process runs one thread under SCHED_FIFO with mlockall, pinned to
``cycle.realtime.cpu`` when set, and opens the CAN bus; a planner, an HMI (Modbus TCP) and a log
writer process exchange with it through POSIX shared memory.

Sources of each check:

- kernel: ``uname -v`` and ``/sys/kernel/realtime`` (both name PREEMPT_RT kernels);
- timer: ``clock_getres(CLOCK_MONOTONIC)`` (1 ns with high-resolution timers, a scheduler tick
  without) and the clocksource in ``/sys/devices/system/clocksource/clocksource0``;
- cpu pinning and isolation: ``cycle.realtime.cpu`` against ``/proc/cmdline``'s ``isolcpus``,
  ``nohz_full`` and ``irqaffinity`` (kernel-parameters.txt); cpu frequency: the cpufreq governor;
- rtprio and memlock: ``getrlimit`` and ``CapEff`` of ``/proc/self/status`` (with CAP_SYS_NICE,
  CAP_IPC_LOCK the limits do not apply); realtime: the settings actually applied in a child process
  (:mod:`runtime.wakeups`), whose virtual size is what mlockall weighs against RLIMIT_MEMLOCK;
- config and eds: :func:`runtime.config.load_config`, ``canopen.import_od``;
- can: ``ip -details -json link show dev CHANNEL`` for SocketCAN (link type, UP, bitrate,
  txqlen, controller state and restart-ms); other python-can interfaces are opened and closed;
- modbus: a trial bind of ``modbus.bind:port``, and the allowlist and watchdog of the config;
- shared memory: a 1 MiB POSIX shared-memory block created and removed;
- latency: :func:`runtime.wakeups.run_wakeup_test` with the configured period and real-time
  settings, judged against the period and ``cycle.overrun_limit``.

Structure: :func:`read_host` reads /proc, /sys and the process limits once into
:class:`HostFacts`; every ``check_*`` function is pure (facts, text and configuration in,
:class:`Check` records out), so tests give them fake file contents and ``ip`` outputs; the
functions that try something (bind, open, create) return what went wrong, or None.

Not done here: changing anything. The doctor reads and tries; every fix is for the operator.
"""

from __future__ import annotations

import argparse
import errno
import ipaddress
import json
import os
import platform
import resource
import shutil
import socket
import subprocess
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from multiprocessing import shared_memory
from pathlib import Path

from runtime.config import (
    SHIPPED_CONFIGS_DIR,
    AxisConfig,
    CanConfig,
    CycleConfig,
    MachineConfig,
    ModbusConfig,
    RealtimeConfig,
    load_config,
)
from runtime.errors import ConfigError
from runtime.version import VERSION
from runtime.wakeups import WakeupResult, run_wakeup_test

#: Seconds of the latency test unless ``--latency-s`` says otherwise.
DEFAULT_LATENCY_S = 10.0
#: Linux capability numbers (linux/capability.h).
CAP_NET_BIND_SERVICE = 10
CAP_IPC_LOCK = 14
CAP_SYS_NICE = 23
#: Clocksources that cost microseconds per read or tick coarsely (a TSC the kernel rejected).
SLOW_CLOCKSOURCES = frozenset({"hpet", "acpi_pm", "jiffies", "refined-jiffies", "pit"})
#: Below this queue length a slow or disturbed bus makes sends fail with ENOBUFS at once
#: (SocketCAN's default is 10 frames).
MIN_TXQUEUELEN = 100
#: p99 lateness above this fraction of the period is SYNC jitter the drives see.
JITTER_WARN_FRACTION = 0.1
SHARED_MEMORY_TEST_BYTES = 1 << 20
DOCS = "docs/deployment.md"
REALTIME_FIX = (
    "a PREEMPT_RT kernel (linux-image-rt-amd64), the cycle's CPU isolated "
    f"(isolcpus, nohz_full, irqaffinity) and cycle.realtime.cpu set to it; see {DOCS}"
)
STOLEN_FIX = (
    "this is a virtual machine whose host took its CPUs away (steal time): give it dedicated, "
    "pinned CPUs, or run the machine on bare metal"
)


class Verdict(Enum):
    """How one check came out."""

    OK = "ok"
    WARN = "warn"
    FAIL = "fail"


@dataclass(frozen=True)
class Check:
    """One line of the report: what was checked, how it came out, and the fix if not ok."""

    name: str
    verdict: Verdict
    detail: str
    fix: str = ""

    def line(self) -> str:
        text = f"{self.verdict.value:<4}  {self.name:<14} {self.detail}"
        return f"{text}; fix: {self.fix}" if self.fix else text


def _ok(name: str, detail: str) -> Check:
    return Check(name, Verdict.OK, detail)


def _warn(name: str, detail: str, fix: str) -> Check:
    return Check(name, Verdict.WARN, detail, fix)


def _fail(name: str, detail: str, fix: str) -> Check:
    return Check(name, Verdict.FAIL, detail, fix)


# -- what the host is ----------------------------------------------------------------------


@dataclass(frozen=True)
class HostFacts:
    """What the checks read from the kernel and the process, read once by :func:`read_host`."""

    kernel_release: str
    kernel_version: str
    """``uname -v``: names PREEMPT_RT, PREEMPT_DYNAMIC, PREEMPT."""
    realtime_flag: str | None
    """/sys/kernel/realtime ("1" on PREEMPT_RT), None where absent."""
    cmdline: str
    clock_resolution_s: float
    clocksource: str | None
    cpu_count: int
    governors: Mapping[int, str]
    """cpufreq scaling governor by CPU; empty where the kernel exposes none."""
    proc_status: str
    """/proc/self/status (CapEff)."""
    rtprio_limit: int
    """Soft RLIMIT_RTPRIO."""
    memlock_limit_bytes: int
    """Soft RLIMIT_MEMLOCK; ``resource.RLIM_INFINITY`` when unlimited."""


def _read_text(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def read_host(root: Path = Path("/")) -> HostFacts:
    """Read the facts the checks need; ``root`` prefixes /proc and /sys (tests use a fake tree)."""
    cpu_dir = root / "sys/devices/system/cpu"
    governors = {}
    for path in cpu_dir.glob("cpu[0-9]*/cpufreq/scaling_governor"):
        governor = _read_text(path)
        if governor is not None:
            governors[int(path.parts[-3][3:])] = governor
    uname = os.uname()
    return HostFacts(
        kernel_release=uname.release,
        kernel_version=uname.version,
        realtime_flag=_read_text(root / "sys/kernel/realtime"),
        cmdline=_read_text(root / "proc/cmdline") or "",
        clock_resolution_s=time.clock_getres(time.CLOCK_MONOTONIC),
        clocksource=_read_text(
            root / "sys/devices/system/clocksource/clocksource0/current_clocksource"
        ),
        cpu_count=os.cpu_count() or 1,
        governors=governors,
        proc_status=_read_text(root / "proc/self/status") or "",
        rtprio_limit=resource.getrlimit(resource.RLIMIT_RTPRIO)[0],
        memlock_limit_bytes=resource.getrlimit(resource.RLIMIT_MEMLOCK)[0],
    )


def kernel_parameters(cmdline: str) -> dict[str, str]:
    """``name=value`` words of a kernel command line (a bare word maps to ""); last one wins."""
    parameters = {}
    for word in cmdline.split():
        if word == "--":
            break
        name, _, value = word.partition("=")
        parameters[name] = value
    return parameters


def cpu_list(text: str, cpu_count: int) -> frozenset[int]:
    """CPUs of a kernel cpu list (``0-2,5``, ``N`` for the last CPU); flag words such as
    isolcpus' ``domain,managed_irq`` are skipped."""
    cpus: set[int] = set()
    for item in text.split(","):
        first, _, last = item.replace("N", str(cpu_count - 1)).partition("-")
        if first.isdigit() and (not last or last.isdigit()):
            cpus.update(range(int(first), int(last or first) + 1))
    return frozenset(cpus)


def format_cpus(cpus: Sequence[int] | frozenset[int]) -> str:
    """A kernel cpu list for ``cpus`` (``0-2,5``)."""
    ordered = sorted(cpus)
    ranges: list[str] = []
    start = previous = None
    for cpu in [*ordered, None]:
        if cpu is not None and previous is not None and cpu == previous + 1:
            previous = cpu
            continue
        if start is not None:
            ranges.append(str(start) if start == previous else f"{start}-{previous}")
        start = previous = cpu
    return ",".join(ranges)


def effective_capabilities(proc_status: str) -> int:
    """The CapEff mask of a /proc/PID/status text (0 when absent)."""
    for line in proc_status.splitlines():
        if line.startswith("CapEff:"):
            return int(line.split()[1], 16)
    return 0


def _has_capability(facts: HostFacts, capability: int) -> bool:
    return bool(effective_capabilities(facts.proc_status) >> capability & 1)


def _mib(kib: int) -> str:
    return f"{kib / 1024:.0f} MiB"


# -- checks of the host ----------------------------------------------------------------------


def check_kernel(facts: HostFacts) -> Check:
    """PREEMPT_RT or not."""
    preemption = next(
        (word for word in facts.kernel_version.split() if word.startswith("PREEMPT")), "no PREEMPT"
    )
    if facts.realtime_flag == "1" or "PREEMPT_RT" in facts.kernel_version.split():
        return _ok("kernel", f"{facts.kernel_release} PREEMPT_RT")
    return _warn(
        "kernel",
        f"{facts.kernel_release} {preemption}, not PREEMPT_RT: wake-up tails of milliseconds",
        "apt install linux-image-rt-amd64 and reboot into it",
    )


def check_timer(facts: HostFacts) -> Check:
    """High-resolution timers and a fast clocksource."""
    resolution_us = facts.clock_resolution_s * 1e6
    if resolution_us > 1.0:
        return _fail(
            "timer",
            f"CLOCK_MONOTONIC resolution {resolution_us:g} us: no high-resolution timers, "
            "every sleep ends on a scheduler tick",
            "boot a kernel with high-resolution timers (Debian's have them) without highres=off",
        )
    source = facts.clocksource or "unknown"
    if source in SLOW_CLOCKSOURCES:
        return _warn(
            "timer",
            f"high-resolution, clocksource {source}: each clock read costs microseconds",
            "find why the TSC was rejected (dmesg | grep -i clocksource); enable the invariant "
            "TSC in the BIOS",
        )
    return _ok("timer", f"high-resolution ({resolution_us * 1e3:g} ns), clocksource {source}")


def check_cpu_pinning(facts: HostFacts, realtime: RealtimeConfig) -> Check:
    """cycle.realtime.cpu set and present."""
    if realtime.cpu is None:
        return _warn(
            "cpu pinning",
            "cycle.realtime.cpu not set: the cycle process shares every CPU",
            "set cycle.realtime.cpu to a CPU isolated for it",
        )
    if realtime.cpu >= facts.cpu_count:
        return _fail(
            "cpu pinning",
            f"cycle.realtime.cpu = {realtime.cpu}, but this machine has CPUs "
            f"{format_cpus(range(facts.cpu_count))}",
            "choose one of them",
        )
    return _ok("cpu pinning", f"the cycle process runs on CPU {realtime.cpu}")


def check_cpu_isolation(facts: HostFacts, realtime: RealtimeConfig) -> Check:
    """isolcpus, nohz_full and irqaffinity on the kernel command line, for the cycle's CPU."""
    parameters = kernel_parameters(facts.cmdline)
    isolated = cpu_list(parameters.get("isolcpus", ""), facts.cpu_count)
    tickless = cpu_list(parameters.get("nohz_full", ""), facts.cpu_count)
    irq_cpus = (
        cpu_list(parameters["irqaffinity"], facts.cpu_count)
        if "irqaffinity" in parameters
        else None
    )
    cpu = realtime.cpu
    if cpu is None:
        if isolated:
            return _warn(
                "cpu isolation",
                f"isolcpus={format_cpus(isolated)}, but cycle.realtime.cpu is not set",
                f"set cycle.realtime.cpu: {min(isolated)}",
            )
        suggested = facts.cpu_count - 1
        return _warn(
            "cpu isolation",
            "no CPU isolated for the cycle",
            f"add {_isolation(suggested, facts.cpu_count)} to GRUB_CMDLINE_LINUX in "
            f"/etc/default/grub, update-grub, reboot; set cycle.realtime.cpu: {suggested}",
        )
    missing = [
        text
        for text, bad in (
            (f"CPU {cpu} not in isolcpus", cpu not in isolated),
            ("not in nohz_full", cpu not in tickless),
            (
                "irqaffinity not set" if irq_cpus is None else f"irqaffinity includes CPU {cpu}",
                irq_cpus is None or cpu in irq_cpus,
            ),
        )
        if bad
    ]
    wanted = _isolation(cpu, facts.cpu_count)
    if missing:
        return _warn(
            "cpu isolation",
            ", ".join(missing) + ": other tasks and interrupts can delay the cycle",
            f"add {wanted} to GRUB_CMDLINE_LINUX in /etc/default/grub, update-grub, reboot",
        )
    return _ok("cpu isolation", wanted)


def _isolation(cpu: int, cpu_count: int) -> str:
    """The kernel parameters that isolate ``cpu`` for the cycle."""
    others = format_cpus(set(range(cpu_count)) - {cpu}) or "0"
    return f"isolcpus={cpu} nohz_full={cpu} irqaffinity={others}"


def check_cpu_frequency(facts: HostFacts, realtime: RealtimeConfig) -> Check:
    """The cpufreq governor of the cycle's CPU (of every CPU when unpinned)."""
    cpus = [realtime.cpu] if realtime.cpu is not None else sorted(facts.governors)
    slow = {
        cpu: facts.governors[cpu]
        for cpu in cpus
        if facts.governors.get(cpu, "performance") != "performance"
    }
    if not facts.governors:
        return _ok("cpu frequency", "no frequency scaling exposed by the kernel")
    if slow:
        listed = ", ".join(f"CPU {cpu} {governor}" for cpu, governor in sorted(slow.items()))
        return _warn(
            "cpu frequency",
            f"{listed}: clock changes and deep idle states add wake-up latency",
            "cpupower frequency-set -g performance (Debian package linux-cpupower)",
        )
    return _ok("cpu frequency", "governor performance")


def check_rtprio(facts: HostFacts, realtime: RealtimeConfig) -> Check:
    """RLIMIT_RTPRIO (or CAP_SYS_NICE) against cycle.realtime.priority."""
    priority = realtime.priority
    if priority == 0:
        return _warn(
            "rtprio",
            "cycle.realtime.priority 0: the cycle runs under the normal scheduler",
            "set cycle.realtime.priority: 80",
        )
    if _has_capability(facts, CAP_SYS_NICE):
        return _ok("rtprio", f"CAP_SYS_NICE: SCHED_FIFO {priority} allowed")
    if facts.rtprio_limit >= priority:
        return _ok("rtprio", f"RLIMIT_RTPRIO {facts.rtprio_limit} >= priority {priority}")
    return _fail(
        "rtprio",
        f"RLIMIT_RTPRIO {facts.rtprio_limit} < cycle.realtime.priority {priority} and no "
        "CAP_SYS_NICE: SCHED_FIFO is refused",
        f"LimitRTPRIO={priority} and AmbientCapabilities=CAP_SYS_NICE in the service "
        "(deploy/softmotion.service has both)",
    )


def check_memlock(facts: HostFacts, realtime: RealtimeConfig, test: WakeupResult | str) -> Check:
    """RLIMIT_MEMLOCK (or CAP_IPC_LOCK) against the process size mlockall must cover.

    ``test`` is the wake-up test's result (or why it failed): without CAP_IPC_LOCK,
    mlockall(MCL_CURRENT) needs the limit above the test process's whole virtual size, and with
    MCL_FUTURE every later mapping too.
    """
    if not realtime.lock_memory:
        return _warn(
            "memlock",
            "cycle.realtime.lock_memory false: page faults can stall the cycle",
            "set cycle.realtime.lock_memory: true",
        )
    if _has_capability(facts, CAP_IPC_LOCK):
        return _ok("memlock", "CAP_IPC_LOCK: no memlock limit applies")
    limit = facts.memlock_limit_bytes
    if limit == resource.RLIM_INFINITY:
        return _ok("memlock", "RLIMIT_MEMLOCK unlimited")
    limit_kib = limit // 1024
    virtual_kib = test.virtual_kib if isinstance(test, WakeupResult) else 0
    fix = "LimitMEMLOCK=infinity and AmbientCapabilities=CAP_IPC_LOCK in the service"
    if limit_kib <= virtual_kib:
        return _fail(
            "memlock",
            f"RLIMIT_MEMLOCK {_mib(limit_kib)} < the test process's virtual size "
            f"{_mib(virtual_kib)}: mlockall is refused",
            fix,
        )
    return _warn(
        "memlock",
        f"RLIMIT_MEMLOCK {_mib(limit_kib)} (test process {_mib(virtual_kib)} virtual): with "
        "memory locked, a mapping past the limit fails",
        fix,
    )


def check_realtime(result: WakeupResult | str, realtime: RealtimeConfig) -> Check:
    """Whether the child process actually got SCHED_FIFO, its CPU and its memory lock
    (``result`` a text: why the test process failed)."""
    if isinstance(result, str):
        return _fail("realtime", result, f"run the test again; see {DOCS}")
    refused = []
    if realtime.priority and result.fifo_priority != realtime.priority:
        refused.append(_report_line(result, "SCHED_FIFO"))
    if realtime.cpu is not None and result.cpus != (realtime.cpu,):
        refused.append(_report_line(result, "CPU affinity"))
    if realtime.lock_memory and result.locked_kib == 0:
        refused.append(_report_line(result, "mlockall"))
    if refused:
        return _fail(
            "realtime",
            "; ".join(refused),
            "LimitRTPRIO, LimitMEMLOCK=infinity and AmbientCapabilities=CAP_SYS_NICE "
            "CAP_IPC_LOCK as in deploy/softmotion.service; a CPU this service may use",
        )
    applied = [f"SCHED_FIFO {result.fifo_priority}" if result.fifo_priority else "normal scheduler"]
    applied.append(f"CPU {realtime.cpu}" if realtime.cpu is not None else "any CPU")
    applied.append(f"mlockall ({_mib(result.locked_kib)})" if result.locked_kib else "no mlockall")
    return _ok("realtime", ", ".join(applied) + ": applied in a test process")


def _report_line(result: WakeupResult, setting: str) -> str:
    return next((line for line in result.report if setting in line), f"{setting} not applied")


def check_latency(result: WakeupResult | str, cycle: CycleConfig, duration_s: float) -> Check:
    """Wake-up lateness against the period: a run of missed periods beyond
    ``cycle.overrun_limit`` stops the machine; SYNC jitter beyond a tenth of the period
    reaches the drives. ``result`` a text: why the test process failed."""
    if isinstance(result, str):
        return _fail("latency", f"not measured: {result}", f"run the test again; see {DOCS}")
    period_us = cycle.period_ms * 1000.0
    p = result.percentiles_us
    detail = (
        f"{result.wakeups} wake-ups in {duration_s:g} s at {cycle.period_ms:g} ms: "
        f"p50 {p['p50']:.1f} us, p99 {p['p99']:.1f} us, max {p['max']:.0f} us "
        f"({p['max'] / period_us:.0%} of the period), {result.missed_periods} periods missed"
    )
    fix = REALTIME_FIX
    if result.steal_ms > 0:
        detail += f"; the hypervisor took {result.steal_ms:.0f} ms of CPU time meanwhile"
        fix = f"{STOLEN_FIX}; {REALTIME_FIX}"
    if result.longest_miss_run > cycle.overrun_limit:
        return _fail(
            "latency",
            f"{detail}, {result.longest_miss_run} in a row: more than cycle.overrun_limit "
            f"{cycle.overrun_limit}, the machine would stop",
            fix,
        )
    if p["p99"] > period_us / 2:
        return _fail("latency", f"{detail}: more than 1 % of the periods missed", fix)
    if result.missed_periods:
        return _warn("latency", f"{detail}: some periods missed", fix)
    if p["p99"] > period_us * JITTER_WARN_FRACTION:
        return _warn("latency", f"{detail}: the drives see that SYNC jitter", fix)
    return _ok("latency", detail)


# -- checks of the configuration -------------------------------------------------------------


def check_config(config: MachineConfig) -> Check:
    """The configuration loaded; what it describes."""
    axes = ", ".join(f"{axis.name} node {axis.node_id}" for axis in config.axes)
    drives = "simulated drives" if config.simulation.drives else "real drives"
    return _ok(
        "config",
        f"{config.source}: {axes}; {drives} on {config.can.interface} {config.can.channel}; "
        f"period {config.cycle.period_ms:g} ms",
    )


def check_config_error(path: Path, error: ConfigError) -> Check:
    return _fail(
        "config",
        f"{path}: {error}",
        f"correct the key it names; {SHIPPED_CONFIGS_DIR / 'ipc-example.yaml'} lists every key",
    )


def read_eds_problem(path: Path) -> str | None:
    """Why the EDS file at ``path`` cannot be used, or None."""
    import canopen

    try:
        canopen.import_od(str(path))
    except OSError as exc:
        return f"cannot read it ({exc.strerror})"
    except Exception as exc:  # canopen raises what its parsers raise
        return f"not a valid EDS ({type(exc).__name__}: {exc})"
    return None


def check_eds(axes: Sequence[AxisConfig], problems: Mapping[Path, str | None]) -> Check:
    """The axes' EDS files; ``problems`` maps each configured path to why it cannot be used."""
    configured = [(i, axis) for i, axis in enumerate(axes) if axis.eds is not None]
    if not configured:
        return _ok("eds", "none configured: the built-in CiA 402 object dictionary is used")
    failed = [
        f"axes[{i}].eds = {axis.eds}: {problems[axis.eds]}"
        for i, axis in configured
        if problems.get(axis.eds)
    ]
    if failed:
        return _fail(
            "eds",
            "; ".join(failed),
            "a relative path is read from the configuration file's directory",
        )
    return _ok("eds", ", ".join(f"{axis.name} {axis.eds}" for _, axis in configured))


def read_can_link(channel: str) -> tuple[str | None, str]:
    """``ip -details -json link show dev CHANNEL``: (stdout, stderr), stdout None on failure
    or where ``ip`` is missing (then stderr says so)."""
    ip = shutil.which("ip") or shutil.which("ip", path="/usr/sbin:/sbin")
    if ip is None:
        return None, "the ip command (iproute2) is not installed"
    done = subprocess.run(
        [ip, "-details", "-json", "link", "show", "dev", channel],
        capture_output=True,
        text=True,
        check=False,
    )
    return (done.stdout if done.returncode == 0 else None), done.stderr.strip()


def _link_fix(channel: str, bitrate: int, kind: str) -> str:
    if kind == "vcan":
        return f"ip link set {channel} up"
    return (
        f"ip link set {channel} down; ip link set {channel} type can bitrate {bitrate} "
        f"restart-ms 100; ip link set {channel} txqueuelen 1000 up"
    )


def check_can_link(can: CanConfig, ip_output: str | None, ip_error: str) -> list[Check]:
    """A SocketCAN link from ``ip -details -json link show dev CHANNEL``: exists and is up,
    bitrate, txqueuelen, controller state. ``ip_output`` None: ``ip`` failed with ``ip_error``."""
    channel = can.channel
    is_vcan_name = channel.startswith("vcan")
    if ip_output is None:
        if "not installed" in ip_error:
            return [_warn("can link", f"{channel}: {ip_error}", "apt install iproute2")]
        create = (
            f"modprobe vcan; ip link add dev {channel} type vcan; ip link set {channel} up"
            if is_vcan_name
            else "connect the adapter and load its driver (dmesg | grep -i can; "
            "ip -brief link show type can lists CAN links), or correct can.channel"
        )
        return [_fail("can link", f"no interface {channel} ({ip_error or 'ip failed'})", create)]
    try:
        link = json.loads(ip_output)[0]
    except (ValueError, IndexError, KeyError) as exc:
        return [_warn("can link", f"{channel}: unreadable ip output ({exc})", "ip -details link")]
    info = link.get("linkinfo", {})
    kind = info.get("info_kind", "")
    data = info.get("info_data", {})
    if link.get("link_type") != "can":
        return [
            _fail(
                "can link",
                f"{channel} is not a CAN link (link type {link.get('link_type')})",
                "correct can.channel (ip -brief link show type can lists CAN links)",
            )
        ]
    if "UP" not in link.get("flags", []):
        return [
            _fail("can link", f"{channel} ({kind}) is down", _link_fix(channel, can.bitrate, kind))
        ]
    checks = [_ok("can link", f"{channel} ({kind}) is up")]
    if kind == "vcan":
        checks.append(_ok("can bitrate", "virtual CAN: no bitrate"))
    else:
        bitrate = data.get("bittiming", {}).get("bitrate")
        if bitrate != can.bitrate:
            checks.append(
                _fail(
                    "can bitrate",
                    f"{channel} runs at {bitrate} bit/s, can.bitrate is {can.bitrate}",
                    _link_fix(channel, can.bitrate, kind),
                )
            )
        else:
            sample_point = data.get("bittiming", {}).get("sample_point")
            checks.append(_ok("can bitrate", f"{bitrate} bit/s, sample point {sample_point}"))
    txqlen = link.get("txqlen", 0)
    if txqlen < MIN_TXQUEUELEN:
        checks.append(
            _warn(
                "can txqueuelen",
                f"{txqlen} frames: a slow or disturbed bus makes sends fail with ENOBUFS at once",
                f"ip link set {channel} txqueuelen 1000",
            )
        )
    else:
        checks.append(_ok("can txqueuelen", f"{txqlen} frames"))
    checks.append(_check_can_state(channel, kind, data))
    return checks


def _check_can_state(channel: str, kind: str, data: Mapping) -> Check:
    if kind == "vcan":
        return _ok("can state", "virtual CAN: no controller")
    state = data.get("state", "unknown")
    counters = data.get("berr_counter", {})
    errors = f"error counters tx {counters.get('tx', '?')} rx {counters.get('rx', '?')}"
    wiring = "check termination (120 ohm at both ends), wiring and every node's bitrate"
    if state in ("BUS-OFF", "STOPPED"):
        return _fail(
            "can state",
            f"{state}, {errors}",
            f"{wiring}; ip link set {channel} type can restart",
        )
    if state != "ERROR-ACTIVE":
        return _warn("can state", f"{state}, {errors}", wiring)
    if data.get("restart_ms", 0) == 0:
        return _warn(
            "can state",
            f"{state}, restart-ms 0: after a bus-off the link stays off until restarted by hand",
            f"ip link set {channel} type can restart-ms 100 (with the link down)",
        )
    return _ok("can state", f"{state}, {errors}, restart-ms {data['restart_ms']}")


def open_bus_problem(can: CanConfig) -> str | None:
    """Open and close the configured python-can bus; why it failed, or None."""
    from drives.bus import open_bus
    from drives.errors import BusUnavailable

    try:
        open_bus(can.interface, can.channel, can.bitrate).shutdown()
    except BusUnavailable as exc:
        return str(exc)
    return None


def check_can_bus(can: CanConfig, problem: str | None) -> Check:
    """A python-can interface other than SocketCAN, opened and closed (``problem`` if not)."""
    if problem is not None:
        return _fail(
            "can link",
            problem,
            f"install the {can.interface} driver and library python-can needs, connect the "
            "adapter, check can.channel, stop a running softmotion (an adapter opens once); "
            f"on Linux most adapters also work as SocketCAN (see {DOCS})",
        )
    return _ok("can link", f"{can.interface} {can.channel} opened at {can.bitrate} bit/s")


def check_can(can: CanConfig) -> list[Check]:
    """The configured CAN bus, by interface."""
    if can.interface == "virtual":
        return [_ok("can link", f"python-can virtual bus {can.channel}: in-process simulation")]
    if can.interface == "socketcan":
        return check_can_link(can, *read_can_link(can.channel))
    return [check_can_bus(can, open_bus_problem(can))]


def bind_problem(modbus: ModbusConfig) -> OSError | None:
    """Bind (and close) a TCP socket on the Modbus address and port; the error, or None."""
    family = socket.AF_INET6 if ipaddress.ip_address(modbus.bind).version == 6 else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((modbus.bind, modbus.port))
    except OSError as exc:
        return exc
    return None


def check_modbus_port(modbus: ModbusConfig, problem: OSError | None) -> Check:
    """The Modbus server's address and port can be bound."""
    if not modbus.enabled:
        return _ok("modbus port", "Modbus server disabled (modbus.enabled false)")
    where = f"{modbus.bind}:{modbus.port}"
    privileged = modbus.port < 1024
    if problem is None:
        note = (
            "; below 1024: the service needs CAP_NET_BIND_SERVICE "
            "(deploy/softmotion.service.d/modbus-port-below-1024.conf)"
            if privileged
            else ""
        )
        return _ok("modbus port", f"{where} free{note}")
    if problem.errno == errno.EADDRINUSE:
        return _fail(
            "modbus port",
            f"{where} in use",
            f"stop what listens there (ss -ltnp 'sport = :{modbus.port}'; softmotion itself?) "
            "or change modbus.port",
        )
    if problem.errno == errno.EACCES and privileged:
        return _fail(
            "modbus port",
            f"{where}: port below 1024 needs CAP_NET_BIND_SERVICE",
            "install deploy/softmotion.service.d/modbus-port-below-1024.conf, or use a port "
            ">= 1024 (1502)",
        )
    if problem.errno == errno.EADDRNOTAVAIL:
        return _fail(
            "modbus port",
            f"{where}: no interface of this machine has address {modbus.bind}",
            "set modbus.bind to one of this machine's addresses (ip -brief address) or 0.0.0.0",
        )
    return _fail("modbus port", f"{where}: {problem.strerror}", "check modbus.bind and port")


def check_modbus_access(modbus: ModbusConfig) -> Check:
    """Who may connect (modbus.allowed_networks against modbus.bind) and the HMI watchdog."""
    if not modbus.enabled:
        return _ok("modbus access", "Modbus server disabled")
    networks = [ipaddress.ip_network(n, strict=False) for n in modbus.allowed_networks]
    listed = ", ".join(modbus.allowed_networks)
    bind = ipaddress.ip_address(modbus.bind)
    if any(network.prefixlen == 0 for network in networks):
        return _warn(
            "modbus access",
            f"allowed_networks {listed}: any host may command the machine",
            "list only the HMI panels' network in modbus.allowed_networks",
        )
    remote = [str(network) for network in networks if not network.is_loopback]
    if bind.is_loopback and remote:
        return _warn(
            "modbus access",
            f"bind {modbus.bind}: clients from {', '.join(remote)} cannot reach it",
            "set modbus.bind to the panels' side address or 0.0.0.0",
        )
    if not bind.is_loopback and not remote:
        return _warn(
            "modbus access",
            f"listens on {modbus.bind} but allows only {listed}",
            "add the HMI panels' network to modbus.allowed_networks, or bind 127.0.0.1",
        )
    watchdog_ms = modbus.watchdog.timeout_ms
    if remote and not modbus.read_only and watchdog_ms == 0:
        return _warn(
            "modbus access",
            f"clients from {listed}, HMI watchdog off: a panel that loses its link leaves the "
            "machine moving",
            "modbus.watchdog.timeout_ms: 3000",
        )
    watchdog = (
        f"watchdog {watchdog_ms} ms ({modbus.watchdog.action})" if watchdog_ms else "no watchdog"
    )
    mode = "read-only" if modbus.read_only else "read-write"
    return _ok("modbus access", f"clients from {listed}, {mode}, {watchdog}")


def shared_memory_problem() -> OSError | None:
    """Create and remove a POSIX shared-memory block; the error, or None."""
    try:
        block = shared_memory.SharedMemory(create=True, size=SHARED_MEMORY_TEST_BYTES)
    except OSError as exc:
        return exc
    block.close()
    block.unlink()
    return None


def check_shared_memory(problem: OSError | None) -> Check:
    """The processes of the runtime exchange setpoints and status through shared memory."""
    if problem is not None:
        return _fail(
            "shared memory",
            f"cannot create a POSIX shared-memory block: {problem}",
            "mount a tmpfs on /dev/shm (systemd does by default) with room to spare",
        )
    return _ok("shared memory", "POSIX shared memory (/dev/shm) usable")


# -- the report ------------------------------------------------------------------------------


def diagnose(config_path: Path, latency_s: float, facts: HostFacts | None = None) -> list[Check]:
    """Every check for the configuration at ``config_path`` on this machine, in report order."""
    facts = facts or read_host()
    checks = [check_kernel(facts), check_timer(facts)]
    try:
        config = load_config(config_path)
    except ConfigError as exc:
        return [*checks, check_config_error(config_path, exc)]
    realtime = config.cycle.realtime
    try:
        result: WakeupResult | str = run_wakeup_test(realtime, config.cycle.period_s, latency_s)
    except Exception as exc:  # the child died or hung: that is the finding
        result = f"the test process failed: {type(exc).__name__}: {exc}"
    eds_problems = {axis.eds: read_eds_problem(axis.eds) for axis in config.axes if axis.eds}
    return [
        *checks,
        check_cpu_pinning(facts, realtime),
        check_cpu_isolation(facts, realtime),
        check_cpu_frequency(facts, realtime),
        check_rtprio(facts, realtime),
        check_memlock(facts, realtime, result),
        check_realtime(result, realtime),
        check_config(config),
        check_eds(config.axes, eds_problems),
        *check_can(config.can),
        check_modbus_port(
            config.modbus, bind_problem(config.modbus) if config.modbus.enabled else None
        ),
        check_modbus_access(config.modbus),
        check_shared_memory(shared_memory_problem()),
        check_latency(result, config.cycle, latency_s),
    ]


def summary(checks: Sequence[Check]) -> str:
    counts = {verdict: sum(c.verdict is verdict for c in checks) for verdict in Verdict}
    return ", ".join(f"{count} {verdict.value}" for verdict, count in counts.items())


def exit_status(checks: Sequence[Check]) -> int:
    """0 when no check failed, 1 otherwise."""
    return int(any(check.verdict is Verdict.FAIL for check in checks))


def _positive_seconds(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"--latency-s {text}: must be > 0")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the doctor's options to ``parser`` (``--config`` comes from the command line)."""
    parser.add_argument(
        "--latency-s",
        type=_positive_seconds,
        default=DEFAULT_LATENCY_S,
        metavar="S",
        help=f"length of the wake-up latency test (default {DEFAULT_LATENCY_S:g} s)",
    )


def run(args: argparse.Namespace) -> int:
    """Print the report for ``args.config``; return the exit status."""
    print(
        f"softmotion {VERSION} doctor: {args.config} on {platform.node()}, "
        f"Python {platform.python_version()}, latency test {args.latency_s:g} s",
        flush=True,
    )
    checks = diagnose(args.config, args.latency_s)
    for check in checks:
        print(check.line())
    print(f"doctor: {summary(checks)}")
    return exit_status(checks)
