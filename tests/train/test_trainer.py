"""The trainer end to end on a tiny model: a run, exact resume after kill -9, data parallel
with 2 processes giving the loss curve of 1 process with the same global batch, ensembles."""

from __future__ import annotations

import csv
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from emlpack.bonding import largest_molecule
from emlpack.data.dataset import load_data
from emlpack.io import read_structures, write_structures
from emlpack.nn.checkpoint import load_model, read_checkpoint
from emlpack.train.config import load_config
from emlpack.train.trainer import train, train_ensemble
from tests.conftest import shared_path
from tests.nn.helpers import as_format_1  # also registers the tests' family "radial"

TINY = {
    "model": {"n_features": 16, "n_filters": 8, "n_rbf": 8, "n_interactions": 1},
    # the CPU: exact resume compares weights to 1e-5, which a GPU's float32 atomic sums do
    # not reproduce run to run (the GPU's own test below is in float64)
    "training": {"batch_size": 8, "max_epochs": 3, "lr": 1e-2, "threads": 1,
                 "decay_epochs": 2.0, "eval_batch_size": 16, "device": "cpu"},
    "output": {"progress": False},
}


@pytest.fixture(scope="module")
def small_data(tmp_path_factory):
    """24 configurations (4 per molecule) of the shared eQM7 subset."""
    frames = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="::25")
    path = tmp_path_factory.mktemp("data") / "small.xyz"
    write_structures(path, frames)
    return path


def _config(tmp_path: Path, data: Path, name: str, **sections) -> Path:
    cfg = {k: dict(v) for k, v in TINY.items()}
    cfg["data"] = {"path": str(data), "hydrides": str(shared_path("data/hydrides")),
                   "split": "configuration", "fractions": [0.75, 0.25, 0.0]}
    cfg["output"] = {**cfg["output"], "dir": str(tmp_path / name)}
    for key, value in sections.items():
        cfg[key] = {**cfg.get(key, {}), **value}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _log(run: Path) -> list[dict]:
    with open(run / "log.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _cli(*args: str, env_extra: dict | None = None) -> list[str]:
    return [sys.executable, "-m", "emlpack.cli", *args]


def _env() -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2]) + os.pathsep + env.get(
        "PYTHONPATH", "")
    return env


def test_training_reduces_the_loss_and_writes_the_run(tmp_path, small_data):
    cfg = load_config(_config(tmp_path, small_data, "run", augmentation={"enabled": True,
                                                                        "probability": 0.5}),
                      ["training.max_epochs=4"])
    best = train(cfg)
    run = best.parent
    rows = _log(run)
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3, 4]
    assert float(rows[-1]["val_loss"]) < float(rows[0]["val_loss"])
    assert sum(int(r["n_augmented"]) for r in rows) > 0
    # lr halves every decay_epochs (smoothly per step)
    steps = int(rows[-1]["step"])
    assert float(rows[-1]["lr"]) == pytest.approx(1e-2 * 0.5 ** (steps / (3 * 2.0)), rel=1e-6)
    for name in ("config.yaml", "split.json", "best.pt", "last.pt"):
        assert (run / name).exists()
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["training"]["max_epochs"] == 4
    model = load_model(best)  # weights_only loading of the model part
    assert model.config.short_range["n_features"] == 16
    meta = read_checkpoint(run / "last.pt")["metadata"]
    assert meta["training"]["epoch"] == 4 and meta["reference"]["kind"] == "hydrides"
    # the training domain the calculator checks: elements and the largest molecule
    structures, _ = load_data(small_data)
    seen = [structures[i] for i in meta["split"]["train"]]
    assert meta["elements"] == sorted({int(z) for s in seen for z in s.numbers})
    assert meta["max_heavy_atoms"] == max(largest_molecule(s.numbers, s.positions)
                                          for s in seen) >= 1


