"""Data augmentation of electron pairs (paper, section 2.6 and appendix B).

One valence pair ``i`` of a configuration is displaced by ``dR`` (|dR| uniform in
[0.06, 0.12] Å, random direction). The labels become

* energy: ``E + 1/2 k |dR|^2`` (a harmonic guess, k = 2 Ha/Å^2);
* force on ``i``: ``f_i + dF`` with ``dF = -k dR`` (pointing back);
* forces on every other particle ``j``: ``f_j + df_j``, the weighted least-norm solution of

      sum_j df_j = -dF                                            (zero net force)
      sum_j r_j x df_j = q_i dR x E - dR x (f_i + dF) - r_i x dF  (torque = d' x E, molecules)

  minimising ``1/2 sum_j phi_j |df_j|^2`` with ``phi(r) = r^2 / f_cut(r)`` (r the distance
  to the displaced pair; particles beyond the cutoff get no force). The solution is
  ``df_j = (lambda + mu x r~_j) / phi_j`` in the frame ``r~ = r + t`` with ``t = -Q1/Q0``:
  ``lambda = -dF/Q0``, ``mu = Q2^-1 M~``;
* polarizability: dropped (the loss's polarizability term takes the model's pair Hessian at
  the labelled DFT centres, not at a displaced pair).

Singular cases: when the weighted particles are collinear (e.g. H2, or a single neighbour),
``Q2`` is singular and the torque condition cannot be met by forces on them; the augmentation
then falls back to the force-only solution (``mu = 0``) and reports it (``singular``). A pair
with no other particle inside the cutoff cannot be balanced and the configuration is left
unchanged (``skipped``). Periodic structures use minimum-image vectors and only the zero net
force condition (the torque of a periodic system is not defined).

Randomness: :func:`augment` takes a ``numpy.random.Generator``; the trainer seeds one per
(seed, epoch, configuration), so augmentation does not depend on batching, workers or ranks.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from emlpack.geometry import cosine_cutoff, minimum_image
from emlpack.structure import PAIR_CHARGE, Structure
from emlpack.units import AUGMENTATION_K_EV_A2


@dataclass
class AugmentationConfig:
    """Settings (Å, eV/Å^2). Defaults are the paper's."""

    enabled: bool = False
    probability: float = 0.1
    min_displacement: float = 0.06
    max_displacement: float = 0.12
    k: float = AUGMENTATION_K_EV_A2
    cutoff: float = 4.0
    cutoff_transition: float = 0.5
    #: Q2 is treated as singular when its smallest eigenvalue is below this times the largest
    singular_rcond: float = 1e-6

    def to_dict(self) -> dict:
        """The settings as a plain dict (the config's ``augmentation`` section)."""
        return asdict(self)


@dataclass
class AugmentationInfo:
    """What :func:`augment` did: displaced a pair (``augmented``; its index among the pairs,
    ``pair``, and its displacement ``dR`` (3,), Å), dropped the torque condition (``singular``)
    or left the configuration unchanged (``skipped``)."""

    augmented: bool = False
    singular: bool = False
    skipped: bool = False
    pair: int = -1
    displacement: np.ndarray | None = None


def compensating_forces(
    positions: np.ndarray,
    i: int,
    old_position: np.ndarray,
    displacement: np.ndarray,
    force_i: np.ndarray,
    restoring: np.ndarray,
    charge_i: float,
    field: np.ndarray,
    weights: np.ndarray,
    periodic: bool,
    rcond: float = 1e-6,
) -> tuple[np.ndarray, bool]:
    """Weighted least-norm forces ``df_j`` (eV/Å) on all particles (zero for ``i``).

    ``positions`` (N, 3) are after the displacement, with ``weights`` = 1/phi (zero for ``i``
    and beyond the cutoff; under PBC the positions must be minimum-image vectors relative to
    the displaced pair). Returns ``(df, singular)``."""
    q0 = weights.sum()
    lam = -restoring / q0
    if periodic:
        return weights[:, None] * lam[None, :], False
    t = -(weights[:, None] * positions).sum(0) / q0
    rt = positions + t
    q2 = (weights[:, None, None] * (
        (rt * rt).sum(-1)[:, None, None] * np.eye(3) - rt[:, :, None] * rt[:, None, :]
    )).sum(0)
    m = (charge_i * np.cross(displacement, field) - np.cross(displacement, force_i + restoring)
         - np.cross(old_position + t, restoring))
    eig = np.linalg.eigvalsh(q2)
    if eig[0] <= rcond * max(eig[-1], 1e-300):
        return weights[:, None] * lam[None, :], True
    mu = np.linalg.solve(q2, m)
    return weights[:, None] * (lam[None, :] + np.cross(mu[None, :], rt)), False


def augment(
    s: Structure, rng: np.random.Generator, config: AugmentationConfig
) -> tuple[Structure, AugmentationInfo]:
    """With probability ``config.probability``, a copy of ``s`` with one pair displaced and
    labels adjusted; otherwise ``s`` itself (unchanged)."""
    info = AugmentationInfo()
    # always draw the same number of variates, so later draws do not depend on the outcome
    coin, u, v, w, pick = rng.random(5)
    if coin >= config.probability or s.n_pairs == 0 or s.energy is None or s.forces is None:
        return s, info
    i = min(int(pick * s.n_pairs), s.n_pairs - 1)
    length = config.min_displacement + w * (config.max_displacement - config.min_displacement)
    nz = 1.0 - 2.0 * u
    rho = math.sqrt(max(0.0, 1.0 - nz * nz))
    direction = np.array([rho * math.sin(2 * math.pi * v), rho * math.cos(2 * math.pi * v), nz])
    d = length * direction
    restoring = -config.k * d

    nc = s.n_cores
    k = nc + i  # particle index of the displaced pair
    pairs = s.pairs.copy()
    old = pairs[i].copy()
    pairs[i] = old + d
    pos = np.concatenate([s.positions, pairs])
    rel = pos - pos[k]
    if s.pbc:
        rel = minimum_image(rel, s.cell)
    r = np.sqrt((rel * rel).sum(-1))
    weights = cosine_cutoff(r, config.cutoff, config.cutoff_transition) / np.maximum(r, 1e-2) ** 2
    weights[k] = 0.0
    if weights.sum() <= 0.0:
        info.skipped = True
        return s, info
    pair_forces = s.pair_forces if s.pair_forces is not None else np.zeros_like(s.pairs)
    if s.pbc:
        # positions relative to the displaced pair (minimum image): translation invariant
        positions = rel
        old_rel = -d
    else:
        positions, old_rel = pos, old
    df, singular = compensating_forces(
        positions, k, old_rel, d, pair_forces[i], restoring, PAIR_CHARGE, s.field, weights,
        s.pbc, config.singular_rcond,
    )
    forces = s.forces + df[:nc]
    new_pair_forces = pair_forces + df[nc:]
    new_pair_forces[i] += restoring
    out = s.copy(
        pairs=pairs,
        energy=s.energy + 0.5 * config.k * length**2,
        forces=forces,
        pair_forces=new_pair_forces,
        polarizability=None,  # a label of the DFT centres, not of the displaced pair
    )
    info.augmented, info.singular, info.pair, info.displacement = True, singular, i, d
    return out, info
