"""torchcbf: batched, differentiable safe planning and control in PyTorch."""
