"""Quality metrics (paper §4: PSNR on values in [0, 1])."""

from __future__ import annotations

import torch


def psnr(pred: torch.Tensor, target: torch.Tensor, *, dim=None, data_range: float = 1.0) -> torch.Tensor:
    """10·log10(range² / MSE), over all values or along `dim`; a perfect match gives +inf."""
    mse = ((pred.double() - target.double()) ** 2).mean(dim=dim) if dim is not None else \
        ((pred.double() - target.double()) ** 2).mean()
    return 10.0 * torch.log10(data_range**2 / mse)
