"""Model Predictive Path Integral (MPPI) control, batched over environments and samples.

One call plans for ``B`` environments at once with ``K`` sampled control sequences each; the
rollouts of all ``B * K`` samples are one batched computation (the only Python loop is over
the ``H`` steps of the horizon).

Algorithm (per environment, as pytorch-mppi / Williams et al. 2017):

1. warm start: the plan ``U [H, m]`` of the previous call is shifted one step (the vacated
   last control is zero, or the previous last control with ``shift_fill="last"``);
2. noise ``eps_k = z_k L'`` with ``z_k ~ N(0, I)`` and ``L = cholesky(Sigma)``;
3. the perturbed controls are clamped to the limits and the noise recomputed,
   ``v_k = clamp(U + eps_k)``, ``eps_k = v_k - U``;
4. rollouts ``x_{j+1} = step(x_j, v_{k,j})`` from the current state (``euler`` or ``rk4``,
   nominal noise-free dynamics);
5. ``S_k = cost(rollout_k) + gamma * sum_j U_j' Sigma^-1 eps_{k,j}`` (the pytorch-mppi form
   of the control cost, ``gamma = control_cost_weight``);
6. ``w_k = exp(-(S_k - min S) / lambda) / sum(...)`` (``lambda = temperature``, floored at
   the dtype's smallest normal number; a weight below that number is zero); a sample whose
   cost is not finite (NaN, +inf or -inf: a cost is a penalty, so -inf is taken as an error
   of the cost, not as a perfect sample) gets weight zero and is counted in
   ``MPPIOutput.nonfinite``; with ``cost_normalization="range"`` (``"std"``) the exponent is
   divided by the range (the standard deviation) of the sample costs;
7. ``U <- U + sum_k w_k eps_k``; the first control ``U_0`` is returned.

Randomness: environment ``b`` draws its noise from its own ``torch.Generator`` on the
device, seeded with ``seed + b``. Environment ``b`` of a batched planner therefore produces
the plans of a one-environment planner built with ``seed + b`` (exactly on the fused path;
up to the rounding of a torch cost's reductions over a different slice of samples on the
others). The global RNG is never used. ``reset()`` re-seeds the generators.

Paths (``MPPI.path`` says which one the last call took):

- ``"fused"``: on the CPU, in float32 or float64, for a built-in model (``SingleIntegrator``,
  ``DoubleIntegrator``, ``Unicycle``, ``AccelUnicycle``) and a cost made of the built-in terms
  (:class:`~torchcbf.mppi.QuadraticGoal`, :class:`~torchcbf.mppi.ObstacleCost`,
  :class:`~torchcbf.mppi.BarrierCost` and :class:`~torchcbf.mppi.DiscreteBarrierCost` over
  :class:`~torchcbf.barriers.Ellipse`/:class:`~torchcbf.barriers.Ball` barriers, and their
  :class:`~torchcbf.mppi.SumCost`), the C kernel of :mod:`torchcbf.mppi._rollout` draws the
  noise, rolls out and scores every sample without storing the rollouts, and regenerates the
  noise of the samples with a non-zero weight for the update. Its noise is counter-based:
  the generator of environment ``b`` gives one key per call, hashed with the sample, step
  and component indices (so seeds stay reproducible and batch = loop still holds). The
  torch path on the CPU draws the same normals (:func:`torchcbf.mppi._rollout.normals`),
  so for one seed every CPU path gives the same plans to rounding.
- ``"rollout"``: a built-in model with any other cost: the kernel draws the noise and rolls
  out into the ``[B, K, H+1, n]`` buffer, torch evaluates the cost.
- on CUDA both paths run the Triton kernel of :mod:`torchcbf.mppi._triton` (where Triton
  imports; it ships with CUDA builds of torch): the same configuration, formulas and
  counter-based noise as the C kernel (given the same keys both kernels give the same
  samples, rollouts and costs to rounding; the keys come from the device's generators,
  which draw other numbers on CUDA than on the CPU), one launch per pass with the loop over
  the horizon inside the kernel. The rollout path on CUDA needs ``layout="component"``.
- either kernel's configuration is read from the planner, its model and its cost once and
  kept until one of their tensors changes (in place or replaced) or one of their number,
  string or tuple attributes changes (a change through ``.data`` is not seen: call
  ``reset()`` after one), so a planning call neither re-encodes it nor waits for the device.
  ``MPPI.engine`` says which kernel the last call ran (``"c"``, ``"triton"`` or ``None``).
- ``"torch"``: everything else (any :class:`~torchcbf.dynamics.ControlAffine`, CUDA without
  Triton, a planner built with ``backend="torch"``, gradients requested through the planner's
  parameters, and the options the kernel does not express: ``step=``, ``noise_abs_cost``,
  ``noise_mu``, ``action_sampler``, ``sample_null_action`` and the variants that sample
  otherwise, :class:`~torchcbf.mppi.SMPPI` and :class:`~torchcbf.mppi.KMPPI`): on the CPU
  the kernel's counter-based normals (where the kernel is built, up to 4 controls; about
  2.5x faster than ``normal_``), otherwise ``normal_`` from each environment's generator;
  rollouts with :mod:`torchcbf.integrators` (or ``step``), buffers allocated once and
  reused.

Every path hands a torch cost ``states [B, K, H+1, n]`` and ``controls [B, K, H, m]``,
sliced over the samples (``cost_chunk``), as views of component-major storage (``[B, n,
H+1, K]``, ``[B, m, H, K]``: each component's samples contiguous) or, with
``layout="sample"``, of C-contiguous buffers (each state contiguous); index them, do not
``.view`` them.

Compilation: ``MPPI(..., compile=True)`` (or a dict of ``torch.compile`` keyword arguments)
compiles the evaluation of a torch cost (cost + control cost, called once on all samples)
and, on the torch path, one integration step that reads and writes the rollout buffers
itself (one graph for every step index); the loop over the horizon, noise sampling,
weights and the plan update stay eager, and a fused cost is not affected. Each planner
compiles its own graphs (:class:`torchcbf._compile.Compiled`). The first call
compiles (3.5-6 s on a 2-core CPU with a cold compile cache, under 1 s with a warm one; see
:mod:`torchcbf._compile`); later calls with the same ``B`` reuse the code, whatever the
values of the state, time and plan. Where the backend fails to build, the planner warns and
runs eager.
"""

from __future__ import annotations

import logging
import math
import numbers
import warnings
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn.parameter import UninitializedTensorMixin

from torchcbf import integrators
from torchcbf._autograd import needs_graph
from torchcbf._checks import (
    TracksShadows,
    as_limit,
    as_matrix,
    as_tensor,
    behaves_as,
    check_bool,
    check_bounds,
    check_compile,
    check_int,
    check_last_dim,
    check_number,
    check_positive,
    check_seed,
    check_spd,
    check_times,
    follow_parts,
    hook_dicts,
    isfinite,
    resolved,
    shadowed_methods,
)
from torchcbf._compile import Compiled, hook_key, read_key
from torchcbf._constants import ExactConstants, remember
from torchcbf._graphs import CapturedCall
from torchcbf._native import keep_freed_heap
from torchcbf._random import seed_rows
from torchcbf._triton import available as triton_available
from torchcbf._triton import interpreted as triton_interpreted
from torchcbf.dynamics.base import ControlAffine
from torchcbf.mppi import _rollout, _triton
from torchcbf.mppi.history import History, HistoryBuffer

INTEGRATORS = ("euler", "rk4")
SHIFT_FILLS = ("zero", "last")
NORMALIZATIONS = ("none", "range", "std")
BACKENDS = ("auto", "torch", "triton")
LAYOUTS = ("component", "sample")
#: state elements (``B x slice x (H+1) x n``) per cost call when ``cost_chunk`` is automatic
AUTO_CHUNK_ELEMENTS = 2**17
#: CPU tensors of the planner, its model and its cost up to this many elements are compared
#: by value before a kept kernel configuration is used again (a configuration reads only
#: small ones: a few goals, shapes, bounds and an ``m x m`` covariance)
VALUE_CHECK = 1024
#: fewest samples per automatic slice (the inner loops of a torch cost run over a slice's
#: samples, which are contiguous in the rollout buffers)
MIN_CHUNK_SAMPLES = 16

logger = logging.getLogger("torchcbf")

_AnyKernel = _rollout.Kernel | _triton.Kernel


def _check_options(
    *,
    num_samples: object,
    keep_rollouts: object,
    zero_noise_samples: object,
    integrator: object,
    cost_normalization: object,
    shift_fill: object,
    temperature: object,
    control_cost_weight: object,
    dt: object,
) -> None:
    """The planner's options a user may set between calls, checked at construction and at
    each call (a ``ValueError`` naming the option)."""
    for name, value, low in (
        ("num_samples", num_samples, 1),
        ("keep_rollouts", keep_rollouts, 0),
        ("zero_noise_samples", zero_noise_samples, 0),
    ):
        if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    if keep_rollouts > num_samples or zero_noise_samples > num_samples:  # type: ignore[operator]
        raise ValueError(
            f"keep_rollouts ({keep_rollouts}) and zero_noise_samples ({zero_noise_samples})"
            f" must not exceed num_samples ({num_samples})"
        )
    for name, value, allowed in (
        ("integrator", integrator, INTEGRATORS),
        ("cost_normalization", cost_normalization, NORMALIZATIONS),
        ("shift_fill", shift_fill, SHIFT_FILLS),
    ):
        if value not in allowed:
            raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
    check_positive("temperature", temperature)  # type: ignore[arg-type]
    check_number("control_cost_weight", control_cost_weight, low=0.0)
    check_positive("dt", dt)  # type: ignore[arg-type]


