"""glibc heap settings for processes that allocate and free the same large arrays over and
over (SCF cycles of the labeler, training steps, Hessians of a geometry optimisation).

glibc serves an allocation above its ``mmap`` threshold (128 kB at first, raised up to 32 MB
as mapped blocks are freed) with fresh pages and unmaps them when it is freed, so the next
allocation of that size page-faults its memory in again; in this sandbox a page fault costs
about 10 µs. :func:`reused_heap` keeps freed memory in the heap for reuse instead.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Iterator
from contextlib import contextmanager

# glibc mallopt parameters and their defaults
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
_DEFAULT_TRIM_THRESHOLD, _DEFAULT_MMAP_MAX = 128 * 1024, 65536
#: open reused_heap blocks (the settings are process-wide: an inner block leaves them to the
#: outermost one)
_depth = 0


def _glibc():
    """glibc through ctypes, or ``None`` (another C library, or no ``mallopt``)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        if not (hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim")):
            return None
    except OSError:
        return None
    return libc


@contextmanager
def reused_heap(keep: bool = False) -> Iterator[None]:
    """Serve large arrays from the heap and keep freed memory for reuse, inside the block.

    Inside the block ``mmap`` is off for ``malloc`` and freed memory is not returned to the
    kernel, so later allocations reuse touched pages; on leaving, glibc's defaults are
    restored and the free memory is given back (``malloc_trim``). Not glibc: does nothing.
    Measured:

    - labeling (``PySCFLabeler(reuse_heap=True)``): each SCF cycle's grid buffers and each
      density-fitting block faulted in again; C3H4 at the paper level: 285 000 -> 12 000
      minor faults, the same numbers;
    - training (``Trainer.train``): the edge-sized float32 tensors of the double backward
      (~6 000 edges x 64 filters, 1.5 MB each) faulted in at every step; mini-eQM7 batches
      of 16, F=G=64, T=3, 1 thread: 5 300 -> 40 minor faults and 0.134 -> 0.108 s CPU per
      step (the same gradients);
    - geometry optimisation (``optimize``, exact Hessians at every iteration): C4H7NO2 with
      member 0 of mini-eqm7, 428 000 -> 16 000 minor faults, 4.5 -> 2.7 s CPU.

    Blocks nest: only the outermost one sets and restores (an inner block inside a training or
    an optimisation does not trim the outer block's memory).

    ``keep=True`` keeps these settings and the memory after the block, for a process that
    does nothing but label: the next label reuses the touched pages (aziridine at the paper
    level, 2nd and 3rd label: 5 700-10 000 -> 5-14 minor faults, 14.0-15.1 -> 12.9-13.3 s
    CPU); the process then holds the largest label's peak memory.
    """
    global _depth
    libc = _glibc()
    if libc is None:
        yield
        return
    if _depth == 0:
        libc.mallopt(_M_MMAP_MAX, 0)
        libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0 and not keep:
            libc.mallopt(_M_MMAP_MAX, _DEFAULT_MMAP_MAX)
            libc.mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM_THRESHOLD)
            libc.malloc_trim(0)
