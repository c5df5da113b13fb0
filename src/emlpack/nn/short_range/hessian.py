"""Exact Hessians of the short-range energy of one structure, for every family.

The short-range energy ``E_sr(x)`` of one structure is differentiated twice in its geometric
variables ``x``: the Cartesian positions of all particles (molecules, or crystals at fixed
cell), or the fractional coordinates and the 9 cell components (crystals, ``r = s @ cell``,
rows = lattice vectors, Å). The neighbour list is the graph's, frozen.

* A family with the capability :class:`~emlpack.nn.short_range.protocol.LengthHessian`
  (SchNet) gives ``J^T (d2E/dr dr) J`` in the edge lengths ``r`` from the edge Jacobian
  ``J = dr/dx`` (:func:`edge_derivatives`); the geometric term ``sum_e dE/dr_e d2r_e/dx2``
  is added here.
* Any other family: reverse over reverse on ``E_sr`` (one reverse pass of the gradient's
  graph per row), exact as well.

:func:`short_range_curvatures` gives the curvatures along a few directions of every
structure of a batch instead, with the graph to the model's parameters kept when asked (the
training loss's polarizability term differentiates them).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch

from emlpack.nn.scatter import pair_blocks_to_matrix, segment_sum
from emlpack.nn.short_range.common import edge_lengths
from emlpack.nn.short_range.protocol import LengthHessian

if TYPE_CHECKING:
    from emlpack.nn.graph import Graph
    from emlpack.nn.potential import EMLP

__all__ = ["edge_derivatives", "geometric_variables", "short_range_curvatures",
           "short_range_hessian", "short_range_position_hessian"]


def geometric_variables(
    g: Graph, x: torch.Tensor, pbc: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (N, 3) (Å) and cell (1, 3, 3) of the one structure of ``g`` at the geometric
    variables ``x``: Cartesian positions (3N,), or with ``pbc`` fractional coordinates and
    the cell (3N + 9,) (``r = s @ cell``)."""
    n = g.n_particles
    if pbc:
        cell = x[3 * n : 3 * n + 9].reshape(3, 3)
        return x[: 3 * n].reshape(n, 3) @ cell, cell[None]
    return x[: 3 * n].reshape(n, 3), g.cell


def edge_derivatives(
    model: EMLP, g: Graph, x0: torch.Tensor, pbc: bool
) -> tuple[torch.Tensor, torch.Tensor, Callable[[torch.Tensor], torch.Tensor]]:
    """Edge lengths ``r`` (E,), their Jacobian ``dr/dx`` (E, m) in the geometric variables
    ``x`` (see :func:`geometric_variables`; m = 3N or 3N + 9) and a function
    ``w -> sum_e w_e d2r_e/dx2`` (m, m).

    ``r = |d|`` with ``d = x_j - x_i`` (molecules) or ``d = (s_j - s_i + shift) A``
    (crystals): ``dr/dd = u = d/r``, ``d2r/dd2 = (1 - u u^T)/r``; for crystals ``dr/ds_j = A u``,
    ``dr/dA_ab = f_a u_b`` (``f = s_j - s_i + shift``) and ``d2d_b/ds_ja dA_a'c = delta_aa'
    delta_bc``.
    """
    n = g.n_particles
    i, j = g.edge_i, g.edge_j
    n_edges = i.numel()
    pos, cell3 = geometric_variables(g, x0, pbc)
    if pbc:
        cell = cell3[0]
        frac = x0[: 3 * n].reshape(n, 3)
        f = frac[j] - frac[i] + g.edge_shift
        m = 3 * n + 9
    else:
        cell = None
        m = 3 * n
    d = model.edge_vectors(g, pos, cell3)
    r = edge_lengths(d)
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


def short_range_hessian(
    model: EMLP,
    g: Graph,
    x0: torch.Tensor,
    pbc: bool,
    columns: torch.Tensor | None = None,
    mixed: bool = False,
) -> torch.Tensor:
    """Exact Hessian (eV per unit of ``x`` squared) of the short-range energy of the one
    structure of ``g`` in its geometric variables ``x0`` (see :func:`geometric_variables`),
    restricted to the variables ``columns`` (indices; None: all): shape (c, c).

    With :class:`~emlpack.nn.short_range.protocol.LengthHessian` (SchNet) in edge-length
    space, ``mixed``: its directional derivatives in float32 (see
    :func:`emlpack.properties.hessian.extended_hessian`); any other family by reverse over
    reverse (``mixed`` does not apply)."""
    sr = model.short_range
    if isinstance(sr, LengthHessian):
        with torch.no_grad():
            r0, jac, geometric = edge_derivatives(model, g, x0, pbc)
            cols = slice(None) if columns is None else columns
            grad_r, h_sr = sr.length_hessian(
                g.numbers, r0, g.edge_i, g.edge_j, jac[:, cols],
                tangent_dtype=torch.float32 if mixed else None,
            )
            if columns is None or len(columns) == len(x0):
                return h_sr + geometric(grad_r)
            return h_sr + geometric(grad_r)[columns][:, columns]
    return _reverse_over_reverse(model, g, x0, pbc, columns)


