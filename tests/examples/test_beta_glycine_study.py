"""examples/beta_glycine/run_study.py end to end with a fast fake labeler (an eMLP with
springs on a two-water crystal), so that the script cannot rot: the labeler's crystal
optimisation, labeling (resumable), FD reference tensors at its optimum, training, a
model-Hessian round, BO cell optimisation, the table."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from emlpack.calculators.labeler import ModelLabeler
from emlpack.data.store import DatasetStore
from emlpack.io.extxyz import write_structures
from emlpack.properties.optimize import optimize
from emlpack.properties.response import crystal_response
from tests.conftest import ROOT
from tests.nn.helpers import water_crystal
from tests.properties.toy import spring_model


def _load_study():
    spec = importlib.util.spec_from_file_location(
        "run_study", ROOT / "examples" / "beta_glycine" / "run_study.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def fake():
    s = water_crystal()
    model = spring_model(s, core_cutoff=3.5, pair_cutoff=2.0)
    res = optimize(model, s, fmax=1e-8)
    assert res.converged, res.reason
    return model, res.structure


def test_study_runs_end_to_end_and_resumes(tmp_path, fake):
    model, s = fake
    study_mod = _load_study()
    xyz = tmp_path / "crystal.xyz"
    write_structures(xyz, [s])
    cfg = study_mod.load_config(ROOT / "examples" / "beta_glycine" / "config.yaml", [
        f"input={xyz}", f"workdir={tmp_path / 'run'}", f"results_dir={tmp_path / 'out'}",
        f"dataset={tmp_path / 'dataset'}", "molecule_id=water-crystal",
        "reference.strain_step=0.001",
        "reference.field_step_au=0.0001",  # the spring model is very nonlinear in strong fields
        "rounds=[{round: 0, field: 3, stress: 3, sigma: 0.02, max_strain: 0.01,"
        " max_field_au: 0.001}, {round: 1, field: 2, stress: 2, hessian: model,"
        " temperature: 100, min_eigenvalue: 5.0, max_field_au: 0.001}]",
        # a 2-epoch model is about its random initialisation: with training seed 0 its true
        # BO minimum at the input has two lone pairs merged (found once relaxations checked
        # their neighbour list at the result; before, a stale list hid it), seed 1 has none
        "training.overrides=['model.n_features=8', 'model.n_filters=8', 'model.n_rbf=8',"
        " 'training.max_epochs=2', 'training.batch_size=8', 'model.elements=[1, 8]']",
        "training.seed=1", "training.members=1",
        "emlp.max_iterations=3", "emlp.fmax=1e-3", "emlp.smax=1e-4",
        "optimization.enabled=true", "optimization.fmax=0.02", "optimization.symprec=null",
    ])
    labeler = ModelLabeler(model, fmax=1e-8)
    lines = []
    with pytest.raises(SystemExit, match="optimize stage"):
        study_mod.run(["label"], cfg, labeler=labeler, log=lines.append)
    study = study_mod.run(["optimize"], cfg, labeler=labeler, log=lines.append)
    # the finite differences alone first (campaign_job.py label --reference-only)
    out = study_mod.stage_label(study, reference_only=True)
    assert out["new"] == 19 and out["failed"] == 0
    with DatasetStore(study.shard_store(0)) as store:
        assert sorted({k.split("/")[0] for k in store.keys()}) == ["opt", "ref-opt"]
    study_mod.run(["optimize", "label", "reference", "train", "sample", "label", "train",
                   "emlp", "table"], cfg, labeler=labeler, log=lines.append)
    opt = json.loads((tmp_path / "run" / "optimization.json").read_text())
    assert opt["converged"] and opt["max_force"] < 0.02
    with DatasetStore(tmp_path / "run" / "labels.h5") as store:
        keys = store.keys()
    n_opt = opt["steps"]
    assert sum(k.startswith("opt/") for k in keys) == n_opt
    assert sum(k.startswith("ref-opt/") for k in keys) == 19
    assert len(keys) == n_opt + 19 + 6 + 4 and len(set(keys)) == len(keys)
    # a second optimize replays the stored steps: nothing new
    study_mod.run(["optimize"], cfg, labeler=labeler, log=lines.append)
    assert json.loads((tmp_path / "run" / "optimization.json").read_text())["calculations"] == 0
    assert sum(k.startswith("r1/") for k in keys) == 4
    # resuming labels nothing twice, nor does a second shard (its own store)
    study_mod.run(["label"], cfg, labeler=labeler, log=lines.append)
    study_mod.run(["label"], cfg, labeler=labeler, log=lines.append, shard=(1, 2))
    with DatasetStore(tmp_path / "run" / "labels.h5") as store:
        assert len(store) == len(keys)
    with DatasetStore(tmp_path / "run" / "labels.1.h5") as store:
        assert len(store) == 0
    # the DFT column is the fake labeler's own clamped-ion physics (2-point central
    # differences at the study's steps: O(h^2) nonlinearity of the springs ~0.1 % at this step)
    result = json.loads((tmp_path / "out" / "results.json").read_text())
    rows = {r["quantity"]: r for r in result["rows"]}
    from emlpack.io.extxyz import read_structures

    optimum = read_structures(tmp_path / "run" / "optimized.xyz")[0]
    exact = crystal_response(model, optimum)
    for i in range(3):
        chi = exact.dielectric_clamped[i, i] - 1.0
        assert rows[f"eps{i + 1}{i + 1}"]["dft"] - 1.0 == pytest.approx(chi, rel=2e-3)
    c11 = exact.as_dict()["stiffness_clamped_ion_voigt_GPa"][0][0]
    assert rows["C11"]["dft"] == pytest.approx(c11, rel=2e-2)
    assert result["summary"]["n_configurations"] == len(keys)
    assert result["summary"]["n_fd_calculations"] == 19
    assert result["summary"]["n_optimization_steps"] == n_opt
    assert np.isfinite(rows["a"]["emlp_clamped"])
    md = (tmp_path / "out" / "results.md").read_text()
    assert "| C66 |" in md and "targets within tolerance" in md
    # campaign_job.py on a fresh machine: the labels live on in committed shards only
    import shutil
    import sys

    sys.path.insert(0, str(ROOT / "examples" / "beta_glycine"))
    before = {k: sys.modules.get(k) for k in ("run_study", "campaign_job")}
    try:
        import campaign_job
    finally:  # no "run_study" left behind for the eqm7 scripts of the same name
        sys.path.pop(0)
        for k, v in before.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    study = study_mod.Study(cfg, labeler=labeler, log=lines.append)
    with DatasetStore(tmp_path / "run" / "labels.h5", "a") as store:
        campaign_job.Exporter(study, 0.0, False, "test").flush(store)
        campaign_job.Exporter(study, 0.0, False, "test").flush(store)  # nothing new: no shard
    shards = list((tmp_path / "dataset" / "shards").glob("*.h5"))
    assert len(shards) == 1
    card = (tmp_path / "dataset" / "README.md").read_text()
    assert f"- {len(keys)} configurations in 1 shards" in card and "| opt |" in card
    shutil.rmtree(tmp_path / "run")
    assert campaign_job.restore(tmp_path / "dataset", tmp_path / "run" / "labels.h5",
                                "opt") == n_opt
    study_mod.run(["optimize", "label"], cfg, labeler=labeler, log=lines.append)
    assert json.loads((tmp_path / "run" / "optimization.json").read_text())["calculations"] == 0
    with DatasetStore(tmp_path / "run" / "labels.h5") as store:
        assert len(store) == n_opt  # the replayed steps only: nothing labeled again
    assert len(study_mod.Study(cfg, log=lines.append).records()) == len(keys)


# ---------------------------------------------------------------------- ensemble and table
#: two-epoch models of a few hundred parameters (compiled step off: no minute of compilation)
TINY = ["model.n_features=8", "model.n_filters=8", "model.n_rbf=8", "model.n_interactions=2",
        "training.max_epochs=2", "training.batch_size=8", "model.elements=[1, 8]",
        "training.compile=false", "training.max_time_minutes=null", "training.threads=1"]
TINY_PAINN = ["model.short_range.n_features=8", "model.short_range.n_rbf=8",
              "model.short_range.n_interactions=1", "training.max_epochs=2",
              "training.batch_size=8", "model.elements=[1, 8]", "training.compile=false",
              "training.max_time_minutes=null", "training.threads=1"]


@pytest.fixture(scope="module")
def labeled(tmp_path_factory, fake):
    """A labeled workdir (the 19 FD calculations and 4 round-0 samples at the fake labeler's
    optimum, the DFT tensors) shared by the ensemble tests: each copies it."""
    model, s = fake
    study_mod = _load_study()
    root = tmp_path_factory.mktemp("bg-labeled")
    write_structures(root / "crystal.xyz", [s])
    overrides = [
        f"input={root / 'crystal.xyz'}", f"dataset={root / 'dataset'}",
        "molecule_id=water-crystal", "reference.strain_step=0.001",
        "reference.field_step_au=0.0001", "optimization.enabled=false", "progress=false",
        "rounds=[{round: 0, field: 2, stress: 2, sigma: 0.02, max_strain: 0.01,"
        " max_field_au: 0.001}]",
    ]
    cfg = study_mod.load_config(ROOT / "examples" / "beta_glycine" / "config.yaml",
                                [*overrides, f"workdir={root / 'run'}"])
    labeler = ModelLabeler(model, fmax=1e-8)
    study_mod.run(["label", "reference"], cfg, labeler=labeler, log=lambda m: None)
    return study_mod, root, overrides, labeler


def _config(labeled, tmp_path, *extra):
    import shutil

    study_mod, root, overrides, _ = labeled
    shutil.copytree(root / "run", tmp_path / "run")
    return study_mod.load_config(ROOT / "examples" / "beta_glycine" / "config.yaml", [
        *overrides, f"workdir={tmp_path / 'run'}", f"results_dir={tmp_path / 'out'}",
        "emlp.max_iterations=1", "emlp.fmax=1e-3", "emlp.smax=1e-4", "emlp.verbose=false",
        "training.members=1", *extra])


def test_tolerances_are_the_issues_22_targets():
    study_mod = _load_study()
    assert len(study_mod.TOLERANCES) == 22
    ok = study_mod.within_tolerance
    assert ok("a", 5.0, 5.09) and not ok("a", 5.0, 5.11)
    assert ok("eps11", 2.0, 2.19) and not ok("eps11", 2.0, 2.21)
    assert ok("C66", 4.0, 4.59) and not ok("C66", 4.0, 4.61) and ok("C12", 1.0, 9.0) is None
    # e: 25 % or 0.02 C/m^2, whichever is larger
    assert ok("e34", 0.01, 0.029) and not ok("e34", 0.01, 0.031)
    assert ok("e16", 0.24, 0.299) and not ok("e16", 0.24, 0.301)
    count = study_mod.tolerance_count({"a": 5.0, "eps11": 2.0}, {"a": 5.0, "eps11": 3.0})
    assert count["within"] == ["a"] and count["outside"] == ["eps11"]
    assert count["n_within"] == 1 and count["n_targets"] == 22 and len(count["missing"]) == 20


def test_ensemble_train_emlp_table_spread_resume_and_warning(tmp_path, labeled):
    """Two tiny members (seeds 1, 2) -> per-member eMLP values -> the table's mean and
    spread; re-running train retrains nothing; a member copied over the other gives spread 0;
    a BO cell optimisation cut at one iteration is a warning in emlp.json and results.md; the
    learning curve's model on the first 12 configurations counts its targets."""
    import shutil

    study_mod, _, _, labeler = labeled
    cfg = _config(labeled, tmp_path, "training.members=2", "training.seed=1",
                  f"training.overrides={TINY}", "learning_curve=[12, 1000]")
    lines = []
    study_mod.run(["train", "emlp", "curve", "table"], cfg, labeler=labeler, log=lines.append)
    study = study_mod.Study(cfg, labeler=labeler, log=lines.append)
    dirs = study_mod.member_dirs(study)
    assert [d.name for d in dirs] == ["seed1", "seed2"] and dirs[0].parent.name == "schnet"
    assert all((d / "best.pt").exists() and (d / "done.json").exists() for d in dirs)
    result = json.loads((tmp_path / "out" / "results.json").read_text())
    members = result["emlp"]["members"]
    assert [m["seed"] for m in members] == [1, 2]
    rows = {r["quantity"]: r for r in result["rows"]}
    cols = [study_mod.emlp_columns(m) for m in members]
    for col in study_mod.COLUMNS:
        assert f"{col}_std" in rows["eps11"]
    # mean and spread (population std) are the members' (neither optimisation converged: the
    # optimised-cell columns take both, flagged)
    for col, name in (("emlp_clamped", "a"), ("emlp_clamped", "eps11"),
                      ("emlp_clamped", "C11"), ("emlp_relaxed_ion", "C11"),
                      ("emlp_relaxed_ion", "e14")):
        values = [c[col][name] for c in cols]
        assert rows[name][col] == pytest.approx(np.mean(values))
        assert rows[name][f"{col}_std"] == pytest.approx(np.std(values))
        assert rows[name][f"{col}_std"] > 0  # two seeds, two models
    # at the DFT geometry a two-epoch model's pairs may not relax (merged, a saddle): that
    # member is left out of the column, with a warning
    at_dft = [c["emlp_clamped_at_dft_geometry"].get("eps11") for c in cols]
    kept = [v for v in at_dft if v is not None]
    assert rows["eps11"]["emlp_clamped_at_dft_geometry"] == (
        pytest.approx(np.mean(kept)) if kept else None)
    assert sum("at the DFT geometry" in w for w in result["summary"]["warnings"]) == (
        len(at_dft) - len(kept))
    # the non-converged optimisations: warned about in the output and the table
    assert not any(o["converged"] for o in result["summary"]["emlp_optimisation"])
    warnings = result["summary"]["warnings"]
    assert sum("NOT converged" in w for w in warnings) == 2
    assert any("NON-STATIONARY" in w for w in warnings)
    assert sum("WARNING" in m and "NOT converged" in m for m in lines) >= 2
    md = (tmp_path / "out" / "results.md").read_text()
    assert "**Warnings:**" in md and md.count("NOT converged") >= 2 and " ± " in md
    assert "targets within tolerance" in md
    tol = result["summary"]["tolerance"]
    assert tol["emlp_clamped"]["n_targets"] == 22
    assert tol["emlp_clamped_at_dft_geometry"]["n_targets"] == 17
    assert tol["emlp_clamped"]["n_within"] == sum(
        bool(r["within_tolerance"]) for r in result["rows"])
    # the learning curve: 12 configurations (1000 is more than there are), then all (member 0)
    curve = result["summary"]["learning_curve"]
    n_all = result["summary"]["n_training_configurations"]
    assert [p["n_configurations"] for p in curve] == [12, n_all] and curve[1]["all"]
    assert "## Learning curve" in md and f"| {n_all} (all) |" in md
    with DatasetStore(dirs[0].parent / "curve-n12" / "train_data.h5") as store:
        subset = sorted(s.info["key"] for s in store)
    with DatasetStore(tmp_path / "run" / "train_data.h5") as store:
        keys = [s.info["key"] for s in store]
    assert subset == sorted(keys[k] for k in study_mod.subset_order(keys, 0)[:12])
    # resumable: a finished member is not retrained (nor the emlp stage recomputed)
    stamps = [(d / "best.pt").stat().st_mtime_ns for d in dirs]
    lines.clear()
    study_mod.run(["train", "emlp"], cfg, labeler=labeler, log=lines.append)
    assert [(d / "best.pt").stat().st_mtime_ns for d in dirs] == stamps
    assert sum("not retrained" in m for m in lines) == 2
    assert sum("done before" in m for m in lines) == 2
    # two identical members: spread 0
    shutil.rmtree(dirs[1])
    shutil.copytree(dirs[0], dirs[1])
    study_mod.run(["emlp", "table"], cfg, labeler=labeler, log=lines.append)
    result = json.loads((tmp_path / "out" / "results.json").read_text())
    for r in result["rows"]:
        for col in study_mod.COLUMNS:
            assert r[f"{col}_std"] in (None, 0.0), (r["quantity"], col)


