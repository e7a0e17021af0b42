"""The device-check tooling: the device selection of the test suite, the CPU comparison of
device answers, and scripts/device_check.sh's JSON, report and argument errors."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _devices import assert_same_answers, device_matches_cpu, devices, triton_target

ROOT = Path(__file__).resolve().parents[1]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_devices_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TORCHCBF_TEST_DEVICES", raising=False)
    assert devices() == ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    monkeypatch.setenv("TORCHCBF_TEST_DEVICES", " cpu, cpu ")
    assert devices() == ["cpu"]
    monkeypatch.setenv("TORCHCBF_TEST_DEVICES", "tpu")
    with pytest.raises(pytest.UsageError, match=r"\['tpu'\] not present"):
        devices()
    if not torch.cuda.is_available():
        monkeypatch.setenv("TORCHCBF_TEST_DEVICES", "cpu,cuda")
        with pytest.raises(pytest.UsageError, match=r"\['cuda'\] not present"):
            devices()


def test_same_answers_tolerances_and_exact_leaves() -> None:
    x = torch.linspace(0, 1, 5, dtype=torch.float64)
    status = torch.tensor([0, 1, 0])
    assert_same_answers((x, status, "path", None), (x + 1e-12, status.clone(), "path", None))
    with pytest.raises(AssertionError, match=r"out\.0 on device differs"):
        assert_same_answers((x, status), (x + 1e-6, status))
    with pytest.raises(AssertionError, match=r"out\.1 on device differs"):
        assert_same_answers((x, status), (x, torch.tensor([0, 1, 2])))
    with pytest.raises(AssertionError, match="'torch' on device, 'kernel' on the CPU"):
        assert_same_answers({"path": "torch"}, {"path": "kernel"})
    x32 = x.float()
    assert_same_answers(x32, x32 * (1 + 5e-5), torch.float32)
    with pytest.raises(AssertionError):
        assert_same_answers(x32, x32 * (1 + 5e-3), torch.float32)
    assert_same_answers(x32, x32 * (1 + 5e-3), torch.float32, rtol=1e-2)


def test_device_matches_cpu_checks_where_results_live() -> None:
    out = device_matches_cpu(lambda dev: torch.ones(3, device=dev), torch.device("cpu"))
    assert out.device.type == "cpu"
    with pytest.raises(AssertionError, match="is on meta, not cpu"):
        device_matches_cpu(lambda dev: torch.ones(3, device="meta"), torch.device("cpu"))
    with pytest.raises(TypeError, match="cannot compare out of type object"):
        device_matches_cpu(lambda dev: object(), torch.device("cpu"))


def _run_json(device: str, value: float, rate: float, commit: str = "abc123") -> dict:
    return {
        "device": device,
        "card": "NVIDIA H200" if device == "cuda" else "x86_64",
        "date": "2026-11-26T19:00:00+00:00",
        "commit": commit,
        "dirty": False,
        "torch": "2.11.0",
        "load_average": 0.5,
        "quick": False,
        "figures": [
            {
                "name": "mppi.builtin.K16384.H100",
                "value": value,
                "unit": "s/call",
                "label": "MPPI, built-in model and cost terms, K=16384, H=100",
            },
            {
                "name": "qp.fwd_bwd.n4.m8.float32",
                "value": rate,
                "unit": "QP/s",
                "label": "solve_qp forward+backward, B=1000000, n=4, m=8, float32",
            },
        ],
        "errors": [{"name": "filter.balls8_box.float64", "error": "RuntimeError: boom"}],
        "skipped": ["filter.balls8_box.float32"],
        "steps": [{"step": "tests", "rc": 1, "seconds": 80.0, "note": "pytest"}],
        "tests": {
            "present": True,
            "total": 10,
            "failed": 1,
            "skipped": 2,
            "passed": 7,
            "seconds": 12.0,
            "failed_ids": ["tests.sim.test_simulate::test_x[cuda]"],
        },
    }


def test_report_tables(tmp_path: Path) -> None:
    report = _script("device_report")
    gpu = _run_json("cuda", 3.0e-4, 2.0e7)
    cpu = _run_json("cpu", 6.0e-3, 1.0e6)
    alone = report.render(gpu)
    assert "### torchcbf on NVIDIA H200" in alone and "commit abc123" in alone
    assert (
        "| `mppi.builtin.K16384.H100` | built-in model and cost terms, K=16384, H=100 | 300 us |"
        in alone
    )
    assert "20.00 MQP/s" in alone
    assert "FAILED: RuntimeError: boom" in alone and "skipped (time budget)" in alone
    assert "| tests | 1 | 80.0 | pytest |" in alone
    assert "7 passed, 1 failed, 2 skipped of 10" in alone and "test_x[cuda]" in alone
    beside = report.render(gpu, cpu)
    # a time: the CPU's over the GPU's; a rate: the GPU's over the CPU's
    assert "| 300 us | 6.00 ms | 20.0 |" in beside
    assert "| 20.00 MQP/s | 1.00 MQP/s | 20.0 |" in beside
    path = tmp_path / "gpu.json"
    path.write_text(json.dumps(gpu))
    (tmp_path / "bad.json").write_text("{}")
    cmd = [sys.executable, str(ROOT / "scripts" / "device_report.py")]
    done = subprocess.run([*cmd, str(path)], capture_output=True, text=True, check=True)
    assert done.stdout == alone
    bad = subprocess.run([*cmd, str(tmp_path / "bad.json")], capture_output=True, text=True)
    assert bad.returncode != 0 and "no 'figures' list" in bad.stderr


def test_collect_reads_figures_steps_and_junit(tmp_path: Path) -> None:
    report = _script("device_report")
    (tmp_path / "figures.json").write_text(json.dumps({"card": "c", "figures": []}))
    (tmp_path / "steps.tsv").write_text("install\t0\t3.5\tpip\ntests\t1\t9.0\tpytest\tnote\n")
    (tmp_path / "tests.xml").write_text(
        '<testsuites><testsuite><testcase classname="a" name="t1" time="1.5"/>'
        '<testcase classname="a" name="t2" time="0.5"><failure message="x"/></testcase>'
        '<testcase classname="b" name="t3"><skipped/></testcase></testsuite></testsuites>'
    )
    metrics = {"results": {"reach-avoid": {"settings": {"seeds": 10}, "seconds": 2.5}}}
    (tmp_path / "scenario_a.json").write_text(json.dumps(metrics))
    out = tmp_path / "device_check.json"
    cmd = [sys.executable, str(ROOT / "scripts" / "device_report.py")]
    subprocess.run([*cmd, "--collect", str(tmp_path), str(out)], check=True)
    data = json.loads(out.read_text())
    assert data["card"] == "c"
    (scenario,) = data["figures"]
    assert scenario["name"] == "scenario.reach-avoid" and scenario["value"] == 2.5
    assert "| `scenario.reach-avoid` | seeds=10 | 2.50 s |" in report.render(data)
    assert data["steps"][1] == {"step": "tests", "rc": 1, "seconds": 9.0, "note": "pytest\tnote"}
    assert data["tests"] == {
        "present": True, "total": 3, "failed": 1, "skipped": 1, "passed": 1,
        "failed_ids": ["a::t2"], "seconds": 2.0,
    }  # fmt: skip
    # before any piece exists: an empty JSON that the report still renders
    empty = tmp_path / "empty"
    empty.mkdir()
    assert report.collect(empty, empty / "j.json") == 0
    assert json.loads((empty / "j.json").read_text()) == {
        "figures": [], "steps": [], "tests": {"present": False}
    }  # fmt: skip
    text = report.render(json.loads((empty / "j.json").read_text()))
    assert "### torchcbf on an unknown device" in text
    assert report.strict_json({"a": [float("nan"), 1.0]}) == {"a": [None, 1.0]}


def test_collect_and_report_the_kernel_launch_settings(tmp_path: Path) -> None:
    report = _script("device_report")
    settings = [
        {"block": 32, "warps": 1, "maxnreg": None, "first_s": 9.0, "median_ms": 21.7,
         "regs": 255, "spills": 0, "card": "H", "dtype": "float32", "states": 1000000,
         "solved": 999990, "solved_default": 999990, "max_dx": 0.0, "layout": "strides"},
        {"block": 16, "warps": 1, "maxnreg": 128, "first_s": 9.0, "median_ms": None,
         "card": "H", "dtype": "float64", "states": 1000000, "solved": 5,
         "solved_default": 5, "max_dx": 2.5e-9},
    ]  # fmt: skip
    (tmp_path / "kernels.json").write_text(json.dumps(settings))
    out = tmp_path / "device_check.json"
    assert report.collect(tmp_path, out) == 0
    data = json.loads(out.read_text())
    assert data["kernels"] == settings
    text = report.render(data)
    row = "| float32 | 1000000 | 32 | 1 | - | strides | 21.700 | 255 | 0 | 999990 | 0.0e+00 |"
    assert row in text
    # a run before the kernel read strides copied its inputs into planes
    assert "| float64 | 1000000 | 16 | 1 | 128 | planes | - | - | - | 5 | 2.5e-09 |" in text


def test_kernel_settings_from_their_names() -> None:
    kernels = _script("device_kernels")
    assert kernels.parse_settings(None) == kernels.SETTINGS
    assert kernels.parse_settings(["16x1", "32x1x128"]) == ((16, 1, None), (32, 1, 128))
    assert all(kernels.parse_settings([kernels._name(s)]) == (s,) for s in kernels.SETTINGS)


@pytest.mark.slow
def test_device_figures_quick_on_the_cpu(tmp_path: Path) -> None:
    """One small figure end to end: the JSON names the device, the commit and the figure."""
    out = tmp_path / "figures.json"
    cmd = [
        sys.executable,
        str(ROOT / "scripts" / "device_figures.py"),
        "--device",
        "cpu",
        "--quick",
        "--only",
        "qp.fwd_bwd.n4.m8.float64",
        "--out",
        str(out),
    ]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=ROOT)
    data = json.loads(out.read_text())
    assert data["device"] == "cpu" and data["quick"] and not data["errors"]
    (fig,) = data["figures"]
    assert fig["name"] == "qp.fwd_bwd.n4.m8.float64" and fig["unit"] == "QP/s"
    assert fig["value"] > 0 and fig["solved_fraction"] > 0.99 and fig["B"] == 10_000


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--device", "tpu", "--out", "{tmp}"], "--device must be cpu or cuda"),
        (["--bogus"], "unknown argument '--bogus'"),
        ([], "no output folder"),
    ],
)
def test_device_check_refuses_bad_arguments(tmp_path: Path, args: list[str], message: str):
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    argv = [a.replace("{tmp}", str(tmp_path)) for a in args]
    done = subprocess.run(
        ["bash", str(ROOT / "scripts" / "device_check.sh"), *argv],
        capture_output=True,
        text=True,
        env=env,
    )
    assert done.returncode == 2 and message in done.stderr


def test_device_check_without_cuda_fails_before_any_work(tmp_path: Path) -> None:
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    done = subprocess.run(
        [
            "bash",
            str(ROOT / "scripts" / "device_check.sh"),
            "--out",
            str(tmp_path),
            "--python",
            sys.executable,
            "--no-install",
        ],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2
    assert "torch.cuda.is_available() is False" in done.stderr
    assert not (tmp_path / "device_check.json").exists()


@pytest.mark.skipif(
    getattr(triton_target(), "type", None) != "cpu",
    reason="the count runs the QP's Triton kernel on the CPU: Triton and TRITON_INTERPRET=1",
)
def test_the_launch_count_sees_the_gpus_path(monkeypatch: pytest.MonkeyPatch) -> None:
    from torchcbf.filters import realtime
    from torchcbf.qp import _dual, solve

    counter = _script("count_launches")
    monkeypatch.setattr(_dual, "dual_engine", _dual.dual_engine)  # the script replaces it
    monkeypatch.setattr(solve, "dual_engine", solve.dual_engine)
    path, ops = counter.count(torch.float32, realtime.MAX_BATCH + 1)  # fewer: the C path
    assert path == "torch/active_set_triton"
    names = {name for name, _, _ in ops}
    assert "view" not in names and "aminmax" not in names  # a CPU checks with amax and amin
    assert 100 < len(ops) < 1000 and all(size >= 0 for _, _, size in ops)
    assert any(where.startswith("qp/solve.py") for _, where, _ in ops)
