"""Hold, resume and feed override mid-curve: the setpoint stream stays on the curve and smooth.

Measured on the setpoints the machine sends each cycle (finite differences, as a drive sees
them), with ideal drives, the paper's curve and limits (T = 4 ms, vmax 100 mm/s, amax
1000 mm/s², jmax 20000 mm/s³, chord error 1 µm).
"""

from __future__ import annotations

import numpy as np
import pytest
from fake_drives import FakeDrives
from machine_harness import Harness, sim_config
from setpoint_checks import chord_errors, differences, realised_feed

from runtime.commands import CommandCode
from runtime.controller import Controller
from runtime.status import MachineState

T = 0.004
VMAX, AMAX, JMAX, DELTA = 100.0, 1000.0, 20000.0, 0.001


@pytest.fixture
def harness():
    controller = Controller(sim_config(), FakeDrives())
    h = Harness(controller)
    h.standby_with_curve()
    controller.trace = []
    yield h
    controller.close()


def curve_rows(h: Harness):
    """Positions and parameters of the setpoints taken on the loaded curve (not the approach)."""
    loaded = h.controller.machine.loaded
    rows = [sp for sp in h.setpoints if sp.path is loaded.path]
    s = np.array([sp.s_mm for sp in rows])
    u = loaded.path.arc.u_of_s(s)
    return loaded.curve, u, np.array([sp.position_mm for sp in rows])


def check_limits(positions: np.ndarray, vmax: float) -> tuple[float, float, float]:
    feed = realised_feed(positions, T)
    accel = differences(feed, T)
    jerk = differences(accel, T)
    figures = (feed.max(), np.abs(accel).max(), np.abs(jerk).max())
    assert figures[0] <= vmax * 1.001, figures
    assert figures[1] <= AMAX * 1.02, figures
    assert figures[2] <= JMAX * 1.05, figures
    return figures


def check_on_curve_and_end(h: Harness) -> None:
    curve, u, positions = curve_rows(h)
    assert np.allclose(curve.evaluate(u)[0], positions, atol=1e-7, rtol=0)
    assert chord_errors(curve, u, positions).max() <= DELTA * 1.01
    assert np.array_equal(positions[-1], curve.end_point)
    assert h.status.state is MachineState.STANDBY


def test_hold_then_resume_stays_on_the_curve_and_smooth(harness: Harness) -> None:
    h = harness
    h.command(CommandCode.START)
    h.until(lambda s: s.path_s_mm > 60.0, 2000)
    h.command(CommandCode.HOLD)
    braking = h.until(lambda s: s.feed_mm_s == 0.0, 100)
    # A jerk-limited stop from at most vmax takes at most 0.15 s (37.5 periods).
    assert braking <= 39
    held = h.status
    h.cycle(20)
    assert h.status.state is MachineState.HOLDING
    assert h.status.path_s_mm == held.path_s_mm
    h.command(CommandCode.RESUME)
    h.until(lambda s: s.state is MachineState.STANDBY, 2000)
    positions = h.sent_targets()
    check_limits(positions, VMAX)
    check_on_curve_and_end(h)


@pytest.mark.parametrize("overrides", [(30.0, 150.0), (150.0, 30.0)])
def test_override_changes_mid_curve_never_step_the_feed(
    harness: Harness, overrides: tuple[float, float]
) -> None:
    h = harness
    h.command(CommandCode.START)
    h.until(lambda s: s.path_s_mm > 20.0, 2000)
    for percent in overrides:
        h.command(CommandCode.SET_OVERRIDE, override_percent=percent)
        h.cycle(150)
        assert h.status.state is MachineState.MOVING
        # After the splice and the transition, the feed obeys the new vmax.
        recent = realised_feed(h.sent_targets()[-60:], T)
        assert recent.max() <= VMAX * percent / 100 * 1.001
    h.until(lambda s: s.state is MachineState.STANDBY, 5000)
    positions = h.sent_targets()
    check_limits(positions, VMAX * max(overrides) / 100)
    check_on_curve_and_end(h)


def test_override_zero_stops_on_the_path_and_a_new_override_moves_on(harness: Harness) -> None:
    h = harness
    h.command(CommandCode.START)
    h.until(lambda s: s.path_s_mm > 40.0, 2000)
    h.command(CommandCode.SET_OVERRIDE, override_percent=0.0)
    h.until(lambda s: s.feed_mm_s == 0.0, 100)
    h.cycle(10)
    assert h.status.state is MachineState.MOVING and h.status.feed_mm_s == 0.0
    h.command(CommandCode.SET_OVERRIDE, override_percent=80.0)
    h.until(lambda s: s.state is MachineState.STANDBY, 3000)
    positions = h.sent_targets()
    check_limits(positions, VMAX)
    check_on_curve_and_end(h)
