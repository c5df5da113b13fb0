"""Extended-xyz reading and writing of :class:`~emlpack.structure.Structure`, on top of ASE.

Each frame is parsed by ASE's extxyz reader (``ase.io.read(..., format="extxyz")``); this module
only splits the file into frames (to name the frame in every error and to stream large files),
interprets the keys and removes core centres. Two conventions:

``reference`` (the TensorFlow eMLP's files; also called legacy)
    electron pairs are rows of species ``Es`` (Z = 99) after the atoms, possibly including the
    1s core centres on C/N/O (removed on read, see :mod:`emlpack.io.cores`); ``efield`` is the
    field in atomic units (Hartree/(e·bohr)); ``Lattice`` (rows = cell vectors, Å) makes a frame
    periodic; ``energy`` in eV; the per-atom ``force`` column in eV/Å (zero on ``Es`` rows, which
    carry no labels).
``native`` (what emlpack writes)
    the same ``Es`` rows (valence pairs only); ``external_field`` in V/Å; ASE's ``energy`` (eV),
    ``forces`` column (eV/Å, zero on ``Es`` rows), optional ``pair_forces`` column (eV/Å, zero on
    atom rows), ``stress`` (eV/Å^3, ASE sign), ``charge`` (e) and an optional
    ``polarizability`` label (9 numbers, the 3x3 tensor row by row, e·Å²/V, nuclei clamped).

``auto`` picks ``native`` for a frame with ``external_field`` and ``reference`` otherwise. The
field is converted between atomic units and V/Å here and nowhere else.
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import IO, TYPE_CHECKING

import ase.io
import numpy as np
from ase import Atoms
from ase.io.extxyz import key_val_str_to_dict_regex
from ase.stress import voigt_6_to_full_3x3_stress
from ase.utils import string2index

from emlpack._files import atomic_write
from emlpack.errors import InputError, MissingFileError
from emlpack.io.cores import CORE_TOLERANCE, split_core_centres
from emlpack.structure import (
    MAX_SUPPORTED_Z,
    PAIR_NUMBER,
    Structure,
    StructureError,
    core_charges,
    n_core_pairs,
)
from emlpack.units import FIELD_AU_IN_V_PER_A

if TYPE_CHECKING:
    from collections.abc import Sequence

__all__ = [
    "ExtxyzError",
    "ReferenceFrame",
    "iread_frame_atoms",
    "read_reference_frames",
    "reference_field",
    "check_pair_count",
    "frame_to_structure",
    "read_frame_atoms",
    "frame_field",
    "iread_structures",
    "read_structures",
    "write_structures",
    "CONVENTIONS",
    "MAX_REFERENCE_FIELD_AU",
]

CONVENTIONS = ("auto", "native", "reference")
#: |efield| (atomic units) above which a reference file is rejected as probably holding V/Å
MAX_REFERENCE_FIELD_AU = 1.0
#: keys of ``Structure.info`` that record the core centres removed on read (Å; rows among Es)
CORE_CENTRES_KEY = "core_centres"
CORE_CENTRE_ROWS_KEY = "core_centre_rows"

_ALWAYS_RESERVED = {
    "efield",
    "external_field",
    "charge",
    "energy",
    "forces",
    "force",
    "pair_forces",
    "pbc",
    "Lattice",
    "Properties",
    CORE_CENTRES_KEY,
    CORE_CENTRE_ROWS_KEY,
}


#: frame keys that hold numbers; a bare word of a free-text comment (value ``True``) is ignored
_NUMERIC_LABELS = {"energy", "free_energy", "charge", "efield", "external_field", "stress",
                   "dipole", "magmom", "polarizability"}


#: the frame keys with a fixed shape that the reader takes, and what each must hold: a frame
#: whose value has another shape is refused with one line naming the key and this
FRAME_KEY_SHAPES = {
    "efield": (3, "3 numbers (the field, atomic units)"),
    "external_field": (3, "3 numbers (the field, V/Å)"),
    "field": (3, "3 numbers"),
    "dipole": (3, "3 numbers (e·Å)"),
    "Lattice": (9, "9 numbers (the three cell vectors, Å)"),
    "stress": (9, "9 numbers (a 3x3 matrix, eV/Å^3)"),
    "polarizability": (9, "9 numbers (a 3x3 matrix row by row, e·Å²/V)"),
    "pbc": (3, "3 flags T or F"),
}
#: the keys of :data:`FRAME_KEY_SHAPES` that hold a vector of 3 numbers
_VECTOR_KEYS = ("efield", "external_field", "field", "dipole")


class ExtxyzError(StructureError):
    """A malformed or inconsistent extxyz file; the message names file, frame and problem."""


# ---------------------------------------------------------------------------------- reading
def read_structures(
    path: str | os.PathLike,
    index: int | slice | str = ":",
    convention: str = "auto",
    core_tolerance: float = CORE_TOLERANCE,
) -> list[Structure]:
    """Read the frames ``index`` (ASE syntax: ``":"``, ``"-1"``, ``"2:10:2"``, int, slice).

    Positions and cell in Å, field in V/Å, energy in eV, forces in eV/Å. Core centres are removed
    within ``core_tolerance`` (Å, minimum image under PBC) and recorded in
    ``structure.info["core_centres"]`` (Å) and ``info["core_centre_rows"]`` (rows among the
    frame's ``Es`` rows) so that :func:`write_structures` can put them back.

    Raises:
        ExtxyzError: (a :class:`StructureError`) naming file, 0-based frame and problem.
    """
    return list(iread_structures(path, index, convention, core_tolerance))


def iread_structures(
    path: str | os.PathLike,
    index: int | slice | str = ":",
    convention: str = "auto",
    core_tolerance: float = CORE_TOLERANCE,
) -> Iterator[Structure]:
    """Iterate over the frames ``index`` of ``path`` one at a time (see :func:`read_structures`).

    Frames are parsed lazily, so memory stays bounded for large files; arguments are checked
    at the call.
    """
    if convention not in CONVENTIONS:
        raise InputError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    frames = iread_frame_atoms(path, index)
    return (_atoms_to_structure(atoms, convention, source, core_tolerance)
            for atoms, source in frames)


def iread_frame_atoms(
    path: str | os.PathLike, index: int | slice | str = ":"
) -> Iterator[tuple[Atoms, str]]:
    """The raw ASE frames ``index`` of ``path`` (``Es`` rows included) with their sources
    (``"PATH, frame I"``), parsed one at a time; the file and ``index`` are checked at the call.

    Raises:
        MissingFileError: no such file.
        ExtxyzError: naming file, 0-based frame and problem.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{path}: no such file")
    wanted = _selection(path, index)
    return _iterate(path, wanted)


def _iterate(path: Path, wanted: range | set[int]) -> Iterator[tuple[Atoms, str]]:
    last = max(wanted) if isinstance(wanted, (set, frozenset)) and wanted else None
    any_frame = False
    n_frames = 0
    for i, line, text in _frame_texts(path):
        any_frame = True
        n_frames = i + 1
        if isinstance(wanted, range) and i >= wanted.stop:
            return
        if last is not None and i > last:
            return
        if i not in wanted:
            continue
        source = f"{path}, frame {i}"
        yield _parse_frame(text, source, line), source
    if not any_frame:
        raise ExtxyzError(f"{path}: the file contains no frames")
    if last is not None and len(wanted) == 1 and last >= n_frames:  # an explicit frame number
        raise ExtxyzError(f"{path}: frame {last} requested but the file has {n_frames} frames")


def _selection(path: Path, index: int | slice | str) -> range | set[int]:
    """Frame numbers selected by ``index``; counts the frames only for negative indices."""
    if isinstance(index, str):
        index = string2index(index)
    if isinstance(index, (int, np.integer)):
        index = int(index)
        if index < 0:
            n = _count_frames(path)
            if index < -n:
                raise ExtxyzError(f"{path}: frame {index} requested but the file has {n} frames")
            index += n
        return {index}
    if not isinstance(index, slice):
        raise TypeError(f"index must be an int, a slice or a string, got {index!r}")
    start, stop, step = index.start, index.stop, index.step
    if (step is None or step > 0) and (start or 0) >= 0 and (stop is None or stop >= 0):
        return range(start or 0, stop if stop is not None else 2**62, step or 1)
    return set(range(_count_frames(path))[index])


def _count_frames(path: Path) -> int:
    return sum(1 for _ in _frame_texts(path))


def _frame_texts(path: Path) -> Iterator[tuple[int, int, str]]:
    """Yield (frame number, first line number, text) per frame; checks only the line counts."""
    with open(path, encoding="utf-8", errors="replace") as fd:
        lineno = 0
        frame = 0
        while True:
            header = fd.readline()
            lineno += 1
            if not header:
                return
            if not header.strip():
                for extra in fd:
                    lineno += 1
                    if extra.strip():
                        raise ExtxyzError(
                            f"{path}, frame {frame}: blank line before line {lineno}, where more"
                            " data follows (frames must not be separated by blank lines)"
                        )
                return
            start = lineno
            try:
                n = int(header.strip())
            except ValueError:
                raise ExtxyzError(
                    f"{path}, frame {frame} (line {lineno}): expected the particle count, got"
                    f" {header.strip()[:60]!r}"
                ) from None
            if n <= 0:
                raise ExtxyzError(
                    f"{path}, frame {frame} (line {lineno}): frame declares {n} particles;"
                    " a frame needs at least one atom"
                )
            lines = [header]
            for _ in range(n + 1):
                line = fd.readline()
                if not line:
                    got = max(len(lines) - 2, 0)
                    raise ExtxyzError(
                        f"{path}, frame {frame} (line {start}): truncated file: the frame declares"
                        f" {n} particles but the file ends after {got} particle lines"
                    )
                lines.append(line)
            lineno += n + 1
            yield frame, start, "".join(lines)
            frame += 1


def _parse_frame(text: str, source: str, line: int) -> Atoms:
    try:
        atoms = ase.io.read(io.StringIO(text), format="extxyz", index=0)
    except KeyError as exc:
        raise ExtxyzError(
            f"{source} (line {line}): unknown element symbol {exc.args[0]!r}"
        ) from None
    except Exception as exc:  # ASE raises XYZError, ValueError, IndexError, TypeError
        shape = _key_shape_problem(text, source)
        if shape:
            raise ExtxyzError(shape) from None
        raise ExtxyzError(f"{source} (line {line}): cannot parse the frame: {exc}") from exc
    # a free-text comment line: ASE reads its bare words as flags (``energy`` -> True); labels
    # come only from numeric key=value pairs, so such flags are dropped
    for key in [k for k, v in atoms.info.items() if v is True and k in _NUMERIC_LABELS]:
        del atoms.info[key]
    if atoms.calc is not None:
        results = atoms.calc.results
        for key in [k for k, v in results.items() if v is True and k in _NUMERIC_LABELS]:
            del results[key]
        if not results:
            atoms.calc = None
    if "pbc=" in text.split("\n", 2)[1]:  # ASE takes any text for true ("T T X": periodic)
        shape = _key_shape_problem(text, source, ("pbc",))
        if shape:
            raise ExtxyzError(shape)
    results = atoms.calc.results if atoms.calc is not None else {}
    for key in _VECTOR_KEYS:  # ASE reads any length; the cell it checks itself
        for where in (atoms.info, results):
            if key in where:
                _vector(where[key], key, source)
    if "charge" in atoms.info:
        _scalar(atoms.info["charge"], "charge", source)
    _finite_positions(atoms, source)
    return atoms


def _key_shape_problem(text: str, source: str, keys: Iterable[str] = tuple(FRAME_KEY_SHAPES)
                       ) -> str:
    """The one-line reason (or ``""``) why a key of :data:`FRAME_KEY_SHAPES` on the comment
    line of a frame's ``text`` has the wrong shape: the diagnosis of a frame ASE could not
    read (it refuses a ``Lattice`` or ``stress`` of other than 9 numbers, and fails on a
    ``pbc`` of other than 3 flags, without naming them so)."""
    lines = text.split("\n", 2)
    try:
        values = key_val_str_to_dict_regex(lines[1] if len(lines) > 1 else "")
    except Exception:  # noqa: BLE001 - a comment line too broken to diagnose: ASE's message
        return ""
    for key in keys:
        size, expected = FRAME_KEY_SHAPES[key]
        if key not in values:
            continue
        value = values[key]
        tokens = (str(value).split() if isinstance(value, str)
                  else np.atleast_1d(np.asarray(value)).reshape(-1).tolist())
        if key == "pbc":
            ok = len(tokens) in (1, size) and all(str(t) in _PBC_FLAGS for t in tokens)
        else:
            ok = len(tokens) == size and not isinstance(value, str)
        if not ok:
            if key == "pbc":  # the regex parser gives booleans: shown as the file wrote them
                value = [{True: "T", False: "F"}.get(t, t) for t in tokens]
            return f"{source}: '{key}' must be {expected}, got {len(tokens)}: {_shown(value)}"
    return ""


#: the flags ASE reads as ``pbc`` values
_PBC_FLAGS = {"T", "F", "true", "false", "True", "False", "TRUE", "FALSE"}


def read_frame_atoms(path: str | os.PathLike, index: int | str = 0) -> Atoms:
    """The raw ASE frame ``index`` (an int; negative counts from the end) of an xyz/extxyz file,
    ``Es`` rows included; errors name the file and the frame (:class:`ExtxyzError`)."""
    path = Path(path)
    if path.is_dir():
        raise ExtxyzError(f"{path}: is a folder, not a structure file")
    if not path.is_file():
        raise ExtxyzError(f"{path}: no such file")
    try:
        wanted = int(index)
    except (TypeError, ValueError):
        raise ExtxyzError(f"{path}: frame index must be an integer, got {index!r}") from None
    if wanted < 0:
        wanted += _count_frames(path)
    n_frames = 0
    for i, line, text in _frame_texts(path):
        n_frames = i + 1
        if i == wanted:
            return _parse_frame(text, f"{path}, frame {i}", line)
    if n_frames == 0:
        raise ExtxyzError(f"{path}: the file contains no frames")
    raise ExtxyzError(f"{path}: frame {index} requested but the file has {n_frames} frames")


def frame_field(atoms: Atoms, source: str) -> np.ndarray | None:
    """The field (V/Å) a raw frame (:func:`read_frame_atoms`, or any ASE frame) carries:
    ``external_field`` (V/Å) or the reference convention's ``efield`` (atomic units,
    :func:`reference_field`); None without either. Errors name ``source``."""
    if "external_field" in atoms.info:
        return _vector(atoms.info["external_field"], "external_field", source)
    if "efield" in atoms.info:
        return reference_field(atoms.info["efield"], source)
    return None


def frame_to_structure(atoms: Atoms, source: str, convention: str = "auto",
                       core_tolerance: float = CORE_TOLERANCE) -> Structure:
    """One frame read by :func:`read_frame_atoms` (``Es`` rows as pairs) as a
    :class:`Structure`, interpreted as :func:`read_structures` does; errors name ``source``."""
    return _atoms_to_structure(atoms, convention, source, core_tolerance)


def _atoms_to_structure(
    atoms: Atoms, convention: str, source: str, core_tolerance: float
) -> Structure:
    """Interpret one ASE frame (atoms and ``Es`` rows) in ``convention``."""
    info = dict(atoms.info)
    results = dict(atoms.calc.results) if atoms.calc is not None else {}
    if convention == "auto":
        convention = "native" if "external_field" in info else "reference"
    numbers = atoms.numbers.astype(np.int64)
    positions = _finite_positions(atoms, source)
    flags = np.asarray(atoms.pbc, dtype=bool)
    if flags.any() and not flags.all():
        raise ExtxyzError(
            f"{source}: mixed periodicity pbc={flags.tolist()} is not supported (all or none)"
        )
    pbc = bool(flags.all())
    cell = atoms.cell.array.copy() if pbc else np.zeros((3, 3))

    polarizability = None
    if convention == "native":
        field = _vector(info.pop("external_field", np.zeros(3)), "external_field", source)
        if "polarizability" in info:
            polarizability = _matrix(info.pop("polarizability"), "polarizability", source)
    else:
        field = reference_field(info.pop("efield", None), source)
    charge = _scalar(info.pop("charge", 0.0), "charge", source)
    energy = results.pop("energy", None)
    if energy is not None:
        energy = _scalar(energy, "energy", source)

    if convention == "native":
        forces_all = results.pop("forces", None)
        if forces_all is None:
            forces_all = atoms.arrays.get("force")
        pair_forces_all = atoms.arrays.get("pair_forces")
    else:
        forces_all = atoms.arrays.get("force")
        if forces_all is None:
            forces_all = results.pop("forces", None)
        pair_forces_all = None
    results.pop("forces", None)
    stress = results.pop("stress", None)
    if stress is not None:
        stress = np.asarray(stress, dtype=np.float64)
        stress = voigt_6_to_full_3x3_stress(stress) if stress.shape == (6,) else stress
        if convention == "reference":  # unit not defined by the reference: keep it as metadata
            info["stress"] = stress
            stress = None
    info.update(results)  # e.g. dipole, free_energy: kept as metadata

    is_pair = numbers == PAIR_NUMBER
    core_rows = np.flatnonzero(~is_pair)
    pair_rows = np.flatnonzero(is_pair)
    centres = positions[pair_rows]
    if len(pair_rows):
        check_pair_count(numbers[core_rows], len(pair_rows), charge, source)
    try:
        kept, removed = split_core_centres(
            numbers[core_rows],
            positions[core_rows],
            centres,
            cell,
            pbc,
            charge,
            core_tolerance,
            source,
        )
    except StructureError as exc:
        raise ExtxyzError(str(exc)) from None
    if len(removed):
        info[CORE_CENTRES_KEY] = centres[removed]
        info[CORE_CENTRE_ROWS_KEY] = removed
    try:
        return Structure(
            numbers=numbers[core_rows],
            positions=positions[core_rows],
            pairs=centres[kept],
            cell=cell,
            pbc=pbc,
            field=field,
            charge=charge,
            energy=energy,
            forces=None if forces_all is None else np.asarray(forces_all)[core_rows],
            pair_forces=(
                None if pair_forces_all is None else np.asarray(pair_forces_all)[pair_rows][kept]
            ),
            stress=stress,
            polarizability=polarizability,
            info=info,
            source=source,
        )
    except StructureError as exc:
        message = str(exc)
        if "electron pairs" in message or "valence electrons" in message:
            message += (
                f" (the frame has {len(pair_rows)} Es rows, {len(removed)} of them removed as"
                f" core centres within {core_tolerance:g} Å)"
            )
        raise ExtxyzError(message) from None


def _finite_positions(atoms: Atoms, source: str) -> np.ndarray:
    """The positions (Å) of all rows of a frame; a non-finite one is an error naming its row."""
    positions = atoms.positions.astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(positions), axis=1))
    if len(bad):
        r = int(bad[0])
        raise ExtxyzError(
            f"{source}: particle row {r} ({atoms.get_chemical_symbols()[r]}) has a non-finite"
            f" position {positions[r].tolist()}"
        )
    return positions


