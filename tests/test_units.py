"""The constants stated in docs/conventions.md are the ones `emlpack.units` uses, to every
digit printed there (the reference's molmod values, not CODATA-2018)."""

from __future__ import annotations

import re

import pytest

from emlpack import units
from tests.conftest import ROOT

DOC = ROOT / "docs" / "conventions.md"


def _stated(pattern: str) -> tuple[float, float]:
    """The number matched by ``pattern`` in the doc and the precision of its last digit."""
    text = " ".join(DOC.read_text().split())
    match = re.search(pattern, text)
    assert match, f"docs/conventions.md no longer states {pattern!r}"
    digits = match.group(1)
    decimals = len(digits.split(".")[1]) if "." in digits else 0
    return float(digits), 0.5 * 10.0**-decimals


@pytest.mark.parametrize(("pattern", "value"), [
    (r"1 Ha = ([\d.]+) eV", units.HARTREE),
    (r"1 Å = ([\d.]+) bohr", units.ANGSTROM_IN_BOHR),
    (r"1 au of field = ([\d.]+) V/Å", units.FIELD_AU_IN_V_PER_A),
    (r"k_e = ([\d.]+) eV·Å", units.COULOMB_EV_A),
    (r"gamma = ([\d.]+)/Å", units.REFERENCE_GAMMA),
    (r"sigma = ([\d.]+) Å", units.REFERENCE_SIGMA),
    (r"\|k\|/\(2 pi\) <= ([\d.]+)/bohr", units.REFERENCE_GCUT_PER_BOHR),
])
def test_documented_constant_equals_the_code(pattern, value):
    stated, half_ulp = _stated(pattern)
    assert abs(stated - value) <= half_ulp * (1 + 1e-12), (pattern, stated, value)


def test_molmod_not_codata_2018():
    """The reference's Hartree differs from CODATA-2018's 27.211386245988 eV in the 7th digit."""
    assert units.HARTREE == pytest.approx(27.2113834736888, rel=1e-15)
    assert abs(units.HARTREE - 27.211386245988) > 1e-6
