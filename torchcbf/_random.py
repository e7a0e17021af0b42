"""Counter-based random numbers: one independent stream per scenario, no generator state.

``counter_normal(seeds, counter, shape)`` is a pure function of ``(seed, counter, element)``,
so a batch of scenarios draws exactly what each scenario would draw alone, on any device,
without a Python loop over scenarios and without touching any global random state.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

_MASK = 0xFFFFFFFF
#: seeds are 32-bit: ``0 <= seed < SEED_LIMIT`` (``2^32`` would repeat seed 0's stream)
SEED_LIMIT = 2**32


def seed_rows(
    seed: int | Sequence[int] | Tensor,
    rows: int,
    device: torch.device,
    *,
    name: str = "seed",
    per: str = "row",
) -> Tensor:
    """One seed per row ``[rows]`` int64: ``seed + i`` from one integer (a NumPy or
    one-value tensor integer too), or the given ``rows`` seeds. A ``ValueError`` naming
    ``name`` where one lies outside ``[0, 2^32)`` (it would share another's stream) or the
    count is wrong (``per``: the word for a row in the message), a ``TypeError`` for what
    is no integer."""
    if isinstance(seed, np.ndarray):
        if not np.issubdtype(seed.dtype, np.integer):
            raise TypeError(f"{name} must hold integers, got a {seed.dtype} array")
        seed = torch.as_tensor(seed, dtype=torch.int64)
    if isinstance(seed, Tensor) and seed.numel() == 1 and rows != 1:
        seed = int(seed)
    if isinstance(seed, numbers.Integral) and not isinstance(seed, bool):
        last = SEED_LIMIT - max(rows, 1)
        if not 0 <= int(seed) <= last:
            raise ValueError(
                f"{name} must lie in [0, {last}] for {rows} {per}s (32-bit noise streams), "
                f"got {int(seed)}"
            )
        return torch.arange(rows, device=device, dtype=torch.int64) + int(seed)
    if isinstance(seed, bool) or (
        not isinstance(seed, Tensor)
        and not (
            isinstance(seed, Sequence)
            and all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in seed)
        )
    ):
        raise TypeError(f"{name} must be an int or a sequence of ints, got {seed!r}")
    if isinstance(seed, Tensor) and (seed.dtype.is_floating_point or seed.dtype == torch.bool):
        raise TypeError(f"{name} must hold integers, got a {seed.dtype} tensor")
    seeds = torch.as_tensor(seed, dtype=torch.int64, device=device).reshape(-1)
    if seeds.shape != (rows,):
        raise ValueError(
            f"{name} must be an int or hold one seed per {per} ({rows}), got {tuple(seeds.shape)}"
        )
    if seeds.numel() and not bool(((seeds >= 0) & (seeds < SEED_LIMIT)).all()):
        raise ValueError(f"{name} must lie in [0, 2^32) (32-bit noise streams): {seeds.tolist()}")
    return seeds


def _mix32(h: Tensor) -> Tensor:
    """murmur3's 32-bit finaliser on int64 tensors holding values in [0, 2^32)."""
    h = h ^ (h >> 16)
    h = (h * 0x85EBCA6B) & _MASK
    h = h ^ (h >> 13)
    h = (h * 0xC2B2AE35) & _MASK
    return h ^ (h >> 16)


def _uniform(keys: Tensor, counter: int, stream: int, numel: int) -> Tensor:
    """Uniforms in (0, 1), shape ``[B, numel]``, from 32-bit hashes of (key, counter,
    index); ``keys [B]`` are hashes already (:func:`seed_keys`)."""
    idx = torch.arange(numel, device=keys.device, dtype=torch.int64)
    key = _mix32((keys.to(torch.int64) & _MASK) ^ ((counter * 0x9E3779B9 + stream) & _MASK))
    h = _mix32((key.unsqueeze(-1) + _mix32(idx * 2 + 1)) & _MASK)
    h2 = _mix32((h ^ 0x5BD1E995) & _MASK)
    bits = (h << 21) | (h2 >> 11)  # 53 random bits
    return (bits.to(torch.float64) + 0.5) / float(1 << 53)


def seed_keys(seeds: Tensor) -> Tensor:
    """The 32-bit key ``[B]`` of each seed. Seeds meet the counter only hashed: raw,
    ``seed ^ f(counter, stream)`` gave seeds ``s`` and ``s ^ 1`` each other's uniforms at
    every even counter, so neighbouring scenarios were dependent. (The offset: the
    finaliser maps 0 to 0.)"""
    return _mix32((seeds.to(torch.int64) ^ 0x3C6EF372) & _MASK)


def keyed_normal(
    keys: Tensor, counter: int, shape: tuple[int, ...], *, dtype: torch.dtype = torch.float32
) -> Tensor:
    """Standard normal samples ``[B, *shape]`` for hashed ``keys [B]`` at step ``counter``
    (Box-Muller over two streams of uniforms)."""
    numel = math.prod(shape)
    u1 = _uniform(keys, counter, 0, numel)
    u2 = _uniform(keys, counter, 1, numel)
    z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u2)
    return z.to(dtype).reshape(keys.shape[0], *shape)


def counter_normal(
    seeds: Tensor, counter: int, shape: tuple[int, ...], *, dtype: torch.dtype = torch.float32
) -> Tensor:
    """Standard normal samples ``[B, *shape]`` for integer ``seeds [B]`` at step ``counter``."""
    return keyed_normal(seed_keys(seeds), counter, shape, dtype=dtype)
