"""Lie terms of quadric barriers on a few CPU states, in one call of a C kernel.

A robot filters ONE state per control tick; there the closed forms of the shapes (a few
hundred tensor operations for an exponential CBF with its Hessian trace) cost far more than
the arithmetic. :func:`lie_terms` hands the same formulas to ``_lie_kernel.c``. It takes the
functions whose :meth:`~torchcbf.barriers.LieFunction.quadric` is known (``Ball``,
``Ellipse``, ``Scaled`` of them), :class:`~torchcbf.barriers.Transformed` and ``Scaled`` of
those, exponential CBFs of relative degree two of any of these
(:class:`~torchcbf.barriers.ExponentialBarrier`, time-invariant),
:class:`~torchcbf.barriers.Intersection` and :class:`~torchcbf.barriers.Union` (hard or
smooth, elementwise or not) of them and :class:`~torchcbf.barriers.BarrierStack` of all
these, along the built-in models with closed-form drift derivatives (a
:meth:`~torchcbf.dynamics.ControlAffine.native_model`) with a constant diffusion or none.

It answers ``None`` wherever the torch path must run instead: a function or model outside
that list, a tensor on another device, a gradient to carry (grad mode on and the state or a
constant requiring grad), sizes beyond the kernel's, or no kernel built (a missing library,
or one built from another version of the source, see :func:`torchcbf._native.load_kernel`).
The torch closed forms (``lie_derivatives(..., method="analytic")``) are the reference: the
two agree to rounding (tests/barriers/test_native_terms.py).
"""

from __future__ import annotations

import array
import ctypes
import functools
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from torchcbf._checks import behaves_as
from torchcbf._native import Layout, float64_pointers, load_kernel, model_code
from torchcbf.barriers.compose import BarrierStack, Intersection, Scaled, Transformed, Union
from torchcbf.barriers.lie import LieFunction, LieTerms, Quadric
from torchcbf.barriers.rectify import ExponentialBarrier
from torchcbf.dynamics.base import ControlAffine

__all__ = [
    "Affine",
    "KERNEL_VERSION",
    "REDUCTION_CODES",
    "TRANSFORM_CODES",
    "available",
    "describes",
    "cbf_conditions",
    "lie_terms",
]

#: version of ``_lie_kernel.c`` this module calls (``LIE_KERNEL_VERSION``)
KERNEL_VERSION = 6
#: the file name of the built kernel, without its extension suffix
KERNEL_STEM = "_lie_kernel"
#: the kernel's sources (``_lie_kernel.h`` names its arguments' fields and codes)
SOURCES = ("_lie_kernel.c", "_lie_kernel.h")
#: the integer constants of ``_lie_kernel.h``: the layout of the kernel's arguments
LAYOUT = Layout.read([Path(__file__).parent / "_lie_kernel.h"])
_pack_header = LAYOUT.packer(
    "META_HEADER", "L_B", "L_N", "L_M", "L_Q", "L_OUTER", "L_OUTER_DIM", "L_BLOCKS",
    "L_GAIN_STRIDE", "L_OFFSET_STRIDE", "L_GROUPS",
)  # fmt: skip
_pack_reals = LAYOUT.packer(
    "REALS_HEADER", "R_TRACE_WEIGHT", "R_GAIN_SCALE", "R_OFFSET_SCALE", "R_NOISE_SCALE"
)
_pack_block = LAYOUT.packer(
    "M_FIXED", "M_K", "M_D", "M_CENTER", "M_AXES", "M_RADIUS", "M_ANGLE", "M_SCALE", "M_SIGN",
    "M_TRANSFORM", "M_OUTER", "M_INNER", "M_INNER_DIM",
)  # fmt: skip
_pack_group = LAYOUT.packer("G_FIXED", "G_MODE", "G_SMOOTH", "G_BLOCKS", "G_OUTPUTS")
#: the kernel's code of each transform of :class:`~torchcbf.barriers.Transformed`
TRANSFORM_CODES: dict[str | None, int] = {
    None: LAYOUT["NO_TRANSFORM"],
    "radius": LAYOUT["RADIUS"],
    "exp": LAYOUT["EXP"],
}
#: the kernel's code of each reduction of a group of blocks (``None``: the outputs as they are)
REDUCTION_CODES: dict[str | None, int] = {
    None: LAYOUT["NO_REDUCTION"],
    "min": LAYOUT["REDUCE_MIN"],
    "max": LAYOUT["REDUCE_MAX"],
}
#: the kernel's largest state, control, position and noise sizes
MAX_SIZE = 32


