"""Labeling campaigns: the molecule list and split, immutable shards, resuming from shards on
a fresh machine, labels interleaved with preparation, and the committed mini-eQM7 list."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import yaml

from emlpack.data.dataset import load_data
from emlpack.data.shards import finished_keys, read_molecule_table, read_shards, shard_paths
from emlpack.data.store import DatasetStore
from emlpack.qm import campaign
from tests.conftest import ROOT, shared_path

MINI_EQM7 = ROOT / "datasets" / "mini-eqm7"
#: QM7 rows 5, 6, 8, 9: acetaldehyde, dimethyl ether, propane, propene
RESERVED = {"CC=O", "COC", "CCC", "C=CC"}


def test_selection_rules():
    path = shared_path("data/qm7_smiles.csv")
    mols = campaign.select_molecules(path, seed=0, n_large=40)
    again = campaign.select_molecules(path, seed=0, n_large=40)
    assert [(m["name"], m["split"]) for m in mols] == [(m["name"], m["split"]) for m in again]
    names = [m["name"] for m in mols]
    assert len(set(names)) == len(names)
    for row in range(10):  # the paper's validation molecules are never listed
        assert f"qm7-{row:04d}" not in names
    canon = {m["canonical"]: m for m in mols}
    assert not RESERVED & set(canon)
    assert all("S" not in m["canonical"].replace("Si", "") for m in mols)
    heavy = [m["n_heavy"] for m in mols]
    n_small = sum(1 for h in heavy if h <= 5)
    assert all(2 <= h <= 5 for h in heavy[:n_small]) and n_small > 150
    assert all(h in (6, 7) for h in heavy[n_small:])
    n_extra = sum(1 for m in mols if m["name"].startswith("extra-"))  # IR molecule not in QM7
    assert len(heavy) - n_small == 40 + n_extra and n_extra <= 1
    for smiles in campaign.IR_TEST_SMILES.values():  # the IR molecules are test molecules
        assert canon[campaign.canonical(smiles)]["split"] == "test"
    counts = {k: sum(1 for m in mols if m["split"] == k) for k in ("train", "val", "test")}
    assert counts["test"] == round(0.05 * len(mols)) and counts["val"] == round(0.05 * len(mols))
    order = campaign.labeling_order(mols)  # held-out small molecules first, nothing lost
    assert sorted(m["name"] for m in order) == sorted(names)
    n_held = sum(1 for m in mols[:n_small] if m["split"] != "train")
    assert n_held > 0 and all(m["split"] != "train" and m["n_heavy"] <= 5 for m in order[:n_held])
    rest = order[n_small:]  # the second block: its held-out molecules first too
    n_rest_held = sum(1 for m in mols[n_small:] if m["split"] != "train")
    assert n_rest_held > 0
    assert all(m["split"] != "train" for m in rest[:n_rest_held])
    assert all(m["split"] == "train" for m in rest[n_rest_held:])
    assert [m["name"] for m in rest if m["split"] == "train"] == [
        m["name"] for m in mols[n_small:] if m["split"] == "train"]  # list order kept
    other = campaign.select_molecules(path, seed=1, n_large=40)
    assert [m["name"] for m in other] != names  # the seed draws another sample


def test_committed_mini_eqm7_has_no_reserved_molecule():
    """The committed list and every committed shard (however many) avoid rows 0-9."""
    rows = read_molecule_table(MINI_EQM7)
    listed = {m["name"]: m for m in rows}
    canon = {campaign.canonical(m["smiles"]) for m in rows}
    assert not RESERVED & canon
    assert not {f"qm7-{i:04d}" for i in range(10)} & set(listed)
    for label, smiles in campaign.IR_TEST_SMILES.items():
        match = [m for m in rows if campaign.canonical(m["smiles"]) == campaign.canonical(smiles)]
        assert len(match) == 1 and match[0]["split"] == "test", label
    from rdkit import Chem

    data = read_shards(MINI_EQM7)
    for s in data.structures:
        name = s.info["molecule_id"]
        assert name in listed, name
        mol = Chem.AddHs(Chem.MolFromSmiles(listed[name]["smiles"]))
        own = sorted(a.GetAtomicNum() for a in mol.GetAtoms())
        # the molecule's own atoms come first (a dimer probe follows)
        assert sorted(s.numbers[: len(own)].tolist()) == own, s.info["key"]
        assert s.info["level"] == "pbe0/aug-cc-pvtz"
    for h in (data.hydrides or {}).get("structures", []):
        assert h.info["level"] == "pbe0/aug-cc-pvtz"


def _tiny_campaign(folder, smiles=("C=O", "CO")):
    """A two-molecule campaign at the tiny level (seconds per configuration)."""
    folder.mkdir()
    recipe = campaign.campaign_recipe(samples_per_molecule=4)
    recipe.update(level="tiny", boys_starts=1, hydrides=False)
    settings = {"name": "tiny", "source": "test", "seed": 0, "n_large": 0, "recipe": recipe}
    (folder / campaign.CAMPAIGN_FILE).write_text(yaml.safe_dump(settings))
    with (folder / "molecules.csv").open("w") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "source", "smiles", "n_heavy", "split"])
        for i, smi in enumerate(smiles):
            w.writerow([f"m{i}", "test", smi, 2, ["train", "test"][i % 2]])
    return folder


def test_campaign_resumes_from_shards_on_a_fresh_machine(tmp_path, monkeypatch):
    folder = _tiny_campaign(tmp_path / "c")
    # stop after the first stored record (as a session ending), then resume elsewhere
    out = campaign.run_campaign(folder, workers=0, hours=0.0, progress=False)
    assert out["new_records"] == 1 and len(out["shards"]) == 1
    first = finished_keys(folder)
    assert len(first) == 1
    shard0 = shard_paths(folder)[0].read_bytes()
    import shutil

    shutil.rmtree(folder / "work")  # a fresh machine: only the committed files remain
    out = campaign.run_campaign(folder, workers=0, progress=False)
    assert out["new_records"] == 7
    assert shard_paths(folder)[0].read_bytes() == shard0  # a shard is never rewritten
    keys = finished_keys(folder)
    assert first < keys and len(keys) == 8
    out = campaign.run_campaign(folder, workers=0, progress=False)
    assert out["new_records"] == 0 and out["shards"] == []
    data = read_shards(folder)
    assert len(data.structures) == 8
    split = data.split_indices()
    assert {data.structures[i].info["molecule_id"] for i in split["test"]} == {"m1"}
    assert len(split["train"]) == 4 and len(split["val"]) == 0
    structures, hydrides = load_data(folder)  # what `emlp train data.path=FOLDER` reads
    assert len(structures) == 8 and hydrides is None
    card = (folder / "README.md").read_text()
    assert "8 configurations of 2 molecules (2 complete)" in card


def test_new_shards_are_packed_beside_appendable_ones(tmp_path):
    """export_shard writes the packed layout (format 2); a folder whose first shard has the
    appendable layout (as every shard committed before) reads as one data set, the card names
    both, and nothing new makes no shard."""
    from emlpack.data import store as store_mod
    from emlpack.data.shards import shards_size_text
    from tests.data.test_store import _methane

    folder = _tiny_campaign(tmp_path / "c")

    def record(i: int, name: str):
        s = _methane(i)
        s.info = {**s.info, "key": f"{name}/nms600/{i:04d}", "molecule_id": name}
        return s

    old = [record(i, "m0") for i in range(3)]
    with DatasetStore(folder / "shards" / "0000.h5", "a", compact=True) as st:  # the old path
        st.append(old)
    hydride = _methane(9).copy(info={"key": "hydride/CH4", "molecule_id": "CH4",
                                     "kind": "hydride"})
    new = [record(i, "m1") for i in range(3, 7)]
    with DatasetStore(tmp_path / "work.h5", "a") as work:
        work.append([*old, *new, hydride])
        work.add_failures([{"key": "m1/nms600/0099", "molecule_id": "m1", "kind": "nms600",
                            "reason": "SCF not converged"}])
        work.set_reference("CH4", -1101.3, "tiny")
        work.set_metadata(recipe="level: tiny\n")
        idx, fail = campaign.unexported(folder, work)
        assert len(idx) == 5 and len(fail) == 1
        shard = campaign.export_shard(folder, work, {"wall_s": 60.0, "host": "h"})
        assert campaign.export_shard(folder, work, {"wall_s": 1.0}) is None
        assert campaign.unexported(folder, work) == ([], [])
    with DatasetStore(shard) as st:
        assert st.storage == {"format_version": store_mod.PACKED_VERSION,
                              "precision": "float64", "compress": True}
        assert len(st) == 5 and st.references() == {"CH4": {"energy": -1101.3, "level": "tiny"}}
        assert st.metadata["run_wall_s"] == 60.0 and st.metadata["recipe"] == "level: tiny\n"
    data = read_shards(folder)
    assert [s.info["key"] for s in data.structures] == [s.info["key"] for s in [*old, *new]]
    np.testing.assert_array_equal(data.structures[4].forces, new[1].forces)
    assert len(data.failures) == 1 and data.metadata[1]["run_host"] == "h"
    text = shards_size_text(folder)
    assert ("shards 0000: float64 positions and forces, appendable layout; shards 0001:"
            " float64 positions and forces, gzip, packed layout") in text
    with pytest.raises(campaign.StoreError, match="unknown storage settings"):
        campaign.shard_storage({"layout": "x"}, folder)


def test_shards_wait_for_enough_records(tmp_path):
    """With a shard due at every stored record, a shard waits for ``shard_min_records`` new
    records; the last one, when the run ends, takes whatever is left."""
    folder = _tiny_campaign(tmp_path / "c")
    out = campaign.run_campaign(folder, workers=0, progress=False, shard_minutes=0.0,
                                shard_min_records=3)
    sizes = [len(DatasetStore(p)) for p in shard_paths(folder)]
    assert out["new_records"] == 8 and sum(sizes) == 8 and len(sizes) == len(out["shards"])
    assert len(sizes) >= 2 and all(n >= 3 for n in sizes[:-1])
    assert "packed layout" in (folder / "README.md").read_text()


def test_a_changed_field_distribution_continues_in_a_new_store(tmp_path):
    """A campaign whose recipe predates ``field_distribution`` (magnitude-uniform fields) goes
    on with the ball: its finished labels (even one no shard holds yet) are kept, the rest is
    labeled in a new working store, and the card says which shards drew which fields."""
    folder = _tiny_campaign(tmp_path / "c")
    settings = yaml.safe_load((folder / campaign.CAMPAIGN_FILE).read_text())
    settings["recipe"].pop("field_distribution")
    (folder / campaign.CAMPAIGN_FILE).write_text(yaml.safe_dump(settings))
    out = campaign.run_campaign(folder, workers=0, hours=0.0, progress=False)
    assert out["new_records"] == 1
    first = shard_paths(folder)[0]
    old_field = read_shards(folder).structures[0].field
    first.unlink()  # as if the run was killed before its last shard: the label is in work/
    settings["recipe"]["field_distribution"] = "ball"
    (folder / campaign.CAMPAIGN_FILE).write_text(yaml.safe_dump(settings))
    out = campaign.run_campaign(folder, workers=0, progress=False)
    assert out["new_records"] == 7
    assert len(list((folder / "work").glob("labels-*.h5"))) == 2
    data = read_shards(folder)
    assert len(data.structures) == 8
    np.testing.assert_array_equal(data.structures[0].field, old_field)
    card = (folder / "README.md").read_text()
    assert "- fields: 1 configurations uniform direction, magnitude uniform" in card
    assert "- fields: 7 configurations uniform in the ball" in card


def test_retry_failed_labels_recorded_failures_once_their_cause_is_fixed(tmp_path,
                                                                        monkeypatch):
    """A molecule whose sampling failed is recorded as failed (its keys are finished); after a
    fix, ``retry_failed`` labels it, the failure records stay in their shard, and the card
    counts them as resolved instead of as failures."""
    from emlpack.qm import labeling
    from emlpack.qm.sampling import SamplingError

    folder = _tiny_campaign(tmp_path / "c")
    real = labeling.configurations

    def broken(mol, *args, **kwargs):
        if mol.name == "m0":
            raise SamplingError("Hessian has negative curvature (-0.1 eV/Å^2/amu): not at a"
                                " minimum")
        return real(mol, *args, **kwargs)

    monkeypatch.setattr(labeling, "configurations", broken)
    out = campaign.run_campaign(folder, workers=0, progress=False)
    assert out["new_records"] == 4 and out["new_failures"] == 4
    assert "failures: 4 (4 × Hessian has negative curvature" in (folder / "README.md").read_text()
    monkeypatch.setattr(labeling, "configurations", real)
    assert campaign.run_campaign(folder, workers=0, progress=False)["new_records"] == 0
    out = campaign.run_campaign(folder, workers=0, progress=False, retry_failed=True)
    assert out["new_records"] == 4
    data = read_shards(folder)
    assert len(data.structures) == 8 and len(data.failures) == 4
    card = (folder / "README.md").read_text()
    assert "- failures: 0; 4 earlier failures labeled on a retry" in card


def test_target_prefix_counts_finished_molecules_by_their_labels():
    """The prefix is the shortest one that reaches both targets, counting a finished molecule
    by its labeled configurations and any other by the recipe's count."""
    from collections import Counter

    order = [{"name": f"m{k}"} for k in range(6)]
    target = {"configurations": 13, "molecules": 2}
    prefix, info = campaign.target_prefix(order, target, 6, Counter(), Counter())
    assert [m["name"] for m in prefix] == ["m0", "m1", "m2"] and not info["reached"]
    # m0 finished with 4 of 6 labeled (2 failures), m1 all failed: two more molecules needed
    labeled, done = Counter(m0=4), Counter(m0=6, m1=6)
    prefix, info = campaign.target_prefix(order, target, 6, labeled, done)
    assert [m["name"] for m in prefix] == ["m0", "m1", "m2", "m3"]
    assert info["labeled"] == 4 and info["labeled_molecules"] == 1 and not info["reached"]
    labeled, done = Counter(m0=4, m2=6, m3=6), Counter(m0=6, m1=6, m2=6, m3=6)
    prefix, info = campaign.target_prefix(order, target, 6, labeled, done)
    assert info["reached"] and info["prefix"] == 4
    prefix, info = campaign.target_prefix(order, None, 6, labeled, done)
    assert len(prefix) == 6 and not info["reached"]


