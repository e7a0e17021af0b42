"""Small smooth networks for learned barriers (twice differentiable, inputs normalised)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchcbf._checks import as_tensor, check_finite
from torchcbf._constants import ExactConstants, remember

_ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "softplus": nn.Softplus,
    "silu": nn.SiLU,
    "gelu": nn.GELU,
}


class MLP(ExactConstants, nn.Module):
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
        if isinstance(hidden, int) or not isinstance(hidden, Sequence):
            raise TypeError(f"hidden must be a sequence of layer widths, got {hidden!r}")
        for name, v in (("in_dim", in_dim), ("out_dim", out_dim), *(("hidden", w) for w in hidden)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must hold positive ints, got {v!r}")
        if activation not in _ACTIVATIONS:
            raise ValueError(
                f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}"
            )
        for name, v in (("low", low), ("high", high)):
            if isinstance(v, Tensor) and v.requires_grad:
                raise TypeError(
                    f"{name} is a fixed input normalisation and takes no gradient: pass "
                    f"{name}.detach()"
                )
        # the box is a constant: Python numbers are kept exact (float64) for .double()
        lo = check_finite(
            "low", as_tensor("low", -1.0 if low is None else low, dtype=torch.float64)
        )
        hi = check_finite(
            "high", as_tensor("high", 1.0 if high is None else high, dtype=torch.float64)
        )
        for name, v in (("low", lo), ("high", hi)):
            if v.dim() > 1 or (v.dim() == 1 and v.shape[0] != in_dim):
                raise ValueError(
                    f"{name} must be a number or have in_dim = {in_dim} entries, got shape "
                    f"{tuple(v.shape)}"
                )
        lo, hi = lo.expand(in_dim).detach().clone(), hi.expand(in_dim).detach().clone()
        if not bool((hi > lo).all()):
            raise ValueError(f"high must exceed low, got low={lo.tolist()}, high={hi.tolist()}")
        remember(self, "center", (lo + hi) / 2)
        remember(self, "half_width", (hi - lo) / 2)
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
