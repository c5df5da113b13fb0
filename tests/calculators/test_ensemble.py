"""Models as users load them: checkpoints with their references on the DFT energy scale,
ensembles with spreads, pretrained names, and the calculator's warnings."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest
import torch
from ase.calculators.calculator import CalculationFailed

from emlpack.calculators.ase import EMLPCalculator
from emlpack.calculators.ensemble import (
    EnsembleError,
    ModelEnsemble,
    as_ensemble,
    load_member,
    load_pretrained,
)
from emlpack.data.references import HydrideReference, hydride_coefficients, load_hydrides
from emlpack.io import read_structures, structure_to_atoms, write_structures
from emlpack.nn.checkpoint import save_model
from emlpack.pairs.relax import RelaxOptions
from emlpack.pairs.solvers import BatchedSolver
from emlpack.pretrained import (
    PretrainedError,
    available,
    export_pretrained,
    model_card,
    resolve_model,
)
from tests.conftest import shared_path
from tests.legacy.test_reference_fixtures import load_model


@pytest.fixture(scope="module")
def hydrides():
    return load_hydrides(shared_path("data/hydrides"))


@pytest.fixture(scope="module")
def models():
    """Two different float64 models: the reference fixture and a perturbed copy."""
    a = load_model("small").double()
    b = copy.deepcopy(a)
    with torch.no_grad():
        for p in b.parameters():
            p.mul_(1.02)
    return a, b


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory, models, hydrides):
    folder = tmp_path_factory.mktemp("models")
    ref = HydrideReference(*hydrides).to_metadata()
    paths = []
    for k, m in enumerate(models):
        paths.append(save_model(m, folder / f"model-{k}.pt",
                                {"reference": ref, "elements": [1, 6, 7, 8]}))
    return folder, paths


def _ethanol():
    s = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index=400)[0]
    return s


def _sound_c3h6():
    """A C3H6 frame whose pairs both test models relax to a minimum (on ethanol they merge
    pairs, and a command then reports no result)."""
    return read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index=525)[0]


def test_hydrides_are_their_dft_energies_on_the_dft_scale(checkpoints, hydrides):
    """E = U + c.(E_DFT - U_hyd): for a hydride at its stored centres, exactly E_DFT."""
    _, paths = checkpoints
    structures, energies = hydrides
    for s, e_dft in zip(structures, energies, strict=True):
        atoms = structure_to_atoms(s)
        atoms.calc = EMLPCalculator(paths[0], relax_pairs=False)
        assert atoms.get_potential_energy() == pytest.approx(e_dft, abs=1e-8)
        assert atoms.calc.results["energy_relative"] == pytest.approx(0.0, abs=1e-8)


def test_dft_scale_is_a_constant_shift(checkpoints, models, hydrides):
    _, paths = checkpoints
    s = _ethanol()
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(paths[0], relax_pairs=False)
    energy = atoms.get_potential_energy()
    u = models[0].evaluate(s)["energy"]
    u_hyd = np.array([models[0].evaluate(h)["energy"] for h in hydrides[0]])
    c = hydride_coefficients(s.numbers)
    assert energy == pytest.approx(u + c @ (hydrides[1] - u_hyd), abs=1e-8)
    assert atoms.calc.results["model_energy"] == pytest.approx(u, abs=1e-10)
    assert atoms.calc.results["energy_relative"] == pytest.approx(u - c @ u_hyd, abs=1e-8)
    # the shift is the same for any geometry: forces are the model's
    np.testing.assert_allclose(atoms.get_forces(), models[0].evaluate(s)["forces"], atol=1e-12)
    # a plain model (no reference) keeps the model's energy
    atoms.calc = EMLPCalculator(models[0], relax_pairs=False)
    assert atoms.get_potential_energy() == pytest.approx(u, abs=1e-10)


def test_ensemble_mean_and_spread(checkpoints, models):
    folder, _ = checkpoints
    s = _ethanol()
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(folder, relax_pairs=False)  # a folder is an ensemble
    assert len(atoms.calc.ensemble) == 2
    single = []
    for path in sorted(folder.glob("*.pt")):
        a = structure_to_atoms(s)
        a.calc = EMLPCalculator(path, relax_pairs=False)
        single.append((a.get_potential_energy(), a.get_forces(), a.get_dipole_moment()))
    e = np.array([x[0] for x in single])
    f = np.array([x[1] for x in single])
    res = atoms.calc.get_property("energy", atoms), atoms.calc.results
    assert res[0] == pytest.approx(e.mean(), abs=1e-10)
    assert res[1]["energy_std"] == pytest.approx(abs(e[0] - e[1]) / 2, abs=1e-10)
    assert res[1]["energy_std"] > 1e-4  # the members differ
    np.testing.assert_allclose(res[1]["forces_std"], np.abs(f[0] - f[1]) / 2, atol=1e-10)
    np.testing.assert_allclose(atoms.get_forces(), f.mean(axis=0), atol=1e-10)
    d = np.array([x[2] for x in single])
    np.testing.assert_allclose(res[1]["dipole_std"], np.abs(d[0] - d[1]) / 2, atol=1e-12)


def test_relaxed_ensemble_members_relax_their_own_pairs(models):
    s = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index=63)[0]  # methane
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(list(models), relax_options=RelaxOptions(fmax=1e-6))
    atoms.get_potential_energy()
    r = atoms.calc.relax_results
    assert len(r) == 2 and not r[0].reason and not r[1].reason
    assert np.abs(r[0].pairs - r[1].pairs).max() > 1e-5  # different minima
    np.testing.assert_allclose(atoms.calc.results["electron_pairs"],
                               (r[0].pairs + r[1].pairs) / 2, atol=1e-12)


class _FailingSolver:
    """A pair solver whose every relaxation fails (counts its calls)."""

    calls = 0

    def relax(self, model, structure):
        self.calls += 1
        return replace(BatchedSolver(RelaxOptions(fmax=1e-6)).relax(model, structure),
                       reason="stub failure")

    def reset(self):
        pass


def test_a_failed_member_raises_or_is_dropped_for_the_molecule(models):
    methane = structure_to_atoms(read_structures(shared_path("data/eqm7_pbe0_subset.xyz"),
                                                 index=63)[0])
    options = RelaxOptions(fmax=1e-6)
    methane.calc = EMLPCalculator(models[0], relax_options=options)
    alone = methane.get_potential_energy()

    methane.calc = EMLPCalculator(list(models), relax_options=options)  # the default: raise
    methane.calc.pair_solvers[1] = _FailingSolver()
    with pytest.raises(CalculationFailed, match=r"\(model 1: .*stub failure"):
        methane.get_potential_energy()

    calc = EMLPCalculator(list(models), relax_options=options, failed_members="drop")
    failing = calc.pair_solvers[1] = _FailingSolver()
    methane.calc = calc
    assert methane.get_potential_energy() == pytest.approx(alone, abs=1e-9)
    assert calc.results["energy_std"] == 0.0 and calc.dropped == {1: "stub failure"}
    assert any("model 1 (" in w and "left out" in w and "1 of 2 models" in w
               for w in calc.warnings)
    moved = methane.copy()
    moved.positions[1] += [0.01, 0.0, 0.0]
    moved.calc = calc
    moved.get_potential_energy()  # the same molecule: member 1 stays out, still said
    assert failing.calls == 1 and len(calc.relax_results) == 1
    assert any("left out" in w for w in calc.warnings)

    ethene = structure_to_atoms(read_structures(shared_path("data/eqm7_pbe0_subset.xyz"),
                                                index=200)[0])
    calc.pair_solvers[1] = BatchedSolver(options)
    ethene.calc = calc
    ethene.get_potential_energy()  # another molecule: every member again
    assert calc.dropped == {} and calc.results["energy_std"] > 0
    assert not any("left out" in w for w in calc.warnings)

    calc.pair_solvers = [_FailingSolver(), _FailingSolver()]
    methane.calc = calc
    with pytest.raises(CalculationFailed, match="every other member had failed before"):
        methane.get_potential_energy()
    with pytest.raises(ValueError, match="failed_members"):
        EMLPCalculator(models[0], failed_members="ignore")


class _SaddleSolver:
    """A pair solver that relaxes as usual but reports a negative smallest pair curvature
    (a saddle) without calling it a failure, as a solver that does not judge one would."""

    def relax(self, model, structure):
        return replace(BatchedSolver(RelaxOptions(fmax=1e-6)).relax(model, structure),
                       min_curvature=-0.5, reason="")

    def reset(self):
        pass


def test_a_member_whose_pairs_are_not_at_a_minimum_is_a_failed_member(models):
    """The calculator reads the curvature itself: a member at a saddle is left out (drop) or
    raises, like a failed relaxation, even when its solver reports no failure."""
    methane = structure_to_atoms(read_structures(shared_path("data/eqm7_pbe0_subset.xyz"),
                                                 index=63)[0])
    options = RelaxOptions(fmax=1e-6)
    methane.calc = EMLPCalculator(models[0], relax_options=options)
    alone = methane.get_potential_energy()
    calc = EMLPCalculator(list(models), relax_options=options, failed_members="drop")
    calc.pair_solvers[1] = _SaddleSolver()
    methane.calc = calc
    assert methane.get_potential_energy() == pytest.approx(alone, abs=1e-9)
    assert list(calc.dropped) == [1] and "negative pair curvature -0.5" in calc.dropped[1]
    methane.calc = EMLPCalculator(list(models), relax_options=options)
    methane.calc.pair_solvers[1] = _SaddleSolver()
    with pytest.raises(CalculationFailed, match="negative pair curvature -0.5 eV/Å"):
        methane.get_potential_energy()


def test_callers_model_is_not_converted(models):
    m32 = copy.deepcopy(models[0]).float()
    EMLPCalculator(m32, relax_pairs=False, dtype=torch.float64)
    assert next(m32.parameters()).dtype == torch.float32


def test_warnings_for_unknown_elements_spread_and_bonding(checkpoints, models, hydrides):
    _, paths = checkpoints
    member = load_member(paths[0])
    member.elements = (1, 6, 8)  # as if trained without nitrogen
    nh3 = structure_to_atoms(hydrides[0][2])
    nh3.calc = EMLPCalculator(ModelEnsemble([member]), relax_pairs=False)
    nh3.get_potential_energy()
    assert any("Z=[7]" in w and "training set" in w for w in nh3.calc.warnings)

    s = _ethanol()
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(list(models), relax_pairs=False, energy_spread_warning=1e-9,
                                force_spread_warning=1e-9)
    atoms.get_potential_energy()
    assert any("energy spread" in w for w in atoms.calc.warnings)
    assert any("force spread" in w for w in atoms.calc.warnings)

    atoms.calc = EMLPCalculator(models[0], relax_pairs=False)
    atoms.get_potential_energy()
    assert atoms.calc.warnings == []
    o = int(np.flatnonzero(atoms.numbers == 8)[0])
    c = int(np.argmin(np.where(atoms.numbers == 6,
                               np.linalg.norm(atoms.positions - atoms.positions[o], axis=1),
                               np.inf)))
    stretched = atoms.copy()
    stretched.info = dict(atoms.info)
    v = stretched.positions[o] - stretched.positions[c]
    stretched.positions[o] = stretched.positions[c] + 2.4 * v / np.linalg.norm(v)
    stretched.calc = atoms.calc
    stretched.get_potential_energy()
    assert any("bonding changed" in w and "broken" in w for w in atoms.calc.warnings)


def test_model_names_and_folders(checkpoints, tmp_path):
    folder, paths = checkpoints
    assert resolve_model(paths[0])[0] == [paths[0]]
    assert resolve_model(folder)[0] == sorted(paths)
    with pytest.raises(PretrainedError, match="no such model file"):
        resolve_model("no-such-model")
    with pytest.raises(PretrainedError, match="folder holds no"):
        resolve_model(tmp_path)
    # a pretrained model installed under a root: loaded by name, with its members
    root = tmp_path / "pretrained"
    (root / "toy").mkdir(parents=True)
    for k, p in enumerate(paths):
        (root / "toy" / f"model-{k}.pt").write_bytes(p.read_bytes())
    assert available(root) == ["toy"]
    ens = load_pretrained("toy", root=root)
    assert len(ens) == 2 and ens.dft_scale and ens.elements == {1, 6, 7, 8}
    with pytest.raises(PretrainedError, match="not installed"):
        resolve_model("mini-eqm7", root=root)


def test_mixed_ensembles_are_refused(checkpoints, models):
    _, paths = checkpoints
    with pytest.raises(EnsembleError, match="disagree"):
        as_ensemble([paths[0], models[1]])


def test_export_pretrained_float32_round_trip(checkpoints, tmp_path):
    folder, paths = checkpoints
    root = tmp_path / "pretrained"
    files = export_pretrained(paths, root / "toy", "# toy\n\ntwo perturbed fixture models\n")
    assert [f.name for f in files] == ["model-0.pt", "model-1.pt", "card.md"]
    assert model_card("toy", root).startswith("# toy")
    # exported again with fewer members: the folder holds only the new ensemble
    export_pretrained(paths, root / "smaller", "# smaller\n")
    export_pretrained(paths[:1], root / "smaller", "# smaller\n")
    assert sorted(p.name for p in (root / "smaller").iterdir()) == ["card.md", "model-0.pt"]
    assert len(load_pretrained("smaller", root=root).members) == 1
    s = _ethanol()
    energies = {}
    for label, model in (("full", folder), ("shipped", "toy")):
        atoms = structure_to_atoms(s)
        atoms.calc = EMLPCalculator(model if label == "full" else
                                    load_pretrained(model, root=root), relax_pairs=False)
        energies[label] = (atoms.get_potential_energy(), atoms.get_forces())
    # float32 weights: energies on the DFT scale within float32 rounding of the weights
    assert energies["shipped"][0] == pytest.approx(energies["full"][0], abs=2e-3)
    np.testing.assert_allclose(energies["shipped"][1], energies["full"][1], atol=2e-3)
    with pytest.raises(PretrainedError, match="no training reference"):
        from emlpack.nn.checkpoint import save_model as _save

        bare = _save(load_member(paths[0]).model, tmp_path / "bare.pt")
        export_pretrained([bare], tmp_path / "x", "")


def test_a_models_notice_is_in_every_result_and_logged_once(checkpoints, tmp_path, caplog):
    """A preliminary export's notice (its metadata) is among the warnings of every calculation
    and of the command-line JSON, and is logged once per calculator, not at every step."""
    import json
    import logging

    from emlpack.cli import main

    _, paths = checkpoints
    root = tmp_path / "pretrained"
    notice = "toy is a preliminary ensemble: check important results with DFT"
    export_pretrained(paths, root / "toy", "# toy\n", notice=notice)
    ensemble = load_pretrained("toy", root=root)
    assert ensemble.notices == [notice]
    atoms = structure_to_atoms(_ethanol())
    atoms.calc = EMLPCalculator(ensemble, relax_pairs=False)
    with caplog.at_level(logging.WARNING):
        for shift in (0.0, 0.01):
            atoms.positions[0, 0] += shift
            atoms.get_potential_energy()
            assert notice in atoms.calc.warnings
    assert sum(notice in r.getMessage() for r in caplog.records) == 1
    out = tmp_path / "pol.json"
    xyz = tmp_path / "c3h6.xyz"  # a molecule whose pairs both members relax to a minimum
    write_structures(xyz, _sound_c3h6())
    assert main(["polarizability", str(root / "toy"), str(xyz), "-o", str(out), "--quiet"]) == 0
    assert notice in json.loads(out.read_text())["warnings"]


def test_a_molecule_larger_than_the_training_molecules_is_warned_once(checkpoints, tmp_path,
                                                                      caplog):
    """The export records the largest training molecule (the checkpoint's own value wins over
    ``domain``); a larger molecule is warned about at every call, logged once."""
    import logging

    from emlpack.nn.checkpoint import read_checkpoint

    _, paths = checkpoints
    root = tmp_path / "pretrained"
    export_pretrained(paths, root / "small", "# small\n", domain={"max_heavy_atoms": 2})
    assert load_pretrained("small", root=root).max_heavy_atoms == 2
    atoms = structure_to_atoms(_ethanol())  # 3 heavy atoms
    atoms.calc = EMLPCalculator(load_pretrained("small", root=root), relax_pairs=False)
    with caplog.at_level(logging.WARNING):
        for shift in (0.0, 0.01):
            atoms.positions[0, 0] += shift
            atoms.get_potential_energy()
            assert any("3 heavy atoms" in w and "at most 2" in w for w in atoms.calc.warnings)
    assert sum("3 heavy atoms" in r.getMessage() for r in caplog.records) == 1
    # the property commands say so too, in their JSON
    import json

    from emlpack.cli import main

    xyz, out = tmp_path / "c3h6.xyz", tmp_path / "pol.json"
    write_structures(xyz, _sound_c3h6())  # 3 heavy atoms, relaxed by both members
    assert main(["polarizability", str(root / "small"), str(xyz), "-o", str(out),
                 "--quiet"]) == 0
    assert any("3 heavy atoms" in w for w in json.loads(out.read_text())["warnings"])
    # recorded in the checkpoint: kept over the export's domain
    big = root / "big"
    export_pretrained(paths, big, "# big\n", domain={"max_heavy_atoms": 7})
    export_pretrained(sorted(big.glob("model-*.pt")), root / "again", "# again\n",
                      domain={"max_heavy_atoms": 2})
    assert read_checkpoint(root / "again" / "model-0.pt")["metadata"]["max_heavy_atoms"] == 7
    atoms.calc = EMLPCalculator(load_pretrained("again", root=root), relax_pairs=False)
    atoms.get_potential_energy()
    assert atoms.calc.warnings == []


def test_an_ensemble_of_two_families(tmp_path):
    """Members of different short-range families in one ensemble (checkpoints in a folder):
    the ensemble's energy and forces are the mean of its members', each relaxing its own
    pairs."""
    from tests.nn.helpers import FAMILIES, random_model, water_molecule

    folder = tmp_path / "mixed"
    folder.mkdir()
    for k, family in enumerate(FAMILIES[:2]):
        save_model(random_model(family=family), folder / f"model-{k}.pt")
    s = water_molecule()
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(folder, relax_options=RelaxOptions(fmax=1e-8))
    assert [m.model.config.family for m in atoms.calc.ensemble.members] == list(FAMILIES[:2])
    single = []
    for path in sorted(folder.glob("*.pt")):
        a = structure_to_atoms(s)
        a.calc = EMLPCalculator(path, relax_options=RelaxOptions(fmax=1e-8))
        single.append((a.get_potential_energy(), a.get_forces()))
    assert atoms.get_potential_energy() == pytest.approx(np.mean([x[0] for x in single]),
                                                         abs=1e-8)
    np.testing.assert_allclose(atoms.get_forces(), np.mean([x[1] for x in single], axis=0),
                               atol=1e-6)
    assert atoms.calc.results["energy_std"] > 1e-3