@functools.lru_cache(maxsize=1)
def _library() -> ctypes.CDLL | None:
    return load_kernel(
        Path(__file__).parent,
        KERNEL_STEM,
        "torchcbf_lie_version",
        KERNEL_VERSION,
        "quadric barriers take their torch closed forms",
        sources=SOURCES,
    )


def available() -> bool:
    """Whether the Lie kernel was built and loads."""
    return _library() is not None


#: the wrappers the kernel evaluates, and the methods each one's encoding stands for
_WRAPPERS: dict[type, tuple[str, ...]] = {
    BarrierStack: ("forward", "parts"),
    ExponentialBarrier: ("forward", "value", "parts"),
    Transformed: ("forward",),
    Scaled: ("forward",),
    Intersection: ("forward", "_columns"),
    Union: ("forward", "_columns"),
}
#: the wrappers whose encoding is a group of blocks (:class:`_Group`), not a block
_REDUCTIONS = (Intersection, Union)


def _wrapper(fn: LieFunction) -> type | None:
    """The wrapper of :data:`_WRAPPERS` nearest ``fn``'s class (in its method resolution
    order) if ``fn`` behaves as that wrapper, else ``None``."""
    for kind in type(fn).__mro__:
        names = _WRAPPERS.get(kind)
        if names is not None:
            return kind if behaves_as(fn, kind, names) else None
    return None


class _Block(NamedTuple):
    """One quadric function ``b``, as ``outer * phi(b)`` with ``phi`` the ``transform`` of
    :class:`~torchcbf.barriers.Transformed` (``None``: ``phi(b) = b``), rectified along
    ``inner`` with ``k0`` where ``inner`` is given."""

    quadric: Quadric
    transform: str | None = None
    rate: float = 1.0
    outer: Tensor | None = None
    inner: ControlAffine | None = None
    k0: Tensor | None = None


#: the blocks of each module met so far while one function is described, by ``id``
_Seen = dict[int, "list[_Block] | None"]


def _blocks(fn: LieFunction, seen: _Seen | None = None) -> list[_Block] | None:
    """``fn`` as the kernel's blocks (their outputs concatenated are ``fn``'s), or ``None``;
    ``seen`` holds the answers for the modules described already (a module shared by two
    parts, as a shape under both children of an intersection, is read once)."""
    if seen is None:
        return _new_blocks(fn, {})
    key = id(fn)
    if key not in seen:
        seen[key] = _new_blocks(fn, seen)
    return seen[key]


def _new_blocks(fn: LieFunction, seen: _Seen) -> list[_Block] | None:
    quadric = fn.quadric()
    if quadric is not None:
        return [_Block(quadric)]
    cls = _wrapper(fn)
    if cls is BarrierStack:
        out: list[_Block] = []
        for child in fn.barriers:
            part = _blocks(child, seen)
            if part is None:
                return None
            out.extend(part)
        return out
    if cls is None or cls in _REDUCTIONS:
        return None
    inner = _blocks(fn.barrier, seen)
    if inner is None or any(b.inner is not None for b in inner):
        return None
    if cls is ExponentialBarrier:
        model = fn.dynamics
        if fn.relative_degree != 2 or fn.time_varying or model_code(model) is None:
            return None
        k0 = fn.coefficients
        return [b._replace(inner=model, k0=k0) for b in inner]
    if cls is Transformed:
        if any(b.transform is not None or b.outer is not None for b in inner):
            return None
        return [b._replace(transform=fn.form, rate=fn.rate) for b in inner]
    # a scale outside a transform (inside one, the quadric holds it)
    if len(inner) != 1:
        return None
    (block,) = inner
    outer = fn.scale if block.outer is None else fn.scale * block.outer
    return [block._replace(outer=outer)]


