"""Hand-written references shared by the arm tests: planar-arm kinematics, finite differences."""

from __future__ import annotations

from collections.abc import Callable

import torch

LENGTHS = (0.5, 0.4, 0.3)


def planar_fk(q: torch.Tensor) -> torch.Tensor:
    """Hand-written planar FK: origins of link1, link2, link3 and ee, ``[..., 4, 3]``."""
    angles = torch.cumsum(q, -1)
    pts = [torch.zeros_like(q[..., :2])]
    for i, length in enumerate(LENGTHS):
        step = torch.stack([torch.cos(angles[..., i]), torch.sin(angles[..., i])], -1)
        pts.append(pts[-1] + length * step)
    xy = torch.stack(pts, -2)
    return torch.cat([xy, torch.zeros_like(xy[..., :1])], -1)


def fd_jacobian(
    fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, eps: float = 1e-6
) -> torch.Tensor:
    """Central differences of ``fn: [B, n] -> [B, k]``: ``[B, k, n]``."""
    cols = []
    for j in range(x.shape[-1]):
        dx = torch.zeros_like(x)
        dx[..., j] = eps
        cols.append((fn(x + dx) - fn(x - dx)) / (2 * eps))
    return torch.stack(cols, -1)
