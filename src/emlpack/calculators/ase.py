"""ASE calculator for the eMLP: one model or an ensemble, with uncertainty and warnings.

The :class:`ase.Atoms` hold the atomic cores; the electron pairs (Å) live in
``atoms.info["electron_pairs"]`` (or are passed to the constructor; without either they are
guessed, see :mod:`emlpack.pairs.guess`) and the homogeneous field (V/Å) in
``atoms.info["external_field"]`` or the constructor's ``field``. By default the pairs are
relaxed to the energy minimum at fixed cores (Born-Oppenheimer) on every call, warm-started
from the previous call's pairs moved rigidly with their nearest core
(:func:`emlpack.geometry.carry_pairs`). ``relax_pairs=False`` gives the static model at the
given pairs. The relaxation is a ``pair_solver`` (:mod:`emlpack.pairs.solvers`): by default
:class:`~emlpack.pairs.solvers.BatchedSolver` (``relax_options``); MD uses the warm-start
solvers (:class:`~emlpack.pairs.solvers.WarmStartSolver`, the paper's
:class:`~emlpack.pairs.solvers.BoxedLBFGSB`), which also return the core forces (no further
evaluation). With several models every member gets its own copy of the solver.

``model`` is an :class:`~emlpack.nn.potential.EMLP`, a checkpoint file, a folder of
checkpoints, a pretrained name (``"mini-eqm7"``), a list of those, or a
:class:`~emlpack.calculators.ensemble.ModelEnsemble`. With several models every member relaxes its
own pairs; results are the mean over members and the ``*_std`` results their standard deviation.

Results: ``energy``/``free_energy`` (eV; on the DFT scale when the models carry their DFT
hydride references, see :mod:`emlpack.calculators.ensemble`; ``energy_relative`` is then the
trained, hydride-relative energy and ``model_energy`` the network's raw output), ``forces`` on the
cores (eV/Å; at relaxed pairs these are the Born-Oppenheimer forces), ``stress`` (periodic, eV/Å^3,
Voigt, ASE sign), ``dipole`` (molecules: sum q r over cores and pairs, e·Å),
``electron_pairs`` (Å), ``pair_forces`` (eV/Å), and ``energy_std``, ``forces_std``,
``electron_pairs_std`` (Å; each member relaxes its own pairs from the same start, so pair k is
the same pair in every member), ``dipole_std``, ``stress_std``. Relaxation diagnostics are in
``calc.relax_result`` (the first member's) and ``calc.relax_results`` (one per member relaxed
in the last call). A failed relaxation (the solver's reason, or pairs not at a minimum: a
smallest pair curvature the solver measured at or below ``-FLAT_CURVATURE``, whatever the
solver said) raises
:class:`ase.calculators.calculator.CalculationFailed` naming the reason; with
``failed_members="drop"`` an ensemble instead leaves the failed member out, of this result and
of every later one of the same molecule (``calc.dropped``: member index -> reason), so that the
results stay one smooth surface, and says so in every result's warnings (as the ``emlp``
commands do); it raises only when every member has failed.

Warnings (``calc.warnings``, also logged) say when a result should not be trusted: an element
the models were not trained on, a molecule with more heavy atoms than the largest training
molecule (:func:`emlpack.bonding.largest_molecule`, recorded in the checkpoints), a spread
across members above ``energy_spread_warning`` (eV/atom) or ``force_spread_warning`` (eV/Å)
(by default the ensemble's calibrated thresholds when its members carry them, see
:mod:`emlpack.calculators.calibration`, else heuristic ones), or a molecule whose bonding
changed since the first geometry this calculator saw (:func:`emlpack.bonding.bonding_changes`);
and a model's own notice from its checkpoint (a preliminary pretrained ensemble's measured
errors). The notices and the element and size warnings are in every result's warnings and
logged once per calculator.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path

import numpy as np
import torch
from ase import Atoms
from ase.calculators.calculator import CalculationFailed, Calculator, all_changes
from ase.stress import full_3x3_to_voigt_6_stress

from emlpack.bonding import bonding_changes
from emlpack.calculators.ensemble import (
    ModelEnsemble,
    SpreadThresholds,
    as_ensemble,
    spread_thresholds,
)
from emlpack.geometry import carry_pairs
from emlpack.io.ase_convert import FIELD_KEY, PAIRS_KEY, atoms_to_structure
from emlpack.nn.potential import EMLP
from emlpack.pairs.checks import FLAT_CURVATURE, check_pairs
from emlpack.pairs.relax import RelaxOptions, RelaxResult
from emlpack.pairs.solvers import BatchedSolver, PairSolver

log = logging.getLogger(__name__)


class EMLPCalculator(Calculator):
    """eMLP energies, forces, stress and dipoles, with electron pairs relaxed by default.

    Args:
        model: an :class:`EMLP`, checkpoint path, folder of checkpoints, pretrained name,
            list of those, or a :class:`ModelEnsemble` (see the module docstring).
        relax_pairs: relax the electron pairs at fixed cores before every evaluation.
        field: default homogeneous field (V/Å) when ``atoms.info`` has none.
        pairs: initial electron pairs (Å) when ``atoms.info`` has none.
        relax_options: :class:`RelaxOptions` of the default solver (default: fmax 1e-4 eV/Å).
        pair_solver: the relaxation (:class:`~emlpack.pairs.solvers.PairSolver`; default
            ``BatchedSolver(relax_options)``); copied for every further ensemble member.
        dtype: evaluation precision (float64 by default; the caller's models are not changed).
        energy_spread_warning: warn above this ensemble energy spread (eV/atom); None: the
            ensemble's calibrated threshold, else the heuristic
            :data:`~emlpack.calculators.ensemble.ENERGY_SPREAD_WARNING`.
        force_spread_warning: warn above this ensemble force spread (eV/Å, largest
            component); None: as ``energy_spread_warning``.
        check_bonding: warn when a molecule's bonding differs from the first geometry seen.
    """

    implemented_properties = [
        "energy",
        "free_energy",
        "forces",
        "stress",
        "dipole",
        "electron_pairs",
        "pair_forces",
        "energy_std",
        "forces_std",
        "electron_pairs_std",
        "dipole_std",
        "stress_std",
        "energy_relative",
        "model_energy",
    ]

    def __init__(
        self,
        model: EMLP | str | Path | list | ModelEnsemble,
        relax_pairs: bool = True,
        field: np.ndarray | None = None,
        pairs: np.ndarray | None = None,
        relax_options: RelaxOptions | None = None,
        dtype: torch.dtype = torch.float64,
        energy_spread_warning: float | None = None,
        force_spread_warning: float | None = None,
        check_bonding: bool = True,
        pair_solver: PairSolver | None = None,
        failed_members: str = "raise",
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        if failed_members not in ("raise", "drop"):
            raise ValueError(f"failed_members: 'raise' or 'drop', got {failed_members!r}")
        self.failed_members = failed_members
        #: ``failed_members="drop"``: the members left out (index -> reason), until the atomic
        #: numbers change or :meth:`reset`
        self.dropped: dict[int, str] = {}
        self.ensemble = as_ensemble(model, dtype)
        self.model = self.ensemble.members[0].model
        self.dtype = dtype
        self.relax = relax_pairs
        self.default_field = np.zeros(3) if field is None else np.asarray(field, float)
        self.initial_pairs = None if pairs is None else np.asarray(pairs, float).reshape(-1, 3)
        self.relax_options = relax_options or RelaxOptions()
        solver = pair_solver or BatchedSolver(self.relax_options)
        #: one solver per ensemble member (warm-start solvers keep per-model state)
        self.pair_solvers: list[PairSolver] = [solver] + [
            copy.deepcopy(solver) for _ in self.ensemble.members[1:]]
        self.pair_solver = solver
        self._given_thresholds = (energy_spread_warning, force_spread_warning)
        self.check_bonding = bool(check_bonding)
        self.relax_result: RelaxResult | None = None
        self.relax_results: list[RelaxResult] = []
        self.warnings: list[str] = []
        self._logged_once: set[str] = set()  # notices and domain warnings: logged once
        self._last_field: np.ndarray | None = None
        self._given_pairs: np.ndarray | None = None
        self._warm: tuple | None = None  # (numbers, cores, cell or None, pairs per member)
        self._bonding_reference: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ state
    def _field_of(self, atoms: Atoms) -> np.ndarray:
        field = atoms.info.get(FIELD_KEY)
        return self.default_field if field is None else np.asarray(field, float).reshape(3)

    def check_state(self, atoms: Atoms, tol: float = 1e-15) -> list[str]:
        """ASE's changes plus ``field`` and ``electron_pairs`` given in ``atoms.info``."""
        changes = [] if self._same_atoms(atoms) else super().check_state(atoms, tol)
        if self._last_field is None or not np.array_equal(self._field_of(atoms), self._last_field):
            changes.append("field")
        given = atoms.info.get(PAIRS_KEY)
        if given is not None and (
            self._given_pairs is None or not np.array_equal(np.asarray(given), self._given_pairs)
        ):
            changes.append("electron_pairs")
        return changes

    def _same_atoms(self, atoms: Atoms) -> bool:
        """True when ``atoms`` equal the last calculation's bit for bit (cell, pbc and every
        array ASE compares): then ASE's tolerance comparison finds no change either, so MD's
        second force call per step skips its ``allclose`` tests (any difference falls back
        to ASE's comparison)."""
        done = self.atoms
        if done is None or done.arrays.keys() != atoms.arrays.keys():
            return False
        if not (np.array_equal(done.cell.array, atoms.cell.array)
                and np.array_equal(done.pbc, atoms.pbc)):
            return False
        return all(np.array_equal(done.arrays[k], atoms.arrays[k])
                   for k in all_changes if k in atoms.arrays)

    def reset(self) -> None:
        """Forget results, the warm start and the solvers' warm-start state."""
        super().reset()
        self._warm = None
        self.dropped = {}
        for solver in self.pair_solvers:
            solver.reset()

    def set_results(self, atoms: Atoms, results: dict) -> None:
        """Take ``results`` as this calculator's for ``atoms`` (e.g. restored from a checkpoint
        or a rollback): a call at the same atoms and field returns them without a calculation."""
        self.atoms = atoms.copy()
        self.atoms.calc = None
        self.results = copy.deepcopy(results)
        self._last_field = self._field_of(atoms).copy()

    def _start_pairs(self, atoms: Atoms) -> list[np.ndarray | None]:
        """Starting pairs (Å) of every member: warm (carried with the cores) or given/guessed
        (None for a member dropped since the warm start)."""
        n = len(self.ensemble)
        given = atoms.info.get(PAIRS_KEY)
        given = None if given is None else np.asarray(given, float).reshape(-1, 3)
        new_given = given is not None and (
            self._given_pairs is None or not np.array_equal(given, self._given_pairs)
        )
        if self._warm is not None and not new_given:
            numbers, cores, cell, member_pairs = self._warm
            if np.array_equal(numbers, atoms.numbers):
                # follow the cell and the cores: each pair moves with its nearest core
                new_cell = atoms.cell[:] if np.any(atoms.pbc) else None
                return [None if pairs is None else  # a dropped member
                        carry_pairs(pairs, cores, atoms.positions, cell, new_cell, atoms.pbc)
                        for pairs in member_pairs]
        if given is not None:
            self._given_pairs = given.copy()
            return [given] * n
        if self.initial_pairs is not None:
            return [self.initial_pairs] * n
        from emlpack.pairs.guess import guess_pairs  # no pairs: Boys (molecule) / Lewis guess

        return [guess_pairs(atoms)] * n

    # ------------------------------------------------------------------ calculation
    def calculate(
        self,
        atoms: Atoms | None = None,
        properties: list[str] | None = None,
        system_changes: list[str] = all_changes,
    ) -> None:
        """Relax each member's pairs at ``atoms`` (unless ``relax_pairs=False``), evaluate the
        members, and set ``self.results`` (ensemble mean and spread) and ``self.warnings``."""
        super().calculate(atoms, properties or ["energy"], system_changes)
        atoms = self.atoms
        field = self._field_of(atoms)
        warnings = list(self.ensemble.notices) + self.ensemble.domain_warnings(
            atoms.numbers, atoms.positions, periodic=bool(np.any(atoms.pbc)))
        once = set(warnings)  # the same at every call: logged at the first
        if self._warm is not None and not np.array_equal(self._warm[0], atoms.numbers):
            self.dropped = {}  # another molecule: every member again
        starts = self._start_pairs(atoms)
        energies, relative, raw, outs, pairs_of, dipoles = [], [], [], [], [], []
        member_pairs: list[np.ndarray | None] = []  # per member, for the next warm start
        self.relax_results = []
        self.relax_result = None
        members = zip(self.ensemble.members, starts, self.pair_solvers, strict=True)
        for k, (member, start, solver) in enumerate(members):
            if k in self.dropped:
                member_pairs.append(None)
                continue
            structure = atoms_to_structure(atoms, pairs=start, field=field,
                                           source="EMLPCalculator")
            out = None
            if self.relax:
                result = solver.relax(member.model, structure)
                self.relax_results.append(result)
                self.relax_result = self.relax_results[0]
                if not result.reason:  # not at a minimum, whatever the solver said
                    result.reason = check_pairs(np.zeros((0, 3)), np.zeros((0, 3)),
                                                min_curvature=result.min_curvature,
                                                flat_curvature=FLAT_CURVATURE)
                if result.reason:
                    which = f" (model {k}: {member.source})" if len(self.ensemble) > 1 else ""
                    failure = (f"electron-pair relaxation failed for"
                               f" {atoms.get_chemical_formula()}{which}: {result.reason}")
                    if self.failed_members == "raise" or len(self.dropped) + 1 == len(
                            self.ensemble):
                        raise CalculationFailed(failure + (
                            "; every other member had failed before" if self.dropped else ""))
                    self.dropped[k] = result.reason
                    log.warning("%s; the member is left out", failure)
                    member_pairs.append(None)
                    continue
                structure = structure.copy(pairs=result.pairs)
                if result.forces is not None and not structure.pbc:
                    # the solver evaluated the model at its result: no further evaluation
                    out = {"energy": result.energy, "forces": result.forces,
                           "pair_forces": result.pair_forces}
            if out is None:
                out = member.model.evaluate(structure, dtype=self.dtype)
            raw.append(out["energy"])
            shift = rel_shift = 0.0
            if self.ensemble.dft_scale and structure.charge == 0:
                shift = member.dft_shift(structure.numbers)
                rel_shift = member.relative_shift(structure.numbers)
            elif self.ensemble.dft_scale and k == 0:
                warnings.append(f"charge {structure.charge:g}: the hydride reference has no DFT"
                                " scale for ions; energies are the model's own")
            energies.append(out["energy"] + shift)
            relative.append(out["energy"] + rel_shift)
            outs.append(out)
            pairs_of.append(structure.pairs.copy())
            member_pairs.append(pairs_of[-1])
            if not structure.pbc:
                dipoles.append(structure.dipole())
        self.relax_result = self.relax_results[0] if self.relax_results else None
        for k, reason in sorted(self.dropped.items()):
            text = (f"model {k} ({self.ensemble.members[k].source}) left out: its electron-pair"
                    f" relaxation failed ({reason}); the results are the mean and spread of"
                    f" {len(outs)} of {len(self.ensemble)} models")
            warnings.append(text)
            once.add(text)
        forces = np.array([o["forces"] for o in outs])
        self.results = {
            "energy": float(np.mean(energies)),
            "free_energy": float(np.mean(energies)),
            "forces": forces.mean(axis=0),
            "electron_pairs": np.mean(pairs_of, axis=0),
            "pair_forces": np.mean([o["pair_forces"] for o in outs], axis=0),
            "energy_std": float(np.std(energies)),
            "forces_std": forces.std(axis=0),
            "electron_pairs_std": np.std(pairs_of, axis=0),
            "model_energy": float(np.mean(raw)),
        }
        if self.ensemble.dft_scale:
            self.results["energy_relative"] = float(np.mean(relative))
        if structure.pbc:
            stress = np.array([full_3x3_to_voigt_6_stress(o["stress"]) for o in outs])
            self.results["stress"] = stress.mean(axis=0)
            self.results["stress_std"] = stress.std(axis=0)
        else:
            self.results["dipole"] = np.mean(dipoles, axis=0)
            self.results["dipole_std"] = np.std(dipoles, axis=0)
        warnings += self._spread_warnings(len(atoms))
        warnings += self._bonding_warnings(atoms)
        for text in warnings:
            if text in self._logged_once:
                continue
            log.warning("%s: %s", atoms.get_chemical_formula(), text)
            if text in once:
                self._logged_once.add(text)
        self.warnings = warnings
        self._last_field = field.copy()
        self._warm = (atoms.numbers.copy(), atoms.positions.copy(),
                      atoms.cell[:].copy() if np.any(atoms.pbc) else None, member_pairs)

    @property
    def spread_thresholds(self) -> SpreadThresholds:
        """When the spread across the members in use is large: the thresholds given to the
        constructor, else the ensemble's calibrated ones (scaled to the members not dropped),
        else the heuristic ones (:func:`emlpack.calculators.ensemble.spread_thresholds`)."""
        energy, forces = self._given_thresholds
        t = spread_thresholds([m for k, m in enumerate(self.ensemble.members)
                               if k not in self.dropped])
        if energy is None and forces is None:
            return t
        return SpreadThresholds(t.energy if energy is None else float(energy),
                                t.forces if forces is None else float(forces), "given")

    def _spread_warnings(self, n_atoms: int) -> list[str]:
        if len(self.ensemble) - len(self.dropped) < 2:
            return []
        return self.spread_thresholds.warnings(n_atoms, self.results["energy_std"],
                                               self.results["forces_std"])

    def _bonding_warnings(self, atoms: Atoms) -> list[str]:
        if not self.check_bonding or np.any(atoms.pbc):
            return []
        ref = self._bonding_reference
        if ref is None or not np.array_equal(ref[0], atoms.numbers):
            self._bonding_reference = (atoms.numbers.copy(), atoms.positions.copy())
            return []
        changes = bonding_changes(atoms.numbers, ref[1], atoms.positions)
        return [f"bonding changed since the first geometry: {c}" for c in changes]
