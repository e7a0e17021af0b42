"""Sampling helpers: boxes, labels from occupancy, dilation, free-space rejection sampling."""

from __future__ import annotations

import pytest
import torch

from torchcbf.barriers import Ball, Ellipse
from torchcbf.learning import (
    dilate,
    label_states,
    make_generator,
    occupancy_from_barrier,
    sample_free,
    sample_labelled,
    uniform_box,
)


def test_uniform_box_bounds_shape_and_reproducibility(device, dtype) -> None:
    lo = torch.tensor([-1.0, 2.0, 0.0], device=device, dtype=dtype)
    hi = torch.tensor([1.0, 5.0, 0.1], device=device, dtype=dtype)
    x = uniform_box(lo, hi, 5000, seed=3)
    assert x.shape == (5000, 3) and x.dtype == dtype and x.device.type == device.type
    assert bool((x >= lo).all()) and bool((x <= hi).all())
    # roughly uniform: mean of each coordinate near the box centre (5000 samples: 4 sigma)
    sd = (hi - lo) / (12**0.5) / (5000**0.5)
    assert bool(((x.mean(0) - (lo + hi) / 2).abs() < 4 * sd).all())
    assert torch.equal(x, uniform_box(lo, hi, 5000, seed=3))
    assert not torch.equal(x, uniform_box(lo, hi, 5000, seed=4))
    gen = make_generator(seed=3, device=device)
    assert torch.equal(x, uniform_box(lo, hi, 5000, generator=gen))


def test_uniform_box_errors() -> None:
    with pytest.raises(ValueError, match="high must exceed low"):
        uniform_box([0.0, 1.0], [1.0, 1.0], 3)
    with pytest.raises(ValueError, match="same shape"):
        uniform_box([0.0, 1.0], [1.0], 3)
    with pytest.raises(ValueError, match="num"):
        uniform_box([0.0], [1.0], 0)
    with pytest.raises(TypeError, match="generator"):
        uniform_box([0.0], [1.0], 2, generator=1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="device 'bogus' is not a device torch knows"):
        uniform_box([-1.0, 0.0], [1.0, 2.0], 3, device="bogus")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device 'cuda': this torch has no CUDA device"):
            uniform_box([-1.0, 0.0], [1.0, 2.0], 3, device="cuda")
    occupied = occupancy_from_barrier(Ball([0.0, 0.0], 0.5))
    for margin in (-0.5, float("nan")):
        with pytest.raises(ValueError, match="margin must be a finite number >= 0"):
            sample_free(occupied, [-1.0, -1.0], [1.0, 1.0], 4, margin=margin)
    with pytest.raises(ValueError, match="max_rounds must be a positive int"):
        sample_free(occupied, [-1.0, -1.0], [1.0, 1.0], 4, max_rounds=0)


def test_labels_match_a_loop_over_states(dtype) -> None:
    ell = Ellipse(torch.tensor([[0.0, 0.0], [2.0, 1.0]]), torch.tensor([[1.0, 0.5], [0.3, 0.8]]))
    ell = ell.to(dtype)
    occ = occupancy_from_barrier(ell)
    data = sample_labelled(occ, [-2.0, -2.0], [3.0, 3.0], 400, seed=1, dtype=dtype)
    for x, safe in zip(data.x, data.safe, strict=True):
        inside0 = (x[0] / 1.0) ** 2 + (x[1] / 0.5) ** 2 < 1
        inside1 = ((x[0] - 2) / 0.3) ** 2 + ((x[1] - 1) / 0.8) ** 2 < 1
        assert bool(safe) == (not (inside0 or inside1))
    assert 0 < int(data.safe.sum()) < 400  # both classes present
    # batch dims: [2, 3, n] -> [2, 3]
    assert label_states(data.x[:6].reshape(2, 3, 2), occ).shape == (2, 3)
    with pytest.raises(ValueError, match="occupied must map"):
        label_states(data.x, lambda x: x > 0)  # [N, 2], not [N]


def test_dilate_grows_a_disk_by_the_radius(dtype) -> None:
    r, d = 1.0, 0.3
    occ = occupancy_from_barrier(Ball([0.5, -0.5], r).to(dtype))
    grown = dilate(occ, d, probes=32)
    ang = torch.linspace(0, 6.28, 97, dtype=dtype)
    ring = torch.stack([ang.cos(), ang.sin()], -1)
    centre = torch.tensor([0.5, -0.5], dtype=dtype)
    # with 32 directions the worst angular miss is pi/32: cos(pi/32) d > 0.99 d
    assert bool(grown(centre + (r + 0.99 * d) * ring).all())
    assert not bool(grown(centre + (r + d + 1e-3) * ring).any())
    assert not bool(occ(centre + (r + 0.5 * d) * ring).any())
    # other state components are untouched (index picks the plane)
    x3 = torch.cat([centre + (r + 0.5 * d) * ring, torch.full((97, 1), 7.0, dtype=dtype)], -1)
    occ3 = occupancy_from_barrier(Ball([0.5, -0.5], r, index=(0, 1)).to(dtype))
    assert bool(dilate(occ3, d, index=(0, 1))(x3).all())


def test_sample_free_respects_the_margin(device) -> None:
    ball = Ball([0.0, 0.0], 1.0).to(device)
    occ = occupancy_from_barrier(ball)
    lo = torch.tensor([-2.0, -2.0], device=device)
    x = sample_free(occ, lo, lo.abs(), 3000, margin=0.2, seed=0)
    assert x.shape == (3000, 2) and x.device.type == device.type
    assert bool((x.norm(dim=-1) > 1.0 + 0.99 * 0.2).all())
    # and it fills the rest of the box (some states close to the margin)
    assert bool((x.norm(dim=-1) < 1.3).any())
    with pytest.raises(ValueError, match="free states"):
        sample_free(lambda x: torch.ones(x.shape[:-1], dtype=torch.bool), [0.0], [1.0], 5)


def test_sample_free_finds_a_small_free_region() -> None:
    """A box 1% free: chunks grow with the rejection rate seen."""

    def occupied(x):
        return ~((x[..., 0] < 0.1) & (x[..., 1] < 0.1))

    x = sample_free(occupied, [0.0, 0.0], [1.0, 1.0], 2000, seed=3, max_rounds=10)
    assert x.shape == (2000, 2) and not bool(occupied(x).any())
    with pytest.raises(ValueError, match=r"about 0 of the box is free"):
        sample_free(lambda x: torch.ones(x.shape[:-1], dtype=torch.bool), [0.0], [1.0], 5,
                    max_rounds=3)  # fmt: skip


def test_a_nan_barrier_value_counts_as_occupied() -> None:
    """``sqrt(1 - |x|^2)`` is NaN outside the unit disc: those states are not free."""
    occ = occupancy_from_barrier(lambda x: torch.sqrt(1 - (x**2).sum(-1)))
    assert occ(torch.tensor([[0.0, 0.0], [2.0, 0.0]])).tolist() == [False, True]
    data = sample_labelled(occ, [-2.0, -2.0], [2.0, 2.0], 500, seed=0)
    assert not bool((data.x[data.safe].norm(dim=-1) > 1).any())


def test_make_generator_takes_numpy_seeds() -> None:
    import numpy as np

    a = torch.rand(3, generator=make_generator(seed=np.int64(3)))
    assert torch.equal(a, torch.rand(3, generator=make_generator(seed=3)))
    with pytest.raises(TypeError, match="seed must be an int"):
        make_generator(seed=3.0)
