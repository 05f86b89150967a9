"""The lateness window's percentiles against numpy's, and its bucket resolution."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.latency import LINEAR_BUCKET_US, LINEAR_LIMIT_US, LOG_RATIO, PERCENTILES, LatenessRing


def exact_us(samples_s: np.ndarray) -> list[float]:
    return list(np.percentile(samples_s * 1e6, list(PERCENTILES.values()), method="higher"))


def assert_within_bucket(reported_us: float, exact: float) -> None:
    """Never below the exact percentile; at most one bucket above it."""
    assert reported_us >= exact
    if exact < LINEAR_LIMIT_US:
        assert reported_us - exact < LINEAR_BUCKET_US * (1.0 + 1e-9)
    else:
        assert reported_us <= exact * LOG_RATIO


@pytest.mark.parametrize("capacity", [1, 7, 2500, 20000])
def test_percentiles_of_the_window_match_numpys_to_a_bucket(capacity: int) -> None:
    rng = np.random.default_rng(capacity)
    # Mostly microseconds, a tail of milliseconds and one stall, then more than a window of
    # other samples so that the first ones are evicted.
    first = np.concatenate([rng.exponential(10e-6, capacity), rng.exponential(3e-3, capacity)])
    rng.shuffle(first)
    later = np.concatenate([rng.exponential(20e-6, capacity), [0.25], rng.exponential(2e-3, 9)])
    ring = LatenessRing(capacity)
    for i, sample in enumerate(np.concatenate([first, later]).tolist()):
        ring.record(sample)
        if i in (0, capacity // 2, len(first) - 1):
            window = np.concatenate([first, later])[max(0, i + 1 - capacity) : i + 1]
            for reported, exact in zip(
                ring.percentiles_us().values(), exact_us(window), strict=True
            ):
                assert_within_bucket(reported, exact)
    window = np.concatenate([first, later])[-capacity:]
    assert len(ring) == capacity
    for reported, exact in zip(ring.percentiles_us().values(), exact_us(window), strict=True):
        assert_within_bucket(reported, exact)


def test_a_bucket_of_equal_samples_reports_them_exactly() -> None:
    ring = LatenessRing(100)
    for sample_s in [0.0] * 60 + [0.015] * 40:
        ring.record(sample_s)
    assert ring.percentiles_us() == {"p50": 0.0, "p99": 15000.0, "p99.9": 15000.0, "max": 15000.0}


def test_an_evicted_sample_leaves_its_emptied_bucket() -> None:
    ring = LatenessRing(3)
    for sample_s in (0.5, 1e-6, 2e-6, 3e-6):
        ring.record(sample_s)
    assert ring.percentiles_us()["max"] == 3.0


def test_samples_beyond_the_last_bucket_share_it_and_negative_ones_count_as_zero() -> None:
    ring = LatenessRing(5)
    for sample_s in (-1e-6, -2e-6, 0.0, 150.0, 400.0):
        ring.record(sample_s)
    figures = ring.percentiles_us()
    assert figures["p50"] == 0.0
    # 150 s and 400 s share the last bucket (from 100 s): the 150 s rank reports its largest.
    assert figures["p99"] == figures["max"] == 400e6
    ring.clear()
    assert len(ring) == 0
    assert ring.percentiles_us() == dict.fromkeys(PERCENTILES, 0.0)
