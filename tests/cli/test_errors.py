"""``emlp``'s one error path: each bad input ends in one line naming file, frame and problem,
exit code 2, no traceback, before any expensive work (the rows of the user-test table).

Commands run in-process through :func:`emlpack.cli.main`; the model is a small random eMLP
saved with :func:`~emlpack.nn.checkpoint.save_model` (tests/cli/helpers.py)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from emlpack.cli import main
from emlpack.errors import (
    EmlpackError,
    InputError,
    MissingFileError,
    ModelFileError,
)
from tests.cli.helpers import run, save_test_model, water_rows, write_xyz


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    return save_test_model(tmp_path_factory.mktemp("model"))


def _error(capsys, argv, code=2):
    """Run ``emlp argv``; check the exit code and that stderr is one line; return it."""
    rc = main(argv)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert rc == code, err
    assert not any("Traceback" in line for line in err), err
    if code == 2:  # the checks come before any progress message
        assert len(err) == 1, err
    return err[-1]


# ------------------------------------------------------------------ the class hierarchy
def test_every_user_error_class_is_an_emlpack_error():
    from emlpack.data.dataset import DataError
    from emlpack.data.references import HydrideReferenceError
    from emlpack.data.store import StoreError
    from emlpack.dynamics.analysis import TrajectoryAnalysisError
    from emlpack.dynamics.md import MDWatchdogError
    from emlpack.io import ExtxyzError
    from emlpack.legacy.tf_checkpoint import TFCheckpointError
    from emlpack.nn.checkpoint import CheckpointError
    from emlpack.properties.fd_reference import CrystalReferenceError
    from emlpack.qm.pyscf_labeler import LabelingError
    from emlpack.qm.sampling import SamplingError
    from emlpack.structure import StructureError
    from emlpack.train.config import ConfigError

    classes = [CrystalReferenceError, DataError, HydrideReferenceError, StoreError, ExtxyzError,
               TFCheckpointError, MDWatchdogError, TrajectoryAnalysisError, CheckpointError,
               LabelingError, SamplingError, StructureError, ConfigError,
               InputError, ModelFileError, MissingFileError]
    for cls in classes:
        assert issubclass(cls, EmlpackError), cls
    # the built-in bases stay, so existing except clauses keep working
    assert issubclass(StructureError, ValueError) and issubclass(StoreError, RuntimeError)
    assert issubclass(MissingFileError, FileNotFoundError)
    assert not issubclass(HydrideReferenceError, ReferenceError)  # the built-in is not shadowed


# ------------------------------------------------------------------ structure files
def test_water_with_three_of_four_pairs(model_file, tmp_path, capsys):
    path = write_xyz(tmp_path / "w3.xyz", water_rows(n_pairs=3))
    line = _error(capsys, ["polarizability", str(model_file), str(path)])
    assert line == (f"emlp polarizability: error: {path}, frame 0: 3 electron pairs (Es rows)"
                    " given, 4 needed for a neutral H2O (5 with the 1s core centres)")


def test_water_with_five_pairs(model_file, tmp_path, capsys):
    rows = water_rows(n_pairs=4) + [("Es", 2.0, 2.0, 2.0)]
    path = write_xyz(tmp_path / "w5.xyz", rows)
    line = _error(capsys, ["ir", str(model_file), str(path)])
    # 5 = 4 valence + 1 core centre is a legal count, but no centre sits on the O nucleus
    assert f"{path}, frame 0: atom 0 (Z=8) has no 1s core centre" in line


def test_water_with_six_pairs(model_file, tmp_path, capsys):
    rows = water_rows(n_pairs=4) + [("Es", 2.0, 2.0, 2.0), ("Es", -2.0, 2.0, 2.0)]
    path = write_xyz(tmp_path / "w6.xyz", rows)
    line = _error(capsys, ["ir", str(model_file), str(path)])
    assert line.endswith(f"{path}, frame 0: 6 electron pairs (Es rows) given, 4 needed for a"
                         " neutral H2O (5 with the 1s core centres)")


def test_odd_electron_count_names_the_charge(model_file, tmp_path, capsys):
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=0))
    line = _error(capsys, ["ir", str(model_file), str(path), "--charge", "1"])
    assert line == (f"emlp ir: error: {path}, frame 0: odd number of valence electrons for"
                    " charge +1 of H2O (eMLP needs closed-shell electron pairs; is the charge"
                    " right?)")


def test_h_on_top_of_o_is_refused_before_the_pair_guess(model_file, tmp_path, capsys):
    rows = [("O", 0.0, 0.0, 0.0), ("H", 0.0, 0.0, 0.05), ("H", -0.757, 0.586, 0.0)]
    path = write_xyz(tmp_path / "ontop.xyz", rows)
    for guess in ("auto", "lewis"):
        line = _error(capsys, ["polarizability", str(model_file), str(path), "--guess", guess])
        assert line == (f"emlp polarizability: error: {path}, frame 0: atoms 0 (O) and 1 (H)"
                        " are 0.05 Å apart (closer than 0.5 Å)")


@pytest.mark.parametrize("element", ["Si", "Cl"])
def test_element_unknown_to_the_model_is_refused_before_the_pair_guess(
        model_file, tmp_path, capsys, element):
    rows = [(element, 0.0, 0.0, 0.0), ("H", 1.5, 0.0, 0.0), ("H", -1.5, 0.0, 0.0),
            ("H", 0.0, 1.5, 0.0), ("H", 0.0, 0.0, 1.5)]
    path = write_xyz(tmp_path / "x.xyz", rows)
    t0 = time.perf_counter()
    line = _error(capsys, ["ir", str(model_file), str(path)])
    assert time.perf_counter() - t0 < 5.0  # no pair guess, no relaxation
    z = {"Si": 14, "Cl": 17}[element]
    assert line == (f"emlp ir: error: {path}, frame 0: element(s) {element} (Z={z}) not"
                    " supported by the model (trained for H, C, N, O)")


def test_a_pair_far_from_every_core_is_refused_naming_the_particle(model_file, tmp_path,
                                                                    capsys):
    """A pair at 1e6 Å (once a SIGFPE inside vesin, exit 136): one line naming file, frame,
    the particle row and the model's cutoff."""
    rows = water_rows(4)
    rows[4] = ("Es", 1e6, 0.0, 0.0)
    path = write_xyz(tmp_path / "far.xyz", rows)
    line = _error(capsys, ["polarizability", str(model_file), str(path)])
    assert line == (f"emlp polarizability: error: {path}, frame 0: electron pair at particle"
                    " row 4 (Es at (1e+06, 0, 0) Å) is 1e+06 Å from the nearest core, farther"
                    " than the model's cutoff 4 Å from every core")


