"""Sampling of configurations as in the paper (eQM7 and beta-glycine).

* molecules from SMILES (RDKit embedding; radical brackets such as ``[N]`` of QM7 restored to
  the closed-shell multiple bonds they stand for);
* normal-mode sampling (NMS, Smith et al. 2017): a random subset of the vibrational modes, each
  with a Boltzmann-distributed amplitude at temperature ``T`` (mean harmonic energy k_B T / 2
  per selected mode);
* torsion sampling: a random rotatable bond, a random angle, the smaller fragment rotated
  rigidly;
* dimer sampling: a CH4, NH3 or H2O probe at a random orientation, with the closest
  intermolecular distance uniform in [0.9, 6] Å;
* a random homogeneous field (uniform direction, magnitude uniform up to 0.01 au);
* cell-extended normal-mode sampling for crystals: the extended Hessian in (positions, cell)
  with the 6 rigid-body modes projected out, sampled from the multivariate normal at ``T``.

Units: Å, eV, eV/Å^2 (Hessians), K, V/Å (fields), amu. Everything takes a
``numpy.random.Generator`` so that a sample is reproducible from its seed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from emlpack import geometry
from emlpack.errors import EmlpackError
from emlpack.optional import import_optional
from emlpack.units import BOLTZMANN_EV_K, FIELD_AU_IN_V_PER_A

if TYPE_CHECKING:
    from collections.abc import Sequence

    from rdkit.Chem import Mol

#: ANI-style floor of the harmonic force constant (eV/Å^2 per amu), avoiding huge amplitudes
#: along nearly free (e.g. methyl-rotor) modes; about 100 cm^-1
MIN_MODE_FORCE_CONSTANT = 0.06


class SamplingError(EmlpackError, ValueError):
    """A molecule or recipe cannot be sampled; the message says which and why."""


# ---------------------------------------------------------------------------------- molecules
@dataclass
class Molecule:
    """A molecule prepared for sampling.

    Attributes:
        name: identifier (e.g. ``"qm7-0003"``).
        numbers: atomic numbers (n,).
        positions: equilibrium positions (Å), (n, 3).
        bonds: bonded atom pairs with bond orders, (n_bonds, 3) ints ``(i, j, order)``
            (order 4 = aromatic).
        ring_bonds: True for bonds in a ring, (n_bonds,).
        hessian: Cartesian Hessian (eV/Å^2), (3n, 3n), or None before preparation.
        smiles: the source SMILES, if any.
    """

    name: str
    numbers: np.ndarray
    positions: np.ndarray
    bonds: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))
    ring_bonds: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    hessian: np.ndarray | None = None
    smiles: str = ""

    def rotatable_bonds(self) -> list[tuple[int, int]]:
        """Single, non-ring bonds between two atoms that both have other neighbours."""
        degree = np.zeros(len(self.numbers), dtype=int)
        for i, j, _ in self.bonds:
            degree[i] += 1
            degree[j] += 1
        out = []
        for (i, j, order), ring in zip(self.bonds, self.ring_bonds, strict=True):
            if order == 1 and not ring and degree[i] > 1 and degree[j] > 1:
                out.append((int(i), int(j)))
        return out


def restore_closed_shell(mol: Mol) -> Mol:
    """Turn QM7's radical brackets (``[N]``, ``[C]``) back into multiple bonds (RDKit mol).

    Adjacent atoms with unpaired electrons get their bond order raised by one per pair, the
    most constrained atoms first. Raises :class:`SamplingError` when electrons stay unpaired.
    """
    from rdkit import Chem

    rw = Chem.RWMol(mol)
    while True:
        rad = {a.GetIdx(): a.GetNumRadicalElectrons() for a in rw.GetAtoms()
               if a.GetNumRadicalElectrons() > 0}
        if not rad:
            break
        options = {
            i: [n.GetIdx() for n in rw.GetAtomWithIdx(i).GetNeighbors() if n.GetIdx() in rad]
            for i in rad
        }
        i = min((i for i in rad if options[i]), key=lambda k: len(options[k]), default=None)
        if i is None:
            raise SamplingError(
                f"{Chem.MolToSmiles(mol)}: unpaired electrons on atoms {sorted(rad)} cannot be"
                " paired into multiple bonds (open shell)"
            )
        j = min(options[i], key=lambda k: len(options[k]))
        bond = rw.GetBondBetweenAtoms(i, j)
        new_order = {Chem.BondType.SINGLE: Chem.BondType.DOUBLE,
                     Chem.BondType.DOUBLE: Chem.BondType.TRIPLE}.get(bond.GetBondType())
        if new_order is None:
            raise SamplingError(f"{Chem.MolToSmiles(mol)}: cannot raise bond {i}-{j} further")
        bond.SetBondType(new_order)
        for k in (i, j):
            atom = rw.GetAtomWithIdx(k)
            atom.SetNumRadicalElectrons(atom.GetNumRadicalElectrons() - 1)
    out = rw.GetMol()
    Chem.SanitizeMol(out)
    return out


def molecule_from_smiles(smiles: str, name: str = "", seed: int = 0) -> Molecule:
    """Embed a SMILES (with hydrogens) in 3D with RDKit (ETKDG, then MMFF/UFF relaxation)."""
    import_optional("rdkit", "a molecule from SMILES (RDKit 3D embedding)")
    from rdkit import Chem, RDLogger
    from rdkit.Chem import AllChem

    RDLogger.DisableLog("rdApp.*")
    mol = Chem.MolFromSmiles(smiles)
    if mol is None:
        raise SamplingError(f"{name or smiles}: RDKit cannot parse SMILES {smiles!r}")
    if any(a.GetSymbol() not in ("H", "C", "N", "O", "F") for a in mol.GetAtoms()):
        bad = sorted({a.GetSymbol() for a in mol.GetAtoms()} - {"H", "C", "N", "O", "F"})
        raise SamplingError(f"{name or smiles}: element(s) {bad} are out of scope")
    mol = restore_closed_shell(mol)
    mol = Chem.AddHs(mol)
    params = AllChem.ETKDGv3()
    params.randomSeed = int(seed)
    if AllChem.EmbedMolecule(mol, params) != 0:
        raise SamplingError(f"{name or smiles}: RDKit embedding failed")
    if AllChem.MMFFHasAllMoleculeParams(mol):
        AllChem.MMFFOptimizeMolecule(mol, maxIters=2000)
    else:
        AllChem.UFFOptimizeMolecule(mol, maxIters=2000)
    pos = mol.GetConformer().GetPositions()
    numbers = np.array([a.GetAtomicNum() for a in mol.GetAtoms()], dtype=np.int64)
    order = {Chem.BondType.SINGLE: 1, Chem.BondType.DOUBLE: 2, Chem.BondType.TRIPLE: 3,
             Chem.BondType.AROMATIC: 4}
    bonds = np.array(
        [(b.GetBeginAtomIdx(), b.GetEndAtomIdx(), order.get(b.GetBondType(), 1))
         for b in mol.GetBonds()], dtype=np.int64,
    ).reshape(-1, 3)
    ring = np.array([b.IsInRing() for b in mol.GetBonds()], dtype=bool)
    return Molecule(name=name or smiles, numbers=numbers, positions=pos, bonds=bonds,
                    ring_bonds=ring, smiles=smiles)


#: SMILES of the dimer probes of the paper
PROBES = {"CH4": "C", "NH3": "N", "H2O": "O"}


# ---------------------------------------------------------------------------------- fields
#: how :func:`random_field` draws the field: ``ball``, uniform in the ball of radius ``max_au``
#: (the authors' eQM7 data: mean |E| 0.0075 au for 0.01 au, 14.5 % of the shared frames below
#: 0.005 au); ``magnitude``, uniform direction with |E| uniform in [0, max_au] (mean 0.005 au;
#: emlpack's recipes before 2026-11-25, ~1.8x less mean E^2, the signal pairs' stiffness is
#: learnt from)
FIELD_DISTRIBUTIONS = ("ball", "magnitude")


def random_field(rng: np.random.Generator, max_au: float = 0.01,
                 distribution: str = "ball") -> np.ndarray:
    """A homogeneous field (V/Å) of at most ``max_au`` au, drawn as ``distribution`` says
    (:data:`FIELD_DISTRIBUTIONS`); both draw the same variates (3 normal, 1 uniform)."""
    if distribution not in FIELD_DISTRIBUTIONS:
        raise SamplingError(f"field distribution {distribution!r}: expected one of"
                            f" {', '.join(FIELD_DISTRIBUTIONS)}")
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    u = rng.uniform(0.0, 1.0)
    magnitude = max_au * (np.cbrt(u) if distribution == "ball" else u)
    return direction * magnitude * FIELD_AU_IN_V_PER_A


# ---------------------------------------------------------------------------------- normal modes
def masses_of(numbers: np.ndarray) -> np.ndarray:
    """Atomic masses (amu) of ASE."""
    from ase.data import atomic_masses

    return atomic_masses[np.asarray(numbers)]


def normal_modes(numbers: np.ndarray, positions: np.ndarray,
                 hessian: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`emlpack.geometry.normal_modes` of a Cartesian Hessian (eV/Å^2) with the masses
    of ``numbers``: ``(k, modes)``, force constants ``omega^2`` (eV/(Å^2 amu)) of the
    vibrations and their mass-weighted orthonormal eigenvectors (3n, n_vib)."""
    return geometry.normal_modes(hessian, positions, masses_of(numbers))


