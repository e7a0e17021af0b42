"""Batched linear-algebra helpers for the Kalman filters (private).

Every function works on a flat batch: vectors ``[B, k]`` and matrices ``[B, k, k]``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from torchcbf._autograd import reaches_other_leaf


def symmetrize(A: Tensor) -> Tensor:
    """``(A + A^T) / 2`` for ``[..., k, k]``."""
    return 0.5 * (A + A.mT)


def jacobian(
    fn: Callable[[Tensor], Tensor], x: Tensor, create_graph: bool
) -> tuple[Tensor, Tensor]:
    """Value and Jacobian of a row-wise map ``fn: [B, n] -> [B, k]``.

    Rows are independent, so the Jacobian of row ``b`` is the gradient of the summed output
    component: one backward pass per output component (a loop over ``k``, never over rows).
    With ``create_graph`` the result stays differentiable (second derivatives included);
    without it the value and the Jacobian are detached, unless grad mode is on and ``fn``
    holds a tensor that requires grad (a closure's), whose gradient they then carry.

    Returns:
        ``(fn(x) [B, k], J [B, k, n])``.
    """
    outer = torch.is_grad_enabled()
    with torch.enable_grad():
        if create_graph and x.requires_grad:
            xr = x
        else:
            xr = x.detach().requires_grad_(True)
        out = fn(xr)
        if not create_graph and outer and out.requires_grad and reaches_other_leaf(out, xr):
            create_graph = True  # the caller's test saw modules only: keep the graph
            if x.requires_grad:
                xr = x
                out = fn(xr)
        if not out.requires_grad:
            # the map does not depend on x (nor on anything that requires grad): its
            # Jacobian is zero, and autograd has no graph to differentiate
            J = out.new_zeros(*out.shape, xr.shape[-1])
            return (out.detach(), J) if not create_graph else (out, J)
        rows = []
        for i in range(out.shape[-1]):
            (grad,) = torch.autograd.grad(
                out[..., i].sum(),
                xr,
                retain_graph=True,
                create_graph=create_graph,
                allow_unused=True,
            )
            rows.append(torch.zeros_like(xr) if grad is None else grad)
    J = torch.stack(rows, dim=-2)
    if not create_graph:
        return out.detach(), J.detach()
    return out, J


#: Pade [13/13] coefficients and the 1-norm up to which it is accurate to float64 rounding
#: (Higham, "The scaling and squaring method for the matrix exponential revisited", 2005)
_PADE13 = (
    64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
    129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0,
    40840800.0, 960960.0, 16380.0, 182.0, 1.0,
)  # fmt: skip
_THETA13 = 5.371920351148152
#: squarings the accelerator path always runs (each masked per row): 1-norms up to
#: ``_THETA13 * 2**24`` (about 9e7), far beyond where the exponential overflows
_MAX_SQUARINGS = 24


def matrix_exp(A: Tensor) -> Tensor:
    """``exp(A)`` for ``A [B, k, k]``: :func:`torch.linalg.matrix_exp` on the CPU; elsewhere
    scaling and squaring with Pade [13/13] and a fixed number of squarings masked per row,
    which never reads a value back (torch's CUDA version copies the norms to the host and
    squares row by row)."""
    if A.device.type == "cpu":
        return torch.linalg.matrix_exp(A)
    return pade_matrix_exp(A)


def pade_matrix_exp(A: Tensor) -> Tensor:
    """The accelerator path of :func:`matrix_exp` (any device), ``A [B, k, k]``."""
    s = _halvings(A, _THETA13)
    E = _pade13(A / torch.exp2(s)[:, None, None])
    for i in range(_MAX_SQUARINGS):
        E = torch.where((s > i)[:, None, None], E @ E, E)
    return E


def _halvings(A: Tensor, bound: float) -> Tensor:
    """``[B]``: how many times to halve ``A [B, k, k]`` for its 1-norm to be at most
    ``bound`` (0 for a non-finite norm, at most ``_MAX_SQUARINGS``)."""
    norm = A.detach().abs().sum(-2).amax(-1)
    s = torch.ceil(torch.log2(norm / bound)).clamp(0, _MAX_SQUARINGS)
    return torch.where(torch.isfinite(s), s, 0.0)


def _pade13(A: Tensor) -> Tensor:
    """Pade [13/13] of ``exp(A)`` for ``A [B, k, k]`` of 1-norm at most ``_THETA13``."""
    b = _PADE13
    eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device).expand_as(A)
    A2 = A @ A
    A4 = A2 @ A2
    A6 = A4 @ A2
    U = A @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4
             + b[3] * A2 + b[1] * eye)  # fmt: skip
    V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2
    V = V + b[0] * eye
    # solve_ex: torch.linalg.solve reads its error code back to raise (V - U is well
    # conditioned once the norm is below theta)
    return torch.linalg.solve_ex(V - U, V + U).result


def discretize(
    F: Tensor,
    h: float,
    xdot: Tensor | None = None,
    Qc: Tensor | None = None,
    *,
    pade: bool | None = None,
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Exact discretization of ``d(dx)/dt = F dx + xdot`` and ``dP/dt = F P + P F^T + Qc``.

    One matrix exponential of the block matrix ``[[F, Qc, xdot], [0, -F^T, 0], [0, 0, 0]] t``
    gives ``Phi = exp(F t)`` (top-left), ``G`` (top-middle) with ``Qd = G Phi^T =
    int_0^t exp(F s) Qc exp(F s)^T ds`` (Van Loan) and ``phi1(F t) t xdot`` (top-right
    column), the exponential-Euler increment. The exponential is taken over ``t = h / 2^s``
    and the piece doubled ``s`` times (``Qd <- Phi Qd Phi^T + Qd``, ``Phi <- Phi Phi``, ``dx
    <- Phi dx + dx``), ``s`` per row: squaring the whole block instead would form
    ``exp(-F^T h)``, which overflows for a stiff stable ``F`` (``|F h|`` past 709 in float64,
    88 in float32) though ``Phi`` and ``Qd`` are bounded, and whose backward loses every
    digit long before (``|F h| = 40``: torch's gradient off by 1e2 against 4e-4). ``s``
    brings the block's 1-norm into Pade [13/13]'s range; off the CPU (``pade``) that
    approximant runs with a fixed number of masked doublings (no host synchronisation).

    Args:
        F: ``[B, n, n]``; xdot: ``[B, n]`` or None; Qc: ``[B, n, n]`` or None.
        pade: the accelerator's way (``None``: off the CPU).

    Returns:
        ``(Phi [B, n, n], dx [B, n] or None, Qd [B, n, n] or None)``.
    """
    B, n = F.shape[0], F.shape[-1]
    size = n + (n if Qc is not None else 0) + (1 if xdot is not None else 0)
    M = F.new_zeros(B, size, size)
    M[:, :n, :n] = F
    col = n
    if Qc is not None:
        M[:, :n, n : 2 * n] = Qc
        M[:, n : 2 * n, n : 2 * n] = -F.mT
        col = 2 * n
    if xdot is not None:
        M[:, :n, col] = xdot
    M = M * h
    if pade is None:
        pade = M.device.type != "cpu"
    s = _halvings(M, _THETA13)
    M = M / torch.exp2(s)[:, None, None]
    if pade:
        E = _pade13(M)
        doublings = _MAX_SQUARINGS
    else:
        E = torch.linalg.matrix_exp(M)
        doublings = int(s.max()) if s.numel() else 0  # no synchronisation on the CPU
    Qd = E[:, :n, n : 2 * n] @ E[:, :n, :n].mT if Qc is not None else None
    # A = [[Phi, dx], [0, 1]]: A @ A = [[Phi Phi, Phi dx + dx], [0, 1]] doubles both
    keep = torch.arange(n + 1, device=E.device)
    keep[n] = col
    A = E[:, :n, :n] if xdot is None else E.index_select(1, keep).index_select(2, keep)
    more = s > torch.arange(doublings, dtype=s.dtype, device=s.device)[:, None]  # [d, B]
    for i in range(doublings):
        step = more[i, :, None, None]
        if Qd is not None:
            Phi = A[:, :n, :n]
            Qd = torch.where(step, torch.baddbmm(Qd, Phi @ Qd, Phi.mT), Qd)
        A = torch.where(step, A @ A, A)
    dx = A[:, :n, n] if xdot is not None else None
    return A[:, :n, :n], dx, symmetrize(Qd) if Qd is not None else None


def robust_cholesky(A: Tensor) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factor of a symmetric ``A [B, k, k]`` that never raises.

    Rows whose factorization fails are retried with a jitter ``eps^(3/4) s I`` and then
    ``eps^(1/2) s I`` (``s`` the mean absolute diagonal, ``eps`` the dtype's machine epsilon);
    a row that still fails gets the diagonal square root ``diag(sqrt(max(diag A, tiny)))``.
    Every attempt runs on the whole batch and is selected with ``torch.where``: no host sync.

    Returns:
        ``(L [B, k, k], regularized [B] bool)``.
    """
    A = symmetrize(A)
    L, info = torch.linalg.cholesky_ex(A)
    ok = info == 0
    regularized = ~ok
    finfo = torch.finfo(A.dtype)
    k = A.shape[-1]
    eye = torch.eye(k, dtype=A.dtype, device=A.device)
    scale = A.diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(finfo.tiny)
    for power in (0.75, 0.5):
        jitter = (finfo.eps**power) * scale
        Lj, info_j = torch.linalg.cholesky_ex(A + jitter[:, None, None] * eye)
        use = ~ok & (info_j == 0)
        L = torch.where(use[:, None, None], Lj, L)
        ok = ok | use
    diag = torch.diag_embed(A.diagonal(dim1=-2, dim2=-1).clamp_min(finfo.tiny).sqrt())
    L = torch.where(ok[:, None, None], L, diag)
    return L, regularized


def wrap_angle(a: Tensor) -> Tensor:
    """Wrap angles to ``[-pi, pi)``."""
    w = torch.remainder(a + torch.pi, 2 * torch.pi) - torch.pi
    # an angle a rounding below -pi comes back as +pi (remainder rounds up to 2 pi)
    return torch.where(w >= torch.pi, w - 2 * torch.pi, w)
