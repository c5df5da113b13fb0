"""The eMLP energy model: short range + Gaussian-charge electrostatics + field term.

``E = E_short_range + E_long_range + E_field`` (eV). The short range is a family of
:mod:`emlpack.nn.short_range` (SchNet by default, the paper's), built by name from the config.
Forces are ``-dE/dr`` for every particle
(cores and electron pairs). The stress is ``(1/V) dE/d(eps)`` for the homogeneous deformation
``r -> r (I + eps)``, ``cell -> cell (I + eps)`` (row vectors, ASE sign, eV/Å^3), taken with
the neighbour list and the k set fixed.

The field term and the stress: the strain derivative of ``E_field = -mu . E`` is
``-mu_a E_b``, which for a crystal depends on which periodic image of each particle is used
(the polarization quantum), so it is not a material property. The stress therefore excludes
it: ``virial = dE/d(eps) + mu (x) E``; the paper's DFT stress labels are at zero field, where
both agree, and the reference's ``compute_static`` makes the same correction. The full
derivative is returned as ``virial_including_field`` for the extended Hessian's use.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from emlpack.nn.electrostatics import coulomb_molecular, ewald_reciprocal, field_energy
from emlpack.nn.graph import Graph, collate
from emlpack.nn.scatter import segment_sum
from emlpack.nn.short_range import (
    HeldEdges,
    HoldsEdges,
    LengthGradient,
    VectorGradient,
    build_short_range,
    family_defaults,
    resolve_params,
)
from emlpack.nn.short_range.common import edge_lengths
from emlpack.structure import Structure
from emlpack.units import ANGSTROM_IN_BOHR, REFERENCE_GAMMA, REFERENCE_GCUT_PER_BOHR

#: the family that a model config without one means (every config before the families)
DEFAULT_FAMILY = "schnet"


@dataclass
class ModelConfig:
    """Hyperparameters of the eMLP (lengths in Å). Defaults are the paper's.

    ``family`` names the short-range family (:func:`emlpack.nn.short_range.families`) and
    ``short_range`` holds its own parameters (its defaults filled in on construction;
    :func:`emlpack.nn.short_range.family_defaults`); ``cutoff`` and ``cutoff_transition``
    are shared by the graph (neighbour list) and the family (cosine switch); the rest is
    the electrostatics."""

    family: str = DEFAULT_FAMILY
    short_range: dict = field(default_factory=dict)
    cutoff: float = 4.0
    cutoff_transition: float = 0.5
    #: Gaussian charge parameter gamma = 1/(2 sigma) (1/Å); also the Ewald alpha
    gamma: float = REFERENCE_GAMMA
    #: Ewald reciprocal cutoff |k|/(2 pi) <= gcut (1/Å); reference: 0.25/bohr
    gcut: float = REFERENCE_GCUT_PER_BOHR * ANGSTROM_IN_BOHR
    #: the reference's 1e-10 Å in erf(gamma r)/(r + eps)
    coulomb_eps: float = 1e-10
    #: elements the model was trained for (cores); electron pairs are number 99
    elements: tuple[int, ...] = (1, 6, 7, 8)

    def __post_init__(self) -> None:
        if not isinstance(self.short_range, dict):
            raise ValueError(f"model config short_range must be a mapping, got"
                             f" {self.short_range!r}")
        self.short_range = resolve_params(self.family, self.short_range)
        self.elements = tuple(int(z) for z in self.elements)

    def to_dict(self) -> dict:
        """The hyperparameters as a plain dict (``elements`` as a list, ``short_range`` a
        copy with every parameter of the family)."""
        return {
            "family": self.family,
            "short_range": copy.deepcopy(self.short_range),
            "cutoff": self.cutoff,
            "cutoff_transition": self.cutoff_transition,
            "gamma": self.gamma,
            "gcut": self.gcut,
            "coulomb_eps": self.coulomb_eps,
            "elements": list(self.elements),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        """The config of a :meth:`to_dict` dict, or of a version-1 flat one (SchNet's
        parameters beside the others, no ``family``: :func:`nest_flat_keys`); unknown keys
        raise ``ValueError``."""
        return cls(**nest_flat_keys(d))


def nest_flat_keys(section: dict) -> dict:
    """A (partial) model config with the version-1 spelling moved into the current one: keys
    that are not :class:`ModelConfig` fields are SchNet parameters written beside the others
    (every config and checkpoint before the families) and go under ``short_range`` with
    ``family: schnet``. Such keys with another family, keys SchNet does not take, and a
    parameter given both ways raise ``ValueError``."""
    fields = set(ModelConfig.__dataclass_fields__)
    flat = {k: v for k, v in section.items() if k not in fields}
    out = {k: v for k, v in section.items() if k in fields}
    if not flat:
        return out
    unknown = sorted(set(flat) - set(family_defaults(DEFAULT_FAMILY)))
    if unknown:
        raise ValueError(f"unknown model config keys: {unknown}")
    family = out.get("family", DEFAULT_FAMILY)
    if family != DEFAULT_FAMILY:
        raise ValueError(f"model config keys {sorted(flat)} beside the others are SchNet's"
                         f" parameters (version-1 spelling); family {family!r} takes its"
                         " parameters under 'short_range'")
    nested = dict(out.get("short_range") or {})
    twice = sorted(set(nested) & set(flat))
    if twice:
        raise ValueError(f"model config keys {twice} given both beside the others and under"
                         " 'short_range'")
    out["family"] = DEFAULT_FAMILY
    out["short_range"] = {**nested, **flat}
    return out


class EMLP(nn.Module):
    """Electron machine learning potential acting on batched :class:`Graph` inputs; its
    short-range family is ``self.short_range`` (:mod:`emlpack.nn.short_range`)."""

    def __init__(self, config: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = config or ModelConfig()
        c = self.config
        self.short_range = build_short_range(c.family, c.short_range, cutoff=c.cutoff,
                                             cutoff_transition=c.cutoff_transition)

    # ------------------------------------------------------------------ input
    def graph(
        self, structures: Structure | list[Structure], dtype: torch.dtype | None = None
    ) -> Graph:
        """Batched input for ``structures`` in the model's dtype (or ``dtype``)."""
        if isinstance(structures, Structure):
            structures = [structures]
        allowed = set(self.config.elements)
        for s in structures:
            unknown = sorted(set(s.numbers.tolist()) - allowed)
            if unknown:
                raise ValueError(
                    f"{s.source}: element(s) Z={unknown} unknown to this model"
                    f" (trained for Z={sorted(allowed)})"
                )
        p = next(self.parameters())
        return collate(
            structures, self.config.cutoff, self.config.gcut, dtype or p.dtype, p.device
        )

    # ------------------------------------------------------------------ energy
    def atomic_energies(
        self,
        g: Graph,
        positions: torch.Tensor,
        cell: torch.Tensor,
        held: HeldEdges | None = None,
    ) -> torch.Tensor:
        """Short-range energies (N,) (eV) of every particle at ``positions`` (N, 3) (Å) and
        ``cell`` (B, 3, 3) (Å) on ``g``'s edges; with ``held`` (:meth:`hold_edges`) only the
        free edges are evaluated."""
        if held is None:
            vectors = self.edge_vectors(g, positions, cell)
            return self.short_range(g.numbers, vectors, g.edge_i, g.edge_j)
        free = held.free
        vectors = self.edge_vectors(g, positions, cell, free)
        return self.short_range(g.numbers, vectors, g.edge_i[free], g.edge_j[free], held=held)

    def energy_parts(
        self,
        g: Graph,
        positions: torch.Tensor | None = None,
        cell: torch.Tensor | None = None,
        field: torch.Tensor | None = None,
        held: HeldEdges | None = None,
        long_range: bool = True,
    ) -> dict[str, torch.Tensor]:
        """Energy parts (eV) per structure; ``positions``/``cell``/``field`` override ``g``'s.
        With ``held`` (:meth:`hold_edges`) the held edges are not evaluated again: their
        vectors must be those of ``g`` (frozen parameters only). ``long_range=False``: the
        electrostatic energy is left out (zero; for callers that add it from its analytic
        derivatives, e.g. the pair relaxation).

        Returns ``energy``, ``energy_short_range``, ``energy_long_range``, ``energy_field``
        (each (B,)) and ``atomic_energies`` (N,).
        """
        pos = g.positions if positions is None else positions
        cell = g.cell if cell is None else cell
        field = g.field if field is None else field
        atomic = self.atomic_energies(g, pos, cell, held)
        b = g.n_structures
        e_sr = segment_sum(atomic, g.batch, b)
        e_lr, e_field = self.electrostatic_energies(g, pos, cell, field, long_range)
        return {
            "energy": e_sr + e_lr + e_field,
            "energy_short_range": e_sr,
            "energy_long_range": e_lr,
            "energy_field": e_field,
            "atomic_energies": atomic,
        }

    def electrostatic_energies(
        self,
        g: Graph,
        positions: torch.Tensor,
        cell: torch.Tensor,
        field: torch.Tensor,
        long_range: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The Gaussian-charge Coulomb energy (molecules: direct sum; crystals: reciprocal
        Ewald) and the field energy ``-mu . E`` (eV), (B,) each, in ``positions``' dtype;
        ``long_range=False``: the Coulomb energy is zero. No parameters enter."""
        c = self.config
        b = g.n_structures
        # Electrostatics always in float64: its pair and self terms cancel to ~1e-2 of their
        # size, which costs float32 models 1e-4 eV; it is cheap next to the short range.
        p64, q64, c64 = positions.double(), g.charges.double(), cell.double()
        if long_range:
            e_lr = coulomb_molecular(
                p64, q64, g.coulomb_i, g.coulomb_j, g.batch, ~g.pbc, b, c.gamma, c.coulomb_eps
            ) + ewald_reciprocal(p64, q64, g.batch, c64, g.kvec_n.double(), g.kvec_batch,
                                 c.gamma)
            e_lr = e_lr.to(positions.dtype)
        else:
            e_lr = positions.new_zeros(b)
        e_field = field_energy(p64, q64, g.batch, field.double()).to(positions.dtype)
        return e_lr, e_field

    @staticmethod
    def edge_vectors(
        g: Graph, positions: torch.Tensor, cell: torch.Tensor, edges: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Vectors ``r_j - r_i`` (+ image shift) of the half-list short-range edges (Å),
        (E, 3); with ``edges`` (indices) of those edges only."""
        i, j, shift = g.edge_i, g.edge_j, g.edge_shift
        if edges is not None:
            i, j, shift = i[edges], j[edges], shift[edges]
        d = positions[j] - positions[i]
        if shift.numel():
            d = d + torch.einsum("ea,eab->eb", shift, cell[g.batch[i]])
        return d

    @classmethod
    def edge_lengths(
        cls,
        g: Graph,
        positions: torch.Tensor,
        cell: torch.Tensor,
        edges: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Lengths (Å) of the half-list short-range edges, ``sqrt(|d|^2 + 1e-20)``, (E,) (with
        ``edges``: of those only)."""
        return edge_lengths(cls.edge_vectors(g, positions, cell, edges))

    def hold_edges(self, g: Graph, hold: torch.Tensor) -> HeldEdges:
        """What the short-range family precomputes for the edges ``hold`` (E,) bool of ``g``
        at ``g``'s geometry, for :meth:`energy_parts` (e.g. the core-core edges while only the
        pairs move; frozen parameters; capability
        :class:`~emlpack.nn.short_range.protocol.HoldsEdges`, ``TypeError`` without it)."""
        if not isinstance(self.short_range, HoldsEdges):
            raise TypeError(f"short-range family {self.config.family!r} cannot hold edges")
        idx = torch.nonzero(hold).squeeze(1)
        with torch.no_grad():
            vectors = self.edge_vectors(g, g.positions.detach(), g.cell.detach(), idx)
        return self.short_range.hold(vectors, g.edge_i[idx], g.edge_j[idx],
                                     torch.nonzero(~hold).squeeze(1))

    def energy(
        self,
        g: Graph,
        positions: torch.Tensor | None = None,
        cell: torch.Tensor | None = None,
        field: torch.Tensor | None = None,
        held: HeldEdges | None = None,
    ) -> torch.Tensor:
        """Total energy (eV) per structure (``held``: see :meth:`energy_parts`)."""
        if held is None:  # subclasses with their own energy_parts take no ``held``
            return self.energy_parts(g, positions, cell, field)["energy"]
        return self.energy_parts(g, positions, cell, field, held=held)["energy"]

    def forward(
        self,
        g: Graph,
        forces: bool = True,
        stress: bool = False,
        create_graph: bool | None = None,
        parameters_only: bool = False,
        compiled: bool = False,
    ) -> dict[str, torch.Tensor]:
        """Energies, and forces (eV/Å, every particle) and stress (eV/Å^3) when asked.

        ``create_graph`` defaults to ``self.training`` (forces in the loss need it).
        ``parameters_only`` (training): the outputs are differentiable in the parameters only,
        not in the positions (:meth:`_forward_parameters_only`, the same values; one
        backward pass for a family with the capability
        :class:`~emlpack.nn.short_range.protocol.LengthGradient` or
        :class:`~emlpack.nn.short_range.protocol.VectorGradient`, through ``torch.compile``
        with ``compiled``).
        """
        if create_graph is None:
            create_graph = self.training
        if parameters_only and create_graph and (forces or stress):
            return self._forward_parameters_only(g, stress, compiled)
        pos = g.positions
        cell = g.cell
        inputs = []
        if forces or stress:
            pos = pos.detach().requires_grad_(True)
            inputs.append(pos)
        if stress:
            strain = torch.zeros_like(g.cell, requires_grad=True)
            inputs.append(strain)
            pos_s = pos + torch.einsum("na,nab->nb", pos, strain[g.batch])
            cell = g.cell + torch.bmm(g.cell, strain)
            out = self.energy_parts(g, pos_s, cell)
        else:
            out = self.energy_parts(g, pos)
        if inputs:
            grads = torch.autograd.grad(
                out["energy"].sum(), inputs, create_graph=create_graph
            )
            out["forces"] = -grads[0]
        if stress:
            out.update(self._stress(g, pos, grads[1]))
        return out

    def _forward_parameters_only(
        self, g: Graph, stress: bool, compiled: bool
    ) -> dict[str, torch.Tensor]:
        """:meth:`forward`'s outputs as functions of the parameters only (training).

        The electrostatic and field parts hold no parameters: their energies, forces and
        virial are computed without a graph. The short range's forces and virial come from
        ``dE/dd`` of the half-list edge vectors ``d`` (``F_i += dE/dd_e``, ``F_j -= dE/dd_e``,
        virial ``sum_e d_e (x) dE/dd_e``): with ``compiled``, from the family's written-out
        length gradient through ``torch.compile`` (capability
        :class:`~emlpack.nn.short_range.protocol.LengthGradient`, ``dE/dd = dE/dr d / r``;
        uncompiled it is slower than autograd) or its written-out vector gradient (capability
        :class:`~emlpack.nn.short_range.protocol.VectorGradient`, PaiNN), else by autograd in
        ``d`` with ``create_graph=True``."""
        n, b = g.positions.shape[0], g.n_structures
        with torch.enable_grad():
            pos = g.positions.detach().requires_grad_(True)
            inputs, pos_s, cell = [pos], pos, g.cell.detach()
            if stress:
                strain = torch.zeros_like(cell, requires_grad=True)
                inputs.append(strain)
                pos_s = pos + torch.einsum("na,nab->nb", pos, strain[g.batch])
                cell = cell + torch.bmm(cell, strain)
            e_lr, e_field = self.electrostatic_energies(g, pos_s, cell, g.field)
            grads = torch.autograd.grad((e_lr + e_field).sum(), inputs)
        d = self.edge_vectors(g, g.positions.detach(), g.cell.detach())
        sr = self.short_range
        if compiled and isinstance(sr, LengthGradient):
            r = edge_lengths(d)
            atomic, dedr = sr.energies_and_length_gradient(g.numbers, r, g.edge_i, g.edge_j,
                                                           compiled=compiled)
            ded = (dedr / r)[:, None] * d
        elif compiled and isinstance(sr, VectorGradient):
            atomic, ded = sr.energies_and_vector_gradient(g.numbers, d, g.edge_i, g.edge_j,
                                                          compiled=compiled)
        else:
            d = d.requires_grad_(True)
            atomic = sr(g.numbers, d, g.edge_i, g.edge_j)
            (ded,) = torch.autograd.grad(atomic.sum(), d, create_graph=True)
            d = d.detach()
        forces = segment_sum(ded, g.edge_i, n) - segment_sum(ded, g.edge_j, n) - grads[0]
        e_sr = segment_sum(atomic, g.batch, b)
        e_lr, e_field = e_lr.detach(), e_field.detach()
        out = {"energy": e_sr + e_lr + e_field, "energy_short_range": e_sr,
               "energy_long_range": e_lr, "energy_field": e_field, "atomic_energies": atomic,
               "forces": forces}
        if stress:
            virial_sr = segment_sum(d[:, :, None] * ded[:, None, :], g.batch[g.edge_i], b)
            out.update(self._stress(g, g.positions, grads[1] + virial_sr))
        return out

    def _stress(
        self, g: Graph, positions: torch.Tensor, virial_with_field: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """``virial_including_field`` (the strain derivative ``dE/d(eps)``, eV), ``virial``
        (without the field term's ``-mu (x) E``) and ``stress`` (``virial / V``, eV/Å^3; V = 1
        for molecules), (B, 3, 3) each, from ``dE/d(eps)``."""
        dipole = self.dipole(g, positions)
        virial = virial_with_field + dipole[:, :, None] * g.field[:, None, :]
        volume = torch.abs(torch.linalg.det(g.cell))
        volume = torch.where(g.pbc, volume, torch.ones_like(volume))
        return {"virial_including_field": virial_with_field, "virial": virial,
                "stress": virial / volume[:, None, None]}

    @staticmethod
    def dipole(g: Graph, positions: torch.Tensor | None = None) -> torch.Tensor:
        """Dipole moment sum_i q_i r_i (e·Å) of every structure, (B, 3)."""
        pos = g.positions if positions is None else positions
        return segment_sum(g.charges[:, None] * pos, g.batch, g.n_structures)

    # ------------------------------------------------------------------ conveniences
    def evaluate(
        self, structure: Structure, stress: bool | None = None, dtype: torch.dtype = torch.float64
    ) -> dict[str, np.ndarray | float]:
        """Energy (eV), core and pair forces (eV/Å), stress (eV/Å^3) of one structure, numpy."""
        stress = structure.pbc if stress is None else stress
        g = self.graph(structure, dtype=dtype)
        out = {k: v.detach() for k, v in self(g, stress=stress, create_graph=False).items()}
        f = out["forces"].cpu().numpy()
        result = {
            "energy": float(out["energy"][0]),
            "energy_short_range": float(out["energy_short_range"][0]),
            "energy_long_range": float(out["energy_long_range"][0]),
            "energy_field": float(out["energy_field"][0]),
            "atomic_energies": out["atomic_energies"].cpu().numpy(),
            "forces": f[: structure.n_cores],
            "pair_forces": f[structure.n_cores :],
        }
        if stress:
            for key in ("stress", "virial", "virial_including_field"):
                result[key] = out[key][0].cpu().numpy()
        return result

    def n_parameters(self) -> int:
        """Number of parameters (scalars) of the model."""
        return sum(p.numel() for p in self.parameters())


def for_evaluation(model: EMLP, dtype: torch.dtype = torch.float64) -> EMLP:
    """``model`` in ``dtype`` and evaluation mode: ``model`` itself when it already is, else a
    copy (the caller's model is never converted or switched to eval in place)."""
    if not model.training and next(model.parameters()).dtype == dtype:
        return model
    return copy.deepcopy(model).to(dtype).eval()
