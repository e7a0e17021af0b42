"""The shared input checks: ``broadcast_shapes`` against ``torch.broadcast_shapes``."""

from __future__ import annotations

import itertools
import random

import pytest
import torch

from torchcbf._checks import broadcast_shapes, check_batch_match


def test_broadcast_shapes_matches_torch_on_every_small_case():
    dims = [(), (1,), (3,), (0,), (2, 1), (1, 3), (2, 3), (4, 1, 3), (0, 3), (1, 1, 1)]
    for combo in itertools.chain(
        itertools.product(dims, repeat=2), itertools.product(dims[:6], repeat=3)
    ):
        try:
            expected = tuple(torch.broadcast_shapes(*combo))
        except RuntimeError:
            with pytest.raises(RuntimeError, match="do not broadcast"):
                broadcast_shapes(*combo)
            continue
        assert broadcast_shapes(*combo) == expected, combo


def test_broadcast_shapes_random_and_torch_size():
    rng = random.Random(0)
    for _ in range(200):
        base = [rng.choice([1, 2, 5]) for _ in range(rng.randint(0, 4))]
        shapes = [
            torch.Size([d if rng.random() < 0.6 else 1 for d in base[rng.randint(0, len(base)) :]])
            for _ in range(rng.randint(1, 4))
        ]
        assert broadcast_shapes(*shapes) == tuple(torch.broadcast_shapes(*shapes))
    assert broadcast_shapes() == ()


def test_check_batch_match_names_both_arguments():
    with pytest.raises(ValueError, match=r"x \(2, 3\) and u \(4, 3\)"):
        check_batch_match("x", torch.zeros(2, 3), "u", torch.zeros(4, 3))
    check_batch_match("x", torch.zeros(2, 3), "u", torch.zeros(1, 3))
