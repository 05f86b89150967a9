"""Cycle lateness statistics over a sliding window: O(1) to record, percentiles in bounded time.

Lateness is how long after its deadline a cycle woke (seconds in, microseconds out). The window
holds the last ``capacity`` samples as a histogram: 0.1 µs buckets below 100 µs, buckets 1 %
wide above (up to 100 s; later samples share the last bucket). Recording is O(1) and
allocation-free: the sample's bucket is counted and the bucket of the sample it evicts is
uncounted (a ring of bucket numbers remembers which), about 1.5 µs. Percentiles walk the bucket
counts in two levels (groups of 64 buckets, then one group): about 35 µs whatever the window.
Sorting a copy of the samples instead took 0.24 ms for a 10 s window at 4 ms and 1 ms for a
90 s one on an idle core, two to three times that under load: enough, once a second, to push
the cyclic thread that computes them past its next deadline.

Percentiles use the "higher" rule and report an observed sample: each bucket keeps the largest
sample it received since it was last empty, and a percentile is that sample of the bucket
holding it. It lies in the same bucket as the exact percentile: never below it, at most the
bucket's width above (under 0.1 µs below 100 µs, under 1 % above), and exact when the bucket's
samples are equal.

Threading: one writer (the cyclic thread). Readers in other threads may compute percentiles at
any time; they see the window possibly one sample newer than the counters they read beside it.
That is the only inconsistency and it is harmless for statistics.
"""

from __future__ import annotations

import math
from array import array

#: Percentiles reported by :meth:`LatenessRing.percentiles_us`, keyed by their names.
PERCENTILES: dict[str, float] = {"p50": 50.0, "p99": 99.0, "p99.9": 99.9, "max": 100.0}
#: Width of the buckets below ``LINEAR_LIMIT_US`` [µs], and the ratio of consecutive bucket
#: edges above it.
LINEAR_BUCKET_US, LINEAR_LIMIT_US, LOG_RATIO = 0.1, 100.0, 1.01
_LINEAR_BUCKETS = round(LINEAR_LIMIT_US / LINEAR_BUCKET_US)
_PER_US = 1.0 / LINEAR_BUCKET_US
#: Samples at or above this share the last bucket [µs].
TOP_US = 100e6
_LOG_SCALE = 1.0 / math.log(LOG_RATIO)
_BUCKETS = _LINEAR_BUCKETS + math.ceil(math.log(TOP_US / LINEAR_LIMIT_US) * _LOG_SCALE) + 1
#: Buckets are also counted in groups of 2**_GROUP_BITS, so that a percentile walks the groups,
#: then the buckets of one group.
_GROUP_BITS = 6
_GROUPS = (_BUCKETS >> _GROUP_BITS) + 1


def bucket_of(lateness_us: float) -> int:
    """The histogram bucket of a sample [µs] (negative samples count as 0)."""
    if lateness_us < LINEAR_LIMIT_US:
        return max(int(lateness_us * _PER_US), 0)
    bucket = _LINEAR_BUCKETS + int(math.log(lateness_us / LINEAR_LIMIT_US) * _LOG_SCALE)
    return min(bucket, _BUCKETS - 1)


class LatenessRing:
    """The last ``capacity`` lateness samples of a cyclic task, as a sliding-window histogram."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"lateness ring: capacity = {capacity}, must be >= 1")
        # Lists and a standard-library array: one item at a time, they are several times
        # quicker to reach from Python than numpy's arrays; the ring stays compact.
        self._buckets = array("H", bytes(2 * capacity))
        self._counts = [0] * _BUCKETS
        self._group_counts = [0] * _GROUPS
        self._largest_us = [0.0] * _BUCKETS
        self._next = 0
        self._count = 0

    @property
    def capacity(self) -> int:
        return len(self._buckets)

    def __len__(self) -> int:
        """Number of samples held (at most ``capacity``)."""
        return self._count

    def record(self, lateness_s: float) -> None:
        """Count one sample, uncounting the oldest once the window is full. O(1)."""
        lateness_us = lateness_s * 1e6
        if 0.0 <= lateness_us < LINEAR_LIMIT_US:
            bucket = int(lateness_us * _PER_US)  # bucket_of, inlined for the common case
        else:
            bucket = bucket_of(lateness_us)
        counts, largest, buckets = self._counts, self._largest_us, self._buckets
        groups = self._group_counts
        index = self._next
        if self._count == len(buckets):
            evicted = buckets[index]
            counts[evicted] -= 1
            groups[evicted >> _GROUP_BITS] -= 1
            if not counts[evicted]:
                largest[evicted] = 0.0
        else:
            self._count += 1
        buckets[index] = bucket
        counts[bucket] += 1
        groups[bucket >> _GROUP_BITS] += 1
        if lateness_us > largest[bucket]:
            largest[bucket] = lateness_us
        index += 1
        self._next = 0 if index == len(buckets) else index

    def clear(self) -> None:
        self._counts = [0] * _BUCKETS
        self._group_counts = [0] * _GROUPS
        self._largest_us = [0.0] * _BUCKETS
        self._next = 0
        self._count = 0

    def percentiles_us(self) -> dict[str, float]:
        """p50, p99, p99.9 and max of the held samples in microseconds; all 0.0 when empty.

        O(buckets), independent of the window's length (see the module docstring).
        """
        count = self._count
        if count == 0:
            return dict.fromkeys(PERCENTILES, 0.0)
        # numpy's "higher" rule: the sample of rank ceil(q (n - 1)) in ascending order.
        ranks = [math.ceil(q / 100.0 * (count - 1)) for q in PERCENTILES.values()]
        return {
            name: self._largest_us[self._bucket_of_rank(rank)]
            for name, rank in zip(PERCENTILES, ranks, strict=True)
        }

    def _bucket_of_rank(self, rank: int) -> int:
        """The bucket holding the sample of ``rank`` (0: the smallest) in ascending order."""
        below = group = 0
        groups = self._group_counts
        while below + groups[group] <= rank:
            below += groups[group]
            group += 1
        bucket = group << _GROUP_BITS
        counts = self._counts
        while below + counts[bucket] <= rank:
            below += counts[bucket]
            bucket += 1
        return bucket
