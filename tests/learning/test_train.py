"""The training loop: it minimises, checkpoints round-trip, resuming equals one run,
non-finite steps are skipped; the MLP's input normalisation."""

from __future__ import annotations

import re

import pytest
import torch
from torch import nn

from torchcbf.learning import MLP, load_checkpoint, save_checkpoint, train


def _problem(device: torch.device | str = "cpu") -> tuple[nn.Module, torch.Tensor, torch.Tensor]:
    torch.manual_seed(0)
    model = nn.Linear(3, 1).to(device=device, dtype=torch.float64)
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(64, 3, generator=gen, dtype=torch.float64).to(device)
    y = x @ torch.tensor([[1.0], [-2.0], [0.5]], dtype=torch.float64, device=device) + 0.3
    return model, x, y


def test_train_fits_a_linear_model(device: torch.device) -> None:
    model, x, y = _problem(device)
    opt = torch.optim.Adam(model.parameters(), lr=0.05)
    seen: list[int] = []

    def loss_fn(step: int):
        loss = ((model(x) - y) ** 2).mean()
        return loss, {"rmse": loss.sqrt()}

    res = train(
        loss_fn, opt, 300, progress=False, callback=lambda s, v, m: seen.append(s), grad_clip=10.0
    )
    assert len(res.losses) == 300 and seen == list(range(300)) and res.step == 300
    assert res.losses[-1] < 1e-4 * res.losses[0]
    assert set(res.metrics) == {"rmse"} and res.skipped == 0 and res.seconds_per_step > 0
    w = model.weight.detach().reshape(-1)
    want = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64, device=device)
    assert torch.allclose(w, want, atol=1e-3)


def test_checkpoint_round_trip_and_resume_equals_one_run(tmp_path, device) -> None:
    def run(model: nn.Module, opt: torch.optim.Optimizer, steps: int, start: int = 0, **kw):
        _, x, y = _problem(device)
        loss_fn = lambda s: ((model(x) - y) ** 2).mean()  # noqa: E731
        return train(loss_fn, opt, steps, start_step=start, progress=False, **kw)

    ref, _, _ = _problem(device)
    run(ref, torch.optim.Adam(ref.parameters(), lr=0.05), 20)

    model, _, _ = _problem(device)
    opt = torch.optim.Adam(model.parameters(), lr=0.05)
    path = tmp_path / "ckpt" / "model.pt"
    res = run(model, opt, 10, checkpoint=path, checkpoint_every=5, module=model)
    assert path.exists() and res.step == 10
    fresh, _, _ = _problem(device)
    with torch.no_grad():
        fresh.weight.zero_()
    fresh_opt = torch.optim.Adam(fresh.parameters(), lr=0.05)
    info = load_checkpoint(path, fresh, fresh_opt)
    assert info["step"] == 10
    assert torch.equal(fresh.weight, model.weight)
    run(fresh, fresh_opt, 10, start=info["step"])
    assert torch.allclose(fresh.weight, ref.weight, atol=1e-12)
    assert torch.allclose(fresh.bias, ref.bias, atol=1e-12)

    save_checkpoint(tmp_path / "plain.pt", model, step=3, note="x")
    info = load_checkpoint(tmp_path / "plain.pt", fresh)
    assert info == {"step": 3, "extra": {"note": "x"}}
    with pytest.raises(ValueError, match="no optimizer state"):
        load_checkpoint(tmp_path / "plain.pt", fresh, fresh_opt)


def test_a_resumed_run_keeps_its_learning_rate_schedule(tmp_path) -> None:
    """The scheduler's state is in the checkpoint: a run resumed from it with the same
    optimizer, scheduler and start_step ends where an uninterrupted one does."""

    def setup():
        model, x, y = _problem()
        opt = torch.optim.SGD(model.parameters(), lr=0.05)
        sched = torch.optim.lr_scheduler.StepLR(opt, step_size=3, gamma=0.1)
        return model, opt, sched, lambda s: ((model(x) - y) ** 2).mean()

    ref, opt, sched, loss = setup()
    train(loss, opt, 8, scheduler=sched, progress=False)

    model, opt, sched, loss = setup()
    path = tmp_path / "run.pt"
    train(loss, opt, 4, scheduler=sched, checkpoint=path, module=model, progress=False)
    fresh, fresh_opt, fresh_sched, fresh_loss = setup()
    info = load_checkpoint(path, fresh, fresh_opt, scheduler=fresh_sched)
    train(fresh_loss, fresh_opt, 4, start_step=info["step"], scheduler=fresh_sched,
          progress=False)  # fmt: skip
    torch.testing.assert_close(fresh.weight, ref.weight, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="no scheduler state"):
        save_checkpoint(tmp_path / "plain.pt", fresh)
        load_checkpoint(tmp_path / "plain.pt", fresh, scheduler=fresh_sched)


