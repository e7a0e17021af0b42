"""Optuna tuning and the Ray engine: reproducible studies, disjoint seeds, and Ray giving
exactly the local numbers."""

from __future__ import annotations

import json
from typing import Any

import pytest

from torchcbf.cli import main
from torchcbf.scenarios import scenarios
from torchcbf.sweep import recommend, run_sweep, search_space

SMALL = {"num_samples": 32}


def _without_wall(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in row.items() if k != "wall_s"} for row in rows]


def test_search_spaces_name_parameters() -> None:
    for name, entry in scenarios().items():
        accepted = entry.defaults()
        for d in entry.search_space:
            assert d.keyword in accepted, (name, d.name)
        assert search_space(name)  # something to search today
    assert {d.name for d in search_space("reach-avoid")} == {
        "num_samples", "horizon", "temperature", "noise_sigma", "control_cost_weight"
    }  # fmt: skip
    names = [d.name for d in search_space("mppi-cbf", fixed={"rectify_gain": 5.0})]
    assert "rectify_gain" not in names and {"control_weight_omega", "noise_sigma"} <= set(names)
    filter_only = [d.name for d in search_space("mppi-cbf", fixed={"method": "scbf"})]
    assert "noise_sigma" not in filter_only and "rectify_gain" in filter_only
    planner_only = [d.name for d in search_space("mppi-cbf", fixed={"method": "mppi"})]
    assert "rectify_gain" not in planner_only and "noise_sigma" in planner_only
    cbfkit = [d.name for d in search_space("mppi-cbf", fixed={"config": "cbfkit"})]
    assert "barrier_scale" not in cbfkit and "rectify_gain" in cbfkit  # its form fixes them
    with pytest.raises(ValueError, match="unknown parameter"):
        search_space("reach-avoid", ["nope"])
    with pytest.raises(ValueError, match="every dimension is fixed"):
        search_space("reach-avoid", ["horizon"], fixed={"horizon": 8})


def _tune(**kwargs: Any) -> dict[str, Any]:
    optuna = pytest.importorskip("optuna")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    from torchcbf.sweep import tune

    options = {"trials": 4, "num_seeds": 2, "fixed": SMALL, "params": ["horizon"], "batch": 2}
    return tune("reach-avoid", progress=False, **{**options, **kwargs})


@pytest.fixture(scope="module")
def study() -> dict[str, Any]:
    return _tune()


def test_tune_is_reproducible_and_reports_best_and_default(study) -> None:
    a, b = study, _tune()
    assert _without_wall(a["trials"]) == _without_wall(b["trials"])
    assert len(a["trials"]) == 4
    objectives = [r["objective"] for r in a["trials"]]
    assert a["best"]["objective"] == max(objectives)
    best_row = a["trials"][a["best"]["trial"]]
    assert a["best"]["arguments"] == {"num_samples": 32, "horizon": best_row["horizon"]}
    assert all(r["first_seed"] == 10_000 for r in a["trials"])  # tuning seeds
    assert a["evaluation"]["best"]["first_seed"] == 0  # evaluation seeds
    assert a["default"]["arguments"] == {
        "num_samples": 32, "horizon": 50, "temperature": 0.03, "noise_sigma": 4.0,
        "control_cost_weight": 0.1,
    }  # fmt: skip
    assert a["evaluation"]["default"]["num_samples"] == 32
    assert "horizon" not in a["evaluation"]["default"]  # the builder's own default
    c = _tune(sampler_seed=1, trials=2)
    assert [r["horizon"] for r in c["trials"]] != [r["horizon"] for r in a["trials"][:2]]


def test_tune_rejects_overlapping_seeds() -> None:
    with pytest.raises(ValueError, match="overlap"):
        _tune(seed=0, eval_seed=1)


@pytest.mark.parametrize("flag", ["--seed", "--eval-seed", "--sampler-seed"])
@pytest.mark.parametrize("value", ["-1", str(2**32)])
def test_cli_refuses_seeds_outside_the_noise_streams(flag, value, capsys) -> None:
    """The noise streams are 32-bit: 2^32 would be seed 0 again (a held-out evaluation on
    the tuning seeds), -1 would be 2^32 - 1."""
    with pytest.raises(SystemExit) as exit_info:
        main(["tune", "reach-avoid", flag, value, "--trials", "1", "--no-progress"])
    assert exit_info.value.code == 2
    assert f"argument {flag}: a seed lies in [0, 2^32)" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["sweep", "tune"])
def test_an_address_where_no_ray_cluster_answers_is_refused_before_any_work(
    command, tmp_path, capsys
) -> None:
    """Ray retries such an address for minutes; the folder would be taken meanwhile."""
    pytest.importorskip("ray")
    out = tmp_path / "run"
    extra = ["--grid", "num_samples=32"] if command == "sweep" else ["--trials", "1"]
    args = [command, "reach-avoid", *extra, "--engine", "ray", "--address", "127.0.0.1:1"]
    assert main([*args, "--out", str(out), "--no-progress"]) == 2
    assert "no Ray cluster answers at 127.0.0.1:1" in capsys.readouterr().err
    assert not out.exists()


