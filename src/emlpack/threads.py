"""Thread and BLAS settings that stay fast on a shared machine (torch-free; call before
importing torch, or PySCF for the OpenBLAS kernels: :func:`configure_openblas_coretype`).

OpenMP's default wait policy lets idle threads spin; on a machine whose cores are busy with
other work, every parallel region then waits for spinning threads that have been descheduled.
Measured (issue 14; 2 cores, load average 10, small trained model, float64, one batched
energy+gradient of 64 eqm7 structures / of one structure, wall per evaluation):

==================================  ============  ============
setting                             batch 64      batch 1
==================================  ============  ============
1 thread                            0.53 s        0.018 s
2 threads, ``OMP_WAIT_POLICY=PASSIVE``  0.15 s        0.010 s
2 threads, default (spinning)       5.39 s        0.218 s
==================================  ============  ============

(issue 14's own figures on a loaded machine: 1.7-3.2 s spinning, 0.24 s with 1 thread,
0.25-0.44 s passive.) Policy: passive waiting always, and at most ``min(cores, 4)`` threads
unless the user asks for more. The wait policy is read when the OpenMP runtime starts (when
torch is imported), so :func:`configure_thread_environment` must run before that;
:func:`apply_threads` sets torch's intra-op threads afterwards.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import MutableMapping

#: threads used when nothing is requested (a few cores help batched evaluations; more
#: rarely do for the eMLP's small matrices)
DEFAULT_MAX_THREADS = 4


def default_threads(cpu_count: int | None = None) -> int:
    """Threads to use when the user asked for none: ``min(cores, DEFAULT_MAX_THREADS)``."""
    n = cpu_count if cpu_count is not None else (os.cpu_count() or 1)
    return max(1, min(n, DEFAULT_MAX_THREADS))


def configure_thread_environment(
    threads: int | None = None, environ: MutableMapping[str, str] | None = None
) -> int:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` and ``OMP_NUM_THREADS`` in ``environ`` (default
    ``os.environ``) unless the user already set them; an explicit ``threads`` always sets
    ``OMP_NUM_THREADS``. Returns the thread count in effect. Call before importing torch."""
    env = os.environ if environ is None else environ
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if threads is not None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, not {threads}")
        env["OMP_NUM_THREADS"] = str(threads)
    elif not env.get("OMP_NUM_THREADS"):
        env["OMP_NUM_THREADS"] = str(default_threads())
    return int(env["OMP_NUM_THREADS"])


def configure_openblas_coretype(
    environ: MutableMapping[str, str] | None = None, cpuinfo: str = "/proc/cpuinfo"
) -> str | None:
    """Ask OpenBLAS for its AVX2 kernels (``OPENBLAS_CORETYPE=Haswell``) on a CPU with AVX2
    and FMA, unless the user chose a core type; returns the core type in effect (``None``:
    OpenBLAS's own detection). Call before importing PySCF: OpenBLAS reads it when loaded.

    PySCF's wheels bundle OpenBLAS 0.3.3 (2018), which does not recognise newer CPUs and
    falls back to its 2007 kernels: on our machines (AMD EPYC with AVX-512) ``perf`` showed
    3/4 of a label's time in ``dgemm_kernel_BARCELONA``, and with the Haswell kernels an
    aziridine label at the paper level took 16.6 s CPU instead of 22.0 s (1 thread), results
    equal to 1e-11 eV. Libraries already loaded (numpy's OpenBLAS) are not affected.
    """
    env = os.environ if environ is None else environ
    if env.get("OPENBLAS_CORETYPE"):
        return env["OPENBLAS_CORETYPE"]
    try:
        with open(cpuinfo) as f:
            flags = next((line.split(":", 1)[1].split() for line in f
                          if line.startswith("flags")), [])
    except OSError:
        return None
    if {"avx2", "fma"} <= set(flags):
        env["OPENBLAS_CORETYPE"] = "Haswell"
        return "Haswell"
    return None


def pyscf_openblas_core() -> str | None:
    """The core type (kernels) of the OpenBLAS bundled with PySCF, e.g. ``"Haswell"``, as it
    reports it (``openblas_get_corename``); ``None`` without PySCF or a bundled OpenBLAS.
    Imports PySCF: call :func:`configure_openblas_coretype` first."""
    import ctypes
    import glob

    from emlpack.optional import is_available

    if not is_available("pyscf"):
        return None
    import pyscf.lib

    libs = glob.glob(os.path.join(os.path.dirname(pyscf.lib.__file__), "libopenblas*.so*"))
    if not libs:
        return None
    corename = ctypes.CDLL(libs[0]).openblas_get_corename
    corename.restype = ctypes.c_char_p
    return corename().decode()


def apply_threads(threads: int | None = None) -> int:
    """Set torch's intra-op threads (``threads``, else ``OMP_NUM_THREADS``, else the default)
    and return the number set."""
    import torch

    n = threads or int(os.environ.get("OMP_NUM_THREADS") or default_threads())
    torch.set_num_threads(n)
    return n
