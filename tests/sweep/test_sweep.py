"""Sweeps: keyword arguments read from the builders, one batch of seeds per configuration,
the rows against direct runs of the scenario, strict JSON, and the CLI."""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import pytest
import torch

from torchcbf.cli import main
from torchcbf.scenarios import reach_avoid
from torchcbf.sim import summarize
from torchcbf.sweep import builder_defaults, configurations, parse_grid, parse_value, run_sweep
from torchcbf.sweep.evaluate import objective, success, tie_break


def test_keywords_come_from_the_parameters_dataclass() -> None:
    a = builder_defaults("reach-avoid")  # num_seeds, seed, device, dtype: set by the run
    assert a == {"num_samples": 10_000, "horizon": 50, "temperature": 0.03, "noise_sigma": 4.0,
                 "control_cost_weight": 0.1}  # fmt: skip
    b = builder_defaults("mppi-cbf")
    assert b["method"] == "mppi_scbf" and "rectify_gain" in b and "num_seeds" not in b


def test_values_take_a_type_the_builder_admits() -> None:
    assert parse_value("reach-avoid", "num_samples", "256") == 256
    assert parse_value("reach-avoid", "num_samples", "1e3") == 1000
    assert parse_value("mppi-cbf", "rectify_gain", "5") == 5.0
    assert isinstance(parse_value("mppi-cbf", "rectify_gain", "5"), float)
    assert parse_value("mppi-cbf", "method", "scbf") == "scbf"
    assert parse_value("mppi-cbf", "control_limit", "none") is None
    assert parse_value("mppi-cbf", "control_limit", "2:4") == (2.0, 4.0)
    assert parse_value("mppi-cbf", "config", "paper") == "paper"
    with pytest.raises(ValueError, match="rectify_gain does not take text"):
        parse_value("mppi-cbf", "rectify_gain", "fast")
    with pytest.raises(ValueError, match="noise_sigma does not take none"):
        parse_value("mppi-cbf", "noise_sigma", "none")
    assert parse_value("mppi-cbf", "control_weight", "1:0.01") == (1.0, 0.01)
    grid = parse_grid("mppi-cbf", ["method=scbf,mppi", "rectify_gain=5,20"])
    assert grid == {"method": ["scbf", "mppi"], "rectify_gain": [5.0, 20.0]}
    assert len(configurations(grid)) == 4
    assert configurations({}) == [{}]


@pytest.mark.parametrize(
    ("items", "match"),
    [
        (["gain=1"], "unknown key 'gain'.*horizon, noise_sigma, num_samples"),
        (["num_seeds=3"], "num_seeds"),
        (["num_samples=1.5"], "num_samples takes an integer"),
        (["num_samples"], "KEY=V1,V2"),
        (["horizon=10", "horizon=20"], "twice"),
    ],
)
def test_bad_grid_items_name_the_problem(items, match) -> None:
    with pytest.raises(ValueError, match=match):
        parse_grid("reach-avoid", items)


def test_bad_values_fail_before_anything_runs() -> None:
    with pytest.raises(ValueError, match="method"):
        run_sweep("mppi-cbf", {"method": ["nope"]}, num_seeds=1, progress=False)
    # one value where a list belongs (a string is not split into its characters)
    for value in (5, "scbf"):
        with pytest.raises(TypeError, match=r"grid\['method'\] must be a list"):
            run_sweep("mppi-cbf", {"method": value}, num_seeds=1, progress=False)
    with pytest.raises(ValueError, match="engine"):
        run_sweep("reach-avoid", {}, engine="spark", progress=False)
    with pytest.raises(ValueError, match="scenario"):
        run_sweep("pendulum", {}, progress=False)


