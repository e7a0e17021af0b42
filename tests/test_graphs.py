"""CUDA graphs of a function: the packing of its outputs (any device) and the capture
(CUDA)."""

from __future__ import annotations

import pytest
import torch

from torchcbf._graphs import CapturedCall, pack, unpack


def test_pack_and_unpack_give_back_every_output():
    a = torch.arange(12.0).reshape(3, 4).mT  # not contiguous
    outputs = [a, None, torch.tensor(2.5), torch.arange(3), torch.zeros(0, 2), a[:, 1]]
    flat, slots = pack(outputs)
    assert sorted(flat, key=str) == [torch.float32, torch.int64]
    assert all(t.dim() == 1 for t in flat.values())
    got = unpack({dtype: t.clone() for dtype, t in flat.items()}, slots)
    assert len(got) == len(outputs)
    for g, want in zip(got, outputs, strict=True):
        if want is None:
            assert g is None
        else:
            assert g.dtype == want.dtype and g.shape == want.shape
            assert torch.equal(g, want)


def test_capture_needs_cuda_tensors():
    with pytest.raises(ValueError, match="CUDA"):
        CapturedCall(lambda x: (x,), (torch.zeros(2),))


@pytest.mark.device
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_a_replay_computes_from_the_new_inputs_and_keeps_earlier_outputs():
    state = torch.zeros(3, device="cuda")

    def fn(x, k):
        state.add_(x)  # a tensor changed in place beside the outputs
        return x * k, None, (x.sum() > 0).long()

    x = torch.tensor([1.0, 2.0, 3.0], device="cuda")
    fn(x, torch.tensor(1.0, device="cuda"))  # uncaptured first run
    state.zero_()
    call = CapturedCall(fn, (x, torch.tensor(1.0, device="cuda")))
    assert torch.equal(state, torch.zeros(3, device="cuda"))  # the capture ran nothing
    first = call(x, torch.tensor(2.0, device="cuda"))
    second = call(-x, torch.tensor(3.0, device="cuda"))
    torch.testing.assert_close(first[0], 2.0 * x)
    torch.testing.assert_close(second[0], -3.0 * x)
    assert first[1] is None and first[2].item() == 1 and second[2].item() == 0
    torch.testing.assert_close(state, torch.zeros(3, device="cuda"))  # x then -x
    with pytest.raises(ValueError, match="input 0"):
        call(x[:2], torch.tensor(1.0, device="cuda"))
