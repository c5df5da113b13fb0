"""CP2K input of the periodic labeler: settings, data files (basis sets, GTH potentials) and the
input text for one structure (Γ point, GPW, Berry-phase field, Wannier centres; Å in, field
converted to atomic units).
"""

from __future__ import annotations

import os
import re
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from emlpack.qm.pyscf_labeler import LabelingError
from emlpack.structure import Structure, core_charges
from emlpack.units import FIELD_AU_IN_V_PER_A

#: where Debian's ``cp2k-data`` puts basis sets, potentials and ``dftd3.dat``
DEFAULT_DATA_DIRS = ("/usr/share/cp2k", "/usr/share/cp2k/data", "/usr/local/share/cp2k")

#: orientation of CP2K's PERIODIC_EFIELD POLARISATION relative to our field vector, chosen so
#: that E(F) - E(0) = -μ·F (checked by tests/qm/cp2k/test_labeler.py)
_FIELD_SIGN = 1.0


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
        wavefunction_guess: a CP2K ``.wfn`` file of the same (super)cell composition to start
            the SCF from whenever no kept wavefunction applies (``reuse_wavefunction`` off, or
            the first point of a composition), e.g. the DFT optimum's
            (:meth:`CP2KLabeler.wavefunction`): a campaign's samples are displacements around
            it. None: the atomic guess.
        supercell: run CP2K on the structure repeated this many times along its cell vectors
            (Γ point of the supercell = a Γ-centred k-point mesh of the cell, for every label:
            the Berry-phase field and the Wannier localisation need the Γ point only); the
            labels are mapped back to the cell (energy / number of cells, the first cell's
            forces and Wannier centres, the stress as is).
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
    wavefunction_guess: str | None = None
    supercell: tuple[int, int, int] = (1, 1, 1)
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
        cells = tuple(int(n) for n in self.supercell)
        sc = "" if cells == (1, 1, 1) else "/gamma-supercell-{}x{}x{}".format(*cells)
        return f"cp2k/{self.xc.lower()}{disp}/{self.basis.lower()}/{self.cutoff_ry:g}ry{sc}"

    def to_dict(self) -> dict:
        """The settings as a plain dict."""
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
        return (f"{s.cp2k} not found on PATH (install CP2K from the system: apt-get install"
                " cp2k cp2k-data openmpi-bin, or `make install-cp2k` in a clone)")
    if s.mpirun and shutil.which(s.mpirun) is None:
        return f"{s.mpirun} not found on PATH (apt-get install openmpi-bin)"
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
