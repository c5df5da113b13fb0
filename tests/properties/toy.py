"""Test models for the response tests: the eMLP plus harmonic springs.

:class:`SpringModel` adds ``sum_b k_b/2 (|d_b| - l_b)^2`` over fixed particle pairs ``b``
(``d_b = r_j - r_i + n_b . cell``) to the eMLP energy. Springs are rotation and translation
invariant, so every symmetry the tests rely on is kept, and they make a random-weight model's
minimum well defined (no merging pairs, no collapsing molecules). With the SchNet weights zero
and one spring per pair to its core (``l = 0``) this is the analytic toy model: a core of
charge q_c and a pair of charge -2 bound by a spring k plus their Gaussian Coulomb attraction,
with the closed-form polarizability :func:`toy_atom_polarizability`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from emlpack.nn import EMLP, ModelConfig
from emlpack.structure import Structure
from emlpack.units import COULOMB_EV_A, REFERENCE_GAMMA, SQRT_PI
from tests.nn.helpers import FAMILY_PARAMS, SMALL


class SpringModel(EMLP):
    """EMLP + harmonic springs between fixed particle pairs (indices into cores + pairs)."""

    def __init__(self, config: ModelConfig, springs: list[tuple[int, int, tuple, float, float]]):
        super().__init__(config)
        self.springs = springs

    def energy_parts(self, g, positions=None, cell=None, field=None):
        out = super().energy_parts(g, positions, cell, field)
        pos = g.positions if positions is None else positions
        cell = g.cell if cell is None else cell
        if not self.springs:
            return out
        n_per = int(g.n_structures and len(pos) // g.n_structures)
        i = torch.tensor([b[0] for b in self.springs])
        j = torch.tensor([b[1] for b in self.springs])
        shift = torch.tensor([b[2] for b in self.springs], dtype=pos.dtype)
        k = torch.tensor([b[3] for b in self.springs], dtype=pos.dtype)
        length = torch.tensor([b[4] for b in self.springs], dtype=pos.dtype)
        energies = []
        for m in range(g.n_structures):
            p = pos[m * n_per : (m + 1) * n_per]
            d = p[j] - p[i] + shift @ cell[m]
            sq = (d * d).sum(-1)
            r = torch.sqrt(sq + 1e-30)
            energies.append((0.5 * k * (sq - 2 * length * r + length**2)).sum())
        spring = torch.stack(energies)
        out["energy"] = out["energy"] + spring
        out["energy_springs"] = spring
        return out


def spring_network(structure: Structure, k_pair: float = 20.0, k_core: float = 20.0,
                   core_cutoff: float = 2.6, pair_cutoff: float = 1.2):
    """Springs at their current lengths: each pair to its nearest core and to every core within
    ``pair_cutoff``; every core-core pair within ``core_cutoff`` (minimum image under PBC)."""
    pos = structure.all_positions
    nc = structure.n_cores
    n = len(pos)
    shifts = [(0, 0, 0)]
    if structure.pbc:
        shifts = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]
    springs = []
    for i in range(n):
        for j in range(i, n):
            for sh in shifts:
                if i == j and sh == (0, 0, 0):
                    continue
                d = pos[j] - pos[i] + np.asarray(sh, float) @ structure.cell
                r = float(np.linalg.norm(d))
                if i < nc and j < nc and r < core_cutoff:
                    springs.append((i, j, sh, k_core, r))
                elif i < nc <= j and r < pair_cutoff:
                    springs.append((i, j, sh, k_pair, r))
    # nearest core of each pair
    for p in range(nc, n):
        best = None
        for c in range(nc):
            for sh in shifts:
                r = float(np.linalg.norm(pos[p] - pos[c] + np.asarray(sh, float) @ structure.cell))
                if best is None or r < best[0]:
                    best = (r, c, sh)
        r, c, sh = best
        if not any(b[0] == c and b[1] == p and b[2] == sh for b in springs):
            springs.append((c, p, sh, k_pair, r))
    return springs


def spring_model(structure: Structure, seed: int = 0, weight_scale: float = 0.3,
                 family: str = "schnet", **kw) -> SpringModel:
    """Small random short range of ``family`` (SchNet by default; weights N(0,
    (scale^2)/fan_in)) plus :func:`spring_network`."""
    torch.manual_seed(seed)
    elements = tuple(sorted(set(structure.numbers.tolist())))
    config = ModelConfig(family=family, short_range=FAMILY_PARAMS.get(family, {}),
                         elements=elements)
    model = SpringModel(config, spring_network(structure, **kw))
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("bias"):
                p.normal_(0.0, 0.05)
            elif p.ndim == 2 and not name.startswith("short_range.embedding"):
                p.normal_(0.0, weight_scale / math.sqrt(p.shape[1]))
    return model.double()


def toy_atom(k: float, z: int = 4) -> tuple[SpringModel, Structure]:
    """One core (Be: charge +2) and one pair on a spring ``k`` (eV/Å²), SchNet switched off."""
    s = Structure([z], [[0.1, -0.2, 0.3]], [[0.1, -0.2, 0.3]])
    model = SpringModel(ModelConfig(short_range=SMALL, elements=(z,)),
                        [(0, 1, (0, 0, 0), k, 0.0)])
    with torch.no_grad():
        for p in model.short_range.parameters():
            p.zero_()
    return model.double(), s


def toy_atom_polarizability(k: float, core_charge: float = 2.0) -> float:
    """alpha = q_p^2 / K (e·Å²/V), K = k + k_e q_c |q_p| 4 gamma^3 / (3 sqrt(pi)): the spring
    plus the curvature of the Gaussian attraction -k_e q_c |q_p| erf(gamma r)/r at r = 0."""
    q_pair = 2.0
    gamma = REFERENCE_GAMMA
    curvature = k + COULOMB_EV_A * core_charge * q_pair * 4.0 * gamma**3 / (3.0 * SQRT_PI)
    return q_pair**2 / curvature
