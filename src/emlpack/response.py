"""Hessians of the eMLP energy and the response properties built on them.

The extended Hessian differentiates the total energy (short range + electrostatics + field
term) twice with respect to

* crystals: the fractional coordinates ``s`` of all particles (cores first, then pairs;
  ``r = s @ cell``), the 9 cell components (row-major, rows = lattice vectors, Å) and the 3
  field components;
* molecules: the Cartesian positions (Å) of all particles and the 3 field components.

The field is in V/Å; multiply the field rows/columns by ``units.FIELD_AU_IN_V_PER_A`` for a
field in atomic units. The neighbour list and the Ewald k set are frozen at the input geometry.
All second derivatives are computed in one vectorised call (no Python loop over rows).
"""

from __future__ import annotations

import torch

from emlpack.nn.potential import EMLP
from emlpack.structure import Structure


def _hessian(fn, x: torch.Tensor) -> torch.Tensor:
    return torch.func.hessian(fn)(x)


def extended_hessian(
    model: EMLP, structure: Structure, dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradient and Hessian of the energy (eV) in the extended variables of ``structure``.

    Returns ``(gradient, hessian)`` of sizes ``3N + 12`` (crystal: fractional coordinates,
    cell, field) or ``3N + 3`` (molecule: Cartesian positions, field), N = cores + pairs.
    """
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

    x = x0.detach().requires_grad_(True)
    grad = torch.autograd.grad(energy(x), x)[0]
    return grad.detach(), _hessian(energy, x0.detach()).detach()
