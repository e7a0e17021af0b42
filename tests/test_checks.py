"""The shared input checks: ``broadcast_shapes`` against ``torch.broadcast_shapes``, the
finiteness checks against ``torch.isfinite``."""

from __future__ import annotations

import itertools
import math
import random

import pytest
import torch

from torchcbf._checks import (
    behaves_as,
    broadcast_shapes,
    check_batch_match,
    check_positive_int,
    check_spd,
    honour_overrides,
    isfinite,
    rows_finite,
    stale_closed_forms,
)


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


def test_as_limit_and_check_bounds():
    from torchcbf._checks import as_limit, check_bounds

    assert as_limit("u_min", None, 3) is None
    lim = as_limit("u_min", 0.1, 3)
    assert lim.dtype == torch.float64 and lim.tolist() == [0.1, 0.1, 0.1]
    assert as_limit("u_max", [1.0, float("inf")], 2).tolist() == [1.0, float("inf")]
    with pytest.raises(ValueError, match=r"u_min must be a scalar or have shape \[3\]"):
        as_limit("u_min", [1.0, 2.0], 3)
    with pytest.raises(ValueError, match="u_min must not contain NaN"):
        as_limit("u_min", [1.0, float("nan")], 2)
    check_bounds("lo", torch.zeros(2), "hi", torch.ones(2))
    with pytest.raises(
        ValueError, match=r"lo \[0.0, 2.0\] exceeds hi \[1.0, 1.0\] at entries \[1\]"
    ):
        check_bounds("lo", torch.tensor([0.0, 2.0]), "hi", torch.ones(2))


