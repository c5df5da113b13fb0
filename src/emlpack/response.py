"""Hessians of the eMLP energy and the response properties built on them (paper, appendix A).

The extended Hessian differentiates the total energy (short range + electrostatics + field
term) twice with respect to

* crystals: the fractional coordinates ``s`` of all particles (cores first, then pairs;
  ``r = s @ cell``), the 9 cell components (row-major, rows = lattice vectors, Å) and the 3
  field components;
* molecules: the Cartesian positions (Å) of all particles and the 3 field components.

The field is in V/Å; multiply the field rows/columns by ``units.FIELD_AU_IN_V_PER_A`` for a
field in atomic units. The neighbour list and the Ewald k set are frozen at the input geometry.

Every response property is a Schur complement of this matrix: eliminating a block ``x``
(relaxing those coordinates at zero gradient) leaves ``S = H_yy - H_yx H_xx^-1 H_xy`` for the
remaining variables ``y``. With the sign of the field term (``E_field = -mu . F``):

* polarizability ``alpha = -d2E/dF2 = H_Fx H_xx^-1 H_xF`` (``H_FF = 0``), e·Å²/V; ``x`` = pairs
  (clamped cores, the paper's main text) or pairs + cores (rigid-body motions projected out);
* Born-Oppenheimer core Hessian ``S_cc`` and dipole derivatives ``dmu/dR = -S_Fc`` (pairs
  eliminated), for IR spectra (:mod:`emlpack.spectra`);
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
    internal_basis,
    rigid_body_modes,
    schur_complement,
    voigt_piezo,
    voigt_stiffness,
)
from emlpack.nn.electrostatics import (
    coulomb_molecular_hessian,
    ewald_reciprocal_hessian_fractional,
)
from emlpack.nn.potential import EMLP
from emlpack.nn.scatter import pair_blocks_to_matrix, segment_sum
from emlpack.nn.schnet_hessian import schnet_edge_hessian
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


# ---------------------------------------------------------------------- extended Hessian
def _energy_function(model: EMLP, structure: Structure, dtype: torch.dtype):
    g = model.graph(structure, dtype=dtype)
    n = g.n_particles
    if structure.pbc:
        cell0 = g.cell[0]
        frac0 = torch.linalg.solve(cell0.T, g.positions.T).T
        x0 = torch.cat([frac0.reshape(-1), cell0.reshape(-1), g.field[0]])

        def energy(x: torch.Tensor) -> torch.Tensor:
            cell = x[3 * n : 3 * n + 9].reshape(3, 3)
            pos = x[: 3 * n].reshape(n, 3) @ cell
            return model.energy(g, pos, cell[None], x[3 * n + 9 :][None])[0]

    else:
        x0 = torch.cat([g.positions.reshape(-1), g.field[0]])

        def energy(x: torch.Tensor) -> torch.Tensor:
            return model.energy(g, x[: 3 * n].reshape(n, 3), None, x[3 * n :][None])[0]

    return energy, x0.detach()


def extended_gradient(
    model: EMLP, structure: Structure, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Gradient of the energy (eV) in the extended variables (see :func:`extended_hessian`)."""
    energy, x0 = _energy_function(model, structure, dtype)
    x = x0.requires_grad_(True)
    return torch.autograd.grad(energy(x), x)[0].detach()


