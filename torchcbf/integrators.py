"""One-step integrators for control-affine dynamics (zero-order hold on the control).

All methods are batched over any leading dimensions of ``x [..., n]`` and ``u [..., m]``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Literal

import torch
from torch import Tensor

from torchcbf._checks import (
    behaves_as,
    broadcast_shapes,
    broadcasts_to,
    check_generator,
    check_last_dim,
    check_positive,
    check_same,
    stale_on,
)
from torchcbf.dynamics.base import MATVEC_COLUMNS_UP_TO, ControlAffine

Method = Literal["euler", "rk4", "euler_maruyama"]
METHODS: tuple[str, ...] = ("euler", "rk4", "euler_maruyama")


def rate_form(dynamics: ControlAffine) -> str:
    """How ``dynamics``' rate is evaluated: ``"module"`` (the module call, where a subclass
    rewrote ``forward`` or ``__call__`` itself, or its calls run hooks or an instance's own
    ``forward``: :func:`~torchcbf._checks.behaves_as`), ``"plain"`` (``xdot`` is
    ``f + g u``, not rewritten, or an instance's own ``f`` or ``g`` leaves a closed form stale:
    a caller may form the sum in any layout) or ``"xdot"`` (the
    model's own ``xdot``)."""
    if not behaves_as(dynamics, ControlAffine, ("forward",)):
        return "module"
    if stale_on(dynamics, "xdot", dynamics.closed_forms):  # the instance's own f or g
        return "plain"
    return "plain" if getattr(dynamics.xdot, "__func__", None) is ControlAffine.xdot else "xdot"


def _rate(
    dynamics: ControlAffine, w: Tensor | None, form: str | None = None
) -> Callable[[Tensor, Tensor], Tensor]:
    """``(x, u) -> xdot`` of checked inputs by :func:`rate_form` (``form``, when the caller
    has it): the model's ``xdot`` directly (no module call, no input checks), with ``M w``
    added where ``w`` is given, or the module call."""
    form = rate_form(dynamics) if form is None else form
    if form == "module":
        return lambda x, u: dynamics(x, u, w)
    # "plain": f + g u, also where the class's closed-form xdot is stale on this instance
    xdot = functools.partial(ControlAffine.xdot, dynamics) if form == "plain" else dynamics.xdot
    if w is None:
        return xdot
    return lambda x, u: xdot(x, u) + dynamics.disturbance(x, w)


def _euler(
    dynamics: ControlAffine, x: Tensor, u: Tensor, dt: float, w: Tensor | None = None
) -> Tensor:
    return _euler_of(_rate(dynamics, w), x, u, dt)


def _rk4(
    dynamics: ControlAffine, x: Tensor, u: Tensor, dt: float, w: Tensor | None = None
) -> Tensor:
    return _rk4_of(_rate(dynamics, w), x, u, dt)


Rate = Callable[[Tensor, Tensor], Tensor]


def _euler_of(rate: Rate, x: Tensor, u: Tensor, dt: float) -> Tensor:
    return x + dt * rate(x, u)


def _rk4_of(rate: Rate, x: Tensor, u: Tensor, dt: float) -> Tensor:
    k1 = rate(x, u)
    k2 = rate(x + 0.5 * dt * k1, u)
    k3 = rate(x + 0.5 * dt * k2, u)
    k4 = rate(x + dt * k3, u)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def unchecked_step(
    dynamics: ControlAffine,
    method: str,
    x: Tensor,
    u: Tensor,
    dt: float,
    *,
    form: str,
    component: bool = False,
) -> Tensor:
    """``euler`` or ``rk4`` without input checks, the rate evaluated as ``form`` says
    (:func:`rate_form`, computed once by the caller: a compiled caller passes it so that
    its graphs differ where the forms do). ``x [..., n]``, ``u [..., m]``; with
    ``component``, component-major ``x [..., n, K]``, ``u [..., m, K]`` (each component's
    ``K`` samples along the last axis; the model is handed ``[..., K, n]`` views) ->
    ``[..., n, K]``: for a ``"plain"`` rate the sum ``f + g u`` is then formed over the
    components directly, so compiled code runs its loops over contiguous samples instead of
    one short state vector at a time."""
    stepper = _stepper(method)
    rate = model_rate = _rate(dynamics, None, form)
    if component:
        plain = form == "plain"

        def component_rate(xc: Tensor, uc: Tensor) -> Tensor:
            x = xc.mT
            if not plain:
                return model_rate(x, uc.mT).mT
            rows = x.shape[:-1]  # f and g may broadcast (a constant g [n, m], say)
            g = dynamics.g(x).expand(*rows, x.shape[-1], uc.shape[-2])
            f = dynamics.f(x).expand(*rows, x.shape[-1])
            if g.shape[-1] > MATVEC_COLUMNS_UP_TO:
                return (f + (g @ uc.mT.unsqueeze(-1)).squeeze(-1)).mT
            xdot = f.mT
            for j in range(g.shape[-1]):
                xdot = xdot + g[..., j].mT * uc[..., j : j + 1, :]
            return xdot

        rate = component_rate
    return stepper(rate, x, u, dt)


def _checked(dynamics: ControlAffine, x: Tensor, u: Tensor, w: Tensor | None, dt: float) -> float:
    """Check the inputs of a public integrator; return ``dt`` (a positive finite number)."""
    dt = check_positive("dt", dt)
    if not isinstance(dynamics, ControlAffine):
        raise TypeError(f"dynamics must be a ControlAffine module, got {type(dynamics).__name__}")
    dynamics.check_inputs(x, u)
    if w is not None:
        check_same("x", x, "w", w)
    return dt


def euler(
    dynamics: ControlAffine, x: Tensor, u: Tensor, dt: float, w: Tensor | None = None
) -> Tensor:
    """Explicit Euler: ``x + dt * xdot(x, u)`` for ``x [..., n]``, ``u [..., m]``."""
    dt = _checked(dynamics, x, u, w, dt)
    return _euler(dynamics, x, u, dt, w)


def rk4(
    dynamics: ControlAffine, x: Tensor, u: Tensor, dt: float, w: Tensor | None = None
) -> Tensor:
    """Classical fourth-order Runge-Kutta with ``u`` (and ``w``) held over the step, for
    ``x [..., n]``, ``u [..., m]``."""
    dt = _checked(dynamics, x, u, w, dt)
    return _rk4(dynamics, x, u, dt, w)


def _stepper(method: str) -> Callable[[Rate, Tensor, Tensor, float], Tensor]:
    """``euler`` or ``rk4`` of a rate function; ``ValueError`` for another method."""
    if method not in ("euler", "rk4"):
        raise ValueError(f"method must be 'euler' or 'rk4', got {method!r}")
    return _euler_of if method == "euler" else _rk4_of


def euler_maruyama(
    dynamics: ControlAffine,
    x: Tensor,
    u: Tensor,
    dt: float,
    w: Tensor | None = None,
    *,
    generator: torch.Generator | None = None,
    noise: Tensor | None = None,
) -> Tensor:
    """Euler-Maruyama for ``dx = (f + g u) dt + sigma dW``: ``x + dt xdot + sqrt(dt) sigma z``.

    ``z ~ N(0, I_q)`` is drawn from ``generator`` or given as ``noise [..., q]`` (batch
    dimensions broadcasting to those of ``x`` and ``u``). Without a diffusion this is
    :func:`euler`.
    """
    dt = _checked(dynamics, x, u, w, dt)
    return _euler_maruyama(dynamics, x, u, dt, w, generator, noise)


def _euler_maruyama(
    dynamics: ControlAffine,
    x: Tensor,
    u: Tensor,
    dt: float,
    w: Tensor | None,
    generator: torch.Generator | None,
    noise: Tensor | None,
) -> Tensor:
    drift = x + dt * dynamics(x, u, w)
    sigma = dynamics.sigma(x)
    if sigma is None:
        return drift
    q = sigma.shape[-1]
    if noise is None:
        if generator is None:
            raise ValueError(
                "euler_maruyama on a model with a diffusion needs generator= or noise= "
                "(torchcbf never draws from the global random state)"
            )
        check_generator(generator, "x", x)
        shape = broadcast_shapes(drift.shape[:-1], sigma.shape[:-2]) + (q,)
        noise = torch.randn(shape, generator=generator, device=x.device, dtype=x.dtype)
    else:
        check_last_dim("noise", noise, q)
        check_same("x", x, "noise", noise)
        batch = tuple(drift.shape[:-1])
        if not broadcasts_to(noise.shape[:-1], batch):
            raise ValueError(
                f"noise must have shape [..., {q}] with batch dimensions that broadcast to "
                f"the step's (x, u) {tuple(batch)}, got {tuple(noise.shape)}"
            )
    return drift + math.sqrt(dt) * (sigma @ noise.unsqueeze(-1)).squeeze(-1)


def step(
    dynamics: ControlAffine,
    x: Tensor,
    u: Tensor,
    dt: float,
    method: Method = "rk4",
    generator: torch.Generator | None = None,
    *,
    w: Tensor | None = None,
    noise: Tensor | None = None,
) -> Tensor:
    """Advance ``x [..., n]`` by ``dt`` under control ``u [..., m]`` (held constant).

    Args:
        method: ``"euler"``, ``"rk4"`` or ``"euler_maruyama"`` (needs ``generator`` or
            ``noise`` when the model has a diffusion).
        w: optional disturbance ``[..., p]`` entering as ``M w``.
        noise: optional standard-normal sample ``[..., q]`` for ``euler_maruyama``.

    Returns:
        The next state ``[..., n]`` (batch dimensions broadcast between ``x`` and ``u``).

    Raises ``TypeError`` when ``u``, ``w`` or ``noise`` has another dtype than ``x`` and
    ``ValueError`` when it is on another device (both named), as for a bad shape or ``dt``.
    """
    dt = _checked(dynamics, x, u, w, dt)
    if method == "euler":
        return _euler(dynamics, x, u, dt, w)
    if method == "rk4":
        return _rk4(dynamics, x, u, dt, w)
    if method == "euler_maruyama":
        return _euler_maruyama(dynamics, x, u, dt, w, generator, noise)
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")
