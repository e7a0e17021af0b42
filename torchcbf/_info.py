"""What this installation of torchcbf can run: versions, devices and the kernels."""

from __future__ import annotations

import platform
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple

import torch

from torchcbf._native import kernel_file
from torchcbf._version import __version__


class KernelInfo(NamedTuple):
    """One kernel (C, or Triton for CUDA): its ``name``, the ``version`` of the source
    this torchcbf calls, whether it ``loaded`` (built, loadable, of that version), the
    ``path`` of the built library (``None``: not built or Triton missing), the ``devices``
    it runs on, and what runs without it
    (``fallback``)."""

    name: str
    version: int
    loaded: bool
    path: str | None
    devices: tuple[str, ...]
    fallback: str


def _kernels() -> list[tuple[str, ModuleType, str]]:
    from torchcbf.barriers import native
    from torchcbf.filters import realtime
    from torchcbf.mppi import _rollout
    from torchcbf.qp import _dual_native

    return [
        ("qp: dual active set", _dual_native, "solve_qp's torch methods"),
        ("barriers: Lie terms of quadrics", native, "the torch closed forms"),
        ("filters: real-time filter", realtime, "the filter's general path"),
        ("mppi: rollouts and built-in costs", _rollout, "MPPI's torch path"),
    ]


def kernels() -> list[KernelInfo]:
    """The four C kernels and the two Triton kernels, and their state (loading each one, so a
    missing or stale build gives its warning here)."""
    found = []
    for name, module, fallback in _kernels():
        path = kernel_file(Path(module.__file__).parent, module.KERNEL_STEM)
        found.append(
            KernelInfo(
                name=name,
                version=int(module.KERNEL_VERSION),
                loaded=bool(module.available()),
                path=None if path is None else str(path),
                devices=("cpu",),
                fallback=fallback,
            )
        )
    from torchcbf import _triton
    from torchcbf.mppi import _triton as mppi_triton
    from torchcbf.qp import _dual_triton

    for name, version, fallback in (
        ("mppi: rollouts and built-in costs (Triton)", mppi_triton.KERNEL_VERSION,
         "MPPI's torch path on CUDA"),
        ("qp: dual active set (Triton)", _dual_triton.KERNEL_VERSION,
         "the dual method in torch on CUDA"),
    ):  # fmt: skip
        found.append(
            KernelInfo(
                name=name,
                version=int(version),
                loaded=_triton.available(),
                path=_triton.location(),
                devices=("cuda",),
                fallback=fallback,
            )
        )
    return found


def info() -> dict[str, Any]:
    """A report of this installation as a plain dict: torchcbf's and torch's versions,
    Python and the platform, the devices torch sees, the threads it uses, and every C kernel
    (:class:`KernelInfo` as a dict). ``torchcbf info`` prints it."""
    cuda = range(torch.cuda.device_count()) if torch.cuda.is_available() else range(0)
    devices = ["cpu", *(f"cuda:{i} ({torch.cuda.get_device_name(i)})" for i in cuda)]
    return {
        "torchcbf": __version__,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "devices": devices,
        "threads": torch.get_num_threads(),
        "kernels": [k._asdict() for k in kernels()],
    }


def format_info(report: dict[str, Any]) -> str:
    """:func:`info` as lines of text."""
    lines = [f"{key}: {report[key]}" for key in ("torchcbf", "torch", "python", "platform")]
    lines.append(f"devices: {', '.join(report['devices'])}")
    lines.append(f"threads: {report['threads']}")
    lines.append("kernels:")
    for k in report["kernels"]:
        state = "loaded" if k["loaded"] else f"NOT LOADED (runs: {k['fallback']})"
        where = k["path"] or ("not built" if "cpu" in k["devices"] else "Triton not installed")
        lines.append(f"  {k['name']}: version {k['version']}, {state}, {where}")
    return "\n".join(lines)
