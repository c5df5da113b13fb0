"""Minimal reader/writer of the reference extxyz convention, for ``emlp relabel``.

Convention of the paper's files: electron-pair centres are rows of species ``Es`` (Z = 99),
including the 1s core centres on top of C/N/O when the file has them; ``energy`` in eV (total
energy, field term included); per-atom ``force`` in eV/Å (zero on centres); ``efield`` in atomic
units. This module converts the field to V/Å on read and back on write and nowhere else.

TODO: switch to :mod:`emlpack.io` once its extxyz reader/writer exists (one parser only).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from emlpack._files import atomic_path
from emlpack.errors import EmlpackError
from emlpack.structure import PAIR_NUMBER
from emlpack.units import FIELD_AU_IN_V_PER_A


class RefXYZError(EmlpackError, ValueError):
    """Bad input file; the message names the file, the frame and the problem."""


@dataclass
class RefFrame:
    """One frame: nuclei, all centres in the file, field (V/Å) and optional labels."""

    numbers: np.ndarray
    positions: np.ndarray
    centres: np.ndarray
    field: np.ndarray
    energy: float | None = None
    forces: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    source: str = "<memory>"


def read_frames(path: str | Path, index: str = ":") -> list[RefFrame]:
    """Read frames of a reference extxyz file (``index`` in ASE's slice syntax)."""
    from ase.io import read

    path = Path(path)
    if not path.exists():
        raise RefXYZError(f"{path}: file not found")
    try:
        images = read(str(path), index=index, format="extxyz")
    except Exception as exc:  # noqa: BLE001 - report any parser failure with the file name
        raise RefXYZError(f"{path}: cannot parse as extended xyz: {exc}") from None
    if not isinstance(images, list):
        images = [images]
    start = _first_index(index)
    return [_frame(atoms, f"{path}, frame {start + i}") for i, atoms in enumerate(images)]


def _first_index(index: str) -> int:
    head = index.split(":")[0].strip()
    try:
        value = int(head) if head else 0
    except ValueError:
        return 0
    return max(value, 0)


def _frame(atoms, source: str) -> RefFrame:
    numbers = np.asarray(atoms.numbers)
    positions = np.asarray(atoms.positions, dtype=float)
    if not np.all(np.isfinite(positions)):
        raise RefXYZError(f"{source}: positions contain NaN or infinity")
    is_centre = numbers == PAIR_NUMBER
    if not np.any(~is_centre):
        raise RefXYZError(f"{source}: no nuclei (only Es centres)")
    efield = atoms.info.get("efield", np.zeros(3))
    try:
        efield = np.asarray(efield, dtype=float).reshape(3)
    except (ValueError, TypeError):
        raise RefXYZError(f"{source}: efield must have 3 components, got {efield!r}") from None
    if not np.all(np.isfinite(efield)):
        raise RefXYZError(f"{source}: efield contains NaN or infinity")
    energy = atoms.info.get("energy")
    if energy is None and atoms.calc is not None:
        energy = atoms.calc.results.get("energy")
    forces = atoms.arrays.get("force")
    if forces is None and atoms.calc is not None and "forces" in atoms.calc.results:
        forces = atoms.calc.results["forces"]
    info = {k: v for k, v in atoms.info.items() if k not in ("efield", "energy")}
    return RefFrame(
        numbers=numbers[~is_centre].astype(np.int64),
        positions=positions[~is_centre],
        centres=positions[is_centre],
        field=efield * FIELD_AU_IN_V_PER_A,
        energy=None if energy is None else float(energy),
        forces=None if forces is None else np.asarray(forces, dtype=float)[~is_centre],
        info=info,
        source=source,
    )


def frame_to_atoms(frame: RefFrame):
    """An ``ase.Atoms`` in the reference convention (nuclei, then Es centres)."""
    from ase import Atoms

    n_nuc, n_c = len(frame.numbers), len(frame.centres)
    numbers = np.concatenate([frame.numbers, np.full(n_c, PAIR_NUMBER)])
    atoms = Atoms(numbers=numbers, positions=np.concatenate([frame.positions, frame.centres]))
    atoms.new_array("Z", numbers.astype(np.int64))
    force = np.zeros((n_nuc + n_c, 3))
    if frame.forces is not None:
        force[:n_nuc] = frame.forces
    atoms.new_array("force", force)
    if frame.energy is not None:
        atoms.info["energy"] = float(frame.energy)
    # round away the 1e-19 au noise of the V/Å round trip
    atoms.info["efield"] = np.round(np.asarray(frame.field, float) / FIELD_AU_IN_V_PER_A, 16)
    for key, value in frame.info.items():
        atoms.info.setdefault(key, value)
    return atoms


def write_frames(path: str | Path, frames: list[RefFrame]) -> None:
    """Write frames atomically: a temporary file in the same directory, then a rename."""
    from ase.io import write

    with atomic_path(path) as tmp:
        write(str(tmp), [frame_to_atoms(f) for f in frames], format="extxyz",
              write_results=False)
