"""Periodic reference labels with CP2K: energy, forces, stress, Wannier centres, Berry-phase field.

One :class:`CP2KLabeler` call writes a CP2K input for a periodic :class:`Structure` (Γ point,
GPW, GTH pseudopotentials), runs ``mpirun -np N cp2k.psmp`` in a scratch directory and returns
a new, labeled :class:`Structure` in emlpack's units:

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
import re
import shutil
import signal
import subprocess
import tempfile
import time
import weakref
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from emlpack._files import atomic_path
from emlpack.geometry import minimum_image
from emlpack.qm.pyscf_labeler import LabelingError
from emlpack.structure import Structure, core_charges
from emlpack.units import ANGSTROM_IN_BOHR, EV_PER_A3_IN_GPA, FIELD_AU_IN_V_PER_A, HARTREE

#: where Debian's ``cp2k-data`` puts basis sets, potentials and ``dftd3.dat``
DEFAULT_DATA_DIRS = ("/usr/share/cp2k", "/usr/share/cp2k/data", "/usr/local/share/cp2k")

#: orientation of CP2K's PERIODIC_EFIELD POLARISATION relative to our field vector, chosen so
#: that E(F) - E(0) = -μ·F (checked by tests/qm/test_cp2k_labeler.py)
_FIELD_SIGN = 1.0
#: CP2K's printed stress ("STRESS| Analytical stress tensor [GPa]") is -1 x the ASE stress
_STRESS_SIGN = -1.0

_TAIL_LINES = 40


class CP2KError(LabelingError):
    """CP2K crashed, timed out, did not converge, or its output could not be parsed."""


class CP2KInputError(LabelingError, ValueError):
    """The structure or settings cannot be labeled with CP2K (nothing was run)."""


@dataclass
class CP2KSettings:
    """Level of theory and run settings of :class:`CP2KLabeler`.

    The defaults are the measured settings of the beta-glycine study (issue 7): PBE + D3(BJ),
    DZVP-MOLOPT-SR-GTH, GTH-PBE, 400 Ry, Γ point.

    Attributes:
        xc: exchange-correlation functional (``&XC_FUNCTIONAL`` section name), e.g. ``"PBE"``.
        dispersion: ``"D3(BJ)"``, ``"D3"`` or None.
        basis: basis set name in ``BASIS_MOLOPT`` (e.g. ``"SZV-MOLOPT-SR-GTH"`` for tests).
        potential: GTH potential family; the ``-qN`` suffix is added per element.
        cutoff_ry, rel_cutoff_ry: plane-wave density cutoff and relative cutoff (Ry).
        eps_scf: SCF convergence (OT gradient, Hartree).
        max_scf: inner (OT) SCF iterations; outer_max_scf: outer SCF loops. Each outer loop
            rebuilds the OT preconditioner: beta-glycine from the atomic guess crawls after ~20
            inner steps (SZV: 1.3e-6 after 50) but converges in 6 more after a rebuild.
        eps_default: CP2K's EPS_DEFAULT (integral screening).
        localize_method: ``&LOCALIZE METHOD`` (CRAZY or JACOBI); eps_localization its tolerance,
            max_localization_iter its iteration limit (not converged = failure).
        wannier: compute Wannier centres (False: energy/forces/stress only, faster).
        reuse_wavefunction: start each SCF from the last converged wavefunction of the same
            composition (same labeler; in :func:`label_task` the same worker process) instead of
            the atomic guess: fewer SCF steps for similar configurations, same result within
            the SCF tolerance.
        n_processes: MPI processes; omp_threads: OMP_NUM_THREADS per process.
        timeout_s: wall-time limit of one CP2K run (s), None = unlimited.
        cp2k: CP2K executable; mpirun: MPI launcher (None: run CP2K directly).
        data_dir: directory with BASIS_MOLOPT, GTH_POTENTIALS, dftd3.dat (None: find it).
    """

    xc: str = "PBE"
    dispersion: str | None = "D3(BJ)"
    basis: str = "DZVP-MOLOPT-SR-GTH"
    potential: str = "GTH-PBE"
    cutoff_ry: float = 400.0
    rel_cutoff_ry: float = 50.0
    eps_scf: float = 1e-7
    max_scf: int = 20
    outer_max_scf: int = 20
    eps_default: float = 1e-12
    localize_method: str = "CRAZY"
    eps_localization: float = 1e-8
    max_localization_iter: int = 10000
    wannier: bool = True
    reuse_wavefunction: bool = False
    n_processes: int = 2
    omp_threads: int = 1
    timeout_s: float | None = None
    cp2k: str = "cp2k.psmp"
    mpirun: str | None = "mpirun"
    data_dir: str | None = None

    def level(self) -> str:
        """Level-of-theory label, e.g. ``"cp2k/pbe-d3bj/dzvp-molopt-sr-gth/400ry"``."""
        disp = re.sub(r"[^a-z0-9]", "", (self.dispersion or "").lower())
        disp = f"-{disp}" if disp else ""
        return f"cp2k/{self.xc.lower()}{disp}/{self.basis.lower()}/{self.cutoff_ry:g}ry"

    def to_dict(self) -> dict:
        return asdict(self)


def find_data_dir(hint: str | None = None) -> Path:
    """The CP2K data directory holding BASIS_MOLOPT, GTH_POTENTIALS and dftd3.dat."""
    candidates = [hint] if hint else [os.environ.get("CP2K_DATA_DIR"), *DEFAULT_DATA_DIRS]
    for c in candidates:
        if c and (Path(c) / "BASIS_MOLOPT").exists() and (Path(c) / "GTH_POTENTIALS").exists():
            return Path(c)
    raise CP2KInputError(
        f"CP2K data directory not found (tried {', '.join(str(c) for c in candidates if c)});"
        " install cp2k-data (`make install-cp2k`) or set CP2KSettings.data_dir / CP2K_DATA_DIR"
    )


def cp2k_available(settings: CP2KSettings | None = None) -> str | None:
    """None when CP2K (executable, launcher, data) is usable, else the reason it is not."""
    s = settings or CP2KSettings()
    if shutil.which(s.cp2k) is None:
        return f"{s.cp2k} not found on PATH (install CP2K: `make install-cp2k`)"
    if s.mpirun and shutil.which(s.mpirun) is None:
        return f"{s.mpirun} not found on PATH"
    try:
        find_data_dir(s.data_dir)
    except CP2KInputError as exc:
        return str(exc)
    return None


# ---------------------------------------------------------------------------------- input
_SYMBOLS = ["X", "H", "He", "Li", "Be", "B", "C", "N", "O", "F", "Ne", "Na", "Mg", "Al", "Si",
            "P", "S", "Cl", "Ar"]


def _field_au(field_v_per_a: np.ndarray) -> tuple[float, np.ndarray]:
    f = np.asarray(field_v_per_a, dtype=float)
    norm = float(np.linalg.norm(f))
    if norm == 0.0:
        return 0.0, np.array([1.0, 0.0, 0.0])
    return norm / FIELD_AU_IN_V_PER_A, _FIELD_SIGN * f / norm


def _check_potentials(numbers: np.ndarray, settings: CP2KSettings, data_dir: Path) -> dict:
    """Potential name per element; its valence must equal the eMLP core charge."""
    text = (data_dir / "GTH_POTENTIALS").read_text(errors="replace")
    names = {}
    for z, q in zip(numbers, core_charges(numbers), strict=True):
        sym = _SYMBOLS[int(z)]
        if sym in names:
            continue
        name = f"{settings.potential}-q{int(q)}"
        if not re.search(rf"^{re.escape(sym)}\s+.*\b{re.escape(name)}\b", text, re.MULTILINE):
            raise CP2KInputError(
                f"{data_dir / 'GTH_POTENTIALS'} has no {sym} {name}: CP2K's valence for {sym}"
                f" must equal the eMLP core charge {int(q)} (semicore GTH potentials such as"
                " Li/Be/Na/Mg are not supported)"
            )
        names[sym] = name
    return names


def build_input(structure: Structure, settings: CP2KSettings, stress: bool,
                project: str = "emlp", data_dir: Path | None = None,
                guess: Path | None = None) -> str:
    """The CP2K input text for ``structure`` (positions and cell in Å, field in V/Å).

    ``guess``: a CP2K ``.wfn`` file to start the SCF from (else the atomic guess).
    """
    s = settings
    data_dir = data_dir or find_data_dir(s.data_dir)
    potentials = _check_potentials(structure.numbers, s, data_dir)
    intensity, direction = _field_au(structure.field)
    disp = ""
    if s.dispersion:
        kind = {"d3(bj)": "DFTD3(BJ)", "d3bj": "DFTD3(BJ)", "d3": "DFTD3"}.get(
            s.dispersion.lower())
        if kind is None:
            raise CP2KInputError(f"unknown dispersion {s.dispersion!r} (use 'D3(BJ)', 'D3', None)")
        disp = f"""
      &VDW_POTENTIAL
        POTENTIAL_TYPE PAIR_POTENTIAL
        &PAIR_POTENTIAL
          TYPE {kind}
          PARAMETER_FILE_NAME {data_dir / 'dftd3.dat'}
          REFERENCE_FUNCTIONAL {s.xc}
        &END PAIR_POTENTIAL
      &END VDW_POTENTIAL"""
    efield = ""
    if intensity > 0.0:
        efield = f"""
    &PERIODIC_EFIELD
      INTENSITY {intensity:.12e}
      POLARISATION {direction[0]:.15f} {direction[1]:.15f} {direction[2]:.15f}
    &END PERIODIC_EFIELD"""
    localize = ""
    if s.wannier:
        localize = f"""
    &LOCALIZE
      METHOD {s.localize_method}
      EPS_LOCALIZATION {s.eps_localization:g}
      MAX_ITER {int(s.max_localization_iter)}
      &PRINT
        &WANNIER_CENTERS
          IONS+CENTERS
          FILENAME ={project}_wannier.xyz
        &END WANNIER_CENTERS
      &END PRINT
    &END LOCALIZE"""
    cell = structure.cell
    coords = "\n".join(
        f"      {_SYMBOLS[int(z)]} {x:.12f} {y:.12f} {w:.12f}"
        for z, (x, y, w) in zip(structure.numbers, structure.positions, strict=True)
    )
    kinds = "\n".join(
        f"""    &KIND {sym}
      BASIS_SET {s.basis}
      POTENTIAL {pot}
    &END KIND""" for sym, pot in potentials.items()
    )
    charge = int(round(structure.charge))
    scf_guess, restart = "SCF_GUESS ATOMIC", ""
    if guess is not None:
        scf_guess, restart = "SCF_GUESS RESTART", f"\n    WFN_RESTART_FILE_NAME {guess}"
    return f"""&GLOBAL
  PROJECT {project}
  RUN_TYPE ENERGY_FORCE
  PRINT_LEVEL LOW
