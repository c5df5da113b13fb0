"""Newton with exact pair Hessians and damped BFGS updates in between
(``initial_hessian="exact"``), or damped BFGS from a scaled identity (``"bfgs"``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from emlpack.nn.potential import EMLP
from emlpack.nn.scatter import segment_sum
from emlpack.pairs.relax.curvature import min_curvature
from emlpack.pairs.relax.options import RelaxOptions, RelaxResult
from emlpack.pairs.relax.problem import ActiveEvaluator, relax_results, setup_problem
from emlpack.pairs.relax.steps import newton_step
from emlpack.structure import Structure

if TYPE_CHECKING:
    from typing import TypeVar

    from emlpack.pairs.relax.options import Bounds

    #: a numpy array or a torch tensor, the same type in and out
    _ArrayT = TypeVar("_ArrayT", np.ndarray, torch.Tensor)


def relax_newton(model: EMLP, structures: Sequence[Structure], opts: RelaxOptions,
                 bounds: Bounds) -> list[RelaxResult]:
    """Newton with exact pair Hessians (``opts.initial_hessian="exact"``) or damped BFGS
    from a scaled identity (``"bfgs"``), on graphs built at the start pairs."""
    dtype = torch.float64
    g, prob, x, lower, upper, projected = setup_problem(model, structures, bounds, dtype,
                                                      opts.filter_table)
    b = g.n_structures

    energy, grad = prob.energy_gradient(x)
    n_eval = torch.ones(b, dtype=torch.long)
    n_hess = torch.zeros(b, dtype=torch.long)
    iters = torch.zeros(b, dtype=torch.long)
    fmax = prob.per_structure_max_norm(projected(grad, x))
    converged = (fmax < opts.fmax) | (g.n_pairs == 0)
    exact_mode = opts.initial_hessian == "exact"
    m = 3 * prob.n_max
    if not exact_mode:
        h0 = opts.initial_curvature if opts.initial_curvature > 0 else 10.0
        hessian = h0 * torch.eye(m, dtype=dtype).repeat(b, 1, 1)
    elif not bool(converged.all()):
        hessian = prob.hessians(x)
        n_hess += (~converged).long()
    else:
        hessian = None
    # "fresh": the model is the exact Hessian (or, in BFGS mode, always: never refreshed)
    fresh = torch.zeros(b, dtype=torch.bool) | (hessian is not None)
    first = torch.full((b,), not exact_mode and opts.initial_curvature <= 0)
    # smallest curvature (eV/Å^2) of the step model: the exact Hessian may be indefinite and is
    # shifted up to 1e-2; the damped-BFGS model is positive definite and is used as it is
    floor = 1e-2 if exact_mode else 1e-8
    since_exact = torch.zeros(b, dtype=torch.long)
    evaluate = ActiveEvaluator(model, prob)
    alpha = torch.ones(b, dtype=dtype)
    stalled = torch.zeros(b, dtype=torch.bool)

    for _ in range(opts.max_iterations):
        active = ~converged & ~stalled
        if not bool(active.any()):
            break
        gp = prob.pad(projected(grad, x))
        held = prob.pad(((x <= lower) | (x >= upper)) & (projected(grad, x) == 0)) > 0
        step = newton_step(prob, hessian, gp, held, floor, active, alpha, opts.max_step)
        x_new = torch.clamp(x + step, lower, upper)
        step = x_new - x
        e_new, g_new = evaluate(x_new, active, energy, grad)
        n_eval += active.long()
        iters += active.long()
        slope = segment_sum((grad * step).sum(1), prob.pair_batch, b)
        accept = active & (e_new <= energy + 1e-4 * slope + 1e-12 * energy.abs())
        reject = active & ~accept
        # accepted: damped BFGS update of the model Hessian, move on
        if bool(accept.any()):
            s = prob.pad(step)
            y = prob.pad(g_new - grad)
            scale_first = accept & first
            if bool(scale_first.any()):
                # Shanno-Phua: rescale the identity start to the observed curvature
                sy = (s * y).sum(1)
                yy = (y * y).sum(1)
                c = torch.where(sy > 1e-20, yy / torch.clamp(sy, min=1e-20), opts.initial_curvature)
                eye = torch.eye(hessian.shape[1], dtype=dtype)
                hessian = torch.where(scale_first[:, None, None], c[:, None, None] * eye, hessian)
                first &= ~accept
            hessian = torch.where(
                accept[:, None, None], damped_bfgs(hessian, s, y), hessian
            )
            acc_p = accept[prob.pair_batch, None]
            x = torch.where(acc_p, x_new, x)
            grad = torch.where(acc_p, g_new, grad)
            energy = torch.where(accept, e_new, energy)
            alpha = torch.where(accept, torch.ones_like(alpha), alpha)
            since_exact += accept.long()
            if exact_mode:
                fresh &= ~accept
        # rejected: halve the step; with a stale model, first refresh the exact Hessian
        alpha = torch.where(reject & fresh, alpha * 0.5, alpha)
        stalled |= reject & (alpha < 1e-6)
        if opts.collapse_distance > 0:
            stalled |= accept & (prob.closest_pair_distance(x) < opts.collapse_distance)
        fmax = prob.per_structure_max_norm(projected(grad, x))
        converged = converged | (fmax < opts.fmax)
        due = since_exact >= opts.hessian_every if opts.hessian_every > 0 else ~active
        refresh = ~converged & ~stalled & ((reject & ~fresh) | due)
        if not exact_mode:
            refresh &= False
        if bool(refresh.any()):
            exact = prob.hessians(x)
            hessian = torch.where(refresh[:, None, None], exact, hessian)
            n_hess += refresh.long()
            fresh |= refresh
            since_exact = torch.where(refresh, torch.zeros_like(since_exact), since_exact)

    min_curv = min_curvature(prob, x, grad, lower, upper, projected, opts, n_hess)
    return relax_results(structures, prob, x, energy, grad, converged, iters, n_eval, n_hess,
                         fmax, min_curv, opts)


def damped_bfgs(h: _ArrayT, s: _ArrayT, y: _ArrayT) -> _ArrayT:
    """Powell-damped BFGS update of Hessian models ``h`` (B, m, m) that keeps them positive
    definite; structures with a zero step keep their model. Torch tensors or numpy arrays
    (``h``, ``s``, ``y`` alike; numpy spares the small models of MD torch's per-call cost)."""
    xp = np if isinstance(h, np.ndarray) else torch
    hs = (h @ s[:, :, None]).squeeze(-1)
    shs = (s * hs).sum(1)
    sy = (s * y).sum(1)
    theta = xp.where(sy >= 0.2 * shs, xp.ones_like(sy), 0.8 * shs / (shs - sy))
    r = theta[:, None] * y + (1 - theta[:, None]) * hs
    sr = (s * r).sum(1)
    ok = (shs > 1e-20) & (sr > 1e-20)
    shs_safe = xp.where(ok, shs, 1.0)
    sr_safe = xp.where(ok, sr, 1.0)
    update = -hs[:, :, None] * hs[:, None, :] / shs_safe[:, None, None] + (
        r[:, :, None] * r[:, None, :] / sr_safe[:, None, None]
    )
    return xp.where(ok[:, None, None], h + update, h)
