"""The :class:`Structure`: atomic cores, electron pairs, cell and external field.

Particles and charges (elementary charges, e):

* an atomic core is a nucleus with its inner-shell electron pairs folded in:
  ``+1`` for H, ``Z - 2`` for Li..Ne (the 1s pair), ``Z - 10`` for Na..Ar;
* a valence electron pair is a particle of charge ``-2`` at the centre of a localized orbital.

Validation: ``sum(core charges) - 2 * n_pairs`` must equal the total charge; every error names
the file and the frame the structure came from (``source``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from dataclasses import field as _field
from typing import TYPE_CHECKING

import numpy as np

from emlpack.errors import EmlpackError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

PAIR_CHARGE = -2.0
#: Particle number used for electron pairs (the reference's "Es", Z = 99).
PAIR_NUMBER = 99
MAX_SUPPORTED_Z = 18


class StructureError(EmlpackError, ValueError):
    """Invalid or inconsistent structure input; the message names file, frame and problem."""


def core_charges(numbers: np.ndarray) -> np.ndarray:
    """Charge (e) of each atomic core: +1 for H, Z-2 for Z<=10, Z-10 for 10<Z<=18."""
    z = np.asarray(numbers, dtype=np.int64)
    q = np.where(z <= 2, z, np.where(z <= 10, z - 2, z - 10))
    q = np.where(z == 2, 0, q)  # He: the 1s pair is the core
    return q.astype(np.float64)


def n_core_pairs(numbers: np.ndarray) -> np.ndarray:
    """Number of electron pairs folded into each core (0 for H, 1 for Li..Ne, 5 for Na..Ar)."""
    z = np.asarray(numbers, dtype=np.int64)
    return np.where(z <= 1, 0, np.where(z <= 10, 1, 5))


@dataclass
class Structure:
    """A configuration of the eMLP: cores, electron pairs, optional cell, external field.

    Attributes:
        numbers: atomic numbers of the cores, shape (n_cores,).
        positions: core positions (Å), shape (n_cores, 3).
        pairs: electron-pair positions (Å), shape (n_pairs, 3).
        cell: lattice vectors as rows (Å), shape (3, 3); zeros for a molecule.
        pbc: periodic boundary conditions; either all True (crystal) or all False (molecule).
        field: homogeneous external field (V/Å), shape (3,).
        charge: total charge (e).
        energy: reference energy label (eV), if any.
        forces: reference core forces (eV/Å), if any.
        pair_forces: reference electron-pair forces (eV/Å), if any (zero for DFT centres).
        stress: reference stress (eV/Å^3, ASE sign, 3x3), if any.
        polarizability: reference static polarizability at these cores (e·Å²/V, 3x3:
            ``alpha_ij = dmu_i/dF_j`` with the nuclei clamped, e.g. DFT by finite fields), if
            any; times ``units.COULOMB_EV_A`` it is in Å³.
        info: any further per-frame metadata.
        source: where the structure came from, e.g. ``"data.xyz, frame 12"`` (used in errors).
    """

    numbers: np.ndarray
    positions: np.ndarray
    pairs: np.ndarray
    cell: np.ndarray = _field(default_factory=lambda: np.zeros((3, 3)))
    pbc: bool = False
    field: np.ndarray = _field(default_factory=lambda: np.zeros(3))
    charge: float = 0.0
    energy: float | None = None
    forces: np.ndarray | None = None
    pair_forces: np.ndarray | None = None
    stress: np.ndarray | None = None
    polarizability: np.ndarray | None = None
    info: dict = _field(default_factory=dict)
    source: str = "<memory>"

    def __post_init__(self) -> None:
        self.numbers = np.asarray(self.numbers, dtype=np.int64).reshape(-1)
        self.positions = _as_array(self.positions, (-1, 3), "core positions", self.source)
        self.pairs = _as_array(self.pairs, (-1, 3), "electron-pair positions", self.source)
        self.cell = _as_array(self.cell, (3, 3), "cell", self.source)
        self.field = _as_array(self.field, (3,), "external field", self.source)
        self.pbc = bool(np.all(self.pbc))
        if self.forces is not None:
            self.forces = _as_array(self.forces, (-1, 3), "forces", self.source)
        if self.pair_forces is not None:
            self.pair_forces = _as_array(self.pair_forces, (-1, 3), "pair forces", self.source)
        if self.stress is not None:
            self.stress = _as_array(self.stress, (3, 3), "stress", self.source)
        if self.polarizability is not None:
            self.polarizability = _as_array(self.polarizability, (3, 3), "polarizability",
                                            self.source)
        self.validate()

    # ------------------------------------------------------------------ properties
    @property
    def n_cores(self) -> int:
        """Number of atomic cores."""
        return len(self.numbers)

    @property
    def n_pairs(self) -> int:
        """Number of electron pairs."""
        return len(self.pairs)

    @property
    def core_charges(self) -> np.ndarray:
        """Charges (e) of the cores, (n_cores,)."""
        return core_charges(self.numbers)

    @property
    def charges(self) -> np.ndarray:
        """Charges (e) of all particles, cores first, then pairs."""
        return np.concatenate([self.core_charges, np.full(self.n_pairs, PAIR_CHARGE)])

    @property
    def all_positions(self) -> np.ndarray:
        """Positions (Å) of all particles, cores first, then pairs."""
        return np.concatenate([self.positions, self.pairs], axis=0)

    @property
    def all_numbers(self) -> np.ndarray:
        """Particle numbers: Z for cores, 99 for electron pairs."""
        return np.concatenate([self.numbers, np.full(self.n_pairs, PAIR_NUMBER)])

    @property
    def volume(self) -> float:
        """Cell volume (Å³); 0 for a molecule."""
        return float(abs(np.linalg.det(self.cell))) if self.pbc else 0.0

    def dipole(self) -> np.ndarray:
        """Dipole moment sum_i q_i r_i (e·Å) of cores and pairs (origin dependent if charged)."""
        return self.charges @ self.all_positions

    def copy(self, **changes) -> Structure:
        """A deep copy, with attributes replaced by ``changes``."""
        new = {
            k: (v.copy() if isinstance(v, np.ndarray) else v)
            for k, v in self.__dict__.items()
        }
        new["info"] = dict(self.info)
        new.update(changes)
        return replace(self, **{k: new[k] for k in new})

    def repeated(self, reps: tuple[int, int, int]) -> Structure:
        """The periodic structure repeated ``reps`` times along its cell vectors (cores and
        pairs; the first cell's particles first, then image by image with the third index
        fastest); labels, which are per cell, are dropped. The field and info are kept."""
        if not self.pbc:
            raise StructureError(f"{self.source}: only a periodic structure can be repeated")
        reps = tuple(int(n) for n in reps)
        if len(reps) != 3 or min(reps) < 1:
            raise StructureError(f"{self.source}: repetitions must be 3 positive integers,"
                                 f" got {reps}")
        shifts = np.array([(a, b, c) for a in range(reps[0]) for b in range(reps[1])
                           for c in range(reps[2])], dtype=float) @ self.cell
        return Structure(
            numbers=np.tile(self.numbers, len(shifts)),
            positions=(self.positions[None] + shifts[:, None]).reshape(-1, 3),
            pairs=(self.pairs[None] + shifts[:, None]).reshape(-1, 3),
            cell=np.array(reps, dtype=float)[:, None] * self.cell, pbc=True,
            field=self.field.copy(), charge=self.charge * len(shifts), info=dict(self.info),
            source=f"{self.source} x {reps[0]}x{reps[1]}x{reps[2]}")

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        """Raise :class:`StructureError` when the structure is inconsistent."""
        where = self.source
        if len(self.positions) != len(self.numbers):
            raise StructureError(
                f"{where}: {len(self.numbers)} atomic numbers but {len(self.positions)} positions"
            )
        if len(self.numbers) == 0:
            raise StructureError(f"{where}: no atomic cores")
        bad = (self.numbers < 1) | (self.numbers > MAX_SUPPORTED_Z)
        if np.any(bad):
            raise StructureError(
                f"{where}: unsupported element(s) with Z={sorted(set(self.numbers[bad].tolist()))}"
                f" (emlpack supports Z=1..{MAX_SUPPORTED_Z})"
            )
        for name, arr in (
            ("core positions", self.positions),
            ("electron-pair positions", self.pairs),
            ("external field", self.field),
            ("cell", self.cell),
            ("polarizability", () if self.polarizability is None else self.polarizability),
        ):
            if not np.all(np.isfinite(arr)):
                raise StructureError(f"{where}: {name} contain NaN or infinity")
        if self.forces is not None and self.forces.shape != self.positions.shape:
            raise StructureError(
                f"{where}: forces have shape {self.forces.shape}, expected {self.positions.shape}"
            )
        if self.pair_forces is not None and self.pair_forces.shape != self.pairs.shape:
            raise StructureError(
                f"{where}: pair forces have shape {self.pair_forces.shape},"
                f" expected {self.pairs.shape}"
            )
        if self.pbc and abs(np.linalg.det(self.cell)) < 1e-6:
            raise StructureError(f"{where}: periodic structure with a singular cell")
        expected_pairs = (self.core_charges.sum() - self.charge) / 2.0
        if expected_pairs != round(expected_pairs):
            raise StructureError(
                f"{where}: odd number of valence electrons (core charges"
                f" {self.core_charges.sum():g}, total charge {self.charge:g});"
                " eMLP needs closed-shell electron pairs"
            )
        if int(round(expected_pairs)) != self.n_pairs:
            raise StructureError(
                f"{where}: {self.n_pairs} electron pairs, but core charges"
                f" {self.core_charges.sum():g} and total charge {self.charge:g} need"
                f" {int(round(expected_pairs))}"
            )


def _as_array(value: ArrayLike, shape: tuple[int, ...], name: str, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
        if shape[0] == -1 and arr.size == 0:
            return arr.reshape(0, *shape[1:])
        return arr.reshape(shape) if shape[0] == -1 else _check_shape(arr, shape)
    except (ValueError, TypeError) as exc:
        raise StructureError(f"{where}: {name} must have shape {shape}: {exc}") from None


def _check_shape(arr: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    if arr.shape != shape:
        raise ValueError(f"got shape {arr.shape}")
    return arr
