"""Dipole polarizability (and Born charges) of a molecule by central finite fields.

Six self-consistent calculations at fields ``F0 ± h e_a`` (a = x, y, z; ``F0`` a base field,
zero by default) at fixed nuclei give
``alpha_ij = (mu_i(+h e_j) - mu_i(-h e_j)) / (2 h)`` (e·Å²/V; symmetrised) and, with forces,
the Born charges ``Z*_a,ib = dF_ib / dE_a = dmu_a / dR_ib`` (e). Each calculation can be kept as
a small file ``CACHE/field_{x,y,z}{+,-}.npz`` (written atomically), so a run resumes per field,
and the files of the eQM7 study's DFT references (``examples/eqm7/run_study.py``) are read as
they are.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from emlpack._files import write_npz_atomic
from emlpack.errors import EmlpackError
from emlpack.units import COULOMB_EV_A, FIELD_AU_IN_V_PER_A, POLARIZABILITY_A3_IN_BOHR3

#: e·Å²/V -> bohr³ (alpha / (4 pi eps0) in Å³, then bohr³)
TO_BOHR3 = COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3


class FiniteFieldError(EmlpackError, RuntimeError):
    """A finite-field calculation failed."""


@dataclass
class FiniteFieldResponse:
    """Result of :func:`finite_field_response`.

    Attributes:
        step_au: the field step h (atomic units).
        dipoles: (3, 2, 3) dipole (e·Å) at +h and -h along each axis.
        forces: (3, 2, n, 3) forces (eV/Å) at those fields, or None.
    """

    step_au: float
    dipoles: np.ndarray
    forces: np.ndarray | None = None

    @property
    def step(self) -> float:
        """The field step (V/Å)."""
        return self.step_au * FIELD_AU_IN_V_PER_A

    @property
    def polarizability(self) -> np.ndarray:
        """(3, 3) symmetrised polarizability (e·Å²/V)."""
        alpha = ((self.dipoles[:, 0] - self.dipoles[:, 1]) / (2 * self.step)).T
        return 0.5 * (alpha + alpha.T)

    @property
    def polarizability_bohr3(self) -> np.ndarray:
        """(3, 3) polarizability (bohr³)."""
        return self.polarizability * TO_BOHR3

    @property
    def born_charges(self) -> np.ndarray | None:
        """(3, 3n) Born charges dmu_a/dR_ib (e), or None without forces."""
        if self.forces is None:
            return None
        return ((self.forces[:, 0] - self.forces[:, 1]) / (2 * self.step)).reshape(3, -1)


def finite_field_response(labeler: Callable, numbers: np.ndarray, positions: np.ndarray,
                          step_au: float = 1e-3, forces: bool = False,
                          cache: str | Path | None = None, charge: float = 0.0,
                          base_field: np.ndarray | None = None) -> FiniteFieldResponse:
    """The six central finite-field calculations of a molecule at fixed nuclei.

    Args:
        labeler: a :class:`emlpack.qm.pyscf_labeler.PySCFLabeler` (or a callable like it:
            ``labeler(numbers, positions, field=, charge=, forces=, localize=)`` returning a
            result with ``ok``, ``error``, ``dipole`` and ``forces``); reuse_density makes the
            second field of each pair start from the first one's density.
        numbers, positions: the molecule (Å).
        step_au: field step (au; 1e-3 as the eQM7 study's references).
        forces: also compute forces (Born charges).
        cache: folder of the per-field files (None: nothing kept; each records its field, and
            one computed at another field raises :class:`FiniteFieldError`).
        base_field: the field (V/Å) about which the derivative is taken (default zero), e.g.
            a training configuration's own field.
    """
    f = step_au * FIELD_AU_IN_V_PER_A
    base = np.zeros(3) if base_field is None else np.asarray(base_field, dtype=float).reshape(3)
    n = len(numbers)
    dip = np.zeros((3, 2, 3))
    frc = np.zeros((3, 2, n, 3)) if forces else None
    for a in range(3):
        for k, sign in enumerate((1.0, -1.0)):
            path = None if cache is None else Path(cache) / f"field_{'xyz'[a]}{'+-'[k]}.npz"
            saved = None
            field = base.copy()
            field[a] += sign * f
            if path is not None and path.exists():
                with np.load(path) as d:
                    saved = {key: d[key] for key in d.files}
                if "field" in saved:
                    kept = saved["field"]
                else:  # a file written before the fields were recorded: zero base field
                    kept = np.zeros(3)
                    kept[a] = sign * f
                if not np.allclose(kept, field, rtol=0.0, atol=1e-12):
                    raise FiniteFieldError(f"{path}: computed at field {kept} V/Å, not at"
                                           f" {field}")
                if forces and "forces" not in saved:
                    saved = None  # kept without forces: compute again
            if saved is None:
                r = labeler(numbers, positions, field=field, charge=charge, forces=forces,
                            localize=False)
                if not r.ok:
                    raise FiniteFieldError(f"calculation under field {field} V/Å failed:"
                                           f" {r.error}")
                saved = {"dipole": np.asarray(r.dipole), "field": field}
                if forces:
                    saved["forces"] = np.asarray(r.forces)
                if path is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    write_npz_atomic(path, **saved)
            dip[a, k] = saved["dipole"]
            if forces:
                frc[a, k] = saved["forces"]
    return FiniteFieldResponse(step_au, dip, frc)
