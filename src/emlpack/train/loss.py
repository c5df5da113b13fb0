"""The paper's cost function (eq. 18) and validation metrics.

    C = lambda_E / B     sum_b ((E_b - E_tr,b) / N_b)^2              (N_b: cores of b)
      + lambda_f / 3N    sum_i |F_i - F_tr,i|^2                      (core forces)
      + lambda_c / 3C    sum_j |f_j - f_tr,j|^2                      (electron-pair forces)
      + lambda_s / 9B_s  sum_b |sigma_b - sigma_tr,b|^2              (stress in GPa, if labelled)
      + lambda_a / 9B_a  sum_b |alpha_b - alpha_tr,b|^2              (polarizability in bohr^3)

The last term is not the paper's (issue 51: a lever on the pairs' stiffness) and is off by
default (``lambda_a = 0``): ``alpha_b`` is the model's clamped-core polarizability
``H_Fp H_pp^-1 H_pF`` from its pair Hessian at the labelled DFT centres
(:func:`predict_polarizability`), for the configurations that carry a ``polarizability``
label; a batch without one leaves the loss as it was.

Validation also reports the pairs' field response (:func:`field_response_slope`).

Each term is a sum divided by a count. :func:`loss_terms` returns the sums and the counts
separately so that data-parallel training can divide by the *global* counts (then the gradient
of K processes equals that of one process with the same global batch).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import torch

from emlpack.data.dataset import Batch
from emlpack.properties.response import clamped_polarizabilities
from emlpack.units import COULOMB_EV_A, EV_PER_A3_IN_GPA, POLARIZABILITY_A3_IN_BOHR3

if TYPE_CHECKING:
    import numpy as np

    from emlpack.data.references import ConstantReference, HydrideReference
    from emlpack.nn.potential import EMLP

log = logging.getLogger(__name__)

#: the terms of the validation metrics and of every loss
TERMS = ("energy", "forces", "pair_forces", "stress")
#: e·Å²/V -> bohr³, the unit of the polarizability term's errors
_ALPHA_IN_BOHR3 = COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3


def field_response_slope(residual: np.ndarray | torch.Tensor,
                         field_force: np.ndarray | torch.Tensor) -> float:
    """``c = sum r . qE / sum |qE|^2`` over electron pairs (dimensionless).

    ``residual`` is predicted minus labelled pair force and ``field_force`` the field's force
    ``q E`` on each pair (eV/Å, same shape). The labels put each pair where DFT's Foster-Boys
    centre sits under the field; a model whose pairs are too soft (stiffness ``K_model``
    against DFT's ``K``) leaves ``(1 - K_model / K) q E`` of the field force unbalanced there,
    so ``c ~ 1 - K_model / K``: 0 when the pairs respond to a field as DFT's centres do, 0.5
    when they move about twice as far (polarizabilities about twice too large). The fields
    are random and independent of the geometry, so other errors average out of ``c``."""
    r = torch.as_tensor(residual, dtype=torch.float64)
    qe = torch.as_tensor(field_force, dtype=torch.float64)
    den = float((qe * qe).sum())
    return float((r * qe).sum()) / den if den > 0 else float("nan")


@dataclass
class LossWeights:
    """lambda_E (1/eV^2), lambda_f, lambda_c (Å^2/eV^2), lambda_s (1/GPa^2), lambda_a
    (1/bohr^6; 0: the polarizability term is off and never computed)."""

    energy: float = 1.0
    forces: float = 1.0
    pair_forces: float = 1.0
    stress: float = 0.1
    polarizability: float = 0.0

    def terms(self) -> tuple[str, ...]:
        """The loss terms these weights use: :data:`TERMS`, and ``polarizability`` when its
        weight is not zero."""
        return (*TERMS, "polarizability") if self.polarizability > 0 else TERMS

    def to_dict(self) -> dict:
        """The weights as a plain dict (the config's ``loss`` section)."""
        return asdict(self)


def predict(model: torch.nn.Module, batch: Batch,
            reference: HydrideReference | ConstantReference, stress: bool | None = None,
            create_graph: bool | None = None, compiled: bool = False,
            parameters_only: bool = True) -> dict[str, torch.Tensor]:
    """Model outputs for ``batch``: ``energy`` (B,) relative to the (live) reference,
    ``forces`` (N_graph, 3), ``stress`` (B, 3, 3) when requested. With a graph (training)
    they are differentiable in the parameters only (``EMLP.forward``'s ``parameters_only``;
    ``compiled``: through ``torch.compile`` where the family allows); ``parameters_only=False``:
    in the positions too (the double backward, as before 2026-12-02)."""
    want_stress = bool(batch.has_stress.any()) if stress is None else stress
    out = model(batch.graph, forces=True, stress=want_stress, create_graph=create_graph,
                parameters_only=parameters_only, compiled=compiled)
    pred = {"energy": reference.correct(out["energy"], batch.coefficients),
            "energy_raw": out["energy"][: batch.n_structures], "forces": out["forces"]}
    if want_stress:
        pred["stress"] = out["stress"][: batch.n_structures]
    return pred


def predict_polarizability(model: EMLP, batch: Batch,
                           create_graph: bool = True) -> dict[str, torch.Tensor]:
    """The polarizability term's prediction: ``polarizability`` (L, 3, 3) (e·Å²/V, float64)
    of the L configurations of ``batch`` that carry a label, from the model's pair Hessian at
    their (DFT) pairs (:func:`emlpack.properties.response.clamped_polarizabilities`;
    ``create_graph``: differentiable in the parameters), and ``polarizability_used`` (B,)
    bool, which they are. A labelled configuration whose pair Hessian there is not positive
    definite has no such response: it is left out with a warning. ``model`` is the plain
    :class:`~emlpack.nn.potential.EMLP` (not a DDP wrapper).

    Why at the DFT centres: the label is DFT's response about its own centres, and there the
    model's pairs should feel DFT's restoring forces (the pair-force labels already ask for
    zero force there); the model's own minimum would need a pair relaxation per labelled
    configuration and step, and differentiating it (implicitly) through the relaxation."""
    used = batch.has_polarizability.clone()
    g = batch.graph
    if not bool(used.any()):
        return {"polarizability": torch.zeros(0, 3, 3, dtype=torch.float64,
                                              device=g.positions.device),
                "polarizability_used": used}
    keep = torch.zeros(g.n_structures, dtype=torch.bool, device=used.device)
    keep[: batch.n_structures] = used
    result = clamped_polarizabilities(model, g.subgraph(keep), create_graph=create_graph)
    labelled = torch.nonzero(used).squeeze(1).tolist()
    ok = []
    for k, problem in zip(labelled, result.problems, strict=True):
        if problem:
            log.warning("configuration %d: polarizability label left out of the loss: %s",
                        batch.indices[k], problem)
            used[k] = False
        ok.append(not problem)
    ok_mask = torch.tensor(ok, dtype=torch.bool, device=result.alpha.device)
    return {"polarizability": result.alpha[ok_mask], "polarizability_used": used}


def loss_terms(pred: dict, batch: Batch) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """``term -> (sum of squared errors, count)`` for the four terms of the cost function, and
    the polarizability term (bohr³) when ``pred`` has :func:`predict_polarizability`'s
    entries."""
    dt = pred["forces"].dtype
    e = ((pred["energy"] - batch.energy) / batch.n_cores.to(dt)) ** 2
    terms = {"energy": (e.sum(), torch.tensor(float(len(e)), dtype=dt))}
    for name, mask in (("forces", batch.core_mask), ("pair_forces", batch.pair_mask)):
        diff = pred["forces"][mask] - batch.forces[mask]
        terms[name] = ((diff * diff).sum(), torch.tensor(float(diff.numel()), dtype=dt))
    if "stress" in pred and bool(batch.has_stress.any()):
        m = batch.has_stress
        diff = (pred["stress"][m] - batch.stress[m]) * EV_PER_A3_IN_GPA
        terms["stress"] = ((diff * diff).sum(), torch.tensor(float(diff.numel()), dtype=dt))
    else:
        zero = pred["forces"].sum() * 0.0
        terms["stress"] = (zero, torch.tensor(0.0, dtype=dt))
    if "polarizability" in pred:
        used = pred["polarizability_used"]
        diff = (pred["polarizability"] - batch.polarizability[used].to(torch.float64))
        diff = diff * _ALPHA_IN_BOHR3
        zero = pred["forces"].sum() * 0.0
        terms["polarizability"] = (zero + (diff * diff).sum().to(dt),
                                   torch.tensor(float(diff.numel()), dtype=dt))
    return terms


def combine(terms: dict, weights: LossWeights, counts: dict | None = None) -> torch.Tensor:
    """``sum_t lambda_t * sum_t / count_t`` (``counts`` overrides, e.g. global counts)."""
    total = 0.0
    for name, (s, n) in terms.items():
        n = counts[name] if counts is not None else n
        if float(n) > 0:
            total = total + getattr(weights, name) * s / n
    return total


class Metrics:
    """Accumulates absolute and squared errors: MAE and RMSE per quantity.

    Energy per core atom (eV/atom), core forces and pair forces per component (eV/Å), stress
    per component (GPa)."""

    def __init__(self) -> None:
        self.sums = {t: [0.0, 0.0, 0.0] for t in TERMS}  # abs, sq, count
        self.field = [0.0, 0.0]  # pairs: sum r . qE, sum |qE|^2 (field_response_slope)

    def update(self, pred: dict, batch: Batch) -> None:
        """Add the errors of ``pred`` against the labels of ``batch`` (and the pairs' field-response
        sums)."""
        with torch.no_grad():
            e = (pred["energy"] - batch.energy) / batch.n_cores.to(batch.energy.dtype)
            self._add("energy", e)
            self._add("forces", pred["forces"][batch.core_mask] - batch.forces[batch.core_mask])
            pairs = batch.pair_mask
            residual = pred["forces"][pairs] - batch.forces[pairs]
            self._add("pair_forces", residual)
            g = batch.graph
            qe = (g.charges[:, None] * g.field[g.batch])[pairs].to(residual.dtype)
            self.field[0] += float((residual * qe).sum())
            self.field[1] += float((qe * qe).sum())
            if "stress" in pred and bool(batch.has_stress.any()):
                m = batch.has_stress
                self._add("stress", (pred["stress"][m] - batch.stress[m]) * EV_PER_A3_IN_GPA)

    def _add(self, name: str, diff: torch.Tensor) -> None:
        d = diff.detach().double().reshape(-1)
        s = self.sums[name]
        s[0] += float(d.abs().sum())
        s[1] += float((d * d).sum())
        s[2] += float(d.numel())

    def tensor(self) -> torch.Tensor:
        """The accumulated sums as one float64 tensor (for an all-reduce; :meth:`load_tensor`)."""
        return torch.tensor([v for t in TERMS for v in self.sums[t]] + self.field,
                            dtype=torch.float64)

    def load_tensor(self, t: torch.Tensor) -> None:
        """Replace the sums by those of ``t``, laid out as :meth:`tensor`'s."""
        vals = t.tolist()
        for k, name in enumerate(TERMS):
            self.sums[name] = vals[3 * k : 3 * k + 3]
        self.field = vals[3 * len(TERMS):]

    def result(self) -> dict[str, float]:
        """``NAME_mae`` and ``NAME_rmse`` of each quantity seen (units: see the class docstring) and
        ``pair_field_slope`` (:func:`field_response_slope`)."""
        out = {}
        for name, (a, s, n) in self.sums.items():
            if n > 0:
                out[f"{name}_mae"] = a / n
                out[f"{name}_rmse"] = (s / n) ** 0.5
        if self.field[1] > 0:
            out["pair_field_slope"] = self.field[0] / self.field[1]
        return out

    def loss(self, weights: LossWeights) -> float:
        """The cost function evaluated with global means over everything accumulated."""
        return sum(getattr(weights, name) * s / n
                   for name, (_, s, n) in self.sums.items() if n > 0)
