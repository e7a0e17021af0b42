"""A slice of the kernel fuzz (scripts/fuzz_kernels.py, whose cases live there): every C
kernel, driven through the public API with odd inputs, answers as the general torch path
does, refuses with a ValueError/TypeError, or reports a per-row status. The full fuzz, with
the kernels built under AddressSanitizer and UBSan, is scripts/sanitize_kernels.sh."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "fuzz_kernels.py"
if not SCRIPT.exists():
    pytest.skip("scripts/fuzz_kernels.py is not in this checkout", allow_module_level=True)


def _load():
    spec = importlib.util.spec_from_file_location("fuzz_kernels", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("fuzz_kernels", module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


fuzz = _load()
#: cases per family: the first of the fuzz's own draw (seed 0), a few seconds in all
CASES = fuzz.cases(seed=0, count=25)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_kernel_fuzz_case(case) -> None:
    outcome, detail = fuzz.run_case(case)
    assert outcome == "ok", detail
