"""The extended Hessian of the eMLP energy (paper, appendix A): the one home of its
construction; the response properties built on it are in :mod:`emlpack.properties.response`.

The extended Hessian differentiates the total energy (short range + electrostatics + field
term) twice with respect to

* crystals: the fractional coordinates ``s`` of all particles (cores first, then pairs;
  ``r = s @ cell``), the 9 cell components (row-major, rows = lattice vectors, Å) and the 3
  field components;
* molecules: the Cartesian positions (Å) of all particles and the 3 field components.

The field is in V/Å; multiply the field rows/columns by ``units.FIELD_AU_IN_V_PER_A`` for a
field in atomic units. The neighbour list and the Ewald k set are frozen at the input geometry.
"""

from __future__ import annotations

import torch

from emlpack.nn.electrostatics import (
    coulomb_molecular_hessian,
    ewald_reciprocal_hessian_fractional,
)
from emlpack.nn.graph import Graph
from emlpack.nn.potential import EMLP
from emlpack.nn.scatter import pair_blocks_to_matrix, segment_sum
from emlpack.nn.schnet_hessian import schnet_edge_hessian
from emlpack.structure import Structure


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
        if standard_energy(model):
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


def standard_energy(model: EMLP) -> bool:
    """Whether ``model``'s energy is EMLP's own (SchNet + electrostatics + field), the energy
    that the fast Hessians here differentiate."""
    cls = type(model)
    return cls.energy is EMLP.energy and cls.energy_parts is EMLP.energy_parts


def short_range_position_hessian(model: EMLP, g: Graph, particles: torch.Tensor,
                                 mixed: bool = False) -> torch.Tensor:
    """Exact Hessian (eV/Å²) of the SchNet energy of the one structure of ``g`` (at
    ``g.positions``, neighbour list as given) in the Cartesian positions of ``particles`` (k,),
    the other particles and the cell held: shape (3k, 3k), particle by particle, x y z.

    The fast method of :func:`extended_hessian` with only these directions: its cost grows
    with 3k instead of the 3N + 3 extended variables (the pair block of a molecule, for the
    pair relaxation's Newton steps). Molecules and crystals at fixed cell alike: with the cell
    held, ``dr_e/dx`` and ``d2r_e/dx2`` are the molecular ones of the image-shifted edge
    vectors. ``mixed``: the directional derivatives in float32 (as in :func:`extended_hessian`).
    """
    n = g.n_particles
    cols = (3 * particles[:, None] + torch.arange(3, device=particles.device)).reshape(-1)
    with torch.no_grad():
        r0, jac, geometric = _edge_derivatives(model, g, g.positions.reshape(-1), pbc=False)
        grad_r, h_sr = schnet_edge_hessian(
            model.schnet, g.numbers, r0, g.edge_i, g.edge_j, jac[:, cols],
            tangent_dtype=torch.float32 if mixed else None,
        )
        if len(cols) == 3 * n:
            return h_sr + geometric(grad_r)
        return h_sr + geometric(grad_r)[cols][:, cols]


def _edge_derivatives(model: EMLP, g: Graph, x0: torch.Tensor, pbc: bool):
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


