"""The bake-off driver (examples/eqm7/bakeoff.py) end to end on a tiny setting.

The tiny data set of the study tests (methane the test molecule, ethene the validation one), a
fake validation reference of ethene (its configuration's Boys centres, a made-up
polarizability), two candidates (a tiny SchNet and a tiny PaiNN) with a CPU budget of a few
seconds, 7 fs of MD. The driver trains, evaluates on the validation molecule only, gives a
resumed training exactly its budget over both parts, writes the table with both rows, and a
re-run redoes nothing.
"""

from __future__ import annotations

import contextlib
import csv
import io
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


def _validation_reference(study, data, root) -> None:
    """The validation molecule's (ethene's) reference, as validation_references.py writes it:
    its first configuration's Boys centres, a made-up polarizability (26 bohr³ isotropic)."""
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


@pytest.fixture(scope="module")
def bakeoff_run(tmp_path_factory):
    mod = example_module("bakeoff")
    study = mod.run_study
    root = tmp_path_factory.mktemp("bakeoff")
    data = tiny_dataset(root / "data")
    _validation_reference(study, data, root)
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


# ---------------------------------------------------------------------- issue 50's pilot
#: a stand-in for the cheap level's labels: eV per atom of each element added to every energy
CHEAP_SHIFT = {1: 0.21, 6: -1.3, 7: 0.8, 8: -0.45}
CHEAP_LEVEL = "pbe0/def2-svpd/grid1"


def _move(path, to):
    path.rename(to)
    return to


@pytest.fixture(scope="module")
def pilot_run(tmp_path_factory):
    """The pilot on the tiny data: a scratch candidate and a pretrained one (pretraining on a
    cheap-level set of three shards, two molecules each, that grows while the bake-off runs;
    30 configurations wanted). First the cheap set holds one shard: the pretrained candidate
    waits. Then a second shard: its pretraining freezes both and is cut off (a kill after an
    epoch); a third shard comes; the bake-off resumes the pretraining with its budget over
    both parts, fine-tunes for the rest of the total and writes the tables."""
    mod = example_module("bakeoff")
    study = mod.run_study
    root = tmp_path_factory.mktemp("pilot")
    data = tiny_dataset(root / "data")
    _validation_reference(study, data, root)
    cheap = tiny_dataset(root / "cheap", shards=3, level=CHEAP_LEVEL, shift=CHEAP_SHIFT)
    aside = {n: _move(cheap / "shards" / n, root / n) for n in ("0001.h5", "0002.h5")}
    total = 0.15  # CPU minutes of every candidate (9 s)
    bake = {
        "study": str(ROOT / "examples" / "eqm7" / "config.yaml"),
        "workdir": str(root / "runs"), "results_dir": str(root / "results"),
        "snapshots": str(root / "snapshots"),
        "cpu_minutes": total, "seed": 0, "group": "aug", "md_molecules": 1,
        "decay_cpu_minutes": 1.0,
        "train_overrides": ["training.compile=false", "training.batch_size=8",
                            "training.lr=0.005", "training.eval_batch_size=64"],
        "study_overrides": [f"data={data}", "evaluate.max_structures=4", "md.time_fs=7.0",
                            "md.checkpoint_every=7", "md.log_every=7", "progress=false"],
        "candidates": {
            "scratch": {"overrides": TINY["schnet"]},
            "pre": {"pretrain": {"data": str(cheap), "cpu_minutes": 0.05,
                                 "min_configurations": 30,
                                 "overrides": ["data.split=molecule",
                                               "data.fractions=[0.75, 0.25, 0.0]"]},
                    "overrides": [*TINY["schnet"], "training.lr=0.002"]}},
        "pilot": {"scratch": "scratch", "pretrained": "pre",
                  "results_dir": str(root / "pilot")},
    }
    path = root / "bakeoff.yaml"
    path.write_text(yaml.safe_dump(bake, sort_keys=False))
    b = mod.load_bakeoff(path)
    names = mod.chosen(b, None)
    out = {"waiting_work": mod.run(b, names, log=lambda m: None)}
    out["waiting_row"] = json.loads((root / "results" / "bakeoff.json").read_text())["rows"][1]
    out["waiting_pilot"] = json.loads((root / "pilot" / "pilot.json").read_text())
    for key in ("waiting", "due"):
        if key == "due":
            _move(aside["0001.h5"], cheap / "shards" / "0001.h5")  # 32 configurations: enough
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            out[f"{key}_done"] = mod.main(["done", "--config", str(path)])
        out[f"{key}_printed"] = printed.getvalue()
    cut_bake = mod.load_bakeoff(path, ["candidates.pre.pretrain.cpu_minutes=0.02"])
    mod.stage_pretrain(cut_bake, "pre", log=lambda m: None)
    pre = root / "runs" / "pre" / "pretrain"
    (pre / "done.json").unlink()  # cut off after an epoch: last.pt, no done.json
    out["cut"] = {"cpu": _cpu(pre), "epochs": len(_log(pre))}
    _move(aside["0002.h5"], cheap / "shards" / "0002.h5")  # the set grows meanwhile
    budget = (out["cut"]["cpu"] + 2.0) / 60.0
    b = mod.load_bakeoff(path, [f"candidates.pre.pretrain.cpu_minutes={budget}"])
    out["work"] = mod.run(b, names, log=lambda m: None)
    return mod, b, root, cheap, out