def test_a_checkpoint_refuses_extras_it_could_not_load(tmp_path) -> None:
    import numpy as np

    model, _, _ = _problem()
    for value, name in (
        (np.float64(1.5), "extra['loss']"),
        ({"dir": tmp_path}, "extra['loss']['dir']"),
    ):
        with pytest.raises(TypeError, match=re.escape(name)):
            save_checkpoint(tmp_path / "x.pt", model, loss=value)
    assert not (tmp_path / "x.pt").exists()
    save_checkpoint(tmp_path / "x.pt", model, loss=[1.5, {"tag": "a", "t": torch.ones(2)}],
                    ema=model.state_dict())  # fmt: skip
    extra = load_checkpoint(tmp_path / "x.pt", model)["extra"]
    assert extra["loss"][0] == 1.5 and torch.equal(extra["ema"]["weight"], model.weight)


def test_non_finite_steps_are_skipped() -> None:
    model, x, y = _problem()
    opt = torch.optim.SGD(model.parameters(), lr=0.01)
    before = model.weight.detach().clone()

    def loss_fn(step: int) -> torch.Tensor:
        loss = ((model(x) - y) ** 2).mean()
        return loss * float("nan") if step == 0 else loss

    with pytest.warns(UserWarning, match="non-finite"):
        res = train(loss_fn, opt, 2, progress=False)
    assert res.skipped == 1 and torch.isfinite(model.weight).all()
    assert not torch.equal(model.weight, before)  # step 1 did update


def test_train_errors() -> None:
    model, _, _ = _problem()
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    with pytest.raises(ValueError, match="steps"):
        train(lambda s: model.weight.sum(), opt, -1)
    with pytest.raises(TypeError, match="optimizer"):
        train(lambda s: model.weight.sum(), "adam", 1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="module="):
        train(lambda s: model.weight.sum(), opt, 1, checkpoint="x.pt")
    with pytest.raises(ValueError, match="scalar"):
        train(lambda s: model.weight, opt, 1, progress=False)
    loss = lambda s: model.weight.sum()  # noqa: E731
    for clip in (-1.0, 0.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="grad_clip must be a finite number > 0"):
            train(loss, opt, 1, grad_clip=clip, progress=False)
    with pytest.raises(ValueError, match="start_step must be a non-negative int"):
        train(loss, opt, 1, start_step=-1, progress=False)
    with pytest.raises(ValueError, match="checkpoint_every must be a non-negative int"):
        train(loss, opt, 1, checkpoint_every=-5, progress=False)
    with pytest.raises(TypeError, match="generator must be a torch.Generator"):
        save_checkpoint("never.pt", model, generator=3)  # type: ignore[arg-type]


def test_a_resumed_run_draws_the_data_it_would_have_drawn(tmp_path) -> None:
    """A loss that draws its batch from a generator: the checkpoint holds the generator's
    state, so the resumed run sees the batches of the uninterrupted one."""

    def setup():
        model, x, y = _problem()
        gen = torch.Generator().manual_seed(7)
        opt = torch.optim.SGD(model.parameters(), lr=0.05)

        def loss_fn(step: int):
            idx = torch.randint(64, (8,), generator=gen)
            return ((model(x[idx]) - y[idx]) ** 2).mean()

        return model, opt, gen, loss_fn

    ref, opt, gen, loss = setup()
    whole = train(loss, opt, 10, progress=False).losses
    model, opt, gen, loss = setup()
    path = tmp_path / "run.pt"
    first = train(loss, opt, 4, checkpoint=path, module=model, generator=gen, progress=False)
    fresh, fresh_opt, fresh_gen, fresh_loss = setup()
    info = load_checkpoint(path, fresh, fresh_opt, generator=fresh_gen)
    rest = train(fresh_loss, fresh_opt, 6, start_step=info["step"], progress=False)
    assert first.losses + rest.losses == whole
    torch.testing.assert_close(fresh.weight, ref.weight, atol=0, rtol=0)
    save_checkpoint(tmp_path / "plain.pt", fresh)
    with pytest.raises(ValueError, match="no generator state"):
        load_checkpoint(tmp_path / "plain.pt", fresh, generator=fresh_gen)


