"""Helpers of the ``emlp`` command-line tests: a small saved model, xyz files, an in-process
runner."""

from __future__ import annotations

import contextlib
import io

from emlpack.cli import main

#: water cores and its four valence pairs (Å), roughly the Boys centres
WATER_CORES = [("O", 0.0, 0.0, 0.0), ("H", 0.757, 0.586, 0.0), ("H", -0.757, 0.586, 0.0)]
WATER_PAIRS = [("Es", 0.38, 0.30, 0.02), ("Es", -0.37, 0.31, -0.01), ("Es", 0.0, -0.25, 0.30),
               ("Es", 0.02, -0.24, -0.31)]


def water_rows(n_pairs: int = 4) -> list[tuple]:
    return WATER_CORES + WATER_PAIRS[:n_pairs]


def write_xyz(path, rows, comment: str = 'Properties=species:S:1:pos:R:3 pbc="F F F"'):
    lines = [str(len(rows)), comment]
    lines += [f"{s} {x:.6f} {y:.6f} {z:.6f}" for s, x, y, z in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def run(argv: list[str]) -> tuple[int, str, str]:
    """``emlp argv`` in this process: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as exc:
            rc = int(exc.code or 0)
    return rc, out.getvalue(), err.getvalue()


def save_test_model(folder, seed: int = 0) -> object:
    """A small random eMLP (H, C, N, O; float64) saved as ``folder/model.pt``; ``seed=1``
    keeps the electron pairs of water at a minimum (what MD needs)."""
    import torch

    from emlpack.nn.checkpoint import save_model
    from tests.nn.helpers import random_model

    torch.set_num_threads(1)
    path = folder / "model.pt"
    save_model(random_model(seed), path)
    return path
