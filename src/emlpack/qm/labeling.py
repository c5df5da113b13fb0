"""``emlp label``: molecules -> preparation -> sampling -> DFT labels -> HDF5 store, on Dask.

Flow per molecule: 3D structure (RDKit from SMILES, or xyz), optimisation and Hessian at the
preparation level (cached beside the store in ``STORE.prep/``), the recipe's configurations,
one labeling task per configuration. Tasks run on a Dask ``LocalCluster`` by default, on any
Dask cluster with ``scheduler=ADDRESS``, or in-process with ``workers=0``. Results are written
by this process only, one committed record at a time (see :mod:`emlpack.data.store`).

Resuming: the store knows which keys are finished (records and recorded failures); a re-run of
the same command skips them, so after a crash (even ``kill -9``) no finished work is lost and
nothing is stored twice. The recipe is saved in the store, and a resumed run must use the same.
"""

from __future__ import annotations

import csv
import logging
import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from emlpack._files import write_npz_atomic
from emlpack.data.store import DatasetStore, StoreError
from emlpack.optional import import_optional
from emlpack.qm.executor import Executor
from emlpack.qm.levels import parse_level
from emlpack.qm.pyscf_labeler import LabelingError, LabelResult, PySCFLabeler
from emlpack.qm.recipe import Configuration, configurations
from emlpack.qm.sampling import (
    PROBES,
    Molecule,
    SamplingError,
    has_negative_curvature,
    masses_of,
    molecule_from_smiles,
    normal_modes,
)
from emlpack.units import ANGSTROM_IN_BOHR, HARTREE

if TYPE_CHECKING:
    from collections.abc import Collection

    from ase import Atoms
    from ase.calculators.calculator import Calculator
    from tqdm import tqdm

log = logging.getLogger(__name__)

#: SMILES of the hydride references
HYDRIDES = {"H2": "[H][H]", "CH4": "C", "NH3": "N", "H2O": "O"}


# ---------------------------------------------------------------------------------- sources
def read_molecules(path: str | Path, select: str | None = None) -> tuple[list, list[str]]:
    """Molecule sources from a SMILES CSV (column ``smiles``), a SMILES list or an xyz file.

    Returns ``(sources, skipped)`` where each source is ``(name, smiles)`` or a
    :class:`Molecule` (xyz input) and ``skipped`` lists reasons for entries left out.
    ``select`` is a Python slice over the entries, e.g. ``"0:3"``.
    """
    path = Path(path)
    if not path.exists():
        raise SamplingError(f"{path}: file not found")
    sources: list = []
    if path.suffix.lower() in (".xyz", ".extxyz"):
        from ase.io import read

        for i, atoms in enumerate(read(str(path), index=":")):
            sources.append(_molecule_from_atoms(atoms, f"{path.stem}-{i:04d}",
                                                f"{path}, frame {i}"))
    elif path.suffix.lower() == ".csv":
        with path.open() as fh:
            reader = csv.DictReader(fh)
            if "smiles" not in (reader.fieldnames or []):
                raise SamplingError(f"{path}: CSV needs a 'smiles' column")
            for i, row in enumerate(reader):
                sources.append((row.get("name") or f"{path.stem}-{i:04d}", row["smiles"]))
    else:
        for i, line in enumerate(path.read_text().splitlines()):
            parts = line.split()
            if parts and not parts[0].startswith("#"):
                sources.append((parts[1] if len(parts) > 1 else f"{path.stem}-{i:04d}", parts[0]))
    if select:
        sources = sources[_parse_slice(select)]
    skipped = []
    kept = []
    for src in sources:
        if isinstance(src, tuple) and re.search(r"[Ss]", src[1].replace("Si", "")):
            skipped.append(f"{src[0]}: contains sulfur (out of scope)")
            continue
        kept.append(src)
    return kept, skipped


def _parse_slice(text: str) -> slice:
    parts = [int(p) if p.strip() else None for p in text.split(":")]
    if len(parts) == 1:
        return slice(parts[0], parts[0] + 1)
    return slice(*parts)