def reference_field(efield: object, source: str) -> np.ndarray:
    """The field (V/Å) of a reference-convention frame from its ``efield`` value (atomic units;
    ``None``: no field). The one conversion of the field unit on reading; a magnitude above
    :data:`MAX_REFERENCE_FIELD_AU` is refused as a field probably written in V/Å."""
    if efield is None:
        return np.zeros(3)
    field_au = _vector(efield, "efield", source)
    magnitude = float(np.linalg.norm(field_au))
    if magnitude > MAX_REFERENCE_FIELD_AU:
        raise ExtxyzError(
            f"{source}: |efield| = {magnitude:.4g} atomic units is implausibly large;"
            " this looks like a field in V/Å stored under 'efield'. The reference"
            " convention stores 'efield' in atomic units (1 au = 51.42 V/Å); write"
            " V/Å under 'external_field' instead"
        )
    return field_au * FIELD_AU_IN_V_PER_A


@dataclass
class ReferenceFrame:
    """One reference-convention frame as the file holds it, before its electron pairs are
    checked: the input of a labeler (``emlp relabel``), which may have no ``Es`` rows, only the
    valence ones or an odd electron count (reported per frame by the labeler, not here).

    ``centres`` are all ``Es`` rows in file order (core centres included), ``field`` is in V/Å
    (converted by :func:`reference_field`), ``forces`` are on the nuclei (eV/Å).
    """

    numbers: np.ndarray
    positions: np.ndarray
    centres: np.ndarray
    field: np.ndarray
    energy: float | None = None
    forces: np.ndarray | None = None
    info: dict = dataclass_field(default_factory=dict)
    source: str = "<memory>"


