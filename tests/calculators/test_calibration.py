"""Spread warnings calibrated on held-out molecules: the thresholds are quantiles of the
ensemble's spreads there, shipped in every member, used by the calculator and the commands."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

from emlpack.calculators.ase import EMLPCalculator
from emlpack.calculators.calibration import (
    calibrate_spread,
    result_spread,
    spread_and_error,
    warned_fraction,
)
from emlpack.calculators.ensemble import (
    ENERGY_SPREAD_WARNING,
    FORCE_SPREAD_WARNING,
    SpreadThresholds,
    as_ensemble,
    load_member,
    load_pretrained,
    spread_thresholds,
)
from emlpack.data.references import HydrideReference, load_hydrides
from emlpack.io import read_structures, structure_to_atoms, write_structures
from emlpack.nn.checkpoint import save_model
from emlpack.pretrained import export_pretrained
from tests.conftest import shared_path
from tests.legacy.test_reference_fixtures import load_model


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Three members: the reference fixture's small model and two perturbed copies, saved
    with the DFT hydride references (energies on the DFT scale)."""
    folder = tmp_path_factory.mktemp("members")
    meta = {"reference": HydrideReference(*load_hydrides(shared_path("data/hydrides")))
            .to_metadata(), "elements": [1, 6, 7, 8]}
    base = load_model("small").double()
    paths = []
    for k, factor in enumerate((1.0, 1.02, 0.985)):
        m = copy.deepcopy(base)
        with torch.no_grad():
            for p in m.parameters():
                p.mul_(factor)
        paths.append(save_model(m, folder / f"model-{k}.pt", meta))
    return paths


@pytest.fixture(scope="module")
def frames():
    """24 labeled configurations of the authors' six molecules (held out from these models'
    perturbation, so their spreads vary)."""
    return read_structures(shared_path("data/eqm7_pbe0_subset.xyz"))[::25]


def test_thresholds_are_quantiles_of_the_held_out_spreads(checkpoints, frames):
    ensemble = as_ensemble(checkpoints)
    cal = calibrate_spread(ensemble, frames, "test frames", quantile=0.9, relax_pairs=False)
    # the spreads and errors, computed member by member
    e_spread, e_error, f_spread = [], [], []
    for s in frames:
        energies, forces = [], []
        for path in checkpoints:
            atoms = structure_to_atoms(s)
            atoms.calc = EMLPCalculator(path, relax_pairs=False)
            energies.append(atoms.get_potential_energy())
            forces.append(atoms.get_forces())
        n = len(s.numbers)
        e_spread.append(np.std(energies) / n)
        e_error.append(abs(np.mean(energies) - s.energy) / n)
        f_spread.append(np.max(np.std(forces, axis=0)))
    assert cal["configurations"] == len(frames) and cal["failed"] == 0
    assert cal["members"] == 3 and cal["pairs"] == "labeled centres"
    assert cal["energy_eV_per_atom"] == pytest.approx(np.quantile(e_spread, 0.9), rel=1e-9)
    assert cal["forces_eV_per_A"] == pytest.approx(np.quantile(f_spread, 0.9), rel=1e-9)
    assert cal["median"]["energy_error"] == pytest.approx(np.median(e_error), rel=1e-9)
    assert cal["error_over_spread"]["energy"] == pytest.approx(
        np.median(e_error) / np.median(e_spread), rel=1e-9)
    # by construction they warn on at most 10 % of the calibration set (ties aside)
    r = spread_and_error(ensemble, frames, relax_pairs=False)
    warned = warned_fraction(r, SpreadThresholds.calibrated(cal, 3))
    assert 0 < warned["energy"] <= 0.1 + 1 / len(frames)
    assert 0 < warned["forces"] <= 0.1 + 1 / len(frames)
    assert warned["either"] >= max(warned["energy"], warned["forces"])
    with pytest.raises(ValueError, match="too few"):
        calibrate_spread(ensemble, frames[:5], "five frames", relax_pairs=False)


