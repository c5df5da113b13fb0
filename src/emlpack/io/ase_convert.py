"""Conversion between :class:`~emlpack.structure.Structure` and :class:`ase.Atoms`.

The ASE side holds the atomic cores only; the rest lives in ``atoms.info``:

* ``"electron_pairs"``: electron-pair positions (Å), shape (n_pairs, 3);
* ``"external_field"``: homogeneous field (V/Å), shape (3,);
* ``"charge"``: total charge (e).

Labels travel as a :class:`~ase.calculators.singlepoint.SinglePointCalculator` (``energy`` eV,
``forces`` eV/Å on cores, ``stress`` eV/Å^3 in Voigt order, ASE sign) with
``calc.results["pair_forces"]`` (eV/Å) when known.
"""

from __future__ import annotations

import numpy as np
from ase import Atoms
from ase.calculators.singlepoint import SinglePointCalculator
from ase.stress import full_3x3_to_voigt_6_stress, voigt_6_to_full_3x3_stress

from emlpack.io.cores import CORE_TOLERANCE, split_core_centres
from emlpack.structure import PAIR_NUMBER, Structure, StructureError

__all__ = ["structure_to_atoms", "atoms_to_structure", "split_pairs", "PAIRS_KEY", "FIELD_KEY",
           "CHARGE_KEY"]

PAIRS_KEY = "electron_pairs"
FIELD_KEY = "external_field"
CHARGE_KEY = "charge"


def structure_to_atoms(structure: Structure) -> Atoms:
    """An :class:`ase.Atoms` of the cores, with pairs, field and charge in ``atoms.info``."""
    s = structure
    atoms = Atoms(
        numbers=s.numbers.copy(),
        positions=s.positions.copy(),
        cell=s.cell.copy() if s.pbc else None,
        pbc=s.pbc,
    )
    atoms.info.update({k: v for k, v in s.info.items()})
    atoms.info[PAIRS_KEY] = s.pairs.copy()
    atoms.info[FIELD_KEY] = s.field.copy()
    atoms.info[CHARGE_KEY] = float(s.charge)
    labels = {}
    if s.energy is not None:
        labels["energy"] = float(s.energy)
    if s.forces is not None:
        labels["forces"] = s.forces.copy()
    if s.stress is not None:
        labels["stress"] = full_3x3_to_voigt_6_stress(s.stress)
    if labels or s.pair_forces is not None:
        atoms.calc = SinglePointCalculator(atoms, **labels)
        if s.pair_forces is not None:
            atoms.calc.results["pair_forces"] = s.pair_forces.copy()
    return atoms


def split_pairs(atoms: Atoms) -> Atoms:
    """The cores of ``atoms`` with the electron pairs moved out of the atom list.

    Files and trajectories keep the pairs as ``Es`` rows (Z = 99, the reference's convention),
    which ASE treats as einsteinium atoms (252 amu): masses, centre of mass and viewers see
    them. This returns a copy with only the atomic cores as atoms and the pair positions (Å)
    in ``atoms.info["electron_pairs"]`` (the layout of :func:`structure_to_atoms`); per-atom
    arrays and a calculator's per-atom results are cut to the cores. Atoms without ``Es``
    rows come back as a copy.
    """
    is_pair = atoms.numbers == PAIR_NUMBER
    cores = atoms[~is_pair]
    cores.info = dict(atoms.info)
    if is_pair.any():
        cores.info[PAIRS_KEY] = atoms.positions[is_pair].copy()
    if atoms.calc is not None and hasattr(atoms.calc, "results"):
        results = {}
        for key, value in atoms.calc.results.items():
            arr = np.asarray(value)
            if arr.ndim >= 1 and arr.shape[0] == len(atoms) and key not in ("stress",):
                results[key] = arr[~is_pair]
            else:
                results[key] = value
        cores.calc = SinglePointCalculator(cores, **results)
    return cores


def atoms_to_structure(
    atoms: Atoms,
    pairs: np.ndarray | None = None,
    field: np.ndarray | None = None,
    charge: float | None = None,
    core_tolerance: float = CORE_TOLERANCE,
    source: str = "<ase.Atoms>",
) -> Structure:
    """A :class:`Structure` from ``atoms``; the inverse of :func:`structure_to_atoms`.

    Electron pairs (Å) come from ``pairs``, else ``atoms.info["electron_pairs"]``, else from
    ``Es`` (Z = 99) particles in ``atoms`` (core centres among them are removed as on file read).
    The field (V/Å) comes from ``field``, else ``atoms.info["external_field"]``, else zero.
    Labels are taken from an attached calculator whose results match the current atoms.
    """
    numbers = atoms.numbers.astype(np.int64)
    positions = atoms.positions.astype(np.float64)
    is_pair = numbers == PAIR_NUMBER
    core_rows = np.flatnonzero(~is_pair)
    pair_rows = np.flatnonzero(is_pair)
    flags = np.asarray(atoms.pbc, dtype=bool)
    if flags.any() and not flags.all():
        raise StructureError(f"{source}: mixed periodicity pbc={flags.tolist()} is not supported")
    pbc = bool(flags.all())
    cell = atoms.cell.array.copy() if pbc else np.zeros((3, 3))
    info = dict(atoms.info)
    info_pairs = info.pop(PAIRS_KEY, None)
    info_field = info.pop(FIELD_KEY, None)
    info_charge = info.pop(CHARGE_KEY, None)
    if charge is None:
        charge = 0.0 if info_charge is None else float(info_charge)
    if field is None:
        field = np.zeros(3) if info_field is None else info_field
    kept = None
    if pairs is None and info_pairs is not None:
        pairs = info_pairs
    if pairs is not None and len(pair_rows):
        raise StructureError(
            f"{source}: electron pairs given both as Es (Z=99) particles and separately"
        )
    if pairs is None:
        if len(pair_rows) == 0:
            raise StructureError(
                f"{source}: no electron pairs: set atoms.info['{PAIRS_KEY}'] (Å) or pass pairs="
            )
        kept, _ = split_core_centres(
            numbers[core_rows],
            positions[core_rows],
            positions[pair_rows],
            cell,
            pbc,
            float(charge),
            core_tolerance,
            source,
        )
        pairs = positions[pair_rows][kept]

    results = _current_results(atoms)
    forces = results.get("forces")
    if forces is not None:
        forces = np.asarray(forces)[core_rows]
    pair_forces = results.get("pair_forces")
    if pair_forces is not None and kept is not None and len(pair_forces) == len(atoms):
        pair_forces = np.asarray(pair_forces)[pair_rows][kept]
    stress = results.get("stress")
    if stress is not None:
        stress = np.asarray(stress, dtype=np.float64)
        stress = voigt_6_to_full_3x3_stress(stress) if stress.shape == (6,) else stress
    energy = results.get("energy")
    return Structure(
        numbers=numbers[core_rows],
        positions=positions[core_rows],
        pairs=pairs,
        cell=cell,
        pbc=pbc,
        field=field,
        charge=float(charge),
        energy=None if energy is None else float(energy),
        forces=forces,
        pair_forces=pair_forces,
        stress=stress,
        info=info,
        source=source,
    )


def _current_results(atoms: Atoms) -> dict:
    """Calculator results that still belong to ``atoms`` (empty if none or stale)."""
    calc = atoms.calc
    if calc is None or not getattr(calc, "results", None):
        return {}
    try:
        if calc.check_state(atoms):
            return {}
    except Exception:  # a calculator without a stored state
        return {}
    return dict(calc.results)
