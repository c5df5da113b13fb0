"""Arguments and checks shared by the ``emlp`` commands.

Every check here is cheap and runs before any expensive work (pair guess, relaxation,
Hessians, MD): the model file, the structure's elements, periodicity, cell, close atoms, pairs
out of the model's reach, a structure too large for the neighbour list, pair count, the field,
run lengths. A failed check raises an :class:`~emlpack.errors.EmlpackError`
whose one-line message names the file, the frame and the problem; ``emlp`` prints it and exits 2.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from emlpack.errors import InputError, MissingDependencyError, ModelFileError

if TYPE_CHECKING:
    from collections.abc import Collection, Iterable, Sequence

    from ase import Atoms

    from emlpack.calculators.ensemble import ModelMember
    from emlpack.nn.potential import EMLP
    from emlpack.structure import Structure

#: a field above this (V/Å; about 0.02 au, twice the training range) needs ``--force``
MAX_FIELD_V_PER_A = 1.0
#: atomic cores closer than this (Å) are refused
MIN_CORE_DISTANCE = 0.5
#: the first bytes of a zip archive, the container of every ``torch.save`` file
ZIP_MAGIC = b"PK\x03\x04"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows ``(default: X)`` for every option with a meaningful default."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (action.default is None or action.default is False
                or action.default == argparse.SUPPRESS or "default" in text):
            return text
        return super()._get_help_string(action)


#: ``sub`` of every ``add_*`` command function: what ``ArgumentParser.add_subparsers()``
#: returns (its class, argparse._SubParsersAction, is private to argparse)
Subparsers = Any


def add_parser(sub: Subparsers, name: str, help: str, description: str | None = None,
               threads: bool = True,
               threads_default: int | None = None) -> argparse.ArgumentParser:
    """A sub-command parser with defaults in ``--help``, ``--debug`` and ``--threads`` (the
    threads of this process and of the processes it starts: ``emlp`` sets ``OMP_NUM_THREADS``
    from it before torch or PySCF is imported; ``threads=False`` for a command group whose
    sub-commands define their own)."""
    p = sub.add_parser(name, help=help, description=description or help,
                       formatter_class=HelpFormatter)
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="show the traceback of an error")
    if threads:
        add_threads_argument(p, threads_default)
    return p


class Log:
    """Progress and results: results go to stdout, progress to stderr unless ``quiet``."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet

    def __call__(self, text: str) -> None:
        """Print a result line to stdout."""
        print(text, flush=True)

    def progress(self, text: str) -> None:
        """Print a progress line to stderr, unless ``quiet`` (above a progress bar, without
        breaking it: :func:`emlpack.progress.write`)."""
        if not self.quiet:
            from emlpack.progress import write

            write(text, file=sys.stderr)

    def bar(self, iterable: Iterable, desc: str, unit: str, total: int | None = None
            ) -> Iterable:
        """``iterable`` with a progress bar on stderr (:func:`emlpack.progress.progress`:
        rate and time left on a terminal, plain lines otherwise), none when ``quiet``."""
        from emlpack.progress import progress

        return progress(iterable, total=total, desc=desc, unit=unit, enabled=not self.quiet,
                        file=sys.stderr)


# --------------------------------------------------------------------------- arguments
@functools.cache
def _pretrained_names() -> str:
    """The installed pretrained names for the help texts (the folder is listed once)."""
    from emlpack.pretrained import available

    return ", ".join(available()) or "none installed"


def add_model_argument(p: argparse.ArgumentParser, ensemble: bool = True) -> None:
    """The MODEL argument; ``ensemble=False`` for the commands that take one model."""
    known = _pretrained_names()
    if ensemble:
        text = ("an emlpack model file (.pt), a folder of them (an ensemble: mean and spread)"
                f" or a pretrained name ({known})")
    else:
        text = ("an emlpack model file (.pt); one file of an ensemble folder or of a"
                f" pretrained ensemble ({known})")
    p.add_argument("model", help=text)


