"""What a run records besides its metrics: the software it ran on, and strict JSON.

Metrics hold ``nan`` for events that never happened (e.g. the time of a goal never
reached). JSON has no NaN: :func:`strict` writes them as ``null``, so every JSON parser
reads the file, and ``null`` always means "did not happen" or "undefined".
"""

from __future__ import annotations

import math
import platform
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcbf._version import __version__


def strict(value: Any) -> Any:
    """``value`` as strict JSON, ready for ``json.dumps(..., allow_nan=False)``: every
    non-finite float (nan, inf) as ``None``, tensors, arrays and tuples as lists (NumPy
    scalars as Python numbers), mappings with
    string keys, dtypes by name, anything else that is not a JSON scalar as its ``str``."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().tolist()
    if isinstance(value, (np.ndarray, np.generic)):
        value = value.tolist()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict(v) for v in value]
    if isinstance(value, torch.dtype):
        return str(value).removeprefix("torch.")
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    return str(value)


def git_commit(path: str | Path | None = None) -> str | None:
    """The commit of the source checkout holding ``path`` (this package by default), or
    ``None`` outside a git checkout."""
    where = Path(path) if path is not None else Path(__file__).resolve().parent
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=5
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() or None


def run_info(device: str | torch.device = "cpu", **extra: Any) -> dict[str, Any]:
    """Versions and machine of a run: torchcbf, torch, Python, git commit, device, threads,
    and ``extra`` (the run's own settings)."""
    dev = torch.device(device)
    info: dict[str, Any] = {
        "torchcbf": __version__,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "git_commit": git_commit(),
        "device": str(dev),
        "torch_threads": torch.get_num_threads(),
    }
    if dev.type == "cuda" and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(dev)
    return {**info, **extra}
