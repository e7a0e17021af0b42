"""Every ```python block of README.md and docs/*.md runs, and prints what the page shows.

The convention (one rule for every page):

- the blocks of one page run in order, in one namespace, with the working directory set to
  a fresh temporary folder;
- a block followed directly (blank lines aside) by a ```text block must print that text;
  numbers are compared with a tolerance (:func:`_numbers_match`), everything else after
  collapsing whitespace; a line ``...`` in the text stands for any number of lines;
- a block preceded by the line ``<!-- docs-test: slow -->`` runs only under ``-m slow``
  (the slow test of that page runs every block in order, the default one skips it);
- a block preceded by ``<!-- docs-test: skip REASON -->`` never runs (a GPU, the network, a
  multi-minute run); the reason is mandatory;
- a block preceded by ``<!-- docs-test: requires MODULE[,MODULE] -->`` runs only where those
  modules import (an optional extra: ``gymnasium``, ``optuna``, ...); a later block that uses
  its names needs the same marker.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import math
import re
import sys
import types
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

_MARKER = re.compile(r"<!--\s*docs-test:\s*(\w+)\s*(.*?)\s*-->")
_FENCE = re.compile(r"^(\s*)(`{3,}|~{3,})\s*([\w+-]*)")
_NUMBER = re.compile(r"[-+]?(?:\d[\d,]*\.?\d*|\.\d+)(?:[eE][-+]?\d+)?%?")

#: relative and absolute tolerance of a printed number (seeded runs differ only by rounding
#: and thread count; a shown number may also be rounded to its last digit)
REL_TOL = 0.02
ABS_TOL = 1e-6


@dataclass
class Block:
    page: str
    line: int  # 1-based line of the opening fence
    code: str
    expected: str | None  # the ```text block right after it, if any
    mode: str  # "run", "slow" or "skip"
    reason: str = ""
    requires: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return f"{self.page}:{self.line}"


def parse(text: str, page: str) -> list[Block]:
    """The python blocks of a markdown page, with their markers and expected outputs."""
    lines = text.splitlines()
    fences: list[tuple[int, int, str, str]] = []  # (start, end, language, body)
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, lang = m.groups()
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith(fence[0] * len(fence)):
            j += 1
        body = "\n".join(line[len(indent) :] for line in lines[i + 1 : j])
        fences.append((i, j, lang.lower(), body + "\n"))
        i = j + 1
    blocks = []
    for k, (start, end, lang, body) in enumerate(fences):
        if lang != "python":
            continue
        mode, reason, requires = "run", "", ()
        prev = start - 1
        while prev >= 0 and not lines[prev].strip():
            prev -= 1
        while prev >= 0 and (marker := _MARKER.search(lines[prev])):  # markers stack
            kind, arg = marker.group(1), marker.group(2)
            if kind not in ("slow", "skip", "requires"):
                raise ValueError(f"{page}:{prev + 1}: unknown docs-test marker {kind!r}")
            if kind in ("skip", "requires") and not arg:
                raise ValueError(f"{page}:{prev + 1}: a docs-test {kind} needs a reason")
            if kind == "requires":
                requires = tuple(m.strip() for m in arg.split(",") if m.strip())
            elif mode == "run" or kind == "skip":
                mode, reason = kind, arg
            prev -= 1
        expected = None
        if k + 1 < len(fences) and fences[k + 1][2] == "text":
            between = lines[end + 1 : fences[k + 1][0]]
            if not any(line.strip() for line in between):
                expected = fences[k + 1][3]
        blocks.append(Block(page, start + 1, body, expected, mode, reason, requires))
    return blocks


def _to_float(token: str) -> float:
    return float(token.rstrip("%").replace(",", ""))


def _decimals(token: str) -> int:
    mantissa = re.split(r"[eE]", token.rstrip("%"))[0]
    return len(mantissa.split(".")[1]) if "." in mantissa else 0


def _numbers_match(got: str, want: str) -> bool:
    """``got`` equals ``want`` within REL_TOL, ABS_TOL and half a unit of ``want``'s last
    shown digit (so a page may show ``0.175`` for a printed ``0.17523``); integers (counts)
    exactly."""
    a, b = _to_float(got), _to_float(want)
    if not re.search(r"[.eE]", want) and not re.search(r"[.eE]", got):
        return a == b
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    exponent = re.split(r"[eE]", want.rstrip("%"))
    scale = 10 ** int(exponent[1]) if len(exponent) == 2 else 1.0
    shown = 0.5 * 10 ** (-_decimals(want)) * scale
    return abs(a - b) <= max(ABS_TOL, REL_TOL * abs(b), shown)


def _split(line: str) -> tuple[list[str], list[str]]:
    """(words between the numbers with whitespace collapsed, the numbers)."""
    numbers = _NUMBER.findall(line)
    words = [" ".join(part.split()) for part in _NUMBER.split(line)]
    return words, numbers


def _lines_match(got: str, want: str) -> bool:
    got_words, got_numbers = _split(got)
    want_words, want_numbers = _split(want)
    return (
        got_words == want_words
        and len(got_numbers) == len(want_numbers)
        and all(_numbers_match(g, w) for g, w in zip(got_numbers, want_numbers, strict=True))
    )


def output_matches(got: str, want: str) -> bool:
    """Printed ``got`` against the page's ``want`` line by line (blank lines ignored); a
    line ``...`` of ``want`` matches any number of lines."""
    got_lines = [line for line in got.splitlines() if line.strip()]
    want_lines = [line for line in want.splitlines() if line.strip()]

    def match(i: int, j: int) -> bool:
        if j == len(want_lines):
            return i == len(got_lines)
        if want_lines[j].strip() == "...":
            return any(match(k, j + 1) for k in range(i, len(got_lines) + 1))
        return (
            i < len(got_lines) and _lines_match(got_lines[i], want_lines[j]) and match(i + 1, j + 1)
        )

    return match(0, 0)


def run_page(blocks: list[Block], *, slow: bool) -> None:
    """Run the blocks of one page in order in one namespace; fail on the first that raises
    or prints something other than its ```text block. The page runs as a module of its own
    (in ``sys.modules`` while it runs), as a script would: dataclasses and pickling work."""
    page = types.ModuleType("__docs__")
    sys.modules[page.__name__] = page
    try:
        _run_blocks(blocks, page.__dict__, slow=slow)
    finally:
        sys.modules.pop(page.__name__, None)


def _run_blocks(blocks: list[Block], namespace: dict[str, object], *, slow: bool) -> None:
    for block in blocks:
        if block.mode == "skip" or (block.mode == "slow" and not slow):
            continue
        if not all(importlib.util.find_spec(m) is not None for m in block.requires):
            continue
        out = io.StringIO()
        try:
            with contextlib.redirect_stdout(out):
                exec(compile(block.code, block.name, "exec"), namespace)
        except Exception as exc:
            raise AssertionError(
                f"the python block at {block.name} raised {type(exc).__name__}: {exc}"
            ) from exc
        if block.expected is not None and not output_matches(out.getvalue(), block.expected):
            raise AssertionError(
                f"the python block at {block.name} printed\n{out.getvalue()}\n"
                f"where the page shows\n{block.expected}"
            )


BLOCKS = {
    page.relative_to(ROOT).as_posix(): parse(page.read_text(), page.relative_to(ROOT).as_posix())
    for page in PAGES
}
WITH_CODE = [name for name, blocks in BLOCKS.items() if any(b.mode != "skip" for b in blocks)]
WITH_SLOW = [name for name, blocks in BLOCKS.items() if any(b.mode == "slow" for b in blocks)]


@pytest.fixture
def _page_env(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    torch.manual_seed(0)
    yield
    import matplotlib.pyplot as plt

    plt.close("all")


@pytest.mark.usefixtures("_page_env")
@pytest.mark.parametrize("page", WITH_CODE)
def test_page_blocks_run_and_print_what_the_page_shows(page: str) -> None:
    run_page(BLOCKS[page], slow=False)


@pytest.mark.slow
@pytest.mark.usefixtures("_page_env")
@pytest.mark.parametrize("page", WITH_SLOW)
def test_page_blocks_including_slow_ones(page: str) -> None:
    run_page(BLOCKS[page], slow=True)


def test_every_extension_point_has_an_executed_example() -> None:
    run = [b for b in BLOCKS["docs/architecture.md"] if b.mode != "skip"]
    assert len(run) >= 5


# --- the checker itself -------------------------------------------------------------------

PAGE = """\
Intro.

```python
x = 2
print("value:", x * 0.5, "of", 10)
```

```text
value: 1.0 of 10
```

<!-- docs-test: skip needs a GPU -->
```python
raise RuntimeError("never runs")
```

<!-- docs-test: slow -->
```python
y = x + 1
```

```python
print(f"{1 / 3:.4f} done")
```
```text
0.33 done
```
"""


def test_parse_reads_markers_and_outputs() -> None:
    blocks = parse(PAGE, "page.md")
    assert [b.mode for b in blocks] == ["run", "skip", "slow", "run"]
    assert blocks[0].expected == "value: 1.0 of 10\n"
    assert blocks[1].reason == "needs a GPU" and blocks[1].expected is None
    assert blocks[3].expected == "0.33 done\n"
    assert blocks[0].line == 3


def test_run_page_runs_in_order_and_compares_output() -> None:
    run_page(parse(PAGE, "page.md"), slow=True)
    run_page(parse(PAGE, "page.md"), slow=False)


def test_run_page_fails_on_wrong_output_and_on_errors() -> None:
    wrong = PAGE.replace("value: 1.0 of 10", "value: 1.5 of 10")
    with pytest.raises(AssertionError, match="page.md:3 printed"):
        run_page(parse(wrong, "page.md"), slow=False)
    broken = PAGE.replace("y = x + 1", "y = undefined_name")
    run_page(parse(broken, "page.md"), slow=False)  # the slow block is not run
    with pytest.raises(AssertionError, match="raised NameError"):
        run_page(parse(broken, "page.md"), slow=True)


def test_requires_skips_blocks_whose_modules_are_missing() -> None:
    page = (
        "<!-- docs-test: requires no_such_module_here -->\n```python\nraise RuntimeError\n```\n"
        "<!-- docs-test: requires json, math -->\n```python\nimport json\nprint(1)\n```\n"
        "```text\n1\n```\n"
    )
    blocks = parse(page, "p.md")
    assert [b.requires for b in blocks] == [("no_such_module_here",), ("json", "math")]
    run_page(blocks, slow=False)
    marked = parse("<!-- docs-test: requires json -->\n<!-- docs-test: slow -->\n"
                   "```python\npass\n```\n", "p.md")  # fmt: skip
    assert (marked[0].mode, marked[0].requires) == ("slow", ("json",))


def test_skip_needs_a_reason_and_markers_are_known() -> None:
    with pytest.raises(ValueError, match="needs a reason"):
        parse("<!-- docs-test: skip -->\n```python\npass\n```\n", "p.md")
    with pytest.raises(ValueError, match="unknown docs-test marker"):
        parse("<!-- docs-test: later -->\n```python\npass\n```\n", "p.md")


@pytest.mark.parametrize(
    ("got", "want", "ok"),
    [
        ("min h: 0.17523", "min h: 0.175", True),
        ("min h: 0.1802", "min h: 0.175", False),
        ("1,826 passed", "1826 passed", True),
        ("256 of 256", "255 of 256", False),
        ("12.5%", "12.4%", True),
        ("12.5%", "11.0%", False),
        ("a 1\nb 2\nc 3\n", "a 1\n...\nc 3\n", True),
        ("a 1\nb 2\n", "a 1\nb 2\nc 3\n", False),
        ("collisions: 0", "collisions: 1", False),
        ("speed 1.0e-3", "speed 1.01e-3", True),
        ("x  =   1", "x = 1", True),
        ("status: solved", "status: relaxed", False),
    ],
)
def test_output_comparison(got: str, want: str, ok: bool) -> None:
    assert output_matches(got, want) is ok
