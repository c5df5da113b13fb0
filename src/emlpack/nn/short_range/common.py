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

__all__ = ["LN2", "CompiledOnce", "cosine_cutoff", "edge_lengths", "edge_linear",
           "shifted_softplus", "softplus_slopes"]

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


# ---------------------------------------------------------------------- oneDNN products
# The edge-sized products of the training steps ((E, K) x (K, K), E ~ 5,700) through oneDNN's
# inner product rather than aten::mm: torch's CPU build calls MKL for float32 mm, which on the
# project's AMD cores (Zen, AVX-512) runs at ~55 GFLOP/s against oneDNN's ~140 (measured,
# docs/performance.md, issue 49). ``torch.ops.mkldnn._linear_pointwise`` is inductor's own
# op for frozen weights (its lowering wants a constant weight), so it is wrapped here in a
# custom op that inductor calls as it is, with its backward written out: the input gradient
# is another inner product; the weight gradient ``g^T x`` stays with MKL, which reads the
# transposed operand in place (oneDNN needs both operands transposed into contiguous copies:
# eagerly 1.7 ms each for (11,400 x 64), fused by inductor no faster overall than MKL;
# measured, docs/performance.md).


def _onednn_ok() -> bool:
    try:
        return bool(torch.backends.mkldnn.is_available())
    except Exception:  # noqa: BLE001
        return False


_ONEDNN = _onednn_ok()


def _onednn_product(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return torch.ops.mkldnn._linear_pointwise(x.contiguous(), w.contiguous(), None, "none",
                                              [], "")


def _make_op(name: str):  # noqa: ANN202
    op = torch.library.custom_op(f"emlpack::{name}", _onednn_product, mutates_args=())

    @op.register_fake
    def _(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        return x.new_empty(x.shape[0], w.shape[0])

    def setup(ctx, inputs, output) -> None:  # noqa: ANN001
        x, w = inputs
        ctx.save_for_backward(x if ctx.needs_input_grad[1] else None,
                              w if ctx.needs_input_grad[0] else None)

    def backward(ctx, g: torch.Tensor):  # noqa: ANN001, ANN202
        x, w = ctx.saved_tensors
        gx = op(g, w.t().contiguous()) if ctx.needs_input_grad[0] else None
        gw = None
        if ctx.needs_input_grad[1]:
            gw = g.t() @ x  # MKL takes the transposed operand as it is
        return gx, gw

    op.register_autograd(backward, setup_context=setup)
    return op


_onednn_linear = _make_op("onednn_linear")


def edge_linear(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``x w^T`` (``nn.functional.linear`` without bias), by oneDNN for float32 on CPU (see
    above; the same product to float32 rounding), else by ``linear``."""
    if _ONEDNN and x.dtype == torch.float32 and x.device.type == "cpu" and x.dim() == 2:
        return _onednn_linear(x, w)
    return nn.functional.linear(x, w)
