"""The reference scenarios: builders, closed-loop success, and the command line."""

from __future__ import annotations

import json

import pytest
import torch

from torchcbf.cli import main
from torchcbf.filters import FilterStatus
from torchcbf.scenarios import METHODS, mppi_cbf, reach_avoid, reach_avoid_spec


def test_reach_avoid_spec_success_check_matches_the_definition() -> None:
    """Robustness >= 0 exactly when every goal is reached in its window and the obstacle is
    never touched (SCENARIOS.md A's success rule), on hand-made paths."""
    spec = reach_avoid_spec().double()
    t = torch.arange(101, dtype=torch.float64) * 0.1
    good = torch.zeros(101, 2, dtype=torch.float64)
    good[:35] = torch.tensor([4.0, 4.0], dtype=torch.float64) * (t[:35, None] / 3.4).clamp(max=1.0)
    good[:35, 1] += 0.0
    good[35:] = torch.tensor([6.0, 9.0])
    good[50:] = torch.tensor([4.0, 1.0])
    # detour around the obstacle at (3, 3): the straight line would cross it
    good[:35, 0] += 1.2 * torch.sin(torch.pi * t[:35] / 3.4)
    late = good.clone()
    late[35:50] = torch.tensor([0.0, 0.0])  # misses the g2 window
    through = good.clone()
    through[20] = torch.tensor([3.1, 3.0])  # touches the obstacle once
    rob = spec.robustness(torch.stack([good, late, through]), t)
    assert rob[0] >= 0 and rob[1] < 0 and rob[2] < 0


def test_reach_avoid_small_closed_loop() -> None:
    scenario = reach_avoid(num_seeds=2, num_samples=2000, horizon=50)
    traj, m = scenario.run(progress=False)
    assert traj.x.shape == (2, 101, 2)
    assert not bool(m["collision"].any())
    assert int(m["spec_satisfied"].sum()) >= 1


@pytest.mark.slow
def test_reach_avoid_paper_sizes() -> None:
    """SCENARIOS.md A at the paper's sizes: at least 9 of 10 seeds satisfy the specification."""
    scenario = reach_avoid(num_seeds=10, num_samples=10_000, horizon=50)
    _, m = scenario.run(progress=False)
    assert int(m["spec_satisfied"].sum()) >= 9
    assert not bool(m["collision"].any())


@pytest.mark.parametrize("method", METHODS)
def test_mppi_cbf_builders_run(method: str) -> None:
    scenario = mppi_cbf(method, num_seeds=3, num_samples=64, horizon=10)
    scenario.steps = 20
    traj, m = scenario.run(progress=False)
    assert traj.x.shape == (3, 21, 4) and torch.isfinite(traj.x).all()
    assert (traj.status is not None) == (method != "mppi")
    if traj.status is not None:
        assert set(traj.status.unique().tolist()) <= {int(s) for s in FilterStatus}
    assert m["collision"].shape == (3,) and m["goal0_reached"].shape == (3,)


def test_mppi_cbf_rejects_unknown_method() -> None:
    with pytest.raises(ValueError, match="method must be one of"):
        mppi_cbf("cbf")


def test_cli_writes_metrics_and_figures(tmp_path, capsys) -> None:
    code = main(
        [
            "reach-avoid",
            "--seeds",
            "2",
            "--samples",
            "256",
            "--horizon",
            "20",
            "--out",
            str(tmp_path),
            "--no-progress",
        ]
    )
    assert code == 0
    data = json.loads((tmp_path / "metrics.json").read_text())
    summary = data["reach-avoid"]["summary"]
    assert summary["collision"]["n"] == 2 and "spec_satisfied" in summary
    for fig in data["reach-avoid"]["figures"]:
        assert (tmp_path / fig.split("/")[-1]).stat().st_size > 1000
    assert (tmp_path / "reach_avoid.gif").exists()
    assert "reach-avoid" in capsys.readouterr().out
