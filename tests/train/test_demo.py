"""The demo pipeline end to end at toy size (PySCF labels, training, evaluation, report)."""

from __future__ import annotations

import pytest

from tests.conftest import require


@pytest.mark.slow
def test_demo_pipeline_writes_the_report(tmp_path):
    require("pyscf")
    from emlpack.demo import run_demo

    assert run_demo(tmp_path, minutes=0.1, n_per_molecule=2) == 0
    report = (tmp_path / "report.md").read_text()
    assert "Static errors" in report and "error rate" in report and "Dipoles" in report
    assert (tmp_path / "evaluation" / "parity.png").exists()
    assert (tmp_path / "run" / "best.pt").exists()
