"""Splits (by molecule, by configuration), the extxyz and HDF5-store adapters, batches."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from emlpack.data.dataset import (
    StructureDataset,
    formula,
    load_data,
    make_batch,
    molecule_id,
    split_indices,
)
from emlpack.data.references import HYDRIDES, HydrideReference, load_hydrides
from emlpack.data.store import DatasetStore
from emlpack.io import read_structures
from tests.conftest import shared_path


@pytest.fixture(scope="module")
def eqm7():
    return read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="::10")


def test_molecule_ids_from_formula(eqm7):
    ids = sorted({molecule_id(s) for s in eqm7})
    assert ids == sorted(["CH4", "C2H6", "C2H4", "C2H2", "C2H6O", "C3H6"])
    assert formula(np.array([8, 1, 1])) == "H2O"


def test_split_by_molecule_holds_unseen_molecules():
    ids = [f"m{k // 5}" for k in range(100)]  # 20 molecules x 5 configurations
    split = split_indices(ids, (0.8, 0.1, 0.1), "molecule", seed=1)
    groups = {k: {ids[i] for i in v} for k, v in split.items()}
    assert len(groups["val"]) == 2 and len(groups["test"]) == 2
    assert not (groups["train"] & groups["val"]) and not (groups["train"] & groups["test"])
    assert sum(len(v) for v in split.values()) == 100
    again = split_indices(ids, (0.8, 0.1, 0.1), "molecule", seed=1)
    assert all(np.array_equal(split[k], again[k]) for k in split)
    other = split_indices(ids, (0.8, 0.1, 0.1), "molecule", seed=2)
    assert any(not np.array_equal(split[k], other[k]) for k in split)


def test_split_by_molecule_with_few_molecules_keeps_every_subset_non_empty():
    split = split_indices(["a", "b", "c"], (0.9, 0.05, 0.05), "molecule")
    assert [len(split[k]) for k in ("train", "val", "test")] == [1, 1, 1]


def test_split_by_configuration_within_each_molecule(eqm7):
    ids = [molecule_id(s) for s in eqm7]
    split = split_indices(ids, (0.6, 0.2, 0.2), "configuration", seed=0)
    for subset in split.values():
        assert {ids[i] for i in subset} == set(ids)
    assert sorted(np.concatenate(list(split.values())).tolist()) == list(range(len(ids)))


def test_dataset_items_and_batch_targets(eqm7):
    ds = StructureDataset(eqm7, indices=[3, 7])
    assert len(ds) == 2 and ds[1][0] == 7
    hydrides = HydrideReference(*load_hydrides(shared_path("data/hydrides")))
    batch = make_batch([eqm7[3], eqm7[7]], hydrides, 4.0, 1.0, torch.float64)
    g = batch.graph
    assert g.n_structures == 2 + len(HYDRIDES)  # the live hydrides ride along
    n_data = int((g.n_cores[:2] + g.n_pairs[:2]).sum())
    assert int(batch.core_mask.sum()) == eqm7[3].n_cores + eqm7[7].n_cores
    assert not batch.core_mask[n_data:].any() and not batch.pair_mask[n_data:].any()
    np.testing.assert_allclose(batch.forces[: eqm7[3].n_cores].numpy(), eqm7[3].forces)


def test_store_adapter_separates_hydrides(tmp_path, eqm7):
    structures, energies = load_hydrides(shared_path("data/hydrides"))
    path = tmp_path / "data.h5"
    with DatasetStore(path, "a") as store:
        for k, s in enumerate(eqm7[:4]):
            s = s.copy()
            s.info = {"key": f"mol/{k}", "molecule_id": f"mol{k % 2}", "kind": "nms"}
            store.append(s)
        for name, s, e in zip(HYDRIDES, structures, energies, strict=True):
            h = s.copy()
            h.info = {"key": f"hydride/{name}/0000", "molecule_id": name, "kind": "hydride"}
            store.append(h)
            store.set_reference(name, e, "test")
    data, hyd = load_data(path)
    assert len(data) == 4 and {molecule_id(s) for s in data} == {"mol0", "mol1"}
    assert hyd is not None
    np.testing.assert_allclose(hyd["energies"], energies)
    assert [len(s.numbers) for s in hyd["structures"]] == [2, 5, 4, 3]
    np.testing.assert_allclose(data[2].forces, eqm7[2].forces)


def test_training_domain_counts_a_molecule_by_its_smallest_configuration():
    """A dimer configuration whose partner came within bonding distance does not make its
    molecule larger; another molecule of that size does."""
    from ase.build import molecule

    from emlpack.data.dataset import training_domain
    from emlpack.structure import Structure, core_charges

    ethanol, water = molecule("CH3CH2OH"), molecule("H2O")
    c = int(np.flatnonzero(ethanol.numbers == 6)[0])
    water.positions += ethanol.positions[c] + np.array([0.0, 0.0, 1.5]) - water.positions[0]
    touching = ethanol + water  # the water O 1.5 Å from a carbon: one fragment of 4 heavy atoms

    def config(atoms, name):  # pairs on the first core (their positions do not matter here)
        n_pairs = int(core_charges(atoms.numbers).sum()) // 2
        return Structure(atoms.numbers, atoms.positions, np.repeat(atoms.positions[:1], n_pairs, 0),
                         info={"molecule_id": name})

    same = [config(ethanol, "ethanol"), config(touching, "ethanol")]
    assert training_domain(same) == {"elements": [1, 6, 8], "max_heavy_atoms": 3}
    other = [config(ethanol, "ethanol"), config(touching, "ethanol-water")]
    assert training_domain(other)["max_heavy_atoms"] == 4


def test_batches_carry_polarizability_labels(eqm7):
    alpha = np.diag([1.0, 2.0, 3.0])
    batch = make_batch([eqm7[0], eqm7[1].copy(polarizability=alpha)],
                       HydrideReference(*load_hydrides(shared_path("data/hydrides"))), 4.0, 1.0,
                       torch.float32)
    assert batch.has_polarizability.tolist() == [False, True]
    assert batch.polarizability.dtype == torch.float64
    np.testing.assert_array_equal(batch.polarizability[1].numpy(), alpha)
    assert float(batch.polarizability[0].abs().sum()) == 0.0


def test_data_set_folders_attach_their_polarizability_labels(tmp_path):
    """``FOLDER/polarizability/KEY.json`` labels reach their configurations through
    ``read_shards``; a label of no record, of a validation molecule, of other cores or under
    another file name is refused naming its file."""
    import json

    from emlpack.data.shards import label_file_name, read_shards
    from emlpack.data.store import StoreError
    from tests.examples.eqm7_data import tiny_dataset

    folder = tiny_dataset(tmp_path / "data")
    data = read_shards(folder)
    assert all(s.polarizability is None for s in data.structures)
    s = next(s for s in data.structures if s.info["molecule_id"] == "ethanol")
    labels = folder / "polarizability"
    labels.mkdir()
    alpha = np.eye(3) * 0.35

    def write(key, numbers, positions, name=None):
        path = labels / (name or label_file_name(key))
        path.write_text(json.dumps({"key": key, "numbers": numbers.tolist(),
                                    "positions": positions.tolist(),
                                    "polarizability_e_A2_per_V": alpha.tolist()}))
        return path

    path = write(s.info["key"], s.numbers, s.positions)
    again = read_shards(folder)
    got = {t.info["key"]: t.polarizability for t in again.structures}
    np.testing.assert_array_equal(got[s.info["key"]], alpha)
    assert sum(v is not None for v in got.values()) == 1
    for key, numbers, positions, name, message in (
        ("ethanol/nms/9999", s.numbers, s.positions, None, "no record"),
        ("ethene/nms/0000", s.numbers, s.positions, None, "ethene is a val molecule"),
        (s.info["key"], s.numbers, s.positions + 1e-3, None, "its cores are not those"),
        (s.info["key"], s.numbers, s.positions, "other.json", "must be named"),
    ):
        path.unlink()
        path = write(key, numbers, positions, name)
        with pytest.raises(StoreError, match=message):
            read_shards(folder)
        assert path.name in str(pytest.raises(StoreError, read_shards, folder).value)
