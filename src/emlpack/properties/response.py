"""Response properties of the eMLP from its extended Hessian (paper, appendix A).

The extended Hessian (:func:`emlpack.properties.hessian.extended_hessian`) differentiates the
total energy twice with respect to particle positions (fractional coordinates and the cell for
crystals) and the field (V/Å).

Every response property is a Schur complement of this matrix: eliminating a block ``x``
(relaxing those coordinates at zero gradient) leaves ``S = H_yy - H_yx H_xx^-1 H_xy`` for the
remaining variables ``y``. With the sign of the field term (``E_field = -mu . F``):

* polarizability ``alpha = -d2E/dF2 = H_Fx H_xx^-1 H_xF`` (``H_FF = 0``), e·Å²/V; ``x`` = pairs
  (clamped cores, the paper's main text: :func:`clamped_response`, the one home of this
  formula) or pairs + cores (rigid-body motions projected out); with the pairs' Hessian taken
  at given pairs and its derivative in the model's parameters,
  :func:`clamped_polarizabilities` (the training loss's polarizability term);
* Born-Oppenheimer core Hessian ``S_cc`` and dipole derivatives ``dmu/dR = -S_Fc`` (pairs
  eliminated), for IR spectra (:mod:`emlpack.properties.ir`);
* with the pairs eliminated at clamped cores, the rotations that leave every core in place
  (:func:`emlpack.geometry.core_fixed_rotations`: a linear molecule's about its axis) are
  projected out of the pairs' space where the Hessian is flat along them (:func:`pair_basis`):
  at relaxed pairs they are symmetries of the energy, exact zero modes of the pair Hessian,
  which the inverse turns into noise of any size and sign (linear hexatriyne with mini-eqm7:
  clamped isotropic polarizabilities of 232 to 6306 bohr³ over the members without the
  projection, 100 to 128 with it; docs/response.md);
* :func:`pair_minimum_problem` says when a result is not at a minimum of the pairs (an
  imaginary pair mode, a negative clamped polarizability eigenvalue): the commands leave such
  a member out of their mean;
* crystals (``A`` = cell, rows = lattice vectors; ``V`` = volume; ``x`` = fractional
  coordinates, with uniform translations projected out):

  - stiffness ``C_ijkl = (1/V) sum_mn A_mi A_nk S_aa[(m,j),(n,l)]``
    = ``(1/V) d2E/(d eps_ij d eps_kl)`` for ``A -> A (I + eps)``, internal coordinates relaxed;
  - dielectric ``eps_ij = delta_ij + alpha_ij / (V eps0)``;
  - proper piezoelectric tensor ``e~_ijk = (1/V) sum_m A_mj (H_Fx H_xx^-1 H_xa)_{i,(m,k)}``
    = ``(1/V) sum_m A_mj (H_Fa - S_Fa)_{i,(m,k)}``, and the improper one
    ``e_ijk = dP_i/d eps_jk`` (``P = mu/V`` from unwrapped positions), related by
    ``e~_ijk = e_ijk + delta_jk P_i - delta_ik P_j`` (Vanderbilt 2000);
  - strain constants ``d = e : C^-1``; Voigt order xx yy zz yz xz xy, engineering shear strain
    (``S_4 = 2 eps_yz``), so ``d_iJ = sum_K e_iK (C^-1)_KJ`` carries the factor 2 on shears.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from emlpack.geometry import (
    VoigtViews,
    core_fixed_rotations,
    internal_basis,
    rigid_body_modes,
    schur_complement,
    voigt_piezo,
    voigt_stiffness,
)
from emlpack.nn.graph import Graph
from emlpack.nn.potential import EMLP
from emlpack.nn.short_range.hessian import short_range_curvatures
from emlpack.pairs.checks import FLAT_CURVATURE
from emlpack.properties.hessian import clamped_pair_hessian, extended_hessian
from emlpack.structure import Structure
from emlpack.units import (
    A_PER_V_IN_PM_PER_V,
    COULOMB_EV_A,
    E_A_IN_DEBYE,
    E_PER_A2_IN_C_PER_M2,
    EPSILON0_E_PER_V_A,
    EV_PER_A3_IN_GPA,
    POLARIZABILITY_A3_IN_BOHR3,
)


# ---------------------------------------------------------------------- molecules
def _molecule_layout(structure: Structure) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices of core, pair and field variables of the molecular extended Hessian."""
    nc, n = structure.n_cores, structure.n_cores + structure.n_pairs
    return np.arange(3 * nc), np.arange(3 * nc, 3 * n), np.arange(3 * n, 3 * n + 3)


