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


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_mppi_cbf_barrier_scale_and_rectify_gain(dtype: torch.dtype) -> None:
    """At rest (v = 0) h_e = c_i (L_f b_i + k b_i) = c_i k b_i(x0), b_i by hand."""
    scales, k = [0.5, 1.0, 0.01, 2.0, 0.25], 3.0
    scenario = mppi_cbf("scbf", num_seeds=2, rectify_gain=k, barrier_scale=scales, dtype=dtype)
    scenario.steps = 1
    traj, _ = scenario.run(progress=False)
    centers = [(1, 2), (3, 2), (2, 5), (-1, 1), (0.5, -1)]
    axes = [(0.5, 1.5), (0.75, 2.0), (2.0, 0.25), (1.0, 0.75), (0.75, 0.5)]
    b0 = [
        (cx / a1) ** 2 + (cy / a2) ** 2 - 1
        for (cx, cy), (a1, a2) in zip(centers, axes, strict=True)
    ]
    expected = torch.tensor([c * k * b for c, b in zip(scales, b0, strict=True)], dtype=dtype)
    rtol = 1e-10 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(traj.h[:, 0], expected.expand(2, 5), rtol=rtol, atol=0.0)


@pytest.mark.parametrize("bad", [0.0, -1.0, [1.0, 1.0], [1.0, 1.0, 1.0, 1.0, float("nan")]])
def test_mppi_cbf_rejects_bad_barrier_scale(bad) -> None:
    with pytest.raises(ValueError, match="barrier_scale"):
        mppi_cbf("scbf", num_seeds=1, barrier_scale=bad)


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
