"""The scenario registry: a scenario registered from outside the package gets the command
line, sweeps and tuning; entries are checked when they are made."""

from __future__ import annotations

import json
import sys
import textwrap
from dataclasses import dataclass

import pytest

from torchcbf.cli import main
from torchcbf.scenarios import (
    Column,
    Dimension,
    ScenarioEntry,
    get,
    register,
    scenarios,
    unregister,
)
from torchcbf.sweep import run_sweep, search_space

# A user's own scenario: a single integrator driven to a goal by a proportional controller
# of gain ``gain`` and filtered by a CBF keeping it out of a disc, in a module of its own.
USER_MODULE = textwrap.dedent(
    """
    from dataclasses import dataclass

    import torch

    from torchcbf.barriers import Ball
    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.filters import SafetyFilter
    from torchcbf.scenarios import Column, Dimension, Scenario, ScenarioEntry, register
    from torchcbf.sim import Goal


    @dataclass(frozen=True)
    class Params:
        gain: float = 1.0
        alpha: float = 1.0


    def build(p, *, num_seeds, seed, device, dtype=None):
        dtype = dtype or torch.float64
        model = SingleIntegrator(2, u_min=-2.0, u_max=2.0).to(device=device, dtype=dtype)
        disc = Ball(torch.tensor([1.0, 0.05]), 0.3).to(device=device, dtype=dtype)
        goal = torch.tensor([2.0, 0.0], device=device, dtype=dtype)
        gen = torch.Generator().manual_seed(seed)
        x0 = 0.05 * torch.randn(num_seeds, 2, generator=gen, dtype=dtype).to(device)
        return Scenario(
            name="user-disc",
            dynamics=model,
            x0=x0,
            steps=60,
            dt=0.05,
            seeds=torch.arange(seed, seed + num_seeds),
            nominal=lambda x, t: p.gain * (goal - x),
            safety_filter=SafetyFilter(model, [disc], alpha=p.alpha),
            barriers=[disc],
            metric_goals=[Goal((2.0, 0.0), 0.3)],
            params={"gain": p.gain, "alpha": p.alpha},
        )


    ENTRY = register(
        ScenarioEntry(
            name="user-disc",
            build=build,
            params=Params,
            description="A user's scenario: a filtered single integrator past a disc.",
            search_space=(Dimension("gain", "float", 0.5, 4.0, log=True),),
            columns=(Column("goal [95% CI]", "goal_reached"), Column("min h", "min_h", "min")),
            num_seeds=4,
        )
    )
    """
)


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    (tmp_path / "user_scenario_pkg.py").write_text(USER_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "user_scenario_pkg"
    sys.modules.pop("user_scenario_pkg", None)
    if "user-disc" in scenarios():
        unregister("user-disc")


def test_a_user_scenario_runs_from_the_command_line(user_module, tmp_path, capsys) -> None:
    out = tmp_path / "run"
    code = main(["--import", user_module, "user-disc", "--seeds", "3", "--set", "gain=2",
                 "--out", str(out), "--no-progress", "--no-gif"])  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert "goal [95% CI]" in text and "3 seeds from 0, gain=2.0" in text
    data = json.loads((out / "metrics.json").read_text())
    result = data["results"]["user-disc"]
    assert result["params"] == {"gain": 2.0, "alpha": 1.0}
    assert result["summary"]["collision"]["count"] == 0  # the filter holds
    assert (out / "user_disc_trajectories.png").exists()  # the standard figures


def test_a_user_scenario_sweeps_and_tunes(user_module, tmp_path, capsys) -> None:
    code = main(["--import", user_module, "sweep", "user-disc", "--grid", "gain=0.5,2",
                 "--seeds", "2", "--out", str(tmp_path / "sweep"), "--no-progress"])  # fmt: skip
    assert code == 0
    assert "held fixed: alpha=1.0" in capsys.readouterr().out
    entry = get("user-disc")
    rows = run_sweep(entry, {"alpha": [0.5, 2.0]}, num_seeds=2, progress=False)
    assert [r["alpha"] for r in rows] == [0.5, 2.0] and all(r["status"] == "ok" for r in rows)
    assert [d.name for d in search_space(entry)] == ["gain"]
    optuna = pytest.importorskip("optuna")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    from torchcbf.sweep import tune

    result = tune(entry, trials=2, num_seeds=2, progress=False)
    assert result["scenario"] == "user-disc" and len(result["trials"]) == 2
    assert result["recommended"]["source"] in ("best", "default")


@dataclass(frozen=True)
class _Params:
    k: float = 1.0


def _build(p, *, num_seeds, seed, device, dtype=None):
    raise AssertionError("not built in these tests")


def test_entries_are_checked_when_made() -> None:
    # a name becomes file and folder names of every run: "my/robot" failed after the run
    for name in ("my/robot", "../x", ".hidden", "two words", ""):
        with pytest.raises(ValueError, match="must be a word"):
            ScenarioEntry(name=name, build=_build, params=_Params)
    with pytest.raises(TypeError, match="dataclass"):
        ScenarioEntry(name="x", build=_build, params=dict)
    with pytest.raises(ValueError, match="not a field"):
        ScenarioEntry(name="x", build=_build, params=_Params, options={"gain": "gain"})
    with pytest.raises(ValueError, match="not a field"):
        ScenarioEntry(
            name="x", build=_build, params=_Params, search_space=(Dimension("g", "float", 0, 1),)
        )
    with pytest.raises(ValueError, match="kind"):
        Column("c", "m", "median")
    with pytest.raises(ValueError, match="num_seeds must be a positive int"):
        ScenarioEntry(name="x", build=_build, params=_Params, num_seeds=0)
    with pytest.raises(ValueError, match=r"demo\['kk'\] names 'kk', which is not a field"):
        ScenarioEntry(name="x", build=_build, params=_Params, demo={"kk": 2.0})
    with pytest.raises(ValueError, match=r"demo\['num_seeds'\] must be a positive int"):
        ScenarioEntry(name="x", build=_build, params=_Params, demo={"num_seeds": 0, "k": 2.0})
    with pytest.raises(ValueError, match="dimension 'k': low 4.0 > high 0.5"):
        Dimension("k", "float", 4.0, 0.5)
    with pytest.raises(ValueError, match="log scale: low > 0"):
        Dimension("k", "float", 0.0, 1.0, log=True)
    entry = ScenarioEntry(name="x-test", build=_build, params=_Params)
    with pytest.raises(ValueError, match="unknown parameter"):
        entry.parameters(gain=2.0)
    register(entry)
    try:
        register(entry)  # the same entry again: nothing happens
        with pytest.raises(ValueError, match="already registered"):
            register(ScenarioEntry(name="x-test", build=_build, params=_Params, num_seeds=3))
    finally:
        unregister("x-test")


def test_names_variants_and_reloads() -> None:
    with pytest.raises(ValueError, match="is a command of torchcbf"):
        ScenarioEntry(name="sweep", build=_build, params=_Params)
    with pytest.raises(ValueError, match="needs its values in choices"):
        ScenarioEntry(name="x", build=_build, params=_Params, variant="k")
    register(ScenarioEntry(name="x-reload", build=_build, params=_Params))
    try:  # the module registering it imported again: new function objects, same names
        import importlib

        module = importlib.import_module(__name__)
        register(ScenarioEntry(name="x-reload", build=module._build, params=module._Params))
    finally:
        unregister("x-reload")


def test_set_of_the_variant_runs_that_variant(tmp_path, capsys, monkeypatch) -> None:
    from torchcbf.scenarios import unicycle_mppi_cbf

    monkeypatch.setattr(unicycle_mppi_cbf, "STEPS", 20)  # a short run: no option for its length
    args = ["mppi-cbf", "--seeds", "1", "--samples", "16", "--horizon", "4", "--no-progress",
            "--no-gif"]  # fmt: skip
    assert main([*args, "--set", "method=scbf", "--out", str(tmp_path / "a")]) == 0
    data = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert set(data["results"]) == {"mppi-cbf/default/scbf"}
    # one method still gets the comparison figures, named after it
    assert (tmp_path / "a" / "mppi_cbf_default_barriers.png").exists()
    settings = json.loads((tmp_path / "a" / "run.json").read_text())["settings"]["mppi-cbf"]
    assert settings["variants"] == ["scbf"] and settings["params"]["num_samples"] == 16
    assert settings["params"]["rectify_gain"] is None  # defaults recorded too
    assert (
        main([*args, "--set", "method=scbf", "--methods", "mppi", "--out", str(tmp_path / "b")])
        == 2
    )
    # an option given twice over, or a method named twice, is refused before any run
    for extra, message in (
        (["--set", "num_samples=20", "--methods", "scbf"], "give --samples or --set num_samples"),
        (["--set", "beta=1", "--set", "beta=2", "--methods", "scbf"], "--set beta given twice"),
        (["--methods", "scbf,scbf"], "--methods names scbf more than once"),
    ):
        assert main([*args, *extra, "--out", str(tmp_path / "c")]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "c").exists()


def test_the_reference_scenarios_are_registered() -> None:
    assert {"reach-avoid", "mppi-cbf", "arm-reach"} <= set(scenarios())
    b = get("mppi-cbf")
    assert b.variant == "method" and b.defaults()["num_samples"] == 20_000
    with pytest.raises(ValueError, match="method must be one of"):
        b.make(method="nope", num_seeds=1)
    with pytest.raises(ValueError, match="scenario must be one of"):
        get("nope")


@pytest.mark.slow
def test_the_demo_runs_every_scenario_with_demo_sizes(tmp_path, capsys) -> None:
    """``torchcbf demo`` (the README's first command) at tiny sizes: the registered entries'
    demo sizes swapped for tiny ones through the public registry."""
    import dataclasses

    originals = {n: e for n, e in scenarios().items() if e.demo is not None}
    assert set(originals) == {"reach-avoid", "mppi-cbf"}
    tiny = {"num_seeds": 1, "num_samples": 16, "horizon": 4}
    try:
        for entry in originals.values():
            register(dataclasses.replace(entry, demo={**entry.demo, **tiny}), replace=True)
        assert main(["demo", "--out", str(tmp_path), "--no-gif", "--no-progress"]) == 0
    finally:
        for entry in originals.values():
            register(entry, replace=True)
    data = json.loads((tmp_path / "metrics.json").read_text())
    methods = get("mppi-cbf").choices["method"]
    assert set(data["results"]) == {"reach-avoid"} | {f"mppi-cbf/default/{m}" for m in methods}
    assert "The paper's size of scenario B" in capsys.readouterr().out


def test_the_arm_scenario_records_its_time_to_the_goal() -> None:
    """Each seed's first time within the reach tolerance (nan where never): what a sweep's
    time_to_goal_s averages, so a tune can break a tie of success rates by it."""
    from torchcbf.scenarios import scenarios as registered
    from torchcbf.sweep.evaluate import evaluate

    entry = registered()["arm-reach"]
    row = evaluate(scenario=entry, params={"steps": 200}, num_seeds=3, seed=0,
                   device="cpu", threads=1)  # fmt: skip
    assert row["goal_count"] >= 1
    assert row["time_to_goal_s"] is not None and 0.0 < row["time_to_goal_s"] <= 200 * 0.02


@dataclass(frozen=True)
class _WallParams:
    speed: float = 1.0


def _wall(p, *, num_seeds, seed, device, dtype=None):
    """A one-component state driven toward a wall at x = 1."""
    import torch

    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.scenarios import Scenario

    model = SingleIntegrator(1, u_min=-2.0, u_max=2.0).double()
    x0 = torch.zeros(num_seeds, 1, dtype=torch.float64)
    return Scenario(name="x-wall", dynamics=model, x0=x0, steps=5, dt=0.05,
                    seeds=torch.arange(seed, seed + num_seeds),
                    nominal=lambda x, t: p.speed * torch.ones_like(x),
                    barriers=[lambda x: 1.0 - x[..., 0]])  # fmt: skip


def _failing_figures(*args, **kwargs):
    raise RuntimeError("no display")


@pytest.mark.parametrize("figures", [None, _failing_figures])
def test_a_run_keeps_its_metrics_whatever_its_figures(figures, tmp_path, capsys) -> None:
    """A state of one component gets the bands alone; figures that fail leave the results
    written and the exit code 1."""
    register(ScenarioEntry(name="x-wall", build=_wall, params=_WallParams, figures=figures))
    try:
        code = main(["x-wall", "--seeds", "2", "--out", str(tmp_path), "--no-progress"])
    finally:
        unregister("x-wall")
    data = json.loads((tmp_path / "metrics.json").read_text())
    result = data["results"]["x-wall"]
    assert result["summary"]["collision"]["n"] == 2
    if figures is None:
        assert code == 0 and [p.split("/")[-1] for p in result["figures"]] == [
            "x_wall_barriers.png"
        ]
    else:
        assert code == 1 and result["figures_failed"] == "RuntimeError: no display"
        assert "the figures of x-wall failed: RuntimeError: no display" in capsys.readouterr().err