def _molecule_from_atoms(atoms: Atoms, name: str, source: str) -> Molecule:
    import_optional("rdkit", f"{source}: the bonds of an xyz molecule (RDKit)")
    from rdkit import Chem
    from rdkit.Chem import rdDetermineBonds

    numbers = atoms.numbers[atoms.numbers != 99]
    pos = atoms.positions[atoms.numbers != 99]
    block = f"{len(numbers)}\n\n" + "".join(
        f"{Chem.GetPeriodicTable().GetElementSymbol(int(z))} {x:.8f} {y:.8f} {w:.8f}\n"
        for z, (x, y, w) in zip(numbers, pos, strict=True)
    )
    mol = Chem.MolFromXYZBlock(block)
    try:
        rdDetermineBonds.DetermineBonds(mol, charge=0)
    except Exception as exc:  # noqa: BLE001
        raise SamplingError(f"{source}: cannot determine bonds: {exc}") from None
    order = {Chem.BondType.SINGLE: 1, Chem.BondType.DOUBLE: 2, Chem.BondType.TRIPLE: 3}
    bonds = np.array([(b.GetBeginAtomIdx(), b.GetEndAtomIdx(), order.get(b.GetBondType(), 4))
                      for b in mol.GetBonds()], dtype=np.int64).reshape(-1, 3)
    ring = np.array([b.IsInRing() for b in mol.GetBonds()], dtype=bool)
    return Molecule(name=name, numbers=numbers, positions=pos, bonds=bonds, ring_bonds=ring)


# ---------------------------------------------------------------------------------- tasks
def labeler_calculator(labeler: PySCFLabeler) -> Calculator:
    """A minimal ASE calculator (energy, forces at zero field; no localization) over a
    :class:`PySCFLabeler`, e.g. for ASE's optimisers."""
    from ase.calculators.calculator import CalculationFailed, Calculator, all_changes

    class _Calc(Calculator):
        implemented_properties = ["energy", "forces"]

        def calculate(self, atoms: Atoms | None = None, properties: Sequence[str] = ("energy",),
                      system_changes: Sequence[str] = all_changes) -> None:
            super().calculate(atoms, properties, system_changes)
            res = labeler(self.atoms.numbers, self.atoms.positions, localize=False)
            if not res.ok:
                raise CalculationFailed(res.error)
            self.results = {"energy": res.energy, "forces": res.forces}

    return _Calc()


def pyscf_hessian(labeler: PySCFLabeler, numbers: np.ndarray,
                  positions: np.ndarray) -> np.ndarray:
    """Analytic Cartesian Hessian (eV/Å^2) at zero field, shape (3n, 3n)."""
    mol, mf = labeler.build(numbers, positions, np.zeros(3), 0.0)
    mf.kernel()
    if not mf.converged:
        raise LabelingError("SCF not converged in the Hessian calculation")
    hess = mf.Hessian()
    hess.verbose = 0
    h = np.asarray(hess.kernel())  # (n, n, 3, 3) Ha/bohr^2
    n = len(numbers)
    return h.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n) * HARTREE * ANGSTROM_IN_BOHR**2


#: preparation levels computed with GFN-xTB (package ``tblite``) instead of PySCF
XTB_LEVELS = {"gfn2-xtb": "GFN2-xTB", "gfn1-xtb": "GFN1-xTB"}
#: a preparation that stops on a saddle point steps down its softest mode (largest atom
#: displacement SADDLE_STEP Å) and optimises again, at most SADDLE_ESCAPES times (mini-eqm7:
#: 2 of 112 molecules stopped on GFN2-xTB saddles, -0.06 and -0.11 eV/Å^2/amu)
SADDLE_ESCAPES = 3
SADDLE_STEP = 0.1


def preparation_level_name(spec: str | None) -> str:
    """Canonical name of a preparation level: an xTB method or a PySCF level name."""
    if isinstance(spec, str) and spec.strip().lower() in XTB_LEVELS:
        return spec.strip().lower()
    return parse_level(spec).name


def _preparation_calculator(level: str, threads: int | None):
    """An ASE calculator (energy, forces at zero field) at a preparation level."""
    if level in XTB_LEVELS:
        TBLite = import_optional("tblite.ase", f"the preparation level {level} (xTB)").TBLite
        return TBLite(method=XTB_LEVELS[level], verbosity=0)
    return labeler_calculator(PySCFLabeler(level, threads=threads))