def _outputs(block: _Block) -> int:
    """The number of outputs of ``block`` (where :func:`_encode` takes it)."""
    center = block.quadric.center
    return center.shape[0] if center.dim() == 2 else 1


class _Group(NamedTuple):
    """Blocks whose outputs ``fn`` gives as they are (``reduction`` ``None``) or reduces, as
    :class:`~torchcbf.barriers.Intersection` (``"min"``) or
    :class:`~torchcbf.barriers.Union` (``"max"``), to ``outputs`` outputs: output ``j`` the
    reduction of the columns ``j, j + outputs, ...`` of the blocks' outputs concatenated."""

    blocks: list[_Block]
    reduction: str | None = None
    smooth: bool = False
    temperature: float = 1.0
    outputs: int = 1


def _groups(fn: LieFunction) -> list[_Group] | None:
    """``fn`` as the kernel's groups of blocks (their outputs concatenated are ``fn``'s), or
    ``None``."""
    cls = None if fn.quadric() is not None else _wrapper(fn)
    if cls is BarrierStack:
        out: list[_Group] = []
        for child in fn.barriers:
            part = _groups(child)
            if part is None:
                return None
            out.extend(part)
        return out
    if cls in _REDUCTIONS:
        return _reduction(fn)
    blocks = _blocks(fn)
    return None if blocks is None else [_Group(blocks)]


def _reduction(fn: Intersection | Union) -> list[_Group] | None:
    """An intersection or union of functions the kernel describes as blocks, as one group."""
    temperature = float(fn.temperature)
    if fn.mode not in ("min", "max") or not 0.0 < temperature < float("inf"):
        return None
    seen: _Seen = {}
    if not fn.elementwise:
        blocks = _blocks(fn.stack, seen)
        return None if blocks is None else [_Group(blocks, fn.mode, fn.smooth, temperature)]
    blocks = []
    counts = set()
    for child in fn.stack.barriers:
        part = _blocks(child, seen)
        if part is None:
            return None
        counts.add(sum(_outputs(b) for b in part))
        blocks.extend(part)
    if len(counts) != 1:
        return None  # the torch path raises
    (k,) = counts
    return [_Group(blocks, fn.mode, fn.smooth, temperature, k)]


def _encode(
    block: _Block, meta: list[int], reals: list[float], tensors: list[Tensor | None]
) -> int | None:
    """Append ``block``'s integers (as ``_lie_kernel.c`` reads them) to ``meta``, its rate to
    ``reals`` and its seven tensors to ``tensors``; return its number of outputs, or ``None``
    where its constants' shapes are not the kernel's (the torch path then answers, or
    raises)."""
    quadric, transform, rate, outer, inner, k0 = block
    index, center, axes, radius, angle, scale, sign = quadric
    d = len(index)
    if center.dim() == 2:
        k = center.shape[0]
        ok = (k,), (1,), ()
    elif center.dim() == 1:
        k = 1
        ok = ((),)  # a [k] constant on one function: the torch path broadcasts it
    else:
        return None
    if center.shape[-1] != d or (axes is not None and axes.shape != center.shape):
        return None
    if angle is not None and d != 2:
        return None
    strides = [d if k > 1 else 0] * 2
    for v in (radius, angle, scale, outer):
        if v is None:
            strides.append(0)
            continue
        shape = v.shape
        if shape not in ok:
            return None
        strides.append(1 if shape == (k,) and k > 1 else 0)
    code, dim = (-1, 0) if inner is None else model_code(inner)  # type: ignore[misc]
    meta += _pack_block(k, d, *strides[:5], int(sign), TRANSFORM_CODES[transform], strides[5],
                        code, dim)  # fmt: skip
    meta += index
    reals.append(rate)
    tensors += (center, axes, radius, angle, scale, outer, k0)
    return k


