"""Optional dependencies: each one's absence, simulated in this process (``sys.modules[name] =
None``, which makes ``import name`` fail as if it were not installed), gives one line that names
the extra providing it (exit 2 from ``emlp``), before anything is written; a feature chosen
when a package is present falls back without it. The table of extras
(:data:`emlpack.optional.PROVIDERS`) matches pyproject.toml, and the base install imports
without any of them. The installed wheel is checked the same way by ``.ci/wheel_check.sh``."""

from __future__ import annotations

import ast
import importlib
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from emlpack.errors import EmlpackError, MissingDependencyError
from emlpack.optional import PROVIDERS, import_optional, install_hint, is_available
from tests.cli.helpers import WATER_CORES, run, save_test_model, water_rows, write_xyz
from tests.conftest import ROOT

SRC = ROOT / "src" / "emlpack"


def hide(monkeypatch, *names: str) -> None:
    """Make ``import name`` (and of its submodules) fail as for a package that is not
    installed, for this test only."""
    for name in names:
        for key in [k for k in sys.modules if k == name or k.startswith(name + ".")]:
            monkeypatch.setitem(sys.modules, key, None)
        monkeypatch.setitem(sys.modules, name, None)


def one_error_line(err: str, command: str, extra: str | None) -> str:
    """The single stderr line of a refused command; asserts its form and the extra it names."""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"emlp {command}: error: "), err
    assert "Traceback" not in err
    if extra is not None:
        assert f"pip install 'emlpack[{extra}]'" in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    return save_test_model(tmp_path_factory.mktemp("model"))


# ------------------------------------------------------------------ the helper
def test_import_optional_returns_the_module_or_one_line_naming_the_extra(monkeypatch):
    mod = import_optional("pyscf", "DFT")
    assert mod.__name__ == "pyscf"
    hide(monkeypatch, "pyscf")
    with pytest.raises(MissingDependencyError) as info:
        import_optional("pyscf", "DFT labeling", alternative="use a model")
    text = str(info.value)
    assert text == ("DFT labeling needs pyscf, which is not installed: pip install"
                    " 'emlpack[qm]'; or use a model")
    assert isinstance(info.value, EmlpackError) and isinstance(info.value, ImportError)
    assert not is_available("pyscf")
    with pytest.raises(KeyError, match="not an optional dependency"):
        import_optional("numpy", "x")


def test_a_base_dependency_is_named_with_its_own_pip_line(monkeypatch):
    hide(monkeypatch, "rdkit")
    with pytest.raises(MissingDependencyError, match=r"a dependency of emlpack that is not"
                       r" installed: pip install rdkit$"):
        import_optional("rdkit.Chem", "--smiles")
    assert install_hint("rdkit.Chem") == "pip install rdkit"
    assert install_hint("tblite.ase") == "pip install 'emlpack[qm]'"


def test_a_broken_package_is_named_as_installed_but_not_importable(monkeypatch):
    class Broken:
        def find_spec(self, name, path=None, target=None):
            if name == "spglib":
                raise ImportError("libsymspg.so.2: cannot open shared object file")
            return None

    monkeypatch.delitem(sys.modules, "spglib", raising=False)
    monkeypatch.setattr(sys, "meta_path", [Broken(), *sys.meta_path])
    with pytest.raises(MissingDependencyError) as info:
        import_optional("spglib", "symprec")
    assert str(info.value) == (
        "symprec needs spglib, which is installed but cannot be imported (libsymspg.so.2:"
        " cannot open shared object file); reinstall it: pip install 'emlpack[periodic]'")


def test_the_table_of_extras_matches_pyproject():
    tomllib = importlib.import_module("tomllib" if sys.version_info >= (3, 11) else "tomli")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]

    def provided(requirements):
        """Distribution names a list of requirements installs (``dask[distributed]`` gives
        dask and distributed)."""
        names = set()
        for req in requirements:
            m = re.match(r"\s*([A-Za-z0-9_.-]+)\s*(\[([^\]]*)\])?", req)
            names.add(m.group(1).lower())
            if m.group(3) and m.group(1).lower() == "dask":
                names |= {e.strip().lower() for e in m.group(3).split(",")}
        return names

    base = provided(project["dependencies"])
    extras = project["optional-dependencies"]
    for module, (distribution, extra) in PROVIDERS.items():
        where = base if extra is None else provided(extras[extra])
        assert distribution in where, (module, distribution, extra)
    # every extra that provides a feature (not the developer tools) has its error line
    assert set(extras) - {"dev"} == {e for _, e in PROVIDERS.values() if e}


def test_every_optional_import_goes_through_the_table_and_none_is_at_module_level():
    """``import_optional``/``is_available`` name known modules, and no module imports an
    optional package at import time (so that every module imports in the base install)."""
    calls, top_level = [], []
    for path in sorted(SRC.rglob("*.py")):
        tree = ast.parse(path.read_text())
        rel = path.relative_to(SRC).as_posix()
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                    and node.func.id in ("import_optional", "is_available") and node.args
                    and isinstance(node.args[0], ast.Constant)):
                calls.append((rel, node.args[0].value))
        for node in tree.body:  # module level; `if TYPE_CHECKING:` blocks are not run
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module] if isinstance(node, ast.ImportFrom) and node.module else [])
            top_level += [f"{rel}: {n}" for n in names if n.split(".")[0] in PROVIDERS]
    assert len(calls) > 10
    assert [c for c in calls if c[1].split(".")[0] not in PROVIDERS] == []
    assert top_level == []


