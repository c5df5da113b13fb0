"""examples/eqm7/active_learning.py: which frames it selects (trust levels, failures,
deduplication, budget, reasons), that it only ever uses training molecules (never a validation,
test or IR molecule nor QM7 rows 0-9, by molecular graph), and one small round end to end
(MD with the shipped ensemble, selection, labels at PBE0/STO-3G into shards/al-NNNN.h5 that
resume and never rewrite a shard)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from emlpack.data.shards import (
    ACTIVE_LEARNING_DIR,
    finished_keys,
    read_molecule_table,
    read_shards,
    shard_paths,
)
from emlpack.errors import InputError
from emlpack.qm.campaign import IR_TEST_SMILES, campaign_recipe, graph_key
from tests.conftest import ROOT, require, shared_path
from tests.examples.eqm7_data import example_module, qm7_with_reserved_ethanol, tiny_dataset

#: trust levels of the synthetic records: forces (eV/Å) and pairs (Å), lower and upper
LEVELS = {"forces": [0.2, 2.0], "pairs": [0.02, 0.5]}


@pytest.fixture(scope="module")
def al():
    require("rdkit")
    return example_module("active_learning")


def frame(step: int, force: float | None = 0.1, pair: float | None = 0.005, n_failed: int = 0,
          bonding: tuple[str, ...] = ()) -> dict:
    """A judged frame as ``spread.json`` holds it (dt 0.5 fs)."""
    return {"step": step, "time_fs": 0.5 * step, "energy_spread": 0.01, "force_spread": force,
            "pair_spread": pair, "n_failed": n_failed,
            "failed": "member 2: pairs merged" if n_failed else "", "bonding": list(bonding)}


def record(frames: list[dict], stopped: int | None = None, events: tuple[int, ...] = (),
           name: str = "m") -> dict:
    return {"molecule": name, "frames": frames, "events": [
        {"step": s, "reason": "energy jump", "fallback": "rigid", "ok": True} for s in events],
        "stopped": None if stopped is None else {"step": stopped, "reason": "pairs lost"}}


def test_trust_levels_classify_frames(al):
    """Below both lower levels: accurate; a spread between its levels, or a member that could
    not relax the pairs: candidate; a spread at an upper level (or no two sound members):
    failed, never selected."""
    assert al.classify(frame(0, 0.1, 0.005), LEVELS) == "accurate"
    assert al.classify(frame(0, 0.5, 0.005), LEVELS) == "candidate"
    assert al.classify(frame(0, 0.1, 0.1), LEVELS) == "candidate"
    assert al.classify(frame(0, 0.1, 0.005, n_failed=1), LEVELS) == "candidate"
    assert al.classify(frame(0, 2.0, 0.005), LEVELS) == "failed"
    assert al.classify(frame(0, 0.5, 0.6), LEVELS) == "failed"
    assert al.classify(frame(0, None, None, n_failed=3), LEVELS) == "failed"
    rec = record([frame(0), frame(10, 0.5), frame(20, 3.0), frame(30, 0.1, 0.03),
                  frame(40, 0.1, 0.005, n_failed=1)])
    found = {c["frame"]["step"]: c["reason"] for c in al.trajectory_candidates(rec, LEVELS)}
    assert found == {10: "spread", 30: "spread", 40: "member failure"}


def test_frames_before_a_failure_and_nothing_after_a_bonding_change(al):
    """The frames just before a watchdog stop or event and before the first bonding change are
    selected whatever their spread; no frame at or after a bonding change (another molecule,
    possibly a held-out one), nor after a stop."""
    frames = [frame(s, 0.5 if s in (10, 50) else 0.1) for s in range(0, 80, 10)]
    for f in frames[4:]:
        f["bonding"] = ["bond C0-H4 broken (1.09 -> 1.80 Å)"]
    cands = al.trajectory_candidates(record(frames, stopped=75, events=(25,)), LEVELS, 1)
    by_step = {c["frame"]["step"]: c["reason"] for c in cands}
    assert by_step == {10: "spread", 20: "watchdog event", 30: "bonding change"}
    assert all(not c["frame"]["bonding"] for c in cands)
    two = al.trajectory_candidates(record(frames[:4], stopped=35), LEVELS, 2)
    assert {c["frame"]["step"]: c["reason"] for c in two} == {
        10: "spread", 20: "watchdog stop", 30: "watchdog stop"}
    high = [frame(0), frame(10, 5.0)]  # above the upper level, but the last before the stop
    assert [c["reason"] for c in al.trajectory_candidates(record(high, stopped=15),
                                                          LEVELS)] == ["watchdog stop"]
    assert al.trajectory_candidates(record(high, stopped=15), LEVELS, 0) == []


def test_deduplication_and_budget(al):
    """At most K per trajectory, spaced in time, failures first then the largest spread; the
    budget goes round-robin over the trajectories."""
    spreads = [0.3, 1.5, 1.4, 0.5, 1.9, 0.25]  # frames every 5 fs
    rec = record([frame(10 * k, f) for k, f in enumerate(spreads)], stopped=60)
    cands = al.trajectory_candidates(rec, LEVELS)
    chosen = al.deduplicate(cands, 3, min_spacing_fs=10.0)
    assert [c["frame"]["step"] for c in chosen] == [50, 10, 30]  # stop first, then 1.5, 0.5
    assert chosen[0]["reason"] == "watchdog stop"
    times = [c["frame"]["time_fs"] for c in chosen]
    assert min(abs(a - b) for i, a in enumerate(times) for b in times[i + 1:]) >= 10.0
    assert len(al.deduplicate(cands, 10, min_spacing_fs=0.0)) == len(cands) == 6
    ranked = [chosen, al.deduplicate(al.trajectory_candidates(record(
        [frame(0, 0.9), frame(10, 0.8)]), LEVELS), 5, 0.0), []]
    picked = al.apply_budget(ranked, 3)
    assert [(k, c["frame"]["step"]) for k, c in picked] == [(0, 50), (1, 0), (0, 10)]
    records = [rec, record([frame(0, 0.9), frame(10, 0.8)]), record([frame(0)])]
    sel = {"failure_frames": 1, "max_per_trajectory": 3, "min_spacing_fs": 10.0, "budget": 4}
    got, counts = al.select(records, LEVELS, sel)
    assert len(got) == 4 and counts["selected"] == {
        "watchdog stop": 1, "bonding change": 0, "watchdog event": 0, "member failure": 0,
        "spread": 3}
    assert counts["frames"] == {"accurate": 1, "candidate": 8, "failed": 0}


def test_calibrated_trust_levels_of_the_shipped_ensemble(al):
    """``calibrated-median`` and ``calibrated``: the median and the warning quantile of the
    shipped ensemble's force spreads on the validation molecules."""
    from emlpack.calculators.ensemble import load_pretrained

    ensemble = load_pretrained("mini-eqm7")
    cal = ensemble.members[0].spread_calibration
    th = al.thresholds({"forces": {"lower": "calibrated-median", "upper": "calibrated"},
                        "pairs": {"lower": 0.02, "upper": 0.5}}, ensemble)
    np.testing.assert_allclose(th["forces"], [cal["median"]["force_spread"],
                                              cal["forces_eV_per_A"]])
    assert th["pairs"] == [0.02, 0.5]
    with pytest.raises(InputError, match="spread calibration"):
        al.thresholds({"forces": {"lower": 0.1, "upper": "calibrated"},
                       "pairs": {"lower": 0.02, "upper": 0.5}}, None)


