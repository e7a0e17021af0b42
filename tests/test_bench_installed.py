"""``torchcbf bench`` as an installed command: run from outside the checkout, with and
without the peer libraries (hidden by packages that raise ImportError first on the path)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

PEERS = ("proxsuite", "qpth", "cvxpy", "cvxpylayers", "cbfpy", "jax", "pytorch_mppi", "qpsolvers")


def _bench(cwd: Path, *args: str, hide_peers: bool = False) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    if hide_peers:
        hidden = cwd / "hidden"
        for name in PEERS:
            (hidden / name).mkdir(parents=True, exist_ok=True)
            (hidden / name / "__init__.py").write_text(f"raise ImportError('{name}: hidden')\n")
        env["PYTHONPATH"] = os.pathsep.join([str(hidden), env.get("PYTHONPATH", "")])
    command = shutil.which("torchcbf", path=str(Path(sys.executable).parent))
    argv = [command] if command else [sys.executable, "-m", "torchcbf.cli"]
    return subprocess.run(
        [*argv, "bench", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=900
    )


def test_bench_finds_its_scripts_outside_the_checkout(tmp_path) -> None:
    done = _bench(tmp_path, "--list")
    assert done.returncode == 0, done.stderr
    names = [line.split()[0] for line in done.stdout.splitlines()]
    assert names == ["qp", "barriers", "filters", "mppi"]


@pytest.mark.slow
def test_bench_quick_filters_runs_outside_the_checkout(tmp_path) -> None:
    done = _bench(tmp_path, "--quick", "--only", "filters", hide_peers=True)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    assert "qp only (torchcbf solve_qp" in done.stdout
    assert "proxsuite not installed: its rows are skipped" in done.stdout


@pytest.mark.slow
@pytest.mark.parametrize("hide_peers", [False, True], ids=["peers", "no-peers"])
def test_bench_quick_runs_every_script_outside_the_checkout(tmp_path, hide_peers) -> None:
    done = _bench(tmp_path, "--quick", hide_peers=hide_peers)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    assert "Traceback" not in done.stderr and "failed" not in done.stderr
    for script in ("bench_qp.py", "bench_barriers.py", "bench_filters.py", "bench_mppi.py"):
        assert script in done.stdout
    if hide_peers:
        assert "not installed" in done.stdout and "ImportError" not in done.stdout
