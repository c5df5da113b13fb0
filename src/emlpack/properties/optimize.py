"""Geometry optimisation of cores, electron pairs and (optionally) the cell.

All particles are minimised together: the minimum over pairs and cores is the minimum of the
Born-Oppenheimer energy surface of the cores (pairs relaxed), as in the reference's
``Optimize``. Variables, re-based at every iteration on the current structure:

* displacements ``du`` (Å) of all particles (cores, then pairs);
* for ``cell=True`` a symmetric strain ``eps`` (6 components, Voigt xx yy zz yz xz xy with
  ``eps_yz = S_4 / 2``): ``r -> (r + du)(I + eps)``, ``cell -> cell (I + eps)``.

Rigid translations (molecules: also rotations) are projected out. ``method="newton"`` takes
Newton steps with the exact extended Hessian (:func:`emlpack.properties.hessian.extended_hessian`),
eigenvalues replaced by ``max(|lambda|, 1e-2 eV/Å²)``, steps capped at ``max_step`` Å and an
Armijo backtracking line search: quadratic convergence, for small systems and tight
tolerances (response properties need ~1e-6 eV/Å). ``method="lbfgs"`` uses scipy's L-BFGS-B
with gradients only (large models, where one Hessian costs hundreds of gradients).
Converged when every particle force (rigid-body components removed: a molecule in a field
feels a torque, which the optimiser does not follow) is below ``fmax`` (eV/Å) and, with
``cell``, every stress component below ``smax`` (eV/Å³), and the electron pairs at the result
pass :func:`emlpack.pairs.checks.check_pairs` (no two merged, none away from every core): a
poorly trained model can have a deep spurious minimum with two pairs on one point (measured:
a member of the preliminary ``mini-eqm7`` on 3-(methylamino)but-2-enal, 19 eV below the
start), which is a broken result, not an optimum. The Newton iterations stop when two pairs
come closer than :data:`~emlpack.pairs.checks.COLLAPSE_DISTANCE` (that member went on for its
100 iterations, 8 s, before).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.optimize
from ase.geometry import cell_to_cellpar

from emlpack.geometry import STRAIN_BASIS, internal_basis, rigid_body_modes, voigt_strain
from emlpack.heap import reused_heap
from emlpack.nn.potential import EMLP
from emlpack.pairs.checks import COLLAPSE_DISTANCE, check_pairs, closest_pair_distance
from emlpack.properties.hessian import extended_gradient, extended_hessian
from emlpack.structure import Structure
from emlpack.units import EV_PER_A3_IN_GPA

if TYPE_CHECKING:
    from collections.abc import Callable


@dataclass
class OptimizeResult:
    """Outcome of :func:`optimize` (Å, eV, eV/Å, eV/Å³)."""

    structure: Structure
    energy: float
    converged: bool
    iterations: int
    max_force: float
    max_stress: float
    min_curvature: float
    reason: str = ""
    #: the last Hessian used, in the variables (du, S) of the final structure's neighbourhood
    hessian: np.ndarray | None = None
    #: what :func:`~emlpack.pairs.checks.check_pairs` found wrong with the pairs at the result
    #: (merged or stray pairs; empty when none); also in ``reason``, and ``converged`` is False
    pair_check: str = ""

    def lattice(self) -> dict:
        """Lattice lengths a, b, c (Å), angles alpha, beta, gamma (degrees), volume (Å³)."""
        s = self.structure
        a, b, c, alpha, beta, gamma = cell_to_cellpar(s.cell)
        return {"a": a, "b": b, "c": c, "alpha": alpha, "beta": beta, "gamma": gamma,
                "volume": s.volume}

    def text(self) -> str:
        """Summary lines: convergence, energy (eV), largest force (eV/Å); for a crystal the largest
        stress (GPa) and the lattice; the lowest internal Hessian eigenvalue when known."""
        lines = [
            f"converged: {self.converged} after {self.iterations} iterations"
            + (f" ({self.reason})" if self.reason else ""),
            f"energy {self.energy:.8f} eV, max force {self.max_force:.2e} eV/Å",
        ]
        if self.structure.pbc:
            lat = self.lattice()
            lines.append(f"max stress {self.max_stress * EV_PER_A3_IN_GPA:.2e} GPa")
            lines.append("lattice lengths (Å): a {a:.4f}  b {b:.4f}  c {c:.4f}".format(**lat))
            lines.append("angles (deg): alpha {alpha:.3f}  beta {beta:.3f}  gamma {gamma:.3f}"
                         .format(**lat))
            lines.append(f"volume (Å^3): {lat['volume']:.3f}")
        if np.isfinite(self.min_curvature):
            lines.append(f"lowest internal Hessian eigenvalue {self.min_curvature:.3g}")
        return "\n".join(lines)


class _Problem:
    """Energy, gradient and Hessian in the re-based variables ``x = [du, S]``."""

    def __init__(self, model: EMLP, cell: bool) -> None:
        self.model = model
        self.cell = cell

    def n_vars(self, s: Structure) -> int:
        return 3 * (s.n_cores + s.n_pairs) + (6 if self.cell else 0)

    def apply(self, s: Structure, x: np.ndarray) -> Structure:
        n = s.n_cores + s.n_pairs
        pos = s.all_positions + x[: 3 * n].reshape(n, 3)
        cell = s.cell
        if self.cell:
            deform = np.eye(3) + voigt_strain(x[3 * n :])
            pos, cell = pos @ deform, cell @ deform
        return s.copy(positions=pos[: s.n_cores], pairs=pos[s.n_cores :], cell=cell)

    def jacobian(self, s: Structure) -> np.ndarray:
        """d(extended variables without field)/dx at x = 0."""
        n = s.n_cores + s.n_pairs
        if not s.pbc:
            return np.eye(3 * n)
        jac = np.zeros((3 * n + 9, self.n_vars(s)))
        jac[: 3 * n, : 3 * n] = np.kron(np.eye(n), np.linalg.inv(s.cell).T)
        if self.cell:
            for k in range(6):
                jac[3 * n :, 3 * n + k] = (s.cell @ STRAIN_BASIS[k]).reshape(-1)
        return jac

    def gradient(self, s: Structure) -> np.ndarray:
        g = extended_gradient(self.model, s).numpy()[:-3]
        return self.jacobian(s).T @ g

    def hessian(self, s: Structure) -> tuple[np.ndarray, np.ndarray]:
        g, h = extended_hessian(self.model, s)
        jac = self.jacobian(s)
        g, h = g.numpy()[:-3], h.numpy()[:-3, :-3]
        # x -> (s, A) is affine (s = (r + du) A^-1, A -> A (I + eps)): exact chain rule
        return jac.T @ g, jac.T @ h @ jac

    def energy(self, s: Structure) -> float:
        return float(self.model.evaluate(s, stress=False)["energy"])

    def basis(self, s: Structure) -> np.ndarray:
        n = s.n_cores + s.n_pairs
        rigid = rigid_body_modes(s.all_positions, rotations=not s.pbc)
        q = internal_basis(rigid)
        if not self.cell:
            return q
        out = np.zeros((3 * n + 6, q.shape[1] + 6))
        out[: 3 * n, : q.shape[1]] = q
        out[3 * n :, q.shape[1] :] = np.eye(6)
        return out

    def measures(self, s: Structure, g: np.ndarray) -> tuple[float, float]:
        """Largest particle force and stress, rigid-body components (the net force and torque
        of a field on a molecule) removed."""
        n = s.n_cores + s.n_pairs
        q = self.basis(s)
        g = q @ (q.T @ g)
        fmax = float(np.linalg.norm(g[: 3 * n].reshape(n, 3), axis=1).max())
        smax = float(np.abs(g[3 * n :]).max() / s.volume) if self.cell else 0.0
        return fmax, smax


def optimize(
    model: EMLP,
    structure: Structure,
    cell: bool = False,
    fmax: float = 1e-5,
    smax: float = 1e-6,
    max_iterations: int = 100,
    max_step: float = 0.2,
    method: str = "newton",
    hessian: np.ndarray | None = None,
    hessian_every: int = 1,
    log: Callable[[str], None] | None = None,
) -> OptimizeResult:
    """Minimise the energy over all particle positions (and the cell for ``cell=True``).

    Args:
        fmax: largest particle force at convergence (eV/Å).
        smax: largest stress component at convergence (eV/Å³), with ``cell``.
        max_step: largest particle displacement per step (Å); strain steps <= max_step/5.
        method: ``"newton"`` (exact Hessians) or ``"lbfgs"`` (gradients only).
        hessian: Hessian in the optimiser's variables (:attr:`OptimizeResult.hessian`, e.g.
            of a nearby structure) to start from instead of computing one.
        hessian_every: recompute the exact Hessian every this many iterations (0: never;
            with ``hessian`` given this is the chord method: linear convergence, one gradient
            per step, ideal for the small perturbations of finite differences).
        log: callable receiving one line per iteration (e.g. ``print``).
    """
    if cell and not structure.pbc:
        raise ValueError(f"{structure.source}: cell optimisation needs a periodic structure")
    if cell and np.any(structure.field != 0):
        raise ValueError(
            f"{structure.source}: cell optimisation under a field is not defined (the field"
            " term's strain derivative depends on the periodic images used)"
        )
    if method not in ("newton", "lbfgs"):
        raise ValueError(f"optimize: unknown method {method!r} (newton, lbfgs)")
    prob = _Problem(model, cell)
    # exact Hessians at every iteration allocate large intermediates: kept in the heap
    # instead of page-faulted in again (C4H7NO2 with member 0 of mini-eqm7: 428 000 ->
    # 16 000 minor faults, 4.5 -> 2.7 s CPU; emlpack.heap)
    with reused_heap():
        if method == "lbfgs":
            return _lbfgs(prob, structure, fmax, smax, max_iterations, log)
        return _newton(prob, structure, cell, fmax, smax, max_iterations, max_step, hessian,
                       hessian_every, log)


def _newton(prob: _Problem, structure: Structure, cell: bool, fmax: float, smax: float,
            max_iterations: int, max_step: float, hessian: np.ndarray | None,
            hessian_every: int, log: Callable[[str], None] | None) -> OptimizeResult:
    """Newton steps with exact Hessians (every ``hessian_every`` iterations) and a
    backtracking line search: :func:`optimize`'s default method."""
    s = structure
    energy = prob.energy(s)
    min_curv = float("nan")
    reason = f"no convergence in {max_iterations} iterations"
    converged = False
    it = 0
    h = hessian
    for it in range(1, max_iterations + 1):
        if h is None or (hessian_every and (it - 1) % hessian_every == 0):
            g, h = prob.hessian(s)
        else:
            g = prob.gradient(s)
        q = prob.basis(s)
        evals, evecs = np.linalg.eigh(q.T @ h @ q)
        min_curv = float(evals[0])
        f_now, s_now = prob.measures(s, g)
        if log:
            log(f"iter {it - 1:3d}  E {energy:.10f} eV  fmax {f_now:.2e} eV/Å"
                + (f"  smax {s_now:.2e} eV/Å^3" if cell else ""))
        if f_now < fmax and s_now < smax:
            converged, reason, it = True, "", it - 1
            break
        coef = -(evecs.T @ (q.T @ g)) / np.maximum(np.abs(evals), 1e-2)
        step = q @ (evecs @ coef)
        step *= min(1.0, max_step / _longest(s, step, cell))
        slope = float(g @ step)
        alpha = 1.0
        while True:
            trial = prob.apply(s, alpha * step)
            e_trial = prob.energy(trial)
            if e_trial <= energy + 1e-4 * alpha * slope + 1e-12 * abs(energy):
                break
            alpha *= 0.5
            if alpha < 1e-6:
                break
        if alpha < 1e-6:
            reason = "line search failed (energy does not decrease)"
            break
        s, energy = trial, e_trial
        if closest_pair_distance(s.pairs, s.cell, s.pbc) < COLLAPSE_DISTANCE:
            reason = f"two electron pairs collapsed onto one point after {it} iterations"
            break
    g = prob.gradient(s)
    f_end, s_end = prob.measures(s, g)
    return _checked(OptimizeResult(s, energy, converged, it, f_end, s_end, min_curv, reason, h))


