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
from typing import TYPE_CHECKING

import numpy as np

from emlpack.errors import EmlpackError
from emlpack.heap import reused_heap
from emlpack.io.cores import find_core_centres
from emlpack.optional import import_optional
from emlpack.qm.levels import Level, parse_level
from emlpack.structure import Structure, StructureError
from emlpack.threads import configure_openblas_coretype
from emlpack.units import ANGSTROM_IN_BOHR, BOHR, FIELD_AU_IN_V_PER_A, HARTREE

if TYPE_CHECKING:
    from numpy.typing import ArrayLike
    from pyscf.dft.gen_grid import Grids
    from pyscf.dft.numint import NumInt
    from pyscf.dft.rks import RKS
    from pyscf.gto import Mole

#: spreads (bohr^2) of two Boys starts closer than this count as the same minimum
BOYS_SPREAD_TOL = 1e-4
#: a core centre must lie this close (Å) to its nucleus
CORE_CENTRE_MAX_DISTANCE = 0.3
#: default memory (MB) for atomic-orbital values on the DFT grid kept between SCF cycles
AO_CACHE_MB = 2048
#: default PySCF ``max_memory`` (MB): the density-fitting tensor of a 20-atom molecule
#: (1.8 GB) is built after the AO cache is filled and must still be held in memory (PySCF
#: keeps it when it needs less than 90 % of ``max_memory`` minus the memory in use)
MAX_MEMORY_MB = 8000
#: largest nuclear displacement (Å) for which ``reuse_density`` starts from a kept density
REUSE_MAX_SHIFT = 0.15
#: converged densities that ``reuse_density`` keeps (the least recently used is dropped)
REUSE_HISTORY = 4
#: how close (Å and V/Å) a state must be to the mirror image of a kept one for extrapolation
MIRROR_TOLERANCE = 1e-9


def density_guess(kept: list[tuple[np.ndarray, np.ndarray]], state: np.ndarray,
                  positions: np.ndarray, max_shift: float = REUSE_MAX_SHIFT,
                  ) -> tuple[np.ndarray | None, list[int]]:
    """An SCF start for ``state`` (positions in Å, then the field in V/Å) from converged
    densities ``kept`` [(state, density matrix)] of the same molecule.

    The mirror image of a kept state ``b`` through another kept state ``a`` (``state = 2 a -
    b``: the second displacement of a central difference, in positions or in the field) starts
    from the linear extrapolation ``2 D_a - D_b``, correct to second order in the step: on
    aziridine (PBE0/aug-cc-pVDZ, 0.005 Å) 3-4 SCF cycles instead of 6-7. Otherwise the nearest
    kept state (positions, then field; Euclidean) whose nuclei all moved less than
    ``max_shift`` Å. Returns the guess (None: none applies) and the indices of ``kept`` used.
    """
    n = np.asarray(positions).size
    for a, (xa, da) in enumerate(kept):
        for b, (xb, db) in enumerate(kept):
            if a != b and np.abs(2.0 * xa - xb - state).max() < MIRROR_TOLERANCE:
                return 2.0 * da - db, [a, b]
    best, key = None, None
    for k, (x, _) in enumerate(kept):
        if np.abs(x[:n] - state[:n]).max() > max_shift:
            continue
        this = (float(np.linalg.norm(x[:n] - state[:n])), float(np.linalg.norm(x[n:] - state[n:])))
        if key is None or this < key:
            best, key = k, this
    return (None, []) if best is None else (kept[best][1], [best])


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
        """True when the configuration was labeled."""
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