def test_resume_after_kill_minus_9_is_exact(tmp_path, small_data):
    cfg = _config(tmp_path, small_data, "ref", training={"max_epochs": 5})
    subprocess.run(_cli("train", str(cfg)), check=True, env=_env(), capture_output=True)
    reference = _log(tmp_path / "ref")

    cfg2 = _config(tmp_path, small_data, "killed", training={"max_epochs": 5})
    run = tmp_path / "killed"
    proc = subprocess.Popen(_cli("train", str(cfg2)), env=_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if (run / "log.csv").exists() and len(_log(run)) >= 2:
            break
        time.sleep(0.02)
    assert proc.poll() is None, "the run finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = len(_log(run))
    assert 2 <= done < 5
    out = subprocess.run(_cli("train", str(cfg2)), check=True, env=_env(), capture_output=True,
                         text=True)
    assert "resumed from" in out.stdout
    resumed = _log(run)
    assert [r["epoch"] for r in resumed] == [r["epoch"] for r in reference]
    for a, b in zip(reference, resumed, strict=True):
        for key in ("train_loss", "val_loss", "lr", "step"):
            assert float(a[key]) == pytest.approx(float(b[key]), rel=1e-6), key
    w_ref = read_checkpoint(tmp_path / "ref" / "last.pt")["state_dict"]
    w_res = read_checkpoint(run / "last.pt")["state_dict"]
    for key in w_ref:
        torch.testing.assert_close(w_ref[key], w_res[key], rtol=1e-5, atol=1e-7)


def test_ddp_two_processes_match_one_process(tmp_path, small_data):
    common = {"training": {"dtype": "float64", "max_epochs": 2}}
    one = _config(tmp_path, small_data, "one", **common)
    two = _config(tmp_path, small_data, "two", **common)
    subprocess.run(_cli("train", str(one)), check=True, env=_env(), capture_output=True)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node",
           "2", "-m", "emlpack.cli", "train", str(two)]
    res = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    a, b = _log(tmp_path / "one"), _log(tmp_path / "two")
    assert len(a) == len(b) == 2
    for ra, rb in zip(a, b, strict=True):
        for key in ("train_loss", "train_forces_mse", "val_loss", "val_forces_mae"):
            assert float(ra[key]) == pytest.approx(float(rb[key]), rel=1e-7), key
    w1 = read_checkpoint(tmp_path / "one" / "last.pt")["state_dict"]
    w2 = read_checkpoint(tmp_path / "two" / "last.pt")["state_dict"]
    for key in w1:
        torch.testing.assert_close(w1[key], w2[key], rtol=1e-6, atol=1e-9)


@pytest.mark.gpu
def test_a_run_on_the_gpu_matches_the_cpu_and_resumes_on_the_cpu(tmp_path, small_data):
    """float64 on the GPU follows the CPU's loss curve; its checkpoints (CPU tensors, optimizer
    state included) resume on the CPU as the CPU run goes on. Passed on an H200 (2026-11-28)."""
    assert torch.cuda.is_available(), "`pytest -m gpu` needs a CUDA GPU"
    common = {"training": {"dtype": "float64"}, "augmentation": {"enabled": True,
                                                                  "probability": 0.5}}
    cpu = load_config(_config(tmp_path, small_data, "cpu", **common),
                      ["training.max_epochs=4", "training.device=cpu"])
    train(cpu)
    gpu = load_config(_config(tmp_path, small_data, "gpu", **common),
                      ["training.max_epochs=2", "training.device=cuda"])
    train(gpu)
    state = read_checkpoint(tmp_path / "gpu" / "last.pt")
    assert all(t.device.type == "cpu" for t in state["state_dict"].values())
    train(load_config(tmp_path / "gpu.yaml", ["training.max_epochs=4", "training.device=cpu"]))
    a, b = _log(tmp_path / "cpu"), _log(tmp_path / "gpu")
    assert [r["epoch"] for r in b] == ["1", "2", "3", "4"]
    for ra, rb in zip(a, b, strict=True):
        for key in ("train_loss", "val_loss", "val_forces_mae", "lr", "step", "n_augmented"):
            assert float(ra[key]) == pytest.approx(float(rb[key]), rel=1e-6), key
    w_cpu = read_checkpoint(tmp_path / "cpu" / "last.pt")["state_dict"]
    w_gpu = read_checkpoint(tmp_path / "gpu" / "last.pt")["state_dict"]
    for key in w_cpu:
        torch.testing.assert_close(w_cpu[key], w_gpu[key], rtol=1e-6, atol=1e-9)


#: the tests' short-range family without SchNet's capabilities (tests/nn/helpers.py)
RADIAL = ["model.family=radial", "model.short_range.n_features=6"]