def test_shipped_calibration_sets_the_calculators_and_the_commands_warnings(
        checkpoints, frames, tmp_path):
    ensemble = as_ensemble(checkpoints)
    r = spread_and_error(ensemble, frames, relax_pairs=False)
    # a calibration between the smallest and the largest energy spread of these frames
    quiet, loud = int(np.argmin(r["energy_spread"])), int(np.argmax(r["energy_spread"]))
    threshold = float(np.sqrt(r["energy_spread"][quiet] * r["energy_spread"][loud]))
    cal = {"energy_eV_per_atom": threshold, "forces_eV_per_A": 1e3, "quantile": 0.95,
           "set": "the test frames", "configurations": 20, "failed": 0, "members": 3,
           "pairs": "labeled centres"}
    export_pretrained(checkpoints, tmp_path / "shipped", "# card\n", spread_calibration=cal)
    shipped = load_pretrained("shipped", root=tmp_path)
    t = shipped.spread_thresholds
    assert t.energy == pytest.approx(threshold) and t.forces == 1e3
    assert t.basis.startswith("calibrated: exceeded on 5% of 20 configurations of the test")

    def warnings(k, **kwargs):
        atoms = structure_to_atoms(frames[k])
        atoms.calc = EMLPCalculator(shipped, relax_pairs=False, **kwargs)
        atoms.get_potential_energy()
        return [w for w in atoms.calc.warnings if "spread" in w]

    assert warnings(quiet) == []
    (w,) = warnings(loud)
    assert "energy spread" in w and "calibrated" in w and f"{threshold:.3g} eV/atom" in w
    # given thresholds win over the calibration
    assert warnings(loud, energy_spread_warning=1e3) == []
    assert "(given)" in warnings(quiet, energy_spread_warning=0.0)[0]
    # fewer members than calibrated: thresholds scaled as the expected population spread
    two = spread_thresholds(shipped.members[:2])
    assert two.energy == pytest.approx(threshold * np.sqrt(0.5 / (2 / 3)))
    assert "scaled to 2 of 3 members" in two.basis
    # members of different calibrations, or none: the heuristic thresholds
    other = load_member(checkpoints[0])
    assert spread_thresholds([shipped.members[0], other]) == SpreadThresholds(
        ENERGY_SPREAD_WARNING, FORCE_SPREAD_WARNING, "heuristic")

    # the commands check the ensemble's energy spread against the same thresholds, at pairs
    # of a minimum (at the labeled centres the pairs are not, and a command reports nothing):
    # a calibration between the two frames' spreads there
    from emlpack.cli import main
    from emlpack.pairs.relax import relax_pairs

    relaxed = [frames[k].copy(pairs=relax_pairs(shipped.members[0].model, frames[k],
                                                fmax=1e-6)[0].pairs) for k in (quiet, loud)]
    spreads = []
    for structure in relaxed:
        atoms = structure_to_atoms(structure)
        atoms.calc = EMLPCalculator(shipped, relax_pairs=False)
        atoms.get_potential_energy()
        spreads.append(atoms.calc.results["energy_std"] / len(atoms))
    order = np.argsort(spreads)
    cal = dict(cal, energy_eV_per_atom=float(np.sqrt(spreads[0] * spreads[1])))
    export_pretrained(checkpoints, tmp_path / "relaxed", "# card\n", spread_calibration=cal)
    flags = []
    for k in order:
        xyz = tmp_path / f"frame{k}.xyz"
        write_structures(xyz, [relaxed[k]])
        out = tmp_path / f"pol{k}.json"
        assert main(["polarizability", str(tmp_path / "relaxed"), str(xyz), "-o", str(out),
                     "--quiet", "--relax", "none"]) == 0
        spread = [w for w in json.loads(out.read_text())["warnings"] if "energy spread" in w]
        assert all("calibrated" in w for w in spread)
        flags.append(bool(spread))
    assert flags == [False, True]


def test_pair_spread_is_the_largest_pair_coordinate_std_over_members():
    """Two models relaxing the pairs of one molecule: ``electron_pairs_std`` is the population
    std over the members of every pair coordinate (each member from the same start, so pair k
    is the same pair in both), and ``result_spread`` reduces the calculator's spreads to their
    largest components (energy per atom)."""
    methane = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"))[0]
    models = [load_model("small").double(), load_model("small").double()]
    with torch.no_grad():
        for p in models[1].parameters():
            p.mul_(1.02)
    atoms = structure_to_atoms(methane)
    atoms.calc = EMLPCalculator(models, check_bonding=False)
    atoms.get_potential_energy()
    r = atoms.calc.results
    pairs = np.array([res.pairs for res in atoms.calc.relax_results])
    np.testing.assert_allclose(r["electron_pairs_std"], pairs.std(axis=0), atol=1e-14)
    spread = result_spread(r, len(atoms))
    assert spread["pair_spread"] == pytest.approx(float(pairs.std(axis=0).max()))
    assert spread["pair_spread"] > 0
    assert spread["force_spread"] == pytest.approx(float(np.max(r["forces_std"])))
    assert spread["energy_spread"] == pytest.approx(r["energy_std"] / len(atoms))
