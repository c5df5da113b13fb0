"""A data set stored as immutable shards beside its card (torch-free reader).

Layout of a data-set folder (see :mod:`emlpack.qm.campaign`, which writes it)::

    molecules.csv      name, source, smiles, n_heavy, split: fixed before any label exists
    campaign.yaml      selection and labeling recipe
    README.md          the data-set card
    shards/NNNN.h5     finished labels, one small :class:`~emlpack.data.store.DatasetStore`
                       per shard, never rewritten once committed (written in the packed
                       layout, :func:`~emlpack.data.store.write_packed`; the earlier ones in
                       the appendable layout: both read alike)
    shards/al-NNNN.h5  optional: labels of configurations picked by active learning (MD of
                       the models, ``examples/eqm7/active_learning.py``), training molecules
                       only, the same level and card; a part of its own, numbered on its own
    active-learning/   optional: the selections those labels were made from (extxyz with the
                       provenance of every configuration), never rewritten
    prepared/NAME.npz  the cheap-level geometry and Hessian each molecule was sampled from
    polarizability/KEY.json
                       optional: a DFT polarizability label of one stored configuration
                       (training split only; :func:`read_polarizability_labels`)

:func:`read_shards` reads every shard as one data set, with the split taken from
``molecules.csv`` (by molecule), so the split never depends on which labels are finished,
and attaches the polarizability labels to their configurations. Shards come in parts
(:data:`SHARD_PARTS`): the campaign's own (``NNNN.h5``), then active learning's
(``al-NNNN.h5``); a reader takes every part, the campaign's target and counts its own.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from emlpack.data.store import PACKED_VERSION, DatasetStore, StoreError
from emlpack.structure import Structure

if TYPE_CHECKING:
    from collections.abc import Sequence

#: the hydride references, in the order the trainer expects them
HYDRIDE_NAMES = ("H2", "CH4", "NH3", "H2O")
SPLITS = ("train", "val", "test")
MOLECULES_FILE = "molecules.csv"
SHARD_DIR = "shards"
#: folder of the polarizability labels, one ``<key>.json`` per configuration
POLARIZABILITY_DIR = "polarizability"
#: the campaign's own shards (``shards/NNNN.h5``)
CAMPAIGN_PART = ""
#: shards labeled from active learning's selections (``shards/al-NNNN.h5``)
ACTIVE_LEARNING_PART = "al-"
#: the shard parts of a data set, in reading order (each numbered on its own)
SHARD_PARTS = (CAMPAIGN_PART, ACTIVE_LEARNING_PART)
#: folder of active learning's selections (the provenance of the ``al-`` shards)
ACTIVE_LEARNING_DIR = "active-learning"
#: a label's cores must sit where its record's do, within this (Å)
LABEL_POSITION_TOLERANCE = 1e-6


@dataclass
class ShardedData:
    """All shards of a data-set folder.

    Attributes:
        structures: labeled configurations (hydride references excluded), shard order.
        hydrides: ``None`` or ``{"structures": [...], "energies": [...]}`` (eV) in the order
            of :data:`HYDRIDE_NAMES`, when all four references are labeled.
        molecules: one dict per row of ``molecules.csv``.
        split_of: molecule name -> ``"train"``, ``"val"`` or ``"test"``.
        failures: recorded failures (``key``, ``molecule_id``, ``kind``, ``reason``).
        shards: the shard files read.
        metadata: per shard, its metadata attributes (e.g. wall time of the run that wrote it).
    """

    structures: list[Structure]
    hydrides: dict | None
    molecules: list[dict]
    split_of: dict[str, str]
    failures: list[dict] = field(default_factory=list)
    shards: list[Path] = field(default_factory=list)
    metadata: list[dict] = field(default_factory=list)

    def split_indices(self) -> dict[str, np.ndarray]:
        """``{"train", "val", "test"}`` -> indices into :attr:`structures` (by the card)."""
        out: dict[str, list[int]] = {k: [] for k in SPLITS}
        for i, s in enumerate(self.structures):
            name = str(s.info.get("molecule_id", ""))
            if name not in self.split_of:
                raise StoreError(f"{s.source}: molecule {name!r} is not in {MOLECULES_FILE}")
            out[self.split_of[name]].append(i)
        return {k: np.array(v, dtype=np.int64) for k, v in out.items()}


def is_sharded(path: str | Path) -> bool:
    """True when ``path`` is a data-set folder (has ``molecules.csv``)."""
    return Path(path).is_dir() and (Path(path) / MOLECULES_FILE).is_file()


def read_molecule_table(folder: str | Path) -> list[dict]:
    """Rows of ``FOLDER/molecules.csv`` (``n_heavy`` as int); checks names and splits."""
    path = Path(folder) / MOLECULES_FILE
    if not path.is_file():
        raise StoreError(f"{folder}: no {MOLECULES_FILE} (not a sharded data set)")
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    seen = set()
    for k, row in enumerate(rows, start=2):
        if row.get("split") not in SPLITS or not row.get("name"):
            raise StoreError(f"{path}, line {k}: needs a name and a split in {SPLITS}")
        if row["name"] in seen:
            raise StoreError(f"{path}, line {k}: duplicate molecule {row['name']!r}")
        seen.add(row["name"])
        row["n_heavy"] = int(row["n_heavy"])
    return rows


def shard_paths(folder: str | Path, part: str | None = None) -> list[Path]:
    """The shard files of ``folder`` in order: of one ``part`` of :data:`SHARD_PARTS`
    (``shards/PARTNNNN.h5``), or of every part (None: the campaign's, then active
    learning's)."""
    if part is not None and part not in SHARD_PARTS:
        raise StoreError(f"unknown shard part {part!r} (one of {SHARD_PARTS})")
    parts = SHARD_PARTS if part is None else (part,)
    return [path for p in parts
            for path in sorted((Path(folder) / SHARD_DIR).glob(f"{p}[0-9][0-9][0-9][0-9].h5"))]


def shards_size_text(folder: str | Path) -> str:
    """The data-set card's words on the shards of ``folder``, measured from the files: their
    size, bytes per stored configuration (hydride references included) and, per run of
    consecutive shards of one part stored alike, the positions' and forces' type, compression
    and layout, e.g. ``"2.1 MB, 1.4 kB per configuration; shards 0000-0157: float64 positions
    and forces, appendable layout; shards 0158-0160: float64 positions and forces, gzip, packed
    layout"``.
    """
    paths = shard_paths(folder)
    size = sum(p.stat().st_size for p in paths)
    n = 0
    runs: list[list] = []  # [first, last, description]
    for path in paths:
        with DatasetStore(path, "r") as store:
            n += len(store)
            how = store.storage
        text = (f"{how['precision']} positions and forces{', gzip' if how['compress'] else ''},"
                f" {'packed' if how['format_version'] == PACKED_VERSION else 'appendable'}"
                " layout")
        if runs and runs[-1][2] == text and runs[-1][0][:-4] == path.stem[:-4]:  # one part
            runs[-1][1] = path.stem
        else:
            runs.append([path.stem, path.stem, text])
    parts = [f"{size / 1e6:.1f} MB, {size / max(n, 1) / 1e3:.1f} kB per configuration"]
    parts += [f"shards {a}{'' if a == b else '-' + b}: {text}" for a, b, text in runs]
    return "; ".join(parts)


def chosen_shards(folder: str | Path, shards: Sequence[str] | None = None) -> list[Path]:
    """The shard files of ``folder``: all of them (None), or those named in ``shards`` (file
    names such as ``0003.h5``, in shard order; a frozen list, e.g. of a training on a set that
    is still growing). A named shard that is not there raises :class:`StoreError`."""
    paths = shard_paths(folder)
    if shards is None:
        return paths
    by_name = {p.name: p for p in paths}
    missing = sorted(set(shards) - set(by_name))
    if missing:
        raise StoreError(f"{folder}: no shard(s) {', '.join(missing)} in {SHARD_DIR}/ (it holds"
                         f" {len(paths)}: {paths[0].name if paths else 'none'}"
                         f"{'..' + paths[-1].name if len(paths) > 1 else ''})")
    wanted = set(shards)
    return [p for p in paths if p.name in wanted]


def shard_counts(folder: str | Path, shards: Sequence[str] | None = None) -> dict:
    """What the shards of ``folder`` (all, or those named, :func:`chosen_shards`) hold, read
    from their record columns only (no labels loaded): ``shards`` (file names),
    ``configurations`` (labeled configurations, hydride references excluded) and
    ``molecules`` (distinct molecules among them)."""
    paths = chosen_shards(folder, shards)
    n, molecules = 0, set()
    for path in paths:
        with DatasetStore(path, "r") as store:
            for kind, name in zip(store.text_column("kind"), store.text_column("molecule_id"),
                                  strict=True):
                if kind != "hydride":
                    n += 1
                    molecules.add(name)
    return {"shards": [p.name for p in paths], "configurations": n,
            "molecules": len(molecules)}


def read_shards(folder: str | Path, shards: Sequence[str] | None = None) -> ShardedData:
    """Every shard of ``folder`` (or the shards named in ``shards``, :func:`chosen_shards`) as
    one data set with the card's split (missing shards: none)."""
    molecules = read_molecule_table(folder)
    split_of = {m["name"]: m["split"] for m in molecules}
    structures: list[Structure] = []
    failures: list[dict] = []
    refs: dict[str, dict] = {}
    hyd: dict[str, Structure] = {}
    metadata = []
    seen: dict[str, Path] = {}
    paths = chosen_shards(folder, shards)
    for path in paths:
        with DatasetStore(path, "r") as store:
            metadata.append(store.metadata)
            refs.update(store.references())
            failures.extend(store.failures())
            for s in store:
                key = str(s.info.get("key", ""))
                if key in seen:
                    raise StoreError(f"{path}: record {key!r} is also in {seen[key]}")
                seen[key] = path
                if s.info.get("kind") == "hydride":
                    hyd[str(s.info.get("molecule_id"))] = s
                else:
                    structures.append(s)
    _attach_polarizabilities(folder, structures, split_of)
    hydrides = None
    if all(h in hyd for h in HYDRIDE_NAMES):
        hydrides = {
            "structures": [hyd[h] for h in HYDRIDE_NAMES],
            "energies": [refs[h]["energy"] if h in refs else hyd[h].energy
                         for h in HYDRIDE_NAMES],
        }
    return ShardedData(structures, hydrides, molecules, split_of, failures, paths, metadata)


def finished_keys(folder: str | Path, failures: bool = True,
                  part: str | None = None) -> set[str]:
    """Keys of every record (and, with ``failures``, every recorded failure) in the shards of
    ``folder`` (of one ``part``, or of all: :func:`shard_paths`)."""
    keys: set[str] = set()
    for path in shard_paths(folder, part):
        with DatasetStore(path, "r") as store:
            keys |= store.done_keys() if failures else set(store.keys())
    return keys


def label_file_name(key: str) -> str:
    """The file name of the polarizability label of record ``key``: its ``/`` as ``__``."""
    return key.replace("/", "__") + ".json"


def read_polarizability_labels(folder: str | Path) -> dict[str, dict]:
    """The polarizability labels of a data-set folder (``FOLDER/polarizability/*.json``, none
    when the folder is absent), by record key: dicts with ``polarizability`` (3, 3) (e·Å²/V),
    ``numbers``, ``positions`` (Å) and ``path``. A file is JSON with ``key``, ``numbers``,
    ``positions`` and ``polarizability_e_A2_per_V`` (see
    ``examples/eqm7/polarizability_labels.py``, which writes them); a file without them, or
    not named after its key, raises :class:`~emlpack.data.store.StoreError` naming it."""
    out: dict[str, dict] = {}
    for path in sorted((Path(folder) / POLARIZABILITY_DIR).glob("*.json")):
        try:
            d = json.loads(path.read_text())
            key = str(d["key"])
            alpha = np.asarray(d["polarizability_e_A2_per_V"], dtype=np.float64)
            numbers = np.asarray(d["numbers"], dtype=np.int64)
            positions = np.asarray(d["positions"], dtype=np.float64).reshape(-1, 3)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise StoreError(f"{path}: not a polarizability label ({exc})") from None
        if alpha.shape != (3, 3) or not np.all(np.isfinite(alpha)):
            raise StoreError(f"{path}: polarizability_e_A2_per_V must be 3x3 finite numbers")
        if path.name != label_file_name(key):
            raise StoreError(f"{path}: the label of record {key!r} must be named"
                             f" {label_file_name(key)}")
        out[key] = {"polarizability": alpha, "numbers": numbers, "positions": positions,
                    "path": path}
    return out


def _attach_polarizabilities(folder: str | Path, structures: list[Structure],
                             split_of: dict[str, str]) -> None:
    """Set ``polarizability`` of the ``structures`` that have a label in ``folder``; a label
    of no stored record, of a validation or test molecule, or of other cores raises
    :class:`~emlpack.data.store.StoreError` naming its file."""
    labels = read_polarizability_labels(folder)
    if not labels:
        return
    by_key = {str(s.info.get("key", "")): k for k, s in enumerate(structures)}
    for key, label in labels.items():
        index = by_key.get(key)
        path = label["path"]
        if index is None:
            raise StoreError(f"{path}: no record {key!r} in the shards of {folder}")
        s = structures[index]
        name = str(s.info.get("molecule_id", ""))
        if split_of.get(name) != "train":
            raise StoreError(f"{path}: {name} is a {split_of.get(name)} molecule; polarizability"
                             " labels belong to training molecules only")
        same = (np.array_equal(label["numbers"], s.numbers)
                and label["positions"].shape == s.positions.shape
                and np.abs(label["positions"] - s.positions).max() <= LABEL_POSITION_TOLERANCE)
        if not same:
            raise StoreError(f"{path}: its cores are not those of record {key!r}")
        structures[index] = s.copy(polarizability=label["polarizability"])
