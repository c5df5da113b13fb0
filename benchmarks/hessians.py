"""Exact Hessian blocks of the pair solvers: closed form against the earlier ways, CPU time.

* pair blocks (``pair_hessian``): ``"fast"`` (closed-form SchNet pair block plus the analytic
  electrostatics) against ``"reverse"`` (one reverse pass per column), each with its graph;
* MD's fresh-start blocks (``exact_blocks``: pair-pair and core-pair from the closed-form
  extended Hessian) against the forward differences of the gradient used before
  (``difference_blocks``).

Molecules from RDKit (ethanol, C4H7NO2, hexane) with guessed and relaxed pairs, member 0 of the
pretrained ``mini-eqm7``; the two ways alternate in one process (``--repeats`` each), 1 thread.
Largest differences are reported relative to the largest element.

Usage: OMP_NUM_THREADS=1 python benchmarks/hessians.py [--json hessians.json] [--repeats 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_info, write_json  # noqa: E402


def cpu_ms(f, *args, **kwargs) -> float:
    """CPU milliseconds of ``f(*args, **kwargs)``."""
    t = time.process_time()
    f(*args, **kwargs)
    return 1e3 * (time.process_time() - t)


def main() -> None:
    from ase import Atoms

    from emlpack.calculators.ensemble import load_pretrained
    from emlpack.io import atoms_to_structure
    from emlpack.pairs.guess import guess_pairs
    from emlpack.pairs.relax import pair_hessian, relax_pairs
    from emlpack.pairs.solvers import difference_blocks, energy_gradient_function, exact_blocks
    from emlpack.qm.sampling import molecule_from_smiles

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_pretrained("mini-eqm7").members[0].model
    rows = []
    for smiles in ("CCO", "CC(=O)NCC=O", "CCCCCC"):
        mol = molecule_from_smiles(smiles)
        atoms = Atoms(numbers=mol.numbers, positions=mol.positions)
        s = atoms_to_structure(atoms, pairs=guess_pairs(atoms))
        s = s.copy(pairs=relax_pairs(model, s)[0].pairs)
        evaluate = energy_gradient_function(model, s)[0]
        fast, rev = pair_hessian(model, s), pair_hessian(model, s, method="reverse")
        (hpp, hcp), (fpp, fcp) = exact_blocks(model, s), difference_blocks(evaluate, s.pairs,
                                                                          s.n_cores)
        t = {"pair_fast": [], "pair_reverse": [], "blocks_exact": [], "blocks_differences": []}
        for _ in range(args.repeats):
            t["pair_reverse"].append(cpu_ms(pair_hessian, model, s, method="reverse"))
            t["pair_fast"].append(cpu_ms(pair_hessian, model, s))
            t["blocks_differences"].append(cpu_ms(difference_blocks, evaluate, s.pairs,
                                                  s.n_cores))
            t["blocks_exact"].append(cpu_ms(exact_blocks, model, s))
        row = {"smiles": smiles, "pairs": int(s.n_pairs), "cpu_ms": t,
               "pair_fast_vs_reverse": float(np.abs(fast - rev).max() / np.abs(rev).max()),
               "differences_error": float(max(np.abs(fpp - hpp).max(), np.abs(fcp - hcp).max())
                                          / np.abs(hpp).max())}
        rows.append(row)
        print(f"{smiles} ({s.n_pairs} pairs): pair block reverse"
              f" {min(t['pair_reverse']):.0f}-{max(t['pair_reverse']):.0f} ms, fast"
              f" {min(t['pair_fast']):.0f}-{max(t['pair_fast']):.0f} ms (agree to"
              f" {row['pair_fast_vs_reverse']:.1e}); MD blocks differences"
              f" {min(t['blocks_differences']):.0f}-{max(t['blocks_differences']):.0f} ms, exact"
              f" {min(t['blocks_exact']):.0f}-{max(t['blocks_exact']):.0f} ms (differences' error"
              f" {row['differences_error']:.1e})")
    if args.json:
        write_json(args.json, {"benchmark": "exact Hessian blocks", "rows": rows,
                               "machine": machine_info()})


if __name__ == "__main__":
    main()
