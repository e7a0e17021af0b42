"""Counter-based random numbers: one independent stream per scenario, no generator state.

``counter_normal(seeds, counter, shape)`` is a pure function of ``(seed, counter, element)``,
so a batch of scenarios draws exactly what each scenario would draw alone, on any device,
without a Python loop over scenarios and without touching any global random state.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

_MASK = 0xFFFFFFFF


def _mix32(h: Tensor) -> Tensor:
    """murmur3's 32-bit finaliser on int64 tensors holding values in [0, 2^32)."""
    h = h ^ (h >> 16)
    h = (h * 0x85EBCA6B) & _MASK
    h = h ^ (h >> 13)
    h = (h * 0xC2B2AE35) & _MASK
    return h ^ (h >> 16)


def _uniform(seeds: Tensor, counter: int, stream: int, numel: int) -> Tensor:
    """Uniforms in (0, 1), shape ``[B, numel]``, from 32-bit hashes of (seed, counter, index)."""
    idx = torch.arange(numel, device=seeds.device, dtype=torch.int64)
    key = _mix32((seeds.to(torch.int64) & _MASK) ^ ((counter * 0x9E3779B9 + stream) & _MASK))
    h = _mix32((key.unsqueeze(-1) + _mix32(idx * 2 + 1)) & _MASK)
    h2 = _mix32((h ^ 0x5BD1E995) & _MASK)
    bits = (h << 21) | (h2 >> 11)  # 53 random bits
    return (bits.to(torch.float64) + 0.5) / float(1 << 53)


def counter_normal(
    seeds: Tensor, counter: int, shape: tuple[int, ...], *, dtype: torch.dtype = torch.float32
) -> Tensor:
    """Standard normal samples ``[B, *shape]`` for integer ``seeds [B]`` at step ``counter``."""
    numel = math.prod(shape)
    u1 = _uniform(seeds, counter, 0, numel)
    u2 = _uniform(seeds, counter, 1, numel)
    z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u2)
    return z.to(dtype).reshape(seeds.shape[0], *shape)
