"""What a short-range family is, and the optional capabilities it may offer.

A **short-range family** is an ``nn.Module`` (:class:`ShortRange`) that maps the particles of a
batch and the half edge list within the eMLP cutoff to one energy per particle::

    atomic = module(numbers, vectors, i, j)   # (N,) eV

* ``numbers`` (N,) long: atomic numbers of the cores, :data:`emlpack.structure.PAIR_NUMBER`
  (99) for the electron pairs; the species are the model's elements plus the pair;
* ``(i, j)`` (E,) long each: the half edge list, each unordered pair within the cutoff once
  (:attr:`emlpack.nn.graph.Graph.edge_i`, ``edge_j``); a family scatters both ways itself;
* ``vectors`` (E, 3) (Å): ``r_j - r_i`` plus the image shift (``shift @ cell``), as
  :meth:`emlpack.nn.potential.EMLP.edge_vectors` gives them; forces, stress, field and strain
  derivatives, Hessians and every response come from autograd through these vectors, so the
  module only computes energies;
* an electron pair may sit on a core: a zero-length edge. Values *and all derivatives* must
  stay finite there (use :func:`emlpack.nn.short_range.common.edge_lengths`, never ``d / |d|``
  without a safe denominator);
* the energy must be invariant under rotations and translations of all vectors and under
  permutations of equal particles, and smooth (twice differentiable) in the vectors: the
  extended Hessian differentiates it twice.

The module is built by :func:`emlpack.nn.short_range.build_short_range` as
``cls(cutoff=..., cutoff_transition=..., **params)``: ``cutoff`` (Å) is the eMLP's (the graph's
neighbour list), ``cutoff_transition`` (Å) the width of the cosine switch
(:func:`~emlpack.nn.short_range.common.cosine_cutoff`) that every family uses to reach zero
at the cutoff; ``params`` are the family's own hyperparameters (plain numbers, strings,
lists), stored in the model config and the checkpoint, and its state dict is saved as the
model's ``short_range.*`` weights.

**Capabilities** (optional speed-ups, detected by the presence of the methods below through
``isinstance(module, Capability)`` with these runtime-checkable protocols, never by the
module's class). Every caller has an exact generic path for a family without them:

* :class:`HoldsEdges`: ``hold(vectors, i, j, free)`` precomputes what the held edges (whose
  vectors do not change between calls: the core-core edges while only the pairs move) add,
  as a :class:`HeldEdges` object, and ``forward(..., held=held)`` with only the free edges'
  vectors evaluates the same energy (frozen parameters; SchNet holds its filters,
  :class:`emlpack.nn.short_range.schnet.HeldFilters`). Generic path: every edge evaluated
  at every call.
* :class:`TabulatesEdges`: ``tabulate(held, spacing)`` returns ``held`` with the free edges'
  per-edge functions taken from a table of that spacing (Å) (energies and first derivatives
  only; SchNet: :class:`~emlpack.nn.short_range.schnet.FilterTable`). Generic path: the
  network.
* :class:`LengthHessian`: ``length_hessian(numbers, r, i, j, jac, tangent_dtype)`` returns
  ``(dE/dr (E,), J^T d2E/dr2 J (m, m))`` of the summed energy for families whose energy
  depends on the edges through their lengths ``r = edge_lengths(vectors)`` only, given the
  Jacobian ``jac = dr/dx`` (E, m) of any m coordinates (SchNet:
  :func:`emlpack.nn.short_range.schnet_hessian.schnet_edge_hessian`); the fast extended
  Hessian and the pair relaxation's exact pair blocks use it
  (:func:`emlpack.nn.short_range.hessian.short_range_hessian`). Generic path: reverse over
  reverse on the short-range energy.

* :class:`LengthGradient`: ``energies_and_length_gradient(numbers, r, i, j, compiled)``
  returns the atomic energies (N,) and ``dE/dr`` (E,) of their sum in the edge lengths as
  one expression that is differentiable once in the parameters (the reverse pass written
  out), for families whose energy depends on the edges through their lengths only; training
  then fits forces with one backward pass, optionally compiled (SchNet:
  :mod:`emlpack.nn.short_range.schnet_gradient`). Generic path: ``dE/d(vectors)`` by
  autograd with ``create_graph=True`` (a double backward).
* :class:`VectorGradient`: ``energies_and_vector_gradient(numbers, vectors, i, j, compiled)``
  returns the atomic energies (N,) and ``dE/d(vectors)`` (E, 3) of their sum as one
  expression that is differentiable once in the parameters, for any family (PaiNN, whose
  energy depends on the directions too: :mod:`emlpack.nn.short_range.painn_gradient`);
  training uses it as :class:`LengthGradient`. Generic path: the same double backward.
* :class:`FrozenAnyDtype`: with frozen parameters the family evaluates in the dtype of its
  input vectors whatever its parameters' dtype (SchNet casts its folded weights); the pair
  relaxation's float32 phase then runs on the float64 model. Generic path: that phase runs
  on a float32 copy of the model.

Inference (forces, Hessians, relaxation, MD) freezes the parameters (``requires_grad=False``);
a family may evaluate faster then (SchNet multiplies its linear maps out:
:meth:`~emlpack.nn.short_range.schnet.SchNet.folded_weights`), with equal results up to
rounding.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

__all__ = ["FrozenAnyDtype", "HeldEdges", "HoldsEdges", "LengthGradient", "LengthHessian",
           "ShortRange", "TabulatesEdges", "VectorGradient"]


@runtime_checkable
class ShortRange(Protocol):
    """A short-range family: per-particle energies (eV) from the half edge list (see above)."""

    def forward(
        self, numbers: torch.Tensor, vectors: torch.Tensor, i: torch.Tensor, j: torch.Tensor
    ) -> torch.Tensor:
        """Atomic energies (N,) (eV) of the particles ``numbers`` (N,) with the half-list
        edges ``(i, j)`` (E,) of vectors ``vectors`` (E, 3) (Å)."""
        ...


class HeldEdges(Protocol):
    """What a family precomputed for the held edges ``(i, j)`` (H,) of a graph; ``free``
    (E - H,) indexes the graph's edges evaluated at every call."""

    i: torch.Tensor
    j: torch.Tensor
    free: torch.Tensor

    def subset(
        self, rows: torch.Tensor, old_to_new: torch.Tensor, free: torch.Tensor
    ) -> HeldEdges:
        """The held edges ``rows`` (H,) bool, their particles renumbered by ``old_to_new``
        (N,), with the new graph's free edges ``free``; nothing recomputed."""
        ...

    def to(self, dtype: torch.dtype) -> HeldEdges:
        """The same held edges with their precomputed values rounded to ``dtype``."""
        ...