def read_reference_frames(
    path: str | os.PathLike, index: int | slice | str = ":"
) -> list[ReferenceFrame]:
    """The frames ``index`` of a reference-convention file as :class:`ReferenceFrame`
    (positions and field checked, errors naming file and frame: :class:`ExtxyzError`)."""
    return [_reference_frame(atoms, source) for atoms, source in iread_frame_atoms(path, index)]


def _reference_frame(atoms: Atoms, source: str) -> ReferenceFrame:
    numbers = atoms.numbers.astype(np.int64)
    positions = _finite_positions(atoms, source)
    is_centre = numbers == PAIR_NUMBER
    if is_centre.all():
        raise ExtxyzError(f"{source}: no nuclei (only Es centres)")
    info = dict(atoms.info)
    results = dict(atoms.calc.results) if atoms.calc is not None else {}
    field = reference_field(info.pop("efield", None), source)
    energy = info.pop("energy", results.get("energy"))
    forces = atoms.arrays.get("force", results.get("forces"))
    return ReferenceFrame(
        numbers=numbers[~is_centre],
        positions=positions[~is_centre],
        centres=positions[is_centre],
        field=field,
        energy=None if energy is None else _scalar(energy, "energy", source),
        forces=None if forces is None else np.asarray(forces, dtype=np.float64)[~is_centre],
        info=info,
        source=source,
    )


