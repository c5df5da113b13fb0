"""Benchmark of the response code: the full extended Hessian and all crystal tensors of
beta-glycine (paper-size model, float64, CPU), and the IR spectrum of a 20-atom molecule
(hexane, pairs from the Lewis guess and relaxed).

    python benchmarks/response.py --json benchmarks/results/response.json [--threads 1]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED, machine_info, paper_model, write_json  # noqa: E402


def _timed(fn, repeat: int = 1) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def hexane():
    """C6H14 (20 atoms): RDKit geometry, Lewis-guess pairs."""
    from ase import Atoms
    from rdkit import Chem
    from rdkit.Chem import AllChem

    from emlpack.pairs.guess import lewis_pairs
    from emlpack.structure import Structure

    mol = Chem.AddHs(Chem.MolFromSmiles("CCCCCC"))
    AllChem.EmbedMolecule(mol, randomSeed=7)
    AllChem.MMFFOptimizeMolecule(mol)
    numbers = [a.GetAtomicNum() for a in mol.GetAtoms()]
    pos = mol.GetConformer().GetPositions()
    atoms = Atoms(numbers=numbers, positions=pos)
    return Structure(numbers, pos, lewis_pairs(atoms), source="hexane (RDKit, Lewis pairs)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", help="write results here")
    ap.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    ap.add_argument("--method", default="loop", choices=["loop", "vmap"])
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    from emlpack.io import read_structures
    from emlpack.pairs.relax import relax_pairs
    from emlpack.response import crystal_response_from_hessian, extended_hessian
    from emlpack.spectra import ir_from_hessian

    model = paper_model(torch.float64)
    results: dict = {"machine": machine_info(), "model": "paper-size (fixture weights_paper)",
                     "dtype": "float64", "hessian_method": args.method}

    glycine = read_structures(SHARED / "data" / "beta_glycine_pbe_wannier.xyz")[0]
    t_h, (_, h) = _timed(lambda: extended_hessian(model, glycine, method=args.method))
    t_t, resp = _timed(lambda: crystal_response_from_hessian(h.numpy(), glycine), repeat=3)
    results["beta_glycine"] = {
        "n_variables": int(h.shape[0]),
        "extended_hessian_s": t_h,
        "all_tensors_from_hessian_s": t_t,
        "total_s": t_h + t_t,
        "eps_clamped_diagonal": np.diag(resp.dielectric_clamped).tolist(),
    }
    print(f"beta-glycine: extended Hessian {h.shape[0]}x{h.shape[0]} {t_h:.2f} s,"
          f" tensors {t_t * 1e3:.1f} ms")

    mol = hexane()
    t_r, r = _timed(lambda: relax_pairs(model, mol)[0])
    mol = mol.copy(pairs=r.pairs)
    t_i, (_, h_mol) = _timed(lambda: extended_hessian(model, mol, method=args.method))
    t_s, ir = _timed(lambda: ir_from_hessian(h_mol.numpy(), mol), repeat=3)
    results["ir_20_atoms"] = {
        "molecule": mol.source,
        "n_variables": int(h_mol.shape[0]),
        "pair_relaxation_s": t_r,
        "pair_relaxation_reason": r.reason,
        "extended_hessian_s": t_i,
        "spectrum_from_hessian_s": t_s,
        "total_ir_s": t_i + t_s,
        "n_modes": len(ir.frequencies),
    }
    print(f"hexane IR: pair relaxation {t_r:.2f} s, extended Hessian {h_mol.shape[0]}x"
          f"{h_mol.shape[0]} {t_i:.2f} s, spectrum {t_s * 1e3:.1f} ms")
    if args.json:
        write_json(args.json, results)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
