"""The ``torchcbf`` command rejects bad arguments with a usage error naming them."""

from __future__ import annotations

import pytest
import torch

from torchcbf.cli import main


@pytest.mark.parametrize(
    "argv, pattern",
    [
        (["bogus"], "invalid choice: 'bogus'"),
        (["reach-avoid", "--device", "tpu"], "argument --device: invalid choice: 'tpu'"),
        (["reach-avoid", "--seeds", "x"], "argument --seeds: invalid int value: 'x'"),
        (["mppi-cbf", "--horizon", "1.5"], "argument --horizon: invalid int value"),
        (["bench", "--device", "tpu"], "argument --device"),
        ([], "command"),
    ],
)
def test_cli_usage_errors_name_the_argument(argv, pattern, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert pattern in capsys.readouterr().err


@pytest.mark.parametrize("methods", ["foo", "", ","])
def test_cli_unknown_method_names_it(methods, tmp_path, capsys):
    """An unknown or empty method list is a usage error before any work (an empty one does
    not mean every method)."""
    argv = ["mppi-cbf", "--seeds", "1", "--methods", methods, "--samples", "10", "--horizon",
            "5", "--no-progress", "--no-gif", "--out", str(tmp_path)]  # fmt: skip
    assert main(argv) == 2
    assert "torchcbf mppi-cbf: --methods must be" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
@pytest.mark.parametrize("command", [["sweep", "reach-avoid"], ["tune", "reach-avoid"],
                                     ["mppi-cbf"], ["reach-avoid"], ["bench"]])  # fmt: skip
def test_cuda_without_cuda_is_a_usage_error_before_any_work(command, tmp_path, capsys):
    out = tmp_path / "out"
    argv = [*command, "--device", "cuda"] + (["--out", str(out)] if command[0] != "bench" else [])
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert "argument --device: device 'cuda': this torch has no CUDA device available" in (
        capsys.readouterr().err
    )
    assert not out.exists()


@pytest.mark.parametrize("command", [["mppi-cbf"], ["reach-avoid"], ["tune", "reach-avoid"]])
def test_scenario_commands_refuse_a_bad_out_before_any_work(command, tmp_path, capsys):
    if command[0] == "tune":
        pytest.importorskip("optuna")  # without it, tune stops first on the missing extra
    (tmp_path / "file").write_text("x")
    assert main([*command, "--out", str(tmp_path / "file" / "below")]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "metrics.json").write_text("{}")
    assert main([*command, "--out", str(tmp_path / "old")]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (tmp_path / "old" / "metrics.json").read_text() == "{}"