&END GLOBAL
&FORCE_EVAL
  METHOD QS
  STRESS_TENSOR {'ANALYTICAL' if stress else 'NONE'}
  &DFT
    BASIS_SET_FILE_NAME {data_dir / 'BASIS_MOLOPT'}
    POTENTIAL_FILE_NAME {data_dir / 'GTH_POTENTIALS'}
    CHARGE {charge}{restart}
    &MGRID
      CUTOFF {s.cutoff_ry:g}
      REL_CUTOFF {s.rel_cutoff_ry:g}
    &END MGRID
    &QS
      EPS_DEFAULT {s.eps_default:g}
    &END QS
    &SCF
      EPS_SCF {s.eps_scf:g}
      MAX_SCF {int(s.max_scf)}
      {scf_guess}
      &OT
        MINIMIZER DIIS
        PRECONDITIONER FULL_SINGLE_INVERSE
      &END OT
      &OUTER_SCF
        EPS_SCF {s.eps_scf:g}
        MAX_SCF {int(s.outer_max_scf)}
      &END OUTER_SCF
      &PRINT
        &RESTART {'ON' if s.reuse_wavefunction else 'OFF'}
          BACKUP_COPIES 0
        &END RESTART
      &END PRINT
    &END SCF
    &XC
      &XC_FUNCTIONAL {s.xc}
      &END XC_FUNCTIONAL{disp}
    &END XC{efield}{localize}
  &END DFT
  &SUBSYS
    &CELL
      A {cell[0, 0]:.12f} {cell[0, 1]:.12f} {cell[0, 2]:.12f}
      B {cell[1, 0]:.12f} {cell[1, 1]:.12f} {cell[1, 2]:.12f}
      C {cell[2, 0]:.12f} {cell[2, 1]:.12f} {cell[2, 2]:.12f}
      PERIODIC XYZ
    &END CELL
    &COORD
{coords}
    &END COORD
{kinds}
  &END SUBSYS
  &PRINT
    &FORCES ON
    &END FORCES{'''
    &STRESS_TENSOR ON
    &END STRESS_TENSOR''' if stress else ''}
  &END PRINT
