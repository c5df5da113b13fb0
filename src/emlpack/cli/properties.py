"""``emlp optimize``, ``ir``, ``raman``, ``polarizability``, ``response``: a structure in,
relaxed as asked, a property out. Every check runs before the pair guess and the relaxation;
whatever looks broken afterwards (bonding changed, a saddle point, a negative stiffness
eigenvalue, a failed pair relaxation) is printed as a warning, recorded in the JSON output
(``"warnings": [...]``) and turns the summary into "converged with warnings".

A member of an ensemble whose result is broken (failed pair relaxation, broken pairs or
changed bonding after the optimisation, pairs not at a minimum: an imaginary pair mode or a
negative clamped polarizability eigenvalue, :func:`emlpack.properties.response.
pair_minimum_problem`) is left out of the mean and spread; with fewer than two members left,
or the single model's result broken, the command writes no values and exits 3 with one line
(:func:`emlpack.calculators.ensemble.sound_members`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from emlpack.cli.common import (
    Log,
    Subparsers,
    add_field_arguments,
    add_model_argument,
    add_parser,
    add_quiet_argument,
    add_structure_arguments,
    apply_field,
    energy_record,
    load_members,
    positive,
    read_structure,
    set_threads,
    settings,
    write_json,
)

if TYPE_CHECKING:
    import argparse
    from collections.abc import Iterable, Iterator

    from emlpack.calculators.ensemble import ModelMember
    from emlpack.nn.potential import EMLP
    from emlpack.structure import Structure

RELAX_LEVELS = ("none", "pairs", "positions", "cell")
#: warn when the ensemble's isotropic polarizability spread exceeds this fraction of its mean
POLARIZABILITY_SPREAD_WARNING = 0.1
#: ``emlp raman --step`` (Å): ``emlpack.properties.raman.STEP`` (tested equal; the parser is
#: built without importing torch)
RAMAN_STEP = 2e-3


def _common(p: argparse.ArgumentParser, relax_default: str, output_default: str,
            output_help: str) -> None:
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
    add_quiet_argument(p)


class Prepared:
    """The checked, relaxed input of a property command and what was noticed on the way.

    With an ensemble (a folder of checkpoints or a pretrained name) every member relaxes its
    own pairs (and positions, cell) from the same input: ``structures[k]`` belongs to
    ``members[k]``; the commands report the members' mean and their spread (``*_std``). A
    member whose relaxation left a broken structure (failed pair relaxation, merged or stray
    pairs after the optimisation, changed bonding) or whose pairs are not at a minimum
    (:meth:`minima`) is left out of them (``left_out``: their sources; a warning says so), as
    long as two members stay (:func:`~emlpack.calculators.ensemble.sound_members`).
    """

    def __init__(self, members: Iterable[ModelMember], structures: Iterable[Structure],
                 where: str, field_info: dict, warnings: list[str], relax_infos: list[dict],
                 log: Log, left_out: Iterable[str] = (), labels: list[str] | None = None):
        self.members, self.structures = list(members), list(structures)
        self.where, self.field_info, self.warnings = where, field_info, warnings
        self.relax_infos, self.log = relax_infos, log
        self.left_out = list(left_out)
        #: how the messages name each member ("model K", K counted over all members)
        self.labels = labels or [f"model {k + 1}" for k in range(len(self.members))]

    @property
    def ensemble(self) -> bool:
        """True for more than one member."""
        return len(self.members) > 1

    @property
    def member(self) -> ModelMember:
        """The first member."""
        return self.members[0]

    @property
    def model(self) -> EMLP:
        """The first member's model."""
        return self.members[0].model

    @property
    def structure(self) -> Structure:
        """The first member's checked, relaxed structure."""
        return self.structures[0]

    def each(self) -> Iterator[tuple[int, ModelMember, Structure]]:
        """``(index, member, structure)`` for every member."""
        return zip(range(len(self.members)), self.members, self.structures, strict=True)

    def leave_out(self, problems: list[str], why: str) -> list[int]:
        """Leave the members with a non-empty ``problems[k]`` out (a warning names them and
        ``why``); returns the indices kept. Raises
        :class:`~emlpack.errors.BrokenResultError` when too few are left
        (:func:`~emlpack.calculators.ensemble.sound_members`)."""
        from emlpack.calculators.ensemble import sound_members

        keep = sound_members(problems, self.labels, self.where)
        if len(keep) < len(self.members):
            names = ", ".join(self.labels[k] for k in range(len(self.members)) if k not in keep)
            self.warnings.append(f"{names} left out of the results ({why}): the mean and"
                                 f" spread of {len(keep)} of {len(self.members)} models")
            self.left_out += [self.members[k].source for k in range(len(self.members))
                              if k not in keep]
            self.members, self.structures, self.relax_infos, self.labels = (
                [seq[k] for k in keep]
                for seq in (self.members, self.structures, self.relax_infos, self.labels))
        return keep

    def hessians(self, what: str = "extended Hessian") -> list[np.ndarray]:
        """The extended Hessian of every member at its structure
        (:func:`emlpack.properties.hessian.extended_hessian`), in order."""
        from emlpack.properties.hessian import extended_hessian

        self.log.progress(f"{what} ...")
        each = list(self.each())
        if self.ensemble:  # per member: a bar with rate and time left
            each = self.log.bar(each, "extended Hessians", "model")
        return [extended_hessian(m.model, s)[1].numpy() for _, m, s in each]

    def minima(self, hessians: list[np.ndarray]) -> list[np.ndarray]:
        """Leave out the members whose pairs are not at a minimum by their extended
        ``hessians`` (:func:`emlpack.properties.response.pair_minimum_problem`; each is also
        a warning); returns the Hessians of the members kept."""
        from emlpack.properties.response import pair_minimum_problem

        problems = [pair_minimum_problem(h, s) for h, s in
                    zip(hessians, self.structures, strict=True)]
        for k, problem in enumerate(problems):
            if problem and self.ensemble:
                self.warnings.append(f"{self.labels[k]}: {problem}")
        keep = self.leave_out(problems, "pairs not at a minimum, see above")
        return [hessians[k] for k in keep]

    def record(self, args: argparse.Namespace, data: dict) -> dict:
        """``data`` with the field, relaxation, warnings, ensemble and settings added."""
        out = dict(data)
        out["structure"] = self.where
        out.update(self.field_info)
        out["relaxation"] = self.relax_infos[0] if not self.ensemble else self.relax_infos
        if self.ensemble or self.left_out:
            out["ensemble"] = {"size": len(self.members),
                               "members": [m.source for m in self.members],
                               "left_out": self.left_out}
        out["warnings"] = list(self.warnings)
        out["settings"] = settings(args)
        return out

    def energies(self) -> dict:
        """Energy record (DFT scale when known) of the members at their structures, with the
        ensemble's mean, ``energy_eV_std`` and a warning when the spread is large."""
        from emlpack.calculators.ensemble import member_spread, spread_thresholds

        records = [energy_record(m, s, m.model.evaluate(s)["energy"])
                   for _, m, s in self.each()]
        if not self.ensemble:
            return records[0]
        out = dict(records[0])
        for key, value in records[0].items():
            if isinstance(value, float):
                out[key] = float(np.mean([r[key] for r in records]))
        out.update(member_spread(records))
        self.warnings += spread_thresholds(self.members).warnings(
            len(self.structure.numbers), out["energy_eV_std"])
        return out

    def summary(self) -> str:
        """The last line: "converged", "not converged" or "done" (nothing relaxed), with
        "with warnings (N)" after the warnings were printed."""
        for w in self.warnings:
            self.log(f"warning: {w}")
        what = "done"
        infos = self.relax_infos
        if any("optimisation" in i for i in infos):
            ok = all(i["optimisation"]["converged"] for i in infos)
            what = "converged" if ok else "not converged"
        elif any("pairs" in i for i in infos):
            what = "not converged" if any(i["pairs"]["failed"] for i in infos) else "converged"
        if self.warnings:
            return f"{what} with warnings ({len(self.warnings)})"
        return what


