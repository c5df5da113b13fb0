"""Periodic reference labels with CP2K: energy, forces, stress, Wannier centres, Berry-phase field.

One :class:`CP2KLabeler` call writes a CP2K input for a periodic :class:`Structure` (Γ point
of the cell or of a supercell, ``CP2KSettings.supercell``; GPW, GTH pseudopotentials), runs
``mpirun -np N cp2k.psmp`` in a scratch directory and returns a new, labeled
:class:`Structure` in emlpack's units:

* energy (eV), including the field term: ``E(F) = E_KS - μ·F`` to first order, with μ the dipole
  of cores and Wannier pairs, i.e. the eMLP's ``E_ext = -Σ q F·r``;
* forces on the cores (eV/Å), including the field forces;
* stress (eV/Å^3, ASE sign ``(1/V) dE/dε``), only with ``stress=True`` and only at zero field
  (CP2K 2023.1: "Stress tensor for periodic E-field not implemented");
* valence electron pairs at the Wannier centres (Å), each moved to the periodic image nearest to
  its closest core; the count must equal the valence electron pairs;
* the field (V/Å) as given.

GTH pseudopotentials carry exactly the valence electrons of the eMLP cores (H 1, C 4, N 5, O 6,
...; :func:`emlpack.structure.core_charges`), so every Wannier centre is a valence pair. Elements
whose GTH potential has semicore states (Li, Be, Na, Mg) are refused.

Units: CP2K reads Å, writes Hartree, Hartree/bohr and GPa; Å in the Wannier xyz file.
Conversions use :mod:`emlpack.units` (molmod constants = CP2K's CODATA-2006 bohr).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
import weakref
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from emlpack._files import atomic_path
from emlpack.qm.cp2k.input import (
    CP2KInputError,
    CP2KSettings,
    build_input,
    cp2k_available,
    find_data_dir,
)
from emlpack.qm.cp2k.output import (
    STRESS_SIGN,
    CP2KError,
    map_centres_to_cores,
    output_tail,
    parse_output,
    read_wannier_xyz,
)
from emlpack.qm.cp2k.runner import run_cp2k
from emlpack.qm.pyscf_labeler import LabelingError
from emlpack.structure import Structure, core_charges
from emlpack.units import ANGSTROM_IN_BOHR, EV_PER_A3_IN_GPA, HARTREE

if TYPE_CHECKING:
    from collections.abc import Iterable, Sequence

    from emlpack.qm.labeling import LabelingSummary


def first_cell_centres(centres: np.ndarray, cell: Structure, run_on: Structure,
                       where: str) -> np.ndarray:
    """The Wannier centres (Å) of ``cell`` from those of ``run_on`` (``cell`` itself or its
    supercell, :meth:`Structure.repeated`, whose first ``cell.n_cores`` cores are the cell's):
    each centre at the image nearest to its closest core, those of the first cell's cores
    kept, then placed at the image nearest to their closest core of ``cell``."""
    mapped, core = map_centres_to_cores(centres, run_on.positions, run_on.cell)
    if run_on is not cell:
        mapped = mapped[core < cell.n_cores]
        n_cells = run_on.n_cores // cell.n_cores
        if len(mapped) * n_cells != len(centres):
            raise CP2KError(f"{where}: {len(mapped)} of the supercell's {len(centres)} Wannier"
                            f" centres are nearest to the first cell's cores, not"
                            f" 1/{n_cells} of them")
        mapped, _ = map_centres_to_cores(mapped, cell.positions, cell.cell)
    return mapped


# ---------------------------------------------------------------------------------- labeler
class CP2KLabeler:
    """Labels periodic structures with CP2K (see the module docstring for units and signs).

    Args:
        settings: level of theory and run settings (default: :class:`CP2KSettings`).
        workdir: parent directory of the per-run scratch directories (default: system temp).
        keep_files: keep each run's directory (input, output, Wannier file) for inspection.
    """

    def __init__(self, settings: CP2KSettings | None = None,
                 workdir: str | Path | None = None, keep_files: bool = False) -> None:
        self.settings = settings or CP2KSettings()
        # absolute: CP2K runs inside its own run directory (restart file paths)
        self.workdir = Path(workdir).resolve() if workdir is not None else None
        self.keep_files = keep_files
        self.last_run_dir: Path | None = None
        self._wfn: dict[bytes, Path] = {}
        self._wfn_dir: Path | None = None

    def __call__(self, structure: Structure, *, stress: bool = False) -> Structure:
        """A new, labeled copy of ``structure``; raises :class:`LabelingError` on failure."""
        s = self.settings
        where = structure.source
        if not structure.pbc:
            raise CP2KInputError(f"{where}: CP2KLabeler needs a periodic structure (pbc=True)")
        if stress and np.any(structure.field != 0.0):
            raise CP2KInputError(
                f"{where}: stress with a nonzero field is not possible (CP2K: stress tensor for"
                " periodic E-field not implemented); label field and stress sets separately"
            )
        missing = cp2k_available(s)  # CP2K comes from the system, not from pip
        if missing is not None:
            raise CP2KInputError(f"{where}: CP2K cannot run: {missing}")
        data_dir = find_data_dir(s.data_dir)
        reps = tuple(int(n) for n in s.supercell)
        cells = int(np.prod(reps))
        # the calculation's structure: the cell itself, or its Γ-point supercell
        run_on = structure if cells == 1 else structure.repeated(reps)
        composition = np.append(run_on.numbers, run_on.charge).tobytes()
        guess = self._wfn.get(composition) if s.reuse_wavefunction else None
        if guess is None and s.wavefunction_guess is not None:
            guess = Path(s.wavefunction_guess).resolve()
            if not guess.is_file():
                raise CP2KInputError(f"{where}: wavefunction_guess {guess} is not a file")
        text = build_input(run_on, s, stress, data_dir=data_dir, guess=guess)
        n_val = core_charges(run_on.numbers).sum() - run_on.charge
        if self.workdir is not None:
            self.workdir.mkdir(parents=True, exist_ok=True)
        run_dir = Path(tempfile.mkdtemp(prefix="cp2k-", dir=self.workdir))
        self.last_run_dir = run_dir
        t0 = time.perf_counter()
        try:
            (run_dir / "emlp.inp").write_text(text)
            output = self._run(run_dir, where)
            try:
                res = parse_output(output, run_on.n_cores, stress)
            except CP2KError as exc:
                self._wfn.pop(composition, None)  # next time from the atomic guess
                raise CP2KError(f"{where}: {exc}; CP2K output tail:\n"
                                f"{output_tail(output)}") from None
            if s.reuse_wavefunction:
                self._keep_wavefunction(run_dir / "emlp-RESTART.wfn", composition)
            pairs = np.zeros((0, 3))
            if s.wannier:
                wfile = run_dir / "emlp_wannier.xyz"
                if not wfile.exists():
                    raise CP2KError(f"{where}: CP2K wrote no Wannier centres; output tail:\n"
                                    f"{output_tail(output)}")
                centres = read_wannier_xyz(wfile, run_on.n_cores)
                if 2 * len(centres) != n_val:
                    raise CP2KError(
                        f"{where}: {len(centres)} Wannier centres, but {n_val:g} valence"
                        f" electrons need {n_val / 2:g}"
                    )
                pairs = first_cell_centres(centres, structure, run_on, where)
        finally:
            if not self.keep_files:
                shutil.rmtree(run_dir, ignore_errors=True)
        info = dict(structure.info)
        info.update({
            "level": s.level(), "wall_time": time.perf_counter() - t0,
            "cp2k_version": res["cp2k_version"], "scf_steps": res["scf_steps"],
        })
        if "spread" in res:
            info["spread"] = res["spread"]
        stress_ev = None
        if stress:
            stress_ev = STRESS_SIGN * res["stress_gpa"] / EV_PER_A3_IN_GPA
        if cells > 1:
            info["supercell"] = list(reps)
        # the supercell's images are copies of the cell: its energy per cell, the first cell's
        # forces (the images' agree to the SCF tolerance)
        return Structure(
            numbers=structure.numbers.copy(), positions=structure.positions.copy(),
            pairs=pairs if s.wannier else structure.pairs.copy(), cell=structure.cell.copy(),
            pbc=True, field=structure.field.copy(), charge=structure.charge,
            energy=res["energy"] * HARTREE / cells,
            forces=res["forces"][:structure.n_cores] * HARTREE * ANGSTROM_IN_BOHR,
            pair_forces=np.zeros((len(pairs) if s.wannier else structure.n_pairs, 3)),
            stress=stress_ev, info=info, source=structure.source,
        )

    def wavefunction(self, structure: Structure) -> Path | None:
        """The kept wavefunction (``.wfn``) of ``structure``'s composition (its supercell's,
        with ``supercell``), from the last converged run of this labeler with
        ``reuse_wavefunction``; None if there is none. Copy it to keep it: the file lives in
        the labeler's scratch folder and goes with the labeler."""
        reps = tuple(int(n) for n in self.settings.supercell)
        run_on = structure if int(np.prod(reps)) == 1 else structure.repeated(reps)
        return self._wfn.get(np.append(run_on.numbers, run_on.charge).tobytes())

    def _keep_wavefunction(self, wfn: Path, composition: bytes) -> None:
        if not wfn.exists():
            return
        if self._wfn_dir is None:
            self._wfn_dir = Path(tempfile.mkdtemp(prefix="cp2k-wfn-", dir=self.workdir))
            weakref.finalize(self, shutil.rmtree, str(self._wfn_dir), True)
        target = self._wfn.get(composition) or self._wfn_dir / f"{len(self._wfn)}.wfn"
        with atomic_path(target) as tmp:
            shutil.copyfile(wfn, tmp)
        self._wfn[composition] = target

    def command(self) -> list[str]:
        """The CP2K command line (``-i emlp.inp -o emlp.out``), under ``mpirun -np n_processes``
        when a launcher is set."""
        s = self.settings
        cmd = [s.cp2k, "-i", "emlp.inp", "-o", "emlp.out"]
        if s.mpirun:
            pre = [s.mpirun]
            if hasattr(os, "geteuid") and os.geteuid() == 0:
                pre.append("--allow-run-as-root")
            pre += ["--bind-to", "none", "-np", str(int(s.n_processes))]
            cmd = pre + cmd
        return cmd

    def _run(self, run_dir: Path, where: str) -> str:
        s = self.settings
        return run_cp2k(self.command(), run_dir, s.omp_threads, s.timeout_s, where)