@dataclass
class NMSSample:
    """A normal-mode sample: positions (Å), selected modes, harmonic energy (eV)."""

    positions: np.ndarray
    modes: np.ndarray
    harmonic_energy: float


def has_negative_curvature(k: np.ndarray) -> bool:
    """True when the force constants ``k`` (eV/(Å^2 amu), :func:`normal_modes`) have one below
    -1e-3 of the largest magnitude (or of 1): a saddle point, not a minimum."""
    k = np.asarray(k, dtype=float)
    return bool(len(k)) and bool(np.any(k < -1e-3 * max(abs(k).max(), 1.0)))


def normal_mode_sample(numbers: np.ndarray, positions: np.ndarray, hessian: np.ndarray,
                       temperature: float, rng: np.random.Generator, n_modes: int | None = None,
                       min_force_constant: float = MIN_MODE_FORCE_CONSTANT,
                       modes: tuple[np.ndarray, np.ndarray] | None = None) -> NMSSample:
    """Displace along a random subset of normal modes with Boltzmann amplitudes at ``T`` (K).

    The number of modes is uniform in 1..n_vib unless ``n_modes`` is given. Each selected
    mode gets ``q ~ N(0, k_B T / k)`` (mass-weighted), so its mean harmonic energy is
    ``k_B T / 2``. Force constants below ``min_force_constant`` are raised to it.
    ``modes`` may pass the result of :func:`normal_modes` to skip the diagonalisation.
    """
    k, modes = normal_modes(numbers, positions, hessian) if modes is None else modes
    if len(k) == 0:
        raise SamplingError("no vibrational modes (a single atom?)")
    if has_negative_curvature(k):
        raise SamplingError(
            f"Hessian has negative curvature ({k.min():.3g} eV/Å^2/amu): not at a minimum"
        )
    k_eff = np.maximum(k, min_force_constant)
    n_sel = int(rng.integers(1, len(k) + 1)) if n_modes is None else int(n_modes)
    chosen = np.sort(rng.choice(len(k), size=n_sel, replace=False))
    kt = BOLTZMANN_EV_K * temperature
    q = rng.normal(size=n_sel) * np.sqrt(kt / k_eff[chosen])
    m = masses_of(numbers)
    dx = (modes[:, chosen] @ q) / np.repeat(np.sqrt(m), 3)
    energy = 0.5 * float(np.sum(k[chosen] * q**2))
    new = np.asarray(positions, dtype=float) + dx.reshape(-1, 3)
    return NMSSample(positions=new, modes=chosen, harmonic_energy=energy)


