"""Segment sums over an index (the batched reductions of the model).

``scatter_add_`` is used rather than ``index_add_``: on CPU, torch's parallel ``index_add_``
takes ~40 ms for a few hundred rows when the 2 cores are busy (measured with torch 2.13),
while ``scatter_add_`` takes ~40 µs; both give the same sums and gradients.
"""

from __future__ import annotations

import torch


def segment_sum(values: torch.Tensor, index: torch.Tensor, n: int) -> torch.Tensor:
    """``out[k] = sum of values[i] with index[i] == k`` along dim 0, ``out`` of length ``n``."""
    out = values.new_zeros((n, *values.shape[1:]))
    if values.dim() == 1:
        return out.scatter_add(0, index, values)
    return out.scatter_add(0, index.view(-1, *([1] * (values.dim() - 1))).expand_as(values), values)


def pair_blocks_to_matrix(
    blocks: torch.Tensor, i: torch.Tensor, j: torch.Tensor, n: int
) -> torch.Tensor:
    """(3n, 3n) Hessian of ``sum_e f_e(x_j - x_i)`` from the (E, 3, 3) Hessians ``blocks`` of
    every term in its pair vector: ``+B`` on the (i, i) and (j, j) blocks, ``-B`` on (i, j)
    and (j, i) (``B`` symmetric; terms with ``i == j`` cancel)."""
    index = torch.cat([i * (n + 1), j * (n + 1), i * n + j, j * n + i])
    out = segment_sum(torch.cat([blocks, blocks, -blocks, -blocks]), index, n * n)
    return out.reshape(n, n, 3, 3).permute(0, 2, 1, 3).reshape(3 * n, 3 * n)


def convolve(
    a: torch.Tensor,
    w: torch.Tensor,
    i: torch.Tensor,
    j: torch.Tensor,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """``conv_i = sum_j a_j * w_ij`` over the half list, each pair scattered both ways (added
    to ``out`` when given, without changing it).

    ``index_select`` + ``scatter_add`` rather than ``a[j]``, ``torch.cat`` and ``index_add_``:
    the backward of advanced indexing is an accumulating ``index_put_`` (it sorts), the cat
    copies both message halves, and the parallel ``index_add_`` stalls when the 2 cores are
    busy (see above).
    """
    k = a.shape[1]
    out = torch.zeros_like(a) if out is None else out
    out = out.scatter_add(0, i[:, None].expand(-1, k), a.index_select(0, j) * w)
    return out.scatter_add(0, j[:, None].expand(-1, k), a.index_select(0, i) * w)
