"""The MODEL argument of the commands: checkpoints with their DFT hydride references report
energies on the DFT scale; ensembles and pretrained names give one clear line."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from emlpack.calculators.ase import EMLPCalculator
from emlpack.data.references import HydrideReference, load_hydrides
from emlpack.io import read_structures, structure_to_atoms
from emlpack.nn.checkpoint import load_model, save_model
from tests.cli.helpers import run, save_test_model, water_rows, write_xyz
from tests.conftest import shared_path


@pytest.fixture(scope="module")
def referenced_model(tmp_path_factory):
    """A small random model saved with the shared DFT hydride references, as `emlp train`."""
    folder = tmp_path_factory.mktemp("ref")
    plain = save_test_model(folder)
    ref = HydrideReference(*load_hydrides(shared_path("data/hydrides"))).to_metadata()
    return save_model(load_model(plain), folder / "referenced.pt",
                      {"reference": ref, "elements": [1, 6, 7, 8]})


def test_optimize_reports_the_dft_scale(referenced_model, tmp_path):
    water = write_xyz(tmp_path / "w.xyz", water_rows(4))
    out = tmp_path / "opt.xyz"
    rc, _, _ = run(["optimize", str(referenced_model), str(water), "-o", str(out),
                    "--relax", "pairs", "--quiet"])
    assert rc == 0
    data = json.loads(out.with_suffix(".json").read_text())
    s = read_structures(out)[0]
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(referenced_model, relax_pairs=False)
    assert data["energy_scale"] == "dft"
    assert data["energy_eV"] == pytest.approx(atoms.get_potential_energy(), abs=1e-6)
    assert data["energy_relative_eV"] == pytest.approx(
        atoms.calc.results["energy_relative"], abs=1e-6)
    assert data["model_energy_eV"] == pytest.approx(atoms.calc.results["model_energy"],
                                                    abs=1e-6)
    # a water molecule on the DFT scale is near the PBE0 total energy (~ -2078 eV), far from
    # the model's own scale
    assert abs(data["energy_eV"] - data["model_energy_eV"]) > 100


def test_pretrained_names_and_single_model_commands_give_one_line(referenced_model, tmp_path,
                                                                   capsys, monkeypatch):
    from emlpack import pretrained
    from emlpack.cli import main

    # as in a copy of emlpack without the shipped model
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "none")
    water = write_xyz(tmp_path / "w.xyz", water_rows(4))
    folder = tmp_path / "ensemble"
    folder.mkdir()
    for k in range(2):
        (folder / f"model-{k}.pt").write_bytes(referenced_model.read_bytes())
    for command, model, expected in (
            ("polarizability", "mini-eqm7", "is not installed"),
            ("polarizability", "no-such-name", "no such model file, folder or pretrained name"),
            ("md", str(folder), "an ensemble of 2 models")):  # MD runs one model
        rc = main([command, model, str(water)])
        err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
        assert rc == 2 and len(err) == 1 and expected in err[0], err
    # a folder holding one checkpoint is that model
    single = tmp_path / "single"
    single.mkdir()
    (single / "model.pt").write_bytes(referenced_model.read_bytes())
    out = tmp_path / "pol.json"
    assert main(["polarizability", str(single), str(water), "-o", str(out), "--quiet"]) == 0
    data = json.loads(out.read_text())
    assert np.isfinite(data["polarizability_isotropic_bohr3"]) and "ensemble" not in data


@pytest.fixture(scope="module")
def ensemble_folder(referenced_model, tmp_path_factory):
    """Two different random members with the DFT hydride references."""
    from tests.nn.helpers import random_model

    folder = tmp_path_factory.mktemp("ens")
    meta = {"reference": HydrideReference(*load_hydrides(shared_path("data/hydrides")))
            .to_metadata(), "elements": [1, 6, 7, 8]}
    save_model(load_model(referenced_model), folder / "member-0.pt", meta)
    save_model(random_model(1), folder / "member-1.pt", meta)
    return folder


@pytest.mark.parametrize("command", ["polarizability", "ir", "raman"])
def test_property_commands_report_the_ensemble_mean_and_spread(ensemble_folder, tmp_path,
                                                               command):
    """An ensemble folder: every member relaxes and computes on its own; the JSON holds the
    members' mean with ``KEY_std`` beside it, equal to the single-model runs' statistics."""
    from emlpack.cli import main

    water = write_xyz(tmp_path / "w.xyz", water_rows(4))
    extra = ["--relax", "pairs"] if command in ("ir", "raman") else []
    singles = []
    for member in sorted(ensemble_folder.glob("*.pt")):
        out = tmp_path / f"{member.stem}.json"
        assert main([command, str(member), str(water), "-o", str(out), "--quiet", *extra]) == 0
        singles.append(json.loads(out.read_text()))
    out = tmp_path / "ensemble.json"
    assert main([command, str(ensemble_folder), str(water), "-o", str(out), "--quiet",
                 *extra]) == 0
    data = json.loads(out.read_text())
    assert data["ensemble"]["size"] == 2 and len(data["relaxation"]) == 2
    keys = {"polarizability": ["polarizability_isotropic_bohr3", "dipole_norm_debye",
                               "energy_eV"],
            "ir": ["frequencies_cm-1", "energy_eV"],
            "raman": ["frequencies_cm-1", "activities_A4_per_amu", "energy_eV"]}[command]
    for key in keys:
        values = np.array([s[key] for s in singles])
        np.testing.assert_allclose(data[f"{key}_std"], values.std(axis=0), rtol=1e-6,
                                   atol=1e-8)
        if key != "dipole_norm_debye":  # the mean vector's norm is not the mean norm
            np.testing.assert_allclose(data[key], values.mean(axis=0), rtol=1e-8, atol=1e-8)
    assert np.max(data[f"{keys[0]}_std"]) > 0  # two different models do differ
    if command != "polarizability":  # the spectrum: the mean of the members' broadened ones
        from emlpack.properties.spectra import lorentzian

        heights, key = {"ir": ("intensities_km_per_mol", "spectrum_km_per_mol_per_cm-1"),
                        "raman": ("activities_A4_per_amu", "spectrum_A4_per_amu_per_cm-1")}[command]
        grid = np.asarray(data["spectrum_grid_cm-1"])
        curves = [lorentzian(grid, s["frequencies_cm-1"], s[heights], 10.0) for s in singles]
        np.testing.assert_allclose(data[key], np.mean(curves, axis=0), rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(data[f"{key}_std"], np.std(curves, axis=0), rtol=1e-8,
                                   atol=1e-10)
        assert len(data["members"]) == 2
    if command == "raman":  # a mode's sign is arbitrary: its derivative tensor has no mean
        assert "polarizability_derivatives_A2_per_sqrt_amu" not in data
        assert all("polarizability_derivatives_A2_per_sqrt_amu" in m for m in data["members"])
        assert len(data["depolarization_ratios_std"]) == len(data["frequencies_cm-1"])


def test_a_member_with_a_broken_structure_is_left_out_of_the_results(ensemble_folder, tmp_path,
                                                                     monkeypatch, capsys):
    """A member whose relaxation leaves a broken structure (here its pair relaxation is made
    to report a failure) is left out of the mean and spread, named in a warning and in
    ``ensemble.left_out``: with three members the values are the two sound members' mean;
    with two, one sound member is no ensemble result: exit 3, one line, nothing written."""
    from emlpack.cli import main, properties

    water = write_xyz(tmp_path / "w.xyz", water_rows(4))
    members = sorted(ensemble_folder.glob("*.pt"))
    three = tmp_path / "three"
    three.mkdir()
    for k, member in enumerate([members[0], members[1], members[1]]):
        (three / f"m{k}.pt").write_bytes(member.read_bytes())
    alone = []
    for k, member in enumerate(members):
        out = tmp_path / f"alone{k}.json"
        assert main(["polarizability", str(member), str(water), "-o", str(out), "--quiet"]) == 0
        alone.append(json.loads(out.read_text())["polarizability_isotropic_bohr3"])
    real, calls = properties.relax, []

    def relax(model, s, level, args, log, warnings):
        out, info = real(model, s, level, args, log, warnings)
        calls.append(level)
        if len(calls) == 2:  # the second member
            info["pairs"]["failed"] = True
            warnings.append("pair relaxation failed: made to fail by the test")
        return out, info

    monkeypatch.setattr(properties, "relax", relax)
    out = tmp_path / "ensemble.json"
    assert main(["polarizability", str(three), str(water), "-o", str(out), "--quiet"]) == 0
    data = json.loads(out.read_text())
    assert [p.rsplit("/", 1)[-1] for p in data["ensemble"]["left_out"]] == ["m1.pt"]
    assert data["ensemble"]["size"] == 2
    assert any(w.startswith("model 2 left out of the results") for w in data["warnings"])
    assert data["polarizability_isotropic_bohr3"] == pytest.approx(np.mean(alone), rel=1e-10)

    calls.clear()
    capsys.readouterr()
    out = tmp_path / "two.json"
    assert main(["polarizability", str(ensemble_folder), str(water), "-o", str(out),
                 "--quiet"]) == 3
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "1 of 2 models sound, at least 2 needed (model 2: pair" in err[0]
    assert not out.exists()


def test_pretrained_lists_the_names_and_shows_a_card_with_its_thresholds(
        ensemble_folder, tmp_path, capsys, monkeypatch):
    """`emlp pretrained` lists the known names and whether they are installed; `emlp
    pretrained NAME` prints the card, the member files and the spread thresholds the
    calculator uses (calibrated when the export stored a calibration)."""
    from emlpack import pretrained
    from emlpack.cli import main
    from emlpack.pretrained import export_pretrained

    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path)
    assert main(["pretrained"]) == 0
    assert "mini-eqm7 (not installed)" in capsys.readouterr().out
    cal = {"energy_eV_per_atom": 0.0123, "forces_eV_per_A": 0.456, "quantile": 0.95,
           "set": "the 3 validation molecules", "configurations": 18, "failed": 0,
           "members": 2, "pairs": "relaxed"}
    export_pretrained(sorted(ensemble_folder.glob("*.pt")), tmp_path / "mini-eqm7",
                      "# mini-eqm7 card\n", spread_calibration=cal)
    assert main(["pretrained"]) == 0
    assert "mini-eqm7 (installed)" in capsys.readouterr().out
    assert main(["pretrained", "mini-eqm7"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("# mini-eqm7 card") and out.count("member: ") == 2
    assert ("spread warnings above 0.0123 eV/atom (energy), 0.456 eV/Å (largest force"
            " component): calibrated: exceeded on 5% of 18 configurations of the 3 validation"
            " molecules") in out
    assert main(["pretrained", "other"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not an installed pretrained name" in err[0]


def test_md_writes_energies_on_the_dft_scale(tmp_path):
    """A checkpoint with DFT hydride references: the trajectory's, the log's and the summary's
    energies are on the DFT scale (the model's energy plus a constant of the composition), as
    the property commands report them; stderr (not a terminal) gets plain progress lines."""
    from emlpack.calculators.ensemble import load_member

    folder = tmp_path / "m"
    folder.mkdir()
    ref = HydrideReference(*load_hydrides(shared_path("data/hydrides"))).to_metadata()
    path = save_model(load_model(save_test_model(folder, seed=4)), folder / "ref.pt",
                      {"reference": ref, "elements": [1, 6, 7, 8]})
    water = write_xyz(tmp_path / "w.xyz", water_rows(4))
    out = tmp_path / "run"
    rc, _, err = run(["md", str(path), str(water), "--steps", "4", "--dt", "0.25", "--nve",
                      "--temperature", "100", "-o", str(out)])
    assert rc == 0, err
    assert "md: 4/4 (100%)" in err and "step/s" in err  # the progress line at the end
    member = load_member(path)
    frames = read_structures(out / "trajectory.xyz")
    shift = member.dft_shift(frames[0].numbers)
    assert abs(shift) > 100  # water: the DFT scale is far from the model's
    for f in frames:
        model_energy = member.model.evaluate(f)["energy"]
        assert f.info["potential_energy"] == pytest.approx(model_energy + shift, abs=1e-5)
        assert f.energy == pytest.approx(f.info["potential_energy"], abs=1e-9)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["energy_scale"] == "dft"
    assert summary["energy_eV"] == pytest.approx(frames[-1].info["potential_energy"], abs=1e-9)
    assert summary["model_energy_eV"] == pytest.approx(summary["energy_eV"] - shift, abs=1e-9)
    assert summary["final_conserved_energy_eV"] == pytest.approx(
        frames[-1].info["conserved_energy"], abs=1e-9)
    assert "energies on the DFT scale" in (out / "md.log").read_text()
    # a run of this model started on the model's scale (before the DFT scale) is not mixed in
    ckpt = out / "checkpoint.npz"
    with np.load(ckpt) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["meta"]))
    meta["signature"].pop("energy_scale")
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(ckpt, **arrays)
    rc, _, err = run(["md", str(path), str(water), "--steps", "6", "--dt", "0.25", "--nve",
                      "--temperature", "100", "-o", str(out), "--quiet"])
    assert rc == 2 and "differs in ['energy_scale']" in err


def test_an_ensemble_shows_its_progress_per_member_unless_quiet(ensemble_folder, tmp_path):
    """Not a terminal (the captured stderr): plain progress lines over the members, with the
    count, rate and time left; ``--quiet``: none."""
    water = write_xyz(tmp_path / "w.xyz", water_rows(4))
    out = tmp_path / "pol.json"
    rc, _, err = run(["polarizability", str(ensemble_folder), str(water), "-o", str(out)])
    assert rc == 0, err
    assert re.search(r"^polarizability: models relaxed: 2/2 \(100%\) .* left,"
                     r" .*(model/s|s/model)$", err, re.M), err
    assert re.search(r"^extended Hessians: 2/2 \(100%\)", err, re.M), err
    rc, _, err = run(["polarizability", str(ensemble_folder), str(water), "-o", str(out),
                      "--quiet"])
    assert rc == 0 and err == ""