def test_every_module_and_command_help_work_without_any_optional_package():
    """In a fresh interpreter where none of the optional packages imports: every module of the
    package imports and every ``emlp COMMAND --help`` exits 0."""
    modules = sorted(
        "emlpack." + ".".join(p.relative_to(SRC).with_suffix("").parts).removesuffix(".__init__")
        for p in SRC.rglob("*.py") if p.name != "__main__.py")
    code = (
        "import contextlib, importlib, io, sys\n"
        f"for name in {sorted(PROVIDERS)!r}:\n"
        "    sys.modules[name] = None\n"
        f"for module in {modules!r}:\n"
        "    importlib.import_module(module)\n"
        "from emlpack.cli import build_parser, main\n"
        "sub = next(a for a in build_parser()._actions if a.dest == 'command')\n"
        "for command in sub.choices:\n"
        "    with contextlib.redirect_stdout(io.StringIO()) as out:\n"
        "        try:\n"
        "            main([command, '--help'])\n"
        "        except SystemExit as exc:\n"
        "            assert exc.code in (0, None), (command, exc.code)\n"
        "    assert out.getvalue().startswith('usage: emlp ' + command), command\n"
        "print(len(sub.choices))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT / "src")},
                       timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    assert int(p.stdout.split()[-1]) >= 15


# ------------------------------------------------------------------ RDKit (a base dependency)
def test_smiles_without_rdkit_is_one_line(monkeypatch, model_file, tmp_path):
    hide(monkeypatch, "rdkit")
    rc, _, err = run(["ir", str(model_file), "--smiles", "O", "-o", str(tmp_path / "ir.json"),
                      "--quiet"])
    assert rc == 2
    line = one_error_line(err, "ir", None)
    assert "--smiles (RDKit 3D embedding) needs rdkit" in line and "pip install rdkit" in line
    assert "give an xyz file" in line
    csv = tmp_path / "m.csv"
    csv.write_text("smiles\nC\nO\n")
    rc, _, err = run(["campaign", "init", str(tmp_path / "ds"), "--smiles", str(csv)])
    assert rc == 2 and "pip install rdkit" in one_error_line(err, "campaign", None)


# ------------------------------------------------------------------ PySCF
def test_boys_guess_without_pyscf_names_the_extra_and_auto_uses_lewis(monkeypatch, model_file,
                                                                      tmp_path):
    from ase import Atoms

    from emlpack.pairs.guess import guess_pairs, lewis_pairs

    hide(monkeypatch, "pyscf")
    water = write_xyz(tmp_path / "w.xyz", WATER_CORES)
    out = tmp_path / "ir.json"
    rc, _, err = run(["ir", str(model_file), str(water), "--guess", "boys", "-o", str(out),
                      "--quiet"])
    assert rc == 2 and not out.exists()
    line = one_error_line(err, "ir", "qm")
    assert "Foster-Boys pair guess" in line and "--guess lewis" in line
    atoms = Atoms([s for s, *_ in WATER_CORES], [xyz for _, *xyz in WATER_CORES])
    np.testing.assert_array_equal(guess_pairs(atoms, "auto"), lewis_pairs(atoms, 0.0))
    assert guess_pairs(atoms, "auto").shape == (4, 3)


def test_labeling_without_pyscf_is_refused_before_a_file_is_written(monkeypatch, tmp_path):
    hide(monkeypatch, "pyscf")
    mol = write_xyz(tmp_path / "mol.xyz", WATER_CORES)
    store = tmp_path / "data.h5"
    rc, _, err = run(["label", str(mol), "-o", str(store), "--workers", "0", "--quiet"])
    assert rc == 2 and not store.exists()
    assert "DFT labeling (PySCF) needs pyscf" in one_error_line(err, "label", "qm")
    src = write_xyz(tmp_path / "w.xyz", water_rows(4),
                    comment='Properties=species:S:1:pos:R:3 energy=0.0 pbc="F F F"')
    out = tmp_path / "out.xyz"
    rc, _, err = run(["relabel", str(src), "-o", str(out), "--quiet"])
    assert rc == 2 and not out.exists()
    one_error_line(err, "relabel", "qm")


def test_demo_without_pyscf_is_refused_before_its_first_step(monkeypatch, tmp_path):
    hide(monkeypatch, "pyscf")
    out = tmp_path / "demo"
    rc, text, err = run(["demo", "-o", str(out)])
    assert rc == 2 and not out.exists() and "[0/4]" not in text
    line = one_error_line(err, "demo", "qm")
    assert "emlp ir mini-eqm7 --smiles C1CN1" in line  # what runs without the extra


def test_campaign_run_without_pyscf_is_one_line(monkeypatch, tmp_path):
    from emlpack.qm import campaign

    csv = tmp_path / "m.csv"
    csv.write_text("smiles\n" + "\n".join(["C", "O", "N", "CC", "CO", "CN", "C=O", "OO", "NN",
                                            "CCO", "CC=O"]) + "\n")
    campaign.init_campaign(tmp_path / "ds", csv, n_large=0)
    hide(monkeypatch, "pyscf")
    rc, _, err = run(["campaign", "run", str(tmp_path / "ds"), "--workers", "0", "--quiet"])
    assert rc == 2
    one_error_line(err, "campaign", "qm")
    assert not (tmp_path / "ds" / "work").exists()


# ------------------------------------------------------------------ Dask
@pytest.mark.parametrize("module", ["distributed", "dask"])
def test_workers_without_dask_name_the_extra_and_workers_0_runs_here(monkeypatch, tmp_path,
                                                                     module):
    from emlpack.qm.executor import Executor

    hide(monkeypatch, module)
    mol = write_xyz(tmp_path / "mol.xyz", WATER_CORES)
    store = tmp_path / "data.h5"
    rc, _, err = run(["label", str(mol), "-o", str(store), "--workers", "2", "--quiet"])
    assert rc == 2 and not store.exists()
    line = one_error_line(err, "label", "qm")
    assert "(Dask)" in line and "--workers 0" in line
    with Executor(workers=0) as ex:  # in this process: no Dask needed
        ex.submit(pow, 2, 10, tag="a")
        assert [f.result() for _, f in ex.completed()] == [1024]


# ------------------------------------------------------------------ tblite
def test_xtb_preparation_without_tblite_names_the_extra(monkeypatch):
    from emlpack.qm.labeling import check_labeling_dependencies

    hide(monkeypatch, "tblite")
    with pytest.raises(MissingDependencyError, match=r"the preparation level gfn2-xtb \(xTB\)"
                       r" needs tblite, which is not installed: pip install 'emlpack\[qm\]'"):
        check_labeling_dependencies({"level": "tiny", "prepare": {"level": "gfn2-xtb"}},
                                    workers=0)
    check_labeling_dependencies({"level": "tiny", "prepare": {"level": "tiny"}}, workers=0)


# ------------------------------------------------------------------ spglib
def test_symmetry_constraint_without_spglib_names_the_extra(monkeypatch):
    from emlpack.calculators.labeler import ModelLabeler
    from emlpack.qm.crystal_optimize import optimize_crystal
    from tests.nn.helpers import water_crystal
    from tests.properties.toy import spring_model

    s = water_crystal()
    labeler = ModelLabeler(spring_model(s, core_cutoff=3.5, pair_cutoff=2.0))
    hide(monkeypatch, "spglib")
    with pytest.raises(MissingDependencyError) as info:
        optimize_crystal(labeler, s, max_steps=1, symprec=0.01, log=lambda m: None)
    assert str(info.value) == (
        "symprec=0.01 (the space-group constraint) needs spglib, which is not installed:"
        " pip install 'emlpack[periodic]'; or symprec=None (no constraint)")
    res = optimize_crystal(labeler, s, max_steps=1, symprec=None, log=lambda m: None)
    assert res.steps >= 1


# ------------------------------------------------------------------ TensorBoard
def test_tensorboard_logging_without_tensorboard_is_refused_before_training(monkeypatch,
                                                                            tmp_path):
    import yaml

    hide(monkeypatch, "tensorboard")
    run_dir = tmp_path / "run"
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump({"data": {"path": str(tmp_path / "data.xyz")},
                                   "output": {"dir": str(run_dir), "tensorboard": True}}))
    rc, _, err = run(["train", str(cfg)])
    assert rc == 2 and not run_dir.exists()
    line = one_error_line(err, "train", "tensorboard")
    assert "output.tensorboard=false" in line


# ------------------------------------------------------------------ CP2K (from the system)
def test_labeling_a_crystal_without_cp2k_is_one_line(monkeypatch, tmp_path):
    from emlpack.qm.cp2k import CP2KInputError, CP2KLabeler, label_into_store
    from emlpack.qm.cp2k import input as cp2k_input
    from tests.nn.helpers import water_crystal

    monkeypatch.setattr(cp2k_input.shutil, "which", lambda name: None)
    s = water_crystal()
    with pytest.raises(CP2KInputError) as info:
        CP2KLabeler()(s)
    text = str(info.value)
    assert "\n" not in text
    assert text == (f"{s.source}: CP2K cannot run: cp2k.psmp not found on PATH (install CP2K"
                    " from the system: apt-get install cp2k cp2k-data openmpi-bin, or `make"
                    " install-cp2k` in a clone)")
    store = tmp_path / "cp2k.h5"  # refused before the store exists, not one failure per item
    with pytest.raises(CP2KInputError, match="CP2K cannot run: cp2k.psmp not found"):
        label_into_store([("water/0000", s, False)], store)
    assert not store.exists()
