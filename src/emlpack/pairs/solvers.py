"""Electron-pair solvers as strategies behind one interface, :class:`PairSolver`.

A solver relaxes the electron pairs of one structure at fixed cores, starting from the
structure's pairs (and, for the warm-start solvers, from what it kept of earlier calls), and
returns a :class:`~emlpack.pairs.relax.RelaxResult` (pairs, energy, pair forces, diagnostics,
``reason`` from :func:`emlpack.pairs.checks.check_pairs`; the warm-start solvers also give the
core forces). :class:`emlpack.calculators.ase.EMLPCalculator` takes any of them (``pair_solver=``).

* :class:`BatchedSolver`: :func:`~emlpack.pairs.relax.relax_pairs` (default quasi-Newton with
  the analytic electrostatic pair Hessian, or exact Newton: ``RelaxOptions.initial_hessian``);
  stateless, many structures at once with :meth:`BatchedSolver.relax_many`.
* :class:`WarmStartSolver` (MD, ``method="warm"``): the pairs are extrapolated from the last
  relaxed steps (cubic in the offsets of each pair from its nearest core, so pairs follow their
  cores) and relaxed by a quasi-Newton method whose pair-Hessian model is carried over from
  call to call (rotated with the molecule, refined by damped BFGS updates, replaced by the
  exact pair Hessian at a fresh start); ``method="corrected"`` (MD's default) adds a carried
  secant model of the core-pair Hessian block, the linear-response predictor, the model-error
  stopping rule and a final Newton correction of pairs, energy and core forces without an
  evaluation; see docs/md.md. The curvature check (``want_curvature``) is a Davidson
  iteration on forward-difference Hessian-vector products preconditioned by the carried model
  (:func:`emlpack.pairs.relax.davidson_min_curvature`; ~6 evaluations instead of the exact
  blocks, :func:`exact_blocks`), whose products also refine the models.
* :class:`BoxedLBFGSB` (MD, the paper's scheme): SciPy L-BFGS-B from the previous pairs with
  every coordinate boxed to ±3x the largest core displacement since the last call (0.1 Å on
  the first), ``gtol`` = ``fmax``.

The warm-start solvers keep their state (:meth:`WarmStartSolver.state`,
:meth:`~WarmStartSolver.set_state`) for an MD driver's rollback and checkpoints, and take a
one-shot ``restart`` (``"rigid"``: the last relaxed pairs carried with their cores,
:func:`emlpack.geometry.carry_pairs`; ``"guess"``: :func:`emlpack.pairs.guess.guess_matched`)
and ``want_curvature`` (smallest exact pair-Hessian eigenvalue at the result) from the
driver's watchdog policy; a ``"guess"`` restart with no guess to give (neither Foster-Boys nor
a Lewis structure at these cores) raises :class:`ase.calculators.calculator.CalculationFailed`,
a failed attempt for the watchdog like a failed relaxation.
A fresh start (first call or a restart) is relaxed by :func:`relax_pairs` first.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import scipy.optimize
import torch
from ase.calculators.calculator import CalculationFailed
from scipy.linalg.lapack import dpotrf as _potrf
from scipy.linalg.lapack import dpotrs as _potrs

from emlpack.errors import EmlpackError
from emlpack.geometry import carry_pairs, nearest_cores
from emlpack.nn.potential import EMLP
from emlpack.pairs.checks import check_pairs
from emlpack.pairs.guess import guess_matched
from emlpack.pairs.relax import (
    RelaxOptions,
    RelaxResult,
    damped_bfgs,
    davidson_min_curvature,
    pair_hessian,
    relax_pairs,
)
from emlpack.properties.hessian import extended_hessian, standard_energy
from emlpack.structure import Structure

__all__ = ["PairSolver", "BatchedSolver", "WarmStartSolver", "BoxedLBFGSB", "md_solver"]

#: smallest curvature (eV/Å^2) of the warm-start quasi-Newton step model
_CURVATURE_FLOOR = 1e-2
#: the condition number (estimated from the Cholesky factor's diagonal) beyond which
#: ``_floored_solve`` does not trust a Cholesky factorisation to tell a positive definite
#: model from an indefinite one (rounding of 1e17 eV/Å^2 curvatures swamps eigenvalues of
#: tens of eV/Å^2); at most 2.3e2 and 4.8e2 in 200 MD steps of 3-(methylamino)but-2-enal and
#: butanenitrile with mini-eqm7, 1e16 where a noaug-s1 MD run had merged two pairs
_CHOLESKY_MAX_CONDITION = 1e12
#: a measured relative model error above this replaces the carried models by exact blocks
#: at the next call (measured on hexane with the trained benchmark model: 0.01-0.25)
_REFRESH_ERROR = 0.5
#: polynomial extrapolation x(n+1) from x(n-k..n), oldest first
_EXTRAPOLATION = {0: [1.0], 1: [-1.0, 2.0], 2: [1.0, -3.0, 3.0], 3: [-1.0, 4.0, -6.0, 4.0],
                  4: [1.0, -5.0, 10.0, -10.0, 5.0]}


@runtime_checkable
class PairSolver(Protocol):
    """Relaxes the electron pairs of ``structure`` (its pairs: the start) at fixed cores."""

    def relax(self, model: EMLP, structure: Structure) -> RelaxResult:
        """Relaxed pairs (Å), energy (eV), pair forces (eV/Å), diagnostics and ``reason``."""
        ...

    def reset(self) -> None:
        """Forget any warm-start state (the next call starts fresh)."""
        ...


@dataclass
class BatchedSolver:
    """:func:`~emlpack.pairs.relax.relax_pairs` with ``options`` (stateless)."""

    options: RelaxOptions = field(default_factory=RelaxOptions)

    def relax(self, model: EMLP, structure: Structure) -> RelaxResult:
        """Relax the pairs of ``structure`` with :func:`~emlpack.pairs.relax.relax_pairs`."""
        return relax_pairs(model, structure, self.options)[0]

    def relax_many(self, model: EMLP, structures: Sequence[Structure]) -> list[RelaxResult]:
        """All ``structures`` in one batch."""
        return relax_pairs(model, structures, self.options)

    def reset(self) -> None:
        """Nothing to forget (stateless)."""


#: "corrected" stops when its estimate of the residual after the final (unevaluated) Newton
#: correction is below this fraction of ``fmax``: the estimate (model error x residual) was up
#: to 5.7x below the evaluated residual on single steps, and at fmax/2 no step of
#: benchmarks/md.py ended above fmax (at 1x: 8 of 100, up to 1.7 fmax)
CORRECTED_MARGIN = 0.5


class WarmStartSolver:
    """MD's pair solver: extrapolated start + carried-Hessian quasi-Newton (float64, molecules).

    Args:
        method: ``"warm"`` or ``"corrected"`` (see the module docstring).
        fmax: largest pair-force component at convergence, eV/Å (``"corrected"``: evaluated,
            or estimated after its final Newton correction with ``CORRECTED_MARGIN``).
        max_iterations: quasi-Newton iterations per call.
        max_step: largest pair displacement per iteration (Å).
        extrapolation: order of the start extrapolation (0 rigid ... 4 quartic).

    ``history`` holds the relaxed (cores, pairs) of the last calls, newest last; ``diagnostics``
    the scalar diagnostics of the last call; ``n_evaluations``/``n_hessians`` the totals.
    """

    methods = ("warm", "corrected")
    #: name of the own start and method in ``diagnostics["start"]``
    label = "warm"
    #: the own method refines the carried pair-Hessian model (BoxedLBFGSB: it does not)
    carries_hessian = True

    def __init__(self, method: str = "warm", fmax: float = 1e-5, max_iterations: int = 50,
                 max_step: float = 0.2, extrapolation: int = 3) -> None:
        if method not in self.methods:
            raise ValueError(f"{type(self).__name__}: method must be one of {self.methods},"
                             f" not {method!r}")
        self.method = method
        #: "corrected": warm + final Newton correction of pairs, energy and core forces
        self.correct = method == "corrected"
        self.fmax = fmax
        self.max_iterations = max_iterations
        self.max_step = max_step
        self.extrapolation = extrapolation
        self.n_history = max(extrapolation + 1, 1)
        self.history: list[tuple[np.ndarray, np.ndarray]] = []
        self.hessian: np.ndarray | None = None
        #: secant (Broyden) model of the core-pair Hessian block d g_cores / d pairs, (3N, 3P)
        self.coupling: np.ndarray | None = None
        #: largest relative model error (pair Hessian or coupling) measured in the last steps
        self.model_error = 1.0
        #: one-shot start for the next call: None, "rigid" or "guess"
        self.restart: str | None = None
        #: smallest eigenvalue of the exact pair Hessian at the result of the next call
        self.want_curvature = False
        self.diagnostics: dict = {}
        self.n_evaluations = 0
        self.n_hessians = 0

    # -------------------------------------------------------------------- state
    def reset(self) -> None:
        """Forget the history, the carried models and a pending restart or curvature request (the
        next call starts fresh); the counters and diagnostics stay."""
        self.history = []
        self.hessian = self.coupling = None
        self.model_error = 1.0
        self.restart = None
        self.want_curvature = False

    def state(self) -> dict:
        """Everything needed to continue bit for bit (numpy arrays and numbers)."""
        return {
            "history": [(c.copy(), p.copy()) for c, p in self.history],
            "hessian": None if self.hessian is None else self.hessian.copy(),
            "coupling": None if self.coupling is None else self.coupling.copy(),
            "model_error": self.model_error,
            "diagnostics": copy.deepcopy(self.diagnostics),
            "n_evaluations": self.n_evaluations,
            "n_hessians": self.n_hessians,
        }

    def set_state(self, state: dict) -> None:
        """Continue from a :meth:`state` (a pending restart or curvature request is cleared)."""
        self.history = [(np.array(c, float), np.array(p, float)) for c, p in state["history"]]
        self.hessian = None if state["hessian"] is None else state["hessian"].copy()
        coupling = state.get("coupling")
        self.coupling = None if coupling is None else coupling.copy()
        self.model_error = float(state.get("model_error", 1.0))
        self.diagnostics = copy.deepcopy(state["diagnostics"])
        self.n_evaluations = state["n_evaluations"]
        self.n_hessians = state["n_hessians"]
        self.restart = None
        self.want_curvature = False

    @property
    def pairs(self) -> np.ndarray | None:
        """The relaxed pairs (Å) of the last call (None before the first)."""
        return self.history[-1][1] if self.history else None

    # -------------------------------------------------------------------- starts
    def rigid(self, structure: Structure) -> np.ndarray:
        """The last relaxed pairs carried with their nearest cores to ``structure``'s cores
        (``structure.pairs`` before the first call)."""
        if not self.history:
            return structure.pairs.copy()
        old_cores, pairs = self.history[-1]
        return carry_pairs(pairs, old_cores, structure.positions)

    def predict(self, cores: np.ndarray) -> np.ndarray:
        """Extrapolated pairs (Å) at the cores ``cores`` (needs a history): the offsets of every
        pair from its nearest core (assignment of the newest step) extrapolated to order
        ``extrapolation`` (0: rigid, 1: linear, 2: quadratic, 3: cubic, 4: quartic)."""
        order = min(self.extrapolation, len(self.history) - 1)
        coefficients = _EXTRAPOLATION[order]
        m = self.history[-1][1].size
        if (self.correct and order > 0 and self.coupling is not None
                and self.hessian is not None and self.coupling.shape == (cores.size, m)):
            # extrapolate pairs and cores alike, then the linear response of the pairs to the
            # cores' extrapolation error: dp = -H_pp^-1 H_pc dc (carried models, no evaluation)
            recent = self.history[-order - 1:]
            c_ex = sum(w * c for w, (c, _) in zip(coefficients, recent, strict=True))
            p_ex = sum(w * p for w, (_, p) in zip(coefficients, recent, strict=True))
            rhs = self.coupling.T @ (cores - c_ex).reshape(-1)
            dp = -_floored_solve(self.hessian, rhs)
            return p_ex + dp.reshape(-1, 3)
        nearest = nearest_cores(self.history[-1][1], self.history[-1][0])
        offsets = [p - c[nearest] for c, p in self.history]
        offset = sum(w * o for w, o in zip(coefficients, offsets[-order - 1:], strict=True))
        return cores[nearest] + offset

    def _start(self, structure: Structure) -> np.ndarray:
        """Start pairs of a call that is neither fresh nor a restart."""
        return self.predict(structure.positions)

    # -------------------------------------------------------------------- relaxation
    def relax(self, model: EMLP, structure: Structure) -> RelaxResult:
        """Relax the pairs of the molecule ``structure`` at fixed cores, warm-started from the
        earlier calls (see the module docstring), and keep a finite result in the history; the
        result includes the core forces (eV/Å)."""
        if structure.pbc:
            raise ValueError(f"{type(self).__name__}: molecules only (no cell)")
        cores = structure.positions.copy()
        restart, self.restart = self.restart, None
        if restart == "rigid":
            x0 = self.rigid(structure)
        elif restart == "guess":
            try:
                x0 = guess_matched(structure.numbers, cores, self.rigid(structure),
                                   structure.charge)
            except (EmlpackError, ValueError) as exc:  # no Boys and no Lewis structure here
                raise CalculationFailed(f"no fresh electron-pair guess: {exc}") from exc
        elif not self.history:
            x0 = structure.pairs.copy()
        else:
            x0 = self._start(structure)
        fresh = bool(restart) or not self.history
        if fresh:
            self.hessian = None  # fresh exact Hessian after a restart
            self.coupling = None
            self.model_error = 1.0
        structure = structure.copy(pairs=np.asarray(x0, float).reshape(-1, 3))
        n_pre = n_pre_hess = 0
        if fresh:
            # a fresh start may be far from the minimum: the robust batched relaxation first
            pre = relax_pairs(model, structure, fmax=self.fmax, max_iterations=50,
                              check_curvature=False)[0]
            n_pre, n_pre_hess = pre.n_evaluations, pre.n_hessians
            self.n_evaluations += n_pre
            self.n_hessians += n_pre_hess
            structure = structure.copy(pairs=pre.pairs)
        # restarts (and the warm-start solvers always) use the carried-Hessian quasi-Newton
        quasi_newton = bool(restart) or self.carries_hessian
        want_curv, self.want_curvature = self.want_curvature, False
        if quasi_newton:
            out = self._relax_warm(model, structure, want_curv)
        else:
            out = self._minimise(model, structure)
        out["n_evaluations"] += n_pre
        pairs = out["pairs"]
        min_curv = out.get("min_curvature", float("nan"))
        if want_curv and len(pairs) and not quasi_newton:
            # no carried model to precondition with: the exact pair Hessian
            exact = pair_hessian(model, structure.copy(pairs=pairs))
            self.n_hessians += 1
            out["n_hessians"] += 1
            min_curv = float(np.linalg.eigvalsh(exact)[0])
        finite = np.isfinite(out["energy"]) and np.all(np.isfinite(out["forces"]))
        if not finite:
            reason = "non-finite energy or forces after the pair relaxation"
        else:
            reason = check_pairs(pairs, cores, converged=out["converged"], fmax=self.fmax,
                                 max_force=out["max_force"], min_curvature=min_curv)
        start = restart or self.label
        self.diagnostics = {
            "converged": out["converged"],
            "n_evaluations": out["n_evaluations"],
            "n_hessians": out["n_hessians"],
            "max_force": out["max_force"],
            "min_curvature": min_curv,
            "reason": reason,
            "start": start,
            # largest pair-force component at the start pairs (eV/Å): the predictor's error
            "first_residual": out.get("first_residual", float("nan")),
        }
        if finite:
            self.history = (self.history + [(cores, pairs.copy())])[-self.n_history:]
        return RelaxResult(
            pairs=pairs.copy(), energy=float(out["energy"]),
            converged=out["converged"] and not reason, iterations=out["iterations"],
            n_evaluations=out["n_evaluations"], n_hessians=out["n_hessians"] + n_pre_hess,
            max_force=out["max_force"], min_curvature=min_curv, reason=reason,
            pair_forces=out["pair_forces"], forces=out["forces"], start=start)

    def _exact_hessian(self, model: EMLP, structure: Structure) -> np.ndarray:
        """Exact pair Hessian into ``self.hessian`` (:func:`pair_hessian`); in
        ``"corrected"`` mode the pair and core-pair blocks (:func:`exact_blocks`, counted as
        one Hessian). Returns the pair Hessian."""
        m = 3 * structure.n_pairs
        if not m:
            self.hessian = np.zeros((0, 0))
        elif not self.correct:
            self.hessian = pair_hessian(model, structure)
        else:
            self.hessian, self.coupling = exact_blocks(model, structure)
            self.model_error = 0.0  # exact models: only this step's measured errors count
        return self.hessian

    def _relax_warm(self, model: EMLP, structure: Structure, want_curvature: bool) -> dict:
        evaluate, counter = energy_gradient_function(model, structure)
        nc = structure.n_cores
        x = structure.pairs.copy()
        m = x.size
        n_hess = 0
        # the best rotation of the last step's cores onto these (one SVD for both blocks)
        rot = _kabsch(self.history[-1][0], structure.positions) if self.history else None
        if self.hessian is None or self.hessian.shape != (m, m):
            self._exact_hessian(model, structure)
            n_hess += 1
            self.n_hessians += 1
        elif rot is not None:
            self.hessian = _rotate_block(self.hessian, rot)
        if self.coupling is None or self.coupling.shape != (3 * nc, m):
            self.coupling = np.zeros((3 * nc, m))  # (plain warm mode: unused)
            self.model_error = 1.0
        elif rot is not None:
            self.coupling = _rotate_block(self.coupling, rot)
        h, cp = self.hessian, self.coupling
        e, grad = evaluate(x)
        gp = grad[nc:].reshape(-1)
        converged = False
        iterations = 0
        #: relative model errors measured in this step (Newton contraction, coupling secant)
        errors: list[float] = []
        estimate = first_residual = _max_norm(gp)
        for _ in range(self.max_iterations):
            fmax = _max_norm(gp)
            step = -_floored_solve(h, gp)
            if self.correct:
                # residual after the final Newton correction ~ model error x residual now;
                # the model error is the largest measured in this and the last step
                estimate = max(errors + [self.model_error]) * fmax if errors else fmax
            if fmax < self.fmax or estimate < CORRECTED_MARGIN * self.fmax or m == 0:
                converged = True
                break
            iterations += 1
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
            h = damped_bfgs(h[None], s, y)[0]
            x, e, grad, gp = x_new, e_new, grad_new, gp_new
        n_eval = counter["n"]
        min_curv = float("nan")
        n_products = 0
        if want_curvature and m:
            # the watchdog's curvature check: Davidson on forward-difference products of the
            # gradient, preconditioned by the carried model; every product is also an exact
            # secant of both carried blocks (BFGS / Broyden updates, no extra cost)
            h, cp, min_curv, n_products = _curvature_check(evaluate, x, grad, nc, h, cp)
            n_hess += 1
            self.n_hessians += 1
        self.hessian, self.coupling = h, cp
        if errors:
            self.model_error = min(1.0, max(errors))
            if self.correct and self.model_error > _REFRESH_ERROR:
                self.hessian = None  # stale models: exact blocks at the next call
        self.n_evaluations += n_eval
        raw = _max_norm(gp)
        gc = grad[:nc].reshape(-1)
        pair_forces = -gp.reshape(-1, 3)
        if self.correct and m and converged:
            # final Newton correction with the models: pairs, energy (to second order) and
            # core gradient g_c + C s (no evaluation)
            x = x + step.reshape(-1, 3)
            e = e + float(gp @ step) + 0.5 * float(step @ h @ step)
            gc = gc + cp @ step
        return {"pairs": x, "energy": e, "forces": -gc.reshape(-1, 3), "converged": converged,
                "n_evaluations": n_eval, "n_hessians": n_hess, "iterations": iterations,
                "max_force": estimate if self.correct else raw, "pair_forces": pair_forces,
                "min_curvature": min_curv, "curvature_products": n_products,
                "first_residual": first_residual}


class BoxedLBFGSB(WarmStartSolver):
    """The paper's MD pair relaxation: SciPy L-BFGS-B from the previous pairs, every coordinate
    boxed to ±3x the largest core displacement since the last call (0.1 Å on the first);
    ``fmax`` is L-BFGS-B's ``gtol`` (largest projected gradient component, eV/Å). Restarts and
    the first call use the warm-start quasi-Newton, as :class:`WarmStartSolver`."""

    methods = ("paper",)
    label = "paper"
    carries_hessian = False

    def __init__(self, method: str = "paper", fmax: float = 1e-5, max_iterations: int = 50,
                 max_step: float = 0.2, extrapolation: int = 3) -> None:
        super().__init__(method, fmax, max_iterations, max_step, extrapolation)

    def _start(self, structure: Structure) -> np.ndarray:
        return self.history[-1][1].copy()

    def _minimise(self, model: EMLP, structure: Structure) -> dict:
        evaluate, counter = energy_gradient_function(model, structure)
        nc = structure.n_cores
        cores = structure.positions
        x0 = structure.pairs.reshape(-1)
        if self.history:
            max_disp = 3.0 * float(np.max(np.abs(cores - self.history[-1][0])))
        else:
            max_disp = 0.1
        bounds = [(v - max_disp, v + max_disp) for v in x0]
        cache: dict[bytes, tuple[float, np.ndarray]] = {}

        def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
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
                "iterations": int(res.nit), "max_force": _max_norm(projected),
                "pair_forces": -gp.reshape(-1, 3)}


def md_solver(relax: str = "corrected", **kwargs) -> WarmStartSolver:
    """MD's pair solver by name: ``"corrected"`` (MD's default), ``"warm"``
    (:class:`WarmStartSolver`) or ``"paper"`` (:class:`BoxedLBFGSB`)."""
    if relax == "paper":
        return BoxedLBFGSB(**kwargs)
    if relax in WarmStartSolver.methods:
        return WarmStartSolver(relax, **kwargs)
    raise ValueError(f"relax must be 'warm', 'corrected' or 'paper', not {relax!r}")


def energy_gradient_function(
    model: EMLP, structure: Structure,
) -> tuple[Callable[[np.ndarray], tuple[float, np.ndarray]], dict]:
    """``f(pairs) -> (energy eV, gradient of all particles eV/Å (N + P, 3))`` at the fixed
    cores of ``structure`` (one molecule, float64; graph built once), and a counter dict whose
    ``"n"`` counts the evaluations."""
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


def exact_blocks(model: EMLP, structure: Structure) -> tuple[np.ndarray, np.ndarray]:
    """Pair-pair (3P, 3P) and core-pair (3N, 3P) blocks (eV/Å^2) of the position Hessian of a
    molecule at its pairs, exactly: the fast extended Hessian
    (:func:`emlpack.properties.hessian.extended_hessian`) for EMLP's own energy (closed-form
    electrostatics, the short range by its family), else the pairs' rows by reverse over
    reverse of the whole energy (:func:`_pair_rows`). Measured with member 0 of
    ``mini-eqm7``, 1 thread: hexane (19 pairs) 0.17-0.23 s instead of 0.78-0.83 s for forward
    differences (:func:`difference_blocks`, used before for other models), C4H7NO2 (20 pairs)
    0.14-0.17 s instead of 0.96-1.04 s; the differences' errors 4e-6-3e-5 relative."""
    k, n = 3 * structure.n_cores, 3 * (structure.n_cores + structure.n_pairs)
    if not standard_energy(model):
        rows = _pair_rows(model, structure)
        hpp = rows[:, k:n]
        return 0.5 * (hpp + hpp.T), rows[:, :k].T.copy()
    h = extended_hessian(model, structure)[1].numpy()
    hpp = h[k:n, k:n]
    return 0.5 * (hpp + hpp.T), h[:k, k:n].copy()


