"""``softmotion plan`` body: summary, CSV trace and the figures 8-11 plot."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import yaml

from planner.nurbs import NurbsCurve
from planner.types import Limits
from runtime.plan_report import run_plan

PAPER = Path(__file__).resolve().parents[2] / "configs" / "curves" / "paper.yaml"
LIMITS = Limits(vmax_mm_s=100.0, amax_mm_s2=1000.0, jmax_mm_s3=20000.0, chord_error_mm=1e-3)


@pytest.fixture(scope="module")
def curve() -> NurbsCurve:
    return NurbsCurve.from_mapping(yaml.safe_load(PAPER.read_text()))


def test_summary_and_trace(curve, tmp_path):
    out = io.StringIO()
    trace = tmp_path / "trace.csv"
    run_plan(
        curve,
        LIMITS,
        0.004,
        lookahead=True,
        update="corrected",
        trace_path=trace,
        plot_path=None,
        out=out,
    )
    text = out.getvalue()
    for label in (
        "curve length",
        "motion time",
        "max feed",
        "max |tangential acc|",
        "max |jerk|",
        "max chord error",
        "feed fluctuation",
        "real-time factor",
    ):
        assert label in text
    assert "173.885 mm" in text
    lines = trace.read_text().splitlines()
    assert lines[0] == "t,u,x,y,z,feed"
    motion_line = next(line for line in text.splitlines() if line.startswith("motion time"))
    rows = int(motion_line.split("(")[1].split()[0])
    assert len(lines) == rows + 1
    last = lines[-1].split(",")
    assert [float(x) for x in last[2:5]] == pytest.approx([132.0, 40.0, 41.0], abs=1e-9)


def test_planar_trace_has_no_z(tmp_path):
    line = NurbsCurve.from_arrays(1, [[0, 0], [2, 0]], [0, 0, 1, 1])
    trace = tmp_path / "t.csv"
    run_plan(
        line,
        LIMITS,
        0.004,
        lookahead=False,
        update="taylor2",
        trace_path=trace,
        plot_path=None,
        out=io.StringIO(),
    )
    assert trace.read_text().splitlines()[0] == "t,u,x,y,feed"


def test_plot_is_written(curve, tmp_path):
    pytest.importorskip("matplotlib")
    plot = tmp_path / "fig.png"
    run_plan(
        curve,
        LIMITS,
        0.004,
        lookahead=True,
        update="corrected",
        trace_path=None,
        plot_path=plot,
        out=io.StringIO(),
    )
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