def finite_difference_hessian(atoms: Atoms, delta: float = 0.005, cache: str | Path | None = None,
                              directions: str = "cartesian", reverse: bool = False) -> np.ndarray:
    """Cartesian Hessian (eV/Å^2) by central differences of the forces.

    ``directions``:
      - ``"cartesian"``: every atom along x, y, z (ASE Vibrations; 6N + 1 force calls);
      - ``"internal"``: the 3N - 6 vibrational directions only (3N - 5 for a linear molecule),
        mass-orthogonal to the rigid translations and rotations (:func:`internal_hessian`;
        2 (3N - 6) + 1 calls). The harmonic frequencies are the same (they only see this
        block); the rigid-body block is zero instead of measured.

    ``cache``: a folder for the per-displacement force files, so that an interrupted run
    resumes with the displacements it finished (one process per folder, or two: ``reverse``);
    a file left empty or cut by a kill is recomputed. Without it the displacements live in a
    temporary folder.
    ``reverse`` (internal directions): the displacements from the last one back, so that a
    second process shares one ``cache`` with a forward one (at most the displacement where
    they meet is computed twice).
    """
    import json
    import tempfile

    from ase.vibrations import Vibrations

    if directions not in ("cartesian", "internal"):
        raise ValueError(f"directions: 'cartesian' or 'internal', got {directions!r}")
    if reverse and directions != "internal":
        raise ValueError("reverse: only with directions='internal' (ASE Vibrations keeps"
                         " its own order)")

    def run(folder: Path) -> np.ndarray:
        if directions == "internal":
            return internal_hessian(atoms, delta, folder, reverse=reverse)
        folder.mkdir(parents=True, exist_ok=True)
        for f in folder.glob("cache.*.json"):  # an unfinished displacement: compute it again
            try:
                json.loads(f.read_text())
            except ValueError:
                f.unlink()
        vib = Vibrations(atoms, name=str(folder), delta=delta, nfree=2)
        vib.run()
        return vib.get_vibrations().get_hessian_2d()

    if cache is not None:
        return run(Path(cache))
    with tempfile.TemporaryDirectory(prefix="emlp-vib-") as tmp:
        return run(Path(tmp) / "vib")


def internal_hessian(atoms: Atoms, delta: float, folder: str | Path,
                     reverse: bool = False) -> np.ndarray:
    """Eckart-projected Cartesian Hessian (eV/Å^2) from central differences of the forces of
    ``atoms`` (its calculator) along the vibrational directions only.

    The directions ``d_k`` (unit Cartesian vectors, ``M^-1/2`` times an orthonormal basis of
    the mass-weighted complement of the rigid translations and rotations) are chosen once and
    saved in ``folder/directions.npz``; each displacement ``x0 -+ delta d_k`` (Å) is one file
    ``folder/KKK-.npz`` / ``KKK+.npz`` (energy, forces), written atomically, so a run resumes
    where it stopped (also on another machine, with the saved directions), and a second
    process with ``reverse`` (the displacements from the last one back) can share the folder
    with a forward one. Returns
    ``H_c = M^1/2 V A V^T M^1/2``, ``A = V^T M^-1/2 H M^-1/2 V`` (symmetrised): the block of the
    mass-weighted Hessian that the harmonic frequencies come from, with exactly zero
    translations and rotations. Saves 12 of the ``6N + 1`` force calls of the Cartesian scheme
    (13 for a linear molecule) at the same O(delta^2) accuracy.
    """
    from emlpack.geometry import internal_basis, rigid_body_modes

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    pos = atoms.get_positions()
    masses = atoms.get_masses()
    saved_file = folder / "directions.npz"
    if saved_file.exists():
        with np.load(saved_file) as saved:
            if (saved["positions"].shape != pos.shape
                    or np.abs(saved["positions"] - pos).max() > 1e-10
                    or float(saved["delta"]) != delta
                    or not np.allclose(saved["masses"], masses, rtol=0, atol=1e-12)):
                raise LabelingError(f"{saved_file}: displacements of another geometry, step or"
                                    " masses; delete the folder to start again")
            dirs = saved["directions"]
    else:
        sqm = np.repeat(np.sqrt(masses), 3)
        x = internal_basis(rigid_body_modes(pos, masses)) / sqm[:, None]  # M^-1/2 V
        dirs = x / np.linalg.norm(x, axis=0)
        write_npz_atomic(saved_file, positions=pos, masses=masses, delta=delta,
                         directions=dirs)
    if any(not (folder / f"{k:03d}{s}.npz").exists() for k in range(dirs.shape[1]) for s in "-+"):
        atoms.get_forces()  # the undisplaced SCF first: each pair then starts from its density

    def forces(k: int, sign: str) -> np.ndarray:
        path = folder / f"{k:03d}{sign}.npz"
        if not path.exists():
            shifted = atoms.copy()
            shifted.calc = atoms.calc
            shifted.positions = pos + (delta if sign == "+" else -delta) * dirs[:, k].reshape(-1, 3)
            f = shifted.get_forces()
            write_npz_atomic(path, positions=shifted.positions, forces=f,
                             energy=shifted.get_potential_energy())
        with np.load(path) as d:
            return d["forces"].ravel()

    order = [(k, sign) for k in range(dirs.shape[1]) for sign in "-+"]
    for k, sign in reversed(order) if reverse else order:
        forces(k, sign)  # every missing displacement first, in this process's order
    # g_k = H d_k; with x_k = d_k / |M^1/2 d_k| (= M^-1/2 v_k): A_jk = x_j . H x_k
    g = np.stack([(forces(k, "-") - forces(k, "+")) / (2.0 * delta)
                  for k in range(dirs.shape[1])], axis=1)
    m3 = np.repeat(masses, 3)
    norm = np.linalg.norm(np.sqrt(m3)[:, None] * dirs, axis=0)
    a = (dirs.T @ g) / np.outer(norm, norm)
    a = 0.5 * (a + a.T)
    w = m3[:, None] * dirs / norm[None, :]  # M^1/2 V
    return w @ a @ w.T


