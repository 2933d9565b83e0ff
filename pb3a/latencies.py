"""Latency histograms: how long values took from write to delivery, as bucket counts.

A reader counts each delivery in one of a fixed set of log-spaced buckets (eight per
doubling, so a bucket spans 9 % or less): a binary search over the buckets' edges, in
C, and one list increment per delivery (about 0.1 us), and small enough to report
(only the buckets used).
Percentiles come from the counts, so they are exact to a bucket's width; the counts
of two reports subtract, which gives the percentiles of the values in between.
"""

from __future__ import annotations

import bisect
import functools
import math
from collections.abc import Mapping, Sequence

PER_DOUBLING = 8
SMALLEST_EXPONENT = -20
BUCKETS = (6 - SMALLEST_EXPONENT) * PER_DOUBLING
# bucket 0 starts at 2**-21 s (0.5 us) and counts all below; the last one starts at
# 30 s and counts all above


def _low_edge(index: int) -> float:
    """The smallest latency bucket ``index`` counts (bucket 0 also counts all below)."""
    exponent, step = divmod(index, PER_DOUBLING)
    return (0.5 + step / (2 * PER_DOUBLING)) * 2.0 ** (exponent + SMALLEST_EXPONENT)


_EDGES = [_low_edge(index) for index in range(1, BUCKETS)]

bucket = functools.partial(bisect.bisect_right, _EDGES)
"""``bucket(seconds)``: the index of the bucket that counts a latency of ``seconds``."""


def bucket_seconds(index: int) -> float:
    """The latency a bucket stands for: the geometric middle of its span."""
    step = index % PER_DOUBLING
    return _low_edge(index) * math.sqrt(1 + 1 / (PER_DOUBLING + step))


def used(counts: Sequence[int]) -> dict[int, int]:
    """The buckets that counted something: what a report carries."""
    return {index: count for index, count in enumerate(counts) if count}


def since(now: Mapping[int, int], before: Mapping[int, int]) -> dict[int, int]:
    """The deliveries counted in ``now`` but not yet in ``before``. A count that went
    down means the reader started over (its worker restarted): then ``now`` is all new."""
    if any(now.get(index, 0) < count for index, count in before.items()):
        return dict(now)
    return {index: count - before.get(index, 0) for index, count in now.items()
            if count > before.get(index, 0)}


def percentile(counts: Mapping[int, int], q: float) -> float:
    """The ``q``-th percentile (0-100) of the latencies ``counts`` holds, in seconds;
    NaN when it holds none."""
    total = sum(counts.values())
    if not total:
        return math.nan
    rank, seen = q / 100.0 * total, 0
    for index in sorted(counts):
        seen += counts[index]
        if seen >= rank:
            return bucket_seconds(index)
    return bucket_seconds(max(counts))