&END FORCE_EVAL
"""


# ---------------------------------------------------------------------------------- output
_FLOAT = r"[-+]?\d+\.\d*(?:[EeDd][-+]?\d+)?"


def _tail(text: str, n: int = _TAIL_LINES) -> str:
    return "\n".join(text.rstrip().splitlines()[-n:])


def parse_output(text: str, n_atoms: int, stress: bool) -> dict:
    """Energy (Ha), forces (Ha/bohr), stress (GPa, CP2K sign), version and SCF status."""
    out: dict = {}
    m = re.search(r"CP2K version (\S+)", text)
    out["cp2k_version"] = m.group(1) if m else ""
    if re.search(r"SCF run NOT converged|outer SCF loop FAILED to converge", text):
        raise CP2KError("SCF not converged")
    m = re.search(r"[Ll]ocali[sz]ation not converged after\s+(\d+)", text)
    if m:
        raise CP2KError(f"Wannier localization not converged after {m.group(1)} iterations")
    m = re.findall(rf"ENERGY\| Total FORCE_EVAL \( QS \) energy \[a\.u\.\]:\s+({_FLOAT})", text)
    if not m:
        raise CP2KError("no total energy in the CP2K output")
    out["energy"] = float(m[-1])
    outer = re.findall(r"outer SCF loop converged in\s+\d+ iterations or\s+(\d+) steps", text)
    steps = re.findall(r"SCF run converged in\s+(\d+) steps", text)
    out["scf_steps"] = int(outer[-1]) if outer else sum(int(x) for x in steps)
    block = text[text.rfind("ATOMIC FORCES in [a.u.]"):]
    if not block.startswith("ATOMIC FORCES"):
        raise CP2KError("no ATOMIC FORCES block in the CP2K output")
    rows = re.findall(rf"^\s+\d+\s+\d+\s+\S+\s+({_FLOAT})\s+({_FLOAT})\s+({_FLOAT})\s*$",
                      block.split("SUM OF ATOMIC FORCES")[0], re.MULTILINE)
    if len(rows) != n_atoms:
        raise CP2KError(f"parsed {len(rows)} force rows for {n_atoms} atoms")
    out["forces"] = np.array(rows, dtype=float)
    if stress:
        i = text.rfind("STRESS| Analytical stress tensor [GPa]")
        if i < 0:
            raise CP2KError("no analytical stress tensor in the CP2K output")
        rows = re.findall(rf"^ STRESS\|\s+[xyz]\s+({_FLOAT})\s+({_FLOAT})\s+({_FLOAT})\s*$",
                          text[i:], re.MULTILINE)[:3]
        if len(rows) != 3:
            raise CP2KError("could not parse the stress tensor in the CP2K output")
        out["stress_gpa"] = np.array(rows, dtype=float)
    m = re.findall(rf"Total Spread \(Berry\) :\s+({_FLOAT})", text)
    if m:
        out["spread"] = float(m[-1])  # sum_i -ln|z_i|^2 (dimensionless, Resta)
    return out


def read_wannier_xyz(path: Path, n_atoms: int) -> np.ndarray:
    """Wannier centres (Å) from CP2K's IONS+CENTERS xyz file (the last frame)."""
    lines = path.read_text().splitlines()
    frames = []
    i = 0
    while i < len(lines):
        if not lines[i].strip():
            i += 1
            continue
        n = int(lines[i].split()[0])
        rows = [ln.split() for ln in lines[i + 2:i + 2 + n]]
        frames.append(rows)
        i += 2 + n
    if not frames:
        raise CP2KError(f"{path.name}: no Wannier centres")
    rows = frames[-1]
    centres = [r[1:4] for r in rows[n_atoms:] if r[0] == "X"]
    if len(rows) - n_atoms != len(centres):
        raise CP2KError(f"{path.name}: unexpected rows after the {n_atoms} ions")
    return np.array(centres, dtype=float).reshape(-1, 3)