def test_the_plan_for_mini_eqm7_holds_training_molecules_only(al):
    """The default config on the shipped data set: every trajectory is of a training molecule
    with a prepared geometry, none of a validation or test molecule, an IR molecule or QM7
    rows 0-9 (compared by molecular graph); two temperatures each, fields of at most 0.01 au."""
    cfg = al.load_config(al.HERE / "active_learning.yaml",
                         [f"smiles={shared_path('data/qm7_smiles.csv')}"])
    allowed, banned = al.allowed_molecules(cfg)
    assert {graph_key(s) for s in IR_TEST_SMILES.values()} <= set(banned)
    assert sum("QM7 row" in why for why in banned.values()) == 10
    plan = al.plan(cfg, allowed, banned)
    rows = {m["name"]: m for m in read_molecule_table(ROOT / "datasets" / "mini-eqm7")}
    names = {t.molecule for t in plan}
    assert len(names) == cfg["explore"]["molecules"] and len(plan) == 2 * len(names)
    assert {rows[n]["split"] for n in names} == {"train"}
    assert not {graph_key(rows[n]["smiles"]) for n in names} & set(banned)
    assert {t.temperature_K for t in plan} == {300.0, 500.0}
    from emlpack.units import FIELD_AU_IN_V_PER_A

    assert max(np.linalg.norm(t.field) for t in plan) <= 0.01 * FIELD_AU_IN_V_PER_A
    assert [t.seed for t in al.plan(cfg, allowed, banned)] == [t.seed for t in plan]


