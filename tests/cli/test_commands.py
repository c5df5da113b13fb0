"""Every ``emlp`` command: ``--help`` shows its defaults, and one small happy path whose output
values and units match the library call (a random small eMLP, water, a few steps)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from emlpack.cli import build_parser
from emlpack.io import read_structures
from tests.cli.helpers import WATER_CORES, run, save_test_model, water_rows, write_xyz
from tests.conftest import ROOT

COMMANDS = ["train", "evaluate", "demo", "pretrained", "label", "relabel", "convert-reference",
            "campaign", "ir", "raman", "polarizability", "response", "optimize", "md",
            "md-analysis", "md-ir"]


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    return save_test_model(tmp_path_factory.mktemp("model"))


@pytest.fixture(scope="module")
def model(model_file):
    from emlpack.nn.checkpoint import load_model

    return load_model(model_file)


@pytest.fixture()
def water_file(tmp_path):
    return write_xyz(tmp_path / "water.xyz", water_rows(4))


def test_the_parser_knows_every_command():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert sorted(sub.choices) == sorted(COMMANDS)


@pytest.mark.parametrize("command", COMMANDS)
def test_help(command):
    rc, out, _ = run([command, "--help"])
    assert rc == 0
    assert f"usage: emlp {command}" in out
    # every command takes --threads (the campaign's on its run sub-command)
    rc, sub_out, _ = run([command, "run", "--help"] if command == "campaign" else
                         [command, "--help"])
    assert rc == 0 and "--threads" in sub_out, command
    if command in ("ir", "raman", "polarizability", "response", "optimize", "md"):
        for flag in ("--smiles", "--index", "--charge", "--field", "--field-au", "--threads",
                     "-o OUTPUT, --output OUTPUT"):
            assert flag in out, (command, flag)
        assert "(default: " in out
    if command == "md":  # a default of 0 is shown too
        assert "seed of the initial velocities (default: 0)" in " ".join(out.split())


def test_model_argument_names_the_pretrained_models_and_help_needs_no_torch():
    """``emlp CMD --help`` lists the installed pretrained names (an ensemble for the
    commands that take one, one file of it for md) and stays fast: no torch import."""
    import subprocess
    import sys

    from emlpack.pretrained import available

    names = available()
    assert names  # mini-eqm7 ships with the package
    for command, words in (("ir", "a pretrained name"), ("md", "one file of an ensemble")):
        out = " ".join(run([command, "--help"])[1].split())
        assert words in out and all(n in out.replace("- ", "-") for n in names), command
    code = ("import sys, emlpack.cli\n"
            "emlpack.cli.build_parser()\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_version():
    from emlpack import __version__

    assert run(["--version"])[:2] == (0, f"emlpack {__version__}\n")


# ------------------------------------------------------------------ properties
def test_polarizability_matches_the_library(model, model_file, water_file, tmp_path):
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.response import molecule_response

    out = tmp_path / "pol.json"
    rc, text, _ = run(["polarizability", str(model_file), str(water_file), "-o", str(out),
                       "--field", "0.01", "0", "0", "--threads", "1"])
    assert rc == 0
    assert "field: [0.01 0.   0.  ] V/Å (from --field)" in text
    data = json.loads(out.read_text())
    s = read_structures(water_file)[0].copy(field=np.array([0.01, 0.0, 0.0]))
    s = s.copy(pairs=relax_pairs(model, s, fmax=1e-6)[0].pairs)
    ref = molecule_response(model, s).as_dict()
    np.testing.assert_allclose(data["polarizability_bohr3"], ref["polarizability_bohr3"],
                               rtol=1e-5)
    np.testing.assert_allclose(data["dipole_debye"], ref["dipole_debye"], rtol=1e-5,
                               atol=1e-7)
    assert data["field_V_per_A"] == [0.01, 0.0, 0.0] and data["field_source"] == "--field"
    assert data["settings"]["relax"] == "pairs" and data["settings"]["threads"] == 1
    assert data["relaxation"]["pairs"]["failed"] is False
    assert isinstance(data["warnings"], list)


def test_ir_and_its_plot(model, model_file, water_file, tmp_path):
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.ir import ir_spectrum

    out, png = tmp_path / "ir.json", tmp_path / "ir.png"
    rc, text, _ = run(["ir", str(model_file), str(water_file), "--relax", "pairs",
                       "-o", str(out), "--plot", str(png), "--quiet"])
    assert rc == 0 and png.stat().st_size > 0
    data = json.loads(out.read_text())
    s = read_structures(water_file)[0]
    s = s.copy(pairs=relax_pairs(model, s, fmax=1e-6)[0].pairs)
    ref = ir_spectrum(model, s)
    np.testing.assert_allclose(data["frequencies_cm-1"], ref.frequencies, rtol=1e-5, atol=1e-3)
    # cores not at a minimum: an imaginary mode is a warning, not a clean spectrum
    assert (ref.frequencies < 0).any()
    assert any("imaginary mode" in w for w in data["warnings"])
    assert text.strip().splitlines()[-1] == "converged with warnings (1)"  # pairs converged


def test_raman_and_its_plot_with_references(model, model_file, water_file, tmp_path):
    """``emlp raman`` gives the library's spectrum (JSON with units, PNG); ``--reference``
    takes the JSON of ``emlp ir`` (wavenumbers only for Raman), a CSV and its own JSON."""
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.raman import raman_spectrum

    ir_json = tmp_path / "ir.json"
    assert run(["ir", str(model_file), str(water_file), "--relax", "pairs", "-o", str(ir_json),
                "--quiet"])[0] == 0
    out, png = tmp_path / "raman.json", tmp_path / "raman.png"
    rc, text, _ = run(["raman", str(model_file), str(water_file), "--relax", "pairs",
                       "-o", str(out), "--plot", str(png), "--reference", str(ir_json),
                       "--reference-label", "IR modes", "--quiet"])
    assert rc == 0 and png.read_bytes()[:4] == b"\x89PNG"
    data = json.loads(out.read_text())
    s = read_structures(water_file)[0]
    s = s.copy(pairs=relax_pairs(model, s, fmax=1e-6)[0].pairs)
    ref = raman_spectrum(model, s)
    np.testing.assert_allclose(data["frequencies_cm-1"], ref.frequencies, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(data["activities_A4_per_amu"], ref.activities, rtol=1e-4,
                               atol=1e-6 * ref.activities.max())
    assert len(data["depolarization_ratios"]) == len(ref.frequencies)
    assert data["fwhm_cm-1"] == 10.0 and data["settings"]["step"] == 2e-3
    assert data["reference_label"] == "IR modes" and "reference_activities_A4_per_amu" not in data
    assert data["reference_frequencies_cm-1"] == json.loads(ir_json.read_text())["frequencies_cm-1"]
    assert len(data["spectrum_A4_per_amu_per_cm-1"]) == len(data["spectrum_grid_cm-1"])
    assert any("imaginary mode" in w for w in data["warnings"])  # cores not at a minimum
    assert "activity (Å^4/amu)  depolarization" in text
    # a CSV reference, and the command's own JSON as a reference of the next run
    csv = tmp_path / "exp.csv"
    csv.write_text("wavenumber,activity\n1600,2.5\n3700,8\n")
    for reference, heights in ((csv, [2.5, 8.0]), (out, data["activities_A4_per_amu"])):
        again = tmp_path / "again.json"
        assert run(["raman", str(model_file), str(water_file), "--relax", "pairs", "-o",
                    str(again), "--reference", str(reference), "--quiet"])[0] == 0
        assert json.loads(again.read_text())["reference_activities_A4_per_amu"] == heights


def test_ir_plot_with_a_reference_and_a_bad_reference(model_file, water_file, tmp_path):
    csv = tmp_path / "ref.csv"
    csv.write_text("1500 30\n3500 60\n")
    out, png = tmp_path / "ir.json", tmp_path / "ir.png"
    rc, _, _ = run(["ir", str(model_file), str(water_file), "--relax", "pairs", "-o", str(out),
                    "--plot", str(png), "--reference", str(csv), "--quiet"])
    assert rc == 0 and png.stat().st_size > 0
    data = json.loads(out.read_text())
    assert data["reference_intensities_km_per_mol"] == [30.0, 60.0]
    assert data["reference_label"] == "reference (ref.csv)"
    csv.write_text("1500 30\n3500 lots\n")
    rc, _, err = run(["ir", str(model_file), str(water_file), "-o", str(out), "--reference",
                      str(csv)])
    assert rc == 2 and err.strip() == (f"emlp ir: error: {csv}, line 2: not two numbers:"
                                       " '3500 lots'")


#: a distorted water whose O-H bond(s) the random model (seed 0) stretches to ~1.44 Å
DISTORTED_WATER = [("O", 0.00118216, 0.04504637, -0.03558404),
                   ("H", 0.80186494, 0.56718315, -0.00766736),
                   ("H", -0.72422974, 0.57691991, 0.00495937),
                   ("Es", 0.42435325, 0.28594210, 0.04848054),
                   ("Es", -0.36087218, 0.28943286, 0.03227257),
                   ("Es", 0.03693315, -0.26358616, 0.34731768),
                   ("Es", -0.00754757, -0.20945041, -0.29191038)]


def test_optimize_reports_broken_bonds_and_writes_pairs_or_not(model, model_file, tmp_path):
    import ase.io

    water_file = write_xyz(tmp_path / "distorted.xyz", DISTORTED_WATER)
    out = tmp_path / "opt.xyz"
    rc, text, err = run(["optimize", str(model_file), str(water_file), "-o", str(out),
                         "--max-iterations", "20", "--quiet"])
    # this random model stretches the O-H bonds: a broken result, never a plain "converged";
    # the single model's is not reported (exit 3, one line, nothing written)
    err = [line for line in err.splitlines() if line.strip()]
    assert rc == 3 and len(err) == 1, err
    assert err[0].startswith(f"emlp optimize: failed: {water_file}, frame 0: no result to"
                             " report: bonding changed: bond O0-H")
    assert not out.exists() and not out.with_suffix(".json").exists()
    rc, text, _ = run(["optimize", str(model_file), str(water_file), "-o", str(out),
                       "--relax", "pairs", "--quiet"])
    assert rc == 0
    s = read_structures(out)[0]
    data = json.loads(out.with_suffix(".json").read_text())
    np.testing.assert_allclose(data["energy_eV"], model.evaluate(s)["energy"], rtol=1e-8)
    np.testing.assert_allclose(data["pairs_A"], s.pairs, atol=1e-6)
    plain = tmp_path / "plain.xyz"
    assert run(["optimize", str(model_file), str(water_file), "-o", str(plain), "--relax",
                "pairs", "--no-pairs", "--quiet"])[0] == 0
    atoms = ase.io.read(plain)
    assert atoms.get_chemical_symbols() == ["O", "H", "H"]  # no Es rows: ASE masses work
    assert np.isclose(atoms.get_masses().sum(), 18.015, atol=0.01)


def _water_crystal(path):
    rows = water_rows(4)
    return write_xyz(path, rows, comment='Lattice="4.5 0 0 0.5 4.6 0 -0.3 0.4 4.8"'
                     ' Properties=species:S:1:pos:R:3 pbc="T T T"')


def test_periodic_optimize_reports_the_stress(model, model_file, tmp_path):
    from emlpack.units import EV_PER_A3_IN_GPA

    path = _water_crystal(tmp_path / "ice.xyz")
    out = tmp_path / "opt.xyz"
    rc, text, _ = run(["optimize", str(model_file), str(path), "-o", str(out),
                       "--max-iterations", "1", "--quiet"])
    assert rc == 0
    data = json.loads(out.with_suffix(".json").read_text())
    s = read_structures(out)[0]
    stress = model.evaluate(s, stress=True)["stress"] * EV_PER_A3_IN_GPA
    np.testing.assert_allclose(data["relaxation"]["optimisation"]["stress_GPa"], stress,
                               rtol=1e-6, atol=1e-9)
    assert np.abs(stress).max() > 1e-3  # not the "0.00e+00 GPa" of a positions-only run
    assert f"max |σ| {np.abs(stress).max():.3g}" in text


def test_response_of_a_crystal(model, model_file, tmp_path):
    from emlpack.io import write_structures
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.response import crystal_response

    given = read_structures(_water_crystal(tmp_path / "ice0.xyz"))[0]
    path = tmp_path / "ice.xyz"  # pairs at their minimum: a response without relaxation
    write_structures(path, given.copy(pairs=relax_pairs(model, given, fmax=1e-8)[0].pairs))
    out = tmp_path / "resp.json"
    rc, _, err = run(["response", str(model_file), str(path), "--relax", "none", "-o",
                      str(out), "--quiet"])
    assert rc == 0, err
    data = json.loads(out.read_text())
    ref = crystal_response(model, read_structures(path)[0]).as_dict()
    np.testing.assert_allclose(data["stiffness_voigt_GPa"], ref["stiffness_voigt_GPa"],
                               rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(data["dielectric_ion_clamped"], ref["dielectric_ion_clamped"],
                               rtol=1e-6)
    low = np.linalg.eigvalsh(np.array(ref["stiffness_voigt_GPa"]))[0]
    assert any("negative stiffness" in w for w in data["warnings"]) == (low < 0)


def test_smiles_input_with_the_lewis_guess(model_file, tmp_path):
    out = tmp_path / "pol.json"
    rc, _, err = run(["polarizability", str(model_file), "--smiles", "O", "--guess", "lewis",
                      "-o", str(out)])
    assert rc == 0, err
    assert "guessing electron pairs (lewis) for H2O" in err  # progress on stderr
    data = json.loads(out.read_text())
    assert data["structure"] == "SMILES O" and data["settings"]["smiles"] == "O"
    assert len(data["dipole_e_A"]) == 3


def test_charge_flag_changes_the_pair_count(model_file, tmp_path):
    # H3O+ without pairs: 4 valence pairs at charge +1 (5 would be odd)
    rows = [("O", 0.0, 0.0, 0.0), ("H", 0.97, 0.0, 0.0), ("H", -0.32, 0.92, 0.0),
            ("H", -0.32, -0.46, 0.8)]
    path = write_xyz(tmp_path / "h3o.xyz", rows)
    out = tmp_path / "pol.json"
    rc, _, err = run(["polarizability", str(model_file), str(path), "--charge", "1",
                      "--guess", "lewis", "--relax", "none", "-o", str(out), "--quiet"])
    assert rc == 0, err
    assert json.loads(out.read_text())["settings"]["charge"] == 1.0


# ------------------------------------------------------------------ dynamics
@pytest.fixture(scope="module")
def md_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("md")
    model_file = save_test_model(folder, seed=4)  # pairs of water at a minimum
    start = write_xyz(folder / "water.xyz", water_rows(4))
    out = folder / "run"
    rc, text, err = run(["md", str(model_file), str(start), "--steps", "10", "--dt", "0.25",
                         "--nve", "--temperature", "100", "-o", str(out), "--quiet",
                         "--checkpoint-every", "2", "--no-pairs"])
    assert rc == 0, err
    assert "INFO" not in err  # --quiet: the log goes to md.log only
    assert "INFO MD NVE: 10 steps" in (out / "md.log").read_text()
    return out, text


def test_md_writes_trajectory_settings_and_warnings(md_run):
    out, text = md_run
    frames = read_structures(out / "trajectory.xyz")
    assert len(frames) == 11
    np.testing.assert_allclose([f.info["time"] for f in frames], 0.25 * np.arange(11))
    settings = json.loads((out / "settings.json").read_text())
    assert settings["steps"] == 10 and settings["field_source"] == "none"
    assert "warnings" in json.loads((out / "warnings.json").read_text())
    assert "10 steps" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 10 and summary["energy_scale"] == "model"  # no hydride reference
    assert summary["energy_eV"] == pytest.approx(frames[-1].info["potential_energy"])
    assert summary["final_conserved_energy_eV"] == pytest.approx(
        frames[-1].info["conserved_energy"])
    import ase.io

    atoms = ase.io.read(out / "trajectory_atoms.xyz", ":")
    assert len(atoms) == 11 and atoms[-1].get_chemical_symbols() == ["O", "H", "H"]
    np.testing.assert_allclose(atoms[-1].positions, frames[-1].positions, atol=1e-6)


def test_md_refuses_a_crystal_and_another_run_in_its_folder(md_run, model_file, tmp_path):
    out, _ = md_run
    start = out.parent / "water.xyz"
    rc, _, err = run(["md", str(model_file), str(start), "--steps", "10", "--dt", "0.5",
                      "--nve", "--temperature", "100", "-o", str(out), "--quiet"])
    assert rc == 2
    assert err.strip().splitlines()[-1].startswith(
        f"emlp md: error: {out / 'checkpoint.npz'}: the checkpoint belongs to a different run"
        " (differs in ['dt_fs'])")
    assert json.loads((out / "settings.json").read_text())["dt"] == 0.25  # kept
    crystal = _water_crystal(tmp_path / "ice.xyz")
    rc, _, err = run(["md", str(model_file), str(crystal), "-o", str(tmp_path / "md")])
    assert rc == 2 and err.strip() == (f"emlp md: error: {crystal}, frame 0: emlp md needs a"
                                       " molecule; this is a crystal (pbc true)")


def test_md_analysis_and_md_ir(md_run, tmp_path):
    out, _ = md_run
    traj = out / "trajectory.xyz"
    js = tmp_path / "stab.json"
    assert run(["md-analysis", str(traj), "--discard", "0", "-o", str(js)])[0] == 0
    runs = json.loads(js.read_text())["runs"]
    assert len(runs) == 1 and runs[0]["n_frames"] == 11
    assert json.loads(js.read_text())["settings"]["discard"] == 0
    ir = tmp_path / "md_ir.json"
    rc, _, err = run(["md-ir", str(traj), "-o", str(ir), "--temperature", "300"])
    assert rc == 0, err
    assert json.loads(ir.read_text())["settings"]["temperature"] == 300
    # too few frames: one line, exit 2
    short = tmp_path / "short.xyz"
    short.write_text("".join(traj.read_text().splitlines(keepends=True)[: 3 * 9]))
    rc, _, err = run(["md-ir", str(short), "-o", str(tmp_path / "x.json")])
    assert rc == 2 and err.strip().startswith(f"emlp md-ir: error: {short}")
    assert len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------ data and training
def test_convert_reference_of_a_missing_prefix_is_one_line(tmp_path):
    rc, _, err = run(["convert-reference", str(tmp_path / "models/eQM7"), "-o",
                      str(tmp_path / "m.pt")])
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert str(tmp_path / "models/eQM7") in err


def test_evaluate_static_errors(tmp_path):
    from emlpack.io import write_structures
    from emlpack.nn.checkpoint import save_model
    from tests.nn.helpers import random_model

    model_file = tmp_path / "trained.pt"
    save_model(random_model(0), model_file,
               metadata={"reference": {"kind": "constant", "value": 0.0}})

    s = read_structures(write_xyz(tmp_path / "w.xyz", water_rows(4)))[0]
    labelled = [s.copy(energy=1.0, forces=np.zeros((3, 3)))]
    data = tmp_path / "data.xyz"
    write_structures(data, labelled)
    rc, text, err = run(["evaluate", str(model_file), str(data), "--subset", "all",
                         "--no-dynamic", "-o", str(tmp_path / "ev"), "--quiet"])
    assert rc == 0, err
    assert (tmp_path / "ev" / "evaluation.json").exists()
    # an ensemble folder stands for its members (as a pretrained name does)
    ensemble = tmp_path / "ensemble"
    ensemble.mkdir()
    for k in range(2):
        save_model(random_model(k), ensemble / f"model-{k}.pt",
                   metadata={"reference": {"kind": "constant", "value": 0.0}})
    rc, text, err = run(["evaluate", str(ensemble), str(data), "--subset", "all",
                         "--no-dynamic", "-o", str(tmp_path / "ens"), "--quiet"])
    assert rc == 0, err
    rows = json.loads((tmp_path / "ens" / "evaluation.json").read_text())
    assert [r["model"] for r in rows] == [str(ensemble / f"model-{k}.pt") for k in range(2)]
    # a split made on another data set is refused in one line, not applied by index
    split_model = tmp_path / "split.pt"
    save_model(random_model(0), split_model, metadata={
        "reference": {"kind": "constant", "value": 0.0}, "data_path": "other.h5",
        "n_structures": 8, "split": {"train": [0, 1, 2, 3, 4, 5], "val": [6], "test": [7]}})
    rc, _, err = run(["evaluate", str(split_model), str(data), "--no-dynamic", "--quiet",
                      "-o", str(tmp_path / "split")])
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "made on other.h5 (8 structures)" in err and "--subset all" in err
    text_model = tmp_path / "notes.pt"
    text_model.write_text("not a model\n")
    rc, _, err = run(["evaluate", str(model_file), str(text_model), str(data)])
    assert rc == 2 and err.strip() == (f"emlp evaluate: error: {text_model}: not an emlpack"
                                       " model file (a text file, not a PyTorch checkpoint"
                                       " archive)")


def test_campaign_init_and_card(tmp_path):
    csv = tmp_path / "qm7.csv"
    csv.write_text("smiles\n" + "\n".join(["C", "O", "N", "CC", "CO", "CN", "C=O", "OO",
                                            "NN", "CCO"]) + "\n")
    folder = tmp_path / "ds"
    rc, text, err = run(["campaign", "init", str(folder), "--smiles", str(csv), "--n-large",
                         "0"])
    assert rc == 0, err
    assert "molecules listed" in text
    rc, text, err = run(["campaign", "card", str(folder)])
    assert rc == 0, err


def test_label_tiny_level(tmp_path):
    path = tmp_path / "mol.xyz"
    write_xyz(path, WATER_CORES)
    out = tmp_path / "data.h5"
    rc, text, err = run(["label", str(path), "-o", str(out), "--level", "tiny",
                         "--samples-per-molecule", "1", "--workers", "0", "--quiet",
                         "-s", "prepare.optimize=false"])
    assert rc == 0, err + text
    assert out.exists()


def test_field_stored_in_the_file_is_printed_and_recorded(model_file, tmp_path):
    path = write_xyz(tmp_path / "wf.xyz", water_rows(4),
                     comment='Properties=species:S:1:pos:R:3 external_field="0.44 0 0"'
                     ' pbc="F F F"')
    out = tmp_path / "pol.json"
    rc, text, err = run(["polarizability", str(model_file), str(path), "-o", str(out),
                         "--quiet"])
    assert rc == 0, err
    assert "field: [0.44 0.   0.  ] V/Å (from the structure file)" in text
    data = json.loads(out.read_text())
    assert data["field_V_per_A"] == [0.44, 0.0, 0.0]
    assert data["field_source"] == "the structure file"


def test_split_pairs_gives_ase_the_atoms_alone(model_file, tmp_path):
    import ase.io

    from emlpack.io import split_pairs

    path = write_xyz(tmp_path / "w.xyz", water_rows(4))
    with_pairs = ase.io.read(path)
    assert with_pairs.get_chemical_symbols().count("Es") == 4  # einsteinium to ASE
    atoms = split_pairs(with_pairs)
    assert atoms.get_chemical_symbols() == ["O", "H", "H"]
    np.testing.assert_allclose(atoms.info["electron_pairs"], [r[1:] for r in water_rows(4)[3:]])
    np.testing.assert_allclose(atoms.get_center_of_mass(),
                               with_pairs[:3].get_center_of_mass())


def test_relabel_one_frame_at_the_tiny_level(tmp_path):
    src = write_xyz(tmp_path / "w.xyz", water_rows(4),
                    comment='Properties=species:S:1:pos:R:3 energy=0.0 pbc="F F F"')
    out = tmp_path / "out.xyz"
    rc, text, err = run(["relabel", str(src), "-o", str(out), "--level", "tiny",
                         "--boys-starts", "1", "--quiet"])
    assert rc == 0, err + text
    s = read_structures(out)[0]
    assert s.n_pairs == 4 and s.energy is not None and s.energy != 0.0


def test_interrupted_label_says_it_resumes(tmp_path, monkeypatch):
    import emlpack.qm.labeling

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(emlpack.qm.labeling, "run_labeling", interrupted)
    path = write_xyz(tmp_path / "mol.xyz", WATER_CORES)
    rc, _, err = run(["label", str(path), "-o", str(tmp_path / "d.h5"), "--workers", "0"])
    assert rc == 130
    assert err.strip().splitlines()[-1] == (
        "emlp label: interrupted; re-run the same command to resume")


def test_train_then_evaluate(model, tmp_path):
    """``emlp train`` on 8 water configurations labelled by the random model (constant
    reference, 2 epochs), then ``emlp evaluate`` of its best model."""
    import yaml

    from emlpack.io import write_structures

    s0 = read_structures(write_xyz(tmp_path / "w.xyz", water_rows(4)))[0]
    rng = np.random.default_rng(0)
    frames = []
    for k in range(8):
        s = s0.copy(positions=s0.positions + rng.normal(scale=0.03, size=(3, 3)),
                    info={"molecule_id": "water"}, source=f"water {k}")
        r = model.evaluate(s)
        frames.append(s.copy(energy=r["energy"], forces=r["forces"],
                             pair_forces=np.zeros_like(s.pairs)))
    data = tmp_path / "data.xyz"
    write_structures(data, frames)
    cfg = {"data": {"path": str(data), "reference": "constant", "split": "configuration",
                    "fractions": [0.75, 0.25, 0.0]},
           "model": {"n_features": 8, "n_filters": 8, "n_rbf": 8, "n_interactions": 1},
           "training": {"batch_size": 4, "max_epochs": 2, "threads": 1},
           "output": {"dir": str(tmp_path / "run"), "progress": False}}
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    rc, text, err = run(["train", str(path)])
    assert rc == 0, err + text
    best = tmp_path / "run" / "best.pt"
    assert f"best model(s): {best}" in text
    rc, text, err = run(["evaluate", str(best), str(data), "--subset", "all", "--no-dynamic",
                         "-o", str(tmp_path / "ev"), "--quiet"])
    assert rc == 0, err
    table = json.loads((tmp_path / "ev" / "evaluation.json").read_text())
    assert table  # the tables were written
    rc, _, err = run(["train", str(path), "training.nonsense=1"])
    assert rc == 2 and err.strip().startswith("emlp train: error:")


def test_threads_below_one_is_one_line_for_every_command(tmp_path):
    for argv in (["md-analysis", "x.xyz"], ["evaluate", "m.pt", "d.h5"], ["ir", "m.pt", "x"]):
        rc, _, err = run([*argv, "--threads", "0"])
        assert rc == 2 and err.strip().endswith("--threads must be at least 1, got 0"), argv
        assert len(err.strip().splitlines()) == 1


def test_train_threads_flag_overrides_the_config(tmp_path, monkeypatch):
    import emlpack.train.trainer as trainer

    seen = {}

    def fake_train(cfg, resume=True):
        seen.update(cfg["training"])
        return tmp_path / "best.pt"

    monkeypatch.setattr(trainer, "train", fake_train)
    rc, _, err = run(["train", str(ROOT / "configs" / "small_cpu.yaml"), "training.threads=2",
                      "--threads", "1", "--device", "cpu"])
    assert rc == 0, err
    assert seen["threads"] == 1 and seen["device"] == "cpu"
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    rc, out, err = run(["train", str(ROOT / "configs" / "small_cpu.yaml"), "--device", "cuda"])
    assert rc != 0 and "training.device=cuda: PyTorch sees no CUDA GPU" in err + out
    assert "Traceback" not in err
