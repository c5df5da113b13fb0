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
from emlpack.nn.short_range.hessian import (
    geometric_variables,
    short_range_hessian,
    short_range_position_hessian,
)
from emlpack.structure import Structure


# ---------------------------------------------------------------------- extended Hessian
def _energy_function(model: EMLP, structure: Structure, dtype: torch.dtype):
    g = model.graph(structure, dtype=dtype)
    if structure.pbc:
        cell0 = g.cell[0]
        frac0 = torch.linalg.solve(cell0.T, g.positions.T).T
        x0 = torch.cat([frac0.reshape(-1), cell0.reshape(-1), g.field[0]])
    else:
        x0 = torch.cat([g.positions.reshape(-1), g.field[0]])

    def energy(x: torch.Tensor) -> torch.Tensor:
        pos, cell = geometric_variables(g, x[:-3], structure.pbc)
        return model.energy(g, pos, cell if structure.pbc else None, x[-3:][None])[0]

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

    * the short range: :func:`emlpack.nn.short_range.hessian.short_range_hessian`; for SchNet
      (capability :class:`~emlpack.nn.short_range.protocol.LengthHessian`)
      :func:`emlpack.nn.short_range.schnet_hessian.schnet_edge_hessian` (filters replaced by
      their exact second-order Taylor expansion in the edge lengths, all directions batched
      in node space) plus ``sum_e dE/dr_e d2r_e/dx2``, for other families reverse over
      reverse on the short-range energy alone;
    * electrostatics in closed form: molecular Gaussian Coulomb
      (:func:`~emlpack.nn.electrostatics.coulomb_molecular_hessian`) or reciprocal Ewald in
      fractional coordinates and cell
      (:func:`~emlpack.nn.electrostatics.ewald_reciprocal_hessian_fractional`);
    * the field term (linear in the field): its blocks written out.

    ``mixed=True`` (fast method with SchNet only, opt-in): the SchNet directional derivatives
    in float32,
    1.3-1.6x faster again. Measured largest relative changes of the reported tensors
    (docs/response.md): crystal tensors (eps, C, e, d) <= 4.3e-7; IR frequencies <= 3e-8,
    intensities <= 1.3e-6; polarizability with relaxed cores 1.0e-5 (trained model, hexane:
    the float32 error grows as 1/omega^2 of the softest modes).

    Models whose energy is not EMLP's composition (:func:`standard_energy`: e.g. test toys
    with extra terms) get the reference method, which differentiates whatever energy they
    define.

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
    """Whether ``model``'s energy is EMLP's composition (short range of its family +
    electrostatics + field term, :meth:`EMLP.energy_parts`), the sum whose parts the closed
    forms here and in the pair relaxation differentiate separately. A model that redefines
    ``energy`` or ``energy_parts`` (a subclass adding a term) is differentiated as a whole
    instead; which short-range family the model has does not matter here (its capabilities
    are asked where they are used)."""
    cls = type(model)
    return cls.energy is EMLP.energy and cls.energy_parts is EMLP.energy_parts


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
    h_sr = short_range_hessian(model, g, x0[:m], structure.pbc, mixed=mixed)
    with torch.no_grad():
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
        hess[:m, :m] += h_sr + h_lr.to(hess.dtype)
    return grad, hess


def clamped_pair_hessian(model: EMLP, g: Graph) -> torch.Tensor:
    """The pair block (3P, 3P) (eV/Å², pair by pair, x y z; float64, no graph) of the molecular
    extended Hessian of the one molecule of ``g`` at ``g.positions``: the pairs' position
    Hessian of the total energy with the cores clamped, from the same parts as
    :func:`extended_hessian`'s fast method (the short range's pair directions,
    :func:`~emlpack.nn.short_range.hessian.short_range_position_hessian`, in ``g``'s dtype,
    plus the analytic Gaussian Coulomb block; the field term is linear in the positions and
    adds nothing). The training loss's polarizability term takes it at the labelled pairs
    (:func:`emlpack.properties.response.clamped_polarizabilities`)."""
    if g.n_structures != 1 or bool(g.pbc.any()):
        raise ValueError("clamped_pair_hessian: one molecule per graph")
    if not standard_energy(model):
        raise ValueError(f"clamped_pair_hessian: {type(model).__name__} defines its own"
                         " energy; its pair Hessian has no closed-form parts")
    pairs = torch.nonzero(g.is_pair).squeeze(1)
    h_sr = short_range_position_hessian(model, g, pairs).double()
    with torch.no_grad():
        c = model.config
        h_lr = coulomb_molecular_hessian(g.positions.detach().double(), g.charges.double(),
                                         g.coulomb_i, g.coulomb_j, c.gamma, c.coulomb_eps)
        cols = (3 * pairs[:, None] + torch.arange(3, device=pairs.device)).reshape(-1)
        return h_sr + h_lr[cols][:, cols]
