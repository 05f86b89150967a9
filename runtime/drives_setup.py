"""The CiA-402 master as the configuration describes it (the cycle process builds it)."""

from __future__ import annotations

import can

from drives.master import AxisSpec, Cia402Master, MasterSettings
from drives.scaling import AxisScaling
from runtime.config import MachineConfig


def master_settings(config: MachineConfig) -> MasterSettings:
    """The CiA-402 master's settings from the machine description."""
    bus = config.can
    return MasterSettings(
        period_s=config.cycle.period_s,
        heartbeat_ms=bus.heartbeat_ms,
        master_node_id=bus.master_node_id,
        master_heartbeat_ms=bus.master_heartbeat_ms,
        heartbeat_loss_periods=bus.heartbeat_loss_periods,
        boot_timeout_s=bus.boot_timeout_s,
        sdo_timeout_s=bus.sdo_timeout_s,
        sdo_retries=bus.sdo_retries,
        stale_feedback_cycles=bus.stale_feedback_cycles,
        sync_window_us=bus.sync_window_us,
        sync_counter_overflow=bus.sync_counter_overflow,
        reset_communication=bus.reset_communication,
        shutdown_timeout_s=bus.shutdown_timeout_s,
    )


def axis_specs(config: MachineConfig) -> tuple[AxisSpec, ...]:
    """The master's view of each configured axis."""
    return tuple(
        AxisSpec(
            name=axis.name,
            node_id=axis.node_id,
            scaling=AxisScaling(
                counts_per_mm=axis.counts_per_mm,
                direction=axis.direction,
                travel_min_mm=axis.travel_min_mm,
                travel_max_mm=axis.travel_max_mm,
            ),
            following_error_window_mm=axis.following_error_window_mm,
            following_error_timeout_ms=axis.following_error_timeout_ms,
            eds=axis.eds,
            pdo=axis.pdo,
            supervision=axis.supervision,
            guard_time_ms=axis.guard_time_ms,
            life_time_factor=axis.life_time_factor,
            feedback_lag_periods=axis.feedback_lag_periods,
        )
        for axis in config.axes
    )


def open_master_bus(config: MachineConfig) -> can.BusABC:
    """The cycle's bus: own frames delivered, so each SYNC's echo dates it on the bus's clock
    (the master matches feedback to the SYNC it answered by it).

    :raises drives.errors.BusUnavailable: if it cannot be opened.
    """
    from drives.bus import open_bus

    bus = config.can
    return open_bus(bus.interface, bus.channel, bus.bitrate, receive_own_messages=True)


def build_master(config: MachineConfig, bus: can.BusABC) -> Cia402Master:
    """The master for ``config`` on ``bus``."""
    return Cia402Master(bus, axis_specs(config), master_settings(config))
