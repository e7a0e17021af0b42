"""The Gymnasium example script runs and prints its table."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("gymnasium")

SCRIPT = Path(__file__).resolve().parents[2] / "examples" / "gym_safety_filter.py"


def test_example_prints_collisions_with_and_without_the_filter() -> None:
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--num-envs", "8", "--steps", "30"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [line.split() for line in done.stdout.splitlines()[1:]]
    assert [(r[0], r[1]) for r in rows] == [
        ("torchcbf/ReachAvoid-v0", "no"),
        ("torchcbf/ReachAvoid-v0", "yes"),
        ("torchcbf/UnicycleEllipses-v0", "no"),
        ("torchcbf/UnicycleEllipses-v0", "yes"),
    ]
    plain, filtered = int(rows[0][3]), int(rows[1][3])
    assert plain > 0 and filtered == 0  # scenario A: the filter removes every collision