def test_another_family_trains_resumes_exactly_and_loads(tmp_path, small_data, caplog):
    """``model.family=radial`` on a SchNet config: the loss falls, a run stopped after
    epoch 2 and resumed ends as an uninterrupted one, and best.pt loads as that family."""
    import logging

    with caplog.at_level(logging.WARNING, logger="emlpack.train.config"):
        ref_cfg = load_config(_config(tmp_path, small_data, "ref"),
                              [*RADIAL, "training.max_epochs=3"])
    assert "are not used" in caplog.text  # the file's SchNet parameters
    train(ref_cfg)
    train(load_config(_config(tmp_path, small_data, "run"), [*RADIAL, "training.max_epochs=2"]))
    best = train(load_config(_config(tmp_path, small_data, "run"),
                             [*RADIAL, "training.max_epochs=3"]))
    a, b = _log(tmp_path / "ref"), _log(tmp_path / "run")
    assert float(a[-1]["val_loss"]) < float(a[0]["val_loss"])
    assert [r["epoch"] for r in a] == [r["epoch"] for r in b] == ["1", "2", "3"]
    for ra, rb in zip(a, b, strict=True):
        for key in ("train_loss", "val_loss", "step"):
            assert float(ra[key]) == pytest.approx(float(rb[key]), rel=1e-6), key
    model = load_model(best)
    assert model.config.family == "radial" and model.config.short_range["n_features"] == 6


def test_a_run_started_before_the_families_resumes(tmp_path, small_data):
    """A run whose last.pt was written in format 1 (flat model config in the checkpoint and in
    its training metadata, ``schnet.*`` weights) resumes with today's config of the same file
    (compared normalised) and ends as an uninterrupted run."""
    train(load_config(_config(tmp_path, small_data, "ref"), ["training.max_epochs=3"]))
    train(load_config(_config(tmp_path, small_data, "run"), ["training.max_epochs=2"]))
    for name in ("last.pt", "best.pt"):
        as_format_1(tmp_path / "run" / name)
    assert torch.load(tmp_path / "run" / "last.pt", weights_only=True)["format_version"] == 1
    train(load_config(_config(tmp_path, small_data, "run"), ["training.max_epochs=3"]))
    a, b = _log(tmp_path / "ref"), _log(tmp_path / "run")
    assert [r["epoch"] for r in b] == ["1", "2", "3"]
    for ra, rb in zip(a, b, strict=True):
        for key in ("train_loss", "val_loss", "step"):
            assert float(ra[key]) == pytest.approx(float(rb[key]), rel=1e-6), key
    # another model config is still refused
    with pytest.raises(ValueError, match="different 'model' config"):
        train(load_config(_config(tmp_path, small_data, "run"),
                          ["training.max_epochs=4", "model.short_range.n_rbf=4"]))


@pytest.mark.slow
def test_ddp_with_another_family_matches_one_process(tmp_path, small_data):
    """Data-parallel training of the tests' radial family (``torchrun``, 2 processes) follows
    the one-process run."""
    common = {"training": {"dtype": "float64", "max_epochs": 2}}
    one = _config(tmp_path, small_data, "one", **common)
    two = _config(tmp_path, small_data, "two", **common)
    cli = [sys.executable, "-m", "tests.train.families_cli", "train"]
    subprocess.run([*cli, str(one), *RADIAL], check=True, env=_env(), capture_output=True)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node",
           "2", "-m", "tests.train.families_cli", "train", str(two), *RADIAL]
    res = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    a, b = _log(tmp_path / "one"), _log(tmp_path / "two")
    assert len(a) == len(b) == 2
    for ra, rb in zip(a, b, strict=True):
        for key in ("train_loss", "train_forces_mse", "val_loss", "val_forces_mae"):
            assert float(ra[key]) == pytest.approx(float(rb[key]), rel=1e-7), key
    assert read_checkpoint(tmp_path / "two" / "best.pt")["config"]["family"] == "radial"


