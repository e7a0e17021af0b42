"""Figures that compare methods run on the same scenario and seeds: every seed's path in one
colour per method, barrier values over time with their spread across seeds, and a GIF of one
seed with every method."""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from torchcbf._checks import check_int
from torchcbf.sim.metrics import _barrier_values
from torchcbf.sim.trajectory import Trajectory
from torchcbf.viz.figures import BarrierFn, _draw_scene, _np, lowest_finite, plane

COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")


def _mark_exits(
    ax: Axes, xy: np.ndarray, xlim: tuple[float, float], ylim: tuple[float, float], color: str
) -> int:
    """A triangle where each path that leaves the view crosses its border; the count."""
    inside = (
        (xy[..., 0] >= xlim[0])
        & (xy[..., 0] <= xlim[1])
        & (xy[..., 1] >= ylim[0])
        & (xy[..., 1] <= ylim[1])
    )
    left = ~inside.all(-1)
    for b in np.flatnonzero(left):
        k = int(np.argmin(inside[b]))  # first step outside
        p = np.clip(xy[b, k], [xlim[0], ylim[0]], [xlim[1], ylim[1]])
        ax.plot(p[0], p[1], marker="^", color=color, ms=7, mec="k", mew=0.5, clip_on=False)
    return int(left.sum())


def _legend_right(ax: Axes, fontsize: int = 8) -> None:
    """The legend right of the axes, where it covers no data (saved with a tight box)."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=fontsize, frameon=False)


def plot_methods(
    trajectories: Mapping[str, Trajectory],
    barriers: Sequence[BarrierFn] = (),
    goals: Sequence[Any] = (),
    *,
    index: tuple[int, int] = (0, 1),
    xlim: tuple[float, float] | None = None,
    ylim: tuple[float, float] | None = None,
    title: str | None = None,
    units: str = "m",
) -> Figure:
    """Every seed's path of every method (``{name: Trajectory}``, ``x [B, T+1, n]``), one
    colour per method, over the obstacles and goals. The view is ``xlim`` x ``ylim`` (default:
    fitted to the goals and the starts); paths that leave it end in a triangle on the border,
    counted in the legend, which sits right of the axes (never over an obstacle or a goal)."""
    _check_methods(trajectories)
    fig, ax = plt.subplots(figsize=(7, 7))
    firsts = np.concatenate([plane(t.x, index)[:, :1] for t in trajectories.values()])
    xlim, ylim = _draw_scene(ax, firsts, barriers, goals, firsts.shape[-1], index, xlim, ylim)
    for j, (name, traj) in enumerate(trajectories.items()):
        color = COLORS[j % len(COLORS)]
        xy = plane(traj.x, index)
        for b in range(xy.shape[0]):
            ax.plot(xy[b, :, 0], xy[b, :, 1], color=color, lw=0.9, alpha=0.55)
        exits = _mark_exits(ax, xy, xlim, ylim, color)
        label = f"{name} ({xy.shape[0]} seeds" + (f", {exits} leave the view)" if exits else ")")
        ax.plot([], [], color=color, lw=2.0, label=label)
    ax.plot(firsts[:, 0, 0], firsts[:, 0, 1], "k.", ms=6, label="start")
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x [{units}]")
    ax.set_ylabel(f"y [{units}]")
    if title:
        ax.set_title(title)
    _legend_right(ax)
    return fig


def _check_methods(trajectories: Mapping[str, Trajectory]) -> None:
    if not trajectories:
        raise ValueError("trajectories is empty: give {method name: Trajectory}")


def barrier_traces(traj: Trajectory, barriers: Sequence[BarrierFn]) -> np.ndarray:
    """``min_i b_i(x)`` over the true states: ``[B, T+1]`` (NaN where a state is); a
    time-varying barrier read at the trajectory's times."""
    if not barriers:
        raise ValueError("barriers is empty: give the barriers whose least value to trace")
    B, T = traj.x.shape[:2]
    if B == 0:
        return np.zeros((0, T))
    return _np(_barrier_values(list(barriers), traj.x, traj.t).min(-1).values)