def prepare_task(source: tuple[str, str] | Molecule, level: str, optimize: bool, fmax: float,
                 seed: int, threads: int | None = None, hessian: bool = True) -> Molecule:
    """Build (SMILES), optimise and compute the Hessian of one molecule (runs on a worker).

    ``level``: a PySCF level (analytic Hessian) or an xTB method of :data:`XTB_LEVELS`
    (seconds per molecule; Hessian by finite differences of the forces).
    """
    from ase import Atoms

    mol = source if isinstance(source, Molecule) else molecule_from_smiles(
        source[1], name=source[0], seed=seed)
    if threads and level in XTB_LEVELS:
        os.environ["OMP_NUM_THREADS"] = str(threads)
    atoms = Atoms(numbers=mol.numbers, positions=mol.positions)
    atoms.calc = _preparation_calculator(level, threads)
    n = 3 * len(mol.numbers)
    for attempt in range(SADDLE_ESCAPES + 1):
        if optimize and len(mol.numbers) > 1:
            from ase.optimize import BFGS

            opt = BFGS(atoms, logfile=None)
            if not opt.run(fmax=fmax, steps=300):
                raise SamplingError(f"{mol.name}: geometry optimisation did not converge")
        mol.positions = atoms.positions.copy()
        if not hessian:
            mol.hessian = np.zeros((n, n))
            return mol
        if level in XTB_LEVELS:
            mol.hessian = finite_difference_hessian(atoms)
        else:
            mol.hessian = pyscf_hessian(PySCFLabeler(level, threads=threads), mol.numbers,
                                        mol.positions)
        k, modes = normal_modes(mol.numbers, mol.positions, mol.hessian)
        if not optimize or not has_negative_curvature(k) or attempt == SADDLE_ESCAPES:
            return mol  # a remaining saddle is refused by the sampling, with its reason
        # a saddle point (BFGS stops on zero forces): step down the softest mode, optimise again
        dx = (modes[:, 0] / np.repeat(np.sqrt(masses_of(mol.numbers)), 3)).reshape(-1, 3)
        atoms.positions = atoms.positions + SADDLE_STEP * dx / np.linalg.norm(dx, axis=1).max()
        log.info("%s: saddle point at %s (curvature %.3g eV/Å^2/amu), stepping %.2f Å down"
                 " its mode and optimising again", mol.name, level, k[0], SADDLE_STEP)
    return mol


