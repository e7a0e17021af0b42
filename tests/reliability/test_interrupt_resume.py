"""Long commands killed at any moment (SIGINT, SIGTERM or SIGKILL) and run again with ``--resume``
end with the outputs of an uninterrupted run, and never leave a half-written file."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from torchcbf._io import is_temporary
from torchcbf.cli import main
from torchcbf.sweep.sweep import read_journal

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
WALL = ("wall_s", "seconds")  # wall times: the only numbers that differ between runs


def _command(args: list[str], out: Path) -> list[str]:
    return [sys.executable, "-m", "torchcbf.cli", *args, "--out", str(out), "--no-progress"]


def _reference(args: list[str], out: Path) -> Path:
    """The uninterrupted run, in this process (one torch thread, as the subprocesses)."""
    assert main([*args, "--out", str(out), "--no-progress"]) == 0
    return out


def _run(args: list[str], out: Path, *extra: str) -> subprocess.CompletedProcess:
    done = subprocess.run(
        _command([*args, *extra], out), env=ENV, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def _interrupt(
    args: list[str], out: Path, ready: Callable[[], bool], sig: int
) -> tuple[bool, subprocess.Popen, str]:
    """Start the command, send ``sig`` once ``ready()``; whether it was still running then."""
    proc = subprocess.Popen(
        _command(args, out), env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 240
    while proc.poll() is None and not ready() and time.monotonic() < deadline:
        time.sleep(0.01)
    signalled = proc.poll() is None
    if signalled:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=240)
    if signalled and sig in (signal.SIGINT, signal.SIGTERM):
        assert proc.returncode == 130, err[-3000:]
        assert "Traceback" not in err and "--resume" in err, err[-3000:]
    elif signalled:
        assert proc.returncode == -signal.SIGKILL
    return signalled, proc, err


def _without_wall(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_wall(v) for k, v in value.items() if k not in WALL}
    if isinstance(value, list):
        return [_without_wall(v) for v in value]
    return value


def _json(path: Path) -> Any:
    """The file's JSON without wall times, its run folder's name written as ``OUT``, and
    without the git commit (a run resumed after a commit records the new one)."""
    data = _without_wall(json.loads(path.read_text().replace(str(path.parent), "OUT")))
    if isinstance(data.get("run"), dict):
        data["run"].pop("git_commit", None)
    return data


def _csv(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return [{k: v for k, v in row.items() if k not in WALL} for row in csv.DictReader(f)]


def _whole_files(out: Path, killed: bool = False) -> None:
    """Every file under ``out`` is complete (JSON parses, PNG ends with its IEND chunk); a
    temporary file (hidden name, never read as an output) only where a kill cut a write."""
    for path in out.rglob("*"):
        if is_temporary(path):
            assert killed, path
            continue
        if path.suffix == ".json":
            json.loads(path.read_text())
        if path.suffix == ".png":
            assert path.read_bytes()[-8:-4] == b"IEND", path


def _lines(path: Path, n: int) -> Callable[[], bool]:
    return lambda: path.exists() and path.read_text().count("\n") >= n


SWEEP = ["sweep", "reach-avoid", "--grid", "num_samples=32,48,64,80", "--grid", "horizon=8",
         "--seeds", "2"]  # fmt: skip


@pytest.fixture(scope="module")
def sweep_reference(tmp_path_factory) -> Path:
    return _reference(SWEEP, tmp_path_factory.mktemp("sweep") / "reference")


@pytest.mark.parametrize(
    ("sig", "when"),
    [
        (signal.SIGINT, "after one point"),
        (signal.SIGTERM, "after one point"),
        pytest.param(signal.SIGKILL, "after two points", marks=pytest.mark.slow),
    ],
)
def test_sweep_killed_then_resumed_equals_an_uninterrupted_run(
    tmp_path, sweep_reference, sig, when
) -> None:
    out = tmp_path / "run"
    ready = {
        "after one point": _lines(out / "sweep.jsonl", 1),
        "after two points": _lines(out / "sweep.jsonl", 2),
    }[when]
    signalled, _, _ = _interrupt(SWEEP, out, ready, sig)
    assert signalled  # four points of about 0.1 s each: it is still running
    _whole_files(out, killed=sig == signal.SIGKILL)
    assert not json.loads((out / "run.json").read_text())["complete"]
    assert 1 <= len(read_journal(out / "sweep.jsonl")) < 4  # what finished is saved
    (out / ".sweep.json.cut_9x2k.tmp.json").write_text('{"rows": [')  # as a kill mid-write leaves
    _run(SWEEP, out, "--resume")
    _whole_files(out)
    resumed, reference = _json(out / "sweep.json"), _json(sweep_reference / "sweep.json")
    assert resumed["run"] == reference["run"], (resumed["run"], reference["run"])
    assert resumed == reference
    assert _csv(out / "sweep.csv") == _csv(sweep_reference / "sweep.csv")
    assert (out / "sweep.png").stat().st_size > 1000


TUNE = ["tune", "reach-avoid", "--trials", "4", "--seeds", "2", "--set", "num_samples=32",
        "--params", "horizon"]  # fmt: skip


@pytest.mark.slow
def test_tune_killed_then_resumed_equals_an_uninterrupted_run(tmp_path) -> None:
    pytest.importorskip("optuna")
    reference = _reference(TUNE, tmp_path / "reference")
    out = tmp_path / "run"
    # SIGKILL once the first trial is told: the storage holds it, and an asked trial or two
    signalled, _, _ = _interrupt(TUNE, out, lambda: (out / "study.csv").exists(), signal.SIGKILL)
    assert signalled
    _whole_files(out, killed=True)
    assert not (out / "best.json").exists()
    _run(TUNE, out, "--resume")
    _whole_files(out)
    assert _json(out / "best.json") == _json(reference / "best.json")
    assert _csv(out / "study.csv") == _csv(reference / "study.csv")
    assert len(_csv(out / "study.csv")) == 4


MPPI_CBF = ["mppi-cbf", "--methods", "scbf,mppi", "--seeds", "2", "--samples", "32",
            "--horizon", "8", "--no-gif"]  # fmt: skip


def _figures(out: Path) -> set[str]:
    return {p.name for p in out.glob("*.png")}


@pytest.mark.slow
def test_mppi_cbf_killed_then_resumed_equals_an_uninterrupted_run(tmp_path) -> None:
    reference = _reference(MPPI_CBF, tmp_path / "reference")
    out = tmp_path / "run"
    parts = out / ".parts"
    signalled, _, _ = _interrupt(
        MPPI_CBF, out, lambda: parts.is_dir() and any(parts.glob("*.json")), signal.SIGINT
    )
    assert signalled
    _whole_files(out)
    assert not (out / "metrics.json").exists()
    _run(MPPI_CBF, out, "--resume")
    _whole_files(out)
    assert _json(out / "metrics.json") == _json(reference / "metrics.json")
    assert _figures(out) == _figures(reference) and len(_figures(out)) >= 3


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["int", "term"])
def test_ray_sweep_interrupted_then_resumed_equals_an_uninterrupted_run(
    tmp_path, sweep_reference, sig
) -> None:
    """Ray installs a SIGTERM handler of its own that exits at once; the run puts back
    the command's, which saves the finished work as Ctrl-C does."""
    pytest.importorskip("ray")
    out = tmp_path / "run"
    ray_args = [*SWEEP, "--engine", "ray", "--num-cpus", "1"]
    signalled, _, _ = _interrupt(ray_args, out, _lines(out / "sweep.jsonl", 1), sig)
    assert signalled
    _whole_files(out)
    assert 1 <= len(read_journal(out / "sweep.jsonl")) < 4
    _run(SWEEP, out, "--resume")  # the engine may change: its numbers are the same
    assert _json(out / "sweep.json")["rows"] == _json(sweep_reference / "sweep.json")["rows"]
    assert _csv(out / "sweep.csv") == _csv(sweep_reference / "sweep.csv")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["int", "term"])
