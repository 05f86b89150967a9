"""The CiA-402 master as the configuration describes it (the cycle process builds it)."""

from __future__ import annotations

import can

from drives.master import AxisSpec, MasterSettings
from drives.scaling import AxisScaling
from runtime.config import MachineConfig


def master_settings(config: MachineConfig) -> MasterSettings:
    """The CiA-402 master's settings from the machine description."""
    can_config = config.can
    return MasterSettings(
        period_s=config.cycle.period_s,
        heartbeat_ms=can_config.heartbeat_ms,
        master_node_id=can_config.master_node_id,
        master_heartbeat_ms=can_config.master_heartbeat_ms,
        heartbeat_loss_periods=can_config.heartbeat_loss_periods,
        boot_timeout_s=can_config.boot_timeout_s,
        sdo_timeout_s=can_config.sdo_timeout_s,
        stale_feedback_cycles=can_config.stale_feedback_cycles,
        sync_window_us=can_config.sync_window_us,
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
        )
        for axis in config.axes
    )


def build_master(config: MachineConfig, bus: can.BusABC):
    """The master for ``config`` on ``bus``."""
    from runtime.cycle.drives_adapter import LegacyDrives

    return LegacyDrives(bus, axis_specs(config), master_settings(config))
