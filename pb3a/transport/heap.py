"""``keep_freed_buffers``: the C heap of a process keeps the memory of freed large
buffers mapped, so that the next one reuses it instead of faulting in fresh pages.

ZeroMQ allocates a buffer for every message it receives, and a remote link's sender
copies every large value into one (``replication``). With glibc's defaults a freed
1 MiB buffer at the top of a thread's heap is handed back to the kernel (the heap
is trimmed beyond 2 MiB free), and the next message's 256 pages are faulted in and
zeroed anew: here that cost the receiving node's ZeroMQ thread about a third of its
time per 1 MiB array. Raising the trim threshold keeps them; raising the mmap
threshold with it (glibc stops adjusting it once either is set) keeps buffers up to
32 MiB on the heaps rather than mapped and unmapped one by one. The price: up to
``TRIM_BYTES`` of freed memory stays mapped per heap (one per thread that allocates,
at most 8 per CPU).

Only glibc has ``mallopt``; elsewhere this does nothing.
"""

from __future__ import annotations

import ctypes
import functools

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3     # glibc's malloc.h
TRIM_BYTES = 64 * 1024 * 1024                   # freed memory a heap keeps mapped
MMAP_BYTES = 32 * 1024 * 1024                   # larger buffers are mapped on their own
                                                # (glibc's largest mmap threshold)


@functools.cache
def keep_freed_buffers() -> bool:
    """Set the thresholds, once per process; False where that is not possible."""
    # the process's own symbols, libc's among them: ``ctypes.util.find_library`` would
    # run ``ldconfig`` in a subprocess, milliseconds inside a migration's preparation
    libc = ctypes.CDLL(None)
    if not hasattr(libc, "gnu_get_libc_version") or not hasattr(libc, "mallopt"):
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_BYTES)
                and libc.mallopt(M_TRIM_THRESHOLD, TRIM_BYTES))