def test_a_core_far_away_is_refused_as_too_large_for_the_neighbour_list(model_file, tmp_path,
                                                                         capsys):
    rows = water_rows(0)
    rows[0] = ("O", 0.0, 1e6, 0.0)  # the pairs are guessed: refused before the guess
    path = write_xyz(tmp_path / "farcore.xyz", rows)
    line = _error(capsys, ["polarizability", str(model_file), str(path)])
    assert line.startswith(f"emlp polarizability: error: {path}, frame 0: the bounding box of"
                           " the particles (1.529 x 1.01e+06 x 1.01 Å) holds 2.52e+05 cells")
    assert line.endswith("particle row 0 (O at (0, 1e+06, 0) Å) is the farthest from the"
                         " others")


def test_a_two_component_field_in_the_file_is_one_line(model_file, tmp_path, capsys):
    """``efield="1 2"`` was a ValueError traceback (exit 1)."""
    path = write_xyz(tmp_path / "e.xyz", water_rows(4),
                     comment='Properties=species:S:1:pos:R:3 pbc="F F F" efield="1 2"')
    line = _error(capsys, ["polarizability", str(model_file), str(path)])
    assert line == (f"emlp polarizability: error: {path}, frame 0: 'efield' must have 3"
                    " components, got 2: '1 2'")


def test_response_on_a_molecule_is_refused_before_any_work(model_file, tmp_path, capsys):
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=0))  # pairs would need a guess
    t0 = time.perf_counter()
    line = _error(capsys, ["response", str(model_file), str(path)])
    assert time.perf_counter() - t0 < 5.0
    assert line == (f"emlp response: error: {path}, frame 0: emlp response needs a crystal"
                    " (Lattice and pbc=\"T T T\"); this is a molecule")