def check_pair_count(
    numbers: np.ndarray | Sequence[int], n_given: int | None, charge: float, source: str
) -> None:
    """Raise :class:`ExtxyzError` unless ``n_given`` electron pairs (``Es`` rows) fit the cores
    ``numbers`` at total ``charge``: the valence pairs, or those plus the 1s core centres
    (``n_given=None``: only that the electron count is even, before pairs are guessed).

    The message says what is given and what is needed, e.g. "3 electron pairs given, 4 needed
    for a neutral H2O".
    """
    numbers = np.asarray(numbers, dtype=np.int64)
    formula = Atoms(numbers=numbers).get_chemical_formula(mode="hill")
    what = "a neutral" if charge == 0 else f"charge {charge:+g} of"
    valence = (float(np.sum(core_charges(numbers))) - charge) / 2.0
    if numbers.size == 0 or numbers.min() < 1 or numbers.max() > MAX_SUPPORTED_Z:
        return  # the element check names the problem
    if valence != round(valence):
        raise ExtxyzError(
            f"{source}: odd number of valence electrons for {what} {formula}"
            " (eMLP needs closed-shell electron pairs; is the charge right?)"
        )
    if n_given is None:
        return
    need = int(round(valence))
    inner = int(n_core_pairs(numbers).sum())
    if n_given == need or (inner and n_given == need + inner):
        return
    with_cores = f" ({need + inner} with the 1s core centres)" if inner else ""
    raise ExtxyzError(
        f"{source}: {n_given} electron pairs (Es rows) given, {need} needed for {what}"
        f" {formula}{with_cores}"
    )