# ---------------------------------------------------------------------- end to end
@pytest.fixture
def tiny(tmp_path, al):
    """The tiny data set (the shared eQM7 subset: methane test, ethene validation, ethane,
    ethyne, ethanol, cyclopropane training) with prepared geometries, a campaign.yaml at the
    tiny level, a QM7 list whose row 5 is ethanol (so ethanol is reserved), and a config."""
    folder = tiny_dataset(tmp_path / "data")
    (folder / "prepared").mkdir()
    for s in read_shards(folder).structures:
        path = folder / "prepared" / f"{s.info['molecule_id']}.npz"
        if not path.exists():
            np.savez(path, numbers=s.numbers, positions=s.positions)
    recipe = campaign_recipe(samples_per_molecule=8)
    recipe.update(level="tiny", boys_starts=1)
    (folder / "campaign.yaml").write_text(yaml.safe_dump(
        {"name": "tiny", "source": "test", "seed": 0, "n_large": 0, "recipe": recipe}))
    qm7 = qm7_with_reserved_ethanol(tmp_path / "qm7.csv")
    overrides = [f"data={folder}", f"smiles={qm7}", f"workdir={tmp_path / 'runs'}",
                 "explore.molecules=1", "explore.temperatures=[300, 500]",
                 "explore.time_fs=5.0", "explore.evaluate_every=5", "progress=false",
                 "select.forces.lower=1.0e-6", "select.forces.upper=1000.0",
                 "select.pairs.lower=1.0e-6", "select.pairs.upper=1000.0",
                 "select.max_per_trajectory=2", "select.min_spacing_fs=0.0", "select.budget=2"]
    return folder, overrides