def extended_hessian(
    model: EMLP,
    structure: Structure,
    dtype: torch.dtype = torch.float64,
    method: str = "fast",
    mixed: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradient and Hessian of the energy (eV) in the extended variables of ``structure``.

    Returns ``(gradient, hessian)`` of sizes ``3N + 12`` (crystal: fractional coordinates,
    cell, field) or ``3N + 3`` (molecule: Cartesian positions, field), N = cores + pairs.

    ``method="fast"`` (default): the energy's parts separately, each exactly
    (equal to ``"reference"`` to ~1e-12 relative):

    * SchNet: :func:`emlpack.nn.schnet_hessian.schnet_edge_hessian` (filters replaced by their
      exact second-order Taylor expansion in the edge lengths, all directions batched in node
      space) plus ``sum_e dE/dr_e d2r_e/dx2``;
    * electrostatics in closed form: molecular Gaussian Coulomb
      (:func:`~emlpack.nn.electrostatics.coulomb_molecular_hessian`) or reciprocal Ewald in
      fractional coordinates and cell
      (:func:`~emlpack.nn.electrostatics.ewald_reciprocal_hessian_fractional`);
    * the field term (linear in the field): its blocks written out.

    ``mixed=True`` (fast method only, opt-in): the SchNet directional derivatives in float32,
    1.3-1.6x faster again. Measured largest relative changes of the reported tensors
    (docs/response.md): crystal tensors (eps, C, e, d) <= 4.3e-7; IR frequencies <= 3e-8,
    intensities <= 1.3e-6; polarizability with relaxed cores 1.0e-5 (trained model, hexane:
    the float32 error grows as 1/omega^2 of the softest modes).

    Models whose class overrides ``EMLP.energy`` or ``energy_parts`` (e.g. test toys with
    extra terms) get the reference method, which differentiates whatever energy they define.

    ``method="reference"`` (alias ``"loop"``): one graph with ``create_graph`` and one reverse
    pass per non-field row of the whole energy (reverse over reverse, filter network
    included); the field rows follow from symmetry and the field-field block is exactly 0.
    ``method="vmap"``: every row by ``torch.func.hessian`` (forward over reverse, vectorised).
    """
    if method == "fast":
        if _standard_energy(model):
            return _extended_hessian_fast(model, structure, dtype, mixed)
        method = "reference"  # a subclass with its own energy: differentiate it as it is
    energy, x0 = _energy_function(model, structure, dtype)
    if method == "vmap":
        x = x0.clone().requires_grad_(True)
        grad = torch.autograd.grad(energy(x), x)[0]
        return grad.detach(), torch.func.hessian(energy)(x0).detach()
    if method not in ("reference", "loop"):
        raise ValueError(
            f"extended_hessian: unknown method {method!r} (fast, reference, vmap)"
        )
    x = x0.clone().requires_grad_(True)
    grad = torch.autograd.grad(energy(x), x, create_graph=True)[0]
    m = len(x0)
    n_rows = m - 3
    hess = x0.new_zeros(m, m)
    for k in range(n_rows):
        (row,) = torch.autograd.grad(
            grad[k], x, retain_graph=k < n_rows - 1, materialize_grads=True
        )
        hess[k] = row.detach()
    hess[n_rows:, :n_rows] = hess[:n_rows, n_rows:].T
    return grad.detach(), hess


def _standard_energy(model: EMLP) -> bool:
    """Whether ``model``'s energy is EMLP's own (SchNet + electrostatics + field)."""
    cls = type(model)
    return cls.energy is EMLP.energy and cls.energy_parts is EMLP.energy_parts


def _edge_derivatives(model: EMLP, g, x0: torch.Tensor, pbc: bool):
    """Edge lengths ``r`` (E,), their Jacobian ``dr/dx`` (E, m) in the geometric extended
    variables ``x`` (positions, or fractional coordinates and cell) and a function
    ``w -> sum_e w_e d2r_e/dx2`` (m, m).

    ``r = |d|`` with ``d = x_j - x_i`` (molecules) or ``d = (s_j - s_i + shift) A``
    (crystals): ``dr/dd = u = d/r``, ``d2r/dd2 = (1 - u u^T)/r``; for crystals ``dr/ds_j = A u``,
    ``dr/dA_ab = f_a u_b`` (``f = s_j - s_i + shift``) and ``d2d_b/ds_ja dA_a'c = delta_aa'
    delta_bc``.
    """
    n = g.n_particles
    i, j = g.edge_i, g.edge_j
    n_edges = i.numel()
    if pbc:
        cell = x0[3 * n : 3 * n + 9].reshape(3, 3)
        frac = x0[: 3 * n].reshape(n, 3)
        pos = frac @ cell
        f = frac[j] - frac[i] + g.edge_shift
        m = 3 * n + 9
    else:
        cell = None
        pos = x0[: 3 * n].reshape(n, 3)
        m = 3 * n
    d = model.edge_vectors(g, pos, g.cell if cell is None else cell[None])
    r = torch.sqrt((d * d).sum(-1) + 1e-20)
    u = d / r[:, None]
    v = u @ cell.T if pbc else u  # dr/dx_j
    jac = x0.new_zeros(n_edges, m)
    rows = torch.arange(n_edges, device=x0.device)[:, None]
    xyz = torch.arange(3, device=x0.device)
    jac.index_put_((rows, 3 * j[:, None] + xyz), v, accumulate=True)
    jac.index_put_((rows, 3 * i[:, None] + xyz), -v, accumulate=True)
    if pbc:
        jac[:, 3 * n :] = (f[:, :, None] * u[:, None, :]).reshape(n_edges, 9)
    eye = torch.eye(3, dtype=x0.dtype, device=x0.device)

    def geometric(w: torch.Tensor) -> torch.Tensor:
        k = (w / r)[:, None, None] * (eye - u[:, :, None] * u[:, None, :])  # (E, 3, 3)
        out = x0.new_zeros(m, m)
        if not pbc:
            out[:] = pair_blocks_to_matrix(k, i, j, n)
            return out
        out[: 3 * n, : 3 * n] = pair_blocks_to_matrix(cell @ k @ cell.T, i, j, n)
        # position-cell: d2r/ds_ja dA_a'c = (A K)_ac f_a' + w u_c delta_aa'
        t = torch.einsum("eac,eb->eabc", cell @ k, f)
        t = t + torch.einsum("ab,ec->eabc", eye, w[:, None] * u)
        mixed = segment_sum(torch.cat([t, -t]).reshape(2 * n_edges, 3, 9),
                            torch.cat([j, i]), n).reshape(3 * n, 9)
        out[: 3 * n, 3 * n :] = mixed
        out[3 * n :, : 3 * n] = mixed.T
        out[3 * n :, 3 * n :] = torch.einsum("ea,ebd,ec->abcd", f, k, f).reshape(9, 9)
        return out

    return r, jac, geometric


def _field_hessian(x0: torch.Tensor, charges: torch.Tensor, n: int, pbc: bool) -> torch.Tensor:
    """Second derivatives of ``E_field = -sum_i q_i F . r_i`` (linear in F) in the extended
    variables: (positions, F) or (fractional coordinates, cell, F)."""
    size = len(x0)
    out = x0.new_zeros(size, size)
    eye = torch.eye(3, dtype=x0.dtype, device=x0.device)
    if not pbc:
        block = -torch.kron(charges[:, None], eye)  # d2E/dr_ia dF_b = -q_i delta_ab
        out[: 3 * n, 3 * n :] = block
        out[3 * n :, : 3 * n] = block.T
        return out
    frac = x0[: 3 * n].reshape(n, 3)
    cell = x0[3 * n : 3 * n + 9].reshape(3, 3)
    field = x0[3 * n + 9 :]
    f0, f1 = 3 * n + 9, 3 * n + 12
    block = -(charges[:, None, None] * cell[None]).reshape(3 * n, 3)  # -q_i A_ab
    dip = charges @ frac  # d2E/dA_ab dF_c = -delta_bc sum_i q_i s_ia
    cell_field = -torch.einsum("a,bc->abc", dip, eye).reshape(9, 3)
    # d2E/ds_ia dA_a'b = -q_i F_b delta_aa'
    frac_cell = -torch.einsum("i,ac,b->iacb", charges, eye, field).reshape(3 * n, 9)
    out[: 3 * n, f0:f1] = block
    out[3 * n : f0, f0:f1] = cell_field
    out[: 3 * n, 3 * n : f0] = frac_cell
    out[f0:f1, : f0] = out[: f0, f0:f1].T
    out[3 * n : f0, : 3 * n] = frac_cell.T
    return out


def _extended_hessian_fast(
    model: EMLP, structure: Structure, dtype: torch.dtype, mixed: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """``method="fast"`` of :func:`extended_hessian`."""
    energy, x0 = _energy_function(model, structure, dtype)
    g = model.graph(structure, dtype=dtype)
    n = g.n_particles
    m = len(x0) - 3  # geometric variables (positions or fractional coordinates + cell)
    c = model.config
    x = x0.clone().requires_grad_(True)
    with torch.enable_grad():
        grad = torch.autograd.grad(energy(x), x)[0].detach()
    with torch.no_grad():
        r0, jac, geometric = _edge_derivatives(model, g, x0, structure.pbc)
        grad_r, h_sr = schnet_edge_hessian(
            model.schnet, g.numbers, r0, g.edge_i, g.edge_j, jac,
            tangent_dtype=torch.float32 if mixed else None,
        )
        q64 = g.charges.double()
        if structure.pbc:
            _, h_lr = ewald_reciprocal_hessian_fractional(
                x0[: 3 * n].reshape(n, 3).double(), q64,
                x0[3 * n : 3 * n + 9].reshape(3, 3).double(), g.kvec_n.double(), c.gamma,
            )
        else:
            h_lr = coulomb_molecular_hessian(
                x0[: 3 * n].reshape(n, 3).double(), q64, g.coulomb_i, g.coulomb_j, c.gamma,
                c.coulomb_eps,
            )
        hess = _field_hessian(x0, g.charges, n, structure.pbc)
        hess[:m, :m] += h_sr + geometric(grad_r) + h_lr.to(hess.dtype)
    return grad, hess


# ---------------------------------------------------------------------- molecules
def _molecule_layout(structure: Structure) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices of core, pair and field variables of the molecular extended Hessian."""
    nc, n = structure.n_cores, structure.n_cores + structure.n_pairs
    return np.arange(3 * nc), np.arange(3 * nc, 3 * n), np.arange(3 * n, 3 * n + 3)


def polarizability_from_hessian(
    hessian: np.ndarray, structure: Structure, relax_cores: bool = False
) -> np.ndarray:
    """Static polarizability alpha_ij = -d2E/dF_i dF_j (e·Å²/V) of a molecule.

    ``relax_cores=False``: pairs relaxed at clamped cores (electronic, the paper's main text);
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
    return -schur_complement(hessian, field, pairs)


def born_oppenheimer_blocks(
    hessian: np.ndarray, structure: Structure
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs eliminated: core Hessian (3Nc, 3Nc) eV/Å², dipole derivatives dmu_a/dR_ib
    (3, 3Nc) e, and clamped-core polarizability (3, 3) e·Å²/V, of a molecule."""
    cores, pairs, field = _molecule_layout(structure)
    keep = np.concatenate([cores, field])
    s = schur_complement(hessian, keep, pairs)
    nc = len(cores)
    return s[:nc, :nc], -s[nc:, :nc], -s[nc:, nc:]


@dataclass
class MoleculeResponse:
    """Dipole and polarizabilities of a molecule (e·Å, e·Å²/V)."""

    dipole: np.ndarray
    polarizability: np.ndarray
    polarizability_relaxed: np.ndarray | None = None

    def as_dict(self) -> dict:
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
    h = h.numpy()
    return MoleculeResponse(
        dipole=structure.dipole(),
        polarizability=polarizability_from_hessian(h, structure),
        polarizability_relaxed=(
            polarizability_from_hessian(h, structure, relax_cores=True) if relax_cores else None
        ),
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
    (relax pairs and positions first, see :func:`emlpack.optimize.optimize`)."""
    _, h = extended_hessian(model, structure)
    return crystal_response_from_hessian(h.numpy(), structure)


def _vec(v, fmt: str = "{:10.5f}") -> str:
    return " ".join(fmt.format(x) for x in np.asarray(v))