def add_structure_arguments(p: argparse.ArgumentParser) -> None:
    """The STRUCTURE argument and ``--smiles``, ``--index``, ``--charge`` (e), ``--guess``."""
    p.add_argument("structure", nargs="?",
                   help="xyz/extxyz file; electron pairs as Es rows (guessed when absent)")
    p.add_argument("--smiles", help="a molecule from SMILES instead of a file (RDKit 3D"
                   " embedding, pairs guessed)")
    p.add_argument("--index", default="0", help="frame of the structure file")
    p.add_argument("--charge", type=float,
                   help="total charge, e (default: the file's 'charge', the SMILES' formal"
                   " charge, else 0)")
    p.add_argument("--guess", default="auto", choices=["auto", "boys", "lewis"],
                   help="electron-pair guess when the input has none")


def add_field_arguments(p: argparse.ArgumentParser) -> None:
    """``--field`` (V/Å) or ``--field-au`` (atomic units), and ``--force`` to accept a field
    above :data:`MAX_FIELD_V_PER_A`."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--field", type=float, nargs=3, metavar=("EX", "EY", "EZ"),
                   help="homogeneous field, V/Å (default: the structure file's, else zero)")
    g.add_argument("--field-au", type=float, nargs=3, metavar=("EX", "EY", "EZ"),
                   help="homogeneous field, atomic units (1 au = 51.42 V/Å)")
    p.add_argument("--force", action="store_true",
                   help=f"accept a field above {MAX_FIELD_V_PER_A:g} V/Å (outside training)")


def add_threads_argument(p: argparse.ArgumentParser, default: int | None = None) -> None:
    """The ``--threads`` option, with ``default`` (None: the policy of :mod:`emlpack.threads`)."""
    p.add_argument("--threads", type=int, default=default,
                   help="threads (torch, PySCF)" + ("" if default else " (default: min(cores,"
                   " 4) unless OMP_NUM_THREADS is set; idle threads wait passively)"))


def add_quiet_argument(p: argparse.ArgumentParser) -> None:
    """The ``--quiet`` option (no progress messages, no progress bar)."""
    p.add_argument("--quiet", action="store_true", help="no progress messages or bar")


def set_threads(n: int | None) -> None:
    """torch's threads: ``n``, else the policy of :mod:`emlpack.threads` (passive waiting, at
    most min(cores, 4) threads unless OMP_NUM_THREADS says otherwise)."""
    from emlpack.threads import apply_threads

    if n is not None and n < 1:
        raise InputError(f"--threads must be at least 1, got {n}")
    apply_threads(n)


def positive(value: float | None, name: str, allow_zero: bool = False) -> None:
    """Refuse a run length, time step or count that is not positive (or negative)."""
    if value is None:
        return
    bad = value < 0 if allow_zero else value <= 0
    if bad or not np.isfinite(value):
        need = "non-negative" if allow_zero else "positive"
        raise InputError(f"{name} must be {need}, got {value:g}")


def settings(args: argparse.Namespace) -> dict:
    """The resolved command-line settings (saved beside every output)."""
    from emlpack import __version__

    out = {k: v for k, v in vars(args).items() if k not in ("func", "debug") and
           not callable(v)}
    out["emlpack_version"] = __version__
    return out


def write_json(path: str | Path, data: dict) -> None:
    """Write ``data`` to ``path`` as indented JSON, atomically (arrays as lists, other
    non-JSON values as text)."""
    from emlpack._files import atomic_write

    atomic_write(Path(path), lambda fh: json.dump(data, fh, indent=1, default=_jsonable))


def _jsonable(obj: object) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return str(obj)


# --------------------------------------------------------------------------- model
def check_model_file(path: str | Path) -> Path:
    """Refuse a file that cannot be an emlpack model before PyTorch is asked to read it.

    ``torch.save`` writes a zip archive holding ``<name>/data.pkl``; anything else (empty,
    text, random bytes, another archive) is refused here with a one-line reason.
    """
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"{path}: no such model file")
    if path.is_dir():
        raise ModelFileError(f"{path}: is a folder, not a model file (.pt)")
    size = path.stat().st_size
    if size == 0:
        raise ModelFileError(f"{path}: empty file, not an emlpack model")
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head != ZIP_MAGIC:
        kind = "a text file" if _looks_like_text(path) else "binary data"
        raise ModelFileError(f"{path}: not an emlpack model file ({kind}, not a PyTorch"
                             " checkpoint archive)")
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except (zipfile.BadZipFile, OSError) as exc:
        raise ModelFileError(f"{path}: damaged model file ({exc})") from None
    if not any(n.endswith("/data.pkl") or n == "data.pkl" for n in names):
        raise ModelFileError(f"{path}: a zip archive, but not a PyTorch checkpoint")
    return path


def _looks_like_text(path: Path) -> bool:
    with open(path, "rb") as fh:
        chunk = fh.read(512)
    try:
        chunk.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return b"\x00" not in chunk


def model_files(name_or_path: str) -> tuple[list[Path], str]:
    """The checkpoint files of a MODEL argument (a checkpoint file, a folder holding one or
    more, or a pretrained name) and a label for messages; each file is checked cheaply."""
    from emlpack.pretrained import resolve_model

    given = Path(name_or_path)
    is_name = not given.exists() and not given.suffix and os.sep not in str(name_or_path)
    if is_name or (given.is_dir() and any(given.glob("*.pt"))):
        files, label = resolve_model(name_or_path)
    else:
        files, label = [given], str(given)
    return [check_model_file(f) for f in files], label


def load_members(name_or_path: str) -> list:
    """Every :class:`emlpack.calculators.ensemble.ModelMember` (float64) of a MODEL argument: one
    for a checkpoint, all of them for an ensemble folder or a pretrained name."""
    from emlpack.calculators.ensemble import load_member as _load
    from emlpack.nn.checkpoint import CheckpointError

    files, _ = model_files(name_or_path)
    members = []
    for path in files:
        try:
            members.append(_load(path))
        except CheckpointError as exc:
            if "weights_only" in str(exc) or "Unpickl" in str(exc):  # never advise unsafe loading
                raise ModelFileError(f"{path}: not an emlpack model (a PyTorch file holding"
                                     " pickled objects; emlpack reads weights only)") from exc
            raise
    return members


def load_member(name_or_path: str, command: str = "this command") -> ModelMember:
    """The one :class:`emlpack.calculators.ensemble.ModelMember` of a MODEL argument, for the
    commands that evaluate a single model (an ensemble is refused with one line)."""
    files, label = model_files(name_or_path)
    if len(files) > 1:
        raise InputError(
            f"{label}: an ensemble of {len(files)} models; {command} evaluates one model: pass"
            f" one of its files (e.g. {files[0]}); emlp optimize, ir, polarizability and"
            f" response take ensembles, and EMLPCalculator(model={str(name_or_path)!r}) gives"
            " the ensemble mean and spread in Python")
    return load_members(str(files[0]))[0]


def load_model(name_or_path: str) -> EMLP:
    """The float64 :class:`EMLP` of a MODEL argument (see :func:`load_member`)."""
    return load_member(name_or_path).model


def energy_record(member: ModelMember, structure: Structure, model_energy: float) -> dict:
    """Energies for a JSON output: ``energy_eV`` on the DFT scale when the checkpoint holds its
    DFT hydride references (neutral molecules), else the model's own; with the scale named
    and the relative and raw model energies beside it (see docs/pretrained.md)."""
    out = {"energy_eV": float(model_energy), "energy_scale": "model",
           "model_energy_eV": float(model_energy)}
    if member.hydride_delta() is not None and not structure.pbc and structure.charge == 0:
        out["energy_eV"] = float(model_energy + member.dft_shift(structure.numbers))
        out["energy_relative_eV"] = float(model_energy
                                          + member.relative_shift(structure.numbers))
        out["energy_scale"] = "dft"
    return out


def model_elements(model: EMLP) -> tuple[int, ...]:
    """The atomic numbers of the elements the model was trained for."""
    return tuple(int(z) for z in model.config.elements)


# --------------------------------------------------------------------------- structures
def read_input_atoms(args: argparse.Namespace) -> tuple[Atoms, str]:
    """``(atoms, where)``: the raw input frame (``Es`` rows kept) from the file or ``--smiles``;
    ``where`` names file and frame for every later message."""
    smiles = getattr(args, "smiles", None)
    path = getattr(args, "structure", None)
    if smiles and path:
        raise InputError("give a structure file or --smiles, not both")
    if not smiles and not path:
        raise InputError("give a structure file or --smiles")
    if smiles:
        from ase import Atoms

        from emlpack.optional import import_optional
        from emlpack.qm.sampling import molecule_from_smiles

        Chem = import_optional("rdkit.Chem", "--smiles (RDKit 3D embedding)",
                               alternative="give an xyz file")

        mol = molecule_from_smiles(smiles, name=f"SMILES {smiles}")
        atoms = Atoms(numbers=mol.numbers, positions=mol.positions)
        atoms.info["charge"] = float(Chem.GetFormalCharge(Chem.MolFromSmiles(smiles)))
        return atoms, f"SMILES {smiles}"
    from emlpack.io.extxyz import read_frame_atoms

    p = Path(path)
    if p.suffix.lower() in (".xyz", ".extxyz") or not p.is_file():
        return read_frame_atoms(p, args.index), f"{p}, frame {args.index}"
    import ase.io

    try:
        index = int(args.index)
    except ValueError:
        raise InputError(f"{p}: frame index must be an integer, got {args.index!r}") from None
    try:
        atoms = ase.io.read(p, index=index)
    except Exception as exc:  # ASE raises many types for foreign files
        raise InputError(f"{p}, frame {index}: cannot read the structure:"
                         f" {one_line_text(exc)}") from None
    return atoms, f"{p}, frame {index}"


def one_line_text(exc: BaseException) -> str:
    """The message of ``exc`` on one line (its class name when it has none)."""
    text = " ".join(part.strip() for part in str(exc).splitlines() if part.strip())
    return text or type(exc).__name__


def check_atoms(atoms: Atoms, where: str, elements: Collection[int], periodic: bool | None = None,
                command: str = "", cutoff: float | None = None) -> None:
    """The cheap checks on the raw frame: elements the model knows, pbc and cell consistent,
    periodicity the command needs, no cores closer than :data:`MIN_CORE_DISTANCE`; with the
    model's ``cutoff`` (Å) also :func:`check_reach`."""
    from ase.data import chemical_symbols

    from emlpack.structure import PAIR_NUMBER

    numbers = atoms.numbers
    cores = numbers != PAIR_NUMBER
    if not cores.any():
        raise InputError(f"{where}: no atoms in the structure")
    unknown = sorted(set(numbers[cores].tolist()) - set(elements))
    if unknown:
        names = ", ".join(f"{chemical_symbols[z]} (Z={z})" for z in unknown)
        known = ", ".join(chemical_symbols[z] for z in sorted(elements))
        raise InputError(f"{where}: element(s) {names} not supported by the model (trained for"
                         f" {known})")
    pbc = np.asarray(atoms.pbc, dtype=bool)
    cell = atoms.cell.array
    has_cell = bool(np.any(np.abs(cell) > 0))
    if pbc.any() and not pbc.all():
        raise InputError(f"{where}: mixed periodicity pbc={pbc.tolist()} is not supported"
                         " (all or none)")
    if has_cell and not pbc.any():
        raise InputError(f"{where}: a cell (Lattice) is given but pbc is false: set"
                         " pbc=\"T T T\" for a crystal or drop the Lattice for a molecule")
    if pbc.all() and abs(np.linalg.det(cell)) < 1e-6:
        raise InputError(f"{where}: periodic structure with a singular or missing cell")
    is_crystal = bool(pbc.all())
    if periodic is True and not is_crystal:
        raise InputError(f"{where}: {command} needs a crystal (Lattice and pbc=\"T T T\");"
                         " this is a molecule")
    if periodic is False and is_crystal:
        raise InputError(f"{where}: {command} needs a molecule; this is a crystal (pbc true)")
    with np.errstate(over="ignore", invalid="ignore"):  # e.g. 1e308 Å: refused below
        _check_distances(atoms, where, cores, cell, is_crystal, cutoff)


