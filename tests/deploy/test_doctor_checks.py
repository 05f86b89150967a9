"""The doctor's checks on fake /proc, /sys, limits and ``ip -details -json link`` outputs."""

from __future__ import annotations

import errno
import json
import os
import resource
from dataclasses import replace
from pathlib import Path

import pytest

from runtime.config import (
    SHIPPED_CONFIGS_DIR,
    AxisConfig,
    CanConfig,
    CycleConfig,
    ModbusConfig,
    RealtimeConfig,
    WatchdogConfig,
)
from runtime.doctor import (
    CAP_IPC_LOCK,
    CAP_SYS_NICE,
    Check,
    HostFacts,
    Verdict,
    check_can_link,
    check_cpu_frequency,
    check_cpu_isolation,
    check_cpu_pinning,
    check_eds,
    check_kernel,
    check_latency,
    check_memlock,
    check_modbus_access,
    check_modbus_port,
    check_realtime,
    check_rtprio,
    check_timer,
    cpu_list,
    exit_status,
    format_cpus,
    read_eds_problem,
    read_host,
)
from runtime.wakeups import WakeupResult, host_steal_s

PINNED = RealtimeConfig(priority=80, cpu=3)
RT_VERSION = "#1 SMP PREEMPT_RT Debian 6.1.119-1 (2024-11-22)"
STOCK_VERSION = "#1 SMP PREEMPT_DYNAMIC Debian 6.1.119-1 (2024-11-22)"


def facts(**changes: object) -> HostFacts:
    """A tuned 4-CPU PREEMPT_RT host, changed by ``changes``."""
    base = HostFacts(
        kernel_release="6.1.0-28-rt-amd64",
        kernel_version=RT_VERSION,
        realtime_flag="1",
        cmdline="BOOT_IMAGE=/vmlinuz ro quiet isolcpus=3 nohz_full=3 irqaffinity=0-2",
        clock_resolution_s=1e-9,
        clocksource="tsc",
        cpu_count=4,
        governors={0: "performance", 1: "performance", 2: "performance", 3: "performance"},
        proc_status="Name:\tpython3\nCapEff:\t0000000000000000\n",
        rtprio_limit=99,
        memlock_limit_bytes=resource.RLIM_INFINITY,
    )
    return replace(base, **changes)


def status_with_capabilities(*capabilities: int) -> str:
    mask = sum(1 << cap for cap in capabilities)
    return f"Name:\tpython3\nCapEff:\t{mask:016x}\n"


