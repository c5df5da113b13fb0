"""examples/eqm7/polarizability_labels.py: which configurations it labels (training molecules
only, never a held-out or reserved graph) and one label end to end at a small basis."""

from __future__ import annotations

import json

import numpy as np
import pytest

from emlpack.data.shards import read_molecule_table, read_shards
from emlpack.qm.campaign import IR_TEST_SMILES, graph_key
from tests.conftest import ROOT, require, shared_path
from tests.examples.eqm7_data import (
    MOLECULES,
    example_module,
    qm7_with_reserved_ethanol,
    tiny_dataset,
)


@pytest.fixture(scope="module")
def labels():
    require("rdkit")
    return example_module("polarizability_labels")


def test_the_selection_of_mini_eqm7_holds_training_molecules_only(labels):
    """On the shipped data set: every chosen configuration is of a training molecule, none of
    a validation or test molecule, an IR molecule or QM7 rows 0-9 (by graph); one per
    molecule before a second; a shorter selection is a prefix of a longer one."""
    data_dir = ROOT / "datasets" / "mini-eqm7"
    data = read_shards(data_dir)
    molecules = read_molecule_table(data_dir)
    banned = labels.banned_graphs(data_dir, shared_path("data/qm7_smiles.csv"))
    assert {graph_key(s) for s in IR_TEST_SMILES.values()} <= set(banned)
    assert sum("QM7 row" in why for why in banned.values()) == 10
    chosen = labels.select_configurations(data.structures, molecules, banned, 100000)
    split = {m["name"]: m["split"] for m in molecules}
    smiles = {m["name"]: m["smiles"] for m in molecules}
    names = [s.info["molecule_id"] for s in chosen]
    assert {split[n] for n in names} == {"train"}
    assert not {graph_key(smiles[n]) for n in set(names)} & set(banned)
    n_mol = len(set(names))
    assert n_mol > 200 and len(set(names[:n_mol])) == n_mol
    short = labels.select_configurations(data.structures, molecules, banned, 50)
    assert [s.info["key"] for s in short] == [s.info["key"] for s in chosen[:50]]


def test_one_label_at_a_small_basis_is_written_resumed_and_read(tmp_path, labels):
    """The tiny data set (the shared eQM7 subset's molecules), a QM7 list whose row 5 is
    ethanol (so ethanol is reserved), one configuration at PBE0/STO-3G: its JSON holds a
    symmetric positive tensor, a second run does nothing, and ``read_shards`` attaches it."""
    require("pyscf")
    folder = tiny_dataset(tmp_path / "data")
    qm7 = qm7_with_reserved_ethanol(tmp_path / "qm7.csv")
    args = ["--data", str(folder), "--smiles", str(qm7), "--level", "tiny"]
    chosen = labels.select_configurations(
        read_shards(folder).structures, read_molecule_table(folder),
        labels.banned_graphs(folder, qm7), 100)
    names = {s.info["molecule_id"] for s in chosen}
    assert names == {m[0] for m in MOLECULES if m[3] == "train"} - {"ethanol"}
    assert labels.main([*args, "--count", "1"]) == 0
    (path,) = (folder / "polarizability").glob("*.json")
    label = json.loads(path.read_text())
    assert label["key"] == chosen[0].info["key"] and label["level"] == "pbe0/sto-3g"
    alpha = np.array(label["polarizability_e_A2_per_V"])
    np.testing.assert_allclose(alpha, alpha.T, atol=1e-12)
    assert np.linalg.eigvalsh(alpha).min() > 0
    np.testing.assert_allclose(label["base_field_V_per_A"], chosen[0].field)
    assert len(list((folder / "polarizability" / "fields").rglob("*.npz"))) == 6
    before = path.stat().st_mtime_ns
    assert labels.main([*args, "--count", "1"]) == 0
    assert path.stat().st_mtime_ns == before
    attached = [s for s in read_shards(folder).structures if s.polarizability is not None]
    assert [s.info["key"] for s in attached] == [label["key"]]