class Affine(NamedTuple):
    """A CBF condition ``a . u + b >= 0`` affine in the Lie terms, as the kernel evaluates
    it: ``a = L_g h`` and ``b = L_f h + dh/dt + trace_weight tr + gain_scale gain h +
    offset_scale offset + noise_scale |sigma' dh/dx|`` (``tr`` the Hessian trace; ``gain``
    and ``offset`` numbers, scalar tensors or one per output ``[K]``, ``None`` for 1 and 0;
    a ``noise_scale`` other than 0 needs the diffusion ``sigma``)."""

    trace_weight: float = 0.0
    gain: Tensor | float | None = None
    gain_scale: float = 1.0
    offset: Tensor | float | None = None
    offset_scale: float = 1.0
    noise_scale: float = 0.0


def describes(fns: Sequence[LieFunction], dynamics: ControlAffine) -> bool:
    """Whether the kernel is built and can evaluate every function of ``fns`` along
    ``dynamics`` by what they declare (``quadric()``, the compositions, ``native_model()``);
    the states of a call decide the rest (their number, dtype and device)."""
    return (
        _library() is not None
        and model_code(dynamics) is not None
        and all(_groups(fn) is not None for fn in fns)
    )


def lie_terms(
    fns: Sequence[LieFunction],
    x: Tensor,
    dynamics: ControlAffine,
    *,
    hessian: bool = True,
) -> tuple[LieTerms, list[int]] | None:
    """Lie terms of time-invariant quadric functions ``fns`` at a few states ``x [B, n]``
    (CPU, float64 or float32), their outputs concatenated: ``h, lfh, dhdt, hess_trace
    [B, K]``, ``lgh [B, K, m]``, ``dhdx [B, K, n]`` and each function's number of outputs,
    as :func:`~torchcbf.barriers.lie.stacked_lie_derivatives` returns them (``hess_trace``
    where ``hessian`` and the model has a diffusion, else ``None``; ``dhdt`` zeros).
    Computed in float64 and returned in ``x``'s dtype, without a graph.

    Returns ``None`` where the kernel does not apply (see the module); the caller then takes
    the torch path, which gives the same terms."""
    found = _evaluate(fns, x, dynamics, hessian, None)
    if found is None:
        return None
    outputs, sizes = found
    h, lfh, dhdt, lgh, trace, dhdx, _ = outputs
    return LieTerms(h, lfh, lgh, dhdt, trace, dhdx), sizes


def cbf_conditions(
    fns: Sequence[LieFunction],
    x: Tensor,
    dynamics: ControlAffine,
    affine: Affine,
    *,
    hessian: bool = True,
) -> tuple[Tensor, Tensor, Tensor, list[int]] | None:
    """The condition ``affine`` of the functions ``fns`` at a few states ``x [B, n]``, as
    :func:`lie_terms` takes them: ``h [B, K]``, ``a [B, K, m]``, ``b [B, K]`` (``x``'s dtype,
    no graph) and each function's number of outputs; ``None`` where the kernel does not
    apply, or the gain or offset is neither a scalar nor ``[K]``."""
    found = _evaluate(fns, x, dynamics, hessian, affine)
    if found is None:
        return None
    outputs, sizes = found
    return outputs[0], outputs[3], outputs[6], sizes


