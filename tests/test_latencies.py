"""Latency histograms: percentiles true to a bucket's width, counts that subtract."""

from __future__ import annotations

import math
import random

from pb3a import latencies


def test_percentiles_are_within_a_bucket_of_the_exact_ones() -> None:
    rng = random.Random(7)
    samples = [rng.lognormvariate(math.log(200e-6), 1.0) for _ in range(20_000)]
    counts = [0] * latencies.BUCKETS
    for seconds in samples:
        counts[latencies.bucket(seconds)] += 1
    ordered = sorted(samples)
    for q in (50, 90, 99):
        exact = ordered[int(q / 100 * len(ordered)) - 1]
        assert abs(latencies.percentile(latencies.used(counts), q) / exact - 1) < 0.1, q


def test_buckets_grow_with_the_latency_and_clamp_at_both_ends() -> None:
    times = [0.0, -1.0, 1e-9, 1e-6, 1e-5, 1e-3, 0.5, 1.0, 60.0, 1e6]
    indices = [latencies.bucket(t) for t in times]
    assert indices == sorted(indices)
    assert indices[0] == indices[1] == indices[2] == 0
    assert indices[-1] == latencies.BUCKETS - 1
    for seconds in (3e-6, 4.5e-4, 0.02, 2.0):
        middle = latencies.bucket_seconds(latencies.bucket(seconds))
        assert abs(middle / seconds - 1) < 0.1, seconds


def test_counts_subtract_and_a_restart_starts_over() -> None:
    before = {10: 5, 11: 2}
    assert latencies.since({10: 7, 11: 2, 12: 1}, before) == {10: 2, 12: 1}
    assert latencies.since({10: 1}, before) == {10: 1}          # the reader started over
    assert math.isnan(latencies.percentile({}, 99))
