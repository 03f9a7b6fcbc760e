"""Standardisation of SIREN weights for the diffusion model (the first paragraph is the per-token mode; `param`,
the default, standardises each weight across lights).

Per-token standardisation: each parameter tensor's values get one scalar mean and std over the training
set. The std is rounded to a power of two, so standardising and de-standardising (in float64) is an
exact round trip; a tensor with zero spread gets std 0: it standardises to 0 and de-standardises to its
mean whatever the model predicts (docs/numerics.md).
"""

from __future__ import annotations

import torch

from diffshadow.diffusion.config import DiffusionError
from diffshadow.siren import WeightLayout


def _pow2_std(s: torch.Tensor) -> torch.Tensor:
    """Round a spread to a power of two (exact scaling), kept inside float32's normal range; 0 where it is 0.

    Found by the stress suite: spreads up to 1e-12 used to get std 1, so the model's ordinary x0 error
    (~1e-2 in standardised units) landed unscaled on tensors whose weights differ by 1e-13 across lights.
    """
    if not torch.isfinite(s).all():
        raise DiffusionError("standardizer: a weight tensor's spread is not finite (NaN/Inf weights in the store?)")
    exp = torch.round(torch.log2(torch.where(s > 0, s, torch.ones_like(s)))).clamp(-126, 127)
    return torch.where(s > 0, 2.0**exp, torch.zeros_like(s))


class Standardizer:
    """Mean and power-of-two std, per token (paper: one scalar per parameter tensor) or per parameter."""

    def __init__(self, layout: WeightLayout, mean: torch.Tensor, std: torch.Tensor):
        self.layout = layout
        self.mean = mean.double()  # (n_tokens,) or (n_params,)
        self.std = std.double()
        self._expanded: dict[tuple, torch.Tensor] = {}

    @classmethod
    def fit(cls, layout: WeightLayout, weights: torch.Tensor, mode: str = "token") -> Standardizer:
        bad = ~torch.isfinite(weights).all(dim=1)
        if bad.any():
            rows = torch.nonzero(bad).flatten().tolist()
            raise DiffusionError(f"standardizer: the weights of light row(s) {rows[:10]}"
                                 f"{'...' if len(rows) > 10 else ''} are not finite; refit those lights")
        w = weights.double()
        if mode == "param":
            # across lights, per weight: what is left is the light-dependent part, at unit scale
            mean = w.mean(dim=0).float().double()  # representable in float32: keeps the round trip exact
            std = w.std(dim=0) if len(w) > 1 else torch.zeros_like(mean)
            return cls(layout, mean, _pow2_std(std))
        if mode != "token":
            raise ValueError(f"diffusion.standardize: expected 'token' or 'param', got {mode!r}")
        parts = w.split(layout.sizes, dim=1)
        mean = torch.tensor([float(p.mean().float()) for p in parts], dtype=torch.float64)
        std = torch.tensor([float(p.std()) if p.numel() > 1 else 0.0 for p in parts], dtype=torch.float64)
        return cls(layout, mean, _pow2_std(std))

    def _expand(self, name: str, like: torch.Tensor, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """`mean` or `std` per parameter (n_params,), in `dtype` on `like`'s device: made once per device and
        dtype, so a training step's de-standardisation copies nothing from the host (two copies and two casts a
        step before; per token, also a repeat whose size CUDA reads back), as a CUDA graph requires."""
        key = (name, like.device, dtype)
        if key not in self._expanded:
            v = getattr(self, name).to(like.device)
            if len(v) != self.layout.n_params:
                sizes = torch.tensor(self.layout.sizes, device=like.device)
                v = torch.repeat_interleave(v, sizes, output_size=self.layout.n_params)
            self._expanded[key] = v.to(dtype)
        return self._expanded[key]

    def standardize(self, w: torch.Tensor) -> torch.Tensor:
        """(..., n_params) weights → standardised, in float64 (0 where the std is 0)."""
        std = self._expand("std", w)
        return (w.double() - self._expand("mean", w)) / torch.where(std > 0, std, 1.0) * (std > 0)

    def destandardize(self, z: torch.Tensor) -> torch.Tensor:
        """Inverse of `standardize`; keeps the autograd graph (the geometry loss differentiates through it)."""
        return z * self._expand("std", z, z.dtype) + self._expand("mean", z, z.dtype)

    def state(self) -> dict:
        return {"mean": self.mean, "std": self.std}
