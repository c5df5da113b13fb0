"""examples/eqm7/unseen_molecules.py: the molecules a grown data set holds beyond a model's
training data, and their error tables."""

from __future__ import annotations

import shutil

import numpy as np

from emlpack.nn.checkpoint import save_model
from tests.examples.eqm7_data import MOLECULES, PER_MOLECULE, example_module, tiny_dataset
from tests.nn.helpers import random_model


def test_unseen_molecules_are_the_grown_shards_training_molecules(tmp_path):
    mod = example_module("unseen_molecules")
    grown = tiny_dataset(tmp_path / "grown", shards=2)
    old = tmp_path / "old"  # the model's data: the first shard only (methane, ethane, ethene)
    (old / "shards").mkdir(parents=True)
    shutil.copy(grown / "molecules.csv", old / "molecules.csv")
    shutil.copy(grown / "shards" / "0000.h5", old / "shards" / "0000.h5")
    structures = mod.unseen(old, grown)
    names = sorted({s.info["molecule_id"] for s in structures})
    assert names == sorted(n for n, *_ in MOLECULES[3:])  # training molecules of shard 0001
    assert len(structures) == 3 * PER_MOLECULE
    assert mod.unseen(grown, grown) == []

    model = tmp_path / "m.pt"
    save_model(random_model(0), model, metadata={"reference": {"kind": "constant",
                                                               "value": 0.0}})
    out = tmp_path / "unseen.json"
    summary = mod.main([str(model), str(old), str(grown), "--json", str(out)])
    assert summary["n_configurations"] == 3 * PER_MOLECULE and out.exists()
    assert summary["molecules"] == names
    assert all(np.isfinite(v) for v in summary["static_mae"].values())
    assert 0.0 <= summary["dynamic_error_rate"] <= 1.0
    # by size: every unseen configuration in one group, keyed by its molecule's heavy atoms
    groups = summary["static_by_size"]
    assert sum(g["configurations"] for g in groups) == summary["n_configurations"]
    sizes = {n: heavy for n, _, heavy, _ in MOLECULES}
    assert {g["heavy_atoms"] for g in groups} == {sizes[n] for n in names}
    assert all(np.isfinite(g["forces_mae"]) and g["forces_mae"] > 0 for g in groups)
