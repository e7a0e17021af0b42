"""Input validation shared by every module: clear errors that name the argument and shapes."""

from __future__ import annotations

import functools
import math
import numbers
import operator
from collections.abc import Collection, Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.nn.modules.module import _global_forward_hooks as _GLOBAL_HOOKS
from torch.nn.modules.module import _global_forward_pre_hooks as _GLOBAL_PRE_HOOKS

#: fast form -> (the methods it stands for, the flags reset with it); see honour_overrides
ClosedForms = Mapping[str, tuple[tuple[str, ...], tuple[str, ...]]]


def broadcast_shapes(*shapes: Sequence[int]) -> tuple[int, ...]:
    """The broadcast of ``shapes`` (as ``torch.broadcast_shapes``, ``RuntimeError`` if they do
    not broadcast). Pure Python on tuples of ints: ``torch.broadcast_shapes`` costs 10 to 60
    us per call, which is most of a small solve or filter call."""
    ndim = max((len(s) for s in shapes), default=0)
    out = [1] * ndim
    for shape in shapes:
        for i, d in enumerate(shape, start=ndim - len(shape)):
            if d == 1:
                continue
            if out[i] != 1 and out[i] != d:
                raise RuntimeError(f"shapes {[tuple(s) for s in shapes]} do not broadcast")
            out[i] = d
    return tuple(out)


def broadcasts_to(shape: Sequence[int], target: Sequence[int]) -> bool:
    """Whether ``shape`` broadcasts to ``target`` (``expand`` would take it)."""
    try:
        return broadcast_shapes(shape, target) == tuple(target)
    except RuntimeError:
        return False


def check_tensor(name: str, value: object) -> Tensor:
    """Raise ``TypeError`` unless ``value`` is a tensor; return it."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def check_last_dim(name: str, value: object, size: int) -> Tensor:
    """Check ``value`` is a tensor of shape ``[..., size]``."""
    value = check_tensor(name, value)
    if value.dim() == 0 or value.shape[-1] != size:
        raise ValueError(f"{name} must have shape [..., {size}], got {tuple(value.shape)}")
    return value


def several_outputs(name: str, h: Tensor, x: Tensor) -> bool:
    """Whether ``h``, a function's values at states ``x [..., n]``, is ``[..., k]`` (True:
    ``k`` outputs) or ``[...]`` (False); any other shape is a ``ValueError`` naming ``name``."""
    batch = x.shape[:-1]
    if h.shape == batch:
        return False
    if h.dim() == x.dim() and h.shape[:-1] == batch:
        return True
    raise ValueError(
        f"{name} must return [...] or [..., k] for a state of shape {tuple(x.shape)}, "
        f"got {tuple(h.shape)}"
    )


def check_batch_match(name_a: str, a: Tensor, name_b: str, b: Tensor, trailing: int = 1) -> None:
    """Check the leading (batch) dimensions of ``a`` and ``b`` broadcast together.

    ``trailing`` is the number of trailing non-batch dimensions of each tensor.
    """
    batch_a = a.shape[: a.dim() - trailing]
    batch_b = b.shape[: b.dim() - trailing]
    try:
        broadcast_shapes(batch_a, batch_b)
    except RuntimeError:
        raise ValueError(
            f"batch dimensions of {name_a} {tuple(a.shape)} and {name_b} {tuple(b.shape)} "
            "do not broadcast"
        ) from None


def _floating(module: torch.nn.Module) -> Iterator[Tensor]:
    """``module``'s floating parameters and buffers, parameters first."""
    return (t for t in (*module.parameters(), *module.buffers()) if t.is_floating_point())


def placement(module: torch.nn.Module) -> tuple[torch.device, torch.dtype]:
    """Device and dtype of ``module``'s first floating parameter or buffer (the CPU and the
    default dtype when it has none)."""
    tensor = next(_floating(module), None)
    if tensor is None:
        return torch.device("cpu"), torch.get_default_dtype()
    return tensor.device, tensor.dtype


def follow_parts(module: torch.nn.Module, parts: Iterable[object]) -> None:
    """Move ``module`` to the device its module ``parts`` share when their floating tensors
    all lie on one accelerator: a filter or planner built from modules on a GPU lives there
    too, its own buffers included. Parts on the CPU, or on several devices, leave it as
    built (a call then names the devices that differ)."""
    devices = {
        t.device for part in parts if isinstance(part, torch.nn.Module) for t in _floating(part)
    }
    if len(devices) == 1:
        (device,) = devices
        if device.type not in ("cpu", "meta"):
            module.to(device)