# ---------------------------------------------------------------------------------- tasks
#: labelers of this process, by settings and workdir (wavefunction reuse across tasks)
_LABELERS: dict[tuple, CP2KLabeler] = {}


def _labeler_for(settings: CP2KSettings | None, workdir: str | Path | None) -> CP2KLabeler:
    settings = settings or CP2KSettings()
    if not settings.reuse_wavefunction:
        return CP2KLabeler(settings, workdir=workdir)
    key = (repr(settings), str(workdir))
    if key not in _LABELERS:
        _LABELERS[key] = CP2KLabeler(settings, workdir=workdir)
    return _LABELERS[key]


def label_task(structure: Structure, settings: CP2KSettings | None, stress: bool, key: str,
               workdir: str | Path | None = None) -> Structure | dict:
    """Label one structure (e.g. on a Dask worker): the labeled structure, or a failure dict.

    The failure dict has ``key``, ``molecule_id``, ``kind`` and ``reason`` (what
    :meth:`DatasetStore.add_failures` stores); failures are data, not exceptions.
    """
    info = structure.info
    kind = str(info.get("kind") or ("stress" if stress else "field"))
    molecule_id = str(info.get("molecule_id") or key.split("/")[0])
    if structure.source == "<memory>":
        structure = structure.copy(source=key)  # errors name the key
    try:
        out = _labeler_for(settings, workdir)(structure, stress=stress)
    except LabelingError as exc:
        return {"key": key, "molecule_id": molecule_id, "kind": kind, "reason": str(exc)}
    except Exception as exc:  # noqa: BLE001 - anything else is recorded too
        return {"key": key, "molecule_id": molecule_id, "kind": kind,
                "reason": f"{type(exc).__name__}: {exc}"}
    out.info.update({"key": key, "molecule_id": molecule_id, "kind": kind})
    return out