def test_a_signal_while_a_temporary_file_is_created_leaves_none(tmp_path, monkeypatch, sig) -> None:
    import tempfile

    from torchcbf import _io

    created = []
    mkstemp = tempfile.mkstemp

    def mkstemp_then_ctrl_c(*args: Any, **kwargs: Any) -> tuple[int, str]:
        fd, name = mkstemp(*args, **kwargs)
        created.append(Path(name))
        if len(created) == 3:  # the signal lands right after the file exists
            os.kill(os.getpid(), sig)
        return fd, name

    monkeypatch.setattr(_io.tempfile, "mkstemp", mkstemp_then_ctrl_c)
    out = tmp_path / "run"
    assert main([*SWEEP, "--out", str(out), "--no-progress"]) == 130
    assert len(created) == 3 and not created[-1].exists()
    assert not [p for p in out.rglob("*") if is_temporary(p)]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_only_the_writers_own_temporary_names_count_as_temporary():
    """A user's ``.draft.tmp.md`` in ``--out`` was taken for a killed write and deleted."""
    assert is_temporary(".sweep.json.k2j3h4g5.tmp.json")
    assert is_temporary(".noext.abcdefgh.tmp")  # a name without a suffix
    assert not is_temporary(".draft.tmp.md")
    assert not is_temporary("sweep.json")


def test_a_write_into_no_folder_names_the_path_asked_for(tmp_path):
    from torchcbf import _io

    with pytest.raises(FileNotFoundError, match="no folder .*missing to write t.json"):
        _io.write_json(tmp_path / "missing" / "t.json", {})
    (tmp_path / "d.json").mkdir()
    with pytest.raises(IsADirectoryError, match="d.json is a folder"):
        _io.write_json(tmp_path / "d.json", {})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.json"]  # no temporary left
