"""``FilteredPolicy``: a policy whose last layer is a safety filter (the batched,
differentiable CBF-QP), so a loss on its actions trains the network through the QP.

``u = filter(x, net(observation))``: where no barrier condition is active the filter is the
identity; where one is, the action is the QP's projection and the gradient of a loss on
``u`` reaches the network through the QP's implicit derivative (the component pushing into
the constraint is cut). The filter runs on its general (autograd) path when gradients are
needed and on its real-time path otherwise (:class:`~torchcbf.filters.SafetyFilter`).
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor, nn

__all__ = ["FilteredPolicy"]


class FilteredPolicy(nn.Module):
    """A network followed by a safety filter.

    Args:
        net: ``observation [..., d] -> nominal action [..., m]``.
        safety_filter: a :class:`~torchcbf.filters.SafetyFilter` on the plant (its
            ``dynamics`` has ``state_dim = n``, ``control_dim = m``).
        state_fn: ``observation [..., d] -> state [..., n]`` (a tensor function, e.g. a
            torchcbf environment's ``state_from_observation``); default: the observation is
            the state.

    ``forward(observation)`` returns ``(u [..., m], u_nominal [..., m], status [...])``:
    the filtered action (differentiable in the network's parameters and the observation),
    the network's action and the filter's :class:`~torchcbf.filters.FilterStatus` codes.
    Wrapped in a ``tensordict.nn.TensorDictModule`` (``out_keys=["loc", "loc_nominal",
    "policy_status"]``: the key :mod:`~torchcbf.envs.safe_ppo` reads) it is the mean of a
    TorchRL ``ProbabilisticActor``.
    """

    def __init__(
        self,
        net: nn.Module,
        safety_filter: nn.Module,
        *,
        state_fn: Callable[[Tensor], Tensor] | None = None,
    ) -> None:
        super().__init__()
        if not callable(net):
            raise TypeError(f"net must be a module or a callable, got {type(net).__name__}")
        if not isinstance(safety_filter, nn.Module):
            raise TypeError(
                f"safety_filter must be a SafetyFilter module, got {type(safety_filter).__name__}"
            )
        if state_fn is not None and not callable(state_fn):
            raise TypeError(f"state_fn must be callable, got {type(state_fn).__name__}")
        self.net = net
        self.safety_filter = safety_filter
        self.state_fn = state_fn

    def forward(self, observation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Filtered action, nominal action and filter status (see the class docstring)."""
        x = observation if self.state_fn is None else self.state_fn(observation)
        n = self.safety_filter.dynamics.state_dim
        if x.shape[-1] != n:
            raise ValueError(
                f"the state has {x.shape[-1]} entries, the plant's {n}: "
                "pass state_fn=<observation -> state>"
            )
        u_nom = self.net(observation)
        out = self.safety_filter(x, u_nom)
        return out.u, u_nom, out.status