@runtime_checkable
class HoldsEdges(Protocol):
    """Capability: edges whose vectors do not change are evaluated once (frozen weights)."""

    def hold(
        self, vectors: torch.Tensor, i: torch.Tensor, j: torch.Tensor, free: torch.Tensor
    ) -> HeldEdges:
        """Precompute the held edges ``(i, j)`` (H,) of vectors ``vectors`` (H, 3) (Å);
        ``free`` (E - H,): the graph's other edges. ``forward(numbers, vectors[free], i[free],
        j[free], held=...)`` then equals the plain evaluation up to rounding."""
        ...


@runtime_checkable
class TabulatesEdges(Protocol):
    """Capability: the free edges' per-edge functions from a table (first derivatives)."""

    def tabulate(self, held: HeldEdges, spacing: float) -> HeldEdges:
        """``held`` whose free edges are evaluated from a table of node spacing ``spacing``
        (Å) instead of the network (energies and gradients only, no second derivatives)."""
        ...


@runtime_checkable
class LengthHessian(Protocol):
    """Capability: the exact Hessian of the summed energy through the edge lengths."""

    def length_hessian(
        self,
        numbers: torch.Tensor,
        r: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        jac: torch.Tensor,
        tangent_dtype: torch.dtype | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(dE/dr (E,), J^T (d2E/dr dr) J (m, m))`` of the summed energy (eV, Å) of one
        structure with edge lengths ``r`` (E,) and Jacobian ``jac = dr/dx`` (E, m);
        ``tangent_dtype``: dtype of the directional derivatives (None: ``r``'s)."""
        ...


@runtime_checkable
class LengthGradient(Protocol):
    """Capability: energies and their length gradient as one first-order expression."""

    def energies_and_length_gradient(
        self,
        numbers: torch.Tensor,
        r: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        compiled: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Atomic energies (N,) (eV) and ``dE/dr`` (E,) (eV/Å) of their sum in the edge
        lengths ``r`` (E,) (Å), differentiable in the parameters (not in ``r``);
        ``compiled``: through ``torch.compile`` where it works."""
        ...


@runtime_checkable
class VectorGradient(Protocol):
    """Capability: energies and their edge-vector gradient as one first-order expression."""

    def energies_and_vector_gradient(
        self,
        numbers: torch.Tensor,
        vectors: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        compiled: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Atomic energies (N,) (eV) and ``dE/d(vectors)`` (E, 3) (eV/Å) of their sum in the
        half-list edge vectors ``vectors`` (E, 3) (Å), differentiable in the parameters (not
        in ``vectors``); ``compiled``: through ``torch.compile`` where it works."""
        ...


@runtime_checkable
class FrozenAnyDtype(Protocol):
    """Capability: with frozen parameters, evaluates in its input vectors' dtype whatever its
    parameters' dtype (declared by the attribute ``frozen_any_dtype = True``)."""

    frozen_any_dtype: bool
