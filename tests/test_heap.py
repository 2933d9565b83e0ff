"""The C heap keeps freed large buffers mapped (``pb3a.transport.heap``): freeing and
allocating 1 MiB buffers again costs no page faults, where glibc's defaults give
the memory back to the kernel and fault it in anew."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

CHURN = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from pb3a.transport.heap import keep_freed_buffers
    if sys.argv[1] == "keep":
        assert keep_freed_buffers() and keep_freed_buffers()    # (once is enough)
    def churn():                   # four 1 MiB buffers live at once, then all freed
        buffers = [np.ones(1 << 17) for _ in range(4)]
        del buffers
    for _ in range(5):
        churn()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        churn()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
""")


def _faults(mode: str) -> int:
    done = subprocess.run([sys.executable, "-c", CHURN, mode], capture_output=True, text=True,
                          timeout=60, check=True)
    return int(done.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_large_buffers_are_reused_without_faulting_pages_in_again() -> None:
    assert _faults("default") >= 20 * 256      # 1 MiB is 256 pages, faulted in every round
    assert _faults("keep") < 256
