"""Born-Oppenheimer relaxation of the electron pairs at fixed cores (batched, float64).

Minimises the eMLP energy over the electron-pair positions of many structures at once.

Default method (``initial_hessian="coulomb"``): a quasi-Newton on the per-structure pair block
(3P x 3P for P pairs) whose model is ``H_el(x) + M``:

1. ``H_el(x)``: the exact analytic electrostatic pair Hessian at the current pairs (Gaussian
   Coulomb for molecules, reciprocal Ewald at fixed cell for crystals;
   :func:`emlpack.nn.electrostatics.coulomb_pair_derivatives`,
   :func:`~emlpack.nn.electrostatics.ewald_reciprocal_derivatives`), recomputed every step;
2. ``M``: the short-range remainder, started block-diagonal from three batched forward
   differences of the gradient ("lumped": per pair the row sum of its short-range couplings)
   and refined by symmetric-rank-one updates from ``y - y_el`` (change of gradient minus change
   of the electrostatic gradient) after every evaluated step;
3. step ``(H_el + M + mu I) p = -g`` with ``mu`` lifting the smallest eigenvalue to 1e-2 eV/Å^2
   (model curvatures below ``-mirror_curvature`` are taken by their magnitude instead and
   left out of ``mu``), in a trust radius (largest pair displacement, at most ``max_step``)
   that is halved to a rejected step and doubled after an accepted one (Armijo test);
4. structures not converged after ``newton_after`` iterations (nearly flat modes) finish with
   the exact-Hessian Newton method below;
5. (``bond_rotations``, molecules) the step is taken in cylindrical coordinates about the axis
   through each pair's two nearest cores (:class:`_BondRotations`): its tangential part turns
   the pair about that bond instead of moving it along the tangent (acetylene's triple-bond
   pairs have a soft rotation about the C-C axis that straight steps zig-zag along);
6. (with 5) the model lives in those coordinates: per turned pair radial, arc length and axial
   (``M`` is Cartesian; the step model adds the connection term of the gradient, ``-g_r/rho``
   tangential and ``g_t/rho`` radial-tangential, :meth:`_BondRotations.connection`); the SR1
   secant is the turned step with the new gradient turned back less that term of the
   short-range gradient, and ``M`` turns with the accepted pairs;
7. (with 5) once per structure, near its minimum, a step along the collective rotation of the
   pairs about each double or triple bond (``rotation_probe``): the lumped start sees those
   pairs turning one at a time, stiff, while together they turn almost freely; its secant
   gives ``M`` that curvature.

Every evaluation holds the core-core edges fixed when the short-range family can (their
vectors do not change at fixed cores and cell; capability
:class:`~emlpack.nn.short_range.protocol.HoldsEdges`, SchNet's filters;
:meth:`emlpack.nn.potential.EMLP.hold_edges`). A model with EMLP's own energy
(:func:`~emlpack.properties.hessian.standard_energy`) is evaluated without its
electrostatics, whose energy and gradient come from the analytic pair terms computed for
``H_el`` anyway. Float32 phase (``float32_above``, batches of
at least ``float32_min_pairs`` pairs): while a structure's largest pair force is above it, its
evaluations are float32 (Armijo test with a 1e-6 |E| allowance, steps below that resolution
accepted on a lower pair-gradient norm), then float64, so the minima are float64 minima.

``initial_hessian="exact"``: Newton with exact pair Hessians (short-range blocks,
:func:`~emlpack.nn.short_range.hessian.short_range_position_hessian`, plus the analytic
electrostatics, :meth:`_PairProblem.hessians`),
refreshed when the line search backtracks or every ``hessian_every`` steps, damped BFGS updates
in between. ``"bfgs"``: damped BFGS from a scaled identity.

Convergence: the largest pair-force norm (projected on the box) below ``fmax`` (eV/Å); a
structure whose pairs collapse onto one point (``collapse_distance``) stops. The graph (the
short-range neighbour list) is built at the start pairs; a structure whose neighbour list at the
result holds an edge the start lacked is relaxed again from its result on a graph built there.
Diagnostics per structure: converged flag, iterations, energy+gradient evaluations, Hessian
evaluations, final max force, smallest eigenvalue of the exact pair Hessian at the result
(default method: Davidson iterations on Hessian-vector products of the structures not yet
converged, preconditioned by the quasi-Newton model, instead of the full Hessian), and a
failure reason from :func:`emlpack.pairs.checks.check_pairs` (no convergence, two pairs closer
than ``min_pair_distance``, a pair farther than ``max_core_distance`` from every core, minimum
image; a curvature at or below ``-flat_curvature``). :mod:`emlpack.pairs.solvers` wraps this
function as :class:`~emlpack.pairs.solvers.BatchedSolver`.

Why each piece is there, with the measurements and what was tried and dropped:
``docs/relaxation.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
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
from emlpack.nn.potential import EMLP, for_evaluation
from emlpack.nn.scatter import segment_sum
from emlpack.nn.short_range import FrozenAnyDtype, HeldEdges, HoldsEdges, TabulatesEdges
from emlpack.nn.short_range.hessian import short_range_position_hessian
from emlpack.pairs.checks import (
    COLLAPSE_DISTANCE,
    FLAT_CURVATURE,
    MAX_CORE_DISTANCE,
    MIN_PAIR_DISTANCE,
    check_pairs,
)
from emlpack.properties.hessian import standard_energy
from emlpack.structure import Structure

if TYPE_CHECKING:
    from typing import TypeVar

    #: a numpy array or a torch tensor, the same type in and out
    _ArrayT = TypeVar("_ArrayT", np.ndarray, torch.Tensor)

    #: per structure None or the (lower, upper) box of its pairs, (P, 3) each (Å)
    _Bounds = Sequence[tuple[np.ndarray, np.ndarray] | None] | None


@dataclass
class RelaxResult:
    """Outcome of relaxing the electron pairs of one structure (Å, eV, eV/Å, eV/Å^2)."""

    pairs: np.ndarray
    energy: float
    converged: bool
    iterations: int
    n_evaluations: int
    n_hessians: int
    max_force: float
    min_curvature: float
    reason: str = ""
    pair_forces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: forces on the cores (eV/Å) at the result when the solver computed them (MD's warm-start
    #: solvers), so that the caller needs no further evaluation; None otherwise
    forces: np.ndarray | None = None
    #: how the start pairs were made ("given"; MD's solvers: "warm", "paper", "rigid", "guess")
    start: str = "given"

    @property
    def failed(self) -> bool:
        """True when ``reason`` names a failure."""
        return bool(self.reason)


@dataclass
class RelaxOptions:
    """Settings of :func:`relax_pairs` (lengths Å, forces eV/Å)."""

    fmax: float = 1e-4
    max_iterations: int = 100
    max_step: float = 0.3
    #: exact Hessian refresh every this many accepted steps (0: never)
    hessian_every: int = 5
    #: "coulomb" (default): quasi-Newton whose model is the exact analytic electrostatic pair
    #: Hessian at every iterate plus an SR1 model of the short-range remainder (one
    #: energy+gradient per iteration, no autograd Hessians); "exact": start from the exact
    #: pair Hessian and refresh it when the model goes stale
    #: (few iterations; a Hessian costs about 2.5 x 3P gradient evaluations); "bfgs": start
    #: from an identity model (``initial_curvature``) and use damped BFGS
    #: updates only, halving rejected steps (more iterations, each one gradient evaluation)
    initial_hessian: str = "coulomb"
    #: ``"bfgs"``: curvature (eV/Å^2) of the identity start model, as SciPy's BFGS (1: H0 = I);
    #: <= 0: Shanno-Phua scaling from the first step instead (measured: about 2x more
    #: iterations on the eqm7 relaxation benchmark, the scaled model is too stiff)
    initial_curvature: float = 1.0
    #: "coulomb": start model of the short-range remainder: "lumped" (three forward
    #: differences of the gradient, counted as evaluations: per pair the row sum of its
    #: short-range 3x3 couplings; on a trained model the short range is ~93 % of the pair
    #: Hessian, measured) or "zero"
    short_range_start: str = "lumped"
    #: "coulomb": structures not converged after this many quasi-Newton iterations finish
    #: with the exact-Hessian Newton method (0: never)
    newton_after: int = 50
    #: "coulomb": structures whose largest pair force is above this (or ``fmax`` when larger;
    #: eV/Å) are evaluated in float32 (start, lumped start and iterations; Armijo test with a
    #: 1e-6 |E| allowance for the float32 energy, and steps whose predicted decrease is below
    #: that allowance accepted on a lower pair-gradient norm), then finished in float64 (first
    #: step: accepted on a lower gradient norm); the minima are float64 minima (0: float64
    #: throughout; the float32 gradient is within ~1.3e-5 eV/Å of float64, measured)
    float32_above: float = 3e-4
    #: ... only in batches of at least this many pairs (measured on the trained model: float32
    #: energy+gradient 2.5x cheaper for 432 pairs, equal for 32, 1.5x dearer for 4); when the
    #: structures still in float32 hold fewer pairs than this, they all go on in float64
    float32_min_pairs: int = 128
    #: "coulomb": the smallest curvature at the result (``check_curvature``) by Davidson
    #: iterations preconditioned by the quasi-Newton model, at most this many exact
    #: Hessian-vector products (0: the full exact pair Hessian instead)
    curvature_steps: int = 20
    #: energies and gradients with the SchNet filters of the pair edges from a cubic Hermite
    #: table of this spacing (Å; :class:`emlpack.nn.short_range.schnet.FilterTable`; families
    #: with the capability :class:`~emlpack.nn.short_range.protocol.TabulatesEdges`) instead
    #: of the filter network (Hessian-vector products and exact Hessians keep the network).
    #: Measured on the trained benchmark model, 64 structures: energies within 3e-11 eV, pair
    #: gradients within 2.5e-8 eV/Å, an energy+gradient 1.5x cheaper in float64 and float32,
    #: the relaxation benchmark 1.27x; batches of at least ``TABLE_MIN_EDGES`` pair edges;
    #: 0: off)
    filter_table: float = 1e-3
    #: failure thresholds of :func:`emlpack.pairs.checks.check_pairs` (Å)
    min_pair_distance: float = MIN_PAIR_DISTANCE
    max_core_distance: float = MAX_CORE_DISTANCE
    check_curvature: bool = True
    #: (method "coulomb", molecules) steps in cylindrical coordinates about the axis through
    #: each pair's two nearest cores (:class:`_BondRotations`) instead of straight ones
    #: (measured on the 64-structure benchmark: acetylene's slowest 58 -> 40 evaluations)
    bond_rotations: bool = True
    #: (method "coulomb", with ``bond_rotations``) a structure with a group of at least
    #: ``rotation_probe_pairs`` pairs about one bond (a double or triple bond's pairs) takes
    #: one step that turns each group together by this arc (Å, downhill) instead of a Newton
    #: step, when its largest pair force first falls below ``rotation_probe_below`` (eV/Å; the
    #: mode is soft near the minimum only); its secant puts that rotation's curvature into
    #: the model (measured on the relaxation benchmark: shipped member 0 CPU -16 %, slowest
    #: 53 -> 36 evaluations; docs/relaxation.md; 0: off). ``rotation_floor``: the Newton
    #: step's curvature floor (eV/Å^2) for a probed structure (a lower one, 3e-3, was faster
    #: on the benchmark but failed more often on linear molecules with two triple bonds,
    #: whose rotations are exactly flat)
    rotation_probe: float = 0.05
    rotation_probe_pairs: int = 2
    rotation_probe_below: float = 3e-2
    rotation_floor: float = 1e-2
    #: (method "coulomb") model curvatures below minus this (eV/Å^2) are replaced by their
    #: magnitude in the step instead of shifting the whole model up to the floor (an SR1
    #: update from a near-orthogonal secant can leave a large spurious negative curvature;
    #: the shifted step then runs along it to the trust radius and is rejected; measured on
    #: the 64-structure benchmark: evaluations sum 922 -> 884, max 26 -> 23; 0: off)
    mirror_curvature: float = 1.0
    #: a structure whose accepted pairs include two closer than this (Å) has collapsed (two
    #: pairs on one point, where the direction of their distance is undefined) and stops; its
    #: result fails as merged (0: never stop; measurements: docs/relaxation.md)
    collapse_distance: float = COLLAPSE_DISTANCE
    #: smallest pair curvatures above minus this (eV/Å^2) are a flat valley, not a saddle
    #: (:func:`~emlpack.pairs.checks.check_pairs`): the azimuth of a triple bond's pairs is
    #: flat (cylindrical symmetry), and a relaxation stopped at ``fmax`` = 1e-4 eV/Å sits
    #: anywhere along it (measured: docs/relaxation.md)
    flat_curvature: float = FLAT_CURVATURE
    #: a relaxation that ends at a saddle (converged, its only failure a pair curvature at or
    #: below ``-flat_curvature``; e.g. a symmetric start whose gradient keeps the symmetry) is
    #: displaced along the softest mode of the exact pair Hessian, both ways, and relaxed
    #: again, at most this many times; the lower minimum is kept (0: off; needs
    #: ``check_curvature``)
    saddle_escapes: int = 2
    #: ... by this much (Å, the largest pair displacement)
    saddle_step: float = 0.1


#: the filter table (``RelaxOptions.filter_table``) only for batches with at least this many
#: pair edges: building it costs ~0.15 s once per model and process (measured), which a
#: single small molecule (hexane: ~600 pair edges, ~15 evaluations) would not earn back
TABLE_MIN_EDGES = 2000


class _PairProblem:
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
        short range alone) plus the analytic electrostatic blocks (:class:`_CoulombPairs`);
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
        _, h, _ = _CoulombPairs(self.model, self)(x)
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
        return v.reshape(self.g.n_structures, self.n_max, 3)[self.pair_batch, self.local]

    def per_structure_max_norm(self, v: torch.Tensor) -> torch.Tensor:
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


class _CoulombPairs:
    """Analytic electrostatics of the pairs at fixed cores: the pair gradient (P_total, 3) and
    the padded pair-block Hessians (B, 3 Pmax, 3 Pmax) of the Gaussian-charge Coulomb energy
    (molecules) and the reciprocal Ewald energy (crystals, fixed cell), and on request the
    energy (B,), float64. The field energy is linear in the positions and adds nothing to
    either difference or curvature."""

    def __init__(self, model: EMLP, prob: _PairProblem) -> None:
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


def _held_subset(prob: _PairProblem, keep: torch.Tensor) -> HeldEdges | None:
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


class _ActiveEvaluator:
    """Energies, gradients and Hessian-vector products of the active structures only: when the
    active set has shrunk below ``fraction`` of the structures evaluated so far (or holds one
    outside them), the batch is compacted to the active ones (same topology), so converged
    structures stop costing model evaluations."""

    def __init__(self, model: EMLP, prob: _PairProblem, fraction: float = 0.75) -> None:
        self.model, self.full, self.fraction = model, prob, fraction
        self.members = torch.ones(prob.g.n_structures, dtype=torch.bool)
        self.sub, self.rows = prob, None
        self._operator = None  # (sub problem, x, v -> H v) of the last products

    def _compact(self, active: torch.Tensor) -> None:
        if int(active.sum()) < self.fraction * int(self.members.sum()) or bool(
            (active & ~self.members).any()
        ):
            self.members = active.clone()
            self.sub = _PairProblem(self.model, self.full.g.subgraph(active),
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
        self._compact(active)
        if self.rows is None:
            return self.full.energy_gradient(x, long_range)
        e_sub, g_sub = self.sub.energy_gradient(x[self.rows], long_range)
        e = energy.clone()
        e[self.members] = e_sub
        gr = grad.clone()
        gr[self.rows] = g_sub
        return e, gr


def relax_pairs(
    model: EMLP,
    structures: Structure | Sequence[Structure],
    options: RelaxOptions | None = None,
    bounds: Sequence[tuple[np.ndarray, np.ndarray] | None] | None = None,
    **overrides,
) -> list[RelaxResult]:
    """Relax the electron pairs of ``structures`` at fixed cores; one result per structure.

    Args:
        model: the eMLP (evaluated in float64).
        structures: starting structures (their ``pairs`` are the initial guess).
        options: :class:`RelaxOptions`; keyword ``overrides`` replace single fields.
        bounds: per structure ``None`` or ``(lower, upper)`` arrays of shape (P, 3) (Å) that box
            every pair coordinate (the paper's MD uses +-3x the largest core displacement).
    """
    if isinstance(structures, Structure):
        structures = [structures]
    opts = options or RelaxOptions()
    for k in overrides:
        if not hasattr(opts, k):
            raise TypeError(f"unknown relaxation option {k!r}")
    opts = replace(opts, **overrides)  # the caller's options are never changed
    if opts.short_range_start not in ("lumped", "zero"):
        raise ValueError(
            f"short_range_start must be 'lumped' or 'zero', not {opts.short_range_start!r}"
        )
    if opts.initial_hessian not in ("coulomb", "exact", "bfgs"):
        raise ValueError(
            f"initial_hessian must be 'coulomb', 'exact' or 'bfgs', not {opts.initial_hessian!r}"
        )
    structures = list(structures)
    # frozen parameters: no parameter gradients are needed, and a family may then use a
    # cheaper frozen-weight evaluation (SchNet's: emlpack.nn.short_range.schnet)
    grad_flags = [(p, p.requires_grad) for p in model.parameters()]
    for p, _ in grad_flags:
        p.requires_grad_(False)
    try:
        results = _relax_once(model, structures, opts, bounds)
        # the graph (short-range neighbour list) is built at the start pairs and kept: a structure
        # whose result has an edge within the cutoff that the start lacked is relaxed again
        # from its result with a graph built there (until the neighbour list holds)
        starts = list(structures)
        for rebuild in range(_MAX_GRAPH_REBUILDS + 1):
            stale = [k for k, r in enumerate(results)
                     if not r.failed and _missing_edges(model, starts[k], r.pairs)]
            if not stale:
                break
            if rebuild == _MAX_GRAPH_REBUILDS:  # still moving into the cutoff: not trusted
                for k in stale:
                    results[k].converged = False
                    results[k].reason = (f"the pairs still moved into the cutoff after"
                                         f" {rebuild} rebuilds of the neighbour list")
                break
            for k in stale:
                starts[k] = starts[k].copy(pairs=results[k].pairs)
            sub_bounds = None if bounds is None else [bounds[k] for k in stale]
            again = _relax_once(model, [starts[k] for k in stale], opts, sub_bounds)
            for k, r in zip(stale, again, strict=True):
                results[k] = _after(results[k], r)
        return results
    finally:
        for p, flag in grad_flags:
            p.requires_grad_(flag)


#: relaxations again from the result with a graph built there, at most (each one usually
#: takes one to three iterations; docs/relaxation.md)
_MAX_GRAPH_REBUILDS = 3


def _missing_edges(model: EMLP, start: Structure, pairs: np.ndarray) -> bool:
    """Whether particles within the short-range cutoff with the pairs at ``pairs`` [P, 3] (Å) were
    farther apart in ``start``, whose neighbour list the relaxation used (only edges of a pair
    can change at fixed cores; edges that left the cutoff contribute exactly zero)."""
    if start.n_pairs == 0 or np.array_equal(pairs, start.pairs):
        return False
    cutoff = model.config.cutoff
    if start.pbc:
        end = start.copy(pairs=pairs)
        from emlpack.nn.neighbors import half_neighbor_list

        def edges(s: Structure) -> set:
            # each unordered edge once, whichever way round the half list gives it
            i, j, shifts = half_neighbor_list(s.all_positions, s.cell, True, cutoff)
            return {min((int(a), int(b), *map(int, c)), (int(b), int(a), *map(int, -c)))
                    for a, b, c in zip(i, j, shifts, strict=True)}

        return not edges(end) <= edges(start)
    p0 = start.all_positions
    p1 = np.concatenate([start.positions, pairs], axis=0)
    d0 = np.linalg.norm(start.pairs[:, None] - p0[None], axis=-1)  # [P, n_particles]
    d1 = np.linalg.norm(pairs[:, None] - p1[None], axis=-1)
    return bool(np.any((d1 < cutoff) & (d0 >= cutoff)))


def _relax_once(model: EMLP, structures: Sequence[Structure], opts: RelaxOptions,
                bounds: _Bounds) -> list[RelaxResult]:
    """One relaxation of ``structures`` on graphs built at their start pairs."""
    if opts.initial_hessian != "coulomb":
        return _escape_saddles(model, structures, _relax(model, structures, opts, bounds),
                               opts, bounds)
    results = _relax_coulomb(model, structures, opts, bounds)
    # a failed quasi-Newton relaxation (e.g. slid into a merged pair, off to a neighbouring
    # basin of a poorly trained model) is tried again with the exact-Hessian Newton method
    # from the same start, so the default fails no more often than the exact method; a
    # converged saddle goes on to the escape along its softest mode instead (the exact
    # Newton method returns to the saddle, or worse)
    retry = [k for k, r in enumerate(results) if r.failed and not (
        opts.saddle_escapes > 0 and opts.check_curvature and _at_saddle(structures[k], r, opts))]
    if retry:
        sub_bounds = None if bounds is None else [bounds[k] for k in retry]
        again = _relax(model, [structures[k] for k in retry],
                       replace(opts, initial_hessian="exact"), sub_bounds)
        for k, r in zip(retry, again, strict=True):
            if r.failed:
                r.reason = f"{results[k].reason} (exact-Hessian retry: {r.reason})"
            results[k] = _after(results[k], r)
    return _escape_saddles(model, structures, results, opts, bounds)


def _at_saddle(structure: Structure, result: RelaxResult, opts: RelaxOptions) -> bool:
    """Whether ``result`` failed only by a negative pair curvature (a converged saddle)."""
    return bool(
        result.failed and result.max_force < opts.fmax
        and np.isfinite(result.min_curvature) and result.min_curvature <= -opts.flat_curvature
        and not check_pairs(result.pairs, structure.positions, structure.cell, structure.pbc,
                            min_pair_distance=opts.min_pair_distance,
                            max_core_distance=opts.max_core_distance)
    )


def _escape_saddles(model: EMLP, structures: Sequence[Structure], results: list[RelaxResult],
                    opts: RelaxOptions, bounds: _Bounds) -> list[RelaxResult]:
    """``results`` with every converged saddle (:func:`_at_saddle`) relaxed again from its
    pairs displaced by ``opts.saddle_step`` along the softest mode of the exact pair Hessian,
    both ways (at most ``opts.saddle_escapes`` rounds): the lowest successful result replaces
    it, counts added up (one exact Hessian per escape)."""
    if opts.saddle_escapes <= 0 or not opts.check_curvature:
        return results
    inner = replace(opts, saddle_escapes=0)
    for _ in range(opts.saddle_escapes):
        stuck = [k for k, r in enumerate(results) if _at_saddle(structures[k], r, opts)]
        if not stuck:
            break
        starts, owners = [], []
        for k in stuck:
            at = structures[k].copy(pairs=results[k].pairs)
            mode = np.linalg.eigh(pair_hessian(model, at))[1][:, 0].reshape(-1, 3)
            mode *= opts.saddle_step / np.linalg.norm(mode, axis=1).max()
            for sign in (1.0, -1.0):
                pairs = at.pairs + sign * mode
                if bounds is not None and bounds[k] is not None:
                    pairs = np.clip(pairs, *bounds[k])
                starts.append(at.copy(pairs=pairs))
                owners.append(k)
        again = _relax_once(model, starts, inner,
                            None if bounds is None else [bounds[k] for k in owners])
        for k in stuck:
            tries = [r for o, r in zip(owners, again, strict=True) if o == k]
            # a minimum first, then a saddle to escape from in the next round; lowest energy
            best = min(tries, key=lambda r: (r.failed, not _at_saddle(structures[k], r, opts),
                                             r.energy))
            for r in tries:
                if r is not best:
                    best = _after(r, best)
            best.n_hessians += 1
            if best.failed:
                best.reason += " (relaxed again from a saddle along its softest mode)"
            results[k] = _after(results[k], best)
    return results


def _after(first: RelaxResult, then: RelaxResult) -> RelaxResult:
    """``then``, a relaxation that went on from ``first``, with both one's counts."""
    then.iterations += first.iterations
    then.n_evaluations += first.n_evaluations
    then.n_hessians += first.n_hessians
    return then


def _setup(
    model: EMLP, structures: Sequence[Structure], bounds: _Bounds,
    dtype: torch.dtype = torch.float64, filter_table: float = 0.0,
) -> tuple[Graph, _PairProblem, torch.Tensor, torch.Tensor, torch.Tensor,
           Callable[[torch.Tensor, torch.Tensor], torch.Tensor]]:
    g = model.graph(structures, dtype=dtype)
    prob = _PairProblem(model, g, filter_table=filter_table)
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


def _newton_step(prob: _PairProblem, hessian: torch.Tensor, gp: torch.Tensor,
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


class _BondRotations:
    """Steps of the pairs in cylindrical coordinates about the axis through each pair's two
    nearest cores (molecules; fixed for the relaxation): the tangential part of a Cartesian
    step rotates the pair about that axis (the distances to both cores are kept), the radial
    and axial parts are applied as they are. To first order this is the Cartesian step; it
    follows soft rotations of pairs about a bond (e.g. acetylene's triple-bond pairs) without
    the radial stretch of a straight step. Pairs closer than ``rho_min`` (Å) to their axis,
    tangential steps over 1 rad, zero steps and crystals take the straight step.

    The quasi-Newton model works in these coordinates (per pair: radial, arc length at the
    current radius, axial; :meth:`connection`, :meth:`generalized`): its SR1 secants are the
    turned step and the gradient turned back, and its short-range part turns with the pairs,
    so a rotation along a soft mode no longer reads as the Cartesian chord (whose radial
    O(theta^2 rho) part made SR1 take away the stiff radial curvature)."""

    def __init__(self, structures: Sequence[Structure], x: torch.Tensor,
                 rho_min: float = 0.3) -> None:
        # (measured: rho_min 0.1, 0.2, 0.3 Å alike on the benchmark's acetylene, with the
        # curvilinear secants 0.2 and 0.3 too; 0.3 kept the fixture-weight propane of
        # tests/pairs within 100 quasi-Newton iterations: 77 evaluations, > 100 with 0.2)
        a, b, on, axis = [], [], [], []
        for k, s in enumerate(structures):
            n = len(s.pairs)
            if n == 0:
                continue
            if np.any(s.pbc) or s.n_cores < 2:
                a.append(np.zeros((n, 3)))
                b.append(np.zeros((n, 3)))
                on.append(np.zeros(n, dtype=bool))
                axis.append(np.full((n, 4), -1))
                continue
            d = np.linalg.norm(s.pairs[:, None] - s.positions[None], axis=-1)
            near = np.argsort(d, axis=1)[:, :2]
            a.append(s.positions[near[:, 0]])
            b.append(s.positions[near[:, 1]])
            on.append(np.ones(n, dtype=bool))
            # the sign orients each axis from its lower-numbered core (the same sense of
            # rotation for every pair of a bond)
            sign = np.where(near[:, 0] < near[:, 1], 1, -1)
            axis.append(np.column_stack([np.full(n, k), np.sort(near, axis=1), sign]))
        cat = np.concatenate
        # per pair: the bond it turns about (structure, both cores); -1 for straight steps
        # and the sign of its axis u relative to that bond
        axis = torch.as_tensor(cat(axis) if axis else np.zeros((0, 4), dtype=np.int64))
        self.axis, self.axis_sign = axis[:, :3], axis[:, 3:].to(x.dtype)
        self.a = torch.as_tensor(cat(a) if a else np.zeros((0, 3)), dtype=x.dtype)
        u = torch.as_tensor(cat(b) if b else np.zeros((0, 3)), dtype=x.dtype) - self.a
        self.u = u / torch.clamp(torch.linalg.norm(u, dim=1, keepdim=True), min=1e-12)
        self.on = torch.as_tensor(cat(on) if on else np.zeros(0, dtype=bool))
        self.rho_min = rho_min
        if len(self.a) != len(x):
            raise ValueError(f"{len(self.a)} pair axes for {len(x)} pairs")

    def __call__(self, x: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        return self.turn(x, step)[0]

    def _frame(self, x: torch.Tensor):
        """Per pair: distance along the axis (P, 1), radius (P, 1), radial and tangential unit
        vectors (P, 3), and whether the pair turns (P, 1) (kept for the last ``x`` object: the
        relaxation asks for it several times per iteration)."""
        cached = getattr(self, "_cache", None)
        if cached is not None and cached[0] is x and cached[1] == x._version:
            return cached[2]
        self._cache = (x, x._version, self._compute_frame(x))
        return self._cache[2]

    def _compute_frame(self, x: torch.Tensor):
        rel = x - self.a
        along = (rel * self.u).sum(1, keepdim=True)
        perp = rel - along * self.u
        rho = torch.linalg.norm(perp, dim=1, keepdim=True)
        rhat = perp / torch.clamp(rho, min=1e-12)
        that = torch.linalg.cross(self.u, rhat, dim=1)
        return along, rho, rhat, that, self.on[:, None] & (rho > self.rho_min)

    def turn(self, x: torch.Tensor, step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The new pairs (P, 3) for the step (P, 3) in cylindrical coordinates (radial,
        tangential as the arc, axial; Å) and each pair's rotation (P, 3, 3) about its axis
        (identity for the straight steps)."""
        along, rho, rhat, that, on = self._frame(x)
        s_t = (step * that).sum(1, keepdim=True)
        s_r = (step * rhat).sum(1, keepdim=True)
        s_a = (step * self.u).sum(1, keepdim=True)
        theta = s_t / torch.clamp(rho, min=1e-12)
        turned = self.a + (along + s_a) * self.u + (rho + s_r) * (
            torch.cos(theta) * rhat + torch.sin(theta) * that
        )
        # (a zero step stays exactly zero: the turn would move the pair by rounding)
        use = on & (theta.abs() <= 1.0) & (step != 0).any(1, keepdim=True)
        theta = torch.where(use, theta, 0.0)[:, :, None]
        # Rodrigues: R = cos I + sin [u]x + (1 - cos) u u^T
        u = self.u
        zero = torch.zeros_like(u[:, 0])
        cross = torch.stack([
            torch.stack([zero, -u[:, 2], u[:, 1]], 1),
            torch.stack([u[:, 2], zero, -u[:, 0]], 1),
            torch.stack([-u[:, 1], u[:, 0], zero], 1),
        ], 1)
        rot = (torch.cos(theta) * torch.eye(3, dtype=x.dtype) + torch.sin(theta) * cross
               + (1 - torch.cos(theta)) * u[:, :, None] * u[:, None, :])
        return torch.where(use, turned, x + step), rot

    def collective(self, x: torch.Tensor, arc: float, min_pairs: int) -> torch.Tensor:
        """A step (P, 3) that turns every group of at least ``min_pairs`` pairs about one bond
        (e.g. a triple bond's three pairs) together, each pair by the arc ``arc`` (Å, a step for
        :meth:`turn`); zero for the other pairs."""
        *_, that, on = self._frame(x)
        on = on[:, 0]
        if not bool(on.any()):
            return torch.zeros_like(x)
        _, group, count = torch.unique(self.axis[on], dim=0, return_inverse=True,
                                       return_counts=True)
        member = torch.zeros_like(on)
        member[on] = count[group] >= min_pairs
        return torch.where(member[:, None], arc * self.axis_sign * that, 0.0)

    def connection(self, x: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
        """Per-pair 3x3 blocks (P, 3, 3; eV/Å^2) that turn a Cartesian pair Hessian at ``x``
        into the Hessian in the cylindrical coordinates of :meth:`turn` (arc length at ``x``'s
        radius, axes in the Cartesian frame of ``x``) given the gradient ``grad`` (P, 3):
        ``-g_r / rho`` on the tangential diagonal, ``g_t / rho`` between radial and
        tangential; zero for the pairs that step straight."""
        _, rho, rhat, that, on = self._frame(x)
        inv = torch.where(on, 1.0 / torch.clamp(rho, min=1e-12), 0.0)[:, :, None]
        g_r = (grad * rhat).sum(1)[:, None, None]
        g_t = (grad * that).sum(1)[:, None, None]
        tt = that[:, :, None] * that[:, None, :]
        rt = rhat[:, :, None] * that[:, None, :]
        return inv * (-g_r * tt + g_t * (rt + rt.transpose(1, 2)))

    def generalized(self, x: torch.Tensor, step: torch.Tensor, rot: torch.Tensor,
                    grad_new: torch.Tensor) -> torch.Tensor:
        """The gradient (P, 3) at ``x`` + the turned ``step`` in the cylindrical coordinates of
        :meth:`turn` at ``x`` (the Cartesian gradient turned back, its tangential part scaled
        by the radius ratio); the straight pairs' gradient as it is."""
        _, rho, rhat, that, _ = self._frame(x)
        back = torch.einsum("pji,pj->pi", rot, grad_new)
        ratio = (step * rhat).sum(1, keepdim=True) / torch.clamp(rho, min=1e-12)
        turned = (rot - torch.eye(3, dtype=x.dtype)).abs().amax((1, 2))[:, None] > 0
        return back + torch.where(turned, ratio, 0.0) * (back * that).sum(1, keepdim=True) * that


def _sr1_update(prob: _PairProblem, short: torch.Tensor, curvilinear: _BondRotations | None,
                x: torch.Tensor, g_short: torch.Tensor, step: torch.Tensor,
                newton: torch.Tensor, rot: torch.Tensor | None, g_short_new: torch.Tensor,
                active: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Symmetric-rank-one update of the short-range model ``short`` (B, m, m; eV/Å^2) from a
    step (P, 3; Å) evaluated at ``x`` + ``step``: short-range gradients ``g_short`` at ``x`` and
    ``g_short_new`` there (eV/Å), only for the ``active`` (B,) structures, skipped when r.s is
    tiny. With ``rot`` (the pairs' rotations from :meth:`_BondRotations.turn` of ``newton``,
    the step before turning) the secant is taken in the cylindrical coordinates of the turned
    pairs: the step (tangential part the arc) and the short-range gradient in them, less the
    connection term of the short-range gradient (``short`` is Cartesian). Returns the model and
    which pairs turned (P,) bool (None for straight steps)."""
    turned_pair = None
    if rot is None:
        s = prob.pad(step)
        r = prob.pad(g_short_new - g_short) - (short @ s[:, :, None]).squeeze(-1)
    else:
        turned_pair = (rot - torch.eye(3, dtype=rot.dtype)).abs().amax((1, 2)) > 0
        s_pairs = torch.where(turned_pair[:, None], newton, step)
        conn = curvilinear.connection(x, g_short)
        conn = torch.where(turned_pair[:, None, None], conn, 0.0)
        y = (curvilinear.generalized(x, newton, rot, g_short_new) - g_short
             - (conn @ s_pairs[:, :, None]).squeeze(-1))
        s = prob.pad(s_pairs)
        r = prob.pad(y) - (short @ s[:, :, None]).squeeze(-1)
    rs = (r * s).sum(1)
    size = torch.linalg.norm(r, dim=1) * torch.linalg.norm(s, dim=1)
    ok = active & (rs.abs() > 1e-8 * size) & (rs.abs() > 1e-30)
    upd = r[:, :, None] * r[:, None, :] / torch.where(ok, rs, 1.0)[:, None, None]
    return torch.where(ok[:, None, None], short + upd, short), turned_pair


def _blocks_to_padded(prob: _PairProblem, blocks: torch.Tensor) -> torch.Tensor:
    """Per-pair 3x3 blocks (P_total, 3, 3) -> block-diagonal padded (B, 3 Pmax, 3 Pmax)."""
    b, n = prob.g.n_structures, prob.n_max
    out = blocks.new_zeros(b, n, n, 3, 3)
    out[prob.pair_batch, prob.local, prob.local] = blocks
    return out.permute(0, 1, 3, 2, 4).reshape(b, 3 * n, 3 * n)


def _relax_coulomb(model: EMLP, structures: Sequence[Structure], opts: RelaxOptions,
                   bounds: _Bounds) -> list[RelaxResult]:
    """Quasi-Newton with the exact analytic electrostatic pair Hessian at every iterate plus a
    symmetric-rank-one model of the short-range remainder, learnt from the change of gradient
    minus the change of the electrostatic gradient (one energy+gradient per iteration)."""
    dtype = torch.float64
    g, prob, x, lower, upper, projected = _setup(model, structures, bounds, dtype,
                                                      opts.filter_table)
    b = g.n_structures
    bounded = bool(torch.isfinite(lower).any() or torch.isfinite(upper).any())
    coulomb = _CoulombPairs(model, prob)
    # float32 phase: structures with a pair force above opts.float32_above (measured on the
    # trained benchmark model: float32 energy+gradient 2.5x cheaper, gradient error 2e-5 eV/Å,
    # energy error 8e-6 eV at |E| = 12 eV)
    # (EMLP's own energy only: subclasses with their own energy_parts stay in float64)
    low = bool(opts.float32_above > 0 and g.n_pairs.max() > 0
               and int(g.n_pairs.sum()) >= opts.float32_min_pairs
               and standard_energy(model))
    prob32 = prob
    if low:
        # the held core-core edges rounded from float64 (not recomputed in float32); a family
        # that cannot evaluate float32 inputs on its float64 weights gets a float32 copy
        held32 = None if prob.held is None else prob.held.to(torch.float32)
        model32 = (model if isinstance(model.short_range, FrozenAnyDtype)
                   else for_evaluation(model, torch.float32))
        prob32 = _PairProblem(model32, g.to(dtype=torch.float32), held=held32,
                              filter_table=prob.filter_table, tabulate=prob.tabulated)
    work = prob32 if low else prob
    # EMLP's own energy: the model evaluations leave out the electrostatics, whose energy and
    # gradient come from the analytic derivatives computed at every iterate anyway (float64)
    analytic = standard_energy(model)
    lr = not analytic  # whether the model evaluations include the electrostatics
    energy, grad = (t.to(dtype) for t in work.energy_gradient(x.to(work.g.dtype), lr))
    use32 = torch.full((b,), bool(low))
    exact64 = ~use32  # energy and gradient are float64 values
    gc, hc, e_coulomb = coulomb(x, energy=analytic)
    g_short = grad if analytic else grad - gc
    if analytic:
        energy, grad = energy + e_coulomb, grad + gc
    m = 3 * prob.n_max
    short = torch.zeros(b, m, m, dtype=dtype)
    n_eval = torch.ones(b, dtype=torch.long)
    pad_eye = torch.diag_embed(
        (torch.arange(m)[None, :] >= 3 * g.n_pairs[:, None]).to(dtype)
    )
    n_hess = torch.zeros(b, dtype=torch.long)
    iters = torch.zeros(b, dtype=torch.long)
    fmax = prob.per_structure_max_norm(projected(grad, x))
    converged = (fmax < opts.fmax) & exact64 | (g.n_pairs == 0)
    if opts.short_range_start == "lumped" and not bool(converged.all()):
        # float32: a larger difference step (measured: 3e-4 Å gives 3e-4 relative error)
        short = _lumped_short_range(work, coulomb, x, g_short, 3e-4 if low else 1e-4, lr)
        n_eval += 3 * (~converged).long()
    evaluate = _ActiveEvaluator(model, prob)
    evaluate32 = _ActiveEvaluator(prob32.model, prob32)
    curvilinear = _BondRotations(structures, x) if opts.bond_rotations else None
    # structures with a group of pairs about one bond take one step along its collective
    # rotation (``rotation_probe``) instead of a Newton step, once; then ``probed``
    unprobed = torch.zeros(b, dtype=torch.bool)
    probed = torch.zeros(b, dtype=torch.bool)
    if curvilinear is not None and opts.rotation_probe > 0:
        unprobed = segment_sum(curvilinear.collective(x, 1.0, opts.rotation_probe_pairs).abs()
                               .sum(1), prob.pair_batch, b) > 0
    # trust radius (Å, largest pair displacement): halved to the rejected step's length,
    # doubled from an accepted one's up to max_step
    radius = torch.full((b,), opts.max_step, dtype=dtype)
    stalled = torch.zeros(b, dtype=torch.bool)
    quasi_newton = min(opts.max_iterations, opts.newton_after or opts.max_iterations)
    # float32 structures leave the float32 phase below this largest pair force (eV/Å)
    leave32 = max(opts.float32_above, opts.fmax)
    for _ in range(quasi_newton):
        active = ~converged & ~stalled
        if not bool(active.any()):
            break
        # float32 structures below the threshold take their next step in float64, accepted
        # when it lowers the pair-gradient norm (no float64 energy to compare with yet); when
        # it does not, they are re-evaluated in float64 where they are (no step), then go on
        trying = active & use32 & (fmax < leave32)
        if int(g.n_pairs[active & use32 & ~trying].sum()) < opts.float32_min_pairs:
            # too few float32 pairs left: a float32 call that small is dispatch-bound (no
            # cheaper than float64) and a second model call per iteration; all leave float32
            # (measured: 33 -> 25 model calls on the 64-structure benchmark)
            trying = active & use32
        switch = active & ~use32 & ~exact64
        moving = active & ~switch
        gp = prob.pad(projected(grad, x))
        held = None
        if bounded:
            held = prob.pad(((x <= lower) | (x >= upper)) & (projected(grad, x) == 0)) > 0
        model_hessian = hc + short + pad_eye
        if curvilinear:
            # the model in the cylindrical coordinates of the turned steps
            model_hessian = model_hessian + _blocks_to_padded(
                prob, curvilinear.connection(x, grad))
        # (a structure whose rotation was probed: its soft mode is in the model, and the
        # floor would shorten the steps along it)
        floor = torch.where(probed, opts.rotation_floor, 1e-2)
        step = _newton_step(prob, model_hessian, gp, held, floor, moving,
                            torch.ones_like(radius), radius, opts.mirror_curvature or None)
        probing = moving & unprobed & (fmax < opts.rotation_probe_below)
        if bool(probing.any()):
            # the lumped start sees a triple bond's pairs turning one at a time, stiff, while
            # together they turn almost freely near the minimum (measured: docs/relaxation.md):
            # a step along that rotation, downhill, puts its curvature into the SR1 model
            rotation = curvilinear.collective(x, opts.rotation_probe, opts.rotation_probe_pairs)
            slope = segment_sum((grad * rotation).sum(1), prob.pair_batch, b)
            downhill = torch.where(slope > 0, -1.0, 1.0).to(dtype)
            step = torch.where(probing[prob.pair_batch, None],
                               downhill[prob.pair_batch, None] * rotation, step)
            unprobed &= ~probing
            probed |= probing
        newton = step
        rot = None
        if curvilinear:
            x_new, rot = curvilinear.turn(x, step)
            if bounded:
                x_turn, x_new = x_new, torch.clamp(x_new, lower, upper)
                # a pair moved by the box bound takes the chord in the secant
                rot = torch.where((x_new != x_turn).any(1)[:, None, None],
                                  torch.eye(3, dtype=dtype), rot)
        else:
            x_new = torch.clamp(x + step, lower, upper) if bounded else x + step
        step = x_new - x
        in32 = moving & use32 & ~trying
        in64 = active & ~in32
        e_new, g_new = energy, grad
        if bool(in64.any()):
            e_new, g_new = evaluate(x_new, in64, energy, grad, lr)
        if bool(in32.any()):
            e32, g32 = evaluate32(x_new.float(), in32, energy.float(), grad.float(), lr)
            e_new = torch.where(in32, e32.to(dtype), e_new)
            g_new = torch.where(in32[prob.pair_batch, None], g32.to(dtype), g_new)
        gc_new, hc_new, ec_new = coulomb(x_new, active, energy=analytic)
        if analytic:
            e_new = torch.where(active, e_new + ec_new, energy)
            g_new = torch.where(active[prob.pair_batch, None], g_new + gc_new, grad)
        n_eval += active.long()
        iters += moving.long()
        slope = segment_sum((grad * step).sum(1), prob.pair_batch, b)
        # structures sent to float64 above leave32 (the small float32 tail) compare their
        # float64 energy with the float32 one, with the float32 allowance
        forced = trying & (fmax >= leave32)
        noisy = in32 | forced
        noise = torch.where(noisy, 1e-6, 1e-12) * energy.abs()
        accept = switch | (moving & ~trying | forced) & (e_new <= energy + 1e-4 * slope + noise)
        # steps whose predicted decrease is below the float32 energy's resolution (near the
        # minimum) are accepted when they lower the pair-gradient norm instead
        flat = noisy & (slope.abs() < noise)
        by_norm = trying & ~forced | flat
        if bool(by_norm.any()):
            norm_new = segment_sum((projected(g_new, x_new) ** 2).sum(1), prob.pair_batch, b)
            norm_old = segment_sum((projected(grad, x) ** 2).sum(1), prob.pair_batch, b)
            accept |= by_norm & (norm_new < norm_old)
        exact64 |= switch | trying & accept
        use32 &= ~trying
        reject = active & ~accept
        # SR1 from every evaluated step, rejected ones included (measured: updating from
        # accepted steps only needs 2-5x more iterations)
        short, turned_pair = _sr1_update(prob, short, curvilinear, x, grad - gc, step, newton,
                                         rot, g_new - gc_new, active)
        if rot is not None:
            # the short-range model turns with the accepted pairs (only the structures with a
            # turned pair: the others' rotations are the identity)
            turning = accept & (segment_sum(turned_pair.to(dtype), prob.pair_batch, b) > 0)
            ks = torch.nonzero(turning).squeeze(1)
            if len(ks):
                rows = turning[prob.pair_batch]
                turn = torch.eye(3, dtype=dtype).repeat(len(ks), prob.n_max, 1, 1)
                new_index = torch.cumsum(turning.long(), 0) - 1
                turn[new_index[prob.pair_batch[rows]], prob.local[rows]] = rot[rows]
                blocks = short[ks].reshape(len(ks), prob.n_max, 3, prob.n_max, 3)
                short[ks] = torch.einsum("biac,bicjd,bjed->biaje", turn, blocks,
                                         turn).reshape(len(ks), m, m)
        acc_p = accept[prob.pair_batch, None]
        x = torch.where(acc_p, x_new, x)
        grad = torch.where(acc_p, g_new, grad)
        gc = torch.where(acc_p, gc_new, gc)
        hc = torch.where(accept[:, None, None], hc_new, hc)
        energy = torch.where(accept, e_new, energy)
        taken = prob.per_structure_max_norm(step)
        old_radius = radius
        radius = torch.where(accept, torch.clamp(torch.maximum(radius, 2.0 * taken),
                                                 max=opts.max_step), radius)
        radius = torch.where(reject, 0.5 * taken, radius)
        radius = torch.where(probing, old_radius, radius)  # a probe leaves the trust radius
        stalled |= reject & (radius < 1e-7)
        if opts.collapse_distance > 0:
            stalled |= accept & (prob.closest_pair_distance(x) < opts.collapse_distance)
        fmax = prob.per_structure_max_norm(projected(grad, x))
        converged = converged | (fmax < opts.fmax) & exact64

    # the few structures still unconverged (nearly flat modes: the SR1 model learns them
    # slowly) finish with the exact-Hessian Newton method
    late = ~converged & ~stalled & (g.n_pairs > 0)
    left = opts.max_iterations - quasi_newton
    if left > 0 and bool(late.any()):
        ks = torch.nonzero(late).squeeze(1).tolist()
        xs = x.detach().numpy()
        pb = prob.pair_batch.numpy()
        sub = [structures[k].copy(pairs=xs[pb == k]) for k in ks]
        sub_opts = replace(opts, initial_hessian="exact", max_iterations=left,
                           check_curvature=False)
        sub_bounds = None if bounds is None else [bounds[k] for k in ks]
        for k, r in zip(ks, _relax(model, sub, sub_opts, sub_bounds), strict=True):
            rows = prob.pair_batch == k
            x[rows] = torch.as_tensor(r.pairs, dtype=dtype)
            grad[rows] = -torch.as_tensor(r.pair_forces, dtype=dtype)
            energy[k] = r.energy
            fmax[k] = r.max_force
            converged[k] = r.max_force < opts.fmax
            iters[k] += r.iterations
            n_eval[k] += r.n_evaluations
            n_hess[k] += r.n_hessians

    model_hessian = hc + short + pad_eye
    min_curv = _min_curvature(prob, x, grad, lower, upper, projected, opts, n_hess,
                              model_hessian, prob32)
    return _results(structures, prob, x, energy, grad, converged, iters, n_eval, n_hess,
                    fmax, min_curv, opts)


def _lumped_short_range(prob: _PairProblem, coulomb: _CoulombPairs, x: torch.Tensor,
                        g_short: torch.Tensor, step: float = 1e-4,
                        long_range: bool = True) -> torch.Tensor:
    """Block-diagonal (3x3 per pair) estimate of the short-range pair Hessian from three
    forward differences of the short-range gradient ``g_short`` (probe: one Cartesian
    direction on every pair at once, ``step`` Å; three batched energy+gradient evaluations in
    ``prob``'s dtype, differences in ``x``'s; ``long_range``: the evaluations include the
    electrostatics, taken off with ``coulomb``): each pair's block is the row sum of its
    short-range couplings (off-diagonal blocks lumped onto it)."""
    n = prob.n_max
    b = prob.g.n_structures
    blocks = x.new_zeros(len(x), 3, 3)
    for c in range(3):
        shifted = x.clone()
        shifted[:, c] += step
        _, g_shift = prob.energy_gradient(shifted.to(prob.g.dtype), long_range)
        g_shift = g_shift.to(x.dtype)
        if long_range:
            g_shift = g_shift - coulomb(shifted, hessian=False)[0]
        blocks[:, :, c] = (g_shift - g_short) / step
    blocks = 0.5 * (blocks + blocks.transpose(1, 2))
    out = x.new_zeros(b, n, n, 3, 3)
    out[prob.pair_batch, prob.local, prob.local] = blocks
    return out.permute(0, 1, 3, 2, 4).reshape(b, 3 * n, 3 * n)


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


def _min_curvature(prob: _PairProblem, x: torch.Tensor, grad: torch.Tensor,
                   lower: torch.Tensor, upper: torch.Tensor,
                   projected: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                   opts: RelaxOptions, n_hess: torch.Tensor,
                   model_hessian: torch.Tensor | None = None,
                   product_prob: _PairProblem | None = None) -> torch.Tensor:
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
        evaluate = _ActiveEvaluator(pp.model, pp)
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


def _relax(model: EMLP, structures: Sequence[Structure], opts: RelaxOptions,
           bounds: _Bounds) -> list[RelaxResult]:
    dtype = torch.float64
    g, prob, x, lower, upper, projected = _setup(model, structures, bounds, dtype,
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
    evaluate = _ActiveEvaluator(model, prob)
    alpha = torch.ones(b, dtype=dtype)
    stalled = torch.zeros(b, dtype=torch.bool)

    for _ in range(opts.max_iterations):
        active = ~converged & ~stalled
        if not bool(active.any()):
            break
        gp = prob.pad(projected(grad, x))
        held = prob.pad(((x <= lower) | (x >= upper)) & (projected(grad, x) == 0)) > 0
        step = _newton_step(prob, hessian, gp, held, floor, active, alpha, opts.max_step)
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

    min_curv = _min_curvature(prob, x, grad, lower, upper, projected, opts, n_hess)
    return _results(structures, prob, x, energy, grad, converged, iters, n_eval, n_hess,
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


def _results(structures: Sequence[Structure], prob: _PairProblem, x: torch.Tensor,
             energy: torch.Tensor, grad: torch.Tensor, converged: torch.Tensor,
             iters: torch.Tensor, n_eval: torch.Tensor, n_hess: torch.Tensor,
             fmax: torch.Tensor, min_curv: torch.Tensor,
             opts: RelaxOptions) -> list[RelaxResult]:
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
    (cores fixed); rows/columns ordered pair by pair, x y z (:meth:`_PairProblem.hessians`:
    ``"fast"``, the short-range block of the family for EMLP's own energy, else, or with
    ``"reverse"``, 3P reverse passes)."""
    g = model.graph(structure, dtype=torch.float64)
    prob = _PairProblem(model, g)
    if prob.n_max == 0:
        return np.zeros((0, 0))
    return prob.hessians(g.positions[prob.pair_idx], method=method)[0].numpy()
