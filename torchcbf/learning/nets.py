"""Small smooth networks for learned barriers (twice differentiable, inputs normalised)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor

_ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "softplus": nn.Softplus,
    "silu": nn.SiLU,
    "gelu": nn.GELU,
}


class MLP(nn.Module):
    """A multilayer perceptron ``[..., in_dim] -> [..., out_dim]`` with smooth activations.

    The input is first mapped affinely from the box ``[low, high]`` (buffers) to
    ``[-1, 1]``, so a barrier over a workspace of any size trains with default
    initialisations. Smooth activations (``tanh`` by default) keep the Lie derivatives
    (and the Hessian terms of stochastic filters) continuous.

    Args:
        in_dim: input size (the state dimension, ``+1`` for a time input).
        hidden: widths of the hidden layers.
        out_dim: output size (1 for one barrier; ``NeuralBarrier`` squeezes it).
        activation: ``"tanh"``, ``"softplus"``, ``"silu"`` or ``"gelu"``.
        low, high: the input box ``[in_dim]`` (default ``[-1, 1]``: no scaling).
    """

    def __init__(
        self,
        in_dim: int,
        hidden: Sequence[int] = (64, 64),
        out_dim: int = 1,
        *,
        activation: str = "tanh",
        low: Tensor | Sequence[float] | None = None,
        high: Tensor | Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        for name, v in (("in_dim", in_dim), ("out_dim", out_dim), *(("hidden", w) for w in hidden)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must hold positive ints, got {v!r}")
        if activation not in _ACTIVATIONS:
            raise ValueError(
                f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}"
            )
        lo = as_tensor("low", -1.0 if low is None else low, dtype=torch.float32)
        hi = as_tensor("high", 1.0 if high is None else high, dtype=torch.float32)
        lo, hi = lo.expand(in_dim).clone(), hi.expand(in_dim).clone()
        if not bool((hi > lo).all()):
            raise ValueError(f"high must exceed low, got low={lo.tolist()}, high={hi.tolist()}")
        self.register_buffer("center", (lo + hi) / 2)
        self.register_buffer("half_width", (hi - lo) / 2)
        layers: list[nn.Module] = []
        width = in_dim
        for w in hidden:
            layers += [nn.Linear(width, w), _ACTIVATIONS[activation]()]
            width = w
        layers.append(nn.Linear(width, out_dim))
        self.layers = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        """``x [..., in_dim] -> [..., out_dim]``."""
        return self.layers((x - self.center.to(x)) / self.half_width.to(x))
