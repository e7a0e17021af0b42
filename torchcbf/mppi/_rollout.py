"""CPU fast path of MPPI: the C kernel ``_rollout_kernel.c`` (noise, rollout, built-in costs).

The kernel is built at install time when a C compiler is present (``setup.py``) and called
through :mod:`ctypes` (which releases the GIL, so the samples are split over
``torch.get_num_threads()`` threads). :func:`encode_model` and :func:`encode_cost` translate
a built-in model and cost into the kernel's configuration, or return ``None`` when the kernel
cannot evaluate them (the planner then uses torch for that part).

Noise: sample ``k``, step ``j`` and component pair ``q`` of environment ``b`` get the
standard normals of one Box-Muller pair computed from ``mix64(key_b + (c + 1) * golden)``
with the counter ``c = (k * H + j) * ceil(m / 2) + q``; ``key_b`` is drawn from environment
``b``'s ``torch.Generator`` once per planning call. The noise of any sample can therefore be
regenerated (the update pass and the re-rolled best sample do) without storing it.
"""

from __future__ import annotations

import ctypes
import functools
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from torchcbf._checks import behaves_as
from torchcbf._native import Layout, load_kernel, model_code, thread_pool
from torchcbf.barriers import LieFunction

logger = logging.getLogger(__name__)

#: ``KERNEL_VERSION`` of the C source this module calls
KERNEL_VERSION = 6
#: the file name of the built kernel, without its extension suffix
KERNEL_STEM = "_rollout_kernel"
#: the kernel's C sources
SOURCES = ("_rollout_kernel.c", "_rollout_kernel.h")
#: the integer constants of the C sources: the kernel's limits, its codes and the layout of
#: its configuration vector (offsets of the fields, sizes of the records), read from there
LAYOUT = Layout.read(Path(__file__).parent / name for name in SOURCES)
record, field = LAYOUT.record, LAYOUT.field
#: limits of the kernel (``NMAX``, ``MMAX``, ``DMAX``, ``TMAX``, ``SMAX`` in the C source)
MAX_STATE, MAX_CONTROL, MAX_DIM, MAX_TERMS, MAX_SHAPES = (
    LAYOUT[name] for name in ("NMAX", "MMAX", "DMAX", "TMAX", "SMAX")
)
#: fewest samples a thread is given
MIN_SAMPLES_PER_THREAD = 256

#: the methods whose formulas the kernel evaluates for a built-in cost term (a subclass that
#: changes one is scored by torch)
_COST_METHODS = ("forward", "stage", "terminal")
TERM_GOAL, TERM_OBSTACLE, TERM_BARRIER, TERM_DISCRETE_BARRIER = (
    LAYOUT[name] for name in ("T_GOAL", "T_OBSTACLE", "T_BARRIER", "T_DISCRETE_BARRIER")
)
SHAPE_ELLIPSE, SHAPE_BALL = LAYOUT["S_ELLIPSE"], LAYOUT["S_BALL"]
INTEGRATOR_CODES = {"euler": LAYOUT["I_EULER"], "rk4": LAYOUT["I_RK4"]}


@functools.lru_cache(maxsize=1)
def _library() -> ctypes.CDLL | None:
    return load_kernel(
        Path(__file__).parent,
        KERNEL_STEM,
        "torchcbf_mppi_version",
        KERNEL_VERSION,
        "MPPI runs in torch",
        sources=SOURCES,
    )


def available() -> bool:
    """Whether the C kernel was built and loads."""
    return _library() is not None


def _kernel() -> ctypes.CDLL:
    lib = _library()
    if lib is None:
        raise RuntimeError("torchcbf: the MPPI kernel was not built (no C compiler at install)")
    return lib


# -- configuration ---------------------------------------------------------------------------
def encode_model(dynamics: nn.Module) -> tuple[int, int] | None:
    """``(model code, dim)`` of a model the kernel knows (its
    :meth:`~torchcbf.dynamics.ControlAffine.native_model`, which a subclass that changes the
    dynamics does not inherit), or ``None``."""
    found = model_code(dynamics)
    if found is None:
        return None
    if dynamics.state_dim > MAX_STATE or dynamics.control_dim > MAX_CONTROL:
        return None
    return found


