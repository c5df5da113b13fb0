"""DFT polarizabilities of mini-eQM7's 15 validation molecules (issue 51, item 1).

Every decision of mini-eQM7 v2 (the bake-off, the pretraining pilot of issue 50) is taken on
validation molecules, never on test ones; the models' polarizabilities need references for
them. Per molecule, at its prepared geometry (the GFN2-xTB optimum of
``datasets/mini-eqm7/prepared/NAME.npz``, a fixed geometry: a model is evaluated there with the
cores clamped and its pairs relaxed), at the paper's level (PBE0/aug-cc-pVTZ + DF): the ground
state (energy, forces, Foster-Boys centres, dipole) and the polarizability from six central
finite fields of 1e-3 au (:func:`emlpack.qm.finite_field.finite_field_response`). Every
calculation is a small file under ``REFS/validation/NAME/`` (written atomically, never
recomputed); ``REFS/validation/NAME.json`` is the result. ``--commit`` commits the finished
files every 25 minutes and at the end::

    OMP_NUM_THREADS=1 python examples/eqm7/validation_references.py --commit

Cost (measured on qm7-0014, 10 atoms, one thread): about a minute for the six fields.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from emlpack._files import write_npz_atomic, write_text_atomic
from emlpack.commits import git_commit
from emlpack.data.shards import read_molecule_table
from emlpack.qm.finite_field import finite_field_response
from emlpack.qm.levels import PAPER
from emlpack.qm.pyscf_labeler import PySCFLabeler

DATA = Path("datasets/mini-eqm7")
OUT = DATA / "references" / "pbe0_aug-cc-pvtz" / "validation"
FIELD_AU = 1e-3


def reference(name: str, smiles: str) -> dict:
    """The validation reference of one molecule (cached per calculation under OUT/NAME/)."""
    cache = OUT / name
    with np.load(DATA / "prepared" / f"{name}.npz") as prep:
        numbers, positions = prep["numbers"], prep["positions"]
    t0 = time.process_time()
    ground_path = cache / "ground.npz"
    if not ground_path.exists():
        r = PySCFLabeler(PAPER, boys_starts=3, threads=1)(numbers, positions)
        if not r.ok:
            raise RuntimeError(f"{name}: ground state failed: {r.error}")
        cache.mkdir(parents=True, exist_ok=True)
        write_npz_atomic(ground_path, energy=r.energy, forces=r.forces, pairs=r.pairs,
                         dipole=r.dipole)
    with np.load(ground_path) as g:
        ground = {k: g[k] for k in g.files}
    resp = finite_field_response(PySCFLabeler(PAPER, boys_starts=1, threads=1,
                                              reuse_density=True),
                                 numbers, positions, FIELD_AU, cache=cache)
    alpha = resp.polarizability_bohr3
    return {"name": name, "smiles": smiles, "level": PAPER.name,
            "geometry": "prepared (GFN2-xTB optimum, datasets/mini-eqm7/prepared)",
            "numbers": numbers.tolist(), "positions": positions.tolist(),
            "energy": float(ground["energy"]), "forces": ground["forces"].tolist(),
            "pairs": ground["pairs"].tolist(), "dipole_e_A": ground["dipole"].tolist(),
            "field_step_au": FIELD_AU, "polarizability_bohr3": alpha.tolist(),
            "polarizability_isotropic_bohr3": float(np.trace(alpha) / 3),
            "cpu_s_this_call": time.process_time() - t0}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--commit", action="store_true")
    args = p.parse_args()
    rows = [m for m in read_molecule_table(DATA) if m["split"] == "val"]
    last = time.monotonic()
    for m in sorted(rows, key=lambda m: m["n_heavy"]):
        path = OUT / f"{m['name']}.json"
        if path.exists():
            continue
        res = reference(m["name"], m["smiles"])
        write_text_atomic(path, json.dumps(res, indent=1))
        print(time.strftime("%H:%M:%S"), m["name"],
              f"alpha_iso {res['polarizability_isotropic_bohr3']:.2f} bohr³,"
              f" {res['cpu_s_this_call']:.0f} s", flush=True)
        if args.commit and time.monotonic() - last > 25 * 60:
            git_commit([OUT], "mini-eqm7 validation references: finished files")
            last = time.monotonic()
    if args.commit:
        git_commit([OUT], "mini-eqm7 validation references: all 15")


if __name__ == "__main__":
    main()