def _pair_rows(model: EMLP, structure: Structure) -> np.ndarray:
    """Rows (3P, 3(N + P)) of the position Hessian (eV/Å^2) of the molecule ``structure`` for
    its pairs' coordinates: one graph of the gradient of ``model.energy`` (float64), one
    reverse pass of it per row."""
    g = model.graph(structure, dtype=torch.float64)
    pos = g.positions.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        (grad,) = torch.autograd.grad(model.energy(g, pos)[0], pos, create_graph=True)
        flat = grad[structure.n_cores:].reshape(-1)
        rows = np.zeros((flat.numel(), pos.numel()))
        if not flat.requires_grad:  # an energy linear in the positions: no curvature
            return rows
        for r in range(flat.numel()):
            (row,) = torch.autograd.grad(flat[r], pos, retain_graph=r < flat.numel() - 1,
                                         materialize_grads=True)
            rows[r] = row.reshape(-1).numpy()
    return rows


def difference_blocks(evaluate: Callable[[np.ndarray], tuple[float, np.ndarray]],
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


def _curvature_check(evaluate: Callable[[np.ndarray], tuple[float, np.ndarray]],
                     x: np.ndarray, grad: np.ndarray, n_cores: int, h: np.ndarray,
                     cp: np.ndarray, step: float = 1e-5, max_products: int = 20,
                     ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Smallest eigenvalue (eV/Å^2) of the exact pair Hessian at the pairs ``x`` (gradient
    ``grad`` of all particles there) by :func:`emlpack.pairs.relax.davidson_min_curvature` on
    forward-difference products ``(g(x + step q) - g(x)) / step`` (one evaluation each),
    preconditioned by the pair-Hessian model ``h``. Returns the models ``h`` and ``cp``
    refined with every product as an exact secant (damped BFGS, Broyden), the eigenvalue and
    the number of products."""
    m = h.shape[0]
    g0 = grad.reshape(-1)
    secants: list[tuple[np.ndarray, np.ndarray]] = []

    def product(q: torch.Tensor) -> torch.Tensor:
        qv = q[0].numpy()
        norm = float(np.linalg.norm(qv))
        if norm == 0.0:
            return torch.zeros_like(q)
        s = (step / norm) * qv
        y = (evaluate(x + s.reshape(-1, 3))[1].reshape(-1) - g0)
        secants.append((s, y))
        return torch.as_tensor(y[3 * n_cores:] * (norm / step))[None]

    mask = torch.ones(1, m, dtype=torch.bool)
    theta = davidson_min_curvature(product, mask, torch.as_tensor(h)[None],
                                   min(max_products, m))
    for s, y in secants:
        yc, yp = y[:3 * n_cores], y[3 * n_cores:]
        cp = cp + np.outer(yc - cp @ s, s) / float(s @ s)
        h = damped_bfgs(h[None], s[None], yp[None])[0]
    return h, cp, float(theta[0]), len(secants)


def _floored_solve(h: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``H^-1 g`` with the eigenvalues of ``H`` floored at :data:`_CURVATURE_FLOOR` (eV/Å^2):
    a Cholesky solve when ``H - floor I`` and ``H`` factorise (the floor changes nothing; the
    usual case of the damped-BFGS model), else by eigendecomposition. (LAPACK ``potrf`` /
    ``potrs`` called directly: the same routines as ``scipy.linalg.cho_factor`` /
    ``cho_solve`` without their checks, which cost more than the factorisation at MD sizes.)
    Beyond a condition number of :data:`_CHOLESKY_MAX_CONDITION` (estimated from the
    factor's diagonal; two pairs merging: curvatures of 1e17 eV/Å^2 beside negative ones)
    rounding can let a factorisation of an indefinite ``H`` pass: the eigendecomposition
    decides there. A non-finite ``H`` or ``g`` raises
    :class:`CalculationFailed` (a failed relaxation: the MD watchdog restarts the pairs)."""
    if not len(g):
        return g.copy()
    if not (np.all(np.isfinite(h)) and np.all(np.isfinite(g))):
        raise CalculationFailed("non-finite pair Hessian model or gradient in the relaxation")
    factor, info = _potrf(h - _CURVATURE_FLOOR * np.eye(len(g)), lower=False, clean=False)
    if info == 0:
        r = np.abs(np.diag(factor))
        if r.min() ** 2 * _CHOLESKY_MAX_CONDITION > r.max() ** 2:
            factor, info = _potrf(h, lower=False, clean=False)
            if info == 0:
                x, info = _potrs(factor, g, lower=False)
                if info == 0:
                    return x
    w, v = np.linalg.eigh(h)
    return v @ ((v.T @ g) / np.maximum(w, _CURVATURE_FLOOR))


def _max_norm(v: np.ndarray) -> float:
    """Largest |component| of a flat (3P,) pair-force vector (0 when empty): the criterion of
    L-BFGS-B's ``gtol`` (the reference's), used by both MD solvers."""
    return float(np.max(np.abs(v), initial=0.0))


def _kabsch(old: np.ndarray, new: np.ndarray) -> np.ndarray | None:
    """The best rotation (Kabsch, 3x3) of the cores ``old`` onto ``new`` (``new ≈ R old``
    about the centroids); None for fewer than three cores."""
    a = old - old.mean(0)
    b = new - new.mean(0)
    if len(a) < 3:
        return None
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    return (u @ np.diag([1.0, 1.0, d]) @ vt).T


def _rotate_block(h: np.ndarray, rot: np.ndarray | None) -> np.ndarray:
    """A Hessian block ``h`` (3a, 3b) turned with the rotation ``rot`` (:func:`_kabsch`):
    ``R H R^T`` 3x3 block by block (``h`` itself when ``rot`` is None)."""
    if rot is None:
        return h
    rows = rot @ h.reshape(h.shape[0] // 3, 3, h.shape[1])  # R on every 3-row block
    return (rows.reshape(-1, 3) @ rot.T).reshape(h.shape)  # R^T on every 3-column block

