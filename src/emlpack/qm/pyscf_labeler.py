"""Reference labels from PySCF: energy, forces and Foster-Boys centres under a homogeneous field.

Physics and conventions (checked against the paper's data, see docs and labeling notes):

* restricted Kohn-Sham, by default PBE0/aug-cc-pVTZ with density fitting (aug-cc-pVTZ-JKFIT);
* a homogeneous field ``E`` (atomic units inside, V/Å at the interface) enters as
  ``E_ext = -sum_i q_i E . r_i``: the core Hamiltonian gets ``+E . r`` (dipole integrals, gauge
  origin 0, electrons have q = -1) and the nuclear repulsion gets ``-sum_A Z_A E . R_A``;
* forces are analytic: PySCF's nuclear gradient (field-perturbed density) plus the two field
  terms it does not know about, the derivative of the dipole integrals with respect to the
  basis-function centres (``int1e_irp``) and the nuclear term ``-Z_A E`` in the gradient;
* all occupied orbitals are Foster-Boys localized from several starts (the atomic guess, then
  random rotations), each refined with PySCF's stability analysis until stable; the lowest
  spread wins, and disagreeing starts are reported. Centres are ``<psi|r|psi>``; the 1s (and for
  Na..Ar the n=2) core centres are recognised as the most compact centres on each heavy nucleus.

Geometry is converted with emlpack's molmod constants (positions are passed to PySCF in bohr),
so the numbers match the paper's data to the last digit that matters.
"""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass, field

import numpy as np

from emlpack.errors import EmlpackError
from emlpack.io.cores import find_core_centres
from emlpack.qm.levels import Level, parse_level
from emlpack.structure import Structure, StructureError
from emlpack.units import ANGSTROM_IN_BOHR, BOHR, FIELD_AU_IN_V_PER_A, HARTREE

#: spreads (bohr^2) of two Boys starts closer than this count as the same minimum
BOYS_SPREAD_TOL = 1e-4
#: a core centre must lie this close (Å) to its nucleus
CORE_CENTRE_MAX_DISTANCE = 0.3


class LabelingError(EmlpackError, RuntimeError):
    """A configuration could not be labeled (SCF not converged, localization failed, ...)."""


@dataclass
class LabelResult:
    """Labels of one configuration.

    Attributes:
        status: ``"ok"`` or ``"failed"``.
        error: reason of a failure (empty when ok).
        numbers: atomic numbers, shape (n_atoms,).
        positions: nuclear positions (Å), shape (n_atoms, 3).
        field: homogeneous field (V/Å), shape (3,).
        charge: total charge (e).
        energy: total energy including the field term (eV).
        forces: forces on nuclei (eV/Å), shape (n_atoms, 3).
        centres: all Foster-Boys centres (Å), core centres first (in atom order), then valence.
        core_mask: True for core centres, shape (n_centres,).
        level: level of theory, e.g. ``"pbe0/aug-cc-pvtz"``.
        wall_time: seconds spent on this configuration.
        pyscf_version: version string of PySCF.
        boys_spreads: final spread (bohr^2) of each localization start.
        boys_note: a note when the starts disagreed (empty otherwise).
        scf_cycles: SCF iterations used.
        dipole: dipole moment (e·Å) from the SCF density and the nuclei, origin 0.
    """

    status: str
    error: str
    numbers: np.ndarray
    positions: np.ndarray
    field: np.ndarray
    charge: float
    level: str
    energy: float = float("nan")
    forces: np.ndarray | None = None
    centres: np.ndarray | None = None
    core_mask: np.ndarray | None = None
    wall_time: float = 0.0
    pyscf_version: str = ""
    boys_spreads: list[float] = field(default_factory=list)
    boys_note: str = ""
    scf_cycles: int = 0
    dipole: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def pairs(self) -> np.ndarray:
        """Valence electron-pair positions (Å)."""
        if self.centres is None:
            return np.zeros((0, 3))
        return self.centres[~self.core_mask]

    def to_structure(self, source: str = "<pyscf>", info: dict | None = None) -> Structure:
        """The labeled configuration as a :class:`Structure` (valence pairs only)."""
        if not self.ok:
            raise LabelingError(f"{source}: labeling failed: {self.error}")
        meta = {
            "level": self.level,
            "wall_time": self.wall_time,
            "pyscf_version": self.pyscf_version,
        }
        meta.update(info or {})
        return Structure(
            numbers=self.numbers,
            positions=self.positions,
            pairs=self.pairs,
            field=self.field,
            charge=self.charge,
            energy=self.energy,
            forces=self.forces,
            pair_forces=np.zeros_like(self.pairs),
            info=meta,
            source=source,
        )