def test_rows_equal_direct_runs_of_the_scenario() -> None:
    rows = run_sweep(
        "reach-avoid", {"num_samples": [32, 64], "horizon": [8]}, num_seeds=3, seed=5,
        progress=False,
    )  # fmt: skip
    assert [(r["num_samples"], r["horizon"]) for r in rows] == [(32, 8), (64, 8)]
    previous = torch.get_num_threads()
    for row in rows:
        scenario = reach_avoid(num_samples=row["num_samples"], horizon=8, num_seeds=3, seed=5)
        torch.set_num_threads(1)  # as the sweep runs it
        try:
            _, per_seed = scenario.run(progress=False)
        finally:
            torch.set_num_threads(previous)
        summary = summarize(per_seed)
        ok = per_seed["spec_satisfied"] & ~per_seed["collision"]
        assert row["success_count"] == int(ok.sum()) and row["num_seeds"] == 3
        assert row["collision_count"] == summary["collision"]["count"]
        assert row["min_h"] == summary["min_h"]["min"]
        assert row["spec_robustness_mean"] == pytest.approx(summary["spec_robustness"]["mean"])
        assert row["objective"] == pytest.approx(objective(per_seed, 10.0))


def test_objective_counts_successes_first_then_the_tie_break() -> None:
    t = torch.tensor
    fast = {
        "goal_reached": t([True, True, False, False]),
        "collision": t([False, True, False, False]),
        "goal0_time": t([1.0, 2.0, float("nan"), float("nan")]),
    }
    slow = {**fast, "goal0_time": t([4.0, 2.0, float("nan"), float("nan")])}
    crashed = {**fast, "collision": t([True, True, False, False])}
    assert tie_break(crashed, 5.0) == 0.0  # reaching the goal through an obstacle earns nothing
    assert success(fast).tolist() == [True, False, False, False]
    assert tie_break(fast, 5.0) == pytest.approx(1 - 1.0 / 5)  # seed 1 collided: not counted
    assert objective(fast, 5.0) > objective(slow, 5.0) > 0.25
    one_more = {**slow, "goal_reached": t([True, True, True, False]), "goal0_time": t([4.9] * 4)}
    assert objective(one_more, 5.0) > objective(fast, 5.0)  # a success beats any tie-break
    assert objective(fast, 5.0) < 0.25 + 1 / 8


def test_cli_sweep_writes_csv_strict_json_and_figure(tmp_path, capsys) -> None:
    import matplotlib

    backend = matplotlib.get_backend()
    matplotlib.use("svg")  # a user's choice, which drawing the figure switched to Agg
    code = main(
        ["sweep", "reach-avoid", "--grid", "num_samples=32,64", "--grid", "horizon=8",
         "--seeds", "2", "--out", str(tmp_path), "--no-progress"]
    )  # fmt: skip
    assert code == 0
    out = capsys.readouterr().out
    assert "num_samples=32 horizon=8" in out and "success (95% CI)" in out
    data = json.loads(
        (tmp_path / "sweep.json").read_text(),
        parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"),
    )
    assert data["grid"] == {"num_samples": [32, 64], "horizon": [8]}
    assert data["run"]["scenario"] == "reach-avoid" and "torch" in data["run"]
    assert len(data["rows"]) == 2 and all(math.isfinite(r["objective"]) for r in data["rows"])
    with (tmp_path / "sweep.csv").open() as f:
        table = list(csv.DictReader(f))
    assert [int(r["num_samples"]) for r in table] == [32, 64]
    assert (tmp_path / "sweep.png").stat().st_size > 1000
    assert matplotlib.get_backend() == "svg"
    matplotlib.use(backend)


def test_cli_sweep_unknown_key_exits_2(tmp_path, capsys) -> None:
    assert main(["sweep", "reach-avoid", "--grid", "alpha=1", "--out", str(tmp_path)]) == 2
    assert "unknown key 'alpha'" in capsys.readouterr().err


def _fails_at_48(**kwargs):
    """``evaluate``, raising for the configuration with 48 samples."""
    from torchcbf.sweep.evaluate import evaluate

    if kwargs["params"].get("num_samples") == 48:
        raise RuntimeError("boom at 48 samples")
    return evaluate(**kwargs)