#: cores within this fraction of the molecule's size of one line count as a linear molecule
#: for :func:`pair_basis` (a DFT optimum holds them on the line to ~1e-5 Å, not exactly)
LINEAR_TOLERANCE = 1e-3
#: a clamped polarizability that rests for more than this fraction on pair modes within the
#: flat curvature (:func:`pair_minimum_problem`) is indeterminate
FLAT_SHARE = 0.1


def pair_basis(hessian: np.ndarray, structure: Structure,
               flat_curvature: float = FLAT_CURVATURE) -> np.ndarray | None:
    """Orthonormal columns (3P) of the pair displacements a clamped-core response relaxes: all
    but the rotations that leave every core in place
    (:func:`~emlpack.geometry.core_fixed_rotations`, cores on a line within
    :data:`LINEAR_TOLERANCE`: the rotation about a linear molecule's axis) along which the
    molecular extended ``hessian`` is flat (curvature within ``flat_curvature``, eV/Å²:
    relaxed pairs, where such a rotation is a zero mode); None when there are none (crystals,
    molecules with three cores off a line)."""
    if structure.pbc or structure.n_pairs == 0:
        return None
    pairs = _molecule_layout(structure)[1]
    return _flat_rotation_basis(hessian[np.ix_(pairs, pairs)], structure.positions,
                                structure.pairs, flat_curvature)


def _flat_rotation_basis(h_pp: np.ndarray, cores: np.ndarray, pairs: np.ndarray,
                         flat_curvature: float) -> np.ndarray | None:
    """:func:`pair_basis` from the pair block ``h_pp`` (3P, 3P) and the positions (Å)."""
    rotations = core_fixed_rotations(cores, pairs, LINEAR_TOLERANCE)
    if not rotations.shape[1]:
        return None
    w, v = np.linalg.eigh(rotations.T @ (0.5 * (h_pp + h_pp.T)) @ rotations)
    flat = rotations @ v[:, np.abs(w) <= flat_curvature]
    return internal_basis(flat) if flat.shape[1] else None


