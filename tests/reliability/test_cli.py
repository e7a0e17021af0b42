"""The ``torchcbf`` command rejects bad arguments with a usage error naming them."""

from __future__ import annotations

import pytest

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


def test_cli_unknown_method_names_it(tmp_path, capsys):
    argv = ["mppi-cbf", "--seeds", "1", "--methods", "foo", "--samples", "10", "--horizon", "5",
            "--no-progress", "--no-gif", "--out", str(tmp_path)]  # fmt: skip
    with pytest.raises(SystemExit) as exc:
        main(argv)
    # the command exits with the message (SystemExit(message), shown on stderr)
    assert "--methods must be" in str(exc.value) + capsys.readouterr().err