def test_a_failing_point_is_recorded_and_the_rest_run(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setattr("torchcbf.sweep.sweep.evaluate", _fails_at_48)
    args = ["sweep", "reach-avoid", "--grid", "num_samples=32,48,64", "--grid", "horizon=8",
            "--seeds", "2", "--out", str(tmp_path), "--no-progress"]  # fmt: skip
    assert main(args) == 0
    assert "1 of 3 configuration(s) failed" in capsys.readouterr().out
    rows = json.loads((tmp_path / "sweep.json").read_text())["rows"]
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert rows[1]["error"] == "RuntimeError: boom at 48 samples" and rows[1]["num_samples"] == 48
    assert rows[2]["success_count"] >= 0  # the point after the failure ran
    with (tmp_path / "sweep.csv").open() as f:
        assert [r["status"] for r in csv.DictReader(f)] == ["ok", "failed", "ok"]
    assert json.loads((tmp_path / "run.json").read_text())["complete"] is True
    # every point failing: the run completes, and the command exits 1
    monkeypatch.setattr("torchcbf.sweep.sweep.evaluate", _always_fails)
    args[args.index(str(tmp_path))] = str(tmp_path / "every")
    assert main(args) == 1
    assert "3 of 3 configuration(s) failed" in capsys.readouterr().out
    assert json.loads((tmp_path / "every" / "run.json").read_text())["complete"] is True


def _always_fails(**kwargs):
    raise RuntimeError("boom")


def test_out_is_checked_before_any_work(tmp_path, monkeypatch, capsys) -> None:
    def never(**kwargs):
        raise AssertionError("a configuration ran")

    monkeypatch.setattr("torchcbf.sweep.sweep.evaluate", never)
    (tmp_path / "file").write_text("x")
    sweep = ["sweep", "reach-avoid", "--grid", "horizon=8", "--no-progress", "--out"]
    assert main([*sweep, str(tmp_path / "file")]) == 2
    assert "is a file" in capsys.readouterr().err
    assert main([*sweep, str(tmp_path / "file" / "below")]) == 2
    assert "file is a file" in capsys.readouterr().err
    (tmp_path / "theirs").mkdir()
    (tmp_path / "theirs" / "notes.txt").write_text("keep")
    assert main([*sweep, str(tmp_path / "theirs")]) == 2
    assert "not a torchcbf run" in capsys.readouterr().err
    assert main([*sweep, str(tmp_path / "theirs"), "--resume"]) == 2
    assert (tmp_path / "theirs" / "notes.txt").read_text() == "keep"


def test_a_read_only_out_is_refused_before_any_work(tmp_path, capsys) -> None:
    if os.geteuid() == 0:  # root writes into any folder of mode 555, not into sysfs
        if not Path("/sys/kernel").is_dir():
            pytest.skip("no sysfs here: no folder root cannot write")
        target = Path("/sys/torchcbf-out")
    else:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        target = ro / "x"
    try:
        code = main(["sweep", "reach-avoid", "--out", str(target), "--no-progress"])
    finally:
        if os.geteuid() != 0:
            (tmp_path / "ro").chmod(0o755)
    assert code == 2 and "cannot be written" in capsys.readouterr().err
    assert not target.exists()


def test_overwrite_replaces_an_earlier_run_and_keeps_other_files(tmp_path) -> None:
    args = ["sweep", "reach-avoid", "--grid", "num_samples=32", "--grid", "horizon=8",
            "--seeds", "2", "--out", str(tmp_path), "--no-progress"]  # fmt: skip
    assert main(args) == 0
    (tmp_path / "notes.txt").write_text("keep")
    (tmp_path / "metrics.json").write_text("{}")  # no manifest lists it: not torchcbf's to remove
    assert main(args) == 2  # a finished run is not replaced without --overwrite
    other = [*args[:3], "num_samples=64", *args[4:], "--overwrite"]
    assert main(other) == 0
    rows = json.loads((tmp_path / "sweep.json").read_text())["rows"]
    assert [r["num_samples"] for r in rows] == [64]
    assert len((tmp_path / "sweep.jsonl").read_text().splitlines()) == 1
    assert (tmp_path / "metrics.json").read_text() == "{}"
    assert (tmp_path / "notes.txt").read_text() == "keep"


def test_overwrite_removes_only_what_a_torchcbf_manifest_lists(tmp_path, capsys) -> None:
    from torchcbf.sweep.rundir import OutputError, RunDir

    args = ["sweep", "reach-avoid", "--grid", "num_samples=32", "--grid", "horizon=8",
            "--seeds", "2", "--no-progress"]  # fmt: skip
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "run.json").write_text('{"files": ["data.csv"], "note": "my experiment"}')
    (mine / "data.csv").write_text("a,b")
    assert (
        main([*args, "--out", str(mine), "--overwrite"]) == 2
    )  # a run.json torchcbf did not write
    assert "torchcbf did not write" in capsys.readouterr().err
    assert (mine / "data.csv").read_text() == "a,b"
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "reach_avoid_final.png").write_text("mine")
    assert main([*args, "--out", str(plain), "--overwrite"]) == 0
    assert (plain / "reach_avoid_final.png").read_text() == "mine"
    held = RunDir.claim(tmp_path / "held", kind="sweep", settings={})
    with pytest.raises(OutputError, match="in use by another torchcbf run"):
        RunDir.claim(tmp_path / "held", kind="sweep", settings={}, resume=True)
    del held


