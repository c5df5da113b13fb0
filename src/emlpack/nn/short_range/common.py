"""Formulas shared by the short-range families: the safe edge length, the eMLP's cosine cutoff
and the shifted softplus (with its slopes as torch's autograd takes them); and the compiled
training step with its fallback (:class:`CompiledOnce`)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import torch
from torch import nn

from emlpack import geometry

__all__ = ["LN2", "CompiledOnce", "cosine_cutoff", "edge_lengths", "shifted_softplus",
           "softplus_slopes"]

LN2 = math.log(2.0)

#: added to ``|d|^2`` before the square root: a pair sitting on a core (zero-length edge)
#: keeps a finite length and a finite gradient (the reference's 1e-20 Å^2)
LENGTH_EPS = 1e-20


def edge_lengths(vectors: torch.Tensor) -> torch.Tensor:
    """Lengths ``sqrt(|d|^2 + 1e-20)`` (E,) (Å) of the edge vectors ``vectors`` (E, 3) (Å):
    finite, with a finite gradient (zero), at ``d = 0``."""
    return torch.sqrt((vectors * vectors).sum(-1) + LENGTH_EPS)


def cosine_cutoff(r: torch.Tensor, cutoff: float, transition: float) -> torch.Tensor:
    """1 below ``cutoff - transition``, cosine switch to 0 at ``cutoff`` (Å): the formula of
    :func:`emlpack.geometry.cosine_cutoff` on tensors."""
    return geometry.cosine_cutoff(r, cutoff, transition, xp=torch)


def shifted_softplus(x: torch.Tensor) -> torch.Tensor:
    """ssp(x) = ln(1 + e^x) - ln 2."""
    return nn.functional.softplus(x) - LN2


def softplus_slopes(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First and second derivatives of ``softplus(x)`` as torch's autograd takes them
    (threshold 20: slope 1 above, curvature 0 from 20 on)."""
    sig = torch.sigmoid(x)
    return torch.where(x > 20.0, 1.0, sig), torch.where(x >= 20.0, 0.0, sig * (1.0 - sig))


class CompiledOnce:
    """``fn`` through ``torch.compile`` (dynamic shapes: one compilation serves every batch
    size), compiled at the first compiled call of the process. A compiler error is logged once
    (``what`` names the step) and ``fn`` runs plainly from then on; :attr:`failure` says why."""

    def __init__(self, fn: Callable, what: str, logger: logging.Logger) -> None:
        self.fn, self.what, self.log = fn, what, logger
        self.compiled: Callable | None = None
        #: why the compiled call failed in this process (None: it did not, or was not tried)
        self.failure: str | None = None

    def __call__(self, *args, compiled: bool):
        """``fn(*args)``, compiled when ``compiled`` and compiling has not failed."""
        if compiled and self.failure is None:
            if self.compiled is None:
                self.compiled = torch.compile(self.fn, dynamic=True)
            try:
                return self.compiled(*args)
            except Exception as err:  # noqa: BLE001 (inductor raises many kinds; fall back)
                self.failure = repr(err)
                self.log.warning("torch.compile of the %s training step failed (%.200r);"
                                 " training goes on uncompiled", self.what, err)
        return self.fn(*args)
