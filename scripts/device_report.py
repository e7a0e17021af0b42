"""Markdown tables from the JSON of ``scripts/device_check.sh`` (``device_check.json``).

One table of figures (with the figure of a second JSON beside each, e.g. a CPU run, and
how many times faster the first is), then the steps, the test counts and any errors.

    python scripts/device_report.py out/device_check.json
    python scripts/device_report.py gpu/device_check.json --cpu cpu/device_check.json --out gpu.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

#: units where a smaller figure is better (times); the others (rates) are better larger
TIME_UNITS = {"s/call", "s"}


def _load(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise SystemExit(f"device_report: cannot read {path}: {err}") from err
    if not isinstance(data, dict) or not isinstance(data.get("figures"), list):
        raise SystemExit(f"device_report: {path} has no 'figures' list (not a device_check JSON)")
    return data


def _value(value: float | None, unit: str) -> str:
    if value is None:
        return "-"
    if unit in TIME_UNITS:
        if value < 1e-3:
            return f"{value * 1e6:.0f} us"
        if value < 1.0:
            return f"{value * 1e3:.2f} ms"
        return f"{value:.2f} s"
    if value >= 1e6:
        return f"{value / 1e6:.2f} M{unit}"
    if value >= 1e3:
        return f"{value / 1e3:.1f} k{unit}"
    return f"{value:.3g} {unit}"


def _who(data: dict[str, Any]) -> str:
    commit = (data.get("commit") or "unknown")[:10] + (" (dirty)" if data.get("dirty") else "")
    quick = ", --quick sizes" if data.get("quick") else ""
    return (
        f"{data.get('card')} ({data.get('device')}), {data.get('date')}, commit {commit}, "
        f"torch {data.get('torch')}, load {data.get('load_average', 0):.1f}{quick}"
    )


def render(data: dict[str, Any], ref: dict[str, Any] | None = None) -> str:
    """The Markdown report of one JSON, with ``ref``'s figures beside where given."""
    lines = [f"### torchcbf on {data.get('card')}", "", f"- run: {_who(data)}"]
    if ref is not None:
        lines.append(f"- beside: {_who(ref)}")
    lines.append("")
    ref_figs = {f["name"]: f for f in (ref or {}).get("figures", [])}
    head = "| figure | size | value |"
    rule = "|---|---|---:|"
    if ref is not None:
        head += f" {ref.get('device')} |  times faster |"
        rule += "---:|---:|"
    lines += [head, rule]
    for fig in data["figures"]:
        unit = fig.get("unit", "")
        size = fig.get("label", fig["name"]).split(", ", 1)[-1]
        row = f"| `{fig['name']}` | {size} | {_value(fig.get('value'), unit)} |"
        if ref is not None:
            other = ref_figs.get(fig["name"])
            if other is None or other.get("value") is None or not fig.get("value"):
                row += " - | - |"
            else:
                a, b = fig["value"], other["value"]
                faster = b / a if unit in TIME_UNITS else a / b
                note = "" if other.get("label") == fig.get("label") else " (other size)"
                row += f" {_value(b, other.get('unit', unit))}{note} | {faster:.1f} |"
        lines.append(row)
    for err in data.get("errors", []):
        lines.append(
            f"| `{err['name']}` | FAILED: {err['error'][:120]} | - |"
            + (" - | - |" if ref is not None else "")
        )
    for name in data.get("skipped", []):
        lines.append(
            f"| `{name}` | skipped (time budget) | - |" + (" - | - |" if ref is not None else "")
        )
    steps = data.get("steps") or []
    if steps:
        lines += ["", "| step | exit | seconds | what |", "|---|---:|---:|---|"]
        lines += [f"| {s['step']} | {s['rc']} | {s['seconds']:.1f} | {s['note']} |" for s in steps]
    tests = data.get("tests") or {}
    if tests.get("present"):
        lines += [
            "",
            f"Tests on {data.get('device')}: {tests['passed']} passed, {tests['failed']} failed, "
            f"{tests['skipped']} skipped of {tests['total']} ({tests['seconds']:.0f} s).",
        ]
        lines += [f"- failed: `{t}`" for t in tests.get("failed_ids", [])]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", type=Path, help="device_check.json of the run to report")
    parser.add_argument("--cpu", type=Path, help="a second device_check.json shown beside")
    parser.add_argument("--out", type=Path, help="write the Markdown here (default: print)")
    args = parser.parse_args()
    text = render(_load(args.json), _load(args.cpu) if args.cpu else None)
    if args.out:
        args.out.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
