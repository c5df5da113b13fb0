"""``emlp optimize``, ``ir``, ``polarizability``, ``response``: a structure in, relaxed as
asked, a property out. Every check runs before the pair guess and the relaxation; whatever
looks broken afterwards (bonding changed, a saddle point, a negative stiffness eigenvalue, a
failed pair relaxation) is printed as a warning, recorded in the JSON output
(``"warnings": [...]``) and turns the summary into "converged with warnings"."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from emlpack.cli.common import (
    Log,
    add_field_arguments,
    add_model_argument,
    add_parser,
    add_quiet_argument,
    add_structure_arguments,
    add_threads_argument,
    apply_field,
    energy_record,
    load_member,
    positive,
    read_structure,
    set_threads,
    settings,
    write_json,
)

RELAX_LEVELS = ("none", "pairs", "positions", "cell")


def _common(p, relax_default: str, output_default: str, output_help: str) -> None:
    add_model_argument(p)
    add_structure_arguments(p)
    p.add_argument("-o", "--output", default=output_default, help=output_help)
    p.add_argument("--relax", default=relax_default, choices=RELAX_LEVELS,
                   help="relax before computing: nothing, the electron pairs, pairs and atom"
                   " positions, or also the cell")
    p.add_argument("--method", default="newton", choices=["newton", "lbfgs"],
                   help="optimiser for positions/cell")
    p.add_argument("--fmax", type=float, default=1e-6, help="force tolerance, eV/Å")
    p.add_argument("--max-iterations", type=int, default=100,
                   help="optimiser iterations for positions/cell")
    add_field_arguments(p)
    add_threads_argument(p)
    add_quiet_argument(p)


class Prepared:
    """The checked, relaxed input of a property command and what was noticed on the way."""

    def __init__(self, member, structure, where, field_info, warnings, relax_info, log):
        self.member, self.model = member, member.model
        self.structure, self.where = structure, where
        self.field_info, self.warnings, self.relax_info, self.log = (
            field_info, warnings, relax_info, log)

    def record(self, args, data: dict) -> dict:
        """``data`` with the field, relaxation, warnings and settings added."""
        out = dict(data)
        out["structure"] = self.where
        out.update(self.field_info)
        out["relaxation"] = self.relax_info
        out["warnings"] = list(self.warnings)
        out["settings"] = settings(args)
        return out

    def summary(self) -> str:
        """The last line: "converged", "not converged" or "done" (nothing relaxed), with
        "with warnings (N)" after the warnings were printed."""
        for w in self.warnings:
            self.log(f"warning: {w}")
        what = "done"
        if "optimisation" in self.relax_info:
            what = "converged" if self.relax_info["optimisation"]["converged"] else "not converged"
        elif "pairs" in self.relax_info:
            what = "not converged" if self.relax_info["pairs"]["failed"] else "converged"
        if self.warnings:
            return f"{what} with warnings ({len(self.warnings)})"
        return what


def prepare(args, periodic: bool | None, command: str) -> Prepared:
    """Cheap checks (arguments, model file, structure, field), then pair guess and relaxation."""
    log = Log(args.quiet)
    positive(args.fmax, "--fmax")
    positive(args.max_iterations, "--max-iterations")
    set_threads(args.threads)
    member = load_member(args.model)
    model = member.model
    s, where = read_structure(args, model, log, periodic=periodic, command=command)
    s, field_info = apply_field(s, args, where, log)
    warnings: list[str] = []
    s, relax_info = relax(model, s, args.relax, args, log, warnings)
    return Prepared(member, s, where, field_info, warnings, relax_info, log)


def relax(model, s, level: str, args, log: Log, warnings: list[str]):
    """Relax ``s`` to ``level``; problems are appended to ``warnings``, never hidden."""
    from emlpack.bonding import bonding_changes
    from emlpack.optimize import optimize
    from emlpack.relax import relax_pairs
    from emlpack.units import EV_PER_A3_IN_GPA

    info: dict = {"level": level}
    if level == "none":
        return s, info
    t0 = time.perf_counter()
    log.progress("relaxing the electron pairs ...")
    r = relax_pairs(model, s, fmax=min(args.fmax, 1e-6))[0]
    if r.failed:
        warnings.append(f"pair relaxation failed: {r.reason}")
    s = s.copy(pairs=r.pairs)
    log(f"pairs relaxed: {r.iterations} iterations, max pair force {r.max_force:.1e} eV/Å"
        f" ({time.perf_counter() - t0:.1f} s)")
    info["pairs"] = {"iterations": int(r.iterations), "max_force_eV_per_A": float(r.max_force),
                     "failed": bool(r.failed), "reason": r.reason}
    if level == "pairs":
        return s, info
    t0 = time.perf_counter()
    log.progress(f"optimising {'positions and cell' if level == 'cell' else 'positions'}"
                 f" ({args.method}) ...")
    res = optimize(model, s, cell=level == "cell", fmax=args.fmax, method=args.method,
                   max_iterations=args.max_iterations)
    if not res.converged:
        warnings.append(f"optimisation not converged: {res.reason or 'iteration limit'}")
    if np.isfinite(res.min_curvature) and res.min_curvature < 0:
        warnings.append(f"saddle point: lowest internal Hessian eigenvalue"
                        f" {res.min_curvature:.3g} eV/Å² is negative")
    if not s.pbc:
        warnings += [f"bonding changed: {c}" for c in
                     bonding_changes(s.numbers, s.positions, res.structure.positions)]
    out = res.structure
    log(f"optimised in {res.iterations} iterations ({time.perf_counter() - t0:.1f} s):"
        f" energy {res.energy:.6f} eV, max force {res.max_force:.2e} eV/Å")
    info["optimisation"] = {"converged": bool(res.converged), "iterations": int(res.iterations),
                            "model_energy_eV": float(res.energy),
                            "max_force_eV_per_A": float(res.max_force),
                            "lowest_internal_hessian_eigenvalue": float(res.min_curvature),
                            "reason": res.reason}
    if out.pbc:  # stress as computed, whether or not the cell was relaxed
        stress = np.asarray(model.evaluate(out, stress=True)["stress"]).reshape(3, 3)
        gpa = stress * EV_PER_A3_IN_GPA
        log(f"stress (GPa, ASE sign): max |σ| {np.abs(gpa).max():.3g}; diagonal"
            f" {np.array2string(np.diag(gpa), precision=3)}")
        info["optimisation"]["stress_GPa"] = gpa.tolist()
        lat = res.lattice()
        log("lattice (Å, deg): a {a:.4f} b {b:.4f} c {c:.4f} alpha {alpha:.3f} beta {beta:.3f}"
            " gamma {gamma:.3f} volume {volume:.3f} Å^3".format(**lat))
        info["optimisation"]["lattice"] = {k: float(v) for k, v in lat.items()}
    return out, info


# --------------------------------------------------------------------------- commands
def add_optimize(sub) -> None:
    p = add_parser(sub, "optimize", "optimise the pairs, positions (and cell) of a structure;"
                   " writes extxyz and a JSON summary")
    _common(p, "positions", "optimized.xyz",
            "extxyz file of the optimised structure (pairs as Es rows); a JSON summary with"
            " the same stem is written beside it")
    p.add_argument("--no-pairs", action="store_true",
                   help="write the atoms only (no Es rows; the pairs stay in the JSON)")

    def run(args):
        import ase.io

        from emlpack.io import split_pairs, structure_to_atoms, write_structures

        prep = prepare(args, None, "emlp optimize")
        s = prep.structure
        energy = prep.model.evaluate(s)
        out = Path(args.output)
        if args.no_pairs:
            atoms = split_pairs(structure_to_atoms(s))
            atoms.info.pop("electron_pairs", None)
            ase.io.write(out, atoms, format="extxyz")
        else:
            write_structures(out, [s])
        data = prep.record(args, {
            **energy_record(prep.member, s, energy["energy"]),
            "numbers": s.numbers.tolist(), "positions_A": s.positions.tolist(),
            "pairs_A": s.pairs.tolist(),
        })
        if s.pbc:
            data["cell_A"] = s.cell.tolist()
        json_path = out.with_suffix(".json")
        write_json(json_path, data)
        prep.log(f"wrote {out} and {json_path}")
        prep.log(prep.summary())
        return 0

    p.set_defaults(func=run)


def add_ir(sub) -> None:
    p = add_parser(sub, "ir", "harmonic IR spectrum of a molecule (JSON, optional PNG)")
    _common(p, "positions", "ir.json", "JSON file of the spectrum")
    p.add_argument("--plot", metavar="FILE.png", help="PNG plot of the spectrum")
    p.add_argument("--png", dest="plot", help=argparse_suppress())
    p.add_argument("--fwhm", type=float, default=10.0, help="Lorentzian FWHM, cm^-1")
    p.add_argument("--reference", help="reference spectrum: text columns cm^-1, km/mol")

    def run(args):
        import json

        from emlpack.spectra import ir_spectrum, write_ir

        positive(args.fwhm, "--fwhm")
        ref = None
        if args.reference:
            ref = _read_reference(args.reference)
        prep = prepare(args, False, "emlp ir")
        t0 = time.perf_counter()
        prep.log.progress("extended Hessian and normal modes ...")
        spec = ir_spectrum(prep.model, prep.structure)
        prep.log(spec.text())
        prep.log(f"(IR spectrum: {time.perf_counter() - t0:.2f} s)")
        n_imag = int(np.sum(spec.frequencies < 0))
        if n_imag:
            prep.warnings.append(f"{n_imag} imaginary mode(s) (lowest"
                                 f" {spec.frequencies.min():.1f} cm^-1): not a minimum")
        write_ir(spec, args.output, args.plot, fwhm=args.fwhm, reference=ref,
                 title=prep.where)
        data = prep.record(args, json.loads(Path(args.output).read_text()))
        write_json(args.output, data)
        prep.log(f"wrote {args.output}" + (f" and {args.plot}" if args.plot else ""))
        prep.log(prep.summary())
        return 0

    p.set_defaults(func=run)


def _read_reference(path: str):
    from emlpack.errors import InputError

    try:
        table = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the reference spectrum: {exc}") from None
    if table.shape[1] < 2:
        raise InputError(f"{path}: the reference spectrum needs two columns (cm^-1, km/mol)")
    return table[:, 0], table[:, 1]


def argparse_suppress():
    import argparse

    return argparse.SUPPRESS


def add_polarizability(sub) -> None:
    p = add_parser(sub, "polarizability", "dipole and polarizabilities of a molecule (JSON)")
    _common(p, "pairs", "polarizability.json", "JSON file of the dipole and polarizabilities")

    def run(args):
        from emlpack.response import molecule_response
        from emlpack.units import COULOMB_EV_A, POLARIZABILITY_A3_IN_BOHR3

        prep = prepare(args, False, "emlp polarizability")
        t0 = time.perf_counter()
        prep.log.progress("extended Hessian and Schur complements ...")
        resp = molecule_response(prep.model, prep.structure, relax_cores=True)
        prep.log(resp.text())
        prep.log(f"(extended Hessian and Schur complements: {time.perf_counter() - t0:.2f} s)")
        low = float(np.linalg.eigvalsh(0.5 * (resp.polarizability + resp.polarizability.T))[0])
        if low < 0:
            prep.warnings.append(
                f"negative polarizability eigenvalue"
                f" {low * COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3:.3g} bohr^3 (pairs not at"
                " a minimum?)")
        write_json(args.output, prep.record(args, resp.as_dict()))
        prep.log(f"wrote {args.output}")
        prep.log(prep.summary())
        return 0

    p.set_defaults(func=run)


def add_response(sub) -> None:
    p = add_parser(sub, "response", "stiffness, dielectric and piezoelectric tensors of a"
                   " crystal (JSON)")
    _common(p, "positions", "response.json", "JSON file of the tensors")

    def run(args):
        from emlpack.response import crystal_response

        prep = prepare(args, True, "emlp response")
        t0 = time.perf_counter()
        prep.log.progress("extended Hessian and all tensors ...")
        resp = crystal_response(prep.model, prep.structure)
        prep.log(resp.text())
        prep.log(f"(extended Hessian and all tensors: {time.perf_counter() - t0:.2f} s)")
        low = float(np.linalg.eigvalsh(resp.stiffness_voigt)[0])
        if low < 0:
            from emlpack.units import EV_PER_A3_IN_GPA

            prep.warnings.append(f"negative stiffness eigenvalue {low * EV_PER_A3_IN_GPA:.3g}"
                                 " GPa: the crystal is not mechanically stable")
        write_json(args.output, prep.record(args, resp.as_dict()))
        prep.log(f"wrote {args.output}")
        prep.log(prep.summary())
        return 0

    p.set_defaults(func=run)


COMMANDS = [add_ir, add_polarizability, add_response, add_optimize]
