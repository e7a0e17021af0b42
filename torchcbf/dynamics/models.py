"""Standard control-affine models.

Every model takes the keyword arguments of :class:`ControlAffine`: ``sigma``, ``u_min``,
``u_max``, ``disturbance_bound`` and ``disturbance_matrix``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchcbf._checks import broadcast_shapes
from torchcbf.dynamics.base import (
    ControlAffine,
    DriftDerivatives,
    NativeModel,
    register_constant,
)


def _zeros(x: Tensor, *shape: int) -> Tensor:
    return x.new_zeros(*x.shape[:-1], *shape)


def _register_eye_g(model: ControlAffine, row: int) -> None:
    """Store a constant ``g [n, m]``: an identity block ``I_m`` in rows ``row:row+m``, zeros
    elsewhere (a buffer outside the state dict, so it follows ``.to()``)."""
    n, m = model.state_dim, model.control_dim
    g = torch.zeros(n, m, dtype=torch.float64)
    g[row : row + m] = torch.eye(m, dtype=torch.float64)
    model.register_buffer("_g", g, persistent=False)


def _constant_drift(x: Tensor, jac: Tensor | None = None) -> DriftDerivatives:
    """Derivatives of an affine drift ``f = J x``: ``jac`` (zeros if ``None``), no curvature."""
    n = x.shape[-1]
    J = x.new_zeros(n, n) if jac is None else jac.to(x)

    def hess_quad(w: Tensor, s: Tensor) -> Tensor:
        return w.new_zeros(w.shape[:-1])

    return DriftDerivatives(J.expand(*x.shape[:-1], n, n), hess_quad)


def _expand_g(g: Tensor, x: Tensor) -> Tensor:
    """The constant ``g [n, m]`` as ``[..., n, m]`` for ``x [..., n]`` (a broadcast view)."""
    return g.to(x).expand(*x.shape[:-1], *g.shape)


class SingleIntegrator(ControlAffine):
    """``xdot = u`` in ``dim`` dimensions (state = position, control = velocity)."""

    def __init__(self, dim: int = 2, **kwargs: Any) -> None:
        super().__init__(dim, dim, **kwargs)
        _register_eye_g(self, 0)

    def f(self, x: Tensor) -> Tensor:
        return torch.zeros_like(x)

    def g(self, x: Tensor) -> Tensor:
        return _expand_g(self._g, x)

    def drift_derivatives(self, x: Tensor) -> DriftDerivatives:
        return _constant_drift(x)

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        # a copy, not a view of u: a caller may write into the rate it gets
        return u.expand(broadcast_shapes(x.shape, u.shape)).clone()

    def native_model(self) -> NativeModel:
        return NativeModel("single_integrator", self.state_dim)


class DoubleIntegrator(ControlAffine):
    """``pdot = v, vdot = u`` in ``dim`` dimensions: state ``(p, v)`` of size ``2 dim``."""

    def __init__(self, dim: int = 2, **kwargs: Any) -> None:
        super().__init__(2 * dim, dim, **kwargs)
        self.dim = dim
        _register_eye_g(self, dim)

    def f(self, x: Tensor) -> Tensor:
        return torch.cat([x[..., self.dim :], torch.zeros_like(x[..., self.dim :])], dim=-1)

    def g(self, x: Tensor) -> Tensor:
        return _expand_g(self._g, x)

    def drift_derivatives(self, x: Tensor) -> DriftDerivatives:
        n, d = self.state_dim, self.dim
        jac = torch.zeros(n, n, dtype=x.dtype, device=x.device)
        jac[:d, d:] = torch.eye(d, dtype=x.dtype, device=x.device)
        return _constant_drift(x, jac)

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        v, u = torch.broadcast_tensors(x[..., self.dim :], u)
        return torch.cat([v, u], dim=-1)

    def native_model(self) -> NativeModel:
        return NativeModel("double_integrator", self.control_dim)


class Unicycle(ControlAffine):
    """Kinematic unicycle: state ``(x, y, theta)``, control ``(v, omega)``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(3, 2, **kwargs)

    def f(self, x: Tensor) -> Tensor:
        return torch.zeros_like(x)

    def drift_derivatives(self, x: Tensor) -> DriftDerivatives:
        return _constant_drift(x)

    def g(self, x: Tensor) -> Tensor:
        theta = x[..., 2]
        zero, one = torch.zeros_like(theta), torch.ones_like(theta)
        rows = [
            torch.stack([torch.cos(theta), zero], -1),
            torch.stack([torch.sin(theta), zero], -1),
            torch.stack([zero, one], -1),
        ]
        return torch.stack(rows, -2)

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        theta = x[..., 2]
        v, omega = u[..., 0], u[..., 1]
        return torch.stack(
            torch.broadcast_tensors(v * torch.cos(theta), v * torch.sin(theta), omega), -1
        )

    def native_model(self) -> NativeModel:
        return NativeModel("unicycle")