def _checked(res: OptimizeResult) -> OptimizeResult:
    """``res`` with the pair check at its structure: broken pairs fail the optimisation."""
    s = res.structure
    res.pair_check = check_pairs(s.pairs, s.positions, s.cell, s.pbc)
    if res.pair_check:
        res.converged = False
        res.reason = "; ".join(r for r in (res.pair_check, res.reason) if r)
    return res


def _longest(s: Structure, step: np.ndarray, cell: bool) -> float:
    n = s.n_cores + s.n_pairs
    longest = float(np.linalg.norm(step[: 3 * n].reshape(n, 3), axis=1).max())
    if cell:
        longest = max(longest, 5.0 * float(np.abs(step[3 * n :]).max()))
    return max(longest, 1e-300)


def _lbfgs(prob: _Problem, s0: Structure, fmax: float, smax: float, max_iterations: int,
           log: Callable[[str], None] | None) -> OptimizeResult:
    calls = {"n": 0}

    jac = prob.jacobian(s0)

    def fun(x: np.ndarray):
        # x -> (fractional coordinates, cell) is affine for a fixed s0: exact chain rule
        s = prob.apply(s0, x)
        calls["n"] += 1
        return prob.energy(s), jac.T @ extended_gradient(prob.model, s).numpy()[:-3]

    res = scipy.optimize.minimize(
        fun, np.zeros(prob.n_vars(s0)), jac=True, method="L-BFGS-B",
        options={"maxiter": max_iterations, "gtol": min(fmax, smax) / 10, "ftol": 1e-15,
                 "maxcor": 30},
    )
    s = prob.apply(s0, res.x)
    g = prob.gradient(s)
    f_end, s_end = prob.measures(s, g)
    converged = f_end < fmax and (s_end < smax)
    reason = "" if converged else f"L-BFGS-B stopped: {res.message}"
    if log:
        log(f"L-BFGS-B: {res.nit} iterations, {calls['n']} evaluations, fmax {f_end:.2e}")
    return _checked(OptimizeResult(s, float(res.fun), converged, int(res.nit), f_end, s_end,
                                   float("nan"), reason))

