"""Electron-pair response to a field: DFT Foster-Boys centre shifts against a model's pair shifts.

    python examples/eqm7/pair_response.py [NAME] [MODEL] [FIELD_AU]

At the DFT optimum of test molecule NAME (default ``qm7-0011``, aziridine; its reference in
``datasets/mini-eqm7/references/pbe0_aug-cc-pvtz/``), fields of +-FIELD_AU (default 0.005 au)
along x, y and z: the valence Boys centres are relabeled at the paper's level (six PySCF
calculations, ~20 s each for aziridine), the model's pairs relaxed (each member of MODEL,
default ``mini-eqm7``); printed per axis, the length of each pair's shift between +F and -F (Å).
Pairs that move farther than the DFT centres make the model's polarizability too large.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from emlpack.calculators.ensemble import as_ensemble
from emlpack.pairs.relax import relax_pairs
from emlpack.qm.pyscf_labeler import PySCFLabeler
from emlpack.structure import Structure
from emlpack.units import FIELD_AU_IN_V_PER_A

REFS = Path(__file__).resolve().parents[2] / "datasets/mini-eqm7/references/pbe0_aug-cc-pvtz"


def nearest(reference: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The point of ``points`` nearest to each row of ``reference``."""
    d = np.linalg.norm(reference[:, None] - points[None], axis=-1)
    return points[d.argmin(1)]


def main(argv: list[str]) -> None:
    name = argv[0] if argv else "qm7-0011"
    ensemble = as_ensemble(argv[1] if len(argv) > 1 else "mini-eqm7")
    field_au = float(argv[2]) if len(argv) > 2 else 0.005
    ref = json.loads((REFS / f"{name}.json").read_text())
    numbers, positions = np.array(ref["numbers"]), np.array(ref["positions"])
    pairs = np.array(ref["pairs"])
    labeler = PySCFLabeler("paper", boys_starts=3)
    for axis in range(3):
        shifted: dict[str, list[np.ndarray]] = {"DFT": []}
        for sign in (1, -1):
            field = np.zeros(3)
            field[axis] = sign * field_au * FIELD_AU_IN_V_PER_A
            centres = np.asarray(labeler(numbers, positions, field, forces=False).centres)
            shifted["DFT"].append(nearest(pairs, centres[-len(pairs):]))
            for k, member in enumerate(ensemble.members):
                s = Structure(numbers, positions, pairs, field=field)
                (r,) = relax_pairs(member.model, [s], fmax=1e-6)
                shifted.setdefault(f"member {k + 1}", []).append(nearest(pairs, r.pairs))
        print(f"{name}, field +-{field_au} au along {'xyz'[axis]}: |shift| per pair (Å)")
        for who, (plus, minus) in shifted.items():
            print(f"  {who:>9}: " + " ".join(f"{x:.4f}" for x in
                                             np.linalg.norm(plus - minus, axis=1)))


if __name__ == "__main__":
    main(sys.argv[1:])