def test_ensemble_of_seeds_and_evaluation_table(tmp_path, small_data):
    from emlpack.train.evaluate import evaluate_models

    cfg = load_config(_config(tmp_path, small_data, "ens"), ["training.max_epochs=1"])
    paths = train_ensemble(cfg, [0, 1])
    assert [p.parent.name for p in paths] == ["seed0", "seed1"]
    w0 = read_checkpoint(paths[0])["state_dict"]
    w1 = read_checkpoint(paths[1])["state_dict"]
    assert not torch.equal(w0["short_range.embedding.weight"], w1["short_range.embedding.weight"])
    table, results = evaluate_models(paths, small_data, tmp_path / "eval", subset="val",
                                     max_structures=3, progress=False)
    assert "±" in table and "error rate" in table and "intrinsic variability" in table
    assert (tmp_path / "eval" / "parity.png").stat().st_size > 1000
    assert len(results["models"]) == 2
    assert np.isfinite(results["models"][0]["static"]["forces"]["mae"])


def test_snapshots_outlive_the_run_folder_and_resume_exactly(tmp_path, small_data):
    """A run on a "fresh machine" (its run folder gone) goes on from the newest snapshot and
    ends as an uninterrupted run does; older snapshots are removed; a grown data set is
    refused on resume."""
    ref = load_config(_config(tmp_path, small_data, "ref"), ["training.max_epochs=4"])
    train(ref)
    snaps = tmp_path / "snapshots"
    data = tmp_path / "data.xyz"  # a copy: grown at the end
    data.write_bytes(small_data.read_bytes())
    first = load_config(_config(tmp_path, data, "run"), [
        "training.max_epochs=2", f"output.snapshot_dir={snaps}", "output.snapshot_minutes=0"])
    train(first)
    kept = sorted(p.name for p in snaps.iterdir())
    assert len(kept) == 1 and kept[0].startswith("step-")  # the epoch-1 snapshot was removed
    assert sorted(p.name for p in (snaps / kept[0]).iterdir()) == ["best.pt", "last.pt",
                                                                    "log.csv"]
    before = _log(snaps / kept[0])
    import shutil

    shutil.rmtree(tmp_path / "run")  # the machine is gone; the snapshot folder stays
    again = load_config(_config(tmp_path, data, "run"), [
        "training.max_epochs=4", f"output.snapshot_dir={snaps}", "output.snapshot_minutes=0"])
    train(again)
    a, b = _log(tmp_path / "ref"), _log(tmp_path / "run")
    assert [r["epoch"] for r in b] == ["1", "2", "3", "4"]
    # epochs 1-2 were not trained again: their rows (timings included) come from the snapshot
    assert [r["epoch_time"] for r in b[:2]] == [r["epoch_time"] for r in before]
    for ra, rb in zip(a, b, strict=True):
        for key in ("train_loss", "val_loss", "lr", "step"):
            assert float(ra[key]) == pytest.approx(float(rb[key]), rel=1e-6), key
    w_ref = read_checkpoint(tmp_path / "ref" / "last.pt")["state_dict"]
    w_run = read_checkpoint(snaps / sorted(p.name for p in snaps.iterdir())[-1] / "last.pt")[
        "state_dict"]
    for key in w_ref:
        torch.testing.assert_close(w_ref[key], w_run[key], rtol=1e-5, atol=1e-7)

    write_structures(data, read_structures(small_data, index=":") * 2)
    with pytest.raises(ValueError, match="now holds 48"):
        train(load_config(tmp_path / "run.yaml", ["training.max_epochs=5"]))


def test_a_snapshot_removes_the_older_snapshots_and_keeps_a_newer_one(tmp_path, small_data):
    """A newer snapshot in the folder came from a machine that went further (a GPU): a run
    still at an older step keeps it, and takes it when started again."""
    from emlpack.train.trainer import Trainer

    snaps = tmp_path / "snapshots"
    (snaps / "step-000000100").mkdir(parents=True)
    (snaps / "step-000000010").mkdir()
    trainer = Trainer(load_config(_config(tmp_path, small_data, "run"),
                                  [f"output.snapshot_dir={snaps}"]))
    trainer._saved_step = 50
    trainer._snapshot()
    assert sorted(p.name for p in snaps.iterdir()) == ["step-000000050", "step-000000100"]
    trainer._saved_step = 150
    trainer._snapshot()
    assert sorted(p.name for p in snaps.iterdir()) == ["step-000000150"]