def test_campaign_stops_at_its_target_and_goes_past_it_when_asked(tmp_path, monkeypatch):
    """With a target of one molecule the campaign labels the first molecule of the order,
    extends the prefix when that one fails, stops once the target is reached (without starting
    any work), and ``past_target`` labels the rest."""
    from emlpack.qm import labeling
    from emlpack.qm.sampling import SamplingError

    folder = _tiny_campaign(tmp_path / "c", smiles=("C=O", "CO", "C"))
    settings = yaml.safe_load((folder / campaign.CAMPAIGN_FILE).read_text())
    settings["target"] = {"configurations": 4, "molecules": 1}
    (folder / campaign.CAMPAIGN_FILE).write_text(yaml.safe_dump(settings))
    real = labeling.configurations
    failing = {"m1", "m2"}  # m1 (test) comes first in the order, m2 is past the target

    def broken(mol, *args, **kwargs):
        if mol.name in failing:
            raise SamplingError("not at a minimum")
        return real(mol, *args, **kwargs)

    monkeypatch.setattr(labeling, "configurations", broken)
    out = campaign.run_campaign(folder, workers=0, progress=False)
    assert out["new_records"] == 0 and out["new_failures"] == 4
    assert not out["target"]["reached"] and out["target"]["prefix"] == 2
    out = campaign.run_campaign(folder, workers=0, progress=False)  # m1 failed: m0 next
    assert out["new_records"] == 4 and out["target"]["reached"]
    assert {k.split("/")[0] for k in finished_keys(folder)} == {"m0", "m1"}
    card = (folder / "README.md").read_text()
    assert ("- target (campaign.yaml): 4 configurations of 1 molecules, reached;"
            " `emlp campaign run` labels the first 2 molecules") in card
    monkeypatch.setattr(labeling, "run_labeling", None)  # a reached target starts no work
    out = campaign.run_campaign(folder, workers=0, progress=False)
    assert out["new_records"] == 0 and out["target"]["reached"] and out["shards"] == []
    monkeypatch.undo()
    monkeypatch.setattr(labeling, "configurations", broken)
    out = campaign.run_campaign(folder, workers=0, progress=False, past_target=True)
    assert out["new_failures"] == 4  # m2
    assert {k.split("/")[0] for k in finished_keys(folder)} == {"m0", "m1", "m2"}