def test_a_pretrained_candidate_waits_for_its_data(pilot_run):
    """Below ``min_configurations`` the pretrained candidate does nothing (the others run),
    its row and the pilot say so, and ``done`` does not count it as work left; once the data
    are there ``done`` does."""
    mod, _, root, _, out = pilot_run
    assert out["waiting_work"]["pre"] == {} and out["waiting_work"]["scratch"]["train"] == 1
    row = out["waiting_row"]
    assert row["pretrain"]["status"] == "waiting" and row["pending"][0] == "pretrain"
    assert "holds 16 of the 30 configurations" in row["waiting"]
    assert out["waiting_pilot"]["verdict"]["decision"] == "pending"
    assert out["waiting_done"] == 0 and out["due_done"] == 1
    assert "pre: waiting (" in out["waiting_printed"]
    assert "pre: pending: pretrain, train" in out["due_printed"]


def test_the_pretraining_resumes_on_its_frozen_shards_with_its_budget(pilot_run):
    """The pretraining froze the two shards there at its start (a third came later), runs on
    the cheap set's own hydride reference, and its resumed part got the budget left over both
    parts; a fresh clone (its run folder gone) takes the list and the state from the
    snapshots and trains no more."""
    import shutil

    from emlpack.data.shards import read_shards

    mod, b, root, cheap, out = pilot_run
    pre = root / "runs" / "pre" / "pretrain"
    assert out["work"]["pre"]["pretrain"] == 1 and out["work"]["scratch"] == {}
    done = json.loads((pre / "done.json").read_text())
    assert done["shards"] == ["0000.h5", "0001.h5"] and done["configurations"] == 32
    assert done["molecules"] == 4 and done["levels"] == [CHEAP_LEVEL]
    assert json.loads((root / "snapshots" / "pre" / "pretrain" / "shards.json").read_text()) \
        == json.loads((pre / "shards.json").read_text())
    ckpt = read_checkpoint(pre / "best.pt")["metadata"]
    assert ckpt["n_structures"] == 32 and ckpt["config"]["data"]["shards"] == done["shards"]
    assert ckpt["reference"]["energies"] == pytest.approx(read_shards(cheap).hydrides["energies"])
    budget = 60.0 * b["candidates"]["pre"]["pretrain"]["cpu_minutes"]
    rows = _log(pre)
    assert len(rows) > out["cut"]["epochs"]  # the first part's epochs and more
    assert budget - 0.5 <= _cpu(pre) <= budget + float(rows[-1]["epoch_time"]) + 1.0
    assert _cpu(pre) < out["cut"]["cpu"] + budget - 1.0  # a fresh budget would give more
    shutil.rmtree(pre)  # a fresh clone: only the committed snapshots are left
    again = mod.stage_pretrain(b, "pre", log=lambda m: None)
    assert again["shards"] == done["shards"] and again["frozen"] == done["frozen"]
    assert again["cpu_seconds"] == pytest.approx(done["cpu_seconds"])
    assert len(_log(pre)) == len(rows)