class AccelUnicycle(ControlAffine):
    """Unicycle with acceleration input: state ``(x, y, v, theta)``, control ``(a, omega)``.

    ``x' = v cos(theta), y' = v sin(theta), v' = a, theta' = omega`` (scenario B).
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(4, 2, **kwargs)
        _register_eye_g(self, 2)

    def f(self, x: Tensor) -> Tensor:
        v, theta = x[..., 2], x[..., 3]
        zero = torch.zeros_like(v)
        return torch.stack([v * torch.cos(theta), v * torch.sin(theta), zero, zero], -1)

    def g(self, x: Tensor) -> Tensor:
        return _expand_g(self._g, x)

    def drift_derivatives(self, x: Tensor) -> DriftDerivatives:
        v, theta = x[..., 2:3], x[..., 3:4]
        cos, sin = torch.cos(theta), torch.sin(theta)
        # df_i/dv = (cos, sin)_i; df_i/dtheta = v (-sin, cos)_i; zero rows for v and theta
        cs, turn = torch.cat([cos, sin], -1), torch.cat([-sin, cos], -1)  # [..., 2]
        block = torch.stack([cs, v * turn], -1)  # [..., 2, 2]: rows (x, y), columns (v, theta)
        jac = torch.nn.functional.pad(block, (2, 0, 0, 2))

        def hess_quad(w: Tensor, s: Tensor) -> Tensor:
            # d2f_i/dv dtheta = (-sin, cos)_i, d2f_i/dtheta2 = -v (cos, sin)_i:
            # tr(S' d2f_i S) = 2 (-sin, cos)_i sum(S_v S_theta) - v (cos, sin)_i sum(S_theta^2)
            sv_st = (s[..., 2, :] * s[..., 3, :]).sum(-1, keepdim=True)
            st2 = s[..., 3, :].square().sum(-1, keepdim=True)
            q = 2 * sv_st * turn - v * st2 * cs  # [..., 2]
            return (w[..., :2] * q.unsqueeze(-2)).sum(-1)

        return DriftDerivatives(jac, hess_quad)

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        v, theta = x[..., 2], x[..., 3]
        parts = torch.broadcast_tensors(
            v * torch.cos(theta), v * torch.sin(theta), u[..., 0], u[..., 1]
        )
        return torch.stack(parts, -1)

    def native_model(self) -> NativeModel:
        return NativeModel("accel_unicycle")


class Bicycle(ControlAffine):
    """Kinematic bicycle (rear-axle reference): state ``(x, y, theta, delta)``,
    control ``(v, steering_rate)``.

    ``x' = v cos(theta), y' = v sin(theta), theta' = v tan(delta) / wheelbase,
    delta' = steering_rate``. Speed enters linearly, which makes the model control-affine.
    """

    def __init__(self, wheelbase: float | Tensor = 1.0, **kwargs: Any) -> None:
        super().__init__(4, 2, **kwargs)
        register_constant(self, "wheelbase", wheelbase, positive=True)
        if self.wheelbase.dim() != 0:
            raise ValueError(f"wheelbase must be a scalar, got shape {tuple(self.wheelbase.shape)}")

    def f(self, x: Tensor) -> Tensor:
        return torch.zeros_like(x)

    def g(self, x: Tensor) -> Tensor:
        theta, delta = x[..., 2], x[..., 3]
        zero, one = torch.zeros_like(theta), torch.ones_like(theta)
        rows = [
            torch.stack([torch.cos(theta), zero], -1),
            torch.stack([torch.sin(theta), zero], -1),
            torch.stack([torch.tan(delta) / self.wheelbase.to(x), zero], -1),
            torch.stack([zero, one], -1),
        ]
        return torch.stack(rows, -2)


class VanDerPol(ControlAffine):
    """Van der Pol oscillator with a force input: ``x1' = x2``,
    ``x2' = mu (1 - x1^2) x2 - x1 + u``."""

    def __init__(self, mu: float | Tensor = 1.0, **kwargs: Any) -> None:
        super().__init__(2, 1, **kwargs)
        _register_eye_g(self, 1)
        register_constant(self, "mu", mu)
        if self.mu.dim() != 0:
            raise ValueError(f"mu must be a scalar, got shape {tuple(self.mu.shape)}")

    def f(self, x: Tensor) -> Tensor:
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x2, self.mu.to(x) * (1 - x1**2) * x2 - x1], -1)

    def g(self, x: Tensor) -> Tensor:
        return _expand_g(self._g, x)


