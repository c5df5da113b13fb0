"""The mini-eQM7 study pipeline (examples/eqm7/run_study.py) end to end on a tiny setting.

A tiny sharded data set (the card's layout: molecules.csv + shards/0000.h5 with the hydride
references) is built in a temporary folder from the shared eQM7 subset (the authors' PBE0 labels
of six molecules, 8 configurations each); 2 models per group, a very small model, 2 epochs,
DFT at the ``tiny`` level for the one test molecule (methane) and, statically, for ethyne as the
second test set's molecule, 14 MD steps. Every stage must
write its outputs, the numbers must be finite and consistent, and re-running must redo nothing.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT, require
from tests.examples.eqm7_data import PER_MOLECULE, example_module, study_module, tiny_dataset


@pytest.fixture(scope="module")
def study_run(tmp_path_factory):
    require("pyscf")
    mod = study_module()
    root = tmp_path_factory.mktemp("eqm7")
    data = tiny_dataset(root / "data")
    overrides = [
        f"data={data}", f"workdir={root / 'work'}", f"results_dir={root / 'results'}",
        "status=preliminary",  # a final config.yaml would export into the package
        "seeds=[0, 1]",
        "train.model.n_features=8", "train.model.n_filters=8", "train.model.n_rbf=8",
        "train.model.n_interactions=1", "train.training.max_epochs=2", "training.steps=null",
        "train.training.batch_size=8", "train.training.lr=0.005",
        "train.training.max_time_minutes=null", "train.training.eval_batch_size=64",
        "evaluate.max_structures=4", "evaluate.max_structures_second=3",
        # one of the second set's molecules gets a static DFT reference (its polarizability)
        "evaluate.second_test_set_molecules={qm7-0003: '[H]C#C[H]'}",
        "dft.level=tiny", "dft.boys_starts=1", "dft.fmax=0.05", "dft.max_steps=30",
        "ir.max_iterations=30", "ir.fmax=0.001",
        "md.time_fs=7.0", "md.checkpoint_every=7", "md.log_every=7",
        "export.spread_min_configurations=5",  # the validation molecule's 8 configurations
        f"training.snapshots={root / 'snapshots'}",  # not a git repository: nothing committed
    ]
    cfg = mod.load_config(ROOT / "examples" / "eqm7" / "config.yaml", overrides)
    lines: list[str] = []
    study = mod.run(["all"], cfg, log=lines.append)
    return mod, cfg, study, root, lines


def test_every_stage_writes_its_outputs(study_run):
    mod, cfg, study, root, _ = study_run
    work = root / "work"
    assert study.work == {"train": 4, "evaluate": 8 if "pbe0_subset" in mod.test_sets(study)
                          else 4, "dft": 3, "polarizability": 8, "ir": 4, "md": 4, "table": 1,
                          "export": 1}
    for group in ("aug", "noaug"):
        for seed in (0, 1):
            run = work / "models" / group / f"seed{seed}"
            assert (run / "best.pt").exists() and (run / "done.json").exists()
            (snap,) = (root / "snapshots" / group / f"seed{seed}").iterdir()  # the final one
            assert (snap / "best.pt").read_bytes() == (run / "best.pt").read_bytes()
            saved = (run / "config.yaml").read_text()
            assert f"enabled: {'true' if group == 'aug' else 'false'}" in saved
            name = f"{group}-s{seed}"
            assert (work / "eval" / "test" / f"{name}.json").exists()
            assert (work / "polarizability" / f"{name}.json").exists()
            second = json.loads((work / "polarizability" / "pbe0_subset" / f"{name}.json")
                                .read_text())
            assert second["set"] == "pbe0_subset" and list(second["molecules"]) == ["qm7-0003"]
            assert (work / "ir" / f"{name}.json").exists()
            assert (work / "md" / name / "methane" / "analysis.json").exists()
            assert (work / "md" / name / "methane" / "trajectory.xyz").exists()
    refs = root / "data" / "references" / "pbe0_sto-3g"
    dft = json.loads((refs / "methane.json").read_text())  # static: optimum, fields
    assert dft["level"] == "pbe0/sto-3g" and "frequencies_cm-1" not in dft
    dft.update(json.loads((refs / "methane.ir.json").read_text()))  # harmonic: Hessian, IR
    assert mod.dft_results(study)["methane"] == dft
    ethyne = json.loads((refs / "qm7-0003.json").read_text())  # the second set: static only
    assert ethyne["numbers"] == [6, 6, 1, 1] and not (refs / "qm7-0003.ir.json").exists()
    assert list(mod.dft_results(study, "pbe0_subset")) == ["qm7-0003"]
    assert list(mod.dft_results(study)) == ["methane"]  # the sets do not mix
    # no campaign preparation in this data set: the start is prepared here (GFN2-xTB)
    assert dft["start_geometry"] == "prepared for the reference (gfn2-xtb)"
    assert (refs / "methane" / "start.npz").exists()
    assert dft["optimisation"]["converged"]
    alpha = np.array(dft["polarizability_bohr3"])
    assert np.all(np.linalg.eigvalsh(alpha) > 0)  # a positive polarizability (sign convention)
    freqs = np.array(dft["frequencies_cm-1"])
    assert len(freqs) == 3 * 5 - 6 and np.all(freqs > 500)  # a minimum: real frequencies
    assert np.all(np.array(dft["intensities_km_per_mol"]) >= 0)
    result = json.loads((root / "results" / "results.json").read_text())
    md = (root / "results" / "results.md").read_text()
    # the table draws the figures of its own models beside results.md (committed with it)
    for name in ("figure3_md.png", "figure3_series.png", "figure4_ir.png"):
        assert (root / "results" / name).stat().st_size > 1000
        assert f"![{name}]({name})" in md
        assert not (work / name).exists()
    shown = result["figures"]
    assert shown["figure4_ir.png"] == [
        "methane: DFT (pbe0/sto-3g)", "methane: eMLP augmented (mean of 2)",
        "methane: eMLP non-augmented (mean of 2)"]
    assert [c.split(":")[0] for c in shown["figure3_md.png"]] == ["augmented", "non-augmented"]
    assert "Table 2" in md and "Table 3" in md and "Targets of issue 15" in md
    assert "4.45 (± 0.11)" in md  # the paper's numbers beside ours
    assert md.count("molecules with a DFT reference") == 2  # both sets' polarizabilities


def _finite(x, path="results"):
    if isinstance(x, dict):
        for k, v in x.items():
            _finite(v, f"{path}.{k}")
    elif isinstance(x, list):
        for k, v in enumerate(x):
            _finite(v, f"{path}[{k}]")
    elif isinstance(x, float):
        assert math.isfinite(x), path


def test_results_are_finite_and_consistent(study_run):
    mod, cfg, study, root, _ = study_run
    res = json.loads((root / "results" / "results.json").read_text())
    assert res["data"]["configurations"] == 6 * PER_MOLECULE
    assert res["data"]["hydrides"] is True
    ev = res["evaluation"]["test"]
    _finite(ev)
    for group in ("aug", "noaug"):
        g = ev["groups"][group]
        per_model = [json.loads((root / "work" / "eval" / "test" / f"{n}.json").read_text())
                     for n in g["models"]]
        assert len(per_model) == 2
        for stat in ("mae", "median"):
            for key in ("energy", "forces", "pair_forces"):
                v = np.array([m["static"][key][stat] for m in per_model])
                entry = g["static"][stat][key]
                assert entry["mean"] == pytest.approx(v.mean())
                assert entry["std"] == pytest.approx(v.std(ddof=1))
        rates = np.array([m["dynamic"]["error_rate"] for m in per_model])
        assert g["dynamic"]["error_rate"]["mean"] == pytest.approx(rates.mean())
    pol = res["polarizability"]
    assert pol["n_molecules"] == 1 and math.isfinite(pol["intrinsic_mae"])
    for g in pol["groups"].values():
        rates = [m["error_rate"] for m in g["per_model"].values()]
        assert g["error_rate"]["mean"] == pytest.approx(np.mean(rates))
        maes = [m["mae"] for m in g["per_model"].values() if m["mae"] is not None]
        if maes:
            assert g["mae"]["mean"] == pytest.approx(np.mean(maes))
    second = res["polarizability_pbe0_subset"]
    assert second["n_molecules"] == 1
    for g in second["groups"].values():  # the second set's file, against its reference
        ref = np.array(json.loads((root / "data" / "references" / "pbe0_sto-3g" / "qm7-0003.json")
                                  .read_text())["polarizability_bohr3"])
        maes = []
        for n in g["per_model"]:
            row = json.loads((root / "work" / "polarizability" / "pbe0_subset" / f"{n}.json")
                             .read_text())["molecules"]["qm7-0003"]
            if not row["failure"]:
                maes.append(np.abs(np.array(row["polarizability_bohr3"]) - ref).mean())
        if maes:
            assert g["mae"]["mean"] == pytest.approx(np.mean(maes))
    md = res["md"]
    assert sum(g["runs"] for g in md["groups"].values()) == 4
    for g in md["groups"].values():
        assert g["stable"] + g["transition"] + g["unstable"] == g["runs"]
    assert len(res["targets"]) == 5
    # the setup beside the paper's (why the numbers differ): each model's own run folder
    for name, setup in res["training_setup"].items():
        rows = (root / "work" / "models" / name.split("-")[0] / f"seed{name[-1]}" / "log.csv")\
            .read_text().splitlines()
        assert setup["n_features"] == 8 and setup["n_interactions"] == 1
        assert setup["steps"] == int(rows[-1].split(",")[1]) > 0 and setup["hours"] > 0
    text = (root / "results" / "results.md").read_text()
    assert "- **Architecture.** F=8, G=8, N=8, T=1" in text
    assert f"{6 * PER_MOLECULE} configurations of 6 molecules" in text
    assert all(t["met"] in (True, False, None) for t in res["targets"])


def test_export_ships_the_augmented_ensemble_with_its_card(study_run):
    """A preliminary study exports into the work folder (never into the package); the export
    loads by name, holds the augmented models and a card quoting the measured errors."""
    from emlpack.calculators.ensemble import load_pretrained
    from emlpack.pretrained import PRETRAINED_DIR, model_card

    mod, cfg, study, root, _ = study_run
    folder = root / "work" / "pretrained"
    ensemble = load_pretrained("mini-eqm7", root=folder)
    assert len(ensemble.members) == 2
    card = model_card("mini-eqm7", folder)
    shipped = PRETRAINED_DIR / "mini-eqm7" / "card.md"
    assert not shipped.exists() or shipped.read_text() != card  # the package is untouched
    result = json.loads((root / "results" / "results.json").read_text())
    mae = result["evaluation"]["test"]["groups"]["aug"]["static"]["mae"]["forces"]["mean"]
    assert f"{1000 * mae:.1f}" in card            # the measured core-force MAE is quoted
    assert "PBE0/aug-cc-pVTZ" in card and "How to cite" in card and "Domain" in card
    assert "Status: **preliminary**" in card and "**Preliminary.**" in card
    n_train = result["data"]["by_split"]["train"]["configurations"]
    assert f"(seeds 0, 1; 2 epochs over {n_train} training configurations;" in card
    # and every calculation with it says so, with the measured error
    assert all(m.notice and "preliminary" in m.notice and f"{1000 * mae:.0f} meV/Å" in m.notice
               for m in ensemble.members)
    # the largest training molecule: in the card and in every member (the calculator's check)
    size = result["data"]["train_domain"]["max_heavy_atoms"]
    assert size >= 1 and ensemble.max_heavy_atoms == size
    assert f"training molecules have at most {size} heavy atoms" in card
    # the spread warnings: calibrated on the validation molecule, the same in every member
    cal = ensemble.members[0].spread_calibration
    n_val = result["data"]["by_split"]["val"]["configurations"]
    assert cal["configurations"] + cal["failed"] == n_val and cal["members"] == 2
    assert all(m.spread_calibration == cal for m in ensemble.members)
    assert ensemble.spread_thresholds.energy == cal["energy_eV_per_atom"]
    assert f"exceeds {cal['energy_eV_per_atom']:.4f} eV/atom (energy)" in card
    assert "of the test molecules they warn on" in card


def test_models_on_the_complete_data_set_carry_no_notice_and_say_what_is_pending(study_run):
    """A study still in progress whose models trained on the complete data set: no
    preliminary notice on every calculation; the card says what is still computed and on how
    much each line was measured."""
    mod, cfg, study, root, _ = study_run
    result = json.loads((root / "results" / "results.json").read_text())
    assert result["data"]["complete"] is None  # the tiny folder has no campaign settings
    assert mod.preliminary_notice(result, "mini-eqm7", "aug")
    result["data"]["complete"] = True
    assert mod.preliminary_notice(result, "mini-eqm7", "aug") is None
    result["ir"]["n_molecules"] = 0 if not result["ir"].get("n_molecules") else 1
    result["data"]["by_split"]["test"]["molecules"] = 2
    card = mod.model_card(result, "mini-eqm7", "aug", 3)
    assert "**Study in progress.** Trained on the complete data set" in card
    assert "**Preliminary.**" not in card
    md = result["md"]["groups"]["aug"]
    assert f"(members 0, 1 of 3 so far): {md['runs']} runs" in card
    if result["ir"]["n_molecules"]:
        assert "over the 1 of 2 test molecules with a DFT Hessian so far" in card
    assert ("(every member's MD, the IR frequencies of every test molecule) are still being"
            " computed") in card
    # every member's MD and every molecule's Hessian finished: the card no longer lists them
    result["ir"]["n_molecules"] = 2
    card = mod.model_card(result, "mini-eqm7", "aug", 2)
    assert "still being computed" not in card
    assert "The study's final export replaces this card" in card
    assert "so far)" not in card and "with a DFT Hessian so far" not in card
    # the final study's card keeps the caution (the same errors), without the pending list
    result["status"] = "final"
    card = mod.model_card(result, "mini-eqm7", "aug", 2)
    assert "**Accuracy.** Trained on the complete data set" in card
    assert "several times the paper's" in card and "Study in progress" not in card
    assert "Status: **final**" in card


def test_dft_plan_finishes_the_figure_molecules_then_polarizabilities_then_hessians():
    mod = study_module()
    rows = [{"name": n} for n in ("a", "fig2", "b", "fig1")]
    plan = [(r["name"], part) for r, part in mod.dft_plan(rows, ["fig1", "fig2"])]
    assert plan == [("fig2", "static"), ("fig2", "ir"), ("fig1", "static"), ("fig1", "ir"),
                    ("a", "static"), ("b", "static"), ("a", "ir"), ("b", "ir")]
    # the second test set's molecules: static references only, before the Hessians
    plan = [(r["name"], part) for r, part in mod.dft_plan(rows, ["fig1", "fig2"], [{"name": "c"}])]
    assert plan[4:] == [("a", "static"), ("b", "static"), ("c", "static"), ("a", "ir"),
                        ("b", "ir")]
    # the Hessians cheapest first (the IR MAE covers the most molecules soonest); an unknown
    # cost (no static reference yet) last
    rows = [{"name": n} for n in ("a", "b", "c", "d", "fig1")]
    cost = {"a": 5.0, "b": None, "c": 1.0, "d": 3.0}
    plan = [(r["name"], part) for r, part in mod.dft_plan(rows, ["fig1"], ir_cost=cost.get)]
    assert plan[2:] == [("a", "static"), ("b", "static"), ("c", "static"), ("d", "static"),
                        ("c", "ir"), ("d", "ir"), ("a", "ir"), ("b", "ir")]


def test_groups_restrict_training_to_the_chosen_group(study_run):
    """``groups=[aug]`` (the shipped ensemble alone) lists, trains and evaluates only the
    augmented models; an unknown group name is one clear error."""
    mod, cfg, study, root, _ = study_run
    only = mod.Study(mod.load_config(ROOT / "examples" / "eqm7" / "config.yaml",
                                     [f"data={root / 'data'}", f"workdir={root / 'work'}",
                                      "seeds=[0, 1]", "groups=[aug]"]), log=lambda m: None)
    assert list(only.groups()) == ["aug"]
    assert {group for group, _, _ in only.models()} == {"aug"}
    assert len(only.models()) == 2
    bad = mod.Study(mod.load_config(ROOT / "examples" / "eqm7" / "config.yaml",
                                    [f"workdir={root / 'work'}", "groups=[augmented]"]),
                    log=lambda m: None)
    with pytest.raises(SystemExit, match="unknown"):
        bad.groups()


def test_a_table_of_one_group_shows_that_group_alone(study_run, tmp_path):
    """The shipped ensemble's table (``groups=[aug]``) draws its figures from the augmented
    models only, and the study's table both groups, whichever stage ran last (the figures
    were once drawn by the ir and md stages, so a run on one group replaced the study's)."""
    mod, cfg, _, root, _ = study_run
    only = mod.Study(dict(cfg, groups=["aug"]), log=lambda m: None)
    result = mod.stage_table(only, tmp_path)
    shown = result["figures"]
    assert shown["figure4_ir.png"] == ["methane: DFT (pbe0/sto-3g)",
                                       "methane: eMLP augmented (mean of 2)"]
    assert [c.split(":")[0] for c in shown["figure3_md.png"]] == ["augmented"]
    assert all(label.startswith("aug-") for label in shown["figure3_series.png"])
    study = json.loads((root / "results" / "results.json").read_text())
    assert "non-augmented" in " ".join(study["figures"]["figure4_ir.png"])


