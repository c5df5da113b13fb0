"""Rules of the test suite itself, checked so that a green CI keeps meaning what it says."""

from __future__ import annotations

import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def test_no_silent_skips_of_installed_dependencies():
    """Optional dependencies the project installs are imported with `tests.conftest.require`
    (fails under CI=true), never with `pytest.importorskip` (skips silently on CI too)."""
    offenders = []
    for path in sorted(TESTS.rglob("*.py")):
        for k, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0]
            if re.search(r"\bimportorskip\s*\(", code) or re.search(r"\bskipif\s*\(", code):
                offenders.append(f"{path.relative_to(TESTS)}:{k}: {line.strip()}")
    assert not offenders, "\n".join(offenders)
