"""The demo pipeline end to end at toy size (PySCF labels, training, evaluation, report)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.conftest import require


@pytest.mark.slow
def test_demo_pipeline_writes_the_report(tmp_path):
    require("pyscf")
    from emlpack.cli.demo import run_demo

    assert run_demo(tmp_path, minutes=0.1, n_per_molecule=2) == 0
    report = (tmp_path / "report.md").read_text()
    assert "Static errors" in report and "error rate" in report and "Dipoles" in report
    assert "How to read the tables" in report and "| formula |" in report
    assert "A pretrained model first" in report
    assert (tmp_path / "ir_water.png").exists() and "ir_water.png" in report
    assert (tmp_path / "evaluation" / "parity.png").exists()
    assert (tmp_path / "run" / "best.pt").exists()


def test_demo_without_the_pretrained_model_says_so(tmp_path, monkeypatch):
    import emlpack.pretrained as pretrained
    from emlpack.cli.demo import _pretrained_lines, pretrained_step

    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "none")
    (tmp_path / "none").mkdir()
    calls = []
    step = pretrained_step(tmp_path, lambda argv: calls.append(argv) or 0)
    assert step["status"] == "not installed" and calls == []
    text = "\n".join(_pretrained_lines(step))
    assert "is not installed" in text and "emlp ir mini-eqm7" in text


def test_demo_starts_with_an_installed_pretrained_model(tmp_path, monkeypatch):
    """A toy ensemble installed as ``mini-eqm7``: the demo's first step runs ``emlp ir`` and
    ``emlp polarizability`` on a SMILES molecule and the report shows the results."""
    require("pyscf")
    require("rdkit")
    import emlpack.pretrained as pretrained
    from emlpack.cli.demo import _pretrained_lines, pretrained_step
    from tests.cli.helpers import run

    # the benchmark fixture: a small model trained on the shared eqm7 subset (methane ... ethanol)
    trained = Path(__file__).resolve().parents[2] / "benchmarks/fixtures/eqm7_small_trained.pt"
    root = tmp_path / "pretrained"
    notice = "toy: a preliminary test ensemble"
    pretrained.export_pretrained([trained, trained], root / "mini-eqm7", "# toy\n", notice=notice)
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", root)
    out = tmp_path / "demo"
    out.mkdir()
    step = pretrained_step(out, lambda argv: run(argv)[0], smiles="C")
    assert step["exit_codes"] == [0, 0], step
    assert step["status"] == "done"
    freqs = np.asarray(step["ir"]["frequencies_cm-1"])
    assert len(freqs) == 9 and 1000 < freqs.min() and freqs.max() < 3600   # methane
    assert step["ir"]["warnings"] == [notice] == step["polarizability"]["warnings"]
    assert "polarizability_isotropic_bohr3_std" in step["polarizability"]   # an ensemble
    assert (out / step["ir_plot"]).exists()
    text = "\n".join(_pretrained_lines(step))
    assert "Isotropic polarizability" in text and "emlp ir mini-eqm7 --smiles C" in text
    assert f"{freqs[-1]:.0f} ± " in text            # the frequencies with their spread
    # the models' notice, reported by both commands, is shown once
    assert [line for line in text.splitlines() if line.startswith("- warning")] == [
        f"- warning: {notice}"]


def test_report_names_configurations_by_key_and_formula(tmp_path):
    from emlpack.cli.demo import _formula, write_report

    dipoles = [{"structure": "data.h5, record 3", "dft_dipole_D": 2.2, "emlp_dipole_D": 2.1,
                "max_pair_shift": 0.02, "failure": ""}]
    calc = [{"structure": "data.h5, record 3", "formula": "H2O", "dft_dipole_D": 2.2,
             "emlp_dipole_D": 2.1, "max_pair_shift_A": 0.02, "relaxation": "converged"}]
    cfg = {"model": {"n_features": 8, "n_filters": 8, "n_rbf": 8, "n_interactions": 1},
           "training": {"max_time_minutes": 1}, "data": {"fractions": [0.6, 0.2, 0.2]}}
    names = {"data.h5, record 3": ("H2O/0003", _formula([8, 1, 1]))}
    text = write_report(tmp_path, {"labeling": 1.0}, "## table\n", dipoles, calc, cfg, 10,
                        names=names).read_text()
    assert "| H2O/0003 | H2O | 2.200 |" in text
    assert "record 3" not in text
    assert "is not installed" in text            # no pretrained model: said, not hidden


def test_the_demo_molecule_is_compared_with_its_dft_reference():
    """Aziridine's committed DFT reference (the labels' level) is shown beside the ensemble's
    values, with the polarizability ratio and a pointer when it is off by more than 20 %."""
    import json

    from emlpack.cli.demo import PRETRAINED_REFERENCE, PRETRAINED_SMILES, ROOT, _pretrained_lines

    ref = json.loads((ROOT / PRETRAINED_REFERENCE).read_text())
    alpha = ref["polarizability_isotropic_bohr3"]
    freqs = np.array(ref["frequencies_cm-1"]) + 10.0
    step = {"name": "mini-eqm7", "smiles": PRETRAINED_SMILES, "status": "done", "commands": [],
            "polarizability": {"polarizability_isotropic_bohr3": 2.5 * alpha,
                               "dipole_norm_debye": 1.5, "warnings": []},
            "ir": {"frequencies_cm-1": freqs.tolist(), "warnings": []}}
    text = "\n".join(_pretrained_lines(step))
    assert f"isotropic polarizability {alpha:.2f} bohr³ (the ensemble's is 2.50x that)" in text
    assert "differ by 10 cm⁻¹ on average" in text and "docs/pretrained.md" in text
    step["polarizability"]["polarizability_isotropic_bohr3"] = 1.05 * alpha
    assert "docs/pretrained.md" not in "\n".join(_pretrained_lines(step))
