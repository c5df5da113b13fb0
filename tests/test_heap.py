"""glibc heap reuse (:mod:`emlpack.heap`): large arrays stay ordinary arrays, errors pass
through, and kept memory serves the next block without page faults."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.heap import reused_heap


def test_reused_heap_is_reentrant_and_restores():
    """Large arrays inside and after the block are ordinary arrays; an error passes through."""
    for _ in range(2):
        with reused_heap():
            a = np.ones(5_000_000)
            del a
            b = np.full(5_000_000, 2.0)
            assert b.sum() == 1e7
    with pytest.raises(ValueError), reused_heap():
        raise ValueError("passes through")
    assert np.zeros(5_000_000).sum() == 0.0


_HEAP_PROBE = """
import resource, sys
import numpy as np
from emlpack.heap import reused_heap
from contextlib import nullcontext
keep = sys.argv[1] == "keep"
outer = reused_heap() if sys.argv[1] == "nested" else nullcontext()
faults = []
with outer:
    for _ in range(2):
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        with reused_heap(keep=keep):
            a = np.ones(25_000_000)  # 200 MB
            del a
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
print(*faults)
"""


@pytest.mark.parametrize("keep", ["keep", "release", "nested"])
def test_kept_heap_serves_the_next_block_without_page_faults(keep):
    """``reused_heap(keep=True)`` (labeling workers): the second block reuses the pages the
    first touched; by default the memory goes back to the kernel and is touched again; an
    inner block inside an outer one (an optimisation inside a training) leaves the memory to
    the outer block."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _HEAP_PROBE, keep], capture_output=True,
                         text=True, check=True).stdout.split()
    first, second = int(out[0]), int(out[1])
    # 200 MB touched: 100 faults in 2 MB pages up to ~49 000 in 4 kB pages, and with
    # transparent huge pages the mix differs from block to block (seen in CI: 15 605 then
    # 2 355 faults with the memory released), so the released case is told apart from the
    # kept one by the second block faulting at all (>= 100 MB in 2 MB pages), not by a ratio
    assert first > 50, out
    if keep in ("keep", "nested"):
        assert second < 0.1 * first and second < 50, out
    else:
        assert second > 50, out
