"""DESIGN.md: reference-data generation (qm/, data/store.py) must not import torch."""

from __future__ import annotations

import subprocess
import sys


def test_qm_and_store_do_not_import_torch():
    code = (
        "import sys\n"
        "import emlpack.qm.labeling, emlpack.qm.relabel, emlpack.qm.recipe\n"
        "import emlpack.qm.pyscf_labeler, emlpack.qm.sampling, emlpack.data.store\n"
        "import emlpack.qm.crystal_sampling, emlpack.qm.crystal_optimize\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
