"""Torch datasets over extxyz files and HDF5 stores, splits, and collation into model batches.

* :func:`load_data` reads an extxyz file or a :class:`~emlpack.data.store.DatasetStore`
  (``.h5``); store records of kind ``hydride`` are returned separately as the hydride
  references with their energies.
* :func:`split_indices` splits by molecule (validation and test hold unseen molecules, as in the
  paper) or by configuration within each molecule (for files with a handful of molecules).
* :class:`StructureDataset` is a map-style torch Dataset of ``(index, Structure)``.
* :class:`Collater` turns a list of ``(index, Structure)`` into a :class:`Batch`: the model's
  :class:`~emlpack.nn.graph.Graph` (with the hydrides appended when the reference is live)
  and the targets, after seeded augmentation.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from emlpack.data.augment import AugmentationConfig, augment
from emlpack.data.references import HYDRIDES, HydrideReference
from emlpack.data.shards import is_sharded, read_shards
from emlpack.errors import EmlpackError
from emlpack.nn.graph import Graph, collate
from emlpack.structure import Structure

if TYPE_CHECKING:
    from emlpack.data.references import ConstantReference

_SYMBOLS = {1: "H", 6: "C", 7: "N", 8: "O", 9: "F", 15: "P", 16: "S", 17: "Cl", 3: "Li",
            11: "Na", 5: "B", 14: "Si", 12: "Mg", 13: "Al", 4: "Be", 2: "He", 10: "Ne", 18: "Ar"}


def formula(numbers: np.ndarray) -> str:
    """Hill formula of the cores, e.g. ``C2H6O``."""
    counts = Counter(_SYMBOLS.get(int(z), f"Z{int(z)}") for z in numbers)
    order = (["C", "H"] if "C" in counts else []) + sorted(
        k for k in counts if "C" not in counts or k not in ("C", "H"))
    return "".join(f"{e}{counts[e] if counts[e] > 1 else ''}" for e in order)


def molecule_id(s: Structure) -> str:
    """The molecule a configuration belongs to: ``info['molecule_id']`` or its formula."""
    mid = s.info.get("molecule_id")
    return str(mid) if mid not in (None, "") else formula(s.numbers)


def training_domain(structures: Sequence[Structure]) -> dict:
    """What a model trained on ``structures`` has seen, as recorded in its checkpoint:
    ``elements`` (sorted atomic numbers of the cores) and ``max_heavy_atoms``, the heavy atoms
    of its largest molecule (None without molecular configurations). A molecule's size is the
    smallest over its configurations (:func:`molecule_id`) of their largest bonded fragment
    (:func:`emlpack.bonding.largest_molecule`), so that a dimer configuration whose partner
    came within bonding distance (mini-eQM7 has 6 in 849 training configurations) does not
    count as a larger molecule. The calculator warns outside either."""
    from emlpack.bonding import largest_molecule

    elements = sorted({int(z) for s in structures for z in s.numbers})
    sizes: dict[str, int] = {}
    for s in structures:
        if not s.pbc:
            n = largest_molecule(s.numbers, s.positions)
            key = molecule_id(s)
            sizes[key] = min(n, sizes.get(key, n))
    return {"elements": elements, "max_heavy_atoms": max(sizes.values()) if sizes else None}


class DataError(EmlpackError, ValueError):
    """Unusable training data; the message names the file."""


def load_data(path: str | Path) -> tuple[list[Structure], dict | None]:
    """Structures of an extxyz file, HDF5 store or data-set folder of shards, and the hydrides
    found in a store or folder.

    Returns ``(structures, hydrides)`` where ``hydrides`` is ``None`` or a dict with
    ``structures`` (in the order of :data:`HYDRIDES`) and ``energies`` (eV)."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such data file")
    if is_sharded(path):
        data = read_shards(path)
        return data.structures, data.hydrides
    if path.suffix in (".h5", ".hdf5"):
        from emlpack.data.store import DatasetStore

        with DatasetStore(path, "r") as store:
            all_structures = list(store)
            refs = store.references()
        structures = [s for s in all_structures if s.info.get("kind") != "hydride"]
        by_name = {s.info.get("molecule_id"): s for s in all_structures
                   if s.info.get("kind") == "hydride"}
        hydrides = None
        if all(h in by_name for h in HYDRIDES):
            energies = [refs[h]["energy"] if h in refs else by_name[h].energy for h in HYDRIDES]
            hydrides = {"structures": [by_name[h] for h in HYDRIDES], "energies": energies}
        return structures, hydrides
    from emlpack.io import read_structures

    return read_structures(path), None