def prepare(args: argparse.Namespace, periodic: bool | None, command: str) -> Prepared:
    """Cheap checks (arguments, model files, structure, field), then pair guess and relaxation
    (by every member of an ensemble)."""
    from emlpack.calculators.ensemble import ModelEnsemble

    log = Log(args.quiet)
    positive(args.fmax, "--fmax")
    positive(args.max_iterations, "--max-iterations")
    set_threads(args.threads)
    members = load_members(args.model)
    s, where = read_structure(args, members[0].model, log, periodic=periodic, command=command)
    s, field_info = apply_field(s, args, where, log)
    # what the models' files ask every result to say (e.g. a preliminary pretrained ensemble),
    # and a structure outside their training domain (e.g. a larger molecule)
    ensemble = ModelEnsemble(members)
    warnings = ensemble.notices + ensemble.domain_warnings(s.numbers, s.positions, s.pbc)
    structures, infos = [], []
    each = list(enumerate(members))
    if len(members) > 1:  # per member: a bar with rate and time left
        each = log.bar(each, f"{command.split()[-1]}: models relaxed", "model")
    for k, member in each:
        if len(members) > 1:
            log.progress(f"model {k + 1} of {len(members)} ({member.source}):")
        notes: list[str] = []
        relaxed, info = relax(member.model, s, args.relax, args, log, notes)
        structures.append(relaxed)
        infos.append(info)
        warnings += [f"model {k + 1}: {w}" if len(members) > 1 else w for w in notes]
    prep = Prepared(members, structures, where, field_info, warnings, infos, log)
    prep.leave_out([_problem(info) for info in infos], "broken structure, see above")
    return prep