def test_the_notes_under_the_title_come_from_notes_or_a_committed_file(study_run, tmp_path):
    """``notes_file`` (the shipped tables' ``shipped/notes.md``) wins over ``notes``; a
    missing file stops the table with its name."""
    mod, cfg, _, _, _ = study_run
    notes = tmp_path / "notes.md"
    notes.write_text("The shipped ensemble,\nwrapped over two lines.\n")
    for extra, first in (({"notes": "Inline notes."}, "Inline notes."),
                         ({"notes": "Inline notes.", "notes_file": str(notes)},
                          "The shipped ensemble,")):
        mod.stage_table(mod.Study(dict(cfg, **extra), log=lambda m: None), tmp_path / "out")
        lines = (tmp_path / "out" / "results.md").read_text().splitlines()
        assert lines[4] == first
    assert mod.study_notes({"notes": None}) == ""
    with pytest.raises(SystemExit, match="gone.md: no such file"):
        mod.study_notes({"notes_file": str(tmp_path / "gone.md")})
    shipped = ROOT / "examples" / "eqm7" / "shipped"
    assert (shipped / "notes.md").read_text().strip() in (shipped / "results.md").read_text()


def test_a_failed_ir_optimisation_is_excluded_and_listed(study_run, tmp_path):
    """An optimisation that changed the bonding (another molecule: no spectrum to compare)
    leaves the frequency MAE and Figure 4's mean spectrum, and the table lists it (it used to
    be averaged in, a tautomer's frequencies against the DFT molecule's)."""
    import shutil

    mod, cfg, _, root, _ = study_run
    work = tmp_path / "work"
    shutil.copytree(root / "work", work, ignore=shutil.ignore_patterns("md", "*.xyz"))
    path = work / "ir" / "aug-s1.json"
    bad = json.loads(path.read_text())
    bad["molecules"]["methane"]["failure"] = "bonding changed: bond C0-H1 (1.09 -> 1.80 Å) broken"
    path.write_text(json.dumps(bad))
    study = mod.Study(dict(cfg, workdir=str(work)), log=lambda m: None)
    ir = mod.ir_summary(study)
    aug, noaug = ir["groups"]["aug"], ir["groups"]["noaug"]
    assert aug["per_model"]["aug-s1"]["frequency_mae"] is None  # nothing left to compare
    assert aug["frequency_mae"]["mean"] == aug["per_model"]["aug-s0"]["frequency_mae"]
    assert (aug["compared"], noaug["compared"]) == (1, 2)
    assert list(aug["excluded"]) == ["aug-s1/methane"] and not noaug["excluded"]
    result = mod.stage_table(study, tmp_path / "results")
    assert "methane: eMLP augmented (mean of 1)" in result["figures"]["figure4_ir.png"]
    md = (tmp_path / "results" / "results.md").read_text()
    assert "Augmented: 1 optimisation compared, 1 excluded" in md
    assert "aug-s1/methane (bonding changed: bond C0-H1 (1.09 -> 1.80 Å) broken)" in md
    assert "By band of the DFT frequency" in md  # the excluded model has no modes there
    assert [b["n"] for b in aug["per_model"]["aug-s1"]["bands"]] == [0, 0, 0, 0]
    # by molecule: the mean over the models that compared it, the others counted apart
    assert ir["molecules"] == {"methane": {"formula": "CH4", "modes": 9}}
    assert aug["per_molecule"]["methane"]["values"] == [
        aug["per_model"]["aug-s0"]["per_molecule"]["methane"]]
    assert noaug["per_molecule"]["methane"]["mean"] == pytest.approx(np.mean(
        [m["per_molecule"]["methane"] for m in noaug["per_model"].values()]))
    row = next(line for line in md.splitlines() if line.startswith("| methane | CH4 | 9 |"))
    assert row.split(" | ")[3].endswith("[1 of 2]") and "[" not in row.split(" | ")[4]
    card = mod.model_card(result, "mini-eqm7", "aug", 2)
    assert "1 of 2 optimisations left out, failed: aug-s1/methane (bonding changed:" in card
    band = next(b for b in aug["bands"] if b["mae"]["mean"] is not None)
    assert (f"By band of the DFT frequency (cm⁻¹; MAE / mean error, model minus DFT, mean over"
            f" members): {band['band'][0]:g}-{band['band'][1]:g}:") in card
    assert "Å (RMSD, largest" in card and "from the DFT optima." in card