class MPPIOutput(NamedTuple):
    """Result of one planning call (``B`` dimension absent when ``x`` was ``[n]``).

    Attributes:
        u: ``[B, m]`` first control of the updated plan.
        plan: ``[B, H, m]`` updated plan (a copy).
        cost_min: ``[B]`` lowest sample cost.
        cost_mean: ``[B]`` mean of the finite sample costs.
        ess: ``[B]`` effective sample size ``1 / sum_k w_k^2`` (0 when ``status != 0``).
        status: ``[B]`` int64, 0 = ok, 1 = no sample had a finite cost (plan only shifted).
        best_states: ``[B, H+1, n]`` rollout of the lowest-cost sample.
        rollouts: ``[B, R, H+1, n]`` the first ``R = keep_rollouts`` sampled rollouts, or None.
        rollout_weights: ``[B, R]`` their weights, or None.
        nonfinite: ``[B]`` int64, samples whose cost was NaN or infinite (weight zero).
        path: the path that planned (``"fused"``, ``"fused_graph"`` (the fused call
            replayed from a CUDA graph), ``"rollout"`` or ``"torch"``, see
            :mod:`torchcbf.mppi.planner`).
        filtered: the safety filter's output for ``u`` where a
            :class:`~torchcbf.mppi.ShieldMPPI` filtered it (its per-row ``status``, ``h``,
            ``path``), else None.
    """

    u: Tensor
    plan: Tensor
    cost_min: Tensor
    cost_mean: Tensor
    ess: Tensor
    status: Tensor
    best_states: Tensor
    rollouts: Tensor | None
    rollout_weights: Tensor | None
    nonfinite: Tensor | None = None
    path: str = "torch"
    filtered: Any = None


_PLAIN = (bool, int, float, str, slice, tuple, type(None))


def _stamp(t: Tensor) -> tuple[Any, ...]:
    """The storage and in-place version of ``t``; its identity for a tensor without
    storage of its own (sparse, or a lazy module's uninitialised parameter: no kernel
    configuration reads one)."""
    if t.layout != torch.strided or isinstance(t, UninitializedTensorMixin):
        return (id(t),)
    return (t.data_ptr(), t._version)


def _state_signature(module: nn.Module) -> tuple[tuple[Any, ...], bool, list[Tensor]]:
    """What a kernel configuration read from ``module`` depends on, read without a host
    sync: the storage and in-place version of each parameter and buffer of its modules,
    their public number, string and tuple attributes (``path`` and ``engine`` report, they
    configure nothing) and their forward hooks (a hooked model or cost runs in torch);
    whether one of those parameters and buffers requires grad; the methods each module
    shadows on itself and what shadows them (``model.f = ...``: the kernel read the class's);
    and the tensors stamped."""
    modules = list(module.modules())
    out: list[Any] = [tuple(k for hooks in hook_dicts(modules) for k in hooks)]
    add = out.append
    tensors: list[Tensor] = []
    grad = False
    for mod in modules:
        shadows = shadowed_methods(mod)
        if shadows:
            add(tuple((name, id(mod.__dict__.get(name))) for name in sorted(shadows)))
        for group in (mod._parameters, mod._buffers):
            for t in group.values():
                if t is None:
                    add(None)
                else:
                    add(_stamp(t))
                    tensors.append(t)
                    grad = grad or t.requires_grad
        for name, value in mod.__dict__.items():
            if name[0] == "_" or name in ("path", "engine"):
                continue
            if isinstance(value, Tensor):
                add((name, _stamp(value)))
                tensors.append(value)
            elif isinstance(value, (*_PLAIN, list, np.ndarray)):
                add((name, _plain(value)))
    return tuple(out), grad, tensors


#: most items of a list or array attribute whose values a configuration's signature holds
#: (a kernel reads short ones: a cost term's ``index``); a longer one counts by identity
_PLAIN_ITEMS = 64


def _plain(value: object) -> object:
    """A plain attribute as a comparable value: a short list as a tuple of its items', a
    small array by its type, shape and bytes (a cost term's ``index = [0, 1]`` edited in
    place shows); a long one (a user's map of 10^5 cells) by its identity and length."""
    if isinstance(value, (list, tuple)):
        if len(value) > _PLAIN_ITEMS:
            return ("long", id(value), len(value))
        return (type(value).__name__, *(_plain(v) for v in value))
    if isinstance(value, np.ndarray):
        if value.size > _PLAIN_ITEMS:
            return ("long", id(value), value.shape)
        return (value.dtype.str, value.shape, value.tobytes())
    return value


class _Values:
    """The values of the small CPU tensors among ``tensors`` (a kernel configuration reads
    only small ones): a write that leaves a tensor's in-place version alone (through
    ``.data``, or into a NumPy array sharing its memory) still shows. Compared bit for bit
    through NumPy (a NaN equals itself); a tensor NumPy cannot view (bfloat16, a conjugate
    view) by ``torch.equal``, so a NaN there reads as a change (the configuration is read
    again: slower, never stale)."""

    def __init__(self, tensors: list[Tensor]) -> None:
        self._kept: list[tuple[Any, Any]] = []
        for t in tensors:
            if isinstance(t, UninitializedTensorMixin) or t.layout != torch.strided:
                continue  # no storage of its own: no kernel configuration reads it
            if t.device.type != "cpu" or t.numel() > VALUE_CHECK:
                continue
            live = t.detach()
            try:
                view = live.numpy()  # shares the memory: reading it later costs no copy
            except (TypeError, RuntimeError):  # no NumPy dtype (bfloat16), conjugate bit
                self._kept.append((live, live.clone()))
            else:
                self._kept.append((view, view.tobytes()))

    def unchanged(self) -> bool:
        for live, kept in self._kept:
            if isinstance(kept, bytes):
                if live.tobytes() != kept:
                    return False
            elif not torch.equal(live, kept):
                return False
        return True


def _limit(name: str, value: object, m: int) -> Tensor | None:
    """A control bound (scalar or ``[m]``; NaN refused) in the dtype of a given tensor, else
    the default dtype."""
    t = as_limit(name, value, m)
    if t is None:
        return None
    return t.to(value.dtype if isinstance(value, Tensor) else torch.get_default_dtype())


def _scale(value: object, m: int, like: Tensor) -> Tensor | None:
    """``u_scale`` as a positive finite ``[m]`` tensor in the dtype of ``like`` (``None``
    for no scale)."""
    if value is None:
        return None
    t = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if t.dim() == 0:
        t = t.expand(m)
    if t.shape != (m,) or not bool(((t > 0) & torch.isfinite(t)).all()):
        raise ValueError(
            f"u_scale must be a positive number or [{m}] positive numbers, got {value!r}"
        )
    return t.clone()


class _Weights(NamedTuple):
    """The samples' weights and the per-environment figures of :class:`MPPIOutput`."""

    w: Tensor  # [B, K] normalised weights (0 for non-finite costs)
    cost_min: Tensor  # [B]
    best: Tensor  # [B] int64
    cost_mean: Tensor  # [B]
    ess: Tensor  # [B]
    status: Tensor  # [B] int64
    nonfinite: Tensor  # [B] int64


class _Capture(NamedTuple):
    """A planner's captured fused call and what it was captured for."""

    kernel: Any  # the kernel object of the configuration
    plan: Tensor  # the plan tensor the graph updates
    shape: torch.Size  # of x
    shifting: bool  # whether the captured call shifts the plan first
    call: CapturedCall | bool | None  # None: not captured yet; False: the capture failed


def _keeps_advance(cls: type) -> bool:
    """Whether ``cls`` records and shifts as :class:`MPPI` does (device work a graph holds;
    a variant's own shift may rebind its tensors, which a replay would not)."""
    return all(getattr(cls, name) is getattr(MPPI, name) for name in ("_advance", "_shift"))


def _unbatched(out: MPPIOutput) -> MPPIOutput:
    """``out`` of one environment without its batch axis."""
    return MPPIOutput(*(v.squeeze(0) if isinstance(v, Tensor) else v for v in out))


def _weighted_sum(z: Tensor, w: Tensor) -> Tensor:
    """``sum_k w_k z_k``: ``z [B, K, S, m]``, ``w [B, K]`` -> ``[B, S, m]``."""
    B, K, S, m = z.shape
    by_component = z.permute(0, 3, 2, 1).reshape(B, m * S, K)
    # a row vector times the transposed block: a few times faster on the CPU than the
    # matrix-vector form (which batched matmul runs as a general product)
    return (w.unsqueeze(1) @ by_component.mT).view(B, m, S).transpose(1, 2)


def _shifted(seq: Tensor, fill: str) -> Tensor:
    """``seq [B, H, m]`` moved one step earlier; the last entry zero (``fill="zero"``) or
    repeated (``"last"``)."""
    last = seq[:, -1:] if fill == "last" else torch.zeros_like(seq[:, -1:])
    return torch.cat([seq[:, 1:], last], 1)


def _resized(seq: Tensor, horizon: int, fill: str) -> Tensor:
    """``seq [B, H, m]`` truncated or extended to ``horizon`` steps (the added entries zero
    or, with ``fill="last"``, the last one)."""
    H = seq.shape[1]
    if horizon <= H:
        return seq[:, :horizon].clone()
    last = seq[:, -1:] if fill == "last" else torch.zeros_like(seq[:, -1:])
    return torch.cat([seq, last.expand(-1, horizon - H, -1)], 1)


#: the methods that say how the torch path samples: the kernel samples for a planner that
#: keeps MPPI's
_SAMPLING = ("_sample_noise", "_perturb", "_candidates", "_settle", "_clamp")


