import dataclasses
import functools
import os
import subprocess
import sys
import types

import pytest
import torch

from torchcbf._compile import Traced, TraceError, _trust_reported_isa

inductor = pytest.importorskip("torch._inductor.cpu_vec_isa")

_PICK = """
import sys
from torch._inductor import cpu_vec_isa
import torch

from torchcbf._compile import Traced, TraceError, _trust_reported_isa
if sys.argv[1] == "trust":
    with _trust_reported_isa():
        isa = cpu_vec_isa.pick_vec_isa()
else:
    isa = cpu_vec_isa.pick_vec_isa()
print(str(isa), isa.build_arch_flags())
"""


def test_trusted_isa_is_restored_after_the_call():
    from torch._inductor import config

    probe = inductor.VecISA.check_build
    with _trust_reported_isa():
        assert config.cpp.vec_isa_ok is True
        assert inductor.VecISA.check_build is not probe
    assert inductor.VecISA.check_build is probe
    assert config.cpp.vec_isa_ok is None


@pytest.mark.slow
def test_trusted_isa_matches_the_probed_one(tmp_path):
    # each choice in a fresh process: inductor computes the list once per process
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path)}
    env.pop("TORCHINDUCTOR_VEC_ISA_OK", None)
    picked = [
        subprocess.run(
            [sys.executable, "-c", _PICK, mode], env=env, capture_output=True, text=True, check=True
        ).stdout
        for mode in ("probe", "trust")
    ]
    assert picked[0] == picked[1]


