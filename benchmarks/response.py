"""Benchmark of the response code: the full extended Hessian and all crystal tensors of
beta-glycine, and the IR spectrum / polarizability of a 20-atom molecule (hexane, pairs from
the Lewis guess and relaxed), CPU, float64.

Every Hessian is computed with today's reference method (``method="reference"``: reverse over
reverse through the whole energy), the default fast method and the fast method with float32
SchNet directions (``mixed=True``), in the same process. Written: wall and CPU time of each,
``hessian_speedup`` (reference wall time / fast wall time, beta-glycine; also
``hessian_speedup_cpu``), the largest relative Hessian difference to the reference, and the
relative change of every reported tensor (polarizabilities, BO Hessian, IR frequencies and
intensities, dielectric, stiffness and piezoelectric tensors) caused by the fast and the mixed
method: ``max |T - T_ref| / max |T_ref|``.

    OMP_NUM_THREADS=1 python benchmarks/response.py --json /tmp/response.json --threads 1
    OMP_NUM_THREADS=1 python benchmarks/response.py --model trained --relax ...

``--model fixture`` (default): paper-size model with the reference fixture's random weights, at
the PBE Wannier geometry of beta-glycine; ``--model trained``: the small trained benchmark
model (``--relax``: pairs and positions of beta-glycine relaxed first, as for real use).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED, benchmark_model, machine_info, write_json  # noqa: E402

METHODS = {
    "reference": {"method": "reference"},
    "fast": {"method": "fast"},
    "mixed": {"method": "fast", "mixed": True},
}


def _timed(fn, repeat: int = 1) -> tuple[dict, object]:
    """Best wall and CPU time (s) of ``repeat`` calls, and the last result."""
    wall, cpu, out = float("inf"), float("inf"), None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return {"wall_s": wall, "cpu_s": cpu, "load_average": list(os.getloadavg())}, out


def _rel(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.abs(a - b).max() / np.abs(b).max())


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


def hessians(model, structure, repeat: int) -> tuple[dict, dict]:
    """Timings and Hessians (numpy) of every method; the reference is run once."""
    from emlpack.properties.hessian import extended_hessian

    extended_hessian(model, structure)  # warm-up: folded weights, first-call costs
    times, out = {}, {}
    for name, kwargs in METHODS.items():
        t, (_, h) = _timed(lambda kw=kwargs: extended_hessian(model, structure, **kw),
                           1 if name == "reference" else repeat)
        times[name], out[name] = t, h.numpy()
    ref = out["reference"]
    for name in ("fast", "mixed"):
        times[name]["hessian_rel_diff_vs_reference"] = _rel(out[name], ref)
    return times, out


def crystal_tensors(h: np.ndarray, s) -> dict:
    from emlpack.properties.response import crystal_response_from_hessian

    d = crystal_response_from_hessian(h, s).as_dict()
    keys = ("dielectric_ion_clamped", "dielectric_relaxed", "stiffness_voigt_GPa",
            "stiffness_clamped_ion_voigt_GPa", "piezo_e_voigt_C_per_m2",
            "piezo_e_clamped_ion_voigt_C_per_m2", "piezo_d_voigt_pm_per_V")
    return {k: np.array(d[k]) for k in keys}


def molecule_tensors(h: np.ndarray, s) -> dict:
    from emlpack.properties.ir import ir_from_hessian
    from emlpack.properties.response import born_oppenheimer_blocks, polarizability_from_hessian

    bo, dmu, _ = born_oppenheimer_blocks(h, s)
    ir = ir_from_hessian(h, s)
    real = np.abs(ir.frequencies) > 50.0  # rigid-body modes excluded
    return {
        "polarizability": polarizability_from_hessian(h, s),
        "polarizability_relaxed_cores": polarizability_from_hessian(h, s, relax_cores=True),
        "bo_core_hessian": bo,
        "dipole_derivatives": dmu,
        "ir_frequencies": ir.frequencies[real],
        "ir_intensities": ir.intensities[real],
    }


def tensor_changes(tensors: dict) -> dict:
    ref = tensors["reference"]
    return {name: {k: _rel(tensors[name][k], ref[k]) for k in ref} for name in ("fast", "mixed")}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", help="write results here")
    ap.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    ap.add_argument("--model", default="fixture", help="fixture | trained | checkpoint path")
    ap.add_argument("--relax", action="store_true",
                    help="relax beta-glycine's pairs and positions first (Newton, fixed cell)")
    ap.add_argument("--repeat", type=int, default=3, help="best of this many fast runs")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    from emlpack.io import read_structures
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.optimize import optimize

    model = benchmark_model(args.model, torch.float64)
    results: dict = {"machine": machine_info(), "model": args.model, "dtype": "float64",
                     "methods": {k: str(v) for k, v in METHODS.items()}}

    glycine = read_structures(SHARED / "data" / "beta_glycine_pbe_wannier.xyz")[0]
    if args.relax:
        opt = optimize(model, glycine)
        glycine = opt.structure
        results["beta_glycine_relaxation"] = {"converged": opt.converged,
                                              "iterations": opt.iterations}
    times, hs = hessians(model, glycine, args.repeat)
    t_t, _ = _timed(lambda: crystal_tensors(hs["fast"], glycine), repeat=3)
    tensors = {name: crystal_tensors(h, glycine) for name, h in hs.items()}
    results["hessian_speedup"] = times["reference"]["wall_s"] / times["fast"]["wall_s"]
    results["hessian_speedup_cpu"] = times["reference"]["cpu_s"] / times["fast"]["cpu_s"]
    results["hessian_speedup_mixed"] = times["reference"]["wall_s"] / times["mixed"]["wall_s"]
    results["beta_glycine"] = {
        "n_variables": int(hs["fast"].shape[0]),
        "extended_hessian": times,
        "all_tensors_from_hessian_s": t_t["wall_s"],
        "tensor_rel_changes": tensor_changes(tensors),
        "eps_clamped_diagonal": np.diag(tensors["fast"]["dielectric_ion_clamped"]).tolist(),
    }
    print(f"beta-glycine {hs['fast'].shape[0]} variables: reference "
          f"{times['reference']['wall_s']:.2f} s ({times['reference']['cpu_s']:.2f} s CPU), "
          f"fast {times['fast']['wall_s']:.3f} s ({times['fast']['cpu_s']:.3f} s CPU), mixed "
          f"{times['mixed']['wall_s']:.3f} s ({times['mixed']['cpu_s']:.3f} s CPU); "
          f"speedup {results['hessian_speedup']:.1f}x wall, "
          f"{results['hessian_speedup_cpu']:.1f}x CPU")

    mol = hexane()
    t_r, r = _timed(lambda: relax_pairs(model, mol)[0])
    mol = mol.copy(pairs=r.pairs)
    times_mol, hs_mol = hessians(model, mol, args.repeat)
    t_s, ir = _timed(lambda: molecule_tensors(hs_mol["fast"], mol), repeat=3)
    tensors_mol = {name: molecule_tensors(h, mol) for name, h in hs_mol.items()}
    results["ir_20_atoms"] = {
        "molecule": mol.source,
        "n_variables": int(hs_mol["fast"].shape[0]),
        "pair_relaxation": t_r,
        "pair_relaxation_reason": r.reason,
        "extended_hessian": times_mol,
        "tensors_from_hessian_s": t_s["wall_s"],
        "tensor_rel_changes": tensor_changes(tensors_mol),
    }
    print(f"hexane {hs_mol['fast'].shape[0]} variables: reference "
          f"{times_mol['reference']['wall_s']:.2f} s, fast {times_mol['fast']['wall_s']:.3f} s,"
          f" mixed {times_mol['mixed']['wall_s']:.3f} s")
    for label, block in (("beta-glycine", results["beta_glycine"]),
                         ("hexane", results["ir_20_atoms"])):
        for name, changes in block["tensor_rel_changes"].items():
            worst = max(changes, key=changes.get)
            print(f"  {label} {name}: largest tensor change {changes[worst]:.1e} ({worst})")
    results["machine"]["load_average_end"] = list(os.getloadavg())
    if args.json:
        write_json(args.json, results)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
