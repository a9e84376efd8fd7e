"""Flat gradient helpers for methods that change the wake's policy gradient (A-GEM, PCGrad, Nash-MTL)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def flat_grad(loss: Tensor, parameters: Sequence[Tensor]) -> Tensor:
    """d loss / d theta as one flat vector (zeros for parameters the loss does not use); ``.grad`` untouched."""
    grads = torch.autograd.grad(loss, list(parameters), allow_unused=True)
    return torch.cat([(torch.zeros_like(p) if g is None else g).reshape(-1) for p, g in zip(parameters, grads,
                                                                                          strict=True)])


def current_grad(parameters: Sequence[Tensor]) -> Tensor:
    """The parameters' ``.grad`` (after the wake's backward pass) as one flat vector."""
    return torch.cat([(torch.zeros_like(p) if p.grad is None else p.grad).reshape(-1) for p in parameters])


def set_grad(parameters: Sequence[Tensor], flat: Tensor) -> None:
    """Write the flat vector ``flat`` into the parameters' ``.grad``."""
    offset = 0
    for p in parameters:
        n = p.numel()
        p.grad = flat[offset:offset + n].view_as(p).clone()
        offset += n
    if offset != flat.numel():
        raise ValueError(f"gradient of {flat.numel()} values for {offset} parameter values")