class PySCFLabeler:
    """Computes :class:`LabelResult` for molecules with PySCF.

    Args:
        level: a :class:`Level`, preset name or ``xc/basis`` string (default: the paper's).
        boys_starts: number of Foster-Boys starts (the first one from PySCF's atomic guess).
        boys_max_rounds: stability-analysis restarts per start.
        seed: seed of the random starting rotations (results are reproducible).
        threads: OpenMP threads for PySCF (``None``: PySCF's default).
        verbose: PySCF verbosity (0 silent).
    """

    def __init__(
        self,
        level: Level | str | None = None,
        boys_starts: int = 3,
        boys_max_rounds: int = 6,
        seed: int = 0,
        threads: int | None = None,
        verbose: int = 0,
    ) -> None:
        self.level = parse_level(level)
        self.boys_starts = max(1, int(boys_starts))
        self.boys_max_rounds = int(boys_max_rounds)
        self.seed = int(seed)
        self.threads = threads
        self.verbose = verbose

    # ------------------------------------------------------------------ public
    def __call__(self, numbers, positions, field=(0.0, 0.0, 0.0), charge: float = 0.0,
                 forces: bool = True, localize: bool = True) -> LabelResult:
        """Label one molecule.

        Args:
            numbers: atomic numbers, shape (n,).
            positions: nuclear positions (Å), shape (n, 3).
            field: homogeneous external field (V/Å), shape (3,).
            charge: total charge (e).
            forces: compute analytic forces.
            localize: compute Foster-Boys centres.
        """
        import pyscf

        numbers = np.asarray(numbers, dtype=np.int64).reshape(-1)
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        field_v = np.asarray(field, dtype=np.float64).reshape(3)
        result = LabelResult(
            status="failed", error="", numbers=numbers, positions=positions, field=field_v,
            charge=float(charge), level=self.level.name, pyscf_version=pyscf.__version__,
        )
        t0 = time.perf_counter()
        try:
            self._label(result, forces=forces, localize=localize)
            result.status = "ok"
        except LabelingError as exc:
            result.error = str(exc)
        except Exception as exc:  # noqa: BLE001 - a failed configuration must not stop a run
            tb = traceback.format_exc(limit=3).strip().splitlines()[-1]
            result.error = f"{type(exc).__name__}: {exc} ({tb})"
        result.wall_time = time.perf_counter() - t0
        return result

    def label_structure(self, structure: Structure, **kwargs) -> LabelResult:
        """Label the nuclei of ``structure`` under its field and charge (its pairs are ignored)."""
        return self(structure.numbers, structure.positions, structure.field, structure.charge,
                    **kwargs)

    # ------------------------------------------------------------------ internals
    def build(self, numbers, positions, field_au, charge):
        """The PySCF ``Mole`` and the field-perturbed (unconverged) RKS object."""
        from pyscf import dft, gto

        if self.threads:
            from pyscf import lib

            lib.num_threads(self.threads)
        lv = self.level
        n_electrons = int(np.sum(numbers)) - int(round(charge))
        if n_electrons % 2:
            raise LabelingError(f"odd number of electrons ({n_electrons}); need a closed shell")
        coords_bohr = np.asarray(positions) * ANGSTROM_IN_BOHR
        mol = gto.Mole()
        mol.atom = [(int(z), tuple(r)) for z, r in zip(numbers, coords_bohr, strict=True)]
        mol.unit = "Bohr"
        mol.basis = lv.basis
        mol.charge = int(round(charge))
        mol.spin = 0
        mol.verbose = self.verbose
        mol.build()
        mf = dft.RKS(mol, xc=lv.xc)
        if lv.density_fit:
            mf = mf.density_fit(auxbasis=lv.auxbasis)
        mf.grids.level = lv.grid_level
        mf.conv_tol = lv.conv_tol
        mf.max_cycle = lv.max_cycle
        mf.verbose = self.verbose
        field_au = np.asarray(field_au, dtype=np.float64)
        if np.any(field_au != 0.0):
            with mol.with_common_origin((0.0, 0.0, 0.0)):
                dip = mol.intor_symmetric("int1e_r", comp=3)
            hcore = mf.get_hcore(mol) + np.einsum("x,xij->ij", field_au, dip)
            enuc = mol.energy_nuc() - float(
                np.einsum("a,ax,x->", mol.atom_charges(), mol.atom_coords(), field_au)
            )
            mf.get_hcore = lambda *args, **kw: hcore
            mf.energy_nuc = lambda *args, **kw: enuc
        return mol, mf

    def _label(self, res: LabelResult, forces: bool, localize: bool) -> None:
        field_au = res.field / FIELD_AU_IN_V_PER_A
        mol, mf = self.build(res.numbers, res.positions, field_au, res.charge)
        energy = mf.kernel()
        cycles = int(getattr(mf, "cycles", 0) or 0)
        if not mf.converged:
            mf2 = mf.newton()
            energy = mf2.kernel(mf.mo_coeff, mf.mo_occ)
            if not mf2.converged:
                raise LabelingError(
                    f"SCF not converged after {self.level.max_cycle} DIIS cycles and a"
                    f" second-order (Newton) attempt, last energy {energy:.10f} Ha"
                )
            mf = mf2
        res.scf_cycles = cycles
        res.energy = float(energy) * HARTREE
        with mol.with_common_origin((0.0, 0.0, 0.0)):
            dip_ints = mol.intor_symmetric("int1e_r", comp=3)
        electronic = -np.einsum("xij,ji->x", dip_ints, mf.make_rdm1())
        res.dipole = (electronic + mol.atom_charges() @ mol.atom_coords()) * BOHR
        if forces:
            res.forces = -self._gradient(mol, mf, field_au) * (HARTREE * ANGSTROM_IN_BOHR)
        if localize:
            occ = mf.mo_coeff[:, mf.mo_occ > 0]
            centres_bohr, spreads, note, _ = self._boys(mol, occ)
            res.boys_spreads = spreads
            res.boys_note = note
            centres = centres_bohr * BOHR
            order, core = assign_core_centres(res.numbers, res.positions, centres)
            res.centres = centres[order]
            res.core_mask = core

    @staticmethod
    def _gradient(mol, mf, field_au: np.ndarray) -> np.ndarray:
        """dE/dR (Hartree/bohr) including the field terms PySCF's gradient does not know."""
        g = mf.nuc_grad_method()
        g.verbose = 0
        grad = np.asarray(g.kernel())
        if np.any(field_au != 0.0):
            dm = mf.make_rdm1()
            nao = mol.nao
            with mol.with_common_origin((0.0, 0.0, 0.0)):
                # irp[k, j, nu, mu] = <nu| r_k d_j |mu>
                irp = mol.intor("int1e_irp", comp=9).reshape(3, 3, nao, nao)
            for a, (_, _, p0, p1) in enumerate(mol.aoslice_by_atom()):
                grad[a] -= 2.0 * np.einsum(
                    "k,kjnm,mn->j", field_au, irp[:, :, :, p0:p1], dm[p0:p1, :]
                )
            grad -= mol.atom_charges()[:, None] * field_au[None, :]
        return grad

    def _boys(self, mol, occ: np.ndarray):
        """Foster-Boys centres (bohr): lowest spread over several stabilised starts."""
        from pyscf import lo

        with mol.with_common_origin((0.0, 0.0, 0.0)):
            r_ints = mol.intor_symmetric("int1e_r", comp=3)
            r2_ints = mol.intor_symmetric("int1e_r2")
        rng = np.random.default_rng(self.seed)
        n = occ.shape[1]
        if n == 1:  # nothing to localize
            centres = np.einsum("xpq,p,q->x", r_ints, occ[:, 0], occ[:, 0])[None, :]
            spread = float(occ[:, 0] @ r2_ints @ occ[:, 0] - centres[0] @ centres[0])
            return centres, [spread], "", np.array([spread])
        best = None
        spreads: list[float] = []
        saved_state = np.random.get_state()  # noqa: NPY002 - PySCF uses it
        try:
            for start in range(self.boys_starts):
                np.random.seed(self.seed * 1000 + start)  # noqa: NPY002
                loc = lo.Boys(mol, occ)
                loc.verbose = 0
                if start == 0:
                    mo = loc.kernel()
                else:
                    q, _ = np.linalg.qr(rng.standard_normal((n, n)))
                    mo = loc.kernel(occ @ q)
                for _ in range(self.boys_max_rounds):
                    mo_new, stable = loc.stability(return_status=True)
                    if stable:
                        break
                    mo = loc.kernel(mo_new)
                centres = np.einsum("xpi,pi->ix", np.einsum("xpq,qi->xpi", r_ints, mo), mo)
                each = np.einsum("pi,pq,qi->i", mo, r2_ints, mo) - np.sum(centres**2, axis=1)
                total = float(each.sum())
                spreads.append(total)
                if best is None or total < best[0]:
                    best = (total, centres, each)
        finally:
            np.random.set_state(saved_state)  # noqa: NPY002
        note = ""
        if max(spreads) - min(spreads) > BOYS_SPREAD_TOL:
            note = (
                "Foster-Boys starts disagree: spreads "
                + ", ".join(f"{s:.5f}" for s in spreads)
                + f" bohr^2; kept {best[0]:.5f}"
            )
        return best[1], spreads, note, best[2]


def assign_core_centres(numbers, positions, centres):
    """Order centres as core centres (in atom order) then valence; return (order, core_mask).

    Each atom with ``k`` core pairs (1 for Li..Ne, 5 for Na..Ar) takes its ``k`` nearest
    centres within :data:`CORE_CENTRE_MAX_DISTANCE` Å (:func:`emlpack.io.cores.find_core_centres`,
    the one home of this rule; a failure is a :class:`LabelingError`).
    """
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    try:
        core = find_core_centres(numbers, positions, centres, tolerance=CORE_CENTRE_MAX_DISTANCE,
                                 source="Foster-Boys centres")
    except StructureError as exc:
        raise LabelingError(str(exc)) from None
    valence = np.setdiff1d(np.arange(len(centres)), core)
    order = np.concatenate([core, valence]).astype(np.int64)
    mask = np.zeros(len(centres), dtype=bool)
    mask[: len(core)] = True
    return order, mask