def test_the_fine_tune_gets_the_rest_of_the_total(pilot_run):
    """The fine-tune starts from the pretraining's best.pt with mini-eQM7's reference and its
    own learning rate, for the total less what the pretraining took: the two parts together
    take the scratch candidate's budget; its checkpoint's lineage names both stages."""
    from emlpack.data.shards import read_shards

    mod, b, root, _, _ = pilot_run
    pre = root / "runs" / "pre" / "pretrain"
    tuned = root / "runs" / "pre" / "models" / "aug" / "seed0"
    total = 60.0 * b["cpu_minutes"]
    cfg = yaml.safe_load((tuned / "config.yaml").read_text())
    assert cfg["training"]["init_weights"] == str(pre / "best.pt")
    assert cfg["training"]["lr"] == 0.002 and cfg["data"]["shards"] is None
    assert 60.0 * cfg["training"]["max_cpu_minutes"] == pytest.approx(total - _cpu(pre))
    both = _cpu(pre) + _cpu(tuned)
    assert total - 1.0 <= both <= total + float(_log(tuned)[-1]["epoch_time"]) + 1.0
    meta = read_checkpoint(tuned / "best.pt")["metadata"]
    assert meta["reference"]["energies"] == pytest.approx(
        read_shards(root / "data").hydrides["energies"])
    lineage = meta["lineage"]
    assert [s["levels"] for s in lineage] == [[CHEAP_LEVEL], ["pbe0/aug-cc-pvtz"]]
    assert lineage[0]["shards"] == ["0000.h5", "0001.h5"] and lineage[1]["shards"] is None
    assert mod.finetune_minutes(b, "pre") == pytest.approx((total - _cpu(pre)) / 60.0)


def test_the_tables_record_the_pretraining_and_the_pilot(pilot_run):
    """bakeoff.json records what the pretraining saw (frozen shards, configurations) and the
    total CPU; the pilot's table puts both models side by side with the changes and the
    rule's verdict, recomputed from the rows."""
    mod, b, root, _, _ = pilot_run
    result = json.loads((root / "results" / "bakeoff.json").read_text())
    scratch, pre = result["rows"]
    assert result["complete"] and pre["pretrain"]["status"] == "done"
    assert pre["pretrain"]["shards"] == ["0000.h5", "0001.h5"]
    assert pre["pretrain"]["configurations"] == 32 and pre["pretrain"]["n_shards"] == 2
    assert pre["total_cpu_minutes"] == pytest.approx(
        pre["pretrain"]["cpu_minutes"] + pre["training"]["cpu_minutes"])
    assert scratch["pretrain"] is None and scratch["total_cpu_minutes"] == pytest.approx(
        scratch["training"]["cpu_minutes"])
    md = (root / "results" / "bakeoff.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| pre |"))
    assert " pretraining + " in row and "pending" not in row
    assert "pretrained on `" in md and "0000.h5-0001.h5" in md
    pilot = json.loads((root / "pilot" / "pilot.json").read_text())
    assert pilot["scratch"]["name"] == "scratch" and pilot["pretrained"]["name"] == "pre"
    v = pilot["verdict"]
    assert v == mod.verdict(scratch, pre) and v["decision"] in ("continue", "stop")
    f = scratch["validation"]["forces_mae_meV_per_A"]
    assert v["gains"]["forces_mae_meV_per_A"] == pytest.approx(
        (f - pre["validation"]["forces_mae_meV_per_A"]) / f)
    text = (root / "pilot" / "pilot.md").read_text()
    assert text.startswith("### Pilot table") and "| from scratch (scratch) |" in text
    assert "| pretrained + fine-tuned (pre) |" in text and "| change with pretraining |" in text
    assert f"**Verdict: {'continue' if v['decision'] == 'continue' else 'stop'}" in text
    assert "32 configurations of 4 molecules" in text


def _rows(forces: tuple, alpha: tuple, pending: tuple = ((), ())) -> tuple[dict, dict]:
    return tuple({"name": name, "pending": list(p),
                  "validation": {"forces_mae_meV_per_A": f},
                  "polarizability": {"isotropic_median_relative_error": a}}
                 for name, f, a, p in zip(("scratch", "pre"), forces, alpha, pending,
                                          strict=True))


def test_the_pilot_rule_continues_at_15_percent_forces_or_25_percent_polarizability():
    mod = example_module("bakeoff")
    assert mod.verdict(*_rows((100.0, 85.0), (0.2, 0.2)))["decision"] == "continue"
    assert mod.verdict(*_rows((100.0, 85.1), (0.2, 0.15)))["decision"] == "continue"
    stop = mod.verdict(*_rows((100.0, 85.1), (0.2, 0.1501)))
    assert stop["decision"] == "stop" and stop["met"] == []
    assert stop["gains"]["forces_mae_meV_per_A"] == pytest.approx(0.149)
    worse = mod.verdict(*_rows((100.0, 120.0), (0.2, 0.3)))
    assert worse["decision"] == "stop" and worse["gains"]["forces_mae_meV_per_A"] < 0
    # no polarizability compared (every relaxation failed): the forces decide
    assert mod.verdict(*_rows((100.0, 80.0), (None, None)))["decision"] == "continue"
    pending = mod.verdict(*_rows((100.0, None), (0.2, None), ((), ("pretrain", "md"))))
    assert pending["decision"] == "pending" and pending["pending"] == ["pre: pretrain"]
    # MD is not part of the rule
    assert mod.verdict(*_rows((100.0, 80.0), (0.2, 0.2), (("md",), ())))["decision"] \
        == "continue"
    assert "Verdict: stop the campaign" in mod.verdict_text(stop)