def _check_distances(atoms: Atoms, where: str, cores: np.ndarray, cell: np.ndarray,
                     is_crystal: bool, cutoff: float | None) -> None:
    from ase.data import chemical_symbols

    numbers = atoms.numbers
    pos = atoms.positions[cores]
    if len(pos) > 1:
        d = pos[:, None, :] - pos[None, :, :]
        if is_crystal:
            from ase.geometry import find_mic

            d = find_mic(d.reshape(-1, 3), cell, True)[0].reshape(d.shape)
        r = np.linalg.norm(d, axis=-1) + np.eye(len(pos)) * 1e9
        i, j = np.unravel_index(int(np.argmin(r)), r.shape)
        if r[i, j] < MIN_CORE_DISTANCE:
            ci, cj = np.flatnonzero(cores)[[min(i, j), max(i, j)]]
            raise InputError(
                f"{where}: atoms {ci} ({chemical_symbols[numbers[ci]]}) and {cj}"
                f" ({chemical_symbols[numbers[cj]]}) are {r[i, j]:.2f} Å apart (closer than"
                f" {MIN_CORE_DISTANCE:g} Å)")
    if cutoff is not None:
        check_reach(atoms, where, cutoff)


def check_reach(atoms: Atoms, where: str, cutoff: float) -> None:
    """Refuse an electron pair (``Es`` row) farther than the model's ``cutoff`` (Å) from every
    core (minimum image in a crystal: outside the reach of every core's short range, so not a
    pair of this structure), and a structure larger than the neighbour list can take
    (:func:`emlpack.nn.neighbors.neighbor_list_problem`; it would crash vesin), naming the
    particle farthest from the others."""
    from ase.data import chemical_symbols

    from emlpack.geometry import minimum_image_distances
    from emlpack.nn.neighbors import neighbor_list_problem
    from emlpack.structure import PAIR_NUMBER

    numbers, positions = atoms.numbers, atoms.positions
    pbc = bool(np.all(atoms.pbc))
    is_pair = numbers == PAIR_NUMBER
    if is_pair.any() and (~is_pair).any():
        d = minimum_image_distances(positions[is_pair], positions[~is_pair], atoms.cell.array,
                                    pbc).min(axis=1)
        k = int(np.argmax(d))
        if d[k] > cutoff:
            row = int(np.flatnonzero(is_pair)[k])
            raise InputError(
                f"{where}: electron pair at particle row {row} (Es at {_xyz(positions[row])} Å)"
                f" is {d[k]:.4g} Å from the"
                f" nearest core, farther than the model's cutoff {cutoff:g} Å from every core")
    problem = neighbor_list_problem(positions, atoms.cell.array, pbc, cutoff)
    if problem:
        far = int(np.argmax(np.linalg.norm(positions - np.median(positions, axis=0), axis=1)))
        raise InputError(
            f"{where}: {problem}: particle row {far} ({chemical_symbols[numbers[far]]} at"
            f" {_xyz(positions[far])} Å) is the farthest from the others")


