"""Figures: rollout colours spread by rank, the deepest violation shown and marked, legends
outside the data."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from matplotlib.colors import to_rgba  # noqa: E402

from torchcbf.barriers import Ball  # noqa: E402
from torchcbf.sim import Trajectory  # noqa: E402
from torchcbf.viz import (  # noqa: E402
    plot_barrier_bands,
    plot_barrier_values,
    plot_methods,
    plot_rollouts,
    weight_ranks,
)


@pytest.fixture(autouse=True)
def _close():
    yield
    plt.close("all")


def _reference_ranks(w: np.ndarray) -> np.ndarray:
    """Mean rank of each value by a loop over the samples, scaled to [0, 1]."""
    out = np.empty(len(w))
    for i, v in enumerate(w):
        below, equal = np.sum(w < v), np.sum(w == v)
        out[i] = (below + (equal - 1) / 2) / (len(w) - 1)
    return out


@pytest.mark.parametrize(
    "w",
    [
        np.exp(-np.linspace(0.0, 700.0, 50)),
        np.array([0.0, 0.0, 1e-300, 0.5, 0.5, 1.0]),
        np.random.default_rng(0).random(33),
    ],
)
def test_weight_ranks_match_a_loop(w) -> None:
    np.testing.assert_allclose(weight_ranks(w), _reference_ranks(w))


def _traj(x: torch.Tensor, dt: float = 0.1) -> Trajectory:
    B, T1, n = x.shape
    zeros = torch.zeros(B, T1 - 1, 2)
    return Trajectory(t=torch.arange(T1) * dt, x=x, x_hat=x, u_nom=zeros, u=zeros, h=None,
                      status=None, failed=torch.zeros(B, dtype=torch.bool),
                      fail_step=torch.full((B,), -1))  # fmt: skip


def test_rollouts_spread_over_the_colour_scale() -> None:
    K, H = 200, 10
    rollouts = torch.randn(K, H + 1, 2).cumsum(1)
    weights = torch.exp(-torch.linspace(0.0, 600.0, K, dtype=torch.float64))  # as MPPI's do
    fig = plot_rollouts(rollouts, weights)
    ax = fig.axes[0]
    cmap = plt.get_cmap("viridis")
    colours = {tuple(np.round(to_rgba(line.get_color())[:3], 4)) for line in ax.lines[:K]}
    assert len(colours) > K // 2  # one colour per rank, not one for almost all
    levels = [to_rgba(line.get_color())[:3] for line in ax.lines[:K]]
    median = np.median([np.argmin([np.abs(np.array(cmap(q)[:3]) - c).sum()
                                   for q in np.linspace(0, 1, 101)]) for c in levels])  # fmt: skip
    assert 40 <= median <= 60


def test_barrier_bands_show_and_mark_the_deepest_violation() -> None:
    x = torch.zeros(3, 21, 2)
    x[:, :, 0] = torch.linspace(-3.0, 0.0, 21)  # every path ends at the ball's centre
    ball = Ball(center=[0.0, 0.0], radius=0.8)  # h = |p|^2 - 0.64: -0.64 at the centre
    fig = plot_barrier_bands({"scbf": _traj(x)}, [ball])
    ax = fig.axes[0]
    assert ax.get_ylim()[0] < -0.64
    labels = ax.get_legend_handles_labels()[1]
    assert any(label.startswith("lowest: -0.64 (scbf") for label in labels)


def test_barrier_bands_far_above_contact_are_in_view() -> None:
    x = torch.zeros(3, 21, 2)
    x[:, :, 0] = torch.linspace(4.0, 5.5, 21)  # h from 15 to 29.25: above the default view
    fig = plot_barrier_bands({"filter": _traj(x)}, [Ball(center=[0.0, 0.0], radius=1.0)])
    low, high = fig.axes[0].get_ylim()
    assert low <= 15.0 <= high


def test_the_rollouts_view_holds_the_executed_path_and_the_plan() -> None:
    rollouts = torch.randn(20, 6, 2, generator=torch.Generator().manual_seed(0)) * 0.1 + 5.0
    executed = torch.linspace(0.0, 5.0, 30).unsqueeze(-1).expand(30, 2)
    plan = torch.linspace(5.0, 8.0, 6).unsqueeze(-1).expand(6, 2)
    ax = plot_rollouts(rollouts, torch.ones(20), plan, executed=executed).axes[0]
    for lo, hi in (ax.get_xlim(), ax.get_ylim()):
        assert lo <= 0.0 and hi >= 8.0


def test_a_state_of_one_component_has_no_plane_to_draw() -> None:
    with pytest.raises(ValueError, match=r"index \(0, 1\) is outside the 1 components"):
        plot_methods({"a": _traj(torch.zeros(2, 5, 1))}, [], [])
    with pytest.raises(ValueError, match=r"index \(0, 1\) is outside the 1 components"):
        plot_rollouts(torch.zeros(4, 3, 1), torch.ones(4))


def test_barrier_values_mark_the_minimum() -> None:
    h = torch.tensor([[1.0, 0.5, 0.2], [1.0, -0.9, 0.3]])
    fig = plot_barrier_values(torch.tensor([0.0, 0.1, 0.2]), h)
    ax = fig.axes[0]
    assert ax.get_ylim()[0] < -0.9
    assert any(
        "lowest: -0.90 (scenario 1, t = 0.10 s)" in s for s in ax.get_legend_handles_labels()[1]
    )


def _outside(fig, ax) -> bool:
    fig.canvas.draw()
    legend = ax.get_legend().get_window_extent()
    box = ax.get_window_extent()
    return not legend.overlaps(box)


def test_legends_do_not_cover_the_workspace() -> None:
    x = torch.zeros(2, 11, 4)
    x[:, :, 0] = torch.linspace(0.0, 3.0, 11)
    obstacle = Ball(center=[1.0, 1.0], radius=0.5)
    fig = plot_methods({"a": _traj(x), "b": _traj(x + 0.1)}, [obstacle])
    assert _outside(fig, fig.axes[0])
    fig = plot_rollouts(torch.randn(20, 6, 2), torch.rand(20), torch.randn(6, 2),
                        barriers=[obstacle])  # fmt: skip
    assert _outside(fig, fig.axes[0])


@pytest.mark.parametrize("kind", ["empty", "all_nan", "one_nan_row"])
def test_barrier_figures_draw_what_is_finite(kind: str) -> None:
    """An empty batch, a batch whose states are all NaN and one NaN row among finite ones:
    the figures draw the finite values (the lowest marker only where there is one) and
    never fail."""
    x = torch.stack([torch.linspace(0.0, 1.0, 6), torch.zeros(6)], -1).expand(3, 6, 2).clone()
    if kind == "empty":
        x = x[:0]
    elif kind == "all_nan":
        x[:] = float("nan")
    else:
        x[1] = float("nan")
    traj = _traj(x)
    ball = Ball([2.0, 0.0], 0.5)
    fig = plot_barrier_bands({"a": traj, "b": _traj(x.clone())}, [ball])
    h = ball(x)
    plot_barrier_values(traj.t, h)
    marks = [ln for ax in fig.axes for ln in ax.lines if ln.get_label().startswith("lowest")]
    assert len(marks) == (1 if kind == "one_nan_row" else 0)


def test_figures_of_batches_without_a_finite_state(tmp_path) -> None:
    """An empty batch or every state NaN: figures framed around the origin (a reduction
    over no finite point raised), and an animation that fails leaves no figure open."""
    from torchcbf.viz import animate, plot_trajectories

    ball = Ball([0.5, 0.5], 0.2)
    for x in (torch.zeros(0, 4, 2), torch.full((2, 4, 2), float("nan"))):
        assert plot_trajectories(_traj(x), [ball]).axes
        animate(_traj(x), tmp_path / "a.gif", [ball])
    one = _traj(torch.zeros(1, 4, 2))
    plt.close("all")  # the figures above are the caller's
    with pytest.raises(FileNotFoundError):
        animate(one, tmp_path / "missing" / "a.gif")
    assert plt.get_fignums() == []
    with pytest.raises(ValueError, match="outside the 1 components"):
        plot_trajectories(_traj(torch.zeros(1, 4, 1)))


def test_empty_inputs_are_named() -> None:
    from torchcbf.viz import animate_methods

    with pytest.raises(ValueError, match="trajectories is empty"):
        plot_methods({})
    with pytest.raises(ValueError, match="trajectories is empty"):
        animate_methods({}, "x.gif")
    with pytest.raises(ValueError, match="barriers is empty"):
        plot_barrier_bands({"a": _traj(torch.zeros(1, 4, 2))}, [])
    with pytest.raises(ValueError, match="h is None"):
        plot_barrier_values(torch.arange(4.0), None)


def test_an_obstacle_out_of_view_or_undefined_somewhere_is_drawn_as_what_is_there() -> None:
    """Nothing of ``{h < 0}`` in view (``h >= 1`` everywhere) shades nothing; a barrier that
    is NaN somewhere shades its finite part; a plain function wrapping a float32 network is
    evaluated in its dtype."""
    from torchcbf.viz import draw_unsafe_set

    fig, ax = plt.subplots()
    draw_unsafe_set(ax, Ball([6.0, 0.0], 0.5), (-1.0, 1.0), (-1.0, 1.0), state_dim=2)
    assert not ax.collections
    nan_beyond = lambda x: torch.where(x[..., 0] > 0.5, torch.nan, x.norm(dim=-1) - 0.3)  # noqa: E731
    draw_unsafe_set(ax, nan_beyond, (-1.0, 1.0), (-1.0, 1.0), state_dim=2)
    assert ax.collections
    net = torch.nn.Linear(2, 1)  # float32
    draw_unsafe_set(ax, lambda x: net(x)[..., 0], (-1.0, 1.0), (-1.0, 1.0), state_dim=2)


def test_goals_are_drawn_in_the_plane_shown() -> None:
    from torchcbf.mppi import Reach
    from torchcbf.viz import plot_trajectories

    goal = Reach((1.0, 2.0, 3.0), 0.3, index=(0, 1, 2))
    x = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]])
    for index, want in (((0, 1), (1.0, 2.0)), ((0, 2), (1.0, 3.0)), ((1, 2), (2.0, 3.0))):
        fig = plot_trajectories(_traj(x), goals=[goal], index=index)
        (circle,) = fig.axes[0].patches
        assert circle.center == pytest.approx(want)
    fig = plot_trajectories(_traj(x), goals=[Reach((1.0, 2.0), 0.3)], index=(1, 2))
    assert not fig.axes[0].patches  # a goal on (x0, x1) has no place in the plane (x1, x2)


def test_barrier_figures_pass_over_minus_infinity() -> None:
    """A log barrier at contact (-inf): the lowest finite value is marked, the axis holds."""
    t = torch.arange(4) * 0.1
    h = torch.tensor([[[1.0], [0.5], [-math.inf], [0.2]]])
    fig = plot_barrier_values(t, h)
    (mark,) = [ln for ln in fig.axes[0].lines if ln.get_label().startswith("lowest")]
    assert mark.get_label().startswith("lowest finite: 0.20")


def test_rollouts_and_weights_of_other_counts_are_named() -> None:
    with pytest.raises(
        ValueError, match=r"weights \[K\]: got rollouts \(50, 11, 2\) and weights \(10,\)"
    ):
        plot_rollouts(torch.zeros(50, 11, 2), torch.ones(10))


def test_bad_figure_arguments_are_named(tmp_path) -> None:
    from torchcbf.viz import animate, barrier_traces, draw_unsafe_set

    fig, ax = plt.subplots()
    ball = Ball([0.0, 0.0], 0.5)
    for kw, message in (
        ({"state_dim": 4, "fill": [0.0, 0.0]}, "fill must have 4 entries"),
        ({"state_dim": 2, "index": (2, 3)}, r"index \(2, 3\) is outside the 2 components"),
        ({"resolution": 1}, "resolution must be an int >= 2"),
    ):
        with pytest.raises(ValueError, match=message):
            draw_unsafe_set(ax, ball, (-1.0, 1.0), (-1.0, 1.0), **kw)
    traj = _traj(torch.zeros(2, 5, 2))
    with pytest.raises(ValueError, match="frames must be an int >= 1"):
        animate(traj, tmp_path / "a.gif", frames=0)
    with pytest.raises(ValueError, match="barriers is empty"):
        barrier_traces(traj, [])
    with pytest.raises(ValueError, match=r"got h \(2, 5\), t \(3,\)"):
        plot_barrier_values(torch.arange(3.0), torch.zeros(2, 5))