def plot_barrier_bands(
    trajectories: Mapping[str, Trajectory],
    barriers: Sequence[BarrierFn],
    *,
    title: str = "closest obstacle over time",
    ylabel: str = "min_i b_i(x)",
    ylim: tuple[float, float] | None = (-0.5, 5.0),
) -> Figure:
    """Per method: the median over seeds of ``min_i b_i(x(t))``, the 5-95 % band across
    seeds (the noise band) and the minimum over seeds; ``b = 0`` (contact) dashed. ``ylim``
    frames the bands; its lower end moves down (or its upper end up) to show the lowest
    value of any method, which is marked with its value."""
    _check_methods(trajectories)
    if not barriers:
        raise ValueError("barriers is empty: the bands are of min_i b_i(x), give the barriers")
    fig, ax = plt.subplots(figsize=(8, 4))
    lowest: dict[str, tuple[float, int, float]] = {}
    for j, (name, traj) in enumerate(trajectories.items()):
        color = COLORS[j % len(COLORS)]
        t = _np(traj.t)
        h = barrier_traces(traj, barriers)
        found = lowest_finite(h)
        if found is None:  # no seed, or none with a finite state: nothing to draw
            continue
        value, (b, k) = found
        lowest[name] = (value, b, float(t[k]))
        h = np.where(np.isneginf(h), np.nan, h)  # -inf (contact of a log barrier): off the axis
        with warnings.catch_warnings():  # a time where every seed is NaN stays NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            lo, med, hi = np.nanpercentile(h, [5, 50, 95], axis=0)
            least = np.nanmin(h, axis=0)
        ax.fill_between(t, lo, hi, color=color, alpha=0.2, lw=0)
        ax.plot(t, med, color=color, lw=1.8, label=f"{name}: median, 5-95 % band")
        ax.plot(t, least, color=color, lw=0.8, ls=":", label=f"{name}: minimum over seeds")
    ax.axhline(0.0, color="tab:red", ls="--", lw=1.0, label="contact (b = 0)")
    if ylim is not None:
        ax.set_ylim(*ylim)
    if lowest:
        worst = min(lowest, key=lambda name: lowest[name][0])
        value, seed, when = lowest[worst]
        lo, hi = ax.get_ylim()
        if value < lo + 0.05 * (hi - lo):
            ax.set_ylim(value - 0.08 * (hi - value), hi)
        elif value > hi - 0.05 * (hi - lo):
            ax.set_ylim(lo, value + 0.08 * (value - lo))
        label = f"lowest: {value:.2f} ({worst}, seed index {seed}, t = {when:.2f} s)"
        ax.plot(when, value, marker="v", color="tab:red", ms=8, mec="k", mew=0.5, zorder=5,
                label=label)  # fmt: skip
    ax.set_xlabel("t [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    _legend_right(ax, fontsize=7)
    return fig


def animate_methods(
    trajectories: Mapping[str, Trajectory],
    path: str | Path,
    barriers: Sequence[BarrierFn] = (),
    goals: Sequence[Any] = (),
    *,
    seed_index: int = 0,
    index: tuple[int, int] = (0, 1),
    xlim: tuple[float, float] | None = None,
    ylim: tuple[float, float] | None = None,
    frames: int = 60,
    fps: int = 15,
    title: str | None = None,
) -> Path:
    """A GIF of scenario ``seed_index`` (the same noise seed) under every method; returns
    its path."""
    check_int("frames", frames, low=1)
    check_int("fps", fps, low=1)
    _check_methods(trajectories)
    path = Path(path)
    for name, traj in trajectories.items():
        if not -traj.batch_size <= seed_index < traj.batch_size:
            raise IndexError(
                f"seed_index {seed_index} is outside {name!r}'s batch of {traj.batch_size}"
            )
    fig, ax = plt.subplots(figsize=(8.4, 6))
    try:
        fig.subplots_adjust(left=0.08, right=0.7)  # room for the legend (frames keep this box)
        xys = {name: plane(t.x, index)[seed_index] for name, t in trajectories.items()}
        starts = np.stack([xy[:1] for xy in xys.values()])
        xlim, ylim = _draw_scene(ax, starts, barriers, goals, starts.shape[-1], index, xlim, ylim)
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        if title:
            ax.set_title(title)
        lines, dots = [], []
        for j, name in enumerate(xys):
            color = COLORS[j % len(COLORS)]
            lines.append(ax.plot([], [], color=color, lw=1.5, label=name)[0])
            dots.append(ax.plot([], [], "o", color=color, ms=5)[0])
        _legend_right(ax)
        t = _np(next(iter(trajectories.values())).t)
        steps = len(t)
        ticks = np.linspace(0, steps - 1, min(frames, steps)).round().astype(int)
        stamp = ax.text(0.98, 0.02, "", transform=ax.transAxes, ha="right", va="bottom")

        def draw(i: int) -> list[Any]:
            k = ticks[i]
            for xy, line, dot in zip(xys.values(), lines, dots, strict=True):
                line.set_data(xy[: k + 1, 0], xy[: k + 1, 1])
                dot.set_data(xy[k : k + 1, 0], xy[k : k + 1, 1])
            stamp.set_text(f"t = {t[k]:.2f} s")
            return [*lines, *dots, stamp]

        FuncAnimation(fig, draw, frames=len(ticks), blit=False).save(
            path, writer=PillowWriter(fps=fps)
        )
    finally:
        plt.close(fig)
    return path