def test_cli_tune_writes_best_json_and_study(tmp_path, capsys) -> None:
    pytest.importorskip("optuna")
    code = main(
        ["tune", "reach-avoid", "--trials", "2", "--seeds", "2", "--set", "num_samples=32",
         "--params", "horizon", "--out", str(tmp_path), "--no-progress"]
    )  # fmt: skip
    assert code == 0
    best = json.loads((tmp_path / "best.json").read_text())
    assert set(best) >= {"best", "default", "evaluation", "space", "run", "tuning_seeds"}
    assert best["tuning_seeds"] == {"first": 10_000, "count": 2}
    assert (tmp_path / "study.csv").read_text().count("\n") == 3  # header + 2 trials
    assert (tmp_path / "study.png").exists()
    out = capsys.readouterr().out
    assert "default configuration" in out and "recommended: the " in out
    assert best["recommended"]["source"] in ("best", "default")
    assert best["evaluation_seeds"] == {"first": 0, "count": 4}  # twice the tuning seeds


def test_recommend_keeps_the_default_unless_the_best_beats_it() -> None:
    ok = {"status": "ok"}
    better = {"best": {**ok, "objective": 0.9}, "default": {**ok, "objective": 0.5}}
    worse = {"best": {**ok, "objective": 0.0}, "default": {**ok, "objective": 1.0}}
    tie = {"best": {**ok, "objective": 0.5}, "default": {**ok, "objective": 0.5}}
    assert recommend(better, {"a": 1}, {"a": 0})["source"] == "best"
    kept = recommend(worse, {"a": 1}, {"a": 0})
    assert kept["source"] == "default" and kept["arguments"] == {"a": 0}
    assert "not better than the default" in kept["reason"]
    assert recommend(tie, {"a": 1}, {"a": 0})["source"] == "default"
    assert (
        recommend({"best": None, "default": better["default"]}, None, {"a": 0})["source"]
        == "default"
    )


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.mark.slow  # a local Ray cluster: 7 s to start
def test_ray_sweep_equals_local(ray_cluster) -> None:
    grid = {"num_samples": [32, 64], "horizon": [8]}
    local = run_sweep("reach-avoid", grid, num_seeds=2, seed=3, progress=False)
    remote = run_sweep("reach-avoid", grid, num_seeds=2, seed=3, engine="ray", progress=False)
    assert _without_wall(remote) == _without_wall(local)


@pytest.mark.slow  # a local Ray cluster: 7 s to start
def test_ray_tune_equals_local(ray_cluster, study) -> None:
    local = study
    remote = _tune(engine="ray")
    assert _without_wall(remote["trials"]) == _without_wall(local["trials"])
    assert remote["best"] == local["best"]


@pytest.mark.slow  # a local Ray cluster: 7 s to start
def test_cli_sweep_on_ray(ray_cluster, tmp_path) -> None:
    args = ["sweep", "reach-avoid", "--grid", "num_samples=32", "--grid", "horizon=8",
            "--seeds", "2", "--no-progress"]  # fmt: skip
    assert main([*args, "--engine", "ray", "--out", str(tmp_path / "ray")]) == 0
    assert main([*args, "--out", str(tmp_path / "local")]) == 0
    rows = [json.loads((tmp_path / d / "sweep.json").read_text())["rows"] for d in ("ray", "local")]
    assert _without_wall(rows[0]) == _without_wall(rows[1])


def _fails_on_long_horizons(**kwargs: Any) -> dict[str, Any]:
    """``evaluate``, raising for a horizon of 40 steps or more (the default runs)."""
    from torchcbf.sweep.evaluate import evaluate

    horizon = kwargs["params"].get("horizon")
    if horizon is not None and horizon >= 40:
        raise RuntimeError(f"boom at horizon {horizon}")
    return evaluate(**kwargs)


def _fails_at_48(**kwargs: Any) -> dict[str, Any]:
    from torchcbf.sweep.evaluate import evaluate

    if kwargs["params"].get("num_samples") == 48:
        raise RuntimeError("boom at 48 samples")
    return evaluate(**kwargs)


def test_a_failing_trial_is_recorded_and_the_study_goes_on(monkeypatch, tmp_path) -> None:
    import sys

    monkeypatch.setattr(sys.modules["torchcbf.sweep.tune"], "evaluate", _fails_on_long_horizons)
    result = _tune(out=tmp_path)
    status = {r["trial"]: r["status"] for r in result["trials"]}
    assert len(status) == 4 and set(status.values()) == {"ok", "failed"}
    for row in result["trials"]:
        if row["status"] == "failed":
            assert row["error"] == f"RuntimeError: boom at horizon {row['horizon']}"
            assert "objective" not in row
    assert result["failed_trials"] == [t for t, s in status.items() if s == "failed"]
    assert result["best"]["trial"] in [t for t, s in status.items() if s == "ok"]
    assert (tmp_path / "study.csv").read_text().count("failed") == len(result["failed_trials"])


