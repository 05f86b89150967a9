"""Cycle lateness statistics: a fixed-size ring of samples, percentiles computed on demand.

Lateness is how long after its deadline a cycle woke (seconds in, microseconds out). Recording
is O(1) and allocation-free (one store into a preallocated float64 array), so the cyclic thread
can record every cycle; percentiles sort a copy of the ring and are computed off the per-cycle
path (see :class:`runtime.scheduler.CyclicTask` for when).

Threading: one writer (the cyclic thread). Readers in other threads may compute percentiles at
any time; they see the last ``capacity`` samples, possibly one cycle newer than the counters they
read beside them. That is the only inconsistency and it is harmless for statistics.

Percentiles use the "higher" rule: each figure is a sample that was actually observed, never an
interpolation below it.
"""

from __future__ import annotations

import numpy as np

#: Percentiles reported by :meth:`LatenessRing.percentiles_us`, keyed by their names.
PERCENTILES: dict[str, float] = {"p50": 50.0, "p99": 99.0, "p99.9": 99.9, "max": 100.0}


class LatenessRing:
    """The last ``capacity`` lateness samples of a cyclic task."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"lateness ring: capacity = {capacity}, must be >= 1")
        self._samples_s = np.zeros(capacity, dtype=np.float64)
        self._next = 0
        self._count = 0

    @property
    def capacity(self) -> int:
        return len(self._samples_s)

    def __len__(self) -> int:
        """Number of samples held (at most ``capacity``)."""
        return self._count

    def record(self, lateness_s: float) -> None:
        """Store one sample, overwriting the oldest once the ring is full. O(1)."""
        self._samples_s[self._next] = lateness_s
        self._next = (self._next + 1) % len(self._samples_s)
        if self._count < len(self._samples_s):
            self._count += 1

    def clear(self) -> None:
        self._next = 0
        self._count = 0

    def percentiles_us(self) -> dict[str, float]:
        """p50, p99, p99.9 and max of the held samples in microseconds; all 0.0 when empty.

        O(capacity): call it outside the cyclic step.
        """
        count = self._count
        if count == 0:
            return dict.fromkeys(PERCENTILES, 0.0)
        held = self._samples_s[:count]
        values = np.percentile(held, list(PERCENTILES.values()), method="higher")
        return {name: float(v) * 1e6 for name, v in zip(PERCENTILES, values, strict=True)}
