"""argparse types shared by the command line and the benchmark scripts: a bad value exits
with status 2 and a message naming the flag (argparse adds the flag's name)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

import torch


def int_at_least(low: int) -> Callable[[str], int]:
    """An argparse type: an integer ``>= low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
        if value < low:
            wanted = "a positive integer" if low == 1 else f"an integer >= {low}"
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}")
        return value

    parse.__name__ = "positive_int" if low == 1 else f"int_at_least_{low}"
    return parse


#: an integer >= 1
positive_int = int_at_least(1)
#: an integer >= 0
non_negative_int = int_at_least(0)


def seed(text: str) -> int:
    """A first seed: an integer in ``[0, 2^32)`` (the noise streams are 32-bit)."""
    value = int_at_least(-(2**63))(text)
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"a seed lies in [0, 2^32), got {value}")
    return value


def torch_device(text: str) -> str:
    """A torch device that is here: ``cpu``, ``cuda`` or ``cuda:N`` (with CUDA available and
    that many devices), or another type torch names and this build has."""
    try:
        dev = torch.device(text)
    except RuntimeError:
        raise argparse.ArgumentTypeError(f"not a torch device: {text!r}") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise argparse.ArgumentTypeError(f"{text}, but CUDA is not available here")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise argparse.ArgumentTypeError(
                f"{text}, but there are {torch.cuda.device_count()} CUDA devices"
            )
    elif dev.type != "cpu" and not getattr(torch, dev.type, None):
        raise argparse.ArgumentTypeError(f"{text}: this torch has no {dev.type} backend")
    return text
