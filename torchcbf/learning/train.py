"""A plain torch training loop with a progress bar and checkpoints.

:func:`train` is the loop below, with a switchable tqdm bar, optional gradient clipping and
periodic checkpoints; copy it if you need something else::

    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    for step in range(steps):
        loss = loss_fn(step)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
"""

from __future__ import annotations

import inspect
import io
import logging
import math
import pickle
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn
from torch.optim.lr_scheduler import LRScheduler
from tqdm.auto import tqdm

from torchcbf._checks import check_int, check_number
from torchcbf._io import atomic_path

log = logging.getLogger(__name__)

LossOutput = Tensor | tuple[Tensor, Mapping[str, Tensor | float]]


class TrainResult(NamedTuple):
    """What :func:`train` did.

    Fields: ``losses`` (the loss after every step, floats), ``metrics`` (the last metrics
    returned by ``loss_fn``, floats), ``seconds_per_step`` (mean wall time of a step,
    the first one excluded when there are several: it includes warm-up), ``skipped``
    (steps skipped because the loss or a gradient was not finite), ``step`` (the index of
    the next step, for resuming).
    """

    losses: list[float]
    metrics: dict[str, float]
    seconds_per_step: float
    skipped: int
    step: int


def save_checkpoint(
    path: str | Path,
    module: nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    *,
    step: int = 0,
    scheduler: LRScheduler | None = None,
    generator: torch.Generator | None = None,
    **extra: Any,
) -> None:
    """Save ``module.state_dict()`` (and the optimizer's, the scheduler's, the state of the
    random ``generator`` the data is drawn with, the step and ``extra``) to ``path``, in one
    atomic write (an interrupted save leaves the previous checkpoint). ``extra`` holds what
    :func:`load_checkpoint` reads back with ``weights_only=True`` (tensors, Python numbers,
    strings, ``None``, containers of them, state dicts); anything else raises ``TypeError``
    naming it, before writing."""
    for key, value in extra.items():
        _check_loadable(f"extra[{key!r}]", value)
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {
        "model": module.state_dict(),
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "scheduler": None if scheduler is None else scheduler.state_dict(),
        "generator": None if generator is None else generator.get_state(),
        "step": int(step),
        "extra": extra,
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _check_loadable(name: str, value: object) -> None:
    """Raise ``TypeError`` naming ``name`` (or the first entry inside it that is at fault)
    where ``value`` would not load back with ``weights_only=True``."""
    buffer = io.BytesIO()
    try:
        torch.save(value, buffer)
        buffer.seek(0)
        torch.load(buffer, weights_only=True)
    except (pickle.PickleError, AttributeError, TypeError):
        items: Any = ()
        if isinstance(value, Mapping):
            items = ((f"{name}[{k!r}]", v) for k, v in value.items())
        elif isinstance(value, (list, tuple)):
            items = ((f"{name}[{i}]", v) for i, v in enumerate(value))
        for inner, item in items:
            _check_loadable(inner, item)
        raise TypeError(
            f"{name} is a {type(value).__module__}.{type(value).__qualname__}: a checkpoint "
            "is loaded with weights_only=True, which reads tensors, numbers, strings, None "
            "and containers of them; convert it (float(), str(), torch.as_tensor())"
        ) from None


def load_checkpoint(
    path: str | Path,
    module: nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    *,
    scheduler: LRScheduler | None = None,
    generator: torch.Generator | None = None,
    map_location: str | torch.device | None = None,
    strict: bool = True,
) -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint` into ``module`` (and
    ``optimizer``, ``scheduler``, the state of ``generator``); returns ``{"step": int,
    "extra": dict}``."""
    state = torch.load(Path(path), map_location=map_location, weights_only=True)
    if not isinstance(state, dict) or "model" not in state:
        raise ValueError(f"{path} is not a checkpoint written by save_checkpoint")
    module.load_state_dict(state["model"], strict=strict)
    if optimizer is not None:
        if state.get("optimizer") is None:
            raise ValueError(f"{path} holds no optimizer state")
        optimizer.load_state_dict(state["optimizer"])
    if scheduler is not None:
        if state.get("scheduler") is None:
            raise ValueError(f"{path} holds no scheduler state")
        scheduler.load_state_dict(state["scheduler"])
    if generator is not None:
        if state.get("generator") is None:
            raise ValueError(f"{path} holds no generator state")
        generator.set_state(state["generator"].cpu())  # map_location may have moved it
    return {"step": int(state.get("step", 0)), "extra": dict(state.get("extra") or {})}


def _params(optimizer: torch.optim.Optimizer) -> list[Tensor]:
    return [p for group in optimizer.param_groups for p in group["params"]]


def _required(method: Callable[..., Any], name: str) -> bool:
    """Whether ``method`` must be given the argument ``name`` (``LBFGS.step`` a closure,
    ``ReduceLROnPlateau.step`` the metric)."""
    param = inspect.signature(method).parameters.get(name)
    return param is not None and param.default is inspect.Parameter.empty


def _loss(out: LossOutput) -> tuple[Tensor, Mapping[str, Tensor | float]]:
    loss, raw = (out, {}) if isinstance(out, Tensor) else out
    if not isinstance(loss, Tensor) or loss.dim() != 0:
        raise ValueError("loss_fn must return a scalar tensor (or (loss, metrics))")
    return loss, raw


def _scalar(name: str, value: Tensor | float) -> float:
    if isinstance(value, Tensor):
        if value.numel() != 1:
            raise ValueError(f"{name} must be a scalar, got shape {tuple(value.shape)}")
        value = value.detach()
    return float(value)


def _clip(params: list[Tensor], max_norm: float | None) -> Tensor | None:
    """The global norm of the gradients, after clipping them to ``max_norm`` when given;
    ``inf``/NaN where a gradient is not finite; ``None`` without gradients. The norms
    accumulate in float64 (float32 where the device has none), so finite gradients below
    float64 have a finite norm."""
    grads = [p.grad.detach() for p in params if p.grad is not None]
    if not grads:
        return None
    acc = torch.float32 if grads[0].device.type == "mps" else torch.float64
    norm = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads, 2, dtype=acc)))
    if max_norm is not None:
        coef = (max_norm / (norm + 1e-6)).clamp(max=1.0)
        torch._foreach_mul_(grads, [coef.to(g.dtype) for g in grads])
    return norm


class _Closure:
    """``optimizer.step``'s closure for an optimizer that evaluates the loss again (LBFGS):
    the first call returns the loss already evaluated (its gradients are in place)."""

    def __init__(
        self,
        loss: Tensor,
        loss_fn: Callable[[int], LossOutput],
        step: int,
        optimizer: torch.optim.Optimizer,
        params: list[Tensor],
        grad_clip: float | None,
    ) -> None:
        self.first: Tensor | None = loss.detach()
        self.loss_fn, self.step, self.optimizer = loss_fn, step, optimizer
        self.params, self.grad_clip = params, grad_clip

    def __call__(self) -> Tensor:
        if self.first is not None:
            first, self.first = self.first, None
            return first
        loss, _ = _loss(self.loss_fn(self.step))
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        _clip(self.params, self.grad_clip)
        return loss.detach()


def train(
    loss_fn: Callable[[int], LossOutput],
    optimizer: torch.optim.Optimizer,
    steps: int,
    *,
    start_step: int = 0,
    scheduler: LRScheduler | None = None,
    generator: torch.Generator | None = None,
    grad_clip: float | None = None,
    progress: bool = True,
    desc: str = "train",
    checkpoint: str | Path | None = None,
    checkpoint_every: int = 0,
    module: nn.Module | None = None,
    callback: Callable[[int, float, dict[str, float]], None] | None = None,
) -> TrainResult:
    """Minimise ``loss_fn(step)`` with ``optimizer`` for ``steps`` steps.

    Args:
        loss_fn: ``step -> loss`` (a scalar tensor) or ``(loss, metrics)`` with a mapping of
            scalars shown on the progress bar and passed to ``callback``.
        optimizer: any ``torch.optim`` optimizer over the parameters to train (one whose
            ``step`` needs a closure, as LBFGS, is given one that evaluates ``loss_fn`` at the
            same step again).
        steps: number of steps; they are numbered ``start_step .. start_step + steps - 1``.
        scheduler: optional learning-rate scheduler, stepped after every optimizer step
            (one whose ``step`` needs a metric, as ``ReduceLROnPlateau``, is given the loss).
        generator: the random generator ``loss_fn`` draws its data with, saved in the
            checkpoints.
        grad_clip: clip the global gradient norm to this value (a finite number > 0).
        progress: show a tqdm bar.
        checkpoint, checkpoint_every, module: save ``module`` (and the optimizer, the
            scheduler and the generator) to ``checkpoint`` every ``checkpoint_every`` steps
            (0: only at the end) with :func:`save_checkpoint`; resume with
            :func:`load_checkpoint` (given the same four) and ``start_step``: the run
            continues as one that was not interrupted, where ``loss_fn`` draws only from
            ``generator`` (or is a function of the step alone).
        callback: ``(step, loss, metrics)`` after every step.

    A step whose loss or gradient is not finite is skipped (no parameter update) and counted
    in ``TrainResult.skipped``, with a warning. One host sync per step reads the loss and
    the gradient's norm.
    """
    steps, start_step, checkpoint_every = (
        check_int(name, value, low=0, what="a non-negative int")
        for name, value in (
            ("steps", steps),
            ("start_step", start_step),
            ("checkpoint_every", checkpoint_every),
        )
    )
    if grad_clip is not None:
        grad_clip = check_number("grad_clip", grad_clip, low=0.0, strict=True)
    if not isinstance(optimizer, torch.optim.Optimizer):
        raise TypeError(
            f"optimizer must be a torch.optim.Optimizer, got {type(optimizer).__name__}"
        )
    if checkpoint is not None and module is None:
        raise ValueError("checkpoint needs module= (the model whose state_dict is saved)")
    params = _params(optimizer)
    takes_closure = _required(optimizer.step, "closure")
    wants_metric = scheduler is not None and _required(scheduler.step, "metrics")
    losses: list[float] = []
    metrics: dict[str, float] = {}
    skipped = 0
    times: list[float] = []
    bar = tqdm(range(start_step, start_step + steps), desc=desc, disable=not progress, leave=False)
    step = start_step
    for step in bar:
        t0 = time.perf_counter()
        out = loss_fn(step)
        loss, raw = _loss(out)
        metrics = {k: _scalar(f"metrics[{k!r}]", v) for k, v in raw.items()}
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        norm = _clip(params, grad_clip)
        if norm is None:  # nothing to step: the loss alone is read
            norm = loss.detach()
        # one read for both, in at least float32 (some devices have no float64)
        read = torch.promote_types(torch.promote_types(loss.dtype, norm.dtype), torch.float32)
        value, size = torch.stack((loss.detach().to(read), norm.to(read))).tolist()
        if math.isfinite(value) and math.isfinite(size):
            if takes_closure:  # LBFGS: its first evaluation is the one above
                optimizer.step(_Closure(loss, loss_fn, step, optimizer, params, grad_clip))
            else:
                optimizer.step()
            if scheduler is not None:
                if wants_metric:
                    scheduler.step(value)
                else:
                    scheduler.step()
        else:
            skipped += 1
            optimizer.zero_grad(set_to_none=True)
            warnings.warn(f"step {step}: non-finite loss or gradient, step skipped", stacklevel=2)
        times.append(time.perf_counter() - t0)
        losses.append(value)
        if progress:
            shown = {f"metric {k}" if k == "loss" else k: f"{v:.4g}" for k, v in metrics.items()}
            bar.set_postfix({"loss": f"{value:.4g}", **shown})
        if callback is not None:
            callback(step, value, metrics)
        if checkpoint is not None and checkpoint_every > 0 and (step + 1) % checkpoint_every == 0:
            save_checkpoint(
                checkpoint,
                module,
                optimizer,
                step=step + 1,
                scheduler=scheduler,
                generator=generator,
            )
    next_step = start_step + steps
    if checkpoint is not None:
        save_checkpoint(
            checkpoint, module, optimizer, step=next_step, scheduler=scheduler, generator=generator
        )
    timed = times[1:] if len(times) > 1 else times
    per_step = sum(timed) / len(timed) if timed else math.nan
    log.debug("trained %d steps, %.4f s/step, %d skipped", steps, per_step, skipped)
    return TrainResult(losses, metrics, per_step, skipped, next_step)
