"""Shared by the mini-eQM7 example tests: the example scripts as modules, and a tiny data set in
the campaign's layout built from the shared eQM7 subset (the authors' PBE0 labels)."""

from __future__ import annotations

import csv
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from emlpack.data.references import load_hydrides
from emlpack.data.store import DatasetStore
from emlpack.io import read_structures
from tests.conftest import ROOT, shared_path

#: the six molecules of eqm7_pbe0_subset.xyz, 100 frames each in this order
MOLECULES = [("methane", "C", 1, "test"), ("ethane", "CC", 2, "train"),
             ("ethene", "C=C", 2, "val"), ("ethyne", "C#C", 2, "train"),
             ("ethanol", "CCO", 3, "train"), ("cyclopropane", "C1CC1", 3, "train")]
PER_MOLECULE = 8


def example_module(name: str) -> ModuleType:
    """``examples/eqm7/NAME.py`` imported as ``eqm7_NAME``."""
    spec = importlib.util.spec_from_file_location(
        f"eqm7_{name}", ROOT / "examples" / "eqm7" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def study_module() -> ModuleType:
    return example_module("run_study")


#: the paper's level, as the shared subset's labels are
PAPER_LEVEL = "pbe0/aug-cc-pvtz"


def tiny_dataset(folder, shards: int = 1, level: str = PAPER_LEVEL,
                 shift: dict[int, float] | None = None):
    """A data-set folder in the campaign's layout (molecules.csv, shards/NNNN.h5 with the
    hydride references in the first), 8 configurations of each molecule of the shared PBE0
    subset; ``shards=2``: the first three molecules (test, train, validation) in shard 0000,
    the other three (training) in 0001. ``level``: the level the records name; ``shift``:
    eV per atom of each element added to every energy, hydrides included (a stand-in for
    another level's labels: the hydride reference then differs, the relative energies not)."""
    frames = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"))
    folder.mkdir()
    (folder / "shards").mkdir()
    with (folder / "molecules.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "source", "smiles", "n_heavy", "split"])
        for name, smiles, n_heavy, split in MOLECULES:
            w.writerow([name, "eqm7_pbe0_subset", smiles, n_heavy, split])
    def offset(numbers) -> float:
        return float(sum((shift or {}).get(int(z), 0.0) for z in numbers))

    per_shard: list[list] = [[] for _ in range(shards)]
    for m, (name, *_rest) in enumerate(MOLECULES):
        for k in range(PER_MOLECULE):
            s = frames[100 * m + 7 * k]
            per_shard[min(m * shards // len(MOLECULES), shards - 1)].append(s.copy(
                energy=s.energy + offset(s.numbers),
                info={"key": f"{name}/nms/{k:04d}", "molecule_id": name, "kind": "nms",
                      "level": level}))
    hydrides, energies = load_hydrides(shared_path("data/hydrides"))
    for h, e in zip(hydrides, energies, strict=True):
        name = h.info["molecule_id"]
        per_shard[0].append(h.copy(energy=float(e) + offset(h.numbers), info={
            "key": f"hydride/{name}", "molecule_id": name, "kind": "hydride",
            "level": level}))
    for n, records in enumerate(per_shard):
        with DatasetStore(folder / "shards" / f"{n:04d}.h5", "a") as store:
            store.append(records)
    return folder


def qm7_with_reserved_ethanol(path: Path) -> Path:
    """A ten-row QM7 SMILES list whose row 5 (a reserved row) is ethanol, the others N2: the
    tiny data set's ethanol then counts as a reserved molecule."""
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["smiles"])
        for i in range(10):
            w.writerow(["CCO" if i == 5 else "N#N"])
    return path
