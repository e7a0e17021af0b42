"""Markdown tables from the JSON of ``scripts/device_check.sh`` (``device_check.json``).

One table of figures (with the figure of a second JSON beside each, e.g. a CPU run, and
how many times faster the first is), then the steps, the test counts and any errors.

    python scripts/device_report.py out/device_check.json
    python scripts/device_report.py gpu/device_check.json --cpu cpu/device_check.json --out gpu.md
    python scripts/device_report.py --collect WORK out/device_check.json   # the JSON itself

``--collect WORK`` writes the JSON from the pieces ``scripts/device_check.sh`` leaves in its
work folder: ``figures.json`` (scripts/device_figures.py), ``tests.xml`` (pytest),
``steps.tsv`` and ``scenario_*.json`` (a scenario run's metrics.json: its simulation seconds
become a figure); it uses only the standard library, so it runs after every step.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import xml.etree.ElementTree as ET
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
    card = data.get("card") or "an unknown device"
    lines = [f"### torchcbf on {card}", "", f"- run: {_who(data)}"]
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
    kernels = data.get("kernels") or []
    if kernels:
        lines += [
            "",
            "QP kernel launch settings (scripts/device_kernels.py, the filter's QP):",
            "",
            "| dtype | states | block | warps | maxnreg | inputs | median ms | regs | spills "
            "| solved | max dx |",
            "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|",
        ]
        for k in kernels:
            median = "-" if k.get("median_ms") is None else f"{k['median_ms']:.3f}"
            lines.append(
                f"| {k['dtype']} | {k['states']} | {k['block']} | {k['warps']} | "
                f"{k['maxnreg'] or '-'} | {k.get('layout', 'planes')} | {median} | "
                f"{k.get('regs', '-')} | "
                f"{k.get('spills', '-')} | {k['solved']} | {k['max_dx']:.1e} |"
            )
    tests = data.get("tests") or {}
    if tests.get("present"):
        lines += [
            "",
            f"Tests on {data.get('device')}: {tests['passed']} passed, {tests['failed']} failed, "
            f"{tests['skipped']} skipped of {tests['total']} ({tests['seconds']:.0f} s).",
        ]
        lines += [f"- failed: `{t}`" for t in tests.get("failed_ids", [])]
    return "\n".join(lines) + "\n"


def strict_json(obj: Any) -> Any:
    """JSON without NaN/Infinity literals (``null`` instead)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: strict_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [strict_json(v) for v in obj]
    return obj


def junit_summary(path: Path) -> dict[str, Any]:
    """Counts and the failed tests' ids from a pytest JUnit XML file."""
    if not path.is_file():
        return {"present": False}
    root = ET.parse(path).getroot()
    cases = list(root.iter("testcase"))
    failed, skipped = [], 0
    for case in cases:
        ident = f"{case.get('classname')}::{case.get('name')}"
        if case.find("failure") is not None or case.find("error") is not None:
            failed.append(ident)
        elif case.find("skipped") is not None:
            skipped += 1
    return {
        "present": True,
        "total": len(cases),
        "failed": len(failed),
        "skipped": skipped,
        "passed": len(cases) - len(failed) - skipped,
        "failed_ids": failed[:200],
        "seconds": sum(float(c.get("time") or 0) for c in cases),
    }


def collect(work: Path, out: Path) -> int:
    """``out`` (device_check.json) from ``work``'s ``figures.json`` (scripts/device_figures.py),
    pytest's JUnit file ``tests.xml``, ``kernels.json`` (scripts/device_kernels.py) and the
    step table ``steps.tsv`` (one line per step: name, exit status, seconds, note;
    tab-separated), each where present."""
    figures_path = work / "figures.json"
    result: dict[str, Any] = (
        json.loads(figures_path.read_text()) if figures_path.is_file() else {"figures": []}
    )
    steps = []
    steps_path = work / "steps.tsv"
    if steps_path.is_file():
        for line in steps_path.read_text().splitlines():
            name, rc, seconds, *note = line.split("\t")
            steps.append(
                {"step": name, "rc": int(rc), "seconds": float(seconds), "note": "\t".join(note)}
            )
    result["steps"] = steps
    result["tests"] = junit_summary(work / "tests.xml")
    kernels_path = work / "kernels.json"  # scripts/device_kernels.py
    if kernels_path.is_file():
        result["kernels"] = json.loads(kernels_path.read_text())
    for path in sorted(work.glob("scenario_*.json")):  # a scenario run's metrics.json
        for name, res in json.loads(path.read_text()).get("results", {}).items():
            settings = res.get("settings", {})
            size = ", ".join(f"{k}={v}" for k, v in settings.items())
            result["figures"].append(
                {
                    "name": f"scenario.{name}",
                    "value": res.get("seconds"),
                    "unit": "s",
                    "label": f"scenario {name} simulation time (figures apart), {size}",
                    "summary": res.get("summary"),
                }
            )
    out.write_text(json.dumps(strict_json(result), indent=1))
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", type=Path, help="device_check.json of the run to report")
    parser.add_argument("--cpu", type=Path, help="a second device_check.json shown beside")
    parser.add_argument("--out", type=Path, help="write the Markdown here (default: print)")
    parser.add_argument(
        "--collect",
        type=Path,
        metavar="WORK",
        help="write JSON (the positional path) from WORK's pieces and exit",
    )
    args = parser.parse_args()
    if args.collect is not None:
        return collect(args.collect, args.json)
    text = render(_load(args.json), _load(args.cpu) if args.cpu else None)
    if args.out:
        args.out.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