def label_into_store(
    items: Iterable[tuple[str, Structure, bool]], store_path: str | Path,
    settings: CP2KSettings | None = None, *,
    workers: int = 0, scheduler: str | None = None, retry_failed: bool = False,
    workdir: str | Path | None = None, progress: bool = False,
) -> LabelingSummary:
    """Label ``(key, structure, stress)`` items into a :class:`DatasetStore`, resumably.

    Keys already in the store (records, and recorded failures unless ``retry_failed``) are
    skipped; failures are recorded with their reason. ``workers=0`` runs in-process; otherwise
    on a Dask ``LocalCluster`` of ``workers`` single-threaded workers (each CP2K run uses
    ``settings.n_processes`` MPI processes) or on the cluster at ``scheduler``.
    Returns a :class:`emlpack.qm.labeling.LabelingSummary`.
    """
    from emlpack.data.store import DatasetStore
    from emlpack.qm.executor import Executor
    from emlpack.qm.labeling import LabelingSummary

    settings = settings or CP2KSettings()
    t0 = time.perf_counter()
    items = list(items)
    keys = [k for k, _, _ in items]
    if len(set(keys)) != len(keys):
        raise ValueError("label_into_store: keys must be unique")
    # refused before the store is opened, not recorded as a failure of every structure (a
    # scheduler's workers may have a CP2K this machine lacks)
    missing = cp2k_available(settings) if scheduler is None else None
    if missing is not None:
        raise CP2KInputError(f"{store_path}: CP2K cannot run: {missing}")
    Executor.check_backend(workers, scheduler)
    store = DatasetStore(store_path, "a")
    done = set(store.keys()) if retry_failed else store.done_keys()
    summary = LabelingSummary(str(store_path))
    todo = [it for it in items if it[0] not in done]
    summary.n_skipped_done = len(items) - len(todo)
    executor = Executor(workers, scheduler)
    from emlpack.progress import progress as progress_bar

    bar = progress_bar(total=len(todo), desc="cp2k", unit="conf", enabled=progress)
    try:
        for key, structure, stress in todo:
            executor.submit(label_task, structure, settings, bool(stress), key, workdir, tag=key)
        for key, fut in executor.completed():
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. a worker died: record it
                res = {"key": key, "molecule_id": key.split("/")[0], "kind": "",
                       "reason": f"task failed: {type(exc).__name__}: {exc}"}
            if isinstance(res, dict):
                store.add_failures([res])
                summary.n_failed_new += 1
                summary.failures.append(f"{key}: {res['reason'].splitlines()[0]}")
            else:
                store.append(res)
                summary.n_new += 1
            bar.update(1)
    finally:
        summary.close_run(store, bar, executor, t0)
    return summary


