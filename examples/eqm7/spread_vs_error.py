"""Ensemble spread against the actual error of a pretrained ensemble (pairs at the DFT centres).

    python examples/eqm7/spread_vs_error.py [DATA] [MODEL]

DATA: a data-set folder of the campaign (default ``datasets/mini-eqm7``; its validation and test
molecules are used) and, when present, the authors' six molecules (every 10th frame of
``../shared/data/eqm7_pbe0_subset.xyz``); MODEL: a pretrained name or ensemble folder (default
``mini-eqm7``). Prints, per set, the medians of the energy spread and error per atom (eV/atom)
and of the largest force-component spread and error (eV/Å), their correlations, and how often
the calculator's default spread warnings (0.02 eV/atom, 0.5 eV/Å) fire.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from emlpack.calculators.ase import EMLPCalculator
from emlpack.calculators.ensemble import as_ensemble
from emlpack.data.shards import read_shards
from emlpack.io import read_structures, structure_to_atoms

ROOT = Path(__file__).resolve().parents[2]


def spread_and_error(ensemble, structures) -> dict[str, np.ndarray]:
    out: dict[str, list] = {"e_spread": [], "e_error": [], "f_spread": [], "f_error": []}
    for s in structures:
        atoms = structure_to_atoms(s)
        atoms.calc = EMLPCalculator(ensemble, relax_pairs=False)
        n = len(atoms)
        error = atoms.get_potential_energy() - s.energy
        out["e_spread"].append(atoms.calc.results["energy_std"] / n)
        out["e_error"].append(abs(error) / n)
        out["f_spread"].append(float(np.max(atoms.calc.results["forces_std"])))
        out["f_error"].append(float(np.max(np.abs(atoms.get_forces() - s.forces))))
    return {k: np.asarray(v) for k, v in out.items()}


def main(argv: list[str]) -> None:
    data = Path(argv[0]) if argv else ROOT / "datasets" / "mini-eqm7"
    ensemble = as_ensemble(argv[1] if len(argv) > 1 else "mini-eqm7")
    shards = read_shards(data)
    split = shards.split_indices()
    sets = {name: [shards.structures[i] for i in split[name]] for name in ("val", "test")}
    six = ROOT.parent / "shared" / "data" / "eqm7_pbe0_subset.xyz"
    if six.exists():
        sets["authors' six"] = read_structures(six)[::10]
    for name, structures in sets.items():
        r = spread_and_error(ensemble, structures)
        print(f"{name} ({len(structures)} configurations): energy spread/error median"
              f" {np.median(r['e_spread']):.3f}/{np.median(r['e_error']):.3f} eV/atom,"
              f" correlation {np.corrcoef(r['e_spread'], r['e_error'])[0, 1]:.2f},"
              f" warned {np.mean(r['e_spread'] > 0.02):.0%}; largest force spread/error median"
              f" {np.median(r['f_spread']):.3f}/{np.median(r['f_error']):.3f} eV/Å,"
              f" correlation {np.corrcoef(r['f_spread'], r['f_error'])[0, 1]:.2f},"
              f" warned {np.mean(r['f_spread'] > 0.5):.0%}")


if __name__ == "__main__":
    main(sys.argv[1:])