@pytest.mark.parametrize("stop", ["ctrl-c", "kill"])
def test_an_interrupted_run_leaves_a_snapshot_of_its_last_finished_epoch(tmp_path, small_data,
                                                                        monkeypatch, stop):
    """Ctrl-C, or ``kill PID`` (SIGTERM: how a session's background trainings are stopped),
    during epoch 3 leaves a snapshot of epoch 2; the SIGTERM handler is restored afterwards."""
    import os
    import signal

    from emlpack.train.trainer import Trainer

    snaps = tmp_path / "snapshots"
    cfg = load_config(_config(tmp_path, small_data, "run"), [
        "training.max_epochs=5", f"output.snapshot_dir={snaps}", "output.snapshot_minutes=1e6"])
    epoch = Trainer._train_epoch

    def interrupted(self):
        if self.epoch == 2:
            if stop == "kill":
                os.kill(os.getpid(), signal.SIGTERM)
            raise KeyboardInterrupt  # not reached after SIGTERM: its handler raises first
        return epoch(self)

    monkeypatch.setattr(Trainer, "_train_epoch", interrupted)
    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        train(cfg)
    assert signal.getsignal(signal.SIGTERM) == previous
    (snap,) = snaps.iterdir()
    state = read_checkpoint(snap / "last.pt")["metadata"]["training"]
    assert state["epoch"] == 2 and snap.name == f"step-{state['step']:09d}"
    assert [r["epoch"] for r in _log(snap)] == ["1", "2"]


def test_one_training_per_run_folder(tmp_path, small_data):
    """A second training in a folder whose training is still running is refused in one line
    (the two would overwrite each other's checkpoints); once the first ends, it runs."""
    import os

    from emlpack._files import try_lock
    from emlpack.train.config import ConfigError

    cfg = load_config(_config(tmp_path, small_data, "run"), ["training.max_epochs=1"])
    held = try_lock(tmp_path / "run" / "train.lock")  # as the running training holds it
    try:
        with pytest.raises(ConfigError, match="another training is running"):
            train(cfg)
        assert not (tmp_path / "run" / "last.pt").exists()
    finally:
        os.close(held)
    train(cfg)
    assert [r["epoch"] for r in _log(tmp_path / "run")] == ["1"]


def test_a_run_that_stopped_early_trains_no_more_when_resumed(tmp_path, small_data):
    # lr 0: the validation loss never improves after epoch 1, so patience 1 stops after epoch 2
    cfg = load_config(_config(tmp_path, small_data, "early"), [
        "training.max_epochs=6", "training.lr=0.0", "training.patience=1"])
    train(cfg)
    assert [r["epoch"] for r in _log(tmp_path / "early")] == ["1", "2"]
    train(cfg)  # e.g. the same study stage on a fresh clone, restored from a snapshot
    assert [r["epoch"] for r in _log(tmp_path / "early")] == ["1", "2"]


def test_init_weights_starts_a_fresh_run_from_a_checkpoint(tmp_path, small_data):
    """Fine-tuning: a run with ``training.init_weights`` starts from that checkpoint's weights
    (its first validation equals the source's at lr 0), with a fresh schedule and counters, on
    other data too; a checkpoint of another architecture is refused in one line; a run that
    resumes from its own last.pt ignores the setting."""
    source = train(load_config(_config(tmp_path, small_data, "source"),
                               ["training.max_epochs=2"]))
    src_last = read_checkpoint(source.parent / "last.pt")
    other = tmp_path / "other.xyz"
    write_structures(other, read_structures(small_data)[::2])
    cfg = load_config(_config(tmp_path, other, "tuned"),
                      [f"training.init_weights={source.parent / 'last.pt'}",
                       "training.max_epochs=1", "training.lr=0.0"])
    tuned = train(cfg)
    after = read_checkpoint(tuned.parent / "last.pt")
    for name, value in src_last["state_dict"].items():
        assert torch.equal(after["state_dict"][name], value), name
    assert after["metadata"]["training"]["epoch"] == 1  # counters start afresh
    # resuming its own run: the init is not applied again (epoch 1 -> 2 from last.pt)
    cfg2 = load_config(_config(tmp_path, other, "tuned"),
                       [f"training.init_weights={source.parent / 'last.pt'}",
                        "training.max_epochs=2", "training.lr=0.01"])
    train(cfg2)
    rows = _log(tuned.parent)
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    with pytest.raises(ValueError, match="n_features"):
        train(load_config(_config(tmp_path, other, "wide"),
                          [f"training.init_weights={source}", "model.n_features=24"]))


