"""Born-Oppenheimer molecular dynamics of the cores with relaxed electron pairs (float64).

:func:`run_md` integrates the cores with ASE (``NoseHooverChainNVT``, chain length 3, time
constant 100 fs as yaff's defaults, or ``VelocityVerlet`` for NVE) on a
:class:`BOPairCalculator`, which relaxes the electron pairs at every new core geometry:

* ``relax="warm"`` (default): the pairs are extrapolated from the last four relaxed steps
  (cubic in the offsets of each pair from its nearest core, so pairs follow their cores) and
  relaxed by a quasi-Newton method whose pair-Hessian model is carried over from step to step
  (rotated with the molecule, refined by damped BFGS updates, replaced by the exact pair Hessian
  at the start and every ``curvature_every`` steps); tight tolerance (``fmax`` 1e-5 eV/Å), so
  the forces are Born-Oppenheimer forces and NVE conserves energy. Measured: about 4
  energy+gradient evaluations per step at dt = 0.5 fs (the pair Hessian changes by ~2 % per
  step, so the carried model converges linearly, ~20x per iteration); see docs/md.md.
* ``relax="corrected"``: ``"warm"`` plus a final Newton correction without an evaluation:
  a secant (Broyden) model ``C`` of the core-pair Hessian block is carried like the pair
  Hessian (exact at the refreshes, from the same Hessian-vector products), and the loop stops
  when (largest relative model error measured in this and the last step) x (largest pair-force
  component) < ``fmax``, i.e. when the pairs after one more model Newton step ``s = -H^-1 g``
  would be converged; the result is then pairs + s, energy + g.s + s.H.s/2 and core gradient
  g_c + C s. About 3.5 evaluations per step (hexane); per-step core forces as accurate as
  ``"warm"`` at the same ``fmax`` (benchmarks/md.py measures it against tightly relaxed pairs).
* ``relax="paper"``: the reference code's scheme, SciPy L-BFGS-B from the previous pairs with
  every pair coordinate boxed to ±3x the largest core displacement since the last step
  (0.1 Å on the first call), ``gtol`` 1e-5 eV/Å.

A :class:`Watchdog` checks every step (relaxation converged, no two pairs closer than
``min_pair_distance``, no pair farther than ``max_core_distance`` from every core, and every
``curvature_every`` steps a positive-definite exact pair Hessian). A failed step is rolled back
(positions, momenta, thermostat, calculator state) and retried from the pairs of the last good
step moved rigidly with their nearest cores, then from :func:`emlpack.pairs.guess.guess_pairs`; if both
fail the run stops with :class:`MDWatchdogError` after writing everything so far.

Outputs in the directory ``output``: ``trajectory.xyz`` (native extxyz, one frame per recorded
step, pairs as ``Es`` rows; see :func:`frame_structure` for the ``info`` keys), ``checkpoint.npz``
(full integrator, thermostat and pair state, written atomically with the byte length of the
trajectory it belongs to), ``md.log`` and ``summary.json``. Re-running the same call resumes from
the checkpoint (a partial trailing frame is cut off) and continues the same trajectory.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import ase.units
import numpy as np
import scipy.optimize
import torch
from ase import Atoms
from ase.calculators.calculator import CalculationFailed, Calculator, all_changes
from ase.md.nose_hoover_chain import NoseHooverChainNVT
from ase.md.velocitydistribution import (
    MaxwellBoltzmannDistribution,
    Stationary,
    ZeroRotation,
)
from ase.md.verlet import VelocityVerlet

from emlpack.errors import EmlpackError
from emlpack.io.extxyz import atomic_write, write_structures
from emlpack.nn.checkpoint import load_model
from emlpack.nn.potential import EMLP
from emlpack.pairs.relax import damped_bfgs, pair_hessian, relax_pairs
from emlpack.structure import Structure

__all__ = [
    "BOPairCalculator",
    "MDResult",
    "MDWatchdogError",
    "Watchdog",
    "run_md",
    "TRAJECTORY",
    "CHECKPOINT",
]

TRAJECTORY = "trajectory.xyz"
CHECKPOINT = "checkpoint.npz"
LOG = "md.log"
SUMMARY = "summary.json"
#: smallest curvature (eV/Å^2) of the quasi-Newton step model
_CURVATURE_FLOOR = 1e-2


class MDWatchdogError(EmlpackError, RuntimeError):
    """The pairs could not be relaxed at some MD step, even from the fallback guesses."""


# ------------------------------------------------------------------------------ calculator
class BOPairCalculator(Calculator):
    """Born-Oppenheimer eMLP calculator for MD: cores in ``atoms``, pairs as internal state.

    Args:
        model: the eMLP (float64).
        pairs: initial electron pairs (Å), shape (P, 3).
        field: homogeneous field (V/Å).
        relax: ``"warm"`` (extrapolation + carried-over quasi-Newton), ``"corrected"`` (warm
            with the model-error criterion and a final Newton correction) or ``"paper"``
            (L-BFGS-B from the previous pairs, boxed to ±3x the largest core displacement).
        fmax: convergence threshold: largest pair-force component (``"warm"``), the same
            times the measured model error (``"corrected"``) or largest projected gradient
            component (``"paper"``, L-BFGS-B's ``gtol``), eV/Å.
        charge: total charge (e).

    After each calculation ``self.diagnostics`` holds ``converged``, ``n_evaluations``,
    ``n_hessians``, ``max_force`` (eV/Å), ``min_curvature`` (eV/Å^2, NaN when not computed),
    ``reason`` (empty when fine) and ``pairs``.
    """

    implemented_properties = ["energy", "free_energy", "forces", "dipole"]

    def __init__(self, model: EMLP, pairs: np.ndarray, field=(0.0, 0.0, 0.0),
                 relax: str = "warm", fmax: float = 1e-5, charge: float = 0.0,
                 max_iterations: int = 50, max_step: float = 0.2, extrapolation: int = 3,
                 **kwargs) -> None:
        super().__init__(**kwargs)
        if relax not in ("warm", "corrected", "paper"):
            raise ValueError(f"relax must be 'warm', 'corrected' or 'paper', not {relax!r}")
        self.model = model
        self.field = np.asarray(field, float).reshape(3)
        #: "corrected": warm + final Newton correction of pairs, energy and core forces
        self.correct = relax == "corrected"
        self.relax_mode = "warm" if self.correct else relax
        self.fmax = fmax
        self.charge = charge
        self.max_iterations = max_iterations
        self.max_step = max_step
        self.extrapolation = extrapolation
        self.n_history = max(extrapolation + 1, 1)
        #: relaxed (cores, pairs) of the last calls, newest last (at most 3)
        self.history: list[tuple[np.ndarray, np.ndarray]] = []
        self.start_pairs = np.asarray(pairs, float).reshape(-1, 3).copy()
        self.hessian: np.ndarray | None = None
        #: secant (Broyden) model of the core-pair Hessian block d g_cores / d pairs, (3N, 3P)
        self.coupling: np.ndarray | None = None
        #: largest relative model error (pair Hessian or coupling) measured in the last steps
        self.model_error = 1.0
        #: one-shot start for the next calculation: None, "rigid" or "guess"
        self.fallback: str | None = None
        #: compute the exact pair Hessian at the result of the next calculation
        self.want_curvature = False
        self.diagnostics: dict = {}
        self.n_evaluations = 0
        self.n_hessians = 0

    # -------------------------------------------------------------------- state
    def state(self) -> dict:
        """Everything needed to continue bit for bit (numpy arrays and numbers)."""
        return {
            "history": [(c.copy(), p.copy()) for c, p in self.history],
            "start_pairs": self.start_pairs.copy(),
            "hessian": None if self.hessian is None else self.hessian.copy(),
            "coupling": None if self.coupling is None else self.coupling.copy(),
            "model_error": self.model_error,
            "results": copy.deepcopy(self.results),
            "atoms_positions": None if self.atoms is None else self.atoms.positions.copy(),
            "diagnostics": copy.deepcopy(self.diagnostics),
            "n_evaluations": self.n_evaluations,
            "n_hessians": self.n_hessians,
        }

    def set_state(self, state: dict, atoms: Atoms) -> None:
        self.history = [(c.copy(), p.copy()) for c, p in state["history"]]
        self.start_pairs = state["start_pairs"].copy()
        self.hessian = None if state["hessian"] is None else state["hessian"].copy()
        coupling = state.get("coupling")
        self.coupling = None if coupling is None else coupling.copy()
        self.model_error = float(state.get("model_error", 1.0))
        self.results = copy.deepcopy(state["results"])
        self.diagnostics = copy.deepcopy(state["diagnostics"])
        self.n_evaluations = state["n_evaluations"]
        self.n_hessians = state["n_hessians"]
        self.fallback = None
        self.want_curvature = False
        if state["atoms_positions"] is None:
            self.atoms = None
        else:
            self.atoms = atoms.copy()
            self.atoms.calc = None
            self.atoms.positions[:] = state["atoms_positions"]

    @property
    def pairs(self) -> np.ndarray:
        """The relaxed pairs (Å) of the last calculation."""
        return self.history[-1][1] if self.history else self.start_pairs

    # -------------------------------------------------------------------- guesses
    def _rigid(self, cores: np.ndarray) -> np.ndarray:
        """The last relaxed pairs moved rigidly with their nearest cores."""
        if not self.history:
            return self.start_pairs.copy()
        old_cores, pairs = self.history[-1]
        nearest = _nearest(pairs, old_cores)
        return pairs + (cores - old_cores)[nearest]

    def predict(self, cores: np.ndarray) -> np.ndarray:
        """Extrapolated pairs (Å) at the cores ``cores``: the offsets of every pair from its
        nearest core (assignment of the newest step) extrapolated to order ``extrapolation``
        (0: rigid, 1: linear, 2: quadratic, 3: cubic, 4: quartic) from the last relaxed steps."""
        if not self.history:
            return self.start_pairs.copy()
        nearest = _nearest(self.history[-1][1], self.history[-1][0])
        offsets = [p - c[nearest] for c, p in self.history]
        order = min(self.extrapolation, len(offsets) - 1)
        coefficients = _EXTRAPOLATION[order]
        m = offsets[0].size
        if (self.correct and order > 0 and self.coupling is not None
                and self.hessian is not None and self.coupling.shape == (cores.size, m)):
            # extrapolate pairs and cores alike, then the linear response of the pairs to the
            # cores' extrapolation error: dp = -H_pp^-1 H_pc dc (carried models, no evaluation)
            recent = self.history[-order - 1:]
            c_ex = sum(w * c for w, (c, _) in zip(coefficients, recent, strict=True))
            p_ex = sum(w * p for w, (_, p) in zip(coefficients, recent, strict=True))
            w, v = np.linalg.eigh(self.hessian)
            rhs = self.coupling.T @ (cores - c_ex).reshape(-1)
            dp = -v @ ((v.T @ rhs) / np.maximum(w, _CURVATURE_FLOOR))
            return p_ex + dp.reshape(-1, 3)
        offset = sum(w * o for w, o in zip(coefficients, offsets[-order - 1:], strict=True))
        return cores[nearest] + offset

    def _guess(self, atoms: Atoms, method: str = "auto") -> np.ndarray:
        """:func:`guess_pairs`, ordered to match the rigidly moved last pairs (Hungarian)."""
        from scipy.optimize import linear_sum_assignment

        from emlpack.pairs.guess import guess_pairs

        probe = Atoms(atoms.numbers, atoms.positions)
        probe.info["charge"] = self.charge
        guess = np.asarray(guess_pairs(probe, method=method), float).reshape(-1, 3)
        ref = self._rigid(atoms.positions)
        if len(guess) == len(ref) and len(ref):
            cost = np.linalg.norm(ref[:, None] - guess[None], axis=-1)
            _, cols = linear_sum_assignment(cost)
            guess = guess[cols]
        return guess

    # -------------------------------------------------------------------- calculation
    def calculate(self, atoms: Atoms | None = None, properties=None,
                  system_changes=all_changes) -> None:
        super().calculate(atoms, properties or ["energy"], system_changes)
        atoms = self.atoms
        cores = atoms.positions.copy()
        fallback, self.fallback = self.fallback, None
        mode = self.relax_mode
        if fallback == "rigid":
            x0, mode = self._rigid(cores), "warm"
        elif fallback == "guess":
            x0, mode = self._guess(atoms), "warm"
        elif mode == "warm":
            x0 = self.predict(cores)
        else:
            x0 = self.pairs.copy()
        if fallback or not self.history:
            self.hessian = None  # fresh exact Hessian after a fallback
            self.coupling = None
            self.model_error = 1.0
        structure = Structure(atoms.numbers, cores, x0, field=self.field, charge=self.charge,
                              source="MD")
        n_pre = 0
        if fallback or not self.history:
            # a fresh start may be far from the minimum: the robust Newton relaxation first
            pre = relax_pairs(self.model, structure, fmax=self.fmax, max_iterations=50,
                              check_curvature=False)[0]
            n_pre = pre.n_evaluations
            self.n_evaluations += n_pre
            self.n_hessians += pre.n_hessians
            structure = structure.copy(pairs=pre.pairs)
        if mode == "warm":
            out = self._relax_warm(structure)
        else:
            out = self._relax_paper(structure)
        out["n_evaluations"] += n_pre
        pairs = out["pairs"]
        want_curv = self.want_curvature
        self.want_curvature = False
        min_curv = float("nan")
        if want_curv and len(pairs):
            hessian, coupling = self.hessian, self.coupling
            exact = self._exact_hessian(structure.copy(pairs=pairs))
            self.n_hessians += 1
            out["n_hessians"] += 1
            min_curv = float(np.linalg.eigvalsh(exact)[0])
            if mode != "warm":
                self.hessian, self.coupling = hessian, coupling
        if not np.isfinite(out["energy"]) or not np.all(np.isfinite(out["forces"])):
            raise CalculationFailed("MD: non-finite energy or forces after the pair relaxation")
        reason = "" if out["converged"] else (
            f"pair relaxation did not converge to {self.fmax:g} eV/Å"
            f" (max force {out['max_force']:.3g} eV/Å)")
        self.diagnostics = {
            "converged": out["converged"],
            "n_evaluations": out["n_evaluations"],
            "n_hessians": out["n_hessians"],
            "max_force": out["max_force"],
            "min_curvature": min_curv,
            "reason": reason,
            "start": fallback or mode,
        }
        charges = structure.charges
        dipole = charges @ np.concatenate([cores, pairs])
        self.results = {
            "energy": out["energy"],
            "free_energy": out["energy"],
            "forces": out["forces"],
            "dipole": dipole,
        }
        self.history = (self.history + [(cores, pairs.copy())])[-self.n_history:]

    # -------------------------------------------------------------------- relaxations
    def _problem(self, structure: Structure):
        """``f(x) -> (energy, gradient of all particles)`` at fixed cores, graph built once."""
        model = self.model
        g = model.graph(structure, dtype=torch.float64)
        nc = structure.n_cores
        base = g.positions.detach()
        counter = {"n": 0}

        def evaluate(x: np.ndarray) -> tuple[float, np.ndarray]:
            counter["n"] += 1
            pos = torch.cat([base[:nc], torch.as_tensor(x.reshape(-1, 3))]).requires_grad_(True)
            e = model.energy(g, pos)[0]
            (grad,) = torch.autograd.grad(e, pos)
            return float(e.detach()), grad.numpy()

        return evaluate, counter

    def _exact_hessian(self, structure: Structure) -> np.ndarray:
        """Exact pair Hessian into ``self.hessian`` (vectorised Hessian-vector products); in
        ``"corrected"`` mode the pair and core-pair blocks by forward differences of the full
        gradient (3P + 1 evaluations, counted as one Hessian; faster than the
        forward-over-reverse products of all particles). Returns the pair Hessian."""
        m = 3 * structure.n_pairs
        if not m:
            self.hessian = np.zeros((0, 0))
        elif not self.correct:
            self.hessian = pair_hessian(self.model, structure)
        else:
            evaluate, _ = self._problem(structure)
            self.hessian, self.coupling = _hessian_columns(evaluate, structure.pairs,
                                                           structure.n_cores)
            self.model_error = 0.0  # exact models: only this step's measured errors count
        return self.hessian

    def _relax_warm(self, structure: Structure) -> dict:
        evaluate, counter = self._problem(structure)
        nc = structure.n_cores
        x = structure.pairs.copy()
        m = x.size
        n_hess = 0
        if self.hessian is None or self.hessian.shape != (m, m):
            self._exact_hessian(structure)
            n_hess += 1
            self.n_hessians += 1
        elif len(self.history):
            self.hessian = _rotate_hessian(self.hessian, self.history[-1][0], structure.positions)
        if self.coupling is None or self.coupling.shape != (3 * nc, m):
            self.coupling = np.zeros((3 * nc, m))  # (plain warm mode: unused)
            self.model_error = 1.0
        elif len(self.history):
            self.coupling = _rotate_hessian(self.coupling, self.history[-1][0],
                                            structure.positions)
        h, cp = self.hessian, self.coupling
        e, grad = evaluate(x)
        gp = grad[nc:].reshape(-1)
        converged = False
        #: relative model errors measured in this step (Newton contraction, coupling secant)
        errors: list[float] = []
        estimate = _max_norm(gp)
        for _ in range(self.max_iterations):
            fmax = _max_norm(gp)
            w, v = np.linalg.eigh(h)
            step = -v @ ((v.T @ gp) / np.maximum(w, _CURVATURE_FLOOR))
            if self.correct:
                # residual after the final Newton correction ~ model error x residual now;
                # the model error is the largest measured in this and the last step
                estimate = max(errors + [self.model_error]) * fmax if errors else fmax
            if fmax < self.fmax or estimate < self.fmax or m == 0:
                converged = True
                break
            longest = _max_norm(step)
            if longest > self.max_step:
                step *= self.max_step / longest
            t = 1.0
            while True:
                x_new = x + (t * step).reshape(-1, 3)
                e_new, grad_new = evaluate(x_new)
                gp_new = grad_new[nc:].reshape(-1)
                noise = 1e-12 * abs(e) + 1e-10
                decrease = e_new <= e + 1e-4 * t * float(gp @ step) + noise
                if decrease or (e_new <= e + noise and _max_norm(gp_new) < fmax):
                    break
                t *= 0.5
                if t < 1e-3:
                    break
            if t < 1e-3:
                break
            s = (t * step)[None]
            y = (gp_new - gp)[None]
            # secant of the core gradient: Broyden update of the coupling block
            sv = s[0]
            yc = (grad_new[:nc] - grad[:nc]).reshape(-1)
            miss = yc - cp @ sv
            errors.append(float(np.linalg.norm(miss) / max(np.linalg.norm(yc), 1e-300)))
            if t == 1.0:
                errors.append(_max_norm(gp_new) / max(fmax, 1e-300))
            cp = cp + np.outer(miss, sv) / max(float(sv @ sv), 1e-300)
            h = damped_bfgs(torch.as_tensor(h)[None], torch.as_tensor(s),
                             torch.as_tensor(y))[0].numpy()
            x, e, grad, gp = x_new, e_new, grad_new, gp_new
        self.hessian, self.coupling = h, cp
        if errors:
            self.model_error = min(1.0, max(errors))
        self.n_evaluations += counter["n"]
        raw = _max_norm(gp)
        gc = grad[:nc].reshape(-1)
        if self.correct and m and converged:
            # final Newton correction with the models: pairs, energy (to second order) and
            # core gradient g_c + C s (no evaluation)
            x = x + step.reshape(-1, 3)
            e = e + float(gp @ step) + 0.5 * float(step @ h @ step)
            gc = gc + cp @ step
        return {"pairs": x, "energy": e, "forces": -gc.reshape(-1, 3), "converged": converged,
                "n_evaluations": counter["n"], "n_hessians": n_hess,
                "max_force": estimate if self.correct else raw, "raw_max_force": raw}

    def _relax_paper(self, structure: Structure) -> dict:
        evaluate, counter = self._problem(structure)
        nc = structure.n_cores
        cores = structure.positions
        x0 = structure.pairs.reshape(-1)
        if self.history:
            max_disp = 3.0 * float(np.max(np.abs(cores - self.history[-1][0])))
        else:
            max_disp = 0.1
        bounds = [(v - max_disp, v + max_disp) for v in x0]
        cache: dict[bytes, tuple[float, np.ndarray]] = {}

        def fun(x):
            e, grad = evaluate(x)
            cache.clear()
            cache[x.tobytes()] = (e, grad)
            return e, grad[nc:].reshape(-1)

        res = scipy.optimize.minimize(
            fun, x0, jac=True, method="L-BFGS-B", bounds=bounds,
            options={"gtol": self.fmax, "ftol": 0.0, "maxiter": 10 * self.max_iterations},
        )
        x = np.asarray(res.x, float)
        e, grad = cache[x.tobytes()] if x.tobytes() in cache else evaluate(x)
        gp = grad[nc:].reshape(-1)
        lo, hi = x0 - max_disp, x0 + max_disp
        projected = np.where(((x <= lo) & (gp > 0)) | ((x >= hi) & (gp < 0)), 0.0, gp)
        # converged: L-BFGS-B's gtol reached, or stopped by the line search within 10x gtol
        ok = bool(res.success) or float(np.max(np.abs(projected), initial=0.0)) < 10 * self.fmax
        self.n_evaluations += counter["n"]
        return {"pairs": x.reshape(-1, 3), "energy": e, "forces": -grad[:nc],
                "converged": ok, "n_evaluations": counter["n"], "n_hessians": 0,
                "max_force": _max_norm(projected)}


def _hessian_columns(evaluate: Callable[[np.ndarray], tuple[float, np.ndarray]],
                     pairs: np.ndarray, n_cores: int,
                     h: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """Pair-pair (3P, 3P) and core-pair (3N, 3P) Hessian blocks (eV/Å^2) by forward
    differences of the gradient of all particles, ``evaluate(pairs) -> (energy, gradient)``:
    3P + 1 gradient evaluations (step ``h`` Å; error ~1e-4 relative, which is far below the
    ~2 % the blocks change per MD step)."""
    x = np.asarray(pairs, float).reshape(-1)
    g0 = evaluate(x.reshape(-1, 3))[1].reshape(-1)
    cols = np.empty((g0.size, x.size))
    for k in range(x.size):
        xk = x.copy()
        xk[k] += h
        cols[:, k] = (evaluate(xk.reshape(-1, 3))[1].reshape(-1) - g0) / h
    hpp = cols[3 * n_cores:]
    return 0.5 * (hpp + hpp.T), cols[:3 * n_cores].copy()


#: polynomial extrapolation x(n+1) from x(n-k..n), oldest first
_EXTRAPOLATION = {0: [1.0], 1: [-1.0, 2.0], 2: [1.0, -3.0, 3.0], 3: [-1.0, 4.0, -6.0, 4.0],
                  4: [1.0, -5.0, 10.0, -10.0, 5.0]}


def _max_norm(v: np.ndarray) -> float:
    """Largest |component| of a flat (3P,) pair-force vector (0 when empty): the criterion of
    L-BFGS-B's ``gtol`` (the reference's), used by both relaxation modes."""
    return float(np.max(np.abs(v), initial=0.0))


def _nearest(pairs: np.ndarray, cores: np.ndarray) -> np.ndarray:
    return np.argmin(np.linalg.norm(pairs[:, None] - cores[None], axis=-1), axis=1)


def _rotate_hessian(h: np.ndarray, old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """A Hessian block ``h`` (3a, 3b) turned with the best rotation (Kabsch) of cores ``old``
    onto ``new``: ``R H R^T`` 3x3 block by block."""
    a = old - old.mean(0)
    b = new - new.mean(0)
    if len(a) < 3:
        return h
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rot = (u @ np.diag([1.0, 1.0, d]) @ vt).T  # new ≈ R old
    hb = h.reshape(h.shape[0] // 3, 3, h.shape[1] // 3, 3)
    return np.einsum("ab,ibjc,dc->iajd", rot, hb, rot).reshape(h.shape)


# ------------------------------------------------------------------------------ watchdog
@dataclass
class Watchdog:
    """Checks of the pairs after every MD step (Å, eV/Å^2)."""

    min_pair_distance: float = 0.2
    max_core_distance: float = 2.0
    #: exact pair Hessian (positive curvature) every this many steps (0: never)
    curvature_every: int = 50

    def check(self, cores: np.ndarray, pairs: np.ndarray, diagnostics: dict) -> str:
        """Empty string when fine, else the reasons."""
        reasons = []
        if diagnostics.get("reason"):
            reasons.append(diagnostics["reason"])
        if len(pairs) > 1:
            d = np.linalg.norm(pairs[:, None] - pairs[None], axis=-1)
            d[np.diag_indices(len(pairs))] = np.inf
            if d.min() < self.min_pair_distance:
                i, j = np.unravel_index(np.argmin(d), d.shape)
                reasons.append(f"pairs {i} and {j} are {d.min():.3g} Å apart (merged;"
                               f" threshold {self.min_pair_distance:g} Å)")
        if len(pairs):
            dc = np.linalg.norm(pairs[:, None] - cores[None], axis=-1).min(axis=1)
            if dc.max() > self.max_core_distance:
                k = int(np.argmax(dc))
                reasons.append(f"pair {k} is {dc[k]:.3g} Å from the nearest core"
                               f" (threshold {self.max_core_distance:g} Å)")
        curv = diagnostics.get("min_curvature", float("nan"))
        if np.isfinite(curv) and curv <= 0:
            reasons.append(f"negative pair curvature {curv:.3g} eV/Å^2 (saddle, not a minimum)")
        return "; ".join(reasons)


# ------------------------------------------------------------------------------ driver
@dataclass
class MDResult:
    """Summary of a run (counts, eV, K, s); per-step figures cover steps 1..``steps`` of the
    whole run (resumed parts included, the initial relaxation of step 0 excluded)."""

    output: str
    steps: int
    frames: int
    watchdog_events: int
    evaluations_per_step: float
    hessians_per_step: float
    seconds_per_step: float
    final_temperature: float
    final_conserved_energy: float
    relax: str
    ensemble: str
    resumed_from: int = 0
    events: list = field(default_factory=list)


def run_md(
    model: EMLP | str | Path,
    structure: Structure,
    steps: int,
    output: str | Path,
    dt_fs: float = 0.5,
    temperature_K: float | None = 300.0,
    ensemble: str = "nvt",
    field=None,
    seed: int = 0,
    tdamp_fs: float = 100.0,
    tchain: int = 3,
    relax: str = "warm",
    fmax: float = 1e-5,
    record_every: int = 1,
    checkpoint_every: int = 10,
    log_every: int = 10,
    resume: bool = True,
    watchdog: Watchdog | None = None,
    extrapolation: int = 3,
    guess_method: str = "auto",
    callback: Callable[[int, Atoms, BOPairCalculator], None] | None = None,
    logger: logging.Logger | None = None,
) -> MDResult:
    """Run (or resume) Born-Oppenheimer MD of ``structure`` for ``steps`` steps in total.

    Args:
        model: the eMLP or a checkpoint path (evaluated in float64).
        structure: start (cores; pairs may be empty: guessed and relaxed). Velocities (Å/fs)
            in ``structure.info["velocities"]`` (flat or (N, 3)) are used when present.
        steps: total number of MD steps (a resumed run continues up to it).
        output: output directory (trajectory, checkpoint, log, summary).
        dt_fs: time step (fs).
        temperature_K: NVT target and initial Maxwell-Boltzmann temperature (K); ``None``
            starts at rest (NVE only).
        ensemble: ``"nvt"`` (Nosé-Hoover chain, ``tchain``, ``tdamp_fs``) or ``"nve"``.
        field: homogeneous field (V/Å); default ``structure.field``.
        seed: seed of the initial velocities.
        relax: ``"warm"``, ``"corrected"`` or ``"paper"`` (see the module docstring).
        fmax: pair-relaxation tolerance (eV/Å).
        record_every: a trajectory frame every this many steps (step 0 included).
        checkpoint_every: frames are appended and the checkpoint written every this many steps.
        resume: continue from ``output/checkpoint.npz`` when it exists.
        watchdog: the checks (:class:`Watchdog`).
        callback: called after every accepted step as ``callback(step, atoms, calc)``.
    """
    if ensemble not in ("nvt", "nve"):
        raise ValueError(f"ensemble must be 'nvt' or 'nve', not {ensemble!r}")
    if ensemble == "nvt" and temperature_K is None:
        raise ValueError("NVT needs temperature_K")
    if structure.pbc:
        raise ValueError(f"{structure.source}: run_md supports molecules only (no cell)")
    watchdog = watchdog or Watchdog()
    out_dir = Path(output)
    out_dir.mkdir(parents=True, exist_ok=True)
    log = logger or _file_logger(out_dir / LOG)
    if isinstance(model, (str, Path)):
        model = load_model(model, torch.float64)
    model = model.double().eval()
    flags = [(p, p.requires_grad) for p in model.parameters()]
    for p, _ in flags:
        p.requires_grad_(False)
    field_v = structure.field if field is None else np.asarray(field, float).reshape(3)
    signature = {
        "numbers": structure.numbers.tolist(), "dt_fs": dt_fs, "temperature_K": temperature_K,
        "ensemble": ensemble, "field": field_v.tolist(), "seed": seed, "tdamp_fs": tdamp_fs,
        "tchain": tchain, "relax": relax, "fmax": fmax, "record_every": record_every,
        "extrapolation": extrapolation,
    }
    try:
        return _Run(model, structure, field_v, out_dir, log, signature, watchdog,
                    guess_method, callback).run(steps, resume, checkpoint_every, log_every)
    finally:
        for p, flag in flags:
            p.requires_grad_(flag)


class _Run:
    def __init__(self, model, structure, field_v, out_dir, log, sig, watchdog, guess_method,
                 callback):
        self.model, self.s0, self.field = model, structure, field_v
        self.dir, self.log, self.sig = out_dir, log, sig
        self.watchdog, self.guess_method, self.callback = watchdog, guess_method, callback
        self.traj = out_dir / TRAJECTORY
        self.ckpt = out_dir / CHECKPOINT
        self.atoms = Atoms(structure.numbers, structure.positions)
        self.calc = BOPairCalculator(model, structure.pairs, field_v, relax=sig["relax"],
                                     fmax=sig["fmax"], charge=structure.charge,
                                     extrapolation=sig["extrapolation"])
        self.atoms.calc = self.calc
        dt = sig["dt_fs"] * ase.units.fs
        if sig["ensemble"] == "nvt":
            self.dyn = NoseHooverChainNVT(self.atoms, dt, sig["temperature_K"],
                                          sig["tdamp_fs"] * ase.units.fs, tchain=sig["tchain"])
        else:
            self.dyn = VelocityVerlet(self.atoms, dt)
        self.step = 0
        self.events: list[dict] = []
        self.buffer: list[Structure] = []
        self.frames = 0
        self.step_evals = 0
        self.step_hess = 0
        self.wall = 0.0
        #: evaluations, Hessians and seconds spent before step 1 (the initial relaxation)
        self.base = [0, 0, 0.0]

    # -------------------------------------------------------------- state
    def snapshot(self) -> dict:
        snap = {
            "positions": self.atoms.positions.copy(),
            "momenta": self.atoms.get_momenta().copy(),
            "calc": self.calc.state(),
        }
        if isinstance(self.dyn, NoseHooverChainNVT):
            snap["eta"] = self.dyn._thermostat._eta.copy()
            snap["p_eta"] = self.dyn._thermostat._p_eta.copy()
        return snap

    def restore(self, snap: dict) -> None:
        self.atoms.calc = None
        self.atoms.positions[:] = snap["positions"]
        self.atoms.set_momenta(snap["momenta"])
        self.calc.set_state(snap["calc"], self.atoms)
        self.atoms.calc = self.calc
        if isinstance(self.dyn, NoseHooverChainNVT):
            self.dyn._thermostat._eta[:] = snap["eta"]
            self.dyn._thermostat._p_eta[:] = snap["p_eta"]
            self.dyn._q = self.atoms.get_positions()
            self.dyn._p = self.atoms.get_momenta()

    def thermostat_energy(self) -> float:
        if isinstance(self.dyn, NoseHooverChainNVT):
            return float(self.dyn._thermostat.get_thermostat_energy())
        return 0.0

    # -------------------------------------------------------------- checkpoint
    def write_checkpoint(self) -> None:
        snap = self.snapshot()
        c = snap.pop("calc")
        hist = c.pop("history")
        arrays = {
            "positions": snap["positions"], "momenta": snap["momenta"],
            "eta": snap.get("eta", np.zeros(0)), "p_eta": snap.get("p_eta", np.zeros(0)),
            "start_pairs": c["start_pairs"],
            "hessian": np.zeros((0, 0)) if c["hessian"] is None else c["hessian"],
            "coupling": np.zeros((0, 0)) if c["coupling"] is None else c["coupling"],
            "history_cores": np.array([h[0] for h in hist]),
            "history_pairs": np.array([h[1] for h in hist]),
            "forces": c["results"]["forces"],
            "dipole": c["results"]["dipole"],
        }
        meta = {
            "signature": self.sig, "step": self.step, "frames": self.frames,
            "trajectory_bytes": self.traj.stat().st_size if self.traj.exists() else 0,
            "energy": c["results"]["energy"], "diagnostics": _jsonable(c["diagnostics"]),
            "n_evaluations": c["n_evaluations"], "n_hessians": c["n_hessians"],
            "events": self.events, "wall": self.wall,
            "has_hessian": c["hessian"] is not None, "base": self.base,
            "has_coupling": c["coupling"] is not None, "model_error": c["model_error"],
        }
        arrays["meta"] = np.array(json.dumps(meta))
        tmp = self.ckpt.with_name(f".{CHECKPOINT}.tmp.npz")
        np.savez(tmp, **arrays)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, self.ckpt)

    def load_checkpoint(self) -> bool:
        if not self.ckpt.exists():
            return False
        with np.load(self.ckpt) as data:
            a = {k: data[k] for k in data.files}
        meta = json.loads(str(a["meta"]))
        if meta["signature"] != _jsonable(self.sig):
            diff = sorted(k for k in self.sig if meta["signature"].get(k) != _jsonable(self.sig[k]))
            raise ValueError(
                f"{self.ckpt}: the checkpoint belongs to a different run (differs in {diff});"
                " use another output directory or start over (resume=False, emlp md --no-resume)")
        results = {"energy": meta["energy"], "free_energy": meta["energy"],
                   "forces": a["forces"], "dipole": a["dipole"]}
        calc_state = {
            "history": list(zip(a["history_cores"], a["history_pairs"], strict=True)),
            "start_pairs": a["start_pairs"],
            "hessian": a["hessian"] if meta["has_hessian"] else None,
            "coupling": a["coupling"] if meta.get("has_coupling") else None,
            "model_error": meta.get("model_error", 1.0),
            "results": results, "atoms_positions": a["positions"],
            "diagnostics": meta["diagnostics"], "n_evaluations": meta["n_evaluations"],
            "n_hessians": meta["n_hessians"],
        }
        snap = {"positions": a["positions"], "momenta": a["momenta"], "calc": calc_state,
                "eta": a["eta"], "p_eta": a["p_eta"]}
        self.restore(snap)
        self.step, self.frames = meta["step"], meta["frames"]
        self.events, self.wall = meta["events"], meta["wall"]
        self.base = meta["base"]
        # cut the trajectory back to what the checkpoint covers (drops a partial frame)
        size = meta["trajectory_bytes"]
        if not self.traj.exists() or self.traj.stat().st_size < size:
            raise ValueError(f"{self.traj}: shorter than the checkpoint says ({size} bytes);"
                             " the trajectory was modified, start a new run")
        with open(self.traj, "r+b") as fh:
            fh.truncate(size)
        return True

    # -------------------------------------------------------------- frames
    def frame(self) -> Structure:
        atoms, calc = self.atoms, self.calc
        d = calc.diagnostics
        kin = float(atoms.get_kinetic_energy())
        pot = float(calc.results["energy"])
        thermo = self.thermostat_energy()
        info = {
            "step": int(self.step),
            "time": float(self.step * self.sig["dt_fs"]),
            "potential_energy": pot,
            "kinetic_energy": kin,
            "thermostat_energy": thermo,
            "conserved_energy": kin + pot + thermo,
            "temperature": float(atoms.get_temperature()),
            "dipole": np.asarray(calc.results["dipole"], float).copy(),
            "relax_evaluations": int(self.step_evals),
            "relax_hessians": int(self.step_hess),
            "relax_max_force": float(d.get("max_force", 0.0)),
            "watchdog_events": len(self.events),
            "velocities": (atoms.get_velocities() * ase.units.fs).reshape(-1),
        }
        return Structure(atoms.numbers, atoms.positions.copy(), calc.pairs.copy(),
                         field=self.field, charge=self.s0.charge, energy=pot,
                         forces=np.asarray(calc.results["forces"]).copy(), info=info)

    def flush(self) -> None:
        """Append the buffered frames (fsync), then write the checkpoint atomically."""
        if self.buffer:
            tmp = self.dir / f".{TRAJECTORY}.chunk"
            write_structures(tmp, self.buffer)
            data = tmp.read_bytes()
            tmp.unlink()
            with open(self.traj, "ab") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            self.frames += len(self.buffer)
            self.buffer = []
        self.write_checkpoint()

    # -------------------------------------------------------------- stepping
    def attempt(self, advance: Callable[[], None]) -> str:
        try:
            advance()
        except CalculationFailed as exc:
            return str(exc)
        d = self.calc.diagnostics
        self.step_evals += d["n_evaluations"]
        self.step_hess += d["n_hessians"]
        return self.watchdog.check(self.atoms.positions, self.calc.pairs, d)

    def guarded(self, advance: Callable[[], None], what: str) -> None:
        """Run ``advance`` with the watchdog: roll back and retry from fallback pairs."""
        snap = self.snapshot()
        self.step_evals = self.step_hess = 0
        every = self.watchdog.curvature_every
        if every and self.step % every == 0:
            self.calc.want_curvature = True
        reason = self.attempt(advance)
        if not reason:
            return
        tried = [f"{self.calc.diagnostics.get('start', 'start')}: {reason}"]
        # rigid follow needs a last good step; at the start only the fresh guess is left
        fallbacks = ["rigid", "guess"] if snap["calc"]["history"] else ["guess"]
        for fb in fallbacks:
            event = {"step": self.step, "reason": reason, "fallback": fb}
            self.events.append(event)
            self.log.warning("watchdog: %s %d: %s -> roll back, retry from %s pairs",
                             what, self.step, reason, fb)
            evals, hess = self.step_evals, self.step_hess
            self.restore(snap)
            self.step_evals, self.step_hess = evals, hess
            self.calc.fallback = fb
            self.calc.want_curvature = True
            reason = self.attempt(advance)
            event["ok"] = not reason
            if not reason:
                self.log.warning("watchdog: %s %d recovered from %s pairs", what, self.step, fb)
                return
            tried.append(f"{fb}: {reason}")
        failed = self.step
        self.restore(snap)
        if what == "step":  # keep everything up to the last good step
            self.step -= 1
            self.flush()
            kept = f"the trajectory and checkpoint up to step {self.step} are in {self.dir}"
        else:
            kept = "nothing written"
        raise MDWatchdogError(
            f"MD {what} {failed}: the electron pairs could not be relaxed ("
            + " | ".join(tried) + f"); stopped, {kept}")

    def initial(self) -> None:
        """Velocities and the relaxed pairs of step 0."""
        sig = self.sig
        vel = self.s0.info.get("velocities")
        if vel is not None:
            self.atoms.set_velocities(np.asarray(vel, float).reshape(-1, 3) / ase.units.fs)
        elif sig["temperature_K"]:
            rng = np.random.default_rng(sig["seed"])
            MaxwellBoltzmannDistribution(self.atoms, temperature_K=sig["temperature_K"], rng=rng)
            Stationary(self.atoms)
            if len(self.atoms) > 1:
                ZeroRotation(self.atoms)
        if isinstance(self.dyn, NoseHooverChainNVT):
            self.dyn._q = self.atoms.get_positions()
            self.dyn._p = self.atoms.get_momenta()
        if self.s0.n_pairs == 0:
            self.log.info("no electron pairs in the start structure: guess_pairs + relaxation")
            self.calc.start_pairs = self.calc._guess(self.atoms, self.guess_method)
        self.guarded(lambda: self.atoms.get_forces(), "start")

    def run(self, steps: int, resume: bool, checkpoint_every: int, log_every: int) -> MDResult:
        resumed = 0
        if resume and self.load_checkpoint():
            resumed = self.step
            self.log.info("resuming from step %d (%d frames) in %s", self.step, self.frames,
                          self.dir)
        else:
            for path in (self.traj, self.ckpt):
                if path.exists():
                    path.unlink()
            self.log.info("MD %s: %d steps, dt %g fs, T %s K, field %s V/Å, relax %s, %d cores,"
                          " %d pairs -> %s", self.sig["ensemble"].upper(), steps,
                          self.sig["dt_fs"], self.sig["temperature_K"], self.sig["field"],
                          self.sig["relax"], len(self.atoms), len(self.calc.start_pairs),
                          self.dir)
            t0 = time.perf_counter()
            self.initial()
            self.wall += time.perf_counter() - t0
            self.base = [self.calc.n_evaluations, self.calc.n_hessians, self.wall]
            self.buffer.append(self.frame())
            self.flush()
        if self.step >= steps:
            self.log.info("the run is complete (%d steps); nothing to do", self.step)
        evals0, hess0, wall0 = self.base
        step0 = 0
        record = self.sig["record_every"]
        try:
            while self.step < steps:
                t0 = time.perf_counter()
                self.step += 1
                self.guarded(self.dyn.step, "step")
                self.wall += time.perf_counter() - t0
                if self.step % record == 0:
                    self.buffer.append(self.frame())
                if self.callback is not None:
                    self.callback(self.step, self.atoms, self.calc)
                if self.step % checkpoint_every == 0 or self.step == steps:
                    self.flush()
                if self.step % log_every == 0 or self.step == steps:
                    f = self.frame()
                    done = max(self.step - step0, 1)
                    self.log.info(
                        "step %d t %.1f fs T %.1f K Epot %.6f eV Econs %.6f eV evals/step %.2f"
                        " s/step %.4f events %d", self.step, f.info["time"],
                        f.info["temperature"], f.info["potential_energy"],
                        f.info["conserved_energy"],
                        (self.calc.n_evaluations - evals0) / done, (self.wall - wall0) / done,
                        len(self.events))
        except MDWatchdogError:
            raise
        except BaseException:
            # interrupted: keep the frames and checkpoint of the last complete flush only
            self.buffer = []
            raise
        done = max(self.step - step0, 1)
        f = self.frame()
        result = MDResult(
            output=str(self.dir), steps=self.step, frames=self.frames,
            watchdog_events=len(self.events),
            evaluations_per_step=(self.calc.n_evaluations - evals0) / done,
            hessians_per_step=(self.calc.n_hessians - hess0) / done,
            seconds_per_step=(self.wall - wall0) / done,
            final_temperature=f.info["temperature"],
            final_conserved_energy=f.info["conserved_energy"],
            relax=self.sig["relax"], ensemble=self.sig["ensemble"], resumed_from=resumed,
            events=self.events,
        )
        atomic_write(self.dir / SUMMARY, lambda fh: json.dump(asdict(result), fh, indent=1))
        self.log.info("done: %d steps, %d frames, %d watchdog events, %.2f evaluations/step,"
                      " %.3f Hessians/step, %.4f s/step", result.steps, result.frames,
                      result.watchdog_events, result.evaluations_per_step,
                      result.hessians_per_step, result.seconds_per_step)
        return result


def _jsonable(obj):
    return json.loads(json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist")
                                 else float(o)))


def _file_logger(path: Path) -> logging.Logger:
    log = logging.getLogger(f"emlpack.md.{path.resolve()}")
    log.setLevel(logging.INFO)
    log.propagate = False
    if not log.handlers:
        fmt = logging.Formatter("%(asctime)s %(levelname)s %(message)s")
        fh = logging.FileHandler(path)
        fh.setFormatter(fmt)
        log.addHandler(fh)
        sh = logging.StreamHandler()
        sh.setFormatter(fmt)
        log.addHandler(sh)
    return log

