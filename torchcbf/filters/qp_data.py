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

import math
from typing import Literal, NamedTuple

import torch
from torch import Tensor

SlackMode = Literal["shared", "per_row", "none"]
SLACK_MODES: tuple[str, ...] = ("shared", "per_row", "none")
#: smallest row norm the CBF rows are divided by
MIN_ROW_NORM = 1e-6
#: cap of the estimate ``v`` of the hard QP's multipliers in the shared slack's weight
MAX_PENALTY_SCALE = 1e3


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
    """``1 + v`` per row ``[B, 1]``, detached: ``v`` estimates the hard QP's multipliers (in
    units of ``rbar``) by how far ``u_nom`` is from the box and the CBF half-spaces
    (normalised violation), capped at ``MAX_PENALTY_SCALE``."""
    with torch.no_grad():
        viol = (-((a @ u_nom.unsqueeze(-1)).squeeze(-1) + b) / norms).clamp_min(0)
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
    G_parts, h_parts = [], []
    if cbf is not None:
        a, b = cbf
        if ks == k:
            eye = torch.eye(k, dtype=u_nom.dtype, device=u_nom.device).expand(B, k, k)
        else:  # one shared slack (ks = 1) or none (ks = 0)
            eye = u_nom.new_ones(B, k, ks)
        G_parts.append(torch.cat([-a / norms.unsqueeze(-1), -eye, u_nom.new_zeros(B, k, c)], -1))
        h_parts.append(b / norms)
    if clf is not None:
        a, b = clf
        eye = torch.eye(c, dtype=u_nom.dtype, device=u_nom.device).expand(B, c, c)
        G_parts.append(torch.cat([a, u_nom.new_zeros(B, c, ks), -eye], -1))
        h_parts.append(-b)
    inf = u_nom.new_full((ks + c,), math.inf)
    lb = torch.cat([lo, torch.zeros_like(inf)]).expand(B, nz)
    ub = torch.cat([hi, inf]).expand(B, nz)
    return FilterQP(Q, p, torch.cat(G_parts, 1), torch.cat(h_parts, 1), lb, ub, ks, norms)
