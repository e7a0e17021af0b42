"""The standard figures of a scenario run: the paths, the MPPI rollouts at the snapshot steps
and an animation; with several variants (scenario B's methods) one colour per variant and
the closest-obstacle bands over time. A registered scenario without figures of its own gets
these (:attr:`ScenarioEntry.figures`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from torchcbf import _io
from torchcbf.scenarios.base import Scenario
from torchcbf.sim import Trajectory


def save(fig: Any, path: Path) -> Path:
    """Save a matplotlib figure atomically (tight bounding box) and close it."""
    return _io.save_figure(fig, path, bbox_inches="tight")


def save_animation(make: Callable[..., Any], path: Path, *args: Any, **kwargs: Any) -> Path:
    """``make(args[0], tmp, *args[1:], **kwargs)`` writes an animation; renamed to ``path``."""
    with _io.atomic_path(path) as tmp:
        make(args[0], tmp, *args[1:], **kwargs)
    return path


def rollout_figures(
    traj: Trajectory, scenario: Scenario, stem: Path, label: str, **view: Any
) -> list[Path]:
    """The MPPI rollouts of the first seed at each snapshot step: ``{stem}_rollouts_t{k}.png``."""
    from torchcbf.viz import plot_rollouts

    paths = []
    for step, snap in traj.planner.items():
        if getattr(snap, "rollouts", None) is None:
            continue
        fig = plot_rollouts(
            snap.rollouts[0],
            snap.rollout_weights[0],
            snap.best_states[0],
            barriers=scenario.barriers,
            goals=scenario.goals,
            executed=traj.x[0, : step + 1],
            title=f"{label}: MPPI rollouts at t = {float(traj.t[step]):.2f} s",
            plan_label="lowest-cost rollout",
            **view,
        )
        paths.append(save(fig, stem.parent / f"{stem.name}_rollouts_t{step}.png"))
    return paths


def standard_figures(
    trajectories: Mapping[str, Trajectory],
    scenario: Scenario,
    out: Path,
    *,
    stem: str,
    title: str,
    gif: bool = True,
    first_seed: int = 0,
    view: Mapping[str, Any] | None = None,
    compare: bool | None = None,
) -> list[Path]:
    """Figures of a finished run into ``out``, named ``{stem}_*``: a single run gives the
    paths (``{stem}_trajectories.png``), its rollouts and ``{stem}.gif``; a comparison of
    variants (``compare``; default: more than one trajectory) gives the paths in one colour
    per variant, the closest-obstacle bands (``{stem}_barriers.png``), each variant's
    rollouts (``{stem}_{variant}_rollouts_*``) and an animation of all of them. A state of
    one component has no plane to draw paths in: it gets the bands alone."""
    from torchcbf.viz import (
        animate,
        animate_methods,
        plot_barrier_bands,
        plot_methods,
        plot_trajectories,
    )

    view = dict(view or {})
    out = Path(out)
    barriers, goals = list(scenario.barriers), list(scenario.goals)
    first = next(iter(trajectories.values()), None)
    n = first.x.shape[0] if first is not None else 0

    def bands() -> list[Path]:
        if not barriers:
            return []
        title_bands = f"{title}: closest obstacle over time ({n} seeds)"
        figure = plot_barrier_bands(trajectories, barriers, title=title_bands)
        return [save(figure, out / f"{stem}_barriers.png")]

    if first is not None and first.x.shape[-1] < 2 and "index" not in view:
        return bands()
    if not (len(trajectories) > 1 if compare is None else compare):
        ((name, traj),) = trajectories.items()
        figures = [
            save(
                plot_trajectories(traj, barriers, goals, title=title, **view),
                out / f"{stem}_trajectories.png",
            )
        ]
        figures += rollout_figures(
            traj, scenario, out / stem, f"{title}, seed {first_seed}", **view
        )
        if gif:
            figures.append(save_animation(animate, out / f"{stem}.gif", traj, barriers, goals))
        return figures
    figures = [
        save(
            plot_methods(
                trajectories, barriers, goals, title=f"{title}: {n} seeds per method", **view
            ),
            out / f"{stem}_trajectories.png",
        )
    ]
    figures += bands()
    for name, traj in trajectories.items():
        label = f"{name}, seed {first_seed}"
        figures += rollout_figures(traj, scenario, out / f"{stem}_{name}", label, **view)
    if gif:
        figures.append(
            save_animation(
                animate_methods,
                out / f"{stem}.gif",
                trajectories,
                barriers,
                goals,
                title=f"{title}, seed {first_seed}",
                **view,
            )
        )
    return figures