def map_centres_to_cores(centres: np.ndarray, positions: np.ndarray,
                         cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move each centre to the periodic image nearest to its closest core (Å).

    Returns ``(mapped, nearest_core)``; the distance to the closest core is minimum-image
    (:func:`emlpack.geometry.minimum_image`, exact for any triclinic cell).
    """
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    vec = minimum_image(centres[:, None, :] - positions[None, :, :], cell)  # (n_c, n_a, 3)
    core = np.linalg.norm(vec, axis=-1).argmin(axis=1)
    return positions[core] + vec[np.arange(len(centres)), core], core


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
        data_dir = find_data_dir(s.data_dir)
        composition = np.append(structure.numbers, structure.charge).tobytes()
        guess = self._wfn.get(composition) if s.reuse_wavefunction else None
        text = build_input(structure, s, stress, data_dir=data_dir, guess=guess)
        n_val = core_charges(structure.numbers).sum() - structure.charge
        if self.workdir is not None:
            self.workdir.mkdir(parents=True, exist_ok=True)
        run_dir = Path(tempfile.mkdtemp(prefix="cp2k-", dir=self.workdir))
        self.last_run_dir = run_dir
        t0 = time.perf_counter()
        try:
            (run_dir / "emlp.inp").write_text(text)
            output = self._run(run_dir, where)
            try:
                res = parse_output(output, structure.n_cores, stress)
            except CP2KError as exc:
                self._wfn.pop(composition, None)  # next time from the atomic guess
                raise CP2KError(f"{where}: {exc}; CP2K output tail:\n{_tail(output)}") from None
            if s.reuse_wavefunction:
                self._keep_wavefunction(run_dir / "emlp-RESTART.wfn", composition)
            pairs = np.zeros((0, 3))
            if s.wannier:
                wfile = run_dir / "emlp_wannier.xyz"
                if not wfile.exists():
                    raise CP2KError(f"{where}: CP2K wrote no Wannier centres; output tail:\n"
                                    f"{_tail(output)}")
                centres = read_wannier_xyz(wfile, structure.n_cores)
                if 2 * len(centres) != n_val:
                    raise CP2KError(
                        f"{where}: {len(centres)} Wannier centres, but {n_val:g} valence"
                        f" electrons need {n_val / 2:g}"
                    )
                pairs, _ = map_centres_to_cores(centres, structure.positions, structure.cell)
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
            stress_ev = _STRESS_SIGN * res["stress_gpa"] / EV_PER_A3_IN_GPA
        return Structure(
            numbers=structure.numbers.copy(), positions=structure.positions.copy(),
            pairs=pairs if s.wannier else structure.pairs.copy(), cell=structure.cell.copy(),
            pbc=True, field=structure.field.copy(), charge=structure.charge,
            energy=res["energy"] * HARTREE, forces=res["forces"] * HARTREE * ANGSTROM_IN_BOHR,
            pair_forces=np.zeros((len(pairs) if s.wannier else structure.n_pairs, 3)),
            stress=stress_ev, info=info, source=structure.source,
        )

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
        env = dict(os.environ, OMP_NUM_THREADS=str(int(s.omp_threads)))
        with open(run_dir / "stdout.txt", "w") as out:
            proc = subprocess.Popen(self.command(), cwd=run_dir, env=env, stdout=out,
                                    stderr=subprocess.STDOUT, start_new_session=True,
                                    preexec_fn=_terminate_with_parent)
            try:
                rc = proc.wait(timeout=s.timeout_s)
            except subprocess.TimeoutExpired:
                _stop_group(proc)
                output = _read(run_dir / "emlp.out")
                raise CP2KError(f"{where}: CP2K timed out after {s.timeout_s} s; output tail:\n"
                                f"{_tail(output)}") from None
            except BaseException:
                # interrupted (Ctrl-C, SystemExit, a Dask cancellation): never leave CP2K running
                _stop_group(proc)
                raise
        output = _read(run_dir / "emlp.out")
        if rc != 0 or "PROGRAM ENDED AT" not in output:
            raise CP2KError(
                f"{where}: CP2K failed (exit code {rc}); output tail:\n{_tail(output)}\n"
                f"launcher output tail:\n{_tail(_read(run_dir / 'stdout.txt'), 15)}"
            )
        return output


def _stop_group(proc: subprocess.Popen) -> None:
    """Terminate CP2K's process group (mpirun and its ranks), then kill it if it lingers."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    except ProcessLookupError:
        pass


def _terminate_with_parent() -> None:
    """In the child before exec: ask Linux to send SIGTERM when the labeling process dies
    (even by SIGKILL), so a killed job leaves no orphaned CP2K behind. No-op elsewhere."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


# ---------------------------------------------------------------------------------- tasks
#: labelers of this process, by settings and workdir (wavefunction reuse across tasks)
_LABELERS: dict[tuple, CP2KLabeler] = {}


def _labeler_for(settings: CP2KSettings | None, workdir) -> CP2KLabeler:
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
    items, store_path: str | Path, settings: CP2KSettings | None = None, *,
    workers: int = 0, scheduler: str | None = None, retry_failed: bool = False,
    workdir: str | Path | None = None, progress: bool = False,
):
    """Label ``(key, structure, stress)`` items into a :class:`DatasetStore`, resumably.

    Keys already in the store (records, and recorded failures unless ``retry_failed``) are
    skipped; failures are recorded with their reason. ``workers=0`` runs in-process; otherwise
    on a Dask ``LocalCluster`` of ``workers`` single-threaded workers (each CP2K run uses
    ``settings.n_processes`` MPI processes) or on the cluster at ``scheduler``.
    Returns a :class:`emlpack.qm.labeling.LabelingSummary`.
    """
    import sys

    from tqdm import tqdm

    from emlpack.data.store import DatasetStore
    from emlpack.qm.executor import Executor
    from emlpack.qm.labeling import LabelingSummary

    settings = settings or CP2KSettings()
    t0 = time.perf_counter()
    items = list(items)
    keys = [k for k, _, _ in items]
    if len(set(keys)) != len(keys):
        raise ValueError("label_into_store: keys must be unique")
    store = DatasetStore(store_path, "a")
    done = set(store.keys()) if retry_failed else store.done_keys()
    summary = LabelingSummary(str(store_path))
    todo = [it for it in items if it[0] not in done]
    summary.n_skipped_done = len(items) - len(todo)
    executor = Executor(workers, scheduler)
    bar = tqdm(total=len(todo), desc="cp2k", unit="conf", disable=not progress, file=sys.stderr)
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
def field_force_check(structure: Structure, settings: CP2KSettings, field_v_per_a,
                      components=((0, 0),), h: float = 0.005,
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
