"""The pair problem of a batch at fixed cores (:class:`PairProblem`: energies, gradients,
Hessian-vector products and pair-block Hessians as functions of all pair coordinates), its
analytic electrostatics (:class:`CoulombPairs`), evaluation of the active structures only
(:class:`ActiveEvaluator`), the set-up of a relaxation and its results."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from emlpack.nn.electrostatics import (
    coulomb_molecular,
    coulomb_pair_terms,
    ewald_reciprocal,
    ewald_reciprocal_derivatives,
)
from emlpack.nn.graph import Graph
from emlpack.nn.potential import EMLP
from emlpack.nn.scatter import segment_sum
from emlpack.nn.short_range import HeldEdges, HoldsEdges, TabulatesEdges
from emlpack.nn.short_range.hessian import short_range_position_hessian
from emlpack.pairs.checks import check_pairs
from emlpack.pairs.relax.options import RelaxOptions, RelaxResult
from emlpack.properties.hessian import standard_energy
from emlpack.structure import Structure

if TYPE_CHECKING:
    from emlpack.pairs.relax.options import Bounds


#: the filter table (``RelaxOptions.filter_table``) only for batches with at least this many
#: pair edges: building it costs ~0.15 s once per model and process (measured), which a
#: single small molecule (hexane: ~600 pair edges, ~15 evaluations) would not earn back
TABLE_MIN_EDGES = 2000


class PairProblem:
    """Energy, gradient and pair-block Hessians as functions of all pair coordinates."""

    def __init__(self, model: EMLP, g: Graph, hold_edges: bool = True,
                 held: HeldEdges | None = None, filter_table: float = 0.0,
                 tabulate: bool | None = None) -> None:
        self.model = model
        self.g = g
        self.pair_idx = torch.nonzero(g.is_pair).squeeze(1)
        self.pair_batch = g.batch[self.pair_idx]
        starts = torch.cumsum(g.n_pairs, 0) - g.n_pairs
        self.local = torch.arange(len(self.pair_idx)) - starts[self.pair_batch]
        self.n_max = int(g.n_pairs.max()) if len(g.n_pairs) else 0
        # the core-core edges keep their vectors: held once when the family can (frozen
        # parameters; models with their own energy_parts evaluate everything)
        self.held = held
        if (
            held is None
            and hold_edges
            and standard_energy(model)
            and isinstance(model.short_range, HoldsEdges)
            and not any(p.requires_grad for p in model.parameters())
        ):
            core_core = ~(g.is_pair[g.edge_i] | g.is_pair[g.edge_j])
            if bool(core_core.any()):
                self.held = model.hold_edges(g, core_core)
        # energies and gradients with the free edges' filters from a table (spacing
        # ``filter_table`` Å, 0: off) when ``tabulate`` (None: in batches of at least
        # TABLE_MIN_EDGES pair edges); Hessian-vector products keep the filter network
        self.filter_table = filter_table
        if tabulate is None:
            tabulate = self.held is not None and len(self.held.free) >= TABLE_MIN_EDGES
        self.tabulated = bool(tabulate and filter_table > 0 and self.held is not None
                              and isinstance(model.short_range, TabulatesEdges))
        self.held_tabulated = self.held
        if self.tabulated:
            self.held_tabulated = model.short_range.tabulate(self.held, filter_table)

    def energy(self, x: torch.Tensor, long_range: bool = True,
               tabulated: bool = False) -> torch.Tensor:
        """Energies (B,) with the pairs at ``x`` (P_total, 3); ``long_range=False``: without
        the electrostatic energy (plain :class:`EMLP` only); ``tabulated``: filters from the
        table when there is one (first derivatives only)."""
        held = self.held_tabulated if tabulated else self.held
        pos = self.g.positions.index_put((self.pair_idx,), x)
        if not long_range:
            return self.model.energy_parts(self.g, pos, held=held, long_range=False)["energy"]
        if held is None:
            return self.model.energy(self.g, pos)
        return self.model.energy(self.g, pos, held=held)

    def energy_gradient(
        self, x: torch.Tensor, long_range: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Energies (B,) and their gradient (P_total, 3) with the pairs at ``x`` (eV, eV/Å;
        filters from the table when there is one)."""
        x = x.detach().requires_grad_(True)
        e = self.energy(x, long_range, tabulated=True)
        (grad,) = torch.autograd.grad(e.sum(), x)
        return e.detach(), grad.detach()

    def hvp(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Hessian-vector product (P_total, 3) of the summed energy, reverse over reverse
        (measured: ~2.3 energy+gradient evaluations, 2.7x cheaper than forward over reverse)."""
        return self.hvp_operator(x)(v)

    def hvp_operator(self, x: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
        """``v -> H v`` at ``x``, the gradient's graph built once and kept: each product is
        one reverse pass (ethanol, one structure: 3.3 ms instead of 7.2 ms a product), and a
        stack ``v`` (k, P_total, 3) takes one vectorised pass (4 products: 9.5 ms)."""
        xx = x.detach().requires_grad_(True)
        (grad,) = torch.autograd.grad(self.energy(xx).sum(), xx, create_graph=True)

        def product(v: torch.Tensor) -> torch.Tensor:
            (hv,) = torch.autograd.grad(grad, xx, v.to(grad.dtype), retain_graph=True,
                                        is_grads_batched=v.dim() == 3)
            return hv.detach()

        return product

    def hessians(self, x: torch.Tensor, method: str = "fast") -> torch.Tensor:
        """Padded pair-block Hessians (B, 3 Pmax, 3 Pmax); padding is the identity.

        ``"fast"`` (models with EMLP's own energy; others get ``"reverse"``): per structure
        the short-range block
        (:func:`emlpack.nn.short_range.hessian.short_range_position_hessian`, the pairs'
        directions only: SchNet's in closed form, other families reverse over reverse on the
        short range alone) plus the analytic electrostatic blocks (:class:`CoulombPairs`);
        C4H7NO2 with 20 pairs (mini-eqm7 member 0): 54-59 ms CPU instead of 0.76-0.90 s.
        ``"reverse"``: column k of every structure's block at once, the product with the
        probe that is 1 on coordinate k of every structure's pairs, one reverse pass each
        from one kept gradient graph (ethanol 95 vs 295 ms, 24 eqm7 structures 0.8 vs 2.7 s
        for the vectorised forward-over-reverse products used before; stacked reverse passes
        (``is_grads_batched``) were no faster than those)."""
        if method not in ("fast", "reverse"):
            raise ValueError(f"hessians: method 'fast' or 'reverse', not {method!r}")
        b, m = self.g.n_structures, 3 * self.n_max
        x = x.detach()
        if method == "fast" and standard_energy(self.model):
            return self._fast_hessians(x)
        product = self.hvp_operator(x)
        columns = []
        for k in range(m):
            probe = torch.zeros_like(x)
            probe[self.local == k // 3, k % 3] = 1.0
            columns.append(product(probe))
        hv = torch.stack(columns)  # (m, P_total, 3): column k of every structure's block
        h = torch.eye(m, dtype=x.dtype).repeat(b, 1, 1)
        rows = (3 * self.local[:, None] + torch.arange(3)).reshape(-1)
        owner = self.pair_batch.repeat_interleave(3)
        valid_cols = torch.arange(m)[None, :] < 3 * self.g.n_pairs[owner][:, None]
        values = hv.reshape(m, -1).T  # (3 P_total, m)
        h[owner, rows] = torch.where(valid_cols, values, h[owner, rows])
        return (0.5 * (h + h.transpose(1, 2))).detach()

    def _fast_hessians(self, x: torch.Tensor) -> torch.Tensor:
        """``hessians(x, "fast")``: short-range pair blocks structure by structure (on the
        problem's frozen neighbour list), the electrostatic ones for the whole batch."""
        g, m = self.g, 3 * self.n_max
        _, h, _ = CoulombPairs(self.model, self)(x)
        h = h.to(x.dtype)
        at_x = g.with_positions(g.positions.detach().index_put((self.pair_idx,), x))
        for k in torch.nonzero(g.n_pairs > 0).squeeze(1).tolist():
            keep = torch.zeros(g.n_structures, dtype=torch.bool, device=x.device)
            keep[k] = True
            sub = at_x.subgraph(keep)
            pairs = torch.nonzero(sub.is_pair).squeeze(1)
            n = 3 * len(pairs)
            h[k, :n, :n] += short_range_position_hessian(self.model, sub, pairs).to(x.dtype)
        pad = torch.arange(m, device=x.device)[None, :] >= 3 * g.n_pairs[:, None]
        h = h + torch.diag_embed(pad.to(x.dtype))
        return 0.5 * (h + h.transpose(1, 2))

    def pad(self, v: torch.Tensor) -> torch.Tensor:
        """(P_total, 3) -> (B, 3 Pmax) with zero padding."""
        out = v.new_zeros(self.g.n_structures, self.n_max, 3)
        out[self.pair_batch, self.local] = v
        return out.reshape(self.g.n_structures, -1)

    def unpad(self, v: torch.Tensor) -> torch.Tensor:
        """(B, 3 Pmax) -> (P_total, 3), the inverse of :meth:`pad`."""
        return v.reshape(self.g.n_structures, self.n_max, 3)[self.pair_batch, self.local]

    def per_structure_max_norm(self, v: torch.Tensor) -> torch.Tensor:
        """The largest row norm of ``v`` (P_total, 3) in each structure, (B,)."""
        norms = torch.linalg.norm(v, dim=1)
        out = norms.new_zeros(self.g.n_structures)
        return out.scatter_reduce(0, self.pair_batch, norms, reduce="amax", include_self=True)

    def closest_pair_distance(self, x: torch.Tensor) -> torch.Tensor:
        """Smallest distance (Å) between two pairs of each structure, [n_struct]; minimum
        image for crystals; inf with fewer than two pairs. ``x``: [P_total, 3] (Å)."""
        g, n = self.g, self.n_max
        padded = x.new_full((g.n_structures, n, 3), float("nan"))
        padded[self.pair_batch, self.local] = x.detach()
        d = padded[:, None] - padded[:, :, None]  # [n_struct, n, n, 3]
        periodic = g.pbc.bool()
        if bool(periodic.any()):
            cell = g.cell[periodic].to(x.dtype)  # rows are the cell vectors
            frac = d[periodic] @ torch.linalg.inv(cell)[:, None]
            d[periodic] = (frac - torch.round(frac)) @ cell[:, None]
        dist = torch.linalg.norm(d, dim=-1) + torch.diag(x.new_full((n,), float("inf")))
        return torch.where(torch.isnan(dist), float("inf"), dist).amin((1, 2))


class CoulombPairs:
    """Analytic electrostatics of the pairs at fixed cores: the pair gradient (P_total, 3) and
    the padded pair-block Hessians (B, 3 Pmax, 3 Pmax) of the Gaussian-charge Coulomb energy
    (molecules) and the reciprocal Ewald energy (crystals, fixed cell), and on request the
    energy (B,), float64. The field energy is linear in the positions and adds nothing to
    either difference or curvature."""

    def __init__(self, model: EMLP, prob: PairProblem) -> None:
        g = prob.g
        self.prob = prob
        self.gamma, self.eps = model.config.gamma, model.config.coulomb_eps
        self.local_of = torch.full((g.n_particles,), -1, dtype=torch.long)
        self.local_of[prob.pair_idx] = prob.local
        self.row_of = torch.full((g.n_particles,), -1, dtype=torch.long)
        self.row_of[prob.pair_idx] = torch.arange(len(prob.pair_idx))
        keep = g.is_pair[g.coulomb_i] | g.is_pair[g.coulomb_j]
        self.ci, self.cj = g.coulomb_i[keep], g.coulomb_j[keep]
        q = g.charges.double()
        self.qq = q[self.ci] * q[self.cj]
        self.positions = g.positions.detach().double()
        self.charges = q
        # the energy of the core-core Coulomb pairs and the self energies do not change
        self.fixed_energy = coulomb_molecular(
            self.positions, q, g.coulomb_i[~keep], g.coulomb_j[~keep], g.batch, ~g.pbc,
            g.n_structures, self.gamma, self.eps)
        self.periodic = []
        for b in torch.unique(g.kvec_batch).tolist():
            members = torch.nonzero(g.batch == b).squeeze(1)
            rows = torch.nonzero(g.is_pair[members]).squeeze(1)
            self.periodic.append((b, members, rows, g.kvec_n[g.kvec_batch == b].double()))

    def __call__(
        self, x: torch.Tensor, active: torch.Tensor | None = None, hessian: bool = True,
        energy: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Gradient, Hessians and energies at ``x``; with ``active`` (B,) bool only those
        structures are computed (the others' entries are zero, their energies meaningless);
        ``hessian=False``: no Hessians (None); ``energy=False``: no energies (None)."""
        prob = self.prob
        g = prob.g
        b, n = g.n_structures, prob.n_max
        pos = self.positions.index_put((prob.pair_idx,), x.detach().double())
        grad = pos.new_zeros(len(prob.pair_idx), 3)
        hess = pos.new_zeros(b, n, n, 3, 3) if hessian else None
        ci, cj, qq = self.ci, self.cj, self.qq
        if active is not None and len(ci):
            keep = active[g.batch[ci]]
            ci, cj, qq = ci[keep], cj[keep], qq[keep]
        e = self.fixed_energy.clone() if energy else None
        if len(ci):
            e_pair, gr, h = coulomb_pair_terms(pos[cj] - pos[ci], qq, self.gamma, self.eps)
            s = g.batch[ci]
            if energy:
                e += segment_sum(e_pair, s, b)
            li, lj = self.local_of[ci], self.local_of[cj]
            pi, pj = li >= 0, lj >= 0
            grad.index_add_(0, self.row_of[cj[pj]], gr[pj])
            grad.index_add_(0, self.row_of[ci[pi]], -gr[pi])
        if len(ci) and hessian:
            hess.index_put_((s[pi], li[pi], li[pi]), h[pi], accumulate=True)
            hess.index_put_((s[pj], lj[pj], lj[pj]), h[pj], accumulate=True)
            both = pi & pj
            hess.index_put_((s[both], li[both], lj[both]), -h[both], accumulate=True)
            hess.index_put_((s[both], lj[both], li[both]), -h[both], accumulate=True)
        for s_idx, members, rows, kn in self.periodic:
            if active is not None and not bool(active[s_idx]):
                continue
            if energy:
                e[s_idx] += ewald_reciprocal(
                    pos[members], self.charges[members], torch.zeros_like(members),
                    g.cell[s_idx:s_idx + 1].double(), kn,
                    torch.zeros(len(kn), dtype=torch.long), self.gamma)[0]
            gr, h = ewald_reciprocal_derivatives(
                pos[members], self.charges[members], g.cell[s_idx].double(), kn, self.gamma,
                rows,
            )
            grad[self.row_of[members[rows]]] += gr
            if hessian:
                m = len(rows)
                hess[s_idx, :m, :m] += h.permute(0, 2, 1, 3)
        if not hessian:
            return grad.to(x.dtype), None, e
        hess = hess.permute(0, 1, 3, 2, 4).reshape(b, 3 * n, 3 * n)
        return grad.to(x.dtype), hess, e


def _held_subset(prob: PairProblem, keep: torch.Tensor) -> HeldEdges | None:
    """``prob``'s held filters restricted to the structures ``keep`` (B,) bool, numbered as in
    ``prob.g.subgraph(keep)`` (no filter is recomputed; measured: rebuilding them took
    ~4 ms per compaction on the benchmark batch, ~20 compactions with the float32 start)."""
    held, g = prob.held, prob.g
    if held is None:
        return None
    part = keep[g.batch]
    old_to_new = torch.cumsum(part.long(), 0) - 1
    rows = part[held.i]
    if not bool(rows.any()):
        return None
    is_free = torch.zeros(len(g.edge_i), dtype=torch.bool)
    is_free[held.free] = True
    return held.subset(rows, old_to_new, torch.nonzero(is_free[part[g.edge_i]]).squeeze(1))


class ActiveEvaluator:
    """Energies, gradients and Hessian-vector products of the active structures only: when the
    active set has shrunk below ``fraction`` of the structures evaluated so far (or holds one
    outside them), the batch is compacted to the active ones (same topology), so converged
    structures stop costing model evaluations."""

    def __init__(self, model: EMLP, prob: PairProblem, fraction: float = 0.75) -> None:
        self.model, self.full, self.fraction = model, prob, fraction
        self.members = torch.ones(prob.g.n_structures, dtype=torch.bool)
        self.sub, self.rows = prob, None
        self._operator = None  # (sub problem, x, v -> H v) of the last products

    def _compact(self, active: torch.Tensor) -> None:
        if int(active.sum()) < self.fraction * int(self.members.sum()) or bool(
            (active & ~self.members).any()
        ):
            self.members = active.clone()
            self.sub = PairProblem(self.model, self.full.g.subgraph(active),
                                   held=_held_subset(self.full, active),
                                   filter_table=self.full.filter_table,
                                   tabulate=self.full.tabulated)
            self.rows = active[self.full.pair_batch]

    def hvp(self, x: torch.Tensor, v: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """Hessian-vector products [P_total, 3] of the ``active`` [n_struct] structures (zero
        rows for the others); ``x``: [P_total, 3], ``v``: [P_total, 3] or a stack [k, P_total,
        3]. Products at the same ``x`` (the same tensor) reuse the gradient's graph until the
        batch is compacted."""
        self._compact(active)
        if self._operator is None or self._operator[0] is not self.sub or (
            self._operator[1] is not x
        ):
            at = x if self.rows is None else x[self.rows]
            self._operator = (self.sub, x, self.sub.hvp_operator(at))
        product = self._operator[2]
        if self.rows is None:
            return product(v)
        out = torch.zeros_like(v)
        out[..., self.rows, :] = product(v[..., self.rows, :])
        return torch.where(active[self.full.pair_batch, None], out, 0.0)

    def __call__(
        self, x: torch.Tensor, active: torch.Tensor, energy: torch.Tensor, grad: torch.Tensor,
        long_range: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Energies (B,) and gradients (P_total, 3) at ``x`` (eV, eV/Å) of at least the
        ``active`` structures; those outside the compacted batch keep ``energy`` and
        ``grad``."""
        self._compact(active)
        if self.rows is None:
            return self.full.energy_gradient(x, long_range)
        e_sub, g_sub = self.sub.energy_gradient(x[self.rows], long_range)
        e = energy.clone()
        e[self.members] = e_sub
        gr = grad.clone()
        gr[self.rows] = g_sub
        return e, gr


def setup_problem(
    model: EMLP, structures: Sequence[Structure], bounds: Bounds,
    dtype: torch.dtype = torch.float64, filter_table: float = 0.0,
) -> tuple[Graph, PairProblem, torch.Tensor, torch.Tensor, torch.Tensor,
           Callable[[torch.Tensor, torch.Tensor], torch.Tensor]]:
    """The graph (built at the start pairs), the problem, the start pairs (P_total, 3; Å)
    clamped into ``bounds``, the lower and upper bounds (+-inf where none) and the
    projection of a gradient on the box (``projected(grad, x)``)."""
    g = model.graph(structures, dtype=dtype)
    prob = PairProblem(model, g, filter_table=filter_table)
    x = g.positions[prob.pair_idx].clone()
    lower = torch.full_like(x, -torch.inf)
    upper = torch.full_like(x, torch.inf)
    if bounds is not None:
        for s_idx, bnd in enumerate(bounds):
            if bnd is None:
                continue
            sel = prob.pair_batch == s_idx
            lower[sel] = torch.as_tensor(np.asarray(bnd[0]), dtype=dtype).reshape(-1, 3)
            upper[sel] = torch.as_tensor(np.asarray(bnd[1]), dtype=dtype).reshape(-1, 3)
        x = torch.clamp(x, lower, upper)

    bounded = bool(torch.isfinite(lower).any() or torch.isfinite(upper).any())

    def projected(grad: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        if not bounded:
            return grad
        at_low = (x <= lower) & (grad > 0)
        at_up = (x >= upper) & (grad < 0)
        return torch.where(at_low | at_up, 0.0, grad)

    return g, prob, x, lower, upper, projected


def relax_results(structures: Sequence[Structure], prob: PairProblem, x: torch.Tensor,
                  energy: torch.Tensor, grad: torch.Tensor, converged: torch.Tensor,
                  iters: torch.Tensor, n_eval: torch.Tensor, n_hess: torch.Tensor,
                  fmax: torch.Tensor, min_curv: torch.Tensor,
                  opts: RelaxOptions) -> list[RelaxResult]:
    """One :class:`RelaxResult` per structure from the final state of the batch, checked
    by :func:`~emlpack.pairs.checks.check_pairs`."""
    xs = x.detach().numpy()
    gs = grad.detach().numpy()
    pb = prob.pair_batch.numpy()
    out = []
    for k, s in enumerate(structures):
        pairs = xs[pb == k]
        reason = check_pairs(pairs, s.positions, s.cell, s.pbc,
                             min_pair_distance=opts.min_pair_distance,
                             max_core_distance=opts.max_core_distance,
                             converged=bool(converged[k]), fmax=opts.fmax,
                             min_curvature=float(min_curv[k]),
                             flat_curvature=opts.flat_curvature)
        out.append(
            RelaxResult(
                pairs=pairs.copy(),
                energy=float(energy[k]),
                converged=bool(converged[k]) and not reason,
                iterations=int(iters[k]),
                n_evaluations=int(n_eval[k]),
                n_hessians=int(n_hess[k]),
                max_force=float(fmax[k]),
                min_curvature=float(min_curv[k]),
                reason=reason,
                pair_forces=-gs[pb == k].copy(),
            )
        )
    return out


def pair_hessian(model: EMLP, structure: Structure, method: str = "fast") -> np.ndarray:
    """Exact pair-block Hessian (eV/Å^2), shape (3P, 3P), of one structure at its pairs
    (cores fixed); rows/columns ordered pair by pair, x y z (:meth:`PairProblem.hessians`:
    ``"fast"``, the short-range block of the family for EMLP's own energy, else, or with
    ``"reverse"``, 3P reverse passes)."""
    g = model.graph(structure, dtype=torch.float64)
    prob = PairProblem(model, g)
    if prob.n_max == 0:
        return np.zeros((0, 0))
    return prob.hessians(g.positions[prob.pair_idx], method=method)[0].numpy()
