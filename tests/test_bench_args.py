"""The benchmark scripts' honesty checks: size and count flags refused with exit status 2
naming the flag, bench_qp's answer check tells which answer is wrong, bench_mppi reports a
failing planner and goes on, bench_barriers checks every timed formulation."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


def _run(
    script: str, *args: str, timeout: float = 300, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
    return subprocess.run(
        [sys.executable, str(SCRIPTS / script), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=timeout,
    )


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


BAD_FLAGS = [
    ("bench_qp.py", "--big", "0"),
    ("bench_qp.py", "--peer-max-batch", "0"),
    ("bench_qp.py", "--goal-peer-batch", "-1"),
    ("bench_qp.py", "--threads", "-1"),
    ("bench_qp.py", "--threads", "0"),
    ("bench_barriers.py", "--batch", "0"),
    ("bench_barriers.py", "--batch", "-3"),
    ("bench_barriers.py", "--repeats", "0"),
    ("bench_barriers.py", "--loop-rows", "0"),
    ("bench_barriers.py", "--barriers", "0"),
    ("bench_barriers.py", "--threads", "-1"),
    ("bench_filters.py", "--batch", "0"),
    ("bench_filters.py", "--barriers", "0"),
    ("bench_filters.py", "--loop-subset", "0"),
    ("bench_filters.py", "--repeat", "0"),
    ("bench_filters.py", "--calls", "0"),
    ("bench_filters.py", "--threads", "-1"),
    ("bench_mppi.py", "--reps", "0"),
    ("bench_mppi.py", "--threads", "0"),
    ("bench_mppi.py", "--threads", "x"),
]


@pytest.mark.parametrize(("script", "flag", "value"), BAD_FLAGS)
def test_bad_size_flags_exit_2_naming_the_flag(
    script: str, flag: str, value: str, monkeypatch, capsys
) -> None:
    main = _load(script.removesuffix(".py")).main
    monkeypatch.setattr(sys, "argv", [script, "--quick", flag, value])
    with pytest.raises(SystemExit) as exit_:
        main()  # argparse refuses the flag before any work
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: expected" in err or f"argument {flag}: invalid int value" in err


@pytest.mark.parametrize("script", ["bench_qp", "bench_barriers", "bench_filters", "bench_mppi"])
def test_a_device_that_is_not_here_exits_2_before_any_work(script, monkeypatch, capsys) -> None:
    main = _load(script).main
    bad = ["gpu"] + ([] if torch.cuda.is_available() else ["cuda"])
    for device in bad:
        monkeypatch.setattr(sys, "argv", [script, "--quick", "--device", device])
        with pytest.raises(SystemExit) as exit_:
            main()
        assert exit_.value.code == 2
        assert "argument --device:" in capsys.readouterr().err


def test_bad_flag_from_the_command_line() -> None:
    done = _run("bench_barriers.py", "--quick", "--batch", "0", timeout=120)
    assert done.returncode == 2, done.stdout[-1000:] + done.stderr[-2000:]
    assert "argument --batch: expected a positive integer, got '0'" in done.stderr
    assert "Traceback" not in done.stderr


def test_bench_qp_agreement_names_the_wrong_answer() -> None:
    bq = _load("bench_qp")
    from torchcbf.qp import solve_qp

    Q, p, G, h = bq.make_problems(16, 3, 6, "cpu", seed=0)
    with torch.no_grad():
        sol = solve_qp(Q, p, G, h)
    assert bool((sol.status == 0).all())
    x_peer = sol.x.clone()
    x_peer[2] += 0.5  # off the optimum: worse objective or infeasible
    x_peer[5] = torch.nan
    text = bq.agreement("peer", sol, x_peer, (Q, p, G, h))
    assert "14/16 agree" in text
    assert "0 where torchcbf's answer is the worse" in text
    assert "KKT point (residual <= 1e-08) on 2 of the 2" in text
    short = bq.agreement("peer", sol, x_peer[:8], (Q, p, G, h), short=True)
    assert short.startswith("6/8 (2 peer worse, 0 torchcbf worse, 0 even")
    assert bq.agreement("peer", sol, sol.x, (Q, p, G, h), short=True) == "16/16"
    # a wrong torchcbf answer is called so
    bad = sol._replace(x=x_peer.nan_to_num(0.0))
    text = bq.agreement("peer", bad, sol.x, (Q, p, G, h))
    assert "2 where torchcbf's answer is the worse" in text


def test_bench_mppi_failing_planner_is_reported_and_the_run_goes_on(tmp_path) -> None:
    # every planner's child process fails as it starts (a site hook reading its --one flag)
    (tmp_path / "sitecustomize.py").write_text(
        "import os, sys\n"
        "if '--one' in sys.orig_argv:\n"
        "    sys.stderr.write('nosuch planner\\n')\n"
        "    sys.stderr.flush()\n"
        "    os._exit(3)\n"
    )
    path = os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])
    done = _run("bench_mppi.py", "--quick", "--only", "realtime", "fused", env={"PYTHONPATH": path})
    assert done.returncode == 1, done.stdout[-1000:] + done.stderr[-2000:]
    rows = [line for line in done.stdout.splitlines() if "failed (exit status" in line]
    planners = 4 if importlib.util.find_spec("pytorch_mppi") else 2
    assert len(rows) == planners, done.stdout  # both lines ran, each planner reported
    assert "last lines of its stderr" in done.stderr
    assert "nosuch" in done.stderr  # the child's own error is shown
    assert f"{planners} planner(s) failed" in done.stderr
    assert "CalledProcessError" not in done.stderr


def test_bench_mppi_quick_labels_use_the_run_sizes() -> None:
    bm = _load("bench_mppi")
    assert bm.sizes("batched:pytorch-mppi") == (1, 20000, 80, 4)
    assert bm.sizes("batched:pytorch-mppi", quick=True) == (1, 2000, 80, 4)
    assert bm.sizes("modelbatch:auto", quick=True) == (32, 200, 80, 4)
    assert "K=20000 (B=1)" not in (SCRIPTS / "bench_mppi.py").read_text()


def test_bench_barriers_checks_every_timed_formulation() -> None:
    done = _run("bench_barriers.py", "--batch", "200", "--loop-rows", "3", "--repeats", "1")
    assert done.returncode == 0, done.stdout[-1000:] + done.stderr[-2000:]
    checks = [line for line in done.stdout.splitlines() if "from torch.func in float64" in line]
    assert len(checks) == 4  # two setups, with and without the Hessian trace
    for line in checks:
        for label in ("autograd", "analytic", "torch.func", "per-row loop (3 rows)"):
            assert f"{label} " in line
        values = [float(part.split()[-1]) for part in line.split(": ", 1)[1].split(", ")]
        assert max(values) < 1e-3, line
