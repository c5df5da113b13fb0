"""The regularised projected-Newton step of both relaxation methods (:func:`newton_step`)."""

from __future__ import annotations

import torch

from emlpack.pairs.relax.problem import PairProblem


def newton_step(prob: PairProblem, hessian: torch.Tensor, gp: torch.Tensor,
                held: torch.Tensor | None, floor: float | torch.Tensor, active: torch.Tensor,
                alpha: torch.Tensor, max_step: float | torch.Tensor,
                mirror: float | None = None) -> torch.Tensor:
    """Regularised projected-Newton step: coordinates held at a bound by the gradient are
    fixed (rows/columns replaced by the identity; ``held`` None: none), the model is shifted
    to curvature >= floor (float or (B,)),
    the longest pair displacement capped to ``max_step`` (float or (B,)) and scaled by
    ``alpha`` (B,). With ``mirror`` (eV/Å^2): model curvatures below ``-mirror`` are replaced
    by their magnitude (a descent step that goes no further along them than along a positive
    curvature of the same size), the shift to the floor is taken from the others."""
    dtype = hessian.dtype
    # only the active structures (converged ones would cost an eigendecomposition each)
    idx = torch.nonzero(active).squeeze(1)
    if held is None:
        reduced = hessian[idx]
    else:
        free = (~held[idx]).to(dtype)
        reduced = hessian[idx] * free[:, :, None] * free[:, None, :] + torch.diag_embed(
            held[idx].to(dtype)
        )
    rhs = gp[idx][:, :, None]
    # models with every curvature above the floor need no shift: a Cholesky solve (the
    # factorisation of model - floor proves it) instead of an eigendecomposition (measured on
    # the relaxation benchmark: 86 % of the solves, step CPU 67-80 -> 36-47 ms per relaxation)
    eye = torch.eye(reduced.shape[1], dtype=dtype)
    floor = torch.as_tensor(floor, dtype=dtype).expand(len(active))[idx]
    _, info = torch.linalg.cholesky_ex(reduced - floor[:, None, None] * eye)
    chol, info_model = torch.linalg.cholesky_ex(reduced)
    plain = (info == 0) & (info_model == 0)
    sol = torch.cholesky_solve(rhs, torch.where(plain[:, None, None], chol, eye)).squeeze(-1)
    if not bool(plain.all()):
        rest = torch.nonzero(~plain).squeeze(1)
        evals, evecs = torch.linalg.eigh(reduced[rest])
        strong = evals < -mirror if mirror is not None else torch.zeros_like(evals, dtype=bool)
        low = torch.where(strong, torch.inf, evals).amin(1, keepdim=True)
        curv = torch.where(strong, evals.abs(),
                           evals + torch.clamp(floor[rest, None] - low, min=0.0))
        coef = (evecs.transpose(1, 2) @ rhs[rest]).squeeze(-1) / curv
        sol[rest] = (evecs @ coef[:, :, None]).squeeze(-1)
    full = gp.new_zeros(gp.shape)
    full[idx] = sol
    step = -prob.unpad(full)
    longest = prob.per_structure_max_norm(step)
    scale = torch.clamp(max_step / torch.clamp(longest, min=1e-300), max=1.0)
    step = step * (scale * alpha)[prob.pair_batch, None]
    return torch.where(active[prob.pair_batch, None], step, 0.0)