def test_an_ir_optimisation_ending_on_a_saddle_point_is_excluded(study_run, tmp_path):
    """A model optimum with an imaginary mode is no minimum: its frequencies leave the MAE as
    a failed optimisation does, also in files written before the stage checked for it."""
    import shutil

    mod, cfg, _, root, _ = study_run
    assert mod.not_a_minimum([12.0, 1500.0]) == ""
    assert (mod.ir_failure({"failure": "", "frequencies": [-50.0, -3.0, 1500.0]})
            == "not a minimum: 2 imaginary mode(s) (lowest -50.0 cm⁻¹)")
    assert mod.ir_failure({"failure": "bonding changed: x", "frequencies": [-5.0]}) == (
        "bonding changed: x")
    work = tmp_path / "work"
    shutil.copytree(root / "work", work, ignore=shutil.ignore_patterns("md", "*.xyz"))
    path = work / "ir" / "noaug-s0.json"
    old = json.loads(path.read_text())
    row = old["molecules"]["methane"]
    row["frequencies"] = [-50.0, *row["frequencies"][1:]]
    path.write_text(json.dumps(old))
    study = mod.Study(dict(cfg, workdir=str(work)), log=lambda m: None)
    noaug = mod.ir_summary(study)["groups"]["noaug"]
    assert noaug["compared"] == 1 and noaug["per_model"]["noaug-s0"]["frequency_mae"] is None
    assert noaug["excluded"] == {
        "noaug-s0/methane": "not a minimum: 1 imaginary mode(s) (lowest -50.0 cm⁻¹)"}