# ---------------------------------------------------------------------------------- torsion
def fragment_of(n_atoms: int, bonds: np.ndarray, i: int, j: int) -> np.ndarray:
    """Atoms on ``j``'s side of bond ``i-j`` (boolean mask); raises if the bond is in a ring."""
    adj: list[list[int]] = [[] for _ in range(n_atoms)]
    for a, b, _ in bonds:
        adj[a].append(int(b))
        adj[b].append(int(a))
    seen = np.zeros(n_atoms, dtype=bool)
    seen[j] = True
    stack = [j]
    while stack:
        a = stack.pop()
        for b in adj[a]:
            if a == j and b == i:
                continue
            if b == i:
                raise SamplingError(f"bond {i}-{j} is in a ring: no rigid torsion")
            if not seen[b]:
                seen[b] = True
                stack.append(b)
    return seen


def rotate_about_bond(positions: np.ndarray, i: int, j: int, mask: np.ndarray,
                      angle: float) -> np.ndarray:
    """Rotate the atoms in ``mask`` rigidly by ``angle`` (rad) about the axis i->j."""
    axis = positions[j] - positions[i]
    axis = axis / np.linalg.norm(axis)
    c, s = np.cos(angle), np.sin(angle)
    r = positions[mask] - positions[j]
    rot = r * c + np.cross(axis, r) * s + np.outer(r @ axis, axis) * (1 - c)
    out = positions.copy()
    out[mask] = rot + positions[j]
    return out


