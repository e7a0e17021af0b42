"""Random draws of the environments: a pure function of (seed, episode, step) per row.

Every sub-environment of a vector env draws exactly what the same environment would draw
alone with the same seed, without a generator per row and without a Python loop over rows.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchcbf._random import keyed_normal

_MASK = 0xFFFFFFFF


def _fmix(h: Tensor) -> Tensor:
    """A 32-bit avalanche mix of int64 tensors holding values in [0, 2^32)."""
    h = h ^ (h >> 16)
    h = (h * 0x7FEB352D) & _MASK
    h = h ^ (h >> 15)
    h = (h * 0x846CA68B) & _MASK
    return h ^ (h >> 16)


def row_keys(seeds: Tensor, episodes: Tensor, steps: Tensor | int) -> Tensor:
    """One 32-bit key per row ``[B]`` (int64) from its seed, episode and step counters
    (``steps``: ``[B]`` or one int for every row, kept a Python number: no copy to the
    device)."""
    if isinstance(steps, Tensor):
        steps = steps.to(torch.int64)
    h = _fmix(seeds.to(torch.int64) & _MASK)
    h = _fmix((h ^ (episodes.to(torch.int64) * 0x9E3779B9)) & _MASK)
    return _fmix((h ^ (steps * 0x632BE5AB + 0x165667B1)) & _MASK)


def normal(
    seeds: Tensor,
    episodes: Tensor,
    steps: Tensor | int,
    dim: int,
    *,
    dtype: torch.dtype,
) -> Tensor:
    """Standard normal samples ``[B, dim]``, one independent stream per (seed, episode, step)."""
    return keyed_normal(row_keys(seeds, episodes, steps), 0, (dim,), dtype=dtype)
