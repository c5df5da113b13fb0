"""examples/eqm7/learning_curve.py on a tiny two-shard data set: every prefix trains for the
same optimizer steps on the same learning-rate schedule, all are evaluated on one test set, and
a re-run trains nothing."""

from __future__ import annotations

import csv
import json

from tests.examples.eqm7_data import PER_MOLECULE, example_module, tiny_dataset

TINY = ["train.model.n_features=8", "train.model.n_filters=8", "train.model.n_rbf=8",
        "train.model.n_interactions=1", "train.training.batch_size=8",
        "train.training.lr=0.005", "train.training.eval_batch_size=64",
        "evaluate.dynamic=false", "evaluate.second_test_set=null", "evaluate.max_structures=4"]


def _log(workdir, shards: int, steps: int) -> list[dict]:
    path = workdir / f"shards-{shards:02d}-steps-{steps}" / "models" / "aug" / "seed0" / "log.csv"
    return list(csv.DictReader(path.open()))


def test_learning_curve_equal_steps_one_test_set_and_resume(tmp_path):
    lc = example_module("learning_curve")
    data = tiny_dataset(tmp_path / "data", shards=2)
    work = tmp_path / "work"
    argv = ["--data", str(data), "--shards", "1", "2", "--steps", "6", "--decay-steps", "3",
            "--workdir", str(work), "--out", str(tmp_path / "lc"), "--set", *TINY]
    lc.main(argv)
    rows = json.loads((tmp_path / "lc.json").read_text())["rows"]
    assert [r["shards"] for r in rows] == [1, 2]
    # shard 0000 holds one training molecule, both shards four
    assert [r["train_configurations"] for r in rows] == [PER_MOLECULE, 4 * PER_MOLECULE]
    assert [r["train_molecules"] for r in rows] == [1, 4]
    assert sorted(p.name for p in (work / "data" / "shards-01" / "shards").iterdir()) \
        == ["0000.h5"]
    # batch 8: 1 and 4 steps per epoch -> 6 epochs of 1 step, round(6 / 4) = 2 epochs of 4
    assert (rows[0]["steps"], rows[0]["epochs"]) == (6, 6)
    assert (rows[1]["steps"], rows[1]["epochs"]) == (8, 2)
    for shards, row in zip((1, 2), rows, strict=True):
        # the same schedule in steps: halved every 3 steps whatever the epoch length
        for entry in _log(work, shards, 6):
            expected = 0.005 * 0.5 ** (int(entry["step"]) / 3)
            assert abs(float(entry["lr"]) - expected) < 1e-9 * expected
        # one test set: the test split of the largest prefix (methane, capped at 4)
        assert row["sets"]["test"]["n_structures"] == 4
        assert set(row["sets"]) == {"test"}
        assert row["sets"]["test"]["forces_meV_per_A"] > 0
    md = (tmp_path / "lc.md").read_text()
    assert len([line for line in md.splitlines() if line.startswith("| ")]) == 3  # header, 2 rows
    best = [work / f"shards-{n:02d}-steps-6" / "models" / "aug" / "seed0" / "best.pt"
            for n in (1, 2)]
    stamps = [p.stat().st_mtime_ns for p in best]
    lc.main(argv)
    assert [p.stat().st_mtime_ns for p in best] == stamps
    assert json.loads((tmp_path / "lc.json").read_text())["rows"] == rows
    # a second seed at the same point: seed 0 is kept, seed 1 trains on the same schedule
    lc.main([*argv[:3], "2", *argv[5:], "--seeds", "0", "1"])
    rows2 = json.loads((tmp_path / "lc.json").read_text())["rows"]
    assert [(r["shards"], r["seed"]) for r in rows2] == [(2, 0), (2, 1)]
    assert best[1].stat().st_mtime_ns == stamps[1]
    assert rows2[0]["sets"] == rows[1]["sets"]
    assert (rows2[1]["steps"], rows2[1]["epochs"]) == (8, 2)
    assert rows2[1]["sets"]["test"]["forces_meV_per_A"] != rows2[0]["sets"]["test"][
        "forces_meV_per_A"]
