"""Starting electron pairs for a bare structure (cores only).

* ``method="boys"`` (molecules; the default for them when PySCF is installed): a quick
  Hartree-Fock calculation at a small basis (``level``, default HF/STO-3G, ~1 s for 10 atoms) and
  Foster-Boys localization via :class:`emlpack.qm.pyscf_labeler.PySCFLabeler`; the valence
  centres are returned. With ``method="auto"`` a failed Boys guess (e.g. a strongly distorted
  MD frame whose localized core orbital is off its nucleus) falls back to the Lewis guess,
  with a logged warning.
* ``method="lewis"`` (crystals, or without PySCF): a Lewis structure. Bonds from covalent radii
  (minimum image under PBC), bond orders raised greedily until every atom reaches its usual
  valence (H 1, B 3, C 4, N 3, O 2, F 1, Si 4, P 3, S 2, Cl 1), lone pairs from valence counting
  ``(v - sum of bond orders) / 2``, the remaining pairs (charges, zwitterions) given to the most
  electronegative atoms with an odd count. Placement: a single-bond pair on the bond, shifted
  toward the more electronegative atom; double/triple-bond pairs off the axis ("banana" pairs
  like Boys/Wannier centres, 0.35 Å); lone pairs ~0.3 Å from the nucleus in the directions
  farthest from the other pairs around the atom.

The model then relaxes the pairs (:func:`emlpack.pairs.relax.relax_pairs`); the guess only has to be
in the right basin. No torch here.
"""

from __future__ import annotations

import logging

import numpy as np
from ase import Atoms
from ase.data import covalent_radii

from emlpack.optional import import_optional, is_available
from emlpack.structure import core_charges

log = logging.getLogger(__name__)

#: usual number of covalent bonds (sum of bond orders) per element
VALENCE = {1: 1, 3: 1, 4: 2, 5: 3, 6: 4, 7: 3, 8: 2, 9: 1, 11: 1, 12: 2, 13: 3, 14: 4, 15: 3,
           16: 2, 17: 1}
#: Pauling electronegativities
ELECTRONEGATIVITY = {1: 2.20, 3: 0.98, 4: 1.57, 5: 2.04, 6: 2.55, 7: 3.04, 8: 3.44, 9: 3.98,
                     11: 0.93, 12: 1.31, 13: 1.61, 14: 1.90, 15: 2.19, 16: 2.58, 17: 3.16,
                     18: 3.2, 10: 4.0, 2: 4.0}
#: lone-pair distance from the nucleus (Å)
LONE_PAIR_DISTANCE = {7: 0.38, 8: 0.32, 9: 0.28, 15: 0.6, 16: 0.55, 17: 0.5}
#: off-axis distance of multiple-bond pairs (Å)
MULTIPLE_BOND_OFFSET = 0.35


def guess_pairs(atoms: Atoms, method: str = "auto", level: str = "hf/sto-3g/nodf",
                charge: float | None = None) -> np.ndarray:
    """Starting electron-pair positions (Å), shape (n_pairs, 3), for the cores in ``atoms``.

    Args:
        method: ``"auto"`` (Boys for molecules when PySCF is importable, else Lewis),
            ``"boys"`` or ``"lewis"``.
        level: PySCF level for ``"boys"`` (``xc/basis[/nodf]`` or a preset name).
        charge: total charge (e); default ``atoms.info["charge"]`` or 0.
    """
    if charge is None:
        charge = float(atoms.info.get("charge", 0.0))
    periodic = bool(np.any(atoms.pbc))
    if method == "auto" and not periodic and _have_pyscf():
        from emlpack.qm.pyscf_labeler import LabelingError

        try:
            return boys_pairs(atoms.numbers, atoms.positions, charge, level)
        except LabelingError as exc:
            log.warning("%s; using the Lewis-structure guess", exc)
            return lewis_pairs(atoms, charge)
    if method == "auto":
        method = "lewis"
    if method == "boys":
        if periodic:
            raise ValueError("guess_pairs: Foster-Boys guess is for molecules; use 'lewis'")
        return boys_pairs(atoms.numbers, atoms.positions, charge, level)
    if method == "lewis":
        return lewis_pairs(atoms, charge)
    raise ValueError(f"guess_pairs: unknown method {method!r} (auto, boys, lewis)")


