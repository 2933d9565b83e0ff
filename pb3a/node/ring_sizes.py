"""How big a link's ring is: the node's choice, from the output's type and the policy.

Pinned arrays (the output declares ``shape`` and ``dtype``) get room for the values
the input may hold as zero-copy views (its queue) plus a few in flight; large ones
travel in a pool of slots beside a small ring. Arrays and objects of unknown size get
a large ring; everything else a small one. The ring of a lossless link says so in
its header, so its writer (a worker or the bridge) waits instead of dropping.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from pb3a.transport.ring import ZERO_COPY_MIN, RingSize

if TYPE_CHECKING:
    from pb3a.model.ports import Policy

SMALL_RING = 1 << 20
LARGE_RING = 16 << 20
ARRAYS_PER_RING = 4       # pinned arrays in flight on a link, at least
MAX_ARRAYS_PER_RING = 64  # ... and at most (64 MiB for 1 MiB arrays)
SLOT_RECORDS_RING = 64 << 10   # a pool's ring carries only the records naming slots

__all__ = ["RingSize", "ring_size"]


def ring_size(cls: type, port: str, policy: Policy) -> RingSize:
    """The ring for a link from output ``port`` of module class ``cls`` into an input
    with ``policy``: at least ARRAYS_PER_RING and at most MAX_ARRAYS_PER_RING pinned
    arrays, else a ring of a default size; lossless when the policy is."""
    spec = cls.outputs[port]
    lossless = policy.lossless
    if spec.shape is not None and spec.dtype is not None:
        nbytes = math.prod(spec.shape) * spec.dtype.itemsize
        held = policy.size + 2 if policy.kind != "latest" else 0
        count = min(max(ARRAYS_PER_RING, held), MAX_ARRAYS_PER_RING)
        if nbytes >= ZERO_COPY_MIN:
            return RingSize(SLOT_RECORDS_RING, count, nbytes, lossless)
        return RingSize(max(SMALL_RING, count * (nbytes + 128)), lossless=lossless)
    if issubclass(spec.type, np.ndarray) or spec.type is object:
        return RingSize(LARGE_RING, lossless=lossless)
    return RingSize(SMALL_RING, lossless=lossless)