class ConditionCall(NamedTuple):
    """A prepared kernel call for the condition of :func:`cbf_conditions`, for a C caller
    (the safety filter's kernel) that fills the ``lgh`` and ``b`` slots of ``pointers`` with
    its own memory and calls the kernel at :func:`kernel_address`. ``h [B, K]`` (float64) is
    written by that call; ``held`` are the tensors the pointers read (keep them alive until
    then); ``sizes`` each function's number of outputs."""

    meta: array.array
    reals: array.array
    pointers: array.array
    h: Tensor
    held: list[Tensor]
    sizes: list[int]


def condition_call(
    fns: Sequence[LieFunction],
    x: Tensor,
    dynamics: ControlAffine,
    affine: Affine,
    *,
    hessian: bool = True,
) -> ConditionCall | None:
    """:func:`cbf_conditions` prepared for a C caller (see :class:`ConditionCall`), or
    ``None`` where it does not apply."""
    found = _arguments(fns, x, dynamics, hessian, affine)
    if found is None:
        return None
    meta, reals, pointers, held, sizes = found
    h = torch.empty(x.shape[0], sum(sizes), dtype=torch.float64)
    arrays = _kernel_arrays(meta, reals, pointers, (h, None, None, None, None, None, None))
    return ConditionCall(*arrays, h, held, sizes)


@functools.lru_cache(maxsize=1)
def kernel_address() -> int | None:
    """The address of the kernel's ``torchcbf_lie_quadrics`` (``None``: no kernel)."""
    lib = _library()
    return None if lib is None else ctypes.cast(lib.torchcbf_lie_quadrics, ctypes.c_void_p).value


def _evaluate(
    fns: Sequence[LieFunction],
    x: Tensor,
    dynamics: ControlAffine,
    hessian: bool,
    affine: Affine | None,
) -> tuple[tuple[Tensor | None, ...], list[int]] | None:
    """One kernel call: ``(h, lfh, dhdt, lgh, hess_trace, dhdx, b)`` in ``x``'s dtype (with
    ``affine``: only ``h``, ``lgh`` and ``b``; without: all but ``b``) and the sizes."""
    found = _arguments(fns, x, dynamics, hessian, affine)
    if found is None:
        return None
    meta, reals, pointers, held, sizes = found
    B, n = x.shape
    K, m = sum(sizes), dynamics.control_dim
    f64 = torch.float64
    h, lgh = torch.empty(B, K, dtype=f64), torch.empty(B, K, m, dtype=f64)
    if affine is None:
        lfh, dhdt = torch.empty(B, K, dtype=f64), torch.empty(B, K, dtype=f64)
        trace = None if pointers[LAYOUT["PT_SIGMA"]] == 0 else torch.empty(B, K, dtype=f64)
        dhdx, b = torch.empty(B, K, n, dtype=f64), None
    else:
        lfh = dhdt = trace = dhdx = None
        b = torch.empty(B, K, dtype=f64)
    outputs = (h, lfh, dhdt, lgh, trace, dhdx, b)
    arrays = _kernel_arrays(meta, reals, pointers, outputs)
    if _library().torchcbf_lie_quadrics(*(a.buffer_info()[0] for a in arrays)):  # type: ignore[union-attr]
        return None
    if x.dtype is not f64:
        outputs = tuple(None if v is None else v.to(x.dtype) for v in outputs)
    return outputs, sizes