def test_cell_with_pbc_false_is_not_silently_a_molecule(model_file, tmp_path, capsys):
    path = write_xyz(tmp_path / "cell.xyz", water_rows(n_pairs=4),
                     comment='Lattice="6 0 0 0 6 0 0 0 6" pbc="F F F"')
    line = _error(capsys, ["polarizability", str(model_file), str(path)])
    assert line == (f"emlp polarizability: error: {path}, frame 0: a cell (Lattice) is given"
                    " but pbc is false: set pbc=\"T T T\" for a crystal or drop the Lattice"
                    " for a molecule")


def test_free_text_comment_containing_energy_is_accepted(model_file, tmp_path, capsys):
    path = write_xyz(tmp_path / "free.xyz", water_rows(n_pairs=4),
                     comment="water, energy minimised; charge unknown")
    out = tmp_path / "pol.json"
    assert main(["polarizability", str(model_file), str(path), "-o", str(out), "--quiet"]) == 0
    data = json.loads(out.read_text())
    assert data["structure"] == f"{path}, frame 0"
    from emlpack.io import read_structures

    s = read_structures(path)[0]
    assert s.energy is None and s.charge == 0.0  # the bare words are not labels


def test_missing_structure_file_and_frame(model_file, tmp_path, capsys):
    line = _error(capsys, ["ir", str(model_file), str(tmp_path / "nope.xyz")])
    assert line == f"emlp ir: error: {tmp_path / 'nope.xyz'}: no such file"
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    line = _error(capsys, ["ir", str(model_file), str(path), "--index", "3"])
    assert line == f"emlp ir: error: {path}: frame 3 requested but the file has 1 frames"
    line = _error(capsys, ["ir", str(model_file), str(tmp_path)])
    assert line == f"emlp ir: error: {tmp_path}: is a folder, not a structure file"
    line = _error(capsys, ["ir", str(model_file), str(path), "--index", "last"])
    assert line == f"emlp ir: error: {path}: frame index must be an integer, got 'last'"
    pdb = tmp_path / "empty.pdb"
    pdb.write_text("REMARK nothing here\n")
    line = _error(capsys, ["ir", str(model_file), str(pdb)])
    assert line == f"emlp ir: error: {pdb}, frame 0: no atoms in the structure"


def test_neither_or_both_structure_and_smiles(model_file, tmp_path, capsys):
    assert _error(capsys, ["ir", str(model_file)]) == (
        "emlp ir: error: give a structure file or --smiles")
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    assert _error(capsys, ["ir", str(model_file), str(path), "--smiles", "O"]) == (
        "emlp ir: error: give a structure file or --smiles, not both")


def test_bad_smiles(model_file, capsys):
    line = _error(capsys, ["ir", str(model_file), "--smiles", "C1CC"])
    assert line == "emlp ir: error: SMILES C1CC: RDKit cannot parse SMILES 'C1CC'"


# ------------------------------------------------------------------ model files
@pytest.mark.parametrize("content, what", [
    (b"", "empty file, not an emlpack model"),
    (b"this is a text file\n", "not an emlpack model file (a text file, not a PyTorch"
     " checkpoint archive)"),
    (bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8)),
     "not an emlpack model file (binary data, not a PyTorch checkpoint archive)"),
])
def test_non_checkpoint_model_file_is_refused_before_pytorch(tmp_path, capsys, content, what):
    model = tmp_path / "model.pt"
    model.write_bytes(content)
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    line = _error(capsys, ["polarizability", str(model), str(path)])
    assert line == f"emlp polarizability: error: {model}: {what}"
    assert "weights_only" not in line and "issue" not in line


def test_zip_that_is_not_a_checkpoint_and_missing_model(tmp_path, capsys):
    import zipfile

    model = tmp_path / "model.pt"
    with zipfile.ZipFile(model, "w") as z:
        z.writestr("readme.txt", "hello")
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    assert _error(capsys, ["ir", str(model), str(path)]) == (
        f"emlp ir: error: {model}: a zip archive, but not a PyTorch checkpoint")
    missing = tmp_path / "none.pt"
    assert _error(capsys, ["ir", str(missing), str(path)]) == (
        f"emlp ir: error: {missing}: no such model file")