def test_ir_errors_by_band_of_the_dft_frequency():
    """The IR errors by band: modes go to the band of their DFT frequency (matched in
    ascending order), MAE and signed mean error per band, None for an empty band."""
    mod = study_module()
    model = [500.0, 1450.0, 3050.0, 3300.0]  # sorted before matching, as the DFT ones
    dft = [3000.0, 1500.0, 520.0, 3200.0]
    first = mod.freq_errors(model, dft)
    assert first[1].tolist() == [520.0, 1500.0, 3000.0, 3200.0]
    assert first[0].tolist() == [-20.0, -50.0, 50.0, 100.0]
    assert mod.freq_errors([1.0, 2.0], [1.0]) is None  # another molecule: not compared
    second = (np.array([-40.0]), np.array([900.0]))
    bands = {tuple(b["band"]): b for b in mod.band_errors([first, second])}
    assert [b["n"] for b in bands.values()] == [2, 1, 0, 2]
    assert bands[(0.0, 1000.0)]["mae"] == pytest.approx(30.0)
    assert bands[(0.0, 1000.0)]["mean_error"] == pytest.approx(-30.0)
    assert bands[(1800.0, 2600.0)]["mae"] is None
    assert bands[(2600.0, 4500.0)]["mean_error"] == pytest.approx(75.0)
    # "Why our numbers differ" names the soft modes' error and the displaced minima
    result = {"data": {"configurations": 12, "by_split": {"train": {"molecules": 2}}},
              "ir": {"groups": {"aug": {"rmsd_vs_dft": {"mean": 0.2}, "bands": [
                  {"band": [0.0, 1000.0], "mae": {"mean": 77.8}, "mean_error": {"mean": -33.0}},
              ]}}}}
    text = "\n".join(mod.differences_md(result))
    assert "soft modes (below 1000 cm⁻¹: MAE 78 cm⁻¹, mean error -33)" in text
    assert "minima lie 0.20 Å (RMSD) from the DFT ones" in text
    result["ir"]["groups"]["aug"]["bands"][0]["mae"]["mean"] = None  # no soft mode compared
    assert "**IR.**" not in "\n".join(mod.differences_md(result))


