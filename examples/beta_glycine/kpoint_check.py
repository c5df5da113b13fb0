"""Beta-glycine's input cell (the paper's PBE cell): CP2K energy and stress at the campaign's
level with the Gamma point only (OT, as the campaign runs) against 3x2x3 Monkhorst-Pack
k-points (diagonalisation and Broyden mixing; OT cannot do k-points). A diagnostic for the
optimisation on hold (examples/beta_glycine/HOLD): does Gamma-only sampling of the 5 Å cell
drive the slide? One process each, one after the other; files in runs/bg_kpoints/.

Usage (from the project root): OMP_NUM_THREADS=1 python examples/beta_glycine/kpoint_check.py
"""
import re
import subprocess
import time
from pathlib import Path

from emlpack.io import read_structures
from emlpack.qm.cp2k.input import CP2KSettings, build_input

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
OT = """      &OT
        MINIMIZER DIIS
        PRECONDITIONER FULL_SINGLE_INVERSE
      &END OT
      &OUTER_SCF
        EPS_SCF 1e-06
        MAX_SCF 20
      &END OUTER_SCF"""
DIAGONALISATION = """      &DIAGONALIZATION
        ALGORITHM STANDARD
      &END DIAGONALIZATION
      &MIXING
        METHOD BROYDEN_MIXING
        ALPHA 0.3
        NBROYDEN 8
      &END MIXING"""
KPOINTS = """    &KPOINTS
      SCHEME MONKHORST-PACK 3 2 3
      FULL_GRID OFF
    &END KPOINTS
    &QS
"""


def main() -> None:
    s = read_structures(SHARED / "data" / "beta_glycine_pbe_wannier.xyz")[0]
    st = CP2KSettings(wannier=False, n_processes=1, mpirun=None, eps_scf=1e-6)
    base = build_input(s, st, stress=True)
    assert OT in base and "      MAX_SCF 20\n" in base
    kp = base.replace(OT, DIAGONALISATION).replace("    &QS\n", KPOINTS)
    kp = kp.replace("      MAX_SCF 20\n", "      MAX_SCF 200\n", 1)
    for name, text in (("gamma", base), ("k323", kp)):
        d = Path("runs/bg_kpoints") / name
        d.mkdir(parents=True, exist_ok=True)
        (d / "in.inp").write_text(text)
        t = time.time()
        subprocess.run(["cp2k.psmp", "-i", "in.inp", "-o", "out.log"], cwd=d, check=False,
                       env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
        out = (d / "out.log").read_text()
        e = re.findall(r"ENERGY\| Total FORCE_EVAL \( QS \) energy \[a\.u\.\]:\s+(\S+)", out)
        stress = re.search(r"STRESS\| Analytical stress tensor \[GPa\]\n(.*?\n.*?\n.*?\n.*?\n)",
                           out, re.S)
        print(name, f"{time.time() - t:.0f} s", "E", e[-1:] if e else None, flush=True)
        print(stress.group(1) if stress else out[-1500:], flush=True)


if __name__ == "__main__":
    main()
