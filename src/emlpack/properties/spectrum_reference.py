"""Reference spectra to overlay on a computed one (``emlp ir|raman --reference FILE``).

Three kinds of file, told apart by their suffix:

* ``.json``: a spectrum written by the same command (``emlp ir``: ``frequencies_cm-1`` and
  ``intensities_km_per_mol``; ``emlp raman``: ``activities_A4_per_amu``), a DFT reference of
  the same keys (``datasets/mini-eqm7/references/*/NAME.json``,
  ``examples/raman/aziridine_dft.py``), or one with only ``frequencies_cm-1``;
* ``.xyz`` / ``.extxyz``: the first frame's atoms (``Es`` rows dropped) with a Cartesian
  Hessian in eV/Å² (``info["hessian"]``, 3N x 3N, which ASE writes as a ``_JSON`` list; or a
  per-atom array ``hessian`` of 9N columns: the 3 rows of each atom), masses of
  ``ase.data.atomic_masses``; the intensities from ``info["dipole_derivatives"]``
  (dmu_a/dR_ib, 3 x 3N, e) for IR and ``info["polarizability_derivatives"]``
  (d alpha_ab/dR_i, 3N x 3 x 3, Å²) for Raman, else wavenumbers only;
* anything else: a text table of two columns, wavenumber (cm^-1) and intensity (km/mol) or
  activity (Å⁴/amu), separated by commas, semicolons or blanks; ``#`` comments and header lines
  before the numbers are skipped.

Every problem is an :class:`~emlpack.errors.InputError` naming the file (and the line).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from emlpack.errors import InputError
from emlpack.properties.ir import ir_intensities, vibrational_modes
from emlpack.properties.raman import normal_coordinate_per_step, raman_activities
from emlpack.properties.spectra import KINDS, LineSpectrum

#: separators of a text table's columns
_SEPARATORS = re.compile(r"[,;\s]+")


def read_reference_spectrum(path: str | Path, kind: str, label: str | None = None) -> LineSpectrum:
    """The reference line spectrum in ``path`` (module docstring) for ``kind`` (``"ir"`` or
    ``"raman"``), labelled ``label`` (default: its level, when the file names one, and the
    file name)."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a reference spectrum")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".json":
        spec = _from_json(path, kind)
    elif suffix in (".xyz", ".extxyz"):
        spec = _from_extxyz(path, kind)
    else:
        spec = _from_table(path, kind)
    if label:
        spec.label = label
    if not np.all(np.isfinite(spec.frequencies)) or (
            spec.heights is not None and not np.all(np.isfinite(spec.heights))):
        raise InputError(f"{path}: the reference spectrum has values that are not finite")
    if spec.heights is not None and np.any(spec.heights < 0):
        raise InputError(f"{path}: the reference spectrum has negative"
                         f" {KINDS[kind].key.split('_')[0]}")
    return spec


def _label(path: Path, level: object = None) -> str:
    if isinstance(level, str) and level:
        return f"reference: {level} ({path.name})"
    return f"reference ({path.name})"


def _from_json(path: Path, kind: str) -> LineSpectrum:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the reference spectrum: {exc}") from None
    if not isinstance(data, dict) or "frequencies_cm-1" not in data:
        raise InputError(f"{path}: no 'frequencies_cm-1' in the JSON reference spectrum")
    key = KINDS[kind].key
    try:
        freqs = np.asarray(data["frequencies_cm-1"], float).ravel()
        heights = None if data.get(key) is None else np.asarray(data[key], float).ravel()
    except (TypeError, ValueError):
        raise InputError(f"{path}: 'frequencies_cm-1' and '{key}' must be lists of"
                         " numbers") from None
    if heights is not None and heights.shape != freqs.shape:
        raise InputError(f"{path}: {len(freqs)} frequencies but {len(heights)} values of"
                         f" '{key}'")
    return LineSpectrum(freqs, heights, _label(path, data.get("level")))


def _from_table(path: Path, kind: str) -> LineSpectrum:
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the reference spectrum: {exc}") from None
    rows = []
    for k, line in enumerate(lines, 1):
        fields = [f for f in _SEPARATORS.split(line.split("#")[0].strip()) if f]
        if not fields:
            continue
        try:
            values = [float(f) for f in fields[:2]]
        except ValueError:
            if not rows:
                continue  # a header line
            raise InputError(f"{path}, line {k}: not two numbers: {line.strip()!r}") from None
        if len(values) < 2:
            raise InputError(f"{path}, line {k}: the reference spectrum needs two columns"
                             f" (cm^-1, {KINDS[kind].unit.replace('$', '')})")
        rows.append(values)
    if not rows:
        raise InputError(f"{path}: no rows of two numbers (cm^-1, intensity) in the reference"
                         " spectrum")
    table = np.array(rows)
    return LineSpectrum(table[:, 0], table[:, 1], _label(path))


def _from_extxyz(path: Path, kind: str) -> LineSpectrum:
    from ase.data import atomic_masses

    from emlpack.io import split_pairs
    from emlpack.io.extxyz import read_frame_atoms

    atoms = split_pairs(read_frame_atoms(path, 0))
    n = 3 * len(atoms)
    where = f"{path}, frame 0"
    if "hessian" in atoms.info:
        hessian = np.asarray(atoms.info["hessian"], float)
    elif "hessian" in atoms.arrays:
        hessian = np.asarray(atoms.arrays["hessian"], float)
    else:
        raise InputError(f"{where}: no Cartesian Hessian (info or per-atom key 'hessian', eV/Å²)"
                         " for the reference spectrum")
    if hessian.size != n * n:
        raise InputError(f"{where}: the Hessian has {hessian.size} entries, {n} x {n} needed"
                         f" for {len(atoms)} atoms")
    hessian = hessian.reshape(n, n)
    if not np.all(np.isfinite(hessian)):
        raise InputError(f"{where}: the Hessian has values that are not finite")
    masses = atomic_masses[atoms.numbers]
    freqs, vecs, modes = vibrational_modes(hessian, atoms.positions, masses)
    heights = None
    if kind == "ir" and "dipole_derivatives" in atoms.info:
        dmu = _shaped(atoms.info["dipole_derivatives"], (3, n), "dipole_derivatives", where)
        heights = ir_intensities(dmu, vecs, masses)
    elif kind == "raman" and "polarizability_derivatives" in atoms.info:
        dalpha = _shaped(atoms.info["polarizability_derivatives"], (n, 3, 3),
                         "polarizability_derivatives", where)
        d_dq = np.einsum("kx,xab->kab", modes.reshape(len(modes), -1), dalpha)
        heights = raman_activities(d_dq / normal_coordinate_per_step(modes, masses)[:, None, None])
    return LineSpectrum(freqs, heights, _label(path, atoms.info.get("level")))


def _shaped(value: object, shape: tuple[int, ...], key: str, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, float)
    except (TypeError, ValueError):
        raise InputError(f"{where}: '{key}' must be numbers") from None
    if arr.size != int(np.prod(shape)):
        raise InputError(f"{where}: '{key}' has {arr.size} entries, shape {shape} needed")
    return arr.reshape(shape)