def _vector(value: object, key: str, source: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ExtxyzError(f"{source}: '{key}' must be 3 numbers, got {_shown(value)}") from None
    if arr.shape != (3,):
        raise ExtxyzError(f"{source}: '{key}' must have 3 components, got {arr.size}:"
                          f" {_shown(value)}")
    if not np.all(np.isfinite(arr)):
        raise ExtxyzError(f"{source}: '{key}' contains NaN or infinity: {_shown(value)}")
    return arr


def _matrix(value: object, key: str, source: str) -> np.ndarray:
    """A 3x3 frame value: 9 numbers row by row (or a 3x3 array), finite."""
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ExtxyzError(f"{source}: '{key}' must be 9 numbers, got {_shown(value)}") from None
    if arr.shape != (9,):
        raise ExtxyzError(f"{source}: '{key}' must be {FRAME_KEY_SHAPES[key][1]}, got"
                          f" {arr.size}: {_shown(value)}")
    if not np.all(np.isfinite(arr)):
        raise ExtxyzError(f"{source}: '{key}' contains NaN or infinity: {_shown(value)}")
    return arr.reshape(3, 3)


def _shown(value: object) -> str:
    """A frame value for a one-line message: as the file wrote it (numbers space-separated,
    at most 12), quoted."""
    if isinstance(value, np.ndarray) or isinstance(value, (list, tuple)):
        items = np.asarray(value, dtype=object).reshape(-1).tolist()
        text = " ".join(str(x) for x in items[:12]) + (" ..." if len(items) > 12 else "")
        return repr(text)
    return repr(" ".join(str(value).split())[:120])


def _scalar(value: object, key: str, source: str) -> float:
    if isinstance(value, (bool, np.bool_)):
        raise ExtxyzError(f"{source}: '{key}' must be a number, got {_shown(value)}")
    try:
        out = float(np.asarray(value, dtype=np.float64).reshape(()))
    except (TypeError, ValueError):
        raise ExtxyzError(f"{source}: '{key}' must be a number, got {_shown(value)}") from None
    if not np.isfinite(out):
        raise ExtxyzError(f"{source}: '{key}' is not finite: {_shown(value)}")
    return out


# ---------------------------------------------------------------------------------- writing
def write_structures(
    path: str | os.PathLike,
    structures: Structure | Iterable[Structure],
    convention: str = "native",
    core_centres: bool | str = False,
) -> None:
    """Write ``structures`` to ``path`` atomically (:func:`emlpack._files.atomic_write`).

    ``convention="native"`` writes ``external_field`` (V/Å), ``forces``, ``pair_forces``,
    ``stress`` (eV/Å^3), ``polarizability`` (e·Å²/V, 9 numbers row by row) and ``charge``;
    ``"reference"`` writes ``efield`` (atomic units), ``energy``, the ``force`` column and
    ``Lattice`` (stress and polarizability are not written: the reference defines no unit for
    them). With ``core_centres=True`` (reference only) the inner-shell centres
    are written as ``Es`` rows too: the ones removed on read (``info["core_centres"]``, at their
    original rows) or else ``n_core_pairs(Z)`` centres on each nucleus, before the valence pairs.
    ``core_centres="recorded"`` writes them only for a structure that records them (a frame read
    with core centres keeps them, one read without stays without).
    An interrupted or failed write leaves an existing ``path`` untouched.
    """
    if convention not in ("native", "reference"):
        raise ValueError(f"convention must be 'native' or 'reference', got {convention!r}")
    if core_centres not in (False, True, "recorded"):
        raise ValueError(f"core_centres must be True, False or 'recorded', got {core_centres!r}")
    if core_centres and convention != "reference":
        raise ValueError("core_centres=True is only meaningful for convention='reference'")
    if isinstance(structures, Structure):
        structures = [structures]
    path = Path(path)

    def write(fd: IO[str]) -> None:
        for k, structure in enumerate(structures):
            if not isinstance(structure, Structure):
                raise TypeError(
                    f"{path}: item {k} to write is a {type(structure).__name__}, not a Structure"
                )
            atoms, columns = _structure_to_frame_atoms(structure, convention, core_centres)
            ase.io.write(fd, atoms, format="extxyz", columns=columns, write_results=False)

    atomic_write(path, write)


def _structure_to_frame_atoms(
    s: Structure, convention: str, core_centres: bool | str
) -> tuple[Atoms, list[str]]:
    n_cores = s.n_cores
    es = s.pairs
    if core_centres is True or (core_centres == "recorded" and CORE_CENTRES_KEY in s.info):
        es = _with_core_centres(s)
    numbers = np.concatenate([s.numbers, np.full(len(es), PAIR_NUMBER)])
    atoms = Atoms(
        numbers=numbers,
        positions=np.concatenate([s.positions, es], axis=0),
        cell=s.cell if s.pbc else None,
        pbc=s.pbc,
    )
    columns = ["symbols", "positions"]
    info: dict = {}
    extra = {k: v for k, v in s.info.items() if k not in _ALWAYS_RESERVED}
    if s.energy is not None:
        info["energy"] = float(s.energy)
    if convention == "reference":
        columns.append("numbers")
        # 15 significant digits: a value read from a file is written back as it was
        info["efield"] = " ".join(f"{x:.15g}" for x in s.field / FIELD_AU_IN_V_PER_A)
        if s.charge != 0.0:
            info["charge"] = float(s.charge)
        info.update(extra)
        if s.forces is not None:
            force = np.zeros((len(atoms), 3))
            force[:n_cores] = s.forces
            atoms.new_array("force", force)
            columns.append("force")
    else:
        info["external_field"] = s.field.copy()
        info["charge"] = float(s.charge)
        extra.pop("stress", None)
        extra.pop("polarizability", None)
        if s.stress is not None:
            info["stress"] = s.stress.copy()
        if s.polarizability is not None:
            info["polarizability"] = s.polarizability.reshape(-1).copy()
        info.update(extra)
        if s.forces is not None:
            forces = np.zeros((len(atoms), 3))
            forces[:n_cores] = s.forces
            atoms.new_array("forces", forces)
            columns.append("forces")
        if s.pair_forces is not None:
            pair_forces = np.zeros((len(atoms), 3))
            pair_forces[n_cores:] = s.pair_forces
            atoms.new_array("pair_forces", pair_forces)
            columns.append("pair_forces")
    atoms.info = info
    return atoms, columns


def _with_core_centres(s: Structure) -> np.ndarray:
    """Es positions (Å) with the inner-shell centres re-inserted (see :func:`write_structures`)."""
    need = n_core_pairs(s.numbers)
    n_inner = int(need.sum())
    stored = s.info.get(CORE_CENTRES_KEY)
    rows = s.info.get(CORE_CENTRE_ROWS_KEY)
    total = s.n_pairs + n_inner
    ok = False
    if stored is not None and rows is not None:
        stored = np.asarray(stored, dtype=np.float64).reshape(-1, 3)
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        ok = (
            len(stored) == n_inner == len(rows)
            and len(np.unique(rows)) == len(rows)
            and (len(rows) == 0 or (rows.min() >= 0 and rows.max() < total))
        )
    if not ok:
        stored = np.repeat(s.positions, need, axis=0)
        rows = np.arange(n_inner)
    es = np.empty((total, 3))
    is_core = np.zeros(total, dtype=bool)
    is_core[rows] = True
    es[rows] = stored
    es[~is_core] = s.pairs
    return es