def test_torch_file_that_is_not_an_emlpack_model(tmp_path, capsys):
    import torch

    model = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, model)
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    line = _error(capsys, ["ir", str(model), str(path)])
    assert line.startswith(f"emlp ir: error: {model}: not an emlpack model checkpoint")
    # a pickled module: refused without PyTorch's advice to load it unsafely
    torch.save(torch.nn.Linear(2, 2), model)
    line = _error(capsys, ["ir", str(model), str(path)])
    assert line == (f"emlp ir: error: {model}: not an emlpack model (a PyTorch file holding"
                    " pickled objects; emlpack reads weights only)")


# ------------------------------------------------------------------ arguments
@pytest.mark.parametrize("args, message", [
    (["--steps", "-5"], "--steps must be positive, got -5"),
    (["--steps", "0"], "--steps must be positive, got 0"),
    (["--dt", "0"], "--dt must be positive, got 0"),
    (["--dt", "-0.5"], "--dt must be positive, got -0.5"),
    (["--temperature", "-300"], "--temperature must be non-negative, got -300"),
    (["--record-every", "0"], "--record-every must be positive, got 0"),
    (["--temperature", "0"], "--temperature must be positive for NVT (the thermostat mass is"
     " proportional to T); use --nve for a run from rest"),
    (["--threads", "0"], "--threads must be at least 1, got 0"),
])
def test_md_run_lengths_are_checked_first(tmp_path, capsys, args, message):
    # the model file does not even exist: the arguments are checked before anything is read
    line = _error(capsys, ["md", str(tmp_path / "none.pt"), "none.xyz", "-o",
                           str(tmp_path / "md"), *args])
    assert line == f"emlp md: error: {message}"
    assert not (tmp_path / "md").exists()


def test_field_above_one_volt_per_angstrom_needs_force(model_file, tmp_path, capsys):
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    line = _error(capsys, ["polarizability", str(model_file), str(path), "--field", "1e9", "0",
                           "0"])
    assert line == (f"emlp polarizability: error: {path}, frame 0: field |F| = 1e+09 V/Å is"
                    " above 1 V/Å (about 0.02 au, twice the training range); pass --force to"
                    " use it anyway")
    line = _error(capsys, ["md", str(model_file), str(path), "-o", str(tmp_path / "md"),
                           "--field-au", "0.1", "0", "0"])
    assert "field |F| = 5.14 V/Å is above 1 V/Å" in line
    # a field stored in the file is checked the same way
    big = write_xyz(tmp_path / "big.xyz", water_rows(n_pairs=4),
                    comment='external_field="3 0 0"')
    assert "field |F| = 3 V/Å is above 1 V/Å" in _error(
        capsys, ["ir", str(model_file), str(big)])


def test_argparse_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as info:
        main(["ir", "--relax", "sideways"])
    assert info.value.code == 2


def test_debug_shows_the_traceback(tmp_path):
    model = tmp_path / "empty.pt"
    model.write_bytes(b"")
    with pytest.raises(ModelFileError, match="empty file"):
        main(["ir", str(model), "--smiles", "O", "--debug"])
    with pytest.raises(ModelFileError, match="empty file"):
        main(["--debug", "ir", str(model), "--smiles", "O"])


# ------------------------------------------------------------------ interrupts
def test_sigint_during_md_exits_130_with_a_resume_hint(model_file, tmp_path, capsys,
                                                       monkeypatch):
    import emlpack.dynamics.md

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(emlpack.dynamics.md, "run_md", interrupted)
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    line = _error(capsys, ["md", str(model_file), str(path), "-o", str(tmp_path / "md")],
                  code=130)
    assert line == "emlp md: interrupted; re-run the same command to resume"


def test_sigint_in_a_command_that_does_not_resume(model_file, tmp_path, capsys, monkeypatch):
    import emlpack.properties.hessian

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(emlpack.properties.hessian, "extended_hessian", interrupted)
    path = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    assert _error(capsys, ["ir", str(model_file), str(path), "--relax", "none"],
                  code=130) == "emlp ir: interrupted"


def test_run():  # the helper itself: a command's stdout and exit code
    rc, out, err = run(["--version"])
    assert rc == 0 and out.startswith("emlpack ")