def _reverse_over_reverse(
    model: EMLP, g: Graph, x0: torch.Tensor, pbc: bool, columns: torch.Tensor | None
) -> torch.Tensor:
    """The generic path of :func:`short_range_hessian`: one graph of the gradient, one
    reverse pass of it per row."""
    x0 = x0.detach()
    cols = torch.arange(len(x0), device=x0.device) if columns is None else columns
    with torch.enable_grad():
        xs = x0[cols].clone().requires_grad_(True)
        pos, cell = geometric_variables(g, x0.index_put((cols,), xs), pbc)
        energy = model.atomic_energies(g, pos, cell).sum()
        hess = x0.new_zeros(len(cols), len(cols))
        if not energy.requires_grad:  # no dependence on the geometry at all
            return hess
        (grad,) = torch.autograd.grad(energy, xs, create_graph=True)
        if not grad.requires_grad:  # linear in x: no curvature
            return hess
        for k in range(len(cols)):
            (row,) = torch.autograd.grad(grad[k], xs, retain_graph=k < len(cols) - 1,
                                         materialize_grads=True)
            hess[k] = row.detach()
    return hess


def short_range_position_hessian(model: EMLP, g: Graph, particles: torch.Tensor,
                                 mixed: bool = False) -> torch.Tensor:
    """Exact Hessian (eV/Å²) of the short-range energy of the one structure of ``g`` (at
    ``g.positions``, neighbour list as given) in the Cartesian positions of ``particles``
    (k,), the other particles and the cell held: shape (3k, 3k), particle by particle, x y z.

    :func:`short_range_hessian` with only these directions: its cost grows with 3k instead
    of the 3N + 3 extended variables (the pair block of a molecule, for the pair
    relaxation's Newton steps). Molecules and crystals at fixed cell alike: with the cell
    held, ``dr_e/dx`` and ``d2r_e/dx2`` are the molecular ones of the image-shifted edge
    vectors. ``mixed``: see :func:`short_range_hessian`.
    """
    cols = (3 * particles[:, None] + torch.arange(3, device=particles.device)).reshape(-1)
    return short_range_hessian(model, g, g.positions.detach().reshape(-1), pbc=False,
                               columns=cols, mixed=mixed)


def short_range_curvatures(model: EMLP, g: Graph, directions: torch.Tensor,
                           create_graph: bool = False) -> torch.Tensor:
    """Curvatures ``M[b, a, c] = d_a^T H_b d_c`` (eV) of the short-range energy of every
    structure ``b`` of ``g`` along the displacements ``directions`` (k, N, 3) (Å) of its
    particles (``H_b``: its Cartesian position Hessian at ``g.positions``, cell held), shape
    (B, k, k).

    Reverse over reverse: one gradient graph and one reverse pass per direction for the whole
    batch (the structures' energies are independent, so the Hessian of their sum is block
    diagonal and each structure's part of ``H d_a`` is its own block's product).
    ``create_graph``: the result keeps its graph to the model's parameters (and is then a
    differentiable function of them)."""
    b = g.n_structures
    k = directions.shape[0]
    with torch.enable_grad():
        pos = g.positions.detach().requires_grad_(True)
        energy = model.atomic_energies(g, pos, g.cell).sum()
        if not energy.requires_grad:
            return pos.new_zeros(b, k, k)
        (grad,) = torch.autograd.grad(energy, pos, create_graph=True)
        if not grad.requires_grad:  # linear in the positions: no curvature
            return pos.new_zeros(b, k, k)
        dirs = directions.to(grad.dtype)
        products = []
        for a in range(k):
            (hv,) = torch.autograd.grad(grad, pos, dirs[a], create_graph=create_graph,
                                        retain_graph=True, materialize_grads=True)
            products.append(hv)
        hd = torch.stack(products)  # [k, N, 3]: H d_a
    per_particle = torch.einsum("anx,cnx->nac", hd, dirs)  # [N, k, k]
    return segment_sum(per_particle, g.batch, b)