def _always_fails(**kwargs: Any) -> dict[str, Any]:
    raise RuntimeError("boom")


def test_cli_tune_whose_every_trial_failed_exits_1(monkeypatch, tmp_path, capsys) -> None:
    """Every trial and the default fail: exit code 1, and nothing is recommended."""
    import sys

    pytest.importorskip("optuna")
    monkeypatch.setattr(sys.modules["torchcbf.sweep.tune"], "evaluate", _always_fails)
    code = main(
        ["tune", "reach-avoid", "--trials", "2", "--seeds", "2", "--set", "num_samples=32",
         "--params", "horizon", "--out", str(tmp_path), "--no-progress"]
    )  # fmt: skip
    assert code == 1
    out = capsys.readouterr().out
    assert "every trial failed" in out and "recommended: nothing" in out
    recommended = json.loads((tmp_path / "best.json").read_text())["recommended"]
    assert recommended["source"] == "none" and recommended["arguments"] is None


@pytest.mark.parametrize(
    ("first", "count"), [("--seed", "--seeds"), ("--eval-seed", "--eval-seeds")]
)
def test_cli_refuses_seeds_that_pass_2_to_the_32(first, count, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["tune", "reach-avoid", first, str(2**32 - 2), count, "3", "--no-progress"])
    assert exit_info.value.code == 2
    assert "pass the bounds [0, 2^32 - 1]" in capsys.readouterr().err


@pytest.mark.slow  # a local Ray cluster: 7 s to start
def test_ray_records_a_failing_point_and_runs_the_rest(ray_cluster, monkeypatch) -> None:
    import sys

    ray_cluster.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    monkeypatch.setattr("torchcbf.sweep.sweep.evaluate", _fails_at_48)
    grid = {"num_samples": [32, 48, 64], "horizon": [8]}
    remote = run_sweep("reach-avoid", grid, num_seeds=2, engine="ray", progress=False)
    local = run_sweep("reach-avoid", grid, num_seeds=2, progress=False)
    assert [r["status"] for r in remote] == ["ok", "failed", "ok"]
    assert remote[1]["error"] == "RuntimeError: boom at 48 samples"
    assert _without_wall(remote) == _without_wall(local)


def _fake_evaluate(scenario, params, *, num_seeds, seed, device="cpu", threads=1):
    """A fast stand-in for ``evaluate``: an objective that depends on every parameter."""
    score = -abs(params.get("horizon", 50) - 33) - abs(params.get("num_samples", 10) - 900) / 100
    return {**params, "num_seeds": num_seeds, "first_seed": seed, "objective": score}


def test_tune_cut_between_two_parameters_resumes_as_if_never_cut(monkeypatch, tmp_path) -> None:
    optuna = pytest.importorskip("optuna")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    import sys

    from torchcbf.sweep import tune
    from torchcbf.sweep.tune import Dimension

    monkeypatch.setattr(sys.modules["torchcbf.sweep.tune"], "evaluate", _fake_evaluate)
    options = {"trials": 6, "num_seeds": 2, "batch": 2, "progress": False}
    reference = tune("reach-avoid", out=tmp_path / "reference", **options)
    original = Dimension.suggest

    def cut(self, trial):
        if trial.number == 3 and self.name == "horizon":  # num_samples drawn, horizon not
            raise KeyboardInterrupt
        return original(self, trial)

    monkeypatch.setattr(Dimension, "suggest", cut)
    with pytest.raises(KeyboardInterrupt):
        tune("reach-avoid", out=tmp_path / "run", **options)
    monkeypatch.setattr(Dimension, "suggest", original)
    resumed = tune("reach-avoid", out=tmp_path / "run", resume=True, **options)
    assert resumed["trials"] == reference["trials"]
    assert resumed["best"] == reference["best"]
    assert len({(r["num_samples"], r["horizon"]) for r in resumed["trials"]}) == 6


def test_tune_checks_its_fixed_values_before_any_work(tmp_path) -> None:
    pytest.importorskip("optuna")
    from torchcbf.sweep import tune

    with pytest.raises(ValueError, match="rho must be in"):
        tune("mppi-cbf", trials=2, num_seeds=1, fixed={"method": "mppi_rascbf", "rho": 5.0},
             params=["noise_sigma"], out=tmp_path / "t", progress=False)  # fmt: skip
    assert not (tmp_path / "t").exists()


def test_the_study_lives_in_the_run_folder_whatever_its_name(tmp_path) -> None:
    """A '?' or '%' in a folder's name is part of the SQLite address's path, escaped."""
    from sqlalchemy.engine import make_url

    from torchcbf.sweep.tune import _sqlite_url

    for name in ("run?a", "pct%41b", "sp ace#x"):
        path = tmp_path / name / "study.db"
        assert make_url(_sqlite_url(path)).database == str(path)