def test_painn_member_and_fine_tune_on_the_crystal(tmp_path, labeled):
    """``training.family=painn``: a PaiNN member trains on the periodic data (stress in the
    loss) and gives tensors; ``training.init_from`` fine-tunes from its checkpoint (the
    architecture the checkpoint's, the folder ``painn-ft``)."""
    study_mod, _, _, labeler = labeled
    cfg = _config(labeled, tmp_path, "training.family=painn",
                  f"training.overrides={TINY_PAINN}")
    study_mod.run(["train", "emlp"], cfg, labeler=labeler, log=lambda m: None)
    study = study_mod.Study(cfg, labeler=labeler, log=lambda m: None)
    (first,) = study_mod.member_dirs(study)
    assert first.parent.name == "painn"
    emlp = json.loads((tmp_path / "run" / "emlp.json").read_text())
    assert emlp["family"] == "painn"
    import csv

    log = list(csv.DictReader((first / "log.csv").open()))
    assert np.isfinite(float(log[-1]["val_stress_mae"]))  # stress in the loss
    opt = emlp["members"][0]["optimized"]  # at the model's own cell: Ewald, cell gradients
    for key in ("dielectric_ion_clamped", "stiffness_voigt_GPa", "piezo_e_voigt_C_per_m2"):
        assert np.isfinite(np.array(opt[key])).all(), key
    tuned = study_mod.load_config(ROOT / "examples" / "beta_glycine" / "config.yaml", [
        *labeled[2], f"workdir={tmp_path / 'run'}", f"training.init_from={first / 'best.pt'}",
        "training.members=1", "training.family=null",  # the start's family
        "training.overrides=['training.max_epochs=1', 'training.compile=false',"
        " 'training.threads=1', 'training.batch_size=8']"])
    study_mod.run(["train"], tuned, labeler=labeler, log=lambda m: None)
    (member,) = study_mod.member_dirs(study_mod.Study(tuned, labeler=labeler,
                                                      log=lambda m: None))
    assert member.parent.name == "painn-ft"
    done = json.loads((member / "done.json").read_text())
    assert done["init_weights"] == str(first / "best.pt") and done["family"] == "painn"
    # a pretrained name resolves to its members (member k starts from the (k mod n)-th)
    named = dict(tuned, training={**tuned["training"], "init_from": "mini-eqm7"})
    files = study_mod._init_files(study_mod.Study(named, labeler=labeler, log=lambda m: None))
    assert len(files) == 4 and files[0].name == "model-0.pt"