def test_read_host_reads_a_fake_proc_and_sys_tree(tmp_path: Path) -> None:
    files = {
        "sys/kernel/realtime": "1\n",
        "proc/cmdline": "ro isolcpus=domain,managed_irq,2-3 nohz_full=2-3\n",
        "proc/self/status": status_with_capabilities(CAP_SYS_NICE),
        "sys/devices/system/clocksource/clocksource0/current_clocksource": "hpet\n",
        "sys/devices/system/cpu/cpu0/cpufreq/scaling_governor": "performance\n",
        "sys/devices/system/cpu/cpu3/cpufreq/scaling_governor": "powersave\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    host = read_host(tmp_path)
    assert host.realtime_flag == "1"
    assert host.clocksource == "hpet"
    assert host.governors == {0: "performance", 3: "powersave"}
    assert host.cmdline.startswith("ro isolcpus=")
    assert check_kernel(replace(host, kernel_version=STOCK_VERSION)).verdict is Verdict.OK
    assert check_timer(host).verdict is Verdict.WARN
    assert check_rtprio(host, PINNED).verdict is Verdict.OK


def test_missing_files_read_as_absent(tmp_path: Path) -> None:
    host = read_host(tmp_path)
    assert (host.realtime_flag, host.clocksource, host.cmdline, host.governors) == (
        None,
        None,
        "",
        {},
    )


def test_cpu_lists() -> None:
    assert cpu_list("domain,managed_irq,2-3,5", 8) == {2, 3, 5}
    assert cpu_list("1-N", 4) == {1, 2, 3}
    assert cpu_list("", 4) == frozenset()
    assert format_cpus({0, 1, 2, 5, 7, 8}) == "0-2,5,7-8"
    assert format_cpus(range(1)) == "0"


def test_kernel_names_its_preemption_and_the_rt_package() -> None:
    assert check_kernel(facts()) == Check("kernel", Verdict.OK, "6.1.0-28-rt-amd64 PREEMPT_RT")
    stock = check_kernel(facts(kernel_version=STOCK_VERSION, realtime_flag=None))
    assert stock.verdict is Verdict.WARN
    assert "PREEMPT_DYNAMIC, not PREEMPT_RT" in stock.detail
    assert "linux-image-rt-amd64" in stock.fix


def test_timer_without_high_resolution_fails() -> None:
    coarse = check_timer(facts(clock_resolution_s=0.004))
    assert coarse.verdict is Verdict.FAIL and "4000 us" in coarse.detail
    assert check_timer(facts()).detail == "high-resolution (1 ns), clocksource tsc"


def test_isolation_of_the_cycle_cpu() -> None:
    assert check_cpu_isolation(facts(), PINNED) == Check(
        "cpu isolation", Verdict.OK, "isolcpus=3 nohz_full=3 irqaffinity=0-2"
    )
    bare = check_cpu_isolation(facts(cmdline="ro quiet"), PINNED)
    assert bare.verdict is Verdict.WARN
    assert bare.detail.startswith("CPU 3 not in isolcpus, not in nohz_full, irqaffinity not set")
    assert "isolcpus=3 nohz_full=3 irqaffinity=0-2" in bare.fix
    irq_on_it = check_cpu_isolation(facts(cmdline="isolcpus=3 nohz_full=3 irqaffinity=0-3"), PINNED)
    assert irq_on_it.detail.startswith("irqaffinity includes CPU 3")
    unpinned = check_cpu_isolation(facts(), RealtimeConfig(cpu=None))
    assert unpinned.verdict is Verdict.WARN and unpinned.fix == "set cycle.realtime.cpu: 3"


def test_pinning_to_a_cpu_the_machine_lacks_fails() -> None:
    assert check_cpu_pinning(facts(), PINNED).verdict is Verdict.OK
    missing = check_cpu_pinning(facts(cpu_count=2), PINNED)
    assert missing.verdict is Verdict.FAIL
    assert "cycle.realtime.cpu = 3, but this machine has CPUs 0-1" in missing.detail
    assert check_cpu_pinning(facts(), RealtimeConfig(cpu=None)).verdict is Verdict.WARN


def test_governor_of_the_cycle_cpu() -> None:
    slow = facts(governors={0: "powersave", 3: "schedutil"})
    warned = check_cpu_frequency(slow, PINNED)
    assert warned.verdict is Verdict.WARN and warned.detail.startswith("CPU 3 schedutil")
    assert check_cpu_frequency(facts(governors={}), PINNED).verdict is Verdict.OK


def test_rtprio_needs_the_limit_or_cap_sys_nice() -> None:
    refused = check_rtprio(facts(rtprio_limit=0), PINNED)
    assert refused.verdict is Verdict.FAIL
    assert refused.detail.startswith("RLIMIT_RTPRIO 0 < cycle.realtime.priority 80")
    assert "LimitRTPRIO=80" in refused.fix
    capable = facts(rtprio_limit=0, proc_status=status_with_capabilities(CAP_SYS_NICE))
    assert check_rtprio(capable, PINNED).verdict is Verdict.OK
    assert check_rtprio(facts(), RealtimeConfig(priority=0)).verdict is Verdict.WARN


def test_memlock_against_the_test_process_size() -> None:
    result = wakeup_result(virtual_kib=300 * 1024)
    small = check_memlock(facts(memlock_limit_bytes=8 << 20), PINNED, result)
    assert small.verdict is Verdict.FAIL
    assert "RLIMIT_MEMLOCK 8 MiB < the test process's virtual size 300 MiB" in small.detail
    assert "LimitMEMLOCK=infinity" in small.fix
    assert check_memlock(facts(memlock_limit_bytes=1 << 30), PINNED, result).verdict is (
        Verdict.WARN
    )
    assert check_memlock(facts(), PINNED, result).verdict is Verdict.OK
    capable = facts(memlock_limit_bytes=8 << 20, proc_status=status_with_capabilities(CAP_IPC_LOCK))
    assert check_memlock(capable, PINNED, result).verdict is Verdict.OK


def wakeup_result(**changes: object) -> WakeupResult:
    base = WakeupResult(
        report=(
            "SCHED_FIFO priority 80 applied to the cyclic thread",
            "CPU affinity {3} applied to the cyclic thread",
            "mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT) applied: pages stay resident",
        ),
        fifo_priority=80,
        cpus=(3,),
        locked_kib=150_000,
        virtual_kib=160_000,
        wakeups=2500,
        percentiles_us={"p50": 8.0, "p99": 25.0, "p99.9": 40.0, "max": 60.0},
        missed_periods=0,
        longest_miss_run=0,
    )
    return replace(base, **changes)


def test_realtime_reports_what_the_test_process_was_refused() -> None:
    assert check_realtime(wakeup_result(), PINNED).verdict is Verdict.OK
    refusal = "SCHED_FIFO priority 80 not applied: PermissionError (needs CAP_SYS_NICE)"
    refused = check_realtime(wakeup_result(fifo_priority=None, report=(refusal,)), PINNED)
    assert refused.verdict is Verdict.FAIL and refused.detail == refusal
    unpinned = check_realtime(wakeup_result(cpus=(0, 1, 2)), PINNED)
    assert unpinned.verdict is Verdict.FAIL and "CPU affinity" in unpinned.detail
    crashed = check_realtime("the test process failed: BrokenProcessPool", PINNED)
    assert crashed.verdict is Verdict.FAIL


def test_latency_judged_against_the_period_and_the_overrun_limit() -> None:
    cycle = CycleConfig(period_ms=4.0, overrun_limit=3)
    good = check_latency(wakeup_result(), cycle, 10.0)
    assert good.verdict is Verdict.OK
    assert good.detail == (
        "2500 wake-ups in 10 s at 4 ms: p50 8.0 us, p99 25.0 us, max 60 us "
        "(2% of the period), 0 periods missed"
    )
    jitter = wakeup_result(percentiles_us={"p50": 80.0, "p99": 900.0, "p99.9": 1500, "max": 1900})
    assert check_latency(jitter, cycle, 10.0).verdict is Verdict.WARN
    stall = wakeup_result(missed_periods=4, longest_miss_run=4)
    stalled = check_latency(stall, cycle, 10.0)
    assert stalled.verdict is Verdict.FAIL
    assert "4 in a row: more than cycle.overrun_limit 3" in stalled.detail
    assert check_latency(stall, replace(cycle, overrun_limit=25), 10.0).verdict is Verdict.WARN


def test_latency_on_a_virtual_machine_names_the_stolen_time_and_its_fix() -> None:
    cycle = CycleConfig(period_ms=4.0, overrun_limit=3)
    stolen = check_latency(
        wakeup_result(missed_periods=5, longest_miss_run=5, steal_ms=310.0), cycle, 10.0
    )
    assert stolen.verdict is Verdict.FAIL
    assert "; the hypervisor took 310 ms of CPU time meanwhile, 5 in a row" in stolen.detail
    assert stolen.fix.startswith("this is a virtual machine whose host took its CPUs away")
    assert "PREEMPT_RT" in stolen.fix
    assert "hypervisor" not in check_latency(wakeup_result(), cycle, 10.0).detail


def test_steal_time_is_read_from_proc_stat(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    stat.write_text("cpu  2996330 0 246638 2765946 20853 0 34005 19881 0 0\ncpu0 1 2 3\n")
    assert host_steal_s(stat) == pytest.approx(19881 / os.sysconf("SC_CLK_TCK"))
    stat.write_text("cpu  1 2 3 4\n")
    assert host_steal_s(stat) == 0.0
    assert host_steal_s(tmp_path / "absent") == 0.0


def ip_link(**changes: object) -> str:
    """``ip -details -json link show dev can0`` of a PEAK USB adapter, up at 1 Mbit/s."""
    link = {
        "ifindex": 5,
        "ifname": "can0",
        "flags": ["NOARP", "UP", "LOWER_UP", "ECHO"],
        "mtu": 16,
        "operstate": "UP",
        "txqlen": 1000,
        "link_type": "can",
        "linkinfo": {
            "info_kind": "can",
            "info_data": {
                "state": "ERROR-ACTIVE",
                "berr_counter": {"tx": 0, "rx": 0},
                "restart_ms": 100,
                "bittiming": {"bitrate": 1000000, "sample_point": "0.875", "tq": 12},
            },
        },
    }
    for key, value in changes.items():
        if key in ("state", "restart_ms", "bittiming"):
            link["linkinfo"]["info_data"][key] = value  # type: ignore[index]
        else:
            link[key] = value
    return json.dumps([link])


CAN0 = CanConfig(interface="socketcan", channel="can0", bitrate=1_000_000)


def verdicts(checks: list[Check]) -> dict[str, Verdict]:
    return {check.name: check.verdict for check in checks}


def test_a_healthy_can_link() -> None:
    checks = check_can_link(CAN0, ip_link(), "")
    assert all(check.verdict is Verdict.OK for check in checks), checks
    assert [check.name for check in checks] == [
        "can link",
        "can bitrate",
        "can txqueuelen",
        "can state",
    ]


def test_a_missing_can_interface_fails_with_the_fix() -> None:
    (missing,) = check_can_link(CAN0, None, 'Device "can0" does not exist.')
    assert missing.verdict is Verdict.FAIL
    assert missing.detail == 'no interface can0 (Device "can0" does not exist.)'
    assert "load its driver" in missing.fix
    (vcan,) = check_can_link(replace(CAN0, channel="vcan0"), None, "does not exist")
    assert vcan.fix == "modprobe vcan; ip link add dev vcan0 type vcan; ip link set vcan0 up"


def test_can_link_down_wrong_bitrate_short_queue_and_error_states() -> None:
    (down,) = check_can_link(CAN0, ip_link(flags=["NOARP", "ECHO"]), "")
    assert down.verdict is Verdict.FAIL and "bitrate 1000000 restart-ms 100" in down.fix
    slow = check_can_link(CAN0, ip_link(bittiming={"bitrate": 500000}), "")
    assert verdicts(slow)["can bitrate"] is Verdict.FAIL
    assert "runs at 500000 bit/s, can.bitrate is 1000000" in slow[1].detail
    short = check_can_link(CAN0, ip_link(txqlen=10), "")
    assert verdicts(short)["can txqueuelen"] is Verdict.WARN
    assert verdicts(check_can_link(CAN0, ip_link(state="BUS-OFF"), ""))["can state"] is (
        Verdict.FAIL
    )
    assert verdicts(check_can_link(CAN0, ip_link(state="ERROR-PASSIVE"), ""))["can state"] is (
        Verdict.WARN
    )
    assert verdicts(check_can_link(CAN0, ip_link(restart_ms=0), ""))["can state"] is Verdict.WARN
    (ether,) = check_can_link(CAN0, ip_link(link_type="ether"), "")
    assert ether.verdict is Verdict.FAIL and "not a CAN link" in ether.detail


def test_a_vcan_link_has_no_bitrate_or_controller() -> None:
    vcan = json.dumps(
        [
            {
                "ifname": "vcan0",
                "flags": ["NOARP", "UP", "LOWER_UP"],
                "txqlen": 1000,
                "link_type": "can",
                "linkinfo": {"info_kind": "vcan"},
            }
        ]
    )
    checks = check_can_link(replace(CAN0, channel="vcan0"), vcan, "")
    assert all(check.verdict is Verdict.OK for check in checks)


def test_modbus_port_problems_name_their_fix() -> None:
    modbus = ModbusConfig(bind="0.0.0.0", port=502, allowed_networks=("192.168.10.0/24",))
    in_use = check_modbus_port(modbus, OSError(errno.EADDRINUSE, "Address already in use"))
    assert in_use.verdict is Verdict.FAIL and "ss -ltnp 'sport = :502'" in in_use.fix
    denied = check_modbus_port(modbus, OSError(errno.EACCES, "Permission denied"))
    assert "CAP_NET_BIND_SERVICE" in denied.detail
    assert "modbus-port-below-1024.conf" in denied.fix
    elsewhere = replace(modbus, bind="10.9.8.7")
    absent = check_modbus_port(elsewhere, OSError(errno.EADDRNOTAVAIL, "Cannot assign"))
    assert "no interface of this machine has address 10.9.8.7" in absent.detail
    free = check_modbus_port(modbus, None)
    assert free.verdict is Verdict.OK and "CAP_NET_BIND_SERVICE" in free.detail


def test_modbus_access() -> None:
    panel = ModbusConfig(
        bind="0.0.0.0",
        port=502,
        allowed_networks=("192.168.10.0/24", "127.0.0.0/8"),
        watchdog=WatchdogConfig(timeout_ms=3000),
    )
    assert check_modbus_access(panel).verdict is Verdict.OK
    anyone = check_modbus_access(replace(panel, allowed_networks=("0.0.0.0/0",)))
    assert anyone.verdict is Verdict.WARN and "any host" in anyone.detail
    unreachable = check_modbus_access(replace(panel, bind="127.0.0.1"))
    assert "192.168.10.0/24 cannot reach it" in unreachable.detail
    no_watchdog = check_modbus_access(replace(panel, watchdog=WatchdogConfig()))
    assert no_watchdog.verdict is Verdict.WARN and "watchdog off" in no_watchdog.detail
    assert check_modbus_access(ModbusConfig()).verdict is Verdict.OK


def test_eds_files_readable_and_valid(tmp_path: Path) -> None:
    shipped = SHIPPED_CONFIGS_DIR / "drives" / "softmotion-sim.eds"
    garbage = tmp_path / "garbage.eds"
    garbage.write_text("[DeviceInfo\nthis is not an EDS\n")
    missing = tmp_path / "missing.eds"
    assert read_eds_problem(shipped) is None
    assert read_eds_problem(missing).startswith("cannot read it")
    assert read_eds_problem(garbage).startswith("not a valid EDS")
    axes = [
        AxisConfig(name="X", node_id=1, counts_per_mm=1000, eds=shipped),
        AxisConfig(name="Y", node_id=2, counts_per_mm=1000, eds=missing),
    ]
    problems = {path: read_eds_problem(path) for path in (shipped, missing)}
    failed = check_eds(axes, problems)
    assert failed.verdict is Verdict.FAIL
    assert failed.detail.startswith(f"axes[1].eds = {missing}: cannot read it")
    assert check_eds(axes[:1], problems).verdict is Verdict.OK
    assert check_eds([replace(axes[0], eds=None)], {}).verdict is Verdict.OK


@pytest.mark.parametrize(
    ("verdict_list", "status"),
    [((Verdict.OK, Verdict.WARN), 0), ((Verdict.OK, Verdict.FAIL, Verdict.WARN), 1), ((), 0)],
)
def test_exit_status_is_one_when_a_check_fails(verdict_list: tuple, status: int) -> None:
    assert exit_status([Check("x", verdict, "") for verdict in verdict_list]) == status


def test_a_line_carries_verdict_name_detail_and_fix() -> None:
    line = Check("can link", Verdict.FAIL, "no interface can0", "plug it in").line()
    assert line == "fail  can link       no interface can0; fix: plug it in"