def test_pretrain_then_fine_tune_records_the_lineage(tmp_path, small_data):
    """Pretraining at a cheap level, then a fine-tune at the paper's level from its checkpoint
    (its own hydride reference, a frozen embedding): the fine-tune's checkpoints carry both
    stages, the frozen parameters stay at the pretrained values, a resume keeps the lineage, and
    ``lineage_lines`` (``emlp pretrained``) names both levels; a prefix naming no parameter is
    refused."""
    from emlpack.pretrained import lineage_lines

    frames = read_structures(small_data)
    cheap, paper = tmp_path / "cheap.xyz", tmp_path / "paper.xyz"
    write_structures(cheap, [f.copy(info={**f.info, "level": "pbe0/def2-svpd/grid1"})
                             for f in frames])
    write_structures(paper, [f.copy(info={**f.info, "level": "pbe0/aug-cc-pvtz"})
                             for f in frames[::2]])
    pre = train(load_config(_config(tmp_path, cheap, "pre"),
                            ["training.max_epochs=1"]))
    names = [n for n, _ in load_model(pre).named_parameters()]
    embedding = next(n for n in names if n.endswith("embedding.weight"))[: -len(".weight")]
    overrides = [f"training.init_weights={pre}", "training.max_epochs=1",
                 f"training.freeze=[{embedding}]"]
    tuned = train(load_config(_config(tmp_path, paper, "tuned"), overrides))
    meta = read_checkpoint(tuned.parent / "last.pt")["metadata"]
    lineage = meta["lineage"]
    assert [s["levels"] for s in lineage] == [["pbe0/def2-svpd/grid1"], ["pbe0/aug-cc-pvtz"]]
    assert [s["reference"] for s in lineage] == ["hydrides", "hydrides"]
    assert [s["n_train"] for s in lineage] == [18, 6]  # 0.75 of 24 and of 12 (rounded)
    assert lineage[1]["init_weights"] == str(pre) and lineage[1]["freeze"] == [embedding]
    before = read_checkpoint(pre)["state_dict"]
    after = read_checkpoint(tuned.parent / "last.pt")["state_dict"]
    assert torch.equal(before[f"{embedding}.weight"], after[f"{embedding}.weight"])
    assert any(not torch.equal(before[k], after[k]) for k in before if "embedding" not in k)
    text = lineage_lines(lineage)
    assert "trained on" in text[0] and "pbe0/def2-svpd/grid1" in text[0]
    assert "fine-tuned" in text[1] and "pbe0/aug-cc-pvtz" in text[1] and embedding in text[1]
    train(load_config(_config(tmp_path, paper, "tuned"), [*overrides[:1],
                                                         "training.max_epochs=2",
                                                         overrides[2]]))  # resumes
    again = read_checkpoint(tuned.parent / "last.pt")["metadata"]["lineage"]
    assert len(again) == 2 and again[1]["epoch"] == 2
    with pytest.raises(ValueError, match="names no parameter"):
        train(load_config(_config(tmp_path, paper, "bad"),
                          [f"training.init_weights={pre}", "training.freeze=[nothing]"]))


#: a stand-in for a cheap level's labels: eV per atom added to every energy, hydrides included
CHEAP_SHIFT = {1: 0.21, 6: -1.3, 7: 0.8, 8: -0.45}


