"""Points the refinement added in earlier plans of a path, offered to re-plans as a warm start.

A re-plan from a motion state (a feed override, a resume) covers a stretch that an earlier plan
of the same path has refined already. Where the feed limit lies below both plans' vmax, the
points refinement added there depend little on vmax or on the start state: they sit where the
plan must follow the limit. Inserting them before the refinement starts leaves it a round or two
of checks instead of the rounds of splits that found them; on the paper's curve a re-plan's
first block where the window holds the sharp stretch drops from about 8.5 to about 5 ms.

A plan from rest at the start of a path is planned cold (:func:`planner.stream.stream_setpoints`
seeds only re-plans), so a program's repeats are the same motion whatever ran before. The checker
still checks every segment of a seeded window: a warm start changes how fast a plan is found,
never which limits it keeps.

Memory: one record per point the refinement added, which grows with the path as its arc-length
table does, more slowly (380 points on a winding 1,000-span curve, none on a smooth 2,000-span
one).

Units: s in mm, feeds mm/s, accelerations mm/s². Pure computation; one path's memory, used by
one plan at a time (as the path itself), not thread-safe.
"""

from __future__ import annotations

import bisect
from collections.abc import Collection
from dataclasses import dataclass

from planner.window import MIN_POINT_GAP_MM, Window

#: A remembered point is offered only below this fraction of both the re-plan's vmax and the
#: vmax of the plan that added it (at or near vmax it was placed by vmax, not by the limit).
VMAX_FRACTION = 0.99


@dataclass(frozen=True)
class RefinedPoint:
    """A point the refinement added, as it stood when its window was planned."""

    s_mm: float
    cap_mm_s: float
    accel_mm_s2: float
    pinned: bool
    flat_cap_mm_s: float
    vmax_mm_s: float
    """The vmax of the plan that added it."""


class RefinedPoints:
    """The points refinement added in the latest plan of each stretch of a path (and in earlier
    ones, above that plan's vmax), in order of s."""

    def __init__(self) -> None:
        self._s: list[float] = []
        self._points: list[RefinedPoint] = []

    def __len__(self) -> int:
        return len(self._points)

    def remember(self, w: Window, initial_s: Collection[float], vmax_mm_s: float) -> None:
        """Replace what is known of the window's stretch by the points refinement added to it
        (those not in ``initial_s``, the window's points before refinement).

        Points known there that this plan would not be offered (at or above
        :data:`VMAX_FRACTION` of its vmax) are kept: a plan at a lower feed override tells
        nothing of the stretch above its vmax, and overrides that go down and up again would
        otherwise leave the faster re-plans without their points."""
        lo = bisect.bisect_left(self._s, w.s[0])
        hi = bisect.bisect_right(self._s, w.s[-1])
        added = [
            RefinedPoint(w.s[i], w.cap[i], w.acc[i], w.pinned[i], w.flat_cap[i], vmax_mm_s)
            for i in range(1, len(w.s) - 1)
            if w.s[i] not in initial_s
        ]
        unseen = [
            point for point in self._points[lo:hi] if point.cap_mm_s >= VMAX_FRACTION * vmax_mm_s
        ]
        points = sorted(added + unseen, key=lambda point: point.s_mm)
        self._s[lo:hi] = [point.s_mm for point in points]
        self._points[lo:hi] = points

    def seed(self, w: Window, vmax_mm_s: float) -> None:
        """Insert the remembered points strictly inside the window that suit a plan with
        ``vmax_mm_s``, away from the window's own points."""
        lo = bisect.bisect_right(self._s, w.s[0] + MIN_POINT_GAP_MM)
        hi = bisect.bisect_left(self._s, w.s[-1] - MIN_POINT_GAP_MM)
        k = 0
        for point in self._points[lo:hi]:
            if point.cap_mm_s >= VMAX_FRACTION * min(vmax_mm_s, point.vmax_mm_s):
                continue
            while w.s[k + 1] <= point.s_mm:
                k += 1
            if min(point.s_mm - w.s[k], w.s[k + 1] - point.s_mm) <= MIN_POINT_GAP_MM:
                continue
            w.insert(
                k,
                point.s_mm,
                point.cap_mm_s,
                acc=point.accel_mm_s2,
                flat_cap=point.flat_cap_mm_s if point.pinned else None,
            )
