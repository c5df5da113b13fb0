"""DFT Raman reference of aziridine (C1CN1) for ``emlp raman --reference``: PBE0/aug-cc-pVDZ
polarizability derivatives along the normal modes, by finite fields and central differences.

    python examples/raman/aziridine_dft.py [--level pbe0/aug-cc-pvdz] [--threads N]
        [--geometry reference|optimize] [--reverse] [--modes 0,5,17]

(from the project root). The recipe:

1. Geometry and normal modes. ``--geometry reference`` (default): the committed mini-eQM7 IR
   reference of aziridine (``datasets/mini-eqm7/references/pbe0_aug-cc-pvtz/qm7-0011.json``:
   the PBE0/aug-cc-pVTZ optimum and its Cartesian Hessian), so the wavenumbers are those of the
   IR reference and the eMLP's training level; ``--geometry optimize``: BFGS at ``--level`` to
   0.005 eV/Å from that geometry (or RDKit's) and PySCF's analytic Hessian there
   (``OUT/opt.npz``, ``OUT/hessian.npz``). Modes by
   :func:`emlpack.properties.ir.vibrational_modes` (as ``emlp ir``/``emlp raman``): unit
   Cartesian displacements ``c_k`` of the 3N - 6 = 18 modes.
2. Polarizability at ``x0 +- h c_k`` (``h = --step``, 0.01 Å, the whole displacement's norm):
   ``alpha_ij = (mu_i(+F e_j) - mu_i(-F e_j)) / 2F`` (``F = --field-au``, 0.002 au; dipoles of
   :class:`emlpack.qm.pyscf_labeler.PySCFLabeler` at ``--level``, SCF energy to 1e-12 Ha and
   orbital gradient to 1e-8, each SCF started from the nearest converged density), symmetrised.
   (The field differences' error is the hyperpolarizability's ``gamma F^2 / 6``, ~1e-4 of
   alpha for ``gamma ~ 1e3`` au: an estimate, not measured.)
3. ``d alpha/d Q_k = (alpha(+h) - alpha(-h)) / (2 h |M^1/2 c_k|)``, the Raman activities
   ``45 a'^2 + 7 gamma'^2`` (Å⁴/amu) and depolarisation ratios by
   :mod:`emlpack.properties.raman` (the formulas ``emlp raman`` uses), written to
   ``examples/raman/aziridine_LEVEL.json`` (``frequencies_cm-1``, ``activities_A4_per_amu``,
   ``depolarization_ratios``, ...: ``emlp raman mini-eqm7 --smiles C1CN1 --reference FILE``).

Resumable per SCF: the plan (geometry, modes, steps, level) is ``OUT/plan.npz`` and every
SCF's dipole a small immutable file ``OUT/KK+/field_x-.npz`` (mode, displacement sign, field
direction and sign; :mod:`emlpack.qm.finite_field`), written atomically; a re-run computes
only the missing ones, a plan of another geometry, level or step is refused. ``--reverse``
runs the SCFs from the last one back, so a second process can share ``OUT`` with a forward
one. ``OUT`` defaults to ``examples/raman/aziridine_dft/`` (the files can be committed as they
finish, as the mini-eQM7 references are).

Cost: 18 modes x 2 displacements x 6 fields = 216 SCFs (no forces, no localisation) with
``--geometry reference``. Measured at PBE0/aug-cc-pVDZ with density fitting (114 basis
functions, 1 thread, this project's 2-core machine with both cores running DFT jobs):
11-13 SCF cycles and 9-14 s wall (~3 s of CPU) per SCF, so 216 x ~10 s ~ 40 min on a busy
core, ~15 min on an idle one. ``--geometry optimize`` adds a few BFGS steps (SCF + forces)
and PySCF's analytic Hessian (not measured). Smoke test (run):
``--level pbe0/sto-3g --modes 0,12 --out /tmp/aziridine_smoke``: 24 SCFs, 47-59 s wall.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: the project root: the working directory when it holds the data (a long job runs a copy of
#: this file from elsewhere), else this file's checkout
ROOT = (Path.cwd() if (Path.cwd() / "datasets/mini-eqm7").is_dir()
        else Path(__file__).resolve().parents[2])
NAME, SMILES = "aziridine", "C1CN1"
REFERENCE = ROOT / "datasets/mini-eqm7/references/pbe0_aug-cc-pvtz/qm7-0011.json"
LEVEL, STEP_A, FIELD_AU = "pbe0/aug-cc-pvdz", 1e-2, 2e-3
#: SCF convergence of the finite fields: energy (Ha) and orbital gradient
CONV_TOL, CONV_TOL_GRAD = 1e-12, 1e-8
SIGNS = "-+"


class PlanError(RuntimeError):
    """The working folder holds another plan (geometry, level or step)."""


def tight_labeler(level: str, threads: int | None):
    """A :class:`PySCFLabeler` at ``level`` with the SCF convergence of the finite fields."""
    from dataclasses import replace

    from emlpack.qm.levels import DEFAULT_CONV_TOL, parse_level
    from emlpack.qm.pyscf_labeler import PySCFLabeler

    class TightLabeler(PySCFLabeler):
        def build(self, *args, **kwargs):
            mol, mf = super().build(*args, **kwargs)
            mf.conv_tol_grad = CONV_TOL_GRAD
            return mol, mf

    lv = parse_level(level)
    if lv.conv_tol == DEFAULT_CONV_TOL:  # not given in the level's name (``/tolX``)
        lv = replace(lv, conv_tol=CONV_TOL)
    return TightLabeler(lv, threads=threads, reuse_density=True)


def reference_geometry() -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """(numbers, positions Å, Hessian eV/Å², origin) of the committed IR reference."""
    data = json.loads(REFERENCE.read_text())
    return (np.array(data["numbers"]), np.array(data["positions"]),
            np.array(data["hessian_eV_A2"]),
            f"{data['level']} optimum and Hessian ({REFERENCE.relative_to(ROOT)})")


def optimized_geometry(out: Path, labeler) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """(numbers, positions, Hessian, origin) at ``labeler``'s level: BFGS from the reference
    geometry (or RDKit's), PySCF's analytic Hessian; each cached in ``out``."""
    from ase import Atoms
    from ase.optimize import BFGS

    from emlpack._files import write_npz_atomic
    from emlpack.qm.labeling import labeler_calculator, pyscf_hessian

    opt_file, hess_file = out / "opt.npz", out / "hessian.npz"
    if not opt_file.exists():
        if REFERENCE.exists():
            numbers, start = reference_geometry()[:2]
        else:
            from emlpack.qm.sampling import molecule_from_smiles

            mol = molecule_from_smiles(SMILES, name=NAME)
            numbers, start = mol.numbers, mol.positions
        atoms = Atoms(numbers=numbers, positions=start)
        atoms.calc = labeler_calculator(labeler)
        if not BFGS(atoms, logfile=None, restart=str(out / ".bfgs.json")).run(fmax=0.005,
                                                                               steps=100):
            raise RuntimeError("BFGS did not converge in 100 steps")
        write_npz_atomic(opt_file, numbers=numbers, positions=atoms.positions)
    with np.load(opt_file) as d:
        numbers, positions = d["numbers"], d["positions"]
    if not hess_file.exists():
        write_npz_atomic(hess_file, hessian=pyscf_hessian(labeler, numbers, positions))
    with np.load(hess_file) as d:
        hessian = d["hessian"]
    return numbers, positions, hessian, f"{labeler.level.name} optimum and analytic Hessian"


def make_plan(numbers: np.ndarray, positions: np.ndarray, hessian: np.ndarray, origin: str,
              level: str, step: float, field_au: float, conv_tol: float = CONV_TOL) -> dict:
    """The displacements: wavenumbers and unit Cartesian modes of ``hessian``, step, field."""
    from ase.data import atomic_masses

    from emlpack.properties.ir import vibrational_modes

    masses = atomic_masses[numbers]
    freqs, _, modes = vibrational_modes(hessian, positions, masses)
    return {"numbers": np.asarray(numbers), "positions": np.asarray(positions, float),
            "masses": masses, "frequencies": freqs, "modes": modes, "step": float(step),
            "field_au": float(field_au), "level": str(level), "origin": str(origin),
            "conv_tol": float(conv_tol)}


def load_or_save_plan(out: Path, plan: dict) -> dict:
    """``plan``, saved as ``out/plan.npz`` the first time; a saved plan must be the same."""
    from emlpack._files import write_npz_atomic

    path = out / "plan.npz"
    if path.exists():
        with np.load(path) as d:
            saved = {k: d[k] for k in d.files}
        same = (saved["positions"].shape == plan["positions"].shape
                and np.abs(saved["positions"] - plan["positions"]).max() < 1e-10
                and np.abs(np.abs(np.einsum("kij,kij->k", saved["modes"], plan["modes"]))
                           - 1).max() < 1e-8
                and float(saved["step"]) == plan["step"]
                and float(saved["field_au"]) == plan["field_au"]
                and str(saved["level"]) == plan["level"]
                and float(saved.get("conv_tol", CONV_TOL)) == plan["conv_tol"])
        if not same:
            raise PlanError(f"{path}: displacements of another geometry, level or step; use"
                            " another --out or delete the folder to start again")
        plan = {**plan, "modes": saved["modes"]}  # the saved signs
    else:
        out.mkdir(parents=True, exist_ok=True)
        write_npz_atomic(path, **plan)
    return plan


def polarizability(labeler, numbers: np.ndarray, positions: np.ndarray, field_au: float,
                   folder: Path) -> tuple[np.ndarray, float]:
    """alpha (Å³, symmetrised) at ``positions`` from the dipoles under +-F along x, y, z
    (:func:`emlpack.qm.finite_field.finite_field_response`, each SCF's dipole cached as
    ``folder/field_{x,y,z}{+,-}.npz``). Returns (alpha, seconds of the SCFs run now)."""
    from emlpack.qm.finite_field import finite_field_response
    from emlpack.units import COULOMB_EV_A

    seconds = []

    def timed(*args, **kwargs):
        result = labeler(*args, **kwargs)
        seconds.append(float(result.wall_time))
        return result

    response = finite_field_response(timed, numbers, positions, step_au=field_au, cache=folder)
    return response.polarizability * COULOMB_EV_A, float(sum(seconds))


def run(out: Path, plan: dict, labeler, modes: list[int] | None = None,
        reverse: bool = False, log: Callable[[str], None] = print) -> dict:
    """Every missing SCF of ``plan`` (``modes``: a subset), then the Raman reference (a dict
    for JSON) of the modes whose displacements are complete."""
    from emlpack.properties.raman import (
        depolarization_ratios,
        derivatives_from_differences,
        raman_activities,
        raman_invariants,
    )
    from emlpack.properties.spectra import nan_as_none

    plan = load_or_save_plan(out, plan)
    n_modes = len(plan["modes"])
    todo = list(range(n_modes)) if modes is None else sorted(set(modes))
    jobs = [(k, s) for k in todo for s in SIGNS]
    alphas, seconds = {}, 0.0
    t0 = time.perf_counter()
    for k, s in reversed(jobs) if reverse else jobs:
        shift = (1.0 if s == "+" else -1.0) * plan["step"] * plan["modes"][k]
        alphas[k, s], sec = polarizability(labeler, plan["numbers"], plan["positions"] + shift,
                                           plan["field_au"], out / f"{k:02d}{s}")
        seconds += sec
        log(f"mode {k:2d} ({plan['frequencies'][k]:7.1f} cm^-1) {s}: alpha done"
            f" ({time.perf_counter() - t0:.0f} s)")
    stack = np.array([[alphas[k, s] for s in SIGNS] for k in todo])  # (n, 2, 3, 3) Å³
    derivs = derivatives_from_differences(stack, plan["step"], plan["modes"][todo],
                                          plan["masses"])
    mean_sq, aniso_sq = raman_invariants(derivs)
    return {
        "name": NAME, "smiles": SMILES, "level": plan["level"],
        "modes_from": plan["origin"],
        "method": (f"central differences ({plan['step']:g} Å along each mode) of the"
                   f" finite-field polarizability (field {plan['field_au']:g} au, central)"),
        "numbers": plan["numbers"].tolist(), "positions_A": plan["positions"].tolist(),
        "masses_amu": plan["masses"].tolist(), "modes": todo, "complete": len(todo) == n_modes,
        "frequencies_cm-1": plan["frequencies"][todo].tolist(),
        "activities_A4_per_amu": raman_activities(derivs).tolist(),
        "depolarization_ratios": nan_as_none(depolarization_ratios(derivs)),
        "depolarization_ratios_natural": nan_as_none(depolarization_ratios(derivs, True)),
        "mean_polarizability_derivative_sq_A4_per_amu": mean_sq.tolist(),
        "anisotropy_sq_A4_per_amu": aniso_sq.tolist(),
        "polarizability_derivatives_A2_per_sqrt_amu": derivs.tolist(),
        "step_A": plan["step"], "field_step_au": plan["field_au"],
        "scf_count": 12 * len(todo), "scf_seconds_this_run": seconds,
        "scf_convergence": {"conv_tol_Ha": float(plan["conv_tol"]),
                            "conv_tol_grad": CONV_TOL_GRAD},
    }


def main(argv: list[str] | None = None) -> int:
    """The command line (module docstring)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--level", default=LEVEL, help="level of the polarizabilities (xc/basis)")
    p.add_argument("--geometry", default="reference", choices=["reference", "optimize"],
                   help="the committed aug-cc-pVTZ optimum and Hessian, or both at --level")
    p.add_argument("--step", type=float, default=STEP_A, help="displacement along a mode, Å")
    p.add_argument("--field-au", type=float, default=FIELD_AU, help="field step, au")
    p.add_argument("--modes", help="comma-separated mode indices (default: all)")
    p.add_argument("--reverse", action="store_true", help="the SCFs from the last one back")
    p.add_argument("--threads", type=int, default=None, help="PySCF threads")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "aziridine_dft",
                   help="working folder of the per-SCF files")
    p.add_argument("--json", type=Path, help="output (default: examples/raman/"
                   "aziridine_LEVEL.json, or OUT/raman.json with --modes)")
    args = p.parse_args(argv)
    from emlpack._files import write_json_atomic

    labeler = tight_labeler(args.level, args.threads)
    source = (reference_geometry() if args.geometry == "reference" else
              optimized_geometry(args.out, labeler))
    level = labeler.level.name.split("/tol")[0]  # the tolerance is recorded on its own
    plan = make_plan(*source, level=level, step=args.step, field_au=args.field_au,
                     conv_tol=labeler.level.conv_tol)
    modes = [int(m) for m in args.modes.split(",")] if args.modes else None
    data = run(args.out, plan, labeler, modes, args.reverse)
    if args.json:
        path = args.json
    elif modes is None:
        path = Path(__file__).parent / f"{NAME}_{level.replace('/', '_')}.json"
    else:
        path = args.out / "raman.json"
    write_json_atomic(path, data)
    print(f"wrote {path}: {data['scf_count']} SCFs ({data['scf_seconds_this_run']:.0f} s of"
          " SCF in this run)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