# ---------------------------------------------------------------------------------- checks
def field_force_check(structure: Structure, settings: CP2KSettings,
                      field_v_per_a: Sequence[float] | np.ndarray,
                      components: Sequence[tuple[int, int]] = ((0, 0),), h: float = 0.005,
                      workdir: str | Path | None = None) -> list[dict]:
    """Berry-phase field forces against central finite differences of the energy.

    CP2K 2023.1 double-counts field forces of atoms that interact with their own periodic
    images (small cells). For each ``(atom, axis)`` this compares the field-induced force
    ``F(field) - F(0)`` with the same difference of ``-dE/dr`` (step ``h`` Å), so that
    grid and SCF errors common to both fields cancel. Costs ``2 + 4 * len(components)``
    energy+force runs (Wannier localization off). Returns one dict per component with
    ``induced`` and ``induced_fd`` (eV/Å) and their difference ``error``, the forces at the
    field (``force``, ``force_fd``) and at zero field (``force0``, ``force0_fd``), and the two
    energies (``energy0``, ``energy``; eV). The SCF restarts from the previous wavefunction.
    """
    from dataclasses import replace

    lab = CP2KLabeler(replace(settings, wannier=False, reuse_wavefunction=True), workdir=workdir)
    fields = (np.zeros(3), np.asarray(field_v_per_a, dtype=float))
    base = [lab(structure.copy(field=f)) for f in fields]
    out = []
    for atom, axis in components:
        fd = []
        for f in fields:
            e = []
            for sign in (1, -1):
                p = structure.positions.copy()
                p[atom, axis] += sign * h
                e.append(lab(structure.copy(positions=p, field=f)).energy)
            fd.append(-(e[0] - e[1]) / (2 * h))
        induced = base[1].forces[atom, axis] - base[0].forces[atom, axis]
        out.append({"atom": atom, "axis": axis, "induced": float(induced),
                    "induced_fd": float(fd[1] - fd[0]), "error": float(induced - fd[1] + fd[0]),
                    "force": float(base[1].forces[atom, axis]), "force_fd": float(fd[1]),
                    "force0": float(base[0].forces[atom, axis]), "force0_fd": float(fd[0]),
                    "energy0": base[0].energy, "energy": base[1].energy})
    return out
