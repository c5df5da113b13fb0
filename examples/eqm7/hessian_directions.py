"""Cartesian (ASE Vibrations, 6N + 1 force calls) against internal (the 3N - 6 vibrational
directions, 2(3N - 6) + 1 calls) central-difference Hessians of one DFT reference molecule:
frequencies, IR intensities (with the reference's Born charges) and CPU time.

    OMP_NUM_THREADS=1 python examples/eqm7/hessian_directions.py [NAME] [LEVEL]

Defaults: qm7-0011 (aziridine) at its paper-level optimum, level ``quick`` (PBE0/6-31G*).
Measured 2026-11-27 (shared 2-core host): 49 calls and 158 s CPU against 37 calls and 125 s;
frequencies within 0.20 cm^-1, intensities within 4e-4 of the largest.
"""

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from ase import Atoms

from emlpack.qm.labeling import finite_difference_hessian, labeler_calculator
from emlpack.qm.pyscf_labeler import PySCFLabeler

sys.path.insert(0, str(Path(__file__).parent))
from run_study import harmonic_ir  # noqa: E402

REFS = Path(__file__).parents[2] / "datasets/mini-eqm7/references/pbe0_aug-cc-pvtz"


def main(name: str = "qm7-0011", level: str = "quick") -> None:
    ref = json.loads((REFS / f"{name}.json").read_text())
    z, r, born = (np.array(ref[k]) for k in ("numbers", "positions", "born_charges_e"))
    out = {}
    for directions in ("cartesian", "internal"):
        atoms = Atoms(numbers=z, positions=r)
        atoms.calc = labeler_calculator(PySCFLabeler(level, boys_starts=1, reuse_density=True))
        t0 = time.process_time()
        with tempfile.TemporaryDirectory() as tmp:
            h = finite_difference_hessian(atoms, 0.005, cache=Path(tmp) / "vib",
                                          directions=directions)
            calls = len(list((Path(tmp) / "vib").glob("*[+-].*"))) + 1
        out[directions] = dict(harmonic_ir(h, born, z, r), cpu_s=time.process_time() - t0,
                               calls=calls)
        print(f"{directions}: {calls} force calls, {out[directions]['cpu_s']:.0f} s CPU")
    c, i = out["cartesian"], out["internal"]
    df = np.abs(c["frequencies"] - i["frequencies"]).max()
    di = np.abs(c["intensities"] - i["intensities"]).max() / c["intensities"].max()
    print(f"frequencies: largest difference {df:.3f} cm^-1; intensities: {di:.1e} of the largest")

if __name__ == "__main__":
    main(*sys.argv[1:])