def test_held_out_and_reserved_molecules_are_refused(tiny, al, tmp_path, capsys):
    """explore.molecule_list with a validation, a test or a reserved molecule (by graph) is
    refused with one line; so is a selection holding a validation molecule's frame."""
    folder, overrides = tiny
    cfg = al.load_config(al.HERE / "active_learning.yaml", overrides)
    allowed, banned = al.allowed_molecules(cfg)
    assert set(allowed) == {"ethane", "ethyne", "cyclopropane"}
    for name, why in (("ethene", "val molecule ethene"), ("methane", "test molecule"),
                      ("ethanol", "QM7 row 5")):
        bad = al.load_config(al.HERE / "active_learning.yaml",
                             [*overrides, f"explore.molecule_list=[{name}]"])
        with pytest.raises(InputError, match=why):
            al.plan(bad, allowed, banned)
    assert al.main(["explore", *overrides, "explore.molecule_list=[ethene]"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "training molecules only" in err[0]
    from emlpack.io.extxyz import write_structures

    s = next(s for s in read_shards(folder).structures if s.info["molecule_id"] == "ethene")
    (folder / ACTIVE_LEARNING_DIR).mkdir()
    write_structures(folder / ACTIVE_LEARNING_DIR / "round-00.xyz", [s.copy(
        energy=None, forces=None, pair_forces=None,
        info={"key": "ethene/al00-md300K/0000", "molecule_id": "ethene", "kind": "al00-md300K"})])
    with pytest.raises(InputError, match="val molecule ethene"):
        al.selection_configurations(cfg, al.selection_files(cfg))
    assert al.main(["label", *overrides]) == 2
    assert al.main(["explore", *overrides, "explore.dt_fs=-1"]) == 2
    assert "explore.dt_fs must be a positive number" in capsys.readouterr().err


def test_a_round_end_to_end(tiny, al):
    """explore (2 trajectories of 10 MD steps, the shipped ensemble, member 0 driving), select
    (2 of the candidates, provenance kept, never rewritten), label at PBE0/STO-3G into
    shards/al-NNNN.h5: stopped after the first label and resumed, no shard rewritten, the
    campaign's shard untouched, the card and read_shards including the new part."""
    require("pyscf")
    folder, overrides = tiny
    cfg = al.load_config(al.HERE / "active_learning.yaml", overrides)
    records = al.stage_explore(cfg, log=lambda m: None)
    assert len(records) == 2 and len({r["molecule"] for r in records}) == 1
    assert {r["molecule"] for r in records} <= {"ethane", "ethyne", "cyclopropane"}
    assert {r["temperature_K"] for r in records} == {300.0, 500.0}
    for r in records:
        assert [f["step"] for f in r["frames"]] == [0, 5, 10] and r["md_seconds_per_step"] > 0
        assert all(f["force_spread"] > 0 and f["pair_spread"] > 0 for f in r["frames"]
                   if not f["n_failed"])
    spread_files = sorted((folder.parent / "runs").rglob(al.SPREAD_FILE))
    before = [p.stat().st_mtime_ns for p in spread_files]
    assert al.stage_explore(cfg, log=lambda m: None) == records  # done: nothing recomputed
    assert [p.stat().st_mtime_ns for p in spread_files] == before

    out = al.stage_select(cfg, log=lambda m: None)
    from emlpack.io.extxyz import read_structures

    chosen = read_structures(out)
    assert len(chosen) == 2
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["configurations"] == 2 and summary["trajectories"] == 2
    for s in chosen:
        info = s.info
        assert info["molecule_id"] in {"ethane", "ethyne", "cyclopropane"}
        assert info["key"].startswith(f"{info['molecule_id']}/al00-md")
        assert info["reason"] in al.REASONS and info["temperature_K"] in (300.0, 500.0)
        assert info["time_fs"] in (0.0, 2.5, 5.0) and info["force_spread"] > 0
        assert s.energy is None and s.forces is None  # the model's labels are not kept
        rec = next(r for r in records if r["path"] == info["trajectory"])
        np.testing.assert_allclose(s.field, rec["field_V_per_A"])
    with pytest.raises(InputError, match="never rewritten"):
        al.stage_select(cfg, log=lambda m: None)

    campaign_shard = shard_paths(folder)[0].read_bytes()
    stop_early = al.load_config(al.HERE / "active_learning.yaml", [*overrides, "label.hours=0"])
    first = al.stage_label(stop_early, log=lambda m: None)
    assert first["new_records"] == 1 and [p.split("/")[-1] for p in first["shards"]] == [
        "al-0000.h5"]
    al0 = (folder / "shards" / "al-0000.h5").read_bytes()
    second = al.stage_label(cfg, log=lambda m: None)
    assert second["new_records"] == 1 and second["skipped_done"] == 1
    assert (folder / "shards" / "al-0000.h5").read_bytes() == al0
    assert shard_paths(folder)[0].read_bytes() == campaign_shard
    third = al.stage_label(cfg, log=lambda m: None)
    assert third["new_records"] == 0 and third["shards"] == []
    assert [p.name for p in shard_paths(folder, "al-")] == ["al-0000.h5", "al-0001.h5"]
    assert finished_keys(folder, part="al-") == {s.info["key"] for s in chosen}
    data = read_shards(folder)
    labeled = [s for s in data.structures if s.info["kind"].startswith("al00-")]
    assert len(labeled) == 2 and {s.info["level"] for s in labeled} == {"pbe0/sto-3g"}
    assert {data.split_of[s.info["molecule_id"]] for s in labeled} == {"train"}
    for s in labeled:
        np.testing.assert_allclose(
            s.positions, next(c for c in chosen if c.info["key"] == s.info["key"]).positions)
    card = (folder / "README.md").read_text()
    assert "active learning: 2 configurations of 1 training molecules" in card
    assert "- 48 configurations of 6 molecules" in card  # the campaign's own counts
    info = al.stage_status(cfg, log=lambda m: None)
    assert info["done"] == 2 and info["labeled"] == 2 and info["left"] == 0
