"""argparse types shared by the command line and the benchmark scripts: a bad value exits
with status 2 and a message naming the flag (argparse adds the flag's name)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from torchcbf._checks import check_device


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
    """A torch device this machine has (:func:`torchcbf._checks.check_device`)."""
    try:
        check_device(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text