def _xyz(point: np.ndarray) -> str:
    """A position (Å) for a message: ``(x, y, z)``, 4 significant digits."""
    return "(" + ", ".join(f"{x:.4g}" for x in point) + ")"


def read_structure(args: argparse.Namespace, model: EMLP, log: Log, periodic: bool | None = None,
                   command: str = "") -> tuple[Structure, str]:
    """The input structure of a command, checked cheaply first, then pairs guessed if needed.

    Returns ``(structure, where)``. The field is applied separately (:func:`apply_field`).
    """
    from emlpack.io.extxyz import check_pair_count, frame_field, frame_to_structure
    from emlpack.structure import PAIR_NUMBER

    atoms, where = read_input_atoms(args)
    if args.charge is not None:
        atoms.info["charge"] = float(args.charge)
    charge = float(atoms.info.get("charge", 0.0))
    check_atoms(atoms, where, model_elements(model), periodic, command, model.config.cutoff)
    requested = requested_field(args)
    check_field(frame_field(atoms, where) if requested is None else requested, args, where)
    is_pair = atoms.numbers == PAIR_NUMBER
    if is_pair.any():
        return frame_to_structure(atoms, where), where
    check_pair_count(atoms.numbers, None, charge, where)
    from emlpack.io import atoms_to_structure
    from emlpack.pairs.guess import guess_pairs

    t0 = time.perf_counter()
    method = args.guess
    log.progress(f"guessing electron pairs ({method}) for {atoms.get_chemical_formula()} ...")
    cores = atoms.copy()
    cores.info.pop("electron_pairs", None)
    try:
        pairs = guess_pairs(cores, method, charge=charge)
    except MissingDependencyError:
        raise  # its own line names the extra
    except Exception as exc:  # PySCF and the Lewis guess raise many types
        raise InputError(f"{where}: the electron-pair guess ({method}) failed:"
                         f" {one_line_text(exc)}") from exc
    log.progress(f"guessed {len(pairs)} electron pairs in {time.perf_counter() - t0:.1f} s")
    field = frame_field(atoms, where)
    return atoms_to_structure(cores, pairs=pairs, field=field, charge=charge,
                              source=f"{where} (guessed pairs)"), where