def guess_matched(numbers: np.ndarray, positions: np.ndarray, reference: np.ndarray,
                  charge: float = 0.0, method: str = "auto") -> np.ndarray:
    """:func:`guess_pairs` for the molecule ``numbers``/``positions`` (Å), ordered to match
    ``reference`` pairs (Å) by the Hungarian algorithm when the counts agree (so that a fresh
    guess continues the pair labels of, e.g., an MD trajectory)."""
    from scipy.optimize import linear_sum_assignment

    atoms = Atoms(numbers, positions)
    atoms.info["charge"] = charge
    guess = np.asarray(guess_pairs(atoms, method=method), float).reshape(-1, 3)
    ref = np.asarray(reference, float).reshape(-1, 3)
    if len(guess) == len(ref) and len(ref):
        cost = np.linalg.norm(ref[:, None] - guess[None], axis=-1)
        _, cols = linear_sum_assignment(cost)
        guess = guess[cols]
    return guess


def _have_pyscf() -> bool:
    from emlpack.threads import configure_openblas_coretype

    configure_openblas_coretype()  # before PySCF loads its OpenBLAS
    return is_available("pyscf")


def boys_pairs(numbers: np.ndarray, positions: np.ndarray, charge: float = 0.0,
               level: str = "hf/sto-3g/nodf") -> np.ndarray:
    """Valence Foster-Boys centres (Å) of a quick PySCF calculation at ``level``."""
    from emlpack.qm.pyscf_labeler import LabelingError, PySCFLabeler

    import_optional("pyscf", "the Foster-Boys pair guess ('boys')",
                    alternative="the Lewis-structure guess ('lewis', --guess lewis)")

    result = PySCFLabeler(level, boys_starts=1)(numbers, positions, charge=charge,
                                                 forces=False, localize=True)
    if not result.ok:
        raise LabelingError(f"guess_pairs: PySCF Foster-Boys guess failed: {result.error}")
    return result.pairs


# ---------------------------------------------------------------------- Lewis structure
def _bonds(atoms: Atoms) -> list[tuple[int, int, np.ndarray]]:
    """(i, j, vector from i to j, Å) for bonded atoms i < j (minimum image)."""
    from ase.neighborlist import neighbor_list

    radii = [covalent_radii[z] * 1.2 for z in atoms.numbers]
    i, j, d = neighbor_list("ijD", atoms, radii)
    return [(a, b, v) for a, b, v in zip(i, j, d, strict=True) if a < b]


