"""Matplotlib figures of closed-loop runs: trajectories over obstacles and goals, barrier values
over time, MPPI rollouts coloured by weight, and a GIF animation.

Obstacles are drawn as the unsafe set ``{h < 0}`` of any barrier (or function of the state)
on a grid, so closed-form shapes, compositions and learned barriers all plot the same way.
Goals are anything with ``center`` and ``radius`` (and optionally ``interval``, a time window).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.axes import Axes
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from torchcbf._checks import check_int
from torchcbf.sim.trajectory import Trajectory

BarrierFn = Callable[[torch.Tensor], torch.Tensor]


def _np(value: Any) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def plane(states: Any, index: tuple[int, int]) -> np.ndarray:
    """The two drawn components ``[..., 2]`` of ``states [..., n]`` (``ValueError`` where
    ``index`` names a component the state does not have)."""
    values = _np(states)
    n = values.shape[-1]
    if len(index) != 2 or not all(0 <= i < n for i in index):
        raise ValueError(f"index {tuple(index)} is outside the {n} components of the state")
    return values[..., list(index)]


def draw_unsafe_set(
    ax: Axes,
    barrier: BarrierFn,
    xlim: tuple[float, float],
    ylim: tuple[float, float],
    *,
    state_dim: int = 2,
    index: tuple[int, int] = (0, 1),
    fill: Sequence[float] | None = None,
    resolution: int = 300,
    color: str = "tab:red",
    label: str | None = "obstacle",
) -> None:
    """Shade ``{h < 0}`` of ``barrier`` over the plane of state components ``index``.

    The other state components are taken from ``fill`` (zeros by default). A barrier that
    returns ``[..., k]`` is reduced by its minimum over ``k``. A time-varying barrier is
    drawn where it is at ``t = 0`` (the figures of trajectories show the start; the
    metrics and :func:`~torchcbf.viz.barrier_traces` read it at each state's time).
    """
    resolution = check_int("resolution", resolution, low=2)
    if len(index) != 2 or not all(0 <= i < state_dim for i in index):
        raise ValueError(f"index {tuple(index)} is outside the {state_dim} components of the state")
    base = np.zeros(state_dim) if fill is None else np.asarray(fill, dtype=float)
    if base.shape != (state_dim,):
        raise ValueError(f"fill must have {state_dim} entries (state_dim), got {base.shape}")
    xs = np.linspace(*xlim, resolution)
    ys = np.linspace(*ylim, resolution)
    X, Y = np.meshgrid(xs, ys)
    states = np.broadcast_to(base, (*X.shape, state_dim)).copy()
    states[..., index[0]] = X
    states[..., index[1]] = Y
    param = next(iter(barrier.parameters()), None) if isinstance(barrier, torch.nn.Module) else None
    buf = next(iter(barrier.buffers()), None) if isinstance(barrier, torch.nn.Module) else None
    ref = param if param is not None else buf
    if ref is not None and ref.is_floating_point():
        dtype = ref.dtype
    elif isinstance(barrier, torch.nn.Module):
        dtype = torch.float64  # a module without tensors: plain arithmetic, drawn exactly
    else:
        dtype = torch.get_default_dtype()  # a function: it may wrap a network of this dtype
    device = ref.device if ref is not None else "cpu"
    with torch.no_grad():
        h = barrier(torch.as_tensor(states, dtype=dtype, device=device))
    h = _np(h).astype(float)
    if h.ndim == X.ndim + 1:
        h = h.min(-1)
    # NaN (a barrier undefined somewhere) is drawn as nothing; -inf as unsafe
    h = np.where(np.isneginf(h), np.finfo(float).min, h)
    finite = np.isfinite(h)
    if finite.any() and h[finite].min() < 0.0:  # else nothing of {h < 0} is in view
        lowest = h[finite].min()
        h = np.ma.masked_invalid(h)
        ax.contourf(X, Y, h, levels=[lowest - 1.0, 0.0], colors=[color], alpha=0.35)
        ax.contour(X, Y, h, levels=[0.0], colors=[color], linewidths=1.2)
    if label:
        ax.plot([], [], color=color, lw=6, alpha=0.35, label=label)


def draw_goals(
    ax: Axes, goals: Sequence[Any], color: str = "tab:green", index: tuple[int, int] = (0, 1)
) -> None:
    """Circles for goal regions in the plane of state components ``index``, annotated with
    their time windows when they have one."""
    for i, goal in enumerate(goals):
        c = _goal_point(goal, index)
        if c is None:
            continue
        r = float(goal.radius)
        ax.add_patch(Circle(tuple(c), r, facecolor=color, alpha=0.25, edgecolor=color, lw=1.5))
        interval = getattr(goal, "interval", None)
        text = f"g{i + 1}"
        if interval is not None:
            text += f"  [{float(interval[0]):g}, {float(interval[1]):g}] s"
        deadline = getattr(goal, "deadline", None)
        if deadline is not None:
            text += f"  by {float(deadline):g} s"
        ax.annotate(text, (c[0] + r, c[1] + r), fontsize=8, color="darkgreen")


def axis_labels(index: tuple[int, int], labels: tuple[str, str] | None = None) -> tuple[str, str]:
    """Axis labels: ``labels`` if given, ``x [m]``/``y [m]`` for the position ``(0, 1)`` (the
    models' convention), else the state components ``x[i]``."""
    if labels is not None:
        return labels
    if tuple(index) == (0, 1):
        return ("x [m]", "y [m]")
    return (f"x[{index[0]}]", f"x[{index[1]}]")


def weight_ranks(weights: np.ndarray) -> np.ndarray:
    """``[K]`` ranks of ``weights [K]`` scaled to ``[0, 1]`` (0: lightest, 1: heaviest; ties
    share their mean rank)."""
    w = np.asarray(weights, dtype=float)
    if w.size < 2:
        return np.ones_like(w)
    order = np.argsort(w, kind="stable")
    ranks = np.empty(w.size)
    ranks[order] = np.arange(w.size, dtype=float)
    _, inverse = np.unique(w, return_inverse=True)
    ranks = np.bincount(inverse, ranks) / np.bincount(inverse)  # mean rank of each value
    return ranks[inverse] / (w.size - 1)


def lowest_finite(h: np.ndarray) -> tuple[float, tuple[int, ...]] | None:
    """The least finite value of ``h`` and its index (``-inf``, a log barrier at contact,
    and NaN are passed over; an axis cannot reach them); ``None`` where none is finite."""
    finite = np.isfinite(h)
    if not finite.any():
        return None
    at = np.unravel_index(np.argmin(np.where(finite, h, np.inf)), h.shape)
    return float(h[at]), tuple(int(i) for i in at)


def mark_minimum(ax: Axes, t: np.ndarray, h: np.ndarray, color: str = "tab:red") -> None:
    """Mark the smallest value of ``h [B, T]`` over time ``t [T]`` with its value, and widen
    the y-axis so that it shows (a fixed lower limit hides the worst collision)."""
    found = lowest_finite(h)
    if found is None:
        return  # nothing finite to mark (an empty batch, every value NaN)
    value, (b, j) = found
    what = "lowest finite" if np.isneginf(h).any() else "lowest"
    ax.plot(t[j], value, marker="v", color=color, ms=8, mec="k", mew=0.5, zorder=5,
            label=f"{what}: {value:.2f} (scenario {b}, t = {t[j]:.2f} s)")  # fmt: skip
    lo, hi = ax.get_ylim()
    if value < lo + 0.05 * (hi - lo):
        ax.set_ylim(value - 0.08 * (hi - value), hi)


def _legend_below(ax: Axes, fontsize: int = 8) -> None:
    """The legend under the axes, where it covers no data (save with a tight bounding box)."""
    if not ax.get_legend_handles_labels()[0]:
        return
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=fontsize,
              frameon=False)  # fmt: skip


def _goal_point(goal: Any, index: tuple[int, int]) -> np.ndarray | None:
    """The centre ``[2]`` of ``goal`` in the plane of state components ``index`` (its centre
    holds the components of the goal's own ``index``, default the first ones); ``None`` for a
    goal on other components (a position goal in a plane of velocities)."""
    centre = _np(goal.center).reshape(-1)
    own = getattr(goal, "index", None)
    if own is None:
        own = range(centre.shape[0])
    elif isinstance(own, slice):  # a specification's contiguous components
        own = range(own.start, own.stop)
    own = [int(i) for i in own]
    if not all(i in own for i in index):
        return None
    return np.array([centre[own.index(i)] for i in index], dtype=float)


def _limits(
    traj_xy: np.ndarray, goals: Sequence[Any], margin: float = 1.0, index: tuple[int, int] = (0, 1)
) -> tuple[tuple[float, float], tuple[float, float]]:
    pts = [traj_xy.reshape(-1, 2)]
    for g in goals:
        c = _goal_point(g, index)
        if c is not None:
            pts.append(c.reshape(1, 2))
    allp = np.concatenate(pts)
    allp = allp[np.isfinite(allp).all(-1)]
    if allp.shape[0] == 0:  # no finite point (an empty batch, every state NaN): around 0
        allp = np.zeros((1, 2))
    lo, hi = allp.min(0) - margin, allp.max(0) + margin
    return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


def _draw_scene(
    ax: Axes,
    points: np.ndarray,
    barriers: Sequence[BarrierFn],
    goals: Sequence[Any],
    state_dim: int,
    index: tuple[int, int],
    xlim: tuple[float, float] | None,
    ylim: tuple[float, float] | None,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Obstacles (the first labelled) and goals behind ``points [..., 2]``; returns the axis
    limits (those given, else fitted to the points and goals)."""
    auto_x, auto_y = _limits(points, goals, index=index)
    xlim, ylim = xlim or auto_x, ylim or auto_y
    for j, barrier in enumerate(barriers):
        draw_unsafe_set(
            ax,
            barrier,
            xlim,
            ylim,
            state_dim=state_dim,
            index=index,
            label="obstacle" if j == 0 else None,
        )
    draw_goals(ax, goals, index=index)
    return xlim, ylim


def plot_trajectories(
    trajectory: Trajectory,
    barriers: Sequence[BarrierFn] = (),
    goals: Sequence[Any] = (),
    *,
    index: tuple[int, int] = (0, 1),
    ax: Axes | None = None,
    title: str | None = None,
    xlim: tuple[float, float] | None = None,
    ylim: tuple[float, float] | None = None,
    color: str | None = None,
    label: str | None = None,
    max_paths: int = 64,
    labels: tuple[str, str] | None = None,
) -> Figure:
    """Paths of (up to ``max_paths``) scenarios over obstacles and goal regions (axis
    ``labels`` as :func:`axis_labels`)."""
    xy = plane(trajectory.x, index)
    fig, ax = (ax.figure, ax) if ax is not None else plt.subplots(figsize=(6, 6))
    xlim, ylim = _draw_scene(ax, xy, barriers, goals, trajectory.x.shape[-1], index, xlim, ylim)
    for b in range(min(xy.shape[0], max_paths)):
        ax.plot(
            xy[b, :, 0],
            xy[b, :, 1],
            color=color or "tab:blue",
            lw=1.0,
            alpha=0.6,
            label=label if b == 0 else None,
        )
    ax.plot(xy[:, 0, 0], xy[:, 0, 1], "k.", ms=6)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal")
    xlabel, ylabel = axis_labels(index, labels)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    if ax.get_legend_handles_labels()[0]:
        _legend_below(ax)
    return fig


def plot_barrier_values(
    t: Any,
    h: Any,
    *,
    ax: Axes | None = None,
    title: str = "barrier values",
    ylabel: str = "min_i h_i(x)",
) -> Figure:
    """``h [B, T, k]`` (or ``[B, T]``) over time: the minimum over barriers for each scenario,
    with the batch's minimum in bold and the safety boundary ``h = 0`` dashed."""
    if h is None:
        raise ValueError(
            "h is None: a trajectory without a safety filter records no barrier values; "
            "pass barrier_traces(traj, barriers) for the barriers' values along it"
        )
    t, h = _np(t), _np(h)
    if h.ndim not in (2, 3) or t.ndim != 1 or t.shape[0] < h.shape[1]:
        raise ValueError(
            f"h must be [B, T, k] or [B, T] with t [T] (or longer): got h {h.shape}, t {t.shape}"
        )
    fig, ax = (ax.figure, ax) if ax is not None else plt.subplots(figsize=(7, 3.5))
    if h.ndim == 3:
        h = h.min(-1) if h.shape[-1] else np.full(h.shape[:2], np.nan)
    t = t[: h.shape[1]]
    for b in range(h.shape[0]):
        label = f"one line per scenario ({h.shape[0]})" if b == 0 else None
        ax.plot(t, h[b], color="tab:blue", alpha=0.3, lw=0.8, label=label)
    if h.shape[0]:
        with warnings.catch_warnings():  # a time where every scenario is NaN stays NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            least = np.nanmin(h, axis=0)
        ax.plot(t, least, color="tab:blue", lw=2.0, label="minimum over scenarios")
    ax.axhline(0.0, color="tab:red", ls="--", lw=1.0, label="h = 0 (boundary)")
    mark_minimum(ax, t, h)
    ax.set_xlabel("t [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    _legend_below(ax)
    return fig


def plot_rollouts(
    rollouts: Any,
    weights: Any,
    plan_states: Any | None = None,
    *,
    barriers: Sequence[BarrierFn] = (),
    goals: Sequence[Any] = (),
    executed: Any | None = None,
    index: tuple[int, int] = (0, 1),
    ax: Axes | None = None,
    title: str = "MPPI rollouts",
    plan_label: str = "chosen plan",
    xlim: tuple[float, float] | None = None,
    ylim: tuple[float, float] | None = None,
) -> Figure:
    """Sampled rollouts ``[K, H+1, n]`` coloured by the rank of their weight ``[K]`` (the
    paper's third figure), a plan's states ``[H+1, n]`` (labelled ``plan_label``) and the
    executed path ``[T, n]``. MPPI's weights span tens of orders of magnitude, so a colour
    scale on the weight (or its logarithm over a few decades) puts almost every rollout at
    its bottom; ranks spread them evenly. The legend sits below the axes."""
    R = plane(rollouts, index)
    w = _np(weights)
    if R.ndim != 3 or w.shape != R.shape[:1]:
        raise ValueError(
            f"rollouts must be [K, H+1, n] and weights [K]: got rollouts "
            f"{tuple(_np(rollouts).shape)} and weights {tuple(w.shape)}"
        )
    E = None if executed is None else plane(executed, index)
    P = None if plan_states is None else plane(plan_states, index)
    fig, ax = (ax.figure, ax) if ax is not None else plt.subplots(figsize=(6, 6))
    rank = weight_ranks(w)
    # the view holds the rollouts, the executed path and the plan
    shown = np.concatenate([a.reshape(-1, 2) for a in (R, E, P) if a is not None])
    n = _np(rollouts).shape[-1]
    xlim, ylim = _draw_scene(ax, shown, barriers, goals, n, index, xlim, ylim)
    cmap = plt.get_cmap("viridis")
    for k in np.argsort(rank, kind="stable"):  # the heaviest drawn last, on top
        ax.plot(R[k, :, 0], R[k, :, 1], color=cmap(rank[k]), lw=0.6, alpha=0.2 + 0.6 * rank[k])
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=Normalize(0.0, 1.0))
    fig.colorbar(sm, ax=ax, label="rank of the sample's weight (1 = heaviest)")
    if E is not None:
        ax.plot(E[:, 0], E[:, 1], "k-", lw=2.0, label="executed")
    if P is not None:
        ax.plot(P[:, 0], P[:, 1], color="tab:orange", lw=2.5, label=plan_label)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal")
    xlabel, ylabel = axis_labels(index)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    _legend_below(ax)
    return fig


def animate(
    trajectory: Trajectory,
    path: str | Path,
    barriers: Sequence[BarrierFn] = (),
    goals: Sequence[Any] = (),
    *,
    index: tuple[int, int] = (0, 1),
    frames: int = 60,
    fps: int = 15,
    max_paths: int = 16,
) -> Path:
    """Write a GIF of the scenarios moving over obstacles and goals; returns its path."""
    check_int("frames", frames, low=1)
    check_int("fps", fps, low=1)
    path = Path(path)
    fig = plot_trajectories(trajectory, barriers, goals, index=index, max_paths=0)
    try:
        ax = fig.axes[0]
        xy = plane(trajectory.x[:max_paths], index)
        t = _np(trajectory.t)
        lines = [ax.plot([], [], color="tab:blue", lw=1.2)[0] for _ in range(xy.shape[0])]
        dots = ax.plot([], [], "o", color="tab:blue", ms=4)[0]
        stamp = ax.text(0.02, 0.97, "", transform=ax.transAxes, va="top")
        ticks = np.linspace(0, xy.shape[1] - 1, min(frames, xy.shape[1])).round().astype(int)

        def draw(i: int) -> list[Any]:
            k = ticks[i]
            for b, line in enumerate(lines):
                line.set_data(xy[b, : k + 1, 0], xy[b, : k + 1, 1])
            dots.set_data(xy[:, k, 0], xy[:, k, 1])
            stamp.set_text(f"t = {t[k]:.2f} s")
            return [*lines, dots, stamp]

        FuncAnimation(fig, draw, frames=len(ticks), blit=False).save(
            path, writer=PillowWriter(fps=fps)
        )
    finally:
        plt.close(fig)
    return path