def _values(t: Tensor) -> list[float]:
    return [float(v) for v in t.detach().reshape(-1).tolist()]


def _per_shape(value: Tensor | None, k: int, default: float) -> list[float] | None:
    """A quadric's per-shape constant (``[]`` or ``[k]``, ``None``: ``default``) as k floats."""
    if value is None:
        return [default] * k
    v = value.detach()
    if v.dim() == 0:
        return _values(v.expand(k))
    return _values(v) if v.shape == (k,) else None


def _shape_records(barrier: object) -> list[list[float]] | None:
    """Kernel records of a barrier's :meth:`~torchcbf.barriers.LieFunction.quadric` (one
    per output), or ``None``. The kernel evaluates ``sign (sum_i (q_i / a_i)^2 - c0)`` with
    ``c0 = r^2`` for a ball (no axes, no rotation) and 1 otherwise, so a quadric's scale
    goes into the sign and a radius into the axes."""
    quadric = barrier.quadric() if isinstance(barrier, LieFunction) else None
    if quadric is None or barrier.time_varying:
        return None
    index = tuple(quadric.index)
    center = quadric.center.detach()
    d = center.shape[-1]
    if center.dim() not in (1, 2) or d > MAX_DIM or len(index) != d:
        return None
    centers = center.reshape(-1, d)
    k = centers.shape[0]
    if quadric.axes is not None and quadric.axes.shape != center.shape:
        return None
    radius = _per_shape(quadric.radius, k, 1.0)
    scale = _per_shape(quadric.scale, k, 1.0)
    angles = None if quadric.angle is None else _per_shape(quadric.angle, k, 0.0)
    if radius is None or scale is None or (quadric.angle is not None and angles is None):
        return None
    if angles is not None and d != 2:
        return None
    ball = quadric.axes is None and angles is None
    axes = torch.ones_like(centers) if quadric.axes is None else quadric.axes.detach()
    axes = axes.reshape(-1, d)
    records = []
    for j in range(k):
        r = radius[j]
        a = _values(axes[j]) if ball else [v * abs(r) for v in _values(axes[j])]
        rec = record(
            "SREC",
            SR_KIND=SHAPE_BALL if ball else SHAPE_ELLIPSE,
            SR_D=d,
            SR_IDX=index,
            SR_CENTER=_values(centers[j]),
            SR_AXES=a,
            SR_RADIUS=r if ball else 0.0,
            SR_SIGN=quadric.sign * scale[j] * (1.0 if ball else r * r),
            SR_ROTATED=float(angles is not None),
            SR_ANGLE=0.0 if angles is None else angles[j],
        )
        records.append(rec)
    return records


def _term(kind: int, weight: float, extra: float, eps: float, **fields: Any) -> list[float]:
    return record("TREC", TR_TYPE=kind, TR_WEIGHT=weight, TR_EXTRA=extra, TR_EPS=eps, **fields)


def _point_term(
    kind: int, weight: float, extra: float, eps: float, index: object, point: Tensor, **fields: Any
) -> list[float] | None:
    idx = list(range(index.start, index.stop)) if isinstance(index, slice) else list(index)
    center = _values(point)
    if len(idx) > MAX_DIM or len(center) != len(idx):
        return None
    return _term(kind, weight, extra, eps, TR_D=len(idx), TR_IDX=idx, TR_CENTER=center, **fields)