def test_emlp_train_pretrains_on_a_cheap_set_and_fine_tunes_at_the_papers_level(
        tmp_path, capsys, monkeypatch):
    """``emlp train`` end to end on two data-set folders: a pretraining on a cheap-level set
    (its own hydride references at that level; a frozen shard list, so the run resumes while
    the set grows) and a fine-tune from its best.pt on a paper-level set (that set's hydride
    reference, fresh counters, a lower learning rate, a frozen embedding). The fine-tune's
    checkpoint records both stages (levels, shards, references); exported, the model card and
    ``emlp pretrained NAME`` show the lineage once. A shard that is not there is one line."""
    import shutil

    from emlpack import pretrained
    from emlpack.cli import main
    from emlpack.data.shards import read_shards
    from emlpack.pretrained import export_pretrained
    from tests.cli.helpers import run
    from tests.examples.eqm7_data import tiny_dataset

    cheap = tiny_dataset(tmp_path / "cheap", shards=2, level="pbe0/def2-svpd/grid1",
                         shift=CHEAP_SHIFT)
    paper = tiny_dataset(tmp_path / "paper")
    cfg = {k: dict(v) for k, v in TINY.items()}
    cfg["data"] = {"reference": "hydrides", "split": "auto"}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    later = (cheap / "shards" / "0001.h5").rename(tmp_path / "0001.h5")  # not labeled yet
    pre, tuned = tmp_path / "pre", tmp_path / "tuned"
    argv = ["train", str(path), f"data.path={cheap}", "data.shards=[0000.h5]",
            f"output.dir={pre}", "training.max_epochs=1"]
    rc, out, err = run(argv)
    assert rc == 0, err + out
    later.rename(cheap / "shards" / "0001.h5")  # the set grew; the run reads its own shards
    rc, out, err = run([*argv[:-1], "training.max_epochs=2"])
    assert rc == 0 and "resumed from" in out, err + out
    meta = read_checkpoint(pre / "best.pt")["metadata"]
    cheap_hydrides = read_shards(cheap).hydrides["energies"]
    assert meta["reference"]["energies"] == pytest.approx(cheap_hydrides)
    assert meta["n_structures"] == 24  # the 3 molecules of shard 0000, not the later shards
    names = [n for n, _ in load_model(pre / "best.pt").named_parameters()]
    embedding = next(n for n in names if n.endswith("embedding.weight"))[: -len(".weight")]
    rc, out, err = run(["train", str(path), f"data.path={paper}", f"output.dir={tuned}",
                        f"training.init_weights={pre / 'best.pt'}", "training.lr=2e-3",
                        f"training.freeze=[{embedding}]", "training.max_epochs=1"])
    assert rc == 0 and f"weights from {pre / 'best.pt'}" in out, err + out
    ckpt = read_checkpoint(tuned / "best.pt")
    meta = ckpt["metadata"]
    paper_hydrides = read_shards(paper).hydrides["energies"]
    assert meta["reference"]["energies"] == pytest.approx(paper_hydrides)
    assert not np.allclose(paper_hydrides, cheap_hydrides)
    assert meta["epoch"] == 1 and meta["config"]["training"]["lr"] == 2e-3
    lineage = meta["lineage"]
    assert [s["levels"] for s in lineage] == [["pbe0/def2-svpd/grid1"], ["pbe0/aug-cc-pvtz"]]
    assert [s["data_path"] for s in lineage] == [str(cheap), str(paper)]
    assert [s["shards"] for s in lineage] == [["0000.h5"], None]
    assert [s["reference"] for s in lineage] == ["hydrides", "hydrides"]
    assert lineage[0]["epoch"] == 2 and lineage[1]["init_weights"] == str(pre / "best.pt")
    assert torch.equal(ckpt["state_dict"][f"{embedding}.weight"],
                       read_checkpoint(pre / "best.pt")["state_dict"][f"{embedding}.weight"])
    # shipped: the card and `emlp pretrained NAME` show the lineage, once
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "shipped")
    export_pretrained([tuned / "best.pt"], tmp_path / "shipped" / "toy", "# toy\n")
    capsys.readouterr()
    assert main(["pretrained", "toy"]) == 0
    shown = capsys.readouterr().out
    assert shown.count("## Lineage") == 1 and shown.count("stage 1: trained on") == 1
    stage1 = next(line for line in shown.splitlines() if "stage 1:" in line)
    assert "shard 0000.h5" in stage1 and "pbe0/def2-svpd/grid1" in stage1
    stage2 = next(line for line in shown.splitlines() if "stage 2:" in line)
    assert "fine-tuned" in stage2 and "pbe0/aug-cc-pvtz" in stage2 and embedding in stage2
    shutil.rmtree(pre)
    rc, out, err = run([*argv[:3], "data.shards=[0000.h5, 0009.h5]", *argv[4:]])
    assert rc == 2 and len(err.strip().splitlines()) == 1, err + out
    assert "no shard(s) 0009.h5" in err
    rc, _, err = run([*argv[:3], "data.shards=0000.h5", *argv[4:]])
    assert rc == 2 and "data.shards must be null or a non-empty list" in err


