"""Can the crystal labels use k-points? Beta-glycine's input cell (the paper's PBE cell, with the
paper's Quantum ESPRESSO + Wannier90 centres beside it) at the campaign's level:

* ``gamma``: the Gamma point only, OT, CP2K's own ``&LOCALIZE`` Wannier centres (as the
  campaign labels today);
* ``k323``: 3x2x3 Monkhorst-Pack k-points (diagonalisation, Broyden mixing), CP2K's
  ``&PRINT &WANNIER90`` interface (it diagonalises the converged k-point Kohn-Sham matrix on
  the full grid and writes the overlaps ``.mmn``), then ``wannier90.x`` (Debian's) from Bloch
  phases: maximally localised Wannier centres of the k-point density;
* ``k333``: the same with the paper's 3x3x3 mesh (Wannier90 3.1 refuses CP2K's 3x2x3
  overlaps: "Non-symmetric k-point neighbours", a mesh of 2 along b);
* ``k323_field``: the k-point input with a small Berry-phase field (``PERIODIC_EFIELD``), one
  SCF step: does CP2K 2023.1 accept a field with k-points?
* ``k212_stress``, ``k222_stress``, ``k323_stress``: the stress with coarser meshes against
  3x2x3 (is a Gamma-point supercell of 2x1x2 or 2x2x2 cells converged enough?);
* ``gamma_212``: the 2x1x2 supercell (80 atoms) at the Gamma point only, OT, stress and
  ``&LOCALIZE`` centres (the first cell's, folded): the cost of a supercell label and its
  agreement with the 2x1x2 mesh (the same sampling).

For each centre set: the distances to the paper's centres after the best one-to-one matching
(minimum image), median and max (Å), and the total spread. CPU seconds of each run, stress in
GPa (CP2K's sign). Files in runs/bg_wannier_kpoints/; a summary in
examples/beta_glycine/wannier_kpoints_check.json (re-running a case replaces its entry).

Usage (from the project root, one core): OMP_NUM_THREADS=1 python
examples/beta_glycine/wannier_kpoints_check.py [--only CASE ...]
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from emlpack.geometry import minimum_image
from emlpack.io import read_structures
from emlpack.qm.cp2k import CP2KLabeler
from emlpack.qm.cp2k.input import CP2KSettings, build_input
from emlpack.qm.cp2k.output import STRESS_SIGN, map_centres_to_cores
from emlpack.units import EV_PER_A3_IN_GPA, HARTREE

sys.path.insert(0, str(Path(__file__).resolve().parent))
from kpoint_check import DIAGONALISATION, OT  # noqa: E402  (the same k-point SCF settings)

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[1].parent / "shared"
RUNS = Path("runs/bg_wannier_kpoints")
KPOINTS = """    &KPOINTS
      SCHEME MONKHORST-PACK {} {} {}
      FULL_GRID OFF
    &END KPOINTS
    &QS