def _arguments(
    fns: Sequence[LieFunction],
    x: Tensor,
    dynamics: ControlAffine,
    hessian: bool,
    affine: Affine | None,
) -> tuple[list[int], list[float], list[int], list[Tensor], list[int]] | None:
    """The kernel's ``meta``, ``reals`` and pointers (all but the seven outputs' slots, from
    ``PT_H``), the tensors those point into (keep them alive through the call) and each
    function's number of outputs; ``None`` where the kernel does not apply."""
    outer = model_code(dynamics)
    if _library() is None or outer is None or not fns or x.dim() != 2 or not x.is_cpu:
        return None
    dtype = x.dtype
    if dtype is not torch.float64 and dtype is not torch.float32:
        return None
    B, n = x.shape
    m = dynamics.control_dim
    if n != dynamics.state_dim or n > MAX_SIZE or m > MAX_SIZE:
        return None
    sigma = dynamics.sigma_matrix if hessian else None
    if hessian and sigma is None and dynamics.has_diffusion:
        return None  # a callable diffusion
    q = 0 if sigma is None else sigma.shape[-1]
    if q > MAX_SIZE or (sigma is not None and tuple(sigma.shape) != (n, q)):
        return None  # a diffusion matrix of another layout: the torch path reads it
    blocks: list[int] = []  # the blocks' integers, then the groups'
    rates: list[float] = []
    tensors: list[Tensor | None] = []
    sizes: list[int] = []
    # per group: its reduction, smooth, blocks and outputs (G_MODE... in the kernel)
    groups: list[list[int]] = []
    temperatures: list[float] = []
    for fn in fns:
        found = _groups(fn)
        if found is None:
            return None
        total = 0
        for group in found:
            columns = 0
            for block in group.blocks:
                k = _encode(block, blocks, rates, tensors)
                if k is None:
                    return None
                columns += k
            if group.reduction is None:
                total += columns
                if groups and groups[-1][0] == 0:  # one group for consecutive plain blocks
                    groups[-1][2:] = groups[-1][2] + len(group.blocks), groups[-1][3] + columns
                    continue
                outputs = columns
            else:
                outputs = group.outputs
                total += outputs
            code = REDUCTION_CODES[group.reduction]
            groups.append([code, int(group.smooth), len(group.blocks), outputs])
            temperatures.append(group.temperature)
        sizes.append(total)
    for group in groups:
        blocks += _pack_group(*group)
    strides: list[int | None] = [0, 0]
    scales = (0.0, 1.0, 1.0, 0.0)
    condition: tuple[Tensor | None, Tensor | None] = (None, None)
    if affine is not None:
        trace_weight, gain, gain_scale, offset, offset_scale, noise_scale = affine
        if noise_scale != 0.0 and sigma is None:
            return None
        if isinstance(gain, (int, float)):  # a plain number folds into its scale
            gain, gain_scale = None, gain_scale * gain
        if isinstance(offset, (int, float)):
            offset = torch.tensor(float(offset), dtype=torch.float64)
        strides = [_output_stride(v, sum(sizes)) for v in (gain, offset)]
        if None in strides:
            return None
        scales = (float(trace_weight), float(gain_scale), float(offset_scale), float(noise_scale))
        condition = gain, offset
    meta = _pack_header(B, n, m, q, *outer, len(rates), *strides, len(groups)) + blocks
    reals = _pack_reals(*scales) + rates + temperatures
    inputs = (x, sigma, *condition, *tensors)
    grads = torch.is_grad_enabled()
    for v in inputs:
        if v is not None and ((grads and v.requires_grad) or not v.is_cpu):
            return None
    pointers, held = float64_pointers(inputs)  # some are temporaries (a product of scales)
    return meta, reals, pointers, held, sizes


def _kernel_arrays(
    meta: list[int],
    reals: list[float],
    pointers: list[int],
    outputs: tuple[Tensor | None, ...],
) -> tuple[array.array, array.array, array.array]:
    """The kernel's three argument arrays, with the seven ``outputs`` (``h, lfh, dhdt, lgh,
    hess_trace, dhdx, b``; ``None``: not written) put into their pointer slots (from
    ``PT_H``)."""
    at = LAYOUT["PT_H"]
    pointers[at:at] = [0 if v is None else v.data_ptr() for v in outputs]
    return array.array("q", meta), array.array("d", reals), array.array("Q", pointers)


def _output_stride(value: Tensor | None, K: int) -> int | None:
    """The kernel's stride per output of a scalar or ``[K]`` constant (``None``: neither)."""
    if value is None or value.dim() == 0 or (K == 1 and value.shape == (1,)):
        return 0
    return 1 if value.shape == (K,) else None