def _problem(info: dict) -> str:
    """Why a member's relaxation record (``relax``) says its structure is broken, or ``""``."""
    pairs, opt = info.get("pairs", {}), info.get("optimisation", {})
    reasons = []
    if pairs.get("failed"):
        reasons.append(f"pair relaxation failed: {pairs.get('reason') or 'failed'}")
    if opt.get("pair_check"):
        reasons.append(f"optimisation failed, broken electron pairs: {opt['pair_check']}")
    if opt.get("bonding_changes"):
        reasons.append("bonding changed: " + "; ".join(opt["bonding_changes"]))
    return "; ".join(reasons)


def relax(model: EMLP, s: Structure, level: str, args: argparse.Namespace, log: Log,
          warnings: list[str]) -> tuple[Structure, dict]:
    """Relax ``s`` to ``level``; problems are appended to ``warnings``, never hidden."""
    from emlpack.bonding import bonding_changes
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.optimize import optimize
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
    if res.pair_check:
        warnings.append(f"optimisation failed, broken electron pairs: {res.reason}")
    elif not res.converged:
        warnings.append(f"optimisation not converged: {res.reason or 'iteration limit'}")
    if np.isfinite(res.min_curvature) and res.min_curvature < 0:
        warnings.append(f"saddle point: lowest internal Hessian eigenvalue"
                        f" {res.min_curvature:.3g} eV/Å² is negative")
    changes = [] if s.pbc else bonding_changes(s.numbers, s.positions, res.structure.positions)
    warnings += [f"bonding changed: {c}" for c in changes]
    out = res.structure
    log(f"optimised in {res.iterations} iterations ({time.perf_counter() - t0:.1f} s):"
        f" energy {res.energy:.6f} eV, max force {res.max_force:.2e} eV/Å")
    info["optimisation"] = {"converged": bool(res.converged), "iterations": int(res.iterations),
                            "model_energy_eV": float(res.energy),
                            "max_force_eV_per_A": float(res.max_force),
                            "lowest_internal_hessian_eigenvalue": float(res.min_curvature),
                            "reason": res.reason, "pair_check": res.pair_check,
                            "bonding_changes": changes}
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
def add_optimize(sub: Subparsers) -> None:
    """Register ``emlp optimize``: optimise the pairs, positions (and cell) of a structure;
    writes extxyz and a JSON summary."""
    p = add_parser(sub, "optimize", "optimise the pairs, positions (and cell) of a structure;"
                   " writes extxyz and a JSON summary")
    _common(p, "positions", "optimized.xyz",
            "extxyz file of the optimised structure (pairs as Es rows); a JSON summary with"
            " the same stem is written beside it")
    p.add_argument("--no-pairs", action="store_true",
                   help="write the atoms only (no Es rows; the pairs stay in the JSON)")

    def run(args: argparse.Namespace):
        import ase.io

        from emlpack._files import atomic_write
        from emlpack.io import split_pairs, structure_to_atoms, write_structures

        prep = prepare(args, None, "emlp optimize")
        prep.minima(prep.hessians("extended Hessian (minimum check)"))
        out = Path(args.output)
        if args.no_pairs:
            frames = []
            for s in prep.structures:
                atoms = split_pairs(structure_to_atoms(s))
                atoms.info.pop("electron_pairs", None)
                frames.append(atoms)
            atomic_write(out, lambda fh: ase.io.write(fh, frames, format="extxyz"))
        else:
            write_structures(out, prep.structures)  # with an ensemble: one frame per member
        data = {**prep.energies(), "numbers": prep.structure.numbers.tolist()}
        if prep.ensemble:
            positions = np.array([s.positions for s in prep.structures])
            spread = np.linalg.norm(positions - positions.mean(axis=0), axis=-1)
            data["positions_A"] = positions.mean(axis=0).tolist()
            data["max_position_deviation_A"] = float(spread.max())
            data["members"] = [{"source": m.source, "positions_A": s.positions.tolist(),
                                "pairs_A": s.pairs.tolist(),
                                **({"cell_A": s.cell.tolist()} if s.pbc else {})}
                               for _, m, s in prep.each()]
            prep.log(f"{len(prep.members)} models: energy {data['energy_eV']:.6f} ±"
                     f" {data['energy_eV_std']:.6f} eV; largest deviation of an atom from"
                     f" the mean geometry {data['max_position_deviation_A']:.3f} Å")
        else:
            s = prep.structure
            data.update({"positions_A": s.positions.tolist(), "pairs_A": s.pairs.tolist()})
            if s.pbc:
                data["cell_A"] = s.cell.tolist()
        data = prep.record(args, data)
        json_path = out.with_suffix(".json")
        write_json(json_path, data)
        prep.log(f"wrote {out} and {json_path}"
                 + (" (one frame per model)" if prep.ensemble else ""))
        prep.log(prep.summary())
        return 0

    p.set_defaults(func=run)