class _Scaled(torch.nn.Module):
    """A buffer, a plain number and a submodule, all read by ``forward``."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("w", torch.tensor([1.0, 2.0]))
        self.gain = 3.0
        self.inner = torch.nn.Linear(2, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.gain * self.inner(x * self.w)


def test_traced_reads_new_values_and_traces_again_for_what_it_baked_in():
    mod = _Scaled().double()

    def fn(x):
        y = mod(x)
        return y, torch.func.vmap(torch.func.jacrev(mod))(x).sum(-1)

    traced = Traced(fn, [mod])
    x = torch.randn(4, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def check(compiles: int) -> None:
        for got, want in zip(traced(x), fn(x), strict=True):
            torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
        assert traced.compiles == compiles

    with torch.no_grad():
        check(1)
        mod.w.mul_(2.0)  # new values, in place: the same code
        mod.inner.weight.add_(1.0)
        check(1)
        mod.gain = 0.5  # a plain number is baked in: traced again
        check(2)
        mod.inner = torch.nn.Linear(2, 2).double()  # a new submodule: traced again
        check(3)
        mod.gain = 3.0
        mod.inner.bias.zero_()
        x = x[:3]  # a new batch size
        check(4)


def test_traced_reads_mutated_containers_and_replaced_data():
    mod = _Scaled().double()
    mod.offsets = [0.5, 1.0]  # a plain list the code reads

    def fn(x):
        return (mod(x) + torch.tensor(mod.offsets, dtype=x.dtype),)

    traced = Traced(fn, [mod])
    x = torch.ones(3, 2, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(traced(x)[0], fn(x)[0])
        mod.offsets[1] = -2.0  # mutated in place: the same object, new contents
        torch.testing.assert_close(traced(x)[0], fn(x)[0])
        mod.w.data = torch.tensor([3.0, 4.0], dtype=torch.float32)  # the same Parameter
        torch.testing.assert_close(traced(x)[0], fn(x)[0])
        assert traced.compiles == 3
        mod.w.data = torch.tensor([[3.0, 4.0]], dtype=torch.float32)  # a new shape
        torch.testing.assert_close(traced(x)[0], fn(x)[0])
        mod.w.data = torch.tensor([[3.0], [4.0]], dtype=torch.float32).mT  # new strides
        torch.testing.assert_close(traced(x)[0], fn(x)[0])
        lookups = traced.lookups
        for _ in range(3):  # each new layout is traced once, then found without a lookup
            torch.testing.assert_close(traced(x)[0], fn(x)[0])
        assert traced.compiles == 5 and traced.lookups == lookups


SHIFT = 1.0


@dataclasses.dataclass(slots=True)
class _Gains:
    slope: float = 2.0


CALLS = 0


def _counted(forward):
    @functools.wraps(forward)
    def wrapper(self, x):
        global CALLS
        CALLS += 1  # a global the method assigns: not part of the key
        return forward(self, x)

    return wrapper


class _Configured(torch.nn.Module):
    """Numbers read from a global (by a decorated method), a ``SimpleNamespace`` and a
    dataclass with slots, and a tensor field of the record."""

    def __init__(self) -> None:
        super().__init__()
        self.cfg = types.SimpleNamespace(gain=1.5, weight=torch.tensor(2.0, dtype=torch.float64))
        self.gains = _Gains()

    @_counted
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scale = self.cfg.gain * self.gains.slope * self.cfg.weight
        return scale * (x + SHIFT) ** 2


def test_traced_sees_globals_and_record_fields_its_modules_read():
    global SHIFT
    mod = _Configured()
    traced = Traced(lambda x: mod(x), [mod])
    x = torch.linspace(-1.0, 1.0, 5, dtype=torch.float64)
    try:
        with torch.no_grad():
            for change, compiles in (
                (lambda: None, 1),
                (lambda: None, 1),  # CALLS changed: the same code
                (lambda: mod.cfg.weight.fill_(3.0), 1),  # a lifted tensor: its new value
                (lambda: setattr(mod.cfg, "gain", 0.5), 2),
                (lambda: setattr(mod.gains, "slope", -1.0), 3),
                (lambda: globals().__setitem__("SHIFT", 4.0), 4),
            ):
                change()
                torch.testing.assert_close(traced(x)[0], mod(x), rtol=1e-12, atol=1e-12)
                assert traced.compiles == compiles
    finally:
        SHIFT = 1.0


class _Margin(torch.nn.Module):
    """A class attribute read as ``self.MARGIN``, and two scalar buffers of one shape."""

    MARGIN = 0.1

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("r", torch.tensor(0.5, dtype=torch.float64))
        self.register_buffer("m", torch.tensor(0.1, dtype=torch.float64))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x**2).sum(-1) - self.r**2 - self.m - self.MARGIN


def test_traced_sees_class_attributes_and_buffers_registered_again_in_another_order():
    mod = _Margin()
    traced = Traced(lambda x: (mod(x),), [mod])
    x = torch.tensor([[0.3, 0.2]], dtype=torch.float64)
    try:
        with torch.no_grad():
            torch.testing.assert_close(traced(x)[0], mod(x))
            _Margin.MARGIN = 0.2  # the class's: every instance reads it
            torch.testing.assert_close(traced(x)[0], mod(x))
            del mod.r  # registered again after m: the same shapes, in another order
            mod.register_buffer("r", torch.tensor(0.7, dtype=torch.float64))
            torch.testing.assert_close(traced(x)[0], mod(x))
            torch.testing.assert_close(mod(x), torch.tensor([0.13 - 0.49 - 0.1 - 0.2]).double())
    finally:
        _Margin.MARGIN = 0.1


def test_traced_sees_hooks_registered_and_removed_after_its_first_call():
    mod = _Scaled().double()
    traced = Traced(lambda x: (mod(x),), [mod])
    x = torch.ones(3, 2, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(traced(x)[0], mod(x))
        outer = mod.register_forward_hook(lambda module, args, out: out - 0.3)
        torch.testing.assert_close(traced(x)[0], mod(x))
        inner = mod.inner.register_forward_pre_hook(lambda module, args: (2.0 * args[0],))
        torch.testing.assert_close(traced(x)[0], mod(x))
        outer.remove()
        inner.remove()
        torch.testing.assert_close(traced(x)[0], mod(x))
        assert traced.compiles == 3  # the last call is the first one's key again
        shift = 0.5
        mod.register_forward_hook(lambda module, args, out: out + shift)
        torch.testing.assert_close(traced(x)[0], mod(x))
        shift = -1.0  # the hook's captured number changed: traced again
        torch.testing.assert_close(traced(x)[0], mod(x))


def test_traced_follows_a_dtype_change_and_a_copy():
    import copy
    import pickle

    mod = _Scaled().double()
    traced = Traced(lambda x: (mod(x),), [mod])
    x = torch.ones(2, 2, dtype=torch.float64)
    with torch.no_grad():
        (got,) = traced(x)
        torch.testing.assert_close(got, mod(x))
        mod.float()  # .to() replaces the tensors: the same names are read
        (got,) = traced(x.float())
        assert got.dtype == torch.float32
        torch.testing.assert_close(got, mod(x.float()))
        assert traced.compiles == 2
        holder = torch.nn.ModuleDict({"mod": mod})
        holder.traced_call = Traced(holder.mod.forward, [holder])
        twin = copy.deepcopy(holder)
        twin.mod.w.fill_(-1.0)
        (a,), (b,) = holder.traced_call(x.float()), twin.traced_call(x.float())
        torch.testing.assert_close(b, twin.mod(x.float()))
        assert not torch.equal(a, b)
        loaded = pickle.loads(pickle.dumps(holder))
        assert loaded.traced_call.compiles == 0  # compiled again where it is loaded
        torch.testing.assert_close(loaded.traced_call(x.float())[0], a)


def test_traced_raises_where_the_function_cannot_be_traced():
    def branchy(x):
        return (x * 2.0,) if bool(x.sum() > 0) else (x,)

    with torch.no_grad(), pytest.raises(TraceError, match="GuardOnDataDependent"):
        Traced(branchy, [])(torch.ones(2))


def test_traced_refuses_a_tensor_it_cannot_lift():
    w = torch.tensor([1.0, 2.0])
    with torch.no_grad(), pytest.raises(TraceError, match="FakeTensor"):
        Traced(lambda x: (x * w,), [])(torch.ones(2))


class _Doubled(torch.nn.Module):
    def forward(self, x):
        return 2.0 * x

    def double(self, x):
        return self(x) + 1.0


def test_compiled_instances_keep_graphs_of_their_own():
    """Modules of one class: the hooked one's compiled method runs its hook, although
    torch.compile does not guard on hooks (each Compiled has its own code object, so its
    own graphs and its own limit on their number), and an unhooked one after it does not."""
    from torchcbf._compile import Compiled

    plain, hooked = _Doubled(), _Doubled()
    hooked.register_forward_hook(lambda module, args, out: out * 10.0)
    x = torch.ones(3)
    first, second = Compiled(plain.double, {}), Compiled(hooked.double, {})
    torch.testing.assert_close(first(x), torch.full((3,), 3.0))
    torch.testing.assert_close(second(x), torch.full((3,), 21.0))
    assert first.compiled.__wrapped__.__code__ is not second.compiled.__wrapped__.__code__
    torch.testing.assert_close(Compiled(_Doubled().double, {})(x), torch.full((3,), 3.0))


WIND = [0.0, 0.1, 0.2]


def test_compiled_traces_an_argument_read_as_a_number_one_value_at_a_time():
    """A step that indexes a list with its step index cannot take the index as an unbacked
    symbol: it is compiled as torch.compile would, not refused."""
    from torchcbf._compile import Compiled

    def step(x, j):
        return x + WIND[j]

    compiled = Compiled(step, {"backend": "eager"}, unbacked=("j",))
    x = torch.zeros(2)
    for j in range(3):
        torch.testing.assert_close(compiled(x, j), x + WIND[j])
    assert compiled.compiled is not None and compiled.unbacked == ()