def encode_cost(cost: object, state_dim: int) -> tuple[list[list[float]], list[list[float]]] | None:
    """``(term records, shape records)`` of a cost built from the built-in terms
    (:class:`QuadraticGoal`, :class:`ObstacleCost`, :class:`BarrierCost` and
    :class:`DiscreteBarrierCost` over :class:`Ellipse`/:class:`Ball` barriers, and
    :class:`SumCost` of them), or ``None``."""
    from torchcbf.mppi.costs import (
        BarrierCost,
        DiscreteBarrierCost,
        ObstacleCost,
        QuadraticGoal,
        SumCost,
    )

    built_in = (QuadraticGoal, ObstacleCost, BarrierCost, DiscreteBarrierCost)

    if behaves_as(cost, SumCost, _COST_METHODS):
        parts = cost.stepwise_terms + cost.whole_terms
    else:
        parts = [cost]
    terms: list[list[float]] = []
    shapes: list[list[float]] = []
    shared: dict[int, tuple[int, int]] = {}  # id(barrier) -> its shape records (evaluated once)
    for part in parts:
        kind = next((c for c in built_in if behaves_as(part, c, _COST_METHODS)), None)
        if kind is QuadraticGoal:
            rec = _point_term(
                TERM_GOAL, part.weight, part.terminal_weight, 0.0, part.index, part.goal
            )
        elif kind is ObstacleCost:
            rec = _point_term(
                TERM_OBSTACLE,
                0.0,
                part.k_o,
                part.eps,
                part.index,
                part.center,
                TR_RADIUS=float(part.radius),
            )
        elif kind in (BarrierCost, DiscreteBarrierCost):
            if id(part.barrier) not in shared:
                recs = _shape_records(part.barrier)
                if recs is None:
                    return None
                shared[id(part.barrier)] = (len(shapes), len(recs))
                shapes.extend(recs)
            shape0, nshape = shared[id(part.barrier)]
            if kind is BarrierCost:
                kind_code, extra, eps = TERM_BARRIER, 0.0, part.eps
            else:
                kind_code, extra = TERM_DISCRETE_BARRIER, part.gamma
                eps = -1 if part.steps is None else part.steps
            rec = _term(kind_code, part.weight, extra, eps, TR_SHAPE0=shape0, TR_NSHAPE=nshape)
        else:
            return None
        if rec is None:
            return None
        terms.append(rec)
    # an index outside the state is left to torch, which raises the usual error
    for rec in terms:
        if any(not 0 <= i < state_dim for i in field(rec, "TR_IDX", int(field(rec, "TR_D")))):
            return None
    for rec in shapes:
        if any(not 0 <= i < state_dim for i in field(rec, "SR_IDX", int(field(rec, "SR_D")))):
            return None
    if len(terms) > MAX_TERMS or len(shapes) > MAX_SHAPES:
        return None
    return terms, shapes


class Configuration(NamedTuple):
    """The kernel's float64 configuration ``values`` and the sizes written in it (``n``,
    ``m``, ``horizon``, ``samples``), against which :func:`run` checks its tensors."""

    values: Tensor
    n: int
    m: int
    horizon: int
    samples: int


def configuration(
    model: tuple[int, int],
    integrator: str,
    n: int,
    m: int,
    horizon: int,
    num_samples: int,
    zero_noise: int,
    u_min: Tensor | None,
    u_max: Tensor | None,
    chol: Tensor,
    dt: float,
    gamma: float,
    cost: tuple[list[list[float]], list[list[float]]] | None,
) -> Configuration:
    """The kernel's configuration (layout of its float64 vector in ``_rollout_kernel.c``)."""
    for name, value, shape in (
        ("u_min", u_min, (m,)),
        ("u_max", u_max, (m,)),
        ("noise_chol", chol, (m, m)),
    ):
        if value is not None and tuple(value.shape) != shape:
            raise ValueError(f"{name} must be {list(shape)}, got {tuple(value.shape)}")
    terms, shapes = cost if cost is not None else ([], [])
    head = record(
        "HDR",
        H_VERSION=KERNEL_VERSION,
        H_MODEL=model[0],
        H_INTEGRATOR=INTEGRATOR_CODES[integrator],
        H_N=n,
        H_M=m,
        H_H=horizon,
        H_K=num_samples,
        H_DIM=model[1],
        H_ZERO_NOISE=zero_noise,
        H_HAS_LO=float(u_min is not None),
        H_HAS_HI=float(u_max is not None),
        H_NTERMS=len(terms),
        H_NSHAPES=len(shapes),
        H_DT=dt,
        H_GAMMA=gamma,
    )
    lo = [0.0] * MAX_CONTROL
    hi = [0.0] * MAX_CONTROL
    if u_min is not None:
        lo[:m] = _values(u_min)
    if u_max is not None:
        hi[:m] = _values(u_max)
    L = [0.0] * (MAX_CONTROL * MAX_CONTROL)
    c = _values(chol)
    for i in range(m):
        for j in range(m):
            L[i * MAX_CONTROL + j] = c[i * m + j]
    flat = head + lo + hi + L
    for rec in terms + shapes:
        flat.extend(rec)
    values = torch.tensor(flat, dtype=torch.float64)
    return Configuration(values, n, m, horizon, num_samples)