class Quadrotor(ControlAffine):
    """Rigid-body quadrotor with ZYX Euler angles.

    State (12): position ``(x, y, z)``, angles ``(phi, theta, psi)``, world-frame velocity
    ``(vx, vy, vz)``, body rates ``(p, q, r)``. Control (4): collective thrust ``T`` and body
    torques ``(tau_x, tau_y, tau_z)``. ``z`` points up; gravity acts along ``-z``.
    """

    def __init__(
        self,
        mass: float | Tensor = 1.0,
        inertia: tuple[float, float, float] | Tensor = (0.01, 0.01, 0.02),
        gravity: float | Tensor = 9.81,
        **kwargs: Any,
    ) -> None:
        super().__init__(12, 4, **kwargs)
        register_constant(self, "mass", mass, positive=True)
        register_constant(self, "inertia", inertia, positive=True)
        register_constant(self, "gravity", gravity)
        for name, shape in (("mass", ()), ("inertia", (3,)), ("gravity", ())):
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"{name} must have shape {shape or 'scalar'}, got {got}")

    def f(self, x: Tensor) -> Tensor:
        phi, theta = x[..., 3], x[..., 4]
        vel, rates = x[..., 6:9], x[..., 9:12]
        p, q, r = rates.unbind(-1)
        sphi, cphi, ttheta, ctheta = (
            torch.sin(phi),
            torch.cos(phi),
            torch.tan(theta),
            torch.cos(theta),
        )
        angle_rates = torch.stack(
            [
                p + sphi * ttheta * q + cphi * ttheta * r,
                cphi * q - sphi * r,
                (sphi * q + cphi * r) / ctheta,
            ],
            -1,
        )
        zero = torch.zeros_like(phi)
        accel = torch.stack([zero, zero, -self.gravity.to(x).expand_as(zero)], -1)
        J = self.inertia.to(x)
        rate_accel = -torch.linalg.cross(rates, rates * J) / J
        return torch.cat([vel, angle_rates, accel, rate_accel], -1)

    def g(self, x: Tensor) -> Tensor:
        phi, theta, psi = x[..., 3], x[..., 4], x[..., 5]
        sphi, cphi = torch.sin(phi), torch.cos(phi)
        sth, cth = torch.sin(theta), torch.cos(theta)
        spsi, cpsi = torch.sin(psi), torch.cos(psi)
        thrust_dir = torch.stack(
            [cphi * sth * cpsi + sphi * spsi, cphi * sth * spsi - sphi * cpsi, cphi * cth], -1
        )
        g = _zeros(x, 12, 4)
        g[..., 6:9, 0] = thrust_dir / self.mass.to(x)
        g[..., 9:12, 1:4] = torch.diag(1.0 / self.inertia.to(x))
        return g


class FixedWing(ControlAffine):
    """Kinematic fixed-wing aircraft: state ``(x, y, z, v, gamma, psi)`` (airspeed, flight-path
    angle, heading), control ``(a, gamma_rate, psi_rate)``.

    ``x' = v cos(gamma) cos(psi), y' = v cos(gamma) sin(psi), z' = v sin(gamma),
    v' = a, gamma' = gamma_rate, psi' = psi_rate``.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(6, 3, **kwargs)
        _register_eye_g(self, 3)

    def f(self, x: Tensor) -> Tensor:
        v, gamma, psi = x[..., 3], x[..., 4], x[..., 5]
        zero = torch.zeros_like(v)
        return torch.stack(
            [
                v * torch.cos(gamma) * torch.cos(psi),
                v * torch.cos(gamma) * torch.sin(psi),
                v * torch.sin(gamma),
                zero,
                zero,
                zero,
            ],
            -1,
        )

    def g(self, x: Tensor) -> Tensor:
        return _expand_g(self._g, x)
