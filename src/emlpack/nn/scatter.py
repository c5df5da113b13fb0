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