def label_task(config: Configuration, level: str, boys_starts: int, seed: int,
               threads: int | None = None) -> tuple[Configuration, LabelResult]:
    """Label one configuration (runs on a worker); returns (config, LabelResult)."""
    import multiprocessing

    # a worker process (Dask's) only labels: it keeps its memory for the next label
    worker = multiprocessing.parent_process() is not None
    labeler = PySCFLabeler(level, boys_starts=boys_starts, seed=seed, threads=threads,
                           keep_heap=worker)
    return config, labeler(config.numbers, config.positions, config.field, config.charge)


# ---------------------------------------------------------------------------------- driver
@dataclass
class LabelingSummary:
    """Outcome of a labeling run: the store, its records, new labels, new failures,
    configurations already done, input entries left out (reasons), failures and wall time (s)."""

    store: str
    n_records: int = 0
    n_new: int = 0
    n_failed_new: int = 0
    n_skipped_done: int = 0
    skipped_molecules: list[str] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    wall_time: float = 0.0

    def add_result(self, store: DatasetStore, conf: Configuration, res: LabelResult, bar: tqdm,
                   name: str) -> None:
        """Store one label (:func:`store_result`), count it as new or failed (``name`` in the
        failure line) and advance the progress bar."""
        if store_result(store, conf, res):
            self.n_new += 1
        else:
            self.n_failed_new += 1
            self.failures.append(f"{name}: {res.error}")
        bar.update(1)

    def close_run(self, store: DatasetStore, bar: tqdm, executor: Executor, t0: float) -> None:
        """End a labeling run (every driver, also on an error): close the progress bar, the
        executor and the store; record the store's size and the wall time since ``t0``."""
        bar.close()
        executor.close()
        self.n_records = len(store)
        store.close()
        self.wall_time = time.perf_counter() - t0

    def text(self) -> str:
        """The report ``emlp label`` prints: counts, skipped molecules and the first 20 failures."""
        lines = [
            f"{self.store}: {self.n_records} records ({self.n_new} new, {self.n_failed_new} new"
            f" failures, {self.n_skipped_done} already done) in {self.wall_time:.1f} s"
        ]
        lines += [f"skipped molecule {s}" for s in self.skipped_molecules]
        lines += [f"failed {s}" for s in self.failures[:20]]
        if len(self.failures) > 20:
            lines.append(f"... and {len(self.failures) - 20} more failures")
        return "\n".join(lines)


def expected_keys(name: str, recipe: dict) -> list[str]:
    """Store keys ``NAME/KIND/NNNN`` of every configuration the recipe asks of molecule ``name``."""
    return [f"{name}/{s['kind']}/{i:04d}" for s in recipe["samples"] for i in range(s["count"])]


def _save_prepared(prep_dir: Path, mol: Molecule, level: str) -> None:
    """Write a prepared molecule once (temporary file, then rename; never overwritten)."""
    prep_dir.mkdir(parents=True, exist_ok=True)
    final = prep_dir / f"{mol.name}.npz"
    if final.exists():
        return
    write_npz_atomic(final, compressed=True, numbers=mol.numbers, positions=mol.positions,
                     bonds=mol.bonds, ring_bonds=mol.ring_bonds, hessian=mol.hessian,
                     smiles=mol.smiles, level=level)


def _load_prepared(prep_dir: Path, name: str, level: str) -> Molecule | None:
    path = prep_dir / f"{name}.npz"
    if not path.exists():
        return None
    with np.load(path) as d:
        if str(d["level"]) != level:
            return None
        mol = Molecule(name=name, numbers=d["numbers"], positions=d["positions"],
                       bonds=d["bonds"], ring_bonds=d["ring_bonds"], hessian=d["hessian"],
                       smiles=str(d["smiles"]))
    if len(mol.numbers) > 1 and np.any(mol.hessian) and has_negative_curvature(
            normal_modes(mol.numbers, mol.positions, mol.hessian)[0]):
        # a saddle point kept before preparations stepped off them (SADDLE_ESCAPES): prepare
        # again (deterministic, seconds at GFN2-xTB; the file is written once, never replaced)
        log.info("%s: the cached preparation %s is a saddle point; preparing again", name, path)
        return None
    return mol


#: Dask priorities: labels of prepared molecules run before the next preparation
_PRIORITY_LABEL, _PRIORITY_PREPARE = 10, 0