def test_resume_with_the_grid_keys_in_another_order_runs_nothing_again(
    tmp_path, monkeypatch
) -> None:
    """The same grid with its keys given in another order is the same sweep: --resume finds
    every finished configuration by its parameters (their indices differ) and runs none."""
    args = ["sweep", "reach-avoid", "--grid", "num_samples=32,48", "--grid", "horizon=6,8",
            "--seeds", "2", "--out", str(tmp_path), "--no-progress"]  # fmt: skip
    assert main(args) == 0
    first = json.loads((tmp_path / "sweep.json").read_text())["rows"]
    monkeypatch.setattr("torchcbf.sweep.sweep.evaluate", _always_fails)
    swapped = ["sweep", "reach-avoid", "--grid", "horizon=6,8", "--grid", "num_samples=32,48",
               "--seeds", "2", "--out", str(tmp_path), "--no-progress", "--resume"]  # fmt: skip
    assert main(swapped) == 0
    again = json.loads((tmp_path / "sweep.json").read_text())["rows"]
    assert all(r["status"] == "ok" for r in again) and len(again) == 4
    key = lambda r: (r["num_samples"], r["horizon"])  # noqa: E731
    assert sorted(map(key, again)) == sorted(map(key, first))
    by_key = {key(r): r["success_count"] for r in first}
    assert all(by_key[key(r)] == r["success_count"] for r in again)
    assert len((tmp_path / "sweep.jsonl").read_text().splitlines()) == 4


def test_figures_drawn_before_an_interrupt_are_removed_by_overwrite(tmp_path, monkeypatch):
    """Ctrl-C while the figures are drawn: the manifest lists the ones already written, so
    a later --overwrite removes them with the rest of the run (they stayed beside the new
    run's outputs)."""
    import torchcbf.scenarios.figures as figures

    def half_drawn(trajectories, scenario, folder, **kwargs):
        (folder / "old_rollouts.png").write_bytes(b"png")
        raise KeyboardInterrupt

    args = ["reach-avoid", "--seeds", "1", "--samples", "64", "--horizon", "6", "--no-gif",
            "--no-progress", "--out", str(tmp_path)]  # fmt: skip
    monkeypatch.setattr(figures, "standard_figures", half_drawn)
    assert main(args) == 130
    assert "old_rollouts.png" in json.loads((tmp_path / "run.json").read_text())["files"]
    monkeypatch.undo()
    assert main([*args, "--overwrite"]) == 0
    assert not (tmp_path / "old_rollouts.png").exists()
    assert (tmp_path / "metrics.json").exists()