def split_indices(
    molecule_ids: Sequence[str],
    fractions: Sequence[float] = (0.9, 0.05, 0.05),
    by: str = "molecule",
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Deterministic train/validation/test split: ``{"train", "val", "test"}`` -> indices.

    ``by="molecule"``: whole molecules go to one subset (unseen molecules in validation and
    test; every non-zero fraction gets at least one molecule when there are enough).
    ``by="configuration"``: each molecule's configurations are split with the fractions.
    (A data-set folder's own split by molecule is :meth:`ShardedData.split_indices`.)"""
    ids = np.asarray(list(molecule_ids), dtype=object)
    f = np.asarray(fractions, dtype=float)
    if len(f) != 3 or np.any(f < 0) or f.sum() <= 0:
        raise ValueError(f"split fractions must be three non-negative numbers, got {fractions}")
    f = f / f.sum()
    rng = np.random.default_rng(seed)
    names = np.array(sorted(set(ids.tolist())), dtype=object)
    out = {"train": [], "val": [], "test": []}
    if by == "molecule":
        order = names[rng.permutation(len(names))]
        counts = _allocate(len(order), f)
        groups = np.split(order, np.cumsum(counts)[:2])
        for key, group in zip(out, groups, strict=True):
            members = set(group.tolist())
            out[key] = [k for k, m in enumerate(ids) if m in members]
    elif by == "configuration":
        for name in names:
            idx = np.flatnonzero(ids == name)
            idx = idx[rng.permutation(len(idx))]
            counts = _allocate(len(idx), f)
            for key, part in zip(out, np.split(idx, np.cumsum(counts)[:2]), strict=True):
                out[key].extend(part.tolist())
    else:
        raise ValueError(f"split 'by' must be 'molecule' or 'configuration', got {by!r}")
    return {k: np.array(sorted(v), dtype=np.int64) for k, v in out.items()}


def _allocate(n: int, f: np.ndarray) -> np.ndarray:
    """Counts per subset summing to ``n``; non-zero fractions get >= 1 when n allows."""
    counts = np.floor(f * n).astype(int)
    need = (f > 0) & (counts == 0)
    for k in np.flatnonzero(need):
        if n - counts.sum() > 0 or counts[0] > 1:
            counts[k] = 1
    counts[0] = n - counts[1:].sum()
    if counts[0] < 0:
        counts[0] = 0
    return counts


class StructureDataset(torch.utils.data.Dataset):
    """Map-style dataset of ``(index, Structure)`` over a sequence of structures."""

    def __init__(self, structures: Sequence[Structure], indices: Sequence[int] | None = None):
        self.structures = structures
        self.indices = np.arange(len(structures)) if indices is None else np.asarray(indices)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, k: int) -> tuple[int, Structure]:
        idx = int(self.indices[k])
        return idx, self.structures[idx]


@dataclass
class Batch:
    """A model batch and its targets. Forces: cores of all structures, then pairs (eV/Å)."""

    graph: Graph
    n_structures: int
    energy: torch.Tensor  # (B,) relative target energy (eV)
    coefficients: torch.Tensor  # (B, 4) hydride coefficients
    n_cores: torch.Tensor  # (B,)
    core_mask: torch.Tensor  # (N_graph,) particles that are cores of data structures
    pair_mask: torch.Tensor  # (N_graph,) particles that are pairs of data structures
    forces: torch.Tensor  # (N_graph, 3) targets (zero where not labelled)
    stress: torch.Tensor  # (B, 3, 3) eV/Å^3
    has_stress: torch.Tensor  # (B,) bool
    indices: list[int]
    n_augmented: int = 0
    n_singular: int = 0
    #: (B, 3, 3) polarizability labels (e·Å²/V, float64; zero where not labelled)
    polarizability: torch.Tensor | None = None
    has_polarizability: torch.Tensor | None = None  # (B,) bool

    def to(self, device: torch.device | str) -> Batch:
        """A copy with the graph and the target tensors on ``device``."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        for name, value in out.items():
            if isinstance(value, torch.Tensor):
                out[name] = value.to(device)
        out["graph"] = self.graph.to(device=device)
        return Batch(**out)


class Collater:
    """Callable for ``DataLoader(collate_fn=...)``: augmentation, reference, graph, targets.

    Augmentation of configuration ``index`` in epoch ``epoch`` uses the generator seeded with
    ``(seed, epoch, index)``; set :attr:`epoch` before each epoch."""

    def __init__(self, reference: HydrideReference | ConstantReference, cutoff: float,
                 gcut: float, dtype: torch.dtype = torch.float32,
                 augmentation: AugmentationConfig | None = None, seed: int = 0):
        self.reference = reference
        self.cutoff, self.gcut, self.dtype = cutoff, gcut, dtype
        self.augmentation = augmentation
        self.seed = seed
        self.epoch = 0

    def __call__(self, items: Sequence[tuple[int, Structure]]) -> Batch:
        """A :class:`Batch` of the ``(index, structure)`` items, each augmented first if enabled."""
        structures, indices = [], []
        n_aug = n_sing = 0
        aug = self.augmentation
        for idx, s in items:
            if aug is not None and aug.enabled:
                rng = np.random.default_rng([self.seed, self.epoch, idx])
                s, info = augment(s, rng, aug)
                n_aug += info.augmented
                n_sing += info.singular
            structures.append(s)
            indices.append(idx)
        return make_batch(structures, self.reference, self.cutoff, self.gcut, self.dtype,
                          indices, n_aug, n_sing)


def make_batch(structures: Sequence[Structure], reference: HydrideReference | ConstantReference,
               cutoff: float, gcut: float, dtype: torch.dtype,
               indices: Sequence[int] | None = None,
               n_augmented: int = 0, n_singular: int = 0) -> Batch:
    """A :class:`Batch` of labelled ``structures`` (hydrides appended for a live reference)."""
    b = len(structures)
    extra = list(reference.structures) if isinstance(reference, HydrideReference) else []
    g = collate(list(structures) + extra, cutoff, gcut, dtype)
    f = {"dtype": dtype}
    n_part = (g.n_cores + g.n_pairs).tolist()
    core_mask = torch.zeros(g.n_particles, dtype=torch.bool)
    pair_mask = torch.zeros(g.n_particles, dtype=torch.bool)
    forces = np.zeros((g.n_particles, 3))
    stress = np.zeros((b, 3, 3))
    has_stress = np.zeros(b, dtype=bool)
    alpha = np.zeros((b, 3, 3))
    has_alpha = np.zeros(b, dtype=bool)
    start = 0
    for k, s in enumerate(structures):
        nc, npair = s.n_cores, s.n_pairs
        if s.forces is not None:
            core_mask[start:start + nc] = True
            forces[start:start + nc] = s.forces
        # DFT centres are stationary: unlabelled pair forces are zero
        pair_mask[start + nc:start + nc + npair] = True
        if s.pair_forces is not None:
            forces[start + nc:start + nc + npair] = s.pair_forces
        if s.stress is not None:
            stress[k], has_stress[k] = s.stress, True
        if s.polarizability is not None:
            alpha[k], has_alpha[k] = s.polarizability, True
        start += n_part[k]
    energy = torch.tensor([reference.target(s) for s in structures], **f)
    coeff = torch.tensor(np.array([reference.coefficients(s) for s in structures]), **f)
    return Batch(
        graph=g, n_structures=b, energy=energy, coefficients=coeff.reshape(b, len(HYDRIDES)),
        n_cores=g.n_cores[:b], core_mask=core_mask, pair_mask=pair_mask,
        forces=torch.as_tensor(forces, **f), stress=torch.as_tensor(stress, **f),
        has_stress=torch.as_tensor(has_stress), indices=list(indices or range(b)),
        n_augmented=n_augmented, n_singular=n_singular,
        polarizability=torch.as_tensor(alpha, dtype=torch.float64),
        has_polarizability=torch.as_tensor(has_alpha),
    )
