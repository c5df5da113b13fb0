"""``emlp demo``: the end-to-end path on data the package generates itself.

1. Geometries of small molecules (ASE's built-in set), displaced randomly, each under a random
   homogeneous field (|E| <= 0.01 au).
2. DFT labels with PySCF at a cheap level (PBE0/STO-3G): energy, forces and Foster-Boys
   electron-pair centres.
3. Written to and read back from an extxyz file (native convention).
4. An eMLP (small, untrained, seeded) saved as a checkpoint, loaded into the ASE calculator:
   static energies/forces at the DFT centres, then Born-Oppenheimer relaxation of the pairs
   with diagnostics, BO forces and dipoles.

Training (and with it meaningful predictions) is added by the training workflow; until then
the model is untrained and the numbers only show that the pipeline runs end to end.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from ase.build import molecule

MOLECULES = ("H2O", "NH3", "CH4")
DEMO_LEVEL = "tiny"


def _write_json(path: Path, data: dict) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        json.dump(data, fh, indent=2)
    os.replace(tmp, path)


def generate_labels(path: Path, n_per_molecule: int = 1, seed: int = 0) -> list:
    """Label displaced molecules under random fields with PySCF; write them to ``path``."""
    from emlpack.io import write_structures
    from emlpack.qm.pyscf_labeler import PySCFLabeler
    from emlpack.qm.sampling import random_field

    rng = np.random.default_rng(seed)
    labeler = PySCFLabeler(DEMO_LEVEL, seed=seed)
    structures = []
    for name in MOLECULES:
        atoms = molecule(name)
        for k in range(n_per_molecule):
            positions = atoms.positions + rng.normal(scale=0.03, size=atoms.positions.shape)
            field = random_field(rng)  # V/Å, |E| <= 0.01 au
            t0 = time.perf_counter()
            result = labeler(atoms.numbers, positions, field=field)
            s = result.to_structure(source=f"demo {name} #{k}")
            print(
                f"  labeled {name} #{k}: E = {s.energy:.4f} eV, {s.n_pairs} pairs,"
                f" |F|max = {np.abs(s.forces).max():.3f} eV/Å ({time.perf_counter() - t0:.1f} s)"
            )
            structures.append(s)
    write_structures(path, structures, convention="native")
    return structures


def run_demo(output: str | Path = "demo_output") -> int:
    """Run the demo, writing labels, model and a summary under ``output``."""
    from ase.calculators.calculator import CalculationFailed

    from emlpack.calculator import EMLPCalculator
    from emlpack.io import read_structures, structure_to_atoms
    from emlpack.nn import EMLP, ModelConfig
    from emlpack.nn.checkpoint import save_model

    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    labels = out / "labels.xyz"
    print(f"[1/3] DFT labels ({DEMO_LEVEL}: PBE0/STO-3G) with Foster-Boys centres -> {labels}")
    if labels.exists():
        print("  (found from an earlier run: reused)")
    else:
        generate_labels(labels)
    structures = read_structures(labels)

    print("[2/3] eMLP model (untrained, seeded) -> model.pt")
    torch.manual_seed(0)
    config = ModelConfig(n_features=64, n_filters=32, n_rbf=16, n_interactions=2)
    model_path = save_model(EMLP(config), out / "model.pt", metadata={"demo": True})

    print("[3/3] static model at the DFT centres, then Born-Oppenheimer pair relaxation")
    rows = []
    for s in structures:
        atoms = structure_to_atoms(s)
        static = EMLPCalculator(model_path, relax_pairs=False)
        atoms.calc = static
        row = {
            "structure": s.source,
            "formula": atoms.get_chemical_formula(),
            "dft_energy_eV": s.energy,
            "model_energy_at_dft_centres_eV": float(atoms.get_potential_energy()),
            "model_max_pair_force_at_dft_centres_eV_per_A": float(
                np.linalg.norm(static.results["pair_forces"], axis=1).max()
            ),
        }
        atoms.calc = EMLPCalculator(model_path)
        try:
            row["bo_energy_eV"] = float(atoms.get_potential_energy())
            row["bo_dipole_eA"] = atoms.get_dipole_moment().tolist()
            row["bo_max_core_force_eV_per_A"] = float(np.abs(atoms.get_forces()).max())
        except CalculationFailed as exc:
            row["bo_failure"] = str(exc)
        r = atoms.calc.relax_result
        row["relaxation"] = {
            "converged": r.converged,
            "iterations": r.iterations,
            "evaluations": r.n_evaluations,
            "max_pair_force": r.max_force,
            "min_pair_curvature": r.min_curvature,
            "reason": r.reason,
        }
        status = "converged" if r.converged else f"FAILED ({r.reason})"
        print(
            f"  {row['formula']:>4}: E(static) = {row['model_energy_at_dft_centres_eV']:9.4f} eV,"
            f" relaxation {status} in {r.iterations} steps"
        )
        rows.append(row)
    summary = {
        "note": "untrained model: the numbers show the pipeline, not eMLP accuracy",
        "level": DEMO_LEVEL,
        "model": str(model_path),
        "results": rows,
    }
    _write_json(out / "summary.json", summary)
    print(f"wrote {out / 'summary.json'}")
    return 0
