"""Reference energies: the training target is ``E - E_ref``, the prediction ``U - U_ref``.

Molecules (paper eq. 19): with ``n_H, n_C, n_N, n_O`` the numbers of cores of each element,

    E_ref = n_C E_CH4 + n_N E_NH3 + n_O E_H2O + 1/2 (n_H - 2 n_O - 3 n_N - 4 n_C) E_H2

a combination of the four hydrides with the same cores and electron pairs as the molecule. The
target uses the DFT hydride energies; the prediction uses the *model's own* energies of the four
hydrides, evaluated live in every mini-batch (the hydrides are appended to the batch), so that
gradients flow through them (:class:`HydrideReference`).

A dataset of a single composition (a crystal) uses a constant reference, the mean DFT energy of
the training set (:class:`ConstantReference`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from emlpack.errors import EmlpackError
from emlpack.structure import Structure
from emlpack.units import HARTREE

if TYPE_CHECKING:
    from collections.abc import Sequence

#: order of the hydrides in coefficient vectors
HYDRIDES = ("H2", "CH4", "NH3", "H2O")
_HCNO = {1, 6, 7, 8}


class HydrideReferenceError(EmlpackError, ValueError):
    """A structure the reference cannot describe (element, charge, missing hydride)."""


def hydride_coefficients(numbers: np.ndarray, source: str = "<memory>",
                         charge: float = 0.0) -> np.ndarray:
    """Coefficients ``(c_H2, c_CH4, c_NH3, c_H2O)`` of eq. 19 for a neutral H/C/N/O molecule."""
    z = np.asarray(numbers)
    unknown = sorted(set(z.tolist()) - _HCNO)
    if unknown:
        raise HydrideReferenceError(
            f"{source}: element(s) Z={unknown} have no hydride reference (only H, C, N, O)"
        )
    if abs(charge) > 1e-12:
        raise HydrideReferenceError(f"{source}: charged molecule (charge {charge:g}) has no hydride"
                             " reference; use reference: constant")
    n = {e: int(np.sum(z == e)) for e in _HCNO}
    c_h2 = 0.5 * (n[1] - 2 * n[8] - 3 * n[7] - 4 * n[6])
    return np.array([c_h2, n[6], n[7], n[8]], dtype=np.float64)


def load_hydrides(directory: str | Path) -> tuple[list[Structure], np.ndarray]:
    """Hydride structures (``H2.xyz`` ... with Es centres) and DFT energies (eV) from a folder
    holding ``energies_*_hartree.txt`` (lines ``name energy``, Hartree), as in the paper's data."""
    from emlpack.io import read_structures

    directory = Path(directory)
    files = sorted(directory.glob("energies*hartree*.txt"))
    if not files:
        raise HydrideReferenceError(
            f"{directory}: no energies_*_hartree.txt file with hydride energies")
    table = {}
    for k, line in enumerate(files[0].read_text().splitlines()):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 2:
            raise HydrideReferenceError(
                f"{files[0]}, line {k + 1}: expected 'name energy', got {line!r}")
        table[parts[0]] = float(parts[1]) * HARTREE
    structures, energies = [], []
    for name in HYDRIDES:
        if name not in table:
            raise HydrideReferenceError(f"{files[0]}: no energy for hydride {name}")
        s = read_structures(directory / f"{name}.xyz")[0]
        s.energy = table[name]
        s.info["molecule_id"] = name
        structures.append(s)
        energies.append(table[name])
    return structures, np.array(energies)


class HydrideReference:
    """The hydride reference of eq. 19 with live model energies of the hydrides.

    Args:
        structures: the four hydrides in the order of :data:`HYDRIDES` (cores and centres).
        energies: their DFT energies (eV).
    """

    kind = "hydrides"
    n_extra = len(HYDRIDES)

    def __init__(self, structures: list[Structure],
                 energies: Sequence[float] | np.ndarray) -> None:
        if len(structures) != len(HYDRIDES):
            raise HydrideReferenceError(f"need the {len(HYDRIDES)} hydrides {HYDRIDES}")
        self.structures = list(structures)
        self.energies = np.asarray(energies, dtype=np.float64)

    def coefficients(self, s: Structure) -> np.ndarray:
        """Coefficients (4,) of eq. 19 for ``s`` (:func:`hydride_coefficients`)."""
        return hydride_coefficients(s.numbers, s.source, s.charge)

    def target(self, s: Structure) -> float:
        """``E_DFT - E_ref(DFT hydrides)`` (eV)."""
        if s.energy is None:
            raise HydrideReferenceError(f"{s.source}: no energy label")
        return float(s.energy - self.coefficients(s) @ self.energies)

    def correct(self, energy: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
        """Relative predictions from a batch's energies: the last four entries are the model's
        energies of the hydrides; ``coefficients`` is (B, 4). Returns (B,)."""
        b = coefficients.shape[0]
        live = energy[b : b + self.n_extra]
        return energy[:b] - coefficients.to(energy.dtype) @ live

    def to_metadata(self) -> dict:
        """The reference as a plain dict for a checkpoint (:func:`reference_from_metadata`)."""
        return {
            "kind": self.kind,
            "energies": self.energies.tolist(),
            "structures": [
                {"numbers": s.numbers.tolist(), "positions": s.positions.tolist(),
                 "pairs": s.pairs.tolist()}
                for s in self.structures
            ],
        }


class ConstantReference:
    """A constant reference energy (eV): the mean DFT energy of the training set."""

    kind = "constant"
    n_extra = 0
    structures: list[Structure] = []

    def __init__(self, value: float) -> None:
        self.value = float(value)

    def coefficients(self, s: Structure) -> np.ndarray:
        """Zeros (4,): a constant reference uses no hydrides."""
        return np.zeros(len(HYDRIDES))

    def target(self, s: Structure) -> float:
        """``E_DFT - value`` (eV)."""
        if s.energy is None:
            raise HydrideReferenceError(f"{s.source}: no energy label")
        return float(s.energy - self.value)

    def correct(self, energy: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
        """The batch's energies (B,) as they are (eV): the model predicts the relative energy."""
        return energy[: coefficients.shape[0]]

    def to_metadata(self) -> dict:
        """The reference as a plain dict for a checkpoint (:func:`reference_from_metadata`)."""
        return {"kind": self.kind, "value": self.value}


def reference_from_metadata(meta: dict) -> HydrideReference | ConstantReference:
    """The reference saved by ``to_metadata`` (e.g. in a model checkpoint)."""
    if meta.get("kind") == "constant":
        return ConstantReference(meta["value"])
    if meta.get("kind") == "hydrides":
        structures = [
            Structure(numbers=d["numbers"], positions=d["positions"], pairs=d["pairs"],
                      source=f"hydride {name} (checkpoint)", info={"molecule_id": name})
            for name, d in zip(HYDRIDES, meta["structures"], strict=True)
        ]
        return HydrideReference(structures, meta["energies"])
    raise HydrideReferenceError(f"unknown reference kind {meta.get('kind')!r}")
