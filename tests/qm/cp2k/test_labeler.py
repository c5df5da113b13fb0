"""CP2K periodic labeler on one water molecule in a small triclinic box (SZV, 200 Ry, 1 process).

Physics checks: forces = -dE/dr (central differences), stress = (1/V) dE/dε (finite strain,
ASE sign), field energy E(F) - E(-F) = -2 μ·F with μ from the Wannier centres (sign and units
of the field term), field forces = -dE/dr at finite field, Wannier-pair count and mapping,
failures recorded in the store. Skipped without CP2K on a user's machine, failing on CI.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from emlpack.data.store import DatasetStore
from emlpack.qm.cp2k import (
    CP2KError,
    CP2KInputError,
    CP2KLabeler,
    CP2KSettings,
    cp2k_available,
    field_force_check,
    label_into_store,
    label_task,
    map_centres_to_cores,
    parse_output,
)
from emlpack.structure import Structure, StructureError
from emlpack.units import FIELD_AU_IN_V_PER_A

#: triclinic cell (rows, Å), edges 5.6-6.0 Å; field forces agree with finite differences here
#: (CP2K 2023.1 double-counts image terms in smaller boxes, see docs/labeling.md)
CELL = np.array([[5.6, 0.0, 0.0], [1.0, 5.7, 0.0], [-1.2, 0.6, 5.8]])
SETTINGS = CP2KSettings(basis="SZV-MOLOPT-SR-GTH", cutoff_ry=200, rel_cutoff_ry=40,
                        n_processes=1, omp_threads=1)
FAST = CP2KSettings(**{**SETTINGS.to_dict(), "wannier": False})
#: field for the energy-sign and field-force checks: 0.005 au, mostly along the dipole (+y)
FIELD = np.array([0.3, 0.8, -0.5]) / np.sqrt(0.98) * 0.005 * FIELD_AU_IN_V_PER_A


@pytest.fixture(scope="module")
def cp2k():
    reason = cp2k_available(SETTINGS)
    if reason is not None:
        message = f"CP2K is not usable: {reason}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)


def water(**changes) -> Structure:
    s = Structure(numbers=[8, 1, 1],
                  positions=[[0.1, 0.2, 0.0], [0.857, 0.786, 0.0], [-0.657, 0.786, 0.1]],
                  pairs=np.zeros((4, 3)), cell=CELL, pbc=True,
                  info={"molecule_id": "water"}, source="water test")
    return s.copy(**changes) if changes else s


#: restarts each SCF from the previous wavefunction (same result, fewer steps)
REUSE = CP2KLabeler(CP2KSettings(**{**FAST.to_dict(), "reuse_wavefunction": True}))


def energy(s: Structure) -> float:
    return REUSE(s).energy


@pytest.fixture(scope="module")
def field_check(cp2k):
    """O y-force at zero field and at FIELD, analytic and by central differences (6 runs)."""
    (check,) = field_force_check(water(), SETTINGS, FIELD, components=((0, 1),))
    return check


@pytest.fixture(scope="module")
def labeled(cp2k, tmp_path_factory):
    """Zero-field energy, forces, stress and centres, labeled into a store and read back."""
    path = tmp_path_factory.mktemp("cp2k") / "store.h5"
    summary = label_into_store([("water/stress/0000", water(), True)], path, SETTINGS)
    assert summary.n_new == 1 and summary.n_failed_new == 0, summary.text()
    with DatasetStore(path) as store:
        return store[0]


def test_store_record_and_resume(labeled, tmp_path_factory):
    s = labeled
    assert s.pbc and np.allclose(s.cell, CELL)
    assert s.info["level"] == SETTINGS.level() == "cp2k/pbe-d3bj/szv-molopt-sr-gth/200ry"
    assert s.info["key"] == "water/stress/0000" and s.info["kind"] == "stress"
    assert s.info["wall_time"] > 0
    assert s.stress is not None and np.allclose(s.stress, s.stress.T, atol=1e-9)
    assert np.allclose(s.field, 0.0)


def test_wannier_pairs(labeled):
    s = labeled
    assert s.n_pairs == 4  # (6 + 1 + 1) valence electrons / 2
    # each pair sits next to a core (mapped to the image nearest its closest core)
    d = np.linalg.norm(s.pairs[:, None] - s.positions[None], axis=-1).min(axis=1)
    assert np.all(d < 0.8)
    # a water dipole of a sensible size, pointing from the pairs towards the hydrogens (+y)
    mu = s.dipole()
    assert 0.2 < np.linalg.norm(mu) < 0.8 and mu[1] > 0


def test_centre_mapping_is_image_consistent():
    rng = np.random.default_rng(0)
    cell = np.array([[5.0, 0.0, 0.0], [1.2, 6.0, 0.0], [-0.8, 0.7, 5.5]])
    cores = rng.uniform(0, 1, (4, 3)) @ cell
    centres = cores[[0, 1, 2, 3, 0]] + rng.normal(0, 0.3, (5, 3))
    shifted = centres + rng.integers(-2, 3, (5, 3)) @ cell
    mapped, core = map_centres_to_cores(shifted, cores, cell)
    assert np.allclose(mapped, centres)
    assert list(core) == [0, 1, 2, 3, 0]


#: step (Å) of the central differences of the energy
FD_STEP = 0.005


@pytest.fixture(scope="module")
def fd_forces(field_check):
    """Zero-field forces on O and H1, all three components, as -dE/dr by central
    differences (restarted energy runs, no Wannier localization; O y from field_check)."""
    base = water()
    fd = np.zeros((2, 3))
    fd[0, 1] = field_check["force0_fd"]
    for atom in range(2):
        for axis in range(3):
            if (atom, axis) == (0, 1):
                continue
            e = []
            for sign in (1, -1):
                p = base.positions.copy()
                p[atom, axis] += sign * FD_STEP
                e.append(energy(base.copy(positions=p)))
            fd[atom, axis] = -(e[0] - e[1]) / (2 * FD_STEP)
    return fd


def test_forces_are_minus_energy_gradient(labeled, field_check, fd_forces):
    """All components of O and H1 (the labeled record: a full run with Wannier centres and
    stress) against central differences; 5e-3 eV/Å covers the grid egg-box error (~3e-3
    eV/Å at 200 Ry, common to both fields, docs/labeling.md)."""
    c = field_check
    assert abs(c["force0"] - labeled.forces[0, 1]) < 1e-6  # FAST (no Wannier) = full run
    assert abs(c["force0"] - c["force0_fd"]) < 5e-3, c
    error = np.abs(labeled.forces[:2] - fd_forces)
    assert error.max() < 5e-3, (labeled.forces[:2], fd_forces)
    assert np.abs(fd_forces).max() > 1.0  # forces well above the tolerance (a strained water)


def test_stress_is_finite_strain_derivative(labeled):
    h = 1e-3
    base = water()
    for i, j in [(0, 0), (0, 1)]:
        e = []
        for sign in (1, -1):
            eps = np.zeros((3, 3))
            eps[i, j] += sign * h / 2
            eps[j, i] += sign * h / 2
            f = np.eye(3) + eps
            e.append(energy(base.copy(positions=base.positions @ f.T, cell=base.cell @ f.T)))
        fd = (e[0] - e[1]) / (2 * h) / base.volume
        assert abs(labeled.stress[i, j] - fd) < 2e-5 + 1e-3 * abs(fd), (i, j, fd)
    # the restarted SCFs converged from the previous wavefunction, in fewer steps
    assert len(REUSE._wfn) == 1


def test_field_energy_sign(labeled, field_check):
    """E(F) - E(-F) = -2 μ·F to first order: our E_ext = -Σ q F·r convention (eV, V/Å)."""
    mu = labeled.dipole()
    de = field_check["energy"] - energy(water(field=-FIELD))
    expected = -2.0 * mu @ FIELD
    assert abs(de - expected) < 0.05 * abs(expected), (de, expected)


def test_field_forces_are_minus_energy_gradient(field_check):
    """Field forces (incl. the Berry-phase term) against finite differences at finite field.

    In a 5.5 Å cubic box the field-induced force matches to ~4e-5 eV/Å; in a 3.5 Å box CP2K
    2023.1's double-counted image term makes it 9% (0.011 eV/Å) off (docs/labeling.md).
    """
    c = field_check
    assert abs(c["force"] - c["force_fd"]) < 5e-3, c
    # the field-induced force change itself (grid errors cancel): much tighter
    assert abs(c["induced"]) > 0.05, c  # the field does move the force
    assert abs(c["error"]) < 1e-3 * max(1.0, abs(c["induced"])) + 5e-4, c


def test_stress_with_field_is_refused():
    with pytest.raises(CP2KInputError, match="stress with a nonzero field"):
        CP2KLabeler(SETTINGS)(water(field=FIELD), stress=True)
    out = label_task(water(field=FIELD), SETTINGS, True, "water/bad/0000")
    assert isinstance(out, dict) and "stress with a nonzero field" in out["reason"]


def test_failure_is_recorded_and_resume_skips(cp2k, tmp_path):
    path = tmp_path / "fail.h5"
    bad = CP2KSettings(**{**FAST.to_dict(), "max_scf": 1, "outer_max_scf": 1})
    items = [("water/field/0000", water(), False)]
    summary = label_into_store(items, path, bad)
    assert summary.n_failed_new == 1 and summary.n_new == 0
    with DatasetStore(path) as store:
        (failure,) = store.failures()
    assert failure["key"] == "water/field/0000"
    assert "SCF not converged" in failure["reason"]
    again = label_into_store(items, path, bad)  # resumable: recorded failures are done
    assert again.n_skipped_done == 1 and again.n_failed_new == 0


def test_crash_and_unconverged_localization_are_clear_errors(cp2k, tmp_path):
    script = tmp_path / "fake_cp2k"
    script.write_text("#!/bin/sh\necho 'ABORT: something broke' > emlp.out\nexit 3\n")
    script.chmod(0o755)
    broken = CP2KSettings(**{**FAST.to_dict(), "cp2k": str(script), "mpirun": None})
    with pytest.raises(CP2KError, match=r"(?s)exit code 3.*something broke"):
        CP2KLabeler(broken)(water())
    script.write_text("#!/bin/sh\nsleep 60\n")
    slow = CP2KSettings(**{**broken.to_dict(), "timeout_s": 0.5})
    with pytest.raises(CP2KError, match="timed out after 0.5 s"):
        CP2KLabeler(slow)(water())
    text = "Crazy Wannier localization not converged after      3\n"
    with pytest.raises(CP2KError, match="localization not converged after 3"):
        parse_output(text + "ENERGY| Total FORCE_EVAL ( QS ) energy [a.u.]: -1.0\n", 3, False)


def test_cp2k_labeler_does_not_import_torch():
    code = ("import sys, emlpack.qm.cp2k\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_killed_labeler_leaves_no_cp2k_running(cp2k, tmp_path):
    """kill -9 of the labeling process also ends its CP2K (a stand-in executable that sleeps)."""
    fake = tmp_path / "fake_cp2k.sh"
    fake.write_text("#!/bin/sh\necho $$ > ../fake.pid\nexec sleep 60\n")
    fake.chmod(0o755)
    script = (
        "import numpy as np\n"
        "from emlpack.qm.cp2k import CP2KLabeler, CP2KSettings\n"
        "from emlpack.structure import Structure\n"
        "s = Structure(numbers=[1, 1], positions=[[0, 0, 0], [0.74, 0, 0]],"
        " pairs=np.zeros((1, 3)), cell=np.eye(3) * 5, pbc=True)\n"
        f"CP2KLabeler(CP2KSettings(cp2k={str(fake)!r}, mpirun=None),"
        f" workdir={str(tmp_path)!r}, keep_files=True)(s)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script])
    pid_files = []
    for _ in range(300):
        pid_files = list(tmp_path.glob("*/fake.pid")) + list(tmp_path.glob("fake.pid"))
        if pid_files and pid_files[0].read_text().strip():
            break
        if proc.poll() is not None:
            pytest.fail(f"the labeling process ended early (exit code {proc.returncode})")
        __import__("time").sleep(0.1)
    assert pid_files, "the stand-in CP2K never started"
    child = int(pid_files[0].read_text())
    proc.kill()
    proc.wait()
    for _ in range(100):
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            return
        __import__("time").sleep(0.1)
    os.kill(child, 9)
    pytest.fail("CP2K kept running after its labeling process was killed")


def test_wavefunction_reuse_with_relative_workdir(cp2k, tmp_path, monkeypatch):
    """The restart file is found from CP2K's run directory when the workdir is relative (it was
    silently ignored before: CP2K warned and started from the atomic guess)."""
    monkeypatch.chdir(tmp_path)
    lab = CP2KLabeler(CP2KSettings(**{**FAST.to_dict(), "reuse_wavefunction": True}),
                      workdir="scratch", keep_files=True)
    first = lab(water())
    second = lab(water(positions=water().positions + 0.01))
    assert "User requested to restart" not in (lab.last_run_dir / "emlp.out").read_text()
    assert second.info["scf_steps"] < first.info["scf_steps"] / 2, (first.info, second.info)


def test_supercell_labels_are_the_cells(cp2k):
    """``CP2KSettings.supercell``: the cell labeled through its 2x1x1 Γ-point supercell gets
    the supercell's labels per cell (energy / 2, the first cell's forces and Wannier centres,
    the stress): the same as labeling the repeated structure itself and taking its first cell."""
    s = water()
    big = s.repeated((2, 1, 1))
    direct = CP2KLabeler(SETTINGS)(big, stress=True)
    via = CP2KLabeler(CP2KSettings(**{**SETTINGS.to_dict(), "supercell": (2, 1, 1)}))(
        s, stress=True)
    assert via.info["level"].endswith("/gamma-supercell-2x1x1") and via.info["supercell"] == [
        2, 1, 1]
    assert via.energy == pytest.approx(direct.energy / 2, abs=1e-6)
    np.testing.assert_allclose(via.forces, direct.forces[:3], atol=1e-5)
    np.testing.assert_allclose(via.forces, direct.forces[3:], atol=1e-4)  # the image's
    np.testing.assert_allclose(via.stress, direct.stress, atol=1e-7)
    assert via.n_pairs == 4 and via.pair_forces.shape == (4, 3)
    # the first cell's centres, each beside a core of the cell
    d = np.linalg.norm(via.pairs[:, None] - direct.pairs[None], axis=-1).min(axis=1)
    assert np.all(d < 1e-4)
    assert np.linalg.norm(via.pairs[:, None] - s.positions[None], axis=-1).min(axis=1).max() < 0.8


def test_repeated_structure():
    s = water(pairs=np.array([[0.1, 0.3, 0.0], [0.4, 0.5, 0.0], [0.0, 0.5, 0.2],
                              [0.2, 0.1, 0.3]]))
    big = s.repeated((2, 1, 3))
    assert big.n_cores == 18 and big.n_pairs == 24
    np.testing.assert_allclose(big.cell, np.diag([2.0, 1.0, 3.0]) @ CELL)
    np.testing.assert_allclose(big.positions[:3], s.positions)
    np.testing.assert_allclose(big.positions[3:6], s.positions + CELL[2])  # third index fastest
    np.testing.assert_allclose(big.pairs[-4:], s.pairs + CELL[0] + 2 * CELL[2])
    assert big.volume == pytest.approx(6 * s.volume)
    np.testing.assert_allclose(big.dipole(), 6 * s.dipole(), atol=1e-12)  # neutral: extensive
    with pytest.raises(StructureError, match="repetitions"):
        s.repeated((0, 1, 1))
    with pytest.raises(StructureError, match="periodic"):
        s.copy(pbc=False, cell=np.zeros((3, 3))).repeated((2, 1, 1))


def test_wavefunction_guess_starts_from_a_kept_wavefunction(cp2k, tmp_path):
    """``CP2KSettings.wavefunction_guess``: a labeler without reuse starts from the given
    ``.wfn`` (the one :meth:`CP2KLabeler.wavefunction` kept) in far fewer SCF steps, with the
    same labels as from the atomic guess; a missing file is one clear error."""
    reuse = CP2KLabeler(CP2KSettings(**{**FAST.to_dict(), "reuse_wavefunction": True}))
    assert reuse.wavefunction(water()) is None
    reuse(water())
    kept = tmp_path / "water.wfn"
    shutil.copyfile(reuse.wavefunction(water()), kept)
    moved = water(positions=water().positions + [[0, 0, 0], [0.03, -0.02, 0], [0, 0, 0]])
    cold = CP2KLabeler(FAST)(moved)
    warm = CP2KLabeler(CP2KSettings(**{**FAST.to_dict(), "wavefunction_guess": str(kept)}))(moved)
    assert warm.info["scf_steps"] < cold.info["scf_steps"] / 2, (cold.info, warm.info)
    assert warm.energy == pytest.approx(cold.energy, abs=1e-4)
    np.testing.assert_allclose(warm.forces, cold.forces, atol=2e-3)
    missing = CP2KLabeler(CP2KSettings(**{**FAST.to_dict(),
                                          "wavefunction_guess": str(tmp_path / "none.wfn")}))
    with pytest.raises(CP2KInputError, match="wavefunction_guess"):
        missing(moved)
