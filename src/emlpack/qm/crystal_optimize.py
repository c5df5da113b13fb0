"""Optimisation of a crystal's core positions and cell with a labeler (DFT or model), by ASE.

The labeler (:class:`emlpack.qm.cp2k.CP2KLabeler`, :class:`emlpack.calculators.labeler.
ModelLabeler`, anything with ``labeler(structure, *, stress=...) -> Structure``) is wrapped as
an ASE calculator (:class:`LabelerCalculator`); ASE's BFGS moves the cores and, through
:class:`ase.filters.FrechetCellFilter`, the cell (zero external pressure, zero field). With
``symprec`` the space group of the start is kept (:class:`ase.constraints.FixSymmetry`, needs
spglib): forces and stress are symmetrised, so numerical noise cannot break it.

Every labeled step is a complete stress-set record (energy, forces, stress, electron pairs):
:func:`optimize_crystal` commits each one to an HDF5 store under ``{prefix}/{step:03d}``, where
it is training data too. The run is resumable: BFGS is deterministic, so a re-run replays the
stored steps bit for bit from the store (a geometry match, no calculation) and continues where
the interrupted run stopped.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from ase import Atoms
from ase.calculators.calculator import Calculator, all_changes
from ase.stress import full_3x3_to_voigt_6_stress

from emlpack.errors import EmlpackError
from emlpack.optional import import_optional
from emlpack.qm.crystal_sampling import carry_reference_pairs
from emlpack.structure import Structure
from emlpack.units import EV_PER_A3_IN_GPA

if TYPE_CHECKING:
    from collections.abc import Sequence

    from emlpack.data.store import DatasetStore

Labeler = Callable[..., Structure]

logger = logging.getLogger(__name__)


class CrystalOptimizationError(EmlpackError, RuntimeError):
    """The optimisation could not run (bad start, labeler failure)."""


def to_atoms(structure: Structure) -> Atoms:
    """The cores of a periodic structure as ASE Atoms (Å)."""
    return Atoms(numbers=structure.numbers, positions=structure.positions,
                 cell=structure.cell, pbc=True)


class LabelerCalculator(Calculator):
    """A labeler as an ASE calculator: energy (eV), forces (eV/Å), stress (eV/Å³, Voigt).

    Each labeled structure (with its electron pairs) is passed to ``on_label``; ``cache``
    holds already labeled structures that are returned instead of a new calculation when the
    geometry (positions and cell) matches to ``atol`` Å.
    """

    implemented_properties = ["energy", "free_energy", "forces", "stress"]

    def __init__(self, labeler: Labeler, template: Structure,
                 on_label: Callable[[Structure, bool], None] | None = None,
                 cache: list[Structure] = (), atol: float = 1e-10) -> None:
        super().__init__()
        self.labeler = labeler
        self.template = template.copy(field=np.zeros(3), energy=None, forces=None,
                                      pair_forces=None, stress=None)
        self.on_label = on_label
        self.cache = list(cache)
        self.atol = atol
        self.last: Structure | None = None

    def _lookup(self, positions: np.ndarray, cell: np.ndarray) -> Structure | None:
        for s in self.cache:
            if (s.positions.shape == positions.shape
                    and np.allclose(s.positions, positions, rtol=0, atol=self.atol)
                    and np.allclose(s.cell, cell, rtol=0, atol=self.atol)):
                return s
        return None

    def calculate(self, atoms: Atoms | None = None, properties: Sequence[str] = ("energy",),
                  system_changes: Sequence[str] = all_changes) -> None:
        """Label the cores and cell of ``atoms`` (or take the cached label of that geometry), the
        pairs started from the last label's; set energy (eV), forces (eV/Å), stress (eV/Å³)."""
        super().calculate(atoms, properties, system_changes)
        positions = np.array(self.atoms.get_positions())
        cell = np.array(self.atoms.get_cell())
        labeled = self._lookup(positions, cell)
        cached = labeled is not None
        if labeled is None:
            start = self.last if self.last is not None else self.template
            guess = start.copy(positions=positions, cell=cell,
                               pairs=carry_reference_pairs(start, positions, cell))
            labeled = self.labeler(guess, stress=True)
            if labeled.stress is None or labeled.forces is None or labeled.energy is None:
                raise CrystalOptimizationError(
                    f"{guess.source or 'structure'}: the labeler returned no energy, forces or"
                    " stress")
        if self.on_label is not None:
            self.on_label(labeled, cached)
        self.last = labeled
        self.results = {
            "energy": float(labeled.energy), "free_energy": float(labeled.energy),
            "forces": np.array(labeled.forces),
            "stress": full_3x3_to_voigt_6_stress(np.array(labeled.stress)),
        }