def clamped_response(hessian: np.ndarray, pairs: np.ndarray, field: np.ndarray,
                     basis: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pairs relaxed at clamped cores, from an extended Hessian whose variables ``pairs``
    (3P indices) are the pairs' Cartesian positions and ``field`` (3) the field:

    * the polarizability ``alpha = H_Fp B (B^T H_pp B)^-1 B^T H_pF`` (3, 3) (e·Å²/V;
      ``-d2E/dF2`` at relaxed pairs, ``H_FF = 0``; the Schur complement
      :func:`~emlpack.geometry.schur_complement`);
    * the pairs' shifts per unit field ``D = dr_p/dF = -B (B^T H_pp B)^-1 B^T H_pF`` (3P, 3)
      (Å per V/Å), so that ``alpha = -H_Fp D`` and, for a change ``dH_pp`` of the pair
      block, ``d alpha = -D^T dH_pp D``;

    ``basis`` (3P, m) orthonormal: the pair displacements relaxed (default: all)."""
    alpha = -schur_complement(hessian, field, pairs, basis)
    h = 0.5 * (hessian + hessian.T)
    h_pp, h_pf = h[np.ix_(pairs, pairs)], h[np.ix_(pairs, field)]
    if basis is None:
        return alpha, -np.linalg.solve(h_pp, h_pf)
    return alpha, -basis @ np.linalg.solve(basis.T @ h_pp @ basis, basis.T @ h_pf)


@dataclass
class ClampedPolarizabilities:
    """Result of :func:`clamped_polarizabilities` for the B molecules of a graph.

    Attributes:
        alpha: (B, 3, 3) polarizabilities (e·Å²/V, float64); with ``create_graph`` a
            differentiable function of the model's parameters.
        problems: per molecule ``""``, or why its pair Hessian at the given pairs is not
            positive definite (its ``alpha`` is then no response: leave it out).
    """

    alpha: torch.Tensor
    problems: list[str]


def clamped_polarizabilities(model: EMLP, g: Graph, create_graph: bool = False,
                             flat_curvature: float = FLAT_CURVATURE) -> ClampedPolarizabilities:
    """Clamped-core polarizability of every molecule of ``g`` from the model's pair Hessian at
    the pairs of ``g`` as they are (not relaxed first): ``alpha = H_Fp H_pp^-1 H_pF``
    (:func:`clamped_response`; the rotation of a linear molecule's pairs about its axis
    projected out where flat, :func:`pair_basis`). At the model's own pair minimum this is
    :func:`polarizability_from_hessian`'s; at other pairs (the DFT centres of training
    labels) it is the harmonic response of the model's pairs about them.

    The pair Hessian is exact (:func:`~emlpack.properties.hessian.clamped_pair_hessian`, per
    molecule, no graph); the parameters enter only through its short-range part, so with
    ``create_graph`` the value is kept and the first derivatives in the parameters come from
    ``d alpha = -D^T dH_sr D`` (``D``: the pairs' shifts per unit field) as the curvatures
    ``D_a^T H_sr D_c`` of the short-range energy along the three columns of ``D``, one
    gradient graph and three reverse passes for all molecules together
    (:func:`~emlpack.nn.short_range.hessian.short_range_curvatures`), differentiable in
    turn. Second derivatives in the parameters are not those of ``alpha``."""
    b = g.n_structures
    alpha = torch.zeros(b, 3, 3, dtype=torch.float64, device=g.positions.device)
    directions = torch.zeros(3, g.n_particles, 3, dtype=torch.float64, device=alpha.device)
    problems = [""] * b
    for k in range(b):
        keep = torch.zeros(b, dtype=torch.bool, device=alpha.device)
        keep[k] = True
        sub = g.subgraph(keep)
        if int(sub.n_pairs[0]) == 0:
            continue
        h_pp = clamped_pair_hessian(model, sub).cpu().numpy()
        n = h_pp.shape[0]
        pos = sub.positions.detach().double().cpu().numpy()
        is_pair = sub.is_pair.cpu().numpy()
        q = sub.charges.detach().double().cpu().numpy()[is_pair]
        h = np.zeros((n + 3, n + 3))
        h[:n, :n] = h_pp
        h[:n, n:] = -np.kron(q[:, None], np.eye(3))  # d2E/dr_ia dF_b = -q_i delta_ab
        h[n:, :n] = h[:n, n:].T
        basis = _flat_rotation_basis(h_pp, pos[~is_pair], pos[is_pair], flat_curvature)
        reduced = h_pp if basis is None else basis.T @ h_pp @ basis
        lowest = float(np.linalg.eigvalsh(0.5 * (reduced + reduced.T))[0])
        if lowest <= flat_curvature:
            problems[k] = (f"lowest pair-Hessian eigenvalue {lowest:.3g} eV/Å^2 at the given"
                           " pairs: not a minimum of the model's pairs there")
            continue
        value, shifts = clamped_response(h, np.arange(n), np.arange(n, n + 3), basis)
        alpha[k] = torch.as_tensor(value, dtype=torch.float64)
        rows = torch.nonzero(g.batch == k).squeeze(1)[sub.is_pair]
        directions[:, rows] = torch.as_tensor(shifts.T.reshape(3, -1, 3), dtype=torch.float64)
    if create_graph:
        curv = short_range_curvatures(model, g, directions.to(g.dtype), create_graph=True)
        alpha = alpha - (curv - curv.detach()).double()
    return ClampedPolarizabilities(alpha, problems)


def polarizability_from_hessian(
    hessian: np.ndarray, structure: Structure, relax_cores: bool = False
) -> np.ndarray:
    """Static polarizability alpha_ij = -d2E/dF_i dF_j (e·Å²/V) of a molecule.

    ``relax_cores=False``: pairs relaxed at clamped cores (electronic, the paper's main text;
    a linear molecule's pairs without their rotation about its axis, :func:`pair_basis`);
    ``True``: cores relaxed as well, rigid-body motions of the whole molecule projected out
    (electronic + vibrational); the geometry should then be a minimum.
    """
    if structure.pbc:
        raise ValueError(f"{structure.source}: polarizability is for molecules; use"
                         " crystal_response for crystals")
    cores, pairs, field = _molecule_layout(structure)
    if relax_cores:
        coords = np.concatenate([cores, pairs])
        basis = internal_basis(rigid_body_modes(structure.all_positions))
        return -schur_complement(hessian, field, coords, basis)
    return clamped_response(hessian, pairs, field, pair_basis(hessian, structure))[0]


def born_oppenheimer_blocks(
    hessian: np.ndarray, structure: Structure
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs eliminated (:func:`pair_basis`): core Hessian (3Nc, 3Nc) eV/Å², dipole derivatives
    dmu_a/dR_ib (3, 3Nc) e, and clamped-core polarizability (3, 3) e·Å²/V, of a molecule."""
    cores, pairs, field = _molecule_layout(structure)
    keep = np.concatenate([cores, field])
    s = schur_complement(hessian, keep, pairs, pair_basis(hessian, structure))
    nc = len(cores)
    return s[:nc, :nc], -s[nc:, :nc], -s[nc:, nc:]


def pair_minimum_problem(hessian: np.ndarray, structure: Structure,
                         flat_curvature: float = FLAT_CURVATURE) -> str:
    """Why the pairs of ``structure`` are not at a well-defined energy minimum at its cores,
    read from its extended Hessian (molecule or crystal layout), or ``""`` when they are:

    * an imaginary pair mode: a pair-Hessian eigenvalue at or below ``-flat_curvature``
      (eV/Å², Cartesian; a linear molecule's rotation about its axis excluded,
      :func:`pair_basis`);
    * a negative eigenvalue of the clamped-core polarizability (the pairs' response to a
      field, positive definite at a minimum): a near-zero negative pair curvature that passes
      as flat still makes it negative, and every response built on it meaningless;
    * a clamped polarizability that rests for more than :data:`FLAT_SHARE` on pair modes
      within the flat curvature (``sum |c_k|^2 / |lambda_k|`` over the modes, ``c_k`` their
      coupling to the field): there the curvature's size and sign are not determined, so
      neither is the response (e.g. the pairs' near-free rotation about a nearly linear
      molecule's axis).
    """
    if structure.n_pairs == 0:
        return ""
    h = 0.5 * (hessian + hessian.T)
    nc, n = structure.n_cores, structure.n_cores + structure.n_pairs
    pairs = np.arange(3 * nc, 3 * n)
    field = (np.arange(3 * n + 9, 3 * n + 12) if structure.pbc
             else np.arange(3 * n, 3 * n + 3))
    h_pp, h_fp = h[np.ix_(pairs, pairs)], h[np.ix_(field, pairs)]
    if structure.pbc:  # fractional -> Cartesian: r = s A, so H_rr = A^-1 H_ss A^-T per block
        t = np.kron(np.eye(structure.n_pairs), np.linalg.inv(structure.cell))
        h_pp, h_fp = t @ h_pp @ t.T, h_fp @ t.T
    basis = pair_basis(h, structure)
    if basis is not None:
        h_pp, h_fp = basis.T @ h_pp @ basis, h_fp @ basis
    lam, modes = np.linalg.eigh(h_pp)
    reasons = []
    if lam[0] <= -flat_curvature:
        reasons.append(f"imaginary pair mode: lowest pair-Hessian eigenvalue {lam[0]:.3g}"
                       " eV/Å^2 (the pairs are at a saddle, not a minimum)")
    coupling = np.sum((h_fp @ modes) ** 2, axis=0)  # |c_k|^2, (e)^2
    with np.errstate(divide="ignore", invalid="ignore"):
        parts = coupling / np.abs(lam)
        alpha = (h_fp @ modes) @ ((h_fp @ modes) / lam).T  # clamped alpha, e·Å²/V
    a = np.linalg.eigvalsh(0.5 * (alpha + alpha.T)) if np.all(np.isfinite(alpha)) else None
    if a is None or a[0] < -1e-8 * abs(a[-1]):
        low = "infinite" if a is None else f"{a[0] * COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3:.3g}"
        reasons.append(f"negative polarizability eigenvalue {low} bohr^3 (the pairs are not"
                       " at a minimum)")
    else:
        flat = np.abs(lam) <= flat_curvature
        share = float(np.sum(parts[flat]) / np.sum(parts)) if np.sum(parts) > 0 else 0.0
        if share > FLAT_SHARE:
            reasons.append(f"the polarizability rests {share:.0%} on pair modes flatter than"
                           f" {flat_curvature:g} eV/Å^2 (lowest {np.min(np.abs(lam)):.2g}):"
                           " indeterminate, the pairs have no well-defined minimum")
    return "; ".join(reasons)


@dataclass
class MoleculeResponse:
    """Dipole and polarizabilities of a molecule (e·Å, e·Å²/V)."""

    dipole: np.ndarray
    polarizability: np.ndarray
    polarizability_relaxed: np.ndarray | None = None

    def as_dict(self) -> dict:
        """Plain dict for JSON: the dipole (e·Å, Debye, norm in Debye) and each polarizability in
        e·Å²/V, Å³ and bohr³, with its isotropic mean (bohr³)."""
        out = {
            "dipole_e_A": self.dipole.tolist(),
            "dipole_debye": (self.dipole * E_A_IN_DEBYE).tolist(),
            "dipole_norm_debye": float(np.linalg.norm(self.dipole) * E_A_IN_DEBYE),
        }
        for key, value in (("polarizability", self.polarizability),
                           ("polarizability_relaxed_cores", self.polarizability_relaxed)):
            if value is None:
                continue
            out[f"{key}_e_A2_per_V"] = value.tolist()
            out[f"{key}_A3"] = (value * COULOMB_EV_A).tolist()
            out[f"{key}_bohr3"] = (value * COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3).tolist()
            out[f"{key}_isotropic_bohr3"] = float(
                np.trace(value) / 3 * COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3
            )
        return out

    def text(self) -> str:
        """Summary lines: the dipole (e·Å, Debye) and the polarizabilities (bohr³)."""
        d = self.as_dict()
        lines = [
            "dipole (e·Å):   " + _vec(self.dipole),
            "dipole (Debye): " + _vec(self.dipole * E_A_IN_DEBYE)
            + f"   |mu| = {d['dipole_norm_debye']:.4f} D",
        ]
        for key, label in (("polarizability", "pairs relaxed, cores clamped"),
                           ("polarizability_relaxed_cores", "pairs and cores relaxed")):
            if f"{key}_bohr3" not in d:
                continue
            lines.append(f"polarizability ({label}), bohr^3:"
                         f"  isotropic {d[f'{key}_isotropic_bohr3']:.4f}")
            lines += ["  " + _vec(row, "{:12.4f}") for row in np.array(d[f"{key}_bohr3"])]
        return "\n".join(lines)


def molecule_response(
    model: EMLP, structure: Structure, relax_cores: bool = True
) -> MoleculeResponse:
    """Dipole (sum q r, e·Å) and polarizabilities of ``structure`` at its given geometry
    (relax the pairs first; relax the cores too for ``relax_cores``)."""
    _, h = extended_hessian(model, structure)
    return molecule_response_from_hessian(h.numpy(), structure, relax_cores)


def molecule_response_from_hessian(hessian: np.ndarray, structure: Structure,
                                   relax_cores: bool = True) -> MoleculeResponse:
    """:func:`molecule_response` from the molecular extended Hessian of ``structure``."""
    return MoleculeResponse(
        dipole=structure.dipole(),
        polarizability=polarizability_from_hessian(hessian, structure),
        polarizability_relaxed=(polarizability_from_hessian(hessian, structure, relax_cores=True)
                                if relax_cores else None),
    )


# ---------------------------------------------------------------------- crystals
def improper_piezo(proper: np.ndarray, polarization: np.ndarray) -> np.ndarray:
    """Improper ``e_ijk = e~_ijk - delta_jk P_i + delta_ik P_j`` (e/Å², P in e/Å²)."""
    eye = np.eye(3)
    return (proper - np.einsum("jk,i->ijk", eye, polarization)
            + np.einsum("ik,j->ijk", eye, polarization))


@dataclass
class CrystalResponse(VoigtViews):
    """Response tensors of a crystal in internal units (eV/Å³, e/Å², Å/V; dimensionless).

    Attributes:
        volume: cell volume (Å³).
        polarization: dipole density ``sum q r / V`` (e/Å², unwrapped positions: not a
            material property).
        stiffness: relaxed-ion C_ijkl (eV/Å³), 3x3x3x3.
        stiffness_clamped: C_ijkl with only the pairs relaxed (cores at fixed fractional
            coordinates).
        dielectric_clamped: ion-clamped eps_ij (pairs relaxed).
        dielectric_relaxed: eps_ij with cores and pairs relaxed.
        piezo: proper e~_ijk (e/Å²), relaxed ions.
        piezo_clamped: proper e~_ijk with only the pairs relaxed.

    Voigt views (:class:`emlpack.geometry.VoigtViews`): ``stiffness_voigt`` C_IJ (eV/Å³),
    ``piezo_voigt`` e_iJ (e/Å²), ``strain_constants_voigt`` d_iJ (Å/V) and the tensor
    ``strain_constants``.
    """

    volume: float
    polarization: np.ndarray
    stiffness: np.ndarray
    stiffness_clamped: np.ndarray
    dielectric_clamped: np.ndarray
    dielectric_relaxed: np.ndarray
    piezo: np.ndarray
    piezo_clamped: np.ndarray

    @property
    def piezo_improper(self) -> np.ndarray:
        """Improper piezoelectric tensor e_ijk (3, 3, 3), e/Å² (:func:`improper_piezo`)."""
        return improper_piezo(self.piezo, self.polarization)

    def as_dict(self) -> dict:
        """All tensors in report units: GPa, C/m², pm/V (and dimensionless dielectric)."""
        return {
            "volume_A3": self.volume,
            "polarization_C_per_m2": (self.polarization * E_PER_A2_IN_C_PER_M2).tolist(),
            "stiffness_voigt_GPa": (self.stiffness_voigt * EV_PER_A3_IN_GPA).tolist(),
            "stiffness_clamped_ion_voigt_GPa": (
                voigt_stiffness(self.stiffness_clamped) * EV_PER_A3_IN_GPA).tolist(),
            "dielectric_ion_clamped": self.dielectric_clamped.tolist(),
            "dielectric_relaxed": self.dielectric_relaxed.tolist(),
            "piezo_e_voigt_C_per_m2": (self.piezo_voigt * E_PER_A2_IN_C_PER_M2).tolist(),
            "piezo_e_clamped_ion_voigt_C_per_m2": (
                voigt_piezo(self.piezo_clamped) * E_PER_A2_IN_C_PER_M2).tolist(),
            "piezo_e_proper_C_per_m2": (self.piezo * E_PER_A2_IN_C_PER_M2).tolist(),
            "piezo_e_improper_C_per_m2": (
                self.piezo_improper * E_PER_A2_IN_C_PER_M2).tolist(),
            "piezo_d_voigt_pm_per_V": (
                self.strain_constants_voigt * A_PER_V_IN_PM_PER_V).tolist(),
            "conventions": (
                "Voigt 1..6 = xx yy zz yz xz xy; strain S4 = 2 eps_yz (engineering); "
                "e proper (Vanderbilt): e~_ijk = e_ijk + delta_jk P_i - delta_ik P_j; "
                "d = e : C^-1 (relaxed-ion C at zero field)"
            ),
        }

    def text(self) -> str:
        """The tables of the paper's beta-glycine section (and the full tensors)."""
        d = self.as_dict()
        eps, c = np.array(d["dielectric_ion_clamped"]), np.array(d["stiffness_voigt_GPa"])
        e, dd = np.array(d["piezo_e_voigt_C_per_m2"]), np.array(d["piezo_d_voigt_pm_per_V"])
        lines = [f"volume {self.volume:.3f} Å^3", "Dielectric constants (ion-clamped)"]
        lines += [f"  eps_{i + 1}{i + 1} {eps[i, i]:10.4f}" for i in range(3)]
        lines.append("Stiffness constants [GPa] (relaxed ions)")
        lines += [f"  C_{i + 1}{i + 1} {c[i, i]:10.3f}" for i in range(6)]
        lines.append("Piezoelectric charge constants [C/m^2] (proper, relaxed ions)")
        lines += [f"  e_{i + 1}{j + 1} {e[i, j]:10.4f}" for i in range(3) for j in range(6)]
        lines.append("Piezoelectric strain constants [pm/V] (d = e : C^-1)")
        lines += [f"  d_{i + 1}{j + 1} {dd[i, j]:10.3f}" for i in range(3) for j in range(6)]
        for key, unit in (("dielectric_ion_clamped", ""), ("dielectric_relaxed", ""),
                          ("stiffness_voigt_GPa", ""), ("stiffness_clamped_ion_voigt_GPa", ""),
                          ("piezo_e_voigt_C_per_m2", ""), ("piezo_d_voigt_pm_per_V", "")):
            lines.append(f"{key}{unit}:")
            lines += ["  " + _vec(row, "{:11.4f}") for row in np.array(d[key])]
        return "\n".join(lines)


def crystal_response_from_hessian(hessian: np.ndarray, structure: Structure) -> CrystalResponse:
    """All crystal tensors from the extended Hessian (fractional coords, cell, field) of
    ``structure`` (whose internal coordinates should be relaxed: zero fractional gradient)."""
    if not structure.pbc:
        raise ValueError(f"{structure.source}: crystal_response needs a periodic structure")
    nc, n = structure.n_cores, structure.n_cores + structure.n_pairs
    frac = np.arange(3 * n)
    pairs = np.arange(3 * nc, 3 * n)
    cell_idx = np.arange(3 * n, 3 * n + 9)
    field_idx = np.arange(3 * n + 9, 3 * n + 12)
    keep = np.concatenate([cell_idx, field_idx])
    a = structure.cell
    volume = structure.volume
    basis = internal_basis(rigid_body_modes(np.zeros((n, 3)), rotations=False))
    h_fa = 0.5 * (hessian[np.ix_(field_idx, cell_idx)] + hessian[np.ix_(cell_idx, field_idx)].T)

    def tensors(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s_aa = s[:9, :9].reshape(3, 3, 3, 3)  # [m, j, n, l]
        stiffness = np.einsum("mi,nk,mjnl->ijkl", a, a, s_aa) / volume
        alpha = -s[9:, 9:]
        coupling = (h_fa - s[9:, :9]).reshape(3, 3, 3)  # [i, m, k]
        piezo = np.einsum("mj,imk->ijk", a, coupling) / volume
        return stiffness, alpha, piezo

    relaxed = tensors(schur_complement(hessian, keep, frac, basis))
    clamped = tensors(schur_complement(hessian, keep, pairs))
    chi = 1.0 / (volume * EPSILON0_E_PER_V_A)
    return CrystalResponse(
        volume=volume,
        polarization=structure.dipole() / volume,
        stiffness=relaxed[0],
        stiffness_clamped=clamped[0],
        dielectric_clamped=np.eye(3) + chi * clamped[1],
        dielectric_relaxed=np.eye(3) + chi * relaxed[1],
        piezo=relaxed[2],
        piezo_clamped=clamped[2],
    )


def crystal_response(model: EMLP, structure: Structure) -> CrystalResponse:
    """Stiffness, dielectric and piezoelectric tensors of a crystal at its given geometry
    (relax pairs and positions first, see :func:`emlpack.properties.optimize.optimize`)."""
    _, h = extended_hessian(model, structure)
    return crystal_response_from_hessian(h.numpy(), structure)


def _vec(v: np.ndarray, fmt: str = "{:10.5f}") -> str:
    return " ".join(fmt.format(x) for x in np.asarray(v))