def test_best_uniform_scale_minimises_the_pooled_mae():
    """The best uniform scale of the model's frequencies is the MAE's minimum over a fine scan
    of scale factors; a model off by exactly 2 % everywhere gets 1/1.02 and MAE 0."""
    mod = study_module()
    rng = np.random.default_rng(3)
    ref = [np.sort(rng.uniform(300, 3500, n)) for n in (9, 14)]
    model = [r * rng.normal(1.03, 0.04, len(r)) + rng.normal(0, 20, len(r)) for r in ref]
    errors = [mod.freq_errors(m, r) for m, r in zip(model, ref, strict=True)]
    best = mod.best_uniform_scale(errors)
    a, b = np.concatenate([np.sort(m) for m in model]), np.concatenate(ref)
    scan = np.linspace(0.8, 1.2, 40001)
    mae = np.abs(scan[:, None] * a - b).mean(axis=1)
    assert best["mae"] == pytest.approx(mae.min(), abs=1e-3)
    assert best["factor"] == pytest.approx(scan[mae.argmin()], abs=2e-5)
    assert best["mae_unscaled"] == pytest.approx(np.abs(a - b).mean())
    assert best["mae"] < best["mae_unscaled"]
    exact = mod.best_uniform_scale([mod.freq_errors(1.02 * ref[0], ref[0])])
    assert exact["factor"] == pytest.approx(1 / 1.02) and exact["mae"] == pytest.approx(0, abs=1e-9)
    assert mod.best_uniform_scale([]) is None


def test_frequency_error_against_geometry_error_is_pearsons_r():
    """The correlation of each (model, molecule)'s frequency MAE with its optimum's RMSD is
    SciPy's Pearson r over the pairs with both; too few or constant: None."""
    from scipy.stats import pearsonr

    mod = study_module()
    models = [{"per_molecule": {"a": 50.0, "b": 80.0, "c": None},
               "rmsd_per_molecule": {"a": 0.1, "b": 0.4}},
              {"per_molecule": {"a": 60.0, "b": 55.0}, "rmsd_per_molecule": {"a": 0.2, "b": 0.3}}]
    r = mod.rmsd_mae_pearson(models)
    assert r == pytest.approx(pearsonr([0.1, 0.4, 0.2, 0.3], [50, 80, 60, 55])[0], abs=1e-12)
    assert mod.rmsd_mae_pearson(models[:1]) is None  # two pairs
    flat = [dict(m, rmsd_per_molecule={"a": 0.2, "b": 0.2}) for m in models]
    assert mod.rmsd_mae_pearson(flat) is None


