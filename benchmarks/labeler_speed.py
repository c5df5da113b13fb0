"""Labeler speed: plain PySCF settings vs the labeler's defaults on stored configurations.

Each configuration of a data-set shard is labeled at the paper's level by every variant in
turn, in one process with one thread (the machine is shared, so only CPU times measured this
way are comparable); the JSON holds CPU time, wall time, minor page faults, SCF cycles and the
label differences to the first variant and to the stored labels (centres matched one to one).

Variants: ``plain`` (PySCF as it comes: no AO cache, PySCF's max_memory, PySCF's XC gradient,
glibc's malloc), ``new`` (the labeler's defaults), ``new_atom_guess``, ``new_no_conv_check``.

OpenBLAS's kernels are chosen when PySCF loads, so they cannot change within a process:
compare them in two runs, e.g. ``OPENBLAS_CORETYPE=Prescott`` (what PySCF's OpenBLAS 0.3.3
picks on our AMD EPYC) against the default (Haswell, ``emlpack.threads``); the JSON records
the kernels in use (``openblas_core``). ``new_keep_heap`` keeps the heap between labels, as
the labeling workers do.

Usage (a 7-atom and a 12-atom configuration of the campaign's first shard)::

    OMP_NUM_THREADS=1 PYTHONPATH=src python benchmarks/labeler_speed.py \\
        --store /work/main/datasets/mini-eqm7/shards/0000.h5 --index 4 8 \\
        --variants plain,new,plain,new --json benchmarks/results/labeler_speed.json
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_info, write_json  # noqa: E402

from emlpack.data.store import DatasetStore  # noqa: E402
from emlpack.qm.pyscf_labeler import PySCFLabeler  # noqa: E402
from emlpack.qm.relabel import match_centres  # noqa: E402

PLAIN = {"ao_cache_mb": 0, "max_memory_mb": None, "fast_xc_gradient": False, "reuse_heap": False}


class _Variant(PySCFLabeler):
    """The labeler with extra attributes set on PySCF's SCF object."""

    def __init__(self, scf_settings: dict | None = None, **kwargs) -> None:
        super().__init__(threads=1, **kwargs)
        self.scf_settings = scf_settings or {}

    def build(self, *args, **kwargs):
        mol, mf = super().build(*args, **kwargs)
        for key, value in self.scf_settings.items():
            setattr(mf, key, value)
        return mol, mf


VARIANTS = {
    "plain": PLAIN,
    "new": {},
    "new_atom_guess": {"scf_settings": {"init_guess": "atom"}},
    "new_no_conv_check": {"scf_settings": {"conv_check": False}},
    "new_keep_heap": {"keep_heap": True},
}


def run(store: str, indices: list[int], variants: list[str]) -> list[dict]:
    data = DatasetStore(store)
    rows = []
    for index in indices:
        s = data[index]
        first = None
        for name in variants:
            labeler = _Variant(**VARIANTS[name])
            faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            cpu0, wall0 = time.process_time(), time.perf_counter()
            r = labeler.label_structure(s)
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
            faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0
            if not r.ok:
                raise SystemExit(f"{name}: {r.error}")
            first = first or r
            row = {
                "index": index, "key": s.info.get("key", ""), "n_atoms": len(s.numbers),
                "variant": name, "cpu_s": cpu, "wall_s": wall, "minor_faults": faults,
                "scf_cycles": r.scf_cycles,
                "d_energy_eV": abs(r.energy - first.energy),
                "d_forces_eV_A": float(np.abs(r.forces - first.forces).max()),
                # one-to-one matching: starts with equal spreads may list the centres in
                # another order
                "d_centres_A": match_centres(first.centres, r.centres)[1],
                "d_pairs_stored_A": match_centres(s.pairs, r.pairs)[1],
                "d_energy_stored_eV": abs(r.energy - s.energy),
                "d_forces_stored_eV_A": float(np.abs(r.forces - s.forces).max()),
            }
            rows.append(row)
            print(row, flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", required=True)
    parser.add_argument("--index", type=int, nargs="+", required=True)
    parser.add_argument("--variants", default="plain,new,plain,new")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    rows = run(args.store, args.index, args.variants.split(","))
    if args.json:
        from emlpack.threads import pyscf_openblas_core

        write_json(args.json, {"machine": machine_info(), "openblas_core": pyscf_openblas_core(),
                               "rows": rows})


if __name__ == "__main__":
    main()
