"""The one check of relaxed electron pairs: merged pairs, stray pairs, convergence, curvature.

:func:`check_pairs` is used by the batched relaxation (:func:`emlpack.pairs.relax.relax_pairs`,
so by :class:`emlpack.calculators.ase.EMLPCalculator` through its solvers) and by MD's watchdog
(:class:`emlpack.dynamics.md.Watchdog`). Distances use the minimum image
(:func:`emlpack.geometry.minimum_image`). The thresholds are named parameters; the callers use

=====================================  ======================  ======================
caller                                 ``min_pair_distance``   ``max_core_distance``
=====================================  ======================  ======================
relaxation (:class:`RelaxOptions`)     0.1 Å                   2 Å
MD watchdog (docs/md.md)               0.2 Å                   2 Å
=====================================  ======================  ======================

(the watchdog also asks for the exact pair curvature every 50 steps; a curvature ``<= 0`` fails
everywhere).
"""

from __future__ import annotations

import numpy as np

from emlpack.geometry import minimum_image

#: relaxation's default: two pairs closer than this (Å) have merged
MIN_PAIR_DISTANCE = 0.1
#: MD watchdog's (docs/md.md): stricter, a trajectory must not continue near a merger
MD_MIN_PAIR_DISTANCE = 0.2
#: a pair farther than this (Å) from every core has left its molecule
MAX_CORE_DISTANCE = 2.0
#: two pairs closer than this (Å) have collapsed onto one point: relaxations and optimisations
#: stop there (the direction of their distance is undefined; docs/relaxation.md)
COLLAPSE_DISTANCE = 1e-3
#: a smallest pair curvature above minus this (eV/Å^2) is a flat valley, not a saddle (the
#: relaxation's ``RelaxOptions.flat_curvature`` and the property commands' check of a result)
FLAT_CURVATURE = 1e-3


def _pair_distances(pairs: np.ndarray, cell: np.ndarray | None, pbc: bool) -> np.ndarray:
    """Distances [n, n] (Å) between ``pairs`` [n, 3], minimum image, inf on the diagonal."""
    pbc3 = [bool(np.all(pbc))] * 3
    d = np.linalg.norm(minimum_image(pairs[:, None] - pairs[None], cell, pbc3), axis=-1)
    d[np.diag_indices(len(pairs))] = np.inf
    return d


def closest_pair_distance(pairs: np.ndarray, cell: np.ndarray | None = None,
                          pbc: bool = False) -> float:
    """Smallest distance (Å) between two of ``pairs`` [n, 3] (Å), minimum image for a
    crystal (``cell`` rows, Å); inf with fewer than two pairs."""
    pairs = np.asarray(pairs, float).reshape(-1, 3)
    return float(_pair_distances(pairs, cell, pbc).min()) if len(pairs) > 1 else float("inf")


def check_pairs(
    pairs: np.ndarray,
    cores: np.ndarray,
    cell: np.ndarray | None = None,
    pbc: bool = False,
    *,
    min_pair_distance: float = MIN_PAIR_DISTANCE,
    max_core_distance: float = MAX_CORE_DISTANCE,
    converged: bool = True,
    fmax: float | None = None,
    max_force: float | None = None,
    min_curvature: float = float("nan"),
    flat_curvature: float = 0.0,
) -> str:
    """Reasons (``"; "``-joined, empty when fine) why relaxed ``pairs`` (Å) at ``cores`` (Å)
    cannot be trusted: two pairs closer than ``min_pair_distance`` (merged), a pair farther
    than ``max_core_distance`` from every core, no convergence to ``fmax`` (eV/Å; largest pair
    force ``max_force`` when known), or a smallest pair-Hessian eigenvalue ``min_curvature``
    at or below ``-flat_curvature`` (eV/Å^2; NaN: not computed; ``flat_curvature`` 0: any
    non-positive one). ``cell`` rows (Å) and ``pbc`` give the minimum image of a crystal."""
    pairs = np.asarray(pairs, float).reshape(-1, 3)
    cores = np.asarray(cores, float).reshape(-1, 3)
    pbc3 = [bool(np.all(pbc))] * 3
    reasons = []
    if len(pairs) > 1:
        d = _pair_distances(pairs, cell, pbc)
        if d.min() < min_pair_distance:
            i, j = np.unravel_index(np.argmin(d), d.shape)
            reasons.append(f"pairs {i} and {j} are {d.min():.3g} Å apart (merged;"
                           f" threshold {min_pair_distance:g} Å)")
    if len(pairs) and len(cores):
        dc = np.linalg.norm(minimum_image(pairs[:, None] - cores[None], cell, pbc3), axis=-1)
        dc = dc.min(axis=1)
        if dc.max() > max_core_distance:
            k = int(np.argmax(dc))
            reasons.append(f"pair {k} is {dc[k]:.3g} Å from the nearest core"
                           f" (threshold {max_core_distance:g} Å)")
    if not converged:
        reasons.append("no convergence" + ("" if fmax is None else f" to fmax={fmax:g} eV/Å")
                       + ("" if max_force is None else f" (max force {max_force:.3g} eV/Å)"))
    if np.isfinite(min_curvature) and min_curvature <= -flat_curvature:
        reasons.append(f"negative pair curvature {min_curvature:.3g} eV/Å^2 at the result"
                       " (saddle, not a minimum)")
    return "; ".join(reasons)