def _spectrum_arguments(p: argparse.ArgumentParser, kind: str) -> None:
    """``--plot``, ``--fwhm``, ``--reference`` and ``--reference-label`` of ``ir`` and
    ``raman``."""
    unit = "km/mol" if kind == "ir" else "Å^4/amu"
    p.add_argument("--plot", metavar="FILE.png",
                   help="plot of the spectrum: the broadened spectrum over its sticks, an"
                   " ensemble's spread as a band, the reference overlaid")
    p.add_argument("--fwhm", type=float, default=10.0, help="Lorentzian FWHM, cm^-1")
    p.add_argument("--reference", metavar="FILE",
                   help=f"reference spectrum to compare with: a JSON written by emlp {kind}"
                   " (or a DFT reference of the same keys), a two-column CSV or text table"
                   f" (cm^-1, {unit}), or an extxyz frame with a Cartesian Hessian (info"
                   " 'hessian', eV/Å^2; docs/raman.md)")
    p.add_argument("--reference-label", metavar="TEXT",
                   help="the reference's name in the plot (default: from the file)")


def _line_spectrum(args: argparse.Namespace, kind: str) -> int:
    """``emlp ir`` and ``emlp raman``: every member's spectrum, their mean and spread, JSON and
    the plot."""
    from emlpack.properties.spectra import ensemble_modes, spectrum_curves, write_spectrum_plot
    from emlpack.properties.spectrum_reference import read_reference_spectrum

    positive(args.fwhm, "--fwhm")
    if kind == "raman":
        positive(args.step, "--step")
    ref = (read_reference_spectrum(args.reference, kind, args.reference_label)
           if args.reference else None)
    prep = prepare(args, False, f"emlp {kind}")
    t0 = time.perf_counter()
    hessians = prep.minima(prep.hessians("extended Hessian and normal modes"))
    if kind == "ir":
        from emlpack.properties.ir import ir_from_hessian

        spectra = [ir_from_hessian(h, s) for h, s in zip(hessians, prep.structures, strict=True)]
        lines = [(x.frequencies, x.intensities) for x in spectra]
    else:
        from emlpack.properties.raman import raman_spectrum

        prep.log.progress("polarizability derivatives ...")
        each = list(prep.each())
        if prep.ensemble:
            each = prep.log.bar(each, "Raman spectra", "model")
        spectra = [raman_spectrum(m.model, s, step=args.step) for _, m, s in each]
        lines = [(x.frequencies, x.activities) for x in spectra]
    for k, x in enumerate(spectra):
        if prep.ensemble:
            prep.log(f"{prep.labels[k]} ({prep.members[k].source}):")
        prep.log(x.text())
    prep.log(f"({'IR' if kind == 'ir' else 'Raman'} spectrum: {time.perf_counter() - t0:.2f} s)")
    for k, x in enumerate(spectra):
        n_imag = int(np.sum(x.frequencies < 0))
        if n_imag:
            who = f"{prep.labels[k]}: " if prep.ensemble else ""
            prep.warnings.append(f"{who}{n_imag} imaginary mode(s) (lowest"
                                 f" {x.frequencies.min():.1f} cm^-1): not a minimum")
    curves = spectrum_curves(lines, kind, args.fwhm, ref)
    data = spectra[0].as_dict(args.fwhm)
    if prep.ensemble:  # modes by rank (ascending wavenumber), mean and spread
        tables = [x.mode_table() for x in spectra]
        signed = "polarizability_derivatives_A2_per_sqrt_amu"  # a mode's sign is arbitrary
        data.pop(signed, None)
        data.update(ensemble_modes(tables, exclude=(signed,)))
        if kind == "raman":
            data["polarizability_e_A2_per_V"] = np.mean(
                [x.polarizability for x in spectra], axis=0).tolist()
        data["members"] = [{"source": m.source, **x} for m, x in
                           zip(prep.members, tables, strict=True)]
        data["spectrum"] = f"mean of the {len(spectra)} models' broadened spectra"
        std = np.asarray(data["frequencies_cm-1_std"], float)
        prep.log(f"ensemble: wavenumber spread (std) median {np.median(std):.1f}, largest"
                 f" {std.max():.1f} cm^-1")
    data.update(curves.as_dict())
    if ref is not None:
        data["reference_file"] = str(args.reference)
        data["reference_label"] = ref.label
        data["reference_frequencies_cm-1"] = ref.frequencies.tolist()
        if ref.heights is not None:
            data[f"reference_{curves.kind.key}"] = ref.heights.tolist()
    if args.plot:
        write_spectrum_plot(args.plot, curves, title=prep.where + (
            f" ({len(spectra)}-model mean)" if prep.ensemble else ""))
    write_json(args.output, prep.record(args, {**prep.energies(), **data}))
    prep.log(f"wrote {args.output}" + (f" and {args.plot}" if args.plot else ""))
    prep.log(prep.summary())
    return 0