def requested_field(args: argparse.Namespace) -> np.ndarray | None:
    """The field (V/Å) of ``--field``/``--field-au``, or None."""
    from emlpack.units import FIELD_AU_IN_V_PER_A

    if getattr(args, "field", None) is not None:
        return np.asarray(args.field, float)
    if getattr(args, "field_au", None) is not None:
        return np.asarray(args.field_au, float) * FIELD_AU_IN_V_PER_A
    return None


def check_field(field: np.ndarray | Sequence[float] | None, args: argparse.Namespace,
                where: str) -> None:
    """Refuse a non-finite field, or one above :data:`MAX_FIELD_V_PER_A` without ``--force``."""
    if field is None:
        return
    field = np.asarray(field, float)
    if not np.all(np.isfinite(field)):
        raise InputError(f"{where}: the field contains NaN or infinity")
    norm = float(np.linalg.norm(field))
    if norm > MAX_FIELD_V_PER_A and not getattr(args, "force", False):
        raise InputError(
            f"{where}: field |F| = {norm:.3g} V/Å is above {MAX_FIELD_V_PER_A:g} V/Å (about"
            " 0.02 au, twice the training range); pass --force to use it anyway")


def apply_field(s: Structure, args: argparse.Namespace, where: str,
                log: Log) -> tuple[Structure, dict]:
    """The structure with ``--field``/``--field-au`` applied (else the file's field), checked
    and printed; returns ``(structure, info)`` with ``info`` for the JSON output."""
    requested = requested_field(args)
    source = "--field" if requested is not None else "the structure file"
    field = s.field if requested is None else requested
    check_field(field, args, where)
    if requested is not None:
        s = s.copy(field=np.asarray(requested, float))
    if not np.any(s.field):
        source = "none"
        log("field: none (zero)")
    else:
        log(f"field: {np.array2string(s.field, precision=5)} V/Å (from {source})")
    return s, {"field_V_per_A": s.field.tolist(), "field_source": source}