def test_a_run_saved_before_a_data_key_existed_resumes(tmp_path, small_data):
    """A last.pt whose saved ``data`` section lacks a key added to the config since (here
    ``data.shards``) resumes: the missing key counts as its default."""
    from emlpack.nn.checkpoint import save_model

    cfg = load_config(_config(tmp_path, small_data, "old"), ["training.max_epochs=1"])
    train(cfg)
    last = tmp_path / "old" / "last.pt"
    payload = read_checkpoint(last)
    payload["metadata"]["config"]["data"].pop("shards")
    save_model(load_model(last), last, payload["metadata"])
    train(load_config(_config(tmp_path, small_data, "old"), ["training.max_epochs=2"]))
    assert [r["epoch"] for r in _log(tmp_path / "old")] == ["1", "2"]


def test_the_step_differentiates_every_parameter_and_nothing_else(tmp_path, small_data):
    """``Trainer._train_epoch`` differentiates the loss with respect to the optimizer's
    parameters only (``backward(inputs=...)``, which skips the positions' second derivatives):
    the list is every parameter of the model, and each gradient equals the plain backward's,
    bit for bit."""
    from emlpack.train.loss import combine, loss_terms, predict
    from emlpack.train.trainer import Trainer

    trainer = Trainer(load_config(_config(tmp_path, small_data, "step")))
    params = list(trainer.model.parameters())
    assert [id(p) for p in trainer.trained_parameters] == [id(p) for p in params]
    batch = next(iter(trainer._loader(0)))
    trainer.model.train()

    def gradients(inputs):
        pred = predict(trainer.model, batch, trainer.reference)
        loss = combine(loss_terms(pred, batch), trainer.weights)
        trainer.optimizer.zero_grad(set_to_none=True)
        loss.backward(inputs=inputs)
        return [p.grad.clone() for p in params]

    plain = gradients(None)
    only = gradients(trainer.trained_parameters)
    assert all(torch.equal(a, b) for a, b in zip(plain, only, strict=True))
    assert any(float(g.abs().max()) > 0 for g in only)


def test_the_cpu_budget_counts_over_resumes(tmp_path, small_data, caplog):
    """``training.max_cpu_minutes``: an epoch starts only while the CPU seconds of the run, kept
    in last.pt over resumes, are within the budget."""
    cfg = _config(tmp_path, small_data, "cpu", training={"max_epochs": 1})
    train(load_config(cfg))
    spent = read_checkpoint(tmp_path / "cpu" / "last.pt")["metadata"]["training"]["cpu_seconds"]
    assert spent > 0.0
    more = ["training.max_epochs=100000"]
    train(load_config(cfg, [*more, f"training.max_cpu_minutes={spent / 120.0}"]))
    assert len(_log(tmp_path / "cpu")) == 1  # the saved total already passes half of it
    budget = 3.0 * spent / 60.0
    with caplog.at_level(logging.INFO, logger="emlpack.train.trainer"):
        train(load_config(cfg, [*more, f"training.max_cpu_minutes={budget}"]))
    assert "stopped: CPU time limit" in caplog.text
    assert 1 < len(_log(tmp_path / "cpu")) < 100000
    total = read_checkpoint(tmp_path / "cpu" / "last.pt")["metadata"]["training"]["cpu_seconds"]
    assert total > spent


def test_the_learning_rate_decays_with_the_cpu_time(tmp_path, small_data):
    """``training.decay_cpu_minutes``: lr0 * factor ** (CPU seconds / decay), the CPU seconds
    of the run over resumes, so the rate falls with each epoch and goes on falling after a
    resume from where it was."""
    cfg = _config(tmp_path, small_data, "lr", training={"max_epochs": 2, "lr": 1e-3})
    decay = 0.01  # CPU minutes per halving: 0.6 s
    train(load_config(cfg, [f"training.decay_cpu_minutes={decay}"]))
    state = read_checkpoint(tmp_path / "lr" / "last.pt")["metadata"]["training"]
    rates = [float(r["lr"]) for r in _log(tmp_path / "lr")]
    assert rates[0] > rates[1]
    # the logged rate is that of the last step, a little before the CPU seconds were saved
    assert 1e-3 * 0.5 ** (state["cpu_seconds"] / (60 * decay)) <= rates[1] < 1e-3
    train(load_config(cfg, [f"training.decay_cpu_minutes={decay}", "training.max_epochs=3"]))
    assert float(_log(tmp_path / "lr")[2]["lr"]) < rates[1]
    with pytest.raises(Exception, match="decay_cpu_minutes must be a positive number"):
        load_config(cfg, ["training.decay_cpu_minutes=0"])