def test_a_metric_named_loss_is_shown_beside_the_loss() -> None:
    model, x, y = _problem()
    opt = torch.optim.SGD(model.parameters(), lr=0.01)

    def loss_fn(step: int):
        loss = ((model(x) - y) ** 2).mean()
        return loss, {"loss": loss.detach() * 2}

    res = train(loss_fn, opt, 2, progress=True)
    assert res.metrics["loss"] == pytest.approx(2 * res.losses[-1], rel=1e-6, abs=0)


def test_a_checkpoint_into_a_folder_names_the_folder(tmp_path) -> None:
    model, _, _ = _problem()
    (tmp_path / "adir").mkdir()
    with pytest.raises(IsADirectoryError, match="adir is a folder"):
        save_checkpoint(tmp_path / "adir", model)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir"]


def test_mlp_normalises_its_input(dtype) -> None:
    torch.manual_seed(0)
    net = MLP(2, (8, 8), low=[-4.0, 0.0], high=[0.0, 10.0], activation="silu").to(dtype)
    x = torch.tensor([[-2.0, 5.0], [0.0, 10.0]], dtype=dtype)
    z = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=dtype)
    assert torch.allclose(net(x), net.layers(z))
    assert net(x).shape == (2, 1) and net(x[0]).shape == (1,)
    assert net(torch.zeros(3, 4, 2, dtype=dtype)).shape == (3, 4, 1)
    with pytest.raises(ValueError, match="activation"):
        MLP(2, activation="relu6")
    with pytest.raises(ValueError, match="high must exceed low"):
        MLP(2, low=[0.0, 0.0], high=[1.0, 0.0])


def test_a_half_precision_loss_with_a_large_gradient_is_not_skipped() -> None:
    """The loss and the gradient's norm are read in at least float32: a norm of 1e5 is
    finite there and infinite in float16."""
    w = torch.nn.Parameter(torch.full((4,), 1e-3))
    opt = torch.optim.SGD([w], lr=1e-9)
    res = train(lambda s: (w * 5e4).half().sum(), opt, 2, progress=False)  # norm 1e5
    assert res.skipped == 0 and res.losses[0] == pytest.approx(200.0, rel=1e-3)


@pytest.mark.parametrize("dtype", [torch.float16, torch.float32])
def test_a_finite_gradient_whose_squares_overflow_is_not_skipped(dtype) -> None:
    """Gradients of 4e4 (float16) or 1e20 (float32): their norm is finite, though the sum
    of their squares is not in their own precision."""
    big = 4e4 if dtype == torch.float16 else 1e20
    for clip in (None, 1.0):
        w = torch.nn.Parameter(torch.ones(2, dtype=dtype))
        opt = torch.optim.SGD([w], lr=0.3 / big if clip is None else 0.1)
        res = train(lambda s, w=w: (w * big - big).sum(), opt, 1, grad_clip=clip, progress=False)
        assert res.skipped == 0
        # without clipping w - lr * grad; clipped to norm 1: each entry moves 1 / sqrt(2)
        want = 0.7 if clip is None else 1 - 0.1 / 2**0.5
        torch.testing.assert_close(w.detach(), torch.full((2,), want, dtype=dtype))


def test_lbfgs_and_a_scheduler_that_reads_the_loss() -> None:
    model, x, y = _problem()
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=20)
    calls = []

    def loss_fn(step):
        calls.append(step)
        return ((model(x) - y) ** 2).mean()

    res = train(loss_fn, opt, 3, progress=False)
    assert res.losses[-1] < 1e-12 and set(calls) == {0, 1, 2}
    model, x, y = _problem()
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, patience=0, factor=0.5)
    train(lambda s: x.new_tensor(1.0) + 0 * model(x).sum(), opt, 3, scheduler=plateau,
          progress=False)  # fmt: skip
    assert opt.param_groups[0]["lr"] == pytest.approx(0.1 * 0.5**2)  # no improvement: halved


def test_a_metric_that_is_not_a_scalar_is_refused_before_the_step() -> None:
    model, x, y = _problem()
    before = [p.detach().clone() for p in model.parameters()]
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    with pytest.raises(ValueError, match=r"metrics\['vec'\] must be a scalar"):
        train(lambda s: (((model(x) - y) ** 2).mean(), {"vec": x[0]}), opt, 1, progress=False)
    for b, p in zip(before, model.parameters(), strict=True):
        assert torch.equal(b, p)
