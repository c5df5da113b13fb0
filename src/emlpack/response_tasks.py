"""The work behind ``emlp ir``, ``emlp polarizability``, ``emlp response`` and ``emlp optimize``:
read a structure (guessing electron pairs when the file has none), relax it as asked, compute,
report and write JSON. The CLI only parses arguments."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from emlpack.structure import Structure, StructureError

#: relaxation levels: nothing, pairs only (BO at the given cores), pairs + cores, + cell
RELAX_LEVELS = ("none", "pairs", "positions", "cell")


def read_input(path: str, index: str = "0", guess: str = "auto") -> Structure:
    """One structure from ``path``; without electron pairs in the file they are guessed with
    :func:`emlpack.guess.guess_pairs` (``guess``: auto, boys, lewis)."""
    from emlpack.io import read_structures

    try:
        return read_structures(path, index)[0]
    except StructureError as exc:
        if "electron pairs" not in str(exc):
            raise
    import ase.io

    from emlpack.guess import guess_pairs
    from emlpack.io import atoms_to_structure

    atoms = ase.io.read(path, index=int(index))
    atoms.info.pop("electron_pairs", None)
    return atoms_to_structure(atoms, pairs=guess_pairs(atoms, guess), source=f"{path} (guessed"
                              f" pairs)")


def relax(model, s: Structure, level: str, method: str = "newton", fmax: float = 1e-6,
          log=print) -> Structure:
    """Relax ``s`` to ``level`` (see :data:`RELAX_LEVELS`); failures are reported, not hidden."""
    from emlpack.optimize import optimize
    from emlpack.relax import relax_pairs

    if level not in RELAX_LEVELS:
        raise ValueError(f"relax level {level!r}: choose from {RELAX_LEVELS}")
    if level == "none":
        return s
    t0 = time.perf_counter()
    r = relax_pairs(model, s, fmax=min(fmax, 1e-6))[0]
    if r.failed:
        log(f"warning: pair relaxation: {r.reason}")
    s = s.copy(pairs=r.pairs)
    log(f"pairs relaxed: {r.iterations} iterations, max force {r.max_force:.1e} eV/Å"
        f" ({time.perf_counter() - t0:.1f} s)")
    if level == "pairs":
        return s
    t0 = time.perf_counter()
    res = optimize(model, s, cell=level == "cell", fmax=fmax, method=method)
    if not res.converged:
        log(f"warning: optimisation: {res.reason}")
    log(res.text() + f"\n({time.perf_counter() - t0:.1f} s)")
    return res.structure


def _write_json(path: str | None, data: dict, log=print) -> None:
    if path:
        Path(path).write_text(json.dumps(data, indent=1))
        log(f"wrote {path}")


def run_polarizability(model, s: Structure, output: str | None, log=print) -> dict:
    from emlpack.response import molecule_response

    t0 = time.perf_counter()
    resp = molecule_response(model, s, relax_cores=True)
    log(resp.text())
    log(f"(extended Hessian and Schur complements: {time.perf_counter() - t0:.2f} s)")
    data = resp.as_dict()
    _write_json(output, data, log)
    return data


def run_ir(model, s: Structure, output: str | None, png: str | None, fwhm: float,
           reference: str | None = None, log=print) -> dict:
    from emlpack.spectra import ir_spectrum, write_ir

    t0 = time.perf_counter()
    spec = ir_spectrum(model, s)
    elapsed = time.perf_counter() - t0
    log(spec.text())
    log(f"(IR spectrum: {elapsed:.2f} s)")
    ref = None
    if reference:
        table = np.loadtxt(reference, ndmin=2)
        ref = (table[:, 0], table[:, 1])
    json_path = output or "ir.json"
    write_ir(spec, json_path, png, fwhm=fwhm, reference=ref, title=s.source)
    log(f"wrote {json_path}" + (f" and {png}" if png else ""))
    return spec.as_dict(fwhm)


def run_response(model, s: Structure, output: str | None, log=print) -> dict:
    from emlpack.response import crystal_response

    t0 = time.perf_counter()
    resp = crystal_response(model, s)
    elapsed = time.perf_counter() - t0
    log(resp.text())
    log(f"(extended Hessian and all tensors: {elapsed:.2f} s)")
    data = resp.as_dict()
    _write_json(output, data, log)
    return data