@pytest.mark.parametrize("argv, message", [
    (["label", "x.csv", "-o", "d.h5", "--samples-per-molecule", "0"],
     "--samples-per-molecule must be positive, got 0"),
    (["label", "x.csv", "-o", "d.h5", "--workers", "-1"], "--workers must be non-negative, got -1"),
    (["relabel", "x.xyz", "-o", "y.xyz", "--boys-starts", "0"],
     "--boys-starts must be positive, got 0"),
    (["evaluate", "m.pt", "d.h5", "--max-structures", "0"],
     "--max-structures must be positive, got 0"),
])
def test_data_and_training_counts_are_checked_first(tmp_path, capsys, monkeypatch, argv,
                                                    message):
    monkeypatch.chdir(tmp_path)
    if argv[0] == "evaluate":  # the model file is checked first
        from tests.cli.helpers import save_test_model

        save_test_model(tmp_path)
        argv = ["evaluate", "model.pt", *argv[2:]]
    line = _error(capsys, argv)
    assert line == f"emlp {argv[0]}: error: {message}"


@pytest.mark.slow  # timing-dependent: on a loaded machine the poll can miss the early steps
def test_real_sigint_during_md_exits_130_and_the_rerun_resumes(tmp_path):
    """``emlp md`` in a subprocess, Ctrl-C (SIGINT) after a few steps: exit 130, one line
    with the resume hint, no traceback; the same command then continues the run."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    from emlpack.io import read_structures

    model = save_test_model(tmp_path, seed=4)
    start = write_xyz(tmp_path / "w.xyz", water_rows(n_pairs=4))
    out = tmp_path / "md"
    cmd = [sys.executable, "-m", "emlpack.cli", "md", str(model), str(start), "-o", str(out),
           "--steps", "2000", "--dt", "0.25", "--nve", "--temperature", "100",
           "--checkpoint-every", "1", "--quiet"]
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    traj = out / "trajectory.xyz"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if traj.exists() and traj.read_text().count("\n7\n") >= 3:
            break
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)  # a loaded machine can be slow to unwind
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == (
        "emlp md: interrupted; re-run the same command to resume")
    done = len(read_structures(traj))
    assert 3 <= done < 2001
    # the re-run continues from the checkpoint (here to a smaller total, so it ends quickly)
    rerun = cmd.copy()
    rerun[rerun.index("2000")] = str(done)
    rc = subprocess.run(rerun, env=env, capture_output=True, text=True, timeout=300)
    assert rc.returncode == 0, rc.stderr
    assert len(read_structures(traj)) == done + 1
    assert "resuming from step" in (out / "md.log").read_text()


def test_molecule_commands_refuse_a_crystal(model_file, tmp_path, capsys):
    path = write_xyz(tmp_path / "ice.xyz", water_rows(n_pairs=4),
                     comment='Lattice="5 0 0 0 5 0 0 0 5" pbc="T T T"')
    for command in ("ir", "polarizability"):
        line = _error(capsys, [command, str(model_file), str(path)])
        assert line == (f"emlp {command}: error: {path}, frame 0: emlp {command} needs a"
                        " molecule; this is a crystal (pbc true)")


def test_close_atoms_across_the_periodic_boundary(model_file, tmp_path, capsys):
    rows = [("O", 0.1, 0.0, 0.0), ("H", 4.8, 0.0, 0.0), ("H", 0.1, 1.0, 0.0)]
    path = write_xyz(tmp_path / "x.xyz", rows, comment='Lattice="5 0 0 0 5 0 0 0 5" pbc="T T T"')
    line = _error(capsys, ["response", str(model_file), str(path)])
    assert line == (f"emlp response: error: {path}, frame 0: atoms 0 (O) and 1 (H) are 0.30 Å"
                    " apart (closer than 0.5 Å)")


def test_mixed_periodicity_and_a_singular_cell(model_file, tmp_path, capsys):
    mixed = write_xyz(tmp_path / "m.xyz", water_rows(4),
                      comment='Lattice="5 0 0 0 5 0 0 0 5" pbc="T T F"')
    assert _error(capsys, ["response", str(model_file), str(mixed)]) == (
        f"emlp response: error: {mixed}, frame 0: mixed periodicity pbc=[True, True, False] is"
        " not supported (all or none)")
    flat = write_xyz(tmp_path / "f.xyz", water_rows(4),
                     comment='Lattice="5 0 0 0 5 0 0 0 0" pbc="T T T"')
    assert _error(capsys, ["response", str(model_file), str(flat)]) == (
        f"emlp response: error: {flat}, frame 0: periodic structure with a singular or missing"
        " cell")