def _bond_orders(numbers: np.ndarray, bonds: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    orders = np.ones(len(bonds), dtype=int)
    need = np.array([VALENCE.get(int(z), 0) for z in numbers])
    for a, b, _ in bonds:
        need[a] -= 1
        need[b] -= 1
    # raise bond orders between unsaturated neighbours, most constrained atoms first
    changed = True
    while changed:
        changed = False
        cand = [k for k, (a, b, _) in enumerate(bonds)
                if need[a] > 0 and need[b] > 0 and orders[k] < 3]
        if not cand:
            break
        n_options = {}
        for k in cand:
            for atom in bonds[k][:2]:
                n_options[atom] = n_options.get(atom, 0) + 1
        k = min(cand, key=lambda c: (min(n_options[bonds[c][0]], n_options[bonds[c][1]]), c))
        a, b, _ = bonds[k]
        orders[k] += 1
        need[a] -= 1
        need[b] -= 1
        changed = True
    return orders


def _lone_pair_counts(numbers: np.ndarray, bonds: list[tuple[int, int, np.ndarray]],
                      orders: np.ndarray, n_pairs_total: int) -> np.ndarray:
    v = core_charges(numbers).astype(int)
    used = np.zeros(len(numbers), dtype=int)
    for (a, b, _), o in zip(bonds, orders, strict=True):
        used[a] += o
        used[b] += o
    free = v - used
    lone = np.maximum(free, 0) // 2
    deficit = n_pairs_total - int(orders.sum()) - int(lone.sum())
    en = np.array([ELECTRONEGATIVITY.get(int(z), 2.5) for z in numbers])
    octet_room = np.where(numbers == 1, 0, 4) - used - lone
    if deficit > 0:
        # odd electron counts first (zwitterions, anions), then the most electronegative
        order = sorted(range(len(numbers)),
                       key=lambda a: (-(free[a] % 2), -en[a]))
        for a in order * 4:
            if deficit == 0:
                break
            if octet_room[a] > 0:
                lone[a] += 1
                octet_room[a] -= 1
                deficit -= 1
    elif deficit < 0:
        for a in sorted(range(len(numbers)), key=lambda a: en[a]) * 4:
            if deficit == 0:
                break
            if lone[a] > 0:
                lone[a] -= 1
                deficit += 1
    if deficit != 0:
        raise ValueError(f"guess_pairs: no Lewis structure found ({deficit:+d} pairs left over)")
    return lone


def _perpendicular(v: np.ndarray, hint: np.ndarray | None = None) -> np.ndarray:
    """A unit vector perpendicular to ``v``, as close as possible to ``hint``."""
    v = v / np.linalg.norm(v)
    if hint is not None:
        p = hint - (hint @ v) * v
        if np.linalg.norm(p) > 1e-3:
            return p / np.linalg.norm(p)
    trial = np.eye(3)[np.argmin(np.abs(v))]
    p = trial - (trial @ v) * v
    return p / np.linalg.norm(p)


def _spread_directions(fixed: list[np.ndarray], n_new: int) -> list[np.ndarray]:
    """``n_new`` unit vectors far from each other and from the ``fixed`` unit vectors
    (repulsion minimisation on the sphere, deterministic start)."""
    if n_new == 0:
        return []
    tet = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / np.sqrt(3)
    if fixed:
        away = -np.sum(fixed, axis=0)
        away = away / np.linalg.norm(away) if np.linalg.norm(away) > 1e-6 else _perpendicular(
            fixed[0])
        side = _perpendicular(away, np.cross(fixed[0], away) if len(fixed) else None)
        start = [away + 0.8 * np.cos(2 * np.pi * k / n_new) * side
                 + 0.8 * np.sin(2 * np.pi * k / n_new) * np.cross(away, side)
                 if n_new > 1 else away for k in range(n_new)]
    else:
        start = list(tet[:n_new]) if n_new <= 4 else list(np.random.default_rng(0).normal(
            size=(n_new, 3)))
    u = np.array([s / np.linalg.norm(s) for s in start])
    f = np.array(fixed).reshape(-1, 3)
    for _ in range(300):
        allp = np.vstack([f, u])
        grad = np.zeros_like(u)
        for k in range(len(u)):
            d = u[k] - allp
            r = np.linalg.norm(d, axis=1)
            mask = r > 1e-9
            grad[k] = -(d[mask] / r[mask, None] ** 3).sum(axis=0)
        u = u - 0.05 * grad
        u /= np.linalg.norm(u, axis=1)[:, None]
    return list(u)


def lewis_pairs(atoms: Atoms, charge: float = 0.0) -> np.ndarray:
    """Electron pairs (Å) of a Lewis structure of ``atoms`` (molecule or crystal)."""
    numbers = atoms.numbers
    pos = atoms.positions
    n_pairs_total = int(round((core_charges(numbers).sum() - charge) / 2))
    bonds = _bonds(atoms)
    orders = _bond_orders(numbers, bonds)
    lone = _lone_pair_counts(numbers, bonds, orders, n_pairs_total)
    en = np.array([ELECTRONEGATIVITY.get(int(z), 2.5) for z in numbers])
    neighbours: dict[int, list[np.ndarray]] = {a: [] for a in range(len(numbers))}
    for a, b, v in bonds:
        neighbours[a].append(v)
        neighbours[b].append(-v)
    pairs: list[np.ndarray] = []
    around: dict[int, list[np.ndarray]] = {a: [] for a in range(len(numbers))}
    for (a, b, v), order in zip(bonds, orders, strict=True):
        length = np.linalg.norm(v)
        unit = v / length
        # fraction of the bond from a: 0.5, shifted toward the more electronegative atom
        frac = 0.5 + 0.12 * np.tanh(en[b] - en[a])
        if numbers[a] == 1 or numbers[b] == 1:
            frac = 0.5 + 0.15 * np.tanh(en[b] - en[a]) + (0.1 if numbers[b] == 1 else -0.1)
        centre = pos[a] + frac * v
        if order == 1:
            points = [centre]
        else:
            others = [w for w in neighbours[a] if not np.allclose(w, v)]
            others += [-w for w in neighbours[b] if not np.allclose(w, -v)]
            hint = np.cross(unit, others[0]) if others else None
            p1 = _perpendicular(unit, hint)
            p2 = np.cross(unit, p1)
            angles = [0.0, np.pi] if order == 2 else [0.0, 2 * np.pi / 3, 4 * np.pi / 3]
            points = [centre + MULTIPLE_BOND_OFFSET * (np.cos(t) * p1 + np.sin(t) * p2)
                      for t in angles]
        for p in points:
            pairs.append(p)
            for atom, origin in ((a, pos[a]), (b, pos[a] + v)):
                d = p - origin
                around[atom].append(d / np.linalg.norm(d))
    for a in range(len(numbers)):
        if lone[a] == 0:
            continue
        dist = LONE_PAIR_DISTANCE.get(int(numbers[a]), 0.4)
        for u in _spread_directions(around[a], int(lone[a])):
            pairs.append(pos[a] + dist * u)
    return np.array(pairs).reshape(-1, 3)