def test_grid_values_without_an_order_or_not_finite_are_refused() -> None:
    import numpy as np

    for bad in ({32, 48}, np.array(32)):
        with pytest.raises(TypeError, match=r"grid\['num_samples'\] must be a list"):
            configurations({"num_samples": bad})
    for bad in (float("nan"), float("inf"), np.float64(-np.inf), (2.0, float("inf"))):
        with pytest.raises(ValueError, match=r"grid\['gain'\] holds .* which is not finite"):
            configurations({"gain": [1.0, bad]})
    assert configurations({"k": range(2), "m": np.array([0.5])}) == [
        {"k": 0, "m": 0.5},
        {"k": 1, "m": 0.5},
    ]


def test_seeds_outside_the_noise_streams_are_refused_before_any_work(tmp_path) -> None:
    for seed, count in ((-1, 2), (2**32 - 1, 2)):
        with pytest.raises(ValueError, match=r"pass the bounds \[0, 2\^32 - 1\]"):
            run_sweep("reach-avoid", {}, num_seeds=count, seed=seed, out=tmp_path / "x",
                      progress=False)  # fmt: skip
    assert not (tmp_path / "x").exists()


def test_a_fresh_run_refuses_outputs_no_manifest_lists(tmp_path, capsys) -> None:
    """A finished sweep whose run.json is gone: its journal is not read back as this run's
    rows (they were for other seeds), and nothing of it is replaced."""
    args = ["sweep", "reach-avoid", "--grid", "num_samples=32", "--grid", "horizon=6",
            "--seeds", "2", "--out", str(tmp_path), "--no-progress"]  # fmt: skip
    assert main(args) == 0
    (tmp_path / "run.json").unlink()
    journal = (tmp_path / "sweep.jsonl").read_text()
    assert main([*args[:7], "3", *args[8:], "--overwrite"]) == 2
    assert "holds sweep.jsonl, sweep.json, sweep.csv, sweep.png" in capsys.readouterr().err
    assert (tmp_path / "sweep.jsonl").read_text() == journal


def test_a_refused_folder_keeps_no_lock_file(tmp_path) -> None:
    from torchcbf.sweep.rundir import LOCK, OutputError, RunDir

    (tmp_path / "mine.txt").write_text("mine")
    with pytest.raises(OutputError, match="files that are not a torchcbf run"):
        RunDir.claim(tmp_path, kind="sweep", settings={})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt"]
    assert LOCK == ".torchcbf.lock"


def test_a_sweep_interrupted_in_this_process_can_be_resumed_by_it(tmp_path, monkeypatch):
    """The folder is released however the run ends (a notebook's Ctrl-C keeps the frames,
    and with them an unreleased lock, alive)."""

    def interrupted(**kwargs):
        raise KeyboardInterrupt

    grid = {"num_samples": [32], "horizon": [6]}
    monkeypatch.setattr("torchcbf.sweep.sweep.evaluate", interrupted)
    with pytest.raises(KeyboardInterrupt) as caught:  # its traceback holds the frames
        run_sweep("reach-avoid", grid, num_seeds=1, out=tmp_path, progress=False)
    monkeypatch.undo()
    rows = run_sweep("reach-avoid", grid, num_seeds=1, out=tmp_path, resume=True, progress=False)
    assert [r["status"] for r in rows] == ["ok"] and caught.value is not None


def test_a_ray_address_of_another_form_is_refused() -> None:
    from torchcbf.sweep.engines import check_address

    for bad in ("localhost", "foo", "host:port", ":6379"):
        with pytest.raises(ValueError, match="address must be 'auto', 'local', host:port"):
            check_address(bad)
    check_address("auto")


def test_table_names_rows_by_their_parameters_even_one_called_label(capsys) -> None:
    from torchcbf.cli import _print_rows

    rows = [
        {"label": name, "status": "ok", "wall_s": 1.0, "success_rate": 0.5,
         "success_ci95_low": 0.1, "success_ci95_high": 0.9}
        for name in ("alpha", "beta")
    ]  # fmt: skip
    _print_rows(rows, ["label"])
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines[1:]] == ["label=alpha", "label=beta"]
    _print_rows(rows, ["label"], names=["best", "default"])
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines[1:]] == ["best", "default"]