# -- calls -----------------------------------------------------------------------------------
def _ptr(t: Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def run(
    cfg: Configuration,
    count: int,
    x0: Tensor,
    plan: Tensor,
    keys: Tensor,
    *,
    pairs: Tensor | None = None,
    wctrl: Tensor | None = None,
    cost: Tensor | None = None,
    states: Tensor | None = None,
    controls: Tensor | None = None,
    eps: Tensor | None = None,
    weights: Tensor | None = None,
    wsum: Tensor | None = None,
    layout: str = "component",
) -> None:
    """Run the kernel on samples ``0..count`` (``pairs [count, 2]`` of ``(b, k)``, or every
    ``(b, k)`` in order when ``None``), writing the requested outputs (see the C source).

    All tensors are CPU tensors of the rollout dtype (``keys``, ``pairs``: int64; ``wsum``:
    ``[T, B, H, m]`` float64 with one slice per thread, summed by the caller). ``x0 [B,
    n]``, ``plan`` and ``wctrl [B, H, m]``, ``cost`` and ``weights [count]``. With
    ``pairs``, ``states [count, H+1, n]``, ``controls`` and ``eps [count, H, m]`` are
    C-contiguous rows; without, they are ``[B, K, H+1, n]`` and ``[B, K, H, m]`` stored as
    ``layout`` says (:func:`rollout_buffer`).
    """
    lib = _kernel()
    # inputs are read row-major: their layout is made so (outputs must already be)
    pairs, x0, plan, wctrl, keys, weights = (
        None if t is None else t.contiguous() for t in (pairs, x0, plan, wctrl, keys, weights)
    )
    cmajor = pairs is None and layout == "component"
    _check_call(cfg, count, x0, plan, keys, pairs, wctrl, cost, states, controls, eps,
                weights, wsum, cmajor)  # fmt: skip
    fn = lib.torchcbf_mppi_run_f64 if x0.dtype == torch.float64 else lib.torchcbf_mppi_run_f32
    inputs = [pairs, x0, plan, wctrl, keys]
    threads = update_threads(count) if wsum is None else wsum.shape[0]
    bounds = [count * i // threads for i in range(threads + 1)]
    if wsum is not None and inputs[0] is not None and threads > 1:
        # each environment's weighted sum is accumulated by one thread, in sample order, so
        # the result does not depend on the number of threads
        envs = inputs[0][:, 0]
        envs = envs.contiguous()
        cut = torch.searchsorted(envs, envs[torch.tensor(bounds[1:-1])], side="left").tolist()
        bounds = [0, *cut, count]
    common = [_ptr(t) for t in inputs]
    outs = [_ptr(cost), _ptr(states), _ptr(controls), _ptr(eps), _ptr(weights)]
    cfg_ptr = cfg.values.data_ptr()

    def call(i: int) -> int:
        part = None if wsum is None else wsum[i].data_ptr()
        return fn(cfg_ptr, bounds[i], bounds[i + 1], *common, *outs, part, int(cmajor))

    if threads == 1:
        codes = [call(0)]
    else:
        codes = list(thread_pool(threads, "torchcbf-mppi").map(call, range(threads)))
    bad = [c for c in codes if c != 0]
    if bad:
        raise RuntimeError(f"torchcbf: the MPPI kernel refused its configuration (code {bad[0]})")


def _check_call(
    cfg: Configuration,
    count: int,
    x0: Tensor,
    plan: Tensor,
    keys: Tensor,
    pairs: Tensor | None,
    wctrl: Tensor | None,
    cost: Tensor | None,
    states: Tensor | None,
    controls: Tensor | None,
    eps: Tensor | None,
    weights: Tensor | None,
    wsum: Tensor | None,
    cmajor: bool,
) -> None:
    """Check every tensor :func:`run` hands the kernel against the sizes of ``cfg``: CPU,
    its dtype, shape and layout; raise ``ValueError`` or ``TypeError`` naming it (the kernel
    reads raw memory and checks none of it). The values of ``pairs`` are the caller's
    (built from ``nonzero`` or ``arange``, sorted by environment)."""
    n, m, H, K = cfg.n, cfg.m, cfg.horizon, cfg.samples
    real = x0.dtype
    if real not in (torch.float32, torch.float64):
        raise TypeError(f"x0 must be float32 or float64, got {real}")
    B = x0.shape[0] if x0.dim() == 2 else -1
    if pairs is None and not 0 <= count <= B * K:
        raise ValueError(f"count must be in [0, {B * K}], got {count}")
    rows = (count,) if pairs is not None else (B, K)
    _expect("x0", x0, (B, n), real)
    _expect("plan", plan, (B, H, m), real)
    _expect("keys", keys, (B,), torch.int64)
    if pairs is not None:
        _expect("pairs", pairs, (count, 2), torch.int64)
    if wctrl is not None:
        _expect("wctrl", wctrl, (B, H, m), real)
    if cost is not None:
        _expect("cost", cost, rows, real)
    if states is not None:
        _expect("states", states, (*rows, H + 1, n), real, cmajor)
    if controls is not None:
        _expect("controls", controls, (*rows, H, m), real, cmajor)
    if eps is not None:
        _expect("eps", eps, (*rows, H, m), real, cmajor)
    if weights is not None:
        _expect("weights", weights, (count,), real)
    if wsum is not None:
        _expect("wsum", wsum, (wsum.shape[0], B, H, m), torch.float64)


def _expect(
    name: str, t: Tensor, shape: tuple[int, ...], dtype: torch.dtype, by_component: bool = False
) -> None:
    """Raise unless ``t`` is a CPU tensor of ``dtype`` and ``shape``, stored component-major
    (``by_component``: :func:`component_major`) or C-contiguous."""
    if t.device.type != "cpu":
        raise ValueError(f"{name} must be on the CPU, got {t.device}")
    if t.dtype != dtype:
        raise TypeError(f"{name} must be {dtype} for this call, got {t.dtype}")
    if t.shape != shape:
        raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
    if by_component and not t.permute(0, 3, 2, 1).is_contiguous():
        raise ValueError(f"{name} must be in component-major storage")
    if not by_component and not t.is_contiguous():
        raise ValueError(f"{name} must be contiguous")


def _noise_target(name: str, t: Tensor) -> None:
    """Check a ``[B, K, H, m]`` noise-shaped output of :func:`normals` or :func:`perturb`."""
    if t.dim() != 4 or not 1 <= t.shape[-1] <= MAX_CONTROL:
        raise ValueError(
            f"{name} must be [B, K, H, m] with m <= {MAX_CONTROL}, got {list(t.shape)}"
        )
    if t.dtype not in (torch.float32, torch.float64) or t.device.type != "cpu":
        raise ValueError(
            f"{name} must be a float32 or float64 CPU tensor, got {t.dtype} on {t.device}"
        )


def _over_samples(
    name: str, keys: Tensor, shape: torch.Size, call: Callable[[int, int, int], int]
) -> None:
    """``call(keys pointer, k_lo, k_hi)`` over slices of the ``K`` samples of ``shape [B, K,
    H, m]``, one per thread, for ``keys [B]`` (int64, CPU); a refusal raises."""
    B, K = shape[0], shape[1]
    keys = keys.contiguous()
    if keys.dtype != torch.int64 or keys.shape != (B,) or keys.device.type != "cpu":
        raise ValueError(
            f"keys must be int64 [{B}] on the CPU, got {keys.dtype} {list(keys.shape)}"
        )
    threads = update_threads(B * K)
    bounds = [K * i // threads for i in range(threads + 1)]

    def one(i: int) -> int:
        return call(keys.data_ptr(), bounds[i], bounds[i + 1])

    if threads == 1:
        codes = [one(0)]
    else:
        codes = list(thread_pool(threads, "torchcbf-mppi").map(one, range(threads)))
    if any(codes):
        raise RuntimeError(f"torchcbf: the MPPI kernel refused the {name} call (code {codes})")


def normals(keys: Tensor, out: Tensor, *, std: float = 1.0) -> None:
    """Fill ``out [B, K, H, m]`` (CPU, float32 or float64, any strides) with the kernel's
    counter-based standard normals times ``std``, from ``keys [B]`` (int64): the noise the
    kernel draws for those keys before the zero-noise samples, the covariance factor and
    the limits are applied (module docstring). Threads split the samples."""
    lib = _kernel()
    _noise_target("out", out)
    B, K, H, m = out.shape
    fn = (
        lib.torchcbf_mppi_normals_f64
        if out.dtype == torch.float64
        else lib.torchcbf_mppi_normals_f32
    )
    tail = (H, m, float(std), out.data_ptr(), *out.stride())
    _over_samples("noise", keys, out.shape, lambda key, lo, hi: fn(key, 0, B, lo, hi, *tail))


def perturb(
    keys: Tensor,
    eps: Tensor,
    controls: Tensor,
    plan: Tensor,
    chol: Tensor,
    *,
    u_min: Tensor | None,
    u_max: Tensor | None,
) -> None:
    """The sampled controls of the torch path in one pass: ``controls = clamp(plan + L z,
    u_min, u_max)`` and ``eps = controls - plan`` for ``eps``, ``controls [B, K, H, m]`` (CPU,
    float32 or float64, any strides), ``plan [B, H, m]``, the lower-triangular factor ``L =
    chol [m, m]``, limits ``[m]`` or ``None``, and ``z`` the normals :func:`normals` draws for
    ``keys [B]`` (the kernel's own arithmetic: the fused path's samples). Threads split the
    samples."""
    lib = _kernel()
    _noise_target("eps", eps)
    B, K, H, m = eps.shape
    if controls.shape != eps.shape or controls.dtype != eps.dtype or not controls.is_cpu:
        raise ValueError(
            f"controls must be {eps.dtype} {list(eps.shape)} on the CPU like eps, got "
            f"{controls.dtype} {list(controls.shape)} on {controls.device}"
        )
    if plan.shape != (B, H, m) or plan.dtype != eps.dtype or not plan.is_cpu:
        raise ValueError(
            f"plan must be {eps.dtype} [{B}, {H}, {m}] on the CPU, got {plan.dtype} "
            f"{list(plan.shape)} on {plan.device}"
        )
    if chol.shape != (m, m):
        raise ValueError(f"chol must be [{m}, {m}], got {list(chol.shape)}")
    L = torch.zeros(MAX_CONTROL, MAX_CONTROL, dtype=torch.float64)
    L[:m, :m] = chol.detach().to("cpu", torch.float64).tril()
    limits = []
    for limit in (u_min, u_max):
        padded = torch.zeros(MAX_CONTROL, dtype=torch.float64)
        if limit is not None:
            padded[:m] = limit.detach().to("cpu", torch.float64).expand(m)
        limits.append(padded)
    plan = plan.contiguous()
    fn = (
        lib.torchcbf_mppi_perturb_f64
        if eps.dtype == torch.float64
        else lib.torchcbf_mppi_perturb_f32
    )
    tail = (
        H,
        m,
        L.data_ptr(),
        plan.data_ptr(),
        limits[0].data_ptr(),
        limits[1].data_ptr(),
        int(u_min is not None),
        int(u_max is not None),
        eps.data_ptr(),
        *eps.stride(),
        controls.data_ptr(),
        *controls.stride(),
    )
    _over_samples("perturb", keys, eps.shape, lambda key, lo, hi: fn(key, 0, B, lo, hi, *tail))


def update_threads(count: int) -> int:
    """Threads of a kernel pass over ``count`` samples (an update pass's ``wsum`` holds one
    slice per thread)."""
    return max(1, min(torch.get_num_threads(), count // MIN_SAMPLES_PER_THREAD))


def draw_keys(generators: list[torch.Generator], device: torch.device) -> Tensor:
    """One 63-bit noise key per environment ``[B]`` (int64, on ``device``, the generators')."""
    high = 2**63 - 1
    keys = [torch.randint(0, high, (1,), generator=g, device=g.device) for g in generators]
    if not keys:  # an empty batch
        return torch.empty(0, dtype=torch.int64, device=device)
    return keys[0] if len(keys) == 1 else torch.cat(keys)


class Kernel:
    """The C kernel bound to one configuration: the passes a planner calls (the Triton
    kernel, :class:`torchcbf.mppi._triton.Kernel`, has the same methods). ``fused``: the
    configuration holds the cost terms (the kernel scores the samples itself)."""

    name = "c"

    def __init__(self, cfg: Configuration, *, fused: bool) -> None:
        self.cfg, self.fused = cfg, fused

    def costs(self, x: Tensor, plan: Tensor, keys: Tensor, wctrl: Tensor | None) -> Tensor:
        """Total cost ``[B, K]`` of every sample."""
        B, K = plan.shape[0], self.cfg.samples
        cost = plan.new_empty(B, K)
        run(self.cfg, B * K, x, plan, keys, wctrl=wctrl, cost=cost)
        return cost

    def update(self, x: Tensor, plan: Tensor, keys: Tensor, w: Tensor) -> Tensor:
        """``sum_k w_k eps_k [B, H, m]`` for ``w [B, K]`` with the noise of the samples of
        non-zero weight regenerated (accumulated in float64)."""
        B, H, m = plan.shape
        if w.dim() != 2 or w.shape[0] != B:
            raise ValueError(f"weights must have shape [{B}, K], got {list(w.shape)}")
        pairs = (w > 0).nonzero()
        count = pairs.shape[0]
        wsum = torch.zeros(update_threads(count), B, H, m, dtype=torch.float64)
        if count:
            w_sel = w[pairs[:, 0], pairs[:, 1]].contiguous()
            run(self.cfg, count, x, plan, keys, pairs=pairs, weights=w_sel, wsum=wsum)
        return wsum.sum(0).to(plan.dtype)

    def weights(self, cost: Tensor, temperature: float) -> None:
        """No weights pass: on the CPU the planner's torch weights are as fast (the Triton
        kernel has one, :meth:`torchcbf.mppi._triton.Kernel.weights`)."""
        return None

    def rows(self, x: Tensor, plan: Tensor, keys: Tensor, pairs: Tensor) -> Tensor:
        """The rollouts ``[P, H+1, n]`` of the samples ``pairs [P, 2]`` of ``(b, k)``."""
        states = plan.new_empty(pairs.shape[0], plan.shape[1] + 1, self.cfg.n)
        run(self.cfg, pairs.shape[0], x, plan, keys, pairs=pairs.contiguous(), states=states)
        return states

    def buffers(
        self,
        x: Tensor,
        plan: Tensor,
        keys: Tensor,
        states: Tensor,
        controls: Tensor,
        wctrl: Tensor | None,
        layout: str,
    ) -> Tensor | None:
        """Fill every sample's ``states [B, K, H+1, n]`` and ``controls [B, K, H, m]``
        (stored as ``layout`` says); return the control cost ``[B, K]`` (``None`` without
        ``wctrl``)."""
        B = plan.shape[0]
        ctrl = None if wctrl is None else plan.new_empty(B, self.cfg.samples)
        run(
            self.cfg, B * self.cfg.samples, x, plan, keys,
            states=states, controls=controls, wctrl=wctrl, cost=ctrl, layout=layout,
        )  # fmt: skip
        return ctrl


def rollout_buffer(like: Tensor, B: int, K: int, steps: int, dim: int, layout: str) -> Tensor:
    """An uninitialised ``[B, K, steps, dim]`` tensor like ``like``, stored component-major
    (:func:`component_major`) for ``layout="component"``, C-contiguous for ``"sample"``."""
    if layout == "component":
        return component_major(like, B, K, steps, dim)
    return like.new_empty(B, K, steps, dim)


def component_major(like: Tensor, B: int, K: int, steps: int, dim: int) -> Tensor:
    """An uninitialised ``[B, K, steps, dim]`` tensor stored as ``[B, dim, steps, K]``:
    each component's ``[steps, K]`` block is contiguous with the samples fastest, so a torch
    cost written on ``[..., dim]`` rows runs long vectorised inner loops."""
    return like.new_empty(B, dim, steps, K).permute(0, 3, 2, 1)