def torsion_sample(molecule: Molecule, positions: np.ndarray,
                   rng: np.random.Generator) -> tuple[np.ndarray, tuple[int, int] | None]:
    """Rotate the smaller side of a random rotatable bond by a uniform random angle.

    Returns the new positions (Å) and the bond, or the input and None without rotatable bonds.
    """
    bonds = molecule.rotatable_bonds()
    if not bonds:
        return np.array(positions, dtype=float), None
    i, j = bonds[int(rng.integers(len(bonds)))]
    mask = fragment_of(len(molecule.numbers), molecule.bonds, i, j)
    if mask.sum() > len(mask) / 2:
        i, j = j, i
        mask = fragment_of(len(molecule.numbers), molecule.bonds, i, j)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    return rotate_about_bond(np.asarray(positions, dtype=float), i, j, mask, angle), (i, j)


# ---------------------------------------------------------------------------------- dimers
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed rotation matrix (3, 3)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def closest_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Smallest distance (Å) between a point of ``a`` and a point of ``b``."""
    return float(np.min(np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)))


def dimer_sample(positions: np.ndarray, probe_positions: np.ndarray, rng: np.random.Generator,
                 d_min: float = 0.9, d_max: float = 6.0) -> tuple[np.ndarray, float]:
    """Place a randomly rotated probe so that the closest intermolecular distance is uniform.

    The probe's centre moves along a random direction from the molecule's centre until the
    closest distance equals ``d ~ U(d_min, d_max)`` (Å); returns (probe positions, d).
    """
    pos = np.asarray(positions, dtype=float)
    probe = np.asarray(probe_positions, dtype=float)
    probe = (probe - probe.mean(axis=0)) @ random_rotation(rng).T
    target = rng.uniform(d_min, d_max)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    centre = pos.mean(axis=0)
    extent = np.max(np.linalg.norm(pos - centre, axis=1)) + np.max(np.linalg.norm(probe, axis=1))
    lo, hi = 0.0, extent + target + 1.0
    # distance along the ray is not monotonic near the molecule: start from far away, walk in
    # until the closest distance first drops below the target, then bisect that bracket
    steps = np.linspace(hi, 0.0, 400)
    prev = hi
    for t in steps:
        if closest_distance(pos, probe + centre + t * direction) < target:
            lo, hi = t, prev
            break
        prev = t
    else:
        raise SamplingError("could not place the probe at the requested distance")
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if closest_distance(pos, probe + centre + mid * direction) < target:
            lo = mid
        else:
            hi = mid
    placed = probe + centre + hi * direction
    return placed, closest_distance(pos, placed)


# ---------------------------------------------------------------------------------- crystals
def cell_normal_mode_sample(numbers: Sequence[int] | np.ndarray, positions: np.ndarray,
                            cell: np.ndarray,
                            hessian: np.ndarray | Callable[[np.ndarray, np.ndarray], np.ndarray],
                            temperature: float, rng: np.random.Generator,
                            min_eigenvalue: float | None = None,
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Cell-extended normal-mode sample of a crystal (paper, beta-glycine).

    ``hessian`` is the extended Hessian (eV/Å^2), (3n+9, 3n+9), in the Cartesian positions and
    the 9 cell-matrix elements (rows = lattice vectors), or a callable ``(positions, cell) ->``
    that matrix. The 3 translations and 3 rigid rotations (of positions and cell together) are
    projected out; the remaining 3n+3 internal coordinates ``x`` are drawn from
    ``N(0, k_B T H_int^-1)`` and mapped back. Returns (positions (Å), cell (Å)).
    ``min_eigenvalue`` (eV/Å^2): internal eigenvalues below it are raised to it instead of
    raising (e.g. a model Hessian evaluated away from the model's own minimum).
    """
    pos = np.asarray(positions, dtype=float)
    cell = np.asarray(cell, dtype=float)
    h = hessian(pos, cell) if callable(hessian) else np.asarray(hessian, dtype=float)
    n = len(pos)
    if h.shape != (3 * n + 9, 3 * n + 9):
        raise SamplingError(f"extended Hessian must be ({3 * n + 9}, {3 * n + 9}), got {h.shape}")
    h = 0.5 * (h + h.T)
    # rigid-body motions of the extended coordinates: translations move positions only,
    # rotations act on positions and on the cell vectors
    full = geometry.internal_basis(geometry.rigid_body_modes(pos, cell=cell))
    h_int = full.T @ h @ full
    w, v = np.linalg.eigh(0.5 * (h_int + h_int.T))
    if min_eigenvalue is not None:
        w = np.maximum(w, min_eigenvalue)
    if np.any(w <= 0):
        raise SamplingError(f"internal extended Hessian is not positive definite ({w.min():.3g})")
    kt = BOLTZMANN_EV_K * temperature
    x = v @ (rng.normal(size=len(w)) * np.sqrt(kt / w))
    d = full @ x
    return pos + d[: 3 * n].reshape(n, 3), cell + d[3 * n:].reshape(3, 3)