def test_ir_modes_diagnostic_gives_a_model_its_own_frequencies_back(study_run):
    """examples/eqm7/ir_modes.py: the DFT modes replaced by the model's own Born-Oppenheimer
    Hessian give its own frequencies back (Rayleigh quotients of its eigenvectors); pairs
    stiffened by 1/(1 - 0) change nothing, and a stiffer pair block only raises the
    frequencies (the pairs' relaxation softens the cores less: Weyl's inequality)."""
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.hessian import extended_hessian
    from emlpack.properties.ir import ir_from_hessian
    from emlpack.train.evaluate import load_for_evaluation

    mod, _, study, _, _ = study_run
    diagnostic = example_module("ir_modes")
    s = mod.dft_structure(mod.ir_references(study)["methane"])
    path = next(p for group, _, p in study.models() if group == "aug")
    model = load_for_evaluation(path)[0]
    relaxed = s.copy(pairs=relax_pairs(model, s)[0].pairs)
    own = ir_from_hessian(extended_hessian(model, relaxed)[1].numpy(), relaxed)
    same = diagnostic.model_frequencies(model, s, own.hessian, 0.0)
    assert same["dft_geometry"] == pytest.approx(own.frequencies.tolist(), abs=1e-6)
    assert same["dft_modes"] == pytest.approx(own.frequencies.tolist(), rel=1e-8, abs=1e-4)
    assert same["stiffer_pairs"] == pytest.approx(same["dft_geometry"], abs=1e-6)
    stiff = diagnostic.model_frequencies(model, s, own.hessian, 0.5)["stiffer_pairs"]
    assert min(np.subtract(stiff, same["dft_geometry"])) > -1e-6
    assert max(np.subtract(stiff, same["dft_geometry"])) > 1.0


def test_step_schedule_gives_the_learning_curves_epochs():
    """``training.steps``: the 10x learning-curve models (849 training configurations, batch
    16: 54 steps per epoch) were trained for 1370 epochs, the rate halved every 174.07."""
    mod = study_module()
    cfg = mod.load_config(ROOT / "examples" / "eqm7" / "config.yaml")
    assert (cfg["training"]["steps"], cfg["training"]["decay_steps"]) == (74000, 9400)
    assert mod.step_schedule(cfg["training"], 849) == [
        "training.max_epochs=1370", f"training.decay_epochs={9400 / 54}",
        "training.max_time_minutes=null", "training.patience=1000000"]
    small = dict(cfg["training"], overrides=["training.batch_size=8"])
    assert mod.step_schedule(small, 17)[0] == f"training.max_epochs={round(74000 / 3)}"
    assert mod.step_schedule(dict(cfg["training"], steps=None), 849) == []


def test_validation_curve_reads_the_committed_snapshots_best_epochs(study_run):
    """validation_curve.py on the training snapshots: with the whole run's steps it finds each
    model's kept best validation epoch (``done.json``), with fewer steps the best among the
    epochs ended by then, with none no point; the group means are NumPy's."""
    curve = example_module("validation_curve")
    _, _, study, root, _ = study_run
    logs = curve.latest_logs(root / "snapshots")
    assert sorted(logs) == ["aug-s0", "aug-s1", "noaug-s0", "noaug-s1"]
    result = curve.curve(root / "snapshots", [0, 10**9])
    for _, name, best in study.models():
        first, whole = result["models"][name]
        assert first is None
        done = json.loads((best.parent / "done.json").read_text())
        assert whole["epoch"] == int(done["best_epoch"])
        assert whole["val_forces_meV_per_A"] == pytest.approx(
            1000 * done["best_val"]["val_forces_mae"], rel=1e-9)
        rows = logs[name].read_text().splitlines()
        epoch1 = dict(zip(rows[0].split(","), rows[1].split(","), strict=True))
        after_one = curve.best_within(logs[name], [int(epoch1["step"])])[0]
        assert (after_one["epoch"], after_one["val_loss"]) == (1, float(epoch1["val_loss"]))
    for group in ("aug", "noaug"):
        vals = [result["models"][f"{group}-s{k}"][1]["val_loss"] for k in (0, 1)]
        assert result["groups"][group][1]["val_loss"]["mean"] == pytest.approx(np.mean(vals))
        assert result["groups"][group][0]["val_loss"]["mean"] is None
    assert "| aug: mean ± std |" in curve.markdown(result)


def test_group_overrides_fine_tune_each_member_from_its_own_earlier_run(study_run):
    """``training.group_overrides`` with ``{group}``/``{seed}``: each augmented member of a new
    workdir starts from the same seed's model of the earlier run (at lr 0 its weights stay
    the source's exactly, so a member started from another seed would be caught)."""
    import torch

    from emlpack.nn.checkpoint import read_checkpoint

    mod, _, _, root, _ = study_run
    assert mod.model_overrides({"overrides": ["a={seed}"], "group_overrides": {
        "aug": ["b={group}/seed{seed}"]}}, "aug", 3) == ["a=3", "b=aug/seed3"]
    source = root / "work" / "models" / "{group}" / "seed{seed}" / "best.pt"
    cfg = mod.load_config(ROOT / "examples" / "eqm7" / "config.yaml", [
        f"data={root / 'data'}", f"workdir={root / 'tuned'}", "seeds=[0, 1]", "groups=[aug]",
        "train.model.n_features=8", "train.model.n_filters=8", "train.model.n_rbf=8",
        "train.model.n_interactions=1", "train.training.max_epochs=1", "training.steps=null",
        "train.training.batch_size=8", "train.training.lr=0.0",
        "train.training.max_time_minutes=null", "train.training.eval_batch_size=64",
        f"training.group_overrides={{aug: ['training.init_weights={source}']}}"])
    study = mod.run(["train"], cfg, log=lambda m: None)
    assert study.work["train"] == 2
    for seed in (0, 1):
        tuned = read_checkpoint(root / "tuned" / "models" / "aug" / f"seed{seed}" / "best.pt")
        start = read_checkpoint(root / "work" / "models" / "aug" / f"seed{seed}" / "best.pt")
        for key, value in start["state_dict"].items():
            assert torch.equal(tuned["state_dict"][key], value), (seed, key)