def check_labeling_dependencies(recipe: dict, workers: int | None = None,
                                scheduler: str | None = None) -> None:
    """Refuse, before anything is written, a labeling run whose packages are missing: PySCF
    (the labels), tblite for an xTB preparation level, Dask unless ``workers=0`` runs it in
    this process (:class:`~emlpack.errors.MissingDependencyError`, one line naming the extra)."""
    import_optional("pyscf", "DFT labeling (PySCF)")
    prep = recipe.get("prepare", {}) or {}
    prep_level = preparation_level_name(prep.get("level") or recipe.get("level"))
    if prep_level in XTB_LEVELS:
        import_optional("tblite", f"the preparation level {prep_level} (xTB)")
    Executor.check_backend(workers, scheduler)


def run_labeling(
    sources: list,
    store_path: str | Path,
    recipe: dict,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    retry_failed: bool = False,
    skipped: list[str] | None = None,
    threads: int | None = None,
    prep_dir: str | Path | None = None,
    exclude_keys: set[str] | None = None,
    on_stored: Callable[[DatasetStore], bool] | None = None,
) -> LabelingSummary:
    """Label ``sources`` (``(name, smiles)`` or :class:`Molecule`) into the store.

    Molecules are prepared in their order, at most one per worker ahead of the labeling: a
    molecule's configurations are labeled as soon as it is prepared, before the next
    preparations (Dask priorities), so labels arrive from the first minutes on.

    Args:
        recipe: a resolved recipe (see :mod:`emlpack.qm.recipe`).
        scheduler: address of an existing Dask scheduler; None starts a ``LocalCluster``.
        workers: LocalCluster workers (default: CPU count); 0 runs everything in-process.
        retry_failed: label again the keys recorded as failed.
        threads: OpenMP threads per task (default: CPU count / workers).
        prep_dir: folder of the prepared molecules (default ``STORE.prep``).
        exclude_keys: keys finished elsewhere (e.g. in committed shards): not labeled again.
        on_stored: called with the store after each stored record or failure; returning
            True stops the run (tasks in flight are dropped, finished ones are kept).
    """
    from emlpack.progress import progress as progress_bar

    t0 = time.perf_counter()
    check_labeling_dependencies(recipe, workers, scheduler)  # before the store is opened
    store_path = Path(store_path)
    level = parse_level(recipe.get("level")).name
    prep = recipe.get("prepare", {}) or {}
    prep_level = preparation_level_name(prep.get("level") or recipe.get("level"))
    seed = int(recipe.get("seed", 0))
    boys = int(recipe.get("boys_starts", 3))
    recipe_text = yaml.safe_dump(recipe, sort_keys=True)

    store = DatasetStore(store_path, "a")
    old = store.metadata.get("recipe")
    if old is not None and old != recipe_text:
        store.close()
        raise StoreError(
            f"{store_path}: was labeled with a different recipe; use a new store or the same"
            f" recipe (stored recipe:\n{old})"
        )
    store.set_metadata(recipe=recipe_text, level=level)
    log.info("labeling into %s: level %s, preparation %s, workers %s, scheduler %s, recipe:\n%s",
             store_path, level, prep_level, workers, scheduler, recipe_text)
    done = set(store.keys()) if retry_failed else store.done_keys()
    done |= set(exclude_keys or ())
    summary = LabelingSummary(str(store_path), skipped_molecules=list(skipped or []))

    names = [s.name if isinstance(s, Molecule) else s[0] for s in sources]
    if len(set(names)) != len(names):
        raise SamplingError("molecule names must be unique")
    todo = {}
    for src, name in zip(sources, names, strict=True):
        keys = [k for k in expected_keys(name, recipe) if k not in done]
        summary.n_skipped_done += len(expected_keys(name, recipe)) - len(keys)
        if keys:
            todo[name] = (src, set(keys))
    hydride_keys = {}
    if recipe.get("hydrides"):
        for h, smi in HYDRIDES.items():
            key = f"hydride/{h}/0000"
            if key in done:
                summary.n_skipped_done += 1
            else:
                hydride_keys[h] = (key, smi)
    need_probes = bool(todo) and any(s.get("dimer") for s in recipe["samples"])
    total = sum(len(k) for _, k in todo.values()) + len(hydride_keys)

    executor = Executor(workers, scheduler)
    n_workers = executor.workers
    if threads is None and executor.uses_dask:
        threads = executor.threads_per_task
    prep_dir = Path(prep_dir) if prep_dir is not None else Path(str(store_path) + ".prep")
    bar = progress_bar(total=total, desc="label", unit="conf", enabled=progress)
    waiting = list(todo)  # molecules still to prepare, in order
    in_flight = {"prep": 0}
    try:
        def submit_prepare(src: tuple[str, str] | Molecule, name: str, hessian: bool = True,
                           level_: str = prep_level) -> None:
            cached = _load_prepared(prep_dir, name, level_)
            if cached is not None:
                executor.submit(_identity, cached, tag=("prep", name),
                                priority=_PRIORITY_PREPARE)
            else:
                executor.submit(prepare_task, src, level_, bool(prep.get("optimize", True)),
                                float(prep.get("fmax", 0.01)), seed, threads, hessian,
                                tag=("prep", name), priority=_PRIORITY_PREPARE)

        def feed() -> None:
            """Keep one preparation per worker ahead of the labeling."""
            while waiting and in_flight["prep"] < max(1, n_workers):
                name = waiting.pop(0)
                submit_prepare(todo[name][0], name)
                in_flight["prep"] += 1

        def submit_label(conf: Configuration, tag: str) -> None:
            executor.submit(label_task, conf, level, boys, seed, threads, tag=("label", tag),
                            priority=_PRIORITY_LABEL)

        probes: dict[str, Molecule] = {}
        for h, (_key, smi) in hydride_keys.items():
            # references: optimised at the labeling level itself, no Hessian needed
            submit_prepare((f"hydride-{h}", smi), f"hydride-{h}", hessian=False, level_=level)
        if need_probes:
            for pname in recipe.get("dimer", {}).get("probes", list(PROBES)):
                submit_prepare((f"probe-{pname}", PROBES[pname]), f"probe-{pname}")
        else:
            feed()
        waiting_probes = len(recipe.get("dimer", {}).get("probes", PROBES)) if need_probes else 0

        def record_failures(name: str, keys: Collection[str], reason: str) -> None:
            store.add_failures({"key": k, "molecule_id": name, "kind": k.split("/")[1],
                                "reason": reason} for k in sorted(keys))
            summary.n_failed_new += len(keys)
            summary.failures.append(f"{name}: {reason}")
            bar.update(len(keys))

        for (kind, name), fut in executor.completed():
            stop = False
            if kind == "prep":
                if not name.startswith(("probe-", "hydride-")):
                    in_flight["prep"] -= 1
                try:
                    mol = fut.result()
                except Exception as exc:  # noqa: BLE001 - recorded, the run goes on
                    reason = f"preparation failed: {type(exc).__name__}: {exc}"
                    if name.startswith("probe-"):
                        raise SamplingError(f"dimer probe {name}: {reason}") from exc
                    if name.startswith("hydride-"):
                        record_failures(name, {hydride_keys[name.split("-", 1)[1]][0]}, reason)
                    else:
                        record_failures(name, todo[name][1], reason)
                        feed()
                    stop = bool(on_stored and on_stored(store))
                    if stop:
                        break
                    continue
                _save_prepared(prep_dir, mol, level if name.startswith("hydride-") else prep_level)
                if name.startswith("probe-"):
                    probes[name.removeprefix("probe-")] = mol
                    mol.name = name.removeprefix("probe-")
                    waiting_probes -= 1
                    if waiting_probes == 0:
                        feed()
                    continue
                if name.startswith("hydride-"):
                    h = name.removeprefix("hydride-")
                    submit_label(Configuration(hydride_keys[h][0], h, "hydride", mol.numbers,
                                               mol.positions, np.zeros(3)), name)
                    continue
                try:
                    confs = configurations(mol, recipe, probes, skip=done)
                except SamplingError as exc:
                    record_failures(name, todo[name][1], str(exc))
                    feed()
                    stop = bool(on_stored and on_stored(store))
                    if stop:
                        break
                    continue
                for conf in confs:
                    submit_label(conf, conf.key)
                feed()
            else:
                try:
                    conf, res = fut.result()
                except Exception as exc:  # noqa: BLE001 - e.g. a worker died: record it
                    key = name if "/" in name else f"hydride/{name.split('-', 1)[1]}/0000"
                    reason = f"task failed: {type(exc).__name__}: {exc}"
                    record_failures(key.split("/")[0], [key], reason)
                    stop = bool(on_stored and on_stored(store))
                    if stop:
                        break
                    continue
                summary.add_result(store, conf, res, bar, conf.molecule_id)
                if on_stored and on_stored(store):
                    break
    finally:
        summary.close_run(store, bar, executor, t0)
    return summary