def add_ir(sub: Subparsers) -> None:
    """Register ``emlp ir``: harmonic IR spectrum of a molecule (JSON, optional PNG)."""
    p = add_parser(sub, "ir", "harmonic IR spectrum of a molecule (JSON, optional PNG)")
    _common(p, "positions", "ir.json", "JSON file of the spectrum")
    _spectrum_arguments(p, "ir")
    p.add_argument("--png", dest="plot", help=argparse_suppress())
    p.set_defaults(func=lambda args: _line_spectrum(args, "ir"))


def add_raman(sub: Subparsers) -> None:
    """Register ``emlp raman``: harmonic Raman spectrum of a molecule (JSON, optional PNG)."""
    p = add_parser(sub, "raman", "harmonic Raman spectrum of a molecule: activities and"
                   " depolarisation ratios (JSON, optional PNG)")
    _common(p, "positions", "raman.json", "JSON file of the spectrum")
    _spectrum_arguments(p, "raman")
    p.add_argument("--step", type=float, default=RAMAN_STEP,
                   help="step (Å) of the polarizability differences along each mode")
    p.set_defaults(func=lambda args: _line_spectrum(args, "raman"))


def argparse_suppress() -> str:
    """``argparse.SUPPRESS``, which hides an option from ``--help`` (this module imports
    argparse for type checking only)."""
    import argparse

    return argparse.SUPPRESS


