"""Batched LU factorisation that stays correct on the CPU with several threads.

Torch's batched ``lu_factor`` on the CPU (MKL builds) returns pivots out of range for
matrices of order above about 150 when torch runs on more than one thread, printing
"Parameter 6 was incorrect on entry to DLASWP" (the batched ``getrf``; one matrix at a time
is exact). :func:`lu_factor_ex` factors such a batch one matrix at a time, where a
factorisation costs far more than the loop around it.
"""

from __future__ import annotations

import torch
from torch import Tensor

#: order from which a CPU batch is factored one matrix at a time (above the largest order
#: seen to factor correctly in one batched call, with a margin)
ONE_AT_A_TIME_FROM = 128


def lu_factor_ex(K: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``torch.linalg.lu_factor_ex(K)`` for ``K [..., N, N]``: ``(LU, pivots, info)``."""
    N = K.shape[-1]
    batch = K.shape[:-2].numel()
    loop = (
        K.device.type == "cpu"
        and N >= ONE_AT_A_TIME_FROM
        and batch > 1
        and torch.get_num_threads() > 1
    )
    if not loop:
        return torch.linalg.lu_factor_ex(K)
    parts = [torch.linalg.lu_factor_ex(k) for k in K.reshape(batch, N, N)]
    LU, pivots, info = (torch.stack(t) for t in zip(*parts, strict=True))
    shape = K.shape[:-2]
    return LU.reshape(K.shape), pivots.reshape(*shape, N), info.reshape(shape)
