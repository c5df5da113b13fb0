"""The package's top level: the user's entry points, loaded lazily (no torch on import)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_entry_points_at_the_top_level_are_the_real_ones():
    import emlpack
    from emlpack.calculators.ase import EMLPCalculator
    from emlpack.calculators.ensemble import load_pretrained

    assert emlpack.EMLPCalculator is EMLPCalculator
    assert emlpack.load_pretrained is load_pretrained
    assert {"EMLPCalculator", "load_pretrained"} <= set(dir(emlpack)) & set(emlpack.__all__)
    with pytest.raises(AttributeError, match="no attribute 'EMLPCalulator'"):
        emlpack.EMLPCalulator  # noqa: B018 - a misspelt name is an AttributeError


def test_importing_the_package_does_not_import_torch():
    code = ("import sys, emlpack\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n"
            "from emlpack import EMLPCalculator\n"
            "assert 'torch' in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