def test_rerun_redoes_nothing(study_run):
    mod, cfg, study, root, _ = study_run
    work = root / "work"
    watched = [p for p in work.rglob("*") if p.is_file() and p.suffix in (".pt", ".json",
                                                                           ".xyz", ".npz")]
    before = {p: p.stat().st_mtime_ns for p in watched}
    lines: list[str] = []
    again = mod.run(["train", "evaluate", "dft", "polarizability", "ir", "md"], cfg,
                    log=lines.append)
    assert sum(again.work.values()) == 0, again.work
    assert {p: p.stat().st_mtime_ns for p in watched} == before
    assert any("skipped" in line for line in lines)


def test_outputs_kept_in_the_repository_continue_the_study_on_a_fresh_machine(study_run):
    """study_outputs.py: the stages' finished outputs saved to an archive (a file being written
    is not), restored into a fresh work directory that has only the models (what the committed
    training snapshots give): evaluate, polarizability, ir and md redo nothing, and the table
    is the same."""
    import shutil

    from tests.examples.eqm7_data import example_module

    outputs = example_module("study_outputs")
    mod, cfg, _, root, _ = study_run
    work, archive, fresh = root / "work", root / "archive", root / "fresh"
    half = work / "ir" / "half-written.json"
    half.write_text('{"molecules": {')  # a file being written: never archived
    try:
        saved = outputs.save(work, archive)
    finally:
        half.unlink()
    rel = sorted(p.relative_to(archive) for p in saved)
    assert len(rel) == 4 * 2 + 4 * 2 + 4 + 4 and Path("ir/half-written.json") not in rel
    assert {p.parts[0] for p in rel} == {"eval", "polarizability", "ir", "md"}
    assert all(p.name == "analysis.json" for p in rel if p.parts[0] == "md")
    assert outputs.save(work, archive) == []  # nothing new
    shutil.copytree(work / "models", fresh / "models")
    assert len(outputs.restore(archive, fresh)) == len(rel)
    assert outputs.restore(archive, fresh) == []
    again = mod.run(["evaluate", "polarizability", "ir", "md", "table"],
                    dict(cfg, workdir=str(fresh), results_dir=str(root / "fresh-results")),
                    log=lambda m: None)
    assert {k: v for k, v in again.work.items() if v} == {"table": 1}
    first = json.loads((root / "results" / "results.json").read_text())
    second = json.loads((root / "fresh-results" / "results.json").read_text())
    for key in ("evaluation", "polarizability", "polarizability_pbe0_subset", "ir", "md"):
        assert json.dumps(second[key]).replace(str(fresh), str(work)) == json.dumps(first[key])


@pytest.mark.slow
def test_dft_route_matches_finite_differences():
    """The dft stage's IR route (~40 s): Born charges from the field-perturbed forces equal the
    finite-difference dipole derivatives, the frequencies equal PySCF's harmonic analysis, and the
    finite-difference Hessian (the stage's default) gives the analytic one's spectrum."""
    require("pyscf")
    from ase import Atoms
    from pyscf.hessian import thermo

    from emlpack.qm.labeling import finite_difference_hessian, labeler_calculator, pyscf_hessian
    from emlpack.qm.pyscf_labeler import PySCFLabeler
    from emlpack.units import FIELD_AU_IN_V_PER_A

    mod = study_module()
    lab = PySCFLabeler("tiny", boys_starts=1)
    z = np.array([8, 1, 1])
    r = np.array([[0.0, 0.0, 0.12], [0.0, 0.76, -0.47], [0.0, -0.76, -0.47]])
    f = 1e-3 * FIELD_AU_IN_V_PER_A
    born = np.zeros((3, 9))
    for a in range(3):
        e = np.zeros(3)
        e[a] = f
        plus, minus = lab(z, r, field=e, localize=False), lab(z, r, field=-e, localize=False)
        born[a] = ((plus.forces - minus.forces) / (2 * f)).ravel()
    h = 1e-3
    fd = np.zeros_like(born)
    for i in range(9):
        d = np.zeros(9)
        d[i] = h
        plus = lab(z, r + d.reshape(3, 3), forces=False, localize=False)
        minus = lab(z, r - d.reshape(3, 3), forces=False, localize=False)
        fd[:, i] = (plus.dipole - minus.dipole) / (2 * h)
    assert np.abs(born - fd).max() < 1e-3 * np.abs(fd).max() + 1e-4
    hess = pyscf_hessian(lab, z, r)
    ir = mod.harmonic_ir(hess, born, z, r)
    mol, mf = lab.build(z, r, np.zeros(3), 0.0)
    mf.kernel()
    ref = thermo.harmonic_analysis(mol, mf.Hessian().kernel())["freq_wavenumber"]
    assert np.allclose(ir["frequencies"], np.real(ref), atol=0.5)
    assert np.all(ir["intensities"] > 0)
    # the stage's default Hessian: central differences of the forces (resumable per displacement)
    atoms = Atoms(numbers=z, positions=r)
    atoms.calc = labeler_calculator(lab)
    fd_ir = mod.harmonic_ir(finite_difference_hessian(atoms, 0.005), born, z, r)
    assert np.allclose(fd_ir["frequencies"], ir["frequencies"], atol=2.0)
    assert np.allclose(fd_ir["intensities"], ir["intensities"], rtol=0.02)
    fd_int = finite_difference_hessian(atoms, 0.005, directions="internal")  # the default
    int_ir = mod.harmonic_ir(fd_int, born, z, r)
    assert np.allclose(int_ir["frequencies"], fd_ir["frequencies"], atol=0.5)
    assert np.allclose(int_ir["intensities"], fd_ir["intensities"], rtol=0.01)


