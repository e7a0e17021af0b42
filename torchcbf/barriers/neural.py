"""Barriers given by a neural network (or any module)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchcbf._checks import check_number
from torchcbf.barriers.base import Barrier
from torchcbf.barriers.lie import FollowsTime, LieFunction, time_tensor


class NeuralBarrier(Barrier):
    """``h(x) = scale * net(x) + offset(x, t)``.

    Args:
        net: any module ``x [..., n] -> [..., 1]`` (squeezed to ``[...]``), ``[...]``, or
            ``[..., k]`` with ``k > 1`` (``k`` barriers at once).
        offset: an optional known barrier added to the network's output (for instance a
            :class:`~torchcbf.barriers.Ball` around the obstacle, so the network only learns a
            correction); its outputs must match the network's.
        scale: a constant multiplying the network's output: a number, or a tensor (an
            ``nn.Parameter`` trains; a tensor that requires grad keeps its gradient).
        time_input: feed ``cat(x, t)`` (``[..., n + 1]``) to the network: a time-varying
            barrier.
    """

    time_varying = FollowsTime(
        lambda self: self.time_input or (self.offset is not None and self.offset.time_varying)
    )

    def __init__(
        self,
        net: nn.Module,
        offset: LieFunction | None = None,
        *,
        scale: float | Tensor = 1.0,
        time_input: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(net, nn.Module):
            raise TypeError(f"net must be an nn.Module, got {type(net).__name__}")
        if offset is not None and not isinstance(offset, LieFunction):
            raise TypeError(f"offset must be a Barrier, got {type(offset).__name__}")
        self.net = net
        self.offset = offset
        self.scale: float | Tensor
        if isinstance(scale, Tensor):
            self.register_constant("scale", scale)
            if self.scale.dim() != 0:
                raise ValueError(f"scale must be a scalar, got shape {tuple(self.scale.shape)}")
        else:
            self.scale = check_number("scale", scale)
        self.time_input = bool(time_input)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """``x [..., n] -> h [...]`` (or ``[..., k]``)."""
        inp = x
        if self.time_input:
            inp = torch.cat([x, time_tensor(t, x).unsqueeze(-1)], -1)
        h = self.net(inp)
        batch = x.shape[:-1]
        if h.shape == (*batch, 1):
            h = h.squeeze(-1)
        if not (h.shape == batch or (h.dim() == x.dim() and h.shape[:-1] == batch)):
            raise ValueError(
                f"net must map a state {tuple(x.shape)} to [..., 1], [...] or [..., k], "
                f"got {tuple(h.shape)}"
            )
        h = (self.scale if isinstance(self.scale, float) else self.scale.to(h)) * h
        if self.offset is not None:
            off = self.offset(x, t)
            if off.shape != h.shape:
                raise ValueError(
                    f"offset output {tuple(off.shape)} does not match the network's "
                    f"{tuple(h.shape)}"
                )
            h = h + off
        return h
