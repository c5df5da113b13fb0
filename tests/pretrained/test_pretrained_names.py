"""Both pretrained names of the mini-eQM7 ensembles (issue 51, item 7): ``mini-eqm7`` (the
shipped one) and ``mini-eqm7-v1`` (the first one, loadable by that name for good). Until v2
ships, ``mini-eqm7-v1`` is an alias of ``mini-eqm7`` (the same files, the same energies);
afterwards it has its own folder. Either way its members are v1's files, byte for byte."""

from __future__ import annotations

import hashlib
import shutil

import numpy as np
import pytest
from ase import Atoms

from emlpack import load_pretrained
from emlpack.calculators.ase import EMLPCalculator
from emlpack.pretrained import (
    KNOWN,
    PRETRAINED_DIR,
    alias_of,
    available,
    folder_of,
    model_card,
    model_files,
    resolve_model,
)

#: sha256 of v1's members (the final study of issue 15, shipped as mini-eqm7 on 2026-11-28,
#: src/emlpack/pretrained/mini-eqm7/model-K.pt at commit 16eaebe)
V1_SHA256 = [
    "674a7a9d78c1165f584ed1f0ba0c76c731c857e6899b0158cd096e081f55dc20",
    "f96279df494c559d7a633e9df40d05f578d991ffe58558220df5364f069bc2b2",
    "602f48b7f06039345d602bd762114cc69fe0d047d3dcc06f0494128b583907b8",
    "e2d57733fad39fd245d49ed6814eee93ad13c3460872f335ddd14e0f44293bad",
]


def _sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_v1_name_is_known_installed_and_serves_v1s_files():
    assert "mini-eqm7-v1" in KNOWN and "mini-eqm7-v1" in available()
    files = model_files("mini-eqm7-v1")
    assert [_sha256(f) for f in files] == V1_SHA256
    assert resolve_model("mini-eqm7-v1") == (files, "mini-eqm7-v1")
    assert "PBE0/aug-cc-pVTZ" in model_card("mini-eqm7-v1")


def test_both_names_load_and_give_the_same_energies_while_v1_is_the_shipped_one():
    """Aziridine from SMILES (a test molecule), pairs guessed and relaxed by every member: the
    same energy, forces and spread from either name while ``mini-eqm7`` is v1; once v2 ships
    (v1 in its own folder) the names must differ."""
    from emlpack.qm.sampling import molecule_from_smiles

    mol = molecule_from_smiles("C1CN1", name="aziridine")
    results = {}
    for name in ("mini-eqm7", "mini-eqm7-v1"):
        ensemble = load_pretrained(name)
        assert ensemble.name == name and len(ensemble.members) == 4
        atoms = Atoms(mol.numbers, mol.positions)
        atoms.calc = EMLPCalculator(ensemble)
        results[name] = (atoms.get_potential_energy(), atoms.get_forces(),
                         atoms.calc.results["energy_std"])
    (e, f, s), (e1, f1, s1) = results.values()
    if alias_of("mini-eqm7-v1") == "mini-eqm7":
        assert e == e1 and s == s1 and np.array_equal(f, f1)
        assert model_files("mini-eqm7") == model_files("mini-eqm7-v1")
    else:  # v2 shipped: v1 lives in its own folder, mini-eqm7 is another ensemble
        assert folder_of("mini-eqm7-v1") == PRETRAINED_DIR / "mini-eqm7-v1"
        assert [_sha256(p) for p in model_files("mini-eqm7")] != V1_SHA256
        assert e != e1


def test_an_installed_folder_of_its_own_wins_over_the_alias(tmp_path, capsys, monkeypatch):
    """The switch of v2's shipping in miniature: first only ``mini-eqm7`` (v1's files) is
    installed and ``mini-eqm7-v1`` reads it; then v1's files move to ``mini-eqm7-v1/`` and
    another ensemble takes ``mini-eqm7``: each name serves its own files, v1 users are
    unaffected."""
    from emlpack import pretrained
    from emlpack.cli import main

    v1 = model_files("mini-eqm7-v1")
    shutil.copytree(v1[0].parent, tmp_path / "mini-eqm7")
    assert available(tmp_path) == ["mini-eqm7", "mini-eqm7-v1"]
    assert alias_of("mini-eqm7-v1", tmp_path) == "mini-eqm7"
    assert model_card("mini-eqm7-v1", tmp_path).startswith(
        "*mini-eqm7-v1: the same files as mini-eqm7")
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path)
    assert main(["pretrained"]) == 0
    out = capsys.readouterr().out
    assert "mini-eqm7-v1 (installed, the same files as mini-eqm7)" in out
    assert "mini-eqm7 (installed)" in out

    (tmp_path / "mini-eqm7").rename(tmp_path / "mini-eqm7-v1")
    assert available(tmp_path) == ["mini-eqm7-v1"]  # the alias's target is gone
    with pytest.raises(pretrained.PretrainedError, match="not installed"):
        resolve_model("mini-eqm7", tmp_path)
    (tmp_path / "mini-eqm7").mkdir()
    shutil.copyfile(v1[0], tmp_path / "mini-eqm7" / "model-0.pt")  # "v2": one member
    assert alias_of("mini-eqm7-v1", tmp_path) is None
    assert [_sha256(f) for f in model_files("mini-eqm7-v1", tmp_path)] == V1_SHA256
    assert len(model_files("mini-eqm7", tmp_path)) == 1
    assert not model_card("mini-eqm7-v1", tmp_path).startswith("*")