def _identity(x: Molecule) -> Molecule:
    return x


def store_result(store: DatasetStore, conf: Configuration, res: LabelResult) -> bool:
    """Store the label ``res`` of ``conf`` as a record (a hydride's energy also as a
    reference), or its failure with the reason; True when labeled."""
    if not res.ok:
        store.add_failures([{"key": conf.key, "molecule_id": conf.molecule_id,
                             "kind": conf.kind, "reason": res.error}])
        return False
    store.append(res.to_structure(source=conf.key, info={
        "key": conf.key, "molecule_id": conf.molecule_id, "kind": conf.kind}))
    if conf.kind == "hydride":
        store.set_reference(conf.molecule_id, res.energy, res.level)
    return True


def label_configurations(
    configs: Sequence[Configuration],
    store_path: str | Path,
    level: str,
    boys_starts: int = 3,
    seed: int = 0,
    workers: int | None = 0,
    threads: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    exclude_keys: set[str] | None = None,
    on_stored: Callable[[DatasetStore], bool] | None = None,
    metadata: dict | None = None,
) -> LabelingSummary:
    """Label given configurations (nuclei in Å, field in V/Å; no preparation, no sampling)
    into the store, as :func:`run_labeling` labels a recipe's: one :func:`label_task` per
    configuration on the :class:`~emlpack.qm.executor.Executor`, each result stored by this
    process as it arrives (a failure recorded with its reason), keys already in the store or in
    ``exclude_keys`` skipped, so a re-run resumes. The store must have been labeled at the same
    ``level`` (its ``level`` attribute); ``metadata`` is stored as file attributes (strings).
    ``on_stored``: as :func:`run_labeling`'s (True stops the run).
    """
    from emlpack.progress import progress as progress_bar

    t0 = time.perf_counter()
    import_optional("pyscf", "DFT labeling (PySCF)")
    Executor.check_backend(workers, scheduler)  # before the store is opened
    keys = [c.key for c in configs]
    if len(set(keys)) != len(keys):
        raise SamplingError("configuration keys must be unique")
    level_name = parse_level(level).name
    store_path = Path(store_path)
    store = DatasetStore(store_path, "a")
    old = store.metadata.get("level")
    if old is not None and old != level_name:
        store.close()
        raise StoreError(f"{store_path}: was labeled at {old}, not {level_name}; use a new store")
    store.set_metadata(level=level_name, **(metadata or {}))
    done = store.done_keys() | set(exclude_keys or ())
    todo = {c.key: c for c in configs if c.key not in done}
    summary = LabelingSummary(str(store_path), n_skipped_done=len(configs) - len(todo))
    log.info("labeling %d configurations into %s at %s (%d done), workers %s, scheduler %s",
             len(todo), store_path, level_name, summary.n_skipped_done, workers, scheduler)
    executor = Executor(workers, scheduler)
    if threads is None and executor.uses_dask:
        threads = executor.threads_per_task
    bar = progress_bar(total=len(todo), desc="label", unit="conf", enabled=progress)
    try:
        for key, conf in todo.items():
            executor.submit(label_task, conf, level_name, int(boys_starts), int(seed), threads,
                            tag=key)
        for key, fut in executor.completed():
            try:
                conf, res = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. a worker died: recorded, run goes on
                conf = todo[key]
                res = LabelResult(status="failed", error=f"task failed: {type(exc).__name__}:"
                                  f" {exc}", numbers=conf.numbers, positions=conf.positions,
                                  field=conf.field, charge=conf.charge, level=level_name)
            summary.add_result(store, conf, res, bar, conf.key)
            if on_stored and on_stored(store):
                break
    finally:
        summary.close_run(store, bar, executor, t0)
    return summary