def caching_numint(budget_mb: float) -> NumInt:
    """A PySCF ``NumInt`` that keeps AO values on the grid between SCF cycles.

    Every SCF cycle of a GGA/hybrid evaluates the atomic orbitals and their first derivatives
    on the whole grid again; they only depend on the grid, which is fixed after the first
    cycle. This ``NumInt`` keeps the blocks of the first pass (as many as fit in ``budget_mb``
    MB, in grid order) and evaluates the rest as PySCF does. The blocks and screening masks are
    PySCF's own, so the numbers are the same (up to the summation order of the fixed block
    size). Other derivative orders (the gradient's second derivatives) are not cached. Call
    ``clear()`` to free the memory.
    """
    from pyscf.dft import gen_grid, numint

    class _CachingNumInt(numint.NumInt):
        cached_deriv = 1

        def __init__(self) -> None:
            super().__init__()
            self.budget_bytes = max(0.0, float(budget_mb)) * 1e6
            self.clear()

        def clear(self) -> None:
            self._key = None
            self._blocks: list[tuple] = []
            self._blksize = None
            self._rest = 0  # first grid point whose block is not cached

        def block_loop(self, mol: Mole, grids: Grids | _GridTail, nao: int | None = None,
                       deriv: int = 0, max_memory: float = 2000,
                       non0tab: np.ndarray | None = None, blksize: int | None = None,
                       buf: np.ndarray | None = None):
            plain = (deriv != self.cached_deriv or non0tab is not None or blksize is not None
                     or buf is not None or grids.coords is None or grids.non0tab is None
                     or mol is not grids.mol or self.budget_bytes <= 0)
            if plain:
                yield from super().block_loop(mol, grids, nao, deriv, max_memory, non0tab,
                                              blksize, buf)
                return
            if nao is None:
                nao = mol.nao
            key = (id(mol), id(grids.coords), grids.coords.shape, id(grids.non0tab), nao)
            if key != self._key:  # first pass on this grid: fill the cache
                self.clear()
                comp = (deriv + 1) * (deriv + 2) * (deriv + 3) // 6
                size = int(max_memory * 1e6 / ((comp + 1) * nao * 8 * gen_grid.BLKSIZE))
                ngrids = grids.coords.shape[0]
                size = max(4, min(size, ngrids // gen_grid.BLKSIZE + 1, 1200))
                self._blksize = size * gen_grid.BLKSIZE
                used = 0.0
                full = False
                for ao, mask, weight, coords in super().block_loop(
                        mol, grids, nao, deriv, max_memory, blksize=self._blksize):
                    if not full and used + ao.nbytes <= self.budget_bytes:
                        self._blocks.append((_layout_copy(ao), mask, weight, coords))
                        used += ao.nbytes
                    else:
                        full = True
                    yield ao, mask, weight, coords
                self._key = key
                self._rest = sum(len(b[2]) for b in self._blocks)
                return
            yield from self._blocks
            if self._rest < grids.coords.shape[0]:
                tail = _GridTail(grids, self._rest, gen_grid.BLKSIZE)
                yield from super().block_loop(mol, tail, nao, deriv, max_memory,
                                              non0tab=tail.non0tab, blksize=self._blksize)

    return _CachingNumInt()


#: indices of the second derivatives d/dx_k d/dx_l in PySCF's AO arrays (xx=4, xy=5, ...)
_SECOND = ((4, 5, 6), (5, 7, 8), (6, 8, 9))


def xc_nuclear_gradient(mf: RKS) -> np.ndarray:
    """The XC part of the RKS nuclear gradient (Hartree/bohr), shape (n_atoms, 3).

    The same quantity as PySCF's ``grad.rks.get_vxc`` (GGA, no grid response) contracted with
    the density, ``2 sum_{mu in A, nu} V^x_{mu nu} D_{nu mu}``, but contracted on the grid
    through the occupied orbitals: ``V^x D`` needs ``(w . phi) C n C^T`` (cost ``n_grid n_ao
    n_occ``) instead of three ``n_ao x n_ao`` matrices (cost ``n_grid n_ao^2`` each), so it is
    several times faster for aug-cc-pVTZ. Equal to PySCF's up to rounding (tested).
    """
    mol = mf.mol
    ni = mf._numint
    occ = mf.mo_occ > 0
    c = np.asarray(mf.mo_coeff[:, occ])
    n_occ = np.asarray(mf.mo_occ[occ])
    cn = c * n_occ
    nao = mol.nao
    t = np.zeros((3, nao))
    from pyscf import lib

    max_memory = max(2000.0, mf.max_memory * 0.9 - lib.current_memory()[0])
    for ao, mask, weight, _ in ni.block_loop(mol, mf.grids, nao, 2, max_memory):
        rho = ni.eval_rho2(mol, ao[:4], c, n_occ, mask, "GGA")
        wv = weight * ni.eval_xc_eff(mf.xc, rho, deriv=1, xctype="GGA")[1]
        wv[0] *= 0.5
        aow = ao[0] * wv[0][:, None]
        for k in range(1, 4):
            aow += ao[k] * wv[k][:, None]
        ao_d = (ao[0] @ cn) @ c.T  # phi D on the grid
        # V^x D = sum_g [d_x phi (w . phi) D + (d_x (w . phi)) phi D]: with b0 = (w . phi) D
        # + w_0 phi D and b_k = w_k phi D, t[x] = sum_g d_x phi b0 + sum_k d_x d_k phi b_k
        b0 = (aow @ cn) @ c.T
        b0 += ao_d * wv[0][:, None]
        bk = [ao_d * wv[1 + k][:, None] for k in range(3)]
        for x in range(3):
            t[x] += np.einsum("gi,gi->i", ao[1 + x], b0)
            for k in range(3):
                t[x] += np.einsum("gi,gi->i", ao[_SECOND[x][k]], bk[k])
    grad = np.zeros((mol.natm, 3))
    for a, (_, _, p0, p1) in enumerate(mol.aoslice_by_atom()):
        grad[a] = -2.0 * t[:, p0:p1].sum(axis=1)
    return grad


def _empty_grids(mol: Mole):
    """A PySCF grid without points (the XC part of a gradient on it is zero)."""
    from pyscf.dft import gen_grid

    grids = gen_grid.Grids(mol)
    grids.coords = np.zeros((0, 3))
    grids.weights = np.zeros(0)
    grids.non0tab = np.zeros((0, mol.nbas), dtype=np.uint8)
    return grids


class _GridTail:
    """The grid points ``start:`` of a PySCF grid (``start`` a multiple of the block size)."""

    def __init__(self, grids: Grids, start: int, blksize: int) -> None:
        self.mol = grids.mol
        self.coords = grids.coords[start:]
        self.weights = grids.weights[start:]
        self.non0tab = grids.non0tab[start // blksize:]
        self.cutoff = grids.cutoff


def _layout_copy(a: np.ndarray) -> np.ndarray:
    """A copy of ``a`` with the same memory layout (PySCF's AO blocks are per-component F)."""
    out = np.empty_like(a, order="K")
    np.copyto(out, a)
    return out


class PySCFLabeler:
    """Computes :class:`LabelResult` for molecules with PySCF.

    Args:
        level: a :class:`Level`, preset name or ``xc/basis`` string (default: the paper's).
        boys_starts: number of Foster-Boys starts (the first one from PySCF's atomic guess).
        boys_max_rounds: stability-analysis restarts per start.
        seed: seed of the random starting rotations (results are reproducible).
        threads: OpenMP threads for PySCF (``None``: PySCF's default).
        verbose: PySCF verbosity (0 silent).
        ao_cache_mb: memory (MB) for AO values kept between SCF cycles
            (:func:`caching_numint`; 0 evaluates them every cycle, as PySCF does).
        max_memory_mb: PySCF's ``max_memory`` (MB; ``None``: PySCF's default, 4000).
        fast_xc_gradient: XC part of the forces by :func:`xc_nuclear_gradient` (GGA and
            hybrid GGA; others use PySCF's).
        reuse_heap: label inside :func:`reused_heap` (glibc keeps freed memory during a label).
        keep_heap: and keep that memory between labels (``reused_heap(keep=True)``: for
            processes that only label, e.g. the labeling workers).
        reuse_density: start each SCF from this labeler's converged densities of the same
            molecule (:func:`density_guess`: the extrapolation ``2 D_a - D_b`` for the second
            step of a central difference, else the nearest one whose nuclei moved less than
            ``REUSE_MAX_SHIFT`` Å) for a series of small steps: optimisation, finite fields,
            finite-difference Hessians; otherwise from PySCF's default guess. The converged
            result is the same to the SCF tolerance.
    """

    def __init__(
        self,
        level: Level | str | None = None,
        boys_starts: int = 3,
        boys_max_rounds: int = 6,
        seed: int = 0,
        threads: int | None = None,
        verbose: int = 0,
        ao_cache_mb: float = AO_CACHE_MB,
        max_memory_mb: float | None = MAX_MEMORY_MB,
        fast_xc_gradient: bool = True,
        reuse_heap: bool = True,
        keep_heap: bool = False,
        reuse_density: bool = False,
    ) -> None:
        self.level = parse_level(level)
        self.boys_starts = max(1, int(boys_starts))
        self.boys_max_rounds = int(boys_max_rounds)
        self.seed = int(seed)
        self.threads = threads
        self.verbose = verbose
        self.ao_cache_mb = float(ao_cache_mb)
        self.max_memory_mb = max_memory_mb
        self.fast_xc_gradient = bool(fast_xc_gradient)
        self.reuse_heap = bool(reuse_heap)
        self.keep_heap = bool(keep_heap)
        self.reuse_density = bool(reuse_density)
        configure_openblas_coretype()  # before PySCF loads OpenBLAS
        import_optional("pyscf", "DFT labeling (PySCFLabeler)")
        # reuse_density: (numbers, charge) of the molecule, then [(state, density matrix)]
        self._molecule: tuple | None = None
        self._densities: list[tuple[np.ndarray, np.ndarray]] = []

    # ------------------------------------------------------------------ public
    def __call__(self, numbers: ArrayLike, positions: ArrayLike,
                 field: ArrayLike = (0.0, 0.0, 0.0), charge: float = 0.0,
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
            if self.reuse_heap:
                with reused_heap(keep=self.keep_heap):
                    self._label(result, forces=forces, localize=localize)
            else:
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
    def build(self, numbers: np.ndarray, positions: np.ndarray, field_au: np.ndarray,
              charge: float) -> tuple[Mole, RKS]:
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
        if self.max_memory_mb is not None:
            mol.max_memory = float(self.max_memory_mb)
        mol.build()
        mf = dft.RKS(mol, xc=lv.xc)
        if lv.density_fit:
            mf = mf.density_fit(auxbasis=lv.auxbasis)
        if self.ao_cache_mb > 0:
            mf._numint = caching_numint(self.ao_cache_mb)
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
        try:
            self._solve(res, mol, mf, field_au, forces, localize)
        finally:
            clear = getattr(mf._numint, "clear", None)
            if clear is not None:
                clear()  # free the AO cache now, not when the SCF object is collected

    @staticmethod
    def _state(res: LabelResult) -> np.ndarray:
        return np.concatenate([res.positions.ravel(), np.asarray(res.field, float).ravel()])

    def _initial_density(self, res: LabelResult) -> np.ndarray | None:
        """A start from the kept densities (:func:`density_guess`) when ``reuse_density``."""
        if not self.reuse_density or not self._densities:
            return None
        numbers, charge = self._molecule
        if charge != res.charge or not np.array_equal(numbers, res.numbers):
            return None
        dm, used = density_guess(self._densities, self._state(res), res.positions)
        self._densities = ([e for k, e in enumerate(self._densities) if k not in used]
                           + [self._densities[k] for k in used])  # most recently used last
        return dm

    def _keep_density(self, res: LabelResult, dm: np.ndarray) -> None:
        molecule = (res.numbers.copy(), res.charge)
        if (self._molecule is None or self._molecule[1] != res.charge
                or not np.array_equal(self._molecule[0], res.numbers)):
            self._molecule, self._densities = molecule, []
        self._densities = [*self._densities, (self._state(res), dm)][-REUSE_HISTORY:]

    def _solve(self, res: LabelResult, mol: Mole, mf: RKS, field_au: np.ndarray, forces: bool,
               localize: bool) -> None:
        energy = mf.kernel(dm0=self._initial_density(res))
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
        if self.reuse_density:
            self._keep_density(res, mf.make_rdm1())
        clear = getattr(mf._numint, "clear", None)
        if clear is not None:
            clear()  # the AO cache is for the SCF; the gradient needs second derivatives
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

    def _gradient(self, mol: Mole, mf: RKS, field_au: np.ndarray) -> np.ndarray:
        """dE/dR (Hartree/bohr) including the field terms PySCF's gradient does not know."""
        g = mf.nuc_grad_method()
        g.verbose = 0
        from pyscf.dft import libxc

        fast_xc = (self.fast_xc_gradient and libxc.xc_type(mf.xc) == "GGA"
                   and not mf.do_nlc() and not g.grid_response)
        if fast_xc:
            xc = xc_nuclear_gradient(mf)
            g.grids = _empty_grids(mol)  # PySCF's gradient without its XC part
            grad = np.asarray(g.kernel()) + xc
        else:
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

    def _boys(self, mol: Mole, occ: np.ndarray):
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


def assign_core_centres(numbers: np.ndarray, positions: np.ndarray,
                        centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
