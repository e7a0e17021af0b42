"""Training data for learned barriers: states sampled in a box, labelled by an occupancy function.

An *occupancy function* ``occupied(x [..., n]) -> bool [...]`` is True where a state is unsafe
(inside an obstacle). It is all a learner needs to know about the obstacles: no closed form,
no distance function. :func:`occupancy_from_barrier` makes one from any barrier (for tests
and examples whose ground truth is known), :func:`dilate` grows one by a safety margin.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._checks import (
    as_tensor,
    check_finite,
    check_generator,
    check_index,
    check_number,
    check_positive,
    check_positive_int,
    check_seed,
    check_tensor,
)

#: the most states drawn at once, whatever ``num``
_MAX_CHUNK = 1 << 20

Occupancy = Callable[[Tensor], Tensor]


class LabelledStates(NamedTuple):
    """States ``x [N, n]`` and their labels ``safe [N]`` (bool, True outside every obstacle)."""

    x: Tensor
    safe: Tensor


def make_generator(
    generator: torch.Generator | None = None,
    seed: int | None = None,
    device: torch.device | str = "cpu",
) -> torch.Generator:
    """``generator`` if given, else a new generator on ``device`` seeded with ``seed`` (0)."""
    if generator is not None:
        if not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
        return generator
    gen = torch.Generator(device=device)
    gen.manual_seed(0 if seed is None else check_seed(seed))
    return gen


def _box(
    low: Tensor | Sequence[float],
    high: Tensor | Sequence[float],
    dtype: torch.dtype | None,
    device: torch.device | str | None,
) -> tuple[Tensor, Tensor]:
    if dtype is None and isinstance(low, Tensor) and low.is_floating_point():
        dtype = low.dtype
    if device is None and isinstance(low, Tensor):
        device = low.device
    lo = as_tensor("low", low, dtype=dtype, device=device)
    hi = as_tensor("high", high, dtype=lo.dtype, device=lo.device)
    check_finite("low", lo)
    check_finite("high", hi)
    if lo.dim() != 1 or hi.shape != lo.shape:
        raise ValueError(
            f"low and high must be vectors [n] of the same shape, got {tuple(lo.shape)} and "
            f"{tuple(hi.shape)}"
        )
    if not bool((hi > lo).all()):
        raise ValueError(
            f"high must exceed low everywhere, got low={lo.tolist()}, high={hi.tolist()}"
        )
    return lo, hi


def uniform_box(
    low: Tensor | Sequence[float],
    high: Tensor | Sequence[float],
    num: int,
    *,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """``num`` states uniform in the box ``[low, high]`` (``[n]`` each): ``[num, n]``.

    Device and dtype: those of ``low`` when it is a tensor, unless given. Randomness from
    ``generator`` (on that device, else ``ValueError``) or a new one seeded with ``seed``
    (default 0).
    """
    lo, hi = _box(low, high, dtype, device)
    num = check_positive_int("num", num)
    gen = make_generator(generator, seed, lo.device)
    check_generator(gen, "low", lo)
    r = torch.rand(num, lo.shape[0], generator=gen, device=lo.device, dtype=lo.dtype)
    return lo + (hi - lo) * r


def label_states(x: Tensor, occupied: Occupancy) -> Tensor:
    """Labels ``safe [...]`` (bool) of states ``x [..., n]``: ``~occupied(x)``."""
    check_tensor("x", x)
    occ = occupied(x)
    if not isinstance(occ, Tensor) or occ.shape != x.shape[:-1]:
        raise ValueError(
            f"occupied must map x {tuple(x.shape)} to a bool tensor {tuple(x.shape[:-1])}, got "
            f"{tuple(occ.shape) if isinstance(occ, Tensor) else type(occ).__name__}"
        )
    return ~occ.to(torch.bool)


def occupancy_from_barrier(barrier: Callable[[Tensor], Tensor]) -> Occupancy:
    """Occupancy of a barrier (or any ``x -> h [...]``/``[..., k]``): occupied where some
    output is negative or NaN. Evaluated without gradients."""

    def occupied(x: Tensor) -> Tensor:
        with torch.no_grad():
            h = barrier(x)
        if h.shape != x.shape[:-1]:
            h = h.amin(-1)
        return ~(h >= 0)  # NaN (the barrier undefined there) counts as occupied

    return occupied


def _directions(dim: int, probes: int) -> Tensor:
    """Unit probe directions ``[P, dim]`` (float64, CPU): a circle in 2D, else the axes and
    fixed pseudo-random directions."""
    if dim == 1:
        return torch.tensor([[1.0], [-1.0]], dtype=torch.float64)
    if dim == 2:
        ang = torch.arange(probes, dtype=torch.float64) * (2 * math.pi / probes)
        return torch.stack([ang.cos(), ang.sin()], -1)
    eye = torch.eye(dim, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    rnd = torch.randn(probes, dim, generator=gen, dtype=torch.float64)
    return torch.cat([eye, -eye, rnd / rnd.norm(dim=-1, keepdim=True)])


def dilate(
    occupied: Occupancy,
    radius: float,
    *,
    index: Sequence[int] = (0, 1),
    probes: int = 32,
    rings: int = 2,
) -> Occupancy:
    """Occupancy grown by ``radius`` in the state components ``index`` (a safety margin).

    A state is occupied if it, or a probe point at distance ``radius * j / rings``
    (``j = 1..rings``) along one of ``probes`` directions, is occupied. Approximate: an
    obstacle thinner than the probe spacing (``2 pi radius / probes`` in 2D) can slip
    between probes, and the directions cover a sphere more thinly in more dimensions (a unit
    ball in 3D grown by ``radius`` 0.5: in the worst direction by 0.31 with 32 probes, 0.39
    with 64, 0.42 with 128, against 0.496 in 2D with 32): raise ``probes`` with the
    dimension.
    """
    radius = check_positive("radius", radius)
    index = check_index("index", index, None)
    probes = check_positive_int("probes", probes)
    rings = check_positive_int("rings", rings)
    dirs = _directions(len(index), probes)
    radii = torch.arange(1, rings + 1, dtype=torch.float64) * (radius / rings)
    offsets = (radii[:, None, None] * dirs[None]).reshape(-1, len(index))  # [R*P, d]

    def grown(x: Tensor) -> Tensor:
        if x.shape[-1] <= max(index):
            raise ValueError(f"index={index} is outside a state of shape {tuple(x.shape)}")
        occ = occupied(x).to(torch.bool)
        shift = x.new_zeros(offsets.shape[0], x.shape[-1])
        shift[:, list(index)] = offsets.to(x)
        probe = x.unsqueeze(-2) + shift  # [..., R*P, n]
        return occ | occupied(probe).to(torch.bool).any(-1)

    return grown


def sample_labelled(
    occupied: Occupancy,
    low: Tensor | Sequence[float],
    high: Tensor | Sequence[float],
    num: int,
    *,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> LabelledStates:
    """``num`` states uniform in ``[low, high]`` with their labels (see :func:`uniform_box`)."""
    x = uniform_box(low, high, num, generator=generator, seed=seed, dtype=dtype, device=device)
    return LabelledStates(x, label_states(x, occupied))


def sample_free(
    occupied: Occupancy,
    low: Tensor | Sequence[float],
    high: Tensor | Sequence[float],
    num: int,
    *,
    margin: float = 0.0,
    index: Sequence[int] = (0, 1),
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    max_rounds: int = 100,
) -> Tensor:
    """``num`` states uniform over the free part of ``[low, high]``: ``[num, n]``.

    Rejection sampling in chunks sized from the free fraction seen so far (not a hot path:
    one host sync per chunk). With ``margin > 0`` a state must be free of the occupancy
    dilated by ``margin`` in the components ``index`` (:func:`dilate`). Raises
    ``ValueError`` if ``max_rounds`` chunks do not yield enough free states.
    """
    lo, hi = _box(low, high, dtype, device)
    num = check_positive_int("num", num)
    margin = check_number("margin", margin, low=0.0)
    max_rounds = check_positive_int("max_rounds", max_rounds)
    gen = make_generator(generator, seed, lo.device)
    occ = dilate(occupied, margin, index=index) if margin > 0 else occupied
    found: list[Tensor] = []
    have = drawn = 0
    cap = min(max(64 * num, 4096), _MAX_CHUNK)  # the occupancy may be a network
    for _ in range(max_rounds):
        rate = (have + 1) / (drawn + 2)  # the free fraction so far (Laplace's estimate)
        chunk = min(max(math.ceil(1.25 * (num - have) / rate), 64), cap)
        x = uniform_box(lo, hi, chunk, generator=gen)
        x = x[label_states(x, occ)]
        found.append(x)
        have, drawn = have + x.shape[0], drawn + chunk
        if have >= num:
            return torch.cat(found)[:num]
    raise ValueError(
        f"found only {have} of {num} free states in {drawn} draws ({max_rounds} rounds): "
        f"about {have / drawn:.2g} of the box is free; raise max_rounds or narrow the box"
    )
