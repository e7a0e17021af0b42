"""Host traffic of a computation, found without an accelerator.

A step meant to stay on the device must not wait for it. Run it on the ``meta`` device
(shapes and dtypes, no data) inside :class:`HostTraffic`:

- a read of a device value (``.item()``, ``bool``, ``float``, ``.tolist()``, a boolean
  mask) raises there, since a meta tensor has no value to read;
- what a CPU run cannot show, and CUDA pays with a stream synchronisation, is recorded: an
  index made of a Python list (its indices are copied to the device on every call),
  ``torch.tensor``/``torch.as_tensor`` of Python data onto the device, and a copy of a CPU
  tensor onto the device.

``HostTraffic.events`` maps ``(kind, "file:line")`` (the innermost torchcbf frame) to a count.
A module of its own so that a test imports it by a name no other folder's conftest shadows.
"""

from __future__ import annotations

import collections
import traceback
from typing import Any

import torch
from torch.overrides import TorchFunctionMode


def _list_index(index: Any) -> bool:
    if isinstance(index, list):
        return True
    return isinstance(index, tuple) and any(isinstance(i, list) for i in index)


def _on_device(device: Any) -> bool:
    return device is not None and torch.device(device).type != "cpu"


class HostTraffic(TorchFunctionMode):
    """Records the host-to-device traffic of the torch calls made inside it (see the module
    docstring)."""

    def __init__(self) -> None:
        super().__init__()
        self.events: collections.Counter[tuple[str, str]] = collections.Counter()

    @staticmethod
    def _where() -> str:
        frames = [f for f in traceback.extract_stack() if "/torchcbf/" in f.filename]
        if not frames:
            return "outside torchcbf"
        frame = frames[-1]
        return f"torchcbf/{frame.filename.split('/torchcbf/', 1)[1]}:{frame.lineno}"

    def __torch_function__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if name in ("__getitem__", "__setitem__") and len(args) > 1 and _list_index(args[1]):
            self.events[("index with a Python list", self._where())] += 1
        if func in (torch.tensor, torch.as_tensor):
            data = args[0] if args else kwargs.get("data")
            if not isinstance(data, torch.Tensor) and _on_device(kwargs.get("device")):
                self.events[(f"torch.{name} of Python data", self._where())] += 1
        out = func(*args, **kwargs)
        if name in ("to", "copy_") and isinstance(out, torch.Tensor) and out.device.type != "cpu":
            source = args[1] if name == "copy_" and len(args) > 1 else args[0]
            if isinstance(source, torch.Tensor) and source.device.type == "cpu":
                self.events[(f"{name} from a CPU tensor", self._where())] += 1
        return out
