"""The smallest curvature of the exact pair Hessian at a relaxation's result: Davidson
iterations preconditioned by the quasi-Newton model (:func:`davidson_min_curvature`) or the
full exact pair Hessian (:func:`min_curvature`)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from emlpack.pairs.relax.options import RelaxOptions
from emlpack.pairs.relax.problem import ActiveEvaluator, PairProblem

_DAVIDSON_TRACE: list | None = None  # set to a list to record (products, residual, value)


def davidson_min_curvature(
    product: Callable[[torch.Tensor], torch.Tensor],
    mask: torch.Tensor,
    model_hessian: torch.Tensor,
    steps: int,
    tol: float = 1e-3,
    block: int = 4,
    batched_start: bool = False,
) -> torch.Tensor:
    """Smallest eigenvalue (B,) of every structure's exact pair Hessian restricted to ``mask``
    (B, m), given its products ``product(q) -> H q`` ((B, m) -> (B, m), padded pair
    coordinates): Davidson iterations preconditioned by the quasi-Newton model ``model_hessian``
    (B, m, m; Olsen's correction, so a model close to the Hessian does not stall), started from
    the model's ``block`` softest directions (one alone can miss a soft mode the model does not
    know: measured on the fixture weights' hexane); one exact Hessian-vector product for the
    whole batch per iteration, at most ``steps``, stopped when every residual r satisfies
    ``r <= tol sqrt(|theta| scale)`` (scale: the model's largest curvature; the eigenvalue
    error is ~ r^2 / gap: measured <= 5e-5 relative on hexane with both test models).
    ``batched_start``: ``product`` also takes a stack (k, B, m), and the ``block`` start
    directions go through it in one call."""
    b, m = mask.shape
    dtype = model_hessian.dtype
    maskf = mask.to(dtype)
    both = mask[:, :, None] & mask[:, None, :]
    mod = torch.where(both, model_hessian, 0.0) + torch.diag_embed(torch.where(mask, 0.0, 1e30))
    lam, vec = torch.linalg.eigh(mod)
    scale = torch.clamp(lam.abs().masked_fill(~mask, 0.0).amax(1), min=1e-6)  # (B,)
    basis, images = [], []
    theta = torch.zeros(b, dtype=dtype)
    starts = [torch.where(mask.sum(1, keepdim=True) > k, vec[:, :, k] * maskf, 0.0)
              for k in range(min(block, steps, m))]  # the model's softest directions
    start_images = product(torch.stack(starts)) if batched_start and starts else None
    for it in range(steps):
        if it < len(starts):
            q = starts[it]
        hq = (start_images[it] if start_images is not None and it < len(starts)
              else product(q)) * maskf
        basis.append(q)
        images.append(hq)
        if it + 1 < len(starts):  # the Ritz step once all start directions are in
            continue
        qs, hqs = torch.stack(basis, 2), torch.stack(images, 2)
        t = qs.transpose(1, 2) @ hqs
        t = 0.5 * (t + t.transpose(1, 2))
        empty = torch.linalg.norm(qs, dim=1) < 0.5  # (B, k) inert zero columns
        t = t + torch.diag_embed(torch.where(empty, 1e30, 0.0))
        evals, evecs = torch.linalg.eigh(t)
        theta, y = evals[:, 0], evecs[:, :, 0]
        u = (qs @ y[:, :, None]).squeeze(-1)
        r = (hqs @ y[:, :, None]).squeeze(-1) - theta[:, None] * u
        res = torch.linalg.norm(r, dim=1)
        done = res <= tol * torch.sqrt(torch.clamp(theta.abs(), min=1e-6 * scale) * scale)
        if _DAVIDSON_TRACE is not None:
            _DAVIDSON_TRACE.append((it + 1, float(res.max()), float(theta[0])))
        if bool(done.all()):
            break
        # Olsen: t = K^-1 r - eps K^-1 u with K = model - theta, eps making t orthogonal to u
        denom = lam - theta[:, None]
        denom = torch.where(denom.abs() < 1e-8 * scale[:, None],
                            1e-8 * scale[:, None] * torch.sign(denom + 1e-300), denom)

        def solve(v: torch.Tensor, denom: torch.Tensor = denom) -> torch.Tensor:
            return (vec @ (((vec.transpose(1, 2) @ v[:, :, None]).squeeze(-1)) / denom)
                    [:, :, None]).squeeze(-1)

        kr, ku = solve(r), solve(u)
        eps = (u * kr).sum(1) / torch.where((u * ku).sum(1).abs() > 1e-300, (u * ku).sum(1), 1.0)
        w = (kr - eps[:, None] * ku) * maskf
        for _ in range(2):
            w = w - (qs @ (qs.transpose(1, 2) @ w[:, :, None])).squeeze(-1)
        norm = torch.linalg.norm(w, dim=1, keepdim=True)
        keep = (norm.squeeze(1) > 1e-12) & ~done
        q = torch.where(keep[:, None], w / torch.clamp(norm, min=1e-300), 0.0)
    return theta


def min_curvature(prob: PairProblem, x: torch.Tensor, grad: torch.Tensor,
                  lower: torch.Tensor, upper: torch.Tensor,
                  projected: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                  opts: RelaxOptions, n_hess: torch.Tensor,
                  model_hessian: torch.Tensor | None = None,
                  product_prob: PairProblem | None = None) -> torch.Tensor:
    """Smallest eigenvalue of the exact pair Hessian over the free coordinates (NaN when not
    checked). With ``model_hessian`` (B, m, m) and ``opts.curvature_steps`` > 0: Davidson
    preconditioned by the model (counted as one Hessian in ``n_hess``; at most
    ``curvature_steps`` Hessian-vector products, each only for the structures not converged
    yet, in ``product_prob``'s dtype: the float32 problem of a relaxation that had a float32
    phase: eigenvalues within 2.2e-5 eV/Å^2 of float64 products, measured in
    docs/relaxation.md); else the exact pair Hessian."""
    g = prob.g
    min_curv = torch.full((g.n_structures,), float("nan"), dtype=torch.float64)
    if opts.check_curvature and prob.n_max and model_hessian is not None and (
        opts.curvature_steps > 0
    ):
        held = prob.pad(((x <= lower) | (x >= upper)) & (projected(grad, x) == 0)) > 0
        mask = (torch.arange(3 * prob.n_max)[None, :] < 3 * g.n_pairs[:, None]) & ~held
        steps = min(opts.curvature_steps, int(mask.sum(1).max()))
        # products only for the structures whose Ritz pair has not converged yet (Davidson
        # zeroes the others' directions)
        pp = product_prob or prob
        evaluate = ActiveEvaluator(pp.model, pp)
        xp = x.to(pp.g.dtype)

        def product(q: torch.Tensor) -> torch.Tensor:
            """(B, m) or a stack (k, B, m) of padded directions -> their products."""
            if q.dim() == 2:
                v = prob.unpad(q)
                active = prob.per_structure_max_norm(v) > 0
                return prob.pad(evaluate.hvp(xp, v.to(xp.dtype), active).to(q.dtype))
            v = torch.stack([prob.unpad(one) for one in q])
            active = prob.per_structure_max_norm(v.abs().amax(0)) > 0
            hv = evaluate.hvp(xp, v.to(xp.dtype), active).to(q.dtype)
            return torch.stack([prob.pad(one) for one in hv])

        min_curv = davidson_min_curvature(product, mask, model_hessian, steps,
                                          batched_start=True)
        n_hess += 1
        return torch.where(mask.any(1), min_curv, torch.nan)
    if opts.check_curvature and prob.n_max:
        exact = prob.hessians(x)
        n_hess += 1
        # curvature over the coordinates that are free (not held at a box bound)
        held = prob.pad(((x <= lower) | (x >= upper)) & (projected(grad, x) == 0)) > 0
        mask = (torch.arange(3 * prob.n_max)[None, :] < 3 * g.n_pairs[:, None]) & ~held
        big = torch.where(mask[:, :, None] & mask[:, None, :], exact, 0.0)
        big = big + torch.diag_embed(torch.where(mask, 0.0, 1e30))
        min_curv = torch.linalg.eigvalsh(big)[:, 0]
        min_curv = torch.where(mask.any(1), min_curv, torch.nan)
    return min_curv