"""
CASES = ("gamma", "k323", "k333", "k323_field", "k212_stress", "k222_stress", "k323_stress",
         "gamma_212")
WANNIER90 = """    &PRINT
      &WANNIER90
        SEED_NAME bg
        MP_GRID {} {} {}
        WANNIER_FUNCTIONS {}
      &END WANNIER90
    &END PRINT
  &END DFT"""
W90_EXTRA = """
use_bloch_phases = .true.
num_iter = 5000
conv_tol = 1e-10
conv_window = 5
write_xyz = .true.
translate_home_cell = .true.
"""


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run(cmd: list[str], cwd: Path) -> float:
    """Run ``cmd`` in ``cwd`` on one thread; its CPU seconds."""
    t = cpu_seconds()
    subprocess.run(cmd, cwd=cwd, check=False, stdout=subprocess.DEVNULL,
                   stderr=subprocess.STDOUT, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    return cpu_seconds() - t


def compare(centres: np.ndarray, reference: np.ndarray, cell: np.ndarray) -> dict:
    """Distances (Å) between two centre sets after the best one-to-one matching (minimum image)."""
    d = np.linalg.norm(minimum_image(centres[:, None] - reference[None], cell), axis=-1)
    rows, cols = linear_sum_assignment(d)
    dist = d[rows, cols]
    return {"n": int(len(centres)), "median_A": float(np.median(dist)),
            "max_A": float(dist.max()), "mean_A": float(dist.mean())}


def stress_gpa(out: str) -> list | None:
    """CP2K's analytical stress (GPa, CP2K's sign), rounded, or None."""
    i = out.rfind("STRESS| Analytical stress tensor [GPa]")
    rows = re.findall(r"^ STRESS\|\s+[xyz]\s+(\S+)\s+(\S+)\s+(\S+)\s*$", out[i:],
                      re.MULTILINE)[:3] if i >= 0 else []
    return np.round(np.array(rows, dtype=float), 3).tolist() if len(rows) == 3 else None


def wannier90_centres(wout: str) -> tuple[np.ndarray, float]:
    """The final Wannier centres (Å) and total spread (Å²) from ``wannier90.x``'s ``.wout``."""
    final = wout[wout.rfind("Final State"):]
    rows = re.findall(r"WF centre and spread\s+\d+\s+\(\s*(\S+),\s*(\S+),\s*(\S+)\s*\)\s+(\S+)",
                      final)
    unit = 0.529177210903 if re.search(r"Length Unit\s*:\s*Bohr", wout) else 1.0
    # the centres are printed in the length unit; spreads in its square
    xyz = np.array([r[:3] for r in rows], dtype=float) * unit
    m = re.search(r"Sum of centres and spreads.*?\)\s+(\S+)", final)
    spread = float(m.group(1)) * unit ** 2 if m else float("nan")
    return xyz, spread


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="*", default=list(CASES), choices=CASES)
    args = ap.parse_args()
    s = read_structures(SHARED / "data" / "beta_glycine_pbe_wannier.xyz")[0]
    n_pairs = len(s.pairs)
    summary_path = HERE / "wannier_kpoints_check.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    summary["structure"] = "shared/data/beta_glycine_pbe_wannier.xyz (the paper's PBE cell)"
    summary["reference_centres"] = "the paper's (Quantum ESPRESSO PBE, 3x3x3, Wannier90)"
    for name in args.only:
        d = RUNS / name
        d.mkdir(parents=True, exist_ok=True)
        if name in ("gamma", "gamma_212"):  # the campaign's labeler, its Γ-point supercell
            reps = (2, 1, 2) if name == "gamma_212" else (1, 1, 1)
            clock = cpu_seconds()
            labeled = CP2KLabeler(CP2KSettings(n_processes=1, mpirun=None, eps_scf=1e-6,
                                               supercell=reps), workdir=d)(s, stress=True)
            row = {"cp2k_cpu_s": round(cpu_seconds() - clock, 1), "level": labeled.info["level"],
                   "energy_eV_per_cell": labeled.energy,
                   "stress_gpa": np.round(STRESS_SIGN * labeled.stress * EV_PER_A3_IN_GPA,
                                          3).tolist(),
                   "vs_paper": compare(labeled.pairs, s.pairs, s.cell)}
            np.save(d / "centres.npy", labeled.pairs)
            g = RUNS / "gamma" / "centres.npy"
            if name == "gamma_212" and g.exists():
                row["vs_gamma"] = compare(labeled.pairs, np.load(g), s.cell)
            summary[name] = row
            print(name, json.dumps(row), flush=True)
            summary_path.write_text(json.dumps(summary, indent=1) + "\n")
            continue
        mesh = tuple(int(c) for c in name[1:4])
        text = build_input(s, CP2KSettings(wannier=False, n_processes=1, mpirun=None,
                                           eps_scf=1e-6), stress=name.endswith("_stress"))
        assert OT in text
        text = text.replace(OT, DIAGONALISATION).replace("    &QS\n",
                                                          KPOINTS.format(*mesh))
        text = text.replace("      MAX_SCF 20\n", "      MAX_SCF 200\n", 1)
        if name in ("k323", "k333"):
            text = text.replace("  &END DFT", WANNIER90.format(*mesh, n_pairs), 1)
        elif name == "k323_field":  # a field with k-points: setup only (one SCF step)
            text = text.replace("  &END DFT", """    &PERIODIC_EFIELD
      INTENSITY 1.0e-3
      POLARISATION 1.0 0.0 0.0
    &END PERIODIC_EFIELD
  &END DFT""", 1).replace("      MAX_SCF 200\n", "      MAX_SCF 1\n", 1)
        (d / "in.inp").write_text(text)
        seconds = run(["cp2k.psmp", "-i", "in.inp", "-o", "out.log"], d)
        out = (d / "out.log").read_text() if (d / "out.log").exists() else ""
        row: dict = {"cp2k_cpu_s": round(seconds, 1)}
        e = re.findall(r"ENERGY\| Total FORCE_EVAL \( QS \) energy \[a\.u\.\]:\s+(\S+)", out)
        row["energy_eV_per_cell"] = float(e[-1]) * HARTREE if e else None
        abort = re.search(r"\[ABORT\].*?\n(.*?)\n", out, re.S) or re.search(
            r"ABORT(.*?)\n", out)
        if abort:
            row["abort"] = " ".join(abort.group(0).split())[:300]
        row["stress_gpa"] = stress_gpa(out)
        if name in ("k323", "k333") and (d / "bg.win").exists():
            with (d / "bg.win").open("a") as f:
                f.write(W90_EXTRA)
            row["wannier90_cpu_s"] = round(run(["wannier90.x", "bg"], d), 1)
            wout = (d / "bg.wout").read_text() if (d / "bg.wout").exists() else ""
            c, spread = wannier90_centres(wout)
            row["spread_A2"] = spread if np.isfinite(spread) else None
            if len(c) == n_pairs:
                c, _ = map_centres_to_cores(c, s.positions, s.cell)
                row["vs_paper"] = compare(c, s.pairs, s.cell)
                np.save(d / "centres.npy", c)
                g = RUNS / "gamma" / "centres.npy"
                if g.exists():
                    row["vs_gamma"] = compare(c, np.load(g), s.cell)
            else:
                row["error"] = f"{len(c)} Wannier90 centres for {n_pairs} pairs"
        summary[name] = row
        print(name, json.dumps(row), flush=True)
        summary_path.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
