"""A function captured in a CUDA graph: a replay computes from new inputs, earlier outputs
stay, a failed capture leaves the warm-up's answer and the thread's stream as they were."""

from __future__ import annotations

import pytest
import torch

from torchcbf._graphs import CapturedCall


def test_capture_needs_cuda_tensors():
    with pytest.raises(ValueError, match="CUDA"):
        CapturedCall(lambda x: (x,), (torch.zeros(2),))


needs_cuda = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device"
)


@pytest.mark.device
@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_replay_computes_from_new_inputs_and_keeps_earlier_outputs(dtype):
    state = torch.zeros(3, device="cuda", dtype=dtype)

    def fn(x, k):
        state.add_(x)  # a tensor changed in place beside the outputs
        return x * k, None, (x.sum() > 0).long()

    x = torch.tensor([1.0, 2.0, 3.0], device="cuda", dtype=dtype)
    two = torch.tensor(2.0, device="cuda", dtype=dtype)
    call = CapturedCall(fn, (x, two))
    assert call.error is None
    torch.testing.assert_close(call.first[0], 2.0 * x)  # the warm-up ran once, for real
    torch.testing.assert_close(state, x)
    second = call(-x, torch.tensor(3.0, device="cuda", dtype=dtype))
    third = call(x, torch.tensor(0.5, device="cuda", dtype=dtype))
    torch.testing.assert_close(second[0], -3.0 * x)
    torch.testing.assert_close(third[0], 0.5 * x)
    assert second[1] is None and second[2].item() == 0 and third[2].item() == 1
    torch.testing.assert_close(state, x)  # x, then -x, then x again
    with pytest.raises(ValueError, match="input 0"):
        call(x[:2], two)


@pytest.mark.device
@needs_cuda
def test_a_capture_that_fails_keeps_the_warm_up_and_the_stream():
    stream = torch.cuda.current_stream()

    def fn(x):
        if bool(x.sum() > 0):  # a host synchronisation: no graph can hold it
            return (x + 1.0,)
        return (x - 1.0,)

    x = torch.ones(4, device="cuda")
    call = CapturedCall(fn, (x,))
    assert call.error is not None
    torch.testing.assert_close(call.first[0], x + 1.0)
    assert torch.cuda.current_stream() == stream
    torch.testing.assert_close(x * 2.0, torch.full((4,), 2.0, device="cuda"))  # CUDA still works
    with pytest.raises(RuntimeError, match="capture failed"):
        call(x)


def test_copies_of_outputs_have_storage_of_their_own(device):
    from torchcbf._graphs import _copies

    grid = torch.arange(12.0, dtype=torch.float64, device=device).reshape(3, 4)
    outputs = (
        grid.mT,  # not contiguous
        None,
        torch.tensor([1, 2, 3], device=device),
        torch.tensor(2.5, dtype=torch.float64, device=device),
        torch.zeros(0, 3, device=device),
        torch.tensor([True, False], device=device),
    )
    copies = _copies(outputs)
    assert copies[1] is None
    for t, c in zip(outputs, copies, strict=True):
        if t is not None:
            assert torch.equal(c, t) and c.dtype == t.dtype and c.is_contiguous()
            own = c.untyped_storage()
            assert c.numel() == 0 or own.data_ptr() != t.untyped_storage().data_ptr()
            assert own.nbytes() == c.numel() * c.element_size()
