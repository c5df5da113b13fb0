"""ASE calculator for the eMLP.

The :class:`ase.Atoms` hold the atomic cores; the electron pairs (Å) live in
``atoms.info["electron_pairs"]`` (or are passed to the constructor) and the homogeneous field
(V/Å) in ``atoms.info["external_field"]`` or the constructor's ``field``. By default the pairs
are relaxed to the energy minimum at fixed cores (Born-Oppenheimer) on every call, warm-started
from the previous call's pairs moved rigidly with their nearest core. ``relax_pairs=False``
gives the static model at the given pairs.

Results: ``energy``/``free_energy`` (eV), ``forces`` on the cores (eV/Å; at relaxed pairs
these are the Born-Oppenheimer forces), ``stress`` (periodic, eV/Å^3, Voigt, ASE sign),
``dipole`` (molecules: sum q r over cores and pairs, e·Å), ``electron_pairs`` (Å) and
``pair_forces`` (eV/Å). Relaxation diagnostics are in ``calc.relax_result``. A failed
relaxation raises :class:`ase.calculators.calculator.CalculationFailed` naming the reason.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from ase import Atoms
from ase.calculators.calculator import CalculationFailed, Calculator, all_changes
from ase.stress import full_3x3_to_voigt_6_stress

from emlpack.io.ase_convert import FIELD_KEY, PAIRS_KEY, atoms_to_structure
from emlpack.nn.checkpoint import load_model
from emlpack.nn.potential import EMLP
from emlpack.relax import RelaxOptions, RelaxResult, relax_pairs


class EMLPCalculator(Calculator):
    """eMLP energies, forces, stress and dipoles, with electron pairs relaxed by default.

    Args:
        model: an :class:`EMLP` or the path of an emlpack checkpoint.
        relax_pairs: relax the electron pairs at fixed cores before every evaluation.
        field: default homogeneous field (V/Å) when ``atoms.info`` has none.
        pairs: initial electron pairs (Å) when ``atoms.info`` has none.
        relax_options: :class:`RelaxOptions` (default: fmax 1e-4 eV/Å).
        dtype: evaluation precision (float64 by default).
    """

    implemented_properties = [
        "energy",
        "free_energy",
        "forces",
        "stress",
        "dipole",
        "electron_pairs",
        "pair_forces",
    ]

    def __init__(
        self,
        model: EMLP | str | Path,
        relax_pairs: bool = True,
        field: np.ndarray | None = None,
        pairs: np.ndarray | None = None,
        relax_options: RelaxOptions | None = None,
        dtype: torch.dtype = torch.float64,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        self.model = load_model(model, dtype) if isinstance(model, (str, Path)) else model
        self.model = self.model.to(dtype).eval()
        self.dtype = dtype
        self.relax = relax_pairs
        self.default_field = np.zeros(3) if field is None else np.asarray(field, float)
        self.initial_pairs = None if pairs is None else np.asarray(pairs, float).reshape(-1, 3)
        self.relax_options = relax_options or RelaxOptions()
        self.relax_result: RelaxResult | None = None
        self._last_field: np.ndarray | None = None
        self._given_pairs: np.ndarray | None = None
        self._warm: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ state
    def _field_of(self, atoms: Atoms) -> np.ndarray:
        field = atoms.info.get(FIELD_KEY)
        return self.default_field if field is None else np.asarray(field, float).reshape(3)

    def check_state(self, atoms: Atoms, tol: float = 1e-15) -> list[str]:
        """ASE's changes plus ``field`` and ``electron_pairs`` given in ``atoms.info``."""
        changes = super().check_state(atoms, tol)
        if self._last_field is None or not np.array_equal(self._field_of(atoms), self._last_field):
            changes.append("field")
        given = atoms.info.get(PAIRS_KEY)
        if given is not None and (
            self._given_pairs is None or not np.array_equal(np.asarray(given), self._given_pairs)
        ):
            changes.append("electron_pairs")
        return changes

    def reset(self) -> None:
        super().reset()
        self._warm = None

    def _start_pairs(self, atoms: Atoms) -> np.ndarray:
        given = atoms.info.get(PAIRS_KEY)
        given = None if given is None else np.asarray(given, float).reshape(-1, 3)
        new_given = given is not None and (
            self._given_pairs is None or not np.array_equal(given, self._given_pairs)
        )
        if self._warm is not None and not new_given:
            numbers, cores, pairs = self._warm
            if np.array_equal(numbers, atoms.numbers):
                # follow the cores: each pair moves rigidly with its nearest core
                d = np.linalg.norm(pairs[:, None] - cores[None], axis=-1)
                nearest = np.argmin(d, axis=1)
                return pairs + (atoms.positions - cores)[nearest]
        if given is not None:
            self._given_pairs = given.copy()
            return given
        if self.initial_pairs is not None:
            return self.initial_pairs
        from emlpack.guess import guess_pairs  # no pairs given: Boys (molecule) / Lewis guess

        return guess_pairs(atoms)

    # ------------------------------------------------------------------ calculation
    def calculate(
        self,
        atoms: Atoms | None = None,
        properties: list[str] | None = None,
        system_changes: list[str] = all_changes,
    ) -> None:
        super().calculate(atoms, properties or ["energy"], system_changes)
        atoms = self.atoms
        field = self._field_of(atoms)
        structure = atoms_to_structure(
            atoms, pairs=self._start_pairs(atoms), field=field, source="EMLPCalculator"
        )
        if self.relax:
            result = relax_pairs(self.model, structure, self.relax_options)[0]
            self.relax_result = result
            if result.reason:
                raise CalculationFailed(
                    f"electron-pair relaxation failed for {atoms.get_chemical_formula()}:"
                    f" {result.reason}"
                )
            structure = structure.copy(pairs=result.pairs)
        out = self.model.evaluate(structure, dtype=self.dtype)
        self.results = {
            "energy": out["energy"],
            "free_energy": out["energy"],
            "forces": out["forces"],
            "electron_pairs": structure.pairs.copy(),
            "pair_forces": out["pair_forces"],
        }
        if structure.pbc:
            self.results["stress"] = full_3x3_to_voigt_6_stress(out["stress"])
        else:
            self.results["dipole"] = structure.dipole()
        self._last_field = field.copy()
        self._warm = (atoms.numbers.copy(), atoms.positions.copy(), structure.pairs.copy())
