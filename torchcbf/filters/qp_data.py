"""The safety filter's QP, assembled from the CBF and CLF conditions.

Over ``z = [u (m); s (ks); delta (c)]`` the filter solves

    min  1/2 |u - u_nom|_R^2 + P_cbf(s) + 1/2 w_clf rbar |delta|^2
    s.t. (a_i . u + b_i) / n_i + s_i >= 0      for each of the k barrier outputs,
         a_j . u + b_j <= delta_j              for each of the c Lyapunov outputs,
         u_min <= u <= u_max,  s >= 0,  delta >= 0,

with ``n_i = max(|a_i|_2, 1e-6)`` and ``rbar = tr(R) / m``. The CBF slack is ``"shared"``
(one ``s`` for every row, exact penalty ``w rbar (s + s^2/2)``), ``"per_row"`` (one per row,
``1/2 w rbar s_i^2``) or ``"none"`` (hard rows only). :func:`assemble` builds the data in
torch (any batch, any device, differentiable); the real-time path's C kernel
(:mod:`torchcbf.filters.realtime`) builds the same data for a few states, with the finite
limits and ``s, delta >= 0`` as rows (the tests compare the two paths' answers).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from torchcbf._checks import check_number
from torchcbf.dynamics.base import matvec

SlackMode = Literal["shared", "per_row", "none"]
SLACK_MODES: tuple[str, ...] = ("shared", "per_row", "none")
#: smallest row norm the CBF rows are divided by
MIN_ROW_NORM = 1e-6
#: cap of the estimate ``v`` of the hard QP's multipliers in the shared slack's weight
MAX_PENALTY_SCALE = 1e3


@dataclasses.dataclass(frozen=True)
class Slack:
    """How the filter's QP relaxes its conditions (the QP above).

    Args:
        mode: ``"shared"`` (default: one slack for every CBF row, exact penalty: the hard
            QP's answer where its multipliers stay below ``w``; where the hard QP is
            infeasible, or needs larger multipliers (barriers whose safe controls form a
            narrow wedge), the least-violating control, status ``RELAXED``),
            ``"per_row"`` (soft CBF rows, one slack each) or ``"none"`` (hard rows only:
            an infeasible row gets the fallback).
        cbf_weight: weight ``w`` of the CBF slack (default 1e3 shared, 1e2 per row).
        clf_weight: weight ``w_clf`` of the CLF relaxation ``delta`` (default 1e2).
        tol: normalised CBF slack (control units) above which a row is ``RELAXED``
            (default 1e-6 in float64, 1e-3 in float32).
        exact: with the shared slack, also solve the hard QP (stacked in the same call)
            and prefer its solution where it is solved (default: when the filter has
            Lyapunov functions, which can pull against a barrier harder than ``w``); with
            Lyapunov functions, where the hard QP is infeasible, the least violation of
            the CBF rows alone bounds the answer's.

    ``SafetyFilter(..., slack="none")`` is short for ``slack=Slack("none")``.
    """

    mode: SlackMode = "shared"
    cbf_weight: float | None = None
    clf_weight: float = 1e2
    tol: float | None = None
    exact: bool | None = None

    def __post_init__(self) -> None:
        if self.mode not in SLACK_MODES:
            raise ValueError(f"slack mode must be one of {SLACK_MODES}, got {self.mode!r}")
        for name in ("cbf_weight", "tol"):
            value = getattr(self, name)
            if value is not None:
                value = check_number(f"slack {name}", value, low=0.0, strict=True)
                object.__setattr__(self, name, value)
        clf = check_number("slack clf_weight", self.clf_weight, low=0.0, strict=True)
        object.__setattr__(self, "clf_weight", clf)
        if self.exact is not None and not isinstance(self.exact, bool):
            raise TypeError(f"slack exact must be a bool or None, got {self.exact!r}")

    def resolved(self, *, lyapunovs: bool) -> Slack:
        """The options with the defaults that depend on the filter filled in (``tol``
        depends on the dtype and stays as given)."""
        weight = self.cbf_weight
        if weight is None:
            weight = 1e2 if self.mode == "per_row" else 1e3
        exact = lyapunovs if self.exact is None else self.exact
        # the hard QP beside the elastic one exists only with the shared slack
        return dataclasses.replace(self, cbf_weight=weight, exact=exact and self.mode == "shared")

    @property
    def two_pass(self) -> bool:
        """Whether the hard QP is solved beside the elastic one."""
        return bool(self.exact) and self.mode == "shared"


class FilterQP(NamedTuple):
    """``min 1/2 z'Qz + p'z, Gz <= h, lb <= z <= ub`` for ``z [B, m + ks + c]``; ``ks`` is the
    number of CBF slack columns and ``norms [B, k]`` the CBF row norms."""

    Q: Tensor
    p: Tensor
    G: Tensor
    h: Tensor
    lb: Tensor
    ub: Tensor
    ks: int
    norms: Tensor | None


def slack_columns(k: int, slack: SlackMode) -> int:
    """Number of CBF slack columns for ``k`` barrier outputs."""
    if not k or slack == "none":
        return 0
    return k if slack == "per_row" else 1


def penalty_scale(
    a: Tensor, b: Tensor, norms: Tensor, u_nom: Tensor, lo: Tensor, hi: Tensor
) -> Tensor:
    """``1 + v`` per row ``[B, 1]``: ``v`` estimates the hard QP's multipliers (in units of
    ``rbar``) by how far ``u_nom`` is from the box and the CBF half-spaces (normalised
    violation), capped at ``MAX_PENALTY_SCALE``. Differentiable: where the weight binds (a
    ``RELAXED`` row whose slack is not zero) the answer depends on it; elsewhere its
    derivative does not reach the answer."""
    viol = (-(matvec(a, u_nom) + b) / norms).clamp_min(0)
    box = (u_nom - torch.clamp(u_nom, lo, hi)).abs()
    v = viol.amax(-1, keepdim=True) + box.amax(-1, keepdim=True)
    v = torch.nan_to_num(v, nan=0.0, posinf=MAX_PENALTY_SCALE).clamp_max(MAX_PENALTY_SCALE)
    return 1.0 + v


def assemble(
    cbf: tuple[Tensor, Tensor] | None,
    clf: tuple[Tensor, Tensor] | None,
    u_nom: Tensor,
    R: Tensor,
    lo: Tensor,
    hi: Tensor,
    *,
    slack: SlackMode,
    cbf_weight: float,
    clf_weight: float,
) -> FilterQP:
    """QP data from the conditions ``cbf = (a [B,k,m], b [B,k])`` (``a . u + b >= 0``) and
    ``clf = (a [B,c,m], b [B,c])`` (``a . u + b <= delta``), ``u_nom [B, m]``, ``R [m, m]``
    and the limits ``lo, hi [m]``."""
    B, m = u_nom.shape
    k = 0 if cbf is None else cbf[1].shape[1]
    c = 0 if clf is None else clf[1].shape[1]
    ks = slack_columns(k, slack)
    nz = m + ks + c
    rbar = torch.diagonal(R).mean()
    norms = None
    if cbf is not None:
        norms = torch.linalg.vector_norm(cbf[0], dim=-1).clamp_min(MIN_ROW_NORM)
    w = u_nom.new_full((B, 1), cbf_weight) * rbar
    if k and slack == "shared":
        w = w * penalty_scale(cbf[0], cbf[1], norms, u_nom, lo, hi)
    lin_s = w if slack == "shared" else torch.zeros_like(w)
    diag = [u_nom.new_zeros(B, m), w.expand(B, ks), (clf_weight * rbar).expand(B, c)]
    Q = torch.diag_embed(torch.cat(diag, -1))
    Q[:, :m, :m] = R
    p = torch.cat([-(u_nom @ R.mT), lin_s.expand(B, ks), u_nom.new_zeros(B, c)], -1)
    # G and h written block by block into one buffer each (one pass over the rows' data)
    G = u_nom.new_empty(B, k + c, nz)
    h = u_nom.new_empty(B, k + c)
    G[:, :, m:] = 0.0
    if cbf is not None:
        a, b = cbf
        G[:, :k, :m] = a / -norms.unsqueeze(-1)  # -a / norms: the signs are exact
        if ks == k:
            G[:, :k, m : m + ks].diagonal(dim1=-2, dim2=-1).fill_(-1.0)
        else:  # one shared slack (ks = 1) or none (ks = 0)
            G[:, :k, m : m + ks] = -1.0
        h[:, :k] = b / norms
    if clf is not None:
        a, b = clf
        G[:, k:, :m] = a
        G[:, k:, m + ks :].diagonal(dim1=-2, dim2=-1).fill_(-1.0)
        h[:, k:] = -b
    inf = u_nom.new_full((ks + c,), math.inf)
    lb = torch.cat([lo, torch.zeros_like(inf)]).expand(B, nz)
    ub = torch.cat([hi, inf]).expand(B, nz)
    return FilterQP(Q, p, G, h, lb, ub, ks, norms)