def check_positive(name: str, value: float) -> float:
    """A finite Python number ``> 0`` as a float (:func:`check_number`)."""
    return check_number(name, value, low=0.0, strict=True)


def check_bool(name: str, value: object) -> bool:
    """A bool (Python's or NumPy's): ``TypeError`` naming ``name`` for anything else (a
    string ``"False"`` would read as true)."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a bool, got {type(value).__name__}")
    return bool(value)


def check_compile(value: object) -> bool | dict:
    """The ``compile=`` option: a bool (NumPy's too) or a dict of ``torch.compile``
    options."""
    if isinstance(value, dict):
        return value
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(
            f"compile must be True, False or a dict of torch.compile options, got {value!r}"
        )
    return bool(value)


def check_positive_int(name: str, value: object) -> int:
    """Check an int (Python's or NumPy's; a bool is not one here) is >= 1."""
    return check_int(name, value, low=1, what="a positive int")


def check_seed(seed: object, name: str = "seed") -> int:
    """A generator seed ``name`` as an int (NumPy's too; not a bool) in ``[0, 2^32)``: the
    library's random streams and torch's CPU generator read 32 bits (``s + 2^32`` would
    repeat seed ``s``)."""
    if not isinstance(seed, numbers.Integral) or isinstance(seed, (bool, np.bool_)):
        raise TypeError(f"{name} must be an int, got {type(seed).__name__}")
    if not 0 <= int(seed) < 2**32:
        raise ValueError(f"{name} must lie in [0, 2^32) (32-bit random streams), got {seed}")
    return int(seed)


def check_int(name: str, value: object, *, low: int, what: str | None = None) -> int:
    """Check ``value`` is an int (NumPy's too; not a bool) ``>= low``: ``TypeError``
    naming ``name`` for another type, ``ValueError`` for a smaller int."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be {what or f'an int >= {low}'}, got {value!r}")
    if value < low:
        raise ValueError(f"{name} must be {what or f'an int >= {low}'}, got {value!r}")
    return int(value)


def check_index(name: str, index: Sequence[int], state_dim: int | None) -> tuple[int, ...]:
    """Check a tuple of state indices is valid for ``state_dim`` (if known): integers, none
    repeated (a closed form keeps one copy of a repeated component, autograd both)."""
    if isinstance(index, (np.ndarray, Tensor)):
        if index.ndim != 1 or index.dtype in (torch.bool, np.bool_):
            raise TypeError(f"{name} must be a 1-D sequence of ints, got {index!r}")
        index = index.tolist()
    if isinstance(index, (str, bytes)) or not isinstance(index, Sequence):
        raise TypeError(f"{name} must be a sequence of ints (in order), got {index!r}")
    index = tuple(index)
    try:
        for i in index:
            if isinstance(i, (bool, np.bool_)) or (isinstance(i, Tensor) and i.dtype == torch.bool):
                raise TypeError
        index = tuple(operator.index(i) for i in index)
    except TypeError:
        raise TypeError(f"{name} must hold ints, got {index!r}") from None
    if len(index) == 0:
        raise ValueError(f"{name} must name at least one state component")
    if len(set(index)) != len(index):
        raise ValueError(f"{name}={index} names a component twice")
    if state_dim is not None and any(i < 0 or i >= state_dim for i in index):
        raise ValueError(f"{name}={index} is outside a state of size {state_dim}")
    if any(i < 0 for i in index):
        raise ValueError(f"{name}={index} must hold non-negative indices")
    return index


def as_tensor(name: str, value: object, *, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """Convert a number, sequence or tensor to a floating tensor (default dtype if not a tensor)."""
    if device is not None and not isinstance(device, torch.device):
        device = check_device(device)  # a name given by a user (a tensor's device exists)
    if isinstance(value, Tensor):
        out = value
        if not out.is_floating_point():
            out = out.to(torch.get_default_dtype())
        if dtype is not None or device is not None:
            try:
                out = out.to(device=device, dtype=dtype)
            except (RuntimeError, AssertionError):  # a device not built in: named
                if device is not None:
                    check_device(device)
                raise
        return out
    dtype = dtype or torch.get_default_dtype()
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        # filled on the device: no copy from the host to wait for
        try:
            return torch.full((), value, dtype=dtype, device=device)
        except (RuntimeError, AssertionError) as err:  # the range, or a device not built in
            if device is not None:
                check_device(device)
            raise ValueError(f"{name} = {value!r} does not fit in {dtype}") from err
    try:
        return torch.as_tensor(value, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError, AssertionError) as err:
        if device is not None:
            check_device(device)
        raise TypeError(f"{name} must be a number, sequence or tensor, got {value!r}") from err


def check_times(name: str, t: object) -> None:
    """Refuse a time ``t`` that is a bool (``TypeError``) or, given as a number, a list or
    an array, is not finite (``ValueError``; read on the host). A tensor is left to the
    caller, which can mark its rows on the device without a synchronisation."""
    if isinstance(t, (bool, np.bool_)):
        raise TypeError(f"{name} must be a number or a tensor of times, got {t!r}")
    if t is not None and not isinstance(t, Tensor):
        if not bool(np.isfinite(np.asarray(t, dtype=float)).all()):
            raise ValueError(f"{name} must be finite, got {t!r}")


def check_device(device: object) -> torch.device:
    """``device`` (a string, index or ``torch.device``) as a ``torch.device``; ``ValueError``
    for a name torch does not know or a device this machine does not have."""
    try:
        dev = torch.device(device)  # type: ignore[arg-type]
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device {device!r} is not a device torch knows: {err}") from None
    if dev.type in ("cpu", "meta"):
        return dev
    # cuda, mps, xpu, ...: torch's module of that type says whether one is here, and how many
    module = getattr(torch, dev.type, None)
    if dev.type == "mps":
        module = torch.backends.mps
    available = getattr(module, "is_available", None)
    name = {"cuda": "CUDA", "mps": "MPS", "xpu": "XPU"}.get(dev.type, dev.type)
    if available is None or not available():
        raise ValueError(f"device {device!r}: this torch has no {name} device available")
    count = getattr(module, "device_count", None)
    if dev.index is not None and count is not None and dev.index >= count():
        raise ValueError(f"device {device!r}: there are {count()} {name} devices here")
    return dev


def check_spd(name: str, matrix: Tensor) -> Tensor:
    """Check a symmetric matrix ``[..., n, n]`` is positive definite: Cholesky succeeds
    and no pivot is lost to rounding (each ``L_ii^2`` above ``8 n eps a_ii``)."""
    matrix = check_tensor(name, matrix)
    if matrix.dim() < 2 or matrix.shape[-1] != matrix.shape[-2]:
        raise ValueError(f"{name} must be a square matrix [..., n, n], got {tuple(matrix.shape)}")
    check_finite(name, matrix)
    # each entry against its row's and column's scales, sqrt(|a_ii a_jj|): relative in a
    # matrix of any scale, and in one of mixed units (a covariance of metres and radians)
    d = matrix.detach().diagonal(dim1=-2, dim2=-1).abs().sqrt()
    scale = d.unsqueeze(-1) * d.unsqueeze(-2)
    if bool(((matrix - matrix.mT).detach().abs() > 1e-6 * scale).any()):
        raise ValueError(f"{name} must be symmetric")
    L, info = torch.linalg.cholesky_ex(matrix.detach())
    # Cholesky also succeeds on some singular matrices, by rounding ([[2, 2], [2, 2]]):
    # each pivot L_ii^2 is the part of a_ii its row does not share with the rows before it
    pivots = L.diagonal(dim1=-2, dim2=-1).square()
    own = matrix.detach().diagonal(dim1=-2, dim2=-1)
    tol = 8 * matrix.shape[-1] * torch.finfo(matrix.dtype).eps
    if bool((info != 0).any()) or bool((pivots <= tol * own).any()):
        raise ValueError(f"{name} must be positive definite")
    return matrix


def check_finite(name: str, value: Tensor, *, allow_inf: bool = False) -> Tensor:
    """Raise ``ValueError`` naming ``name`` if ``value`` holds NaN (or ``inf``, unless allowed).

    A constructor-time check (one host sync); never call it inside a hot loop.
    """
    if value.device.type == "meta" or not value.is_floating_point():
        return value
    data = value.detach()
    bad = torch.isnan(data) if allow_inf else ~torch.isfinite(data)
    if bool(bad.any()):
        what = "NaN" if allow_inf else "NaN or inf"
        got = data.tolist() if data.numel() <= 16 else f"{int(bad.sum())} of {data.numel()} entries"
        raise ValueError(f"{name} must not contain {what}, got {got}")
    return value


def check_same(name_a: str, a: Tensor, name_b: str, b: Tensor) -> None:
    """Raise ``TypeError`` (dtype) or ``ValueError`` (device) unless ``a`` and ``b`` agree,
    naming both arguments and both dtypes or devices."""
    if a.dtype != b.dtype:
        raise TypeError(
            f"{name_b} has dtype {b.dtype} but {name_a} has dtype {a.dtype}: "
            f"convert one of them (e.g. {name_b}.to({name_a}.dtype))"
        )
    if a.device != b.device:
        raise ValueError(
            f"{name_b} is on device {b.device} but {name_a} is on device {a.device}: "
            "move them to one device"
        )


def check_generator(generator: torch.Generator, name: str, like: Tensor) -> None:
    """Raise ``ValueError`` unless ``generator`` draws on the device of ``like`` (the tensor
    ``name``). A CUDA generator made with ``device="cuda"`` reports no index: it draws on
    the current device."""
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    gen = generator.device
    index = gen.index
    if gen.type == "cuda" and index is None:
        index = torch.cuda.current_device()
    if gen.type != like.device.type or (index is not None and index != like.device.index):
        raise ValueError(f"generator is on device {gen} but {name} is on device {like.device}")


def as_limit(name: str, value: object, size: int) -> Tensor | None:
    """A bound given as a scalar or ``[size]`` vector, as a float64 ``[size]`` tensor (``None``
    stays ``None``). ``+-inf`` means unbounded; NaN raises. A tensor that requires grad keeps
    its graph (the cast is differentiable)."""
    if value is None:
        return None
    t = as_tensor(name, value, dtype=torch.float64)
    if t.dim() == 0:
        t = limit_shape(t, size).clone()
    if t.shape != (size,):
        raise ValueError(f"{name} must be a scalar or have shape [{size}], got {tuple(t.shape)}")
    return check_finite(name, t, allow_inf=True)


def limit_shape(value: Tensor, size: int) -> Tensor:
    """The float64 ``[size]`` that :func:`as_limit` makes of a tensor already checked by it
    (a scalar expanded), without checks: what a module reads at each call from a bound it
    keeps as given (:func:`torchcbf._constants.derive`)."""
    t = value.to(torch.float64)
    return t.expand(size) if t.dim() == 0 else t


def to_float64(value: Tensor) -> Tensor:
    """``value`` in float64 (its graph kept)."""
    return value.to(torch.float64)


def check_bounds(name_lo: str, lo: Tensor | None, name_hi: str, hi: Tensor | None) -> None:
    """Raise ``ValueError`` naming both bounds where ``lo > hi`` in some entry, or naming one
    that admits nothing (a lower bound of ``+inf``, an upper bound of ``-inf``)."""
    for name, bound, empty in ((name_lo, lo, float("inf")), (name_hi, hi, float("-inf"))):
        if bound is not None and bound.device.type != "meta" and bool((bound == empty).any()):
            raise ValueError(f"{name} must not be {empty}, got {bound.detach().tolist()}")
    if lo is None or hi is None or lo.device.type == "meta":
        return
    bad = lo.detach() > hi.detach()
    if bool(bad.any()):
        idx = bad.nonzero().flatten().tolist()
        raise ValueError(
            f"{name_lo} {lo.detach().tolist()} exceeds {name_hi} {hi.detach().tolist()} "
            f"at entries {idx}"
        )


def clamp_control(u: Tensor, lo: Tensor | None, hi: Tensor | None) -> Tensor:
    """Clip ``u [..., m]`` to ``[lo, hi]`` (``[m]`` each, cast to ``u``; ``None``: unbounded)."""
    lo = None if lo is None else lo.to(u)
    hi = None if hi is None else hi.to(u)
    if lo is None and hi is None:
        return u
    return torch.clamp(u, lo, hi)


def as_matrix(
    name: str, value: object, size: int, *, dtype: torch.dtype | None = None, spd: bool = True
) -> Tensor:
    """A square ``[size, size]`` matrix given as a scalar (``v I``), a vector ``[size]`` (its
    diagonal) or the matrix itself; finite, and symmetric positive definite when ``spd``."""
    t = as_tensor(name, value, dtype=dtype)
    if t.dim() == 1 and t.shape[0] != size:
        raise ValueError(f"{name} as a vector must have shape [{size}], got {tuple(t.shape)}")
    t = matrix_shape(t, size)
    if t.shape != (size, size):
        raise ValueError(
            f"{name} must be a scalar, [{size}] or [{size}, {size}], got {tuple(t.shape)}"
        )
    check_finite(name, t)
    if spd and t.device.type != "meta":
        check_spd(name, t)
    return t


def matrix_shape(value: Tensor, size: int, dtype: torch.dtype | None = None) -> Tensor:
    """The ``[size, size]`` matrix that :func:`as_matrix` makes of a tensor (a scalar times
    ``I``, a vector on the diagonal; in ``dtype`` where given), without checks: what a module
    reads at each call from a matrix it keeps as given."""
    t = value if dtype is None else value.to(dtype)
    if t.dim() == 0:
        return t * torch.eye(size, dtype=t.dtype, device=t.device)
    return torch.diag(t) if t.dim() == 1 else t


def check_number(
    name: str, value: object, *, low: float | None = None, strict: bool = False
) -> float:
    """A finite Python number (``>= low``, or ``> low`` when ``strict``) as a float.

    A tensor raises ``TypeError``: these options are plain numbers, and converting a tensor
    that requires grad would cut its gradient silently.
    """
    if isinstance(value, Tensor):
        raise TypeError(
            f"{name} must be a Python number, got a tensor (it would be cut from the autograd "
            "graph: pass float(...) explicitly)"
        )
    # NumPy's scalars are numbers.Real too (a configuration file's np.float32, say)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    v = float(value)
    bound = "" if low is None else f" {'>' if strict else '>='} {low:g}"
    if v != v or v in (float("inf"), float("-inf")):
        raise ValueError(f"{name} must be a finite number{bound}, got {v}")
    if low is not None and (v <= low if strict else v < low):
        raise ValueError(f"{name} must be a finite number{bound}, got {v}")
    return v


def _defines(cls: type, name: str) -> type:
    return next(c for c in cls.__mro__ if name in c.__dict__)


def stale_closed_forms(cls: type, rules: ClosedForms) -> list[str]:
    """The fast forms of ``rules`` that class ``cls`` inherits from a class that does not
    also define what they stand for, and those a class written outside torchcbf rewrites
    alone, every method they stand for being torchcbf's (a ``quadric`` or ``derivatives``
    of a ``Ball`` subclass that keeps ``Ball.forward``: the function is its ``forward``);
    see :func:`honour_overrides`."""
    stale = []
    for fast, (stands_for, _) in rules.items():
        owner = _defines(cls, fast)
        refs = [_defines(cls, ref) for ref in stands_for]
        alone = not _ours(owner) and not any(_is_user(r) for r in refs)
        if alone or not all(issubclass(owner, r) for r in refs):
            stale.append(fast)
    return stale


def _is_user(cls: type) -> bool:
    """Whether ``cls`` is written outside torchcbf and torch (a user's class)."""
    return not _ours(cls) and cls.__module__.partition(".")[0] not in ("torch", "builtins")


def rewritten_helpers(cls: type) -> list[str]:
    """The private methods (one leading underscore) that ``cls``, a class written outside
    torchcbf, rewrites from a torchcbf class above it (``Ball._diff``, say; not those of
    ``nn.Module``, such as ``_apply``): the closed forms of the torchcbf class do not call
    them, so none of them can be trusted."""
    if _ours(cls):
        return []
    above = cls.__mro__[1:]
    return [
        name
        for name in vars(cls)
        if name.startswith("_")
        and not name.startswith("__")
        and any(_ours(c) and _is_method(vars(c).get(name)) for c in above)
        and not any(not _ours(c) and name in vars(c) for c in above)  # torch's (``_apply``)
    ]


def _ours(cls: type) -> bool:
    return cls.__module__.partition(".")[0] == "torchcbf"


def _is_method(value: object) -> bool:
    return callable(value) or isinstance(value, (property, staticmethod, classmethod))


def honour_overrides(cls: type, base: type, rules: ClosedForms) -> None:
    """Give class ``cls`` (a new subclass of ``base``) ``base``'s general version of every
    fast form it would inherit stale.

    ``rules`` maps the name of a fast form (a closed-form ``xdot``, a shape's
    ``derivatives``, a native description) to ``(stands_for, companions)``: the methods it
    stands for, and the flags that go with it (reset together). A fast form is trusted only
    when the class defining it is the class defining each method it stands for, or a
    subclass of it: a subclass that overrides ``f`` alone does not inherit a closed-form
    ``xdot`` of the old ``f``; it gets ``f + g u``. A subclass restores an inherited fast
    form by naming it in its own body (``xdot = Parent.xdot``). A fast form a user's class
    rewrites alone, every method it stands for being torchcbf's, is not trusted either (a
    ``Ball`` subclass's own ``quadric``: the ball is its ``forward``). A class written outside
    torchcbf that rewrites a private helper of a torchcbf class (:func:`rewritten_helpers`)
    gets the general version of every fast form it does not define itself. Called from
    ``__init_subclass__``, so the rule holds for every path that asks the object.
    """
    stale = stale_closed_forms(cls, rules)
    if rewritten_helpers(cls):
        stale += [fast for fast in rules if fast not in vars(cls) and fast not in stale]
    for fast in stale:
        for name in (fast, *rules[fast][1]):
            setattr(cls, name, base.__dict__[name])


def apply_rules(cls: type, base: type) -> None:
    """The rules of ``base``'s family for its subclass ``cls``: :func:`honour_overrides`
    and :func:`unless_hooked` with ``cls.closed_forms`` and ``cls.hooked_forms``, noting the
    methods they saw (:func:`reapply_rules` compares). Called from ``__init_subclass__``."""
    honour_overrides(cls, base, cls.closed_forms)  # type: ignore[attr-defined]
    unless_hooked(cls, cls.hooked_forms, cls.closed_forms)  # type: ignore[attr-defined]
    type.__setattr__(cls, "_rules_seen", _class_state(cls))


def reapply_rules(kind: type) -> None:
    """Apply the rules of its family again to ``kind``, a class written outside torchcbf,
    if its methods changed since they were applied (a class decorator that replaces
    ``forward``, ``Cls.g = ...`` after the class statement) or they never were (a parent's
    ``__init_subclass__`` that does not call ``super()``). Called as an instance is made
    (:class:`TracksShadows`); families name their base as ``rules_base``."""
    base = getattr(kind, "rules_base", None)
    if base is None or _ours(kind):
        return
    if kind.__dict__.get("_rules_seen") != _class_state(kind):
        apply_rules(kind, base)
        _keeps.cache_clear()


def _class_state(kind: type) -> tuple[tuple[str, int], ...]:
    """The attributes of the classes above ``kind`` written outside torchcbf and torch, by
    identity."""
    return tuple(
        (name, id(value))
        for c in kind.__mro__
        if _is_user(c)
        for name, value in vars(c).items()
        if name != "_rules_seen"
    )


def hook_dicts(modules: Iterable[torch.nn.Module]) -> list[dict[int, Any]]:
    """The dicts of forward and forward-pre hooks that calls of ``modules`` run: the global
    module hooks' and each module's own (keyed by the hooks' handle ids)."""
    dicts = [_GLOBAL_PRE_HOOKS, _GLOBAL_HOOKS]
    for mod in modules:
        dicts.append(mod._forward_pre_hooks)
        dicts.append(mod._forward_hooks)
    return dicts


def hooked(obj: object) -> bool:
    """Whether calling ``obj`` (a module) runs more than its class's ``forward``: forward or
    forward-pre hooks (its own or the global module hooks,
    ``torch.nn.modules.module.register_module_forward_hook``), or a ``forward`` set on the
    instance itself (``obj.forward = ...``)."""
    return bool(
        _GLOBAL_HOOKS
        or _GLOBAL_PRE_HOOKS
        or (
            isinstance(obj, torch.nn.Module)
            and (obj._forward_hooks or obj._forward_pre_hooks or "forward" in obj.__dict__)
        )
    )


def shadowed(obj: object, names: Sequence[str]) -> bool:
    """Whether the instance ``obj`` holds an attribute of its own named in ``names``
    (``model.f = ...``): it shadows the class's method, as a subclass's override would."""
    own = getattr(obj, "__dict__", None)
    if own:
        for name in names:
            if name in own:
                return True
    return False


def stale_on(obj: object, fast: str, rules: ClosedForms) -> bool:
    """Whether the fast form ``fast`` of ``rules`` is stale on the instance ``obj``: ``obj``
    shadows a method it stands for (:func:`shadowed`) and not ``fast`` itself. The instance
    counterpart of :func:`honour_overrides`: ``model.f = ...`` makes a closed-form ``xdot``
    of the class's ``f`` as stale as a subclass's ``f`` does."""
    return fast not in getattr(obj, "__dict__", ()) and shadowed(obj, rules[fast][0])


class TracksShadows(torch.nn.Module):
    """A module that keeps, in ``obj.__dict__["_shadows"]``, the names of the methods of its
    class (public or private, properties too) that the instance shadows with attributes of
    its own (``model.f = ...``, ``ball._diff = ...``), updated as they are set and deleted:
    the instance counterpart of :func:`rewritten_helpers`, read in one lookup by the fast
    forms (:func:`unless_hooked`) and by :func:`behaves_as` (see :func:`shadowed_methods`).
    Making an instance applies its family's rules again where its class changed
    (:func:`reapply_rules`)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        reapply_rules(type(self))

    def __setattr__(self, name: str, value: Any) -> None:
        super().__setattr__(name, value)
        _track_shadow(self, name)

    def __delattr__(self, name: str) -> None:
        super().__delattr__(name)
        _track_shadow(self, name)


def _track_shadow(obj: torch.nn.Module, name: str) -> None:
    own = obj.__dict__
    if name == "_shadows":
        return
    was = own.get("_shadows", frozenset())
    shadows = name in own and name in _method_names(type(obj))
    now = was | {name} if shadows else was - {name}
    if now != was:
        own["_shadows"] = now


def shadowed_methods(obj: object) -> Collection[str]:
    """The methods of ``obj``'s class that ``obj`` shadows with attributes of its own: kept
    up to date by :class:`TracksShadows`, found by a look at every attribute otherwise."""
    own = getattr(obj, "__dict__", None)
    if not own:
        return ()
    if isinstance(obj, TracksShadows):
        return own.get("_shadows", ())
    methods = _method_names(type(obj))
    return [k for k in own if k in methods]


@functools.lru_cache(maxsize=512)
def _method_names(kind: type) -> frozenset[str]:
    """The names of the methods (properties too) the classes of ``kind``'s MRO define."""
    return frozenset(k for c in kind.__mro__ for k, v in vars(c).items() if _is_method(v))


def _stands_for(rules: ClosedForms) -> dict[str, tuple[str, ...]]:
    """Each fast form of ``rules`` and each of its companions, mapped to what it stands for."""
    out: dict[str, tuple[str, ...]] = {}
    for fast, (stands, companions) in rules.items():
        for name in (fast, *companions):
            out[name] = tuple(stands)
    return out


def unless_hooked(
    cls: type, fast_forms: Mapping[str, object], rules: ClosedForms | None = None
) -> None:
    """Make each fast form class ``cls`` defines in its own body (a method or a property
    of ``self`` alone) answer ``fast_forms[name]`` (its "none": ``None``, ``False``) for an
    instance whose calls run hooks (:func:`hooked`). A fast form stands for ``forward`` as
    the class wrote it; a hook changes what a call computes, so a hooked instance takes the
    general path, which calls it. Likewise for an instance that shadows a method the form
    stands for in ``rules`` (:func:`stale_on`: ``obj.lie = ...``, ``model.f = ...``; an
    instance ``forward`` for a form ``rules`` does not name), and for an instance of a
    :class:`TracksShadows` class that shadows any method of its class (a private helper the
    closed forms call, ``ball._diff = ...``). A fast form may take arguments. Called from
    ``__init_subclass__`` next to :func:`honour_overrides`; a hook registered or removed, or
    an instance attribute set or deleted, at any time is seen at the next question."""
    stands = _stands_for(rules or {})
    for name, none in fast_forms.items():
        if name not in cls.__dict__:
            continue
        attr = cls.__dict__[name]
        inherited = next((c.__dict__[name] for c in cls.__mro__[1:] if name in c.__dict__), None)
        if (
            not isinstance(attr, property)
            and not callable(attr)
            and isinstance(inherited, property)
        ):
            attr = property(lambda self, _value=attr: _value)  # a flag set as a class value
        is_property = isinstance(attr, property)
        fn = attr.fget if is_property else attr
        if not callable(fn) or getattr(fn, "_unless_hooked", False):
            continue

        # an instance's __call__ is never called (Python looks it up on the class)
        extra = tuple(n for n in stands.get(name, ()) if n not in ("forward", "__call__"))

        def guarded(
            self: torch.nn.Module, *args: Any, _fn=fn, _none=none, _extra=extra, **kwargs: Any
        ) -> object:
            # hooked(self) and shadowed(self, ...), inline: some fast forms are asked several
            # times per filter call
            own = self.__dict__
            if (
                _GLOBAL_HOOKS
                or _GLOBAL_PRE_HOOKS
                or self._forward_hooks
                or self._forward_pre_hooks
                or "forward" in own
                or own.get("_shadows")
            ):
                return _none
            for n in _extra:
                if n in own:
                    return _none
            return _fn(self, *args, **kwargs)

        functools.update_wrapper(guarded, fn)
        guarded._unless_hooked = True  # type: ignore[attr-defined]
        setattr(cls, name, property(guarded, doc=attr.__doc__) if is_property else guarded)


def behaves_as(obj: object, cls: type, methods: Sequence[str]) -> bool:
    """Whether ``obj`` is an instance of ``cls`` whose class keeps ``cls``'s ``methods`` (a
    subclass may add to them, not change them), which shadows none of them nor any other
    method of its class (:func:`shadowed_methods`: a private helper shadowed on the instance
    changes the formulas as a rewritten one does) and, where ``forward`` is among them, whose
    calls run no hooks (:func:`hooked`: a hook changes what a call computes): the test for
    handing ``obj`` to a kernel that evaluates ``cls``'s formulas. A class that rewrites
    ``__call__`` changes ``forward`` too, and one that rewrites a private helper of
    torchcbf's (:func:`rewritten_helpers`) changes them all."""
    if "forward" in methods:  # a call runs __call__, its hooks and the instance's forward
        if hooked(obj):
            return False
        if isinstance(obj, torch.nn.Module):
            methods = (*methods, "__call__")
    if shadowed(obj, methods) or shadowed_methods(obj):
        return False
    if not isinstance(obj, cls):
        return False
    kind, names = type(obj), tuple(methods)
    # the methods themselves are in the key: one assigned to the class later is seen
    return _keeps(kind, cls, names, tuple([getattr(kind, name, None) for name in names]))


@functools.lru_cache(maxsize=512)
def _keeps(kind: type, cls: type, methods: tuple[str, ...], own: tuple[object, ...]) -> bool:
    same = all(mine is getattr(cls, name, None) for name, mine in zip(methods, own, strict=True))
    return same and not rewritten_helpers(kind)


def resolved(value: Tensor) -> Tensor:
    """``value`` with its negative bit applied (``t.conj().imag`` of a complex tensor keeps
    it): a C or Triton kernel reads memory, where such a view holds the values negated."""
    return value.resolve_neg() if value.is_neg() else value


def isfinite(t: Tensor) -> Tensor:
    """``torch.isfinite(t)`` as ``|t| < inf`` (false for NaN and both infinities): two
    kernels, where ``torch.isfinite`` launches four."""
    return t.detach().abs() < math.inf


def per_row(rows: Tensor, like: Tensor) -> Tensor:
    """``rows [B]`` viewed to broadcast over ``like [B, ...]`` (a mask per row, say)."""
    return rows.view(-1, *(1,) * (like.dim() - 1))


def rows_finite(t: Tensor | None, trailing: int, batch: int) -> Tensor | None:
    """``[batch]`` bool: which rows of ``t`` (``batch`` rows of ``trailing`` dimensions each)
    hold neither a NaN nor an infinity (``None`` for no tensor)."""
    if t is None:
        return None
    flat = t.detach().reshape(batch, math.prod(t.shape[t.dim() - trailing :]))
    if flat.shape[-1] == 0:
        return torch.ones(batch, dtype=torch.bool, device=t.device)
    # a row's largest and smallest entries are finite exactly when all are (NaN propagates):
    # on a GPU one reading pass finds both; on a CPU torch.aminmax is twice as slow in
    # float32 as the two passes
    if flat.device.type == "cpu":
        hi, lo = flat.amax(-1), flat.amin(-1)
    else:
        lo, hi = torch.aminmax(flat, dim=-1)
    return (hi < math.inf) & (lo > -math.inf)


def check_finite_action(name: str, action: Tensor) -> None:
    """Refuse a non-finite ``action`` (``ValueError`` naming ``name``). On the CPU at once; on
    an accelerator asynchronously (``torch._assert_async``: the failure surfaces at a later
    synchronisation), so that a step never waits for the device."""
    finite = torch.isfinite(action).all()
    if action.device.type == "cpu":
        if not bool(finite):  # a CPU reduction: nothing to wait for
            raise ValueError(f"{name} must be finite")
    else:
        torch._assert_async(finite, f"{name} must be finite")
