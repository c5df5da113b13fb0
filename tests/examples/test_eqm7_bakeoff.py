"""The bake-off driver (examples/eqm7/bakeoff.py) end to end on a tiny setting.

The tiny data set of the study tests (methane the test molecule, ethene the validation one), a
fake validation reference of ethene (its configuration's Boys centres, a made-up
polarizability), two candidates (a tiny SchNet and a tiny PaiNN) with a CPU budget of a few
seconds, 7 fs of MD. The driver trains, evaluates on the validation molecule only, gives a
resumed training exactly its budget over both parts, writes the table with both rows, and a
re-run redoes nothing.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from emlpack.nn.checkpoint import read_checkpoint
from tests.conftest import ROOT
from tests.examples.eqm7_data import example_module, tiny_dataset

TINY = {
    "schnet": ["model.n_features=8", "model.n_filters=8", "model.n_rbf=8",
               "model.n_interactions=1"],
    "painn": ["model.family=painn", "model.short_range.n_features=8",
              "model.short_range.n_rbf=8", "model.short_range.n_interactions=1"],
}


def _cpu(run) -> float:
    return read_checkpoint(run / "last.pt")["metadata"]["training"]["cpu_seconds"]


def _log(run) -> list[dict]:
    return list(csv.DictReader((run / "log.csv").open()))


@pytest.fixture(scope="module")
def bakeoff_run(tmp_path_factory):
    mod = example_module("bakeoff")
    study = mod.run_study
    root = tmp_path_factory.mktemp("bakeoff")
    data = tiny_dataset(root / "data")
    # the validation molecule's reference, as validation_references.py writes it
    s = next(x for x in study.Study(study.load_config(ROOT / "examples" / "eqm7" / "config.yaml",
                                                      [f"data={data}",
                                                       f"workdir={root / 'scratch'}"]))
             .shards().structures if x.info.get("molecule_id") == "ethene")
    refs = data / "references" / "pbe0_aug-cc-pvtz" / "validation"
    refs.mkdir(parents=True)
    (refs / "ethene.json").write_text(json.dumps({
        "name": "ethene", "smiles": "C=C", "level": "pbe0/aug-cc-pvtz",
        "numbers": s.numbers.tolist(), "positions": s.positions.tolist(),
        "pairs": s.pairs.tolist(), "polarizability_bohr3": np.diag([30.0, 26.0, 22.0]).tolist(),
        "polarizability_isotropic_bohr3": 26.0}))
    bake = {
        "study": str(ROOT / "examples" / "eqm7" / "config.yaml"),
        "workdir": str(root / "runs"), "results_dir": str(root / "results"),
        "cpu_minutes": 0.05, "seed": 0, "group": "aug", "md_molecules": 1,
        "train_overrides": ["training.compile=false", "training.batch_size=8",
                            "training.lr=0.005", "training.eval_batch_size=64"],
        "study_overrides": [f"data={data}", "evaluate.max_structures=4", "md.time_fs=7.0",
                            "md.checkpoint_every=7", "md.log_every=7", "progress=false"],
        "candidates": {name: {"decay_epochs": 10, "overrides": over}
                       for name, over in TINY.items()},
    }
    path = root / "bakeoff.yaml"
    path.write_text(yaml.safe_dump(bake, sort_keys=False))
    # a training cut off (a kill after an epoch: last.pt, no done.json) at about 6 CPU s
    first = mod.load_bakeoff(path, ["cpu_minutes=0.1"])
    study.run(["train"], mod.candidate_config(first, "schnet"), log=lambda m: None)
    run = root / "runs" / "schnet" / "models" / "aug" / "seed0"
    (run / "done.json").unlink()
    cut = {"cpu": _cpu(run), "epochs": len(_log(run))}
    # then the bake-off with a budget 3 CPU s above what the first part spent
    budget = (cut["cpu"] + 3.0) / 60.0
    bake = mod.load_bakeoff(path, [f"cpu_minutes={budget}"])
    lines: list[str] = []
    work = mod.run(bake, mod.chosen(bake, None), log=lines.append)
    return mod, bake, root, work, cut, lines


def test_each_candidate_runs_every_stage_on_the_validation_molecules(bakeoff_run):
    mod, bake, root, work, _, _ = bakeoff_run
    assert work == {name: {"train": 1, "evaluate": 1, "polarizability": 1, "md": 1}
                    for name in TINY}
    for name in TINY:
        w = root / "runs" / name
        assert (w / "models" / "aug" / "seed0" / "done.json").exists()
        assert not (w / "models" / "noaug").exists() and not (w / "eval" / "test").exists()
        ev = json.loads((w / "eval" / "val" / "aug-s0.json").read_text())
        assert ev["set"] == "val" and ev["n_structures"] == 4
        pol = json.loads((w / "polarizability" / "val" / "aug-s0.json").read_text())
        assert list(pol["molecules"]) == ["ethene"]
        assert (w / "md" / "aug-s0" / "ethene" / "analysis.json").exists()
        assert sorted(p.name for p in (w / "md" / "aug-s0").iterdir()) == ["ethene"]
    # nothing names the test molecule (methane) or uses the second test set
    texts = [p.read_text() for p in (root / "runs").rglob("*.json")]
    texts += [(root / "results" / n).read_text() for n in ("bakeoff.md", "bakeoff.json")]
    assert texts and not any("methane" in t or "pbe0_subset" in t for t in texts)
    assert not any("methane" in str(p) for p in (root / "runs").rglob("*"))


def test_a_resumed_training_gets_its_budget_over_both_parts(bakeoff_run):
    """The training cut off at ``cut`` CPU seconds goes on from its last.pt (its epochs kept)
    and stops after the epoch that passes the budget counted over both parts, not a fresh
    budget for the resumed part."""
    _, bake, root, _, cut, _ = bakeoff_run
    budget = 60.0 * bake["cpu_minutes"]
    for name in TINY:
        run = root / "runs" / name / "models" / "aug" / "seed0"
        rows = _log(run)
        spent = _cpu(run)  # at the last epoch's end, a moment before the check that stopped
        assert spent >= budget - 0.5
        # over by at most the last epoch (its wall time bounds its CPU time, one thread)
        assert spent - budget <= float(rows[-1]["epoch_time"]) + 1.0
        assert [int(r["epoch"]) for r in rows] == list(range(1, len(rows) + 1))
        done = json.loads((run / "done.json").read_text())
        assert done["cpu_seconds"] == pytest.approx(spent) and done["epochs"] == len(rows)
    resumed = root / "runs" / "schnet" / "models" / "aug" / "seed0"
    assert len(_log(resumed)) > cut["epochs"]  # the first part's epochs and more
    assert _cpu(resumed) < cut["cpu"] + budget - 1.0  # a fresh budget would give more


def test_the_table_has_a_row_per_candidate(bakeoff_run):
    mod, bake, root, _, _, _ = bakeoff_run
    result = json.loads((root / "results" / "bakeoff.json").read_text())
    assert result["complete"] and [r["name"] for r in result["rows"]] == list(TINY)
    assert result["setup"]["references"] == 1 and result["setup"]["validation_molecules"] == 1
    for r in result["rows"]:
        assert r["pending"] == [] and r["training"]["finished"]
        assert r["training"]["cpu_minutes"] == pytest.approx(
            _cpu(root / "runs" / r["name"] / "models" / "aug" / "seed0") / 60.0)
        ev = json.loads((root / "runs" / r["name"] / "eval" / "val" / "aug-s0.json").read_text())
        assert r["validation"]["forces_mae_meV_per_A"] == pytest.approx(
            1000 * ev["static"]["forces"]["mae"])
        assert r["validation"]["pair_field_slope"] == pytest.approx(
            ev["static"]["pair_field_slope"])
        p = r["polarizability"]
        row = json.loads((root / "runs" / r["name"] / "polarizability" / "val" / "aug-s0.json")
                         .read_text())["molecules"]["ethene"]
        if row["failure"]:
            assert p["isotropic_compared"] == 0 and p["isotropic_within_10pct"] == 0
        else:
            iso = np.trace(row["polarizability_bohr3"]) / 3
            assert p["isotropic_median_relative_error"] == pytest.approx(abs(iso - 26.0) / 26.0)
        assert r["md"]["runs"] == 1 and r["md"]["molecules"] == 1
    md = (root / "results" / "bakeoff.md").read_text()
    rows = [line for line in md.splitlines() if line.startswith(("| schnet |", "| painn |"))]
    assert len(rows) == 2 and not any("pending" in line for line in rows)
    assert "`model.family=painn`" in md
    # a candidate not run yet: its row says pending, the table is not complete
    later = dict(bake, results_dir=str(root / "later"), candidates={
        **bake["candidates"], "later": {"decay_epochs": 5, "overrides": TINY["schnet"]}})
    result = mod.table(later, list(later["candidates"]), log=lambda m: None)
    assert not result["complete"] and result["rows"][2]["pending"] == list(mod.STAGES)
    row = next(line for line in (root / "later" / "bakeoff.md").read_text().splitlines()
               if line.startswith("| later |"))
    assert row.count("pending") == 11


def test_a_rerun_redoes_nothing_and_done_says_complete(bakeoff_run, capsys):
    mod, bake, root, _, _, _ = bakeoff_run
    work = mod.run(bake, ["painn"], log=lambda m: None)
    assert work == {"painn": {}}
    path = root / "bakeoff.yaml"
    budget = f"cpu_minutes={bake['cpu_minutes']}"
    assert mod.main(["done", budget, "--config", str(path)]) == 0
    assert "schnet: complete" in capsys.readouterr().out
    with pytest.raises(SystemExit, match=r"--only: unknown candidate\(s\) \['nope'\]"):
        mod.main(["table", "--only", "nope", "--config", str(path)])


def test_split_val_refuses_the_test_molecules_stages(bakeoff_run):
    """With split val: dft, table and export refuse in one line, ir skips (no harmonic
    validation reference), the references are DATA/.../validation; a bad split is one line."""
    mod, bake, root, _, _, _ = bakeoff_run
    study = mod.run_study
    cfg = mod.candidate_config(bake, "schnet")
    lines: list[str] = []
    s = study.run(["ir"], cfg, log=lines.append)
    assert not s.work and any("ir: no harmonic DFT reference of the val molecules" in m
                              for m in lines)
    assert s.dft_dir.name == "validation" and s.sets() == ("val",)
    assert [m["name"] for m in s.split_molecules()] == ["ethene"]
    for stage, why in (("dft", "validation_references.py"), ("table", "bakeoff.py table"),
                       ("export", "test molecules")):
        with pytest.raises(SystemExit, match=f"{stage}: not with split val .*{why}"):
            study.run([stage], cfg, log=lambda m: None)
    with pytest.raises(SystemExit, match="split: test or val, got 'train'"):
        study.Study(dict(cfg, split="train"))


def test_bad_bakeoff_config_is_one_line(tmp_path):
    mod = example_module("bakeoff")
    path = tmp_path / "b.yaml"
    path.write_text(yaml.safe_dump({"candidates": {"a": {"overrides": []}}}))
    with pytest.raises(SystemExit, match="candidate a: decay_epochs .* is required unless"):
        mod.load_bakeoff(path)
    assert mod.load_bakeoff(path, ["decay_cpu_minutes=30"])["candidates"]["a"]
    with pytest.raises(SystemExit, match="cpu_minutes must be a positive number"):
        mod.load_bakeoff(path, ["cpu_minutes=0"])
    path.write_text(yaml.safe_dump({"candidates": {"a b": {"decay_epochs": 3}}}))
    with pytest.raises(SystemExit, match="names a folder"):
        mod.load_bakeoff(path)
    shipped = mod.load_bakeoff()  # the committed bakeoff.yaml: the screen
    assert shipped["cpu_minutes"] == 120 and shipped["seed"] == 0 and shipped["group"] == "aug"
    assert {"v1-schnet", "painn-f64", "painn-f128"} <= set(shipped["candidates"])
    cfg = mod.candidate_config(shipped, "v1-schnet")
    assert cfg["split"] == "val" and cfg["training"]["steps"] is None
    assert cfg["workdir"] == "runs/bakeoff/v1-schnet" and cfg["seeds"] == [0]
    assert "training.max_cpu_minutes=120" in cfg["training"]["overrides"]
    # the shipped schedule is by CPU time, the same for every family; decay_epochs replaces it
    assert "training.decay_cpu_minutes=35" in cfg["training"]["overrides"]
    assert not any(o.startswith("training.decay_epochs") for o in cfg["training"]["overrides"])
    by_epochs = mod.load_bakeoff(overrides=["candidates.v1-schnet.decay_epochs=400"])
    over = mod.training_overrides(by_epochs, "v1-schnet")
    assert "training.decay_epochs=400" in over and not any("decay_cpu" in o for o in over)
    assert mod.schedule_text(by_epochs, "v1-schnet") == "every 400 epochs"
    assert mod.schedule_text(shipped, "painn-f64") == "every 35 CPU minutes"
    bad = mod.load_bakeoff(overrides=["candidates.v1-schnet.overrides=[model.bogus=1]"])
    with pytest.raises(SystemExit, match="bakeoff: candidate v1-schnet: unknown config key"):
        mod.run(bad, ["v1-schnet"], log=lambda m: None)
