"""The MODEL argument of the commands: checkpoints with their DFT hydride references report
energies on the DFT scale; ensembles and pretrained names give one clear line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from emlpack.calculator import EMLPCalculator
from emlpack.data.references import HydrideReference, load_hydrides
from emlpack.io import read_structures, structure_to_atoms
from emlpack.nn.checkpoint import load_model, save_model
from tests.cli_helpers import run, save_test_model, water_rows, write_xyz
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


def test_ensembles_and_pretrained_names_give_one_line(referenced_model, tmp_path, capsys):
    from emlpack.cli import main

    water = write_xyz(tmp_path / "w.xyz", water_rows(4))
    folder = tmp_path / "ensemble"
    folder.mkdir()
    for k in range(2):
        (folder / f"model-{k}.pt").write_bytes(referenced_model.read_bytes())
    for model, expected in ((str(folder), "an ensemble of 2 models"),
                            ("mini-eqm7", "is not installed"),
                            ("no-such-name", "no such model file, folder or pretrained name")):
        rc = main(["polarizability", model, str(water)])
        err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
        assert rc == 2 and len(err) == 1 and expected in err[0], err
    # a folder holding one checkpoint is that model
    single = tmp_path / "single"
    single.mkdir()
    (single / "model.pt").write_bytes(referenced_model.read_bytes())
    out = tmp_path / "pol.json"
    assert main(["polarizability", str(single), str(water), "-o", str(out), "--quiet"]) == 0
    assert np.isfinite(json.loads(out.read_text())["polarizability_isotropic_bohr3"])
