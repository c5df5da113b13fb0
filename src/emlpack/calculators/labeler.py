"""An eMLP wrapped as a labeler, and the model's Born-Oppenheimer Hessian for crystal sampling.

:class:`ModelLabeler` obeys the labeler protocol of :mod:`emlpack.properties.fd_reference` and the
CP2K labeler: ``labeler(structure, *, stress=False) -> Structure`` with the electron pairs
relaxed at fixed cores (Born-Oppenheimer, :func:`emlpack.pairs.relax.relax_pairs`), energy (eV,
field term included), core forces (eV/Å), stress (eV/Å³, ASE sign, only with ``stress=True``)
and the relaxed pairs (Å). Uses: the finite-difference reference tensors of a model (checked
against :func:`emlpack.properties.response.crystal_response`), fast stand-ins for DFT in tests, and
the active-learning loop.

:func:`bo_cell_hessian` is the Hessian (eV/Å²) of the Born-Oppenheimer energy of the cores in
(Cartesian core positions, 9 cell elements) with the pairs eliminated by a Schur complement:
the matrix :func:`emlpack.qm.sampling.cell_normal_mode_sample` samples from.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from emlpack.errors import EmlpackError
from emlpack.geometry import schur_complement
from emlpack.nn.potential import EMLP, for_evaluation
from emlpack.pairs.relax import RelaxOptions, relax_pairs
from emlpack.structure import Structure


class ModelLabelingError(EmlpackError, RuntimeError):
    """The electron pairs of a structure could not be relaxed with the model."""


class ModelLabeler:
    """An eMLP as a labeler (see the module docstring).

    Args:
        model: the eMLP (evaluated in float64).
        fmax: pair-force tolerance of the relaxation (eV/Å); finite differences need ~1e-8.
        level: text stored in ``info["level"]`` of the labeled structures.
    """

    def __init__(self, model: EMLP, fmax: float = 1e-8, level: str = "emlp",
                 max_iterations: int = 200) -> None:
        self.model = for_evaluation(model, torch.float64)  # the caller's model is not changed
        self.options = RelaxOptions(fmax=fmax, max_iterations=max_iterations)
        self.level = level

    def __call__(self, structure: Structure, *, stress: bool = False) -> Structure:
        """``structure`` with its pairs relaxed at fixed cores and the model's labels: energy (eV),
        core forces (eV/Å), zero pair forces and, with ``stress`` for a crystal, stress (eV/Å³);
        a failed relaxation raises :class:`ModelLabelingError`."""
        if stress and np.any(structure.field != 0):
            raise ValueError(f"{structure.source}: stress under a field is not defined")
        result = relax_pairs(self.model, structure, self.options)[0]
        if result.failed:
            raise ModelLabelingError(f"{structure.source}: pair relaxation failed:"
                                     f" {result.reason}")
        relaxed = structure.copy(pairs=result.pairs)
        out = self.model.evaluate(relaxed, stress=bool(stress and structure.pbc))
        info = dict(structure.info, level=self.level)
        return relaxed.copy(
            energy=out["energy"], forces=out["forces"],
            pair_forces=np.zeros_like(result.pairs),
            stress=out["stress"] if stress and structure.pbc else None, info=info)


def cartesian_cell_hessian(model: EMLP, structure: Structure) -> np.ndarray:
    """Hessian (eV/Å²) of the energy in the Cartesian positions of all particles (cores, then
    pairs) and the 9 cell elements (row-major; rows = lattice vectors), at fixed field."""
    g = model.graph(structure, dtype=torch.float64)
    n = g.n_particles
    x0 = torch.cat([g.positions.reshape(-1), g.cell[0].reshape(-1)]).detach()
    field = g.field

    def energy(x: torch.Tensor) -> torch.Tensor:
        return model.energy(g, x[: 3 * n].reshape(n, 3), x[3 * n:].reshape(1, 3, 3), field)[0]

    x = x0.clone().requires_grad_(True)
    grad = torch.autograd.grad(energy(x), x, create_graph=True)[0]
    m = len(x0)
    hess = np.zeros((m, m))
    for k in range(m):
        (row,) = torch.autograd.grad(grad[k], x, retain_graph=k < m - 1, materialize_grads=True)
        hess[k] = row.detach().numpy()
    return 0.5 * (hess + hess.T)


def bo_cell_hessian(model: EMLP, structure: Structure, fmax: float = 1e-6) -> np.ndarray:
    """Born-Oppenheimer Hessian (eV/Å²) in (core positions, cell), shape (3n_c+9, 3n_c+9):
    pairs relaxed at ``structure``'s cores and then eliminated (Schur complement)."""
    model = for_evaluation(model, torch.float64)
    result = relax_pairs(model, structure, RelaxOptions(fmax=fmax))[0]
    if result.failed:
        raise ModelLabelingError(f"{structure.source}: pair relaxation failed: {result.reason}")
    s = structure.copy(pairs=result.pairs)
    h = cartesian_cell_hessian(model, s)
    nc, n = s.n_cores, s.n_cores + s.n_pairs
    keep = np.concatenate([np.arange(3 * nc), np.arange(3 * n, 3 * n + 9)])
    return schur_complement(h, keep, np.arange(3 * nc, 3 * n))


def model_hessian_callable(model: EMLP, template: Structure
                           ) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``(core positions, cell) -> bo_cell_hessian`` for
    :func:`emlpack.qm.sampling.cell_normal_mode_sample`; pairs start from ``template``'s,
    moved with the cell (same fractional coordinates)."""

    def hessian(positions: np.ndarray, cell: np.ndarray) -> np.ndarray:
        frac = template.pairs @ np.linalg.inv(template.cell)
        s = template.copy(positions=np.asarray(positions, float), pairs=frac @ cell,
                          cell=np.asarray(cell, float), field=np.zeros(3))
        return bo_cell_hessian(model, s)

    return hessian
