"""Fallback policy of :class:`~torchcbf.filters.SafetyFilter`: the control of rows whose QP
failed (not ``SOLVED``) or whose data were non-finite."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from torch import Tensor, nn

from torchcbf._checks import check_last_dim
from torchcbf._constants import store

FallbackSpec = Literal["clip", "brake"] | Tensor | Callable[[Tensor, Tensor], Tensor]


class Fallback(nn.Module):
    """A fallback control ``[B, m]``, always finite and within the limits (clipped to them).

    Args:
        spec: ``"clip"`` (``u_nom`` clipped to the limits, default), ``"brake"`` (zero
            clipped to the limits), a tensor ``[m]`` (one that requires grad keeps its
            gradient, a parameter trains), or a callable
            ``(x [B, n], u_nom [B, m]) -> [B, m]``. A tensor's or a callable's control is
            cast to ``u_nom``'s dtype and clipped to the limits; wherever it is non-finite,
            zero clipped to the limits is used. Where its control carries a graph,
            :class:`~torchcbf.filters.SafetyFilter` calls a callable again on the rows that
            fall back alone (see :meth:`select`).
        control_dim: ``m``.
    """

    def __init__(self, spec: FallbackSpec, control_dim: int) -> None:
        super().__init__()
        self.register_buffer("control", None)
        self.function: Callable[[Tensor, Tensor], Tensor] | None = None
        if isinstance(spec, str):
            if spec not in ("clip", "brake"):
                raise ValueError(
                    f"fallback must be 'clip', 'brake', a tensor [m] or a callable, got {spec!r}"
                )
            self.kind = spec
        elif isinstance(spec, Tensor):
            if spec.shape != (control_dim,):
                raise ValueError(
                    f"fallback as a tensor must have shape [{control_dim}], got {tuple(spec.shape)}"
                )
            self.kind = "tensor"
            del self._buffers["control"]
            store(self, "control", spec)  # a tensor that requires grad keeps its gradient
        elif callable(spec):
            self.kind = "callable"
            self.function = spec
        else:
            raise TypeError(f"fallback must be a string, tensor or callable, got {spec!r}")

    def trains(self) -> bool:
        """Whether the control is a tensor that requires grad (the filter's output then
        carries a graph, zero where no row falls back; a callable's carries one where a row
        falls back, see :meth:`select`)."""
        return self.kind == "tensor" and self.control.requires_grad

    def forward(self, x: Tensor, u_nom: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        """Fallback controls ``[B, m]`` at ``x [B, n]`` for ``u_nom [B, m]`` within
        ``lo, hi [m]``."""
        return self._finished(self._control(x, u_nom), u_nom, lo, hi)

    @staticmethod
    def _finished(raw: Tensor, u_nom: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        """``raw [B, m]`` clipped to the limits, zero clipped to them in non-finite rows."""
        fb = torch.clamp(raw, lo, hi)
        zero = torch.clamp(torch.zeros_like(u_nom), lo, hi)
        return torch.where(torch.isfinite(fb).all(-1, keepdim=True), fb, zero)

    def _control(self, x: Tensor, u_nom: Tensor) -> Tensor:
        """The spec's control ``[B, m]`` before it is clipped and non-finite rows replaced
        (``"brake"``: zero)."""
        if self.kind == "clip":
            return u_nom
        if self.kind == "brake":
            return torch.zeros_like(u_nom)
        if self.kind == "tensor":
            return self.control.to(u_nom).expand_as(u_nom)
        assert self.function is not None
        fb = self.function(x, u_nom)
        check_last_dim("fallback(x, u_nom)", fb, u_nom.shape[-1])
        return fb.to(u_nom.dtype).expand_as(u_nom)

    def select(
        self, ok: Tensor, u: Tensor, x: Tensor, u_nom: Tensor, lo: Tensor, hi: Tensor
    ) -> Tensor:
        """``u [B, m]`` in the rows ``ok [B]``, the fallback's control in the others. A
        callable whose control carries a graph runs again on the rows that use it and where
        it is finite, alone (one host synchronisation): its backward on any other row would
        multiply a zero gradient by its partial derivatives there, NaN where it divides by
        zero (``x / |x|`` at 0) or where ``x`` is not finite, and every parameter it shares
        across rows would get a NaN gradient. A row where it is infinite keeps its value
        clipped to the limits, without a gradient (it is saturated there)."""
        raw = self._control(x, u_nom)
        if self.kind != "callable" or not raw.requires_grad:
            return torch.where(ok.unsqueeze(-1), u, self._finished(raw, u_nom, lo, hi))
        finite = torch.isfinite(raw).all(-1)
        out = torch.where(ok.unsqueeze(-1), u, self._finished(raw.detach(), u_nom, lo, hi))
        rows = (~ok & finite).nonzero().squeeze(-1)
        if rows.numel() == 0:
            return out
        return out.index_put((rows,), self(x[rows], u_nom[rows], lo, hi))

    def extra_repr(self) -> str:
        return self.kind