def add_polarizability(sub: Subparsers) -> None:
    """Register ``emlp polarizability``: dipole and polarizabilities of a molecule (JSON)."""
    p = add_parser(sub, "polarizability", "dipole and polarizabilities of a molecule (JSON)")
    _common(p, "pairs", "polarizability.json", "JSON file of the dipole and polarizabilities")

    def run(args: argparse.Namespace):
        from emlpack.calculators.ensemble import member_mean, member_spread
        from emlpack.properties.response import molecule_response_from_hessian
        from emlpack.units import COULOMB_EV_A, POLARIZABILITY_A3_IN_BOHR3

        prep = prepare(args, False, "emlp polarizability")
        t0 = time.perf_counter()
        hessians = prep.minima(prep.hessians("extended Hessian and Schur complements"))
        members = [molecule_response_from_hessian(h, s, relax_cores=True)
                   for h, s in zip(hessians, prep.structures, strict=True)]
        resp = member_mean(members) if prep.ensemble else members[0]
        prep.log(resp.text())
        data = resp.as_dict()
        if prep.ensemble:
            data.update(member_spread([r.as_dict() for r in members]))
            iso, iso_std = (data["polarizability_isotropic_bohr3"],
                            data["polarizability_isotropic_bohr3_std"])
            prep.log(f"ensemble of {len(members)}: |mu| {data['dipole_norm_debye']:.4f} ±"
                     f" {data['dipole_norm_debye_std']:.4f} D, isotropic polarizability"
                     f" {iso:.4f} ± {iso_std:.4f} bohr^3")
            if iso_std > POLARIZABILITY_SPREAD_WARNING * abs(iso):
                prep.warnings.append(
                    f"ensemble polarizability spread {iso_std:.3g} bohr^3 is more than"
                    f" {POLARIZABILITY_SPREAD_WARNING:.0%} of its mean: outside the models'"
                    " domain?")
        prep.log(f"(extended Hessian and Schur complements: {time.perf_counter() - t0:.2f} s)")
        for k, r in enumerate(members):  # the clamped one is positive (prep.minima)
            relaxed = r.polarizability_relaxed
            low = float(np.linalg.eigvalsh(0.5 * (relaxed + relaxed.T))[0])
            if low < 0:
                who = f"{prep.labels[k]}: " if prep.ensemble else ""
                prep.warnings.append(
                    f"{who}negative eigenvalue of the polarizability with relaxed cores"
                    f" {low * COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3:.3g} bohr^3: the cores"
                    " are not at a minimum (--relax positions)")
        write_json(args.output, prep.record(args, {**prep.energies(), **data}))
        prep.log(f"wrote {args.output}")
        prep.log(prep.summary())
        return 0

    p.set_defaults(func=run)


def add_response(sub: Subparsers) -> None:
    """Register ``emlp response``: stiffness, dielectric and piezoelectric tensors of a crystal
    (JSON)."""
    p = add_parser(sub, "response", "stiffness, dielectric and piezoelectric tensors of a"
                   " crystal (JSON)")
    _common(p, "positions", "response.json", "JSON file of the tensors")

    def run(args: argparse.Namespace):
        from emlpack.calculators.ensemble import member_mean, member_spread
        from emlpack.properties.response import crystal_response_from_hessian

        prep = prepare(args, True, "emlp response")
        t0 = time.perf_counter()
        hessians = prep.minima(prep.hessians("extended Hessian and all tensors"))
        members = [crystal_response_from_hessian(h, s)
                   for h, s in zip(hessians, prep.structures, strict=True)]
        resp = member_mean(members) if prep.ensemble else members[0]
        prep.log(resp.text())
        data = resp.as_dict()
        if prep.ensemble:
            data.update(member_spread([r.as_dict() for r in members]))
            prep.log(f"(mean of {len(members)} models; the spread of every tensor is in the"
                     " JSON output as KEY_std)")
        prep.log(f"(extended Hessian and all tensors: {time.perf_counter() - t0:.2f} s)")
        for k, r in enumerate(members):
            low = float(np.linalg.eigvalsh(r.stiffness_voigt)[0])
            if low < 0:
                from emlpack.units import EV_PER_A3_IN_GPA

                who = f"{prep.labels[k]}: " if prep.ensemble else ""
                prep.warnings.append(f"{who}negative stiffness eigenvalue"
                                     f" {low * EV_PER_A3_IN_GPA:.3g} GPa: the crystal is not"
                                     " mechanically stable")
        write_json(args.output, prep.record(args, {**prep.energies(), **data}))
        prep.log(f"wrote {args.output}")
        prep.log(prep.summary())
        return 0

    p.set_defaults(func=run)


COMMANDS = [add_ir, add_raman, add_polarizability, add_response, add_optimize]