def _step_options(kwargs: dict[str, Any]) -> dict[str, Any]:
    """``torch.compile`` keyword arguments for a component-major step: the user's, with two
    inductor options of its own unless the user sets them (or names a ``mode``, or another
    backend, or the installed inductor lacks them). By default inductor on the CPU writes
    each component of a model's ``torch.stack`` into a sample-major buffer (so ``cos``/
    ``sin`` run one scalar at a time) and vectorises the short loop over the components
    with masked tails; building the stack as a pointwise expression and vectorising over
    the samples only made a compiled unicycle step 2.2-2.7x faster written as ``f``/``g``
    and 1.3x as a ``step`` function (measured on the CPU)."""
    if kwargs.get("backend", "inductor") != "inductor" or kwargs.get("mode") is not None:
        return kwargs  # torch.compile takes either a mode or options
    from torch._inductor import config

    known = config.get_config_copy()
    own = {"force_pointwise_cat": True, "cpp.enable_loop_tail_vec": False}
    own = {name: value for name, value in own.items() if name in known}
    return {**kwargs, "options": {**own, **(kwargs.get("options") or {})}}


class MPPI(TracksShadows, ExactConstants):
    """MPPI planner (see the module docstring for the algorithm, the paths and the RNG).

    Args:
        dynamics: a :class:`~torchcbf.dynamics.ControlAffine` model (nominal dynamics).
        cost: ``cost(states [B, K, H+1, n], controls [B, K, H, m], t0 [B]) -> [B, K]``; a
            callable or module. The cost of a sample must depend on its own rollout only
            (the planner may call it on slices of the samples, see ``cost_chunk``). Costs
            with ``needs_time = True`` (a barrier cost over a time-varying barrier) are also
            given ``dt=``, those with ``needs_history = True`` (the specifications of
            :mod:`torchcbf.mppi.specs`) ``dt=`` and ``history=``.
        horizon: ``H >= 1`` steps.
        num_samples: ``K >= 1`` samples per environment.
        dt: rollout time step.
        noise_sigma: control noise covariance: scalar (``s I``), vector (diagonal) or
            ``[m, m]`` symmetric positive definite matrix.
        temperature: ``lambda > 0``.
        control_cost_weight: ``gamma >= 0`` of ``gamma sum_j U_j' Sigma^-1 eps_j``.
        u_min, u_max: control limits (scalar or ``[m]``); default: the dynamics' limits.
        integrator: ``"euler"`` (default: the rollouts of scenarios A and B, and exact for
            the integrators) or ``"rk4"``.
        seed: environment ``b`` uses a generator seeded with ``seed + b``.
        keep_rollouts: return the first ``R`` sampled rollouts and weights (0: none).
        history_size: slots of the executed-state history read by specifications (one per
            call; a warning where a goal's term reads it and it is full: older states, a
            goal reached among them, are forgotten).
        shift_fill: ``"zero"`` (default) or ``"last"``: control appended by the warm start.
        zero_noise_samples: the first samples of each environment get no noise (they
            evaluate the shifted previous plan itself).
        cost_normalization: ``"none"`` (default, as pytorch-mppi and Williams et al., so a
            temperature carries over from them), ``"range"`` or ``"std"``: divide
            ``S - min S`` by the range (as CBFkit does) or by the standard deviation of the
            finite sample costs of the environment before the temperature, which makes
            ``temperature`` relative to the spread of the costs. No one choice serves both
            reference scenarios, so each builder states its own: scenario B's planner
            uses ``"none"``; on A (temperature 0.03) ``"none"`` is nearly greedy (effective
            sample size ~1, the control-cost noise decides), ``"range"`` averages so much
            that the hairpin at g2 is cut, and ``"std"`` succeeds (see
            tests/mppi/test_scenario_a.py).
        compile: ``True`` or a dict of ``torch.compile`` kwargs: compile a torch cost (and the
            torch path's integration step); see the module docstring and docs/mppi.md.
        backend: ``"auto"`` (default: the C kernel on the CPU and the Triton kernel on
            CUDA where they apply, see the module docstring), ``"torch"`` (always the torch
            path) or ``"triton"`` (the Triton kernel where it applies, also on the CPU under
            ``TRITON_INTERPRET=1``; Triton must import).
        cost_chunk: samples per call of a torch cost: ``None`` (default) slices the samples
            on the CPU so that one slice holds about ``AUTO_CHUNK_ELEMENTS`` state values and
            at least ``MIN_CHUNK_SAMPLES`` samples (the cost's intermediates then stay in
            cache, about 3x faster for a cost written on whole rollouts) and calls it once on
            other devices or when compiled; ``0`` calls it once on all samples; ``c`` on
            slices of ``c`` samples.
        layout: the memory of the rollouts a torch cost receives (``states [B, K, H+1, n]``,
            ``controls [B, K, H, m]``): ``"component"`` (default) stores them as ``[B, n,
            H+1, K]`` (each component's samples contiguous: fastest for a cost that works on
            components, ``states[..., 0]``, ``states[..., :2] - goal``, 1.4x faster than
            ``"sample"`` on scenario B's cost), ``"sample"`` as ``[B, K, H+1, n]`` (each
            state contiguous: fastest for a cost that reduces over the state axis,
            ``.norm(dim=-1)``, ``.sum(-1)``, up to 18x faster than ``"component"``). Either
            way a cost should index its inputs, not ``.view`` them. The plans do not depend
            on it beyond the rounding of the cost's reductions.
        step: discrete-time dynamics ``step(x [B, K, n], u [B, K, m], j) -> [B, K, n]`` with
            ``j`` the step of the horizon (``0 .. H-1``, as pytorch-mppi's
            ``step_dependent_dynamics``; the global time of the step is ``t + j dt``), used
            instead of integrating ``dynamics`` (which still gives ``n``, ``m`` and the
            default limits). Runs on the torch path.
        u_scale: action scale ``s > 0`` (scalar or ``[m]``): the planner samples actions
            ``a`` with covariance ``noise_sigma`` and applies ``u = s a``, so the applied
            noise has covariance ``S Sigma S`` (``S = diag(s)``). Everything the planner
            returns or takes (``u``, ``plan``, ``u_min``/``u_max``, ``correct``) is in the
            applied units ``u``, and the cost sees ``u`` (pytorch-mppi returns ``a`` and
            bounds ``a``: multiply both by ``s``).
        noise_abs_cost: the control cost reads ``|eps|``: ``gamma sum_j U_j' Sigma^-1
            |eps_j|`` (pytorch-mppi's option of that name). Runs on the torch path.
        action_sampler: extra candidate sequences ``action_sampler(x [B, n], t [B]) ->
            [S, H, m]`` (for every environment) or ``[B, S, H, m]``, in the applied units;
            they take the samples after the zero-noise (and null-action) samples, are
            clamped to the limits and weighted like any sample (pytorch-mppi's
            ``specific_action_sampler``). Runs on the torch path.
        sample_null_action: one sample is the zero control sequence (pytorch-mppi's
            ``sample_null_action``), after the zero-noise samples. Runs on the torch path.
        noise_mu: mean of the sampled noise (scalar or ``[m]``, in the units of
            ``noise_sigma``; pytorch-mppi's ``noise_mu``): biases the samples. Runs on the
            torch path.
        cuda_graph: capture the fused path's planning call on CUDA (built-in model and cost
            terms, the Triton kernel) in a CUDA graph and replay it: the kernels, torch's
            weights, the plan update, the history record, the warm-start shift and the
            outputs become one replay (what stays per call: drawing the noise keys,
            copying the state and time in and the outputs out). The first call of a
            configuration runs uncaptured; the second runs once for real on a stream of
            its own and captures; later calls replay (a call that shifts where the capture
            did not, or the reverse, runs uncaptured). The graph is captured again when the
            configuration (any tensor or number of the planner, its model or its cost, or
            their hooks), ``B``, the dtype or the plan's storage changes. The plans are the
            uncaptured path's (the same kernels on the same inputs); the output's ``path``
            says ``"fused_graph"``. Elsewhere (the CPU, the rollout and torch paths) it
            changes nothing. Where the capture fails the planner logs a warning and runs
            uncaptured.

    Control limits are one-sided when one side is given: ``u_max`` alone bounds the control
    from above only (pytorch-mppi mirrors it into ``u_min = -u_max``); write ``u_min=-b,
    u_max=b`` for a symmetric bound.
    """

    #: how the samples are drawn: ``"gaussian"`` around the plan (the C kernel's sampling);
    #: a variant that samples otherwise (``"smooth"``, ``"kernel"``) runs on the torch path
    sampling: ClassVar[str] = "gaussian"

    def __init__(
        self,
        dynamics: ControlAffine,
        cost: Callable[..., Tensor],
        horizon: int,
        num_samples: int,
        dt: float,
        noise_sigma: float | Tensor,
        temperature: float,
        control_cost_weight: float = 0.0,
        *,
        u_min: float | Tensor | None = None,
        u_max: float | Tensor | None = None,
        integrator: str = "euler",
        seed: int = 0,
        keep_rollouts: int = 0,
        history_size: int = 1024,
        shift_fill: str = "zero",
        zero_noise_samples: int = 0,
        cost_normalization: str = "none",
        compile: bool | dict[str, Any] = False,
        backend: str = "auto",
        cost_chunk: int | None = None,
        layout: str = "component",
        step: Callable[[Tensor, Tensor, int], Tensor] | None = None,
        u_scale: float | Tensor | None = None,
        noise_abs_cost: bool = False,
        action_sampler: Callable[[Tensor, Tensor], Tensor] | None = None,
        sample_null_action: bool = False,
        noise_mu: float | Tensor | None = None,
        cuda_graph: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(dynamics, ControlAffine):
            raise TypeError(
                f"dynamics must be a ControlAffine module, got {type(dynamics).__name__}"
            )
        if not callable(cost):
            raise TypeError(f"cost must be callable, got {type(cost).__name__}")
        horizon = check_int("horizon", horizon, low=1, what="an integer >= 1")
        history_size = check_int("history_size", history_size, low=1, what="an integer >= 1")
        _check_options(
            num_samples=num_samples, keep_rollouts=keep_rollouts,
            zero_noise_samples=zero_noise_samples, integrator=integrator,
            cost_normalization=cost_normalization, shift_fill=shift_fill,
            temperature=temperature, control_cost_weight=control_cost_weight, dt=dt,
        )  # fmt: skip
        if cost_chunk is not None and (
            not isinstance(cost_chunk, int) or isinstance(cost_chunk, bool) or cost_chunk < 0
        ):
            raise ValueError(f"cost_chunk must be None or an integer >= 0, got {cost_chunk!r}")
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        seed = check_seed(seed)
        if step is not None and not callable(step):
            raise TypeError(f"step must be callable or None, got {type(step).__name__}")
        if action_sampler is not None and not callable(action_sampler):
            raise TypeError(
                f"action_sampler must be callable or None, got {type(action_sampler).__name__}"
            )
        for name, flag in (("noise_abs_cost", noise_abs_cost),
                           ("sample_null_action", sample_null_action),
                           ("cuda_graph", cuda_graph)):  # fmt: skip
            check_bool(name, flag)
        if sample_null_action and zero_noise_samples + 1 > num_samples:
            raise ValueError(
                f"sample_null_action needs a sample beyond the zero_noise_samples "
                f"({zero_noise_samples}) of num_samples ({num_samples})"
            )
        self.dynamics = dynamics
        self.cost = cost
        m = dynamics.control_dim
        self._horizon, self.num_samples = horizon, num_samples
        self.dt = float(dt)  # checked by _check_options above
        self.temperature = float(temperature)  # checked by _check_options above
        self.control_cost_weight = float(control_cost_weight)
        self.integrator, self.seed, self.shift_fill = integrator, seed, shift_fill
        self.keep_rollouts, self.history_size = keep_rollouts, history_size
        self.zero_noise_samples = zero_noise_samples
        self.cost_normalization = cost_normalization
        self.backend = backend
        self.cost_chunk = cost_chunk
        self.layout = layout
        #: the path of the last call: ``"fused"``, ``"rollout"`` or ``"torch"``
        self.path: str | None = None
        #: the kernel of the last call's fused or rollout path: ``"c"`` or ``"triton"``
        self.engine: str | None = None

        self.step = step
        self.noise_abs_cost = bool(noise_abs_cost)  # checked above
        self.action_sampler = action_sampler
        self.sample_null_action = bool(sample_null_action)
        self.cuda_graph = bool(cuda_graph)
        given = isinstance(noise_sigma, Tensor)
        cov = as_matrix("noise_sigma", noise_sigma, m, dtype=None if given else torch.float64)
        scale = _scale(u_scale, m, cov)
        if scale is not None:  # u = s a with a ~ N(U_a, Sigma): the applied noise is S Sigma S
            cov = scale.unsqueeze(-1) * cov * scale
        self.register_buffer("u_scale", scale)  # [m] or None; already applied to noise_cov
        mu = as_limit("noise_mu", noise_mu, m)  # float64 [m] or None
        if mu is not None and not bool(torch.isfinite(mu).all()):
            raise ValueError(f"noise_mu must be finite, got {noise_mu!r}")
        if mu is not None and scale is not None:
            mu = mu * scale.to(mu)
        if mu is not None and not isinstance(noise_mu, Tensor):
            remember(self, "noise_mu", mu)  # Python numbers: exact
        else:
            dtype = noise_mu.dtype if isinstance(noise_mu, Tensor) else None
            self.register_buffer("noise_mu", None if mu is None else mu.to(dtype))
        chol = torch.linalg.cholesky(cov)
        for name, value in (("noise_cov", cov), ("noise_chol", chol),
                            ("noise_cov_inv", torch.cholesky_inverse(chol))):  # fmt: skip
            if given:
                self.register_buffer(name, value)
            else:  # Python numbers: exact under .double()
                remember(self, name, value)
        self._noise_form_kept: tuple[tuple, bool, float | None, Tensor] | None = None
        lo = _limit("u_min", u_min, m) if u_min is not None else dynamics.u_min
        hi = _limit("u_max", u_max, m) if u_max is not None else dynamics.u_max
        check_bounds("u_min", lo, "u_max", hi)
        for name, value, spec in (("u_min", lo, u_min), ("u_max", hi, u_max)):
            if value is not None and spec is not None and not isinstance(spec, Tensor):
                remember(self, name, as_limit(name, spec, m))  # Python numbers: exact
            else:
                self.register_buffer(name, None if value is None else value.clone())

        compile = check_compile(compile)
        self._compiled = bool(compile)
        self._step_into_fn: Callable[..., None] = self._step_into
        self._score_fn: Callable[..., Tensor] = self._score
        if compile:
            kwargs = compile if isinstance(compile, dict) else {}
            self._step_into_fn = Compiled(self._step_into, _step_options(kwargs), unbacked=("j",))
            self._score_fn = Compiled(self._score, kwargs)
        if backend == "triton" and not triton_available():
            raise ValueError("backend='triton' needs Triton, which does not import here")
        self._key: tuple[Any, ...] | None = None
        self._kernel_cache: tuple[Any, _AnyKernel | None, _Values] | None = None
        self._captured: _Capture | None = None
        self._fresh = True
        self._unknown_time: Tensor | None = None  # rows of a call whose time is not finite
        self._sampled_rows: slice | None = None  # the action_sampler's rows of this call
        self._calls = 0  # since the history was last cleared: one slot each
        follow_parts(self, [dynamics, cost])

    # -- state -------------------------------------------------------------------------------
    #: pairs of bounds ``[m]`` a user may set between calls, checked as the constructor
    #: checks them
    _BOUNDS: tuple[tuple[str, str], ...] = (("u_min", "u_max"),)

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "noise_cov" and "noise_chol" in self._buffers:
            # a number, a diagonal or the matrix, as the constructor takes noise_sigma (here
            # with u_scale applied), in the planner's dtype and on its device
            ref = self._buffers["noise_chol"]
            m = self.dynamics.control_dim
            if not isinstance(value, Tensor):  # numbers: exact under .double(), as when made
                exact = as_matrix(name, value, m, dtype=torch.float64)
                remember(self, name, exact, dtype=ref.dtype, device=ref.device)
                return
            if value.shape != (m, m):
                value = as_matrix(name, value, m, dtype=ref.dtype, spd=False)
            if value.dtype != ref.dtype or value.device != ref.device:
                value = value.to(ref)
            check_spd("noise_cov", value.detach())
        pair = next((p for p in self._BOUNDS if name in p), None)
        if pair is not None and isinstance(value, Tensor) and "_buffers" in vars(self):
            m = self.dynamics.control_dim
            if value.shape == (m,):
                as_limit(name, value, m)  # NaN refused; the tensor kept as given
            else:
                value = _limit(name, value, m)  # one number for every control: [m]
            other = self._buffers.get(pair[1] if name == pair[0] else pair[0])
            lo, hi = (value, other) if name == pair[0] else (other, value)
            check_bounds(pair[0], lo, pair[1], hi)
        super().__setattr__(name, value)

    def reset(self) -> None:
        """Forget the plan, the history and re-seed the generators (next call starts afresh)."""
        self._key = None
        self._kernel_cache = None
        self._captured = None
        self._fresh = True
        self._noise_form_kept = None

    def _history_matters(self) -> bool:
        """Whether a term of the cost reads what the history holds as achieved (a goal's)."""
        parts = self.cost.modules() if isinstance(self.cost, nn.Module) else [self.cost]
        return self._needs_history and any(getattr(m, "remembers_history", False) for m in parts)

    def _ensure_state(self, B: int, device: torch.device, dtype: torch.dtype) -> None:
        key = (B, device, dtype)
        if self._key == key:
            return
        H, m, n = self.horizon, self.dynamics.control_dim, self.dynamics.state_dim
        self._plan = torch.zeros(B, H, m, device=device, dtype=dtype)
        self._work: tuple[tuple, Tensor, Tensor] | None = None
        self._noise: Tensor | None = None
        # row b draws from seed + b: all of them 32-bit (torch's generator reads 32 bits)
        seeds = seed_rows(self.seed, B, torch.device("cpu"), per="environment").tolist()
        self._generators = [torch.Generator(device=device).manual_seed(s) for s in seeds]
        self._history = HistoryBuffer(self.history_size, B, n, device=device, dtype=dtype)
        self._calls = 0
        self._rows = torch.arange(B, device=device)
        self._allocate(B, device, dtype)
        self._key = key
        self._fresh = True

    def _allocate(self, B: int, device: torch.device, dtype: torch.dtype) -> None:
        """Per-batch state of a variant beside the plan (none here)."""

    def _sampling_steps(self) -> int:
        """Rows of the sampled noise per sample: ``H`` (one per plan step) here."""
        return self.horizon

    def _rollout_buffers(self, noise: bool) -> tuple[Tensor | None, Tensor, Tensor]:
        """``eps [B, K, H, m]`` (``None`` unless ``noise``: the kernel's rollout path
        regenerates the noise it needs), ``controls [B, K, H, m]``, ``states [B, K, H+1, n]``
        stored as :attr:`layout` says (:func:`torchcbf.mppi._rollout.rollout_buffer`),
        allocated on first use (the fused path never needs them)."""
        B, H, m = self._plan.shape
        K, n = self.num_samples, self.dynamics.state_dim
        like, layout, steps = self._plan, self.layout, self._sampling_steps()
        shape = (K, H, m, n, steps, layout)  # a number of samples or a layout set since
        if self._work is None or self._work[0] != shape:
            self._work = (
                shape,
                _rollout.rollout_buffer(like, B, K, H, m, layout),
                _rollout.rollout_buffer(like, B, K, H + 1, n, layout),
            )
            self._noise = None
        if noise and self._noise is None:
            self._noise = _rollout.rollout_buffer(like, B, K, steps, m, layout)
        return (self._noise if noise else None), *self._work[1:]

    @property
    def history(self) -> History | None:
        """The recorded executed states and times (``None`` before the first call)."""
        return None if self._key is None else self._history.view()

    def correct(self, u: Tensor) -> None:
        """Replace the first control of the current plan by the control actually applied.

        ``u``: ``[m]`` or ``[B, m]`` (e.g. a safety filter's output for the control this
        planner returned), stored as given. The next call's warm start then
        continues from the executed control: with ``shift=False`` it refines the plan from
        it, and with the shifting warm start it replaces it by ``plan[1]`` as usual (the
        rest of the plan is kept either way).
        """
        if self._key is None:
            raise ValueError("correct() needs a plan: call the planner first")
        plan = self._plan
        B, _, m = plan.shape
        if not isinstance(u, Tensor):
            raise TypeError(f"u must be a tensor, got {type(u).__name__}")
        if u.shape not in ((m,), (B, m)):
            raise ValueError(f"u must have shape [{m}] or [{B}, {m}], got {tuple(u.shape)}")
        value = u.detach().to(plan).expand(B, m)
        plan[:, 0] = value

    # -- one planning call -------------------------------------------------------------------
    def forward(self, x: Tensor, t: float | Tensor = 0.0, shift: bool = True) -> MPPIOutput:
        """Plan from ``x [n]`` or ``[B, n]`` at global time ``t`` (scalar or ``[B]``). A
        time that is not finite is a ``ValueError`` given as a number, a list or an array;
        in a tensor, its row plans nothing (``status`` 1, as where no sample has a finite
        cost: read on the device).

        ``shift=False`` refines the plan without the warm-start shift (e.g. several
        iterations at the same time).

        ``x`` may be a NumPy array (as a Gymnasium environment returns it): it is planned
        on the planner's device in its own floating dtype (float32 or float64; others in
        torch's default dtype), and every array field of the output is then a NumPy array
        (``out.u`` goes straight into ``env.step``).
        """
        if isinstance(x, np.ndarray):
            out = self.forward(self._from_numpy(x), t, shift)
            return MPPIOutput(
                *(v.detach().cpu().numpy() if isinstance(v, Tensor) else v for v in out)
            )
        n = self.dynamics.state_dim
        check_last_dim("x", x, n)
        if x.dim() > 2:
            raise ValueError(f"x must have shape [{n}] or [B, {n}], got {tuple(x.shape)}")
        if not x.is_floating_point():
            raise TypeError(f"x must be a floating tensor, got {x.dtype}")
        if x.device != self.noise_cov.device:
            raise ValueError(
                f"x is on device {x.device} but the planner is on device "
                f"{self.noise_cov.device}: move one of them (planner.to(x.device))"
            )
        # options set since the last call are checked as the constructor checks them
        _check_options(
            num_samples=self.num_samples, keep_rollouts=self.keep_rollouts,
            zero_noise_samples=self.zero_noise_samples, integrator=self.integrator,
            cost_normalization=self.cost_normalization, shift_fill=self.shift_fill,
            temperature=self.temperature, control_cost_weight=self.control_cost_weight,
            dt=self.dt,
        )  # fmt: skip
        unbatched = x.dim() == 1
        xb = resolved(x.unsqueeze(0) if unbatched else x)
        B = xb.shape[0]
        self._ensure_state(B, xb.device, xb.dtype)
        check_times("t", t)
        t0 = resolved(as_tensor("t", t, device=xb.device, dtype=xb.dtype))  # a number: no copy
        if t0.dim() > 1 or (t0.dim() == 1 and t0.shape[0] not in (1, B)):
            raise ValueError(f"t must be a scalar or have shape [{B}], got {tuple(t0.shape)}")
        t0 = t0.reshape(-1).expand(B)
        self._calls += 1
        if self._calls == self.history_size + 1 and self._history_matters():
            warnings.warn(
                f"the executed-state history of {self.history_size} slots (one per call) is "
                "full: the oldest states are overwritten, and a goal reached among them counts "
                "as not reached again; raise history_size (or reset() between episodes)",
                stacklevel=2,
            )
        # a row of a tensor t that is not finite plans nothing (its windows would all be
        # empty, its obstacles ignored): its costs are NaN, so it reports status 1 (read on
        # the device, no host synchronisation)
        self._unknown_time = ~torch.isfinite(t0) if isinstance(t, Tensor) else None
        shifting = check_bool("shift", shift) and not self._fresh
        self._noise_form()  # a noise_cov set since the last call: its factors made again
        kernel = self._kernel(xb)
        self._fresh = False
        self.engine = None if kernel is None else kernel.name
        if kernel is not None and kernel.fused:
            self.path = "fused"
            return self._fused(kernel, xb, t0, shifting, unbatched)
        self._advance(xb, t0, shifting)
        plan = self._plan
        eps, controls, states = self._rollout_buffers(noise=kernel is None)
        if xb.device.type == "cpu":
            keep_freed_heap()  # a torch cost's intermediates are reused, not faulted in again
        history = self._history.view() if self._needs_history else None
        cost_key = self._compile_key(self.cost)
        if kernel is not None:
            # the kernel stores the rollouts for the torch cost and adds the control cost;
            # the update regenerates the noise of the weighted samples (as on the fused path)
            self.path = "rollout"
            keys = _rollout.draw_keys(self._generators, self._plan.device)
            xc = xb.contiguous()
            wctrl = self._control_weights(plan)
            ctrl = kernel.buffers(xc, plan, keys, states, controls, wctrl, self.layout)
            cost = self._score_fn(states, controls, None, plan, t0, history, cost_key)
            if ctrl is not None:
                cost = cost + ctrl
            weights = self._weights(cost, kernel)
            if weights.w.requires_grad:
                # a cost holding a tensor that requires grad (a closure's): the update in
                # torch from the stored samples (``u - plan`` is the kernel's noise, clipped
                # as it clips it), so that the plan keeps that gradient
                delta = _weighted_sum(controls - plan.unsqueeze(1), weights.w)
            else:
                delta = kernel.update(xc, plan, keys, weights.w)
        else:
            self.path = "torch"
            assert eps is not None
            ctrl_eps = self._sample(xb, t0, eps, controls)
            self._rollout(xb, controls, states)
            cost = self._score_fn(
                states, controls, ctrl_eps, self._cost_plan(), t0, history, cost_key
            )
            extra = self._extra_cost(controls)
            if extra is not None:
                cost = cost + extra
            weights = self._weights(cost)
            delta = _weighted_sum(self._finite_candidates(eps), weights.w)
        best_states = states[self._rows, weights.best].contiguous()  # [B, H+1, n]
        rollouts = None
        if self.keep_rollouts:
            rollouts = states[:, : self.keep_rollouts].clone(memory_format=torch.contiguous_format)
        out = self._output(weights, delta, best_states, rollouts)
        return _unbatched(out) if unbatched else out

    def _from_numpy(self, x: np.ndarray) -> Tensor:
        dtype = x.dtype if x.dtype in (np.float32, np.float64) else None
        t = torch.as_tensor(x, dtype=None if dtype is not None else torch.get_default_dtype())
        return t.to(self.noise_cov.device)

    def _advance(self, x: Tensor, t0: Tensor, shifting: bool) -> None:
        """What every call does before it samples: record ``x [B, n]`` at ``t0 [B]`` in the
        history and, where ``shifting``, shift the plan (a CUDA graph of the fused call
        holds it where the planner's class keeps MPPI's ``_advance`` and ``_shift``)."""
        self._history.record(x, t0)
        if shifting:
            self._shift()

    def _shift(self) -> None:
        """The warm start: the plan moves one step, the last control is ``shift_fill``'s."""
        self._plan.copy_(_shifted(self._plan, self.shift_fill))

    def change_horizon(self, horizon: int) -> None:
        """Plan over ``horizon`` steps from the next call on, keeping the current plan: a
        shorter horizon truncates it, a longer one extends it with ``shift_fill``'s control
        (zero, or the last one). The sample buffers are rebuilt on the next call."""
        horizon = check_int("horizon", horizon, low=1, what="an integer >= 1")
        if self._key is not None:
            self._resize(horizon)
            self._work, self._noise = None, None
        self._horizon = horizon

    @property
    def horizon(self) -> int:
        """Steps ``H`` of the plan; setting it is :meth:`change_horizon`."""
        return self._horizon

    @horizon.setter
    def horizon(self, horizon: int) -> None:
        self.change_horizon(horizon)

    def _resize(self, horizon: int) -> None:
        self._plan = _resized(self._plan, horizon, self.shift_fill)

    def rollout_samples(
        self,
        x: Tensor,
        num_rollouts: int = 1,
        *,
        plan: Tensor | None = None,
        seed: int | None = None,
    ) -> Tensor:
        """Roll out a control sequence for display: ``[R, H+1, n]`` for ``x [n]`` (``[B, R,
        H+1, n]`` for ``x [B, n]``), ``R = num_rollouts``, ``states[..., 0, :] = x``.

        ``plan``: ``[H, m]`` or ``[B, H, m]`` controls in the dynamics' units (default: the
        current plan, which needs a previous call with the same ``B``). The planner's
        dynamics (``step`` or the integrator) rolls out; for an SDE model (one with
        ``sigma``) each rollout draws its own diffusion noise (Euler-Maruyama, from a
        generator seeded with ``seed``, default the planner's), otherwise the ``R``
        rollouts are equal. The planner's state is not changed.
        """
        n, m = self.dynamics.state_dim, self.dynamics.control_dim
        num_rollouts = check_int("num_rollouts", num_rollouts, low=1, what="an integer >= 1")
        seed = self.seed if seed is None else check_seed(seed)
        check_last_dim("x", x, n)
        if x.dim() > 2:
            raise ValueError(f"x must have shape [{n}] or [B, {n}], got {tuple(x.shape)}")
        xb = x.unsqueeze(0) if x.dim() == 1 else x
        B = xb.shape[0]
        if plan is None:
            if self._key is None or self._plan.shape[0] != B:
                raise ValueError(
                    f"rollout_samples needs a plan for {B} environment(s): pass plan= or call "
                    "the planner with this batch first"
                )
            plan = self._plan
        if not isinstance(plan, Tensor) or plan.dim() not in (2, 3) or plan.shape[-1] != m:
            shape = tuple(plan.shape) if isinstance(plan, Tensor) else type(plan).__name__
            raise ValueError(f"plan must have shape [H, {m}] or [{B}, H, {m}], got {shape}")
        if plan.dim() == 3 and plan.shape[0] != B:
            raise ValueError(
                f"plan must have shape [H, {m}] or [{B}, H, {m}], got {tuple(plan.shape)}"
            )
        plan = plan.to(xb).expand(B, *plan.shape[-2:])
        H, R = plan.shape[1], num_rollouts
        stochastic = self.step is None and self.dynamics.has_diffusion
        gen = torch.Generator(device=xb.device).manual_seed(seed)
        states = xb.new_empty(B, R, H + 1, n)
        states[:, :, 0] = xb.unsqueeze(1)
        state = states[:, :, 0]
        with torch.no_grad():
            for j in range(H):
                u = plan[:, j].unsqueeze(1).expand(B, R, m)
                if stochastic:
                    state = integrators.euler_maruyama(
                        self.dynamics, state, u, self.dt, generator=gen
                    )
                else:
                    state = self._step(state, u, j)
                states[:, :, j + 1] = state
        return states[0] if x.dim() == 1 else states

    # -- torch path ----------------------------------------------------------------------------
    def _sample(self, x: Tensor, t0: Tensor, eps: Tensor, controls: Tensor) -> Tensor:
        """The noise into ``eps`` and the sampled controls into ``controls`` (both ``[B, K, H,
        m]``); return the noise the control cost reads. Where the C kernel draws the noise
        (:meth:`_kernel_draws`) and the planner samples as this class does, the kernel also
        scales, adds and clamps in the same pass; the rows of the zero-noise samples and of
        the candidates are then redone as :meth:`_perturb` does."""
        if not (
            self._kernel_draws(eps)
            and self.noise_mu is None
            and behaves_as(self, MPPI, _SAMPLING)
            and not any(name in vars(self) for name in _SAMPLING)  # nor replaced on self
        ):
            self._sample_noise(eps)
            return self._perturb(x, t0, eps, controls)
        keys = _rollout.draw_keys(self._generators, self._plan.device)
        _rollout.perturb(
            keys, eps, controls, self._plan, self.noise_chol, u_min=self.u_min, u_max=self.u_max
        )
        first = self.zero_noise_samples
        rows = self._candidates(x, t0, controls)
        if first or rows is not None:
            redo = slice(0, first if rows is None else rows.stop)
            if first:
                controls[:, :first] = self._plan.unsqueeze(1)
            self._settle(controls[:, redo], eps[:, redo])
        return eps

    def _kernel_draws(self, eps: Tensor) -> bool:
        """Whether the C kernel draws the noise of ``eps`` (float32 or float64 on the CPU,
        at most its number of controls); else ``normal_`` does."""
        return (
            eps.device.type == "cpu"
            and eps.dtype in (torch.float32, torch.float64)
            and eps.shape[-1] <= _rollout.MAX_CONTROL
            and _rollout.available()
        )

    def _noise_form(self) -> tuple[bool, float | None]:
        """``(diagonal, std)`` of ``noise_cov`` as it is now: whether it is diagonal, and
        ``s`` where it is ``s^2 I`` (else ``None``). Worked out again where the buffer was
        replaced or written in place (``load_state_dict``, ``copy_``), and then
        ``noise_chol`` and ``noise_cov_inv`` are made again from it: ``noise_cov`` is the
        one a user sets."""
        cov = self.noise_cov
        key = (cov.data_ptr(), cov._version, cov.device, cov.dtype)
        kept = self._noise_form_kept
        # on the CPU the matrix is also compared by value: a write through ``.data`` or a
        # NumPy view keeps its version (on a GPU that would wait for the device)
        if (
            kept is None
            or kept[0] != key
            or (cov.device.type == "cpu" and not torch.equal(cov.detach(), kept[3]))
        ):
            chol = self.noise_chol.detach()
            tol = 1e-10 if cov.dtype == torch.float64 else 1e-5
            if not torch.allclose(chol @ chol.mT, cov.detach(), rtol=tol, atol=0.0):
                check_spd("noise_cov", cov.detach())  # set in place: checked as when made
                exact = torch.linalg.cholesky(cov.detach().double())  # the factors follow
                self.noise_chol.copy_(exact)
                self.noise_cov_inv.copy_(torch.cholesky_inverse(exact))
            diag = torch.diagonal(cov)
            diagonal = bool(torch.equal(cov, torch.diag(diag)))
            isotropic = diagonal and bool((diag == diag[0]).all())
            std = float(diag[0].detach().sqrt()) if isotropic else None
            kept = (key, diagonal, std, cov.detach().clone())
            self._noise_form_kept = kept
        return kept[1], kept[2]

    def _sample_noise(self, eps: Tensor) -> None:
        diagonal, std = self._noise_form()
        if self._kernel_draws(eps):
            keys = _rollout.draw_keys(self._generators, self._plan.device)
            _rollout.normals(keys, eps, std=1.0 if std is None else float(std))
        else:
            storage = eps.permute(0, 3, 2, 1)  # [B, m, H, K]: contiguous, component layout
            scratch = None if storage.is_contiguous() else eps.new_empty(storage.shape[1:])
            for b, gen in enumerate(self._generators):
                # Sigma = s^2 I: drawn scaled in one pass; otherwise standard, scaled below;
                # the same draws in [m, H, K] order in either layout
                target = storage[b] if scratch is None else scratch
                target.normal_(0.0, 1.0 if std is None else std, generator=gen)
                if scratch is not None:
                    storage[b].copy_(scratch)
        if std is None and diagonal:
            eps.mul_(torch.diagonal(self.noise_cov).to(eps).sqrt())
        elif std is None:
            eps.copy_(eps @ self.noise_chol.to(eps).mT)
        if self.noise_mu is not None:
            eps.add_(self.noise_mu.to(eps))
        if self.zero_noise_samples:
            eps[:, : self.zero_noise_samples].zero_()

    def _step(
        self, x: Tensor, u: Tensor, j: int, *, rate: str | None = None, component: bool = False
    ) -> Tensor:
        """Step ``j`` of the model (``step``, or the integrator with the model's
        :func:`~torchcbf.integrators.rate_form` ``rate``, found here where not given) from
        states ``x [B, K, n]`` and controls ``u [B, K, m]``, or ``[B, n, K]`` and ``[B, m,
        K]`` where ``component``."""
        if self.step is not None:
            return self.step(x.mT, u.mT, j).mT if component else self.step(x, u, j)
        form = integrators.rate_form(self.dynamics) if rate is None else rate
        return integrators.unchecked_step(
            self.dynamics, self.integrator, x, u, self.dt, form=form, component=component
        )

    def _clamp(self, u: Tensor) -> Tensor:
        """``u`` clamped to the control limits, in place."""
        if self.u_min is not None or self.u_max is not None:
            lo = None if self.u_min is None else self.u_min.to(u)
            hi = None if self.u_max is None else self.u_max.to(u)
            u.clamp_(lo, hi)
        return u

    def _perturb(self, x: Tensor, t0: Tensor, eps: Tensor, controls: Tensor) -> Tensor:
        """Fill ``controls [B, K, H, m]`` with the samples ``clamp(U + eps)`` (candidates from
        ``action_sampler`` and the null action in their rows) and recompute ``eps`` from them
        in place; return the noise the control cost reads (``eps`` here)."""
        torch.add(eps, self._plan.unsqueeze(1), out=controls)
        self._candidates(x, t0, controls)
        self._settle(controls, eps)
        return eps

    def _settle(self, controls: Tensor, eps: Tensor) -> None:
        """Clamp sampled ``controls [B, S, H, m]`` in place and write their noise around the
        plan into ``eps`` (the same rows)."""
        self._clamp(controls)
        torch.sub(controls, self._plan.unsqueeze(1), out=eps)

    def _candidates(self, x: Tensor, t0: Tensor, controls: Tensor) -> slice | None:
        """Write the null action and the ``action_sampler``'s sequences into their rows of
        ``controls [B, K, H, m]`` (after the zero-noise samples); return those rows."""
        first = self.zero_noise_samples
        row = first
        if self.sample_null_action:
            controls[:, row].zero_()
            row += 1
        self._sampled_rows = None
        if self.action_sampler is not None:
            seqs = self._sampled_actions(x, t0, row)
            controls[:, row : row + seqs.shape[1]] = seqs
            self._sampled_rows = slice(row, row + seqs.shape[1])
            row += seqs.shape[1]
        return slice(first, row) if row > first else None

    def _finite_candidates(self, z: Tensor) -> Tensor:
        """``z [B, K, ...]`` (the samples' noise) with the non-finite entries of the
        ``action_sampler``'s rows zeroed: such a candidate's cost is not finite and its
        weight 0, and ``0 * NaN`` would still reach the plan."""
        rows = self._sampled_rows
        if rows is None:
            return z
        block = z[:, rows]
        clean = block.masked_fill(~torch.isfinite(block), 0.0)
        if z.requires_grad:
            return torch.cat((z[:, : rows.start], clean, z[:, rows.stop :]), 1)
        block.copy_(clean)
        return z

    def _sampled_actions(self, x: Tensor, t0: Tensor, row: int) -> Tensor:
        """The sampler's sequences ``[B, S, H, m]``, checked (``[S, H, m]`` is broadcast)."""
        assert self.action_sampler is not None
        B, H, m = self._plan.shape
        seqs = self.action_sampler(x, t0)
        room = self.num_samples - row
        if not isinstance(seqs, Tensor) or not seqs.is_floating_point():
            what = seqs.dtype if isinstance(seqs, Tensor) else type(seqs).__name__
            raise TypeError(f"action_sampler must return a floating tensor, got {what}")
        if seqs.dim() == 3:
            seqs = seqs.unsqueeze(0).expand(B, *seqs.shape)
        if (
            seqs.dim() != 4
            or seqs.shape[0] != B
            or seqs.shape[2:] != (H, m)
            or seqs.shape[1] > room
        ):
            raise ValueError(
                f"action_sampler must return [S, {H}, {m}] or [{B}, S, {H}, {m}] with S <= "
                f"{room} (the samples left after the zero-noise and null-action samples), "
                f"got {tuple(seqs.shape)}"
            )
        if seqs.device != x.device:
            raise ValueError(
                f"action_sampler returned a tensor on {seqs.device}, the planner is on {x.device}"
            )
        return seqs.to(x.dtype)

    def _cost_plan(self) -> Tensor:
        """The plan ``[B, H, m]`` the control cost pairs with the sampled noise."""
        return self._plan

    def _extra_cost(self, controls: Tensor) -> Tensor | None:
        """A variant's own cost of the samples ``[B, K]`` (none here)."""
        return None

    def _update_plan(self, delta: Tensor) -> None:
        """The update ``U <- clamp(U + delta)`` of the plan."""
        self._clamp(self._plan.add_(delta))

    def _rollout(self, x: Tensor, controls: Tensor, states: Tensor) -> None:
        """Roll the sampled controls out into the state buffer."""
        states[:, :, 0] = x.unsqueeze(1)
        component = self.layout == "component"
        if component:
            # each step reads and writes each component's samples contiguously
            states, controls = states.permute(0, 3, 2, 1), controls.permute(0, 3, 2, 1)
        # the rate's form and the model's hooks are arguments of the compiled step, so a
        # graph traced for one model is not reused for a model of the same class that is
        # evaluated otherwise (torch.compile does not guard on a module's hooks)
        rate = integrators.rate_form(self.dynamics)
        if needs_graph(self, x, controls):
            # out of place: a step writing into the buffer would change, under autograd,
            # the state an earlier step saved for its backward (a cos of a heading)
            steps = [states.select(2, 0).clone()]
            for j in range(self.horizon):
                u = controls.select(2, j)
                steps.append(self._step(steps[-1], u, j, rate=rate, component=component))
            states.copy_(torch.stack(steps, 2))
            return
        hooks = self._compile_key(self.dynamics)
        for j in range(self.horizon):
            self._step_into_fn(states, controls, j, component, rate, hooks)

    def _step_into(
        self, states: Tensor, controls: Tensor, j: int, component: bool, rate: str, hooks: str
    ) -> None:
        """Step ``j`` of the rollout in place: from ``states[:, :, j]`` and ``controls[:, :,
        j]`` into ``states[:, :, j + 1]``, the buffers ``[B, K, H+1, n]`` and ``[B, K, H, m]``,
        or ``[B, n, H+1, K]`` and ``[B, m, H, K]`` where ``component``; ``rate``: the model's
        :func:`~torchcbf.integrators.rate_form`; ``hooks``: its
        :func:`~torchcbf._compile.hook_key` (compiled, a new value traces again). Compiled,
        the code reads and writes the buffers directly, one graph for every ``j``."""
        read_key(hooks)
        x, u = states.select(2, j), controls.select(2, j)
        states.select(2, j + 1).copy_(self._step(x, u, j, rate=rate, component=component))

    def _score(
        self,
        states: Tensor,
        controls: Tensor,
        eps: Tensor,
        plan: Tensor,
        t0: Tensor,
        history: History | None,
        hooks: str,
    ) -> Tensor:
        """Cost ``[B, K]`` of the rollouts (``[B, K, H+1, n]``, ``[B, K, H, m]``), checked and
        cast by :meth:`_check_cost`, plus the control cost of the noise ``eps`` (none where
        ``eps`` is ``None``: the kernel adds it). ``hooks``: the cost's
        :func:`~torchcbf._compile.hook_key` (as in :meth:`_step_into`)."""
        read_key(hooks)
        chunk = self._chunk(states)
        K = states.shape[1]
        timed = bool(getattr(self.cost, "needs_time", False))
        if chunk >= K:
            cost = self._check_cost(self._rollout_cost(states, controls, t0, history, timed))
        else:  # slices small enough for the cost's intermediates to stay in cache
            cost = states.new_empty(states.shape[:2])
            for k in range(0, K, chunk):
                part = self._rollout_cost(
                    states[:, k : k + chunk], controls[:, k : k + chunk], t0, history, timed
                )
                cost[:, k : k + chunk] = self._check_cost(part, min(chunk, K - k))
        if self.control_cost_weight > 0.0 and eps is not None:
            if self.noise_abs_cost:
                eps = eps.abs()
            B, K, H, m = eps.shape
            weighted = (plan @ self.noise_cov_inv.to(plan)).transpose(1, 2)  # [B, m, H]
            by_component = eps.permute(0, 3, 2, 1).reshape(B, m * H, K)
            ctrl = (weighted.reshape(B, 1, m * H) @ by_component).squeeze(1)
            cost = cost + self.control_cost_weight * ctrl
        return cost

    def _compile_key(self, obj: object) -> str:
        """``obj``'s :func:`~torchcbf._compile.hook_key` where the planner compiles (the
        argument of a compiled step or cost that makes a new hook trace again), else
        ``""``."""
        return hook_key(obj) if self._compiled else ""

    @property
    def _needs_history(self) -> bool:
        """Whether the cost reads the history (read at each call: a cost's terms may change)."""
        return bool(getattr(self.cost, "needs_history", False))

    def _rollout_cost(
        self, states: Tensor, controls: Tensor, t0: Tensor, history: History | None, timed: bool
    ) -> Tensor:
        """The cost of rollouts, given ``dt=`` where it reads times (``timed``: its
        ``needs_time``) and ``history=`` too where it ``needs_history``."""
        if self._needs_history:
            return self.cost(states, controls, t0, dt=self.dt, history=history)
        if timed:
            return self.cost(states, controls, t0, dt=self.dt)
        return self.cost(states, controls, t0)

    def _chunk(self, states: Tensor) -> int:
        """Samples per cost call."""
        K = states.shape[1]
        if self.cost_chunk is not None:
            return self.cost_chunk or K
        if self._compiled or states.device.type != "cpu":
            return K
        per_sample = max(states.shape[0] * states.shape[2] * states.shape[3], 1)
        return max(MIN_CHUNK_SAMPLES, AUTO_CHUNK_ELEMENTS // per_sample)

    # -- kernel paths --------------------------------------------------------------------------
    def _kernel_may_plan(self, x: Tensor) -> bool:
        """Whether a kernel may plan for ``x`` as far as the options and dtype say (read
        without walking the modules)."""
        return (
            self.backend != "torch"
            and x.dtype in (torch.float32, torch.float64)
            and self._kernel_expresses()
        )

    def _engine(self, x: Tensor, grad: bool) -> str | None:
        """The kernel that plans for ``x`` where :meth:`_kernel_may_plan`: ``"c"`` on the
        CPU, ``"triton"`` on CUDA (or with ``backend="triton"``), ``None`` where torch runs
        (``grad``: a parameter or buffer of the planner requires grad)."""
        if needs_graph(self, x, module_grad=grad):
            return None
        if self.backend == "triton":
            if x.device.type == "cpu" and not triton_interpreted():
                raise ValueError(
                    "backend='triton' plans on CUDA tensors (on the CPU only under "
                    "TRITON_INTERPRET=1); x is on the CPU"
                )
            return "triton"
        if x.device.type == "cpu":
            return "c" if _rollout.available() else None
        return "triton" if x.device.type == "cuda" and triton_available() else None

    def _kernel(self, x: Tensor) -> _AnyKernel | None:
        """The kernel bound to this planner's configuration, or ``None`` where torch runs:
        fused where the cost is made of built-in terms, else for the rollouts alone. The
        kernel and its configuration are kept until a tensor or number of the planner, its
        model or its cost changes (checked by in-place versions, without reading the device:
        no host sync; small CPU tensors also by value, :class:`_Values`)."""
        if not self._kernel_may_plan(x):
            return None
        state, grad, tensors = _state_signature(self)
        engine = self._engine(x, grad)
        if engine is None:
            return None
        # `_horizon` is private, which _state_signature skips
        signature = (engine, x.device, x.dtype, self.backend, self.horizon, state)
        cached = self._kernel_cache
        if cached is not None and cached[0] == signature and cached[2].unchanged():
            return cached[1]
        model = _rollout.encode_model(self.dynamics)
        cost = None
        if model is not None and not self._needs_history:
            cost = _rollout.encode_cost(self.cost, self.dynamics.state_dim)
        kernel: _AnyKernel | None = None
        if model is not None:
            cfg = self._configuration(model, cost)
            if engine == "c":
                kernel = _rollout.Kernel(cfg, fused=cost is not None)
            elif cost is not None or self.layout == "component":
                tab = _triton.tables(cfg, x.dtype, x.device)
                kernel = _triton.Kernel(tab, fused=cost is not None)
        self._kernel_cache = (signature, kernel, _Values(tensors))
        return kernel

    def _kernel_expresses(self) -> bool:
        """Whether the kernel's sampling, rollout and control cost are this planner's: the
        plain Gaussian samples around the plan, the model's own integration and the linear
        control cost (a variant's sampling, ``step``, ``noise_abs_cost`` and candidate
        samples run in torch)."""
        return (
            self.sampling == "gaussian"
            and self.step is None
            and not self.noise_abs_cost
            and self.action_sampler is None
            and not self.sample_null_action
            and self.noise_mu is None
        )

    def _configuration(
        self,
        model: tuple[int, int],
        cost: tuple[list[list[float]], list[list[float]]] | None,
    ) -> _rollout.Configuration:
        return _rollout.configuration(
            model,
            self.integrator,
            self.dynamics.state_dim,
            self.dynamics.control_dim,
            self.horizon,
            self.num_samples,
            self.zero_noise_samples,
            self.u_min,
            self.u_max,
            self.noise_chol,
            self.dt,
            self.control_cost_weight,
            cost,
        )

    def _control_weights(self, plan: Tensor) -> Tensor | None:
        """``plan @ Sigma^-1 [B, H, m]``, the kernel's control-cost weights (``None`` without
        a control cost)."""
        if self.control_cost_weight == 0.0:
            return None
        return (plan @ self.noise_cov_inv.to(plan)).contiguous()

    def _fused(
        self, kernel: _AnyKernel, x: Tensor, t0: Tensor, shifting: bool, unbatched: bool
    ) -> MPPIOutput:
        x = x.contiguous()
        keys = _rollout.draw_keys(self._generators, self._plan.device)
        out = None
        if self.cuda_graph and x.is_cuda and _keeps_advance(type(self)):
            out = self._replayed(kernel, x, t0, keys, shifting)
        if out is None:
            out = self._fused_call(kernel, x, t0, keys, shifting)
        return _unbatched(out) if unbatched else out

    def _fused_call(
        self, kernel: _AnyKernel, x: Tensor, t0: Tensor, keys: Tensor, shifting: bool
    ) -> MPPIOutput:
        """One fused planning call from ``x [B, n]`` at ``t0 [B]`` with the noise ``keys
        [B]`` (:meth:`_advance` first): the plan updated in place, the batched output
        returned."""
        self._advance(x, t0, shifting)
        B, H, _ = self._plan.shape
        n = self.dynamics.state_dim
        plan = self._plan
        cost = kernel.costs(x, plan, keys, self._control_weights(plan))
        weights = self._weights(cost, kernel)
        delta = kernel.update(x, plan, keys, weights.w)
        # re-roll the best sample and the kept samples
        R = self.keep_rollouts
        picks = [torch.stack([self._rows, weights.best], -1)]
        if R:
            ks = torch.arange(R, device=x.device)
            picks.append(torch.cartesian_prod(self._rows, ks))
        rolled = kernel.rows(x, plan, keys, torch.cat(picks))
        rollouts = rolled[B:].view(B, R, H + 1, n) if R else None
        return self._output(weights, delta, rolled[:B], rollouts)

    def _replayed(
        self, kernel: _AnyKernel, x: Tensor, t0: Tensor, keys: Tensor, shifting: bool
    ) -> MPPIOutput | None:
        """The fused call replayed from its CUDA graph (``cuda_graph=True``), or ``None``
        where this call runs uncaptured: the first call of a configuration (so that a
        configuration that changes every call is never captured), a call that shifts the
        plan where the capture did not or the reverse (the graph holds the history record
        and the shift, :meth:`_advance`), and every call after a failed capture. The second
        call runs once for real and captures (:class:`~torchcbf._graphs.CapturedCall`)."""
        cap = self._captured
        if cap is None or not (
            cap.kernel is kernel and cap.plan is self._plan and cap.shape == x.shape
        ):
            self._captured = _Capture(kernel, self._plan, x.shape, shifting, None)
            return None
        if cap.call is False:
            return None
        if cap.call is None:
            call = CapturedCall(
                lambda x, t, k: self._fused_call(kernel, x, t, k, shifting)[:-1], (x, t0, keys)
            )
            if call.error is not None:
                logger.warning(
                    "torchcbf: MPPI's CUDA graph capture failed (%s); the planner runs uncaptured",
                    call.error,
                )
            call_or_failed = False if call.error is not None else call
            self._captured = cap._replace(shifting=shifting, call=call_or_failed)
            return MPPIOutput(*call.first, path=self.path)
        if cap.shifting != shifting:
            return None
        self.path = "fused_graph"
        return MPPIOutput(*cap.call(x, t0, keys), path=self.path)

    def __getstate__(self) -> dict[str, Any]:
        # a CUDA graph neither copies nor pickles: a copy captures its own
        return {**super().__getstate__(), "_captured": None}

    # -- weights and update --------------------------------------------------------------------
    def _check_cost(self, cost: Tensor, count: int | None = None) -> Tensor:
        """The cost's ``[B, K]`` (``K = count`` for a slice) in the planner's dtype: a
        floating cost of another dtype is cast (documented); anything else raises."""
        plan = self._plan
        B, K = plan.shape[0], self.num_samples if count is None else count
        if not isinstance(cost, Tensor) or cost.shape != (B, K):
            shape = tuple(cost.shape) if isinstance(cost, Tensor) else type(cost).__name__
            raise ValueError(f"cost must return shape [{B}, {K}], got {shape}")
        if not cost.is_floating_point():
            raise TypeError(f"cost must return a floating-point tensor, got {cost.dtype}")
        if cost.device != plan.device:
            raise ValueError(
                f"cost returned a tensor on {cost.device}, the planner is on {plan.device}"
            )
        return cost if cost.dtype == plan.dtype else cost.to(plan.dtype)

    def _weights(self, cost: Tensor, kernel: _AnyKernel | None = None) -> _Weights:
        """The weights of the samples' costs ``[B, K]`` and the figures of the output: by
        ``kernel``'s weights pass where it has one for this call
        (:meth:`torchcbf.mppi._triton.Kernel.weights`), else in torch."""
        lam = max(self.temperature, torch.finfo(cost.dtype).tiny)
        if self._unknown_time is not None:
            cost = torch.where(self._unknown_time.unsqueeze(-1), math.nan, cost)
        if kernel is not None and self.cost_normalization == "none":
            fused = kernel.weights(cost, lam)
            if fused is not None:
                return _Weights(*fused)
        # one launch per line where it can (a GPU call is bound by its launches); a row
        # without a finite cost needs no branch of its own
        finite = isfinite(cost)
        clean = torch.where(finite, cost, math.inf)
        cost_min, best = clean.min(-1)
        ok = cost_min < math.inf
        # NaN (inf - inf) on the rows without a finite cost: every weight there is 0 below
        if self.cost_normalization == "none":
            shifted = clean - cost_min.unsqueeze(-1)
        else:
            # in float64: float32 costs spread by 1e20 overflow the sums, by 3e38 the shift
            wide = clean.double() - cost_min.double().unsqueeze(-1)
            kept = torch.where(finite, wide, 0.0)
            if self.cost_normalization == "range":
                span = kept.amax(-1, keepdim=True)
            else:  # "std": standard deviation of the finite costs
                # of the costs over their range: squares of spreads beyond 1e154 overflow
                top = kept.amax(-1, keepdim=True).clamp_min(torch.finfo(torch.float64).tiny)
                unit = kept / top
                n_fin = finite.sum(-1, keepdim=True).clamp_min(1)
                mean = unit.sum(-1, keepdim=True) / n_fin
                dev = torch.where(finite, unit - mean, 0.0)
                span = top * (dev.square().sum(-1, keepdim=True) / n_fin).sqrt()
            tiny = torch.finfo(torch.float64).tiny
            shifted = (wide / span.clamp_min(tiny)).to(cost.dtype)
        # exponents below log(tiny) give weight 0 (their exp would be subnormal: no
        # difference to the weights); exp runs on 0 there instead, since results at the
        # bottom of the normal range take a slow path of the vectorised exp (10x slower)
        expo = shifted.mul_(-1.0 / lam)
        live = expo >= math.log(torch.finfo(cost.dtype).tiny)  # false for NaN
        w = torch.where(live, torch.exp(torch.where(live, expo, 0.0)), 0.0)
        w = w.div_(w.sum(-1, keepdim=True).clamp_min(1.0))  # the best sample has weight 1 before
        count = finite.sum(-1)
        return _Weights(
            w,
            cost_min,
            best,
            # summed in float64: float32 costs of 1e37 would overflow their sum
            cost_mean=(
                torch.where(finite, cost, 0.0).sum(-1, dtype=torch.float64) / count.clamp_min(1)
            ).to(cost.dtype),
            ess=ok / w.square().sum(-1).clamp_min(1e-30),  # 0 where no cost is finite
            status=torch.where(ok, 0, 1),
            nonfinite=cost.shape[-1] - count,
        )

    def _output(
        self,
        weights: _Weights,
        delta: Tensor,
        best_states: Tensor,
        rollouts: Tensor | None,
    ) -> MPPIOutput:
        self._update_plan(delta)
        plan = self._plan
        w = weights.w
        out = MPPIOutput(
            u=plan[:, 0].clone(),
            plan=plan.clone(),
            cost_min=weights.cost_min,
            cost_mean=weights.cost_mean,
            ess=weights.ess,
            status=weights.status,
            best_states=best_states,
            rollouts=rollouts,
            rollout_weights=w[:, : self.keep_rollouts].clone() if self.keep_rollouts else None,
            nonfinite=weights.nonfinite,
            path=self.path,
        )
        # the outputs keep this call's graph; what later calls start from or write into does
        # not (a graph carried from call to call would grow and reach back to old states)
        if any(t.requires_grad for t in self._kept()):
            self._release_graph()
        return out

    def _kept(self) -> tuple[Tensor, ...]:
        """The tensors a call leaves for later calls: the plan, the history and the buffers
        the rollouts are written into."""
        buffers = () if self._work is None else self._work[1:]
        noise = () if self._noise is None else (self._noise,)
        return (self._plan, self._history.states, self._history.times, *buffers, *noise)

    def _release_graph(self) -> None:
        """Replace each of :meth:`_kept` by a copy of its values without their graph, and let
        the next call allocate its buffers afresh: the graph this call's outputs keep may
        have saved them, and writing into them in place would break its backward."""
        self._plan = self._plan.detach().clone()
        history = self._history
        history.states, history.times = (
            history.states.detach().clone(),
            history.times.detach().clone(),
        )
        self._work, self._noise = None, None

    def extra_repr(self) -> str:
        return (
            f"horizon={self.horizon}, num_samples={self.num_samples}, dt={self.dt}, "
            f"temperature={self.temperature}, control_cost_weight={self.control_cost_weight}, "
            f"integrator={self.integrator!r}, seed={self.seed}, backend={self.backend!r}"
        )
