"""`emlp label`: sampling recipe -> DFT labels -> HDF5 store; resumable after kill -9; Dask."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from emlpack.cli import main
from emlpack.data.store import DatasetStore
from emlpack.qm.recipe import configurations, load_recipe, rescale_counts
from emlpack.qm.sampling import SamplingError
from emlpack.units import FIELD_AU_IN_V_PER_A
from tests.conftest import ROOT


def counting_emt():
    """ASE's EMT calculator class with a counter of its calculations (``cls.calls``)."""
    from ase.calculators.emt import EMT

    class Counting(EMT):
        calls = 0

        def calculate(self, *args, **kwargs):
            Counting.calls += 1
            super().calculate(*args, **kwargs)

    return Counting

# tiny level, no optimisation, one Boys start: seconds per configuration
QUICK = ["--level", "tiny", "-s", "prepare.optimize=false", "-s", "boys_starts=1",
         "-s", "hydrides=false"]


def _smiles_file(tmp_path, smiles=("C", "CC")):
    path = tmp_path / "mols.smi"
    path.write_text("".join(f"{s} mol{i}\n" for i, s in enumerate(smiles)))
    return path


def _check_store(path, n_expected, level="pbe0/sto-3g"):
    with DatasetStore(path) as st:
        keys = st.keys()
        failed = [f["key"] for f in st.failures()]
        assert len(keys) == len(set(keys)), "duplicate records"
        assert not set(keys) & set(failed)
        assert len(keys) + len(failed) == n_expected, (len(keys), failed)
        for s in st:
            assert np.isfinite(s.energy) and s.forces is not None
            assert s.info["level"] == level and s.info["key"].startswith(s.info["molecule_id"])
        return keys, st.failures()


def test_recipe_defaults_overrides_and_rescaling(tmp_path):
    r = load_recipe()
    assert [s["count"] for s in r["samples"]] == [100, 100, 150, 150]
    assert r["level"] == "paper" and r["field_max_au"] == 0.01
    r = load_recipe(None, ["level=tiny", "prepare.optimize=false"], samples_per_molecule=10)
    assert [s["count"] for s in r["samples"]] == [2, 2, 3, 3]
    assert r["level"] == "tiny" and r["prepare"]["optimize"] is False
    assert sum(s["count"] for s in rescale_counts(r["samples"], 7)) == 7
    bad = tmp_path / "bad.yaml"
    bad.write_text("samples:\n  - {kind: a/b, count: 1}\n")
    with pytest.raises(SamplingError, match="contains '/'"):
        load_recipe(bad)


def test_configurations_are_reproducible_and_skip_done_keys():
    from emlpack.qm.sampling import Molecule

    rng = np.random.default_rng(0)
    pos = np.array([[0, 0, 0], [0.63, 0.63, 0.63], [-0.63, -0.63, 0.63], [-0.63, 0.63, -0.63],
                    [0.63, -0.63, -0.63]])
    n = 15
    a = rng.normal(size=(n, n))
    mol = Molecule("m", np.array([6, 1, 1, 1, 1]), pos, hessian=a @ a.T + n * np.eye(n))
    probe = Molecule("H2O", np.array([8, 1, 1]),
                     np.array([[0, 0, 0], [0.96, 0, 0], [-0.24, 0.93, 0]]), hessian=np.eye(9) * 5)
    recipe = load_recipe(None, samples_per_molecule=8)
    confs = configurations(mol, recipe, {"H2O": probe})
    again = configurations(mol, recipe, {"H2O": probe}, skip={confs[0].key, confs[5].key})
    assert len(confs) == 8 and len(again) == 6
    by_key = {c.key: c for c in confs}
    for c in again:  # a resumed run regenerates exactly the same configurations
        np.testing.assert_array_equal(c.positions, by_key[c.key].positions)
        np.testing.assert_array_equal(c.field, by_key[c.key].field)
    dimers = [c for c in confs if c.kind == "nms800-dimer"]
    assert dimers and all(len(c.numbers) == 8 for c in dimers)


def _nms_only_recipe(tmp_path, count):
    path = tmp_path / "recipe.yaml"
    path.write_text(f"samples:\n  - {{kind: nms600, count: {count}, temperature: 600}}\n")
    return path


def _label_cmd(tmp_path, smi, store, workers):
    return [sys.executable, "-m", "emlpack.cli", "label", str(smi), "-o", str(store),
            "--recipe", str(_nms_only_recipe(tmp_path, 4)), "--workers", str(workers),
            "--quiet", *QUICK]