@dataclass
class CrystalOptimization:
    """Result of :func:`optimize_crystal`.

    Attributes:
        structure: the last labeled structure (optimised cores, cell, pairs and labels).
        converged: BFGS reached ``fmax`` (filter forces: core forces and the cell's virial
            per atom, eV/Å and eV).
        steps: labeled steps (including replayed ones).
        calculations: new labeler calls in this run (the rest replayed from the store).
        max_force: largest core force at the end (eV/Å).
        max_stress_gpa: largest stress component at the end (GPa).
        history: per step ``(energy eV, max force eV/Å, max |stress| GPa)``.
    """

    structure: Structure
    converged: bool
    steps: int
    calculations: int
    max_force: float
    max_stress_gpa: float
    history: list[tuple[float, float, float]] = field(default_factory=list)


def symmetrized_start(structure: Structure, symprec: float) -> Structure:
    """The structure with positions and cell symmetrised to the space group found at
    ``symprec`` (Å; ASE ``refine_symmetry``, which needs spglib); pairs carried along."""
    from ase.spacegroup.symmetrize import refine_symmetry

    import_optional("spglib", f"symprec={symprec:g} (the space-group constraint)",
                    alternative="symprec=None (no constraint)")

    atoms = to_atoms(structure)
    refine_symmetry(atoms, symprec=symprec)
    positions, cell = atoms.get_positions(), np.array(atoms.get_cell())
    return structure.copy(positions=positions, cell=cell,
                          pairs=carry_reference_pairs(structure, positions, cell))


def optimize_crystal(labeler: Labeler, structure: Structure, *, fmax: float = 0.01,
                     max_steps: int = 100, cell: bool = True, symprec: float | None = 0.01,
                     maxstep: float = 0.1, store_path: str | Path | None = None,
                     prefix: str = "opt", level: str = "",
                     log: Callable[[str], None] | None = None,
                     on_stored: Callable[[DatasetStore], None] | None = None,
                     ) -> CrystalOptimization:
    """BFGS optimisation of positions (and cell, ``cell=True``) at zero field and pressure.

    Args:
        labeler: computes energy, forces and stress (``stress=True``) of a structure.
        structure: periodic start (pairs are a guess for the labeler; labels ignored).
        fmax: convergence of the filter forces (eV/Å for cores; the cell gradient is the
            virial per atom in eV, so 0.01 is ~0.2 GPa for a 20-atom 158 Å³ cell).
        max_steps: BFGS steps at most.
        symprec: keep the space group found at this tolerance (Å), None = no constraint.
        maxstep: largest step of one BFGS update (Å).
        store_path: HDF5 store receiving every labeled step as ``{prefix}/NNN`` (kind
            ``stress``; numbered on from the records already there); stored geometries are
            replayed instead of recomputed.
        level: level-of-theory text for the records.
        log: receives the progress messages (default: this module's logger, INFO).
        on_stored: called with the open store after each new step is stored (e.g. to turn
            the finished steps into an immutable shard now and then).
    """
    from ase.filters import FrechetCellFilter
    from ase.optimize import BFGS

    log = log or logger.info
    if not structure.pbc:
        raise CrystalOptimizationError(f"{structure.source}: a crystal optimisation needs a"
                                       " periodic structure")
    start = symmetrized_start(structure, symprec) if symprec else structure
    store = None
    cache: list[Structure] = []
    if store_path is not None:
        from emlpack.data.store import DatasetStore

        store = DatasetStore(store_path, "a")
        keys = store.keys()
        cache = [store.structure(i) for i, k in enumerate(keys) if k.startswith(f"{prefix}/")]
    history: list[tuple[float, float, float]] = []
    counts = {"steps": 0, "new": 0}

    def on_label(s: Structure, cached: bool) -> None:
        step = counts["steps"]
        counts["steps"] += 1
        f = float(np.abs(s.forces).max())
        sig = float(np.abs(s.stress).max() * EV_PER_A3_IN_GPA)
        history.append((float(s.energy), f, sig))
        if not cached:
            counts["new"] += 1
            if store is not None:
                # next free index: a re-run with other settings continues the numbering
                info = dict(s.info, key=f"{prefix}/{len(cache) + counts['new'] - 1:03d}",
                            kind="stress")
                if level:
                    info["level"] = level
                store.append(s.copy(info=info))
                if on_stored is not None:
                    on_stored(store)
        log(f"optimize step {step:3d}{' (stored)' if cached else ''}: E = {s.energy:.6f} eV,"
            f" max force {f:.4f} eV/Å, max stress {sig:.3f} GPa")

    atoms = to_atoms(start)
    calc = LabelerCalculator(labeler, start, on_label=on_label, cache=cache)
    atoms.calc = calc
    if symprec:
        from ase.constraints import FixSymmetry

        atoms.set_constraint(FixSymmetry(atoms, symprec=symprec))
    target = FrechetCellFilter(atoms, scalar_pressure=0.0) if cell else atoms
    try:
        converged = bool(BFGS(target, maxstep=maxstep, logfile=None).run(fmax=fmax,
                                                                        steps=max_steps))
    finally:
        if store is not None:
            store.close()
    final = calc.last
    return CrystalOptimization(
        structure=final, converged=converged, steps=counts["steps"],
        calculations=counts["new"], max_force=float(np.abs(final.forces).max()),
        max_stress_gpa=float(np.abs(final.stress).max() * EV_PER_A3_IN_GPA), history=history)
