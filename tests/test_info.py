"""torchcbf.info(): versions, devices and the state of every kernel (C and Triton); a C
kernel that is not built warns, naming what runs instead."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
import torch

import torchcbf
from torchcbf import _triton
from torchcbf._info import format_info, kernels
from torchcbf._native import load_kernel
from torchcbf.barriers import native
from torchcbf.filters import realtime
from torchcbf.mppi import _rollout
from torchcbf.qp import _dual_native, _dual_triton


def test_info_reports_versions_devices_and_every_kernel() -> None:
    report = torchcbf.info()
    json.dumps(report)  # plain data
    assert report["torchcbf"] == torchcbf.__version__ and report["torch"] == torch.__version__
    assert report["devices"][0] == "cpu"
    cuda = torch.cuda.device_count() if torch.cuda.is_available() else 0
    assert len(report["devices"]) == 1 + cuda
    names = [k["name"] for k in report["kernels"]]
    assert len(names) == 6 and len(set(names)) == 6
    modules = (_dual_native, native, realtime, _rollout)
    found = kernels()
    for k, module in zip(found[:4], modules, strict=True):
        assert k.loaded == module.available() and k.version == module.KERNEL_VERSION
        assert not k.loaded or Path(k.path).name.startswith(module.KERNEL_STEM)
    mppi_gpu, qp_gpu = found[4:]
    for gpu in (mppi_gpu, qp_gpu):
        assert gpu.devices == ("cuda",) and gpu.loaded == _triton.available()
    assert mppi_gpu.version == _rollout.KERNEL_VERSION  # it reads the C kernel's configuration
    assert qp_gpu.version == _dual_triton.KERNEL_VERSION
    text = format_info(report)
    assert all(name in text for name in names)


def test_a_kernel_that_is_not_built_warns_once_naming_the_fallback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="torchcbf"):
        assert load_kernel(tmp_path, "_missing_kernel", "v", 1, "torch runs instead") is None
    (record,) = caplog.records
    assert "_missing_kernel is not built" in record.getMessage()
    assert record.getMessage().endswith("torch runs instead")


def test_the_info_command_prints_the_report(capsys: pytest.CaptureFixture[str]) -> None:
    from torchcbf.cli import main

    assert main(["info", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["torchcbf"] == torchcbf.__version__ and len(report["kernels"]) == 6
    assert main(["info"]) == 0
    assert "kernels:" in capsys.readouterr().out