def test_label_resumes_after_kill_9(tmp_path):
    """kill -9 of a running `emlp label`, then the same command: no loss, no duplicates."""
    smi = _smiles_file(tmp_path, ("C",))
    store = tmp_path / "s.h5"
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"), OMP_NUM_THREADS="1")
    proc = subprocess.Popen(_label_cmd(tmp_path, smi, store, 0), env=env,
                            start_new_session=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    before: dict[str, float] = {}
    try:
        deadline = time.time() + 240
        while time.time() < deadline and proc.poll() is None:
            time.sleep(0.5)
            if store.exists():
                try:
                    with DatasetStore(store) as st:
                        if len(st) >= 1:
                            before = {s.info["key"]: s.energy for s in st}
                            break
                except Exception:  # noqa: BLE001 - the writer may be creating the file
                    pass
        assert proc.poll() is None, "labeling ended before it could be killed"
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL and before
    with DatasetStore(store) as st:
        n_killed = len(st)
        assert 1 <= n_killed < 4
    rerun = subprocess.run(_label_cmd(tmp_path, smi, store, 0), env=env, capture_output=True,
                           text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr
    assert f"{n_killed} already done" in rerun.stdout
    keys, _ = _check_store(store, 4)
    with DatasetStore(store) as st:
        after = {s.info["key"]: s.energy for s in st}
    for key, energy in before.items():  # finished work is kept as it was
        assert after[key] == energy


def test_label_on_a_two_worker_local_cluster(tmp_path):
    """The Dask path: 2 worker processes, 2 molecules x 2 samples, then nothing left to do."""
    smi = _smiles_file(tmp_path, ("C", "N"))
    store = tmp_path / "s.h5"
    args = ["label", str(smi), "-o", str(store), "--recipe",
            str(_nms_only_recipe(tmp_path, 2)), "--workers", "2", "--quiet", *QUICK]
    assert main(args) == 0
    keys, failures = _check_store(store, 4)
    assert {k.split("/")[0] for k in keys} == {"mol0", "mol1"}
    assert (tmp_path / "s.h5.prep" / "mol0.npz").exists()
    with DatasetStore(store) as st:
        assert {s.info["kind"] for s in st} == {"nms600"}
        assert "pbe0/sto-3g" in st.metadata["level"]
        assert all(np.linalg.norm(s.field) <= 0.01 * FIELD_AU_IN_V_PER_A for s in st)
    assert main(args) == 0  # second run: everything done, nothing added
    assert _check_store(store, 4)[0] == keys


def test_label_refuses_a_different_recipe_and_reports_bad_input(tmp_path, capsys):
    smi = _smiles_file(tmp_path, ("C",))
    store = tmp_path / "s.h5"
    with DatasetStore(store, "a") as st:
        st.set_metadata(recipe="something else")
    assert main(["label", str(smi), "-o", str(store), "--workers", "0", *QUICK]) == 2
    assert "different recipe" in capsys.readouterr().err
    assert main(["label", str(tmp_path / "none.csv"), "-o", str(store), *QUICK]) == 2
    assert "none.csv: file not found" in capsys.readouterr().err


@pytest.mark.slow
def test_three_qm7_molecules_ten_samples_quick_preset_with_kill(tmp_path):
    """Issue 3's acceptance run: 3 QM7 molecules x 10 samples at 'quick', killed, resumed."""
    from tests.conftest import shared_path

    csv = shared_path("data/qm7_smiles.csv")
    store = tmp_path / "s.h5"
    cmd = [sys.executable, "-m", "emlpack.cli", "label", str(csv), "-o", str(store),
           "--molecules", "0:3", "--samples-per-molecule", "10", "--level", "quick",
           "--workers", "2", "--quiet", "-s", "hydrides=false"]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    proc = subprocess.Popen(cmd, env=env, start_new_session=True)
    try:
        while proc.poll() is None:
            time.sleep(2)
            if store.exists():
                try:
                    with DatasetStore(store) as st:
                        if len(st) >= 5:
                            break
                except Exception:  # noqa: BLE001
                    pass
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    subprocess.run(cmd, env=env, check=True, timeout=7200)
    _check_store(store, 30, level="pbe0/6-31g*")


def test_read_molecules_from_csv_smiles_and_xyz(tmp_path):
    from emlpack.qm.labeling import read_molecules

    csv = tmp_path / "m.csv"
    csv.write_text("smiles,target\nC,1\nCS,2\n[H]OC([H])([H])C([H])([H])[H],3\n")
    sources, skipped = read_molecules(csv)
    assert [s[0] for s in sources] == ["m-0000", "m-0002"]
    assert skipped == ["m-0001: contains sulfur (out of scope)"]
    assert read_molecules(csv, "1:")[0][0][0] == "m-0002"
    xyz = tmp_path / "ethanol.xyz"
    xyz.write_text(
        "9\n\nC -0.0011 -0.0034 0.0\nC 1.5127 0.0120 0.0\nO 1.9594 1.3537 0.0\n"
        "H -0.3819 -1.0279 0.0\nH -0.3897 0.5098 0.8840\nH -0.3897 0.5098 -0.8840\n"
        "H 1.8980 -0.5000 0.8800\nH 1.8980 -0.5000 -0.8800\nH 2.9230 1.3400 0.0\n"
    )
    (mol,), _ = read_molecules(xyz)
    assert mol.name == "ethanol-0000" and len(mol.bonds) == 8
    assert len(mol.rotatable_bonds()) == 2


def test_hydride_references_are_stored_with_the_dataset_fast(tmp_path):
    """The default-suite version of the slow test below: H2 as the data set's molecule, one
    Boys start and a looser optimisation (prepare.fmax 0.05 eV/Å)."""
    _check_hydride_references(tmp_path, "boys_starts: 1\nprepare: {fmax: 0.05}\n", fmax=0.05,
                              smiles="[H][H]")


@pytest.mark.slow
def test_hydride_references_are_stored_with_the_dataset(tmp_path):
    """hydrides: true labels optimised H2, CH4, NH3, H2O at the labeling level."""
    _check_hydride_references(tmp_path, "", fmax=0.05)


def _check_hydride_references(tmp_path, extra_recipe: str, fmax: float, smiles: str = "C"):
    smi = _smiles_file(tmp_path, (smiles,))
    recipe = tmp_path / "r.yaml"
    recipe.write_text("samples: []\nhydrides: true\n" + extra_recipe)
    store = tmp_path / "s.h5"
    assert main(["label", str(smi), "-o", str(store), "--recipe", str(recipe), "--level",
                 "tiny", "--workers", "0", "--quiet"]) == 0
    with DatasetStore(store) as st:
        refs = st.references()
        assert set(refs) == {"H2", "CH4", "NH3", "H2O"}
        assert all(r["level"] == "pbe0/sto-3g" for r in refs.values())
        by_id = {s.info["molecule_id"]: s for s in st}
        assert {k: s.info["kind"] for k, s in by_id.items()} == dict.fromkeys(refs, "hydride")
        for name, s in by_id.items():
            assert s.energy == refs[name]["energy"]
            assert np.abs(s.forces).max() < fmax  # optimised at the same level
        assert by_id["H2O"].n_pairs == 4 and by_id["H2"].n_pairs == 1


def test_finite_difference_hessian_resumes_from_its_cache(tmp_path):
    """The cached finite-difference Hessian equals an uncached one, and a rerun after a kill
    recomputes only the displacements whose files are empty or cut (EMT water, 18
    displacements)."""
    from ase.build import molecule

    from emlpack.qm.labeling import finite_difference_hessian

    Counting = counting_emt()
    atoms = molecule("H2O")
    atoms.calc = Counting()
    plain = finite_difference_hessian(atoms)
    cache = tmp_path / "vib"
    first = finite_difference_hessian(atoms, cache=cache)
    np.testing.assert_allclose(first, plain, rtol=0, atol=1e-12)
    np.testing.assert_allclose(first, first.T, atol=1e-3)  # a Hessian, and finite differences
    files = sorted(f for f in cache.glob("cache.*.json") if f.name != "cache.eq.json")
    assert len(files) == 2 * 3 * len(atoms)  # and the undisplaced cache.eq.json
    files[0].write_text("")                                # locked, killed before writing
    files[1].write_text(files[1].read_text()[:20])         # killed while writing
    Counting.calls = 0
    again = finite_difference_hessian(atoms, cache=cache)
    assert Counting.calls == 2
    np.testing.assert_allclose(again, first, rtol=0, atol=1e-12)


def test_internal_hessian_gives_the_frequencies_with_fewer_force_calls(tmp_path):
    """Central differences along the 3N - 6 vibrational directions only: on a quadratic
    potential (where central differences are exact) the frequencies equal those of the exact
    Hessian to 1e-9; on EMT methanol they equal the Cartesian scheme's within its O(delta^2)
    error with 31 instead of 37 force calls; translations and rotations are exactly zero; a
    rerun recomputes only missing displacements, and a moved geometry is refused."""
    from ase.build import molecule
    from ase.calculators.calculator import Calculator, all_changes

    from emlpack.geometry import normal_modes, rigid_body_modes
    from emlpack.qm.labeling import finite_difference_hessian
    from emlpack.qm.pyscf_labeler import LabelingError

    Counting = counting_emt()
    atoms = molecule("CH3OH")
    n, m = len(atoms), atoms.get_masses()
    rng = np.random.default_rng(3)
    b = rng.normal(size=(3 * n, 3 * n))
    k_exact = b @ b.T + np.eye(3 * n)
    x0 = atoms.positions.copy()

    class Quadratic(Calculator):
        implemented_properties = ["energy", "forces"]

        def calculate(self, atoms=None, properties=("energy",), system_changes=all_changes):
            super().calculate(atoms, properties, system_changes)
            u = (self.atoms.positions - x0).ravel()
            self.results = {"energy": 0.5 * u @ k_exact @ u,
                            "forces": -(k_exact @ u).reshape(-1, 3)}

    atoms.calc = Quadratic()
    h = finite_difference_hessian(atoms, 0.01, cache=tmp_path / "q", directions="internal")
    np.testing.assert_allclose(normal_modes(h, x0, m)[0], normal_modes(k_exact, x0, m)[0],
                               rtol=1e-9, atol=1e-9)

    atoms.calc = Counting()
    cartesian = finite_difference_hessian(atoms)
    Counting.calls = 0
    cache = tmp_path / "vib-internal"
    internal = finite_difference_hessian(atoms, cache=cache, directions="internal")
    assert Counting.calls == 2 * (3 * n - 6) + 1
    w_c, w_i = normal_modes(cartesian, x0, m)[0], normal_modes(internal, x0, m)[0]
    assert np.abs(w_i - w_c).max() < 1e-4 * np.abs(w_c).max()
    rb = rigid_body_modes(x0, m) * np.repeat(1.0 / np.sqrt(m), 3)[:, None]  # Cartesian rigid
    assert np.abs(internal @ rb).max() < 1e-10 * np.abs(internal).max()
    np.testing.assert_allclose(internal, internal.T, atol=1e-12)
    for f in sorted(cache.glob("*[+-].npz"))[:2]:
        f.unlink()
    Counting.calls = 0
    again = finite_difference_hessian(atoms, cache=cache, directions="internal")
    assert Counting.calls == 3  # the undisplaced SCF, then the two missing displacements
    np.testing.assert_allclose(again, internal, rtol=0, atol=1e-12)
    atoms.positions[0, 0] += 0.01
    with pytest.raises(LabelingError, match="another geometry"):
        finite_difference_hessian(atoms, cache=cache, directions="internal")


def test_a_reverse_process_shares_the_internal_hessian_folder(tmp_path):
    """A process stopped after a few displacements leaves its files; a second one with
    ``reverse`` computes the missing ones from the last back (none twice) and both then give
    the one-process Hessian; the Cartesian scheme refuses ``reverse``."""
    from ase.build import molecule

    from emlpack.qm.labeling import finite_difference_hessian

    Counting = counting_emt()

    class Stopped(Exception):
        pass

    class StopsAfter(Counting):
        limit = 6  # the undisplaced SCF and 5 displacements, then "killed"
        seen: list[np.ndarray] = []

        def calculate(self, atoms=None, *args, **kwargs):
            if Counting.calls == StopsAfter.limit:
                raise Stopped
            StopsAfter.seen.append(atoms.positions.copy())
            super().calculate(atoms, *args, **kwargs)

    atoms = molecule("CH3OH")
    n_disp = 2 * (3 * len(atoms) - 6)
    atoms.calc = Counting()
    plain = finite_difference_hessian(atoms, directions="internal")
    cache = tmp_path / "shared"
    Counting.calls = 0
    atoms.calc = StopsAfter()
    with pytest.raises(Stopped):
        finite_difference_hessian(atoms, cache=cache, directions="internal")
    assert len(list(cache.glob("*[+-].npz"))) == 5
    with np.load(cache / "directions.npz") as d:
        last = d["positions"] + 0.005 * d["directions"][:, -1].reshape(-1, 3)
    Counting.calls, StopsAfter.limit, StopsAfter.seen = 0, 10**6, []
    atoms.calc = StopsAfter()
    second = finite_difference_hessian(atoms, cache=cache, directions="internal", reverse=True)
    assert Counting.calls == 1 + n_disp - 5  # only what the first left
    np.testing.assert_allclose(StopsAfter.seen[1], last, atol=1e-12)  # the last "+" first
    np.testing.assert_allclose(second, plain, rtol=0, atol=1e-10)
    Counting.calls = 0
    first = finite_difference_hessian(atoms, cache=cache, directions="internal")
    assert Counting.calls == 0
    np.testing.assert_allclose(first, plain, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="reverse"):
        finite_difference_hessian(atoms, reverse=True)


@pytest.mark.parametrize("escapes", [0, 3])
def test_preparation_steps_off_a_saddle_point(escapes, monkeypatch):
    """Planar NH3 is a GFN2-xTB saddle (the umbrella inversion) on which BFGS stays, as its
    forces have no out-of-plane part: without escapes the preparation returns it (and the
    sampling refuses it); with them it steps down the umbrella mode to the pyramid."""
    from tests.conftest import require

    require("tblite")
    from emlpack.qm import labeling
    from emlpack.qm.sampling import Molecule, has_negative_curvature, normal_modes

    monkeypatch.setattr(labeling, "SADDLE_ESCAPES", escapes)
    a = 2 * np.pi / 3
    h = np.array([[np.cos(i * a), np.sin(i * a), 0.0] for i in range(3)])
    planar = Molecule("planar-nh3", np.array([7, 1, 1, 1]),
                      np.vstack([np.zeros(3), 1.0 * h]),
                      np.array([[0, 1, 1], [0, 2, 1], [0, 3, 1]]), np.zeros(3, dtype=bool))
    mol = labeling.prepare_task(planar, "gfn2-xtb", optimize=True, fmax=0.01, seed=0,
                                threads=1)
    k, _ = normal_modes(mol.numbers, mol.positions, mol.hessian)
    height = abs(mol.positions[0, 2] - mol.positions[1:, 2].mean())
    if escapes:
        assert not has_negative_curvature(k) and height > 0.2
    else:
        assert has_negative_curvature(k) and height < 1e-6


def test_a_cached_saddle_point_preparation_is_prepared_again(tmp_path):
    """A preparation cached before preparations stepped off saddle points (planar NH3 with
    its negative umbrella curvature) is not reused: the molecule is prepared again, labeled
    from the pyramid, and the cached file is left as it was (written once)."""
    from emlpack._files import write_npz_atomic
    from emlpack.qm.labeling import preparation_level_name, run_labeling

    recipe = load_recipe(overrides=["level=tiny", "hydrides=false", "boys_starts=1"],
                         samples_per_molecule=1)
    a = 2 * np.pi / 3
    planar = np.vstack([np.zeros(3), [[np.cos(i * a), np.sin(i * a), 0.0] for i in range(3)]])
    hessian = np.eye(12)
    hessian[2::3, 2::3] -= 3.0  # out-of-plane block: negative curvature
    prep = tmp_path / "prepared"
    prep.mkdir()
    cached = prep / "nh3.npz"
    write_npz_atomic(cached, numbers=np.array([7, 1, 1, 1]), positions=planar,
                     bonds=np.array([[0, 1, 1], [0, 2, 1], [0, 3, 1]]),
                     ring_bonds=np.zeros(3, dtype=bool), hessian=hessian, smiles="N",
                     level=preparation_level_name("tiny"))
    before = cached.read_bytes()
    summary = run_labeling([("nh3", "N")], tmp_path / "s.h5", recipe, workers=0,
                           progress=False, prep_dir=prep)
    assert summary.n_new == 1 and summary.n_failed_new == 0
    with DatasetStore(tmp_path / "s.h5", "r") as store:
        s = next(iter(store))
    height = abs(s.positions[0, 2] - s.positions[1:, 2].mean())
    assert height > 0.15  # not the planar saddle (NMS moves atoms by ~0.05 Å)
    assert cached.read_bytes() == before