def test_cheap_level_hessian_starts_bfgs_in_fewer_steps(tmp_path):
    """The dft stage starts BFGS from the preparation's Hessian (eigenvalues floored): here a
    GFN1-xTB Hessian at its minimum starts a GFN2-xTB optimisation, which reaches the same
    minimum as ASE's default start (70 eV/Å² x identity) in fewer than half the steps."""
    require("tblite")
    from ase import Atoms
    from ase.optimize import BFGS
    from ase.vibrations import Vibrations
    from tblite.ase import TBLite

    from emlpack.qm.sampling import molecule_from_smiles

    mod = study_module()
    m = molecule_from_smiles("C1CN1", "aziridine")
    atoms = Atoms(numbers=m.numbers, positions=m.positions)
    atoms.calc = TBLite(method="GFN1-xTB", verbosity=0)
    BFGS(atoms, logfile=None).run(fmax=1e-3)
    vib = Vibrations(atoms, name=str(tmp_path / "vib"), delta=0.005)
    vib.run()
    hessian = vib.get_vibrations().get_hessian_2d()
    h0 = mod.bfgs_start_hessian(hessian, floor=0.5)
    evals = np.linalg.eigvalsh(h0)
    assert evals.min() == pytest.approx(0.5) and np.allclose(h0, h0.T)
    runs = []
    for start in (None, h0):
        b = atoms.copy()
        b.calc = TBLite(method="GFN2-xTB", verbosity=0)
        opt = BFGS(b, logfile=None, maxstep=0.1)
        if start is not None:
            opt.H0 = start
        assert opt.run(fmax=0.01, steps=100)
        runs.append((opt.get_number_of_steps(), b.get_potential_energy()))
    (n_default, e_default), (n_start, e_start) = runs
    assert 2 * n_start < n_default, runs
    assert abs(e_start - e_default) < 1e-3  # eV: the same minimum


def test_md_starts_without_a_dft_reference_from_the_prepared_geometry(study_run):
    mod, _, study, _, _ = study_run
    s, origin = mod._md_start(study, {"name": "ethane", "smiles": "CC"})  # no DFT reference
    assert origin == "prepared for the reference (gfn2-xtb), pairs guessed"
    assert sorted(s.numbers.tolist()) == [1] * 6 + [6] * 2 and s.n_pairs == 7
    assert np.linalg.norm(s.positions[0] - s.positions[1]) < 1.6  # the C-C bond of ethane


def test_dft_optimisation_resumes_on_a_fresh_machine_as_if_uninterrupted(tmp_path):
    """The reference's BFGS steps are committed step files: a run killed after a few steps
    and resumed without BFGS's saved Hessian (another machine) replays them and ends where an
    uninterrupted run ends, with the same steps. A run whose ``dft.max_steps`` end before
    convergence fails (never an optimum at a non-stationary point) and keeps its steps."""
    from emlpack.qm.pyscf_labeler import PySCFLabeler

    mod = study_module()
    data = tiny_dataset(tmp_path / "data")

    def study(work):
        cfg = mod.load_config(ROOT / "examples" / "eqm7" / "config.yaml", [
            f"data={data}", f"workdir={work}", "dft.level=tiny", "dft.boys_starts=1",
            "dft.fmax=1e-4", "dft.max_steps=30", f"dft.dir={work / 'refs'}"])
        return mod.Study(cfg, log=lambda m: None)

    row = next(r for r in study(tmp_path / "w").split_molecules())
    labeler = PySCFLabeler("tiny", boys_starts=1, reuse_density=True)
    whole = mod.dft_static(study(tmp_path / "whole"), row, labeler)

    class Killed(Exception):
        pass

    class Dies(PySCFLabeler):
        calls = 0

        def __call__(self, *args, **kwargs):
            Dies.calls += 1
            if Dies.calls > 3:
                raise Killed
            return super().__call__(*args, **kwargs)

    cut = study(tmp_path / "cut")
    with pytest.raises(Killed):
        mod.dft_static(cut, row, Dies("tiny", boys_starts=1, reuse_density=True))
    cache = cut.dft_dir / row["name"]
    saved = len(list((cache / "opt").glob("*.npz")))  # the start and the finished steps
    assert 2 <= saved < whole["optimisation"]["steps"] + 1
    (cache / ".bfgs.json").unlink()  # a fresh machine: only the committed files
    short = study(tmp_path / "cut")
    short.cfg["dft"]["max_steps"] = saved - 1  # the steps done: not converged yet
    with pytest.raises(RuntimeError, match=f"did not reach fmax 0.0001 eV/Å in {saved - 1} st"):
        mod.dft_static(short, row, PySCFLabeler("tiny", boys_starts=1, reuse_density=True))
    assert not (cache / "opt.npz").exists()  # never cached as an optimum
    assert len(list((cache / "opt").glob("*.npz"))) == saved  # its steps are kept
    again = mod.dft_static(cut, row, PySCFLabeler("tiny", boys_starts=1, reuse_density=True))
    assert again["optimisation"]["steps"] == whole["optimisation"]["steps"]
    np.testing.assert_allclose(again["positions"], whole["positions"], atol=1e-6)