def test_clamp_control_matches_a_loop():
    from torchcbf._checks import clamp_control

    u = torch.randn(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    lo = torch.tensor([-0.5, -1.0, -float("inf")])
    hi = torch.tensor([0.5, 0.2, 0.1])
    out = clamp_control(u, lo, hi)
    assert out.dtype == torch.float64
    for b in range(u.shape[0]):
        for j in range(3):
            assert out[b, j].item() == min(max(u[b, j].item(), lo[j].item()), hi[j].item())
    assert clamp_control(u, None, None) is u
    assert torch.equal(clamp_control(u, None, hi), torch.minimum(u, hi.double()))


def test_as_matrix_forms_and_errors():
    from torchcbf._checks import as_matrix

    assert torch.equal(as_matrix("R", 2.0, 2), 2.0 * torch.eye(2))
    assert torch.equal(as_matrix("R", [1.0, 3.0], 2), torch.diag(torch.tensor([1.0, 3.0])))
    assert as_matrix("R", 0.1, 2, dtype=torch.float64)[0, 0].item() == 0.1
    with pytest.raises(ValueError, match=r"R as a vector must have shape \[2\]"):
        as_matrix("R", [1.0, 2.0, 3.0], 2)
    with pytest.raises(ValueError, match=r"R must be a scalar, \[2\] or \[2, 2\]"):
        as_matrix("R", torch.ones(3, 3), 2)
    with pytest.raises(ValueError, match="R must not contain NaN"):
        as_matrix("R", float("nan"), 2)
    with pytest.raises(ValueError, match="R must be positive definite"):
        as_matrix("R", -1.0, 2)
    assert torch.equal(as_matrix("M", -1.0, 2, spd=False), -torch.eye(2))


def test_check_same_and_check_number():
    from torchcbf._checks import check_finite, check_number, check_same

    p = torch.tensor([[1.0, 2.0], [0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(TypeError, match="b has dtype torch.float32 but a has dtype torch.float64"):
        check_same("a", p, "b", p.float())
    with pytest.raises(ValueError, match="b is on device meta but a is on device cpu"):
        check_same("a", p, "b", p.to("meta"))
    assert check_number("k", 2) == 2.0
    for bad, err in ((float("nan"), ValueError), (True, TypeError), (torch.tensor(1.0), TypeError)):
        with pytest.raises(err, match="k"):
            check_number("k", bad)
    with pytest.raises(ValueError, match="k must be a finite number > 0, got 0.0"):
        check_number("k", 0.0, low=0.0, strict=True)
    assert check_finite("v", torch.tensor([float("inf")]), allow_inf=True) is not None
    with pytest.raises(ValueError, match="v must not contain NaN or inf"):
        check_finite("v", torch.tensor([float("inf")]))


def test_check_positive_int_takes_ints_from_one() -> None:
    assert check_positive_int("n", 1) == 1 and check_positive_int("n", 40) == 40
    for bad in (0, -3):
        with pytest.raises(ValueError, match="n must be a positive int"):
            check_positive_int("n", bad)
    for bad in (2.0, 1.5, True, None, "3"):
        with pytest.raises(TypeError, match="n must be a positive int"):
            check_positive_int("n", bad)


def test_check_spd_symmetry_is_relative_to_the_matrix_scale() -> None:
    tiny = 1e-12 * torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="P must be symmetric"):
        check_spd("P", tiny)
    big = 1e9 * torch.tensor([[2.0, 1.0], [1.0 + 1e-9, 2.0]], dtype=torch.float64)
    assert check_spd("P", big) is big
    mixed = torch.tensor([[1e6, 0.5], [0.9, 1.0]], dtype=torch.float64)  # metres and radians
    with pytest.raises(ValueError, match="P must be symmetric"):
        check_spd("P", mixed)
    a = torch.randn(5, 3, 3, generator=torch.Generator().manual_seed(0))
    check_spd("P", a @ a.mT + 0.1 * torch.eye(3))  # float32 products: symmetric to rounding


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_check_spd_refuses_singular_matrices_cholesky_rounds_through(dtype) -> None:
    for singular in ([[2.0, 2.0], [2.0, 2.0]], [[0.3, 0.3], [0.3, 0.3]]):
        with pytest.raises(ValueError, match="P must be positive definite"):
            check_spd("P", torch.tensor(singular, dtype=dtype))
    # mixed units and a strong correlation are still positive definite
    check_spd("P", torch.tensor([[1e-6, 0.0], [0.0, 1e6]], dtype=dtype))
    check_spd("P", torch.tensor([[1.0, 0.999], [0.999, 1.0]], dtype=dtype))


def test_honour_overrides_follows_the_class_that_defines_each_method() -> None:
    rules = {"quadric": (("forward",), ("flag",)), "fast": (("f", "g"), ())}

    class Base:
        flag = False

        def forward(self):
            return "base forward"

        def quadric(self):
            return None

        def f(self): ...

        def g(self): ...

        def fast(self):
            return "general"

        def __init_subclass__(cls) -> None:
            honour_overrides(cls, Base, rules)

    class Shape(Base):
        flag = True

        def forward(self):
            return "shape"

        def quadric(self):
            return "quadric of shape"

        def f(self): ...

        def fast(self):
            return "closed form"

    class NewForward(Shape):
        def forward(self):
            return "padded"

    class Both(NewForward):
        def quadric(self):
            return "quadric of padded"

    class Plain(Shape):
        pass

    class NewG(Shape):
        def g(self): ...

    class Restored(NewG):
        fast = Shape.fast

    assert stale_closed_forms(Shape, rules) == []
    assert Plain().quadric() == "quadric of shape" and Plain.flag  # inherits both
    assert NewForward().quadric() is None and not NewForward.flag  # the inherited one is stale
    assert Both().quadric() == "quadric of padded" and not Both.flag
    assert Shape().fast() == "closed form" and NewForward().fast() == "closed form"
    assert NewG().fast() == "general"  # stands for f and g: a new g drops it
    assert Restored().fast() == "closed form"  # named in the body: trusted again


def test_behaves_as_needs_every_named_method_unchanged() -> None:
    class Term:
        def forward(self): ...

        def stage(self): ...

    class Renamed(Term):
        weight = 2.0

    class NewStage(Term):
        def stage(self): ...

    assert behaves_as(Term(), Term, ("forward", "stage"))
    assert behaves_as(Renamed(), Term, ("forward", "stage"))
    assert not behaves_as(NewStage(), Term, ("forward", "stage"))
    assert behaves_as(NewStage(), Term, ("forward",))
    assert not behaves_as(object(), Term, ("forward",))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_finiteness_checks_match_torch_isfinite(device, dtype):
    gen = torch.Generator().manual_seed(0)
    t = torch.randn(40, 5, 3, generator=gen).to(dtype)
    info = torch.finfo(dtype)
    t[1, 2, 0], t[2, 0, 1], t[3, 4, 2] = math.nan, math.inf, -math.inf
    t[4] = math.nan
    t[5, 0, 0], t[6, 1, 1] = info.max, -info.max  # finite, and their sum is not
    t[7, 2, 2] = info.tiny / 4  # subnormal
    t = t.to(device)
    want = torch.isfinite(t)
    assert torch.equal(isfinite(t), want)
    assert torch.equal(rows_finite(t, 2, 40), want.flatten(1).all(-1))
    assert torch.equal(rows_finite(t, 1, 200), want.reshape(200, 3).all(-1))
    assert torch.equal(
        rows_finite(t[:, :, :0], 1, 200), torch.ones(200, dtype=torch.bool, device=device)
    )
    assert rows_finite(None, 1, 3) is None


def test_a_number_beyond_the_dtype_is_a_value_error_naming_it() -> None:
    from torchcbf._checks import as_tensor
    from torchcbf.barriers import Ball
    from torchcbf.dynamics import SingleIntegrator
    from torchcbf.filters import SafetyFilter

    with pytest.raises(ValueError, match=r"gain = 1e\+39 does not fit in torch.float32"):
        as_tensor("gain", 1e39, dtype=torch.float32)
    assert float(as_tensor("gain", 1e39, dtype=torch.float64)) == 1e39
    with pytest.raises(ValueError, match="alpha"):
        SafetyFilter(SingleIntegrator(2), Ball([1.0, 0.0], 0.5), alpha=1e39)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a machine without CUDA")
def test_a_device_the_machine_lacks_is_named() -> None:
    from torchcbf._checks import as_tensor

    for device in ("cuda", torch.device("cuda:0")):
        with pytest.raises(ValueError, match="this torch has no CUDA device"):
            as_tensor("low", [1.0, 2.0], device=device)
        with pytest.raises(ValueError, match="this torch has no CUDA device"):
            as_tensor("low", 1.0, device=device)
    with pytest.raises(ValueError, match="'bogus' is not a device torch knows"):
        as_tensor("low", [1.0], device="bogus")
    with pytest.raises(ValueError, match="this torch has no CUDA device"):
        as_tensor("low", torch.ones(2), device=torch.device("cuda"))