def test_bad_pretrain_or_pilot_config_is_one_line(tmp_path):
    mod = example_module("bakeoff")
    path = tmp_path / "b.yaml"
    good = {"decay_cpu_minutes": 30, "cpu_minutes": 120, "candidates": {
        "a": {"overrides": []},
        "p": {"pretrain": {"data": "datasets/qm7-pbe0-def2svpd", "cpu_minutes": 60},
              "overrides": []}},
        "pilot": {"scratch": "a", "pretrained": "p"}}
    path.write_text(yaml.safe_dump(good))
    bake = mod.load_bakeoff(path)
    p = bake["candidates"]["p"]["pretrain"]
    assert p["checkpoint"] == "best" and p["min_configurations"] is None
    assert bake["pilot"]["results_dir"] == "examples/qm7_cheap"
    for over, match in (
            (["candidates.p.pretrain.cpu_minutes=120"], "below cpu_minutes \\(120"),
            (["candidates.p.pretrain.checkpoint=first"], "best or last"),
            (["candidates.p.pretrain.min_configurations=0"], "positive integer"),
            (["candidates.p.pretrain.bogus=1"], "unknown key\\(s\\) \\['bogus'\\]"),
            (["candidates.p.pretrain.overrides=[nokey]"], "'key=value' strings"),
            (["pilot.scratch=p"], "pilot.scratch must name a candidate without"),
            (["pilot.pretrained=a"], "pilot.pretrained must name a candidate with")):
        with pytest.raises(SystemExit, match=match):
            mod.load_bakeoff(path, over)
    model = mod.load_bakeoff(path, ["candidates.p.pretrain.overrides=[model.n_features=8]"])
    with pytest.raises(SystemExit, match="candidate p: the pretraining's model differs"):
        mod.check_candidate(model, "p")
    missing = mod.load_bakeoff(path, [f"candidates.p.pretrain.data={tmp_path}"])
    with pytest.raises(SystemExit, match="pretrain.data .*: not a data-set folder"):
        mod.check_candidate(missing, "p")


def test_the_shipped_bakeoff_has_the_pilot_after_painn_f64():
    """bakeoff.yaml: schnet-pretrained after v1-schnet and painn-f64 (the running bake-off's
    first two keep their order), pretrained on the cheap set for 60 of the 120 CPU minutes
    once it holds 2000 configurations (the first pilot), fine-tuned for the rest; the pilot
    compares it with v1-schnet into examples/qm7_cheap."""
    mod = example_module("bakeoff")
    bake = mod.load_bakeoff()
    assert list(bake["candidates"]) == ["v1-schnet", "painn-f64", "schnet-pretrained",
                                        "painn-f128"]
    p = bake["candidates"]["schnet-pretrained"]["pretrain"]
    assert p["data"] == "datasets/qm7-pbe0-def2svpd" and p["cpu_minutes"] == 60
    assert p["min_configurations"] == 2000
    assert bake["pilot"] == {"scratch": "v1-schnet", "pretrained": "schnet-pretrained",
                             "results_dir": "examples/qm7_cheap"}
    over = mod.training_overrides(bake, "schnet-pretrained")
    if mod.pretrain_record(bake, "schnet-pretrained") is None:  # not pretrained here
        assert "training.max_cpu_minutes=60" in over
    assert "training.init_weights=runs/bakeoff/schnet-pretrained/pretrain/best.pt" in over
    pre = mod.pretrain_overrides(bake, "schnet-pretrained", ["0000.h5"])
    assert "data.path=datasets/qm7-pbe0-def2svpd" in pre and 'data.shards=["0000.h5"]' in pre
    assert "training.max_cpu_minutes=60" in pre and "augmentation.enabled=true" in pre
    assert "output.snapshot_dir=examples/eqm7/snapshots/bakeoff/schnet-pretrained/pretrain" \
        in pre
    assert mod.training_overrides(bake, "v1-schnet")[0] == "training.max_cpu_minutes=120"