def test_sigterm_turns_finished_labels_into_a_shard(tmp_path, monkeypatch):
    """``kill PID`` (the end of a session) stops the run like Ctrl-C, and the labels finished
    so far become a shard before it exits."""
    import os
    import signal

    from emlpack.qm import labeling

    folder = _tiny_campaign(tmp_path / "c")
    calls = {"n": 0}
    real = labeling.label_task

    def label_then_terminate(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:  # two labels are finished and stored by now
            os.kill(os.getpid(), signal.SIGTERM)
        return real(*args, **kwargs)

    monkeypatch.setattr(labeling, "label_task", label_then_terminate)
    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        campaign.run_campaign(folder, workers=0, progress=False)
    assert signal.getsignal(signal.SIGTERM) == previous  # the handler is restored
    assert len(shard_paths(folder)) == 1 and len(finished_keys(folder)) == 2


def test_labels_are_interleaved_with_preparation(tmp_path):
    """The first label is stored before the second molecule is prepared."""
    from emlpack.qm.labeling import run_labeling

    folder = _tiny_campaign(tmp_path / "c")
    settings = campaign.load_settings(folder)
    prepared_at_first_record = []

    def on_stored(store):
        if not prepared_at_first_record:
            prepared_at_first_record.extend(
                sorted(p.stem for p in (folder / "prepared").glob("m*.npz")))
        return False

    run_labeling([("m0", "C=O"), ("m1", "CO")], tmp_path / "s.h5", settings["recipe"],
                 workers=0, progress=False, prep_dir=folder / "prepared", on_stored=on_stored)
    assert prepared_at_first_record == ["m0"]
    with DatasetStore(tmp_path / "s.h5") as st:
        assert len(st) == 8
        with np.load(folder / "prepared" / "m1.npz") as d:
            assert str(d["level"]) == "gfn2-xtb"
            hess = d["hessian"]
            assert np.allclose(hess, hess.T, atol=1e-3 * np.abs(hess).max())


def test_campaign_init_refuses_to_overwrite(tmp_path):
    folder = _tiny_campaign(tmp_path / "c")
    with pytest.raises(Exception, match="exists already"):
        campaign.init_campaign(folder, tmp_path / "unused.csv")


def test_pretraining_selection_leaves_out_every_held_out_graph(tmp_path):
    """A pretraining set lists every allowed QM7 molecule but rows 0-9, the IR molecules and
    mini-eQM7's validation and test molecules, by molecular graph; its card names the cheap
    level as not the paper's, and its order is the seeded random list with the splits
    interleaved."""
    path = shared_path("data/qm7_smiles.csv")
    folder = tmp_path / "qm7-cheap"
    mols = campaign.init_campaign(folder, path, seed=0, level="pbe0/def2-svpd/grid1",
                                  exclude=[MINI_EQM7], target={"configurations": 60,
                                                               "molecules": 10},
                                  storage={"precision": "float32", "compress": True})
    graphs = {campaign.graph_key(m["smiles"]) for m in mols}
    assert len(graphs) == len(mols) > 5000
    assert not RESERVED & {m["canonical"] for m in mols}
    held = {campaign.graph_key(m["smiles"]) for m in read_molecule_table(MINI_EQM7)
            if m["split"] != "train"}
    held |= {campaign.graph_key(s) for s in campaign.IR_TEST_SMILES.values()}
    assert len(held) >= 30 and not held & graphs
    train = {campaign.graph_key(m["smiles"]) for m in read_molecule_table(MINI_EQM7)
             if m["split"] == "train"}
    assert len(train & graphs) > 200  # mini-eQM7's training molecules may be pretrained on
    assert not {f"qm7-{i:04d}" for i in range(10)} & {m["name"] for m in mols}
    assert {m["split"] for m in mols} == {"train", "val"}
    settings = campaign.load_settings(folder)
    assert settings["recipe"]["level"] == "pbe0/def2-svpd/grid1"
    prefix, target = campaign.campaign_target(folder)
    order = campaign.campaign_order(settings, mols)
    assert [m["name"] for m in prefix] == [m["name"] for m in order[:len(prefix)]]
    assert sorted(m["name"] for m in order) == sorted(m["name"] for m in mols)
    for split in ("train", "val"):  # each split in the list's order, at its share of a prefix
        assert [m["name"] for m in order if m["split"] == split] == [
            m["name"] for m in mols if m["split"] == split]
    share = sum(m["split"] == "val" for m in mols) / len(mols)
    for n in (20, 100, 1000):
        assert abs(sum(m["split"] == "val" for m in order[:n]) - share * n) <= 1
    assert target["prefix"] == 10 and not target["reached"]
    card = (folder / "README.md").read_text()
    assert "not the paper's level" in card and "pbe0/def2-svpd/grid1" in card
    assert "new shards: float32 positions and forces, gzip, packed layout" in card
    with pytest.raises(campaign.StoreError, match="exists already"):
        campaign.init_campaign(folder, path, exclude=[MINI_EQM7])


def test_committed_pretraining_sets_hold_no_held_out_molecule():
    """Every committed pretraining set (``selection: all``) and every one of its shards avoid
    rows 0-9, the IR molecules and mini-eQM7's validation and test molecules (by graph)."""
    from rdkit import Chem

    held = {campaign.graph_key(m["smiles"]) for m in read_molecule_table(MINI_EQM7)
            if m["split"] != "train"}
    held |= {campaign.graph_key(s) for s in campaign.IR_TEST_SMILES.values()}
    held |= {campaign.graph_key(s) for s in RESERVED}
    folders = [p.parent for p in (ROOT / "datasets").glob("*/campaign.yaml")
               if campaign.load_settings(p.parent).get("selection") == "all"]
    for folder in folders:
        rows = read_molecule_table(folder)
        listed = {m["name"]: m for m in rows}
        assert not held & {campaign.graph_key(m["smiles"]) for m in rows}, folder
        assert not {f"qm7-{i:04d}" for i in range(10)} & set(listed)
        level = campaign.load_settings(folder)["recipe"]["level"]
        for shard in shard_paths(folder):
            with DatasetStore(shard) as store:
                for s in store:
                    name = s.info["molecule_id"]
                    if s.info["kind"] == "hydride":
                        continue
                    assert name in listed, (shard, name)
                    mol = Chem.AddHs(Chem.MolFromSmiles(listed[name]["smiles"]))
                    own = sorted(a.GetAtomicNum() for a in mol.GetAtoms())
                    assert sorted(s.numbers[: len(own)].tolist()) == own, s.info["key"]
                    assert s.info["level"] == level != "pbe0/aug-cc-pvtz"


def test_the_card_includes_the_files_its_notes_name(tmp_path):
    """A ``<!-- include: PATH -->`` line of notes.md (PATH relative to the data-set folder,
    e.g. the pilot's table that the bake-off writes under examples/) becomes that file's text
    in the card, or a line saying it is not written yet; the other lines stay verbatim."""
    folder = _tiny_campaign(tmp_path / "c")
    (folder / campaign.NOTES_FILE).write_text(
        "## Pilot\n\nWritten elsewhere:\n\n<!-- include: ../tables/pilot.md -->\n")
    card = campaign.write_card(folder).read_text()
    assert "## Pilot\n\nWritten elsewhere:\n\n*(`../tables/pilot.md`: not written yet)*" in card
    (tmp_path / "tables").mkdir()
    (tmp_path / "tables" / "pilot.md").write_text("### Pilot table\n\n| a | b |\n|---|---|\n")
    card = campaign.write_card(folder).read_text()
    assert "Written elsewhere:\n\n### Pilot table\n\n| a | b |\n|---|---|\n" in card
    assert "include:" not in card and "not written yet" not in card
